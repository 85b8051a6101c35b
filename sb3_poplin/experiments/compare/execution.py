"""
Running the jobs: one ``sb3-poplin-zoo train`` process per run, locally (a pool of ``--jobs``) or as Ray tasks,
each continuing its interrupted run where there is one and marking its folder complete when it finishes.
"""

from __future__ import annotations

import concurrent.futures
import ctypes
import json
import os
import signal
import subprocess
from pathlib import Path
from typing import Any


from sb3_poplin.experiments.compare.jobs import (
    COMPLETE_FILE,
    RUN_FILE_SUFFIXES,
    Job,
    JobResult,
    find_interrupted,
    find_run,
)


def _load_prctl() -> Any:
    """:return: Linux's ``prctl`` (resolved here, not in the forked child), or ``None`` elsewhere"""
    try:
        return ctypes.CDLL(None, use_errno=True).prctl
    except (OSError, AttributeError):
        return None


_PRCTL = _load_prctl()
PR_SET_PDEATHSIG = 1


def _die_with_parent() -> None:
    """In a run's process (Linux): be killed when the comparison's process dies, so no orphan trains on."""
    if _PRCTL is not None:
        _PRCTL(PR_SET_PDEATHSIG, signal.SIGKILL)


def mark_complete(job: Job, run_dir: str) -> None:
    """
    Write the completion marker into a finished run's folder (if it has none), so that its small files alone make it
    complete (a committed run folder, whose zips git ignores).

    :param job: the job
    :param run_dir: its finished run (relative to the log folder)
    """
    path = Path(job.log_folder) / run_dir / COMPLETE_FILE
    if not path.is_file():
        marker = {"job": job.name, "command": job.command()[1:], "n_timesteps": job.n_timesteps}
        path.write_text(json.dumps(marker, indent=1))


def execute(job: Job, force: bool = False, collect_files: bool = False) -> JobResult:
    """
    Run one job (or reuse its complete run).

    :param job: the job
    :param force: train again even if a complete run exists
    :param collect_files: return the run's files (Ray tasks on machines without a shared file system)
    :return: the outcome
    """
    run_dir = None if force else find_run(job)
    result = JobResult(job, 0, run_dir, reused=run_dir is not None)
    if run_dir is not None:
        mark_complete(job, run_dir)  # a comparison killed after the run finished did not mark it
    else:
        interrupted = None if force else find_interrupted(job)
        os.makedirs(os.path.join(job.log_folder, "compare_logs"), exist_ok=True)
        log_file = os.path.join(job.log_folder, "compare_logs", f"{job.name}.log")
        env = dict(os.environ, OMP_NUM_THREADS="1", MKL_NUM_THREADS="1")
        command = job.command(resume=interrupted)
        with open(log_file, "a" if interrupted else "w") as output:
            if interrupted:
                output.write(f"\n--- continuing the interrupted run {interrupted} ---\n")
                output.flush()
            process = subprocess.run(
                command, stdout=output, stderr=subprocess.STDOUT, env=env, check=False, preexec_fn=_die_with_parent
            )
        result.returncode = process.returncode
        result.resumed = interrupted
        result.run_dir = find_run(job) if process.returncode == 0 else None
        if result.run_dir is not None:
            mark_complete(job, result.run_dir)
        else:
            with open(log_file) as output:
                result.output_tail = "".join(output.readlines()[-30:])
            result.returncode = result.returncode or 1
    if collect_files and result.run_dir is not None:
        run_path = Path(job.log_folder) / result.run_dir
        for path in run_path.rglob("*"):
            if path.is_file() and path.suffix in RUN_FILE_SUFFIXES:
                result.files[str(path.relative_to(job.log_folder))] = path.read_bytes()
    return result


def run_local(jobs: list[Job], n_parallel: int, force: bool) -> list[JobResult]:
    """
    Run the jobs in a pool of ``n_parallel`` processes.

    :param jobs: the jobs
    :param n_parallel: runs at a time
    :param force: train again even if a complete run exists
    :return: the results, in the jobs' order
    """
    futures: dict[int, concurrent.futures.Future[JobResult]] = {}
    with concurrent.futures.ThreadPoolExecutor(max_workers=n_parallel) as pool:
        for index in execution_order(jobs):
            futures[index] = pool.submit(execute, jobs[index], force)
        for future in concurrent.futures.as_completed(futures.values()):
            report_progress(future.result())
    return [futures[index].result() for index in range(len(jobs))]


def execution_order(jobs: list[Job]) -> list[int]:
    """
    The order in which runs start: seed by seed, each seed's algorithms together (task by task), so that the
    algorithms' first seeds finish first and a partial comparison is a paired one.

    :param jobs: the jobs (algorithm-major, as :func:`plan_jobs` makes them)
    :return: indices into ``jobs``
    """
    seeds = sorted({job.seed for job in jobs})
    return sorted(range(len(jobs)), key=lambda index: (seeds.index(jobs[index].seed), index))


RAY_NICENESS = "RAY_worker_niceness"


def start_local_ray(ray: Any, n_parallel: int) -> None:
    """
    Start a Ray instance on this machine whose workers run at the caller's priority, as ``--jobs`` runs do without
    Ray: Ray's default lowers its workers' priority by 15, so that anything else on the machine (another run, a test
    suite) starves the runs. A niceness given in ``RAY_worker_niceness`` is kept.

    :param ray: the ``ray`` module
    :param n_parallel: CPUs of the instance
    """
    given = os.environ.get(RAY_NICENESS)
    os.environ[RAY_NICENESS] = given if given is not None else "0"  # the raylet started here reads its environment
    try:
        ray.init(num_cpus=n_parallel, include_dashboard=False, log_to_driver=False)
    finally:
        if given is None:
            del os.environ[RAY_NICENESS]


def run_ray(jobs: list[Job], address: str, n_parallel: int, force: bool) -> list[JobResult]:
    """
    Run the jobs as Ray tasks of one CPU each; the files of runs made on other machines are written to the
    local log folder. Complete runs in the local log folder are reused without a task. An interrupted run continues
    from its checkpoint only where the node that runs it sees the run's folder (a shared file system); elsewhere it
    starts again.

    :param jobs: the jobs
    :param address: ``"local"`` (start a Ray instance here), ``"auto"`` or a cluster address
    :param n_parallel: CPUs of a local Ray instance
    :param force: train again even if a complete run exists
    :return: the results, in the jobs' order
    """
    try:
        import ray
    except ImportError:
        raise SystemExit("--ray-address needs Ray: pip install 'sb3_poplin[ray]'") from None
    if address == "local":
        start_local_ray(ray, n_parallel)
    else:
        ray.init(address=address, log_to_driver=False)
    try:
        task = ray.remote(num_cpus=1)(execute)
        remote: Any = task.remote  # Ray's stubs type a remote function by its first signature only
        results: dict[int, JobResult] = {}
        submitted = {}
        for index, job in enumerate(jobs):
            local = None if force else find_run(job)
            if local is not None:  # complete here: the nodes need not see this folder
                results[index] = JobResult(job, 0, local, reused=True)
                mark_complete(job, local)
                report_progress(results[index])
            else:
                submitted[remote(job, force, True)] = index
        pending = list(submitted)
        while pending:
            done, pending = ray.wait(pending, num_returns=1)
            result = ray.get(done[0])
            for relative, content in result.files.items():
                path = Path(result.job.log_folder) / relative
                if not path.exists():
                    path.parent.mkdir(parents=True, exist_ok=True)
                    path.write_bytes(content)
            result.files = {}
            report_progress(result)
            results[submitted[done[0]]] = result
    finally:
        ray.shutdown()
    return [results[index] for index in range(len(jobs))]


def report_progress(result: JobResult) -> None:
    """
    :param result: a finished job, printed as one line (with the end of its output when it failed)
    """
    if result.returncode == 0:
        state = "reused" if result.reused else "resumed" if result.resumed else "done"
        print(f"[{state}] {result.job.name}: {result.run_dir}", flush=True)
    else:
        print(f"[failed {result.returncode}] {result.job.name}\n{result.output_tail}", flush=True)
