"""
``make demo``: POPLIN-P learns Pendulum-v1 on a CPU, then plays it in both of the paper's control modes next to a
random policy.

    python -m sb3_poplin.demo [--variant poplin-p] [--env Pendulum-v1] [--steps 2000] [--eval-episodes 5]
                              [--params KEY:VALUE ...] [--threads 1] [--seed 0] [--out demo_output]

1. The agent's settings are the env's entry in the packaged ``poplin_cpu.yml`` (a planner and model sized for two
   CPU cores; :func:`sb3_poplin.experiments.presets.poplin_settings`), with ``--variant`` in place of the entry's ``policy``
   (``pets``, ``rs``, ``poplin-a``) and ``--params`` on top, as rl-zoo3's ``-params``.
2. Training: one episode of uniform random actions, then MPC (every action planned with the learned model), the
   model refit and the policy network distilled after every episode. After each episode the policy network alone
   (policy control) plays a few episodes as well, so the learning curve shows both modes.
3. The model is saved, loaded back, and plays ``--eval-episodes`` episodes with MPC control and with policy
   control; uniform random actions play the same start states.
4. ``--out`` receives the zip, ``learning_curve.png`` and ``summary.json``.

``--steps`` defaults to 2000 (one random episode and nine MPC episodes), where the CPU settings already swing the
pendulum up with MPC (docs/usage.md, "The demo"), so that the demo fits in minutes on two cores; the
entry's ``n_timesteps`` is the budget of the zoo runs, and ``--steps`` can be raised to it.
"""

from __future__ import annotations

import argparse
import json
import os
import time
from collections.abc import Callable, Sequence
from typing import Any, NamedTuple

import gymnasium as gym
import numpy as np
import torch as th
from stable_baselines3.common.callbacks import BaseCallback, CallbackList
from stable_baselines3.common.env_util import make_vec_env

from sb3_poplin.callbacks import ControlModesEvalCallback
from sb3_poplin.common import parse_params
from sb3_poplin.poplin import POPLIN
from sb3_poplin.experiments.presets import config_path, load_config, poplin_settings
from sb3_poplin.tasks import task_env_kwargs

DEFAULT_ENV = "Pendulum-v1"
DEFAULT_STEPS = 2000
# the planner and model sizes of an entry: what tests and benchmarks reuse with a variant of their own
SIZE_KEYS = ("horizon", "population_size", "num_elites", "cem_iterations", "ensemble_size", "dynamics_net_arch")
VARIANT_NAMES = {"pets": "PETS", "rs": "Random shooting", "poplin-a": "POPLIN-A", "poplin-p": "POPLIN-P"}
# what an agent acts with in evaluation: (observation, first step of the episode?) -> action in env units
Actor = Callable[[np.ndarray, bool], np.ndarray]


class DemoConfig(NamedTuple):
    """An agent's settings, from a ``poplin_cpu.yml`` entry."""

    variant: str  # POPLIN's policy argument
    kwargs: dict[str, Any]  # the other POPLIN keyword arguments (not env, seed, verbose)
    env_kwargs: dict[str, Any]  # the entry's env kwargs plus those its task's reward needs
    n_timesteps: int | None  # the entry's zoo budget


def cpu_config(env_id: str = DEFAULT_ENV, variant: str | None = None, overrides: dict[str, Any] | None = None) -> DemoConfig:
    """
    The settings of ``env_id``'s entry in the packaged ``poplin_cpu.yml``.

    :param env_id: gymnasium id with an entry in the file
    :param variant: ``"pets"``, ``"rs"``, ``"poplin-a"`` or ``"poplin-p"`` instead of the entry's ``policy``;
        ``None`` keeps the entry's
    :param overrides: settings replacing or adding to the entry's (POPLIN keyword arguments)
    :return: the variant, POPLIN keyword arguments and env kwargs
    """
    kwargs = poplin_settings(env_id, "cpu", **(overrides or {}))
    path = config_path("poplin", "cpu")
    assert path is not None
    entry = load_config(path)[env_id]
    chosen = variant if variant is not None else kwargs.get("policy", "poplin-p")
    kwargs.pop("policy", None)
    return DemoConfig(chosen, kwargs, task_env_kwargs(env_id, entry.get("env_kwargs")), entry.get("n_timesteps"))


# The planner and model sizes of the packaged Pendulum-v1 CPU entry (the numbers live in poplin_cpu.yml only).
CPU_SETTINGS: dict[str, Any] = {key: cpu_config().kwargs[key] for key in SIZE_KEYS}


class EpisodeRecorder(BaseCallback):
    """
    Records (env steps, return) of every finished training episode, and prints a line per episode.

    :param policy_eval: the callback that evaluates policy control at episode ends (run before this one); its
        result at the same step is printed on the episode's line
    :param verbose: 1 prints a line per episode
    """

    def __init__(self, policy_eval: ControlModesEvalCallback | None = None, verbose: int = 0) -> None:
        super().__init__(verbose)
        self.policy_eval = policy_eval
        self.steps: list[int] = []
        self.returns: list[float] = []

    def _on_step(self) -> bool:
        for info in self.locals.get("infos", []):
            if "episode" in info:
                learning_starts = getattr(self.model, "learning_starts", 0)
                warmup = all(end <= learning_starts for end in self.steps)  # no fit before this episode
                self.steps.append(self.num_timesteps)
                self.returns.append(float(info["episode"]["r"]))
                if self.verbose >= 1:
                    self._print_episode("random warm-up" if warmup else "MPC")
        return True

    def _print_episode(self, mode: str) -> None:
        line = f"  episode ending at step {self.steps[-1]:6d}: {mode:>14} {self.returns[-1]:9.1f}"
        evaluated = self.policy_eval
        if evaluated is not None and evaluated.timesteps[-1:] == [self.num_timesteps] and evaluated.results["policy"]:
            line += f", then policy control {np.mean(evaluated.results['policy'][-1]):9.1f}"
        print(line, flush=True)


def warmup_episodes(episode_ends: Sequence[int], learning_starts: int) -> int:
    """
    How many of the first training episodes acted at random: with the default ``learning_starts`` (one episode
    of random actions until the first fit), the episodes up to the first that ends after ``learning_starts`` steps.

    :param episode_ends: env steps at the end of each training episode
    :param learning_starts: the model's ``learning_starts``
    """
    for index, end in enumerate(episode_ends):
        if end > learning_starts:
            return index + 1
    return len(episode_ends)


def episode_returns(env: gym.Env, act: Actor, episodes: int, seed: int) -> list[float]:
    """
    Returns of ``episodes`` episodes, episode ``i`` from ``env.reset(seed=seed + i)`` (the same start states for
    every agent given the same seed).

    :param env: the env to play
    :param act: ``(observation, episode start) -> action`` in env units
    :param episodes: episodes to play
    :param seed: seed of the first episode's reset
    """
    returns = []
    for episode in range(episodes):
        obs, _ = env.reset(seed=seed + episode)
        total, done, start = 0.0, False, True
        while not done:
            obs, reward, terminated, truncated, _ = env.step(act(obs, start))
            total += float(reward)
            done, start = terminated or truncated, False
        returns.append(total)
    return returns


def random_policy_returns(env_id: str, episodes: int, seed: int, env_kwargs: dict[str, Any] | None = None) -> list[float]:
    """
    Returns of uniform random actions, for reference.

    :param env_id: gymnasium id
    :param episodes: episodes to play
    :param seed: seed of the resets (as :func:`episode_returns`) and of the action space's sampler
    :param env_kwargs: keyword arguments of ``gym.make``
    """
    env = gym.make(env_id, **(env_kwargs or {}))
    env.action_space.seed(seed)
    try:
        return episode_returns(env, lambda obs, start: env.action_space.sample(), episodes, seed)
    finally:
        env.close()


def agent_actor(model: POPLIN) -> Actor:
    """The agent as an :data:`Actor`; under MPC the planner's warm start is passed along and reset at episode starts."""
    state = None

    def act(obs: np.ndarray, start: bool) -> np.ndarray:
        nonlocal state
        actions, state = model.predict(obs[None], state=state, episode_start=np.array([start]), deterministic=True)
        return actions[0]

    return act


def plot_curve(
    path: str,
    title: str,
    training: EpisodeRecorder,
    warmup: int,
    policy_curve: tuple[list[int], list[list[float]]] | None,
    final: dict[str, list[float]],
) -> bool:
    """
    Write the learning curve: MPC training episodes, policy-control evaluations, the final evaluation of each mode
    and the random policy's mean return.

    :param path: the PNG to write
    :param title: the figure's title
    :param training: the training episodes
    :param warmup: the number of leading training episodes that acted at random
    :param policy_curve: (env steps, returns of each evaluation) of policy control during training, or None
    :param final: mode (``"mpc"``, ``"policy"``, ``"random"``) -> returns of the final evaluation
    :return: False when matplotlib is not installed
    """
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return False
    fig, ax = plt.subplots(figsize=(7, 4.5))
    steps, returns = training.steps, training.returns
    if warmup:
        ax.plot(steps[:warmup], returns[:warmup], "x", color="grey", label="random warm-up episode")
    ax.plot(steps[warmup:], returns[warmup:], "o-", color="C0", label="MPC control (training episodes)")
    if policy_curve is not None and policy_curve[0]:
        means = [float(np.mean(r)) for r in policy_curve[1]]
        ax.plot(policy_curve[0], means, "s--", color="C1", label="policy control (evaluated after each episode)")
    last = steps[-1] if steps else 0
    offset = 0.02 * max(last, 1)
    for i, (mode, color, name) in enumerate((("mpc", "C0", "MPC"), ("policy", "C1", "policy"))):
        if mode in final:
            mean, std = float(np.mean(final[mode])), float(np.std(final[mode]))
            ax.errorbar(
                [last + (i + 1) * offset], [mean], yerr=[std], fmt="D", color=color, capsize=4,
                label=f"final {name} control ({mean:.0f} ± {std:.0f})",
            )  # fmt: skip
    random = float(np.mean(final["random"]))
    ax.axhline(random, color="grey", linestyle=":", label=f"random policy ({random:.0f})")
    ax.set_xlabel("environment steps")
    ax.set_ylabel("episode return")
    ax.set_title(title)
    ax.legend(loc="best", fontsize="small")
    ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return True


def _summary_stats(returns: list[float]) -> dict[str, Any]:
    return {"returns": [float(r) for r in returns], "mean": float(np.mean(returns)), "std": float(np.std(returns))}


MODE_LABELS = {
    "mpc": "MPC control (plans every action with the learned model)",
    "policy": "policy control (the distilled policy network alone)",
    "random": "uniform random actions",
}


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--variant", choices=list(POPLIN.policy_aliases), default=None, help="default: the entry's")
    parser.add_argument("--env", default=DEFAULT_ENV, help="an env with an entry in poplin_cpu.yml")
    parser.add_argument("--steps", type=int, default=DEFAULT_STEPS, help="training env steps")
    parser.add_argument("--eval-episodes", type=int, default=5, help="final evaluation episodes per mode")
    parser.add_argument("--curve-episodes", type=int, default=3, help="policy-control episodes after each episode")
    parser.add_argument("--params", nargs="*", default=[], metavar="KEY:VALUE", help="settings over the entry's")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--threads", type=int, default=1, help="torch threads (1 is fastest on small CPUs)")
    parser.add_argument("--out", default="demo_output")
    return parser


def _evaluate_saved(path: str, env_id: str, env_kwargs: dict[str, Any], episodes: int, seed: int) -> dict[str, list[float]]:
    """The returns of the saved agent in each of its control modes, from the same start states."""
    loaded = POPLIN.load(path)
    env = gym.make(env_id, **env_kwargs)
    final: dict[str, list[float]] = {}
    for mode in ("mpc", "policy") if loaded.policy.actor is not None else ("mpc",):
        loaded.control = mode
        final[mode] = episode_returns(env, agent_actor(loaded), episodes, seed)
    env.close()
    return final


def main(argv: list[str] | None = None) -> dict[str, Any]:
    """
    Run the demo (see the module docstring).

    :param argv: command-line arguments; ``None`` reads ``sys.argv``
    :return: what ``summary.json`` holds
    """
    parser = _parser()
    args = parser.parse_args(argv)
    if args.steps < 1 or args.eval_episodes < 1 or args.curve_episodes < 1:
        parser.error("--steps, --eval-episodes and --curve-episodes must be >= 1")

    config = cpu_config(args.env, args.variant, parse_params(args.params))
    th.set_num_threads(args.threads)
    os.makedirs(args.out, exist_ok=True)
    name = VARIANT_NAMES.get(config.variant, config.variant)
    settings = ", ".join(f"{key}={value}" for key, value in config.kwargs.items())
    print(f"{name} on {args.env}, {args.steps} steps, settings from {config_path('poplin', 'cpu')}:", flush=True)
    print(f"  {settings}", flush=True)

    model = POPLIN(config.variant, make_vec_env(args.env, env_kwargs=config.env_kwargs), seed=args.seed, **config.kwargs)
    policy_eval = None
    if model.policy.actor is not None:  # policy control exists for POPLIN-A/P only
        policy_eval = ControlModesEvalCallback(
            make_vec_env(args.env, env_kwargs=config.env_kwargs, seed=args.seed + 2000),
            eval_freq=gym.spec(args.env).max_episode_steps or 1000,
            n_eval_episodes=args.curve_episodes,
            modes=("policy",),
        )
    recorder = EpisodeRecorder(policy_eval, verbose=1)
    # the policy is evaluated first, so that the recorder prints both returns on the episode's line
    callbacks: list[BaseCallback] = [recorder] if policy_eval is None else [policy_eval, recorder]
    start = time.time()
    model.learn(args.steps, callback=CallbackList(callbacks))
    train_time = time.time() - start
    warmup = warmup_episodes(recorder.steps, model.learning_starts)

    model_path = os.path.join(args.out, f"{config.variant}_{args.env.replace('/', '_')}.zip")
    model.save(model_path)
    start = time.time()
    final = _evaluate_saved(model_path, args.env, config.env_kwargs, args.eval_episodes, args.seed + 1000)
    eval_time = time.time() - start
    final["random"] = random_policy_returns(args.env, args.eval_episodes, args.seed + 1000, config.env_kwargs)

    plot_path = os.path.join(args.out, "learning_curve.png")
    curve = (policy_eval.timesteps, policy_eval.results["policy"]) if policy_eval else None
    plotted = plot_curve(plot_path, f"sb3_poplin: {name} on {args.env}", recorder, warmup, curve, final)
    summary = dict(
        variant=config.variant,
        env=args.env,
        steps=args.steps,
        seed=args.seed,
        config_file=str(config_path("poplin", "cpu")),
        settings={key: list(value) if isinstance(value, tuple) else value for key, value in config.kwargs.items()},
        training_episodes=dict(steps=recorder.steps, returns=recorder.returns, random_warmup=warmup),
        policy_control_curve=dict(steps=curve[0], returns=curve[1]) if curve else None,
        evaluation={mode: _summary_stats(returns) for mode, returns in final.items()},
        eval_episodes=args.eval_episodes,
        train_seconds=round(train_time, 1),
        eval_seconds=round(eval_time, 1),
        model=model_path,
    )
    summary_path = os.path.join(args.out, "summary.json")
    with open(summary_path, "w") as file:
        json.dump(summary, file, indent=2)

    print()
    print(
        f"{name} on {args.env} after {args.steps} steps ({train_time:.0f} s training, {eval_time:.0f} s "
        f"evaluation), {args.eval_episodes} episodes per agent from the same start states:"
    )
    for mode, returns in final.items():
        print(f"  {MODE_LABELS[mode]:<56} {np.mean(returns):8.1f} ± {np.std(returns):6.1f}")
    print(f"Wrote {model_path}, {summary_path}" + (f" and {plot_path}" if plotted else ""))
    return summary


if __name__ == "__main__":
    main()
