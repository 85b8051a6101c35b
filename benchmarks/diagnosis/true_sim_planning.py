"""
The planner's quality apart from any learned model: CEM and iCEM planning with the true MuJoCo dynamics.

The package's own planner classes (the :class:`~sb3_poplin.planning.CEM` with its iCEM options, the search spaces,
:meth:`~sb3_poplin.planning.MPCPlanner.plan` with its warm start and carried elites) plan every step of an episode;
only :meth:`~sb3_poplin.planning.MPCPlanner.rollout` is replaced: each candidate is stepped through the simulator
(``mujoco.rollout`` from the env's exact state, one env step of ``frame_skip`` substeps at a time), its actions come
from the search space on its own true observations (POPLIN-P: every candidate's perturbed network acts on its own
states, closed loop), and the task's reward scores it. Tasks: ``sb3_poplin/PETSCheetah-v0`` and ``HalfCheetah-v5``
(never terminating; observations rebuilt from the physics state).

Each planner is given as ``NAME:POPxIT[:key=value,...]``, e.g. ``cem:500x5`` (the paper's CEM), ``icem:100x3`` (iCEM's
defaults) or ``icem:100x3:noise_beta=0.25`` (any ``optimizer_kwargs``); elites are ``--elite-fraction`` of the
population (the paper's 10 %). Returns per start state (env seeds ``--seed``, ``--seed`` + 1, ...)::

    python benchmarks/diagnosis/true_sim_planning.py --env sb3_poplin/PETSCheetah-v0 --horizon 30 \\
        --planners cem:500x5 icem:200x3 icem:100x3:noise_beta=0.25 --starts 4 --steps 300

``--search poplin-p --policy ZIP`` plans as POPLIN-P Sep around that agent's policy network (``--policy init``: a new
agent's initial network). Adds one row per planner to benchmarks/RESULTS.md unless ``--no-record``; ``--output``
also writes every return as JSON.
"""

from __future__ import annotations

import argparse
import ast
import datetime
import json
import os
import sys
import time
from dataclasses import replace
from typing import Any

import gymnasium as gym
import mujoco
import numpy as np
import torch as th
from gymnasium.envs.mujoco.half_cheetah_v5 import HalfCheetahEnv
from mujoco import rollout

from sb3_poplin import POPLIN
from sb3_poplin.envs.mujoco_variants import PETSCheetahEnv
from sb3_poplin.planning import CEM, OPTIMIZERS, ActionSequences, MPCPlanner, PolicyParameterNoise, SearchSpace
from sb3_poplin.policies import PolicyNetwork
from sb3_poplin.tasks import make_env, make_task
from sb3_poplin.variants import VARIANTS

# benchmarks/, where results_file.py (shared by the scripts of every subfolder) lives
sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
from results_file import append_row, describe_machine

SUPPORTED = (HalfCheetahEnv, PETSCheetahEnv)


def parse_planner(text: str, elite_fraction: float) -> CEM:
    """
    ``NAME:POPxIT[:key=value,...]`` -> the CEM it describes. Keys: the ``optimizer_kwargs``
    (:class:`~sb3_poplin.planning.CEMOptions`, e.g. ``variance_cap=True``) and ``sampling`` (``truncated``, the
    default, or ``clipped``).
    """
    parts = text.split(":")
    if len(parts) not in (2, 3) or parts[0] not in OPTIMIZERS or "x" not in parts[1]:
        raise ValueError(f"planner {text!r}: expected NAME:POPxIT[:key=value,...] with NAME one of {list(OPTIMIZERS)}")
    population, iterations = (int(v) for v in parts[1].split("x"))
    options: dict[str, Any] = {}
    sampling = "truncated"
    if len(parts) == 3:
        for item in parts[2].split(","):
            key, value = item.split("=")
            if key == "sampling":
                sampling = value
            else:
                options[key] = ast.literal_eval(value) if value not in ("mean", "best") else value
    cem_options = replace(OPTIMIZERS[parts[0]], **options)
    elites = max(1, round(population * elite_fraction))
    return CEM(population, elites, iterations, alpha=0.1, sampling=sampling, options=cem_options)


class TrueSimulator:
    """Steps batches of full-physics MuJoCo states by one env step and rebuilds the task's observations."""

    def __init__(self, env: gym.Env) -> None:
        self.env = env.unwrapped
        nq, nv = self.env.model.nq, self.env.model.nv
        if type(self.env) not in SUPPORTED or env.observation_space.shape != (nq + nv,):
            raise ValueError(
                f"The true-simulator planner rebuilds observations as [qpos, qvel] (HalfCheetah-v5 with x kept) or "
                f"PETSCheetah's velocity observation, and never terminates; {type(self.env).__name__} with observation "
                f"shape {env.observation_space.shape} is not one of them."
            )
        self.mj_model = self.env.model
        self.mj_data = mujoco.MjData(self.mj_model)
        self.spec = mujoco.mjtState.mjSTATE_FULLPHYSICS
        self.frame_skip = self.env.frame_skip
        self.qpos, self.qvel = slice(1, 1 + nq), slice(1 + nq, 1 + nq + nv)  # [time, qpos, qvel, ...]
        self.velocity_obs = isinstance(self.env, PETSCheetahEnv)  # obs[0]: the last step's mean x velocity

    def state(self) -> np.ndarray:
        """The env's exact full-physics state."""
        state = np.empty(mujoco.mj_stateSize(self.mj_model, self.spec))
        mujoco.mj_getState(self.mj_model, self.env.data, state, self.spec)
        return state

    def step(self, states: np.ndarray, actions: np.ndarray) -> np.ndarray:
        """``states [N, nstate]``, actions in env units ``[N, a]`` -> the states one env step later."""
        control = np.repeat(actions[:, None, :], self.frame_skip, axis=1)
        after, _ = rollout.rollout(self.mj_model, self.mj_data, states, control)
        return after[:, -1]

    def observation(self, before: np.ndarray, after: np.ndarray) -> np.ndarray:
        """The observation of the states ``after`` one env step from ``before`` (``[N, nstate]`` each)."""
        obs = np.concatenate([after[:, self.qpos], after[:, self.qvel]], axis=1)
        if self.velocity_obs:
            obs[:, 0] = (after[:, self.qpos.start] - before[:, self.qpos.start]) / self.env.dt
        return obs


class TrueSimulatorPlanner(MPCPlanner):
    """:class:`MPCPlanner` whose rollout steps every candidate through the true simulator from the env's state."""

    def __init__(self, simulator: TrueSimulator, space: SearchSpace, optimizer: CEM, task: Any, action_space: Any) -> None:
        # the learned model is never used: a one-member stand-in satisfies the constructor
        from sb3_poplin.dynamics import ProbabilisticEnsemble

        obs_dim = int(np.prod(simulator.env.observation_space.shape))
        stand_in = ProbabilisticEnsemble(obs_dim, int(action_space.shape[0]), 1, ())
        low = th.as_tensor(action_space.low, dtype=th.float32)
        high = th.as_tensor(action_space.high, dtype=th.float32)
        super().__init__(stand_in, space, optimizer, task.reward_fn, None, "expectation", 1, low, high)
        self.simulator = simulator
        self.start: np.ndarray | None = None  # the env's exact state, set before each plan

    def rollout(self, obs: th.Tensor, z: th.Tensor, context: Any, generator: th.Generator | None = None) -> th.Tensor:
        assert self.start is not None and obs.shape[0] == 1, "one env, its exact state set before planning"
        n = z.shape[1]
        states = np.tile(self.start, (n, 1))
        observations = obs.expand(n, -1)  # [N, o]
        total = th.zeros(n, dtype=th.float64)
        for t in range(self.search_space.horizon):
            scaled = self.search_space.actions(z, t, observations.view(1, n, 1, -1), context).view(n, -1)
            actions = self.to_env_units(scaled)
            after = self.simulator.step(states, actions.double().numpy())
            next_obs = th.as_tensor(self.simulator.observation(states, after), dtype=th.float32)
            total += self.reward_fn(observations, actions, next_obs).double()  # type: ignore[misc]
            states, observations = after, next_obs
        return total.float().unsqueeze(0)


def search_space(args: argparse.Namespace, action_dim: int, env_id: str) -> SearchSpace:
    if args.search == "pets":
        return ActionSequences(args.horizon, action_dim, VARIANTS["pets"].init_var)
    if args.policy == "init":
        policy = POPLIN("poplin-p", env_id, seed=0, device="cpu").policy.actor
    else:
        policy = POPLIN.load(args.policy, device="cpu").policy.actor
    assert isinstance(policy, PolicyNetwork)
    return PolicyParameterNoise(args.horizon, action_dim, VARIANTS["poplin-p"].init_var, policy, "sep")


def episode(planner: TrueSimulatorPlanner, env: gym.Env, steps: int, seed: int) -> tuple[float, float]:
    """The return of ``steps`` planned steps from the reset of ``seed``, and seconds per step."""
    obs, _ = env.reset(seed=seed)
    generator = th.Generator().manual_seed(seed)
    state = planner.initial_state(1, th.device("cpu"))
    total, start = 0.0, time.perf_counter()
    for _ in range(steps):
        planner.start = planner.simulator.state()
        plan = planner.plan(th.as_tensor(obs, dtype=th.float32).unsqueeze(0), state, generator)
        state = plan.next_state
        obs, reward, terminated, truncated, _ = env.step(planner.to_env_units(plan.action)[0].double().numpy())
        total += float(reward)
        if terminated or truncated:
            break
    return total, (time.perf_counter() - start) / steps


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--env", required=True, choices=["sb3_poplin/PETSCheetah-v0", "HalfCheetah-v5"])
    parser.add_argument("--search", choices=["pets", "poplin-p"], default="pets")
    parser.add_argument("--policy", default="init", help="POPLIN-P: a saved agent's zip, or 'init' (a new network)")
    parser.add_argument("--horizon", type=int, default=30)
    parser.add_argument("--planners", nargs="+", required=True, help="NAME:POPxIT[:key=value,...], e.g. cem:500x5")
    parser.add_argument("--elite-fraction", type=float, default=0.1)
    parser.add_argument("--starts", type=int, default=4)
    parser.add_argument("--steps", type=int, default=300)
    parser.add_argument("--seed", type=int, default=1000)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--output", help="JSON file for every return")
    parser.add_argument("--no-record", action="store_true")
    args = parser.parse_args()
    th.set_num_threads(args.threads)
    env = make_env(args.env)
    task = make_task(args.env)
    simulator = TrueSimulator(env)
    space = search_space(args, int(env.action_space.shape[0]), args.env)
    results = []
    for label in args.planners:
        cem = parse_planner(label, args.elite_fraction)
        planner = TrueSimulatorPlanner(simulator, space, cem, task, env.action_space)
        returns, times = [], []
        for start in range(args.starts):
            ret, seconds = episode(planner, env, args.steps, args.seed + start)
            returns.append(ret)
            times.append(seconds)
            print(f"{label}: start {args.seed + start}: {ret:.1f} ({seconds:.3f} s/step)", flush=True)
        samples = cem.evaluations(reuse=True)
        results.append(dict(planner=label, samples_per_step=samples, returns=returns, seconds_per_step=float(np.mean(times))))
        print(f"{label}: {samples} candidates/step, {np.mean(returns):.1f} ± {np.std(returns):.1f}", flush=True)
        if not args.no_record:
            record(args, label, samples, returns, float(np.mean(times)))
    if args.output:
        with open(args.output, "w") as file:
            json.dump(dict(vars(args), results=results), file, indent=1)


def record(args: argparse.Namespace, label: str, samples: int, returns: list[float], seconds: float) -> None:
    search = "PETS (action sequences)" if args.search == "pets" else f"POPLIN-P Sep around {os.path.basename(args.policy)}"
    command = (
        f"`python benchmarks/diagnosis/true_sim_planning.py --env {args.env} --search {args.search}"
        + (f" --policy {args.policy}" if args.search == "poplin-p" else "")
        + f" --horizon {args.horizon} --planners {label} --starts {args.starts} --steps {args.steps} --seed {args.seed}`"
    )
    row = [
        str(datetime.date.today()),
        describe_machine(args.threads),
        args.env,
        search,
        str(args.horizon),
        label,
        str(samples),
        f"{np.mean(returns):.1f} ± {np.std(returns):.1f} ({', '.join(f'{r:.1f}' for r in returns)})",
        f"{seconds:.3f}",
        command,
    ]
    header = [
        "date",
        "machine",
        "task",
        "search space",
        "H",
        "planner",
        "candidates / step",
        f"{args.steps}-step return, mean ± std (per start)",
        "s / step",
        "command",
    ]
    intro = (
        "The planner apart from the model (`benchmarks/diagnosis/true_sim_planning.py`, issue 35): our CEM and iCEM "
        "plan with the true MuJoCo dynamics from the env's exact state, episodes of a fixed length from fixed starts."
    )
    append_row("Planning with the true simulator: CEM against iCEM", intro, header, row)


if __name__ == "__main__":
    main()
