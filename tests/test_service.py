"""Live service (issue 12): a real ``robustloc serve`` on a free loopback port.

Every server is started by a fixture and stopped in its teardown (``ServerProcess`` sends
SIGTERM, then SIGKILL).  Unit tests of the pieces (row validation, epoch assembly, the
store's crash recovery, the processor abstraction) run in-process.
"""

from __future__ import annotations

import json
import subprocess
import time
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

pytest.importorskip("starlette")
pytest.importorskip("uvicorn")
httpx = pytest.importorskip("httpx")

from robustloc.io import read_anchors, read_measurements  # noqa: E402
from robustloc.io.tables import to_epochs  # noqa: E402
from robustloc.service.assembly import EpochAssembler  # noqa: E402
from robustloc.service.launch import ROBUSTLOC, ServerProcess, read_metric  # noqa: E402
from robustloc.service.processor import LocateProcessor  # noqa: E402
from robustloc.service.rows import BodyError, RowDecoder, parse_body, validate_rows  # noqa: E402
from robustloc.service.store import SegmentLog  # noqa: E402

TOKEN = "s3cret-token"


def _cli(*args: str) -> None:
    subprocess.run([*ROBUSTLOC, *args], check=True,
                   capture_output=True, text=True)


@pytest.fixture(scope="module")
def ble(tmp_path_factory) -> Path:
    d = tmp_path_factory.mktemp("ble")
    _cli("simulate", "ble-corridor", "--seed", "1", "--out", str(d))
    return d


@pytest.fixture(scope="module")
def uwb(tmp_path_factory) -> Path:
    d = tmp_path_factory.mktemp("uwb")
    _cli("simulate", "uwb-cart", "--seed", "1", "--out", str(d))
    return d


@pytest.fixture(scope="module")
def corridor(tmp_path_factory) -> Path:
    """Four nearly collinear anchors, the tag always on one side: fixes whose mirror fits
    as well are placed by the log's side prior (``--side-prior``)."""
    from _corridor import write_side_files  # (tests/_corridor.py)

    d = tmp_path_factory.mktemp("corridor")
    write_side_files(d, n=300, tag="T1")
    return d


def wait_for(cond, timeout: float = 60.0, what: str = "condition"):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        v = cond()
        if v is not None and v is not False and not (isinstance(v, list) and not v):
            return v
        time.sleep(0.1)
    raise AssertionError(f"timed out waiting for {what}")


def metric(url: str, name: str, headers: dict | None = None) -> float:
    return read_metric(url, name, headers)


# --------------------------------------------------------------------------------------
# replay through the server == batch locate
# --------------------------------------------------------------------------------------


@pytest.mark.parametrize(("scenario", "method", "transport", "scale"),
                         [("ble", "auto", "http", "mad"), ("uwb", "igg", "ws", "mad"),
                          # --side-prior none on both sides: the fixes stay unmoved
                          ("corridor", "auto", "ws", "log,none"),
                          # the log's scale from the recorded log (--scale-from): fixes
                          # no longer depend on which epochs share a batch
                          ("ble", "auto", "http", "log"),
                          # and the side of ambiguous fixes is the recorded log's
                          ("corridor", "auto", "http", "log")])
def test_replay_equals_batch_locate(scenario, method, transport, scale, request,
                                    server_factory, tmp_path):
    """Positions computed live equal ``robustloc locate`` on the file to 1e-9 m.

    Both run locate_protected with the same Locator on the same epochs (the service pivots
    with to_epochs, as the batch reader does); the only difference allowed is the
    floating-point summation order of averaged duplicates, far below 1e-9 m.  With
    ``--scale-from`` the service takes the noise scale of the log by locate's own first
    pass, so it equals locate's default (``--robust-scale log``).
    """
    from robustloc.commands.replay import replay

    d = request.getfixturevalue(scenario)
    batch = tmp_path / "batch.parquet"
    meas = str(d / "measurements.csv")
    scale, _, side = scale.partition(",")
    extra = ["--robust-scale", "mad"] if scale == "mad" else []
    if side:
        extra += ["--side-prior", side]
    _cli("locate", meas, "--anchors", str(d / "anchors.csv"), "--method", method,
         "-o", str(batch), "--quiet", *extra)
    want = pd.read_parquet(batch)
    srv = server_factory(["--anchors", str(d / "anchors.csv"), "--method", method,
                          "--store", str(tmp_path / "store"), "--idle-flush", "0.3",
                          *(["--scale-from", meas] if scale == "log" else []),
                          *(["--side-prior", side] if side else [])])
    res = replay(str(d / "measurements.csv"), srv.url, speed=0, transport=transport)
    assert res["accepted"] == res["rows"] and not res["rejected"]

    def got():
        g = pd.DataFrame(httpx.get(srv.url + "/api/positions").json())
        return g if len(g) == len(want) else None

    g = wait_for(got, what="all epochs solved")
    key = ["tag", "time"]
    g = g.sort_values(key).reset_index(drop=True)
    w = want.assign(tag=want["tag"].astype(str)).sort_values(key).reset_index(drop=True)
    assert (g["tag"] == w["tag"]).all()
    np.testing.assert_array_equal(g["time"], w["time"])
    assert (g["status"] == w["status"]).all()
    np.testing.assert_array_equal(g["n_used"], w["n_used"])
    for c in ("x", "y"):
        np.testing.assert_allclose(g[c].astype(float), w[c], rtol=0, atol=1e-9,
                                   equal_nan=True)
    assert (g["excluded"].fillna("") == w["excluded"].fillna("")).all()
    if scenario == "corridor" and not side:  # the precondition: the prior moved fixes
        off = tmp_path / "off.parquet"
        _cli("locate", meas, "--anchors", str(d / "anchors.csv"), "--method", method,
             "-o", str(off), "--quiet", "--side-prior", "none")
        assert (pd.read_parquet(off)["y"] > 0).sum() >= 3 and not (w["y"] > 0).any()


# --------------------------------------------------------------------------------------
# the HTTP contract
# --------------------------------------------------------------------------------------


@pytest.fixture
def tokened(ble, server_factory, tmp_path) -> ServerProcess:
    return server_factory(
        ["--anchors", str(ble / "anchors.csv"), "--store", str(tmp_path / "s"),
         "--max-body-bytes", "200000", "--idle-flush", "0.3", "--latency-window", "1"],
        env={"ROBUSTLOC_TOKEN": TOKEN})


AUTH = {"Authorization": f"Bearer {TOKEN}"}


def test_token_guards_ingest_and_reads(tokened):
    u = tokened.url
    row = [{"time": 0.0, "tag": "T", "anchor": "1", "rssi": -70.0}]
    for path in ("/api/positions", "/api/anchors", "/metrics", "/api/status"):
        assert httpx.get(u + path).status_code == 401
        assert httpx.get(u + path, headers={"Authorization": "Bearer wrong"}).status_code == 401
        assert httpx.get(u + path, headers=AUTH).status_code == 200
    r = httpx.post(u + "/api/measurements", json=row)
    assert r.status_code == 401 and r.headers["www-authenticate"] == "Bearer"
    assert httpx.post(u + "/api/measurements", json=row, headers=AUTH).status_code == 202
    assert httpx.get(u + "/healthz").json() == {"status": "ok"}
    assert "<svg" in httpx.get(u + "/").text  # the page itself holds no data
    assert metric(u, 'robustloc_requests_rejected_total{reason="unauthorized"}', AUTH) >= 9


def test_a_websocket_without_the_token_is_refused_403_at_the_handshake(tokened):
    """The documented answer (README, app doc): HTTP 403 at the handshake (the docs said
    401, and the code's close code 1008 never reaches the client), counted."""
    from websockets.exceptions import InvalidStatus
    from websockets.sync.client import connect

    w = tokened.url.replace("http://", "ws://")
    before = metric(tokened.url, 'robustloc_requests_rejected_total{reason="unauthorized"}',
                    AUTH)
    for path in ("/ws/positions", "/ws/measurements", f"/ws/positions?token={TOKEN}x"):
        with pytest.raises(InvalidStatus) as refused:
            connect(w + path, open_timeout=10)
        assert refused.value.response.status_code == 403
    assert metric(tokened.url, 'robustloc_requests_rejected_total{reason="unauthorized"}',
                  AUTH) == before + 3
    with connect(w + f"/ws/measurements?token={TOKEN}", open_timeout=10) as ws:
        ws.send("[]")
        assert json.loads(ws.recv(timeout=10))["accepted"] == 0


def test_post_answers(tokened):
    u = tokened.url
    rows = [
        {"time": 1.0, "tag": "T1", "anchor": "1", "rssi": -70.5},   # ok
        {"time": 1.0, "tag": "T1", "anchor": "99", "rssi": -70.5},  # unknown anchor
        {"time": "x", "tag": "T1", "anchor": "2", "rssi": -70.5},   # time not a number
        {"time": 1.0, "tag": "", "anchor": "2", "rssi": -70.5},     # empty tag
        {"time": 1.0, "tag": "T1", "anchor": "2", "rssi": 500},     # implausible RSSI
        {"time": 1.0, "tag": "T1", "anchor": "2", "range": 3.0},    # wrong value kind
        {"time": 1.0, "tag": "T1", "anchor": "2"},                  # no value
        [1, 2, 3],                                                   # not an object
        {"time": 1.0, "tag": "T1", "anchor": 3, "rssi": -60},       # ok (integer id)
        {"time": None, "tag": "T1", "anchor": "2", "rssi": -60},    # missing time
        {"time": True, "tag": "T1", "anchor": "2", "rssi": -60},    # boolean time
    ]
    r = httpx.post(u + "/api/measurements", json=rows, headers=AUTH)
    assert r.status_code == 202
    body = r.json()
    assert body["accepted"] == 2
    rej = {x["index"]: x["error"] for x in body["rejected"]}
    assert sorted(rej) == [1, 2, 3, 4, 5, 6, 7, 9, 10]
    assert "unknown anchor" in rej[1] and "not a number" in rej[2]
    assert "empty 'tag'" in rej[3] and "rssi must lie in" in rej[4]
    assert "locates from rssi" in rej[5] and "no value" in rej[6]
    assert "expected an object" in rej[7] and "missing 'time'" in rej[9]
    assert "boolean" in rej[10]
    # NDJSON, with one line that is not JSON
    nd = b'{"time": 2, "tag": "T1", "anchor": "1", "rssi": -71}\n{oops\n' \
         b'{"time": 2, "tag": "T1", "anchor": "2", "rssi": -72}\n'
    r = httpx.post(u + "/api/measurements", content=nd, headers=AUTH)
    assert r.status_code == 202 and r.json()["accepted"] == 2
    assert [x["index"] for x in r.json()["rejected"]] == [1]
    # bodies that are not rows
    assert httpx.post(u + "/api/measurements", content=b"[1, 2", headers=AUTH).status_code == 400
    assert httpx.post(u + "/api/measurements", content=b"", headers=AUTH).status_code == 400
    assert httpx.post(u + "/api/measurements", content=b"42", headers=AUTH).status_code == 422
    big = json.dumps(rows[:1] * 5000).encode()
    assert len(big) > 200_000
    assert httpx.post(u + "/api/measurements", content=big, headers=AUTH).status_code == 413
    assert metric(u, "robustloc_rows_rejected_total", AUTH) == 10
    assert metric(u, "robustloc_rows_accepted_total", AUTH) == 4
    text = httpx.get(u + "/metrics", headers=AUTH).text
    assert 'robustloc_anchor_rows_heard_total{anchor="1"} 2' in text
    # rows naming anchor 2 with a bad value/time/tag/kind: indexes 2, 3, 4, 5, 6, 9, 10
    assert 'robustloc_anchor_rows_rejected_total{anchor="2"} 7' in text
    assert "robustloc_position_latency_seconds_bucket" in text
    anchors = httpx.get(u + "/api/anchors", headers=AUTH).json()
    a2 = next(a for a in anchors if a["anchor"] == "2")
    assert a2["rows_rejected"] == 7 and a2["rows_heard"] == 1
    assert a2["rejection_rate"] == pytest.approx(7 / 8)


def test_bad_queries_and_fuzz_never_crash(tokened):
    """Random bytes get a 4xx or a 202 that accepts nothing; each hand-made body gets the
    answer ``robustloc.service.rows`` documents for it: a body that starts like an array
    and does not decode (nested past the parser's depth) or a single line that is not
    JSON is refused whole (400); a JSON array or NDJSON of several lines is taken row by
    row (202), each bad row rejected at its index; a number beyond float range (1e400)
    is read as inf so that only its row is refused; ids are at most 128 characters.  No
    row of any of them reaches the store: ``robustloc_rows_accepted_total`` stays put."""
    u = tokened.url
    for q in ("since=abc", "until=nan", "limit=0", "limit=x"):
        assert httpx.get(u + "/api/positions?" + q, headers=AUTH).status_code == 400
    accepted0 = metric(u, "robustloc_rows_accepted_total", AUTH)
    rng = np.random.default_rng(7)
    bodies = [bytes(rng.integers(0, 256, int(n), dtype=np.uint8)) for n in rng.integers(1, 400, 60)]
    for b in bodies:
        r = httpx.post(u + "/api/measurements", content=b, headers=AUTH)
        assert r.status_code in (202, 400, 413, 422), (b[:40], r.status_code, r.text)
        if r.status_code == 202:
            assert r.json()["accepted"] == 0, (b[:40], r.text)
    # (body, status, indexes of the rejected rows for a 202)
    known = [(b"[" * 5000 + b"]" * 5000, 400, None),
             (b'{"time": 1e400, "tag": "a", "anchor": "1", "rssi": 1}', 202, [0]),
             (b'[{"time": 1, "tag": {"x": 1}, "anchor": [1], "rssi": "NaN"}]', 202, [0]),
             (b"\xff\xfe\x00", 400, None),
             (b'[null, true, "row", 1.5, {}]', 202, [0, 1, 2, 3, 4]),
             (b'{"a": 1}\n[]\n7\n', 202, [0, 1, 2]),
             (json.dumps([{"time": 1, "tag": "t" * 1000, "anchor": "1", "rssi": -60}]).encode(),
              202, [0])]
    for b, status, rejected in known:
        r = httpx.post(u + "/api/measurements", content=b, headers=AUTH)
        assert r.status_code == status, (b[:40], r.status_code, r.text)
        if status == 202:
            assert r.json()["accepted"] == 0, (b[:40], r.text)
            assert [x["index"] for x in r.json()["rejected"]] == rejected, (b[:40], r.text)
        else:
            assert "error" in r.json(), (b[:40], r.text)
    assert metric(u, "robustloc_rows_accepted_total", AUTH) == accepted0
    # a good row after all of them is still taken and counted (the counter is live)
    good = [{"time": 0.0, "tag": "T", "anchor": "1", "rssi": -70.0}]
    assert httpx.post(u + "/api/measurements", json=good, headers=AUTH).json()["accepted"] == 1
    assert metric(u, "robustloc_rows_accepted_total", AUTH) == accepted0 + 1
    assert httpx.get(u + "/healthz").status_code == 200
    assert tokened.proc.poll() is None


def test_late_rows_stored_and_counted(tokened):
    u = tokened.url
    rows = [{"time": t, "tag": "L", "anchor": a, "rssi": -70.0}
            for t in (0.0, 1.0, 2.0, 3.0) for a in ("1", "2", "3", "4")]
    assert httpx.post(u + "/api/measurements", json=rows, headers=AUTH).json()["accepted"] == 16
    # window 1 s: epochs 0 and 1 are ready (older than 3 - 1); a row for t=1 is late (its
    # epoch solved)
    late = [{"time": 1.0, "tag": "L", "anchor": "1", "rssi": -70.0}]
    assert httpx.post(u + "/api/measurements", json=late, headers=AUTH).json()["accepted"] == 1
    assert metric(u, "robustloc_rows_late_total", AUTH) == 1
    pos = wait_for(lambda: (p := httpx.get(u + "/api/positions?tag=L", headers=AUTH).json())
                   and len(p) == 4 and p, what="4 epochs (2 by the window, 2 by idle flush)")
    assert [p["time"] for p in pos] == [0.0, 1.0, 2.0, 3.0]
    sub = httpx.get(u + "/api/positions?tag=L&since=1&until=2", headers=AUTH).json()
    assert [p["time"] for p in sub] == [1.0, 2.0]


def test_websockets(tokened):
    from websockets.sync.client import connect

    ws_url = tokened.url.replace("http://", "ws://")
    with pytest.raises(Exception):  # noqa: B017 - the server closes with 1008 or refuses
        with connect(ws_url + "/ws/positions") as ws:
            ws.recv(timeout=5)
    with connect(ws_url + f"/ws/positions?tag=W&token={TOKEN}") as sub, \
            connect(ws_url + "/ws/measurements", additional_headers=AUTH) as pub:
        rows = [{"time": t, "tag": g, "anchor": a, "rssi": -65.0 - int(a)}
                for t in (0.0, 1.0) for g in ("W", "V") for a in "12345"]
        pub.send(json.dumps(rows))
        assert json.loads(pub.recv(timeout=10)) == {"accepted": 20, "rejected": [],
                                                     "n_rejected": 0, "late": 0}
        pub.send("not json [")
        assert json.loads(pub.recv(timeout=10))["status"] == 400
        msgs = [json.loads(sub.recv(timeout=30)) for _ in range(2)]
        assert [m["tag"] for m in msgs] == ["W", "W"]  # the tag filter holds V back
        assert sorted(m["time"] for m in msgs) == [0.0, 1.0]
        assert {"x", "y", "status", "cov_xx", "cov_xy", "cov_yy"} <= set(msgs[0])
    # batch=1: one message per solved block, the array of its rows (with the tag filter)
    with connect(ws_url + f"/ws/positions?batch=1&token={TOKEN}") as every, \
            connect(ws_url + f"/ws/positions?batch=1&tag=B1&token={TOKEN}") as one, \
            connect(ws_url + "/ws/measurements", additional_headers=AUTH) as pub:
        rows = [{"time": t, "tag": g, "anchor": a, "rssi": -65.0 - int(a)}
                for t in (5.0, 6.0) for g in ("B1", "B2") for a in "12345"]
        pub.send(json.dumps(rows))
        assert json.loads(pub.recv(timeout=10)) == {"accepted": 20, "rejected": [],
                                                     "n_rejected": 0, "late": 0}
        got: list[dict] = []
        while len(got) < 4:  # every epoch once, in arrays (one per solved block)
            blk = json.loads(every.recv(timeout=30))
            assert isinstance(blk, list) and blk
            got += blk
        assert sorted((r["time"], r["tag"]) for r in got) == [
            (5.0, "B1"), (5.0, "B2"), (6.0, "B1"), (6.0, "B2")]
        mine: list[dict] = []
        while len(mine) < 2:
            mine += json.loads(one.recv(timeout=30))
        assert {r["tag"] for r in mine} == {"B1"} and len(mine) == 2


def test_rate_limit(ble, server_factory, tmp_path):
    """1 row/s: a 15-row body passes once (burst), then the client owes 13 s."""
    srv = server_factory(["--anchors", str(ble / "anchors.csv"), "--rate-limit", "1"])
    rows = [{"time": float(i), "tag": "R", "anchor": "1", "rssi": -60.0} for i in range(15)]
    assert httpx.post(srv.url + "/api/measurements", json=rows).status_code == 202
    r = httpx.post(srv.url + "/api/measurements", json=rows)
    assert r.status_code == 429 and 5 <= int(r.headers["retry-after"]) <= 14
    assert metric(srv.url, 'robustloc_requests_rejected_total{reason="rate_limited"}') == 1
    assert metric(srv.url, "robustloc_rows_accepted_total") == 15


# --------------------------------------------------------------------------------------
# durability: kill -9 and restart
# --------------------------------------------------------------------------------------


def test_kill9_loses_nothing_acknowledged(ble, server_factory, tmp_path):
    store = tmp_path / "store"
    args = ["--anchors", str(ble / "anchors.csv"), "--store", str(store),
            "--latency-window", "0", "--idle-flush", "600"]
    meas = read_measurements(ble / "measurements.csv").sort_values("time", kind="stable")
    recs = [{"time": float(t), "tag": g, "anchor": a, "rssi": float(v)} for t, g, a, v in
            zip(meas["time"], meas["tag"], meas["anchor"], meas["rssi"])]
    half = len(recs) // 2
    srv = server_factory(args)
    acked = 0
    for i in range(0, half, 50):
        r = httpx.post(srv.url + "/api/measurements", json=recs[i:min(i + 50, half)])
        acked += r.json()["accepted"]
    srv.kill9()
    # every acknowledged row is in the store (read by an independent reader of the files)
    log = SegmentLog(store / "measurements", fsync=False)
    assert log.scan().num_rows == acked == half
    log.close()
    srv2 = server_factory(args)
    for i in range(half, len(recs), 50):
        httpx.post(srv2.url + "/api/measurements", json=recs[i:i + 50])
    srv2.stop()  # graceful: the last epoch of each tag stays pending in the store
    srv3 = server_factory(args[:-1] + ["0.3"])
    n_epochs = len(meas.groupby(["time", "tag"]))
    pos = wait_for(lambda: (p := httpx.get(srv3.url + "/api/positions").json())
                   and len(p) == n_epochs and p, what="every epoch solved once")
    keys = {(p["time"], p["tag"]) for p in pos}
    assert len(keys) == n_epochs
    # per-tag state resumed: a row older than the solved epochs is late, not re-solved
    r = httpx.post(srv3.url + "/api/measurements",
                   json=[{"time": 0.0, "tag": "S1", "anchor": "1", "rssi": -70.0}])
    assert r.json()["accepted"] == 1
    assert metric(srv3.url, "robustloc_rows_late_total") == 1


def test_store_truncates_torn_tail(tmp_path):
    import pyarrow as pa

    log = SegmentLog(tmp_path, seal_rows=10)
    for i in range(4):
        log.append(pa.table({"time": [float(i)] * 3, "tag": ["a"] * 3}))
    log.wait_sealed()
    assert len(list(tmp_path.glob("*.parquet"))) == 1  # 12 rows >= 10: sealed once
    log.close()
    wal = sorted(tmp_path.glob("*.wal"))[-1]
    with open(wal, "ab") as f:  # a crash in the middle of a frame
        f.write(b"RLW1\x10\x00\x00\x00garbage")
    log2 = SegmentLog(tmp_path)
    assert log2.truncated_bytes == 15
    assert sorted(log2.scan()["time"].to_pylist()) == sorted([0.0, 1.0, 2.0, 3.0] * 3)
    log2.close()


def _small_log(directory, frames: int):
    """A closed measurements-like log of ``frames`` frames (times 0, 1, ..., two rows
    each); returns its file."""
    import pyarrow as pa

    log = SegmentLog(directory, fsync=False)
    for i in range(frames):
        log.append(pa.table({"time": [float(i)] * 2, "tag": ["a"] * 2}))
    log.close()
    (wal,) = directory.glob("*.wal")
    return wal


def test_store_says_it_truncated_a_torn_tail(tmp_path, capsys):
    wal = _small_log(tmp_path, 3)
    data = wal.read_bytes()
    wal.write_bytes(data[:-7])  # the last append cut short by a crash: never acknowledged
    log2 = SegmentLog(tmp_path, fsync=False)
    try:
        cut = len(data) - 7 - log2.truncated_bytes
        assert sorted(log2.scan()["time"].to_pylist()) == [0.0, 0.0, 1.0, 1.0]
    finally:
        log2.close()
    err = capsys.readouterr().err
    assert f"warning: {wal}: {log2.truncated_bytes} bytes of an incomplete last frame cut " \
           f"off at byte {cut}" in err


@pytest.mark.parametrize("where", ["payload", "length"])
def test_store_refuses_a_log_damaged_before_intact_frames(tmp_path, where):
    """One bad byte in a log's first frame: every later (acknowledged) frame was cut off
    at the next open, silently (the serve review).  The open is refused naming the file
    and the offsets, and the file is left as it is."""
    from robustloc.service.store import StoreError

    wal = _small_log(tmp_path, 3)
    data = bytearray(wal.read_bytes())
    second = data.find(b"RLW1", 1)
    data[40 if where == "payload" else 5] ^= 0xFF  # (5: the first frame's length)
    wal.write_bytes(bytes(data))
    with pytest.raises(StoreError) as e:
        SegmentLog(tmp_path, fsync=False)
    assert e.value.path == str(wal)
    assert e.value.message == (f"damaged write-ahead log of the store (a bad frame at byte "
                               f"0, intact frames from byte {second}); move it aside to "
                               "start without its rows")
    assert wal.read_bytes() == bytes(data)  # nothing cut off
    data[40 if where == "payload" else 5] ^= 0xFF  # repaired: every row back
    wal.write_bytes(bytes(data))
    log = SegmentLog(tmp_path, fsync=False)
    try:
        assert sorted(log.scan()["time"].to_pylist()) == [0.0, 0.0, 1.0, 1.0, 2.0, 2.0]
        assert log.truncated_bytes == 0
    finally:
        log.close()


def test_a_torn_frame_holding_a_frame_in_its_rows_is_a_torn_tail(tmp_path, capsys):
    """A crash mid-append leaves a prefix of the frame; its rows' text (a tag id) may
    spell a whole frame.  That is no intact frame after damage (the frames from it do not
    run to the end of the file): the tail is cut with a warning, the store opens (it
    refused to start: the review of the fix)."""
    import pyarrow as pa

    from robustloc.service.store import _encode

    wal = _small_log(tmp_path, 2)
    good = wal.read_bytes()
    inner = _encode(pa.table({"time": [9.0], "tag": ["x"]}))
    torn = _encode(pa.table({"time": [2.0] * 3, "tag": ["p" * 50, inner.hex(), "q" * 300]}))
    # the torn frame's bytes hold the inner frame (hex-spelled here: a tag of bytes that
    # are a frame) and stop after it and some more of the payload
    raw = inner + b"z" * 40
    wal.write_bytes(good + torn[:60] + raw)
    log = SegmentLog(tmp_path, fsync=False)
    try:
        assert sorted(log.scan()["time"].to_pylist()) == [0.0, 0.0, 1.0, 1.0]
        assert log.truncated_bytes == 60 + len(raw)
    finally:
        log.close()
    assert "incomplete last frame cut off" in capsys.readouterr().err


def test_a_positions_log_damaged_mid_file_is_cut_not_refused(tmp_path, capsys):
    """The positions log is not synced (its rows are recomputed after a crash): a page of
    it lost in a power cut, later ones written, must not stop the service.  Opened with
    ``refuse_damage=False`` it is cut at the damage, with a warning; the measurements'
    default refuses the same file."""
    from robustloc.service.store import StoreError

    wal = _small_log(tmp_path, 4)
    data = bytearray(wal.read_bytes())
    second = data.find(b"RLW1", 1)
    data[second + 20: second + 60] = b"\0" * 40  # the second frame's page lost
    wal.write_bytes(bytes(data))
    with pytest.raises(StoreError, match="damaged write-ahead log"):
        SegmentLog(tmp_path, fsync=False)
    log = SegmentLog(tmp_path, fsync=False, refuse_damage=False)
    try:
        assert log.scan()["time"].to_pylist() == [0.0, 0.0]
        assert log.truncated_bytes == len(data) - second
    finally:
        log.close()
    assert "from a damaged frame on" in capsys.readouterr().err


# --------------------------------------------------------------------------------------
# pieces
# --------------------------------------------------------------------------------------


def test_assembler_rule_by_hand():
    """window 0.5: epoch t is ready once a row with time > t + 0.5 of the same tag came."""
    a = EpochAssembler(["A", "B"], latency_window_s=0.5, idle_flush_s=100)
    obj = lambda *x: np.array(x, dtype=object)  # noqa: E731
    late = a.add(np.array([0.0, 0.0, 0.4]), obj("t", "t", "t"), np.array([0, 1, 0]),
                 np.array([1.0, 2.0, 3.0]), wall=0.0)
    assert not late.any() and a.take_ready(0.0) is None  # 0.0 is not older than 0.4 - 0.5
    a.add(np.array([0.6]), obj("u"), np.array([0]), np.array([4.0]), wall=0.0)
    assert a.take_ready(0.0) is None  # another tag does not release t
    a.add(np.array([0.6]), obj("t"), np.array([1]), np.array([5.0]), wall=0.0)
    r = a.take_ready(0.0)
    assert r["time"].tolist() == [0.0, 0.0] and r["value"].tolist() == [1.0, 2.0]
    late = a.add(np.array([0.0, 0.05, 0.4]), obj("t", "t", "t"), np.array([0, 0, 1]),
                 np.array([9.0, 9.0, 9.0]), wall=150.0)
    assert late.tolist() == [True, True, False]  # 0.05 < newest 0.6 - 0.5: late too
    r = a.take_ready(200.0)  # u idle since wall 0 (> 100 s), t heard at wall 150
    assert r["tag"].tolist() == ["u"] and r["time"].tolist() == [0.6]
    assert sorted(a.take_ready(0.0, flush_all=True)["time"].tolist()) == [0.4, 0.4, 0.6]


@pytest.mark.parametrize(("first", "reason"), [
    ({"range": "abc"}, "'range': 'abc' is not a number"),
    ({"range": 1e12}, "range must lie in"),
    ({"rssi": 500.0}, "rssi must lie in"),
    ({"range": 5.0, "time": 1e30}, "time must lie in"),
    ({"range": 5.0, "anchor": "nope"}, "unknown anchor id"),
])
def test_a_rejected_first_row_does_not_fix_the_value(first, reason):
    """The value was taken from the first row without an error *before* the value checks:
    a first row with a range that is not a number (rejected) fixed the service to ranges,
    and the next body's rssi rows were all rejected (the serve review)."""
    idx = pd.Index(["A", "B"])
    bad = {"time": 1.0, "tag": "T", "anchor": "A", **first}
    good = {"time": 2.0, "tag": "T", "anchor": "B", "rssi" if "range" in first else "range":
            -70.0 if "range" in first else 4.0}
    batch, kind, rejected = validate_rows([bad, good], idx, None)
    assert kind == ("rssi" if "range" in first else "range")
    assert len(batch) == 1 and batch.time.tolist() == [2.0]
    assert [i for i, _ in rejected] == [0]
    batch, kind, rejected = validate_rows([bad], idx, None)
    assert kind is None and not len(batch) and reason in rejected[0][1], rejected


def test_a_rejected_first_row_does_not_fix_the_services_value(ble, server_factory, tmp_path):
    """On a server with a store: a rejected range row, then an rssi row: the rssi row is
    accepted, the store's meta.json says rssi, and a restart with --value rssi starts."""
    store = tmp_path / "store"
    args = ["--anchors", str(ble / "anchors.csv"), "--store", str(store)]
    s = server_factory(args)
    r = httpx.post(s.url + "/api/measurements",
                   json=[{"time": 1, "tag": "T", "anchor": "1", "range": "abc"}])
    assert r.status_code == 202 and r.json()["accepted"] == 0
    assert json.loads((store / "meta.json").read_text())["value"] is None
    r = httpx.post(s.url + "/api/measurements",
                   json=[{"time": 2, "tag": "T", "anchor": "1", "rssi": -70}])
    assert r.status_code == 202 and r.json()["accepted"] == 1, r.text
    assert json.loads((store / "meta.json").read_text())["value"] == "rssi"
    s.stop()
    s = server_factory([*args, "--value", "rssi"])
    assert httpx.get(s.url + "/healthz").status_code == 200


def test_validate_rows_vectorized_matches_rowwise():
    idx = pd.Index(["1", "2"], dtype=object)
    rows = [{"time": 1, "tag": " a ", "anchor": "1", "range": 2.5},
            {"time": "2.5", "tag": 7, "anchor": 2, "range": -1}]
    b, kind, rej = validate_rows(rows, idx, None)
    assert kind == "range" and rej == []
    assert b.tag.tolist() == ["a", "7"] and b.anchor_col.tolist() == [0, 1]
    assert b.time.tolist() == [1.0, 2.5] and b.value.tolist() == [2.5, -1.0]
    with pytest.raises(BodyError) as e:
        parse_body(b"[1,")
    assert e.value.status == 400


@pytest.mark.parametrize("text", ["1_000", "\u0661\u0662", "0x10", "abc"])
def test_a_number_as_text_is_read_as_the_files_are(text, tmp_path):
    """A value sent as text is a number exactly when ``locate`` reads it as one from a
    file (``robustloc._arrays.to_number``).  Python's float() also took "1_000" and the
    digits of other scripts (Arabic-Indic "\u0661\u0662" read 12), which the batch reader
    refuses: the same log gave positions live and ``error: ... is not a number`` in
    ``locate`` (the serve review of 2026-12-06)."""
    from robustloc.io.tables import InputError, read_measurements

    idx = pd.Index(["1"], dtype=object)
    rows = [{"time": text, "tag": "a", "anchor": "1", "range": 2.0},
            {"time": " 7 ", "tag": "a", "anchor": "1", "range": "3"}]
    b, kind, rej = validate_rows(rows, idx, None)
    assert [i for i, _ in rej] == [0] and "is not a number" in rej[0][1]
    assert b.time.tolist() == [7.0]  # padded digits: read by both
    path = tmp_path / "m.csv"
    path.write_text(f"time,tag,anchor,range\n{text},a,1,2\n", encoding="utf-8")
    with pytest.raises(InputError, match="is not a number"):
        read_measurements(path)


def test_a_whole_number_of_5000_digits_is_infinite_in_files_and_live(tmp_path):
    """pandas read a whole number of more than 4 300 digits (Python's conversion limit)
    as NaN, "not a number", where one of 1 000 digits read +inf; the service, reading
    text as the files are read, said "not a number" for the first too.  Both read +-inf
    now: a file's row says "infinite value", the service's "not finite"."""
    from robustloc._arrays import to_number
    from robustloc.io.tables import InputError, read_measurements

    big = "9" * 5000
    assert to_number(pd.Series([big, "-" + big, "7", "x" * 5000], dtype=object)).tolist()[
        :3] == [np.inf, -np.inf, 7.0]
    path = tmp_path / "m.csv"
    path.write_text(f"time,tag,anchor,range\n{big},a,1,2\n", encoding="utf-8")
    with pytest.raises(InputError, match="infinite value"):
        read_measurements(path)
    _, _, rej = validate_rows([{"time": big, "tag": "a", "anchor": "1", "range": 2.0}],
                              pd.Index(["1"], dtype=object), None)
    assert "not finite" in rej[0][1]


_REGULAR = {"time": 1.5, "tag": "T1", "anchor": "A1", "range": 2.5}


@pytest.mark.parametrize(("rows", "fast_accepts"), [
    ([_REGULAR, {**_REGULAR, "time": 2, "range": 3}], True),  # ints are numbers
    ([{**_REGULAR, "time": 1_764_600_000}], True),  # an integer Unix time
    ([], True),
    ([{**_REGULAR, "time": True}], False),  # a boolean is not a number
    ([{**_REGULAR, "range": "2.5"}], False),  # a string number: the row path takes it
    ([{**_REGULAR, "tag": " T1 "}], False),  # the row path strips ids
    ([{**_REGULAR, "anchor": " A1"}], False),
    ([{**_REGULAR, "tag": 7}], False),  # an integer id: the row path takes it
    ([{**_REGULAR, "tag": ""}], False),
    ([{**_REGULAR, "tag": "x" * 129}], False),
    ([{**_REGULAR, "anchor": "nope"}], False),
    ([{**_REGULAR, "range": 1e9}], False),  # outside the physical limits
    ([{**_REGULAR, "time": -1.5e12}], False),
    ([{k: v for k, v in _REGULAR.items() if k != "range"}], False),
    ([{**_REGULAR, "rssi": -60.0}], False),  # both values
    ([{**_REGULAR, "extra": 1}], False),  # an unknown key
    ([{"time": 1.5, "tag": "T1", "anchor": "A1", "rssi": -60.0}], False),  # other value
    ([_REGULAR, [1, 2]], False),
])
def test_fast_decoder_agrees_with_row_path(rows, fast_accepts):
    """The msgspec fast path takes a body only when every row is regular and valid, and
    then gives the row-by-row path's columns; any other body it declines (None) and the
    row path answers it (with the reason of every rejected row)."""
    if not RowDecoder(["A0"]).available:
        pytest.skip("msgspec not installed")
    ids = ["A0", "A1"]
    body = json.dumps(rows).encode()
    fast = RowDecoder(ids).decode(body, "range")
    slow, kind, rejected = validate_rows(parse_body(body)[0], pd.Index(ids, dtype=object),
                                         "range")
    assert (fast is not None) == fast_accepts
    if fast is None:
        return
    assert rejected == [] and kind == "range" and len(fast) == len(rows)
    for f in ("time", "tag", "anchor", "value", "anchor_col"):
        np.testing.assert_array_equal(getattr(fast, f), getattr(slow, f))
    assert fast.time.dtype == slow.time.dtype and fast.anchor_col.dtype == np.int64


def test_fast_decoder_declines_before_the_value_is_known():
    body = json.dumps([_REGULAR]).encode()
    assert RowDecoder(["A1"]).decode(body, None) is None
    assert RowDecoder(["A1"]).decode(b"[1,", "range") is None
    assert RowDecoder(["A1"]).decode(b'{"time": 1}', "range") is None


def test_locate_processor_equals_locator(ble):
    """The processor is the batch path: locate_protected on to_epochs, as locate does."""
    from robustloc.estimators.ranging import Locator
    from robustloc.integrity.fixes import locate_protected
    from robustloc.models.pathloss import log_distance_arrays

    anchors = read_anchors(ble / "anchors.csv")
    meas = read_measurements(ble / "measurements.csv")
    ep = to_epochs(meas, anchors["anchor"])
    out = LocateProcessor(anchors, method="igg").process(ep)
    A, n = log_distance_arrays(anchors)
    sol = locate_protected(Locator("igg", robust_scale="mad"),
                           anchors[["x", "y"]].to_numpy(float), ep.values, "rssi", A=A, n=n)
    np.testing.assert_array_equal(out[["x", "y"]].to_numpy(), sol.position)
    np.testing.assert_array_equal(out["cov_xy"].to_numpy(), sol.covariance[:, 0, 1])
    np.testing.assert_array_equal(out["hpl"].to_numpy(), sol.extra["hpl"])
    assert len(out) == ep.n_epochs and set(out["method"]) == {"igg"}
    with pytest.raises(ValueError, match="--scale-from"):
        LocateProcessor(anchors, robust_scale="log")


def test_track_processor(ble):
    """--track runs robustloc.tracking.Tracker behind the same processor interface."""
    pytest.importorskip("robustloc.tracking")
    from robustloc.service.processor import TrackProcessor

    anchors = read_anchors(ble / "anchors.csv")
    ep = to_epochs(read_measurements(ble / "measurements.csv"), anchors["anchor"])
    p = TrackProcessor(anchors)
    out = p.process(ep)
    assert len(out) == ep.n_epochs
    state = p.state_dict()
    q = TrackProcessor(anchors)
    q.load_state_dict(state)
    assert isinstance(state, dict)
    # a store written before a setting existed (range_offset: added later) still loads,
    # the setting at its default; one written with other options is refused, named
    old = json.loads(json.dumps(state))
    for k in ("range_offset", "range_offset_sd", "range_offset_q"):
        del old["settings"][k]
    TrackProcessor(anchors).load_state_dict(old)
    with pytest.raises(ValueError, match=r"range_offset False \(now True\).*new --store"):
        TrackProcessor(anchors, range_offset=True).load_state_dict(state)


def test_track_without_tracker_is_a_clear_error(ble, monkeypatch):
    import builtins

    real = builtins.__import__

    def fake(name, *a, **k):
        if name == "robustloc.tracking":
            raise ImportError("No module named 'robustloc.tracking'")
        return real(name, *a, **k)

    monkeypatch.setattr(builtins, "__import__", fake)
    from robustloc.service.processor import TrackProcessor

    with pytest.raises(RuntimeError, match="--track needs robustloc.tracking"):
        TrackProcessor(read_anchors(ble / "anchors.csv"))


def test_track_mode_replay_equals_batch_track(ble, server_factory, tmp_path):
    """``serve --track`` gives the tracker's rows for the replayed log, to 1e-9 m.

    The batch reference feeds the whole file to the same Tracker in one ``step`` (every
    tag's epochs in time order); the service feeds blocks as epochs become ready.  The
    tracker's per-tag recursion makes both identical.
    """
    track = pytest.importorskip("robustloc.tracking")
    Tracker = track.Tracker

    anchors = read_anchors(ble / "anchors.csv")
    ep = to_epochs(read_measurements(ble / "measurements.csv"), anchors["anchor"])
    want = Tracker(anchors).step(ep)
    srv = server_factory(["--anchors", str(ble / "anchors.csv"), "--track",
                          "--store", str(tmp_path / "store"), "--idle-flush", "0.3"])
    g = _replayed_rows_equal(srv, ble / "measurements.csv", want, ("x", "y"))
    assert {"hpl", "var_x", "cov_xy"} <= set(g.columns)


def _replayed_rows_equal(srv, log, want: pd.DataFrame, columns: tuple[str, ...]
                         ) -> pd.DataFrame:
    """Replay ``log`` into ``srv``, wait for one position per epoch of ``want`` and check
    the statuses and ``columns`` against it (to 1e-9); returns the service's rows."""
    from robustloc.commands.replay import replay

    res = replay(str(log), srv.url, speed=0)
    assert res["accepted"] == res["rows"]

    def got():
        d = pd.DataFrame(httpx.get(srv.url + "/api/positions").json())
        return d if len(d) == len(want) else None

    return rows_equal(wait_for(got, what="every epoch solved"), want, columns)


def rows_equal(got: pd.DataFrame, want: pd.DataFrame, columns: tuple[str, ...]
               ) -> pd.DataFrame:
    """The service's rows ``got`` against ``want`` by (tag, time): the same statuses, and
    ``columns`` to 1e-9 (the JSON round trip of float64 positions); returns ``got``
    sorted."""
    key = ["tag", "time"]
    g = got.sort_values(key).reset_index(drop=True)
    w = want.assign(tag=want["tag"].astype(str)).sort_values(key).reset_index(drop=True)
    assert (g["status"] == w["status"]).all()
    for c in columns:
        np.testing.assert_allclose(g[c].astype(float), w[c], rtol=0, atol=1e-9, equal_nan=True)
    return g


def test_track_range_offset_replay_equals_batch_track(uwb, server_factory, tmp_path):
    """``serve --track --track-range-offset`` gives the rows of ``Tracker(range_offset=True)``
    on the replayed range log (to 1e-9 m, offset column included), and refuses an RSSI row
    with the reason (the service locates from ranges only)."""
    track = pytest.importorskip("robustloc.tracking")
    # anchors with path-loss columns: RSSI rows would be solvable, the option refuses them
    read_anchors(uwb / "anchors.csv").assign(A=-40.0, n=2.0).to_csv(tmp_path / "a.csv",
                                                                    index=False)
    anchors = read_anchors(tmp_path / "a.csv")
    ep = to_epochs(read_measurements(uwb / "measurements.csv"), anchors["anchor"])
    want = track.Tracker(anchors, range_offset=True).step(ep)
    srv = server_factory(["--anchors", str(tmp_path / "a.csv"), "--track",
                          "--track-range-offset", "--store", str(tmp_path / "store"),
                          "--idle-flush", "0.3"])
    # the first row is RSSI: refused (without the option it would fix the service's value)
    a0 = str(anchors["anchor"].iloc[0])
    r = httpx.post(srv.url + "/api/measurements",
                   json=[{"time": 0.0, "tag": "x", "anchor": a0, "rssi": -60.0}])
    assert r.status_code == 202 and r.json()["accepted"] == 0
    assert "locates from range" in r.json()["rejected"][0]["error"]
    _replayed_rows_equal(srv, uwb / "measurements.csv", want,
                         ("x", "y", "range_offset", "var_range_offset"))


def test_track_link_offsets_replay_equals_batch_track(ble, server_factory, tmp_path):
    """``serve --track --track-link-offsets`` gives the rows of
    ``Tracker(link_offsets=True)`` on the replayed RSSI log (to 1e-9 m), whose positions
    differ from the plain tracker's (the offsets are estimated)."""
    track = pytest.importorskip("robustloc.tracking")
    anchors = read_anchors(ble / "anchors.csv")
    ep = to_epochs(read_measurements(ble / "measurements.csv"), anchors["anchor"])
    want = track.Tracker(anchors, link_offsets=True).step(ep)
    plain = track.Tracker(anchors).step(ep)
    assert np.abs(want["x"] - plain["x"]).max() > 1e-3
    srv = server_factory(["--anchors", str(ble / "anchors.csv"), "--track",
                          "--track-link-offsets", "--store", str(tmp_path / "store"),
                          "--idle-flush", "0.3"])
    _replayed_rows_equal(srv, ble / "measurements.csv", want, ("x", "y", "hpl"))


def test_track_settings_reach_the_live_tracker(ble, server_factory, tmp_path):
    """``serve --track --sigma S --domain rssi --track-q Q --track-weight W`` gives the rows
    of ``Tracker(sigma=S, domain="rssi", q=Q, weight=W)`` (to 1e-9 m): ``--sigma`` and
    ``--domain`` were ignored with --track without a word, and the tracker's process
    noise and weight, tuned with ``robustloc track``, could not be set live."""
    track = pytest.importorskip("robustloc.tracking")
    anchors = read_anchors(ble / "anchors.csv")
    ep = to_epochs(read_measurements(ble / "measurements.csv"), anchors["anchor"])
    opts = {"sigma": 5.0, "domain": "rssi", "q": 0.05, "weight": "igg3"}
    want = track.Tracker(anchors, **opts).step(ep)
    assert np.abs(want["x"] - track.Tracker(anchors).step(ep)["x"]).max() > 1e-3
    srv = server_factory(["--anchors", str(ble / "anchors.csv"), "--track",
                          "--sigma", "5", "--domain", "rssi", "--track-q", "0.05",
                          "--track-robust", "igg3", "--idle-flush", "0.3"])
    _replayed_rows_equal(srv, ble / "measurements.csv", want, ("x", "y", "hpl"))


@pytest.mark.parametrize(("extra", "message"), [
    (["--track", "--dim", "3"], "--dim applies to the per-epoch fixes, not to --track"),
    (["--track", "--alert-limit", "2", "--k-noise", "3"],
     "--alert-limit, --k-noise apply to the per-epoch fixes, not to --track"),
    (["--track", "--robust-scale", "apriori"], "--robust-scale applies to the per-epoch"),
    (["--track-q", "0.1"], "--track-q applies to the tracker: add --track"),
    (["--track-model", "ca"], "--track-model applies to the tracker: add --track"),
])
def test_serve_refuses_the_other_modes_options(ble, extra, message):
    # (each was ignored without a word, and the service served: a subprocess with a
    # timeout, so that a regression fails instead of serving for ever)
    r = subprocess.run([*ROBUSTLOC, "serve", "--anchors", str(ble / "anchors.csv"),
                        "--port", "0", *extra], capture_output=True, text=True, timeout=120)
    assert r.returncode == 2 and message in r.stderr, r.stderr


def test_serve_cli_errors(ble, tmp_path, capsys):
    """A user's mistake is `error: ...` on stderr and exit code 2, never a traceback."""
    from robustloc.cli import main

    a = str(ble / "anchors.csv")
    assert main(["serve", "--anchors", str(tmp_path / "missing.csv")]) == 2
    assert "missing.csv" in capsys.readouterr().err
    assert main(["serve", "--anchors", a, "--floorplan", a]) == 2
    assert "--floorplan-extent" in capsys.readouterr().err
    def code(argv: list[str]) -> int:  # argparse errors: exit 2, raised or returned
        try:
            return main(argv)
        except SystemExit as e:
            return int(e.code)

    assert code(["serve", "--anchors", a, "--floorplan-extent", "1,2,3"]) == 2
    assert code(["serve", "--anchors", a, "--latency-window", "nan"]) == 2
    # the range offset is a tracker's, and for ranges
    assert main(["serve", "--anchors", a, "--track-range-offset"]) == 2
    assert "goes with --track" in capsys.readouterr().err
    assert main(["serve", "--anchors", a, "--track", "--track-range-offset",
                 "--value", "rssi"]) == 2
    assert "is for ranges" in capsys.readouterr().err
    # --domain rssi is RSSI in dB: the service accepted it with ranges, ignored it, and
    # with --track-range-offset refused every RSSI row (the service review, 2026-12-06)
    assert main(["serve", "--anchors", a, "--track", "--track-range-offset",
                 "--domain", "rssi"]) == 2
    assert "--domain rssi fits RSSI in dB: not with --track-range-offset" in (
        capsys.readouterr().err)
    assert main(["serve", "--anchors", a, "--value", "range", "--domain", "rssi"]) == 2
    assert "not with --value range" in capsys.readouterr().err
    assert main(["serve", "--anchors", a, "--track-link-offsets"]) == 2
    assert "goes with --track" in capsys.readouterr().err
    assert main(["serve", "--anchors", a, "--track", "--track-link-offsets",
                 "--track-range-offset"]) == 2
    assert "exclude each other" in capsys.readouterr().err
    from robustloc.service.launch import free_port

    nobody = f"http://127.0.0.1:{free_port()}"  # nothing listens there
    assert main(["replay", str(ble / "measurements.csv"), "--url", nobody]) == 2
    assert "error:" in capsys.readouterr().err


@pytest.mark.parametrize("extra, message", [
    (["--port", "99999"], "argument --port: expected a TCP port 1-65535"),  # (was 99999 %
    (["--port", "-5"], "argument --port: expected a TCP port"),  # 65536, announced 99999)
    (["--host", "999.1.1.1"], "error: cannot listen on 999.1.1.1:"),
    (["--mqtt", "127.0.0.1:1", "--mqtt-topic", "a/#/b"], "'#' must be a whole level"),
    (["--mqtt", "127.0.0.1:1", "--mqtt-topic", "a/b+"], "'+' must be a whole level"),
    (["--mqtt", "127.0.0.1:1", "--mqtt-topic", ""], "an empty topic filter"),
    # a token no client sends the same way (curl: UTF-8; the server reads Latin-1): 401
    # for the right token
    (["--token", "s\u00e9kret"], "error: --token: use printable ASCII characters"),
])
def test_serve_refuses_a_bad_address_or_topic_before_serving(ble, extra, message):
    """A bad port or host ended the service with uvicorn's log line and exit 3 after it
    had announced itself (``--port 99999`` served on 34463); an invalid MQTT topic filter
    killed paho's thread at the first connection and the service ran on without MQTT or
    a word of why (the service review).  Now exit 2 and one ``error:`` line, before
    anything starts (a subprocess with a timeout: a regression fails, not serves)."""
    r = subprocess.run([*ROBUSTLOC, "serve", "--anchors", str(ble / "anchors.csv"),
                        *extra], capture_output=True, text=True, timeout=120)
    assert r.returncode == 2, r.stderr
    assert message in r.stderr and "Traceback" not in r.stderr, r.stderr
    assert "robustloc serve: http" not in r.stderr


def test_serve_on_a_port_in_use_or_any_free_port(ble, tmp_path):
    """A port in use is ``error: cannot listen on ...: address already in use``, exit 2
    (was uvicorn's ``ERROR: [Errno 98]`` and exit 3), and the store it opened is released
    (the next start on it serves); ``--port 0`` announces the port the system gave (it
    announced port 0)."""
    import re
    import socket

    store = str(tmp_path / "store")
    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen(1)
        port = busy.getsockname()[1]
        r = subprocess.run([*ROBUSTLOC, "serve", "--anchors", str(ble / "anchors.csv"),
                            "--port", str(port), "--store", store], capture_output=True,
                           text=True, timeout=120)
    assert r.returncode == 2, r.stderr
    assert r.stderr.strip().splitlines()[-1] == (
        f"error: cannot listen on 127.0.0.1:{port}: address already in use (give another "
        "--port, or --port 0 for any free one)"), r.stderr
    proc = subprocess.Popen([*ROBUSTLOC, "serve", "--anchors", str(ble / "anchors.csv"),
                             "--port", "0", "--store", store], stderr=subprocess.PIPE,
                            text=True)
    try:
        line = ""
        while "robustloc serve: http" not in line:
            line = proc.stderr.readline()
            assert line, "the service ended before announcing itself"
        got = int(re.search(r"http://127\.0\.0\.1:(\d+)/", line).group(1))
        assert got > 0
        assert httpx.get(f"http://127.0.0.1:{got}/healthz", trust_env=False).json() == {
            "status": "ok"}
    finally:
        proc.terminate()
        proc.wait(30)


def test_mqtt_ingest_checks_its_topic_filter():
    import re

    from robustloc.service.topics import check_topic_filter

    for good in ("#", "+", "a/+/b", "robustloc/measurements/#", "a//b", "/"):
        assert check_topic_filter(good) == good
    for bad, why in (("a/#/b", "'#'"), ("a#", "'#'"), ("+a", "'+'"), ("a/b+/c", "'+'"),
                     ("", "empty"), ("a\0b", "NUL"), ("x" * 65536, "65535"),
                     ("\udcff", "UTF-8")):
        with pytest.raises(ValueError, match=re.escape(why)):
            check_topic_filter(bad)


def test_latency_reservoir_is_uniform():
    """The vectorized reservoir (algorithm R) keeps each of N latencies with probability
    cap/N: over 200 runs the first 100 of N = 1 000 (fed in blocks of 37) are kept
    200 * 100 * cap/N = 1 000 times in expectation, binomial sd ~31; 5 sd allowed."""
    from robustloc.service import metrics as metrics_mod

    kept = 0
    for seed in range(200):
        m = metrics_mod.Metrics(["A0"])
        m._reservoir = np.empty(50)
        m._rng = np.random.default_rng(seed)
        x = np.arange(1000, dtype=float)
        for i in range(0, 1000, 37):
            blk = x[i:i + 37]
            m.solved(np.array(["ok"] * len(blk), dtype=object), blk)
        s = m.latency_sample()
        assert len(s) == 50 and len(np.unique(s)) == 50
        kept += int((s < 100).sum())
    assert abs(kept - 1000) < 5 * np.sqrt(1000 * 0.95)
    m = metrics_mod.Metrics(["A0"])  # not yet full: every latency kept, in order
    m.solved(np.array(["ok"] * 3, dtype=object), np.array([0.3, 0.1, 0.2]))
    assert m.latency_sample().tolist() == [0.3, 0.1, 0.2]


def test_epoch_rows_finds_each_epochs_block():
    """Blocks solved together: each epoch's ready time is its block's (looked up by its
    exact (time, tag) among the rows)."""
    from robustloc.service.engine import _epoch_rows

    t = np.array([0.1, 0.1, 0.2, 0.1, 0.3, 0.2])
    code = np.array([0, 0, 1, 1, 0, 0])
    et = np.array([0.1, 0.1, 0.2, 0.2, 0.3])
    ecode = np.array([0, 1, 0, 1, 0])
    i = _epoch_rows(t, code, et, ecode)
    assert (t[i] == et).all() and (code[i] == ecode).all()


def test_assembler_epochs_equal_to_epochs():
    """The live pivot (rows already coded) is the batch pivot: same epochs in the same
    order (time, then tag name, whatever order the tags were first seen in), duplicates
    averaged and counted, implausible values counted as invalid."""
    rng = np.random.default_rng(3)
    ids = ["A0", "A1", "A2"]
    n = 400
    t = np.round(rng.integers(0, 20, n) * 0.1, 1)
    tags = rng.choice(np.array(["z", "b", "Ä", "a10", "a9"], dtype=object), n)
    col = rng.integers(0, 3, n)
    v = rng.normal(5, 1, n)
    v[::37] = 1e9  # outside the range limits: invalid, counted
    a = EpochAssembler(ids, 0.0, 1.0)
    a.add(t, tags, col, v, wall=0.0)
    rows = a.take_ready(0.0, flush_all=True)
    got = a.epochs(rows, "range")
    want = to_epochs(pd.DataFrame({"time": t, "tag": tags, "anchor": np.array(ids)[col],
                                   "range": v}), ids, "range")
    for f in ("time", "tag", "values", "line", "n_invalid"):
        np.testing.assert_array_equal(getattr(got, f), getattr(want, f))
    assert got.n_duplicates == want.n_duplicates > 0 and want.n_invalid.sum() > 0


def test_assembler_idle_hint():
    """The solver asks may_have_idle (no lock) before taking the ingest lock for idle
    flushes: True exactly when a tag with pending rows has been quiet for idle_flush_s."""
    a = EpochAssembler(["A0"], 0.5, 100.0)
    assert not a.may_have_idle(1e9)  # nothing pending
    obj = lambda *x: np.array(x, dtype=object)  # noqa: E731
    a.add(np.array([0.0]), obj("t"), np.array([0]), np.array([1.0]), wall=0.0)
    a.add(np.array([0.0]), obj("u"), np.array([0]), np.array([1.0]), wall=60.0)
    assert not a.may_have_idle(99.0)
    assert a.may_have_idle(100.0)  # t quiet for 100 s
    assert a.take_ready(100.0)["tag"].tolist() == ["t"]
    assert not a.may_have_idle(100.0) and a.may_have_idle(160.0)


# --------------------------------------------------------------------------------------
# defects found by fuzzing the live service (2026-12-02): each test fails on the old code
# --------------------------------------------------------------------------------------


def test_deep_json_huge_numbers_and_many_rows_are_4xx(ble, server_factory, tmp_path):
    """A body of 100 000 nested objects killed the server (orjson's stack overflow,
    SIGSEGV); an integer beyond float range gave a 500; a body of 1.2 M tiny rows held the
    server for minutes and answered with one `rejected` entry per row.  Now: 400 (too
    deep), the row rejected with its reason, 413 (too many rows), and a reply listing at
    most 1 000 rejected rows with their count."""
    s = server_factory(["--anchors", str(ble / "anchors.csv"),
                        "--max-body-bytes", "4000000"])
    u = s.url
    post = lambda b: httpx.post(u + "/api/measurements", content=b, timeout=60)  # noqa: E731
    for deep in (b'{"a":' * 100_000 + b"1" + b"}" * 100_000,
                 b'[{"time":' + b'{"a":' * 100_000 + b"1" + b"}" * 100_000 + b"}]"):
        r = post(deep)
        assert r.status_code == 400 and "nested too deeply" in r.json()["error"], r.text
    huge = b'[{"time": 1' + b"0" * 400 + b', "tag": "T", "anchor": "1", "rssi": -60}]'
    r = post(huge)
    assert r.status_code == 202 and "beyond the range of a float" in r.json()["rejected"][0][
        "error"]
    r = post(b"[" + b"0," * 1_200_000 + b"0]")
    assert r.status_code == 413 and "rows" in r.json()["error"]
    r = post(json.dumps([1] * 1500).encode())
    body = r.json()
    assert r.status_code == 202 and body["n_rejected"] == 1500
    assert len(body["rejected"]) == 1000 and body["rejected"][-1]["index"] == 999
    assert s.proc.poll() is None and httpx.get(u + "/healthz").status_code == 200
    assert metric(u, 'robustloc_requests_rejected_total{reason="too_many_rows"}') == 1


def test_rows_beyond_counts_what_parse_body_decodes():
    """The count before decoding equals the rows :func:`parse_body` decodes: JSON arrays
    whose strings hold brackets, commas, quotes and backslashes, NDJSON with blank lines,
    at every chunk boundary (hypothesis)."""
    hypothesis = pytest.importorskip("hypothesis")
    from hypothesis import strategies as hs

    import robustloc.service.rows as rows_mod
    from robustloc.service.rows import rows_beyond

    text = hs.text(alphabet='\\"[]{},: ax\u00e9', max_size=6)
    value = hs.recursive(hs.none() | hs.integers() | text,
                         lambda inner: hs.lists(inner, max_size=3)
                         | hs.dictionaries(text, inner, max_size=3), max_leaves=12)

    @hypothesis.settings(max_examples=400, deadline=None)
    @hypothesis.given(doc=hs.lists(value, max_size=8), sep=hs.sampled_from([",", " ,\n "]),
                      chunk=hs.sampled_from([1, 2, 3, 5, 1 << 20]), ndjson=hs.booleans(),
                      blank=hs.sampled_from(["", " ", "\t\r "]))
    def check(doc, sep, chunk, ndjson, blank):
        if ndjson:
            body = f"\n{blank}\n".join(json.dumps(d) for d in doc if isinstance(d, dict))
        else:
            body = json.dumps(doc, separators=(sep, ":"))
        try:
            want = len(parse_body(body)[0])
        except BodyError:
            return
        saved = rows_mod._COUNT_CHUNK
        rows_mod._COUNT_CHUNK = chunk
        try:
            assert rows_beyond(body, -1) == want
            assert rows_beyond(body, want) is None
        finally:
            rows_mod._COUNT_CHUNK = saved

    check()


def test_bodies_decoded_row_by_row_take_turns(monkeypatch):
    """At most MAX_CONCURRENT_ROW_PARSES bodies are decoded row by row at once (each
    holds its rows as Python objects); the others wait, and every body is answered."""
    import asyncio
    import threading

    import pandas as pd

    import robustloc.service.app as app_mod
    from robustloc.service.defaults import MAX_CONCURRENT_ROW_PARSES
    from robustloc.service.engine import Engine

    anchors = pd.DataFrame({"anchor": ["A1", "A2", "A3"], "x": [0, 10, 0.0],
                            "y": [0, 0, 10.0]})
    eng = Engine(anchors, LocateProcessor(anchors, method="nls"), latency_window_s=0.0,
                 idle_flush_s=600.0, fsync=False)
    lock, now, most = threading.Lock(), [0], [0]

    def slow_parse(body):
        with lock:
            now[0] += 1
            most[0] = max(most[0], now[0])
        time.sleep(0.3)
        with lock:
            now[0] -= 1
        return parse_body(body)

    monkeypatch.setattr(app_mod, "parse_body", slow_parse)
    app = app_mod.create_app(eng)
    body = b'{"time": 1, "tag": "T", "anchor": "A1", "range": 5}\n'  # NDJSON: row by row

    async def main():
        transport = httpx.ASGITransport(app=app)
        async with httpx.AsyncClient(transport=transport, base_url="http://t") as client:
            return await asyncio.gather(*(client.post("/api/measurements", content=body)
                                          for _ in range(6)))

    try:
        answers = asyncio.run(main())
    finally:
        eng.stop()
    assert [r.status_code for r in answers] == [202] * 6
    assert most[0] == MAX_CONCURRENT_ROW_PARSES


def _hwm_kb(pid: int) -> int:
    """The peak resident memory of a process (kB, Linux ``VmHWM``)."""
    return int(Path(f"/proc/{pid}/status").read_text().split("VmHWM:")[1].split()[0])


@pytest.mark.parametrize("kind", ["ndjson", "array"])
def test_a_body_of_too_many_rows_is_refused_before_it_is_decoded(ble, server_factory, kind):
    """A 32 MiB body of ``{}`` rows (within the default --max-body-bytes) was decoded
    whole before its 413 for too many rows: 1.5 GB of the server's memory per body, 4.66
    GB for three at once (the serve review).  It is refused, with the same reason and
    counter, with a bounded peak."""
    if not Path("/proc/self/status").exists():
        pytest.skip("the peak memory is read from /proc (Linux)")
    s = server_factory(["--anchors", str(ble / "anchors.csv")])
    n = (32 * 1024 * 1024 - 2) // 3
    body = b"{}\n" * n if kind == "ndjson" else b"[" + b"{}," * (n - 1) + b"{}]"
    before = _hwm_kb(s.proc.pid)
    r = httpx.post(s.url + "/api/measurements", content=body, timeout=120)
    assert r.status_code == 413, r.text
    assert r.json()["error"] == f"body holds {n} rows, more than 1000000: send it in parts"
    # the body itself is held twice or thrice (received chunks, joined, stripped)
    assert _hwm_kb(s.proc.pid) - before < 400_000
    assert metric(s.url, 'robustloc_requests_rejected_total{reason="too_many_rows"}') == 1
    assert httpx.get(s.url + "/healthz").status_code == 200


def test_the_rows_of_a_body_are_counted_without_decoding_it(monkeypatch):
    """In process: the refusal does not call the decoder, and its peak allocation is a
    fraction of what decoding took (tracemalloc)."""
    import tracemalloc

    import pandas as pd

    import robustloc.service.app as app_mod
    from robustloc.service.engine import Engine

    anchors = pd.DataFrame({"anchor": ["A1", "A2", "A3"], "x": [0, 10, 0.0],
                            "y": [0, 0, 10.0]})
    eng = Engine(anchors, LocateProcessor(anchors, method="nls"), latency_window_s=0.0,
                 idle_flush_s=600.0, fsync=False)
    calls = []
    monkeypatch.setattr(app_mod, "parse_body", lambda *a: calls.append(a) or parse_body(*a))
    import asyncio

    async def post(body: bytes):
        transport = httpx.ASGITransport(app=app_mod.create_app(eng))
        async with httpx.AsyncClient(transport=transport, base_url="http://t") as client:
            return await client.post("/api/measurements", content=body)

    body = b"{}\n" * 3_000_000  # 9 MB: 3 million rows
    tracemalloc.start()
    try:
        r = asyncio.run(post(body))
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
        eng.stop()
    assert r.status_code == 413 and "3000000 rows" in r.json()["error"]
    assert not calls
    assert peak < 100e6  # (decoding it: some 450 MB)
    assert eng.metrics.requests_rejected == {"too_many_rows": 1}


def test_a_body_the_fast_decoder_takes_is_held_to_the_row_limit(monkeypatch):
    """A JSON array of valid rows goes through the fast decoder, which skipped the row
    limit (a body of more than 1 000 000 rows was accepted above --max-body-bytes 44 MB:
    the review of the fix).  With the limit at 5 (monkeypatched), 6 valid rows get the
    413 and nothing is stored; 5 are accepted."""
    import asyncio

    import pandas as pd

    import robustloc.service.app as app_mod
    from robustloc.service.engine import Engine

    monkeypatch.setattr(app_mod, "MAX_ROWS_PER_BODY", 5)
    anchors = pd.DataFrame({"anchor": ["A1", "A2", "A3"], "x": [0, 10, 0.0],
                            "y": [0, 0, 10.0]})
    eng = Engine(anchors, LocateProcessor(anchors, method="nls"), latency_window_s=0.0,
                 idle_flush_s=600.0, fsync=False)

    def body(n: int) -> bytes:
        return json.dumps([{"time": float(i), "tag": "t", "anchor": "A1", "range": 5.0}
                           for i in range(n)]).encode()

    eng.ingest([{"time": 100.0, "tag": "u", "anchor": "A1", "range": 5.0}])  # (the value)
    assert eng.decode(body(6)) is not None  # (the fast path, once the value is fixed)

    async def post(data: bytes):
        transport = httpx.ASGITransport(app=app_mod.create_app(eng))
        async with httpx.AsyncClient(transport=transport, base_url="http://t") as client:
            return await client.post("/api/measurements", content=data)

    try:
        r = asyncio.run(post(body(6)))
        assert r.status_code == 413 and "6 rows, more than 5" in r.json()["error"]
        assert eng.metrics.requests_rejected == {"too_many_rows": 1}
        r = asyncio.run(post(body(5)))
        assert r.status_code == 202 and r.json()["accepted"] == 5
    finally:
        eng.stop()


def test_unknown_routes_and_methods_are_json_and_counted(tokened):
    u = tokened.url
    r = httpx.get(u + "/nope", headers=AUTH)
    assert r.status_code == 404 and "/nope" in r.json()["error"]
    r = httpx.put(u + "/api/measurements", headers=AUTH)
    assert r.status_code == 405 and "POST" in r.json()["error"]
    assert metric(u, 'robustloc_requests_rejected_total{reason="not_found"}', AUTH) == 1
    assert metric(u, 'robustloc_requests_rejected_total{reason="method_not_allowed"}',
                  AUTH) == 1


def test_a_body_that_stops_arriving_gets_408(ble, server_factory):
    """A client that announces 100 bytes and sends 10 held its connection forever."""
    import socket

    s = server_factory(["--anchors", str(ble / "anchors.csv"), "--body-timeout", "1"])
    with socket.create_connection(("127.0.0.1", s.port), timeout=20) as c:
        c.sendall(b"POST /api/measurements HTTP/1.1\r\nHost: x\r\nContent-Length: 100\r\n"
                  b"Content-Type: application/json\r\n\r\n[{\"time\":")
        reply = c.recv(4096)
    assert reply.startswith(b"HTTP/1.1 408"), reply[:80]
    assert metric(s.url, 'robustloc_requests_rejected_total{reason="body_timeout"}') == 1


def test_times_round_trip_and_late_rows_are_reported(ble, server_factory):
    """Positions came back with 15 decimals (3.3000000000000003 -> 3.3, 1/3 ->
    0.333333333333333): a client matching its epochs by time missed them.  The reply
    now also counts the late rows it accepted."""
    s = server_factory(["--anchors", str(ble / "anchors.csv"), "--latency-window", "0",
                        "--idle-flush", "0.3"])
    u = s.url
    times = [1.1 + 2.2, 10 + 1 / 3, 20.0]
    rows = [{"time": t, "tag": "R", "anchor": a, "rssi": -65.0 - int(a)}
            for t in times for a in "12345"]
    assert httpx.post(u + "/api/measurements", json=rows).json()["late"] == 0
    # a row of a solved epoch (window 0: solved as the next came; an epoch never solved
    # would be solved all the same: test_service_late_epochs.py)
    late = [{"time": times[0], "tag": "R", "anchor": "1", "rssi": -60.0}]
    body = httpx.post(u + "/api/measurements", json=late).json()
    assert body["accepted"] == 1 and body["late"] == 1
    got = wait_for(lambda: (p := httpx.get(u + "/api/positions?tag=R").json())
                   and len(p) == 3 and p, what="three positions")
    assert [p["time"] for p in got] == times  # exactly, as sent
    latest = httpx.get(u + "/api/latest").json()
    assert [p["time"] for p in latest] == [20.0]


def test_rssi_rows_cannot_lock_a_range_service(server_factory, tmp_path):
    """Anchors without path loss: the first accepted row fixed the service's value, so one
    stray RSSI row locked it to RSSI for good (even across restarts) and every range row
    was refused.  Now RSSI rows are refused with the reason and ranges are located."""
    anchors = tmp_path / "a.csv"
    anchors.write_text("anchor,x,y\nA1,0,0\nA2,10,0\nA3,10,10\nA4,0,10\nA5,5,12\n")
    store = tmp_path / "store"
    s = server_factory(["--anchors", str(anchors), "--store", str(store),
                        "--latency-window", "0", "--idle-flush", "0.3"])
    u = s.url
    r = httpx.post(u + "/api/measurements",
                   json=[{"time": 1, "tag": "x", "anchor": "A1", "rssi": -60}])
    assert r.status_code == 202 and r.json()["accepted"] == 0
    assert "path-loss" in r.json()["rejected"][0]["error"]
    xy = {"A1": (0, 0), "A2": (10, 0), "A3": (10, 10), "A4": (0, 10), "A5": (5, 12)}
    rows = [{"time": t, "tag": "x", "anchor": a, "range": float(np.hypot(3 - p[0], 4 - p[1]))}
            for t in (2.0, 3.0) for a, p in xy.items()]
    r = httpx.post(u + "/api/measurements", json=rows)
    assert r.json()["accepted"] == 10 and r.json()["n_rejected"] == 0
    got = wait_for(lambda: (p := httpx.get(u + "/api/positions?tag=x").json())
                   and len(p) == 2 and p, what="two fixes")
    assert [(round(p["x"], 6), round(p["y"], 6)) for p in got] == [(3.0, 4.0)] * 2
    assert httpx.get(u + "/api/status").json()["value"] == "range"


def test_new_tags_while_solving_lose_no_epoch(ble):
    """The solver thread read (and grew) the assembler's tag registry without the ingest
    lock: with many tags, blocks failed ("Inconsistent object during array creation") and
    their epochs were lost.  Four threads now register new tags while the solver runs;
    every accepted epoch gets exactly one position row and the solver never fails."""
    import threading

    from robustloc.service.engine import Engine

    anchors = read_anchors(ble / "anchors.csv")
    ids = [str(a) for a in anchors["anchor"]]
    eng = Engine(anchors, LocateProcessor(anchors, method="ls"), latency_window_s=0.0,
                 idle_flush_s=0.05, fsync=False)
    eng.assembler.codes(np.array([f"pre{i}" for i in range(50_000)], dtype=object))
    eng.start()
    try:
        def feed(k: int) -> None:
            for j in range(40):
                rows = [{"time": t, "tag": f"w{k}-{j}-{g}", "anchor": a, "rssi": -70.0}
                        for g in range(20) for t in (0.0, 1.0) for a in ids[:4]]
                assert eng.ingest(rows).accepted == len(rows)

        threads = [threading.Thread(target=feed, args=(k,)) for k in range(4)]
        for th in threads:
            th.start()
        for th in threads:
            th.join()
        eng.flush()
        pos = eng.positions(limit=10_000_000)
    finally:
        eng.stop()
    assert eng.solver_errors == 0, eng.last_error
    assert len(pos) == 4 * 40 * 20 * 2
    assert not pos.duplicated(["time", "tag"]).any()


def test_a_failing_block_costs_only_its_failing_tag():
    """A processor that raises lost every epoch of its block.  Now a stateless processor's
    block is split by tag, then by epoch, and retried: every other epoch gets its fix, the
    failing epoch a `solver_error` row, and the failure is counted and reported."""
    from robustloc.io.tables import Epochs
    from robustloc.service.engine import Engine

    anchors = pd.DataFrame({"anchor": ["A1", "A2", "A3", "A4"], "x": [0, 10, 10, 0.0],
                            "y": [0, 0, 10, 10.0]})

    class Flaky(LocateProcessor):  # fails on any block holding tag "bad" at t = 1
        def process(self, epochs: Epochs) -> pd.DataFrame:
            if ((epochs.tag == "bad") & (epochs.time == 1.0)).any():
                raise FloatingPointError("boom")
            return super().process(epochs)

    eng = Engine(anchors, Flaky(anchors, method="nls"), latency_window_s=0.0,
                 idle_flush_s=10.0, value="range", fsync=False)
    xy = anchors[["x", "y"]].to_numpy(float)
    rng = np.hypot(*(xy - [3.0, 4.0]).T)
    rows = [{"time": t, "tag": g, "anchor": a, "range": float(r)}
            for t in (0.0, 1.0, 2.0) for g in ("a", "bad", "c", "d", "e")
            for a, r in zip(anchors["anchor"], rng)]
    assert eng.ingest(rows).accepted == len(rows)
    eng.flush()
    pos = eng.positions()
    assert len(pos) == 15 and not pos.duplicated(["time", "tag"]).any()
    bad = (pos["tag"] == "bad") & (pos["time"] == 1.0)  # only the failing epoch
    assert (pos.loc[bad, "status"] == "solver_error").all() and pos.loc[bad, "x"].isna().all()
    assert bad.sum() == 1
    np.testing.assert_allclose(pos.loc[~bad, ["x", "y"]].to_numpy(float),
                               np.tile([3.0, 4.0], (14, 1)), atol=1e-6)
    assert eng.solver_errors >= 1 and "FloatingPointError: boom" in eng.last_error
    eng.stop()


def test_a_failing_track_block_is_rolled_back_and_costs_only_its_failing_tag():
    """`serve --track`: a tracker that raised gave its whole block `solver_error` rows
    (stop 33's left-out list), and its state might have advanced part-way.  Now the
    tracker is rolled back to its state before the block and the block retried tag by tag:
    the other tags' rows are exactly a tracker's that never met the failure, and the
    failing tag's state stays as before the block (its next rows are a tracker's that never
    saw the failed epoch)."""
    from robustloc.io.tables import Epochs
    from robustloc.service.engine import Engine
    from robustloc.service.processor import TrackProcessor
    from robustloc.tracking import Tracker

    anchors = pd.DataFrame({"anchor": ["A1", "A2", "A3", "A4"], "x": [0, 10, 10, 0.0],
                            "y": [0, 0, 10, 10.0]})

    class Flaky(TrackProcessor):  # advances every tag's state, then fails on "bad" at t=2
        def process(self, epochs: Epochs) -> pd.DataFrame:
            out = super().process(epochs)
            if ((epochs.tag == "bad") & (epochs.time == 2.0)).any():
                raise FloatingPointError("boom")
            return out

    eng = Engine(anchors, Flaky(anchors), latency_window_s=0.0, idle_flush_s=10.0,
                 value="range", fsync=False)
    xy = anchors[["x", "y"]].to_numpy(float)
    tags = ("a", "bad", "c")
    rows_at = {t: [{"time": t, "tag": g, "anchor": a,
                    "range": float(np.hypot(*(p - [3.0 + 0.5 * t + i, 4.0])))}
                   for i, g in enumerate(tags) for a, p in zip(anchors["anchor"], xy)]
               for t in (0.0, 1.0, 2.0, 3.0, 4.0)}
    try:
        for rows in rows_at.values():
            assert eng.ingest(rows).accepted == len(rows)
            eng.flush()  # one block per time
        pos = eng.positions().sort_values(["time", "tag"]).reset_index(drop=True)
    finally:
        eng.stop()
    assert len(pos) == 15 and not pos.duplicated(["time", "tag"]).any()
    failed = (pos["tag"] == "bad") & (pos["time"] == 2.0)
    assert (pos.loc[failed, "status"] == "solver_error").all() and failed.sum() == 1
    assert not (pos.loc[~failed, "status"] == "solver_error").any()
    assert eng.solver_errors >= 1 and "FloatingPointError: boom" in eng.last_error
    # the reference: a tracker fed the same blocks without the failed epoch
    ref = Tracker(anchors)
    want = []
    for t, rows in rows_at.items():
        keep = [r for r in rows if not (r["tag"] == "bad" and t == 2.0)]
        ep = to_epochs(pd.DataFrame(keep), ["A1", "A2", "A3", "A4"])
        want.append(ref.step(ep))
    want = pd.concat(want).sort_values(["time", "tag"]).reset_index(drop=True)
    got = pos.loc[~failed].reset_index(drop=True)
    np.testing.assert_allclose(got[["x", "y"]].to_numpy(float),
                               want[["x", "y"]].to_numpy(float), rtol=0, atol=1e-9)
    assert got["status"].tolist() == want["status"].tolist()


def test_track_snapshot_does_not_claim_blocks_queued_meanwhile(tmp_path):
    """The tracker's snapshot saved the assembler's watermarks, which also count blocks the
    ingest threads queued while the solver was busy; after a restart those epochs were
    taken as solved and never got a row.  The snapshot now saves the epochs the processor
    has processed: every epoch gets exactly one row across the restart."""
    pytest.importorskip("robustloc.tracking")
    from robustloc.service.engine import Engine
    from robustloc.service.processor import TrackProcessor

    anchors = pd.DataFrame({"anchor": ["A1", "A2", "A3", "A4"], "x": [0, 10, 10, 0.0],
                            "y": [0, 0, 10, 10.0]})
    xy = anchors[["x", "y"]].to_numpy(float)
    rng = np.hypot(*(xy - [3.0, 4.0]).T)

    def rows(times):
        return [{"time": float(t), "tag": "T", "anchor": a, "range": float(r)}
                for t in times for a, r in zip(anchors["anchor"], rng)]

    store = tmp_path / "store"
    eng = Engine(anchors, TrackProcessor(anchors), store_dir=store, latency_window_s=0.0,
                 idle_flush_s=600.0, value="range", fsync=False, snapshot_s=0)
    inner = eng.processor.process
    calls = []

    def busy(epochs):  # rows arrive while the solver works: epochs 2 and 3 become ready
        if not calls:
            eng.ingest(rows([3.0, 4.0]))
        calls.append(epochs.n_epochs)
        return inner(epochs)

    eng.processor.process = busy
    eng.ingest(rows([0.0, 1.0, 2.0]))  # 0 and 1 ready (window 0)
    eng.step()  # solves 0, 1; meanwhile 2, 3 are queued
    eng._snapshot()
    eng.stop()  # the queued block is not solved: a crash at this point
    assert calls == [2]
    eng2 = Engine(anchors, TrackProcessor(anchors), store_dir=store, latency_window_s=0.0,
                  idle_flush_s=600.0, value="range", fsync=False, snapshot_s=0)
    eng2.flush()
    pos = eng2.positions()
    eng2.stop()
    assert sorted(pos["time"].tolist()) == [0.0, 1.0, 2.0, 3.0, 4.0]


def test_websocket_frame_over_the_size_limit_is_counted(tokened):
    """A WebSocket frame larger than ``--max-body-bytes`` is closed by the server (1009,
    message too big) before the app sees it; the refusal is counted in ``/metrics`` as an
    HTTP body of that size is (``reason="too_large"``), and the service keeps serving."""
    from websockets.exceptions import ConnectionClosed
    from websockets.sync.client import connect

    ws_url = tokened.url.replace("http://", "ws://")
    name = 'robustloc_requests_rejected_total{reason="too_large"}'
    before = metric(tokened.url, name, AUTH)
    with connect(ws_url + "/ws/measurements", additional_headers=AUTH,
                 max_size=None) as pub:
        pub.send("[" + " " * 300_000 + "]")  # 300 kB against the limit of 200 000 bytes
        with pytest.raises(ConnectionClosed) as info:
            pub.recv(timeout=10)
    assert info.value.rcvd is not None and info.value.rcvd.code == 1009
    wait_for(lambda: metric(tokened.url, name, AUTH) == before + 1, timeout=10,
             what="the oversized frame counted")
    # still serving WebSocket ingest
    with connect(ws_url + "/ws/measurements", additional_headers=AUTH) as pub:
        pub.send(json.dumps([{"time": 0.0, "tag": "Z", "anchor": "1", "rssi": -70.0}]))
        assert json.loads(pub.recv(timeout=10))["accepted"] == 1


def test_serve_names_a_suspect_anchor_of_its_recorded_log(server_factory, tmp_path):
    """``serve --scale-from LOG`` runs locate's first pass: an anchor placed 100 m from
    where its ranges say is named at start, as ``locate`` names it (same message, same
    ratio); the correctly placed layout starts without a warning."""
    from test_cli_locate import _room_with_a_misplaced_anchor

    m, a, _ = _room_with_a_misplaced_anchor(tmp_path, 100.0)
    out = subprocess.run([*ROBUSTLOC, "locate", str(m), "--anchors", str(a), "-o",
                          str(tmp_path / "f.csv"), "--json"], check=True,
                         capture_output=True, text=True).stdout
    ratio = json.loads(out)["anchors_suspect"]["A2"]
    srv = server_factory(["--anchors", str(a), "--scale-from", str(m),
                          "--store", str(tmp_path / "store")])
    assert f"warning: {a}: the measurements of anchor(s) A2 ({ratio:g}x)" in srv.log()
    m0, a0, _ = _room_with_a_misplaced_anchor(tmp_path, 0.0)
    ok = server_factory(["--anchors", str(a0), "--scale-from", str(m0),
                         "--store", str(tmp_path / "store0")])
    assert "warning" not in ok.log()


def test_store_scan_has_every_segments_columns(tmp_path):
    """A dataset of several Parquet files takes the first file's schema: a first segment
    of the engine's fallback rows (six columns, ``solver_error``) hid ``hpl`` and the
    covariance terms of every later segment after a restart (the service review found
    it).  The scan now reads the union of the segments' columns."""
    import pyarrow as pa
    import pyarrow.dataset as ds

    log = SegmentLog(tmp_path, seal_rows=1, fsync=False)
    log.append(pa.table({"time": [1.0], "tag": ["a"], "x": pa.nulls(1, pa.float64()),
                         "status": ["solver_error"]}))
    log.append(pa.table({"time": [2.0], "tag": ["g"], "x": [1.5], "status": ["ok"],
                         "hpl": [3.0], "n_used": pa.array([4], pa.int64())}))
    log.wait_sealed()
    log.close()
    log2 = SegmentLog(tmp_path, fsync=False)
    assert len(list(tmp_path.glob("*.parquet"))) == 2
    t = log2.scan().to_pandas().sort_values("time")
    assert list(t.columns) == ["time", "tag", "x", "status", "hpl", "n_used"]
    assert t["hpl"].isna().tolist() == [True, False] and t["hpl"].iloc[1] == 3.0
    g = log2.scan(columns=["time", "hpl"], expression=ds.field("tag") == "g").to_pandas()
    assert g.to_dict("list") == {"time": [2.0], "hpl": [3.0]}
    log2.close()


def test_a_store_of_track_rows_refuses_a_locate_service_and_back(tmp_path):
    """Track rows and position rows in one store: after a restart the later rows lost the
    columns the first kind lacked.  The store records its kind of rows (``meta.json``)
    and a service of the other kind is refused with a message naming the flag."""
    pytest.importorskip("robustloc.tracking")
    from robustloc.service.engine import Engine
    from robustloc.service.processor import TrackProcessor

    anchors = pd.DataFrame({"anchor": ["A1", "A2", "A3", "A4"], "x": [0, 10, 10, 0.0],
                            "y": [0, 0, 10, 10.0]})
    rng = np.hypot(*(anchors[["x", "y"]].to_numpy(float) - [3.0, 4.0]).T)
    rows = [{"time": t, "tag": "T", "anchor": a, "range": float(r)}
            for t in (0.0, 1.0, 2.0) for a, r in zip(anchors["anchor"], rng)]
    for first, second, flag in (("locate", "track", "without --track"),
                                ("track", "locate", "with --track")):
        store = tmp_path / first

        def make(kind, store=store):
            proc = (TrackProcessor(anchors) if kind == "track"
                    else LocateProcessor(anchors, method="nls"))
            return Engine(anchors, proc, store_dir=store, latency_window_s=0.0,
                          idle_flush_s=600.0, fsync=False)

        eng = make(first)
        eng.ingest(rows)
        eng.flush()
        eng.stop()
        with pytest.raises(ValueError, match=flag):
            make(second)
        eng = make(first)  # the same kind restarts
        assert len(eng.positions()) == 3
        eng.stop()


def test_a_client_that_leaves_mid_body_is_counted_as_its_own_reason(ble, server_factory):
    """A client that closed its connection mid-body was logged with a traceback and
    counted as ``internal_error`` (a server defect).  It is the client's doing: counted
    as ``client_disconnect``, nothing stored, the server keeps serving."""
    import socket

    s = server_factory(["--anchors", str(ble / "anchors.csv")])
    for _ in range(3):
        with socket.create_connection(("127.0.0.1", s.port), timeout=20) as c:
            c.sendall(b"POST /api/measurements HTTP/1.1\r\nHost: x\r\nContent-Length: 100"
                      b"\r\n\r\n[{\"time\":1")
    wait_for(lambda: metric(s.url, 'robustloc_requests_rejected_total'
                                   '{reason="client_disconnect"}') == 3,
             what="three client_disconnect rejections")
    assert metric(s.url, 'robustloc_requests_rejected_total{reason="internal_error"}') == 0
    assert httpx.get(s.url + "/healthz").status_code == 200


def test_assembler_rebases_a_tag_whose_clock_jumped():
    """One row at 9e11 s made every later row of its tag late (stored, never solved)
    for good (the service review).  A row more than ``time_jump_s`` behind the tag's
    newest time, nothing near that time for ``idle_flush_s``, re-bases the tag; a
    delayed row while the tag's stream stays current does not."""
    a = EpochAssembler(["A"], latency_window_s=0.0, idle_flush_s=2.0, time_jump_s=3600.0)
    obj = lambda *x: np.array(x, dtype=object)  # noqa: E731

    def add(t, tag="v", wall=0.0):
        code = a.codes(obj(*([tag] * len(t))))
        reb = a.rebase(np.array(t, float), code, wall)
        late = a.late(np.array(t, float), code)
        a.add_coded(np.array(t, float), code, np.zeros(len(t), np.int64),
                    np.ones(len(t)), wall, late)
        return reb.size, late.tolist()

    assert add([10.0, 11.0, 12.0]) == (0, [False] * 3)
    assert a.take_ready(0.0)["time"].tolist() == [10.0, 11.0]
    assert add([9e11]) == (0, [False])  # ahead: not late; 12 becomes ready
    assert a.take_ready(0.1)["time"].tolist() == [12.0]
    # the stream goes on at 13: within the idle time of the 9e11 row, late (one delayed
    # row is not a jump); after it, the tag re-bases and its 9e11 epoch is released
    assert add([13.0], wall=1.0) == (0, [True])
    assert add([13.0], wall=3.0) == (1, [False])
    r = a.take_ready(3.0)
    assert r["time"].tolist() == [9e11]
    assert add([14.0], wall=3.5) == (0, [False])
    assert a.take_ready(3.5)["time"].tolist() == [13.0]
    assert a.rebased == 1 and a.watermarks()["v"] == 13.0
    # a gateway uploading rows buffered for two hours while the tag stays current:
    # late, no re-base
    for k in range(10):
        add([20_000.0 + k], tag="g", wall=100.0 + k)
        assert add([20_000.0 + k - 7200.0], tag="g", wall=100.0 + k) == (0, [True])
    assert a.rebased == 1


@pytest.mark.parametrize("track", [False, True])
def test_a_tag_whose_clock_jumped_gets_its_rows_solved_again(ble, server_factory, track):
    """The review's reproduction on a real server: epochs 10-12, one row at 9e11, then
    13-15.  They were accepted as late and never solved; now the tag re-bases once
    (counted) and every epoch after the jump gets its row (the tracker's too: its time
    goes back from 9e11 to 13)."""
    if track:
        pytest.importorskip("robustloc.tracking")
    s = server_factory(["--anchors", str(ble / "anchors.csv"), "--latency-window", "0",
                        "--idle-flush", "0.3", *(["--track"] if track else [])])
    u = s.url

    def epochs(times):
        return [{"time": t, "tag": "V", "anchor": a, "rssi": -65.0 - int(a)}
                for t in times for a in "12345"]

    httpx.post(u + "/api/measurements", json=epochs([10.0, 11.0, 12.0]))
    httpx.post(u + "/api/measurements",
               json=[{"time": 9e11, "tag": "V", "anchor": "1", "rssi": -70.0}])
    wait_for(lambda: len(httpx.get(u + "/api/positions?tag=V").json()) == 4,
             what="the 9e11 epoch solved by the idle flush")
    time.sleep(0.5)  # nothing near 9e11 for the idle flush: the next rows re-base
    body = httpx.post(u + "/api/measurements", json=epochs([13.0, 14.0, 15.0])).json()
    assert body["accepted"] == 15 and body["late"] == 0
    got = wait_for(lambda: (p := httpx.get(u + "/api/positions?tag=V").json())
                   and len(p) == 7 and p, what="seven positions")
    assert sorted(p["time"] for p in got) == [10.0, 11.0, 12.0, 13.0, 14.0, 15.0, 9e11]
    after = [p for p in got if 13.0 <= p["time"] <= 15.0]
    assert all(p["status"] != "solver_error" and p["x"] is not None for p in after)
    assert metric(u, "robustloc_tags_rebased_total") == 1
    assert httpx.get(u + "/api/status").json()["tags_rebased"] == 1


#: The anchors of the restart tests: a 10 m square.
RESTART_ANCHORS = pd.DataFrame({"anchor": ["A1", "A2", "A3", "A4"], "x": [0, 10, 10, 0.0],
                                "y": [0, 0, 10, 10.0]})


def _store_engine(tmp_path):
    """An nls Engine on the store ``tmp_path / "s"`` (a new one per call: a restart)."""
    from robustloc.service.engine import Engine

    return Engine(RESTART_ANCHORS, LocateProcessor(RESTART_ANCHORS, method="nls"),
                  store_dir=tmp_path / "s", latency_window_s=0.0, idle_flush_s=600.0,
                  fsync=False)


def _ranges_at(tag, p, times):
    """Exact range rows of ``tag`` at ``p`` to every restart anchor, at ``times``."""
    xy = RESTART_ANCHORS[["x", "y"]].to_numpy(float)
    return [{"time": float(t), "tag": tag, "anchor": a, "range": float(r)}
            for t in times for a, r in zip(RESTART_ANCHORS["anchor"], np.hypot(*(xy - p).T))]


def _latest_across_a_restart(tmp_path, tags, between=None):
    """``/api/latest`` of an Engine fed ``tags`` ((tag, position, times), ...), then of a
    new Engine on the same store (``between()`` runs before the restart)."""
    rows = [r for g, p, times in tags for r in _ranges_at(g, p, times)]
    eng = _store_engine(tmp_path)
    try:
        eng.ingest(rows)
        eng.flush()
        before = eng.latest().sort_values("tag").reset_index(drop=True)
    finally:
        eng.stop()
    if between is not None:
        between()
    eng = _store_engine(tmp_path)
    try:
        after = eng.latest().sort_values("tag").reset_index(drop=True)
    finally:
        eng.stop()
    return before, after


def test_latest_positions_survive_a_restart(tmp_path):
    """``/api/latest`` was empty after a restart until new rows came (the map page
    started blank; the review found it).  It is seeded from the store: each tag's
    latest stored row, the same as before the restart."""
    before, after = _latest_across_a_restart(
        tmp_path, (("a", [3.0, 4.0], (0.0, 1.0, 2.0)), ("b", [6.0, 2.0], (5.0,))))
    assert before["time"].tolist() == [2.0, 5.0]
    pd.testing.assert_frame_equal(after[before.columns], before, check_dtype=False)



def test_the_last_fix_of_a_tag_without_one_survives_a_restart(tmp_path):
    """``/api/latest`` gives a tag whose latest row has no position its last fix
    (``fix_*``: the map page draws it hollow there).  That came from the fixes solved
    since the start, so after a restart such a tag had none ("no fix yet"; left out in
    stop 47's note).  It is now read from the store: the same fix before and after.
    Writing this test found that a tag with two fixes solved in one block (one ingest of
    two epochs) made ``latest_with_fixes`` raise pandas' "Reindexing only valid with
    uniquely valued Index objects", a 500 from ``/api/latest``, once its latest row had
    no position: the "before" query below."""
    rows = _ranges_at("walker", [3.0, 4.0], [0]) + _ranges_at("walker", [3.5, 4.0], [1])
    rows += [{"time": 2.0, "tag": "walker", "anchor": "A1", "range": 5.0},  # one anchor
             {"time": 3.0, "tag": "still", "anchor": "A1", "range": 5.0}]  # never a fix
    rows += _ranges_at("fine", [6.0, 2.0], [3])
    eng = _store_engine(tmp_path)
    try:  # (stopped even when the query raises, as it did: the store's lock released)
        eng.ingest(rows)
        eng.flush()
        before = eng.latest_with_fixes().set_index("tag").sort_index()
    finally:
        eng.stop()
    eng = _store_engine(tmp_path)
    try:
        after = eng.latest_with_fixes().set_index("tag").sort_index()
    finally:
        eng.stop()
    assert before.loc["walker", "status"] == "insufficient_anchors"
    assert before.loc["walker", "fix_time"] == 1.0
    assert before.loc["walker", "fix_x"] == pytest.approx(3.5, abs=1e-6)
    for c in ("fix_time", "fix_x", "fix_y", "fix_status", "fix_solved_at"):
        assert after.loc["walker", c] == before.loc["walker", c], c
        assert pd.isna(after.loc["still", c]) and pd.isna(after.loc["fine", c]), c
    assert after.loc["fine", "x"] == pytest.approx(6.0, abs=1e-6)


def test_an_ndjson_line_that_is_not_json_is_named_so_in_the_reply():
    """The reply listed such a line with the decoder's message alone ("JSON is
    malformed: ..."), not saying which kind of mistake it was."""
    idx = pd.Index(["A1"], dtype=object)
    rows, _ = parse_body(b'{"time": 1, "tag": "t", "anchor": "A1", "range": 3}\n{bad\n')
    _, _, rejected = validate_rows(rows, idx, None, ("range", "rssi"))
    assert [i for i, _ in rejected] == [1]
    assert rejected[0][1].startswith("line is not JSON: ")


def test_a_restart_reads_only_the_latest_rows_of_the_tags(tmp_path, monkeypatch):
    """Seeding ``/api/latest`` read every row since the oldest of the tags' latest times:
    one tag silent since the start made a restart read the whole store (left out in
    stop 32's note).  It now reads the rows at the tags' latest times only.  (The
    recovery still reads the time and tag of every row: it looks for unsolved epochs.)"""
    from robustloc.service.store import SegmentLog as Store

    read = []
    scan = Store.scan

    def counting(self, columns=None, expression=None):
        table = scan(self, columns, expression)
        if columns is None:  # whole rows (the recovery reads two columns of each)
            read.append(table.num_rows)
        return table

    before, after = _latest_across_a_restart(
        tmp_path, (("silent", [6.0, 2.0], (0,)), ("busy", [3.0, 4.0], range(300))),
        between=lambda: monkeypatch.setattr(Store, "scan", counting))
    pd.testing.assert_frame_equal(after[before.columns], before, check_dtype=False)
    assert before["time"].tolist() == [299.0, 0.0]
    assert sum(read) <= 3, read  # busy's rows at times 0 and 299, silent's at 0 (was 301)


@pytest.mark.parametrize("ndjson", [False, True])
def test_a_number_beyond_the_parsers_range_costs_only_its_row(ndjson):
    """``1e400`` and integers of 5 000 digits are valid JSON; msgspec refuses them
    ("Number out of range"), and the whole body was refused as "not valid JSON" with its
    good rows (the service review).  Now only the rows holding them are refused, each
    with its reason; and a ``null`` row is named ``null``, not ``NoneType``."""
    idx = pd.Index(["A1"], dtype=object)
    good = b'{"time": 2, "tag": "t", "anchor": "A1", "range": 3}'
    bad = [b'{"time": 1e400, "tag": "t", "anchor": "A1", "range": 3}',
           b'{"time": 1, "tag": "t", "anchor": "A1", "range": -1e400}',
           b'{"time": 1, "tag": ' + b"7" * 5000 + b', "anchor": "A1", "range": 3}',
           b'{"time": ' + b"9" * 5000 + b', "tag": "t", "anchor": "A1", "range": 3}',
           b"null",
           # a tag or an anchor of 1e400 (an OverflowError: a 500 over HTTP, a closed
           # WebSocket, the whole MQTT message dead-lettered with its good rows)
           b'{"time": 1, "tag": 1e400, "anchor": "A1", "range": 3}',
           b'{"time": 1, "tag": "t", "anchor": -1e400, "range": 3}']
    parts = [*bad, good]
    body = b"\n".join(parts) if ndjson else b"[" + b",".join(parts) + b"]"
    rows, _ = parse_body(body)
    batch, _, rejected = validate_rows(rows, idx, None, ("range", "rssi"))
    assert len(batch) == 1 and batch.time[0] == 2.0
    why = dict(rejected)
    assert sorted(why) == [0, 1, 2, 3, 4, 5, 6]
    assert "not finite" in why[0] and "range" in why[1]
    assert "longer than" in why[2] and "not finite" in why[3]
    assert why[4] == "row is a JSON null, expected an object"
    assert why[5] == "'tag' is a number, expected a string id"
    assert why[6] == "'anchor' is a number, expected a string id"


def test_subscribers_that_stop_reading_then_vanish_leave_no_traceback(uwb, server_factory):
    """Position subscribers that never read (their sends block on a full socket) and then
    abort their connection: each one's sender ended with ``WebSocketDisconnect`` that
    nobody read, and asyncio printed "Task exception was never retrieved" with a traceback
    on the service's stderr (the service review: 20 subscribers, 20 tracebacks).  Bounded:
    20 subscribers, 24 bodies of 6 000 rows, on loopback."""
    import asyncio

    import websockets

    s = server_factory(["--anchors", str(uwb / "anchors.csv")])
    port = s.port
    anchors = [str(a) for a in read_anchors(uwb / "anchors.csv")["anchor"]]

    async def dead_subscriber():
        r, w = await asyncio.open_connection("127.0.0.1", port, limit=1024)
        w.transport.set_write_buffer_limits(0)
        w.write(b"GET /ws/positions HTTP/1.1\r\nHost: x\r\nUpgrade: websocket\r\n"
                b"Connection: Upgrade\r\nSec-WebSocket-Key: dGhlIHNhbXBsZSBub25jZQ==\r\n"
                b"Sec-WebSocket-Version: 13\r\n\r\n")
        await w.drain()
        await r.readuntil(b"\r\n\r\n")
        w.transport.pause_reading()
        return w

    async def run():
        subs = [await dead_subscriber() for _ in range(20)]
        async with websockets.connect(f"ws://127.0.0.1:{port}/ws/measurements",
                                      max_size=None) as ws:
            for k in range(24):
                body = [{"time": 1000.0 + k * 100 + i // 50, "tag": f"t{i % 50}",
                         "anchor": a, "range": 5.0} for i in range(2000) for a in anchors]
                await ws.send(json.dumps(body))
                await ws.recv()
        await asyncio.sleep(2.0)
        for w in subs:
            w.transport.abort()
        await asyncio.sleep(2.0)

    asyncio.run(run())
    assert httpx.get(s.url + "/healthz", timeout=10).status_code == 200
    log = s.log()
    assert "never retrieved" not in log and "Traceback" not in log, log[-2000:]


def test_no_floorplan_and_plain_http_to_a_websocket_are_counted_with_a_reason(
        uwb, server_factory):
    """``GET /floorplan`` without one was a 404 that was not counted; ``GET /ws/positions``
    said "no such endpoint" for an endpoint that exists (the service review).  Now both
    are counted, and the second is 426 Upgrade Required saying to use ws://."""
    s = server_factory(["--anchors", str(uwb / "anchors.csv")])
    r = httpx.get(s.url + "/floorplan")
    assert r.status_code == 404 and "floor plan" in r.json()["error"]
    for path in ("/ws/positions", "/ws/measurements"):
        r = httpx.get(s.url + path)
        assert r.status_code == 426 and "WebSocket endpoint" in r.json()["error"]
        assert r.headers["upgrade"] == "websocket"
    assert metric(s.url, 'robustloc_requests_rejected_total{reason="not_found"}') == 1
    assert metric(s.url, 'robustloc_requests_rejected_total{reason="upgrade_required"}') == 2


def test_new_tags_beyond_max_tags_are_refused_row_by_row(uwb):
    """A gateway sending random tag ids grew the service by ~4 kB per id, for good: 0.9 GB
    after 200 000 (the service review).  With ``max_tags`` the rows of a new tag beyond it
    are rejected, each with its reason and its place in the body, on both ingest paths
    (decoded in one pass, or row by row); known tags go on being accepted; the refused
    tags are counted."""
    from robustloc.service.engine import Engine

    anchors = read_anchors(uwb / "anchors.csv")
    ids = [str(a) for a in anchors["anchor"]]
    eng = Engine(anchors, LocateProcessor(anchors, method="nls"), latency_window_s=0.0,
                 fsync=False, max_tags=3, value="range")

    def rows(tags, t=0.0):
        return [{"time": t, "tag": g, "anchor": a, "range": 5.0} for g in tags for a in ids]

    m = len(ids)
    body = json.dumps(rows(["a", "b", "c", "d", "e"])).encode()
    batch = eng.decode(body)
    assert batch is not None  # the one-pass path
    res = eng.ingest_batch(batch).to_json()
    assert res["accepted"] == 3 * m and res["n_rejected"] == 2 * m
    assert [r["index"] for r in res["rejected"]] == list(range(3 * m, 5 * m))
    assert all("at most 3 tags" in r["error"] and "new" in r["error"]
               for r in res["rejected"])
    # row by row (a malformed row among them keeps its own reason and place)
    mixed = [{"time": 1.0, "tag": "f", "anchor": ids[0], "range": 5.0},
             {"time": 1.0, "tag": "a", "anchor": "nope", "range": 5.0},
             *rows(["a", "c"], 1.0)]
    res = eng.ingest(mixed).to_json()
    assert res["accepted"] == 2 * m
    assert [r["index"] for r in res["rejected"]] == [0, 1]
    assert "at most 3 tags" in res["rejected"][0]["error"]
    assert "at most 3 tags" not in res["rejected"][1]["error"]
    assert eng.metrics.tags_refused == 3 and len(eng.assembler.tags) == 3
    with pytest.raises(ValueError):
        Engine(anchors, LocateProcessor(anchors), max_tags=0)


def test_serve_max_tags_refuses_new_tags_and_counts_them(uwb, server_factory):
    s = server_factory(["--anchors", str(uwb / "anchors.csv"), "--max-tags", "2"])
    a = str(read_anchors(uwb / "anchors.csv")["anchor"].iloc[0])
    rows = [{"time": 0.0, "tag": g, "anchor": a, "range": 5.0} for g in ("x", "y", "z")]
    r = httpx.post(s.url + "/api/measurements", json=rows)
    assert r.status_code == 202 and r.json()["accepted"] == 2
    assert [e["index"] for e in r.json()["rejected"]] == [2]
    assert metric(s.url, "robustloc_tags_refused_total") == 1
    assert httpx.get(s.url + "/api/status").json()["tags"] == 2


@pytest.mark.parametrize("level", ["warning", "error"])
def test_what_the_http_server_refuses_itself_is_counted_without_a_traceback(
        uwb, server_factory, level):
    """A request that is not HTTP and a WebSocket text frame that is not UTF-8 are refused
    by uvicorn before the application sees them (400, close 1007): neither was counted,
    and the second printed a traceback on the service's stderr (the service review).
    With ``--log-level error`` neither warning line is shown, and both are counted (the
    first was not even logged, so not counted, at that level)."""
    import socket

    s = server_factory(["--anchors", str(uwb / "anchors.csv"), "--log-level", level])
    for raw in (b"POST /api/measurements HTTP/1.1\r\nHost: x\r\nContent-Length: abc\r\n\r\n",
                b"BREW /pot HTTP/1.1\r\nHost: x\r\n\r\n"):
        with socket.create_connection(("127.0.0.1", s.port), timeout=10) as c:
            c.sendall(raw)
            assert c.recv(4096).startswith(b"HTTP/1.1 400")
    with socket.create_connection(("127.0.0.1", s.port), timeout=10) as c:
        c.sendall(b"GET /ws/measurements HTTP/1.1\r\nHost: x\r\nUpgrade: websocket\r\n"
                  b"Connection: Upgrade\r\nSec-WebSocket-Key: dGhlIHNhbXBsZSBub25jZQ==\r\n"
                  b"Sec-WebSocket-Version: 13\r\n\r\n")
        buf = b""
        while b"\r\n\r\n" not in buf:
            buf += c.recv(4096)
        c.sendall(bytes([0x81, 0x82]) + b"\x00\x00\x00\x00" + b"\xff\xfe")  # masked, ff fe
        close = b""
        while len(close) < 4:  # the close frame: opcode, length, then the code
            chunk = c.recv(4096)
            assert chunk, f"connection closed after {close!r}"
            close += chunk
        assert close[:1] == b"\x88" and close[2:4] == (1007).to_bytes(2, "big")
    time.sleep(0.5)
    assert metric(s.url, 'robustloc_requests_rejected_total{reason="invalid_http"}') == 2
    assert metric(s.url, 'robustloc_requests_rejected_total{reason="invalid_utf8"}') == 1
    assert httpx.get(s.url + "/healthz").status_code == 200
    log = s.log()
    assert "Traceback" not in log, log[-2000:]
    for line in ("Invalid UTF-8", "Invalid HTTP request"):  # one warning line each
        assert (line in log) == (level == "warning"), log[-2000:]


def test_floor_plan_deleted_after_start_is_a_404_with_its_reason(uwb, tmp_path, server_factory):
    """The image given to --floorplan deleted while the service runs: every request for it
    (the map page asks every 2 s) was a 500 with a traceback in the server's log (the map
    review).  Now a 404 naming the image, counted, and no traceback."""
    plan = tmp_path / "plan.png"
    plan.write_bytes(b"\x89PNG\r\n\x1a\n" + b"\0" * 64)
    s = server_factory(["--anchors", str(uwb / "anchors.csv"), "--floorplan", str(plan),
                        "--floorplan-extent", "0,0,10,10"])
    assert httpx.get(s.url + "/floorplan").status_code == 200
    plan.unlink()
    for _ in range(3):
        r = httpx.get(s.url + "/floorplan")
        assert r.status_code == 404
        assert "plan.png cannot be read" in r.json()["error"]
    assert metric(s.url, 'robustloc_requests_rejected_total{reason="not_found"}') == 3
    assert metric(s.url, 'robustloc_requests_rejected_total{reason="internal_error"}') == 0
    assert "Traceback" not in s.log()


def test_serve_refuses_an_anchor_id_no_row_could_name(tmp_path):
    """The anchors file took a 300-character id, but every row naming it is rejected (ids
    of at most 128 characters): the anchor could never be heard, and nothing said so (the
    map review).  Now ``serve`` refuses it at start, with the file and line."""
    p = tmp_path / "a.csv"
    p.write_text("anchor,x,y\nA1,0,0\n" + "B" * 300 + ",10,0\nA3,5,5\n")
    r = subprocess.run([*ROBUSTLOC, "serve", "--anchors", str(p)], capture_output=True,
                       text=True, timeout=120)
    assert r.returncode == 2 and "Traceback" not in r.stderr
    assert r.stderr.startswith(f"error: {p}:3: anchor id of 300 characters")


def test_a_snapshot_on_a_full_disk_neither_stops_nor_loses(tmp_path, monkeypatch, capsys):
    """A full disk when the tracker's state is saved (``processor.pkl``): at a stop it
    raised out of :meth:`Engine.stop` (a traceback, "Application shutdown failed") and
    the measurement and position logs were left unclosed; during the run it was counted
    as a solver error (the service review).  Now one warning, counted as a snapshot
    error, the logs closed, and a restart gives every epoch its row."""
    import errno

    from robustloc.service import engine as engine_mod
    from robustloc.service.engine import Engine
    from robustloc.service.processor import TrackProcessor

    anchors = pd.DataFrame({"anchor": ["A1", "A2", "A3", "A4"], "x": [0, 10, 10, 0.0],
                            "y": [0, 0, 10, 10.0]})
    xy = anchors[["x", "y"]].to_numpy(float)
    rng = np.hypot(*(xy - [3.0, 4.0]).T)
    rows = [{"time": float(t), "tag": "T", "anchor": a, "range": float(r)}
            for t in range(6) for a, r in zip(anchors["anchor"], rng)]
    store = tmp_path / "store"

    def full(*args, **kwargs):
        raise OSError(errno.ENOSPC, "No space left on device")

    eng = Engine(anchors, TrackProcessor(anchors), store_dir=store, latency_window_s=0.0,
                 idle_flush_s=600.0, value="range", fsync=False, snapshot_s=0)
    eng.ingest(rows)
    eng.step()
    monkeypatch.setattr(engine_mod.os, "replace", full)
    eng._snapshot()
    assert eng.snapshot_errors == 1 and "no space left" in eng.last_snapshot_error.lower()
    assert eng.solver_errors == 0
    eng.stop()  # the stop's snapshot fails too: no exception, the logs closed
    assert eng.snapshot_errors == 2
    assert not list((store / "state").glob("*.tmp"))
    err = capsys.readouterr().err
    assert err.count("the state's snapshot was not written") == 1, err
    monkeypatch.undo()
    eng2 = Engine(anchors, TrackProcessor(anchors), store_dir=store, latency_window_s=0.0,
                  idle_flush_s=600.0, value="range", fsync=False, snapshot_s=0)
    eng2.flush()
    pos = eng2.positions()
    eng2.stop()
    assert sorted(set(pos["time"].tolist())) == [float(t) for t in range(6)]


def test_scale_from_a_log_of_the_other_values_is_refused(ble, tmp_path):
    """``--scale-from`` took a log of ranges for a service of RSSI and applied its noise
    scale (metres as dB) without a word; fixes of fault-free epochs said
    ``fault_detected`` (the service review).  Now the log's values must be the
    service's; without ``--value`` the log fixes them."""
    from robustloc.cli import build_parser
    from robustloc.commands.serve import build
    from robustloc.io import read_anchors

    ids = [str(a) for a in read_anchors(ble / "anchors.csv")["anchor"]]
    log = tmp_path / "ranges.csv"
    pd.DataFrame({"time": np.repeat(np.arange(20.0), len(ids)), "tag": "t",
                  "anchor": ids * 20, "range": 5.0}).to_csv(log, index=False)
    a = str(ble / "anchors.csv")
    # (a subprocess with a timeout: the old code served, a regression must fail)
    r = subprocess.run([*ROBUSTLOC, "serve", "--anchors", a, "--value", "rssi",
                        "--scale-from", str(log), "--port", "0"], capture_output=True,
                       text=True, timeout=120)
    assert r.returncode == 2
    assert r.stderr.strip() == (f"error: {log}: holds range rows; this service locates "
                                "from rssi (--value): give a log of rssi rows"), r.stderr
    args = build_parser().parse_args(["serve", "--anchors", a, "--scale-from", str(log)])
    engine, _, _ = build(args)
    try:
        assert engine.kind == "range"
    finally:
        engine.stop()


def test_connections_that_never_finish_their_headers_are_closed(ble, server_factory):
    """Slowloris: connections that send a request line and one header, then nothing, were
    held for ever (neither the keep-alive timeout nor --body-timeout applies), and 300 of
    them made the service refuse everyone (the service review).  Each is now closed
    --header-timeout after it started, and counted; a request that completes its headers
    in time, and a WebSocket past its upgrade, are not affected.  Bounded: 20 connections
    on loopback, a 1 s timeout."""
    import socket

    from websockets.sync.client import connect

    srv = server_factory(["--anchors", str(ble / "anchors.csv"), "--header-timeout", "1"])
    name = 'robustloc_requests_rejected_total{reason="header_timeout"}'
    with connect(srv.url.replace("http://", "ws://") + "/ws/positions") as ws:
        socks = []
        try:
            for _ in range(20):
                so = socket.create_connection(("127.0.0.1", srv.port), timeout=10)
                so.sendall(b"GET /healthz HTTP/1.1\r\nHost: x\r\n")
                socks.append(so)
            slow = socket.create_connection(("127.0.0.1", srv.port), timeout=10)
            socks.append(slow)
            slow.sendall(b"GET /healthz HTTP/1.1\r\n")
            time.sleep(0.5)
            slow.sendall(b"Host: x\r\nConnection: close\r\n\r\n")  # in time
            assert slow.recv(65536).startswith(b"HTTP/1.1 200 ")
            t0 = time.monotonic()
            for so in socks[:20]:
                assert so.recv(65536) == b""  # closed by the server, no answer
            assert time.monotonic() - t0 < 5
        finally:
            for so in socks:
                so.close()
        wait_for(lambda: metric(srv.url, name) == 20, timeout=10,
                 what="the 20 connections counted")
        assert httpx.get(srv.url + "/healthz", trust_env=False).status_code == 200
        with pytest.raises(TimeoutError):
            ws.recv(timeout=1.5)  # (open past the header timeout: nothing to receive)
        assert ws.ping().wait(5)  # the WebSocket still answers


def test_other_sites_pages_can_neither_send_nor_listen(ble, server_factory):
    """With no token, any web page the user had open could add rows (a ``no-cors`` POST,
    which CORS does not stop) and read every live position over a WebSocket (browsers
    apply no CORS to WebSockets); a name that DNS points at 127.0.0.1 made a page of the
    service's own origin (the map review).  Now a POST or a WebSocket from another
    origin is refused unless --cors-origin allows it, a loopback service answers only
    its own host names, and each refusal is counted."""
    from websockets.exceptions import InvalidStatus
    from websockets.sync.client import connect

    srv = server_factory(["--anchors", str(ble / "anchors.csv"),
                          "--cors-origin", "http://trusted.example"])
    anchor = str(read_anchors(ble / "anchors.csv")["anchor"].iloc[0])
    row = [{"time": 1.0, "tag": "t", "anchor": anchor, "rssi": -60.0}]
    url = srv.url + "/api/measurements"
    c = httpx.Client(trust_env=False)
    evil = c.post(url, json=row, headers={"Origin": "http://evil.example"})
    assert evil.status_code == 403 and "--cors-origin" in evil.json()["error"]
    own = f"http://127.0.0.1:{srv.port}"
    for origin in (own, "http://trusted.example", None):  # (None: not a browser)
        h = {} if origin is None else {"Origin": origin}
        assert c.post(url, json=row, headers=h).status_code == 202, origin
    ws = srv.url.replace("http://", "ws://")
    with pytest.raises(InvalidStatus) as refused:
        connect(ws + "/ws/positions", origin="http://evil.example").close()
    assert refused.value.response.status_code == 403
    with connect(ws + "/ws/positions", origin=own) as fine:
        assert fine.ping().wait(5)
    # (a browser's request: it sends Sec-Fetch-* headers; tools may name any Host)
    rebound = c.get(srv.url + "/api/latest", headers={"Host": f"evil.example:{srv.port}",
                                                      "Sec-Fetch-Mode": "cors"})
    assert rebound.status_code == 403 and "not this machine's" in rebound.json()["error"]
    assert c.get(srv.url + "/api/latest",
                 headers={"Host": f"evil.example:{srv.port}"}).status_code == 200
    assert c.get(f"http://localhost:{srv.port}/healthz").status_code == 200
    assert metric(srv.url, 'robustloc_requests_rejected_total{reason="cross_origin"}') == 2
    assert metric(srv.url, 'robustloc_requests_rejected_total{reason="foreign_host"}') == 1
    # a CORS preflight: allowed, answered by CORS; refused with a reason, and counted
    # (CORSMiddleware answered those in plain text, uncounted; the serve review)
    ok = c.options(url, headers={"Origin": "http://trusted.example",
                                 "Access-Control-Request-Method": "POST",
                                 "Access-Control-Request-Headers": "content-type"})
    assert ok.status_code == 200
    assert ok.headers["access-control-allow-origin"] == "http://trusted.example"
    for h in ({"Origin": "http://evil.example", "Access-Control-Request-Method": "POST"},
              {"Origin": "http://trusted.example", "Access-Control-Request-Method": "DELETE"},
              {"Origin": "http://trusted.example", "Access-Control-Request-Method": "POST",
               "Access-Control-Request-Headers": "x-evil"}):
        refused = c.options(url, headers=h)
        assert refused.status_code == 400 and refused.json()["error"], h
    assert metric(srv.url, 'robustloc_requests_rejected_total{reason="cors_preflight"}') == 3
    assert c.get(srv.url + "/api/status").json()["requests_rejected"]["cors_preflight"] == 3
