"""Live service benchmark (issue 12): ingest rate, latency, durability, malformed input.

Everything runs on 127.0.0.1, bounded in rows and seconds, and every process started here
(``robustloc serve``, Mosquitto) is stopped in a ``finally``.

Workload: ``--tags`` tags (default 1 000) x 8 anchors at ``--rate-hz`` (default 10 Hz) =
80 000 range rows/s; anchors on the corners and edge midpoints of a 60 m x 60 m square,
tags on random walks inside, ranges with N(0, 0.1 m) noise.  The bodies are encoded before
the clock starts so the client's JSON encoding does not compete with the server.

Sections (``--only`` picks some):

``store``      durable append of 8 000-row batches (sync per batch): the service's
               write-ahead log beside SQLite (WAL, synchronous=FULL) and DuckDB (if
               installed) - the measurement behind the store's design.
``http``       sustained ingest through batched POSTs (one 8 000-row body per tick),
               paced at the target rate for ``--seconds``: rows/s acknowledged, request
               p50/p99, position latency p50/p99 (epoch ready -> position stored and
               published, i.e. beyond the latency window), server CPU and peak RSS.
``capacity``   unpaced HTTP ingest (``--workers`` connections, each posting its next body as
               soon as the last is acknowledged) for ``--seconds``: the most rows/s the
               server acknowledges on this machine (the client shares it), with the
               request and position latency at that rate.
``mqtt``       the same rows published to Mosquitto (QoS 1, one message per tick per
               publisher) and ingested by the service's MQTT client.
``kill9``      POSTs in a loop, ``kill -9`` of the server mid-stream, restart on the same
               store: acknowledged rows missing from the store (must be 0); epochs whose
               rows were acknowledged but not solved are solved after the restart.
``malformed``  10 000 malformed messages (HTTP, WebSocket, MQTT): the server keeps serving
               and every one is counted in /metrics.
``replay``     robustloc replay of a simulated log == robustloc locate --robust-scale mad
               on the file (the service's default noise scale; both method auto).

Usage::

    python benchmarks/bench_serve.py                  # all sections, 20 s of ingest each
    python benchmarks/bench_serve.py --quick          # 8 s each, fewer malformed
    python benchmarks/bench_serve.py --only http,kill9 --seconds 30 --json
"""

from __future__ import annotations

import argparse
import json
import os
import sqlite3
import subprocess
import sys
import tempfile
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np
import pandas as pd

try:
    import orjson

    def dumps(obj: object) -> bytes:
        return orjson.dumps(obj)
except ImportError:  # pragma: no cover
    def dumps(obj: object) -> bytes:
        return json.dumps(obj).encode()

from robustloc.service.launch import ROBUSTLOC, MosquittoProcess, ServerProcess

ANCHORS = pd.DataFrame({
    "anchor": [f"A{i}" for i in range(8)],
    "x": [0.0, 30.0, 60.0, 60.0, 60.0, 30.0, 0.0, 0.0],
    "y": [0.0, 0.0, 0.0, 30.0, 60.0, 60.0, 60.0, 30.0],
})


def workload(n_tags: int, n_ticks: int, rate_hz: float, seed: int = 1,
             t0: float = 0.0) -> list[list[dict]]:
    """Rows per tick: ``n_tags * 8`` range rows each (random walks, 0.1 m noise)."""
    rng = np.random.default_rng(seed)
    pos = rng.uniform(5, 55, (n_tags, 2))
    a = ANCHORS[["x", "y"]].to_numpy()
    tags = [f"T{i:04d}" for i in range(n_tags)]
    ids = ANCHORS["anchor"].tolist()
    ticks = []
    for k in range(n_ticks):
        pos = np.clip(pos + rng.normal(0, 0.1, pos.shape), 1, 59)
        d = np.linalg.norm(pos[:, None, :] - a[None], axis=2) + rng.normal(0, 0.1, (n_tags, 8))
        t = round(t0 + k / rate_hz, 6)
        ticks.append([{"time": t, "tag": tags[i], "anchor": ids[j], "range": float(d[i, j])}
                      for i in range(n_tags) for j in range(8)])
    return ticks


def pct(x: list[float] | np.ndarray, q: float) -> float:
    return float(np.percentile(np.asarray(x), q)) if len(x) else float("nan")


def scrape(url: str) -> dict[str, float]:
    import httpx

    out: dict[str, float] = {}
    for ln in httpx.get(url + "/metrics", timeout=30).text.splitlines():
        if ln and not ln.startswith("#"):
            k, v = ln.rsplit(" ", 1)
            out[k] = float(v)
    return out


def total(m: dict[str, float], name: str) -> float:
    return sum(v for k, v in m.items() if k == name or k.startswith(name + "{"))


class ProcWatch:
    """CPU (% of one core) and peak RSS of a process, sampled every 0.5 s."""

    def __init__(self, pid: int) -> None:
        import psutil

        self.p = psutil.Process(pid)
        self.peak_rss = 0
        self._stop = threading.Event()
        self.t0 = time.monotonic()
        self.c0 = sum(self.p.cpu_times()[:2])
        self.th = threading.Thread(target=self._run, daemon=True)
        self.th.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                self.peak_rss = max(self.peak_rss, self.p.memory_info().rss)
            except Exception:
                return
            time.sleep(0.5)

    def stop(self) -> tuple[float, float]:
        self._stop.set()
        cpu = sum(self.p.cpu_times()[:2]) - self.c0
        self.cpu_s = cpu
        wall = time.monotonic() - self.t0
        return 100 * cpu / wall, self.peak_rss / 2**20


def write_anchors(d: Path) -> Path:
    p = d / "anchors.csv"
    ANCHORS.to_csv(p, index=False)
    return p


# --------------------------------------------------------------------------------------


def bench_store(tmp: Path, batches: int) -> list[dict]:
    """Durable append of 8 000-row batches, one sync per batch."""
    import pyarrow as pa

    from robustloc.service.engine import MEAS_SCHEMA
    from robustloc.service.store import SegmentLog

    rows = workload(1000, 1, 10)[0]
    n = len(rows)
    cols = {"time": np.array([r["time"] for r in rows]), "tag": [r["tag"] for r in rows],
            "anchor": [r["anchor"] for r in rows], "value": np.array([r["range"] for r in rows])}
    out = []
    log = SegmentLog(tmp / "wal", seal_rows=10**9)
    t = time.perf_counter()
    for _ in range(batches):
        log.append(pa.table({**cols, "arrival": np.zeros(n), "late": np.zeros(n, bool),
                             "source": ["http"] * n, "run": np.zeros(n, np.int64)},
                            schema=MEAS_SCHEMA))
    dt = time.perf_counter() - t
    log.close()
    out.append({"store": "robustloc WAL (Arrow IPC frames + fdatasync) -> Parquet",
                "rows/s": n * batches / dt, "ms/batch": 1000 * dt / batches})
    con = sqlite3.connect(tmp / "s.db", isolation_level=None)
    con.execute("PRAGMA journal_mode=WAL")
    con.execute("PRAGMA synchronous=FULL")
    con.execute("CREATE TABLE m (time REAL, tag TEXT, anchor TEXT, value REAL)")
    tup = list(zip(cols["time"].tolist(), cols["tag"], cols["anchor"], cols["value"].tolist()))
    t = time.perf_counter()
    for _ in range(batches):
        con.execute("BEGIN")
        con.executemany("INSERT INTO m VALUES (?, ?, ?, ?)", tup)
        con.execute("COMMIT")
    dt = time.perf_counter() - t
    con.close()
    out.append({"store": "SQLite WAL, synchronous=FULL, executemany", "rows/s": n * batches / dt,
                "ms/batch": 1000 * dt / batches})
    try:
        import duckdb
    except ImportError:
        out.append({"store": "DuckDB (not installed)", "rows/s": float("nan"),
                    "ms/batch": float("nan")})
    else:
        con = duckdb.connect(str(tmp / "d.duckdb"))
        con.execute("CREATE TABLE m (time DOUBLE, tag VARCHAR, anchor VARCHAR, value DOUBLE)")
        con.register("tab", pa.table(cols))
        t = time.perf_counter()
        for _ in range(batches):
            con.execute("INSERT INTO m SELECT * FROM tab")  # autocommit: WAL synced
        dt = time.perf_counter() - t
        con.close()
        out.append({"store": "DuckDB, INSERT from Arrow, autocommit",
                    "rows/s": n * batches / dt, "ms/batch": 1000 * dt / batches})
    return out


def _post_paced(url: str, bodies: list[bytes], rate_hz: float, workers: int,
                rows_per: int) -> dict:
    import httpx

    lat: list[float] = []
    acked = [0]
    errors: list[str] = []
    clients = threading.local()

    def send(b: bytes) -> None:
        c = getattr(clients, "c", None)
        if c is None:
            c = clients.c = httpx.Client(timeout=60)
        t = time.perf_counter()
        try:
            r = c.post(url + "/api/measurements", content=b,
                       headers={"Content-Type": "application/json"})
            if r.status_code == 202:
                acked[0] += r.json()["accepted"]
            else:
                errors.append(f"{r.status_code} {r.text[:80]}")
        except Exception as exc:  # recorded, the run goes on
            errors.append(repr(exc))
        lat.append(time.perf_counter() - t)

    t0 = time.perf_counter()
    with ThreadPoolExecutor(workers) as ex:
        futs = []
        for k, b in enumerate(bodies):
            due = t0 + k / rate_hz
            wait = due - time.perf_counter()
            if wait > 0:
                time.sleep(wait)
            futs.append(ex.submit(send, b))
        for f in futs:
            f.result()
    wall = time.perf_counter() - t0
    return {"rows_sent": rows_per * len(bodies), "rows_acked": acked[0], "wall_s": wall,
            "rows_per_s": acked[0] / wall, "req_p50_ms": 1000 * pct(lat, 50),
            "req_p99_ms": 1000 * pct(lat, 99), "errors": errors[:5], "n_errors": len(errors)}


def _post_unpaced(url: str, bodies: list[bytes], workers: int, rows_per: int,
                  seconds: float) -> dict:
    """``workers`` connections, each posting the next body as soon as its last one is
    acknowledged, for at most ``seconds`` (or until the bodies run out)."""
    import httpx

    lat: list[float] = []
    acked = [0]
    errors: list[str] = []
    nxt = [0]
    lock = threading.Lock()
    t0 = time.perf_counter()

    def run() -> None:
        with httpx.Client(timeout=60) as c:
            while time.perf_counter() - t0 < seconds:
                with lock:
                    k = nxt[0]
                    nxt[0] += 1
                if k >= len(bodies):
                    return
                t = time.perf_counter()
                try:
                    r = c.post(url + "/api/measurements", content=bodies[k],
                               headers={"Content-Type": "application/json"})
                    if r.status_code == 202:
                        with lock:
                            acked[0] += r.json()["accepted"]
                    else:
                        errors.append(f"{r.status_code} {r.text[:80]}")
                except Exception as exc:  # recorded, the run goes on
                    errors.append(repr(exc))
                lat.append(time.perf_counter() - t)

    ths = [threading.Thread(target=run) for _ in range(workers)]
    for th in ths:
        th.start()
    for th in ths:
        th.join()
    wall = time.perf_counter() - t0
    return {"rows_sent": rows_per * min(nxt[0], len(bodies)), "rows_acked": acked[0],
            "wall_s": wall, "rows_per_s": acked[0] / wall, "bodies_exhausted":
            nxt[0] >= len(bodies), "req_p50_ms": 1000 * pct(lat, 50),
            "req_p99_ms": 1000 * pct(lat, 99), "errors": errors[:5], "n_errors": len(errors)}


def _settle(url: str, expected_epochs: int, timeout: float) -> dict[str, float]:
    deadline = time.monotonic() + timeout
    m = scrape(url)
    while time.monotonic() < deadline:
        m = scrape(url)
        if total(m, "robustloc_positions_total") >= expected_epochs:
            break
        time.sleep(0.5)
    return m


def _latency(url: str) -> tuple[float, float]:
    import httpx

    s = httpx.get(url + "/api/status", timeout=30).json()
    return 1000 * (s["latency_p50_s"] or float("nan")), 1000 * (s["latency_p99_s"] or float("nan"))


def bench_http(tmp: Path, args) -> dict:
    n_ticks = int(args.seconds * args.rate_hz)
    ticks = workload(args.tags, n_ticks, args.rate_hz)
    bodies = [dumps(t) for t in ticks]
    del ticks
    anchors = write_anchors(tmp)
    with ServerProcess(["--anchors", str(anchors), "--store", str(tmp / "store-http"),
                        "--method", args.method, "--latency-window", str(args.window),
                        "--idle-flush", "1"]) as srv:
        subs = _Subscribers(srv.url, args.subscribers, args.ws_batch)
        try:
            watch = ProcWatch(srv.proc.pid)
            res = _post_paced(srv.url, bodies, args.rate_hz, args.workers, args.tags * 8)
            m = _settle(srv.url, args.tags * n_ticks, 60)
            cpu, rss = watch.stop()
            p50, p99 = _latency(srv.url)
        finally:
            res_ws = subs.stop()
    if args.subscribers:
        res.update(res_ws)
    res.update({"target_rows_per_s": args.tags * 8 * args.rate_hz, "server_cpu_pct": cpu,
                "server_cpu_us_per_row": 1e6 * watch.cpu_s / max(res["rows_acked"], 1),
                "server_peak_rss_mib": rss, "positions": total(m, "robustloc_positions_total"),
                "epochs_sent": args.tags * n_ticks, "pos_latency_p50_ms": p50,
                "pos_latency_p99_ms": p99, "late_rows": total(m, "robustloc_rows_late_total")})
    return res


class _Subscribers:
    """``n`` WebSocket clients of /ws/positions (as the map page), counting messages."""

    def __init__(self, url: str, n: int, batch: bool = False) -> None:
        from websockets.sync.client import connect

        self.count = [0] * n
        self.batch = batch
        self._stop = threading.Event()
        q = "?batch=1" if batch else ""
        self._socks = [connect(url.replace("http", "ws", 1) + "/ws/positions" + q,
                               max_size=2**26) for _ in range(n)]
        self._threads = [threading.Thread(target=self._run, args=(i,), daemon=True)
                         for i in range(n)]
        for th in self._threads:
            th.start()

    def _run(self, i: int) -> None:
        ws = self._socks[i]
        while not self._stop.is_set():
            try:
                msg = ws.recv(timeout=0.5)
            except TimeoutError:
                continue
            except Exception:  # closed
                return
            self.count[i] += len(json.loads(msg)) if self.batch else 1

    def stop(self) -> dict:
        self._stop.set()
        for th in self._threads:
            th.join(timeout=5)
        for ws in self._socks:
            ws.close()
        return {"ws_subscribers": len(self.count), "ws_batch": self.batch,
                "ws_rows_min": min(self.count, default=0)}


def bench_capacity(tmp: Path, args) -> dict:
    """Unpaced HTTP ingest: the most rows/s the server acknowledges (the client shares
    the machine), with its request and position latency."""
    n_ticks = int(args.seconds * args.rate_hz * args.capacity_factor)
    ticks = workload(args.tags, n_ticks, args.rate_hz, seed=4)
    bodies = [dumps(t) for t in ticks]
    del ticks
    anchors = write_anchors(tmp)
    with ServerProcess(["--anchors", str(anchors), "--store", str(tmp / "store-capacity"),
                        "--method", args.method, "--latency-window", str(args.window),
                        "--idle-flush", "1"]) as srv:
        watch = ProcWatch(srv.proc.pid)
        res = _post_unpaced(srv.url, bodies, args.workers, args.tags * 8, args.seconds)
        sent_epochs = res["rows_sent"] // 8
        m = _settle(srv.url, sent_epochs, 60)
        cpu, rss = watch.stop()
        p50, p99 = _latency(srv.url)
    res.update({"server_cpu_pct": cpu,
                "server_cpu_us_per_row": 1e6 * watch.cpu_s / max(res["rows_acked"], 1),
                "server_peak_rss_mib": rss, "positions": total(m, "robustloc_positions_total"),
                "epochs_sent": sent_epochs, "pos_latency_p50_ms": p50,
                "pos_latency_p99_ms": p99, "late_rows": total(m, "robustloc_rows_late_total"),
                # epochs whose every row came late: solved apart, published with late=true
                "late_epochs_solved": total(m, "robustloc_late_epochs_solved_total")})
    return res


def bench_mqtt(tmp: Path, args) -> dict:
    import paho.mqtt.client as mqtt

    n_ticks = int(args.seconds * args.rate_hz)
    ticks = workload(args.tags, n_ticks, args.rate_hz, seed=2)
    bodies = [dumps(t) for t in ticks]
    del ticks
    anchors = write_anchors(tmp)
    with MosquittoProcess() as broker, ServerProcess(
            ["--anchors", str(anchors), "--store", str(tmp / "store-mqtt"),
             "--method", args.method, "--latency-window", str(args.window),
             "--idle-flush", "1", "--mqtt", f"127.0.0.1:{broker.port}"]) as srv:
        pub = mqtt.Client(mqtt.CallbackAPIVersion.VERSION2)
        pub.max_inflight_messages_set(100)
        pub.connect("127.0.0.1", broker.port)
        pub.loop_start()
        try:
            deadline = time.monotonic() + 60  # wait for the service's subscription
            probe = dumps([{"time": -1.0, "tag": "probe", "anchor": "A0", "range": 1.0}])
            while total(scrape(srv.url), "robustloc_rows_accepted_total") == 0:
                if time.monotonic() > deadline:
                    raise RuntimeError("the service did not subscribe")
                pub.publish("robustloc/measurements/bench", probe, qos=1)
                time.sleep(0.5)
            time.sleep(1)
            base = total(scrape(srv.url), "robustloc_rows_accepted_total")
            watch = ProcWatch(srv.proc.pid)
            t0 = time.perf_counter()
            infos = []
            for k, b in enumerate(bodies):
                wait = t0 + k / args.rate_hz - time.perf_counter()
                if wait > 0:
                    time.sleep(wait)
                infos.append(pub.publish("robustloc/measurements/bench", b, qos=1))
            for i in infos:
                i.wait_for_publish(120)
            sent = args.tags * 8 * n_ticks
            deadline = time.monotonic() + 120
            while time.monotonic() < deadline:
                got = total(scrape(srv.url), "robustloc_rows_accepted_total") - base
                if got >= sent:
                    break
                time.sleep(0.2)
            wall = time.perf_counter() - t0
            m = _settle(srv.url, args.tags * n_ticks, 60)
            cpu, rss = watch.stop()
            p50, p99 = _latency(srv.url)
        finally:
            pub.loop_stop()
            pub.disconnect()
    return {"rows_sent": sent, "rows_acked": got, "wall_s": wall, "rows_per_s": got / wall,
            "target_rows_per_s": args.tags * 8 * args.rate_hz, "server_cpu_pct": cpu,
            "server_cpu_us_per_row": 1e6 * watch.cpu_s / max(got, 1),
            "server_peak_rss_mib": rss, "pos_latency_p50_ms": p50, "pos_latency_p99_ms": p99,
            "positions": total(m, "robustloc_positions_total")}


def bench_kill9(tmp: Path, args) -> dict:
    import httpx

    from robustloc.service.store import SegmentLog

    n_ticks = int(args.seconds * args.rate_hz)
    ticks = workload(args.tags, n_ticks, args.rate_hz, seed=3)
    anchors = write_anchors(tmp)
    store = tmp / "store-kill9"
    srv_args = ["--anchors", str(anchors), "--store", str(store), "--method", args.method,
                "--latency-window", str(args.window), "--idle-flush", "1"]
    acked_keys: list[tuple] = []
    lock = threading.Lock()
    srv = ServerProcess(srv_args)
    try:
        srv.start()
        stop = threading.Event()

        def sender(ks: list[int]) -> None:
            c = httpx.Client(timeout=30)
            for k in ks:
                if stop.is_set():
                    return
                try:
                    r = c.post(srv.url + "/api/measurements", content=dumps(ticks[k]))
                except Exception:
                    return  # the server died under us: this batch was not acknowledged
                if r.status_code == 202 and not r.json()["rejected"]:
                    with lock:
                        acked_keys.extend((x["time"], x["tag"], x["anchor"]) for x in ticks[k])

        ths = [threading.Thread(target=sender, args=(list(range(i, n_ticks, 3)),))
               for i in range(3)]
        for t in ths:
            t.start()
        time.sleep(args.seconds / 2)
        srv.kill9()
        stop.set()
        for t in ths:
            t.join()
        log = SegmentLog(store / "measurements", fsync=False)
        tab = log.scan(columns=["time", "tag", "anchor", "late"]).to_pandas()
        # epochs with a row in time: the ones solved live (a late row is stored and
        # counted, not solved live; 3 concurrent senders on a loaded machine make some)
        live = tab[~tab["late"].to_numpy(bool)]
        live_epochs = len(set(zip(live["time"].tolist(), live["tag"].tolist())))
        late_rows = int(tab["late"].sum())
        log.close()
        stored = set(zip(tab["time"].tolist(), tab["tag"].tolist(), tab["anchor"].tolist()))
        lost = sum(1 for k in acked_keys if k not in stored)
        t_restart = time.perf_counter()
        srv2 = ServerProcess(srv_args)
        try:
            srv2.start()
            restart_s = time.perf_counter() - t_restart
            epochs = live_epochs
            m = _settle(srv2.url, 1, 5)
            deadline = time.monotonic() + 120
            n_pos = 0
            while time.monotonic() < deadline:
                n_pos = len(httpx.get(srv2.url + "/api/positions",
                                      params={"limit": 10_000_000}, timeout=60).json())
                if n_pos >= epochs:
                    break
                time.sleep(1)
        finally:
            srv2.stop()
    finally:
        srv.stop()
    return {"rows_acked_before_kill": len(acked_keys), "rows_in_store": len(stored),
            "acked_rows_lost": lost, "restart_s": restart_s, "epochs_stored": epochs,
            "late_rows_in_store": late_rows,
            "epochs_solved_after_restart": n_pos, "metrics_after_restart": bool(m)}


def malformed_bodies(n: int, seed: int = 5) -> list[tuple[bytes, str]]:
    """(body, kind): kind "row" = one rejected row, "body" = one refused body."""
    rng = np.random.default_rng(seed)
    kinds = [
        (b'[{"time": "soon", "tag": "T", "anchor": "A0", "range": 1}]', "row"),
        (b'[{"time": 1, "tag": "", "anchor": "A0", "range": 1}]', "row"),
        (b'[{"time": 1, "tag": "T", "anchor": "nope", "range": 1}]', "row"),
        (b'[{"time": 1, "tag": "T", "anchor": "A0", "range": 1e9}]', "row"),
        (b'[{"time": 1, "tag": "T", "anchor": "A0", "rssi": -50}]', "row"),
        (b'[{"time": 1, "tag": "T", "anchor": "A0"}]', "row"),
        (b'[{"time": 1, "tag": {"a": 1}, "anchor": "A0", "range": 1}]', "row"),
        (b"[[1, 2, 3]]", "row"),
        (b'[{"time": NaN, "tag": "T", "anchor": "A0", "range": 1}]', "body"),
        (b"[1, 2", "body"),
        (b"42", "body"),
        (b"", "body"),
        (b"\xff\xfe garbage", "row"),  # one NDJSON line that is not JSON
    ]
    out = []
    for i in range(n):
        b, k = kinds[i % len(kinds)]
        if i % len(kinds) == 12:
            b = b"\xff" + bytes(rng.integers(0, 256, 30, dtype=np.uint8)).replace(b"\n", b"")
        out.append((b, k))
    return out


def bench_malformed(tmp: Path, args) -> dict:
    import httpx
    import paho.mqtt.client as mqtt
    from websockets.sync.client import connect

    anchors = write_anchors(tmp)
    msgs = malformed_bodies(args.malformed)
    with MosquittoProcess() as broker, ServerProcess(
            ["--anchors", str(anchors), "--mqtt", f"127.0.0.1:{broker.port}",
             "--value", "range"]) as srv:
        pub = mqtt.Client(mqtt.CallbackAPIVersion.VERSION2)
        pub.connect("127.0.0.1", broker.port)
        pub.loop_start()
        time.sleep(2)  # the service subscribes
        watch = ProcWatch(srv.proc.pid)
        c = httpx.Client(timeout=30)
        codes: dict[int, int] = {}
        t0 = time.perf_counter()
        try:
            with connect(srv.url.replace("http", "ws") + "/ws/measurements") as ws:
                infos = []
                for i, (b, _) in enumerate(msgs):
                    if i % 3 == 0:
                        r = c.post(srv.url + "/api/measurements", content=b)
                        codes[r.status_code] = codes.get(r.status_code, 0) + 1
                    elif i % 3 == 1:
                        ws.send(b.decode("utf-8", "replace") if b else " ")
                        ws.recv(timeout=30)
                    else:
                        infos.append(pub.publish("robustloc/measurements/x", b, qos=1))
                for inf in infos:
                    inf.wait_for_publish(60)
        finally:
            pub.loop_stop()
            pub.disconnect()
        time.sleep(1)
        wall = time.perf_counter() - t0
        m = scrape(srv.url)
        alive = srv.proc.poll() is None and c.get(srv.url + "/healthz").status_code == 200
        cpu, rss = watch.stop()
    counted = total(m, "robustloc_rows_rejected_total") + total(
        m, "robustloc_requests_rejected_total")
    return {"messages": len(msgs), "counted": counted, "server_alive": alive,
            "http_codes": codes, "wall_s": wall, "msgs_per_s": len(msgs) / wall,
            "accepted_by_mistake": total(m, "robustloc_rows_accepted_total")}


def bench_replay(tmp: Path, args) -> dict:
    from robustloc.commands.replay import replay

    d = tmp / "ble"
    subprocess.run([*ROBUSTLOC, "simulate", "ble-corridor", "--seed", "1", "--out", str(d)],
                   check=True, capture_output=True)
    out = tmp / "batch.parquet"
    subprocess.run([*ROBUSTLOC, "locate", str(d / "measurements.csv"), "--anchors",
                    str(d / "anchors.csv"), "-o", str(out), "--quiet", "--robust-scale", "mad"],
                   check=True, capture_output=True)
    import httpx

    want = pd.read_parquet(out)
    with ServerProcess(["--anchors", str(d / "anchors.csv"), "--idle-flush", "0.3"]) as srv:
        replay(str(d / "measurements.csv"), srv.url, speed=0)
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline:
            got = pd.DataFrame(httpx.get(srv.url + "/api/positions").json())
            if len(got) == len(want):
                break
            time.sleep(0.3)
    key = ["tag", "time"]
    g = got.sort_values(key).reset_index(drop=True)
    w = want.assign(tag=want["tag"].astype(str)).sort_values(key).reset_index(drop=True)
    diff = np.hypot(g["x"] - w["x"], g["y"] - w["y"]).max()
    return {"epochs": len(w), "max_position_difference_m": float(diff),
            "status_equal": bool((g["status"] == w["status"]).all())}


#: The sections, in the order they run (``--only`` picks some).
SECTIONS = ("store", "http", "capacity", "mqtt", "kill9", "malformed", "replay")


def parse_sections(text: str) -> set[str]:
    """``--only``: a comma-separated subset of :data:`SECTIONS`."""
    names = {t.strip() for t in text.split(",") if t.strip()}
    unknown = sorted(names - set(SECTIONS))
    if unknown:
        raise argparse.ArgumentTypeError(
            f"unknown section(s) {', '.join(unknown)}; choose from {', '.join(SECTIONS)}")
    if not names:
        raise argparse.ArgumentTypeError(f"no section named; choose from {', '.join(SECTIONS)}")
    return names


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter,
                                 epilog="Exit status: 0, or 1 when any section failed (its "
                                        "error is printed under the table / in the JSON).")
    ap.add_argument("--tags", type=int, default=1000,
                    help="tags, 8 range rows each per tick (default: %(default)s)")
    ap.add_argument("--rate-hz", type=float, default=10.0,
                    help="ticks per second of the paced ingest (default: %(default)s)")
    ap.add_argument("--seconds", type=float, default=20.0, help="ingest seconds per section")
    ap.add_argument("--method", default="huber",
                    help="robustloc serve --method: the server's estimator "
                         "(default: %(default)s)")
    ap.add_argument("--window", type=float, default=0.5, help="--latency-window of the server")
    ap.add_argument("--workers", type=int, default=4, help="concurrent HTTP connections")
    ap.add_argument("--malformed", type=int, default=10_000,
                    help="malformed section: messages sent (default: %(default)s)")
    ap.add_argument("--store-batches", type=int, default=100,
                    help="store section: 8 000-row batches appended per store "
                         "(default: %(default)s)")
    ap.add_argument("--subscribers", type=int, default=0,
                    help="http section: WebSocket clients of /ws/positions")
    ap.add_argument("--ws-batch", action="store_true",
                    help="the subscribers take ?batch=1 (one message per block, as the page)")
    ap.add_argument("--capacity-factor", type=float, default=2.5,
                    help="capacity section: bodies for this multiple of the paced rate")
    ap.add_argument("--only", type=parse_sections, default=",".join(SECTIONS),
                    help="comma-separated sections to run, from "
                         f"{', '.join(SECTIONS)} (default: all)")
    ap.add_argument("--quick", action="store_true", help="8 s sections, 2 000 malformed")
    ap.add_argument("--json", action="store_true",
                    help="print the results as JSON instead of the table")
    args = ap.parse_args(argv)
    if args.quick:
        args.seconds, args.malformed, args.store_batches = 8.0, 2000, 30
    only = args.only
    results: dict[str, object] = {"cpus": os.cpu_count(),
                                  "loadavg_at_start": os.getloadavg()}
    with tempfile.TemporaryDirectory() as td:
        tmp = Path(td)
        # in the order of SECTIONS
        for name, fn in (("store", lambda: bench_store(tmp, args.store_batches)),
                         ("http", lambda: bench_http(tmp, args)),
                         ("capacity", lambda: bench_capacity(tmp, args)),
                         ("mqtt", lambda: bench_mqtt(tmp, args)),
                         ("kill9", lambda: bench_kill9(tmp, args)),
                         ("malformed", lambda: bench_malformed(tmp, args)),
                         ("replay", lambda: bench_replay(tmp, args))):
            if name not in only:
                continue
            print(f"[{name}] ...", file=sys.stderr, flush=True)
            try:
                results[name] = fn()
            except Exception as exc:  # one failed section must not hide the others
                results[name] = {"error": f"{type(exc).__name__}: {exc}"}
            print(f"[{name}] {json.dumps(results[name], default=str)}", file=sys.stderr,
                  flush=True)
    results["loadavg_at_end"] = os.getloadavg()
    failed = [n for n in SECTIONS if isinstance(results.get(n), dict) and "error" in results[n]]
    if args.json:
        print(json.dumps(results, indent=2, default=str))
    else:
        report(results, args)
    if failed:
        print(f"failed section(s): {', '.join(failed)}", file=sys.stderr)
        return 1
    return 0


def report(r: dict, args) -> None:
    def f(x, fmt="{:,.0f}"):
        return "-" if x is None or (isinstance(x, float) and np.isnan(x)) else fmt.format(x)

    print(f"robustloc serve benchmark - {r['cpus']} CPUs, load average at start "
          f"{r['loadavg_at_start'][0]:.1f} (machine shared with other jobs)")
    if "store" in r and isinstance(r["store"], list):
        print("\nDurable append, 8 000-row batches, one sync per batch")
        print(f"{'store':58s} {'rows/s':>12s} {'ms/batch':>9s}")
        for s in r["store"]:
            print(f"{s['store']:58s} {f(s['rows/s']):>12s} {f(s['ms/batch'], '{:.2f}'):>9s}")
    print(f"\n{'target':52s} {'measured':>22s}")
    h, q, c = r.get("http", {}), r.get("mqtt", {}), r.get("capacity", {})
    k, m, p = r.get("kill9", {}), r.get("malformed", {}), r.get("replay", {})
    def pair(d: dict, a: str, b: str) -> str:
        return f"{f(d.get(a), '{:.0f}')} / {f(d.get(b), '{:.0f}')}"

    rows = [
        (f"HTTP ingest {args.tags} tags x 8 at {args.rate_hz:g} Hz (rows/s)",
         f(h.get("rows_per_s"))),
        ("  server position latency p50 / p99 beyond window (ms)",
         pair(h, "pos_latency_p50_ms", "pos_latency_p99_ms")),
        ("  request p50 / p99 (ms)",
         pair(h, "req_p50_ms", "req_p99_ms")),
        ("  server CPU (% of a core) / peak RSS (MiB)",
         f"{f(h.get('server_cpu_pct'))} / {f(h.get('server_peak_rss_mib'))}"),
        ("  server CPU per row, incl. solving (us)", f(h.get("server_cpu_us_per_row"), "{:.1f}")),
        ("  positions / epochs sent", f"{f(h.get('positions'))} / {f(h.get('epochs_sent'))}"),
        (f"  WebSocket position rows, fewest of {h.get('ws_subscribers', 0)} subscribers"
         + (" (batch=1)" if h.get("ws_batch") else ""), f(h.get("ws_rows_min"))),
        ("HTTP capacity, unpaced (rows/s acknowledged)",
         f(c.get("rows_per_s")) + (" (all sent)" if c.get("bodies_exhausted") else "")),
        ("  request p50 / p99 (ms)", pair(c, "req_p50_ms", "req_p99_ms")),
        ("  position latency p50 / p99 beyond window (ms)",
         pair(c, "pos_latency_p50_ms", "pos_latency_p99_ms")),
        ("  server CPU (% of a core) / per row (us)",
         f"{f(c.get('server_cpu_pct'))} / {f(c.get('server_cpu_us_per_row'), '{:.1f}')}"),
        ("  positions / epochs sent", pair(c, "positions", "epochs_sent")),
        ("  late rows / late epochs solved apart", pair(c, "late_rows", "late_epochs_solved")),
        ("MQTT ingest (rows/s)", f(q.get("rows_per_s"))),
        ("  position latency p50 / p99 (ms)",
         pair(q, "pos_latency_p50_ms", "pos_latency_p99_ms")),
        ("  server CPU (%) / peak RSS (MiB)",
         f"{f(q.get('server_cpu_pct'))} / {f(q.get('server_peak_rss_mib'))}"),
        ("  server CPU per row, incl. solving (us)", f(q.get("server_cpu_us_per_row"), "{:.1f}")),
        ("kill -9: acknowledged rows lost (target 0)",
         f"{f(k.get('acked_rows_lost'))} of {f(k.get('rows_acked_before_kill'))}"),
        ("  epochs solved after restart / stored in time",
         f"{f(k.get('epochs_solved_after_restart'))} / {f(k.get('epochs_stored'))}"),
        ("malformed messages counted / sent (server alive)",
         f"{f(m.get('counted'))} / {f(m.get('messages'))} ({m.get('server_alive')})"),
        ("replay == batch: max position difference (m)",
         f(p.get("max_position_difference_m"), "{:.1e}")),
    ]
    for a, b in rows:
        print(f"{a:52s} {b:>22s}")
    for name in SECTIONS:
        if isinstance(r.get(name), dict) and "error" in r[name]:
            print(f"{name}: {r[name]['error']}")


if __name__ == "__main__":
    sys.exit(main())
