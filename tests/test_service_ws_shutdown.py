"""``serve`` at SIGTERM answers the WebSocket message it is storing before it closes.

uvicorn closed every WebSocket at once (code 1012): a message being stored was stored
without its answer, and a replay resumed from its last answer sent those rows again
(the partition/replay review, 2026-12-07: 3 604 rows stored for a log of 3 600 after a
graceful stop; HTTP and ``kill -9`` gave 3 600).  A real server on a free loopback port;
bounded (one message of 300 000 rows; one replay of 1 200 rows); every server stopped.
"""

from __future__ import annotations

import json
import signal
import threading

import numpy as np
import pandas as pd
import pytest

pytest.importorskip("starlette")
pytest.importorskip("uvicorn")
pytest.importorskip("websockets")

from test_replay_resume import (  # noqa: E402
    ANCHORS,
    _anchors_file,
    _await_rows,
    _kill,
    _start_replay,
    _stored,
)

from robustloc.cli import main  # noqa: E402
from robustloc.service.launch import ServerProcess  # noqa: E402


def test_a_message_in_progress_is_answered_before_the_close(tmp_path):
    from websockets.sync.client import connect

    store = tmp_path / "store"
    srv = ServerProcess(["--anchors", str(_anchors_file(tmp_path)), "--store", str(store)],
                        startup_timeout_s=120)
    n = 300_000
    rows = [{"time": 1000.0 + (i // 4) * 0.001, "tag": f"w{i % 50}",
             "anchor": f"A{i % 4 + 1}", "range": 5.0} for i in range(n)]
    body = json.dumps(rows)
    try:
        srv.start()
        assert srv.proc is not None
        with connect(srv.url.replace("http", "ws") + "/ws/measurements", max_size=None,
                     proxy=None) as c:
            timer = threading.Timer(0.3, srv.proc.send_signal, args=(signal.SIGTERM,))
            timer.start()
            c.send(body)
            answer = json.loads(c.recv(timeout=60))
            timer.join()
        assert answer["accepted"] == n, answer
        srv.proc.wait(timeout=60)
        assert "every acknowledged row is in" in srv.log()
    finally:
        srv.stop()
    assert len(_stored(store)) == n


def test_a_websocket_replay_stopped_gracefully_resumes_without_duplicates(tmp_path):
    """Replay over WebSocket, SIGTERM to the server mid-way, resume with the --skip the
    replay printed (JSON ``sent``) on a restarted server: the store holds the log's rows,
    each once."""
    anchors = _anchors_file(tmp_path)
    xy = np.array(list(ANCHORS.values()))
    d = np.hypot(*(xy - [3.0, 4.0]).T)
    log = pd.DataFrame([{"time": float(t) * 0.1, "tag": f"T{k}", "anchor": a, "range": r}
                        for t in range(100) for k in range(3) for a, r in zip(ANCHORS, d)])
    log.to_csv(tmp_path / "m.csv", index=False)
    store = tmp_path / "store"
    args = ["--anchors", str(anchors), "--store", str(store)]
    srv = ServerProcess(args, startup_timeout_s=120)
    srv2 = rep = None
    try:
        srv.start()
        rep = _start_replay(srv.url, tmp_path / "m.csv", "--speed", "2", "--transport",
                            "ws", "--json", "--batch-rows", "12")
        _await_rows(srv, rep, 300)
        srv.stop()  # SIGTERM: the graceful stop
        out, err = rep.communicate(timeout=120)
        assert rep.returncode == 2, err
        skip = json.loads(out)["sent"]
        assert 0 < skip < len(log)
        srv2 = ServerProcess(args, port=srv.port, startup_timeout_s=120)
        srv2.start()
        assert main(["replay", str(tmp_path / "m.csv"), "--url", srv2.url, "--speed", "0",
                     "--transport", "ws", "--skip", str(skip), "-q"]) == 0
    finally:
        _kill(rep)
        srv.stop()
        if srv2 is not None:
            srv2.stop()
    counts = _stored(store).groupby(["time", "tag", "anchor"]).size()
    assert len(counts) == len(log) and int(counts.max()) == 1, counts[counts > 1]
