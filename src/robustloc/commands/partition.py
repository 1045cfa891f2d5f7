"""``robustloc partition``: big CSV/Parquet input -> a partitioned Parquet dataset."""

from __future__ import annotations

import argparse
import json
import re
import sys

NAME = "partition"
HELP = "repartition big measurements (CSV/Parquet, any order) by tag or time, out of core"
DESCRIPTION = """\
Turns measurements in any order (a CSV or Parquet file, a directory or a glob of them)
into the partitioned Parquet dataset that `--engine dask` runs on, out of core (DuckDB
spills to disk beyond --memory-limit):

  --by tag   one directory per tag (tag=T1/part-0.parquet), or per bucket of tags with
             --buckets N; each file sorted by time.  For filter and track: a tag's whole
             history is in one file, in time order.
  --by time  contiguous time bins (time_bin=000003/part-0.parquet) of --span seconds
             (default: about --rows-per-partition rows each), sorted by time, tag, anchor.
             All rows of one time land in one file, so an epoch is never split.  For
             locate and evaluate (locate also runs on a dataset by tag).

The files hold the input's columns (tag too); the folder names only organize them.  To
read the dataset with pandas or pyarrow, leave the folder keys out:
pandas.read_parquet(DIR, partitioning=None) or pyarrow.dataset.dataset(DIR,
format="parquet", partitioning=None) (read as a column, tag= clashes with the files' tag:
"Field tag has incompatible types").

--method duckdb (default: a partitioned COPY, then a sort of each file) was faster than
--method dask (a dask shuffle) on this project's benchmark (benchmarks/bench_dask.py).
A progress bar is shown on a terminal (-q or --json hides it).

  robustloc partition big.csv -o meas-by-time --by time
  robustloc partition 'logs/*.parquet' -o meas-by-tag --by tag
  robustloc locate meas-by-time --anchors anchors.csv -o positions --engine dask"""


def add_arguments(p: argparse.ArgumentParser) -> None:
    from robustloc.engines.partition import BY, METHODS
    from robustloc.options import float_in, local_workers, nonnegative_int, positive_int

    p.add_argument("input", help="measurements: CSV or Parquet file, directory or glob")
    p.add_argument("-o", "--out", required=True, help="dataset directory to write")
    p.add_argument("--by", required=True, choices=BY, help="partition key")
    # (1e-300 surfaced DuckDB's "can't be cast" text: times up to 1e12 s over a span
    # below 1e-6 s number more bins than an int64 holds -- the input review)
    p.add_argument("--span", type=float_in(1e-6, 1e12), default=None, metavar="S",
                   help="--by time: bin width in seconds, 1e-6 to 1e12 (default: from "
                        "--rows-per-partition)")
    p.add_argument("--rows-per-partition", type=positive_int, default=ROWS_PER_PARTITION,
                   metavar="N",
                   help="--by time without --span: target rows per file (default 2000000); "
                        "--method dask: also about the rows of each of its shuffle's tasks")
    p.add_argument("--buckets", type=nonnegative_int, default=0, metavar="N",
                   help="--by tag: hash the tags into N buckets (default 0: one per tag)")
    p.add_argument("--method", choices=METHODS, default="duckdb",
                   help="duckdb (default, measured faster) or dask (a shuffle)")
    p.add_argument("--memory-limit", type=memory_size, default="2GB", metavar="SIZE",
                   help="DuckDB memory limit before spilling to disk, e.g. 500MB, 2GB, "
                        "1.5GiB or 50%% of the RAM (default 2GB; --method dask: of the "
                        "DuckDB scan that checks the input first)")
    p.add_argument("--threads", type=positive_int, default=None,
                   help="DuckDB threads (default: the cores available; --method dask: "
                        "of its input check)")
    p.add_argument("--scheduler", default=None, metavar="ADDRESS",
                   help="--method dask: a running scheduler (default: a LocalCluster)")
    p.add_argument("--workers", type=local_workers, default=None, metavar="N",
                   help="--method dask without --scheduler: LocalCluster workers")
    p.add_argument("--json", action="store_true", help="print the summary as JSON")
    p.add_argument("-q", "--quiet", action="store_true",
                   help="no progress bar and no summary line (errors and warnings stay), as "
                        "the other commands")


_SIZE = re.compile(r"^\s*(\d+(\.\d*)?|\.\d+)\s*(KB|MB|GB|TB|KIB|MIB|GIB|TIB|%)\s*$",
                   re.IGNORECASE)


def memory_size(text: str) -> str:
    """``--memory-limit``: a positive size with its unit (``500MB``, ``2GB``, ``1.5GiB``)
    or a share of the RAM (``50%``), as DuckDB's ``memory_limit`` takes it.

    Raises
    ------
    argparse.ArgumentTypeError
        Anything else (``abc``, ``100`` without a unit, ``0GB``, ``150%``).
    """
    m = _SIZE.match(text)
    ok = m is not None and 0 < float(m.group(1)) < float("inf")
    if ok and m.group(3) == "%":
        ok = float(m.group(1)) <= 100
    if not ok:
        raise argparse.ArgumentTypeError(
            f"expected a size with its unit such as 500MB, 2GB or 1.5GiB, or a share of "
            f"the RAM such as 50%, got {text!r}")
    return text.strip()


#: More partitions than this, of fewer rows than :data:`FEW_ROWS` each on average, get a
#: note: each costs a file, a sort and (under --engine dask) a task.
MANY_PARTITIONS = 1000
FEW_ROWS = 1000


#: ``--rows-per-partition``'s default, by which a value given is told from none.
ROWS_PER_PARTITION = 2_000_000


def _refuse_idle_options(args: argparse.Namespace) -> None:
    """Options that the other key or method never reads, refused (they were taken and
    changed nothing: the commands review).  ``--rows-per-partition`` chooses the span of
    ``--by time`` without ``--span``; under ``--method dask`` it also sizes the shuffle's
    tasks, so it is refused only for ``--method duckdb``.  ``--memory-limit`` and
    ``--threads`` apply under either method (``dask`` checks its input with DuckDB)."""
    from robustloc.errors import InputError

    idle = []
    if args.by == "time" and args.buckets:
        idle.append(("--buckets", "--by tag", "--by time bins the rows by time"))
    if args.by == "tag" and args.span is not None:
        idle.append(("--span", "--by time", "--by tag partitions by the tags"))
    if (args.method == "duckdb" and args.rows_per_partition != ROWS_PER_PARTITION
            and (args.by == "tag" or args.span is not None)):
        idle.append(("--rows-per-partition", "--by time without --span, or --method dask",
                     "--span gives the bins" if args.by == "time"
                     else "--by tag partitions by the tags"))
    if args.method == "duckdb":
        for flag, value in (("--scheduler", args.scheduler), ("--workers", args.workers)):
            if value is not None:
                idle.append((flag, "--method dask", "--method duckdb runs in this process"))
    if idle:
        flag, where, why = idle[0]
        raise InputError(f"{flag} applies to {where} only ({why})")


def run(args: argparse.Namespace) -> int:
    from robustloc.engines.partition import partition_dataset

    _refuse_idle_options(args)  # before any work
    s = partition_dataset(
        args.input, args.out, args.by, span_s=args.span,
        rows_per_partition=args.rows_per_partition, buckets=args.buckets, method=args.method,
        memory_limit=args.memory_limit, threads=args.threads, scheduler=args.scheduler,
        workers=args.workers, progress=not (args.quiet or args.json),
    )
    if s.files > MANY_PARTITIONS and s.rows / s.files < FEW_ROWS and not args.quiet:
        # one sorted file per partition costs a few ms each (20 000 tags of 10 rows: 2
        # min, against 2.4 s with --buckets 64; the partition review, 2026-12-07)
        hint = ("--buckets B groups the tags into B partitions" if s.key == "tag"
                else "a longer --span (or leave it out: about --rows-per-partition rows)")
        print(f"note: {s.files} partitions of {s.rows / s.files:.0f} rows on average: "
              f"each is a file and a task; {hint}", file=sys.stderr)
    if args.json:
        print(json.dumps({**s.__dict__, "out": str(args.out)}, indent=2))
    elif not args.quiet:
        span = f", {s.span_s:.6g} s bins" if s.span_s is not None else ""
        print(f"{s.rows} rows -> {s.files} files by {s.key}{span} in {args.out} "
              f"({s.seconds:.2f} s, {s.method})")
    return 0
