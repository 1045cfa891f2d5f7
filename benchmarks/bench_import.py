"""Import time of ``robustloc`` (target: ``import robustloc`` <= 0.3 s), peers side by side.

Each statement runs in a fresh interpreter (``python -c``), best and median of ``--repeat``
runs of the wall time, minus nothing (the interpreter's own start-up is the first row);
the last columns are the wall time minus the bare start-up and what
``python -X importtime`` attributes to the import itself (the
cumulative time of the top-level module, best run).  The machine is shared: compare rows
of one run, not runs of different days.

    python benchmarks/bench_import.py [--repeat 7]
"""

from __future__ import annotations

import argparse
import os
import re
import statistics
import subprocess
import sys
import time

CASES = [
    ("python start-up (baseline)", "pass", None),
    ("import robustloc", "import robustloc", "robustloc"),
    ("robustloc.__version__", "import robustloc; robustloc.__version__", "robustloc"),
    ("robustloc.locate (loads the API)", "import robustloc; robustloc.locate",
     "robustloc.api"),
    ("import numpy (peer)", "import numpy", "numpy"),
    ("import pandas (peer)", "import pandas", "pandas"),
    ("import scipy.optimize (peer)", "import scipy.optimize", "scipy.optimize"),
    ("import statsmodels.api (peer)", "import statsmodels.api", "statsmodels.api"),
]


def _wall(code: str, env: dict[str, str]) -> float:
    t0 = time.perf_counter()
    subprocess.run([sys.executable, "-c", code], check=True, env=env,
                   stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    return time.perf_counter() - t0


def _importtime(code: str, module: str, env: dict[str, str]) -> float:
    """Cumulative microseconds ``-X importtime`` reports for ``module`` (as seconds)."""
    res = subprocess.run([sys.executable, "-X", "importtime", "-c", code], check=True,
                         env=env, capture_output=True, text=True)
    best = 0.0
    for line in res.stderr.splitlines():
        m = re.match(r"import time:\s+\d+ \|\s+(\d+) \|(\s*)(\S+)$", line)
        if m and m.group(3) == module:
            best = max(best, int(m.group(1)) / 1e6)
    return best


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--repeat", type=int, default=7,
                    help="fresh interpreters per statement, best and median reported "
                         "(default: %(default)s)")
    args = ap.parse_args()
    env = dict(os.environ)
    print(f"{'statement':36s} {'best s':>8s} {'median s':>9s} {'best - start-up':>16s} "
          f"{'-X importtime s':>16s}")
    base = None
    for label, code, module in CASES:
        try:
            walls = [_wall(code, env) for _ in range(args.repeat)]
        except subprocess.CalledProcessError:
            print(f"{label:36s} {'(not installed)':>8s}")
            continue
        imp = "" if module is None else \
            f"{min(_importtime(code, module, env) for _ in range(3)):.3f}"
        base = min(walls) if base is None else base
        print(f"{label:36s} {min(walls):8.3f} {statistics.median(walls):9.3f} "
              f"{min(walls) - base:16.3f} {imp:>16s}")
    print("\ntarget: `python -c 'import robustloc'` <= 0.3 s; the import's own share is the "
          "last two columns (the rest is the interpreter's start-up)")


if __name__ == "__main__":
    main()
