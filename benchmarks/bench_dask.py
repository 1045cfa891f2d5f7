"""``--engine dask`` against the single-process engine, and DuckDB against a dask shuffle.

Workload (issue 13): a site of ``--tags`` tags (default 500) and 8 anchors at 10 Hz, RSSI
from the log-distance model (A = -40 dBm, n = 2.2, sigma = 2 dB, 5 % of readings 6-20 dB
low: body blocking), tags walking slowly in a 40 m x 30 m hall.  One time-sorted Parquet
file of N rows is written chunk by chunk (a pyarrow ParquetWriter, ``--chunk-rows`` rows
at a time: never the whole log in memory), for each N of ``--rows`` (default 10 M;
``--rows 10M,50M,200M`` for the issue's full table: 200 M rows are ~1.6 GB of input plus
two partitioned copies, and hours on a small machine).

Per size, one line per step:

* ``partition``: ``robustloc partition --by time`` and ``--by tag`` (``--buckets``, default
  one per worker) with DuckDB, and ``--by time`` with a dask shuffle
  (``--shuffle-max-rows`` bounds the sizes it is timed on; it is the slower of the two);
* ``locate``: ``robustloc locate --method huber`` in one process vs ``--engine dask`` on
  the time-partitioned dataset;
* ``track``: ``robustloc track`` in one process vs ``--engine dask`` on the tag-partitioned
  dataset, on the warm cluster and (``(cold)``, unless ``--no-cold``) on the command's own
  fresh LocalCluster, all of its start-up timed;
* ``filter``: ``robustloc filter`` in one process vs ``--engine dask`` on a dataset of
  ``--filter-buckets`` tag buckets (``--filter-max-rows``: it holds its input in memory).

The single-process runs are subprocesses on one thread (the workers' environment: a
per-core baseline), peak RSS polled.  The dask runs use a LocalCluster of ``--workers``
single-threaded worker processes started once and warmed up before the timings (each
command once on a small dataset: imports and numba cache loads done, as on a long-lived
cluster), reached through ``--scheduler`` as on a real cluster.  Columns: wall seconds, CPU
seconds (dask: workers + scheduler + client), rows/s, epochs or samples/s, per-worker-core
throughput as % of the single-process run by wall clock and by CPU seconds (the target is
>= 70 %), peak RSS of the single process or of the largest worker (sampled every 0.2 s;
the target is <= 2 GiB per worker), the load average (1/5 min) at the end of the line, and
whether the outputs are identical (sorted by key, every column, exactly).

The single-process baseline runs as a new process, so its wall clock and CPU seconds
include the interpreter's start-up, robustloc's imports and the numba cache loads, which
the warm cluster has already paid.  That start-up is measured once per command (the same
command, one thread, on a 4 000-row input, ``STARTUP_ROWS``; best of two runs) and
subtracted from the baseline's wall and CPU seconds before the %/core columns are
computed; the ``(cold)`` track line is compared with the baseline as measured (both pay
a start-up).

The measured figures (and their notes) are in docs/dask.md (section "Performance"; its
single-process figures still include the ~2 s start-up, small beside 70-600 s runs).

Usage::

    python benchmarks/bench_dask.py --rows 1M --workers 2          # a quick look
    python benchmarks/bench_dask.py                                # the 10 M line
    python benchmarks/bench_dask.py --rows 10M,50M,200M --dir /big/disk --json
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import resource
import shutil
import subprocess
import sys
import threading
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

A_DBM, N_EXP, SIGMA_DB = -40.0, 2.2, 2.0
HALL_M = (40.0, 30.0)
ANCHORS = np.array([[0, 0], [20, 0], [40, 0], [40, 15], [40, 30], [20, 30], [0, 30], [0, 15]],
                   dtype=float)
RATE_HZ = 10.0
#: The commands --steps may name.
STEPS = ("locate", "track", "filter")
#: Rows of the input on which each command's start-up (interpreter, imports, numba cache
#: loads, a few epochs of work) is timed, to be subtracted from the single-process runs.
STARTUP_ROWS = 4_000


@dataclass
class Line:
    rows: int
    step: str
    engine: str
    seconds: float
    cpu_s: float
    rows_per_s: float
    units_per_s: float
    per_core_pct: float | None
    per_cpu_s_pct: float | None
    peak_rss_mib: float
    identical: str
    load: str = ""

    def __post_init__(self) -> None:
        # the machine's load while this line ran: 1- and 5-minute averages at its end
        if not self.load:
            la = os.getloadavg()
            self.load = f"{la[0]:.1f}/{la[1]:.1f}"


def parse_steps(text: str) -> frozenset[str]:
    """``--steps``: a comma-separated subset of :data:`STEPS` (empty: partitioning only)."""
    names = {t.strip() for t in text.split(",") if t.strip()}
    unknown = sorted(names - set(STEPS))
    if unknown:
        raise argparse.ArgumentTypeError(
            f"unknown step(s) {', '.join(unknown)}; choose from {', '.join(STEPS)}")
    return frozenset(names)


def parse_rows(text: str) -> list[int]:
    out = []
    for t in text.split(","):
        t = t.strip().upper()
        mult = {"K": 10**3, "M": 10**6, "G": 10**9}.get(t[-1:], 1)
        out.append(int(float(t.rstrip("KMG")) * mult))
    return out


def write_anchors(path: Path) -> None:
    import pandas as pd

    pd.DataFrame({"anchor": [f"A{i}" for i in range(len(ANCHORS))], "x": ANCHORS[:, 0],
                  "y": ANCHORS[:, 1], "A": A_DBM, "n": N_EXP}).to_csv(path, index=False)


def write_measurements(path: Path, n_rows: int, n_tags: int, chunk_rows: int, seed: int
                       ) -> None:
    """A time-sorted RSSI log of ``n_rows`` rows, written ``chunk_rows`` at a time."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    rng = np.random.default_rng(seed)
    m = len(ANCHORS)
    tags = np.array([f"T{i:05d}" for i in range(n_tags)], dtype=object)
    anchors = np.array([f"A{i}" for i in range(m)], dtype=object)
    start = rng.uniform([2, 2], [HALL_M[0] - 2, HALL_M[1] - 2], size=(n_tags, 2))
    heading = rng.uniform(0, 2 * np.pi, n_tags)
    per_step = n_tags * m
    steps_per_chunk = max(1, chunk_rows // per_step)
    n_steps = -(-n_rows // per_step)
    writer = None
    written = 0
    try:
        for s0 in range(0, n_steps, steps_per_chunk):
            k = np.arange(s0, min(n_steps, s0 + steps_per_chunk))
            t = k / RATE_HZ
            # slow walks (0.25 m/s) on circles of 2.5 m around each tag's start
            ang = heading[None, :] + 0.1 * t[:, None]
            pos = start[None] + 2.5 * np.stack([np.cos(ang), np.sin(ang)], -1)
            d = np.linalg.norm(pos[:, :, None, :] - ANCHORS[None, None], axis=-1)
            rssi = A_DBM - 10 * N_EXP * np.log10(np.maximum(d, 0.5))
            rssi = rssi + rng.normal(0, SIGMA_DB, rssi.shape)
            blocked = rng.random(rssi.shape) < 0.05
            rssi = rssi - blocked * rng.uniform(6, 20, rssi.shape)
            n = rssi.size
            take = min(n, n_rows - written)
            table = pa.table({
                "time": np.repeat(t, n_tags * m)[:take],
                "tag": pa.array(np.tile(np.repeat(tags, m), len(k))[:take], pa.string()),
                "anchor": pa.array(np.tile(anchors, n_tags * len(k))[:take], pa.string()),
                "rssi": rssi.reshape(-1)[:take],
            })
            if writer is None:
                writer = pq.ParquetWriter(path, table.schema)
            writer.write_table(table, row_group_size=1_000_000)
            written += take
    finally:
        if writer is not None:
            writer.close()


class RssPoller:
    """Peak resident memory of a set of processes (and their children), polled."""

    def __init__(self, pids: list[int], interval_s: float = 0.2) -> None:
        import psutil

        self.procs = [psutil.Process(p) for p in pids]
        self.peak = {p: 0 for p in pids}
        #: the last CPU seconds seen per process (a worker the nanny restarts -- over its
        #: memory limit -- is gone at the end; its CPU up to the last poll still counts)
        self.cpu = {p: 0.0 for p in pids}
        self.interval = interval_s
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def _run(self) -> None:
        import psutil

        while not self._stop.is_set():
            for p in self.procs:
                try:
                    rss = p.memory_info().rss
                    for c in p.children(recursive=True):
                        rss += c.memory_info().rss
                    t = p.cpu_times()
                    self.cpu[p.pid] = t.user + t.system
                except psutil.Error:
                    continue
                self.peak[p.pid] = max(self.peak[p.pid], rss)
            self._stop.wait(self.interval)

    def __enter__(self) -> RssPoller:
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join()

    def max_mib(self) -> float:
        return max(self.peak.values()) / 2**20


def _children_cpu_s() -> float:
    r = resource.getrusage(resource.RUSAGE_CHILDREN)
    return r.ru_utime + r.ru_stime


def _cpu_s(pids: list[int], last_seen: dict[int, float] | None = None) -> float:
    """CPU seconds used so far by these processes and by this one (the scheduler, the
    client's planning): what a dask run costs, counted against dask.  A process that is
    gone counts with ``last_seen[pid]`` (its last polled value), else 0."""
    import psutil

    total = 0.0
    for pid in pids:
        try:
            c = psutil.Process(pid).cpu_times()
            total += c.user + c.system
        except psutil.NoSuchProcess:
            total += (last_seen or {}).get(pid, 0.0)
    r = resource.getrusage(resource.RUSAGE_SELF)
    return total + r.ru_utime + r.ru_stime


def run_cli(argv: list[str], one_thread: bool = False, scratch: Path | None = None
            ) -> tuple[float, float, float]:
    """A robustloc command in a subprocess: (seconds, CPU seconds, peak RSS MiB).

    ``one_thread``: with the workers' environment (one numba/BLAS thread), the
    single-process baseline of a per-core comparison (``track``'s fusion kernel otherwise
    spreads 256+ tags over every core, and on a loaded machine its threads mostly wait
    for each other: 1 M rows, load 6: 19.3 s with 2 threads, 7.2 s with one).
    ``scratch``: dask's temporary directory for a cluster the command starts itself."""
    from robustloc.engines.cluster import WORKER_ENV

    env = dict(os.environ, **WORKER_ENV) if one_thread else None
    if scratch is not None:
        env = dict(env or os.environ, DASK_TEMPORARY_DIRECTORY=str(scratch))
    t0, c0 = time.perf_counter(), _children_cpu_s()
    proc = subprocess.Popen([sys.executable, "-m", "robustloc.cli", *argv],
                            stdout=subprocess.DEVNULL, env=env)
    with RssPoller([proc.pid]) as poll:
        rc = proc.wait()
    if rc:
        raise RuntimeError(f"robustloc {' '.join(argv)} exited with {rc}")
    return time.perf_counter() - t0, _children_cpu_s() - c0, poll.max_mib()


def run_in_cluster(client: object, argv: list[str]) -> tuple[float, float, float]:
    """A command on ``client``'s cluster: (seconds, CPU seconds, peak worker MiB)."""
    from robustloc.cli import main

    pids = list(client.run(os.getpid).values())
    t0, c0 = time.perf_counter(), _cpu_s(pids)
    # the command's own report to stderr: stdout carries only the table (or the JSON)
    with RssPoller(pids) as poll, contextlib.redirect_stdout(sys.stderr):
        rc = main([*argv, "--scheduler", client.scheduler.address])
    if rc:
        raise RuntimeError(f"robustloc {' '.join(argv)} exited with {rc}")
    wall = time.perf_counter() - t0
    gone = set(pids) - set(client.run(os.getpid).values())
    if gone:  # the nanny restarted a worker (over its memory limit): say so, loudly
        print(f"WARNING: {len(gone)} worker(s) restarted during {argv[0]}; their CPU after "
              "the last poll and the new workers' memory are not counted", file=sys.stderr)
    return wall, _cpu_s(pids, poll.cpu) - c0, poll.max_mib()


def same(a_path: Path, b_path: Path, key: list[str]) -> str:
    """'yes' if two outputs hold the same rows (sorted by key, every column of a, exactly).

    In Arrow, one column at a time (the key columns once, to order both): no Python
    objects per row, so the check of a 200 M-row run's output fits the client."""
    import pyarrow as pa
    import pyarrow.compute as pc
    import pyarrow.dataset as pads
    import pyarrow.parquet as pq

    da = pads.dataset(str(a_path), format="parquet")
    db = pads.dataset(sorted(str(f) for f in Path(b_path).glob("part-*.parquet")),
                      format="parquet")
    if da.count_rows() != db.count_rows():
        return f"no ({da.count_rows()} vs {db.count_rows()} rows)"

    def column(d: object, c: str) -> pa.Array:
        col = d.to_table(columns=[c]).column(c).combine_chunks()
        return col.dictionary_decode() if pa.types.is_dictionary(col.type) else col

    def order(d: object) -> pa.Array:
        t = pa.table({c: column(d, c) for c in key})
        return pc.sort_indices(t, sort_keys=[(c, "ascending") for c in key])

    oa, ob = order(da), order(db)
    for c in pq.read_schema(a_path).names:
        x, y = column(da, c).take(oa), column(db, c).take(ob)
        if x.type != y.type:
            try:
                y = y.cast(x.type)
            except (pa.ArrowInvalid, pa.ArrowNotImplementedError):
                x, y = x.cast(pa.string()), y.cast(pa.string())
        eq = pc.fill_null(pc.equal(x, y), False)
        eq = pc.or_(eq, pc.and_(x.is_null(), y.is_null()))
        if pa.types.is_floating(x.type):
            eq = pc.or_(eq, pc.fill_null(pc.and_(pc.is_nan(x), pc.is_nan(y)), False))
        if not pc.all(eq).as_py():
            return f"no (column {c})"
    return "yes"


def bench_size(n: int, args: argparse.Namespace, client: object, work: Path,
               startup: dict[str, tuple[float, float]]) -> list[Line]:
    """One size's lines; ``startup``: per command, the wall and CPU seconds of a
    single-process run's start-up (:func:`measure_startup`), taken off the baseline."""
    lines: list[Line] = []
    d = work / f"n{n}"
    shutil.rmtree(d, ignore_errors=True)
    d.mkdir(parents=True)
    anchors = d / "anchors.csv"
    write_anchors(anchors)
    meas = d / "meas.parquet"
    t0 = time.perf_counter()
    write_measurements(meas, n, args.tags, args.chunk_rows, args.seed)
    print(f"[{n:,} rows] written in {time.perf_counter() - t0:.1f} s "
          f"({meas.stat().st_size / 2**20:.0f} MiB)", file=sys.stderr)
    n_epochs = -(-n // len(ANCHORS))
    n_workers = len(client.scheduler_info()["workers"])
    by_time, by_tag = d / "by_time", d / "by_tag"
    rpp = str(min(args.rows_per_partition, -(-n // (4 * n_workers))))
    by_tag_f = d / "by_tag_filter"
    parts = [("time", by_time, args.buckets)] if "locate" in args.steps else []
    if "track" in args.steps:
        parts.append(("tag", by_tag, args.buckets))
    if "filter" in args.steps and n <= args.filter_max_rows:
        parts.append(("tag", by_tag_f, args.filter_buckets))
    for by, out, buckets in parts:
        s, c, mib = run_cli(["partition", str(meas), "-o", str(out), "--by", by,
                             "--rows-per-partition", rpp, "--buckets", str(buckets)])
        lines.append(Line(n, f"partition --by {by}" + (f" ({buckets} b.)" if by == "tag"
                                                        else ""),
                          "duckdb", s, c, n / s, n / s, None, None, mib, ""))
    if n <= args.shuffle_max_rows:
        out = d / "by_time_dask"
        try:
            s, c, mib = run_in_cluster(client, ["partition", str(meas), "-o", str(out), "--by",
                                                "time", "--method", "dask",
                                                "--rows-per-partition", rpp])
            lines.append(Line(n, "partition --by time", "dask shuffle", s, c, n / s, n / s,
                              None, None, mib, ""))
        except Exception as exc:  # noqa: BLE001 - e.g. workers killed over their memory limit
            print(f"dask shuffle failed: {type(exc).__name__}: {exc}", file=sys.stderr)
            lines.append(Line(n, "partition --by time", "dask shuffle", float("nan"),
                              float("nan"), float("nan"), float("nan"), None, None,
                              float("nan"), f"failed: {type(exc).__name__}"))
            client.restart()
        shutil.rmtree(out, ignore_errors=True)
    steps = []
    if "locate" in args.steps:
        steps.append(("locate huber", ["locate", "--method", "huber"], by_time, n_epochs,
                      ["method", "time", "tag"]))
    if "track" in args.steps:
        steps.append(("track", ["track"], by_tag, n_epochs, ["time", "tag"]))
    if "filter" in args.steps and n <= args.filter_max_rows:
        steps.append(("filter", ["filter"], by_tag_f, n, ["tag", "anchor", "time"]))
    for name, cmd, dataset, units, key in steps:
        one = d / "one.parquet"
        s0, c0, m1 = run_cli([cmd[0], str(meas), "--anchors", str(anchors), *cmd[1:],
                              "-o", str(one)], one_thread=True)
        # the process's start-up (interpreter, imports, numba cache loads), which the warm
        # cluster does not pay, taken off the baseline (never below 1 % of the run)
        su_s, su_c = startup[cmd[0]]
        s1, c1 = max(s0 - su_s, 0.01 * s0), max(c0 - su_c, 0.01 * c0)
        lines.append(Line(n, name, "single process", s1, c1, n / s1, units / s1, 100.0, 100.0,
                          m1, ""))
        ds = d / "out_ds"
        s2, c2, m2 = run_in_cluster(client, [cmd[0], str(dataset), "--anchors", str(anchors),
                                             *cmd[1:], "-o", str(ds), "--engine", "dask",
                                             "--quiet"])
        lines.append(Line(n, name, f"dask x{n_workers}", s2, c2, n / s2, units / s2,
                          100.0 * (s1 / s2) / n_workers, 100.0 * c1 / c2, m2,
                          same(one, ds, key)))
        shutil.rmtree(ds, ignore_errors=True)
        if name == "track" and args.cold:
            # what a user without a cluster sees: the command starts its own LocalCluster
            # (fresh workers: imports, numba cache loads) and closes it, all timed
            s3, c3, m3 = run_cli([cmd[0], str(dataset), "--anchors", str(anchors), *cmd[1:],
                                  "-o", str(ds), "--engine", "dask", "--quiet", "--workers",
                                  str(n_workers)], scratch=work / "dask-scratch")
            # against the baseline as measured: both pay a process start-up
            lines.append(Line(n, name + " (cold)", f"dask x{n_workers} own", s3, c3, n / s3,
                              units / s3, 100.0 * (s0 / s3) / n_workers, 100.0 * c0 / c3,
                              m3, same(one, ds, key) + " (peak: all processes)"))
            shutil.rmtree(ds, ignore_errors=True)
        one.unlink()
    if not args.keep:
        shutil.rmtree(d, ignore_errors=True)
    return lines


def measure_startup(args: argparse.Namespace, work: Path) -> dict[str, tuple[float, float]]:
    """Per command of ``--steps``: wall and CPU seconds of the single-process run (one
    thread, as the baseline) on a ``STARTUP_ROWS``-row input, best of two: the
    interpreter's start-up, the imports and the numba cache loads that every
    single-process run pays and the warm cluster does not."""
    d = work / "startup"
    shutil.rmtree(d, ignore_errors=True)
    d.mkdir(parents=True)
    write_anchors(d / "anchors.csv")
    write_measurements(d / "meas.parquet", STARTUP_ROWS, 50, STARTUP_ROWS, args.seed)
    out: dict[str, tuple[float, float]] = {}
    for cmd in STEPS:
        if cmd in args.steps:
            extra = ["--method", "huber"] if cmd == "locate" else []
            runs = [run_cli([cmd, str(d / "meas.parquet"), "--anchors", str(d / "anchors.csv"),
                             *extra, "-o", str(d / f"o-{cmd}.parquet")], one_thread=True)
                    for _ in range(2)]
            out[cmd] = (min(r[0] for r in runs), min(r[1] for r in runs))
    shutil.rmtree(d, ignore_errors=True)
    return out


def warm_up(client: object, args: argparse.Namespace, work: Path) -> None:
    """Each timed command once on a small dataset, on the cluster: the workers import
    robustloc and load the compiled kernels from numba's cache, as the workers of a
    long-lived cluster (``--scheduler``) have done after their first run.  Not timed."""
    d = work / "warm"
    shutil.rmtree(d, ignore_errors=True)
    d.mkdir(parents=True)
    write_anchors(d / "anchors.csv")
    write_measurements(d / "meas.parquet", 40_000, 50, 40_000, args.seed)
    for by in ("time", "tag"):
        run_cli(["partition", str(d / "meas.parquet"), "-o", str(d / by), "--by", by,
                 "--rows-per-partition", "10000", "--buckets", str(args.workers)])
    for cmd, by in (("locate", "time"), ("track", "tag"), ("filter", "tag")):
        if cmd in args.steps:
            extra = ["--method", "huber"] if cmd == "locate" else []
            run_in_cluster(client, [cmd, str(d / by), "--anchors", str(d / "anchors.csv"),
                                    *extra, "-o", str(d / f"o-{cmd}"), "--engine", "dask",
                                    "--quiet"])
    shutil.rmtree(d, ignore_errors=True)


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--rows", default="10M",
                   help="sizes, e.g. 1M or 10M,50M,200M (default: %(default)s)")
    p.add_argument("--tags", type=int, default=500,
                   help="tags of the simulated site (default: %(default)s)")
    p.add_argument("--workers", type=int, default=2,
                   help="LocalCluster worker processes (default: %(default)s)")
    p.add_argument("--rows-per-partition", type=int, default=1_000_000,
                   help="robustloc partition --rows-per-partition, capped at rows / (4 x "
                        "workers) (default: %(default)s)")
    p.add_argument("--buckets", type=int, default=None,
                   help="--by tag for track: tag buckets (0: a directory per tag; default "
                        "one per worker: the tracker is vectorized over the tags of a "
                        "partition and pays a fixed cost per time step, so the fewer the "
                        "buckets the less it pays; a partition is streamed, its size does "
                        "not matter)")
    p.add_argument("--filter-buckets", type=int, default=None,
                   help="--by tag for filter: tag buckets (default 2 per worker: the filter "
                        "holds its partition in memory)")
    p.add_argument("--chunk-rows", type=int, default=2_000_000,
                   help="rows written at a time (default: %(default)s)")
    p.add_argument("--shuffle-max-rows", type=int, default=10_000_000,
                   help="time the dask shuffle only up to this size (default: %(default)s)")
    p.add_argument("--filter-max-rows", type=int, default=10_000_000,
                   help="run filter only up to this size (one process holds it whole) "
                        "(default: %(default)s)")
    p.add_argument("--steps", type=parse_steps, default=",".join(STEPS),
                   help="comma-separated commands to time, from "
                        f"{', '.join(STEPS)}; '' times only the partitioning "
                        "(default: %(default)s)")
    p.add_argument("--no-cold", dest="cold", action="store_false",
                   help="skip the track run on the command's own fresh LocalCluster")
    p.add_argument("--dir", default=None, help="work directory (default: a temporary one)")
    p.add_argument("--keep", action="store_true", help="keep the data")
    p.add_argument("--seed", type=int, default=1,
                   help="seed of the simulated measurements (default: %(default)s)")
    p.add_argument("--json", action="store_true",
                   help="print the lines (and the start-up figures) as JSON instead of a table")
    args = p.parse_args()
    if args.buckets is None:
        args.buckets = args.workers
    if args.filter_buckets is None:
        args.filter_buckets = 2 * args.workers

    import tempfile

    import dask
    import distributed

    from robustloc.engines.cluster import WORKER_ENV, WORKER_MEMORY_BYTES

    work = Path(args.dir) if args.dir else Path(tempfile.mkdtemp(prefix="bench_dask-"))
    work.mkdir(parents=True, exist_ok=True)
    # the scheduler's, the workers' and a command's own cluster's scratch space inside the
    # work directory, removed with it (else dask leaves /tmp/dask-scratch-space behind)
    scratch = work / "dask-scratch"
    dask.config.set({"temporary-directory": str(scratch)})
    t0 = time.perf_counter()
    cluster = distributed.LocalCluster(n_workers=args.workers, threads_per_worker=1,
                                       memory_limit=WORKER_MEMORY_BYTES, env=dict(WORKER_ENV),
                                       dashboard_address=":0", local_directory=str(scratch))
    client = distributed.Client(cluster)
    lines: list[Line] = []
    try:
        startup = time.perf_counter() - t0
        t1 = time.perf_counter()
        warm_up(client, args, work)
        warm = time.perf_counter() - t1
        print(f"LocalCluster of {args.workers} workers up in {startup:.1f} s, warmed up in "
              f"{warm:.1f} s", file=sys.stderr)
        single_startup = measure_startup(args, work)
        for cmd, (su_s, su_c) in single_startup.items():
            print(f"single-process start-up of {cmd} ({STARTUP_ROWS:,} rows, one thread): "
                  f"{su_s:.1f} s, {su_c:.1f} CPU-s", file=sys.stderr)
        for n in parse_rows(args.rows):
            lines += bench_size(n, args, client, work, single_startup)
    finally:
        client.close()
        cluster.close()
        if not args.dir and not args.keep:
            shutil.rmtree(work, ignore_errors=True)
        elif not args.keep:
            shutil.rmtree(scratch, ignore_errors=True)
    if args.json:
        print(json.dumps({"cluster_startup_s": startup, "warm_up_s": warm,
                          "single_process_startup": {
                              cmd: {"wall_s": w, "cpu_s": c, "rows": STARTUP_ROWS}
                              for cmd, (w, c) in single_startup.items()},
                          "lines": [asdict(x) for x in lines]}, indent=2))
        return 0
    sw = max([len("step")] + [len(x.step) for x in lines])
    ew = max([len("engine")] + [len(x.engine) for x in lines])
    print(f"{'rows':>11} {'step':{sw}} {'engine':{ew}} {'wall s':>7} {'CPU s':>7} {'rows/s':>8} "
          f"{'units/s':>8} {'%/core':>6} {'%/CPU-s':>7} {'peak MiB':>8} {'load':>9} identical")
    for x in lines:
        pc = "" if x.per_core_pct is None else f"{x.per_core_pct:.0f}"
        pcs = "" if x.per_cpu_s_pct is None else f"{x.per_cpu_s_pct:.0f}"
        print(f"{x.rows:>11,} {x.step:{sw}} {x.engine:{ew}} {x.seconds:7.1f} {x.cpu_s:7.1f} "
              f"{x.rows_per_s:8.0f} {x.units_per_s:8.0f} {pc:>6} {pcs:>7} "
              f"{x.peak_rss_mib:8.0f} {x.load:>9} {x.identical}")
    print("units/s: epochs/s for locate, samples/s otherwise.  %/core: dask wall-clock "
          "throughput per worker as % of one process (meaningful on an idle machine); "
          "%/CPU-s: rows per CPU second of dask (workers + scheduler + client) as % of one "
          "process's (robust to other load).  peak MiB: the process, or the largest worker.")
    if single_startup:
        su = "; ".join(f"{cmd} {w:.1f} s, {c:.1f} CPU-s"
                       for cmd, (w, c) in single_startup.items())
        print(f"single process: wall and CPU seconds with the process's start-up taken off "
              f"(interpreter, imports, numba cache loads; measured as the same command on a "
              f"{STARTUP_ROWS:,}-row input, one thread, best of two: {su}), as the warm "
              "cluster has paid it already; the (cold) line is compared with the baseline "
              "as measured, start-up included.")
    return 0


if __name__ == "__main__":
    sys.exit(main())
