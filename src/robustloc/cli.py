"""Command-line entry point ``robustloc``.

Each subcommand lives in its own module under :mod:`robustloc.commands` and exposes

* ``NAME`` (str), ``HELP`` (one line),
* ``add_arguments(parser)`` and ``run(args) -> int``.

Modules are discovered automatically, so adding a command touches no shared file.
User errors (:class:`~robustloc.errors.InputError`, ``ValueError``, missing files) print
``error: ...`` on stderr and exit with code 2, never a traceback.
"""

from __future__ import annotations

import argparse
import importlib
import pkgutil
import sys
import warnings
from collections.abc import Sequence

from robustloc import __version__
from robustloc.errors import InputError


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
    return parser


def error(message: str) -> int:
    """Print ``error: message`` on stderr and return exit code 2."""
    print(f"error: {message}", file=sys.stderr)
    return 2


def main(argv: Sequence[str] | None = None) -> int:
    """Run the command line; returns the process exit code."""
    warnings.filterwarnings("ignore", category=FutureWarning)
    warnings.filterwarnings("ignore", category=DeprecationWarning)
    argv = list(sys.argv[1:] if argv is None else argv)
    first = next((a for a in argv if not a.startswith("-")), None)
    parser = build_parser(first)
    args = parser.parse_args(argv)
    if not getattr(args, "_run", None):
        parser.print_help()
        return 2
    try:
        return int(args._run(args) or 0)
    except InputError as exc:
        return error(str(exc))
    except FileNotFoundError as exc:
        name = exc.filename if exc.filename is not None else str(exc)
        return error(f"{name}: file not found")
    except IsADirectoryError as exc:
        return error(f"{exc.filename}: is a directory, expected a file")
    except PermissionError as exc:
        return error(f"{exc.filename}: permission denied")
    except ValueError as exc:
        return error(str(exc))
    except KeyboardInterrupt:
        return error("interrupted")
    except BrokenPipeError:  # output piped into `head` and closed: not an error
        import os

        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
