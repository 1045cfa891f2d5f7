"""Durability of the live service under hostile operations (the service review's 1, 4, 5,
6, 9 and 10): a second server on one store, a full disk, MQTT downtime, a stuck client at
shutdown, damaged store files, WebSockets to unknown paths.

Every server is a real ``robustloc serve`` on a free loopback port (``ServerProcess``) and
every broker a real Mosquitto, each stopped in a ``finally``/fixture teardown.  A full disk
is a file size limit (``RLIMIT_FSIZE``) set on the running server with ``prlimit``: no
root and no mount needed (Python ignores ``SIGXFSZ``, so a write past the limit fails with
``EFBIG`` as one past a full disk fails with ``ENOSPC``).
"""

from __future__ import annotations

import contextlib
import json
import resource
import shutil
import signal
import socket
import subprocess
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("starlette")
pytest.importorskip("uvicorn")
httpx = pytest.importorskip("httpx")

from _waiting import wait_until  # noqa: E402

from robustloc.service.launch import (  # noqa: E402
    ROBUSTLOC,
    MosquittoProcess,
    ServerProcess,
    free_port,
    read_metric,
)

ANCHORS = {"A1": (0.0, 0.0), "A2": (10.0, 0.0), "A3": (10.0, 10.0), "A4": (0.0, 10.0)}
#: Options that keep every epoch pending (nothing solved, so only the measurements log is
#: written while a test limits the server's file size).
PENDING = ["--latency-window", "1000", "--time-jump", "5000", "--idle-flush", "1000"]


def _rows(times: range | list[float], tag: str = "T") -> list[dict]:
    xy = np.array(list(ANCHORS.values()))
    d = np.hypot(*(xy - [3.0, 4.0]).T)
    return [{"time": float(t), "tag": tag, "anchor": a, "range": float(r)}
            for t in times for a, r in zip(ANCHORS, d)]


def _metric(url: str, name: str) -> float:
    return read_metric(url, name, timeout_s=10.0)


def _stored_times(store: Path) -> list[float]:
    """The times of the rows in a (closed) store's measurements log."""
    from robustloc.service.store import SegmentLog

    log = SegmentLog(store / "measurements", fsync=False)
    try:
        return sorted(log.scan(columns=["time"])["time"].to_pylist())
    finally:
        log.close()


def _limit_file_size(pid: int, nbytes: int | None) -> None:
    """Set (``None``: lift) the soft file size limit of a running process."""
    _, hard = resource.prlimit(pid, resource.RLIMIT_FSIZE)
    resource.prlimit(pid, resource.RLIMIT_FSIZE,
                     (resource.RLIM_INFINITY if nbytes is None else nbytes, hard))


@pytest.fixture
def anchors(tmp_path) -> Path:
    p = tmp_path / "anchors.csv"
    p.write_text("anchor,x,y\n" + "".join(f"{a},{x},{y}\n" for a, (x, y) in ANCHORS.items()))
    return p


@pytest.fixture
def servers(server_factory) -> Callable[..., ServerProcess]:
    """``servers(args)``: a started ``ServerProcess`` (a slow machine: 120 s to start);
    every one is stopped at teardown (conftest's ``server_factory``)."""
    return lambda args, **kw: server_factory(args, **{"startup_timeout_s": 120, **kw})


@pytest.fixture
def broker() -> Iterator[MosquittoProcess]:
    if not (shutil.which("mosquitto") or Path("/usr/sbin/mosquitto").exists()):
        pytest.skip("the mosquitto binary is missing (apt-get install mosquitto)")
    b = MosquittoProcess()
    try:
        yield b.start()
    finally:
        b.stop()


# --------------------------------------------------------------------------------------
# 1. one server per store
# --------------------------------------------------------------------------------------


def test_a_second_server_on_a_store_is_refused_and_nothing_acknowledged_is_lost(
        anchors, servers, tmp_path):
    """A second server on the same --store sealed and deleted the first one's active log:
    the first kept answering 202 into a deleted file and lost those rows.  Now the second
    one exits 2 before serving, naming the store, and every acknowledged row is kept."""
    store = tmp_path / "s"
    args = ["--anchors", str(anchors), "--store", str(store), *PENDING]
    a = servers(args)
    acked: list[float] = []
    r = httpx.post(a.url + "/api/measurements", json=_rows(range(0, 5)))
    assert r.status_code == 202
    acked += [float(t) for t in range(0, 5)]
    with pytest.raises(RuntimeError, match="exited with 2") as err:
        servers(args)
    assert f"error: {store}: store in use by another server" in str(err.value)
    assert "Traceback" not in str(err.value)
    r = httpx.post(a.url + "/api/measurements", json=_rows(range(5, 10)))
    assert r.status_code == 202
    acked += [float(t) for t in range(5, 10)]
    a.stop()
    assert _stored_times(store) == sorted(t for t in acked for _ in ANCHORS)
    # the lock dies with its holder: the store opens again
    b = servers(args)
    assert httpx.get(b.url + "/healthz").status_code == 200


def test_a_store_folder_opens_once(tmp_path):
    """The store's own guard: a second open of a log folder is refused (it would seal and
    delete the first one's active log) until the first is closed."""
    import pyarrow as pa

    from robustloc.service.store import SegmentLog, StoreInUse

    log = SegmentLog(tmp_path, fsync=False)
    log.append(pa.table({"time": [1.0]}))
    with pytest.raises(StoreInUse, match="store in use"):
        SegmentLog(tmp_path, fsync=False)
    assert len(list(tmp_path.glob("*.wal"))) == 1  # the active log is untouched
    log.close()
    log2 = SegmentLog(tmp_path, fsync=False)
    assert log2.scan()["time"].to_pylist() == [1.0]
    log2.close()


# --------------------------------------------------------------------------------------
# 4. disk full
# --------------------------------------------------------------------------------------


def test_a_body_the_store_cannot_write_is_507_and_not_stored(anchors, servers, tmp_path):
    """The log was written buffered: a body whose write failed was answered 500, its frame
    stayed in the buffer and the next body's flush stored it.  Now a failed append leaves
    the log as it was, the body is answered 507 with a reason (counted as store_error);
    over a WebSocket the 507 answer comes, then a close with 1013 and the reason."""
    from websockets.exceptions import ConnectionClosed
    from websockets.sync.client import connect

    store = tmp_path / "s"
    srv = servers(["--anchors", str(anchors), "--store", str(store), *PENDING])
    url = srv.url + "/api/measurements"
    assert httpx.post(url, json=_rows(range(0, 20))).status_code == 202
    (wal,) = (store / "measurements").glob("seg-*.wal")
    size = wal.stat().st_size
    _limit_file_size(srv.proc.pid, size + 500)  # less than one more body's frame
    try:
        r = httpx.post(url, json=_rows(range(20, 40)))
        assert r.status_code == 507, r.text
        assert "store write failed" in r.json()["error"]
        assert r.headers["retry-after"] == "5"
        assert wal.stat().st_size == size  # the partial frame was cut back
        with connect(srv.url.replace("http", "ws") + "/ws/measurements") as ws:
            ws.send(json.dumps(_rows(range(40, 60))))
            reply = json.loads(ws.recv(timeout=30))
            assert reply["status"] == 507 and "store write failed" in reply["error"]
            with pytest.raises(ConnectionClosed):
                ws.recv(timeout=30)
            assert ws.close_code == 1013
            assert "store write failed" in ws.close_reason
    finally:
        _limit_file_size(srv.proc.pid, None)
    assert httpx.post(url, json=_rows(range(60, 80))).status_code == 202
    assert _metric(srv.url, 'robustloc_requests_rejected_total{reason="store_error"}') == 2
    assert _metric(srv.url, 'robustloc_requests_rejected_total{reason="internal_error"}') == 0
    srv.stop()
    assert "Traceback" not in srv.log()
    want = [float(t) for t in [*range(0, 20), *range(60, 80)] for _ in ANCHORS]
    assert _stored_times(store) == sorted(want)


def test_an_mqtt_message_the_store_cannot_write_is_not_acknowledged(
        anchors, servers, broker, tmp_path):
    """MQTT counted a store failure as an internal error and acknowledged the message: the
    broker dropped it.  Now it is not acknowledged, counted (mqtt_store_error), logged in
    one line, and delivered again once the store can write."""
    mqtt = pytest.importorskip("paho.mqtt.client")
    store = tmp_path / "s"
    srv = servers(["--anchors", str(anchors), "--store", str(store), *PENDING,
                   "--mqtt", f"127.0.0.1:{broker.port}"])
    topic = "robustloc/measurements/gw-1"
    pub = mqtt.Client(mqtt.CallbackAPIVersion.VERSION2)
    pub.connect("127.0.0.1", broker.port)
    pub.loop_start()
    try:
        t = -1000.0
        while _metric(srv.url, "robustloc_rows_accepted_total") == 0:  # until subscribed
            assert t < -900, "the service never subscribed"
            pub.publish(topic, json.dumps(_rows([t], tag="probe")), qos=1).wait_for_publish(5)
            t += 1
            time.sleep(0.5)
        time.sleep(1.0)
        n0 = _metric(srv.url, "robustloc_rows_accepted_total")
        (wal,) = (store / "measurements").glob("seg-*.wal")
        _limit_file_size(srv.proc.pid, wal.stat().st_size + 100)
        try:
            pub.publish(topic, json.dumps(_rows(range(0, 10))), qos=1).wait_for_publish(5)
            wait_until(lambda: _metric(srv.url, 'robustloc_requests_rejected_total'
                                           '{reason="mqtt_store_error"}') >= 1,
                  30, "the store failure counted")
            assert _metric(srv.url, "robustloc_rows_accepted_total") == n0
        finally:
            _limit_file_size(srv.proc.pid, None)
        wait_until(lambda: _metric(srv.url, "robustloc_rows_accepted_total") == n0 + 40,
              60, "the message delivered again and stored")
    finally:
        pub.loop_stop()
        pub.disconnect()
    assert _metric(srv.url, 'robustloc_requests_rejected_total'
                            '{reason="mqtt_internal_error"}') == 0
    srv.stop()
    log = srv.log()
    assert "not stored and not acknowledged" in log and "Traceback" not in log
    times = _stored_times(store)
    assert [x for x in times if x >= 0] == sorted(float(t) for t in range(10) for _ in ANCHORS)


# --------------------------------------------------------------------------------------
# 5. MQTT downtime
# --------------------------------------------------------------------------------------


def test_mqtt_rows_published_while_the_service_is_down_arrive_after_the_restart(
        anchors, servers, broker, tmp_path):
    """A clean session and a random client id: the broker queued nothing for the service
    while it was down and those rows were lost.  With --store the session is persistent
    under a client id derived from the store."""
    mqtt = pytest.importorskip("paho.mqtt.client")
    store = tmp_path / "s"
    args = ["--anchors", str(anchors), "--store", str(store), *PENDING,
            "--mqtt", f"127.0.0.1:{broker.port}"]
    topic = "robustloc/measurements/gw-1"
    pub = mqtt.Client(mqtt.CallbackAPIVersion.VERSION2)
    pub.connect("127.0.0.1", broker.port)
    pub.loop_start()
    try:
        srv = servers(args)
        _until_subscribed(srv, pub, topic, "robustloc_rows_accepted_total")
        srv.stop()
        for k in range(10):  # the service is down
            pub.publish(topic, json.dumps(_rows([float(k)])), qos=1).wait_for_publish(5)
        srv2 = servers(args)
        wait_until(lambda: _metric(srv2.url, 'robustloc_rows_accepted_total{source="mqtt"}') >= 40,
              60, "the queued messages delivered")
        time.sleep(0.5)
        assert _metric(srv2.url, 'robustloc_rows_accepted_total{source="mqtt"}') == 40
    finally:
        pub.loop_stop()
        pub.disconnect()
    srv2.stop()
    times = _stored_times(store)
    assert [x for x in times if x >= 0] == sorted(float(t) for t in range(10) for _ in ANCHORS)


def _until_subscribed(srv, pub, topic: str, metric: str) -> None:
    """Publish probe rows (tag ``probe``, times from -1000 s) until the service has
    subscribed and accepted one (``metric`` above 0)."""
    t = -1000.0
    while _metric(srv.url, metric) == 0:
        assert t < -900, "the service never subscribed"
        pub.publish(topic, json.dumps(_rows([t], tag="probe")), qos=1).wait_for_publish(5)
        t += 1
        time.sleep(0.5)


def test_a_retained_mqtt_message_is_stored_once_across_restarts(
        anchors, servers, broker, tmp_path):
    """The broker re-sends a topic's retained message at every subscription, so each start
    of the service stored its rows again (the serve review: one 3-row retained message,
    three starts, 9 rows stored, the later copies late).  A retained delivery is now
    acknowledged and not ingested (counted); the message was stored when it came live,
    or, published while the service was down, from the persistent session's queue (the
    broker delivers both with the retain flag cleared)."""
    mqtt = pytest.importorskip("paho.mqtt.client")
    store = tmp_path / "s"
    args = ["--anchors", str(anchors), "--store", str(store), *PENDING,
            "--mqtt", f"127.0.0.1:{broker.port}"]
    topic = "robustloc/measurements/gw-1"
    accepted = 'robustloc_rows_accepted_total{source="mqtt"}'
    ignored = "robustloc_mqtt_retained_ignored_total"
    pub = mqtt.Client(mqtt.CallbackAPIVersion.VERSION2)
    pub.connect("127.0.0.1", broker.port)
    pub.loop_start()
    try:
        srv = servers(args)
        _until_subscribed(srv, pub, topic, accepted)
        n0 = _metric(srv.url, accepted)
        pub.publish(topic, json.dumps(_rows([1.0])), qos=1, retain=True).wait_for_publish(5)
        wait_until(lambda: _metric(srv.url, accepted) == n0 + 4, 30, "the live message")
        srv.stop()
        # the retained message is re-sent at each start: ignored, counted
        srv = servers(args)
        wait_until(lambda: _metric(srv.url, ignored) + _metric(srv.url, accepted) > 0, 30,
                   "the retained copy")
        time.sleep(1.0)
        assert (_metric(srv.url, accepted), _metric(srv.url, ignored)) == (0, 1)
        srv.stop()
        # one published (retained) while the service is down: queued, stored once
        pub.publish(topic, json.dumps(_rows([2.0])), qos=1, retain=True).wait_for_publish(5)
        srv = servers(args)
        wait_until(lambda: _metric(srv.url, accepted) == 4, 30, "the queued message")
        wait_until(lambda: _metric(srv.url, ignored) == 1, 30, "the retained copy")
        time.sleep(1.0)
        assert _metric(srv.url, accepted) == 4
        assert httpx.get(srv.url + "/api/status").json()["mqtt"]["retained_ignored"] == 1
        srv.stop()
    finally:
        pub.publish(topic, b"", qos=1, retain=True).wait_for_publish(5)  # (clears it)
        pub.loop_stop()
        pub.disconnect()
    assert "retained message on robustloc/measurements/gw-1 ignored" in srv.log()
    times = _stored_times(store)
    assert [x for x in times if x >= 0] == [1.0] * 4 + [2.0] * 4


def test_mqtt_client_id_is_stable_per_store(tmp_path):
    from robustloc.service.mqtt import client_id_for_store

    a = client_id_for_store(tmp_path / "a")
    assert a == client_id_for_store(str(tmp_path / "a"))
    assert a != client_id_for_store(tmp_path / "b")
    assert a.startswith("robustloc-") and len(a) <= 23  # what every MQTT 3.1.1 broker takes


# --------------------------------------------------------------------------------------
# 6. shutdown with a stuck client
# --------------------------------------------------------------------------------------


def test_a_half_sent_body_does_not_hold_the_shutdown(anchors, servers):
    """A client that sent half a body kept the service alive after SIGTERM for up to
    --body-timeout; uvicorn's graceful shutdown is now bounded (--shutdown-grace).  When
    the grace runs out the request is cancelled: it was answered a bare 500 "Internal
    Server Error", with uvicorn's traceback in the log (the service review); now a 503
    that says nothing was stored, and one warning line."""
    srv = servers(["--anchors", str(anchors), "--body-timeout", "60",
                   "--shutdown-grace", "1"])
    with socket.create_connection(("127.0.0.1", srv.port), timeout=10) as k:
        k.sendall(b"POST /api/measurements HTTP/1.1\r\nHost: x\r\n"
                  b"Content-Length: 1000\r\n\r\n[{")
        time.sleep(0.5)
        t0 = time.monotonic()
        srv.proc.send_signal(signal.SIGTERM)
        try:
            srv.proc.wait(timeout=15)
        except subprocess.TimeoutExpired:
            srv.kill9()
            pytest.fail("still running 15 s after SIGTERM (a half-sent body holds it)")
        answer = b""
        with contextlib.suppress(OSError):
            while chunk := k.recv(65536):
                answer += chunk
    assert time.monotonic() - t0 < 15
    head, _, body = answer.partition(b"\r\n\r\n")
    assert head.startswith(b"HTTP/1.1 503 "), answer
    assert b"retry-after: " in head.lower()
    assert "none of the body's rows was stored" in json.loads(body)["error"]
    log = srv.log()
    assert "Traceback" not in log and "ERROR" not in log, log
    assert "still running after --shutdown-grace" in log


def test_a_second_ctrl_c_stops_without_a_traceback(anchors, servers, tmp_path):
    """A second Ctrl-C cuts the graceful stop short: the application's lifespan is
    cancelled, and a 10-line ``CancelledError`` traceback was logged as an error (the
    service review).  Now one warning line; the acknowledged rows are in the store."""
    store = tmp_path / "s"
    srv = servers(["--anchors", str(anchors), "--store", str(store),
                   "--shutdown-grace", "5"])
    assert httpx.post(srv.url + "/api/measurements", json=_rows(range(3))).status_code == 202
    with socket.create_connection(("127.0.0.1", srv.port), timeout=10) as k:
        k.sendall(b"POST /api/measurements HTTP/1.1\r\nHost: x\r\n"
                  b"Content-Length: 100\r\n\r\n[")  # holds the graceful stop
        time.sleep(0.3)
        srv.proc.send_signal(signal.SIGINT)
        time.sleep(0.5)
        srv.proc.send_signal(signal.SIGINT)
        try:
            assert srv.proc.wait(timeout=15) == 0
        except subprocess.TimeoutExpired:
            srv.kill9()
            pytest.fail("still running 15 s after two SIGINTs")
    log = srv.log()
    assert "Traceback" not in log and "ERROR" not in log, log
    assert "stop forced by a second signal" in log
    again = servers(["--anchors", str(anchors), "--store", str(store)])
    wait_until(lambda: sorted(p["time"] for p in httpx.get(
        again.url + "/api/positions", params={"limit": 100}).json()) == [0.0, 1.0, 2.0],
        timeout=30, what="the 3 acknowledged epochs solved after the restart")


# --------------------------------------------------------------------------------------
# 9. damaged store files named at start-up
# --------------------------------------------------------------------------------------


def _serve_once(args: list[str]) -> subprocess.CompletedProcess:
    """``robustloc serve ARGS`` expected to refuse to start (bounded: it must not serve)."""
    return subprocess.run([*ROBUSTLOC, "serve", *args, "--port", str(free_port())],
                          capture_output=True, text=True, timeout=120)


def test_damaged_store_files_are_named_at_start(anchors, servers, tmp_path):
    """A truncated meta.json and a damaged Parquet segment were reported against the
    anchors file (the JSON or Arrow message with the wrong file name)."""
    store = tmp_path / "s"
    args = ["--anchors", str(anchors), "--store", str(store), *PENDING]
    srv = servers(args)
    assert httpx.post(srv.url + "/api/measurements", json=_rows(range(3))).status_code == 202
    srv.stop()
    servers(args).stop()  # a restart seals the log into a Parquet segment
    (seg,) = (store / "measurements").glob("seg-*.parquet")

    meta = store / "meta.json"
    good = meta.read_text()
    meta.write_text(good[:10])
    p = _serve_once(args)
    assert p.returncode == 2, p.stderr
    assert p.stderr.strip().splitlines()[-1].startswith(f"error: {meta}: ")
    assert "Traceback" not in p.stderr and str(anchors) not in p.stderr
    meta.write_text(good)

    data = seg.read_bytes()
    seg.write_bytes(data[:100])
    p = _serve_once(args)
    assert p.returncode == 2, p.stderr
    assert p.stderr.strip().splitlines()[-1].startswith(f"error: {seg}: ")
    assert "Traceback" not in p.stderr and str(anchors) not in p.stderr
    seg.write_bytes(data)
    assert _stored_times(store) == sorted(float(t) for t in range(3) for _ in ANCHORS)


def test_a_segment_damaged_in_its_data_is_named_at_start(anchors, servers, tmp_path):
    """A Parquet segment damaged in its data, its footer intact (the schema reads): the
    start ended in a traceback and exit 1 (the serve review).  It is named with the
    damaged-segment message, exit 2."""
    import pyarrow.parquet as pq

    store = tmp_path / "s"
    args = ["--anchors", str(anchors), "--store", str(store), *PENDING]
    srv = servers(args)
    assert httpx.post(srv.url + "/api/measurements",
                      json=_rows(range(500))).status_code == 202
    srv.stop()
    servers(args).stop()  # a restart seals the log into a Parquet segment
    (seg,) = (store / "measurements").glob("seg-*.parquet")
    meta = pq.read_metadata(seg)
    names = [meta.schema.column(i).name for i in range(meta.num_columns)]
    chunk = meta.row_group(0).column(names.index("time"))  # (a column the start reads)
    # (its first page's header: damaged data inside a page may read without an error,
    # Parquet pages carry no checksum by default)
    at = chunk.dictionary_page_offset or chunk.data_page_offset
    good = seg.read_bytes()
    seg.write_bytes(good[:at] + b"x" * 50 + good[at + 50:])
    pq.read_schema(seg)  # (the footer is intact)
    p = _serve_once(args)
    assert p.returncode == 2, p.stderr
    last = p.stderr.strip().splitlines()[-1]
    assert last.startswith(f"error: {seg}: damaged Parquet segment of the store ("), last
    assert last.endswith("); move it aside to start without its rows")
    assert "Traceback" not in p.stderr and str(anchors) not in p.stderr
    seg.write_bytes(good)
    assert _stored_times(store) == sorted(float(t) for t in range(500) for _ in ANCHORS)


def test_a_log_damaged_mid_file_is_named_at_start_and_nothing_is_cut(anchors, servers,
                                                                     tmp_path):
    """One bad byte in the first frame of the measurements log after ``kill -9``: the
    restart cut every later, acknowledged frame off, silently (the serve review).  It is
    refused (exit 2) naming the log and the offset, like a damaged segment; repaired, every
    acknowledged row is there."""
    store = tmp_path / "s"
    args = ["--anchors", str(anchors), "--store", str(store), *PENDING]
    srv = servers(args)
    for k in range(3):  # three bodies: three frames
        r = httpx.post(srv.url + "/api/measurements", json=_rows([k]))
        assert r.status_code == 202
    srv.kill9()
    (wal,) = (store / "measurements").glob("seg-*.wal")
    good = wal.read_bytes()
    bad = bytearray(good)
    bad[40] ^= 0xFF
    wal.write_bytes(bytes(bad))
    p = _serve_once(args)
    assert p.returncode == 2, p.stderr
    last = p.stderr.strip().splitlines()[-1]
    assert last.startswith(f"error: {wal}: damaged write-ahead log of the store (a bad "
                           "frame at byte 0, intact frames from byte "), last
    assert last.endswith("move it aside to start without its rows")
    assert "Traceback" not in p.stderr
    assert wal.read_bytes() == bytes(bad)
    wal.write_bytes(good)
    assert _stored_times(store) == sorted(float(t) for t in range(3) for _ in ANCHORS)


# --------------------------------------------------------------------------------------
# 10. WebSocket to an unknown path
# --------------------------------------------------------------------------------------


def test_a_websocket_to_an_unknown_path_is_closed_with_a_reason_and_counted(anchors, servers):
    from websockets.exceptions import ConnectionClosed
    from websockets.sync.client import connect

    srv = servers(["--anchors", str(anchors)])
    paths = ("/ws/nope", "/api/positions", "/static/x")
    for path in paths:
        with connect(srv.url.replace("http", "ws") + path, open_timeout=10) as ws:
            with pytest.raises(ConnectionClosed):
                ws.recv(timeout=10)
            assert ws.close_code == 1008
            assert f"no such WebSocket endpoint: {path}" in ws.close_reason
    assert _metric(srv.url, 'robustloc_requests_rejected_total{reason="not_found"}') == len(paths)
    assert httpx.get(srv.url + "/healthz").status_code == 200


def test_an_mqtt_message_an_internal_error_stops_is_kept_in_the_dead_letter_folder(
        anchors, broker, tmp_path, capsys):
    """A defect of the service (here: ingest raises) acknowledged the message and the
    broker dropped it, rows and all.  Now its payload is first kept, byte for byte, in
    ``STORE/dead-letter`` (then acknowledged: sent again it would fail again); where that
    file cannot be written the message is not acknowledged, and the broker delivers it
    again after the reconnect.  A real Mosquitto, the real MqttIngest and Engine; the
    defect is injected by replacing the engine's ingest."""
    mqtt = pytest.importorskip("paho.mqtt.client")
    from robustloc.io import read_anchors
    from robustloc.service import mqtt as service_mqtt
    from robustloc.service.engine import Engine
    from robustloc.service.processor import LocateProcessor

    a = read_anchors(anchors)
    eng = Engine(a, LocateProcessor(a, method="ls"), store_dir=tmp_path / "s",
                 latency_window_s=0.0, idle_flush_s=600.0, value="range", fsync=False,
                 snapshot_s=0)

    def defect(*args, **kw):
        raise RuntimeError("injected defect")

    eng.ingest_batch = defect
    eng.ingest = defect
    ing = service_mqtt.MqttIngest(eng, "127.0.0.1", broker.port,
                                  client_id="robustloc-dead-letter-test", persistent=True)
    acked: list[int] = []
    real_ack = ing.client.ack
    ing.client.ack = lambda mid, qos: (acked.append(mid), real_ack(mid, qos))[1]
    dead = tmp_path / "s" / "dead-letter"
    pub = mqtt.Client(mqtt.CallbackAPIVersion.VERSION2)
    pub.connect("127.0.0.1", broker.port)
    pub.loop_start()
    ing.start()
    try:
        wait_until(ing.connected.is_set, 30, "the service's MQTT connection")
        time.sleep(0.5)  # (the subscription)
        first = json.dumps(_rows([1.0, 2.0])).encode()
        pub.publish("robustloc/measurements/gw", first, qos=1).wait_for_publish(5)
        files = wait_until(lambda: sorted(dead.glob("*.payload")), 30, "the dead-letter file")
        assert [f.read_bytes() for f in files] == [first]
        wait_until(lambda: len(acked) == 1, 10, "the acknowledgement")
        # the folder cannot be written (a file in its place): not acknowledged, delivered
        # again after the reconnect, then kept once it can be
        shutil.rmtree(dead)
        dead.write_text("in the way")
        second = json.dumps(_rows([3.0])).encode()
        pub.publish("robustloc/measurements/gw", second, qos=1).wait_for_publish(5)
        wait_until(lambda: eng.metrics.requests_rejected.get("mqtt_internal_error", 0) >= 2, 30,
              "the second message")
        time.sleep(0.5)
        assert len(acked) == 1
        dead.unlink()
        files = wait_until(lambda: sorted(dead.glob("*.payload")) if dead.is_dir() else [],
                      service_mqtt.STORE_RETRY_S + 30, "the message delivered again")
        assert [f.read_bytes() for f in files] == [second]
        wait_until(lambda: len(acked) == 2, 10, "its acknowledgement")
    finally:
        ing.stop()
        pub.loop_stop()
        pub.disconnect()
        eng.stop()
    err = capsys.readouterr().err
    assert "its payload is kept in" in err and "not acknowledged; reconnecting" in err
    assert "Traceback" not in err
