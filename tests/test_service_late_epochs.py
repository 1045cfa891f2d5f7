"""Live epochs whose every row arrives late (``robustloc.service.assembly``).

A gateway that delivers whole epochs more than the latency window after another gateway's
later ones left those epochs without any live position (stored, counted late, solved only
by the batch commands).  A stateless service (``serve`` without ``--track``) now solves
them: the assembler remembers each tag's latest solved epoch times and tells an epoch never
solved from the late rows of one solved.  The assembler's rule by hand, then a real server.
"""

from __future__ import annotations

import json

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from robustloc.service.assembly import RECENT_SOLVED, EpochAssembler

obj = lambda *x: np.array(x, dtype=object)  # noqa: E731


def _epochs(a: EpochAssembler, tag: str, times, wall: float, anchors=(0, 1, 2)):
    t = np.repeat(np.asarray(times, dtype=float), len(anchors))
    col = np.tile(np.asarray(anchors, dtype=np.int64), len(times))
    return a.add(t, np.array([tag] * len(t), dtype=object), col, np.ones(len(t)), wall)


def test_a_late_epoch_never_solved_is_released_with_late_set():
    a = EpochAssembler(["A", "B", "C"], latency_window_s=0.5, idle_flush_s=2.0,
                       live_late=True)
    assert not _epochs(a, "t", [0, 1, 2, 3, 4, 5], wall=10.0).any()
    r = a.take_ready(10.0)
    assert sorted(set(r["time"].tolist())) == [0, 1, 2, 3, 4] and not r["late"].any()
    # every row of epoch 2.5 arrives late (older than 5 - 0.5): never solved, so held for
    # the rest of its epoch, then released with `late`
    late = _epochs(a, "t", [2.5], wall=11.0, anchors=(0, 1))
    assert not late.any()  # (not late in the sense of the reply: it will be solved)
    late = _epochs(a, "t", [2.5], wall=12.0, anchors=(2,))  # the rest of its epoch
    assert not late.any()
    r = a.take_ready(12.9)  # it waits idle_flush_s from its first row (epoch 5 is idle)
    assert r["time"].tolist() == [5.0] * 3 and not r["late"].any()
    r = a.take_ready(13.0)
    assert r["time"].tolist() == [2.5] * 3 and r["late"].all()
    assert sorted(r["anchor_col"].tolist()) == [0, 1, 2] and a.late_epochs == 1
    # solved now: a row of it, or of any solved epoch, is late as before
    assert _epochs(a, "t", [2.5, 3.0, 5.0], wall=14.0, anchors=(0,)).all()
    assert a.take_ready(100.0) is None and a.n_pending == 0


def test_what_the_tag_no_longer_remembers_stays_late():
    """Only the latest RECENT_SOLVED solved times are remembered: an epoch older than all
    of them may have been solved, so its late rows are not solved again."""
    a = EpochAssembler(["A", "B", "C"], latency_window_s=0.0, idle_flush_s=2.0,
                       live_late=True)
    n = RECENT_SOLVED + 8
    _epochs(a, "t", np.arange(n + 1.0), wall=0.0)
    assert len(set(a.take_ready(0.0)["time"].tolist())) == n  # 0 .. n-1 solved
    oldest = n - RECENT_SOLVED  # the oldest time remembered
    assert _epochs(a, "t", [oldest - 1.5], wall=1.0).all()  # before it: late
    assert not _epochs(a, "t", [oldest + 0.5], wall=1.0).any()  # within: solved late
    r = a.take_ready(3.5)  # (epoch n by idle flush, then the late one)
    assert r["time"][r["late"]].tolist() == [oldest + 0.5] * 3
    assert r["time"][~r["late"]].tolist() == [float(n)] * 3


def test_a_restart_knows_nothing_before_its_restored_watermark():
    a = EpochAssembler(["A", "B", "C"], latency_window_s=0.0, idle_flush_s=2.0,
                       live_late=True)
    a.set_watermarks({"t": 10.0}, {"t": 10.0})
    assert _epochs(a, "t", [4.5, 10.0], wall=0.0).all()  # at or before 10: late
    assert not _epochs(a, "t", [11.0], wall=0.0).any()


def test_a_row_of_an_epoch_still_pending_joins_it():
    """After a restart the store's unsolved rows are pending again, older than their tag's
    newest time: a row of one of those epochs was late, taken for a late epoch never
    solved, and the epoch solved twice (the second fix, from one row, replacing the first
    in /api/positions; the late-epoch review).  It joins its epoch."""
    a = EpochAssembler(["A", "B", "C"], latency_window_s=0.5, idle_flush_s=8.0,
                       live_late=True)
    a.set_watermarks({"t": 10.0}, {})
    _epochs(a, "t", np.arange(11.0, 21.0), wall=0.0)  # put back, not yet taken
    a.set_watermarks({}, {"t": 20.0})
    late = a.add(np.array([12.0]), obj("t"), np.array([0]), np.array([7.0]), wall=1.0)
    assert not late.any()
    r = a.take_ready(1.0)
    assert not r["late"].any() and (r["time"] == 12.0).sum() == 4
    assert a.late_epochs == 0


def test_without_live_late_every_late_row_stays_late():
    a = EpochAssembler(["A", "B", "C"], latency_window_s=0.0, idle_flush_s=2.0)
    _epochs(a, "t", [0.0, 1.0, 2.0], wall=0.0)
    a.take_ready(0.0)
    assert _epochs(a, "t", [0.5], wall=0.0).all()
    assert a.take_ready(100.0)["time"].tolist() == [2.0] * 3  # (idle flush of epoch 2)


def test_late_rows_held_keep_their_tag_and_go_with_a_rebase():
    a = EpochAssembler(["A", "B", "C"], latency_window_s=0.0, idle_flush_s=2.0,
                       time_jump_s=100.0, live_late=True)
    _epochs(a, "t", [500.0, 501.0, 502.0], wall=0.0)
    a.take_ready(0.0)
    _epochs(a, "t", [500.5], wall=1.0)  # a late epoch, held
    assert a.n_pending == 3 + 3  # epoch 502 and the late one
    assert a.idle_tags(1e9).size == 0  # a tag holding late rows is not forgotten
    with pytest.raises(ValueError, match="pending"):
        a.forget(np.array([a.known["t"]]))
    # the device restarted its clock (2 s later, nothing new since): a re-base releases
    # the held late epoch with the tag's earlier run, and its memory restarts
    code = a.codes(obj("t"))
    assert a.rebase(np.array([3.0]), code, wall=3.0).tolist() == code.tolist()
    r = a.take_ready(3.0)
    assert sorted(set(r["time"][r["late"]].tolist())) == [500.5]
    assert sorted(set(r["time"][~r["late"]].tolist())) == [502.0]
    assert not _epochs(a, "t", [3.0, 4.0], wall=3.0).any()


# --------------------------------------------------------------------------------------
# a real server
# --------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def ble(tmp_path_factory):
    import subprocess

    from robustloc.service.launch import ROBUSTLOC

    d = tmp_path_factory.mktemp("ble")
    subprocess.run([*ROBUSTLOC, "simulate", "ble-corridor", "--seed", "1", "--out", str(d)],
                   check=True, capture_output=True, text=True)
    return d


def _rows(ble, tag: str, times) -> list[dict]:
    """The simulated log's epochs of tag S1 at ``times``, as rows of ``tag``."""
    from robustloc.io import read_measurements

    m = read_measurements(ble / "measurements.csv")
    m = m[m["tag"] == "S1"]
    ts = np.sort(m["time"].unique())
    return [{"time": float(t), "tag": tag, "anchor": str(a), "rssi": float(v)}
            for t in ts[list(times)] for a, v in
            zip(m.loc[m["time"] == t, "anchor"], m.loc[m["time"] == t, "rssi"])]


@pytest.mark.parametrize("track", [False, True])
def test_a_late_epoch_gets_its_live_position(ble, server_factory, track):
    """Every row of one epoch arrives after ten later epochs were solved: without
    ``--track`` it is solved all the same (the fix equals that of the same epoch sent in
    order as another tag, to 1e-9 m), stored, published on the WebSocket with ``late``
    true and counted; it is not the tag's latest row.  With ``--track`` (a filter cannot
    go back) its rows are late, stored and counted as before."""
    httpx = pytest.importorskip("httpx")
    from test_service import wait_for  # (tests/ is on the path)
    from websockets.sync.client import connect

    from robustloc.service.launch import read_metric

    srv = server_factory(["--anchors", str(ble / "anchors.csv"), "--latency-window", "0.5",
                          "--idle-flush", "0.3", *(["--track"] if track else [])])
    u = srv.url
    first = _rows(ble, "G", [i for i in range(12) if i != 4])
    assert httpx.post(u + "/api/measurements", json=first).json()["late"] == 0
    late_rows = _rows(ble, "G", [4])
    t_late, t_last = late_rows[0]["time"], first[-1]["time"]

    def positions(tag):
        return httpx.get(u + f"/api/positions?tag={tag}").json()

    wait_for(lambda: len(positions("G")) == 11, what="the eleven epochs sent in order")
    with connect(u.replace("http://", "ws://") + "/ws/positions?tag=G") as sub:
        body = httpx.post(u + "/api/measurements", json=late_rows).json()
        assert body["accepted"] == len(late_rows)
        if track:
            assert body["late"] == len(late_rows)
            assert read_metric(u, "robustloc_rows_late_total") == len(late_rows)
            with pytest.raises(TimeoutError):
                sub.recv(timeout=2.0)
            assert t_late not in [p["time"] for p in positions("G")]
            assert read_metric(u, "robustloc_late_epochs_solved_total") == 0
            return
        assert body["late"] == 0
        msg = json.loads(sub.recv(timeout=30))
    assert msg["time"] == t_late and msg["late"] is True
    got = wait_for(lambda: [p for p in positions("G") if p["time"] == t_late],
                   what="the late epoch stored")
    assert len(got) == 1 and np.isfinite(got[0]["x"]) and "late" not in got[0]
    # the same epoch in order, as another tag: the same fix
    httpx.post(u + "/api/measurements", json=_rows(ble, "H", [4]))
    ref = wait_for(lambda: positions("H"), what="H solved")[0]
    assert (got[0]["x"], got[0]["y"]) == pytest.approx((ref["x"], ref["y"]), abs=1e-9)
    assert got[0]["status"] == ref["status"] and msg["x"] == pytest.approx(ref["x"], abs=1e-9)
    assert read_metric(u, "robustloc_late_epochs_solved_total") == 1
    assert read_metric(u, "robustloc_rows_late_total") == 0
    latest = {r["tag"]: r for r in httpx.get(u + "/api/latest").json()}
    assert latest["G"]["time"] == t_last
    # a row of it again: its epoch is solved now, the row is late
    assert httpx.post(u + "/api/measurements", json=late_rows[:1]).json()["late"] == 1


def test_a_late_epoch_acknowledged_before_a_kill_9_is_solved_after_the_restart(
        ble, server_factory, tmp_path):
    """A late epoch never solved, acknowledged with ``late`` 0, waits for the rest of its
    epoch; killed (SIGKILL) meanwhile, the service restarted without ever solving it: the
    restart took every epoch up to the tag's latest stored position as solved (the serve
    review).  It is solved after the restart, once; nothing else is solved twice."""
    httpx = pytest.importorskip("httpx")
    from test_service import wait_for  # (tests/ is on the path)

    # --idle-flush 1000: the late epoch (and the newest) wait, so the kill comes first
    args = ["--anchors", str(ble / "anchors.csv"), "--latency-window", "0.5",
            "--idle-flush", "1000", "--store", str(tmp_path / "store")]
    srv = server_factory(args)
    u = srv.url
    first = _rows(ble, "G", [i for i in range(12) if i != 4])
    assert httpx.post(u + "/api/measurements", json=first).json()["late"] == 0
    late_rows = _rows(ble, "G", [4])
    t_late = late_rows[0]["time"]

    def times(url):
        return sorted(p["time"] for p in httpx.get(url + "/api/positions?tag=G").json())

    wait_for(lambda: len(times(u)) == 10, what="the epochs before the newest solved")
    body = httpx.post(u + "/api/measurements", json=late_rows).json()
    assert body["accepted"] == len(late_rows) and body["late"] == 0
    srv.kill9()

    srv = server_factory(args)
    got = wait_for(lambda: t_late in times(srv.url) and times(srv.url),
                   what="the late epoch solved after the restart")
    assert got.count(t_late) == 1 and len(got) == len(set(got)) == 11
    srv.stop()  # a graceful stop solves the newest epoch
    srv = server_factory(args)
    # every epoch once, none solved again
    assert times(srv.url) == sorted({r["time"] for r in first + late_rows})


def _check_memory(a: EpochAssembler, solved: dict[int, set[float]], qc, qt) -> None:
    got = a.late_unsolved(qt, qc, np.ones(len(qt), dtype=bool))
    for k, v, g in zip(qc.tolist(), qt.tolist(), got.tolist()):
        top = sorted(solved[k], reverse=True)
        floor = top[RECENT_SOLVED] if len(top) > RECENT_SOLVED else -np.inf
        assert g == (v not in solved[k] and v > floor), (k, v, g, floor)


@settings(max_examples=80, deadline=None)
@given(st.lists(st.tuples(st.lists(st.tuples(st.integers(0, 3), st.integers(0, 200)),
                                   max_size=60),
                          st.booleans()), min_size=1, max_size=20),
       st.lists(st.tuples(st.integers(0, 3), st.integers(0, 210)), min_size=1, max_size=30))
def test_memory_of_solved_epochs_equals_a_reference(batches, queries):
    """The memory (folded lazily, a fast path for one newest time per tag, the general
    sort otherwise) against its definition: a time is an epoch never solved when it is not
    among the tag's solved times and above the (R+1)-th largest of them.  Batches are
    noted and, after some, the memory is read (a fold); the streams of one newest time per
    tag (the fast path) come from the batches' order."""
    a = EpochAssembler(["A"], latency_window_s=0.0, idle_flush_s=1.0, live_late=True)
    a.codes(obj("t0", "t1", "t2", "t3"))
    solved: dict[int, set[float]] = {k: set() for k in range(4)}
    qc = np.array([q[0] for q in queries], dtype=np.int64)
    qt = np.array([q[1] / 2 for q in queries])
    for batch, read in batches:
        if batch:
            c = np.array([b[0] for b in batch], dtype=np.int64)
            t = np.array([b[1] / 2 for b in batch])
            a._remember(t, c)
            for k, v in zip(c.tolist(), t.tolist()):
                solved[k].add(v)
        if read:
            _check_memory(a, solved, qc, qt)
    _check_memory(a, solved, qc, qt)


def test_memory_of_a_live_stream_and_a_burst():
    """The fast path (one newest time per tag and fold), then a burst of more than
    RECENT_SOLVED times of a tag in one fold (its oldest let go at once)."""
    a = EpochAssembler(["A"], latency_window_s=0.0, idle_flush_s=1.0, live_late=True)
    a.codes(obj("t0", "t1"))
    solved: dict[int, set[float]] = {0: set(), 1: set()}
    q = np.arange(0.0, 200.0, 0.5)
    qc0, qc1 = np.zeros(len(q), dtype=np.int64), np.ones(len(q), dtype=np.int64)
    for k in range(60):  # a fold after each release: the fast path
        a._remember(np.array([float(k), float(k)]), np.array([0, 1]))
        solved[0].add(float(k))
        solved[1].add(float(k))
        _check_memory(a, solved, qc0, q)
    a._remember(np.array([61.0, 60.0]), np.array([0, 0]))  # two in a fold: the sort
    solved[0].update([60.0, 61.0])
    _check_memory(a, solved, qc0, q)
    burst = np.arange(100.0, 150.0)  # 50 times of tag 1 in one fold
    a._remember(burst, np.ones(len(burst), dtype=np.int64))
    solved[1].update(burst.tolist())
    _check_memory(a, solved, qc1, q)
    _check_memory(a, solved, qc0, q)


def test_a_time_remembered_twice_takes_one_slot():
    """The falsifying example hypothesis found (2026-12-06): times solved in one fold and
    again in a later one were kept twice, so 15 distinct times filled the 32 slots and an
    earlier, never solved time counted as let go."""
    a = EpochAssembler(["A"], latency_window_s=0.0, idle_flush_s=1.0, live_late=True)
    a.codes(obj("t0"))
    solved: dict[int, set[float]] = {0: set()}
    for n, read in ((9, True), (15, True), (9, False)):
        t = np.arange(1, n + 1) / 2
        a._remember(t, np.zeros(n, dtype=np.int64))
        solved[0] |= set(t.tolist())
        if read:
            _check_memory(a, solved, np.array([0]), np.array([0.0]))
    _check_memory(a, solved, np.array([0]), np.array([0.0]))
