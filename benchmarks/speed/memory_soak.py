"""
Resident memory over many training iterations: RSS after every model fit + distillation. With a
small replay buffer and distillation window that fill early, RSS must stay flat once both are full. Adds one row to
benchmarks/RESULTS.md.

    python benchmarks/speed/memory_soak.py [--variant poplin-p] [--iterations 25] [--buffer-size 2000]
"""

from __future__ import annotations

import argparse
import datetime
import os
import sys

import torch as th
from stable_baselines3.common.callbacks import BaseCallback

from sb3_poplin import POPLIN
from sb3_poplin.experiments.presets import poplin_settings

# benchmarks/, where results_file.py (shared by the scripts of every subfolder) lives
sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
from results_file import append_row, describe_machine


def rss_mib() -> float:
    """Current resident set size of this process, MiB (Linux)."""
    with open("/proc/self/status") as file:
        for line in file:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024
    raise RuntimeError("VmRSS not found: this benchmark needs Linux /proc")


class RssPerFit(BaseCallback):
    """Reads RSS at every rollout start, i.e. right after each fit."""

    def __init__(self) -> None:
        super().__init__()
        self.rss: list[float] = []

    def _on_rollout_start(self) -> None:
        self.rss.append(rss_mib())

    def _on_step(self) -> bool:
        return True


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--variant", default="poplin-p")
    parser.add_argument("--distillation", default="gan")
    parser.add_argument("--iterations", type=int, default=25)
    parser.add_argument("--buffer-size", type=int, default=2000)
    parser.add_argument("--distill-window", type=int, default=None, help="default: the buffer size")
    args = parser.parse_args()
    th.set_num_threads(1)
    # the CPU settings' model, a smaller planner: the soak measures memory over many iterations, not control
    settings = poplin_settings("Pendulum-v1", horizon=10, population_size=50, num_elites=5, cem_iterations=2)
    settings.update(
        policy=args.variant,
        buffer_size=args.buffer_size,
        distill_window=args.distill_window or args.buffer_size,
        distillation=args.distillation if args.variant == "poplin-p" else None,
    )
    model = POPLIN(env="Pendulum-v1", seed=0, **settings)
    callback = RssPerFit()
    model.learn(200 * (args.iterations + 1), callback=callback)
    rss = callback.rss[1:]  # after each fit
    for i, value in enumerate(rss, start=1):
        print(f"iteration {i:3d}: RSS {value:7.1f} MiB")
    full_at = args.buffer_size // 200
    after_full = rss[full_at:]
    growth = max(after_full) - min(after_full) if after_full else float("nan")
    print(f"RSS range once the buffer is full (iterations {full_at + 1}..{len(rss)}): {growth:.1f} MiB")
    command = "python " + " ".join(sys.argv)
    machine = describe_machine()
    append_row(
        "Memory over training iterations (`benchmarks/memory_soak.py`)",
        "RSS after each model fit + distillation (Pendulum-v1, 200-step episodes). The replay buffer and the "
        "distillation window fill after buffer_size / 200 iterations; after that RSS must stay flat.",
        ["date", "command", "RSS per iteration (MiB)", "range once the buffer is full", "machine"],
        [
            str(datetime.date.today()),
            f"`{command}`",
            ", ".join(f"{value:.0f}" for value in rss),
            f"{growth:.1f} MiB",
            machine,
        ],
    )


if __name__ == "__main__":
    main()
