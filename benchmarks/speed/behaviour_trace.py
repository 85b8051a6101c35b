"""
A seeded behaviour trace of every variant and distillation, to show that a refactoring changed nothing.

For each configuration (tiny settings on Pendulum-v1, CPU, seeded) the trace records the parameters and buffers of
every network after ``learn``, the replay buffer's actions, MPC ``predict`` on fixed observations (fresh and with
the returned state passed back), policy control where there is a policy, and the same MPC call after a save/load
round trip. Only the public API is used, so the same script runs on the code before and after a change::

    python benchmarks/speed/behaviour_trace.py record before.pt --threads 1   # on the old code
    python benchmarks/speed/behaviour_trace.py record after.pt --threads 1    # on the new code
    python benchmarks/speed/behaviour_trace.py compare before.pt after.pt     # bit for bit
"""

from __future__ import annotations

import argparse
import io
import sys
import time
from typing import Any

import numpy as np
import torch as th

from sb3_poplin import POPLIN

TINY: dict[str, Any] = dict(
    horizon=5, population_size=20, num_elites=4, cem_iterations=2, ensemble_size=2, dynamics_net_arch=(16, 16), model_epochs=2
)
# name -> POPLIN keyword arguments beyond TINY: spelled out here, not taken from sb3_poplin.variants, because the
# script must run on versions of the package that predate that module
CONFIGS: dict[str, dict[str, Any]] = {
    "pets": dict(policy="pets"),
    "pets/tsinf": dict(policy="pets", propagation="tsinf", num_particles=4),
    "pets/ds/learned-reward": dict(policy="pets", propagation="ds", num_particles=4, learned_reward=True),
    "pets/bf16": dict(policy="pets", planning_dtype="bfloat16"),
    "rs": dict(policy="rs"),
    "poplin-a/init": dict(policy="poplin-a", proposal="init"),
    "poplin-a/replan": dict(policy="poplin-a", proposal="replan"),
    "poplin-p/sep/avg": dict(policy="poplin-p", noise="sep", distillation="avg"),
    "poplin-p/sep/bc": dict(policy="poplin-p", noise="sep", distillation="bc"),
    "poplin-p/sep/gan": dict(policy="poplin-p", noise="sep", distillation="gan"),
    "poplin-p/uni/avg": dict(policy="poplin-p", noise="uni", distillation="avg"),
    "poplin-p/uni/bc": dict(policy="poplin-p", noise="uni", distillation="bc"),
    "poplin-p/uni/gan": dict(policy="poplin-p", noise="uni", distillation="gan"),
    "poplin-p/sep/bc/window-none": dict(policy="poplin-p", noise="sep", distillation="bc", distill_window=None),
}
OBS = np.array([[0.3, 0.95, -1.0], [-1.0, 0.0, 2.0], [0.0, -1.0, 0.5]], dtype=np.float32)
STEPS = 800  # a random episode, then three planned ones; a fit (and a distillation) after each


def _array(value: Any) -> np.ndarray:
    return value.detach().cpu().numpy() if isinstance(value, th.Tensor) else np.asarray(value)


def trace_one(kwargs: dict[str, Any]) -> dict[str, np.ndarray]:
    """The trace of one configuration: name -> array."""
    model = POPLIN(env="Pendulum-v1", seed=0, **TINY, **kwargs)
    model.learn(STEPS)
    out = {f"param/{k}": _array(v) for k, v in model.policy.state_dict().items()}
    out["buffer/actions"] = model.replay_buffer.actions[: model.replay_buffer.pos].copy()
    starts = np.ones(len(OBS), dtype=bool)
    action, state = model.predict(OBS, episode_start=starts)
    out["mpc/action"], out["mpc/state"] = action, _array(state)
    action, state = model.predict(OBS, state=state, episode_start=~starts)
    out["mpc/action2"], out["mpc/state2"] = action, _array(state)
    if model.policy.actor is not None:
        model.control = "policy"
        out["policy/action"] = model.predict(OBS)[0]
        model.control = "mpc"
    buffer = io.BytesIO()
    model.save(buffer)
    buffer.seek(0)
    loaded = POPLIN.load(buffer)
    out["loaded/mpc/action"] = loaded.predict(OBS, episode_start=starts)[0]
    out["loaded/own/action"] = model.predict(OBS, episode_start=starts)[0]
    return out


def record(path: str, threads: int, names: list[str]) -> None:
    th.set_num_threads(threads)
    traces = {}
    for name in names:
        start = time.perf_counter()
        traces[name] = trace_one(CONFIGS[name])
        print(f"{name}: {len(traces[name])} arrays, {time.perf_counter() - start:.1f} s", flush=True)
    th.save({"threads": threads, "traces": traces}, path)


def compare(path_a: str, path_b: str) -> int:
    a, b = th.load(path_a, weights_only=False), th.load(path_b, weights_only=False)
    failures = 0
    for name in sorted(set(a["traces"]) | set(b["traces"])):
        ta, tb = a["traces"].get(name), b["traces"].get(name)
        if ta is None or tb is None:
            print(f"{name}: only in {'b' if ta is None else 'a'}")
            failures += 1
            continue
        bad = [k for k in sorted(set(ta) | set(tb)) if k not in ta or k not in tb or not np.array_equal(ta[k], tb[k])]
        status = "identical" if not bad else f"DIFFERENT in {bad}"
        print(f"{name}: {len(ta)} arrays {status}")
        failures += bool(bad)
    print(f"{len(set(a['traces']) | set(b['traces'])) - failures} identical, {failures} different")
    return 1 if failures else 0


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = parser.add_subparsers(dest="command", required=True)
    rec = sub.add_parser("record", help="record a trace")
    rec.add_argument("output")
    rec.add_argument("--threads", type=int, default=1)
    rec.add_argument("--configs", nargs="+", default=list(CONFIGS), choices=list(CONFIGS))
    cmp = sub.add_parser("compare", help="compare two traces bit for bit")
    cmp.add_argument("a")
    cmp.add_argument("b")
    args = parser.parse_args()
    if args.command == "record":
        record(args.output, args.threads, args.configs)
        return 0
    return compare(args.a, args.b)


if __name__ == "__main__":
    sys.exit(main())
