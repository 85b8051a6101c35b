"""
Checkpoints that let a killed training run continue where it was, with nothing recorded twice or lost.

A run with checkpoints (``sb3-poplin-zoo train ... --checkpoints``, which ``sb3-poplin-zoo compare`` always asks
for) saves one after every finished episode, once the agent has learned from it: at the start of the next rollout,
when the env has just been reset. A checkpoint is a folder ``checkpoints/step-<N>`` in the run's folder with

* ``model.zip``: the agent as ``save`` writes it (networks, optimizers, the planner's warm start and generator,
  the distiller's state, the step and episode counters, the last observation);
* ``replay_buffer.npz``: the filled part of the replay buffer;
* ``state.pt``: the random states (python, numpy, torch, the agent's action space, every env's generator), what
  is needed to rebuild the training env exactly as it was (the generator state before its last reset, replayed
  on resume and checked against the saved observation), the Monitor's counters, the callbacks' counters and
  evaluation lists, and the bytes of the run's result files (``*.monitor.csv``, ``evaluations*.npz``) as they were.

It is written to ``step-<N>.tmp`` and renamed when complete, so a run killed while saving keeps its previous
checkpoint. :func:`restore_checkpoint` puts all of it back into a freshly built agent, env and callbacks.

Exact continuation needs one env in a ``DummyVecEnv`` without ``VecNormalize`` and an off-policy algorithm (POPLIN,
SAC, TD3, ...): their rollouts can end at episode ends. :func:`unsupported_reason` says why another run cannot have
checkpoints (it then restarts from zero when interrupted).
"""

from __future__ import annotations

import copy
import fcntl
import io
import os
import pathlib
import random
import re
import shutil
from collections.abc import Iterator
from typing import Any

import gymnasium as gym
import numpy as np
import torch as th
from stable_baselines3.common.base_class import BaseAlgorithm
from stable_baselines3.common.buffers import ReplayBuffer
from stable_baselines3.common.callbacks import BaseCallback, CallbackList
from stable_baselines3.common.monitor import Monitor
from stable_baselines3.common.off_policy_algorithm import OffPolicyAlgorithm
from stable_baselines3.common.vec_env import DummyVecEnv, VecEnv, VecEnvWrapper, VecNormalize

CHECKPOINT_FOLDER = "checkpoints"
CHECKPOINT_FILES = ("model.zip", "replay_buffer.npz", "state.pt")
LOCK_FILE = "run.lock"
# result files of a run folder restored to their checkpoint content (the Monitor's CSV, the evaluation files)
RESULT_FILE_PATTERN = re.compile(r"(.*\.monitor\.csv|evaluations.*\.npz)$")
# callback attributes that hold a run's progress, restored on resume: every callback's call and step counters, those of
# SB3's EvalCallback, StopTrainingOnNoModelImprovement, StopTrainingOnMaxEpisodes and EveryNTimesteps, rl-zoo3's
# RawStatisticsCallback and ControlModesEvalCallback (tests/test_reliability.py compares every counter of SB3's and
# ControlModesEvalCallback with an uninterrupted run's); a callback of one's own keeps its progress under these names
CALLBACK_ATTRIBUTES = (
    "n_calls",
    "num_timesteps",
    "evaluations_results",
    "evaluations_timesteps",
    "evaluations_length",
    "evaluations_successes",
    "_is_success_buffer",
    "best_mean_reward",
    "last_mean_reward",
    "last_best_mean_reward",
    "no_improvement_evals",
    "n_episodes",
    "last_time_trigger",
    "_timesteps_counter",
    "timesteps",
    "results",
    "lengths",
)
MONITOR_ATTRIBUTES = ("episode_returns", "episode_lengths", "episode_times", "total_steps", "t_start")
REPLAY_ARRAYS = ("observations", "next_observations", "actions", "rewards", "dones", "timeouts")


class ResetRecorder(gym.Wrapper):
    """
    Remember how the env was last reset: the seed and options given, and the state of its random generator just
    before, so that the reset can be replayed on resume (:func:`replay_reset`). Adds nothing else.

    :param env: the env (outermost wrapper of one ``DummyVecEnv`` slot)
    """

    def __init__(self, env: gym.Env) -> None:
        super().__init__(env)
        self.last_reset: dict[str, Any] = {"generator": None, "seed": None, "options": None}

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None) -> tuple[Any, dict[str, Any]]:
        self.last_reset = {"generator": generator_state(self.env.unwrapped), "seed": seed, "options": copy.deepcopy(options)}
        return self.env.reset(seed=seed, options=options)


# ------------------------------------------------------------------------------ private state of gymnasium and SB3
# An exact restore needs state that gymnasium and SB3 keep in private attributes: an env's generator
# (``gymnasium.Env._np_random``, ``_np_random_seed``) and a DummyVecEnv's pending reset arguments and buffered
# observations (``_seeds``, ``_options``, ``_save_obs``). Only the functions of this section touch them, and they
# refuse other releases than those they were written against (setup.cfg pins the same ranges).
PRIVATE_STATE_RELEASES = {"gymnasium": "1.4", "stable_baselines3": "2.9"}


def check_private_state_releases() -> None:
    """
    :raises RuntimeError: gymnasium or SB3 is not of the release whose private attributes checkpoints use
    """
    import stable_baselines3

    installed = {"gymnasium": gym.__version__, "stable_baselines3": stable_baselines3.__version__}
    for package, release in PRIVATE_STATE_RELEASES.items():
        if ".".join(installed[package].split(".")[:2]) != release:
            raise RuntimeError(
                f"Checkpoints read private state of {package} {release}.x, but {package} {installed[package]} is "
                f"installed: install {package}=={release}.* (as setup.cfg pins it), or train without checkpoints."
            )


def generator_state(env: gym.Env) -> dict[str, Any] | None:
    """
    :param env: an unwrapped env
    :return: its random generator's state, or ``None`` when it has none yet (reading ``np_random`` would make one)
    """
    generator = getattr(env, "_np_random", None)
    if generator is None:
        return None
    return {"state": copy.deepcopy(generator.bit_generator.state), "seed": getattr(env, "_np_random_seed", None)}


def set_generator_state(env: gym.Env, saved: dict[str, Any] | None) -> None:
    """
    :param env: an unwrapped env
    :param saved: what :func:`generator_state` returned
    """
    if saved is None:
        env._np_random = None  # type: ignore[attr-defined]
        return
    bit_generator = getattr(np.random, saved["state"]["bit_generator"])()
    bit_generator.state = saved["state"]
    env._np_random = np.random.Generator(bit_generator)  # type: ignore[attr-defined]
    if hasattr(env, "_np_random_seed"):
        env._np_random_seed = saved["seed"]  # type: ignore[attr-defined]


def pending_reset(inner: DummyVecEnv, index: int) -> dict[str, Any]:
    """:return: the seed and options a DummyVecEnv passes to env ``index``'s next reset"""
    return {"seed": inner._seeds[index], "options": copy.deepcopy(inner._options[index])}


def set_pending_reset(inner: DummyVecEnv, index: int, seed: int | None, options: dict[str, Any]) -> None:
    """Set what a DummyVecEnv passes to env ``index``'s next reset."""
    inner._seeds[index] = seed
    inner._options[index] = copy.deepcopy(options)


def set_buffered_observation(inner: DummyVecEnv, index: int, observation: Any) -> None:
    """Put ``observation`` in a DummyVecEnv's buffer of env ``index``'s last observation."""
    inner._save_obs(index, observation)


# ------------------------------------------------------------------------------------------------------------------
def dummy_vec_env(env: VecEnv) -> DummyVecEnv | None:
    """
    :param env: a VecEnv, possibly wrapped
    :return: the ``DummyVecEnv`` inside, or ``None`` when there is none or a ``VecNormalize`` wraps it
    """
    while isinstance(env, VecEnvWrapper):
        if isinstance(env, VecNormalize):
            return None
        env = env.venv
    return env if isinstance(env, DummyVecEnv) else None


def unsupported_reason(model: BaseAlgorithm, env: VecEnv) -> str | None:
    """
    :param model: the agent
    :param env: its training env
    :return: why the run cannot continue exactly from a checkpoint, or ``None`` when it can
    """
    if not isinstance(model, OffPolicyAlgorithm):
        return f"{type(model).__name__} is on-policy: its rollouts end in the middle of episodes"
    if type(model.replay_buffer) is not ReplayBuffer or model.replay_buffer.optimize_memory_usage:
        return "its replay buffer is not a plain ReplayBuffer without optimize_memory_usage (HER, dict observations)"
    if getattr(model, "use_sde", False):
        return "gSDE draws its exploration noise before a checkpoint could be taken"
    if dummy_vec_env(env) is None:
        return "the training env is not a DummyVecEnv without VecNormalize"
    if env.num_envs != 1:
        return f"the training env has {env.num_envs} envs: their episodes end at different steps"
    return None


def record_resets(env: VecEnv) -> None:
    """
    Wrap each env of the ``DummyVecEnv`` inside ``env`` in :class:`ResetRecorder` (before its first reset).

    :param env: the training env
    """
    inner = dummy_vec_env(env)
    assert inner is not None, "record_resets needs a DummyVecEnv (see unsupported_reason)"
    inner.envs = [slot if isinstance(slot, ResetRecorder) else ResetRecorder(slot) for slot in inner.envs]


def find_monitor(env: gym.Env) -> Monitor | None:
    """
    :param env: a wrapped env
    :return: the ``Monitor`` in its wrappers, if any
    """
    while isinstance(env, gym.Wrapper):
        if isinstance(env, Monitor):
            return env
        env = env.env
    return None


def iter_callbacks(callbacks: list[BaseCallback] | BaseCallback) -> Iterator[BaseCallback]:
    """
    :param callbacks: callbacks (a list, a ``CallbackList`` or one)
    :return: every callback, nested ones (``CallbackList``, an ``EvalCallback``'s children) included
    """
    items = callbacks if isinstance(callbacks, list) else [callbacks]
    for callback in items:
        if isinstance(callback, CallbackList):
            yield from iter_callbacks(callback.callbacks)
            continue
        yield callback
        for child in ("callback", "callback_on_new_best", "callback_after_eval"):
            nested = getattr(callback, child, None)
            if isinstance(nested, BaseCallback):
                yield from iter_callbacks(nested)


def eval_envs(callbacks: list[BaseCallback]) -> list[VecEnv]:
    """
    :param callbacks: the run's callbacks
    :return: their evaluation envs (each once)
    """
    found: list[VecEnv] = []
    for callback in iter_callbacks(callbacks):
        env = getattr(callback, "eval_env", None)
        if isinstance(env, VecEnv) and all(env is not other for other in found):
            found.append(env)
    return found


def vec_env_state(env: VecEnv, replay: bool) -> list[dict[str, Any]]:
    """
    :param env: a VecEnv (a ``DummyVecEnv`` inside)
    :param replay: record how each env was last reset (training env) rather than its generator's state now
    :return: per env: the pending seed and options, the generator state (or the last reset), the Monitor's counters
    """
    inner = dummy_vec_env(env)
    if inner is None:
        raise ValueError("Checkpoints need a DummyVecEnv without VecNormalize (see unsupported_reason).")
    states = []
    for index, slot in enumerate(inner.envs):
        state: dict[str, Any] = pending_reset(inner, index)
        if replay:
            if not isinstance(slot, ResetRecorder):
                raise ValueError("The training env's resets are not recorded: wrap it with record_resets first.")
            state["last_reset"] = copy.deepcopy(slot.last_reset)
        else:
            state["generator"] = generator_state(slot.unwrapped)
        monitor = find_monitor(slot)
        if monitor is not None:
            state["monitor"] = {name: copy.deepcopy(getattr(monitor, name)) for name in MONITOR_ATTRIBUTES}
        states.append(state)
    return states


def restore_vec_env(env: VecEnv, states: list[dict[str, Any]], last_obs: np.ndarray | None) -> None:
    """
    Put a freshly made VecEnv back in its saved state. A training env replays its last reset from the generator
    state it had then; the observation must come out as saved.

    :param env: the VecEnv, as made for the run
    :param states: what :func:`vec_env_state` returned
    :param last_obs: the agent's saved last observation (training env), checked against the replayed reset
    :raises RuntimeError: the replayed reset gives another observation (the env is not deterministic under its
        seed): the run cannot continue exactly and must start again
    """
    inner = dummy_vec_env(env)
    if inner is None or len(inner.envs) != len(states):
        raise ValueError(f"The checkpoint holds {len(states)} envs; the run's env does not match it.")
    for index, (slot, state) in enumerate(zip(inner.envs, states, strict=True)):
        if "last_reset" in state:
            reset = state["last_reset"]
            set_generator_state(slot.unwrapped, reset["generator"])
            observation, inner.reset_infos[index] = slot.reset(seed=reset["seed"], options=reset["options"])
            if last_obs is not None and not np.array_equal(np.asarray(observation), np.asarray(last_obs)[index]):
                raise RuntimeError(
                    f"Replaying env {index}'s last reset did not give the checkpoint's observation: the env is not "
                    "deterministic under its random generator, so the run cannot continue exactly. Start it again "
                    "(sb3-poplin-zoo compare --force, or train without --resume)."
                )
            set_buffered_observation(inner, index, observation)
        else:
            set_generator_state(slot.unwrapped, state["generator"])
        set_pending_reset(inner, index, state["seed"], state["options"])
        monitor = find_monitor(slot)
        if monitor is not None and "monitor" in state:
            for name, value in state["monitor"].items():
                setattr(monitor, name, copy.deepcopy(value))


def replay_buffer_arrays(buffer: ReplayBuffer) -> dict[str, Any]:
    """
    :param buffer: a replay buffer
    :return: its filled rows (and ``pos``, ``full``) as arrays
    """
    size = buffer.buffer_size if buffer.full else buffer.pos
    arrays = {
        name: getattr(buffer, name)[:size] for name in REPLAY_ARRAYS if isinstance(getattr(buffer, name, None), np.ndarray)
    }
    return {**arrays, "pos": np.array(buffer.pos), "full": np.array(buffer.full)}


def restore_replay_buffer(buffer: ReplayBuffer, arrays: dict[str, np.ndarray]) -> None:
    """
    :param buffer: a freshly made replay buffer of the same size
    :param arrays: what :func:`replay_buffer_arrays` returned
    """
    for name in REPLAY_ARRAYS:
        if name in arrays:
            rows = arrays[name]
            getattr(buffer, name)[: len(rows)] = rows
    buffer.pos = int(arrays["pos"])
    buffer.full = bool(arrays["full"])


def random_states(model: BaseAlgorithm) -> dict[str, Any]:
    """
    :param model: the agent
    :return: the global random states and the agent's action space's
    """
    states: dict[str, Any] = {
        "python": random.getstate(),
        "numpy": np.random.get_state(),
        "torch": th.get_rng_state(),
        "action_space": copy.deepcopy(model.action_space.np_random.bit_generator.state),
    }
    if th.cuda.is_available():
        states["cuda"] = th.cuda.get_rng_state_all()
    return states


def restore_random_states(model: BaseAlgorithm, states: dict[str, Any]) -> None:
    """
    :param model: the agent
    :param states: what :func:`random_states` returned
    """
    random.setstate(states["python"])
    np.random.set_state(states["numpy"])
    th.set_rng_state(states["torch"])
    if "cuda" in states and th.cuda.is_available():
        th.cuda.set_rng_state_all(states["cuda"])
    model.action_space.np_random.bit_generator.state = states["action_space"]


def checkpoint_folders(run_dir: str | pathlib.Path) -> list[pathlib.Path]:
    """
    :param run_dir: a run's folder
    :return: its complete checkpoints, oldest first
    """
    root = pathlib.Path(run_dir) / CHECKPOINT_FOLDER
    if not root.is_dir():
        return []
    found = [
        (int(path.name.split("-", 1)[1]), path)
        for path in root.iterdir()
        if re.fullmatch(r"step-\d+", path.name) and all((path / name).is_file() for name in CHECKPOINT_FILES)
    ]
    return [path for _, path in sorted(found)]


def latest_checkpoint(run_dir: str | pathlib.Path) -> pathlib.Path | None:
    """
    :param run_dir: a run's folder
    :return: its newest complete checkpoint, or ``None``
    """
    folders = checkpoint_folders(run_dir)
    return folders[-1] if folders else None


def drop_checkpoints(run_dir: str | pathlib.Path) -> None:
    """
    Remove a finished run's checkpoints: the folder is first renamed (atomically), so that a run killed while they
    are deleted is already seen as finished, never as a run with no checkpoint to start again.

    :param run_dir: the run's folder
    """
    folder = pathlib.Path(run_dir) / CHECKPOINT_FOLDER
    if not folder.exists():
        return
    finished = folder.with_name(f"{CHECKPOINT_FOLDER}.finished")
    if finished.exists():  # left by a run killed while deleting
        shutil.rmtree(finished, ignore_errors=True)
    os.replace(folder, finished)
    shutil.rmtree(finished, ignore_errors=True)


def save_checkpoint(run_dir: str | pathlib.Path, model: BaseAlgorithm, callbacks: list[BaseCallback]) -> pathlib.Path:
    """
    Save everything the run needs to continue from here (see the module's docstring), atomically.

    :param run_dir: the run's folder
    :param model: the agent, between two rollouts (its env just reset)
    :param callbacks: the run's callbacks
    :return: the checkpoint's folder
    """
    check_private_state_releases()
    run_dir = pathlib.Path(run_dir)
    final = run_dir / CHECKPOINT_FOLDER / f"step-{model.num_timesteps}"
    temporary = final.with_name(final.name + ".tmp")
    shutil.rmtree(temporary, ignore_errors=True)
    temporary.mkdir(parents=True)
    model.save(temporary / "model.zip")
    assert isinstance(model, OffPolicyAlgorithm) and isinstance(model.replay_buffer, ReplayBuffer)
    np.savez(temporary / "replay_buffer.npz", **replay_buffer_arrays(model.replay_buffer))
    env = model.get_env()
    assert env is not None
    files = {
        path.name: path.read_bytes() for path in run_dir.iterdir() if path.is_file() and RESULT_FILE_PATTERN.match(path.name)
    }
    state = {
        "num_timesteps": model.num_timesteps,
        "random": random_states(model),
        "env": vec_env_state(env, replay=True),
        "eval_envs": [vec_env_state(eval_env, replay=False) for eval_env in eval_envs(callbacks)],
        "callbacks": [
            {name: copy.deepcopy(getattr(callback, name)) for name in CALLBACK_ATTRIBUTES if hasattr(callback, name)}
            for callback in iter_callbacks(callbacks)
        ],
        "files": files,
    }
    buffer = io.BytesIO()
    th.save(state, buffer)
    with open(temporary / "state.pt", "wb") as file:
        file.write(buffer.getvalue())
        file.flush()
        os.fsync(file.fileno())
    shutil.rmtree(final, ignore_errors=True)
    os.replace(temporary, final)
    for older in checkpoint_folders(run_dir)[:-1]:
        shutil.rmtree(older, ignore_errors=True)
    return final


def restore_checkpoint(
    folder: str | pathlib.Path,
    model_class: type[BaseAlgorithm],
    env: VecEnv,
    callbacks: list[BaseCallback],
    device: th.device | str = "auto",
) -> BaseAlgorithm:
    """
    Continue a run from a checkpoint: load the agent onto the run's freshly made env, refill its replay buffer, put
    the env, the evaluation envs, the callbacks, the result files and the random states back as they were.

    :param folder: a checkpoint folder (:func:`latest_checkpoint`)
    :param model_class: the agent's class
    :param env: the run's training env, made as for a new run (:func:`record_resets` applied)
    :param callbacks: the run's callbacks, made as for a new run
    :param device: torch device
    :return: the agent, ready for ``learn(remaining, reset_num_timesteps=False)``
    """
    check_private_state_releases()
    folder = pathlib.Path(folder)
    state = th.load(folder / "state.pt", weights_only=False)
    model = model_class.load(folder / "model.zip", env=env, device=device, force_reset=False)
    assert isinstance(model, OffPolicyAlgorithm) and isinstance(model.replay_buffer, ReplayBuffer)
    with np.load(folder / "replay_buffer.npz") as arrays:
        restore_replay_buffer(model.replay_buffer, dict(arrays))
    last_obs = model._last_obs
    restore_vec_env(env, state["env"], last_obs if isinstance(last_obs, np.ndarray) else None)
    found = eval_envs(callbacks)
    if len(found) != len(state["eval_envs"]):
        raise ValueError(f"The checkpoint has {len(state['eval_envs'])} evaluation envs, the run {len(found)}.")
    for eval_env, saved in zip(found, state["eval_envs"], strict=True):
        restore_vec_env(eval_env, saved, None)
    every = list(iter_callbacks(callbacks))
    if len(every) != len(state["callbacks"]):
        raise ValueError(f"The checkpoint has {len(state['callbacks'])} callbacks, the run {len(every)}.")
    for callback, saved in zip(every, state["callbacks"], strict=True):
        for name, value in saved.items():
            setattr(callback, name, copy.deepcopy(value))
    restore_result_files(folder.parent.parent, state["files"], env)
    restore_random_states(model, state["random"])
    return model


def restore_result_files(run_dir: pathlib.Path, files: dict[str, bytes], env: VecEnv) -> None:
    """
    Put the run's result files back as they were at the checkpoint: a file written after it is removed or cut back,
    so that nothing the continued run writes again appears twice. An open Monitor file is rewritten in place.

    :param run_dir: the run's folder
    :param files: file name -> content at the checkpoint
    :param env: the training env (its Monitors hold their CSV files open)
    """
    open_files = {}
    inner = dummy_vec_env(env)
    for slot in inner.envs if inner is not None else []:
        monitor = find_monitor(slot)
        writer = getattr(monitor, "results_writer", None)
        if writer is not None:
            open_files[pathlib.Path(writer.file_handler.name).name] = writer.file_handler
    for path in run_dir.iterdir():
        if path.is_file() and RESULT_FILE_PATTERN.match(path.name) and path.name not in files:
            if path.name in open_files:
                open_files[path.name].seek(0)
                open_files[path.name].truncate()
            else:
                path.unlink()
    for name, content in files.items():
        if name in open_files:
            handle = open_files[name]
            handle.seek(0)
            handle.truncate()
            handle.write(content.decode())
            handle.flush()
        else:
            (run_dir / name).write_bytes(content)


class EpisodeCheckpointCallback(BaseCallback):
    """
    Save a checkpoint (:func:`save_checkpoint`) at the start of every rollout whose previous rollout ended with an
    episode, i.e. once the agent has learned from the episode and the env has been reset (with ``train_freq`` in
    steps, only the rollouts that end where an episode ends).

    :param run_dir: the run's folder
    :param callbacks: the run's other callbacks (their progress is saved too)
    :param verbose: 1 prints each checkpoint
    """

    def __init__(self, run_dir: str | pathlib.Path, callbacks: list[BaseCallback], verbose: int = 0) -> None:
        super().__init__(verbose)
        self.run_dir = pathlib.Path(run_dir)
        self.tracked = callbacks
        self._episode_ended = False

    def _on_step(self) -> bool:
        # the latest step only: a rollout of N steps may run past an episode's end into the next one
        self._episode_ended = bool(np.all(self.locals.get("dones", False)))
        return True

    def _on_rollout_start(self) -> None:
        if not self._episode_ended:
            return
        self._episode_ended = False
        folder = save_checkpoint(self.run_dir, self.model, self.tracked)
        if self.verbose >= 1:
            print(f"Checkpoint: {folder}")


class RunLock:
    """
    An exclusive lock on a run's folder, held while a process trains in it: a second process (a resumed
    comparison while the killed one's run still goes on, say) gets a clear error instead of writing the same files.

    :param run_dir: the run's folder
    """

    def __init__(self, run_dir: str | pathlib.Path) -> None:
        self.path = pathlib.Path(run_dir) / LOCK_FILE
        self.file: io.TextIOWrapper | None = None

    def acquire(self) -> None:
        """:raises RuntimeError: another process holds the lock"""
        self.path.parent.mkdir(parents=True, exist_ok=True)
        file = open(self.path, "a+")
        try:
            fcntl.flock(file, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            file.seek(0)
            holder = file.read().strip() or "unknown"
            file.close()
            raise RuntimeError(
                f"{self.path.parent} is in use by another training process (pid {holder}): wait for it to finish or "
                "stop it, then run the command again."
            ) from None
        file.seek(0)
        file.truncate()
        file.write(str(os.getpid()))
        file.flush()
        self.file = file

    def release(self) -> None:
        """Release the lock (also released by the OS when the process dies)."""
        if self.file is not None:  # the file stays: removing it would let two processes lock two files of one name
            fcntl.flock(self.file, fcntl.LOCK_UN)
            self.file.close()
            self.file = None
