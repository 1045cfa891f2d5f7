"""Benchmark: streaming a large measurements file through io (bounded memory).

Writes a time-sorted measurements CSV (and Parquet) of ``--rows`` rows (10 anchors per
epoch, one tag), then in a fresh child process each

* streams it with :func:`robustloc.io.iter_epochs` (chunks of ``--chunk-rows``), and
* reads it whole with :func:`robustloc.io.read_measurements` + :func:`to_epochs`,

and prints rows/s and the child's peak resident memory.  Run:

    python benchmarks/bench_io.py --rows 10000000          # the issue's 10-million-row case
    python benchmarks/bench_io.py --rows 1000000 --skip-whole
"""

from __future__ import annotations

import argparse
import multiprocessing as mp
import resource
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import pandas as pd

from robustloc.options import positive_int


def _make(path: Path, rows: int, m: int = 10, block: int = 1_000_000) -> None:
    rng = np.random.default_rng(0)
    ids = np.array([str(i) for i in range(m)], dtype=object)
    first = True
    for start in range(0, rows, block):
        k = np.arange(start, min(start + block, rows))
        df = pd.DataFrame({
            "time": (k // m) * 0.1, "tag": "T1", "anchor": ids[k % m],
            "rssi": np.round(rng.normal(-60, 4, k.size), 1),
        })
        df.to_csv(path, mode="w" if first else "a", header=first, index=False)
        first = False


def _peak_mb() -> float:
    """Peak resident memory of this process (VmHWM; ru_maxrss survives fork/exec on Linux
    and would report the parent's peak)."""
    try:
        with open("/proc/self/status") as fh:
            for line in fh:
                if line.startswith("VmHWM:"):
                    return int(line.split()[1]) / 1024
    except OSError:
        pass
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def _stream(path: str, chunk_rows: int, q: mp.Queue) -> None:
    from robustloc.io import iter_epochs

    ids = [str(i) for i in range(10)]
    t0 = time.perf_counter()
    n_ep = 0
    for e in iter_epochs(path, ids, chunk_rows=chunk_rows):
        n_ep += e.n_epochs
    dt = time.perf_counter() - t0
    q.put((n_ep, dt, _peak_mb()))


def _whole(path: str, chunk_rows: int, q: mp.Queue) -> None:
    from robustloc.io import read_measurements, to_epochs

    t0 = time.perf_counter()
    e = to_epochs(read_measurements(path), [str(i) for i in range(10)])
    dt = time.perf_counter() - t0
    q.put((e.n_epochs, dt, _peak_mb()))


def _child(fn, *args) -> tuple[int, float, float]:
    ctx = mp.get_context("spawn")  # a fresh interpreter: peak memory is the work's own
    q = ctx.Queue()
    p = ctx.Process(target=fn, args=(*args, q))
    p.start()
    out = q.get()
    p.join()
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--rows", type=positive_int, default=2_000_000,
                    help="rows of the measurements file (10 anchors per epoch, one tag); "
                         ">= 1 (default: %(default)s)")
    ap.add_argument("--chunk-rows", type=positive_int, default=500_000,
                    help="rows per chunk of the streamed read (and per Parquet row group); "
                         ">= 1 (default: %(default)s)")
    ap.add_argument("--skip-whole", action="store_true", help="skip the read-whole comparison")
    args = ap.parse_args(argv)
    with tempfile.TemporaryDirectory() as tmp:
        csv = Path(tmp) / "m.csv"
        t0 = time.perf_counter()
        _make(csv, args.rows)
        size_mb = csv.stat().st_size / 2**20
        dt_make = time.perf_counter() - t0
        print(f"{args.rows:,} rows, {size_mb:.0f} MB CSV (written in {dt_make:.1f} s)")
        pq = Path(tmp) / "m.parquet"
        if args.rows <= 20_000_000:
            import pyarrow.csv as pacsv
            import pyarrow.parquet as papq

            papq.write_table(
                pacsv.read_csv(csv, convert_options=pacsv.ConvertOptions(
                    column_types={"anchor": "string", "tag": "string"})), pq,
                row_group_size=args.chunk_rows,
            )
        rows = []
        for label, fn, path in (
            ("stream csv", _stream, csv), ("stream parquet", _stream, pq),
            ("whole csv", _whole, csv),
        ):
            if label.startswith("whole") and args.skip_whole:
                continue
            if not path.exists():
                continue
            n_ep, dt, rss = _child(fn, str(path), args.chunk_rows)
            rows.append((label, n_ep, dt, args.rows / dt, rss))
        print(f"{'mode':16s} {'epochs':>10s} {'seconds':>8s} {'rows/s':>12s} {'peak RSS MB':>12s}")
        for label, n_ep, dt, rate, rss in rows:
            print(f"{label:16s} {n_ep:10,d} {dt:8.1f} {rate:12,.0f} {rss:12.0f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
