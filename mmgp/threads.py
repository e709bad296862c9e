"""The one thread policy of every mmgp command: how many CPU threads the numerics may use.

Why:

* Small factorisations must run on one thread. With several OpenMP/BLAS threads a busy machine
  makes every parallel region wait for a descheduled thread, which costs far more than the
  threads gain at these sizes; on an idle machine one thread loses little there (EM sweeps,
  ``mmgp compare`` folds, hyperparameter evaluations: benchmarks/README.md, "sixth session: tuning history").
* Large factorisations (thousands of rows: the exact GP on a whole log, SGPR conditioning) gain
  from threads only where cores are idle.

Policy (:func:`threads_for`): on a GPU the CPU does bookkeeping only: one thread. On a CPU, one
thread below :data:`PARALLEL_FROM_ROWS` kernel rows; from there, as many threads as there are
idle cores (cores this process may use minus the 1-minute load average, plus the one this
process occupies), never more than the cap the user set (``OMP_NUM_THREADS``). Commands and
library entry points wrap their numerics in :func:`limit_threads` / :func:`threads_for_rows`,
which set torch's intra-op threads and, through threadpoolctl, every BLAS/OpenMP pool numpy,
scipy and scikit-learn use, and restore them after.

No torch import at module level (``import mmgp`` stays light).
"""
from __future__ import annotations

import contextlib
import os
from typing import Iterator

#: kernel matrices with fewer rows than this are factorised on one thread (see the module doc)
PARALLEL_FROM_ROWS = 4000

#: thread-count variables of the numerical libraries (OpenMP, OpenBLAS, MKL, BLIS, Apple
#: Accelerate, numexpr) set to one thread: a worker process started with them has one thread
#: in every pool from the start, before numpy or torch load (the environment twin of
#: ``limit_threads(1)``)
ONE_THREAD_ENV = {name: "1" for name in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS",
                                         "BLIS_NUM_THREADS", "VECLIB_MAXIMUM_THREADS", "NUMEXPR_NUM_THREADS")}

def usable_cores() -> int:
    """CPU cores this process may run on (its affinity mask where the OS has one)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):
        return max(1, os.cpu_count() or 1)


def thread_cap() -> int:
    """The most threads mmgp ever uses: ``OMP_NUM_THREADS`` when set to a positive integer, else
    the usable cores."""
    env = os.environ.get("OMP_NUM_THREADS", "").strip()
    cap = int(env) if env.isdigit() and int(env) > 0 else usable_cores()
    return max(1, min(cap, usable_cores()))


def idle_cores() -> int:
    """Usable cores not taken by other work: cores minus the 1-minute load average, plus the
    core this process itself occupies; at least 1."""
    cores = usable_cores()
    try:
        load = os.getloadavg()[0]
    except (AttributeError, OSError):
        return cores
    return int(max(1, min(cores, cores - round(load) + 1)))


def threads_for(rows: int, device="cpu") -> int:
    """Threads for numerics on kernel matrices of ``rows`` rows on ``device`` (module doc)."""
    if str(device).split(":")[0] != "cpu" or rows < PARALLEL_FROM_ROWS:
        return 1
    return max(1, min(thread_cap(), idle_cores()))


@contextlib.contextmanager
def limit_threads(n: int, blas_only: bool = False) -> Iterator[None]:
    """Run the block with ``n`` torch intra-op threads and at most ``n`` threads in every
    BLAS/OpenMP pool (threadpoolctl); the previous counts are restored afterwards.
    ``blas_only``: only the BLAS pools (torch's threads and OpenMP's untouched)."""
    from threadpoolctl import threadpool_limits

    n = max(1, int(n))
    if blas_only:
        with threadpool_limits(limits=n, user_api="blas"):
            yield
        return
    import torch

    before = torch.get_num_threads()
    torch.set_num_threads(n)
    try:
        with threadpool_limits(limits=n):
            yield
    finally:
        torch.set_num_threads(before)


def threads_for_rows(rows: int, device="cpu"):
    """:func:`limit_threads` with :func:`threads_for` ``(rows, device)`` threads."""
    return limit_threads(threads_for(rows, device))
