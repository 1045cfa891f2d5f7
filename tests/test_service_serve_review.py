"""``robustloc serve`` after the serve review: a ``--track`` service killed before its
first state snapshot resumes every tag's filter; a position subscriber that never reads
holds a bounded number of bytes.

Real ``robustloc serve`` processes on free loopback ports, stopped by the tests; the
offline reference is ``robustloc track`` on the same file.  Bounded: two tags of 120
epochs of four ranges, one ``kill -9``, two server starts; 110 epochs of 2 000 tags into
one stalled WebSocket.
"""

from __future__ import annotations

import base64
import json
import os
import socket
import urllib.request
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

pytest.importorskip("starlette")
pytest.importorskip("uvicorn")
pytest.importorskip("robustloc.tracking")

from _waiting import wait_until  # noqa: E402
from test_replay_resume import ANCHORS, _anchors_file  # noqa: E402

from robustloc.cli import main  # noqa: E402
from robustloc.service.launch import ServerProcess, read_metric  # noqa: E402

#: epochs per tag (every 0.5 s), and the epochs sent before the kill
N_EPOCHS, CUT = 120, 50


def _walk_log(path: Path) -> pd.DataFrame:
    """Two tags walking circles in the anchors' square, four noisy ranges per epoch (a
    fixed seed); written to ``path``."""
    rng = np.random.default_rng(7)
    xy = np.array(list(ANCHORS.values()))
    rows = []
    for k in range(N_EPOCHS):
        t = 0.5 * k
        for j, tag in enumerate(("T1", "T2")):
            p = np.array([5.0, 5.0]) + (2.0 + j) * np.array([np.cos(0.05 * t + j),
                                                             np.sin(0.05 * t + j)])
            d = np.hypot(*(xy - p).T) + rng.normal(0.0, 0.3, len(xy))
            rows += [{"time": t, "tag": tag, "anchor": a, "range": float(r)}
                     for a, r in zip(ANCHORS, d)]
    df = pd.DataFrame(rows)
    df.to_csv(path, index=False)
    return df


def _post(url: str, rows: pd.DataFrame) -> dict:
    body = json.dumps(rows.to_dict("records")).encode()
    req = urllib.request.Request(url + "/api/measurements", body,
                                 {"content-type": "application/json"})
    with urllib.request.urlopen(req, timeout=60) as r:  # noqa: S310 - http://127.0.0.1
        return json.load(r)


def _positions(url: str) -> pd.DataFrame:
    with urllib.request.urlopen(url + "/api/positions?limit=1000000",  # noqa: S310
                                timeout=60) as r:
        return pd.DataFrame(json.load(r))


def test_a_track_service_killed_before_its_first_snapshot_resumes_every_filter(tmp_path):
    """Without ``state/processor.pkl`` the restart took the stored positions as solved and
    left the tracker empty: each tag restarted from a fresh filter, and the rows after
    the restart were not those of ``robustloc track`` (the serve review: 62-98 of 900 rows
    off by up to 2.45 m, ``reinit`` 0).  Now every stored row is solved again from the
    first: the positions equal the offline track's to rounding."""
    anchors = _anchors_file(tmp_path)
    log = _walk_log(tmp_path / "m.csv")
    # the offline reference first (it also compiles the tracker's kernels, so the server
    # solves its first block well within its 10 s snapshot interval)
    assert main(["track", str(tmp_path / "m.csv"), "--anchors", str(anchors),
                 "-o", str(tmp_path / "offline.csv"), "-q"]) == 0
    want = pd.read_csv(tmp_path / "offline.csv")
    store = tmp_path / "store"
    args = ["--anchors", str(anchors), "--store", str(store), "--track",
            "--idle-flush", "0.3"]
    srv = ServerProcess(args, startup_timeout_s=120)
    srv2 = None
    first = log[log["time"] < 0.5 * CUT]
    try:
        srv.start()
        assert _post(srv.url, first)["accepted"] == len(first)
        wait_until(lambda: len(_positions(srv.url)) == 2 * CUT, 60,
                   "the first epochs solved")
        # the case under test: no snapshot of the filters yet when the service dies
        assert not (store / "state" / "processor.pkl").exists()
        srv.kill9()
        srv2 = ServerProcess(args, port=srv.port, startup_timeout_s=120)
        srv2.start()
        rest = log[log["time"] >= 0.5 * CUT]
        assert _post(srv2.url, rest)["accepted"] == len(rest)
        (got,) = wait_until(lambda: [p for p in [_positions(srv2.url)]
                                     if len(p) == 2 * N_EPOCHS], 60, "every epoch solved")
    finally:
        srv.stop()
        if srv2 is not None:
            srv2.stop()
    key = ["tag", "time"]
    got = got.sort_values(key).reset_index(drop=True)
    want = want.assign(tag=want["tag"].astype(str)).sort_values(key).reset_index(drop=True)
    assert (got[key].to_numpy() == want[key].to_numpy()).all()
    assert (got["status"] == want["status"]).all()
    assert (got["reinit"].to_numpy() == want["reinit"].to_numpy()).all()
    for c in ("x", "y", "vx", "vy"):
        # (rounding: the same tracker on the same epochs in the same order; the CSV
        # writes 17 significant digits)
        np.testing.assert_allclose(got[c].astype(float), want[c], rtol=0, atol=1e-9,
                                   equal_nan=True, err_msg=c)


def test_a_batch_subscriber_that_never_reads_holds_at_most_ws_queue_bytes(
        tmp_path, server_factory):
    """A ``/ws/positions?batch=1`` subscriber that never reads: its queue was bounded by
    20 000 messages, each a whole solved block (650 kB at 2 000 tags: some 13 GB held
    before the first drop; the serve review's 400 blocks grew the server by 255 MB more
    than without the subscriber, no drop).  Now by :data:`WS_QUEUE_BYTES` too: the queue
    stops growing at 32 MiB, and the oldest blocks are dropped and counted."""
    srv = server_factory(["--anchors", str(_anchors_file(tmp_path))],
                         startup_timeout_s=120)
    port = srv.url.rsplit(":", 1)[1]
    sock = socket.create_connection(("127.0.0.1", int(port)))
    try:  # a WebSocket handshake, then never a byte read (a small receive window)
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
        key = base64.b64encode(os.urandom(16)).decode()
        sock.sendall(f"GET /ws/positions?batch=1 HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\n"
                     "Upgrade: websocket\r\nConnection: Upgrade\r\n"
                     f"Sec-WebSocket-Key: {key}\r\nSec-WebSocket-Version: 13\r\n\r\n"
                     .encode())
        head = b""
        while b"\r\n\r\n" not in head:  # (the answer's headers; no frame comes before)
            head += sock.recv(1024)
        assert head.startswith(b"HTTP/1.1 101 "), head
        xy = np.array(list(ANCHORS.values()))
        d = np.hypot(*(xy - [3.0, 4.0]).T)
        n_tags, queued = 2000, []
        for k in range(110):  # one block of 2 000 rows (some 420 kB of JSON) per epoch
            rows = pd.DataFrame([{"time": float(k), "tag": f"t{j:05d}", "anchor": a,
                                  "range": float(r)}
                                 for j in range(n_tags) for a, r in zip(ANCHORS, d)])
            assert _post(srv.url, rows)["accepted"] == len(rows)
            if k in (90, 109):
                wait_until(lambda n=k: read_metric(srv.url, "robustloc_positions_total")
                           >= n * n_tags, 60, "the blocks solved")
                queued.append(read_metric(srv.url, "robustloc_ws_queued_bytes"))
        dropped = read_metric(srv.url, "robustloc_ws_messages_dropped_total")
    finally:
        sock.close()
    # 110 blocks of some 420 kB (46 MB) into a 32 MiB queue: the oldest dropped, counted
    assert dropped > 0, (dropped, queued)
    # the queue stops growing: full (within one block of the bound), never beyond it
    from robustloc.service.app import WS_QUEUE_BYTES

    block = 2 * WS_QUEUE_BYTES / 100  # (a block is some 420 kB: 2 % of the bound is wider)
    assert all(WS_QUEUE_BYTES - block <= q <= WS_QUEUE_BYTES for q in queued), queued
