"""
Planning quality against the population size on a fixed model (Wang & Ba 2019, section 5.3): for every method and
population, the model-predicted return of the plans (the final elites' mean) and the real return of short MPC
episodes. The paper reports that POPLIN-P improves with a larger population and PETS does not.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import gymnasium as gym
import numpy as np

from sb3_poplin.analysis.model_error import mpc_episode
from sb3_poplin.variants import replanner


def population_sweep(
    agent: Any,
    env: gym.Env,
    methods: Sequence[str],
    populations: Sequence[int],
    episodes: int = 1,
    steps: int = 100,
    seed: int = 0,
    elite_fraction: float | None = None,
) -> list[dict[str, Any]]:
    """
    :param agent: a trained POPLIN agent (its model, task and policy network are used)
    :param env: the env to run the episodes in
    :param methods: variants to plan as (``"pets"``, ``"poplin-a"``, ``"poplin-p"``, ``"rs"``)
    :param populations: population sizes
    :param episodes: episodes per method and population (start states ``seed, seed + 1, ...``, the same for all)
    :param steps: steps per episode
    :param seed: seed of the episodes and the planners' generators
    :param elite_fraction: elites as a fraction of the population; ``None``: the agent's fraction
    :return: one row per method and population: real and planned returns (mean over episodes, and per episode)
    """
    fraction = agent.settings.num_elites / agent.settings.population_size if elite_fraction is None else elite_fraction
    rows = []
    for method in methods:
        for population in populations:
            elites = max(1, min(population, round(population * fraction)))
            controller = replanner(agent, method, seed=seed, population_size=population, num_elites=elites)
            episodes_run = [mpc_episode(controller, env, steps, seed + k) for k in range(episodes)]
            real = [episode.total for episode in episodes_run]
            planned = [float(episode.planned_returns.mean()) for episode in episodes_run]
            rows.append(
                dict(
                    method=method,
                    population=population,
                    elites=elites,
                    real_return=float(np.mean(real)),
                    planned_return=float(np.mean(planned)),
                    real_returns=real,
                    planned_returns=planned,
                )
            )
    return rows


def plot_population_sweep(rows: list[dict[str, Any]], path: str, title: str = "") -> None:
    """Real and planned return against population size, one line per method."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(10, 4))
    for method in dict.fromkeys(row["method"] for row in rows):
        mine = [row for row in rows if row["method"] == method]
        pops = [row["population"] for row in mine]
        for ax, key in zip(axes, ("real_return", "planned_return"), strict=True):
            ax.plot(pops, [row[key] for row in mine], marker="o", label=method)
    for ax, label in zip(axes, ("real return (MPC episodes)", "planned return (model)"), strict=True):
        ax.set_xscale("log")
        ax.set_xlabel("population size")
        ax.set_ylabel(label)
        ax.legend()
    fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
