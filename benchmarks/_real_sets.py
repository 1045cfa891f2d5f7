"""The command line and the epochs shared by the benchmarks that score variants on every
shared real data set, on the epochs of the report's section ``s05_out_of_box`` (every
k-th epoch, at most :data:`MAX_ROWS` per set): ``--data``, ``--sets``, ``-o``."""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pandas as pd

from robustloc.eval.realdata import CASES, load_cases
from robustloc.paths import default_data_dir

MAX_ROWS = 1500  # as the report's s05 section


def cases(doc: str, argv: list[str] | None) -> tuple[argparse.Namespace, Iterator]:
    """The parsed options and ``(case, rows)`` of each data set asked for (``rows``: the
    report's epochs); the time each took goes to stderr when the next is asked for."""
    ap = argparse.ArgumentParser(description=doc.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", type=Path, default=None,
                    help="real-data folder (default ../shared/data; else the excerpts)")
    ap.add_argument("--sets", default=None,
                    help=f"comma-separated data sets (default all: {', '.join(CASES)})")
    ap.add_argument("-o", "--out", type=Path, default=None, help="also write the table (CSV)")
    args = ap.parse_args(argv)
    data = args.data if args.data is not None else default_data_dir()
    only = None if args.sets is None else [s.strip() for s in args.sets.split(",")]
    if only is not None and set(only) - set(CASES):
        ap.error(f"unknown data set(s) {sorted(set(only) - set(CASES))}; choose from {CASES}")

    def each() -> Iterator:
        for case in load_cases(data, only=only):
            t0 = time.perf_counter()
            N = len(case.time)
            yield case, np.arange(0, N, max(1, int(np.ceil(N / MAX_ROWS))))
            print(f"  {case.name}: {time.perf_counter() - t0:.1f} s", file=sys.stderr)

    return args, each()


def show(table: list[dict], out: Path | None, digits: str = ".4g") -> None:
    """Print the table (and write it to ``out`` as CSV)."""
    df = pd.DataFrame(table)
    with pd.option_context("display.width", 200, "display.max_rows", 200):
        print(df.to_string(index=False, float_format=lambda v: f"{v:{digits}}"))
    if out is not None:
        df.to_csv(out, index=False)
