"""Live service: ``GET /api/positions`` reads bounded (the serve review).

Every query read the whole positions log into a frame, and encoded its JSON body on the
event loop: 8 queries at once over a store of 125 000 positions raised the server's peak
by 660-680 MiB and held ``/healthz`` for up to 2.6 s and a POST of rows for up to 4.2 s.
Now at most
:data:`~robustloc.service.defaults.MAX_CONCURRENT_POSITION_READS` queries are read and
encoded at once, in worker threads of their own (not anyio's default pool, which ingest
uses), and a query reads every column of the rows it answers only.

The replies must not change: a real ``robustloc serve`` on a free loopback port answers
queries over a store written here, whose rows the test knows one by one (several sealed
segments and an unsealed log, epochs re-solved after a restart, two runs of a tag, a
column some segments lack), and each reply is checked against the rows the query must
answer, built from that list.
"""

from __future__ import annotations

import asyncio
import json
import threading
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import pandas as pd
import pytest

pytest.importorskip("starlette")
pytest.importorskip("uvicorn")
httpx = pytest.importorskip("httpx")
pa = pytest.importorskip("pyarrow")

from robustloc.service.defaults import MAX_CONCURRENT_POSITION_READS  # noqa: E402
from robustloc.service.engine import Engine  # noqa: E402
from robustloc.service.processor import LocateProcessor  # noqa: E402
from robustloc.service.store import SegmentLog  # noqa: E402

ANCHORS = pd.DataFrame({"anchor": ["A1", "A2", "A3", "A4"], "x": [0.0, 10.0, 10.0, 0.0],
                        "y": [0.0, 0.0, 10.0, 10.0]})


# --------------------------------------------------------------------------------------
# concurrency: bounded, and off the default thread pool
# --------------------------------------------------------------------------------------


def test_positions_reads_are_bounded_and_leave_the_default_pool_to_ingest(monkeypatch):
    """In process (as the bound on row-by-row parses is tested): more positions queries
    than anyio's default pool has threads, each held in its read until released.  At most
    ``MAX_CONCURRENT_POSITION_READS`` read at once, none takes a thread of the default
    pool, and a POST of rows and ``/healthz`` are answered while they are all held (each
    query took a default-pool thread: the POST then waited for a free one)."""
    import anyio

    import robustloc.service.app as app_mod

    eng = Engine(ANCHORS, LocateProcessor(ANCHORS, method="nls"), latency_window_s=0.0,
                 idle_flush_s=600.0, fsync=False, value="range")
    real = eng.positions_counted
    lock, now, most, pool_used = threading.Lock(), [0], [0], []
    release = threading.Event()

    def held_read(*args):
        with lock:
            now[0] += 1
            most[0] = max(most[0], now[0])
        pool_used.append(anyio.from_thread.run_sync(
            lambda: anyio.to_thread.current_default_thread_limiter().borrowed_tokens))
        release.wait(60)  # (a bound: a test that fails does not hang)
        with lock:
            now[0] -= 1
        return real(*args)

    monkeypatch.setattr(eng, "positions_counted", held_read)
    app = app_mod.create_app(eng)
    row = json.dumps([{"time": 1.0, "tag": "T", "anchor": a, "range": 5.0}
                      for a in ANCHORS["anchor"]])

    async def main():
        n = int(anyio.to_thread.current_default_thread_limiter().total_tokens) + 1
        transport = httpx.ASGITransport(app=app)
        async with httpx.AsyncClient(transport=transport, base_url="http://t",
                                     timeout=120) as client:
            queries = [asyncio.ensure_future(client.get("/api/positions"))
                       for _ in range(n)]
            while not pool_used:  # the first reads are held
                await asyncio.sleep(0.01)
            try:
                with anyio.fail_after(30):  # (a bound on a hang, not a speed)
                    post = await client.post("/api/measurements", content=row)
                    health = await client.get("/healthz")
                held = now[0]
            finally:
                release.set()
            return n, post, health, held, await asyncio.gather(*queries)

    try:
        n, post, health, held, answers = asyncio.run(main())
    finally:
        release.set()
        eng.stop()
    assert post.status_code == 202 and post.json()["accepted"] == len(ANCHORS)
    assert health.status_code == 200
    assert held == MAX_CONCURRENT_POSITION_READS  # (the others wait, holding no thread)
    assert [r.status_code for r in answers] == [200] * n
    assert most[0] == MAX_CONCURRENT_POSITION_READS
    assert pool_used and set(pool_used) == {0}


class _HeldReads:
    """``Engine.positions_counted`` held in its thread until :attr:`release` is set,
    counting the reads begun (an app of :func:`create_app` in process)."""

    def __init__(self, monkeypatch) -> None:
        import robustloc.service.app as app_mod

        self.eng = Engine(ANCHORS, LocateProcessor(ANCHORS, method="nls"),
                          latency_window_s=0.0, idle_flush_s=600.0, fsync=False,
                          value="range")
        real = self.eng.positions_counted
        self.lock, self.begun, self.release = threading.Lock(), [0], threading.Event()

        def held_read(*args):
            with self.lock:
                self.begun[0] += 1
            self.release.wait(60)  # (a bound: a test that fails does not hang)
            return real(*args)

        monkeypatch.setattr(self.eng, "positions_counted", held_read)
        self.app = app_mod.create_app(self.eng)

    async def request(self, gone: asyncio.Event | None = None) -> dict:
        """``GET /api/positions`` as uvicorn calls the app: the request, and
        ``http.disconnect`` once ``gone`` is set (at once when it is); returns the
        status, the headers and the body sent (``None`` before ``http.response.start``)."""
        scope = {"type": "http", "asgi": {"version": "3.0"}, "http_version": "1.1",
                 "method": "GET", "scheme": "http", "path": "/api/positions",
                 "raw_path": b"/api/positions", "query_string": b"", "root_path": "",
                 "headers": [(b"host", b"t")], "client": ("127.0.0.1", 5),
                 "server": ("127.0.0.1", 80)}
        sent: dict = {"status": None, "headers": {}, "body": b""}
        first = [True]
        gone = gone or asyncio.Event()

        async def receive() -> dict:  # (as uvicorn's: a client gone is told first)
            if first[0] and not gone.is_set():
                first[0] = False
                return {"type": "http.request", "body": b"", "more_body": False}
            await gone.wait()
            return {"type": "http.disconnect"}

        async def send(msg: dict) -> None:
            if msg["type"] == "http.response.start":
                sent["status"] = msg["status"]
                sent["headers"] = {k.decode(): v.decode() for k, v in msg["headers"]}
            else:
                sent["body"] += msg.get("body", b"")

        await self.app(scope, receive, send)
        return sent

    async def until_begun(self, n: int) -> None:
        with anyio_fail_after(30):
            while self.begun[0] < n:
                await asyncio.sleep(0.01)


def anyio_fail_after(seconds: float):
    """:func:`anyio.fail_after` (a bound on a hang, not a speed)."""
    import anyio

    return anyio.fail_after(seconds)


def test_positions_queries_waiting_at_shutdown_are_answered_503(monkeypatch):
    """The stop's ``--shutdown-grace`` ran out while positions queries waited for a read
    slot (uvicorn cancels them): each was answered a plain-text 500 with a
    ``CancelledError ... acquire`` traceback (the serve review: 8 of 12 queries).  Now
    the ones waiting, which hold nothing, get ``503`` with a JSON reason and
    ``Retry-After`` (as a body still arriving), counted as ``shutting_down``, and are not
    read; the ones reading are read to the end and answered, or ``503`` when the event
    loop itself ends first (a second cancellation)."""
    held = _HeldReads(monkeypatch)
    n_wait = 3

    async def main():
        tasks = [asyncio.ensure_future(held.request())
                 for _ in range(MAX_CONCURRENT_POSITION_READS + n_wait)]
        await held.until_begun(MAX_CONCURRENT_POSITION_READS)
        await asyncio.sleep(0.2)  # (the others wait for a slot)
        for t in tasks:  # the grace runs out
            t.cancel("Task cancelled, timeout graceful shutdown exceeded")
        await asyncio.sleep(0.2)
        reading = [t for t in tasks if not t.done()]
        for t in reading[:1]:  # the event loop ends: the others' are cancelled again
            t.cancel()
        await asyncio.sleep(0.2)
        held.release.set()
        with anyio_fail_after(30):
            return reading, await asyncio.gather(*tasks)

    try:
        reading, answers = asyncio.run(main())
    finally:
        held.release.set()
        held.eng.stop()
    assert len(reading) == MAX_CONCURRENT_POSITION_READS  # (not ended by the cancel)
    assert held.begun[0] == MAX_CONCURRENT_POSITION_READS  # (the waiting: not read)
    stopping = [a for a in answers if a["status"] == 503]
    assert len(stopping) == n_wait + 1, [a["status"] for a in answers]
    for a in stopping:
        assert a["headers"]["content-type"] == "application/json"
        assert a["headers"]["retry-after"] == "5"
        assert "the service is stopping" in json.loads(a["body"])["error"]
    done = [a for a in answers if a["status"] == 200]
    assert len(done) == MAX_CONCURRENT_POSITION_READS - 1
    assert all(json.loads(a["body"]) == [] for a in done)
    assert held.eng.metrics.requests_rejected.get("shutting_down") == n_wait + 1


def test_positions_query_whose_client_left_while_it_waited_is_not_read(monkeypatch):
    """A query whose client disconnected while it waited for a read slot was read and
    encoded for nobody, and the queries behind it waited for that (the serve review: a
    ``limit=1`` query waited 12.4 s behind 16 abandoned ones).  Now it is not read:
    counted as ``client_disconnect``; a query whose client stays is read and answered."""
    held = _HeldReads(monkeypatch)

    async def main():
        first = [asyncio.ensure_future(held.request())
                 for _ in range(MAX_CONCURRENT_POSITION_READS)]
        await held.until_begun(MAX_CONCURRENT_POSITION_READS)
        gone = asyncio.Event()
        left = [asyncio.ensure_future(held.request(gone)) for _ in range(3)]
        stays = asyncio.ensure_future(held.request())
        await asyncio.sleep(0.2)  # (all waiting for a slot)
        gone.set()  # their clients leave
        await asyncio.sleep(0.1)
        held.release.set()
        with anyio_fail_after(30):
            return (await asyncio.gather(*first), await asyncio.gather(*left),
                    await stays)

    try:
        first, left, stays = asyncio.run(main())
    finally:
        held.release.set()
        held.eng.stop()
    assert [a["status"] for a in first] == [200] * MAX_CONCURRENT_POSITION_READS
    assert stays["status"] == 200 and json.loads(stays["body"]) == []
    assert held.begun[0] == MAX_CONCURRENT_POSITION_READS + 1  # (not the 3 that left)
    assert held.eng.metrics.requests_rejected.get("client_disconnect") == 3
    assert all(a["body"] == b"" for a in left)


# --------------------------------------------------------------------------------------
# the replies: as before, over a store of several parts
# --------------------------------------------------------------------------------------


def _stored_rows() -> list[dict]:
    """Position rows as a store holds them, in their order: tags A, B, C at times 0 ..
    29; A's epochs 10 .. 19 solved again after a restart (the later row holds, its x
    differs); C re-based at time 25 (a second run at times 0 .. 4, as many epochs as
    the first run's); the first 40 rows without ``n_used`` (an earlier version's rows:
    null in the query)."""
    rows = []
    for t in range(30):
        for tag in ("B", "A", "C"):
            rows.append({"time": float(t), "tag": tag, "x": t + 0.25, "y": 1.0,
                         "method": "nls", "status": "ok", "n_used": 4, "run": 0})
        if t == 25:
            rows += [{"time": float(k), "tag": "C", "x": 100.0 + k, "y": 2.0,
                      "method": "nls", "status": "ok", "n_used": 3, "run": 1}
                     for k in range(5)]
    rows += [{"time": float(t), "tag": "A", "x": t + 0.5, "y": 1.0, "method": "nls",
              "status": "ok", "n_used": 4, "run": 0} for t in range(10, 20)]
    for r in rows[:40]:
        r["n_used"] = None
    return rows


def _expected(rows: list[dict], tag: str | None, since: float | None,
              until: float | None, limit: int) -> tuple[list[dict], int]:
    """What a query answers, from the rows themselves: the rows matching, each epoch
    ``(time, tag, method, run)`` once (its last row), sorted by time then tag (store
    order among equals), the latest ``limit``; and how many matched."""
    match = [r for r in rows if (tag is None or r["tag"] == tag)
             and (since is None or r["time"] >= since)
             and (until is None or r["time"] <= until)]
    last = {(r["time"], r["tag"], r["method"], r["run"]): i for i, r in enumerate(match)}
    kept = sorted((i for i in last.values()),
                  key=lambda i: (match[i]["time"], match[i]["tag"], i))
    return [{k: v for k, v in match[i].items() if k != "run"} for i in kept][-limit:], len(kept)


@pytest.fixture(scope="module")
def store_server(tmp_path_factory):
    """A real server on a store holding :func:`_stored_rows`: sealed segments (12 rows
    each, written by a log of ``seal_rows`` 12) and an unsealed log of the last 9 rows
    (sealed when the server opens the store)."""
    from robustloc.service.launch import ServerProcess

    d: Path = tmp_path_factory.mktemp("posreads")
    rows = _write_store(d)
    s = ServerProcess(["--anchors", str(d / "anchors.csv"), "--store", str(d / "store"),
                       "--value", "range"])
    s.start()
    try:
        yield s, rows
    finally:
        s.stop()


def _write_store(d: Path) -> list[dict]:
    """``d/anchors.csv``, and ``d/store`` holding :func:`_stored_rows` (returned): sealed
    segments of 12 rows and an unsealed log of the last 9 rows."""
    ANCHORS.to_csv(d / "anchors.csv", index=False)
    rows = _stored_rows()
    log = SegmentLog(d / "store" / "positions", seal_rows=12, fsync=False)
    try:
        # blocks as the solver appends them; the first ones of the old schema (no
        # ``n_used``, no ``run``), as a store of an earlier version holds
        for i in range(0, len(rows), 4):
            block = pd.DataFrame(rows[i:i + 4])
            if i < 40:
                block = block.drop(columns=["n_used", "run"])
            else:
                block["n_used"] = block["n_used"].astype("int64")
            log.append(pa.Table.from_pandas(block, preserve_index=False))
        log.wait_sealed()
        assert len(list((d / "store" / "positions").glob("*.parquet"))) > 5
        assert 0 < sum(len(t) for ts in log._memory.values() for t in ts)  # (a tail)
    finally:
        log.close()
    return rows


QUERIES = [(tag, since, until, limit)
           for tag in (None, "A", "C", "nobody")
           for since, until in ((None, None), (12.0, None), (None, 14.5), (3.0, 3.0))
           for limit in (1, 4, 31, None)]


def test_positions_replies_are_the_rows_the_query_must_answer(store_server):
    """Rows, their order, the re-solved epochs once (the last), both runs of C, and the
    headers, for every combination of tag, since, until and limit; a count column with
    nulls among the matching rows (re-solved ones included) is a float in every reply
    (``4.0``: as when every matching row was read into one frame), also when the rows
    answered have none."""
    s, rows = store_server
    with httpx.Client(base_url=s.url, timeout=60) as c:
        for tag, since, until, limit in QUERIES:
            q = {k: v for k, v in (("tag", tag), ("since", since), ("until", until),
                                   ("limit", limit)) if v is not None}
            r = c.get("/api/positions", params=q)
            assert r.status_code == 200, (q, r.text)
            want, total = _expected(rows, tag, since, until, limit or 100_000)
            got = r.json()
            assert [(p["time"], p["tag"], p["x"]) for p in got] == \
                [(p["time"], p["tag"], p["x"]) for p in want], q
            assert got == want, q
            assert r.headers["x-total-count"] == str(total), q
            assert r.headers.get("x-truncated") == ("true" if total > len(got) else None), q
            # (a row of the matching ones, re-solved or not, without a count)
            nulls = any(r["n_used"] is None for r in rows
                        if (tag is None or r["tag"] == tag)
                        and (since is None or r["time"] >= since)
                        and (until is None or r["time"] <= until))
            assert all(isinstance(p["n_used"], float if nulls else int) for p in got
                       if p["n_used"] is not None), q
    assert any(_expected(rows, *q[:3], 100_000)[1] > 31 for q in QUERIES)  # (truncated)


def test_concurrent_positions_queries_get_the_same_reply(store_server):
    """Eight queries at once (most wait their turn): each the same bytes and headers as
    the same query alone."""
    s, _ = store_server
    alone = httpx.get(s.url + "/api/positions?since=5&limit=40", timeout=60)
    with ThreadPoolExecutor(8) as ex:
        replies = list(ex.map(lambda _: httpx.get(s.url + "/api/positions?since=5&limit=40",
                                                   timeout=60), range(8)))
    for r in replies:
        assert r.status_code == 200 and r.content == alone.content
        assert r.headers["x-total-count"] == alone.headers["x-total-count"]
        assert r.headers.get("x-truncated") == alone.headers.get("x-truncated") == "true"
    assert len(alone.json()) == 40


def test_damaged_segment_is_named_in_the_reply(tmp_path):
    """A sealed segment cut while the service runs: every positions query was answered
    ``500 {"error": "internal error: StoreError"}`` with a traceback in the log, the
    store's own reason (the file, what is wrong) never reached the client.  Now ``500``
    with that reason, counted as ``store_error``, one log line (not one per query), and
    the service goes on (``/healthz``)."""
    import os

    from robustloc.service.launch import ServerProcess, read_metric

    _write_store(tmp_path)
    with ServerProcess(["--anchors", str(tmp_path / "anchors.csv"), "--store",
                        str(tmp_path / "store"), "--value", "range"]) as s:
        assert httpx.get(s.url + "/api/positions?limit=1", timeout=60).status_code == 200
        seg = sorted((tmp_path / "store" / "positions").glob("seg-*.parquet"))[2]
        os.truncate(seg, seg.stat().st_size // 2)
        errors = read_metric(s.url, 'robustloc_requests_rejected_total{reason="store_error"}')
        for q in ("limit=1", "tag=A&limit=5", "since=3&until=20"):
            r = httpx.get(s.url + "/api/positions?" + q, timeout=60)
            assert r.status_code == 500, (q, r.text)
            why = r.json()["error"]
            assert why.startswith(f"{seg}: damaged Parquet segment of the store"), why
        assert read_metric(
            s.url, 'robustloc_requests_rejected_total{reason="store_error"}') == errors + 3
        assert httpx.get(s.url + "/healthz").status_code == 200
        log = s.log()
    assert "Traceback" not in log, log
    assert log.count(f"{seg}: damaged Parquet segment") == 1, log


# --------------------------------------------------------------------------------------
# unsealed rows: a filter copies the columns asked for only
# --------------------------------------------------------------------------------------

_UNSEALED_SCAN = """
import sys, tempfile
import numpy as np, pyarrow as pa, pyarrow.dataset as ds
from robustloc.service.engine import _MemoryLog
from robustloc.service.store import SegmentLog
kind = sys.argv[1]
log = (_MemoryLog() if kind == "memory" else
       SegmentLog(tempfile.mkdtemp() + "/p", seal_rows=10**8, fsync=False))
n, rng = 200_000, np.random.default_rng(1)
for i in range(0, n, 5000):
    k = np.arange(i, i + 5000)
    log.append(pa.table({"time": k * 0.1, "tag": pa.array([f"t{j % 50}" for j in k]),
                         **{f"c{j}": rng.normal(size=5000) for j in range(12)}}))
snap = log.snapshot()
pool = pa.default_memory_pool()
base = pool.bytes_allocated()
expr = (ds.field("time") >= n * 0.05) & (ds.field("tag") != "t3")
got = snap.scan(columns=["time", "c0"], expression=expr)
peak = pool.max_memory() - base
rows = snap.scan()  # (every row: the store's are all unsealed)
assert rows.num_rows == n
assert got.equals(rows.filter(expr).select(["time", "c0"])), "not the rows of a filter"
whole = snap.scan(columns=["tag", "time"], expression=ds.field("time") >= 0)
assert whole.equals(rows.select(["tag", "time"])), "not every row"
print(peak)
"""


@pytest.mark.parametrize("kind", ["memory", "store"])
def test_filtered_scan_of_unsealed_rows_copies_the_columns_asked_for(kind):
    """A scan with a filter over rows held in memory (a service without ``--store``, or
    the store's log not yet sealed) filtered every column, then kept those asked for:
    the first pass of a ``since`` query over 1 000 000 rows took 134 MiB of Arrow memory
    (23 MiB without a filter).  Now the columns asked for are filtered only (the
    expression read over the columns it names), none when every row is kept: here 2 of
    14 columns, half of 200 000 rows kept.  A fresh interpreter: Arrow's peak is the
    process's."""
    import subprocess
    import sys

    out = subprocess.run([sys.executable, "-c", _UNSEALED_SCAN, kind], capture_output=True,
                         text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    peak = int(out.stdout.split()[-1])
    # all 14 columns of the 100 000 rows kept: 11 MB (the old filter); 2 of them: 1.6 MB
    assert peak < 4 * 2**20, peak


# --------------------------------------------------------------------------------------
# the body's encoder
# --------------------------------------------------------------------------------------


@pytest.mark.parametrize("n", [0, 1, 8191, 8192, 8193, 20_000])
def test_chunked_body_is_the_array_json_bytes(n):
    """:func:`_array_json_bytes` (chunks of 8 192 rows) gives :func:`_array_json`'s bytes:
    rows of several columns, and rows without columns (their chunks encode to nothing:
    over 8 192 such rows it gave ``[,,]``, not ``[]``)."""
    import numpy as np

    from robustloc.service.app import _array_json, _array_json_bytes

    frame = pd.DataFrame({"time": np.arange(n) * 0.1, "tag": ["A"] * n,
                          "x": np.where(np.arange(n) % 7 == 0, np.nan, 1.5)})
    assert _array_json_bytes(frame) == _array_json(frame).encode()
    bare = frame[[]]  # (the rows, no column)
    assert len(bare) == n
    assert _array_json_bytes(bare) == _array_json(bare).encode() == b"[]"


def test_a_segment_damaged_before_any_read_of_its_schema_is_named(tmp_path):
    """A segment sealed while the service runs and damaged before any query read its
    schema: the read of its footer raised Arrow's own error (``ArrowInvalid``, a generic
    500 at the endpoint), not the store's, since only the data read was checked.  Now the
    store's error naming the file, as at open and for a segment damaged in its data."""
    import os

    import pyarrow as pa

    from robustloc.service.store import SegmentLog, StoreError

    log = SegmentLog(tmp_path / "p", seal_rows=100, fsync=False)
    try:
        log.append(pa.table({"time": [float(i) for i in range(150)], "tag": ["A"] * 150}))
        log.wait_sealed()
        (seg,) = sorted((tmp_path / "p").glob("seg-*.parquet"))
        os.truncate(seg, seg.stat().st_size // 2)
        with pytest.raises(StoreError, match="damaged Parquet segment of the store") as e:
            log.snapshot().scan(columns=["time"])
        assert str(seg) in str(e.value)
    finally:
        log.close()
