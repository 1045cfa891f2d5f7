"""Command-line entry point ``robustloc``.

Each subcommand lives in its own module under :mod:`robustloc.commands` and exposes

* ``NAME`` (str), ``HELP`` (one line),
* ``add_arguments(parser)`` and ``run(args) -> int``.

Modules are discovered automatically, so adding a command touches no shared file.
One error path:

* a user's mistake (:class:`~robustloc.errors.InputError`, including
  :class:`~robustloc.errors.OutputError`, or an :class:`OSError` about a path the user gave:
  missing file, permission, no space, read-only file system, a parent that is a file) prints
  ``error: FILE[:LINE]: what`` on stderr and exits with code 2, never a traceback;
* Ctrl-C prints ``error: interrupted`` and exits with 130, SIGTERM ``error: terminated``
  and 143 (128 + signal number); in both cases ``finally`` blocks run, so no partial
  output is left at a final path;
* any other exception is a bug in robustloc, not the user's fault: it prints
  ``internal error`` with the traceback and exits with code 1 (never 2, so that a bug
  does not pass for a user error).  One transitional exception: a ``ValueError`` raised
  by a command module itself (its own option check, innermost frame in
  ``robustloc/commands/``) is still a user error; from any lower layer it is a bug;
* output piped into ``head`` and closed early is not an error (exit 0).
"""

from __future__ import annotations

import argparse
import importlib
import pkgutil
import re
import sys
import warnings
from collections.abc import Callable, Sequence
from typing import Any

from robustloc import __version__
from robustloc.errors import (  # noqa: F401 - the exit codes are also this module's
    EXIT_INTERNAL,
    EXIT_SIGINT,
    EXIT_SIGTERM,
    EXIT_USER,
    InputError,
    Terminated,
)


def _command_modules(only: str | None = None) -> list:
    """Command modules; ``only`` (a module name) imports just that one, so running a
    command does not pay for importing every other command's dependencies."""
    import robustloc.commands as pkg

    mods = []
    names = [i.name for i in pkgutil.iter_modules(pkg.__path__) if not i.name.startswith("_")]
    if only is not None and only.replace("-", "_") in names:
        names = [only.replace("-", "_")]
    for name in sorted(names):
        mod = importlib.import_module(f"robustloc.commands.{name}")
        if hasattr(mod, "NAME") and hasattr(mod, "run"):
            mods.append(mod)
    order = getattr(pkg, "ORDER", [])
    mods.sort(key=lambda m: (order.index(m.NAME) if m.NAME in order else len(order), m.NAME))
    return mods


#: A negative number, or a comma-separated list that starts with one (``-1,3``,
#: ``-5,10,0,8``, ``-1e4``): what a command line means as an option's value.
NEGATIVE_NUMBERS = re.compile(
    r"^-(\d+\.?\d*|\.\d+)([eE][-+]?\d+)?"
    r"(,\s*[-+]?(\d+\.?\d*|\.\d+)([eE][-+]?\d+)?)*$")


def build_parser(only: str | None = None) -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="robustloc",
        description="Robust positioning from RSSI, ranges, NMEA and GNSS pseudoranges.",
    )
    parser.add_argument("--version", action="version", version=f"robustloc {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for mod in _command_modules(only):
        p = sub.add_parser(
            mod.NAME,
            help=mod.HELP,
            description=getattr(mod, "DESCRIPTION", mod.HELP),
            formatter_class=argparse.RawDescriptionHelpFormatter,
        )
        mod.add_arguments(p)
        p.set_defaults(_run=mod.run)
    _numbers_are_values(parser)
    return parser


def _numbers_are_values(parser: argparse.ArgumentParser) -> None:
    """In ``parser`` and every parser under it (``simulate gnss``), a value that starts
    with a minus is a value, not an option, when it reads as numbers: ``--position
    -1,3``, ``--area -5,10,0,8`` and ``--height -1e4`` were refused as "expected one
    argument" (argparse reads only a plain negative number so; ``=`` was needed: the
    simulate/montecarlo review, 2026-12-06)."""
    parser._negative_number_matcher = NEGATIVE_NUMBERS
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for child in dict.fromkeys(action.choices.values()):
                _numbers_are_values(child)


def _parse(parser: argparse.ArgumentParser, argv: list[str],
           command: str | None) -> argparse.Namespace:
    """Parse ``argv``; a command's positional given after its options is still read.

    ``robustloc spp OBS --raim NAV`` was refused as "unrecognized arguments: NAV": argparse
    fills a positional from the first run of positionals only.  When something is left
    over, the command's own parser reads the line again intermixed (positionals anywhere
    among the options), and reports only what is still left over.
    """
    args, extra = parser.parse_known_args(argv)
    if not extra:  # the usual case: parsed once
        return args
    if command is None or command not in argv:
        return parser.parse_args(argv)  # argparse's own message for what is left over
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    own = sub.choices[command]
    try:
        ns = own.parse_intermixed_args(argv[argv.index(command) + 1:])
    except TypeError:  # a parser intermixed parsing does not support (argparse's rule)
        return parser.parse_args(argv)
    for key, value in vars(args).items():
        if not hasattr(ns, key):
            setattr(ns, key, value)
    return ns


#: The options (by ``dest``) that name an input file, of every command: standard input
#: can feed one of them (:func:`_one_stdin_input`).
_INPUT_DESTS = frozenset({
    "measurements", "anchors", "truth", "positions", "survey", "self_log", "ranges", "nmea",
    "candidates", "obs", "nav", "sp3", "clk", "input", "scale_from", "floorplan"})


def _one_stdin_input(parser: argparse.ArgumentParser, args: argparse.Namespace) -> None:
    """Refuse ``-`` (standard input) given for two inputs of the command, naming both.

    Standard input is one stream.  Every input named ``-`` read the first one's copy:
    ``evaluate - --truth -`` compared the positions with themselves and exited 0 with
    every error 0; ``calibrate --self - --anchors -`` blamed the anchors for the
    measurements' columns (the input review).  Checked before anything is read, so the
    message names the options, not whichever file was read first.
    (:func:`robustloc.io.tables._claim_stdin` refuses it in the library as well.)

    Raises
    ------
    InputError
        ``<stdin>: standard input is already read as another input of this command
        (FIRST), so SECOND cannot also be - (...)``.
    """
    sub = next((a for a in parser._actions if isinstance(a, argparse._SubParsersAction)),
               None)
    own = None if sub is None else sub.choices.get(getattr(args, "command", None) or "")
    if own is None:
        return
    named = []
    for action in own._actions:
        if action.dest not in _INPUT_DESTS:
            continue
        value = getattr(args, action.dest, None)
        values = value if isinstance(value, (list, tuple)) else [value]
        for v in values:
            if isinstance(v, str) and v == "-":
                longs = [o for o in action.option_strings if o.startswith("--")]
                named.append(longs[0] if longs else str(action.metavar or action.dest.upper()))
    if len(named) > 1:
        second = named[1] if named[1] != named[0] else f"a second {named[1]}"
        raise InputError(
            f"standard input is already read as another input of this command "
            f"({named[0]}), so {second} cannot also be - (one input per command can "
            "come from standard input: give the other one as a file)", "<stdin>")


def error(message: str) -> int:
    """Print ``error: message`` on stderr and return exit code 2."""
    print(f"error: {message}", file=sys.stderr)
    return 2


#: The signals received during the current command (SIGINT, SIGTERM numbers): a library
#: that catches the exception a handler raises and raises its own (DuckDB: "RuntimeError:
#: Query interrupted") still leaves the run marked as interrupted (:func:`_signalled`).
_received: list[int] = []
#: The timers of :func:`_deliver_later` not yet known to be done: cancelled and joined
#: when the command ends (:func:`_restore_sigterm`).  One that fired after the command had
#: printed ``error: interrupted`` and restored Python's own SIGINT handler raised a
#: KeyboardInterrupt during the interpreter's exit: the process died of SIGINT (status
#: -2, not 130; seen once in the full suite run in two workers).
_redeliver: list[Any] = []


def _deliver_later(signum: int) -> None:
    """Send ``signum`` again to the main thread in 50 ms (out of the callback by then; a
    real signal, so that a blocking call of the main thread is woken as by the first)."""
    import signal
    import threading

    t = threading.Timer(0.05, signal.pthread_kill, args=(threading.main_thread().ident, signum))
    t.daemon = True
    _redeliver.append(t)
    t.start()


def _raise_terminated(signum: int, frame: object) -> None:
    _received.append(signum)
    raise Terminated()


def _raise_interrupt(signum: int, frame: object) -> None:
    _received.append(signum)
    raise KeyboardInterrupt()


def _unraisable(hook: Callable[[Any], None]) -> Callable[[Any], None]:
    """``sys.unraisablehook`` that sends an interrupt raised where it cannot propagate
    again, once out of there, and leaves everything else to ``hook``.

    A signal's handler runs wherever the main thread is: inside a callback from C (numba
    compiling: llvmlite's object cache; distributed's garbage-collection callback), the
    ``KeyboardInterrupt`` it raises was printed as "Exception ignored ..." with a
    traceback, and dropped (the full suite, an interrupt while ``--engine dask``
    started)."""
    import signal

    def hook_(unraisable: Any) -> None:
        exc = getattr(unraisable, "exc_value", None)
        if isinstance(exc, KeyboardInterrupt | Terminated):
            _deliver_later(signal.SIGINT if isinstance(exc, KeyboardInterrupt)
                           else signal.SIGTERM)
            return
        hook(unraisable)

    return hook_


def _install_sigterm() -> object:
    """SIGTERM raises :class:`Terminated`, SIGINT :class:`KeyboardInterrupt`, both noted in
    :data:`_received` (main thread only), an interrupt raised where it cannot propagate
    sent again (:func:`_unraisable`); returns the old handlers and hook."""
    import signal
    import threading

    _received.clear()
    if threading.current_thread() is not threading.main_thread():
        return None
    old_hook = sys.unraisablehook
    sys.unraisablehook = _unraisable(old_hook)
    old_int = signal.getsignal(signal.SIGINT)
    # (a SIGINT ignored by the parent, as for a background job of a shell, stays ignored)
    if old_int is signal.default_int_handler:
        signal.signal(signal.SIGINT, _raise_interrupt)
    return signal.signal(signal.SIGTERM, _raise_terminated), old_int, old_hook


def _restore_sigterm(old: object) -> None:
    """End the command's signal handling: re-deliveries of :func:`_deliver_later` still
    due are dropped and one under way is waited for (its interrupt, raised here, is
    dropped too: the command has returned, its result and exit code stand), then the old
    handlers and hook are put back."""
    # (until none is left: one that an interrupt dropped during the join sends again
    # (the hook is still installed) is appended while this runs; cancel and join are
    # idempotent: an interrupt here starts the pass again)
    while _redeliver:
        pending = list(_redeliver)
        try:
            for t in pending:
                t.cancel()
            for t in pending:
                t.join()
        except (KeyboardInterrupt, Terminated):
            continue
        for t in pending:
            _redeliver.remove(t)
    _restore_handlers(old)


#: Set by :func:`entry` (the process ends with the command): an interrupted command's
#: end ignores SIGINT and SIGTERM instead of putting Python's own handlers back.  With
#: them back, a signal landing before :func:`entry` could ignore it (the re-sent one of
#: :func:`_deliver_later`, or one more from the user) raised a KeyboardInterrupt where
#: nothing caught it, and the process died of SIGINT after printing ``error:
#: interrupted`` (status -2, not 130: the full suite, ``test_reproduce_atomic``, a third
#: time after the two guards of :func:`entry`).
_exit_after_command = False


def _restore_handlers(old: object) -> None:
    import signal

    interrupted = bool(_received)
    _received.clear()
    if old is not None:
        term, intr, hook = old  # type: ignore[misc]
        if _exit_after_command and interrupted:  # (first: no window with Python's own)
            signal.signal(signal.SIGINT, signal.SIG_IGN)
            signal.signal(signal.SIGTERM, signal.SIG_IGN)
        else:
            signal.signal(signal.SIGTERM, term)
            signal.signal(signal.SIGINT, intr)
        sys.unraisablehook = hook


def _oserror_path(exc: OSError) -> str | None:
    name = exc.filename if exc.filename is not None else exc.filename2
    return None if name is None else str(name)


def main(argv: Sequence[str] | None = None) -> int:
    """Run the command line; returns the process exit code."""
    try:
        code = _main(argv)
    except KeyboardInterrupt:  # while the libraries load, before the command's handlers
        print("error: interrupted", file=sys.stderr)
        code = EXIT_SIGINT
    if code in (EXIT_SIGINT, EXIT_SIGTERM):
        _quiet_after_interrupt()
    return code


def _quiet_after_interrupt() -> None:
    """After ``error: interrupted`` / ``terminated``, the event loop of a Dask client
    torn down mid-run logs its tasks' exceptions as the process exits ("Task exception
    was never retrieved ... distributed.client.AllExit", a traceback after the one line
    the interrupt promises: the partition review, 2026-12-07): those loggers are
    silenced for the exit."""
    import logging

    for name in ("asyncio", "distributed", "tornado"):
        logging.getLogger(name).setLevel(logging.CRITICAL + 1)


def entry() -> int:
    """The process's entry point (the ``robustloc`` script, ``python -m robustloc.cli``):
    :func:`main`, and after an interrupted command SIGINT and SIGTERM ignored, since the
    process exits with the code it printed.  A signal that arrived, or was re-sent
    (:func:`_deliver_later`), after the command had returned met Python's own handler
    again and killed the process during its exit (status -2, not 130, after ``error:
    interrupted``: the full suite, ``test_reproduce_atomic``, 2026-12-07).  Programs that
    call :func:`main` keep their handlers (an ignored SIGINT is inherited by every
    process they start)."""
    import signal
    import threading

    global _exit_after_command
    _exit_after_command = True
    try:
        code = main()
    except KeyboardInterrupt:
        # the re-sent SIGINT landing between main's return and the SIG_IGN below (its
        # "error: interrupted" already printed): status -2 in the full suite again,
        # test_reproduce_atomic, 2026-12-07 (second time)
        code = EXIT_SIGINT
    if code in (EXIT_SIGINT, EXIT_SIGTERM) and (
            threading.current_thread() is threading.main_thread()):
        for sig in (signal.SIGINT, signal.SIGTERM):
            signal.signal(sig, signal.SIG_IGN)
    return code


def _main(argv: Sequence[str] | None) -> int:
    import os

    from robustloc.io.atomic import describe_oserror

    warnings.filterwarnings("ignore", category=FutureWarning)
    warnings.filterwarnings("ignore", category=DeprecationWarning)
    argv = list(sys.argv[1:] if argv is None else argv)
    first = next((a for a in argv if not a.startswith("-")), None)
    parser = build_parser(first)
    try:  # argparse's own errors (unknown option, a refused value) exit with code 2
        args = _parse(parser, argv, first)
    except SystemExit as exc:
        return exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 2)
    if not getattr(args, "_run", None):
        parser.print_help()
        return 2
    if getattr(args, "engine", None) == "local":  # options of the dask engine, given alone
        given = [o for o, v in (("--scheduler", getattr(args, "scheduler", None)),
                                ("--workers", getattr(args, "workers", None))) if v is not None]
        if given:
            verb = "apply" if len(given) > 1 else "applies"
            return error(f"{' and '.join(given)} only {verb} with --engine dask")
    old = _install_sigterm()
    try:
        from robustloc.io.tables import spool_scope

        _one_stdin_input(parser, args)
        with spool_scope():  # standard input / a FIFO: copied once for the command
            return int(args._run(args) or 0)
    except InputError as exc:
        if _received and (code := _signalled(exc)) is not None:  # (a wrapped interrupt)
            return code
        return error(str(exc))
    except KeyboardInterrupt:
        print("error: interrupted", file=sys.stderr)
        return EXIT_SIGINT
    except Terminated:
        print("error: terminated", file=sys.stderr)
        return EXIT_SIGTERM
    except BrokenPipeError:  # output piped into `head` and closed: not an error
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        return 0
    except OSError as exc:
        if (code := _signalled(exc)) is not None:
            return code
        name = _oserror_path(exc)
        if name is None:  # an OS error about no path the user gave: a bug
            return _internal_error()
        return error(f"{name}: {describe_oserror(exc)}")
    except ValueError as exc:
        if (code := _signalled(exc)) is not None:
            return code
        if _raised_by_command_module(exc):  # a command's own check of its options
            return error(str(exc))
        return _internal_error()
    except Exception as exc:  # noqa: BLE001 - anything else is a bug, shown as one
        if (code := _signalled(exc)) is not None:
            return code
        return _internal_error()
    finally:
        _restore_sigterm(old)


def _signalled(exc: BaseException) -> int | None:
    """The exit code of an interrupt that a library turned into another exception.

    A signal handled while a library runs its own Python code can surface wrapped: a
    SIGINT that lands while numba loads a cached kernel (its ``_numba_unpickle``) reaches
    the command as numba's error with the ``KeyboardInterrupt`` as its cause or context
    (seen in ``tests/test_noloss_outputs.py``); DuckDB drops it and raises "Query
    interrupted" (the no-loss review): the handlers note every signal in
    :data:`_received`.  Such a run was interrupted, not a bug: ``error: interrupted`` /
    ``terminated`` and exit 130 / 143.  None when no interrupt is in ``exc``'s chain and
    no signal was noted.
    """
    seen: set[int] = set()
    e: BaseException | None = exc
    while e is not None and id(e) not in seen:
        seen.add(id(e))
        if isinstance(e, KeyboardInterrupt):
            print("error: interrupted", file=sys.stderr)
            return EXIT_SIGINT
        if isinstance(e, Terminated):
            print("error: terminated", file=sys.stderr)
            return EXIT_SIGTERM
        e = e.__cause__ or e.__context__
    import signal

    if signal.SIGTERM in _received:  # the interrupt was swallowed by a library (DuckDB)
        print("error: terminated", file=sys.stderr)
        return EXIT_SIGTERM
    if signal.SIGINT in _received:
        print("error: interrupted", file=sys.stderr)
        return EXIT_SIGINT
    return None


def _raised_by_command_module(exc: BaseException) -> bool:
    """True if ``exc`` was raised in a command module itself (``robustloc/commands/``),
    i.e. by the command's own check of its options, not from deep inside the library.

    Transitional: commands should raise :class:`~robustloc.errors.InputError`; a
    ``ValueError`` from any lower layer is a bug and exits with code 1.
    """
    import os

    tb = exc.__traceback__
    last = None
    while tb is not None:
        last = tb
        tb = tb.tb_next
    if last is None:
        return False
    path = os.path.normpath(last.tb_frame.f_code.co_filename)
    return os.path.join("robustloc", "commands") + os.sep in path


def _internal_error() -> int:
    """Print ``internal error`` and the traceback (a bug in robustloc); exit code 1."""
    import traceback

    print("internal error (a bug in robustloc, please report it with this traceback):",
          file=sys.stderr)
    traceback.print_exc(file=sys.stderr)
    return EXIT_INTERNAL


if __name__ == "__main__":  # pragma: no cover
    sys.exit(entry())
