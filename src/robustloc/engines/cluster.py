"""A dask.distributed client for one command run, always closed at the end."""

from __future__ import annotations

import logging
import os
import sys
from collections.abc import Iterator, Sequence
from contextlib import contextmanager

#: Environment of LocalCluster workers: one thread per worker for numba and BLAS, so
#: ``workers x threads`` never oversubscribes the cores (dask runs one task per worker
#: thread; the kernels are single-threaded per call).
WORKER_ENV = {"NUMBA_NUM_THREADS": "1", "OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1",
              "MKL_NUM_THREADS": "1"}
#: Memory limit of one LocalCluster worker (the engine's target is <= 2 GiB per worker).
WORKER_MEMORY_BYTES = 2 * 1024**3


def machine_cores() -> int:
    """CPU cores this process may use (affinity-aware)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # pragma: no cover - not Linux
        return max(1, os.cpu_count() or 1)


def import_distributed():
    """Import dask.distributed, or explain how to install it."""
    try:
        import distributed
    except ImportError:
        raise ValueError(
            "--engine dask needs dask.distributed: pip install 'robustloc[dask]'"
        ) from None
    return distributed


@contextmanager
def dask_client(scheduler: str | None, workers: int | None = None,
                processes: bool = True) -> Iterator[object]:
    """A ``distributed.Client``: on ``scheduler``, or on a new LocalCluster.

    Parameters
    ----------
    scheduler : str or None
        Address of a running scheduler (``tcp://host:8786``), or None to start a
        LocalCluster of ``workers`` single-threaded worker processes (default: the cores
        available), each limited to :data:`WORKER_MEMORY_BYTES`.
    workers : int, optional
        LocalCluster size.
    processes : bool
        LocalCluster workers as processes (default) or threads.

    The client, and the LocalCluster when one was started, are closed when the block
    exits, also on an error or an interrupt.
    """
    distributed = import_distributed()
    cluster = None
    client = None
    try:
        if scheduler is not None:
            try:
                client = distributed.Client(scheduler, timeout="20s")
            except OSError as exc:
                raise ValueError(f"--scheduler {scheduler}: cannot connect ({exc})") from None
        else:
            n = workers or machine_cores()
            extra = {"env": dict(WORKER_ENV)} if processes else {}
            cluster = distributed.LocalCluster(
                n_workers=n, threads_per_worker=1, processes=processes,
                memory_limit=WORKER_MEMORY_BYTES, dashboard_address=None, **extra,
            )
            client = distributed.Client(cluster)
        yield client
    finally:
        if client is not None:
            client.close()
        if cluster is not None:
            # A worker slow to exit is killed by its nanny, which logs a warning the user
            # can do nothing about; keep the terminal for the command's own output.
            nanny = logging.getLogger("distributed.nanny")
            level = nanny.level
            nanny.setLevel(logging.ERROR)
            try:
                cluster.close()
            finally:
                nanny.setLevel(level)


def gather_with_progress(client: object, futures: Sequence[object], show: bool) -> list:
    """Wait for ``futures`` with dask's progress bar (on a terminal) and gather them.

    The first failed future's exception is raised (an :class:`~robustloc.errors.InputError`
    from a worker keeps its partition file and line); the others are cancelled.
    """
    distributed = import_distributed()
    if show and sys.stdout.isatty():
        distributed.progress(futures)
        sys.stdout.write("\n")
    try:
        return client.gather(list(futures))
    except BaseException:
        client.cancel(list(futures))
        raise
