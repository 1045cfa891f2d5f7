"""Tags that come and go: the live service's memory and its ``--max-tags`` bound under
tag churn, with and without ``--forget-after``.

A site whose tags come and go (visitors' badges, pallets passing through) hears new tag
ids all the time.  Each wave here is ``--tags`` new ids, one epoch each (4 anchors, ranges
of a point inside the square), sent over HTTP in bodies of 5 000 rows; then the benchmark
waits until every epoch is solved and, with forgetting on, until the wave is forgotten.
Per wave it prints the rows accepted and refused, the tags held (``/api/status``), the
tags forgotten (``/metrics``) and the server's resident memory (``/proc/PID/status``).

Without forgetting (``--forget-after never``), the second wave is refused whole once the
first filled ``--max-tags``; with it, every wave is accepted and the memory levels off.

Each server has a store on disk (in a temporary folder): without one, the service keeps
every row and position in memory, which grows with the rows whatever happens to the tags.
Everything runs on 127.0.0.1, and the servers are stopped in a ``finally``.

Usage::

    python benchmarks/bench_serve_tags.py                     # 3 waves of 50 000, --track
    python benchmarks/bench_serve_tags.py --tags 100000 --waves 4 --max-tags 100000
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import httpx
import numpy as np

from robustloc.service.launch import ServerProcess
from robustloc.service.launch import read_metric as metric

ANCHORS = "anchor,x,y\nA1,0,0\nA2,20,0\nA3,20,20\nA4,0,20\n"
XY = np.array([[0, 0], [20, 0], [20, 20], [0, 20]], dtype=float)


def rss_mb(pid: int) -> float:
    """Resident set size of ``pid`` (MB)."""
    for ln in Path(f"/proc/{pid}/status").read_text().splitlines():
        if ln.startswith("VmRSS:"):
            return int(ln.split()[1]) / 1024
    return float("nan")


def bodies(wave: int, n_tags: int, rows_per_body: int, rng: np.random.Generator
           ) -> list[bytes]:
    """JSON bodies of ``n_tags`` new tags (ids unique to the wave), one epoch each."""
    p = rng.uniform(2, 18, (n_tags, 2))
    d = np.hypot(p[:, None, 0] - XY[:, 0], p[:, None, 1] - XY[:, 1])
    rows = [{"time": 0.0, "tag": f"w{wave}-{i}", "anchor": f"A{k + 1}",
             "range": round(float(d[i, k]), 3)} for i in range(n_tags) for k in range(4)]
    return [json.dumps(rows[j:j + rows_per_body]).encode()
            for j in range(0, len(rows), rows_per_body)]


def run(forget: str, args: argparse.Namespace) -> list[dict]:
    out = []
    with tempfile.TemporaryDirectory() as tmp:
        (Path(tmp) / "anchors.csv").write_text(ANCHORS)
        # (a store on disk: without one, the service keeps every row and position in
        # memory, which grows with the rows whatever happens to the tags)
        cmd = ["--anchors", str(Path(tmp) / "anchors.csv"), "--store", str(Path(tmp) / "st"),
               "--latency-window", "0",
               "--idle-flush", "0.5", "--max-tags", str(args.max_tags),
               "--forget-after", forget, "--log-level", "error"]
        if args.track:
            cmd.append("--track")
        s = ServerProcess(cmd).start()
        try:
            rng = np.random.default_rng(0)
            assert s.proc is not None
            pid = s.proc.pid
            solved = 0.0
            with httpx.Client(timeout=120) as c:
                for w in range(args.waves):
                    acc = rej = 0
                    for b in bodies(w, args.tags, 5000, rng):
                        r = c.post(s.url + "/api/measurements", content=b,
                                   headers={"content-type": "application/json"})
                        r.raise_for_status()
                        acc += r.json()["accepted"]
                        rej += r.json()["n_rejected"]
                    want = solved + acc / 4
                    deadline = time.monotonic() + 600
                    while (metric(s.url, "robustloc_positions_total") < want
                           and time.monotonic() < deadline):
                        time.sleep(0.5)
                    solved = metric(s.url, "robustloc_positions_total")
                    held_peak = c.get(s.url + "/api/status").json()["tags"]
                    rss_peak = rss_mb(pid)
                    if forget != "never":  # until the wave is forgotten (and counted)
                        deadline = time.monotonic() + float(forget) + 120
                        while ((c.get(s.url + "/api/status").json()["tags"] > 0
                                or metric(s.url, "robustloc_tags_forgotten_total")
                                < (w + 1) * args.tags)
                               and time.monotonic() < deadline):
                            time.sleep(0.5)
                    out.append({
                        "forget_after": forget, "wave": w + 1,
                        "rows_accepted": acc, "rows_refused": rej,
                        "tags_held_after_wave": held_peak,
                        "tags_held_after_wait": c.get(s.url + "/api/status").json()["tags"],
                        "tags_forgotten": int(metric(s.url, "robustloc_tags_forgotten_total")),
                        "rss_mb_after_wave": round(rss_peak, 1),
                        "rss_mb_after_wait": round(rss_mb(pid), 1),
                    })
                    print(out[-1], file=sys.stderr, flush=True)
        finally:
            s.stop()
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--tags", type=int, default=50_000, help="new tags per wave")
    ap.add_argument("--waves", type=int, default=3)
    ap.add_argument("--max-tags", type=int, default=50_000)
    ap.add_argument("--forget-after", default="5",
                    help="seconds (the run with forgetting; the other uses 'never')")
    ap.add_argument("--no-track", dest="track", action="store_false",
                    help="locate instead of --track")
    ap.add_argument("--json", action="store_true", help="print the rows as JSON")
    args = ap.parse_args(argv)
    rows = run("never", args) + run(args.forget_after, args)
    if args.json:
        print(json.dumps(rows, indent=1))
        return 0
    import pandas as pd

    print(pd.DataFrame(rows).to_string(index=False))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
