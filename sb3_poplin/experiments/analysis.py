"""
``python -m sb3_poplin.analysis COMMAND``: the paper's analyses on a saved agent or an rl-zoo3 log folder.

    python -m sb3_poplin.analysis surface --model agent.zip --env HalfCheetah-v5 --output out/
    python -m sb3_poplin.analysis popsize --model agent.zip --env HalfCheetah-v5 --populations 100 200 500 --output out/
    python -m sb3_poplin.analysis control --log-folder logs --env Pendulum-v1 --output out/
    python -m sb3_poplin.analysis model-error --model agent.zip --env HalfCheetah-v5
    python -m sb3_poplin.analysis record --env HalfCheetah-v5 --variant pets --steps 15000 --output datasets/
    python -m sb3_poplin.analysis model-quality --data datasets/X.npz --train-episodes 8 --hooks raw sincos

Each command prints a table and writes it (``.md`` and ``.json``) with its figures into ``--output``.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from collections.abc import Sequence
from typing import Any

import numpy as np
import torch as th

from sb3_poplin.analysis.control import control_curves, plot_control_curves
from sb3_poplin.analysis.model_error import mpc_episode, model_error
from sb3_poplin.analysis.model_quality import TransitionDataset, dataset_from_replay, model_quality, record
from sb3_poplin.analysis.popsize import plot_population_sweep, population_sweep
from sb3_poplin.analysis.surface import plot_surface, reward_surface
from sb3_poplin.common import parse_params
from sb3_poplin.poplin import POPLIN
from sb3_poplin.experiments.presets import poplin_settings
from sb3_poplin.tasks import ModelHooks, make_env
from sb3_poplin.variants import replanner


def markdown_table(header: Sequence[str], rows: Sequence[Sequence[Any]]) -> str:
    """A markdown table (floats with 4 significant digits)."""

    def cell(value: Any) -> str:
        return f"{value:.4g}" if isinstance(value, float) else str(value)

    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(cell(v) for v in row) + " |" for row in rows]
    return "\n".join(lines)


def write_report(output: str, name: str, table: str, data: Any, command: str) -> None:
    """Print the table and write ``<name>.md`` (the command and the table) and ``<name>.json`` into ``output``."""
    print(table)
    with open(os.path.join(output, f"{name}.md"), "w") as file:
        file.write(f"`{command}`\n\n{table}\n")
    with open(os.path.join(output, f"{name}.json"), "w") as file:
        json.dump(data, file, indent=2)


def load_agent(path: str, env_id: str) -> POPLIN:
    """A saved agent on the CPU, its env made with the task's env kwargs."""
    return POPLIN.load(path, env=make_env(env_id), device="cpu")


def real_state(agent: POPLIN, env_id: str, steps: int, seed: int) -> th.Tensor:
    """The observation after ``steps`` MPC steps of the saved agent from ``reset(seed=seed)`` (0: the start state)."""
    env = make_env(env_id)
    if steps == 0:
        return th.as_tensor(env.reset(seed=seed)[0], dtype=th.float32)
    return th.as_tensor(mpc_episode(agent.mpc, env, steps, seed).obs[-1], dtype=th.float32)


def methods_of(agent: POPLIN) -> list[str]:
    """PETS's action search, and POPLIN-A's and POPLIN-P's where the agent has a policy network."""
    return ["pets", "poplin-a", "poplin-p"] if agent.policy.actor is not None else ["pets"]


def surface_command(args: argparse.Namespace, command: str) -> None:
    agent = load_agent(args.model, args.env)
    obs = real_state(agent, args.env, args.state_from_episode, args.seed)
    rows, data = [], {}
    for method in args.methods or methods_of(agent):
        surface = reward_surface(replanner(agent, method, seed=args.seed), method, obs, grid=args.grid)
        plot_surface(surface, os.path.join(args.output, f"surface_{method}.png"))
        stats = surface.stats
        keys = ("roughness", "local_maxima", "explained_variance_1", "explained_variance_2", "planned_return")
        rows.append([method, *(stats[key] for key in keys)])
        data[method] = {**stats, "x": surface.x.tolist(), "y": surface.y.tolist(), "returns": surface.returns.tolist()}
    header = ["method", "roughness", "local maxima", "PC1 variance", "PC2 variance", "planned return"]
    write_report(args.output, "surface", markdown_table(header, rows), data, command)


def popsize_command(args: argparse.Namespace, command: str) -> None:
    agent = load_agent(args.model, args.env)
    methods = args.methods or methods_of(agent)
    rows = population_sweep(agent, make_env(args.env), methods, args.populations, args.episodes, args.steps, args.seed)
    plot_population_sweep(rows, os.path.join(args.output, "popsize.png"), title=args.env)
    table = markdown_table(
        ["method", "population", "elites", "real return", "planned return"],
        [[r["method"], r["population"], r["elites"], r["real_return"], r["planned_return"]] for r in rows],
    )
    write_report(args.output, "popsize", table, rows, command)


def control_command(args: argparse.Namespace, command: str) -> None:
    curves = control_curves(args.log_folder, args.env)
    plot_control_curves(curves, os.path.join(args.output, "control.png"), title=args.env)
    rows = [[mode, len(c.runs), int(c.timesteps[-1]), float(c.mean[-1]), float(c.std[-1])] for mode, c in curves.items()]
    data = {m: {"runs": c.runs, "timesteps": c.timesteps.tolist(), "returns": c.returns.tolist()} for m, c in curves.items()}
    table = markdown_table(["mode", "runs", "last step", "mean", "std"], rows)
    write_report(args.output, "control", table, data, command)


def model_error_command(args: argparse.Namespace, command: str) -> None:
    agent = load_agent(args.model, args.env)
    episode = mpc_episode(agent.mpc, make_env(args.env), args.steps, args.seed)
    errors = model_error(agent, episode, args.stride)
    rows = [[k + 1, *(errors[key][k] for key in errors)] for k in range(len(errors["state_rmse"]))]
    table = markdown_table(["k", "state RMSE (std units)", "k-step return abs error", "real k-step return abs"], rows)
    table += f"\n\nMPC episode: return {episode.total:.1f} over {len(episode.actions)} steps"
    write_report(args.output, "model_error", table, {"episode_return": episode.total, **errors}, command)


def dataset_name(env_id: str, variant: str, steps: int, seed: int) -> str:
    """The file name ``record`` gives a dataset: ``<env>-<variant>-<steps>-seed<seed>.npz`` (``/`` in an id as ``-``)."""
    return f"{env_id.replace('/', '-')}-{variant}-{steps}-seed{seed}.npz"


def record_command(args: argparse.Namespace, command: str) -> None:
    if args.from_checkpoint:
        data = checkpoint_dataset(args.from_checkpoint, args.env, dict(variant=args.variant, seed=args.seed))
        name = dataset_name(args.env, args.variant, len(data.obs), args.seed)
    elif args.steps is None:
        raise SystemExit("record needs --steps (the env steps to train) or --from-checkpoint (a run's checkpoint)")
    else:
        data = record(args.env, args.variant, args.steps, args.seed, args.budget, **parse_params(args.params))
        name = dataset_name(args.env, args.variant, args.steps, args.seed)
    data.meta["command"] = command
    path = os.path.join(args.output, name)
    data.save(path)
    returns = [float(data.rewards[a:b].sum()) for a, b in data.episode_bounds()]
    print(f"{path}: {len(data.obs)} transitions, {data.num_episodes} episodes (returns {np.round(returns, 1).tolist()})")


def checkpoint_dataset(path: str, env_id: str, meta: dict[str, Any]) -> TransitionDataset:
    """The dataset of a training run's checkpoint (:mod:`.checkpoints`: its folder or its ``replay_buffer.npz``)."""
    if os.path.isdir(path):
        path = os.path.join(path, "replay_buffer.npz")
    space = make_env(env_id).action_space
    low, high = space.low.astype(np.float64), space.high.astype(np.float64)  # type: ignore[attr-defined]
    with np.load(path) as arrays:
        return dataset_from_replay(
            dict(arrays), lambda scaled: low + 0.5 * (scaled + 1.0) * (high - low), env_id, {**meta, "checkpoint": path}
        )


def hook_candidates(env_id: str, names: Sequence[str]) -> dict[str, ModelHooks | None]:
    """The model hooks of ``--hooks``: ``task`` (the registered spec's) or a name of ``HOOK_CANDIDATES``."""
    from sb3_poplin.tasks.mujoco import HOOK_CANDIDATES

    known = HOOK_CANDIDATES.get(env_id, {})
    chosen: dict[str, ModelHooks | None] = {}
    for name in names:
        if name == "task":
            chosen[name] = None
        elif name in known:
            chosen[name] = known[name].hooks()
        else:
            raise SystemExit(f"--hooks {name!r}: {env_id} has the candidates {['task', *known]}.")
    return chosen


def model_quality_command(args: argparse.Namespace, command: str) -> None:
    data = TransitionDataset.load(args.data)
    if args.steps is not None:
        data = data.first_steps(args.steps)
    settings = poplin_settings(data.env_id, args.budget, **parse_params(args.params))
    train = args.train_episodes or data.num_episodes - (args.heldout_episodes or 2)
    rows, results = [], []
    for name, hooks in hook_candidates(data.env_id, args.hooks).items():
        for seed in args.seeds:
            report = model_quality(data, train, args.heldout_episodes, settings, hooks, seed, stride=args.stride)
            results.append(dict(hooks=name, seed=seed, **report))
            rows.append(
                [
                    name,
                    seed,
                    *(report["state_error"][k] for k in (1, 5, 15, 30)),
                    *(v for h in (15, 30) for v in (report["return_error"][h], report["return_correlation"][h])),
                    report["nll"],
                    report["mse"],
                    report["fit_seconds"],
                ]
            )
    header = ["hooks", "seed", "k=1", "k=5", "k=15", "k=30", "ret15 err", "ret15 corr", "ret30 err", "ret30 corr"]
    header += ["NLL", "MSE", "fit s"]
    table = markdown_table(header, rows)
    heldout = data.num_episodes - train if args.heldout_episodes is None else args.heldout_episodes
    table += (
        f"\n\n{data.env_id}, {args.data}{f' (first {args.steps} steps)' if args.steps else ''}: fitted on episodes "
        f"0-{train - 1} (a refit after each), measured on the next {heldout}; "
        "state error in std units of each entry over the held-out states; NLL and MSE per target entry, target units"
    )
    stem = os.path.splitext(os.path.basename(args.data))[0]
    write_report(args.output, f"model_quality_{stem}", table, results, command)


def parser() -> argparse.ArgumentParser:
    top = argparse.ArgumentParser(
        prog="python -m sb3_poplin.analysis", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    top.add_argument("--threads", type=int, default=1, help="torch threads")
    sub = top.add_subparsers(dest="command", required=True)

    def common(name: str, help_text: str, model: bool = True) -> argparse.ArgumentParser:
        p = sub.add_parser(name, help=help_text)
        if model:
            p.add_argument("--model", required=True, help="a saved POPLIN zip")
        p.add_argument("--env", required=True, help="the gymnasium id the agent was trained on")
        p.add_argument("--output", default=".", help="folder for the table and the figures")
        p.add_argument("--seed", type=int, default=0)
        return p

    p = common("surface", "reward surface in the PCA plane of the candidates, per search space")
    p.add_argument("--state-from-episode", type=int, default=0, help="MPC steps before the analysed state")
    p.add_argument("--grid", type=int, default=25, help="grid points per PCA axis")
    p.add_argument("--methods", nargs="+", choices=["pets", "rs", "poplin-a", "poplin-p"], help="default: all the agent can")
    p = common("popsize", "planned and real return against the population size")
    p.add_argument("--populations", type=int, nargs="+", default=[100, 200, 500, 1000, 2000])
    p.add_argument("--methods", nargs="+", choices=["pets", "rs", "poplin-a", "poplin-p"], help="default: all the agent can")
    p.add_argument("--episodes", type=int, default=1)
    p.add_argument("--steps", type=int, default=100, help="steps per episode")
    p = common("control", "MPC and policy-control curves of rl-zoo3 runs", model=False)
    p.add_argument("--log-folder", required=True, help="the zoo's -f folder")
    p = common("model-error", "open-loop k-step model error on an MPC episode")
    p.add_argument("--steps", type=int, default=1000, help="length of the MPC episode")
    p.add_argument("--stride", type=int, default=5, help="start a prediction every n-th state")
    p = common("record", "train with a packaged preset and write its transitions (a dataset for model-quality)", model=False)
    p.add_argument("--variant", default="pets", choices=["pets", "poplin-p", "poplin-a", "rs"])
    p.add_argument("--steps", type=int, default=None, help="env steps to train (and record)")
    p.add_argument(
        "--from-checkpoint",
        default=None,
        help="no training: the transitions of a run's checkpoint (its folder or replay_buffer.npz; --variant and --seed "
        "only name the file)",
    )
    p.add_argument("--budget", default="cpu", choices=["cpu", "paper"], help="the preset: poplin_cpu.yml or poplin.yml")
    p.add_argument("--params", nargs="*", default=[], help="settings replacing the preset's, KEY:VALUE (as rl-zoo3's -params)")
    p = sub.add_parser("model-quality", help="fit model configurations on a dataset's episodes, measure them on later ones")
    p.add_argument("--data", required=True, help="a dataset written by record")
    p.add_argument("--steps", type=int, default=None, help="use the dataset's first steps (whole episodes), e.g. 5000")
    p.add_argument("--train-episodes", type=int, default=None, help="default: all but --heldout-episodes (2)")
    p.add_argument("--heldout-episodes", type=int, default=None, help="default: every episode after the training ones")
    p.add_argument("--hooks", nargs="+", default=["task"], help="task (the registered spec's) or a HOOK_CANDIDATES name")
    p.add_argument("--budget", default="cpu", choices=["cpu", "paper"], help="the preset whose model settings are used")
    p.add_argument("--params", nargs="*", default=[], help="model settings replacing the preset's, KEY:VALUE")
    p.add_argument("--seeds", type=int, nargs="+", default=[0], help="model seeds (one fit each)")
    p.add_argument("--stride", type=int, default=5, help="start a prediction every n-th held-out state")
    p.add_argument("--output", default=".", help="folder for the table")
    return top


COMMANDS = {
    "surface": surface_command,
    "popsize": popsize_command,
    "control": control_command,
    "model-error": model_error_command,
    "record": record_command,
    "model-quality": model_quality_command,
}


def main(argv: Sequence[str] | None = None) -> None:
    args = parser().parse_args(argv)
    th.set_num_threads(args.threads)
    os.makedirs(args.output, exist_ok=True)
    np.set_printoptions(precision=4)
    command = "python -m sb3_poplin.analysis " + " ".join(sys.argv[1:] if argv is None else argv)
    COMMANDS[args.command](args, command)


if __name__ == "__main__":
    main()
