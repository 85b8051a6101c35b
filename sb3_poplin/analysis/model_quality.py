"""
How good is a dynamics model where planning uses it? Fixed datasets of recorded transitions, and a report of a model
configuration fitted on some of their episodes and measured on later, held-out ones.

- :class:`TransitionDataset`: the transitions of a training run, whole episodes in order, as a float32 ``.npz``
  (``record``: a POPLIN run with a packaged preset; the first ``n`` episodes of a 15k-step run are its 5k-step
  dataset).
- :func:`fit_after_every_episode`: fits a model the way ``POPLIN`` trains it: a refit on all transitions so far after
  every training episode (the first after episode 1), with the agent's persistent optimizer.
- :func:`evaluate`: on the held-out episodes, the one-step Gaussian NLL and squared error of the targets (in the
  model's target units: comparable between configurations with the same targets), the open-loop k-step state error
  under the recorded actions (expectation propagation, as the planner uses it; in units of each state entry's standard
  deviation over the held-out states) and the error and correlation of the predicted h-step return (the task's reward
  on the predicted states) with the recorded one -- what CEM ranks candidates by.

The model under test is anything with the two methods of :class:`ModelUnderTest`, so that another library's model
(``benchmarks/diagnosis/mbrl_model_quality.py``: mbrl-lib's) is measured by the same code.
"""

from __future__ import annotations

import json
import math
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np
import torch as th

from sb3_poplin.tasks import ModelHooks, RewardFn, TerminationFn, make_task

DATASET_FORMAT = 1
ARRAYS = ("obs", "actions", "rewards", "next_obs", "terminated", "episode")


@dataclass
class TransitionDataset:
    """
    Transitions of whole episodes, in the order they were collected.

    :param env_id: the gymnasium id (made with the task's env kwargs, as ``make_env`` does)
    :param obs: ``[N, o]`` observations
    :param actions: ``[N, a]`` actions in env units (what ``env.step`` received)
    :param rewards: ``[N]`` rewards
    :param next_obs: ``[N, o]`` the observations after the step (the terminal one at an episode's end)
    :param terminated: ``[N]`` the env terminated at this step (a time limit is not a termination)
    :param episode: ``[N]`` the episode of each row: ``0, 0, ..., 1, ...``, consecutive
    :param meta: how the data was made (variant, seed, steps, command, release)
    """

    env_id: str
    obs: np.ndarray
    actions: np.ndarray
    rewards: np.ndarray
    next_obs: np.ndarray
    terminated: np.ndarray
    episode: np.ndarray
    meta: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        n = len(self.obs)
        for name in ARRAYS:
            if len(getattr(self, name)) != n:
                raise ValueError(f"TransitionDataset: {name} has {len(getattr(self, name))} rows, obs has {n}.")
        if n and (self.episode[0] != 0 or not np.isin(np.diff(self.episode), (0, 1)).all()):
            raise ValueError("TransitionDataset: episode must count 0, 0, ..., 1, 1, ... (whole episodes, in order).")

    @property
    def num_episodes(self) -> int:
        return int(self.episode[-1]) + 1 if len(self.episode) else 0

    def episode_bounds(self) -> list[tuple[int, int]]:
        """:return: ``(start, stop)`` rows of every episode"""
        starts = np.flatnonzero(np.diff(self.episode, prepend=-1))
        stops = [*starts[1:], len(self.episode)]
        return [(int(a), int(b)) for a, b in zip(starts, stops, strict=True)]

    def episodes(self, first: int, stop: int) -> TransitionDataset:
        """
        :param first: the first episode kept
        :param stop: one past the last
        :return: those episodes (renumbered from 0), with this dataset's ``meta``
        """
        if not 0 <= first < stop <= self.num_episodes:
            raise ValueError(f"Episodes {first}..{stop - 1} asked of a dataset of {self.num_episodes} episodes.")
        rows = (self.episode >= first) & (self.episode < stop)
        return TransitionDataset(
            self.env_id,
            obs=self.obs[rows],
            actions=self.actions[rows],
            rewards=self.rewards[rows],
            next_obs=self.next_obs[rows],
            terminated=self.terminated[rows],
            episode=self.episode[rows] - first,
            meta=dict(self.meta),
        )

    def first_steps(self, steps: int) -> TransitionDataset:
        """
        The dataset a run of ``steps`` steps would have recorded: its first rows, which must end an episode.

        :raises ValueError: when ``steps`` falls inside an episode
        """
        ends = [stop for _, stop in self.episode_bounds()]
        if steps not in ends:
            before = max((end for end in ends if end < steps), default=None)
            after = min((end for end in ends if end > steps), default=None)
            nearest = " and ".join(str(end) for end in (before, after) if end is not None)
            raise ValueError(
                f"{steps} steps end inside an episode of this dataset: pass an episode end, the nearest are {nearest}."
            )
        return self.episodes(0, ends.index(steps) + 1)

    def save(self, path: str) -> None:
        """Write a compressed ``.npz`` (float32 arrays; ``meta`` and ``env_id`` as JSON)."""
        arrays = {name: getattr(self, name) for name in ARRAYS}
        arrays = {k: v.astype(np.float32) if v.dtype.kind == "f" else v for k, v in arrays.items()}
        header = json.dumps(dict(format=DATASET_FORMAT, env_id=self.env_id, meta=self.meta))
        np.savez_compressed(path, header=np.array(header), **arrays)

    @classmethod
    def load(cls, path: str) -> TransitionDataset:
        """Read a file written by :meth:`save`."""
        with np.load(path) as data:
            header = json.loads(str(data["header"]))
            if header.get("format") != DATASET_FORMAT:
                raise ValueError(f"{path} is a dataset of format {header.get('format')}; this release reads {DATASET_FORMAT}.")
            arrays = {name: data[name] for name in ARRAYS}
        return cls(header["env_id"], meta=header["meta"], **arrays)


def dataset_from_replay(
    arrays: Mapping[str, np.ndarray],
    unscale: Callable[[np.ndarray], np.ndarray],
    env_id: str,
    meta: dict[str, Any] | None = None,
) -> TransitionDataset:
    """
    The transitions of a replay buffer's arrays (one env, never wrapped around), cut at the last finished episode.

    :param arrays: ``sb3_poplin.experiments.checkpoints.replay_buffer_arrays`` of the buffer (a checkpoint's
        ``replay_buffer.npz``)
    :param unscale: the agent's ``policy.unscale_action`` (the buffer holds actions in [-1, 1])
    :param env_id: the task
    :param meta: recorded with the data
    """
    if arrays["observations"].shape[1] != 1 or bool(arrays["full"]):
        raise ValueError(
            "A dataset needs one env and a replay buffer that never wrapped around (buffer_size >= the steps "
            f"trained); this one has {arrays['observations'].shape[1]} envs and is {'full' if arrays['full'] else 'not full'}."
        )
    dones = arrays["dones"][:, 0].astype(bool)
    if not dones.any():
        raise ValueError("The replay buffer holds no finished episode: train for at least one episode.")
    n = int(np.flatnonzero(dones)[-1]) + 1
    dones = dones[:n]
    timeouts = arrays["timeouts"][:n, 0].astype(bool)
    return TransitionDataset(
        env_id,
        obs=arrays["observations"][:n, 0].astype(np.float32),
        actions=unscale(arrays["actions"][:n, 0]).astype(np.float32),
        rewards=arrays["rewards"][:n, 0].astype(np.float32),
        next_obs=arrays["next_observations"][:n, 0].astype(np.float32),
        terminated=dones & ~timeouts,
        episode=np.concatenate([[0], np.cumsum(dones[: n - 1])]).astype(np.int64),
        meta=dict(meta or {}),
    )


def dataset_from_agent(agent: Any, meta: dict[str, Any] | None = None) -> TransitionDataset:
    """
    The transitions in a trained agent's replay buffer (see :func:`dataset_from_replay`).

    :param agent: a ``POPLIN`` agent after ``learn``, one env, ``buffer_size`` at least the steps trained
    :param meta: recorded with the data
    """
    from sb3_poplin.experiments.checkpoints import replay_buffer_arrays

    return dataset_from_replay(replay_buffer_arrays(agent.replay_buffer), agent.policy.unscale_action, agent.task_id, meta)


def record(env_id: str, variant: str, steps: int, seed: int, budget: str = "cpu", **overrides: Any) -> TransitionDataset:
    """
    Train a POPLIN agent with a packaged preset (:func:`sb3_poplin.experiments.presets.poplin_settings`) and keep its
    transitions.

    :param env_id: a task with an entry in the preset's file
    :param variant: ``"pets"``, ``"poplin-p"``, ...
    :param steps: env steps to train
    :param seed: the run's seed
    :param budget: ``"cpu"`` (``poplin_cpu.yml``) or ``"paper"``
    :param overrides: settings that replace the file's
    """
    from sb3_poplin import POPLIN, __version__
    from sb3_poplin.experiments.presets import config_path, load_config, poplin_settings
    from sb3_poplin.tasks import make_env

    path = config_path("poplin", budget)
    assert path is not None
    settings = poplin_settings(env_id, budget, policy=variant, **overrides)
    # one row more than the steps: a buffer filled exactly is "full" and could not be told from one that wrapped
    settings["buffer_size"] = max(int(settings.get("buffer_size", 0)), steps + 1)
    env = make_env(env_id, **load_config(path)[env_id].get("env_kwargs", {}))
    agent = POPLIN(env=env, seed=seed, **settings)
    start = time.perf_counter()
    agent.learn(steps)
    meta = dict(
        variant=variant,
        seed=seed,
        steps=steps,
        budget=budget,
        overrides={k: list(v) if isinstance(v, tuple) else v for k, v in overrides.items()},
        sb3_poplin_version=__version__,
        train_seconds=round(time.perf_counter() - start, 1),
        training_returns=[float(info["r"]) for info in agent.ep_info_buffer or []],
    )
    return dataset_from_agent(agent, meta)


# ------------------------------------------------------------------------------------------------ fitting
class ModelUnderTest(Protocol):
    """What :func:`evaluate` needs of a fitted model."""

    def one_step(self, obs: th.Tensor, actions: th.Tensor, next_obs: th.Tensor, rewards: th.Tensor) -> tuple[float, float]:
        """:return: the Gaussian NLL per target entry (members averaged) and the members' mean squared error, in the
        model's target units, of the transitions (actions in env units)"""
        ...

    def step(self, states: th.Tensor, actions: th.Tensor) -> th.Tensor:
        """:return: the next states ``[N, o]`` the planner would imagine (expectation) from ``[N, o]`` and env-unit
        actions ``[N, a]``"""
        ...


def fit_after_every_episode(fit: Callable[[TransitionDataset], Any], train: TransitionDataset) -> float:
    """
    Refit on the first 1, 2, ..., E episodes of ``train``, as training does after every episode.

    :param fit: fits the model on all the transitions it is given
    :param train: the training episodes
    :return: the seconds all the fits took
    """
    start = time.perf_counter()
    for count in range(1, train.num_episodes + 1):
        fit(train.episodes(0, count))
    return time.perf_counter() - start


class EnsembleUnderTest:
    """
    A ``POPLIN`` agent's ensemble as a :class:`ModelUnderTest`, fitted through :meth:`POPLIN.fit_dynamics` (the
    code ``POPLIN.train`` runs).

    :param agent: a ``POPLIN`` agent (only its ensemble, optimizer, settings and generator are used)
    """

    def __init__(self, agent: Any) -> None:
        self.agent = agent
        self.device = agent.device

    def _tensors(self, data: TransitionDataset) -> tuple[th.Tensor, ...]:
        scaled = self.agent.policy.scale_action(data.actions)
        return tuple(
            th.as_tensor(a, dtype=th.float32, device=self.device) for a in (data.obs, scaled, data.next_obs, data.rewards)
        )

    def fit(self, data: TransitionDataset) -> None:
        self.agent.policy.set_training_mode(True)
        self.agent.fit_dynamics(*self._tensors(data))
        self.agent.policy.set_training_mode(False)

    @th.no_grad()
    def one_step(self, obs: th.Tensor, actions: th.Tensor, next_obs: th.Tensor, rewards: th.Tensor) -> tuple[float, float]:
        dynamics = self.agent.policy.dynamics
        scaled = th.as_tensor(self.agent.policy.scale_action(actions.cpu().numpy()), dtype=th.float32, device=self.device)
        target = dynamics.training_target(obs, next_obs, rewards)
        x = dynamics.model_input(obs, scaled).unsqueeze(0).expand(dynamics.ensemble_size, -1, -1)
        mean, logvar = dynamics.predict(x)
        mean = dynamics._to_delta(mean)
        logvar = logvar + 2.0 * dynamics.target_std.log()
        nll = 0.5 * ((target - mean) ** 2 * th.exp(-logvar) + logvar + math.log(2.0 * math.pi))
        return float(nll.mean()), float(((target - mean) ** 2).mean())

    @th.no_grad()
    def step(self, states: th.Tensor, actions: th.Tensor) -> th.Tensor:
        scaled = th.as_tensor(self.agent.policy.scale_action(actions.cpu().numpy()), dtype=th.float32, device=self.device)
        next_states, _ = self.agent.policy.dynamics.propagate(states.unsqueeze(1), scaled.unsqueeze(1), "expectation")
        return next_states[:, 0]


# ------------------------------------------------------------------------------------------------ evaluation
def _correlation(a: th.Tensor, b: th.Tensor) -> float:
    a, b = a - a.mean(), b - b.mean()
    denominator = float(a.norm() * b.norm())
    return float((a * b).sum()) / denominator if denominator > 0 else math.nan


@th.no_grad()
def evaluate(
    model: ModelUnderTest,
    heldout: TransitionDataset,
    reward_fn: RewardFn,
    termination_fn: TerminationFn | None = None,
    state_dims: Sequence[int] | None = None,
    ks: Sequence[int] = (1, 5, 15, 30),
    return_horizons: Sequence[int] = (15, 30),
    stride: int = 5,
) -> dict[str, Any]:
    """
    The model's errors on held-out episodes.

    :param model: the fitted model
    :param heldout: whole episodes the model was not fitted on
    :param reward_fn: the task's reward on ``(obs, env-unit action, next_obs)``
    :param termination_fn: the task's termination; a predicted termination ends a predicted return (as in planning)
    :param state_dims: observation entries the state error is measured on; ``None``: all (pass the entries without the
        root positions, whose error grows with the distance run and shows in the return error instead)
    :param ks: prediction steps at which the state error is reported
    :param return_horizons: lengths h of the predicted returns
    :param stride: a prediction starts at every ``stride``-th state of an episode
    :return: ``nll``, ``mse`` (one step, target units), ``state_error`` {k: RMSE in std units}, ``return_error``
        {h: mean absolute error}, ``return_correlation`` {h: Pearson r}, ``real_return_std`` {h}, ``starts``
    """
    as_tensor = lambda a: th.as_tensor(a, dtype=th.float32)  # noqa: E731
    obs, actions, next_obs, rewards = (as_tensor(a) for a in (heldout.obs, heldout.actions, heldout.next_obs, heldout.rewards))
    nll, mse = model.one_step(obs, actions, next_obs, rewards)
    horizon = max([*ks, *return_horizons])
    dims = th.as_tensor(list(range(obs.shape[1])) if state_dims is None else list(state_dims))
    std = obs[:, dims].std(dim=0).clamp(min=1e-6)
    sq_error: dict[int, list[th.Tensor]] = {k: [] for k in ks}
    predicted: dict[int, list[th.Tensor]] = {h: [] for h in return_horizons}
    real: dict[int, list[th.Tensor]] = {h: [] for h in return_horizons}
    for a, b in heldout.episode_bounds():
        if b - a < horizon:
            continue
        states_seq = th.cat([obs[a:b], next_obs[b - 1 : b]])  # [T + 1, o]
        starts = th.arange(0, b - a - horizon + 1, stride)
        state = states_seq[starts]
        total = th.zeros(len(starts))
        alive = th.ones(len(starts), dtype=th.bool)
        for k in range(1, horizon + 1):
            action = actions[a + starts + k - 1]
            nxt = model.step(state, action)
            total = total + th.where(alive, reward_fn(state, action, nxt), th.zeros(()))
            if termination_fn is not None:
                alive = alive & ~termination_fn(state, action, nxt)
            state = nxt
            if k in sq_error:
                sq_error[k].append(((state - states_seq[starts + k])[:, dims] / std) ** 2)
            if k in predicted:
                predicted[k].append(total.clone())
                real[k].append(th.stack([rewards[a + s : a + s + k].sum() for s in starts.tolist()]))
    if not any(sq_error.values()) and not any(predicted.values()):
        raise ValueError(f"No held-out episode has the {horizon} steps the longest prediction needs.")
    report: dict[str, Any] = dict(nll=nll, mse=mse, state_error={}, return_error={}, return_correlation={}, real_return_std={})
    for k, errors in sq_error.items():
        report["state_error"][k] = float(th.cat(errors).mean().sqrt())
    for h in return_horizons:
        p, r = th.cat(predicted[h]), th.cat(real[h])
        report["return_error"][h] = float((p - r).abs().mean())
        report["return_correlation"][h] = _correlation(p, r)
        report["real_return_std"][h] = float(r.std()) if len(r) > 1 else math.nan
    report["starts"] = int(sum(len(e) for e in predicted[return_horizons[0]]))
    return report


# ------------------------------------------------------------------------------------------------ configurations
def model_agent(env_id: str, settings: dict[str, Any], hooks: ModelHooks | None = None, seed: int = 0) -> Any:
    """
    A PETS agent with a preset's model settings, whose ensemble is the model under test.

    :param env_id: the dataset's task
    :param settings: POPLIN keyword arguments (``ensemble_size``, ``dynamics_net_arch``, ``model_epochs``, ...)
    :param hooks: model hooks in place of the task's
    :param seed: seeds the initialisation and the fits' bootstrap and shuffling
    """
    from sb3_poplin import POPLIN
    from sb3_poplin.tasks import make_env

    kept = {k: v for k, v in settings.items() if k not in ("policy", "noise")}
    return POPLIN("pets", make_env(env_id), seed=seed, device="cpu", model_hooks=hooks, **kept)


def model_quality(
    data: TransitionDataset,
    train_episodes: int,
    heldout_episodes: int | None = None,
    settings: dict[str, Any] | None = None,
    hooks: ModelHooks | None = None,
    seed: int = 0,
    **evaluate_kwargs: Any,
) -> dict[str, Any]:
    """
    Fit a model configuration on the first episodes of a dataset (a refit after every episode) and measure it on the
    next ones.

    :param data: the dataset
    :param train_episodes: episodes fitted on
    :param heldout_episodes: the episodes after them that are measured; ``None``: all the rest
    :param settings: the model's POPLIN settings; ``None``: the CPU preset's for the task
    :param hooks: model hooks in place of the task's
    :param seed: the model's seed
    :param evaluate_kwargs: passed to :func:`evaluate` (``ks``, ``return_horizons``, ``stride``)
    :return: :func:`evaluate`'s report with ``fit_seconds``
    """
    from sb3_poplin.experiments.presets import poplin_settings

    stop = data.num_episodes if heldout_episodes is None else train_episodes + heldout_episodes
    train, heldout = data.episodes(0, train_episodes), data.episodes(train_episodes, stop)
    task = make_task(data.env_id)
    agent = model_agent(data.env_id, poplin_settings(data.env_id) if settings is None else settings, hooks, seed)
    model = EnsembleUnderTest(agent)
    seconds = fit_after_every_episode(model.fit, train)
    state_dims = [i for i in range(data.obs.shape[1]) if i not in task.model_input_exclude]
    report = evaluate(model, heldout, task.reward_fn, task.termination_fn, state_dims=state_dims, **evaluate_kwargs)
    report["fit_seconds"] = seconds
    return report
