"""Standard error as a test compares it, without numba's one-time compile notice.

``robustloc: numba is compiling ...`` (:mod:`robustloc._jitnotice`) is printed by the
first command of a process that compiles a kernel its cache lacks: which test that is
depends on the order the tests run in (under ``pytest -n``, each worker's first).  A
test that compares a command's whole stderr compares it without that line."""

from __future__ import annotations

NOTICE = "robustloc: numba is compiling "


def without_jit_notice(err: str) -> str:
    """``err`` without the compile notice's line(s)."""
    return "".join(line for line in err.splitlines(keepends=True)
                   if not line.startswith(NOTICE))
