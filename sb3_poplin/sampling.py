"""
The speed layer of the CEM's candidate sampling: what it computes is ``mean + std * eps`` with ``eps`` standard
normal truncated to [-2, 2] (or plain normal); everything here is about computing it fast on a CPU.

- :func:`truncated_normal`: truncated-normal samples by inverting the CDF. On the CPU, where POPLIN-P's searches wait
  for the random number generator (tens of millions of samples per plan), each 64-bit draw gives four 16-bit
  uniforms and each picks one of 65,536 equally likely bins of the law, whose midpoint quantile is looked up in a
  table (finer than 3e-4 in x everywhere, with the law's mean and variance).
- :class:`CandidateSampler`: the candidates of one CEM iteration into a reused buffer. On the CPU the rows are drawn
  in chunks of about :data:`CHUNK_SAMPLES` samples, chunk ``c`` from a ``numpy.random.SFC64`` stream seeded with
  ``base + c`` (``base``: one draw from the caller's generator), scaled into the candidates while in cache, and the
  chunks are shared among the intra-op threads (:func:`run_shares`; torch's CPU generator is serial) with the same
  candidates for any thread count.
- :class:`Workspace`: named flat buffers reused across calls (at POPLIN-P's sizes a fresh tensor per iteration costs
  as much in page faults as drawing the samples).

Why these choices: docs/results.md, "Planner speed".
"""

from __future__ import annotations

import math
import os
import threading
from collections.abc import Callable, Sequence
from concurrent.futures import Future, ThreadPoolExecutor
from itertools import pairwise

import numpy as np
import torch as th

SAMPLINGS = ("truncated", "clipped")
# the standard normal CDF at -2 and +2: bounds of the uniform draw for a normal truncated at 2 sigma
_PHI_MINUS_2 = 0.5 * (1.0 + math.erf(-2.0 / math.sqrt(2.0)))
_PHI_PLUS_2 = 0.5 * (1.0 + math.erf(2.0 / math.sqrt(2.0)))
# a 16-bit uniform integer v picks the v-th of 65,536 equally likely bins of the truncated normal; the sample is the
# law's quantile at the bin's midpoint, Phi^-1(Phi(-2) + (Phi(2) - Phi(-2)) (v + 0.5) / 2^16), computed once in
# float64 (a table of 256 KiB per device and scale)
_LEVELS = 65536
_QUANTILE_TABLES: dict[tuple[str, bool], th.Tensor] = {}
_GATHER_CHUNK = 65536  # samples per table lookup: the int32 index chunk stays in cache
# CPU candidates are drawn in chunks of rows of about this many samples (1 MiB of noise, which stays in cache until
# it is scaled into the candidates)
CHUNK_SAMPLES = 1 << 18


class Workspace:
    """Named flat buffers, reused while large enough (grown otherwise)."""

    def __init__(self) -> None:
        self._buffers: dict[str, th.Tensor] = {}

    def get(self, name: str, numel: int, dtype: th.dtype, device: th.device | str) -> th.Tensor:
        """A flat buffer of ``numel`` elements (contents undefined)."""
        buffer = self._buffers.get(name)
        if buffer is None or buffer.numel() < numel or buffer.dtype != dtype or buffer.device != th.device(device):
            buffer = th.empty(numel, dtype=dtype, device=device)
            self._buffers[name] = buffer
        return buffer[:numel]


def _quantile_table(device: th.device, unit_variance: bool) -> th.Tensor:
    key = (str(device), unit_variance)
    if key not in _QUANTILE_TABLES:
        mid = (th.arange(_LEVELS, dtype=th.float64) + 0.5) / _LEVELS
        quantiles = th.special.ndtri(_PHI_MINUS_2 + (_PHI_PLUS_2 - _PHI_MINUS_2) * mid)
        if not unit_variance:
            quantiles = quantiles / math.sqrt(2.0)
        _QUANTILE_TABLES[key] = quantiles.to(device=device, dtype=th.float32)
    return _QUANTILE_TABLES[key]


def truncated_normal(
    shape: tuple[int, ...],
    device: th.device | str,
    generator: th.Generator | None = None,
    out: th.Tensor | None = None,
    scratch: th.Tensor | None = None,
    unit_variance: bool = True,
) -> th.Tensor:
    """
    Standard normal samples truncated to [-2, 2], by inverting the CDF (a 16-bit quantile table on the CPU, one
    float uniform and ``erfinv`` per sample elsewhere).

    :param shape: shape of the samples
    :param device: device of the samples
    :param generator: random generator
    :param out: contiguous float32 tensor of ``shape`` to fill (a reused buffer)
    :param scratch: contiguous int64 CPU buffer of at least ``ceil(numel / 4)`` elements for the raw bits
    :param unit_variance: False returns the samples divided by sqrt(2), which saves one pass when the caller
        scales them anyway
    :return: the samples (``out`` if given)
    """
    n = math.prod(shape)
    if out is None:
        out = th.empty(shape, device=device)
    elif tuple(out.shape) != tuple(shape) or not out.is_contiguous():
        raise ValueError(f"out must be a contiguous tensor of shape {tuple(shape)}, got {tuple(out.shape)}")
    if th.device(device).type == "cpu":
        n_words = (n + 3) // 4
        if scratch is None or scratch.numel() < n_words:
            scratch = th.empty(n_words, dtype=th.int64, device=device)
        bits = scratch[:n_words].random_(-(2**63), None, generator=generator)
        return levels_to_samples(bits.view(th.uint16)[:n], out, unit_variance)
    out.view(-1).uniform_(2.0 * _PHI_MINUS_2 - 1.0, 2.0 * _PHI_PLUS_2 - 1.0, generator=generator)
    out.erfinv_().clamp_(-math.sqrt(2.0), math.sqrt(2.0))
    return out.mul_(math.sqrt(2.0)) if unit_variance else out


def levels_to_samples(levels: th.Tensor, out: th.Tensor, unit_variance: bool, index: th.Tensor | None = None) -> th.Tensor:
    """
    Fill the contiguous CPU tensor ``out`` with the truncated-normal quantiles of the 16-bit ``levels``.

    :param levels: uint16 levels, one per sample
    :param out: the samples' tensor
    :param unit_variance: see :func:`truncated_normal`
    :param index: int32 scratch of at least ``min(levels.numel(), 65536)`` elements (a reused buffer), or None
    """
    n, flat = levels.numel(), out.view(-1)
    table = _quantile_table(flat.device, unit_variance)
    if index is None or index.numel() < min(n, _GATHER_CHUNK):
        index = th.empty(min(n, _GATHER_CHUNK), dtype=th.int32)
    for start in range(0, n, _GATHER_CHUNK):
        stop = min(start + _GATHER_CHUNK, n)
        chunk = index[: stop - start]
        chunk.copy_(levels[start:stop])
        th.index_select(table, 0, chunk, out=flat[start:stop])
    return out


class CandidateSampler:
    """
    The candidates ``z = mean + std * eps`` of one CEM iteration, ``[n_envs, N, D]``, in a buffer reused across
    iterations and plans (callers copy what they keep).

    :param population_size: candidates N per env
    :param sampling: ``"truncated"`` (``eps`` standard normal truncated at 2 sigma) or ``"clipped"`` (plain
        standard normal; the search space clips what leaves its bounds)
    """

    def __init__(self, population_size: int, sampling: str = "truncated") -> None:
        self.population_size = population_size
        self.truncated = sampling == "truncated"
        self.workspace = Workspace()

    def sample(self, mean: th.Tensor, std: th.Tensor, generator: th.Generator | None, count: int | None = None) -> th.Tensor:
        """
        :param mean: ``[n_envs, D]``
        :param std: ``[n_envs, D]``
        :param generator: the planner's random generator (CPU: only one draw from it, the chunks' base seed)
        :param count: candidates per env (default: the population size)
        :return: the candidates ``[n_envs, count, D]`` (the reused buffer)
        """
        if self.truncated:  # the noise is drawn divided by sqrt(2) (one pass fewer), the scale makes up for it
            std = std * math.sqrt(2.0)
        n_envs, dim = mean.shape
        pop = self.population_size if count is None else count
        z = self.workspace.get("candidates", n_envs * pop * dim, th.float32, mean.device).view(n_envs, pop, dim)
        if mean.device.type != "cpu":
            if self.truncated:
                truncated_normal(z.shape, z.device, generator, out=z, unit_variance=False)
            else:
                z.normal_(generator=generator)
            return th.addcmul(mean.unsqueeze(1), z, std.unsqueeze(1), out=z)
        rows = max(1, CHUNK_SAMPLES // dim)
        chunks = [(env, start, min(start + rows, pop)) for env in range(n_envs) for start in range(0, pop, rows)]
        base = int(th.randint(0, 2**62, (1,), generator=generator).item())

        def share(index: int, first: int, last: int) -> Callable[[], None]:
            def run() -> None:
                noise = self.workspace.get(f"noise{index}", rows * dim, th.float32, z.device)
                lookup = self.workspace.get(f"index{index}", min(rows * dim, _GATHER_CHUNK), th.int32, z.device)
                chunk_generator = None if self.truncated else th.Generator()
                for c in range(first, last):
                    env, start, stop = chunks[c]
                    out = noise[: (stop - start) * dim].view(stop - start, dim)
                    if chunk_generator is None:
                        bits = th.from_numpy(np.random.SFC64(base + c).random_raw((out.numel() + 3) // 4))
                        levels_to_samples(bits.view(th.uint16)[: out.numel()], out, False, lookup)
                    else:
                        out.normal_(generator=chunk_generator.manual_seed(base + c))
                    th.addcmul(mean[env], out, std[env], out=z[env, start:stop])

            return run

        ranges = split_range(len(chunks), th.get_num_threads())
        run_shares([share(i, first, last) for i, (first, last) in enumerate(ranges)])
        return z


# ---------------------------------------------------------------------------------------- shares on several cores
_POOLS: dict[tuple[int, int], ThreadPoolExecutor] = {}
_POOLS_LOCK = threading.Lock()


def _pool(workers: int) -> ThreadPoolExecutor:
    # one pool per process and size (a forked child starts its own); its threads run torch single-threaded
    key = (os.getpid(), workers)
    with _POOLS_LOCK:
        pool = _POOLS.get(key)
        if pool is None:
            pool = ThreadPoolExecutor(workers, thread_name_prefix="sb3_poplin", initializer=th.set_num_threads, initargs=(1,))
            _POOLS[key] = pool
    return pool


def run_shares(tasks: Sequence[Callable[[], None]]) -> None:
    """
    Run ``tasks[0]`` on the calling thread and the others on worker threads, all single-threaded and with the
    caller's grad and inference mode, and wait for all: element-wise work that torch's intra-op threads cannot split
    (CPU random number generation is serial) on several cores. An exception in any task is raised here, after all
    tasks have finished. Use it for coarse pieces only: alternating it with multi-threaded ops makes the OpenMP team
    and the workers compete for the cores.

    :param tasks: one callable per share; they must write to disjoint memory
    """
    if len(tasks) == 1:
        tasks[0]()
        return
    grad, inference = th.is_grad_enabled(), th.is_inference_mode_enabled()

    def in_mode(task: Callable[[], None]) -> None:
        with th.inference_mode(inference), th.set_grad_enabled(grad):
            task()

    futures: list[Future[None]] = [_pool(len(tasks) - 1).submit(in_mode, task) for task in tasks[1:]]
    threads = th.get_num_threads()
    th.set_num_threads(1)  # thread-local in torch: this thread's share stays on its core
    try:
        tasks[0]()
    finally:
        th.set_num_threads(threads)
        errors = [future.exception() for future in futures]
    for error in errors:
        if error is not None:
            raise error


def split_range(total: int, parts: int) -> list[tuple[int, int]]:
    """``[0, total)`` cut into at most ``parts`` contiguous non-empty ranges of nearly equal size."""
    cuts = [round(total * k / parts) for k in range(parts + 1)]
    return [(lo, hi) for lo, hi in pairwise(cuts) if hi > lo]
