"""
Cutting the planner's element-wise CPU work into single-threaded shares run on several cores.

Some of the planner's work cannot use torch's intra-op threads: CPU random number generation is serial, and the
CEM's candidate sampling is mostly that. :func:`run_shares` runs independent pieces of such work at once, the
first on the calling thread and the others on worker threads, each single-threaded.
"""

from __future__ import annotations

import os
import threading
from collections.abc import Callable, Sequence
from concurrent.futures import Future, ThreadPoolExecutor
from itertools import pairwise

import torch as th

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
    caller's grad and inference mode, and wait for all. An exception in any task is raised here, after all
    tasks have finished.

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
