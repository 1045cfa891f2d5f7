"""``robustloc evaluate POSITIONS --truth TRUTH``: error statistics per tag and method."""

from __future__ import annotations

import argparse
import json
from typing import TextIO

import numpy as np
import pandas as pd

from robustloc.engines import add_engine_arguments
from robustloc.errors import InputError

NAME = "evaluate"
HELP = "error statistics of positions against truth, per tag and method"
DESCRIPTION = """\
Matches each position to the truth of its tag at the same time (--time-tolerance) and
reports, per tag and method, over the epochs with a usable fix: max, min, mean, RMS (the
paper's sigma0), spread sigma1, median and 95th percentile of the horizontal error (and
the 3-D error when both files have z: over the n_ok_3d usable fixes with a z, as the
vertical bound's columns below; a fix whose z is empty -- a 2-D method beside 3-D ones --
counts in the horizontal statistics only, and a method without any z has empty 3-D
columns, null in --json), the number of failed epochs (status not usable, no
coordinates, or missing: a truth epoch without a positions row of the method), and the
improvement of mean and RMS over the `ls` method (--baseline) in %, 100 (ls - method) /
ls: columns mean_impr_pct and rms_impr_pct in every output (empty, null in --json, when
the file has no such method; the text report then leaves them out). When the positions
carry `hpl` (every `locate` and `track` output does), the integrity of the bounds too: the
usable fixes whose horizontal error exceeds their `hpl` (n_misleading, misleading_pct; a
missing bound counts as exceeded), the median hpl and its ratio to the median error
(hpl_over_error); in 3-D with `vpl`, the vertical bound likewise (n_misleading_v,
misleading_pct_v, vpl_median, vpl_over_error).  An unbounded statistic (hpl_median where
more than half of the usable fixes have no finite hpl) is inf in -o and in the text
report; --json, which has no infinity, writes null and lists the column in the row's
"infinite".
Two positions rows with the same
time, tag and method are an error. `-o -` writes the table as CSV to standard output (the
text report then goes to stderr).
Rows: the tags by name, and in each the --baseline method first, the others by name,
whatever the order of the positions' rows.
Aggregates: tag "all" pools every epoch (its counts are the sums over the tags), tag
"mean" averages the per-tag statistics (the paper's Table 1 average rows), its counts
too: n, n_missing, n_failed (n_ok, n_ok_3d, ...) are per-tag means, fractional in the
table of -o and --json, shown with "/tag" in the text report (n 42.9/tag); column
`aggregate` is true on them (and the report shows them as [all] and [mean] when a real
tag bears one of those names).

`--plot FILE.png` draws the figure a person would rather look at: the error CDF of each
method and, when the positions carry `hpl`, each method's Stanford diagram (error against
hpl, log-log; fixes below the diagonal are misleading, counted as n_misleading counts them).
Errors of 0 and absurd ones (beyond 1e9 m) are drawn on the edge of the log axes, fixes
far from the truth are left off the map, and the legends name the first 10 methods (in
the table's order): each panel says what it left out.  The figure is drawn before
anything is written, and the names of -o and --plot are checked before any work.

  robustloc evaluate positions.csv --truth truth.csv
  robustloc evaluate positions.csv --truth truth.csv --json -o errors.csv
  robustloc evaluate positions.csv --truth truth.csv --plot evaluation.png"""

_SHOW = ("tag", "method", "n", "n_missing", "n_failed", "max", "min", "mean", "rms", "sigma1",
         "median", "p95", "misleading_pct", "hpl_over_error", "mean_impr_pct", "rms_impr_pct")


def add_arguments(p: argparse.ArgumentParser) -> None:
    from robustloc.options import figure_path, nonnegative_float

    p.add_argument("positions", help="positions file (time, tag, x, y[, z], method, status, ...)")
    p.add_argument("--truth", required=True, help="truth file (time, tag, x, y[, z])")
    p.add_argument("-o", "--out",
                   help="write the full statistics table (CSV or Parquet; - for CSV on stdout)")
    p.add_argument("--json", action="store_true",
                   help='print {"n_unmatched": N, "rows": [one record per row]} as JSON')
    p.add_argument(
        "--time-tolerance", type=nonnegative_float, default=1e-6, metavar="S",
        help="largest |time difference| between a position and its truth (default 1e-6 s)",
    )
    p.add_argument("--baseline", default="ls",
                   help="method improvements refer to (default ls, when the file has it; "
                        "another must be one of the file's methods)")
    p.add_argument("--plot", type=figure_path, metavar="FILE",
                   help="draw the error CDF per method and each method's Stanford diagram "
                        "(error against hpl) into FILE (.png, .svg or .pdf; --engine "
                        "local)")
    p.add_argument("-q", "--quiet", action="store_true",
                   help="with -o: no text table and no progress bar (notes stay); without "
                        "-o the table (or --json's records) is the output and is printed")
    add_engine_arguments(p, what="the positions dataset",
                         output="the one statistics table of -o, as without it")


def _metres(v: float) -> str:
    """A table cell: 2 decimals, or 3 significant digits beyond 1e9 (an absurd position
    of 1e300 m printed 300 digits per cell)."""
    if np.isnan(v):
        return ""
    if np.isinf(v):  # (an unbounded hpl: blank said "no such value", not "unbounded")
        return "inf" if v > 0 else "-inf"
    return f"{v:.2f}" if abs(v) < 1e9 else f"{v:.3g}"


def run(args: argparse.Namespace) -> int:
    import sys

    from robustloc.eval.metrics import error_table
    from robustloc.io import read_positions, write_table
    from robustloc.io.atomic import check_not_input, writes_to_stdout

    check_not_input(args.out, [args.positions, args.truth])
    check_not_input(args.plot, [args.positions, args.truth])
    # -o's format before any work: `-o table.xlsx` was refused after the figure was written
    _check_table_out(args.out)
    if args.plot and args.engine == "dask":
        from robustloc.errors import InputError

        raise InputError("--plot draws from the whole table in memory: use it with "
                         "--engine local (the default)")
    if args.engine == "dask":
        from robustloc.engines.dask import evaluate_dataset
        table = evaluate_dataset(args)
    else:
        from robustloc.eval.metrics import check_baseline

        pos = read_positions(args.positions)
        check_baseline(args.baseline, pos["method"], args.positions)
        truth = _read_truth_said(args.truth)
        table = error_table(pos, truth, time_tolerance_s=args.time_tolerance,
                            baseline=args.baseline)
        if args.plot:  # drawn (into memory) before a file is written: see below
            from robustloc.eval.metrics import epoch_errors
            from robustloc.eval.plots import render_evaluation_figure

            figure, _ = render_evaluation_figure(
                epoch_errors(pos, truth, args.time_tolerance), args.plot,
                baseline=args.baseline)
    if args.plot:
        # the figure's temporary file is renamed into place only once the table is
        # written: a table that cannot be written leaves no figure behind, and the reverse
        from robustloc.io.atomic import atomic_output

        with atomic_output(args.plot) as (target, stream):
            if stream is not None:  # pragma: no cover - a figure's name is never "-"
                stream.write(figure)
            else:
                with open(target, "wb") as f:
                    f.write(figure)
            if args.out:
                write_table(_integral_counts(table), args.out)
    elif args.out:
        write_table(_integral_counts(table), args.out)
    # the report never goes into a data stream: stderr when the table goes to stdout
    dest = sys.stderr if writes_to_stdout(args.out) else sys.stdout
    n_unmatched = table.attrs.get("n_unmatched", 0)
    if args.json:
        # JSON has no NaN or infinity: both are null, and each row's "infinite" lists
        # the columns that are null for being infinite (an infinite hpl_median: more
        # than half of the usable fixes unbounded), so that "unbounded" and "no such
        # value" differ (the evaluate review, 2026-12-06)
        num = table.select_dtypes("number")
        inf_cols = [[c for c in num.columns if np.isinf(row[c])]
                    for row in num.to_dict(orient="records")]
        recs = table.replace({np.nan: None, np.inf: None, -np.inf: None}).to_dict(
            orient="records")
        for r, cols in zip(recs, inf_cols, strict=True):
            r["infinite"] = cols
        for r in recs:  # counts as integers (the "mean" rows may average to a fraction)
            for c in COUNTS:
                v = r.get(c)
                if v is not None and float(v).is_integer():
                    r[c] = int(v)
        print(json.dumps({"n_unmatched": n_unmatched, "rows": recs}, indent=2,
                         allow_nan=False), file=dest)
        return 0
    agg = table["aggregate"].to_numpy(dtype=bool)
    pooled = agg & (table["tag"] == "all").to_numpy()
    n_missing = int(table.loc[pooled, "n_missing"].sum())
    n_scored = int(table.loc[pooled, "n"].sum())
    if args.quiet and args.out:  # the table is in the file: only the notes
        _notes(n_missing, n_unmatched, n_scored, sys.stderr)
        return 0
    show = table[[c for c in _SHOW if c in table.columns]].copy()
    if np.isin(table.loc[~agg, "tag"].astype(str), ("all", "mean")).any():
        # a real tag bears an aggregate's name: the aggregates are shown bracketed
        show.loc[agg, "tag"] = "[" + show.loc[agg, "tag"].astype(str) + "]"
    # the mean row's counts are per-tag means: said so in the cell (n 42.9/tag)
    per_tag = agg & (table["tag"] == "mean").to_numpy()
    for c in ("n", "n_missing", "n_failed"):
        show[c] = _count_cells(show[c], per_tag)
    for c in show.columns[5:]:
        show[c] = show[c].map(_metres)
    # the improvement columns keep the names of -o and --json; without a baseline row
    # they are empty there and left out here (they were mean_vs_ls_% with no ls at all)
    impr = [c for c in ("mean_impr_pct", "rms_impr_pct") if c in table.columns]
    has_impr = bool(impr) and bool(np.isfinite(table[impr].to_numpy(dtype=float)).any())
    if not has_impr:
        show = show.drop(columns=impr)
    # what the columns mean, on the title line (the table's rows follow it directly)
    title = "horizontal error (m)"
    if has_impr:
        title += (f"; mean_impr_pct, rms_impr_pct: % improvement of mean and rms over "
                  f"method {args.baseline} of the same tag")
    if per_tag.any():
        title += "; mean: the tags' average, of the counts too (/tag)"
    print(title, file=dest)
    print(show.to_string(index=False), file=dest)
    if "rms_3d" in table.columns:
        cols = ["tag", "method", "n_ok_3d", "mean_3d", "rms_3d", "p95_3d", "max_3d"]
        t3 = table[cols].copy()
        t3["n_ok_3d"] = _count_cells(t3["n_ok_3d"], per_tag)
        for c in cols[3:]:
            t3[c] = t3[c].map(_metres)
        print("\n3-D error (m)", file=dest)
        print(t3.to_string(index=False), file=dest)
    _notes(n_missing, n_unmatched, n_scored, dest)
    if args.out:
        print(f"written: {args.out}", file=dest)
    if args.plot:
        print(f"figure: {args.plot}", file=dest)
    return 0


def _read_truth_said(path: str):  # noqa: ANN202 - a truth frame
    """:func:`robustloc.io.read_truth`; a refused file that carries positions' columns
    (``method``, ``status``) says the arguments look swapped (`evaluate truth.csv --truth
    positions.csv` named only a NaN on some line: the new-user review)."""
    import sys

    from robustloc.io import read_truth

    def looks_swapped() -> bool:
        try:
            head = pd.read_csv(path, nrows=0).columns
        except Exception:  # noqa: BLE001 - not a CSV header: no guess
            return False
        return bool({"method", "status"} & {str(c) for c in head})

    try:
        truth = read_truth(path)
    except InputError as exc:
        if looks_swapped():
            raise InputError(exc.message + "; this file has the columns of a positions "
                             "file (method, status): are the positions and --truth "
                             "swapped?", exc.path, exc.line) from None
        raise
    if looks_swapped():  # (read as truth all the same: the table's method 'unknown')
        print(f"warning: {path}: --truth has the columns of a positions file (method, "
              "status): are the positions and --truth swapped?", file=sys.stderr)
    return truth


def _notes(n_missing: int, n_unmatched: int, n_scored: int, dest: TextIO) -> None:
    """The notes under the table: truth epochs without a position, positions without truth.

    ``n_scored``: the epochs scored over the methods (matched positions rows and missing
    truth epochs, the ``all`` rows' ``n``), so ``n_scored - n_missing`` positions rows
    matched."""
    if n_missing:
        print(f"note: {n_missing} truth epochs (summed over methods) had no position and "
              "count as failed", file=dest)
    if n_unmatched:
        print(f"note: {n_unmatched} position rows had no truth and were not scored", file=dest)
    # most of both sides unmatched (it was n_missing >= n_unmatched // 2: with one row
    # unmatched, always, 1000 of 1001 rows matched)
    n_positions = n_unmatched + n_scored - n_missing
    if 2 * n_unmatched > n_positions and 2 * n_missing > n_scored:
        print("hint: positions and truth mostly miss each other's times: are both in "
              "seconds on one clock (times in ms match nothing)?  --time-tolerance sets "
              "the matching window", file=dest)


#: The count columns: integers in --json and -o (a "mean" row's average may be a fraction).
COUNTS = ("n", "n_missing", "n_failed", "n_ok", "n_ok_3d", "n_misleading", "n_misleading_v")


def _check_table_out(out: str | None) -> None:
    """Refuse an ``-o`` name :func:`robustloc.io.write_table` would refuse only after the
    work (``.png``, ``.xlsx``, ``.json``; a ``.bz2`` compression), before it."""
    if out is not None:
        from robustloc.io.tables import check_table_path

        check_table_path(out)


def _count(v: float) -> str:
    """A count as people read it: ``1234``, or ``617.5`` for a ``mean`` row's average
    (it printed ``1.23e+03``)."""
    if not np.isfinite(v):
        return ""
    return f"{int(v)}" if float(v).is_integer() else f"{v:.1f}"


def _count_cells(values: pd.Series, per_tag: np.ndarray) -> pd.Series:
    """A count column as the text report shows it (:func:`_count`), the ``mean`` row's
    (``per_tag``) marked as the per-tag average it is: ``42.9/tag``."""
    cells = values.map(_count)
    mark = per_tag & (cells != "").to_numpy()
    cells[mark] = cells[mark] + "/tag"
    return cells


def _integral_counts(table):
    """The count columns as integers where every value is whole (the CSV showed
    ``2000.0``); a ``mean`` row's fractional average keeps its column float."""
    out = table.copy()
    for c in COUNTS:
        if c in out.columns:
            v = out[c].to_numpy(dtype=float)
            fin = np.isfinite(v)
            if np.all(v[fin] == np.round(v[fin])):
                out[c] = out[c].astype("Int64")
    return out
