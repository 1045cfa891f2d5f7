"""The summary that ``locate`` and ``track`` print after their output file: where it
goes, ``--json``, the anchors' warnings, ``--quiet``, and the notes on the input (rows
sorted, duplicates averaged, rows outside the physical limits)."""

from __future__ import annotations

import argparse
import json
import sys
from typing import Any, TextIO


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


def input_notes(summary: dict[str, Any]) -> list[str]:
    """The summary's lines on the input rows (each indented by two spaces)."""
    lines = []
    if summary.get("sorted_first"):  # (the Dask engine's summary has no such key)
        lines.append("  rows were not in epoch order: sorted by time and tag first")
    if summary.get("duplicates_merged"):
        lines.append(f"  {summary['duplicates_merged']} duplicate rows (same epoch and "
                     "anchor) averaged")
    if summary.get("invalid_measurement_rows"):
        lines.append(f"  invalid_measurement: {summary['invalid_measurement_rows']} rows "
                     "(outside the physical limits of robustloc.io.limits; not used)")
    return lines
