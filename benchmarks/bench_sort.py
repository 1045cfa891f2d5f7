"""Sorting a measurements file whose rows are not in epoch order: in memory (pandas),
pyarrow (in memory, Arrow tables), DuckDB (external sort that spills to disk).

Each variant runs in its own process (peak RSS is per process); the table prints wall time
and peak RSS side by side, plus the streaming read of the same rows already sorted (the
floor).  Every variant reads, validates and pivots the whole file to epochs the same way
except ``pyarrow sort only`` (reading and sorting only: what pyarrow alone offers, with no
out-of-core path).

    python benchmarks/bench_sort.py --rows 2000000
"""

from __future__ import annotations

import argparse
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import pandas as pd

from robustloc.options import positive_int

VARIANTS = {
    "streamed (sorted file)": "stream",
    "pandas in memory": "memory",
    "pyarrow sort only": "pyarrow",
    "DuckDB out of core": "duckdb",
}


def _generate(path: Path, rows: int, shuffled: bool) -> None:
    """``rows`` rows, 4 anchors per epoch (the last epoch short when ``rows`` is not a
    multiple of 4)."""
    rng = np.random.default_rng(0)
    n_ep = -(-rows // 4)
    k = np.repeat(np.arange(n_ep), 4)[:rows]
    df = pd.DataFrame({"time": (k // 3) * 0.1, "tag": np.char.add("T", (k % 3).astype(str)),
                       "anchor": np.tile(np.array(list("abcd")), n_ep)[:rows],
                       "range": rng.uniform(1, 30, rows).round(3)})
    if shuffled:
        df = df.sample(frac=1, random_state=1)
    df.to_csv(path, index=False)


def _child(mode: str, path: str) -> None:
    from robustloc.io import iter_epochs

    t0 = time.perf_counter()
    n = 0
    if mode == "pyarrow":
        import pyarrow.csv as pacsv

        table = pacsv.read_csv(path).sort_by([("time", "ascending"), ("tag", "ascending")])
        n = table.num_rows
    else:
        order = {"stream": "auto", "memory": "sort", "duckdb": "sort"}[mode]
        budget = 0 if mode == "duckdb" else None
        for e in iter_epochs(path, list("abcd"), order=order, memory_budget_bytes=budget):
            n += e.n_epochs
    wall = time.perf_counter() - t0
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    print(f"{n} {wall:.2f} {rss:.0f}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--rows", type=positive_int, default=2_000_000,
                    help="rows of the measurements file, 4 anchors per epoch, 3 tags; any "
                         "count >= 1 (default: %(default)s)")
    ap.add_argument("--child", nargs=2, help=argparse.SUPPRESS)
    ap.add_argument("--gen", nargs=3, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.gen:
        _generate(Path(args.gen[0]), int(args.gen[1]), args.gen[2] == "1")
        return
    if args.child:
        _child(*args.child)
        return
    with tempfile.TemporaryDirectory() as tmp:
        shuffled, ordered = Path(tmp) / "shuffled.csv", Path(tmp) / "sorted.csv"
        for path, flag in ((shuffled, "1"), (ordered, "0")):  # in a child: keep RSS low
            subprocess.run([sys.executable, __file__, "--gen", str(path), str(args.rows), flag],
                           check=True)
        print(f"{args.rows} rows, 4 anchors per epoch, 3 tags; CSV "
              f"{shuffled.stat().st_size / 1e6:.0f} MB (machine shared: times are indicative)")
        print(f"{'variant':26s} {'wall s':>8s} {'peak RSS MB':>12s}")
        for name, mode in VARIANTS.items():
            src = ordered if mode == "stream" else shuffled
            # /usr/bin/time: a forked child's ru_maxrss starts at the parent's RSS
            r = subprocess.run(["/usr/bin/time", "-f", "%M", sys.executable, __file__,
                                "--child", mode, str(src)],
                               capture_output=True, text=True, check=True)
            _, wall, _ = r.stdout.split()
            rss = float(r.stderr.strip().splitlines()[-1]) / 1024
            print(f"{name:26s} {float(wall):8.1f} {float(rss):12.0f}")


if __name__ == "__main__":
    main()
