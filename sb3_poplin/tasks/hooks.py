"""
Model hooks for locomotion observations, built from four choices instead of written per task.

The raw layout of the v5 locomotion tasks (made with the root position kept) is ``[root position(s), root height,
root angle(s), joint angles, velocities]``. What the dynamics model sees and learns can differ from it in three
ways, each a field of :class:`LocomotionHooks`:

- ``exclude``: the root positions are not inputs (the dynamics do not depend on where the body is); their change
  is still predicted, since the forward reward needs it;
- ``angles``: a wrapping angle (the root pitch of a cheetah that flips) enters as its sine and cosine, so that a
  turn by 2 pi looks the same;
- ``rates``: the change of these entries is predicted divided by ``dt`` -- the forward progress as a velocity, on
  the scale of the other velocity entries instead of ``dt`` times smaller;
- ``bounded``: these inputs enter squashed, ``bound * tanh(x / bound)`` (about ``x`` inside ``±bound / 2``), so that
  the rare large velocities of a flailing body do not dominate the whitened input.

``obs_postproc(obs, targ_proc(obs, next_obs)) == next_obs`` up to float rounding. The hooks are a frozen dataclass,
not closures, so that an agent that uses them pickles.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property
from typing import Any

import torch as th


def _runs(indices: list[int]) -> tuple[tuple[int, int], ...]:
    """:return: the sorted indices as maximal runs ``(start, stop)`` of consecutive values (slices need no tensors)"""
    runs: list[list[int]] = []
    for index in sorted(indices):
        if runs and runs[-1][1] == index:
            runs[-1][1] = index + 1
        else:
            runs.append([index, index + 1])
    return tuple((start, stop) for start, stop in runs)


@dataclass(frozen=True)
class LocomotionHooks:
    """
    ``obs_preproc``, ``targ_proc`` and ``obs_postproc`` (see :mod:`sb3_poplin.dynamics`) for one observation layout.

    :param obs_dim: the observation size
    :param exclude: indices that are not model inputs (their change is still predicted)
    :param angles: indices that enter the model as their sine and cosine (not with ``exclude``)
    :param rates: indices whose change is predicted divided by ``dt``
    :param dt: seconds per env step (used with ``rates``)
    :param bounded: indices whose input is squashed to ``(-bound, bound)`` (targets are unchanged)
    :param bound: the squashing scale of ``bounded``
    """

    obs_dim: int
    exclude: tuple[int, ...] = ()
    angles: tuple[int, ...] = ()
    rates: tuple[int, ...] = ()
    dt: float = 1.0
    bounded: tuple[int, ...] = ()
    bound: float = 10.0

    def __post_init__(self) -> None:
        for name in ("exclude", "angles", "rates", "bounded"):
            indices = getattr(self, name)
            if len(set(indices)) != len(indices) or any(not 0 <= i < self.obs_dim for i in indices):
                raise ValueError(
                    f"LocomotionHooks.{name} must hold distinct indices in [0, {self.obs_dim}) (obs_dim), got {indices}."
                )
        if set(self.exclude) & set(self.angles):
            raise ValueError(
                f"LocomotionHooks: indices {sorted(set(self.exclude) & set(self.angles))} are both excluded and fed as "
                "sine and cosine; an index is one or the other."
            )
        if set(self.bounded) & (set(self.exclude) | set(self.angles)):
            raise ValueError(
                f"LocomotionHooks: indices {sorted(set(self.bounded) & (set(self.exclude) | set(self.angles)))} are "
                "bounded and also excluded or fed as sine and cosine; only a plain input can be bounded."
            )
        if self.bounded and not self.bound > 0:
            raise ValueError(f"LocomotionHooks.bound must be > 0 with bounded indices, got {self.bound}.")
        if self.rates and not self.dt > 0:
            raise ValueError(f"LocomotionHooks.dt must be > 0 with rates (seconds per env step), got {self.dt}.")

    @cached_property
    def _plain_runs(self) -> tuple[tuple[int, int, bool], ...]:
        """Runs ``(start, stop, is_bounded)`` of the plain (not excluded, not angle) inputs, in order."""
        skipped = set(self.exclude) | set(self.angles)
        bounded = set(self.bounded)
        runs: list[tuple[int, int, bool]] = []
        for start, stop in _runs([i for i in range(self.obs_dim) if i not in skipped]):
            for index in range(start, stop):
                flag = index in bounded
                if runs and runs[-1][1] == index and runs[-1][2] == flag:
                    runs[-1] = (runs[-1][0], index + 1, flag)
                else:
                    runs.append((index, index + 1, flag))
        return tuple(runs)

    @cached_property
    def _angle_runs(self) -> tuple[tuple[int, int], ...]:
        return _runs(list(self.angles))

    @cached_property
    def _scaled_runs(self) -> tuple[tuple[int, int, bool], ...]:
        """Runs ``(start, stop, is_rate)`` covering every index, in order."""
        rates = set(self.rates)
        runs: list[tuple[int, int, bool]] = []
        for index in range(self.obs_dim):
            is_rate = index in rates
            if runs and runs[-1][2] == is_rate:
                runs[-1] = (runs[-1][0], index + 1, is_rate)
            else:
                runs.append((index, index + 1, is_rate))
        return tuple(runs)

    @property
    def feature_dim(self) -> int:
        """Model input features per observation: the plain entries, then a sine and a cosine per angle."""
        return self.obs_dim - len(self.exclude) + len(self.angles)

    def obs_preproc(self, obs: th.Tensor) -> th.Tensor:
        """
        :param obs: raw observations ``[..., obs_dim]``
        :return: ``[plain entries (bounded ones squashed), sin(angles), cos(angles)]`` ``[..., feature_dim]``
        """
        parts = [
            self.bound * th.tanh(obs[..., start:stop] / self.bound) if flag else obs[..., start:stop]
            for start, stop, flag in self._plain_runs
        ]
        if self.angles:
            angles = th.cat([obs[..., start:stop] for start, stop in self._angle_runs], dim=-1)
            parts += [th.sin(angles), th.cos(angles)]
        return th.cat(parts, dim=-1)

    def targ_proc(self, obs: th.Tensor, next_obs: th.Tensor) -> th.Tensor:
        """:return: ``next_obs - obs``, divided by ``dt`` at the ``rates`` indices"""
        delta = next_obs - obs
        if not self.rates:
            return delta
        return th.cat([delta[..., a:b] / self.dt if rate else delta[..., a:b] for a, b, rate in self._scaled_runs], dim=-1)

    def obs_postproc(self, obs: th.Tensor, prediction: th.Tensor) -> th.Tensor:
        """:return: ``obs + prediction``, the prediction times ``dt`` at the ``rates`` indices"""
        if not self.rates:
            return obs + prediction
        delta = th.cat(
            [prediction[..., a:b] * self.dt if rate else prediction[..., a:b] for a, b, rate in self._scaled_runs], dim=-1
        )
        return obs + delta

    def model_hooks(self, policy: bool = False) -> dict[str, Any]:
        """
        The ``TaskSpec`` keyword arguments of these hooks.

        :param policy: the policy network sees the model's input features too; else the raw observation without
            ``exclude``
        """
        return dict(
            model_input_exclude=(),
            obs_preproc=self.obs_preproc,
            targ_proc=self.targ_proc if self.rates else None,
            obs_postproc=self.obs_postproc if self.rates else None,
            policy_input_exclude=() if policy else self.exclude,
            policy_obs_preproc=self.obs_preproc if policy else None,
        )
