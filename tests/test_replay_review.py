"""``robustloc replay`` against servers that are not ``robustloc serve`` (all on
127.0.0.1, stopped by each test): every odd answer stops the replay with its reason and
exit 2, never a traceback or a hang (the replay review)."""

from __future__ import annotations

import json
import threading
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path

import pandas as pd
import pytest

from robustloc.cli import main

ANSWERS = {
    "list": (500, b"[1,2]"),
    "badjson": (202, b"{not json"),
    "empty202": (202, b"{}"),
    "index_out_of_range": (202, json.dumps({"accepted": 0, "rejected": [
        {"index": 99, "error": "x"}]}).encode()),
    "accepts_more_than_sent": (202, b'{"accepted": 1000, "rejected": []}'),
    # a 202 for only part of the batch (2 rows: 1 accepted, none rejected) exited 0
    "accounts_for_part": (202, b'{"accepted": 1, "rejected": [], "n_rejected": 0}'),
}


def _log(tmp_path: Path) -> str:
    path = tmp_path / "m.csv"
    pd.DataFrame({"time": [0.0, 0.0, 1.0], "tag": "t", "anchor": ["a", "b", "a"],
                  "range": [1.0, 2.0, 1.5]}).to_csv(path, index=False)
    return str(path)


def _serve(answer) -> ThreadingHTTPServer:  # noqa: ANN001
    """A server on 127.0.0.1 answering each POST with ``answer(rows) -> (status, body)``."""

    class Handler(BaseHTTPRequestHandler):
        def do_POST(self) -> None:  # noqa: N802 (http.server's name)
            rows = json.loads(self.rfile.read(int(self.headers.get("Content-Length", 0))))
            status, body = answer(rows)
            self.send_response(status)
            self.send_header("Content-Type", "application/json")
            self.send_header("Content-Length", str(len(body)))
            self.end_headers()
            self.wfile.write(body)

        def log_message(self, *args: object) -> None:
            pass

    server = ThreadingHTTPServer(("127.0.0.1", 0), Handler)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    return server


def _replay(tmp_path: Path, answer) -> int:  # noqa: ANN001
    """``robustloc replay`` of :func:`_log` (unpaced) to a :func:`_serve` server, stopped
    after; its exit code."""
    server = _serve(answer)
    try:
        return main(["replay", _log(tmp_path), "--url",
                     f"http://127.0.0.1:{server.server_address[1]}", "--speed", "0"])
    finally:
        server.shutdown()
        server.server_close()


@pytest.mark.parametrize("mode", sorted(ANSWERS))
def test_an_unexpected_answer_stops_the_replay_with_its_reason(tmp_path, capsys, mode):
    code = _replay(tmp_path, lambda rows: ANSWERS[mode])
    err = capsys.readouterr().err
    assert code == 2 and "Traceback" not in err
    assert "unexpected answer" in err or "server answered 500" in err
    assert "stopped after 0 of 3 rows" in err


def test_a_rate_limit_answer_is_bounded(tmp_path, capsys):
    """``retry_after_s: -1`` was "sleep length must be non-negative" (and 1e9 slept
    1e9 s).  The wait is clamped to [0.1, 60] s: the server answers 429 with -1 once,
    then accepts."""
    import time

    calls: list[float] = []

    def answer(rows: list) -> tuple[int, bytes]:
        calls.append(time.monotonic())
        if len(calls) == 1:
            return 429, b'{"retry_after_s": -1}'
        return 202, json.dumps({"accepted": len(rows), "rejected": []}).encode()

    code = _replay(tmp_path, answer)
    assert code == 0, capsys.readouterr().err
    assert calls[1] - calls[0] >= 0.1  # (not a busy loop)


def test_a_token_a_header_cannot_carry_is_refused(tmp_path, capsys):
    """'sécret' was a UnicodeEncodeError traceback."""
    code = main(["replay", _log(tmp_path), "--url", "http://127.0.0.1:9", "--speed", "0",
                 "--token", "sécret"])
    err = capsys.readouterr().err
    assert code == 2 and "printable ASCII" in err and "Traceback" not in err


def test_a_websocket_replay_that_cannot_connect_still_says_how_far_it_got(tmp_path, capsys):
    """Over WebSocket a refused connection gave no --json summary and no "stopped after"
    (the connection was opened outside the replay's error handling)."""
    pytest.importorskip("websockets")
    import socket

    s = socket.socket()
    s.bind(("127.0.0.1", 0))
    port = s.getsockname()[1]
    s.close()  # (a port nothing listens on)
    code = main(["replay", _log(tmp_path), "--url", f"http://127.0.0.1:{port}", "--speed",
                 "0", "--transport", "ws", "--json", "--retry-s", "0"])
    out, err = capsys.readouterr()
    assert code == 2 and "stopped after 0 of 3 rows" in err
    assert json.loads(out)["sent"] == 0


def test_a_timeout_with_a_batch_in_flight_says_so(tmp_path, capsys, monkeypatch):
    """A batch that got no answer within the timeout may have been stored: the line says
    so with its rows, as on Ctrl-C (it advised the --skip alone)."""
    import time

    import robustloc.commands.replay as rp

    monkeypatch.setattr(rp, "ANSWER_TIMEOUT_S", 0.5)
    calls: list[int] = []

    def answer(rows: list) -> tuple[int, bytes]:
        calls.append(len(rows))
        if len(calls) == 2:  # the second time step: no answer in time
            time.sleep(1.5)
        return 202, json.dumps({"accepted": len(rows), "rejected": []}).encode()

    code = _replay(tmp_path, answer)
    err = capsys.readouterr().err
    assert code == 2 and "Traceback" not in err
    assert ("stopped after 2 of 3 rows; 2 accepted; resume with --skip 2; a batch in "
            "flight (row 3 of the replay's order) may have reached the server") in err


def test_a_directory_is_refused_without_the_engine_hint(tmp_path, capsys):
    """replay has no --engine: a directory said "a partitioned dataset is read with
    --engine dask" all the same."""
    code = main(["replay", str(tmp_path), "--url", "http://127.0.0.1:9", "--speed", "0"])
    err = capsys.readouterr().err
    assert code == 2 and "Traceback" not in err
    assert err.startswith(f"error: {tmp_path}: is a directory, expected a file (this "
                          "command reads one file")
    assert "--engine" not in err
