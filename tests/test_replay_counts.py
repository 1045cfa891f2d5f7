"""``robustloc replay`` against a real server: every rejected row is counted (the server
lists at most MAX_REJECTED_LISTED per reply), and a replay that stops part-way says how
many rows the server had accepted (exit 2)."""

from __future__ import annotations

import json
import subprocess
from pathlib import Path

import pytest

pytest.importorskip("starlette")
pytest.importorskip("httpx")

from robustloc.service.defaults import MAX_REJECTED_LISTED  # noqa: E402
from robustloc.service.launch import ROBUSTLOC, ServerProcess  # noqa: E402

ANCHORS = [("1", 0.0, 0.0), ("2", 10.0, 0.0), ("3", 0.0, 10.0), ("4", 10.0, 10.0)]


def _anchors(path: Path) -> Path:
    path.write_text("anchor,x,y\n" + "".join(f"{a},{x},{y}\n" for a, x, y in ANCHORS))
    return path


def _replay(log: Path, url: str, *extra: str) -> subprocess.CompletedProcess:
    return subprocess.run([*ROBUSTLOC, "replay", str(log), "--url", url, "--speed", "0",
                           *extra], capture_output=True, text=True, timeout=120)


def test_replay_counts_every_rejected_row_of_a_large_batch(tmp_path):
    n_bad = 3 * MAX_REJECTED_LISTED  # one time step: one batch, more than the server lists
    log = tmp_path / "bad.csv"
    log.write_text("time,tag,anchor,range\n"
                   + "".join(f"0,T{k},99,5.0\n" for k in range(n_bad))  # unknown anchor
                   + "".join(f"0,G,{a},5.0\n" for a, _, _ in ANCHORS))
    with ServerProcess(["--anchors", str(_anchors(tmp_path / "a.csv"))]) as srv:
        p = _replay(log, srv.url)
        pj = _replay(log, srv.url, "--json")
    assert p.returncode == 1, p.stderr
    assert p.stdout.strip().startswith(f"{len(ANCHORS)} of {n_bad + len(ANCHORS)} rows "
                                       "accepted")
    assert f"{n_bad} rows rejected" in p.stderr
    assert f"... {n_bad - 20} more rejected rows" in p.stderr
    # --json: the same counts on stdout, the listed rows with their file lines, same code
    assert pj.returncode == 1, pj.stderr
    s = json.loads(pj.stdout)
    assert (s["rows"], s["accepted"], s["n_rejected"]) == (n_bad + len(ANCHORS),
                                                           len(ANCHORS), n_bad)
    assert s["measurements"] == str(log) and s["url"] == srv.url
    assert len(s["rejected"]) == MAX_REJECTED_LISTED
    assert all(r["line"] == k + 2 and "99" in r["error"]
               for k, r in enumerate(s["rejected"]))
    assert pj.stderr == ""


def test_replay_stopped_by_an_error_answer_says_how_far_it_got(tmp_path):
    # three small time steps, then one whose body exceeds --max-body-bytes: 413
    good = "".join(f"{t},T,{a},{5.0 + t}\n" for t in range(3) for a, _, _ in ANCHORS)
    big = "".join(f"3,T{k},{ANCHORS[k % 4][0]},7.0\n" for k in range(400))
    log = tmp_path / "log.csv"
    log.write_text("time,tag,anchor,range\n" + good + big)
    with ServerProcess(["--anchors", str(_anchors(tmp_path / "a.csv")),
                        "--max-body-bytes", "4000"]) as srv:
        p = _replay(log, srv.url)
        pj = _replay(log, srv.url, "--json")
    assert p.returncode == 2, p.stderr
    n_good, n = 3 * len(ANCHORS), 3 * len(ANCHORS) + 400
    assert "413" in p.stderr
    assert f"stopped after {n_good} of {n} rows; {n_good} accepted" in p.stderr
    # (it advised "resume with --skip 12", which failed again the same way, for ever)
    assert (f"the server refuses a batch of 400 rows as too large: resume with --skip "
            f"{n_good} and a --batch-rows below 400") in p.stderr
    assert "Traceback" not in p.stderr
    # --json: how far it got on stdout too (the same error line on stderr).  The second
    # replay re-sends the first three steps, accepted again (as any client's retry)
    assert pj.returncode == 2, pj.stderr
    sj = json.loads(pj.stdout)
    assert (sj["rows"], sj["sent"], sj["accepted"]) == (n, n_good, n_good)
    assert "413" in sj["stopped"] and "413" in pj.stderr


def test_rows_rejected_before_a_replay_stopped_are_reported(tmp_path):
    """A replay that stops (here a 413) after the server rejected rows reports them as a
    finished run does: the count, ``FILE:LINE: reason`` and --json's ``n_rejected`` and
    ``rejected`` (they were never reported, and the ``--skip`` resumes past them)."""
    good = "".join(f"{t},T,{a},{5.0 + t}\n" for t in range(3) for a, _, _ in ANCHORS)
    bad = "1,T,99,5.0\n"  # line 14: an unknown anchor, rejected
    big = "".join(f"3,T{k},{ANCHORS[k % 4][0]},7.0\n" for k in range(400))
    log = tmp_path / "log.csv"
    log.write_text("time,tag,anchor,range\n" + good + bad + big)
    with ServerProcess(["--anchors", str(_anchors(tmp_path / "a.csv")),
                        "--max-body-bytes", "4000"]) as srv:
        p = _replay(log, srv.url)
        pj = _replay(log, srv.url, "--json")
    n_good, n = 3 * len(ANCHORS), 3 * len(ANCHORS) + 1 + 400
    assert p.returncode == 2, p.stderr
    assert (f"stopped after {n_good + 1} of {n} rows; {n_good} accepted, 1 rejected; "
            f"the server refuses") in p.stderr
    assert "1 rows rejected" in p.stderr and f"  {log}:14: " in p.stderr
    assert pj.returncode == 2, pj.stderr
    sj = json.loads(pj.stdout)
    assert (sj["sent"], sj["accepted"], sj["n_rejected"]) == (n_good + 1, n_good, 1)
    assert [r["line"] for r in sj["rejected"]] == [14] and "99" in sj["rejected"][0]["error"]


def test_batch_rows_keeps_the_pace(tmp_path):
    """``--batch-rows`` with ``--speed`` > 0: a batch ends with its time step, so no row
    goes out before its paced time (a batch of 2000 rows was sent at its first row's
    time: 59 s of a log in 0.56 s at --speed 1)."""
    log = tmp_path / "log.csv"
    log.write_text("time,tag,anchor,range\n" + "".join(
        f"{t},T,{a},5.0\n" for t in range(5) for a, _, _ in ANCHORS))  # 0..4 s
    with ServerProcess(["--anchors", str(_anchors(tmp_path / "a.csv"))]) as srv:
        p = subprocess.run([*ROBUSTLOC, "replay", str(log), "--url", srv.url, "--speed",
                            "4", "--batch-rows", "1000", "--json"],
                           capture_output=True, text=True, timeout=120)
    assert p.returncode == 0, p.stderr
    s = json.loads(p.stdout)
    assert s["accepted"] == 5 * len(ANCHORS) and s["seconds"] >= 4 / 4 - 0.05, s


def test_websocket_stops_say_what_to_do(tmp_path):
    """Over WebSocket: a wrong token said only "HTTP 403" (HTTP says the token), and a
    batch over --max-body-bytes (close 1009) advised a --skip that fails again."""
    pytest.importorskip("websockets")
    big = "".join(f"0,T{k},{ANCHORS[k % 4][0]},7.0\n" for k in range(400))
    log = tmp_path / "log.csv"
    log.write_text("time,tag,anchor,range\n" + big)
    with ServerProcess(["--anchors", str(_anchors(tmp_path / "a.csv")),
                        "--max-body-bytes", "4000", "--token", "s3cret"]) as srv:
        wrong = _replay(log, srv.url, "--transport", "ws", "--token", "wrong")
        big = _replay(log, srv.url, "--transport", "ws", "--token", "s3cret")
    assert wrong.returncode == 2 and "403: missing or wrong --token?" in wrong.stderr
    assert big.returncode == 2, big.stderr
    assert ("the server refuses a batch of 400 rows as too large: resume with --skip 0 "
            "and a --batch-rows below 400") in big.stderr
