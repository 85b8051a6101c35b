"""
Planner speed at the paper setting, against this machine's own matmul peak (measured in the same
process, at the same thread count). Adds one row per run to benchmarks/RESULTS.md.

    python benchmarks/speed/planning_speed.py [--threads 1] [--repeats 5] [--quick] [--envs 1] [--device cpu]

Paper setting: HalfCheetah-v5 sizes, population 500, horizon 30, 5 CEM iterations, 50 elites, a
5-member 4x200 ensemble; expectation propagation and 20-particle TS-infinity; PETS, POPLIN-A (init)
and POPLIN-P (sep, [32] policy); fp32 and bf16. FLOPs are the matrix products torch counts during one plan
(``sb3_poplin.planning.plan_flops``: 2 per multiply-add, biases and activations not counted; POPLIN-P's perturbed
layers of one particle are two products, x theta + x omega; rows before 2026-12-07 counted one, from the shapes).
``--envs N`` plans N envs in one batch (rows marked "N envs"; the FLOPs and each product's rows scale with N).
The ratios (POPLIN-P/PETS, bf16 speed-ups) come from interleaved rounds, one plan per configuration in turn, so that
the drift of a shared machine affects both sides of a ratio alike. ``--device cuda`` plans on the GPU (the matmul
peak then comes from 8192^3 products, synchronised; ``benchmarks/device_check.sh`` runs it).
"""

from __future__ import annotations

import argparse
import datetime
import os
import resource
import statistics
import sys
import time
import warnings

import numpy as np
import torch as th
from stable_baselines3 import SAC
from stable_baselines3.common.env_util import make_vec_env

from sb3_poplin import POPLIN
from sb3_poplin.planning import plan_flops

# benchmarks/, where results_file.py (shared by the scripts of every subfolder) lives
sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
from results_file import append_row, describe_machine

ENV_ID = "HalfCheetah-v5"
CPU = th.device("cpu")
PAPER = dict(horizon=30, population_size=500, num_elites=50, cem_iterations=5, ensemble_size=5)
RUNS = [
    ("pets", dict(policy="pets"), "expectation", "float32"),
    ("pets", dict(policy="pets"), "expectation", "bfloat16"),
    ("pets", dict(policy="pets"), "tsinf", "float32"),
    ("pets", dict(policy="pets"), "tsinf", "bfloat16"),
    ("poplin-a/init", dict(policy="poplin-a", proposal="init"), "expectation", "float32"),
    ("poplin-p/sep", dict(policy="poplin-p", noise="sep"), "expectation", "float32"),
    ("poplin-p/sep", dict(policy="poplin-p", noise="sep"), "expectation", "bfloat16"),
]


def synchronize(device: th.device) -> None:
    """Wait for the device's queued work (a no-op on the CPU, where every op has finished when it returns)."""
    if device.type == "cuda":
        th.cuda.synchronize(device)


def matmul_peak(dtype: th.dtype, device: th.device = CPU, repeats: int = 5) -> float:
    """Best GFLOP/s of a square matmul (the roofline the planner is measured against): 2048^3 on a CPU, 8192^3 on a
    GPU (smaller products leave a GPU's units idle)."""
    size = 2048 if device.type == "cpu" else 8192
    a, b = th.randn(size, size, device=device).to(dtype), th.randn(size, size, device=device).to(dtype)
    a @ b  # warm-up
    best = 0.0
    for _ in range(repeats):
        synchronize(device)
        start = time.perf_counter()
        a @ b
        synchronize(device)
        best = max(best, 2 * size**3 / (time.perf_counter() - start) / 1e9)
    return best


def time_plans(model: POPLIN, obs: np.ndarray, repeats: int) -> float:
    for _ in range(2):
        model.predict(obs)
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        model.predict(obs)
        times.append(time.perf_counter() - start)
    return statistics.median(times)


def make(variant: dict, propagation: str, dtype: str, arch: tuple[int, ...], n_envs: int = 1, device: str = "cpu") -> POPLIN:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return POPLIN(
            env=ENV_ID if n_envs == 1 else make_vec_env(ENV_ID, n_envs=n_envs),
            seed=0,
            device=device,
            propagation=propagation,
            num_particles=20,
            planning_dtype=dtype,
            dynamics_net_arch=arch,
            **variant,
            **PAPER,
        )


def interleaved_ratios(models: dict[tuple[str, str, str], tuple[POPLIN, np.ndarray]], rounds: int) -> str:
    """
    Plan-time ratios from ``rounds`` rounds of one ``predict`` per model in turn: the median over rounds of each
    round's ratio, so that the machine's drift (other tenants on a shared host) affects both sides alike.
    """
    samples: dict[tuple[str, str, str], list[float]] = {key: [] for key in models}
    for _ in range(rounds):
        for key, (model, obs) in models.items():
            start = time.perf_counter()
            model.predict(obs)
            samples[key].append(time.perf_counter() - start)

    def ratio(num: tuple[str, str, str], den: tuple[str, str, str]) -> float:
        return statistics.median(a / b for a, b in zip(samples[num], samples[den], strict=True))

    pets, pets_bf16 = ("pets", "expectation", "float32"), ("pets", "expectation", "bfloat16")
    tsinf, tsinf_bf16 = ("pets", "tsinf", "float32"), ("pets", "tsinf", "bfloat16")
    return (
        f"POPLIN-P/PETS {ratio(('poplin-p/sep', 'expectation', 'float32'), pets):.2f}x, "
        f"POPLIN-A/PETS {ratio(('poplin-a/init', 'expectation', 'float32'), pets):.2f}x, "
        f"bf16 speed-up PETS {ratio(pets, pets_bf16):.2f}x, TS-inf {ratio(tsinf, tsinf_bf16):.2f}x, "
        f"POPLIN-P {ratio(('poplin-p/sep', 'expectation', 'float32'), ('poplin-p/sep', 'expectation', 'bfloat16')):.2f}x "
        f"(medians of {rounds} interleaved rounds; PETS fp32 {statistics.median(samples[pets]) * 1000:.0f} ms)"
    )


def bf16_effect(arch: tuple[int, ...], plans: int, device: str = "cpu") -> str:
    """How bf16 changes the executed action and the elite set, with a model fit on random data."""
    model = make(dict(policy="pets"), "expectation", "float32", arch, device=device)
    model.learn(1000)  # one random episode, then one fit
    env = model.get_env()
    assert env is not None
    obs = env.reset()
    action_diffs, overlaps = [], []
    planner = model.planner
    for i in range(plans):
        obs_t = th.as_tensor(obs, dtype=th.float32, device=model.device)
        shape = (1, model.settings.population_size, planner.search_space.dim)
        z = th.randn(shape, generator=th.Generator().manual_seed(i)) * 0.5
        z = z.to(model.device)
        with th.inference_mode():
            planner.dtype = th.float32
            fp32 = planner.rollout(obs_t, z, None)
            planner.dtype = th.bfloat16
            bf16 = planner.rollout(obs_t, z, None)
        k = model.settings.num_elites
        overlaps.append(len(set(fp32[0].topk(k).indices.tolist()) & set(bf16[0].topk(k).indices.tolist())) / k)
        actions = []
        for dtype in (th.float32, th.bfloat16):
            planner.dtype = dtype
            model.set_random_seed(100 + i)
            actions.append(model.predict(obs, episode_start=np.ones(1, dtype=bool))[0])
        action_diffs.append(float(np.abs(actions[0] - actions[1]).max()))
        obs, *_ = env.step(actions[0])
    return (
        f"elite-set overlap (same candidates) mean {np.mean(overlaps):.2f}, min {np.min(overlaps):.2f}; "
        f"executed action max abs diff median {np.median(action_diffs):.3f}, max {np.max(action_diffs):.3f} "
        f"(actions in [-1, 1]) over {plans} plans"
    )


def policy_latency(repeats: int, device: str = "cpu") -> tuple[float, float]:
    """Median seconds of one policy-control predict: POPLIN-P's [32] policy and SAC's default actor."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        poplin = POPLIN("poplin-p", ENV_ID, seed=0, control="policy", device=device, **PAPER)
    sac = SAC("MlpPolicy", ENV_ID, seed=0, device=device)
    obs = poplin.observation_space.sample()
    sac_obs = sac.observation_space.sample()
    results = []
    for model, o in ((poplin, obs), (sac, sac_obs)):
        for _ in range(20):
            model.predict(o, deterministic=True)
        times = []
        for _ in range(repeats):
            start = time.perf_counter()
            model.predict(o, deterministic=True)
            times.append(time.perf_counter() - start)
        results.append(statistics.median(times))
    return results[0], results[1]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--quick", action="store_true", help="a 2x64 ensemble instead of 4x200 (smoke test)")
    parser.add_argument(
        "--envs", type=int, default=1, help="envs planned in one batch (a VecEnv of this many; FLOPs and rows scale with it)"
    )
    parser.add_argument("--device", default="cpu", help="torch device to plan on: cpu, cuda, cuda:1, ...")
    args = parser.parse_args()
    device = th.device(args.device)
    if device.type == "cuda" and not th.cuda.is_available():
        parser.error("--device cuda: this torch build sees no CUDA device (torch.cuda.is_available() is False)")
    th.set_num_threads(args.threads)
    arch = (64, 64) if args.quick else (200, 200, 200, 200)
    command = "python " + " ".join(sys.argv)
    machine = describe_machine(args.threads, device)
    fp32_peak, bf16_peak = matmul_peak(th.float32, device), matmul_peak(th.bfloat16, device)
    print(f"matmul peak: fp32 {fp32_peak:.1f} GFLOP/s, bf16 {bf16_peak:.1f} GFLOP/s ({machine})")
    section = "Planner speed at the paper setting (`benchmarks/planning_speed.py`)"
    intro = (
        "HalfCheetah-v5 sizes, population 500, horizon 30, 5 CEM iterations, 5 x (200, 200, 200, 200) ensemble; "
        "median time of a single-env `predict` after warm-up; FLOPs counted analytically; the fp32/bf16 matmul peak is "
        "the best of five 2048^3 matmuls measured in the same process at the same thread count (since 2026-12-01: "
        "right before each row's timing)."
    )
    header = [
        "date",
        "command",
        "variant",
        "propagation",
        "dtype",
        "time per plan",
        "GFLOP/plan",
        "GFLOP/s",
        "fraction of peak",
        "peak RSS",
        "machine",
    ]
    models = {}
    for name, variant, propagation, dtype in RUNS:
        model = make(variant, propagation, dtype, arch, args.envs, args.device)
        obs = (
            np.stack([model.observation_space.sample() for _ in range(args.envs)])
            if args.envs > 1
            else model.observation_space.sample()
        )
        peak = matmul_peak(th.float32 if dtype == "float32" else th.bfloat16, device)  # right before: the machine drifts
        seconds = time_plans(model, obs, args.repeats)
        flops = plan_flops(model.planner, np.atleast_2d(obs))  # counted by torch during one plan
        rate = flops / seconds / 1e9
        peak_rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
        key = (name, propagation, dtype)
        models[key] = (model, obs)
        fraction = rate / peak
        print(
            f"{name:14s} {propagation:11s} {dtype:8s} {seconds * 1000:8.1f} ms {flops / 1e9:7.1f} GFLOP "
            f"{rate:6.1f} GFLOP/s {fraction:6.1%} of {dtype} peak {peak:.0f}, peak RSS {peak_rss:.0f} MiB",
            flush=True,
        )
        append_row(
            section,
            intro,
            header,
            [
                str(datetime.date.today()),
                f"`{command}`",
                name if args.envs == 1 else f"{name}, {args.envs} envs",
                propagation,
                dtype,
                f"{seconds * 1000:.0f} ms",
                f"{flops / 1e9:.1f}",
                f"{rate:.1f}",
                f"{fraction:.0%} of {peak:.0f}",
                f"{peak_rss:.0f} MiB",
                machine,
            ],
        )
    ratios = interleaved_ratios(models, 2 * args.repeats)
    effect = bf16_effect(arch, plans=10, device=args.device)
    poplin_latency, sac_latency = policy_latency(200, args.device)
    latency = (
        f"policy-control predict {poplin_latency * 1e6:.0f} us vs SAC actor {sac_latency * 1e6:.0f} us "
        f"({poplin_latency / sac_latency:.2f}x)"
    )
    print(ratios)
    print("bf16 effect:", effect)
    print(latency)
    append_row(
        "Planner speed: ratios, bf16 effect and policy-control latency (`benchmarks/planning_speed.py`)",
        "Same process as the rows above; since 2026-12-01 the ratios are medians over interleaved rounds (one plan "
        "per configuration in turn), before that ratios of the rows' medians.",
        ["date", "command", "ratios", "bf16 effect", "policy-control latency", "machine"],
        [str(datetime.date.today()), f"`{command}`", ratios, effect, latency, machine],
    )


if __name__ == "__main__":
    main()
