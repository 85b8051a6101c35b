"""
Callbacks for POPLIN training.

:class:`ControlModesEvalCallback` evaluates the agent under both control modes during training,
MPC (planning with the model) and policy control (the distilled network alone), as the paper's
figures do. It logs ``eval/mpc_mean_reward`` and ``eval/policy_mean_reward`` and writes
``evaluations_mpc.npz`` / ``evaluations_policy.npz`` in the format of SB3's ``EvalCallback``
(``timesteps``, ``results``, ``ep_lengths``), so rl-zoo3's plotting reads them. With rl-zoo3:

.. code-block:: yaml

    callback:
      - sb3_poplin.callbacks.ControlModesEvalCallback:
          eval_freq: 1000
          n_eval_episodes: 5
"""

from __future__ import annotations

import os
from typing import Any

import gymnasium as gym
import numpy as np
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.evaluation import evaluate_policy
from stable_baselines3.common.vec_env import VecEnv

from sb3_poplin.tasks import task_env_kwargs


class ControlModesEvalCallback(BaseCallback):
    """
    Evaluate MPC and policy control every ``eval_freq`` steps.

    :param eval_env: evaluation env (id, Env or VecEnv); ``None`` makes one from the model's task id
    :param eval_freq: evaluate every this many calls (env steps of the training VecEnv)
    :param n_eval_episodes: episodes per mode and evaluation
    :param log_path: folder for the ``.npz`` files; ``None``: the logger's folder, if it has one
    :param modes: control modes to evaluate; policy control is skipped for agents without a policy network
    :param deterministic: passed to ``predict``
    :param verbose: 1 prints each evaluation
    """

    def __init__(
        self,
        eval_env: gym.Env | VecEnv | str | None = None,
        eval_freq: int = 1000,
        n_eval_episodes: int = 5,
        log_path: str | None = None,
        modes: tuple[str, ...] = ("mpc", "policy"),
        deterministic: bool = True,
        verbose: int = 0,
    ) -> None:
        super().__init__(verbose)
        if eval_freq < 1 or n_eval_episodes < 1:
            raise ValueError(f"eval_freq and n_eval_episodes must be >= 1, got {eval_freq} and {n_eval_episodes}")
        self.eval_env = eval_env
        self.eval_freq = eval_freq
        self.n_eval_episodes = n_eval_episodes
        self.log_path = log_path
        self.modes = tuple(modes)
        self.deterministic = deterministic
        self.timesteps: list[int] = []
        self.results: dict[str, list[list[float]]] = {mode: [] for mode in self.modes}
        self.lengths: dict[str, list[list[int]]] = {mode: [] for mode in self.modes}

    def _init_callback(self) -> None:
        if self.eval_env is None:
            env_id = getattr(self.model, "task_id", None)
            if env_id is None:
                raise ValueError("ControlModesEvalCallback needs eval_env= when the model's env id is unknown.")
            self.eval_env = env_id
        if isinstance(self.eval_env, str):
            env_id = self.eval_env
            self.eval_env = make_vec_env(env_id, n_envs=1, env_kwargs=task_env_kwargs(env_id))
        if self.log_path is None and self.logger is not None and self.logger.get_dir():
            self.log_path = self.logger.get_dir()
        if self.log_path is not None:
            os.makedirs(self.log_path, exist_ok=True)

    def _active_modes(self) -> list[str]:
        has_policy = getattr(self.model.policy, "actor", None) is not None
        return [mode for mode in self.modes if mode == "mpc" or has_policy]

    def _on_step(self) -> bool:
        if self.n_calls % self.eval_freq != 0:
            return True
        model: Any = self.model
        previous = model.control
        self.timesteps.append(self.num_timesteps)
        try:
            for mode in self._active_modes():
                model.control = mode
                returns, lengths = evaluate_policy(
                    model,
                    self.eval_env,  # type: ignore[arg-type]
                    n_eval_episodes=self.n_eval_episodes,
                    deterministic=self.deterministic,
                    return_episode_rewards=True,
                )
                assert isinstance(returns, list) and isinstance(lengths, list)
                self.results[mode].append([float(r) for r in returns])
                self.lengths[mode].append([int(n) for n in lengths])
                self.logger.record(f"eval/{mode}_mean_reward", float(np.mean(returns)))
                self.logger.record(f"eval/{mode}_std_reward", float(np.std(returns)))
                if self.verbose >= 1:
                    print(f"Eval {mode} at {self.num_timesteps} steps: {np.mean(returns):.2f} ± {np.std(returns):.2f}")
                if self.log_path is not None:
                    np.savez(
                        os.path.join(self.log_path, f"evaluations_{mode}.npz"),
                        timesteps=np.array(self.timesteps),
                        results=np.array(self.results[mode]),
                        ep_lengths=np.array(self.lengths[mode]),
                    )
        finally:
            model.control = previous
        self.logger.dump(self.num_timesteps)
        return True
