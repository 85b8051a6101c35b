"""
Train a POPLIN agent with the packaged CPU settings of an env (``poplin_cpu.yml``) and save it, for the analyses
(``python -m sb3_poplin.analysis``):

    python benchmarks/diagnosis/train_analysis_model.py --env HalfCheetah-v5 --steps 10000 --out benchmarks/analysis/models
"""

from __future__ import annotations

import argparse
import os
import time

import torch as th

from sb3_poplin import POPLIN
from sb3_poplin.experiments.presets import load_config, config_path, poplin_settings
from sb3_poplin.tasks import make_env


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--env", required=True)
    parser.add_argument("--steps", type=int, default=None, help="default: the file's n_timesteps")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--variant", default=None, help="default: the file's policy")
    parser.add_argument("--out", default="benchmarks/analysis/models")
    args = parser.parse_args()
    th.set_num_threads(1)
    path = config_path("poplin", "cpu")
    assert path is not None
    entry = load_config(path)[args.env]
    settings = poplin_settings(args.env)
    if args.variant:
        settings["policy"] = args.variant
    steps = args.steps or int(entry["n_timesteps"])
    model = POPLIN(env=make_env(args.env, **entry.get("env_kwargs", {})), seed=args.seed, **settings)
    start = time.time()
    model.learn(steps)
    os.makedirs(args.out, exist_ok=True)
    name = f"{args.env.replace('/', '-')}-{settings['policy']}-{steps}-seed{args.seed}"
    model.save(os.path.join(args.out, name))
    returns = [info["r"] for info in model.ep_info_buffer]
    print(f"{name}: {steps} steps in {time.time() - start:.0f} s; training episode returns {returns}")


if __name__ == "__main__":
    main()
