"""A dask.distributed client for one command run, always closed at the end."""

from __future__ import annotations

import logging
import os
import sys
import threading
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass

from robustloc.errors import InputError, Terminated

#: Environment of LocalCluster workers: one thread per worker for numba and BLAS, so
#: ``workers x threads`` never oversubscribes the cores (dask runs one task per worker
#: thread; the compiled kernels split a long batch over numba's thread count, which this
#: sets to 1).
WORKER_ENV = {"NUMBA_NUM_THREADS": "1", "OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1",
              "MKL_NUM_THREADS": "1"}
#: Memory limit of one LocalCluster worker (the engine's target is <= 2 GiB per worker).
WORKER_MEMORY_BYTES = 2 * 1024**3
#: Seconds to wait for a first worker on a ``--scheduler`` that has none yet (an adaptive
#: cluster starting its workers) before ``error: --scheduler ADDRESS: no workers after N
#: s``, exit 2 (without it, a scheduler with no workers made every command wait forever).
WORKER_WAIT_SECONDS = 30.0
#: Seconds to wait for a connection to a ``--scheduler``.
CONNECT_TIMEOUT_SECONDS = 20.0
#: Most seconds an interrupt is held while a LocalCluster starts (:func:`_signals_held`).
SIGNAL_HOLD_SECONDS = 10.0


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
def _signals_held(limit: int | None = 2) -> Iterator[list[int]]:
    """SIGINT and SIGTERM held while the block runs (main thread only): a handler notes
    them in the yielded list, the old handlers come back at the end, and the caller
    delivers what was noted.  The ``limit``-th signal (default: a second one; None:
    none) raises ``KeyboardInterrupt`` at once, and so does the first one held for
    :data:`SIGNAL_HOLD_SECONDS` (the ways out of a start or close that hangs).  A signal
    ignored stays ignored.

    Used around the start of a LocalCluster: interrupted half-way, its worker processes
    never reach a state ``close()`` accepts, distributed's ``atexit`` hook then fails on
    it (``AssertionError: Status.init`` with two tracebacks after ``error: interrupted``),
    and the variable our cleanup would close was never assigned.
    """
    import signal

    got: list[int] = []
    if threading.current_thread() is not threading.main_thread():
        yield got
        return

    import _thread

    timer: list[threading.Timer] = []
    expired: list[bool] = []

    def deadline() -> None:
        expired.append(True)
        _thread.interrupt_main()  # (runs ``note`` in the main thread)

    def note(signum: int, frame: object) -> None:
        got.append(signum)
        if expired or (limit is not None and len(got) >= limit):  # out at once
            raise KeyboardInterrupt()
        if not timer:
            # held for SIGNAL_HOLD_SECONDS at most: a start that hangs must not keep a
            # SIGTERM (``timeout``'s only one) waiting for ever (the Dask review)
            t = threading.Timer(SIGNAL_HOLD_SECONDS, deadline)
            t.daemon = True
            t.start()
            timer.append(t)

    old = {}
    for sig in (signal.SIGINT, signal.SIGTERM):
        if signal.getsignal(sig) is not signal.SIG_IGN:
            old[sig] = signal.signal(sig, note)
    try:
        yield got
    finally:
        for t in timer:
            t.cancel()
        for sig, handler in old.items():
            signal.signal(sig, handler)


@contextmanager
def _cleanup_signals_held(exc: BaseException | None) -> Iterator[None]:
    """SIGINT and SIGTERM noted, not raised, while the block cleans up after ``exc``
    (None: a normal end): cancelling the tasks, closing the client and the LocalCluster
    (main thread only; a close that hangs is left after :data:`SIGNAL_HOLD_SECONDS`).
    What was noted is dropped when ``exc`` is itself an interrupt (the command ends
    ``interrupted`` already), else delivered after the block.

    Those are calls of distributed's ``sync()``, which waits for its coroutine on the
    event loop: an interrupt raised in that wait before the loop had started the
    coroutine ran distributed's cancel callback on an unset variable (``NameError:
    cannot access free variable 'future'``, a tornado traceback above ``error:
    interrupted``; distributed 2026.11).  After a Ctrl-C the next signal lands there:
    a second Ctrl-C, or the one ``timeout`` forwards to its child and again to the
    process group (the dask review: 1 run in 6 of ``locate --engine dask``, 2 of 8 of
    ``partition --method dask``), and it also cut the close short.
    """
    import signal

    interrupted = isinstance(exc, KeyboardInterrupt | Terminated)
    # the cluster torn down mid-run: its scheduler (in this process for a LocalCluster)
    # logs the tasks it drops ("distributed.core - ERROR - Exception while handling op
    # shuffle_barrier ... KeyError", a partition --method dask shuffle interrupted: the
    # dask review); the user asked for it to stop, the one line says so.  For the
    # cleanup only (the command then silences them for the exit: cli's
    # _quiet_after_interrupt)
    # (each logger of theirs: distributed's configuration gives some their own level,
    # tornado.application's ERROR, which a parent's level does not override)
    noisy = [n for n in ("distributed", "tornado", "asyncio",
                         *logging.Logger.manager.loggerDict)
             if interrupted and n.split(".")[0] in ("distributed", "tornado", "asyncio")]
    levels = {name: logging.getLogger(name).level for name in noisy}
    for name in noisy:
        logging.getLogger(name).setLevel(logging.CRITICAL + 1)
    try:
        with _signals_held(limit=None) as got:
            yield
    finally:
        for name, level in levels.items():
            logging.getLogger(name).setLevel(level)
    if got and not interrupted:
        for signum in dict.fromkeys(got):
            signal.raise_signal(signum)


def _cancel(client: object, futures: Sequence[object]) -> None:
    """``client.cancel(futures)``, nothing when the client is no longer running: closed
    by the main thread after an interrupt, before or while this runs (the watch thread
    of :func:`gather_with_progress` then raised ``ClosedClientError`` twice, a traceback
    above ``error: interrupted``: the dask review).  Any other failure of a running
    client is raised."""
    if getattr(client, "status", "running") != "running":
        return
    try:
        client.cancel(futures)  # type: ignore[attr-defined]
    except Exception:
        if getattr(client, "status", "running") == "running":
            raise


@contextmanager
def _sigint_blocked_in_new_threads() -> Iterator[None]:
    """SIGINT blocked in the threads the block starts (main thread only), so that the
    worker processes they spawn never see a terminal's Ctrl-C.

    Ctrl-C sends SIGINT to the terminal's whole process group, LocalCluster's worker
    processes included: a worker starting died of it (``internal error ... RuntimeError:
    Nanny failed to start``, exit 1) and a worker running printed its traceback and
    ``distributed.nanny - ERROR`` lines (4-6 tracebacks above ``error: interrupted``).
    A signal mask passes to a new thread and through fork and exec to a process (a
    disposition set to a handler does not; ``SIG_IGN`` would, but this process must see
    the signal): the main thread blocks SIGINT while the cluster starts its event-loop
    thread (which starts every worker process, a restarted one too), and a catcher
    thread started before receives the signal meanwhile for the main thread's handler
    (Python runs a handler in the main thread whichever thread the signal reached).
    Only this process then handles Ctrl-C; it closes the cluster, which stops the
    workers.
    """
    import signal

    if (threading.current_thread() is not threading.main_thread()
            or not hasattr(signal, "pthread_sigmask")):  # pragma: no cover - not POSIX
        yield
        return
    # multiprocessing's resource tracker unblocks SIGINT in the thread that starts it
    # (the event loop's, at the first worker): started here first, it never does
    from multiprocessing import resource_tracker

    resource_tracker.ensure_running()
    stop = threading.Event()
    catcher = threading.Thread(target=stop.wait, name="robustloc SIGINT catcher",
                               daemon=True)
    catcher.start()
    old = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, old)
        stop.set()
        catcher.join()


@contextmanager
def dask_client(scheduler: str | None, workers: int | None = None,
                processes: bool = True) -> Iterator[object]:
    """A ``distributed.Client``: on ``scheduler``, or on a new LocalCluster.

    Parameters
    ----------
    scheduler : str or None
        Address of a running scheduler (``tcp://host:8786``; a malformed one, one that
        cannot be reached, or one without a worker after :data:`WORKER_WAIT_SECONDS` is
        an :class:`~robustloc.errors.InputError`), or None to start a
        LocalCluster of ``workers`` single-threaded worker processes (default: the cores
        available), each limited to :data:`WORKER_MEMORY_BYTES`.
    workers : int, optional
        LocalCluster size.
    processes : bool
        LocalCluster workers as processes (default) or threads.

    The client, and the LocalCluster when one was started, are closed when the block
    exits, also on an error or an interrupt.  An interrupt (SIGINT, SIGTERM) while the
    LocalCluster starts (1-3 s) is held until it has started, then it is closed and the
    signal delivered (:func:`_signals_held`).
    """
    distributed = import_distributed()
    cluster = None
    client = None
    failed: BaseException | None = None
    restore: dict[str, int] = {}
    client_log = logging.getLogger("distributed.client")
    no_loss_noise = _NoConnectionLossTraceback()
    client_log.addFilter(no_loss_noise)
    try:
        if scheduler is not None:
            client = _connect(distributed, scheduler)
        else:
            n = workers or machine_cores()
            extra = {"env": dict(WORKER_ENV)} if processes else {}
            # the client's start and its first call to the workers too: an interrupt
            # inside distributed's synchronous calls can leave its event loop mid-way
            _quiet_scheduler(restore)
            with _signals_held() as got:
                with _sigint_blocked_in_new_threads():
                    cluster = distributed.LocalCluster(
                        n_workers=n, threads_per_worker=1, processes=processes,
                        memory_limit=WORKER_MEMORY_BYTES, dashboard_address=":0", **extra,
                    )
                client = distributed.Client(cluster)
                _quiet_worker_logs(client)
            if got:  # interrupted while it started: close it, then deliver the signal
                import signal

                _close(client, cluster, KeyboardInterrupt())
                client = cluster = None
                for signum in dict.fromkeys(got):
                    signal.raise_signal(signum)
        yield client
    except BaseException as exc:
        failed = exc
        raise
    finally:
        try:
            _close(client, cluster, failed)
        finally:  # (a signal held meanwhile is delivered at its end)
            for name, level in restore.items():
                logging.getLogger(name).setLevel(level)
            client_log.removeFilter(no_loss_noise)


def check_scheduler_address(scheduler: str) -> None:
    """Refuse a malformed ``--scheduler`` address before any connection is tried.

    Parameters
    ----------
    scheduler : str
        The address as given (``tcp://host:8786``, ``host:8786``, ``tls://...``).

    Raises
    ------
    InputError
        ``--scheduler ADDRESS: not a scheduler address (...)``: no port
        (``127.0.0.1``), an unknown scheme (``foo://h:1``), a port that is not a number.
        (distributed raised a ValueError, shown as an internal error with a traceback.)
    """
    from distributed.comm import get_address_host_port
    from distributed.comm.addressing import parse_address

    try:
        scheme, _ = parse_address(scheduler)
        if scheme != "inproc":  # (an in-process cluster's address has no host and port)
            get_address_host_port(scheduler)
    except (ValueError, TypeError) as exc:
        raise InputError(f"--scheduler {scheduler}: not a scheduler address ({exc}); "
                         "expected e.g. tcp://HOST:8786") from None


def _probe(scheduler: str) -> None:
    """Open and close one connection to a ``tcp://`` scheduler within
    :data:`CONNECT_TIMEOUT_SECONDS`, handshake included.

    ``Client(timeout=...)`` bounds the TCP connect, not the handshake's read: a port that
    accepts and never answers hung the command for good, and one that sent a banner (an
    SSH server) made distributed allocate 2.8 EiB for the frame it read (the Dask review).

    Raises
    ------
    InputError
        ``--scheduler ADDRESS: cannot connect (...)``.
    """
    import asyncio

    from distributed.comm import connect
    from distributed.comm.addressing import parse_address

    if parse_address(scheduler)[0] != "tcp":  # (tls needs its security; inproc no probe)
        return

    async def once() -> None:
        comm = await connect(scheduler, timeout=CONNECT_TIMEOUT_SECONDS)
        await comm.close()

    try:
        asyncio.run(asyncio.wait_for(once(), CONNECT_TIMEOUT_SECONDS))
    except (TimeoutError, asyncio.TimeoutError):
        raise InputError(f"--scheduler {scheduler}: cannot connect (no dask scheduler "
                         f"answered within {CONNECT_TIMEOUT_SECONDS:g} s)") from None
    except Exception as exc:  # noqa: BLE001 - whatever the address answered
        raise InputError(f"--scheduler {scheduler}: cannot connect ({type(exc).__name__}: "
                         f"{exc}; is it a dask scheduler?)") from None


def _connect(distributed: object, scheduler: str) -> object:
    """A client of the running scheduler ``scheduler`` that has at least one worker.

    Raises
    ------
    InputError
        A malformed address, a scheduler that cannot be reached, or one without a worker
        after :data:`WORKER_WAIT_SECONDS` (``--scheduler ADDRESS: no workers after N s``).
    """
    check_scheduler_address(scheduler)
    _probe(scheduler)
    try:
        client = distributed.Client(  # type: ignore[attr-defined]
            scheduler, timeout=f"{CONNECT_TIMEOUT_SECONDS:g}s")
    except Exception as exc:  # noqa: BLE001 - whatever the address answered
        # a user's mistake in every command (spp ended in a traceback here)
        raise InputError(f"--scheduler {scheduler}: cannot connect "
                         f"({type(exc).__name__}: {exc})") from None
    try:
        if not client.scheduler_info().get("workers"):  # type: ignore[attr-defined]
            print(f"note: --scheduler {scheduler} has no workers yet; waiting up to "
                  f"{WORKER_WAIT_SECONDS:g} s", file=sys.stderr)
        client.wait_for_workers(1, timeout=WORKER_WAIT_SECONDS)
    except (OSError, TimeoutError):  # (asyncio's and dask's TimeoutError are builtins')
        client.close()
        raise InputError(f"--scheduler {scheduler}: no workers after "
                         f"{WORKER_WAIT_SECONDS:g} s (start workers: dask worker "
                         f"{scheduler})") from None
    except BaseException:
        client.close()
        raise
    return client


#: distributed's loggers whose warnings a LocalCluster's workers print on the user's
#: terminal about what the command did on purpose: "Async instruction ... ended with
#: CancelledError" when a failed run cancels the tasks still running and closes them.
_QUIET_LOGGERS = ("distributed.worker.state_machine",)


#: The start of the error a worker logs, with a traceback, when its heartbeat finds the
#: scheduler gone: the command closing its own LocalCluster (on an interrupt, the
#: scheduler can go first; seen once under load, at 2.5 s in
#: ``test_interrupt_while_the_local_cluster_starts_ends_cleanly``).
_HEARTBEAT_LOST = "Failed to communicate with scheduler during heartbeat"


class _NoHeartbeatAtClose(logging.Filter):
    """Drops :data:`_HEARTBEAT_LOST` records (the command's own cluster closing); every
    other record of the worker's logger passes."""

    def filter(self, record: logging.LogRecord) -> bool:
        return not str(record.msg).startswith(_HEARTBEAT_LOST)


class _NoConnectionLossTraceback(logging.Filter):
    """Drops the ``distributed.client`` errors that come with tracebacks when the client
    loses its scheduler (its reconnection's ``CommClosedError``/``OSError``, then the
    ``CancelledError`` of its close, and "Failed to reconnect to scheduler after 20 s"):
    the command reports that loss itself, ``error: lost the dask scheduler ...`` (exit
    2).  A killed cluster printed 40 lines of three tracebacks above that line (measured
    with a real external LocalCluster)."""

    def filter(self, record: logging.LogRecord) -> bool:
        import asyncio

        exc = record.exc_info[1] if record.exc_info else None
        if isinstance(exc, (OSError, asyncio.CancelledError)):
            return False
        return not str(record.msg).startswith("Failed to reconnect to scheduler")


def _quiet_loggers() -> None:
    """Run on each worker: only errors from :data:`_QUIET_LOGGERS`, and no
    :data:`_HEARTBEAT_LOST` error from ``distributed.worker``."""
    for name in _QUIET_LOGGERS:
        logging.getLogger(name).setLevel(logging.ERROR)
    worker = logging.getLogger("distributed.worker")
    if not any(isinstance(f, _NoHeartbeatAtClose) for f in worker.filters):
        worker.addFilter(_NoHeartbeatAtClose())


#: Loggers of the scheduler, which a LocalCluster runs in the command's own process, that
#: report routine at WARNING level: the P2P shuffle's start and end, two lines per
#: shuffle of ``partition --method dask`` ("Shuffle ... initialized by task ...",
#: "... deactivated due to stimulus ..."; distributed's maintainers call them spammy,
#: dask/distributed#8358).  Only their errors are shown.
_QUIET_SCHEDULER_LOGGERS = ("distributed.shuffle._scheduler_plugin",)


def _quiet_scheduler(restore: dict[str, int]) -> None:
    """Only errors from :data:`_QUIET_SCHEDULER_LOGGERS` (their levels saved in
    ``restore``, for :func:`dask_client` to put back)."""
    for name in _QUIET_SCHEDULER_LOGGERS:
        log = logging.getLogger(name)
        restore.setdefault(name, log.level)
        log.setLevel(logging.ERROR)


def _thread_lock_for_progress_bars() -> None:
    """Run on each worker: tqdm's lock a thread lock, unless tqdm has one already.

    tqdm's first bar (also a disabled one: a task's ``locate``/``track`` loop creates one)
    makes a multiprocessing lock, a named semaphore registered with the resource tracker
    that the worker process shares with the command.  A worker busy in a task when the
    command is interrupted is killed by its nanny, its semaphore never released, and the
    tracker printed ``resource_tracker: There appear to be 2 leaked semaphore objects to
    clean up at shutdown`` below ``error: interrupted`` (the Dask review; one per worker).
    A task's bars never draw (they are disabled there) and a worker's tasks are threads.
    """
    import threading

    try:
        from tqdm import tqdm
    except ImportError:  # pragma: no cover - a dependency of robustloc
        return
    if "_lock" not in vars(tqdm):
        tqdm.set_lock(threading.RLock())


def _setup_workers() -> None:
    """Run on each worker of the command's own LocalCluster: :func:`_quiet_loggers` and
    :func:`_thread_lock_for_progress_bars`."""
    _quiet_loggers()
    _thread_lock_for_progress_bars()


def _quiet_worker_logs(client: object) -> None:
    """:func:`_setup_workers` on the workers of the command's own LocalCluster (a user's
    ``--scheduler`` workers keep their own logging and locks)."""
    try:
        client.run(_setup_workers)  # type: ignore[attr-defined]
    except Exception:  # noqa: BLE001 - only cosmetic
        pass


def _close(client: object, cluster: object, exc: BaseException | None) -> None:
    """Close ``client`` and then ``cluster`` (either may be None) after ``exc`` (None: a
    normal end), with the signals held (:func:`_cleanup_signals_held`)."""
    with _cleanup_signals_held(exc):
        try:
            if client is not None:
                client.close()  # type: ignore[attr-defined]
        finally:
            if cluster is not None:
                _close_cluster(cluster)


def _close_cluster(cluster: object) -> None:
    """Close a LocalCluster.  A worker slow to exit is killed by its nanny, which logs a
    warning the user can do nothing about; keep the terminal for the command's own
    output."""
    nanny = logging.getLogger("distributed.nanny")
    level = nanny.level
    nanny.setLevel(logging.ERROR)
    try:
        cluster.close()  # type: ignore[attr-defined]
    finally:
        nanny.setLevel(level)


@dataclass(frozen=True)
class UserFailure:
    """A user's mistake found by a task, returned as a value (not raised), so the worker
    does not log it as a crash and the client re-raises it with its file and line."""

    kind: str
    message: str
    path: str | None = None
    line: int | None = None
    filename: str | None = None

    def exception(self) -> BaseException:
        if self.kind == "input":
            return InputError(self.message, self.path, self.line)
        if self.kind == "missing":
            return FileNotFoundError(2, self.message, self.filename)
        return ValueError(self.message)


def user_errors_as_values(fn: Callable[..., object], *args: object, **kwargs: object) -> object:
    """``fn(*args, **kwargs)`` on a worker, a user's mistake returned as a UserFailure."""
    try:
        return fn(*args, **kwargs)
    except InputError as exc:
        return UserFailure("input", exc.message, exc.path, exc.line)
    except FileNotFoundError as exc:
        return UserFailure("missing", exc.strerror or "file not found", filename=exc.filename)
    except ValueError as exc:
        return UserFailure("value", str(exc))


def submit_all(client: object, fn: Callable[..., object], arg_lists: Sequence[tuple],
               **kwargs: object) -> list:
    """One task per argument tuple, each running ``fn`` through user_errors_as_values."""
    return [client.submit(user_errors_as_values, fn, *a, pure=False, **kwargs)
            for a in arg_lists]


def gather_with_progress(client: object, futures: Sequence[object], show: bool) -> list:
    """Wait for ``futures`` with dask's progress bar (on a terminal) and gather them.

    Fails fast: the first task that reports a user's mistake (a :class:`UserFailure`)
    cancels the others, and its error is raised here (an :class:`InputError` keeps the
    partition file and line); so is any other exception a task raised.
    """
    distributed = import_distributed()
    futures = list(futures)
    index = {f.key: i for i, f in enumerate(futures)}
    results: list[object] = [None] * len(futures)
    first: list[BaseException] = []

    def watch() -> None:
        try:
            for fut in distributed.as_completed(futures):
                if fut.status == "finished":
                    res = fut.result()
                    results[index[fut.key]] = res
                    if isinstance(res, UserFailure):
                        first.append(res.exception())
                elif fut.status == "error":
                    first.append(fut.exception())
                elif fut.status == "cancelled" and not first:
                    first.append(RuntimeError("a dask task was cancelled"))
                if first:
                    _cancel(client, futures)
                    return
        except BaseException as exc:  # noqa: BLE001 - reported by the main thread
            first.append(exc)
            _cancel(client, futures)

    watcher = threading.Thread(target=watch, daemon=True)
    watcher.start()
    try:
        if show and sys.stdout.isatty():
            distributed.progress(futures)
            sys.stdout.write("\n")
        watcher.join()
    except BaseException as exc:
        with _cleanup_signals_held(exc):
            _cancel(client, futures)
        raise
    if first:
        raise _cluster_failure(first[0], client) or first[0]
    return results


def _cluster_failure(exc: BaseException, client: object) -> InputError | None:
    """The cluster's own failure as an :class:`InputError` (``error: ...``, exit 2), or
    None for a task's error: workers that died (killed, or over their memory limit) or a
    scheduler lost were reported as a bug in robustloc, with a traceback (the Dask
    review)."""
    distributed = import_distributed()
    from distributed.comm.core import CommClosedError

    name = type(exc).__name__
    if isinstance(exc, distributed.KilledWorker):
        return InputError(f"the dask workers running a task died ({name}: {exc}); a worker "
                          "over its memory limit is stopped by its nanny: rerun with more "
                          "memory per worker, smaller partitions, or fewer workers")
    lost = getattr(client, "status", "running") != "running"
    if isinstance(exc, CommClosedError) or (
            isinstance(exc, RuntimeError) and "cancelled" in str(exc) and lost):
        return InputError(f"lost the dask scheduler or its workers mid-run ({name}: {exc}); "
                          "the output was not written: rerun once the cluster is back")
    return None
