"""Simulation scenarios, one module each, discovered by ``robustloc simulate``.

A scenario module exposes

* ``NAME`` (str, e.g. ``"ble-corridor"``), ``HELP`` (one line),
* ``add_arguments(parser)`` for its own options,
* ``simulate(out_dir: Path, seed: int, args: argparse.Namespace) -> dict[str, Path]``
  which writes the contract files (``anchors.csv``, ``measurements.csv``, ``truth.csv``,
  ``survey.csv`` where calibration applies, ...) and returns them by name,
* optionally ``refuse_idle_options(args)``, which raises
  :class:`robustloc.errors.InputError` for an option that the other options make idle
  (``robustloc simulate`` calls it before any work).

Scenarios sample from the same measurement models the estimators use.
"""

from __future__ import annotations

import importlib
import pkgutil


def scenario_modules() -> dict:
    """Discovered scenario modules by ``NAME``."""
    import robustloc.sim as pkg

    out = {}
    for info in pkgutil.iter_modules(pkg.__path__):
        if info.name.startswith("_"):
            continue
        mod = importlib.import_module(f"robustloc.sim.{info.name}")
        if hasattr(mod, "NAME") and hasattr(mod, "simulate"):
            out[mod.NAME] = mod
    return dict(sorted(out.items()))
