"""A one-line notice before numba compiles the kernels (the first run after installing).

The compiled kernels (:mod:`robustloc.estimators._compiled`, :mod:`robustloc.filters._compiled`)
are cached on disk after their first compilation, which takes 15-40 s.  A command that is
about to use them calls :func:`compile_notice` so the user knows why the first run pauses.
"""

from __future__ import annotations

import os
import sys
from importlib import import_module

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


def compile_notice(*kinds: str) -> None:
    """Print ``robustloc: compiling ...`` on stderr if any of ``kinds`` is not cached yet."""
    todo = [k for k in kinds if needs_compile(k)]
    if todo:
        print(f"robustloc: compiling the {' and '.join(todo)} kernels (first run after "
              "installing, 15-40 s; cached for later runs) ...", file=sys.stderr, flush=True)
