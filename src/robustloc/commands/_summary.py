"""The summary that ``locate`` and ``track`` print after their output file: where it
goes, ``--json``, the anchors' warnings, ``--quiet``, the notes on the input (rows
sorted, duplicates averaged, rows outside the physical limits), the timing, and the lines
after the first, which the Dask engine prints too
(:func:`robustloc.pipelines.locate.locate_lines`,
:func:`robustloc.pipelines.track.track_lines`: one formatter for both engines)."""

from __future__ import annotations

import argparse
import json
import sys
from typing import Any, TextIO

from robustloc.pipelines.locate import input_notes  # noqa: F401 - (it lived here)


def summary_head(args: argparse.Namespace, summary: dict[str, Any]) -> TextIO | None:
    """Print what comes before a command's own summary lines; returns the stream for
    them, or None when there are none (``--json`` printed the summary, or ``--quiet``).

    The summary never goes into a data stream: to stderr when the output file is standard
    output.  The anchors' warnings go to stderr, even with ``--quiet``.
    """
    from robustloc.io.atomic import writes_to_stdout
    from robustloc.pipelines.locate import anchor_warnings

    dest = sys.stderr if writes_to_stdout(args.out) else sys.stdout
    if args.json:
        print(json.dumps(summary, indent=2), file=dest)
        return None
    for line in anchor_warnings(summary, args.anchors):
        print(f"warning: {line}", file=sys.stderr)
    return None if args.quiet else dest


def rate_text(rate: float) -> str:
    """A rate as people read it: whole numbers from 10 on, else two significant digits
    (a run that solved epochs never shows ``0``)."""
    if not rate > 0:
        return "0"
    return f"{rate:.0f}" if rate >= 10 else f"{rate:.2g}"


def timing_text(summary: dict[str, Any], rate_key: str, unit: str) -> str:
    """The summary's ``(seconds, rate)`` of the first line: the whole run's seconds, the
    share numba spent compiling kernels that were not cached (``compile_seconds``, when
    any), and ``summary[rate_key]`` in ``unit`` (a rate over the work without the
    compiling)."""
    compiling = float(summary.get("compile_seconds") or 0.0)
    text = f"{summary['seconds']:.2f} s"
    if compiling >= 0.05:
        text += f", of which {compiling:.1f} s compiling kernels"
    return f"({text}; {rate_text(float(summary.get(rate_key) or 0.0))} {unit})"
