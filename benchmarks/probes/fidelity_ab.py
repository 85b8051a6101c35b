"""
The fidelity A/B (issue 19): sb3_poplin 0.2.0's distillation and model choices against the original code's, each
change alone and all together, per configuration and seed. Every finished run writes one small JSON file
(``benchmarks/fidelity_ab/<task>/<configuration>/<arm>/seed<k>.json``; the agent itself goes to
``benchmarks/fidelity_ab_models/``, not committed, for ``diagnose_mpc.py``), so an interrupted A/B resumes where it
stopped; ``--report`` turns the files into the table of ``benchmarks/RESULTS.md``.

Arms (POPLIN keyword arguments on top of the task's CPU settings from ``poplin_cpu.yml``):

- ``v0.2``: the 0.2.0 behaviour (whitening ``function_from_raw``, Avg ``add`` with step 0.1, executed-action
  targets from a 10 000-step window, standardised model targets; on PETSCheetah no PETS model hooks);
- ``v0.3``: the defaults of the 0.3.0 line when the A/B ran (whitening ``function``, Avg ``overwrite``, executed
  targets from the 10 000-step window, standardised model targets; PETS's hooks), spelled out;
- ``defaults``: the settings above at ``POPLIN``'s current default values (PETS's hooks): since round 5 of the A/B
  the same settings as ``original-without-whitening-plain`` for POPLIN-P and ``v0.3+raw-targets`` for the others;
- ``original``: the original code's (:func:`sb3_poplin.variants.original_code_settings`, PETS's hooks; POPLIN-A
  clones the executed actions, as the original's BC-AR/BC-AI);
- one change from ``v0.2`` each: ``whitening`` (``function``: the first update starts whitened), ``whitening-plain``,
  ``avg-overwrite``, ``avg-add-1`` (the paper's equation, step 1), ``planned-target``, ``latest-window`` (BC/GAN on
  the latest episode only), ``raw-targets`` (model targets not standardised), ``pets-hooks`` (PETSCheetah only);
- one change from ``v0.3`` each (the defaults plus one of the original's choices): ``v0.3+whitening-plain``,
  ``v0.3+avg-add-1``, ``v0.3+planned-target``, ``v0.3+latest-window``, ``v0.3+raw-targets``; and
  ``v0.3+planned-latest`` (both of the original's BC data choices: planned targets of the latest episode);
- leave one out (the original's settings with one of them back at its ``v0.3`` value):
  ``original-without-whitening-plain``, ``original-without-planned-target``, ``original-without-latest-window``,
  ``original-without-raw-targets``.

Protocol per run: ``learn(steps)`` from seed k; the training episodes' returns; then MPC and policy control
(POPLIN-A/P) on deterministic evaluation episodes of a fresh env seeded 1000 + k.

    python benchmarks/probes/fidelity_ab.py --task Pendulum-v1 --configs poplin-p/sep/avg poplin-p/sep/bc \\
        --arms v0.2 original --seeds 0 1 2 3 --jobs 2
    python benchmarks/probes/fidelity_ab.py --report --paired v0.3
"""

from __future__ import annotations

import argparse
import datetime
import json
import multiprocessing
import os
import sys
import time
from concurrent.futures import ProcessPoolExecutor, as_completed
from pathlib import Path
from typing import Any

import numpy as np

from sb3_poplin import POPLIN
from sb3_poplin.compat import SETTINGS_BEFORE_0_3
from sb3_poplin.variants import DEFAULT_SETTINGS, ORIGINAL_CODE_SETTINGS, configuration, original_code_settings

# benchmarks/, where results_file.py (shared by the scripts of every subfolder) lives
sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
from results_file import code_version, describe_machine

HERE = Path(__file__).resolve().parent
# the run records stay in benchmarks/fidelity_ab/ (committed), beside the other result folders, not in probes/
OUTPUT = HERE.parent / "fidelity_ab"
# the trained agents (no replay buffer), for the MPC diagnosis (diagnose_mpc.py); not committed
MODELS = HERE.parent / "fidelity_ab_models"
STEPS = {"Pendulum-v1": 3000, "sb3_poplin/PETSCheetah-v0": 10_000}
# the PETSCheetah task as 0.2.0 modelled it (raw observations in, deltas out): the same env under another id
RAW_CHEETAH = "sb3_poplin_ab/PETSCheetahRawModel-v0"

# 0.2.0's behaviour: the settings added since with their earlier behaviour, and 0.2.0's Avg step and window
FAILED_BELOW = -1000.0
V0_2: dict[str, Any] = {**SETTINGS_BEFORE_0_3, "avg_step_size": 0.1, "distill_window": 10_000}
ORIGINAL: dict[str, Any] = dict(ORIGINAL_CODE_SETTINGS)
# the defaults of the 0.3.0 development line as the ``v0.3`` runs used them, spelled out so that the arm keeps its
# meaning when a default changes; ``defaults`` is whatever POPLIN's signature says now
V0_3: dict[str, Any] = dict(
    whitening="function",
    avg_update="overwrite",
    distill_target="executed",
    standardise_targets=True,
    avg_step_size=0.1,
    distill_window=10_000,
)
DEFAULTS: dict[str, Any] = {key: DEFAULT_SETTINGS[key] for key in V0_2}
ARMS: dict[str, dict[str, Any]] = {
    "v0.2": {},
    "v0.3": V0_3,
    "defaults": DEFAULTS,
    "original": ORIGINAL,
    "whitening": dict(whitening="function"),
    "whitening-plain": dict(whitening="plain"),
    "avg-overwrite": dict(avg_update="overwrite"),
    "avg-add-1": dict(avg_step_size=1.0),
    "planned-target": dict(distill_target="planned"),
    "latest-window": dict(distill_window=None),
    "raw-targets": dict(standardise_targets=False),
    "pets-hooks": {},
}
# one change from the defaults each: ``v0.3+planned-target`` ... (the same changes as the single arms above)
SINGLE_CHANGES = ("whitening-plain", "avg-add-1", "planned-target", "latest-window", "raw-targets")
ARMS.update({f"v0.3+{name}": {**V0_3, **ARMS[name]} for name in SINGLE_CHANGES})
# the original's BC data together (its planned targets of the latest episode), with the defaults' whitening and model
ARMS["v0.3+planned-latest"] = {**V0_3, **ARMS["planned-target"], **ARMS["latest-window"]}
# leave one out: the original's settings with one of them back at its ``v0.3`` value (``original-without-raw-targets``
# standardises the model targets, and so on); the settings depend on the variant, as ``original``'s do
LEFT_OUT = ("whitening-plain", "planned-target", "latest-window", "raw-targets")
ARMS.update({f"original-without-{name}": {} for name in LEFT_OUT})


def arm_settings(arm: str, policy: str) -> dict[str, Any]:
    """
    :param arm: an arm of :data:`ARMS`
    :param policy: the variant the arm runs (``original`` and the leave-one-out arms depend on it)
    :return: the POPLIN keyword arguments the arm sets on top of ``V0_2``
    """
    if arm == "original":
        return original_code_settings(policy)
    if arm.startswith("original-without-"):
        name = arm.removeprefix("original-without-")
        return {**original_code_settings(policy), **{key: V0_3[key] for key in ARMS[name]}}
    return dict(ARMS[arm])


def uses_pets_hooks(task: str, arm: str) -> bool:
    """PETSCheetah runs with PETS's model hooks in the arms that say so (the others model it as 0.2.0 did)."""
    return arm in ("v0.3", "defaults", "original", "pets-hooks") or arm.startswith(("v0.3+", "original-without-"))


def register_raw_cheetah() -> None:
    """Register ``RAW_CHEETAH``: the PETSCheetah env and reward without PETS's model hooks (0.2.0's model)."""
    import gymnasium as gym

    from sb3_poplin.tasks import TaskSpec, has_task, make_task, register_task

    if has_task(RAW_CHEETAH):
        return
    spec = gym.spec("sb3_poplin/PETSCheetah-v0")
    gym.register(RAW_CHEETAH, entry_point=spec.entry_point, max_episode_steps=spec.max_episode_steps)
    task = make_task("sb3_poplin/PETSCheetah-v0")
    register_task(TaskSpec(env_id=RAW_CHEETAH, reward_fn=task.reward_fn, description="PETSCheetah without model hooks"))


def run_path(task: str, config: str, arm: str, seed: int) -> Path:
    return OUTPUT / task.replace("/", "_") / config.replace("/", "_") / arm / f"seed{seed}.json"


def model_path(task: str, config: str, arm: str, seed: int) -> Path:
    return MODELS / run_path(task, config, arm, seed).relative_to(OUTPUT).with_suffix(".zip")


def run_one(
    task: str,
    config: str,
    arm: str,
    seed: int,
    steps: int,
    eval_mpc: int,
    eval_policy: int,
    commit: str,
    forward_path: str = "fused",
) -> dict[str, Any]:
    """
    Train and evaluate one (task, configuration, arm, seed); :return: the record written to its JSON file.

    :param commit: the code the run executes: the version when the invocation started (its workers import the
        package once, so commits made while it runs do not change it)
    :param forward_path: the ensemble's forward path for the run (``SB3_POPLIN_FORWARD_PATH``); ``"fused"`` (the
        fused oneDNN forward at every size, as before the paths were chosen per host) replays the earlier rounds'
        numbers on the same host
    """
    import torch as th
    from stable_baselines3.common.evaluation import evaluate_policy
    from stable_baselines3.common.monitor import Monitor
    from stable_baselines3.common.vec_env import DummyVecEnv

    from sb3_poplin import kernels
    from sb3_poplin.experiments.presets import poplin_settings
    from sb3_poplin.tasks import make_env

    th.set_num_threads(1)
    os.environ[kernels.PATH_ENV] = forward_path
    env_name = task
    if task == "sb3_poplin/PETSCheetah-v0" and not uses_pets_hooks(task, arm):
        register_raw_cheetah()
        env_name = RAW_CHEETAH
    cpu = {k: v for k, v in poplin_settings(task).items() if k not in ("policy", "noise", "n_timesteps")}
    settings = {**cpu, **configuration(config), **V0_2, **arm_settings(arm, configuration(config)["policy"])}
    model = POPLIN(env=make_env(env_name), seed=seed, **settings)
    start = time.time()
    model.learn(steps)
    train_time = time.time() - start
    train_returns = [float(info["r"]) for info in model.ep_info_buffer or []]

    def evaluate(control: str, episodes: int) -> list[float]:
        model.control = control
        env = DummyVecEnv([lambda: Monitor(make_env(env_name))])
        env.seed(1000 + seed)
        returns, _ = evaluate_policy(model, env, n_eval_episodes=episodes, deterministic=True, return_episode_rewards=True)
        assert isinstance(returns, list)
        return [float(r) for r in returns]

    start = time.time()
    mpc = evaluate("mpc", eval_mpc)
    policy = evaluate("policy", eval_policy) if model.policy.actor is not None else None
    record = dict(
        task=task,
        configuration=config,
        arm=arm,
        seed=seed,
        steps=steps,
        settings={k: (list(v) if isinstance(v, tuple) else v) for k, v in settings.items()},
        pets_hooks=env_name == task and task == "sb3_poplin/PETSCheetah-v0",
        train_returns=train_returns,
        mpc_returns=mpc,
        policy_returns=policy,
        train_time_s=round(train_time, 1),
        eval_time_s=round(time.time() - start, 1),
        date=str(datetime.date.today()),
        commit=commit,
        machine=describe_machine(1),
        forward_path=forward_path,
    )
    saved = model_path(task, config, arm, seed)
    saved.parent.mkdir(parents=True, exist_ok=True)
    model.save(saved)
    path = run_path(task, config, arm, seed)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(record, indent=1))
    return record


def load_runs() -> list[dict[str, Any]]:
    return [json.loads(p.read_text()) for p in sorted(OUTPUT.rglob("seed*.json"))]


def _cell(values: list[float]) -> str:
    return f"{np.mean(values):.0f} ± {np.std(values):.0f}" if values else "n/a"


def report() -> str:
    """The A/B table: per task, configuration and arm, the mean ± std over seeds of each seed's mean return."""
    rows: dict[tuple[str, str, str], list[dict[str, Any]]] = {}
    for r in load_runs():
        rows.setdefault((r["task"], r["configuration"], r["arm"]), []).append(r)
    lines = [
        "| task | configuration | arm | seeds | MPC return | policy return | last-3-episodes training return | "
        "failed training episodes | per seed: MPC / policy |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    arm_order = list(ARMS)
    for (task, config, arm), runs in sorted(rows.items(), key=lambda kv: (kv[0][0], kv[0][1], arm_order.index(kv[0][2]))):
        runs.sort(key=lambda r: r["seed"])
        mpc = [float(np.mean(r["mpc_returns"])) for r in runs]
        policy = [float(np.mean(r["policy_returns"])) for r in runs if r["policy_returns"] is not None]
        train = [float(np.mean(r["train_returns"][-3:])) for r in runs if r["train_returns"]]
        # Pendulum: training episodes of the last 7 below -1000 (a swing-up that failed), over all seeds
        failed = sum(sum(ret < FAILED_BELOW for ret in r["train_returns"][-7:]) for r in runs)
        failed_cell = f"{failed} / {sum(len(r['train_returns'][-7:]) for r in runs)}" if task == "Pendulum-v1" else "n/a"
        per_seed = ", ".join(
            f"s{r['seed']}: {np.mean(r['mpc_returns']):.0f} / "
            + ("n/a" if r["policy_returns"] is None else f"{np.mean(r['policy_returns']):.0f}")
            for r in runs
        )
        lines.append(
            f"| {task} | {config} | {arm} | {len(runs)} | {_cell(mpc)} | {_cell(policy)} | {_cell(train)} | {failed_cell} "
            f"| {per_seed} |"
        )
    return "\n".join(lines)


def _seed_means(runs: list[dict[str, Any]], key: str) -> dict[int, float]:
    return {r["seed"]: float(np.mean(r[key])) for r in runs if r[key] is not None}


def paired(reference: str) -> str:
    """
    Each arm against ``reference`` on the seeds both ran (the same seed is the same start states and first data):
    on how many seeds the arm's MPC and policy returns were higher, and the mean paired difference.

    :param reference: the arm every other arm of a (task, configuration) is compared with
    """
    cells: dict[tuple[str, str], dict[str, list[dict[str, Any]]]] = {}
    for r in load_runs():
        cells.setdefault((r["task"], r["configuration"]), {}).setdefault(r["arm"], []).append(r)
    lines = [
        "| task | configuration | arm | against | seeds | MPC higher on | MPC difference | policy higher on | "
        "policy difference |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    arm_order = list(ARMS)
    for (task, config), arms in sorted(cells.items()):
        if reference not in arms:
            continue
        for arm in sorted(arms, key=arm_order.index):
            if arm == reference:
                continue
            row = [f"| {task} | {config} | {arm} | {reference} "]
            seeds: set[int] = set()
            for key in ("mpc_returns", "policy_returns"):
                ours, theirs = _seed_means(arms[arm], key), _seed_means(arms[reference], key)
                shared = sorted(set(ours) & set(theirs))
                seeds |= set(shared)
                diffs = [ours[k] - theirs[k] for k in shared]
                higher = f"{sum(d > 0 for d in diffs)} / {len(diffs)}" if diffs else "n/a"
                row.append(f"| {higher} | {round(float(np.mean(diffs))):+d} " if diffs else "| n/a | n/a ")
            lines.append(row[0] + f"| {len(seeds)} " + "".join(row[1:]) + "|")
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--task", default="Pendulum-v1", choices=list(STEPS))
    parser.add_argument("--configs", nargs="+", default=["poplin-p/sep/avg", "poplin-p/sep/bc"])
    parser.add_argument("--arms", nargs="+", default=["v0.2", "original"], choices=list(ARMS))
    parser.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2, 3])
    parser.add_argument("--steps", type=int, default=None, help="env steps per run (Pendulum 3000, PETSCheetah 10000)")
    parser.add_argument("--eval-mpc", type=int, default=2, help="MPC evaluation episodes per run")
    parser.add_argument("--eval-policy", type=int, default=10, help="policy-control evaluation episodes per run")
    parser.add_argument("--jobs", type=int, default=2, help="runs in parallel (one thread each)")
    parser.add_argument(
        "--forward-path",
        choices=["fused", "batched", "members"],
        default="fused",
        help="the ensemble's forward path for the runs: fused (default) replays the earlier rounds' numerics on the same "
        "host; the others are the same function up to float rounding",
    )
    parser.add_argument("--report", action="store_true", help="print the table of the finished runs and exit")
    parser.add_argument("--paired", metavar="ARM", default=None, help="with --report: also each arm against ARM, seed by seed")
    args = parser.parse_args()
    if args.report:
        print(report())
        if args.paired:
            print()
            print(paired(args.paired))
        return
    steps = args.steps or STEPS[args.task]
    # seeds outermost: the first seeds of every arm finish first
    todo = [
        (args.task, config, arm, seed)
        for seed in args.seeds
        for config in args.configs
        for arm in args.arms
        if not run_path(args.task, config, arm, seed).exists()
    ]
    print(f"{len(todo)} runs to do", flush=True)
    commit = code_version()
    with ProcessPoolExecutor(max_workers=args.jobs, mp_context=multiprocessing.get_context("spawn")) as pool:
        futures = {
            pool.submit(run_one, *job, steps, args.eval_mpc, args.eval_policy, commit, args.forward_path): job for job in todo
        }
        for future in as_completed(futures):
            r = future.result()
            policy = "n/a" if r["policy_returns"] is None else f"{np.mean(r['policy_returns']):.1f}"
            print(
                f"{futures[future]}: MPC {np.mean(r['mpc_returns']):.1f}, policy {policy}, "
                f"train {r['train_time_s']} s, eval {r['eval_time_s']} s",
                flush=True,
            )


if __name__ == "__main__":
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    main()
