"""
How the networks see observations: :class:`ModelHooks`, the record an agent is built from and saved with, and
:class:`LocomotionHooks`, which makes the hooks of a locomotion task from four choices instead of written per task.

A :class:`ModelHooks` is part of an agent's state, like its network sizes: ``POPLIN(model_hooks=...)`` takes one (by
default the task's, :attr:`sb3_poplin.tasks.TaskSpec.hooks`), the zip keeps it, and a loaded agent's networks are
built from the one it saved, whatever the task's hooks are now.

The raw layout of the v5 locomotion tasks (made with the root position kept) is ``[root position(s), root height,
root angle(s), joint angles, velocities]``. What the dynamics model sees and learns can differ from it in four ways,
each a field of :class:`LocomotionHooks`:

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

from collections.abc import Callable, Mapping
from dataclasses import dataclass, fields
from functools import cached_property
from types import MethodType
from typing import Any

import torch as th

ObsPreproc = Callable[[th.Tensor], th.Tensor]
TargProc = Callable[[th.Tensor, th.Tensor], th.Tensor]
ObsPostproc = Callable[[th.Tensor, th.Tensor], th.Tensor]


def _same(a: Any, b: Any) -> bool:
    """Equal hooks: a method of a hooks record equals the same method of an equal record (also once unpickled)."""
    if isinstance(a, MethodType) and isinstance(b, MethodType):
        return a.__func__ is b.__func__ and a.__self__ == b.__self__
    return a == b


@dataclass(frozen=True, eq=False)
class ModelHooks:
    """
    The observation handling of an agent's networks (PETS's hooks, plus the policy network's inputs).

    :param model_input_exclude: observation indices the dynamics model does not take as inputs (it still predicts
        their change); not with ``obs_preproc``
    :param obs_preproc: the model's input features from raw observations, ``obs [..., o] -> features [..., f]``;
        ``None``: the observation without ``model_input_exclude``
    :param targ_proc: the model's target, ``(obs, next_obs) -> target``; ``None``: ``next_obs - obs``
    :param obs_postproc: its inverse, ``(obs, prediction) -> next_obs``; ``None``: ``obs + prediction``
    :param policy_input_exclude: observation indices the policy network does not see; ``None``: ``model_input_exclude``,
        resolved on creation (``dataclasses.replace`` of ``model_input_exclude`` alone keeps the policy's)
    :param policy_obs_preproc: the policy network's input features from raw observations; ``None``: the
        observation without ``policy_input_exclude`` (not with a non-empty one)
    """

    model_input_exclude: tuple[int, ...] = ()
    obs_preproc: ObsPreproc | None = None
    targ_proc: TargProc | None = None
    obs_postproc: ObsPostproc | None = None
    policy_input_exclude: tuple[int, ...] | None = None
    policy_obs_preproc: ObsPreproc | None = None

    def __post_init__(self) -> None:
        from sb3_poplin.dynamics import check_model_hooks  # the model's rule; dynamics imports nothing of tasks

        object.__setattr__(self, "model_input_exclude", tuple(int(i) for i in self.model_input_exclude))
        policy_exclude = self.model_input_exclude if self.policy_input_exclude is None else self.policy_input_exclude
        object.__setattr__(self, "policy_input_exclude", tuple(int(i) for i in policy_exclude))  # resolved: None goes
        check_model_hooks(self.model_input_exclude, self.obs_preproc, self.targ_proc, self.obs_postproc, owner="ModelHooks: ")
        if self.policy_obs_preproc is not None and self.policy_exclude:
            raise ValueError(
                "ModelHooks: the policy takes either policy_input_exclude (by default model_input_exclude) or "
                "policy_obs_preproc, not both: pass policy_input_exclude=() and drop the indices inside the preproc."
            )

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, ModelHooks):
            return NotImplemented
        return all(_same(getattr(self, f.name), getattr(other, f.name)) for f in fields(self))

    def __hash__(self) -> int:
        return hash((self.model_input_exclude, self.policy_input_exclude))

    @property
    def policy_exclude(self) -> tuple[int, ...]:
        """The indices the policy network does not see (``policy_input_exclude``, resolved)."""
        assert self.policy_input_exclude is not None
        return self.policy_input_exclude

    def network_kwargs(self) -> dict[str, Any]:
        """:return: the keyword arguments of :class:`sb3_poplin.policies.POPLINPolicy` these hooks set"""
        return dict(
            model_input_exclude=list(self.model_input_exclude),
            obs_preproc=self.obs_preproc,
            targ_proc=self.targ_proc,
            obs_postproc=self.obs_postproc,
            policy_input_exclude=list(self.policy_exclude),
            policy_obs_preproc=self.policy_obs_preproc,
        )

    @classmethod
    def from_network_kwargs(cls, kwargs: Mapping[str, Any]) -> ModelHooks:
        """
        :param kwargs: a policy's keyword arguments (those :meth:`network_kwargs` gives; others are ignored, a
            missing one takes its default)
        :return: the hooks they set
        """
        return cls(**{f.name: kwargs[f.name] for f in fields(cls) if f.name in kwargs})


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

    def hooks(self, policy: bool = False) -> ModelHooks:
        """
        These hooks as an agent's record (``POPLIN(model_hooks=...)``).

        :param policy: the policy network sees the model's input features too; else the raw observation without
            ``exclude``
        """
        return ModelHooks(**self.model_hooks(policy))

    def model_hooks(self, policy: bool = False) -> dict[str, Any]:
        """
        The ``TaskSpec`` keyword arguments of these hooks (see :meth:`hooks`).

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
