"""``replay --skip``: a replay cut off by a server killed mid-way resumes where it stopped.

A real ``robustloc serve --store`` is killed (SIGKILL) while a paced replay runs; the
replay stops with exit 2 and says which ``--skip`` resumes it; the server restarts on
its store and port; the replay with that ``--skip`` completes.  The store then holds
every row of the log, and no row more than once except those of the one batch that was
in flight when the server died (stored, perhaps, without an answer).  Before, the
message said how many rows had been accepted and nothing could resume: a user sent the
whole log again (every row twice) or cut the file by hand.

Bounded: 40 time steps of 4 rows, one kill, two server starts; the servers are stopped
by the test.
"""

from __future__ import annotations

import json
import re
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

pytest.importorskip("starlette")
pytest.importorskip("uvicorn")
pytest.importorskip("httpx")

from robustloc.cli import main  # noqa: E402
from robustloc.service.launch import ROBUSTLOC, ServerProcess, read_metric  # noqa: E402

ANCHORS = {"A1": (0.0, 0.0), "A2": (10.0, 0.0), "A3": (10.0, 10.0), "A4": (0.0, 10.0)}
STEPS = 40


def _log(path: Path) -> pd.DataFrame:
    xy = np.array(list(ANCHORS.values()))
    d = np.hypot(*(xy - [3.0, 4.0]).T)
    df = pd.DataFrame([{"time": float(t), "tag": "T", "anchor": a, "range": float(r)}
                       for t in range(STEPS) for a, r in zip(ANCHORS, d)])
    df.to_csv(path, index=False)
    return df


def _stored(store: Path) -> pd.DataFrame:
    from robustloc.service.store import SegmentLog

    log = SegmentLog(store / "measurements", fsync=False)
    try:
        return log.scan(columns=["time", "tag", "anchor"]).to_pandas()
    finally:
        log.close()


def _anchors_file(tmp_path: Path) -> Path:
    p = tmp_path / "anchors.csv"
    p.write_text("anchor,x,y\n" + "".join(f"{a},{x},{y}\n" for a, (x, y) in ANCHORS.items()))
    return p


def _resume_point(err: str, prefix: str, n_rows: int) -> int:
    """The ``--skip`` a stopped replay's error line gives, checked against its counts
    (every acknowledged row accepted, some but not all of the log's ``n_rows``)."""
    m = re.search(re.escape(prefix) + r"\(?.*?stopped after (\d+) of (\d+) rows; (\d+) "
                  r"accepted; resume with --skip (\d+)", err)
    assert m, err
    sent, rows, accepted, skip = map(int, m.groups())
    assert rows == n_rows and sent == skip == accepted and 0 < skip < rows
    return skip


def _start_replay(url: str, log: Path, *extra: str) -> subprocess.Popen:
    """``robustloc replay LOG --url URL EXTRA...`` running in a subprocess (pipes)."""
    return subprocess.Popen([*ROBUSTLOC, "replay", str(log), "--url", url, *extra],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def _await_rows(srv: ServerProcess, rep: subprocess.Popen, n: int) -> None:
    """Until the server has accepted ``n`` rows of the running replay ``rep`` (120 s)."""
    deadline = time.monotonic() + 120
    while read_metric(srv.url, "robustloc_rows_accepted_total", timeout_s=10.0) < n:
        assert rep.poll() is None and time.monotonic() < deadline, "no rows arrived"
        time.sleep(0.05)


def _kill(rep: subprocess.Popen | None) -> None:
    if rep is not None and rep.poll() is None:
        rep.kill()
        rep.wait(10)


def test_a_replay_stopped_by_a_killed_server_resumes_with_skip(tmp_path):
    anchors = _anchors_file(tmp_path)
    log = _log(tmp_path / "m.csv")
    store = tmp_path / "store"
    args = ["--anchors", str(anchors), "--store", str(store)]
    srv = ServerProcess(args, startup_timeout_s=120)
    srv2 = rep = None
    try:
        srv.start()
        # 40 steps at 10x real time: 4 s; the server dies once it has 10 steps' rows
        rep = _start_replay(srv.url, tmp_path / "m.csv", "--speed", "10", "-q")
        _await_rows(srv, rep, 10 * len(ANCHORS))
        srv.kill9()
        _, err = rep.communicate(timeout=120)
        assert rep.returncode == 2, err
        skip = _resume_point(err, "", len(log))
        # the same store and port, the rest of the log
        srv2 = ServerProcess(args, port=srv.port, startup_timeout_s=120)
        srv2.start()
        assert main(["replay", str(tmp_path / "m.csv"), "--url", srv2.url, "--speed", "0",
                     "--skip", str(skip), "-q", "--json"]) == 0
    finally:
        _kill(rep)
        srv.stop()
        if srv2 is not None:
            srv2.stop()
    got = _stored(store)
    key = ["time", "tag", "anchor"]
    counts = got.groupby(key).size()
    want = log.set_index(key).index
    assert set(counts.index) == set(want), "rows of the log missing from the store"
    twice = counts[counts > 1]
    # only the batch in flight when the server died may be stored twice: one time step
    assert len(twice) <= len(ANCHORS) and set(twice.index.get_level_values("time")) <= {
        float(log["time"].iloc[skip])}, twice


def test_skip_beyond_the_log_is_refused(tmp_path, capsys):
    _log(tmp_path / "m.csv")
    assert main(["replay", str(tmp_path / "m.csv"), "--url", "http://127.0.0.1:9",
                 "--skip", str(4 * STEPS + 1)]) == 2
    assert f"--skip {4 * STEPS + 1}: the log has {4 * STEPS} rows" in capsys.readouterr().err


def test_skip_all_rows_sends_nothing_and_says_so(tmp_path, capsys):
    _log(tmp_path / "m.csv")
    # nothing to send: no connection is made (the URL has no server), exit 0
    assert main(["replay", str(tmp_path / "m.csv"), "--url", "http://127.0.0.1:9",
                 "--skip", str(4 * STEPS), "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert (out["rows"], out["skipped"], out["accepted"]) == (4 * STEPS, 4 * STEPS, 0)


def test_skip_is_in_the_help():
    r = subprocess.run([sys.executable, "-m", "robustloc.cli", "replay", "--help"],
                       capture_output=True, text=True)
    assert "--skip N" in r.stdout and "resume" in r.stdout


def test_a_replay_interrupted_by_ctrl_c_says_where_to_resume(tmp_path):
    """Ctrl-C (SIGINT) on a paced replay: exit 130, and the line says how far it got and
    the --skip that resumes (it said only "error: interrupted"; the replay review of
    2026-12-07); --json gives the same counts on stdout.  The resumed replay completes:
    the store holds every row of the log, none twice but the batch in flight."""
    import signal

    anchors = _anchors_file(tmp_path)
    log = _log(tmp_path / "m.csv")
    store = tmp_path / "store"
    srv = ServerProcess(["--anchors", str(anchors), "--store", str(store)],
                        startup_timeout_s=120)
    rep = None
    try:
        srv.start()
        rep = _start_replay(srv.url, tmp_path / "m.csv", "--speed", "10", "-q", "--json")
        _await_rows(srv, rep, 10 * len(ANCHORS))
        rep.send_signal(signal.SIGINT)
        out, err = rep.communicate(timeout=120)
        assert rep.returncode == 130, err
        skip = _resume_point(err, "error: interrupted ", len(log))
        summary = json.loads(out)
        assert (summary["sent"], summary["stopped"]) == (skip, "interrupted")
        assert main(["replay", str(tmp_path / "m.csv"), "--url", srv.url, "--speed", "0",
                     "--skip", str(skip), "-q"]) == 0
    finally:
        _kill(rep)
        srv.stop()
    counts = _stored(store).groupby(["time", "tag", "anchor"]).size()
    assert len(counts) == len(log)
    assert (counts > 1).sum() <= len(ANCHORS)


@pytest.mark.parametrize("transport", ["http", "ws"])
def test_a_refused_connection_and_a_restart_are_retried(tmp_path, transport):
    """A refused connection (no server yet) and a graceful restart between two time steps
    (WebSocket: closed with 1012) stopped the replay; the batch certainly was not
    received, so it is sent again (--retry-s) and the replay completes: every row of the
    log stored once, the retries said on stderr."""
    if transport == "ws":
        pytest.importorskip("websockets")
    from robustloc.service.launch import free_port

    anchors = _anchors_file(tmp_path)
    log = tmp_path / "m.csv"
    df = pd.DataFrame([{"time": float(t), "tag": "T", "anchor": a, "range": 5.0}
                       for t in (0, 20) for a in ANCHORS])
    df.to_csv(log, index=False)
    store = tmp_path / "store"
    args = ["--anchors", str(anchors), "--store", str(store)]
    port = free_port()
    srv = ServerProcess(args, port=port, startup_timeout_s=120)
    srv2 = rep = None
    try:
        # nothing listens yet: refused, retried until the server is up
        rep = _start_replay(srv.url, log, "--speed", "1", "-q", "--transport", transport,
                            "--retry-s", "120")
        time.sleep(1.0)
        srv.start()
        _await_rows(srv, rep, len(ANCHORS))
        srv.stop()  # the restart, in the 20 s between the two time steps
        srv2 = ServerProcess(args, port=port, startup_timeout_s=120)
        srv2.start()
        out, err = rep.communicate(timeout=180)
    finally:
        _kill(rep)
        srv.stop()
        if srv2 is not None:
            srv2.stop()
    assert rep.returncode == 0, err
    assert f"{2 * len(ANCHORS)} of {2 * len(ANCHORS)} rows accepted" in out
    assert f"rows 1 to {len(ANCHORS)} not sent: sending them again" in err
    if transport == "ws":
        assert (f"the WebSocket was closed (code 1012); rows {len(ANCHORS) + 1} to "
                f"{2 * len(ANCHORS)} not sent") in err
    counts = _stored(store).groupby(["time", "tag", "anchor"]).size()
    assert len(counts) == len(df) and (counts == 1).all()
