"""robustloc: robust positioning from noisy radio measurements.

Batched estimators (linearized LS, WLS, Gauss-Newton, robust IRLS, LEGE), integrity
statistics (global test, w-test data snooping, B-method, reliability), Kalman filters and
GNSS single-point positioning, with a command line (``robustloc --help``).

The DataFrame-level API (:mod:`robustloc.api`) is exported here and loaded on first use,
so that ``import robustloc`` stays fast (``benchmarks/bench_import.py`` measures it)::

    import robustloc
    positions = robustloc.locate("measurements.csv", "anchors.csv")
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from robustloc.errors import InputError

if TYPE_CHECKING:  # the static view of the lazy names below
    __version__: str
    from robustloc.api import (
        calibrate,
        evaluate,
        locate,
        read_anchors,
        read_measurements,
        read_positions,
        read_truth,
        spp,
        track,
        write_positions,
    )


__all__ = [
    "InputError",
    "__version__",
    "calibrate",
    "evaluate",
    "locate",
    "read_anchors",
    "read_measurements",
    "read_positions",
    "read_truth",
    "spp",
    "track",
    "write_positions",
]


#: Names loaded from :mod:`robustloc.api` on first access.
_API = frozenset(__all__) - {"InputError", "__version__"}


def _version() -> str:
    """The installed distribution's version (``importlib.metadata``), the one source."""
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("robustloc")
    except PackageNotFoundError:  # pragma: no cover - a source tree that was never installed
        return "0+unknown"


def __getattr__(name: str) -> Any:
    if name == "__version__":
        value: Any = _version()
    elif name in _API:  # loaded on first access (PEP 562 module ``__getattr__``)
        from robustloc import api

        value = getattr(api, name)
    else:
        raise AttributeError(f"module 'robustloc' has no attribute {name!r}")
    globals()[name] = value  # later look-ups skip this function
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))
