"""
Our PETS planner beside mbrl-lib 0.2.0's, in one process, at the paper setting: HalfCheetah-v5 sizes (18-dim
observation with x kept, as our task makes it; 6-dim action), population 500, horizon 30, 5 CEM iterations, 50 elites
(mbrl-lib: ``elite_ratio`` 0.1, ``alpha`` 0.1), a 5-member ensemble of 4 x 200 SiLU layers, one thread. Two
propagations: expectation (PE-E: mbrl-lib's ``propagation_method="expectation"``, one particle) and TS1 with 20
particles (``"random_model"``; ours ``ts1``). The reward is the same cheap function on both sides (forward velocity
minus 0.1 |a|^2), no termination, untrained models (a plan costs the same).

The plans alternate, one of each library per round, and the reported ratio is the median of the rounds' ratios, so the
drift of a shared machine affects both sides alike; the fp32 matmul peak is measured in the same process. Appends one
row per propagation to benchmarks/RESULTS.md.

mbrl-lib 0.2.0 pins old dependencies: run this in the virtualenv of ``benchmarks/diagnosis/mbrl_model_quality.py``
(its docstring has the set-up; the package installed there with ``pip install -e .``, so both libraries load here)::

    /work/mbrl-venv/bin/python benchmarks/speed/mbrl_plan_speed.py [--rounds 7] [--threads 1]
"""

from __future__ import annotations

import argparse
import datetime
import os
import statistics
import sys
import time
import warnings
from typing import Any

import gymnasium as gym
import numpy as np
import omegaconf
import torch as th

import mbrl.models
import mbrl.planning
import mbrl.types
from sb3_poplin import POPLIN
from sb3_poplin.planning import plan_flops

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))  # speed/: planning_speed
# benchmarks/, where results_file.py (shared by the scripts of every subfolder) lives
sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from planning_speed import matmul_peak
from results_file import append_row, describe_machine

# HalfCheetah-v5 as our task makes it: x kept (18 entries; our model's input 18 features + 6 actions, mbrl-lib's the 18 + 6)
OBS, ACT, HIDDEN, LAYERS, MEMBERS = 18, 6, 200, 4, 5
PAPER = dict(horizon=30, population_size=500, num_elites=50, cem_iterations=5)
# ours -> (mbrl-lib's propagation method, particles)
PROPAGATIONS = {"expectation": ("expectation", 1), "ts1": ("random_model", 20)}


class Spaces(gym.Env):
    """HalfCheetah-v5's spaces, for mbrl-lib's ``ModelEnv`` (it never steps this env)."""

    observation_space = gym.spaces.Box(-np.inf, np.inf, (OBS,), np.float32)
    action_space = gym.spaces.Box(-1.0, 1.0, (ACT,), np.float32)


def velocity_reward(act: th.Tensor, next_obs: th.Tensor) -> th.Tensor:
    """mbrl-lib's signature: forward velocity (entry 9 with x kept) minus 0.1 |a|^2, ``[B, 1]``."""
    return (next_obs[:, 9] - 0.1 * act.square().sum(dim=1)).view(-1, 1)


def no_termination(act: th.Tensor, next_obs: th.Tensor) -> th.Tensor:
    return th.zeros(next_obs.shape[0], 1, dtype=th.bool, device=next_obs.device)


def mbrl_agent(propagation: str, particles: int) -> mbrl.planning.TrajectoryOptimizerAgent:
    """mbrl-lib's PETS agent (its ``pets_halfcheetah`` planner at the paper's population and horizon)."""
    silu = omegaconf.OmegaConf.create({"_target_": "torch.nn.SiLU"})
    network = mbrl.models.GaussianMLP(
        OBS + ACT, OBS, "cpu", num_layers=LAYERS, ensemble_size=MEMBERS, hid_size=HIDDEN,
        propagation_method=propagation, activation_fn_cfg=silu,
    )  # fmt: skip
    model = mbrl.models.OneDTransitionRewardModel(network, target_is_delta=True, normalize=True, learned_rewards=False)
    rng = np.random.default_rng(0)
    batch = mbrl.types.TransitionBatch(
        rng.normal(size=(1000, OBS)).astype(np.float32),
        rng.uniform(-1, 1, size=(1000, ACT)).astype(np.float32),
        rng.normal(size=(1000, OBS)).astype(np.float32),
        np.zeros(1000, dtype=np.float32),
        np.zeros(1000, dtype=bool),
        np.zeros(1000, dtype=bool),
    )
    model.update_normalizer(batch)  # statistics as after a first fit (the planner normalises every input)
    model_env = mbrl.models.ModelEnv(Spaces(), model, no_termination, velocity_reward, generator=th.Generator().manual_seed(0))
    config = omegaconf.OmegaConf.create(
        {
            "_target_": "mbrl.planning.TrajectoryOptimizerAgent",
            "_recursive_": False,  # the agent builds its optimizer from optimizer_cfg itself
            "planning_horizon": PAPER["horizon"],
            "replan_freq": 1,
            "verbose": False,
            "action_lb": [-1.0] * ACT,
            "action_ub": [1.0] * ACT,
            "optimizer_cfg": {
                "_target_": "mbrl.planning.CEMOptimizer",
                "num_iterations": PAPER["cem_iterations"],
                "elite_ratio": PAPER["num_elites"] / PAPER["population_size"],
                "population_size": PAPER["population_size"],
                "alpha": 0.1,
                "lower_bound": [[-1.0] * ACT] * PAPER["horizon"],
                "upper_bound": [[1.0] * ACT] * PAPER["horizon"],
                "return_mean_elites": True,
                "device": "cpu",
            },
        }
    )
    return mbrl.planning.create_trajectory_optim_agent_for_model(model_env, config, num_particles=particles)


def our_agent(propagation: str, particles: int) -> POPLIN:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return POPLIN(
            "pets", "HalfCheetah-v5", seed=0, device="cpu", propagation=propagation, num_particles=particles,
            ensemble_size=MEMBERS, dynamics_net_arch=(HIDDEN,) * LAYERS, **PAPER,  # type: ignore[arg-type]
        )  # fmt: skip


def interleaved(plans: dict[str, Any], rounds: int) -> dict[str, list[float]]:
    """``rounds`` rounds of one call of each plan function in turn (after one warm-up each): the seconds per call."""
    for plan in plans.values():
        plan()
    samples: dict[str, list[float]] = {name: [] for name in plans}
    for _ in range(rounds):
        for name, plan in plans.items():
            start = time.perf_counter()
            plan()
            samples[name].append(time.perf_counter() - start)
    return samples


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--rounds", type=int, default=7)
    parser.add_argument("--threads", type=int, default=1)
    args = parser.parse_args()
    th.set_num_threads(args.threads)
    command = "/work/mbrl-venv/bin/python " + " ".join(sys.argv)
    machine = describe_machine(args.threads)
    obs = np.random.default_rng(1).normal(size=OBS).astype(np.float32)
    section = "Our planner beside mbrl-lib's (`benchmarks/speed/mbrl_plan_speed.py`)"
    intro = (
        "PETS at the paper setting (HalfCheetah-v5 sizes, population 500, horizon 30, 5 CEM iterations, 50 elites, "
        "5 x 4 x 200 SiLU), one process, one plan of each library per round (medians; the ratio is the median of the "
        "rounds' ratios); the fp32 matmul peak measured in the same process; FLOPs: the matrix products of one of our "
        "plans as torch counts them (`sb3_poplin.planning.plan_flops`; mbrl-lib's plan makes the same network products)."
    )
    header = [
        "date",
        "command",
        "propagation",
        "ours",
        "mbrl-lib 0.2.0",
        "ours / mbrl-lib",
        "fraction of peak (ours / mbrl-lib)",
        "machine",
    ]
    for ours_name, (theirs_name, particles) in PROPAGATIONS.items():
        ours, theirs = our_agent(ours_name, particles), mbrl_agent(theirs_name, particles)
        flops = plan_flops(ours.planner, obs[None])  # mbrl-lib's plan makes the same network products
        peak = matmul_peak(th.float32)
        samples = interleaved(
            {"ours": lambda a=ours: a.predict(obs), "mbrl": lambda a=theirs: (a.reset(), a.act(obs))}, args.rounds
        )
        peak = max(peak, matmul_peak(th.float32))
        ratio = statistics.median(a / b for a, b in zip(samples["ours"], samples["mbrl"], strict=True))
        t_ours, t_mbrl = statistics.median(samples["ours"]), statistics.median(samples["mbrl"])
        fractions = f"{flops / t_ours / 1e9 / peak:.0%} / {flops / t_mbrl / 1e9 / peak:.0%} of {peak:.0f} GFLOP/s"
        label = f"{ours_name} ({theirs_name}, {particles} particle{'s' if particles > 1 else ''})"
        print(f"{label}: ours {t_ours * 1000:.0f} ms, mbrl-lib {t_mbrl * 1000:.0f} ms, ratio {ratio:.2f}x; {fractions}")
        row = [str(datetime.date.today()), f"`{command}`", label, f"{t_ours * 1000:.0f} ms", f"{t_mbrl * 1000:.0f} ms"]
        append_row(section, intro, header, [*row, f"{ratio:.2f}x", fractions, machine])


if __name__ == "__main__":
    main()
