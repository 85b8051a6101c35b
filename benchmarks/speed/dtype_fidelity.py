"""
Does bf16 planning control as well as fp32 planning? Held-out MPC episodes of trained agents, planned once with
``planning_dtype="float32"`` and once with ``"bfloat16"``, from the same resets and planner seeds.

For every model, reset seed and dtype: one MPC episode of ``--steps`` steps (the agent's own search and model; the
agent's planner budget, or the paper's with ``--budget paper``), its return and the planning seconds per step. Along
the fp32 episode, every ``--compare-every``-th step is planned a second time in bf16 from the same state, warm start
and random state: the largest change of the executed action (in [-1, 1] units) on the states an fp32 controller
visits; beside it the same change between two fp32 plans from the same inputs but different random states (a third
controller, seeded ``seed + 1``), the scale of what the sampling alone moves. ``--changes-only`` runs only that
comparison episode. One row per model in benchmarks/RESULTS.md, section "bf16 planning on trained agents", unless
``--no-record``.

    python benchmarks/speed/dtype_fidelity.py --env HalfCheetah-v5 --models a.zip b.zip --seeds 1000 1001

The seconds per step include the simulator step and are timed while other runs may share the host: a plan-speed
ratio belongs to ``planning_speed.py`` (one process, idle cores), not to this script.
"""

from __future__ import annotations

import argparse
import datetime
import os
import sys
import time
import warnings

import numpy as np
import torch as th

from sb3_poplin import POPLIN
from sb3_poplin.analysis.model_error import mpc_episode
from sb3_poplin.planning import MPCController
from sb3_poplin.tasks import make_env
from sb3_poplin.variants import replanner

# benchmarks/, where results_file.py (shared by the scripts of every subfolder) lives
sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
from results_file import append_row, describe_machine

DTYPES = ("float32", "bfloat16")
# the paper's planner (poplin.yml): population 500, 50 elites, horizon 30, 5 iterations
PAPER_BUDGET = dict(horizon=30, population_size=500, num_elites=50, cem_iterations=5)


def controllers(agent: POPLIN, seed: int, budget: str, dtypes: tuple[str, ...] = DTYPES) -> dict[str, MPCController]:
    """The agent's own search at its (or the paper's) budget, one controller per dtype, each seeded with ``seed``."""
    overrides = PAPER_BUDGET if budget == "paper" else {}
    return {dtype: replanner(agent, agent.variant, seed=seed, planning_dtype=dtype, **overrides) for dtype in dtypes}


def action_changes(
    agent: POPLIN, env_id: str, seed: int, budget: str, steps: int, every: int
) -> tuple[list[float], list[float]]:
    """
    At every ``every``-th step of an fp32 MPC episode, the largest executed-action change of a bf16 plan from the fp32
    plan's exact inputs (random state included), and of an fp32 plan from the same state and warm start with another
    random state.
    """
    plans = controllers(agent, seed, budget)
    fp32, bf16 = plans["float32"], plans["bfloat16"]
    reseeded = controllers(agent, seed + 1, budget, ("float32",))["float32"]
    env = make_env(env_id)
    obs, _ = env.reset(seed=seed)
    state: np.ndarray | None = None
    changes: tuple[list[float], list[float]] = ([], [])
    for t in range(steps):
        obs_tensor = th.as_tensor(obs, dtype=th.float32, device=fp32.device).unsqueeze(0)
        start = np.array([t == 0])
        if t % every == 0:
            bf16.generator.set_state(fp32.generator.get_state())
            others = [bf16.step(obs_tensor, state, episode_start=start).actions[0]]
            others.append(reseeded.step(obs_tensor, state, episode_start=start).actions[0])
        step = fp32.step(obs_tensor, state, episode_start=start)
        if t % every == 0:
            scaled = agent.policy.scale_action(np.stack([step.actions[0], *others]))
            for k in (0, 1):
                changes[k].append(float(np.abs(scaled[0] - scaled[k + 1]).max()))
        state = step.state
        obs, _, terminated, truncated, _ = env.step(step.actions[0])
        if terminated or truncated:
            break
    return changes


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--models", nargs="+", required=True, help="saved POPLIN zips")
    parser.add_argument("--env", required=True, help="gymnasium id of the task they were trained on")
    parser.add_argument("--steps", type=int, default=1000, help="steps per held-out episode")
    parser.add_argument("--seeds", type=int, nargs="+", default=[1000], help="reset and planner seeds")
    parser.add_argument("--budget", choices=["own", "paper"], default="own", help="the agent's planner or the paper's")
    parser.add_argument("--compare-every", type=int, default=10, help="0: no same-input action comparison")
    parser.add_argument("--changes-only", action="store_true", help="only the same-input comparison episode")
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--label", default="", help="what the models are (for the RESULTS row)")
    parser.add_argument("--no-record", action="store_true")
    args = parser.parse_args()
    th.set_num_threads(args.threads)
    for path in args.models:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            agent = POPLIN.load(path, device="cpu")
        returns: dict[str, list[float]] = {dtype: [] for dtype in DTYPES}
        seconds: dict[str, list[float]] = {dtype: [] for dtype in DTYPES}
        for seed in [] if args.changes_only else args.seeds:
            for dtype, controller in controllers(agent, seed, args.budget).items():
                begin = time.perf_counter()
                episode = mpc_episode(controller, make_env(args.env), args.steps, seed)
                seconds[dtype].append((time.perf_counter() - begin) / len(episode.actions))
                returns[dtype].append(float(episode.rewards.sum()))
                print(f"{os.path.basename(os.path.dirname(path))} seed {seed} {dtype}: return {returns[dtype][-1]:.1f}")
        changes, reference = (
            action_changes(agent, args.env, args.seeds[0], args.budget, args.steps, args.compare_every)
            if args.compare_every
            else ([], [])
        )
        if changes:
            print(f"  action change: median {np.median(changes):.4f}, max {max(changes):.4f} over {len(changes)} plans")
            print(f"  fp32 reseeded: median {np.median(reference):.4f}, max {max(reference):.4f}")
        if args.no_record:
            continue
        settings = agent.settings
        h, pop, it = (
            (30, 500, 5) if args.budget == "paper" else (settings.horizon, settings.population_size, settings.cem_iterations)
        )
        command = (
            f"`python benchmarks/speed/dtype_fidelity.py --models {path} --env {args.env} --steps {args.steps} "
            f"--seeds {' '.join(map(str, args.seeds))} --budget {args.budget} --compare-every {args.compare_every}"
            + (" --changes-only`" if args.changes_only else "`")
        )
        row = [
            str(datetime.date.today()),
            describe_machine(args.threads),
            args.label or os.path.basename(os.path.dirname(path)),
            f"{agent.variant}, H {h}, pop {pop}, {it} it, {settings.propagation}",
            " / ".join(f"{r:.1f}" for r in returns["float32"]) or "not run",
            " / ".join(f"{r:.1f}" for r in returns["bfloat16"]) or "not run",
            f"{np.mean(returns['bfloat16']) - np.mean(returns['float32']):+.1f}" if returns["float32"] else "not run",
            (
                f"{np.median(changes):.4f} / {max(changes):.4f} ({len(changes)}); fp32 reseeded "
                f"{np.median(reference):.4f} / {max(reference):.4f}"
                if changes
                else "not run"
            ),
            (
                f"{np.mean(seconds['float32']) * 1000:.0f} / {np.mean(seconds['bfloat16']) * 1000:.0f}"
                if returns["float32"]
                else "not run"
            ),
            command,
        ]
        header = [
            "date",
            "machine",
            "model",
            "planner",
            "fp32 returns (per seed)",
            "bf16 returns (per seed)",
            "bf16 - fp32 (mean)",
            "executed-action change on fp32's states, median / max (plans)",
            "ms per step fp32 / bf16 (env included, not a speed measurement)",
            "command",
        ]
        intro = (
            "Held-out MPC episodes of trained agents planned in fp32 and in bf16 from the same resets and planner "
            "seeds (`benchmarks/speed/dtype_fidelity.py`), and the executed action's change when a plan of the fp32 "
            "episode is repeated in bf16 from the same inputs."
        )
        append_row("bf16 planning on trained agents", intro, header, row)


if __name__ == "__main__":
    main()
