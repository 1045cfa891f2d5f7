"""A one-line notice when numba compiles the kernels, and the time it spent doing so.

The compiled kernels (:mod:`robustloc.estimators._compiled`, :mod:`robustloc.filters._compiled`,
:mod:`robustloc.tracking._compiled`, ...) are cached on disk after their first compilation,
which takes from under a minute to several minutes.  numba compiles a kernel whenever the
cache lacks it for the argument types at hand: the first run after installing, but also
the first run of an option that needs other kernels (``track --model ca``, ``--filter
ukf``) while the others are cached.  :func:`compile_watch` therefore listens to numba's
own ``numba:compile`` events (fired only when it really compiles, never when it loads a
kernel from the cache): the notice is printed when the first kernel starts compiling,
whichever pass of the command that is, and the seconds spent compiling are counted, so
that a command can report its solving rate without them.  :func:`compile_notice` is the
earlier check of the cache files (before any work; kept for ``fuse`` and ``reproduce``).
"""

from __future__ import annotations

import os
import sys
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from importlib import import_module
from typing import Any

#: Kernels each command uses: module and numba dispatcher names.
KERNELS = {
    "positioning": ("robustloc.estimators._compiled", ("_fit_ranges", "_initial_fixes")),
    "filter": ("robustloc.filters._compiled", ("fusion_step_4_4", "fusion_step_4",
                                                "fusion_step_6")),
    "tracker": ("robustloc.tracking._compiled", ("track_round_4", "track_round_6")),
}


def needs_compile(kind: str) -> bool:
    """True when no kernel of ``kind`` has an on-disk cache index yet, i.e. on the first run
    (best effort: numba's cache layout is internal, so any surprise counts as "cached")."""
    module, names = KERNELS[kind]
    try:
        mod = import_module(module)
        return all(
            not os.path.exists(getattr(mod, n)._cache._cache_file._index_path) for n in names
        )
    except Exception:  # noqa: BLE001 - numba internals changed: say nothing
        return False


def _print_notice(kinds: tuple[str, ...]) -> None:
    what = f"the {' and '.join(kinds)} kernels" if kinds else "robustloc's kernels"
    print(f"robustloc: numba is compiling {what}, which are not in its cache yet (the "
          "first run after installing, or the first run of options that need other "
          "kernels); this takes from under a minute to several minutes, once: later runs "
          "load them from the cache ...", file=sys.stderr, flush=True)


def compile_notice(*kinds: str) -> None:
    """Print ``robustloc: numba is compiling ...`` on stderr now if no kernel of any of
    ``kinds`` is cached yet (:func:`needs_compile`); else announce the first kernel numba
    compiles later in this process (a kernel the cache lacks although others of ``kinds``
    are there) when it starts compiling.  Commands that can run their work inside
    :func:`compile_watch` use that instead: its notice comes when compiling starts."""
    todo = tuple(k for k in kinds if needs_compile(k))
    if todo:
        _print_notice(todo)
        return
    listener = _listener()
    if listener is not None:
        with listener.lock:
            listener.once = tuple(kinds)


@dataclass
class CompileWatch:
    """What numba compiled while a :func:`compile_watch` was open.

    Attributes
    ----------
    kinds : tuple of str
        The kernels the work uses, as named in the notice.
    seconds : float
        Wall-clock seconds numba spent compiling so far (0 when every kernel came from the
        cache).
    announced : bool
        The notice was printed.
    """

    kinds: tuple[str, ...]
    seconds: float = 0.0
    announced: bool = False


class _CompileListener:
    """One listener of numba's ``numba:compile`` events for the process (registered on
    first use): the open watches' notice and compile time.  numba holds its compiler
    lock while it fires the events; ``lock`` guards the watches against the thread that
    opens and closes them."""

    def __init__(self) -> None:
        self.lock = threading.Lock()
        self.watches: list[CompileWatch] = []
        self.once: tuple[str, ...] | None = None  # compile_notice's deferred notice
        self.depth = 0
        self.t0 = 0.0

    def on_start(self, event: Any) -> None:
        if self.depth == 0:
            self.t0 = time.perf_counter()
            with self.lock:
                watches, once = list(self.watches), self.once
            ours = _is_robustloc(event)
            if ours and (once is not None or (watches and not any(w.announced
                                                                   for w in watches))):
                _print_notice(watches[0].kinds if watches else once or ())
                with self.lock:
                    self.once = None
                    for w in self.watches:
                        w.announced = True
        self.depth += 1

    def on_end(self, event: Any) -> None:
        self.depth = max(self.depth - 1, 0)
        if self.depth == 0:
            dt = time.perf_counter() - self.t0
            with self.lock:
                for w in self.watches:
                    w.seconds += dt


def _is_robustloc(event: Any) -> bool:
    """The event compiles a robustloc kernel (best effort: unknown -> True)."""
    try:
        return str(event.data["dispatcher"].py_func.__module__).startswith("robustloc.")
    except Exception:  # noqa: BLE001 - numba internals changed
        return True


_LISTENER: list[_CompileListener | None] = []


def _listener() -> _CompileListener | None:
    """The process's :class:`_CompileListener`, registered with numba on first use; None
    when numba's event API is not there (the notice then falls back to the cache files)."""
    if not _LISTENER:
        try:
            from numba.core import event

            class _Adapter(event.Listener):
                def __init__(self, target: _CompileListener) -> None:
                    self.target = target

                def on_start(self, ev: Any) -> None:
                    self.target.on_start(ev)

                def on_end(self, ev: Any) -> None:
                    self.target.on_end(ev)

            lis = _CompileListener()
            event.register("numba:compile", _Adapter(lis))
            _LISTENER.append(lis)
        except Exception:  # noqa: BLE001 - no numba event API: say what the files say
            _LISTENER.append(None)
    return _LISTENER[0]


@contextmanager
def compile_watch(*kinds: str, announce: bool = True) -> Iterator[CompileWatch]:
    """Watch numba while the work inside runs: the notice on stderr when it starts
    compiling a robustloc kernel the cache lacks (once per watch, whichever kernel and
    pass comes first; nothing when every kernel is cached), and the seconds it spends
    compiling (:attr:`CompileWatch.seconds`, readable during the work).

    Parameters
    ----------
    *kinds : str
        The kernels the work uses (keys of :data:`KERNELS`, or any words), named in the
        notice.
    announce : bool
        Print the notice (False: ``--quiet``, or a library call: the seconds are still
        counted).

    Yields
    ------
    CompileWatch
        ``seconds`` and ``announced``.  A watch opened inside another shares its notice
        (one per run).  Without numba's event API, :func:`compile_notice` is printed
        before the work and ``seconds`` stays 0.
    """
    watch = CompileWatch(tuple(kinds))
    listener = _listener()
    if listener is None:
        if announce:
            compile_notice(*(k for k in kinds if k in KERNELS))
        yield watch
        return
    with listener.lock:
        # (a silent watch counts as announced: the listener prints for no watch of it)
        watch.announced = not announce or any(w.announced for w in listener.watches)
        listener.watches.append(watch)
    try:
        yield watch
    finally:
        with listener.lock:
            listener.watches.remove(watch)
