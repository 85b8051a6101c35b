"""
Model error or planner error? Diagnose a trained agent on a MuJoCo task.

1. A held-out episode: the agent plans with its learned model (MPC) for ``--steps`` steps from a fresh
   reset; its return is the reference.
2. Model error on that episode: from every ``--stride``-th state, the learned ensemble (expectation
   propagation, as the planner uses it) predicts the next ``horizon`` states open-loop under the actions
   that were executed. Reported per prediction step k: the RMSE of the predicted state, in units of each
   dimension's standard deviation over the episode, and the error of the predicted k-step return
   (the quantity CEM ranks candidates by) against the real one.
3. Planner error: the same CEM (population, elites, iterations, momentum, horizon, action-sequence search
   with the PETS variance bound) plans with the *true simulator* (batched ``mujoco.rollout`` from the
   env's exact state) for ``--true-steps`` steps from the same reset. If this return is far above the
   learned-model MPC return, the model is what limits the agent; if it is not, the planner budget is.

    python benchmarks/diagnosis/diagnose_mpc.py --model logs/.../HalfCheetah-v5.zip --env HalfCheetah-v5

Adds one row to benchmarks/RESULTS.md (section "MPC diagnosis") unless ``--no-record``.
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import sys
import time

import gymnasium as gym
import mujoco
import numpy as np
import torch as th
from mujoco import rollout

from sb3_poplin import POPLIN
from gymnasium.envs.mujoco.half_cheetah_v5 import HalfCheetahEnv

from sb3_poplin.envs.mujoco_variants import PETSCheetahEnv
from sb3_poplin.analysis.model_error import model_error, mpc_episode
from sb3_poplin.planning import CEM, ActionSequences
from sb3_poplin.tasks import make_env, make_task
from sb3_poplin.variants import VARIANTS, replanner

# benchmarks/, where results_file.py (shared by the scripts of every subfolder) lives
sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
from results_file import append_row, describe_machine


class TrueModelPlanner:
    """
    CEM over action sequences whose candidates are scored by rolling out the true MuJoCo simulator.

    :param env: the (unwrapped-accessible) MuJoCo env
    :param model: the trained agent (its CEM settings and task reward are used)
    :param budget: ``(horizon, population, elites, iterations)`` to plan with instead of the agent's (its
        momentum, bounds and task are kept): what a perfect model reaches at another planner budget
    """

    # the envs whose observations this planner rebuilds from MuJoCo states (and that never terminate)
    SUPPORTED = (HalfCheetahEnv, PETSCheetahEnv)

    def __init__(self, env: gym.Env, model: POPLIN, budget: tuple[int, int, int, int] | None = None) -> None:
        self.env = env.unwrapped
        nq, nv = self.env.model.nq, self.env.model.nv
        if type(self.env) not in self.SUPPORTED or env.observation_space.shape != (nq + nv,):
            raise ValueError(
                f"The true-simulator planner rebuilds observations as [qpos, qvel] (HalfCheetah-v5 with x kept) or "
                f"PETSCheetah's velocity observation, and never terminates; {type(self.env).__name__} with observation "
                f"shape {env.observation_space.shape} is not one of them: its scores would not be what the env pays. "
                f"Pass --true-steps 0 to skip the true-simulator planning."
            )
        self.task = make_task(model.task_id)
        if budget is None:
            s = model.settings
            budget = (s.horizon, s.population_size, s.num_elites, s.cem_iterations)
        if len(budget) != 4 or min(budget) < 1:
            raise ValueError(f"budget must be four positive integers (horizon, population, elites, iterations), got {budget}")
        self.horizon, population, elites, iterations = (int(b) for b in budget)
        self.cem = CEM(population, elites, iterations, model.settings.cem_alpha)
        self.to_env_units = model.planner.to_env_units  # scaled actions -> env units, from the agent's bounds
        self.action_dim = int(model.action_space.shape[0])
        # PETS's search space: its initial variance, its bound-aware variance cap and its shift
        self.space = ActionSequences(self.horizon, self.action_dim, VARIANTS["pets"].init_var)
        self.frame_skip = self.env.frame_skip
        self.mj_model = self.env.model
        self.mj_data = mujoco.MjData(self.mj_model)
        self.spec = mujoco.mjtState.mjSTATE_FULLPHYSICS
        self.generator = th.Generator().manual_seed(0)
        self.mean = self.space.initial_mean(1, th.device("cpu"))
        self.qpos = slice(1, 1 + nq)  # full-physics state: [time, qpos, qvel, ...]
        self.qvel = slice(1 + nq, 1 + nq + nv)

    def observation(self, state: np.ndarray) -> np.ndarray:
        """Observation (x position kept) of full-physics states ``[..., nstate]``."""
        return np.concatenate([state[..., self.qpos], state[..., self.qvel]], axis=-1)

    def observations(self, initial_state: np.ndarray, states: np.ndarray) -> np.ndarray:
        """
        :param initial_state: the full-physics state planned from
        :param states: ``[N, H, nstate]`` the states after each step of the candidates
        :return: ``[N, H + 1, obs]`` the task's observations of the start and of every step
        """
        n = states.shape[0]
        obs = np.concatenate([np.tile(self.observation(initial_state), (n, 1, 1)), self.observation(states)], axis=1)
        if isinstance(self.env, PETSCheetahEnv):  # obs[0] is the last step's mean x velocity, not x
            x = obs[..., 0].copy()
            obs[:, 1:, 0] = np.diff(x, axis=1) / self.env.dt
            obs[:, 0, 0] = self.env._get_obs()[0]
        return obs

    def evaluate(self, initial_state: np.ndarray, z: th.Tensor) -> th.Tensor:
        """Returns ``[1, N]`` of candidates ``z [1, N, H * a]`` (scaled actions) rolled out in MuJoCo."""
        n = z.shape[1]
        scaled = z[0].clamp(-1.0, 1.0).view(n, self.horizon, self.action_dim)
        actions = self.to_env_units(scaled).double().numpy()  # [N, H, a] env units
        control = np.repeat(actions, self.frame_skip, axis=1)  # each action held for frame_skip substeps
        states, _ = rollout.rollout(self.mj_model, self.mj_data, np.tile(initial_state, (n, 1)), control)
        states = states[:, self.frame_skip - 1 :: self.frame_skip]  # [N, H, nstate] after each env step
        obs = self.observations(initial_state, states)
        obs_t = th.as_tensor(obs, dtype=th.float32)
        act_t = th.as_tensor(actions, dtype=th.float32)
        flat = self.task.reward_fn(
            obs_t[:, :-1].reshape(-1, obs.shape[-1]),
            act_t.reshape(-1, self.action_dim),
            obs_t[:, 1:].reshape(-1, obs.shape[-1]),
        )
        return flat.view(n, self.horizon).sum(dim=1).unsqueeze(0)

    def act(self) -> np.ndarray:
        """Plan from the env's current exact state; return the first action in env units."""
        state = np.empty(mujoco.mj_stateSize(self.mj_model, self.spec))
        mujoco.mj_getState(self.mj_model, self.env.data, state, self.spec)
        space = self.space
        evaluate = lambda z: self.evaluate(state, z)  # noqa: E731
        result = self.cem.optimize(evaluate, self.mean, space.initial_var(self.mean), space.constrain_var, self.generator)
        first = space.executed_action(result.solution, th.empty(0), None)
        self.mean = space.shift(result.solution)
        return self.to_env_units(first)[0].double().numpy()


def true_model_episode(
    env: gym.Env, model: POPLIN, steps: int, seed: int, budget: tuple[int, int, int, int] | None = None
) -> tuple[float, float]:
    """
    :param budget: ``(horizon, population, elites, iterations)``; None: the agent's
    :return: the return of ``steps`` steps planned with the true simulator, and seconds per step (0, nan: none)
    """
    if steps == 0:
        return 0.0, float("nan")
    planner = TrueModelPlanner(env, model, budget)
    env.reset(seed=seed)
    total, start = 0.0, time.perf_counter()
    for _ in range(steps):
        _, reward, terminated, truncated, _ = env.step(planner.act())
        total += float(reward)
        if terminated or truncated:
            break
    return total, (time.perf_counter() - start) / steps


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--model", required=True, help="a saved POPLIN zip")
    parser.add_argument("--env", required=True, help="gymnasium id of the MuJoCo task it was trained on")
    parser.add_argument("--steps", type=int, default=1000, help="length of the held-out MPC episode")
    parser.add_argument("--true-steps", type=int, default=1000, help="steps planned with the true simulator")
    parser.add_argument("--stride", type=int, default=5, help="start every n-th state for the model error")
    parser.add_argument("--seed", type=int, default=1000)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--label", default="", help="what the model is (for the RESULTS row)")
    parser.add_argument(
        "--search",
        choices=["own", "pets"],
        default="own",
        help="pets: plan the held-out episode with the same learned model but PETS's action-sequence search "
        "(same CEM budget), to tell a POPLIN search-space problem from a model problem",
    )
    parser.add_argument(
        "--true-budget",
        type=int,
        nargs=4,
        metavar=("HORIZON", "POPULATION", "ELITES", "ITERATIONS"),
        help="plan with the true simulator at this CEM budget instead of the model's (e.g. the paper's 30 500 50 5)",
    )
    parser.add_argument("--no-record", action="store_true")
    args = parser.parse_args()
    th.set_num_threads(args.threads)
    model = POPLIN.load(args.model, device="cpu")
    controller = model.mpc if args.search == "own" else replanner(model, "pets")
    env = make_env(args.env)
    start = time.perf_counter()
    episode = mpc_episode(controller, env, args.steps, args.seed)
    mpc_time = (time.perf_counter() - start) / len(episode.actions)
    errors = model_error(model, episode, args.stride)
    true_return, true_time = true_model_episode(env, model, args.true_steps, args.seed, args.true_budget)
    ran_true = args.true_steps > 0
    mpc_return = float(episode.rewards[: args.true_steps].sum())
    ks = sorted({0, 4, model.settings.horizon - 1} & set(range(model.settings.horizon)))
    summary = {
        "mpc_return": float(episode.rewards.sum()),
        "mpc_return_first_true_steps": mpc_return if ran_true else None,
        "true_model_return": true_return if ran_true else None,
        "state_rmse": {k + 1: errors["state_rmse"][k] for k in ks},
        "return_abs_error": {k + 1: errors["return_abs_error"][k] for k in ks},
        "real_return_abs": {k + 1: errors["real_return_abs"][k] for k in ks},
        "seconds_per_step": {"learned": mpc_time, "true": true_time if ran_true else None},
    }
    print(json.dumps(summary, indent=2))
    if args.no_record:
        return
    budget = (
        f"{model.variant if args.search == 'own' else 'pets'} search, H {model.settings.horizon}, "
        f"pop {model.settings.population_size}, elites {model.settings.num_elites}, "
        f"{model.settings.cem_iterations} it"
    )
    if args.true_budget and ran_true:
        h_, p_, e_, i_ = args.true_budget
        budget += f"; true simulator: H {h_}, pop {p_}, elites {e_}, {i_} it"
    h = model.settings.horizon
    command = (
        f"`python benchmarks/diagnosis/diagnose_mpc.py --model {args.model} --env {args.env} --steps {args.steps} "
        f"--true-steps {args.true_steps} --seed {args.seed}"
        + (f" --search {args.search}" if args.search != "own" else "")
        + (f" --true-budget {' '.join(map(str, args.true_budget))}" if args.true_budget else "")
        + "`"
    )
    row = [
        str(datetime.date.today()),
        describe_machine(args.threads),
        args.label or os.path.basename(args.model),
        args.env,
        budget,
        f"{summary['mpc_return']:.1f} ({len(episode.actions)} steps)",
        f"{mpc_return:.1f}" if ran_true else "not run",
        f"{true_return:.1f}" if ran_true else "not run (--true-steps 0)",
        f"{errors['state_rmse'][0]:.3f} / {errors['state_rmse'][h - 1]:.3f}",
        f"{errors['return_abs_error'][h - 1]:.1f} / {errors['real_return_abs'][h - 1]:.1f}",
        command,
    ]
    header = [
        "date",
        "machine",
        "model",
        "task",
        "planner budget",
        "learned-model MPC return",
        "same, first true-steps",
        "true-simulator MPC return (true-steps)",
        "state RMSE (std units) k=1 / k=H",
        "H-step return error / mean abs real H-step return",
        "command",
    ]
    intro = (
        "Model error or planner error (`benchmarks/diagnosis/diagnose_mpc.py`): a held-out MPC episode with the learned "
        "model, the ensemble's open-loop prediction error along it, and the same CEM planning with the true simulator."
    )
    append_row("MPC diagnosis", intro, header, row)


if __name__ == "__main__":
    main()
