"""What the scenarios share to write their files: the memory budget, the progress bar and
chunked CSV writing (not a scenario: :func:`robustloc.sim.scenario_modules` skips it).

A scenario either generates its files in chunks and streams them to disk (``gnss``: its
output grows with ``--epochs`` and is meant to be big, so its memory does not) or, where
the draws are whole arrays (``wifi-room``: AR(1) noise along each link, the log sorted by
time), refuses before any work a size whose memory exceeds :data:`MEMORY_BUDGET_BYTES`
(the second simulate review: ``wifi-room --samples-per-point 1000000`` ended in a
MemoryError traceback; ``gnss --epochs 1000000`` ran for twenty minutes without a sign
of progress, holding every epoch's frame).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

import pandas as pd

#: Memory a scenario may take for the arrays and frames of one run, bytes (1 GiB).
MEMORY_BUDGET_BYTES = 2**30

#: Rows of a frame written at once by :func:`write_csv` (a progress bar step).
WRITE_CHUNK_ROWS = 200_000


def _size(n_bytes: float) -> str:
    """``1 GiB``, ``340 MiB``: a size for a message (``%g``-style, never 300 digits)."""
    for unit, scale in (("GiB", 2**30), ("MiB", 2**20), ("KiB", 2**10)):
        if n_bytes >= scale:
            return f"{n_bytes / scale:.4g} {unit}"
    return f"{n_bytes:.4g} bytes"


def check_memory(needed_bytes: float, option: str, value: float, at_most: float,
                 what: str, budget: float | None = None) -> None:
    """Refuse a run whose memory exceeds the budget, naming the option and its limit.

    Parameters
    ----------
    needed_bytes : float
        The run's estimated peak memory (rows times bytes per row).
    option : str
        The option to blame, e.g. ``"--samples-per-point"``.
    value : float
        Its value.
    at_most : float
        The largest value of ``option`` within the budget (the other options as given).
    what : str
        What the rows are, for the message (``"80000000 rows"``).
    budget : float, optional
        Bytes allowed; default :data:`MEMORY_BUDGET_BYTES` (read when called, so a test
        can lower it).

    Raises
    ------
    robustloc.errors.InputError
        ``--option: VALUE gives WHAT, about 11.9 GiB of memory, over the 1 GiB a
        simulation may take: at most LIMIT``.
    """
    from robustloc.errors import InputError

    limit = MEMORY_BUDGET_BYTES if budget is None else budget
    if needed_bytes <= limit:
        return
    shown = f"{value:d}" if isinstance(value, int) else f"{value:g}"
    raise InputError(f"{option}: {shown} gives {what}, about {_size(needed_bytes)} of "
                     f"memory, over the {_size(limit)} a simulation may take: at most "
                     f"{max(int(at_most), 0):d}")


def progress_bar(args: argparse.Namespace, total: int, unit: str, desc: str) -> Any:
    """A tqdm bar on stderr, as the other commands draw it: only on a terminal, and not
    with ``-q`` (``args.quiet``; a namespace without it draws)."""
    from tqdm import tqdm

    return tqdm(total=total, unit=unit, desc=desc, unit_scale=True, file=sys.stderr,
                disable=bool(getattr(args, "quiet", False)) or not sys.stderr.isatty())


def write_csv(frame: pd.DataFrame, path: Path, bar: Any = None,
              rows: int = WRITE_CHUNK_ROWS, **to_csv: Any) -> Path:
    """Write ``frame`` as CSV in chunks of ``rows`` rows, advancing ``bar`` by the rows
    written; the file is the one ``frame.to_csv(path, index=False, **to_csv)`` writes."""
    with open(path, "w", newline="", encoding="utf-8") as fh:
        if frame.empty:
            frame.to_csv(fh, index=False, **to_csv)
        for start in range(0, len(frame), rows):
            part = frame.iloc[start:start + rows]
            part.to_csv(fh, index=False, header=start == 0, **to_csv)
            if bar is not None:
                bar.update(len(part))
    return path
