"""Running the fleet's tasks: in this process one after another, or as Ray tasks.

Ray runs locally by default (``ray.init(num_cpus=workers)``: one task per core), or on the
cluster at ``address``; a session this process already opened is reused and left open. Every
task gets one CPU and runs its numerics on one thread: :data:`mmgp.threads.ONE_THREAD_ENV` is in
every worker's environment from its start, and :func:`mmgp.threads.limit_threads` (1) holds
inside the task. A local Ray started here inherits those variables from this process (set only
while Ray starts), so the workers Ray starts in advance serve the tasks; a cluster, or a session
opened elsewhere, gets them as the tasks' ``runtime_env`` (Ray then starts workers for that
environment: about 5 s more on a busy 2-core machine, measured).
"""
from __future__ import annotations

import contextlib
import os
import time
from typing import Callable, Iterator, Sequence

from ..threads import ONE_THREAD_ENV, usable_cores
from .work import blank_outcome, process_log

RAY_MISSING = ("mmgp fleet runs its tasks on Ray, which is not installed: pip install 'mmgp[fleet]' "
               "(or pip install ray), or run the logs one after another with --serial")

#: every task takes one CPU of Ray's budget
TASK_OPTIONS = {"num_cpus": 1}
#: the task options where the workers do not inherit ONE_THREAD_ENV (a cluster, a session opened elsewhere)
JOINED_TASK_OPTIONS = dict(TASK_OPTIONS, runtime_env={"env_vars": dict(ONE_THREAD_ENV)})

Progress = Callable[[int, int, dict], None]


class RayMissingError(ImportError):
    """Ray is needed (the ``fleet`` extra) but not installed."""


def import_ray():
    try:
        import ray
    except ImportError:
        raise RayMissingError(RAY_MISSING) from None
    return ray


def run_serial(jobs: Sequence[dict], progress: Progress | None = None) -> list[dict]:
    """Every job in this process, in order (the reference the Ray engine is measured against)."""
    outcomes = []
    for job in jobs:
        outcomes.append(process_log(job))
        if progress is not None:
            progress(len(outcomes), len(jobs), outcomes[-1])
    return outcomes


@contextlib.contextmanager
def _environ(values: dict) -> Iterator[None]:
    before = {k: os.environ.get(k) for k in values}
    os.environ.update(values)
    try:
        yield
    finally:
        for k, v in before.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v


@contextlib.contextmanager
def ray_session(address: str | None, workers: int | None) -> Iterator[tuple]:
    """``(ray, task_options)``: the Ray session already open, else a new local instance
    (``workers`` CPUs) or a connection to the cluster at ``address``, shut down afterwards; and
    the options that give its tasks one CPU and one thread each."""
    ray = import_ray()
    if ray.is_initialized():
        yield ray, JOINED_TASK_OPTIONS
        return
    kwargs = {"include_dashboard": False, "log_to_driver": False}
    if address is None:
        with _environ(ONE_THREAD_ENV):
            ray.init(num_cpus=workers or usable_cores(), **kwargs)
    else:
        ray.init(address=address, **kwargs)
    try:
        yield ray, TASK_OPTIONS if address is None else JOINED_TASK_OPTIONS
    finally:
        ray.shutdown()


def _collect(ray, ref, job: dict) -> dict:
    try:
        return ray.get(ref)
    except ray.exceptions.RayError as exc:  # the worker died (memory, signal): no outcome came back
        return blank_outcome(job, error=f"task failed ({type(exc).__name__}): {exc}")


def run_ray(jobs: Sequence[dict], *, address: str | None = None, workers: int | None = None,
            progress: Progress | None = None, timings: dict | None = None) -> list[dict]:
    """Every job as a Ray task (one CPU each); at most ``workers`` in flight when given.
    Outcomes come back in the order of ``jobs``; ``timings`` (a dict) receives ``ray_start_s``,
    the seconds it took to start or join Ray."""
    t0 = time.perf_counter()
    with ray_session(address, workers) as (ray, options):
        if timings is not None:
            timings["ray_start_s"] = time.perf_counter() - t0
        task = ray.remote(**options)(process_log)
        limit = workers or len(jobs)
        outcomes: list = [None] * len(jobs)
        pending: dict = {}
        submitted = finished = 0
        while submitted < len(jobs) or pending:
            while submitted < len(jobs) and len(pending) < limit:
                pending[task.remote(jobs[submitted])] = submitted
                submitted += 1
            ready, _ = ray.wait(list(pending), num_returns=1)
            for ref in ready:
                i = pending.pop(ref)
                outcomes[i] = _collect(ray, ref, jobs[i])
                finished += 1
                if progress is not None:
                    progress(finished, len(jobs), outcomes[i])
        return outcomes
