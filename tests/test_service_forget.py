"""A live service forgets the tags that stopped reporting (``serve --forget-after``).

Before, every tag ever heard kept its state for as long as the service ran (and a restart
recovered them all), so a site whose tags come and go reached ``--max-tags`` and then
refused every new tag, for good (*Known limits*, "A live service forgets no tag").  These
tests check what forgetting must keep: the other tags' states exactly (the tracker's
compaction), the store (every row and position stays), no epoch solved twice (a restart
after a forget re-solved a forgotten tag's whole history from a snapshot that no longer
held it), and a returning tag's epochs never taken for solved ones (a new run).
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

pytest.importorskip("starlette")
httpx = pytest.importorskip("httpx")

from robustloc.io.tables import Epochs  # noqa: E402
from robustloc.service.assembly import EpochAssembler  # noqa: E402
from robustloc.service.engine import Engine  # noqa: E402
from robustloc.service.processor import LocateProcessor, TrackProcessor  # noqa: E402
from robustloc.tracking import Tracker  # noqa: E402

ANCHORS = pd.DataFrame({"anchor": ["A1", "A2", "A3", "A4"], "x": [0.0, 10.0, 10.0, 0.0],
                        "y": [0.0, 0.0, 10.0, 10.0]})
XY = ANCHORS[["x", "y"]].to_numpy()


def _ranges(tag: str, times, start=(2.0, 3.0), v=(0.5, 0.2), seed=0) -> list[dict]:
    """Exact-plus-noise ranges of a tag moving at ``v`` from ``start`` (rows of the API)."""
    rng = np.random.default_rng(seed)
    rows = []
    for t in times:
        p = np.asarray(start) + np.asarray(v) * t
        d = np.hypot(*(XY - p).T) + rng.normal(0, 0.05, 4)
        rows += [{"time": float(t), "tag": tag, "anchor": a, "range": float(r)}
                 for a, r in zip(ANCHORS["anchor"], d)]
    return rows


def _engine(processor=None, **kw) -> Engine:
    return Engine(ANCHORS, processor or LocateProcessor(ANCHORS, method="nls"),
                  latency_window_s=0.0, fsync=False, value="range", **kw)


def _stored_positions(store: Path, tag: str) -> pd.DataFrame:
    """Every row of the positions log of ``tag`` (no de-duplication: a re-solved epoch
    shows twice)."""
    import pyarrow.dataset as ds

    from robustloc.service.store import SegmentLog

    log = SegmentLog(store / "positions", 1_000_000, fsync=False)
    try:
        t = log.scan(expression=ds.field("tag") == tag).to_pandas()
    finally:
        log.close()
    return t


# ---------------------------------------------------------------------------------------
# the assembler: codes freed and reused, pending tags never forgotten
# ---------------------------------------------------------------------------------------


def test_assembler_forgets_idle_tags_and_reuses_their_codes():
    a = EpochAssembler(["A1", "A2"], 0.0, 1.0)
    t = np.array([0.0, 0.0, 1.0])
    a.add(t, np.array(["x", "y", "x"], dtype=object), np.array([0, 0, 1]),
          np.ones(3), wall=100.0)
    # both hold pending rows (x's epoch 1.0, y's epoch 0.0): neither may go
    assert a.idle_tags(1e9).size == 0
    with pytest.raises(ValueError, match="pending"):
        a.forget(np.array([0]))
    ready = a.take_ready(wall=1e9)  # idle flush: everything solved
    assert sorted(set(ready["tag"].tolist())) == ["x", "y"]
    assert a.idle_tags(99.0).size == 0  # heard at 100: not silent before it
    codes = a.idle_tags(100.0)
    assert codes.tolist() == [0, 1]
    assert a.forget(codes[:1]) == ["x"]
    assert a.n_tags == 1 and a.tags == ["y"] and "x" not in a.known
    assert a.watermarks() == {"y": 0.0}
    # a new tag takes x's code; x heard again is new (no watermark: its old times pass)
    assert a.codes(np.array(["z", "x"], dtype=object)).tolist() == [0, 2]
    assert not a.late(np.array([0.0]), np.array([2])).any()
    assert a.forget(np.array([2, 2])) == ["x"]  # (a code listed twice: forgotten once)
    with pytest.raises(KeyError, match="free"):
        a.forget(np.array([2]))


def test_late_rows_keep_a_tag_heard():
    """A gateway uploading a tag's old rows (late, stored, not solved) keeps it heard: it
    is not forgotten while its rows still come."""
    a = EpochAssembler(["A1"], 0.0, 1.0)
    a.add(np.array([5.0, 6.0]), np.array(["x", "x"], dtype=object), np.zeros(2, int),
          np.ones(2), wall=0.0)
    a.take_ready(wall=1e9, flush_all=True)
    late = a.add(np.array([1.0]), np.array(["x"], dtype=object), np.zeros(1, int),
                 np.ones(1), wall=500.0)
    assert late.all()
    assert a.idle_tags(499.0).size == 0 and a.idle_tags(500.0).tolist() == [0]


# ---------------------------------------------------------------------------------------
# the tracker: forgetting tags leaves the others' states exactly as they were
# ---------------------------------------------------------------------------------------


def _epochs(rows: list[dict]) -> Epochs:
    from robustloc.io.tables import to_epochs

    df = pd.DataFrame(rows)
    return to_epochs(df.sort_values(["time", "tag"], kind="stable"),
                     list(ANCHORS["anchor"]), "range")


@pytest.mark.parametrize("engine", ["numpy", "compiled"])
def test_tracker_forget_keeps_the_other_tags_exactly(engine):
    """Tags A, B, C tracked for 20 epochs; B forgotten; 20 more epochs of A, B, C.  The
    rows of A and C equal those of a tracker that never forgot (bit for bit: their state
    rows were moved, not recomputed), and B's equal those of a fresh tracker given only
    B's last 20 epochs (it starts afresh)."""
    first = sum((_ranges(g, np.arange(20) * 0.5, seed=k) for k, g in enumerate("ABC")), [])
    second = sum((_ranges(g, 10 + np.arange(20) * 0.5, seed=10 + k)
                  for k, g in enumerate("ABC")), [])
    opts = {"engine": engine}
    kept, forgot = Tracker(ANCHORS, **opts), Tracker(ANCHORS, **opts)
    kept.step(_epochs(first))
    forgot.step(_epochs(first))
    assert forgot.forget(["B", "nobody"]) == 1 and forgot.tags == ["A", "C"]
    a = kept.step(_epochs(second))
    b = forgot.step(_epochs(second))
    fresh = Tracker(ANCHORS, **opts).step(_epochs([r for r in second if r["tag"] == "B"]))
    for tag in "AC":
        pd.testing.assert_frame_equal(a[a["tag"] == tag].reset_index(drop=True),
                                      b[b["tag"] == tag].reset_index(drop=True))
    pd.testing.assert_frame_equal(b[b["tag"] == "B"].reset_index(drop=True),
                                  fresh.reset_index(drop=True))
    assert sorted(forgot.tags) == ["A", "B", "C"]


def test_recording_tracker_refuses_to_forget():
    tr = Tracker(ANCHORS, record=True)
    tr.step(_epochs(_ranges("A", np.arange(5) * 0.5)))
    with pytest.raises(ValueError, match="record"):
        tr.forget(["A"])


# ---------------------------------------------------------------------------------------
# the engine: state dropped, room for new tags, a returning tag's epochs solved again
# ---------------------------------------------------------------------------------------


def test_engine_forgets_silent_tags_and_makes_room_for_new_ones(tmp_path):
    eng = _engine(store_dir=tmp_path / "s", max_tags=2, forget_after_s=3600.0)
    assert eng.ingest(_ranges("a", [0.0, 1.0]) + _ranges("b", [0.0, 1.0])).accepted == 16
    eng.flush()
    assert sorted(eng.latest()["tag"]) == ["a", "b"]
    # the bound reached: a third tag refused
    assert eng.ingest(_ranges("c", [0.0])).accepted == 0
    assert eng.forget_idle(time.time() + 1800.0) == 0  # silent for half an hour only
    assert eng.forget_idle(time.time() + 3601.0) == 2
    assert eng.latest().empty and eng.assembler.n_tags == 0
    assert eng.metrics.tags_forgotten == 2 and eng.metrics.summary()["tags_forgotten"] == 2
    assert "robustloc_tags_forgotten_total 2" in eng.metrics.render(0, 0)
    # room again; and a returning tag whose device restarted its clock (times 0, 1 again):
    # a new tag in a new run, its epochs solved (not taken as late)
    res = eng.ingest(_ranges("c", [0.0, 1.0]) + _ranges("a", [0.0, 1.0], start=(7.0, 7.0)))
    assert res.accepted == 16 and res.late == 0
    eng.flush()
    assert sorted(eng.latest()["tag"]) == ["a", "c"]
    eng.stop()
    pos = _stored_positions(tmp_path / "s", "a")
    assert sorted(zip(pos["run"], pos["time"])) == [(0, 0.0), (0, 1.0), (1, 0.0), (1, 1.0)]
    # both runs' epochs kept by the positions query (two epochs each at times 0 and 1)
    eng2 = _engine(store_dir=tmp_path / "s", forget_after_s=3600.0)
    try:
        got = eng2.positions(tag="a")
        assert len(got) == 4 and np.isclose(got["x"].iloc[-1], 7.5, atol=0.3)
    finally:
        eng2.stop()


def test_pending_and_queued_tags_are_not_forgotten():
    eng = _engine(forget_after_s=10.0)
    eng.ingest(_ranges("a", [0.0, 1.0]))  # epoch 1.0 pending (nothing later of a)
    assert eng.forget_idle(time.time() + 60.0) == 0
    assert eng.assembler.n_tags == 1
    eng.flush()
    assert eng.forget_idle(time.time() + 60.0) == 1


def test_forget_after_must_be_positive():
    for bad in (0.0, -1.0, float("nan"), "7d"):
        with pytest.raises(ValueError, match="forget_after_s"):
            _engine(forget_after_s=bad)
    _engine(forget_after_s=float("inf")).stop()  # never


def test_tracker_engine_forgets_filters_and_restarts_them():
    eng = _engine(TrackProcessor(ANCHORS), forget_after_s=60.0)
    eng.ingest(_ranges("a", np.arange(10) * 0.5) + _ranges("b", np.arange(10) * 0.5))
    eng.flush()
    tracker = eng.processor.tracker
    assert sorted(tracker.tags) == ["a", "b"]
    assert eng.forget_idle(time.time() + 61.0) == 2
    assert tracker.tags == [] and eng._processed == {}
    eng.ingest(_ranges("a", 5 + np.arange(4) * 0.5))
    eng.flush()
    assert tracker.tags == ["a"]


# ---------------------------------------------------------------------------------------
# restarts: silent tags forgotten again, a forgotten tag's epochs never solved twice
# ---------------------------------------------------------------------------------------


def test_restart_forgets_the_stores_silent_tags(tmp_path):
    store = tmp_path / "s"
    eng = _engine(store_dir=store, forget_after_s=0.5)
    eng.ingest(_ranges("a", [0.0, 1.0]))
    eng.flush()
    eng.stop()
    time.sleep(0.6)  # the tag's last row arrived more than forget_after ago
    eng = _engine(store_dir=store, forget_after_s=0.5)
    try:
        assert eng.assembler.n_tags == 0 and eng.latest().empty
        assert eng.metrics.tags_forgotten == 1
        assert len(eng.positions(tag="a")) == 2  # the store keeps it
    finally:
        eng.stop()
    eng = _engine(store_dir=store, forget_after_s=float("inf"))  # never: all recovered
    try:
        assert eng.assembler.n_tags == 1 and eng.latest()["tag"].tolist() == ["a"]
    finally:
        eng.stop()


def _track_a_and_b_then_forget_a(store: Path) -> None:
    """Tags a and b tracked (6 epochs each), then b goes on while a stays silent for
    --forget-after (0.5 s) and is forgotten; the engine stopped (its snapshot holds b's
    filter and watermark only)."""
    eng = _engine(TrackProcessor(ANCHORS), store_dir=store, forget_after_s=0.5,
                  snapshot_s=0.0)
    eng.ingest(_ranges("a", np.arange(6) * 0.5) + _ranges("b", np.arange(6) * 0.5))
    eng.flush()
    time.sleep(0.6)
    eng.ingest(_ranges("b", 3 + np.arange(4) * 0.5))  # b goes on; a is silent
    eng.flush()  # (its pass forgets a)
    assert eng.metrics.tags_forgotten == 1 and eng.processor.tracker.tags == ["b"]
    eng.stop()


def test_restart_after_a_forget_does_not_solve_the_forgotten_tag_again(tmp_path):
    """A tracker's snapshot holds the watermarks of the tags it tracks.  A tag forgotten
    before the snapshot is not in it: the restart took its epochs as never solved and
    tracked its whole stored history again (a month of rows for a tag silent a month).
    Now it takes them as solved up to its stored positions."""
    store = tmp_path / "s"
    _track_a_and_b_then_forget_a(store)
    n_a = len(_stored_positions(store, "a"))
    assert n_a == 6
    eng = _engine(TrackProcessor(ANCHORS), store_dir=store, forget_after_s=0.5)
    try:
        eng.flush()
        assert eng.recovered_rows == 0
        assert eng.processor.tracker.tags == ["b"]
    finally:
        eng.stop()
    assert len(_stored_positions(store, "a")) == n_a


# ---------------------------------------------------------------------------------------
# the real server: --forget-after, the metric, /api/latest and a returning tag
# ---------------------------------------------------------------------------------------


def test_serve_forget_after(tmp_path, server_factory):
    ANCHORS.to_csv(tmp_path / "anchors.csv", index=False)
    s = server_factory(["--anchors", str(tmp_path / "anchors.csv"), "--latency-window", "0",
                        "--idle-flush", "0.2", "--forget-after", "1.5"])
    from test_service import metric, wait_for

    r = httpx.post(s.url + "/api/measurements", json=_ranges("a", [0.0, 1.0]))
    assert r.status_code == 202
    wait_for(lambda: httpx.get(s.url + "/api/latest").json(), what="a's position")
    wait_for(lambda: metric(s.url, "robustloc_tags_forgotten_total") == 1, timeout=10,
             what="a forgotten")
    assert httpx.get(s.url + "/api/latest").json() == []
    assert httpx.get(s.url + "/api/status").json()["tags"] == 0
    assert len(httpx.get(s.url + "/api/positions", params={"tag": "a"}).json()) == 2
    # heard again with its old times: solved again, as a new tag
    r = httpx.post(s.url + "/api/measurements", json=_ranges("a", [0.0, 1.0]))
    assert r.json()["late"] == 0
    wait_for(lambda: httpx.get(s.url + "/api/latest").json(), what="a's new position")


def test_serve_forget_after_option_values(tmp_path):
    import subprocess

    from robustloc.service.launch import ROBUSTLOC

    ANCHORS.to_csv(tmp_path / "anchors.csv", index=False)
    for bad in ("0", "-5", "nan", "soon"):
        p = subprocess.run([*ROBUSTLOC, "serve", "--anchors", str(tmp_path / "anchors.csv"),
                            "--forget-after", bad], capture_output=True, text=True,
                           timeout=60)
        assert p.returncode == 2 and "--forget-after" in p.stderr and "Traceback" not in p.stderr
    from robustloc.commands.serve import _forget_after

    assert _forget_after("never") == float("inf") and _forget_after("86400") == 86400.0


def test_a_tag_forgotten_twice_comes_back_in_a_run_it_never_had(tmp_path):
    """Tags A and X forgotten in one pass, A back (run 1) and forgotten again, a new tag Z,
    then A back once more: A took X's old code, whose run was still the first pass's base
    (1), so A's third visit shared run 1 with its second: its epochs were solved twice in
    one run, the positions query kept one of each, and after a crash acknowledged rows
    below the run's watermark never got a position (the forget review)."""
    store = tmp_path / "s"
    eng = _engine(store_dir=store, forget_after_s=10.0)
    later = lambda: eng.forget_idle(time.time() + 11.0)  # noqa: E731
    eng.ingest(_ranges("A", [0.0, 1.0]) + _ranges("X", [0.0, 1.0]))
    eng.flush()
    assert later() == 2
    eng.ingest(_ranges("A", [0.0, 1.0], start=(5.0, 5.0)))
    eng.flush()
    assert later() == 1
    eng.ingest(_ranges("Z", [0.0, 1.0]))
    eng.ingest(_ranges("A", [0.0, 1.0], start=(7.0, 7.0)))
    eng.flush()
    assert len(eng.positions(tag="A")) == 6
    eng.stop()
    pos = _stored_positions(store, "A")
    assert sorted(zip(pos["run"], pos["time"])) == [
        (0, 0.0), (0, 1.0), (1, 0.0), (1, 1.0), (2, 0.0), (2, 1.0)]


def test_restarts_with_a_longer_forget_after_do_not_solve_a_forgotten_tag_again(tmp_path):
    """A forgotten under --forget-after 0.5 s; a restart with 'never' held it again but
    its next snapshot lacked A's watermark; the restart after that tracked A's whole
    stored history again (the forget review)."""
    store = tmp_path / "s"
    _track_a_and_b_then_forget_a(store)
    for _ in range(2):
        eng = _engine(TrackProcessor(ANCHORS), store_dir=store, forget_after_s=float("inf"))
        try:
            eng.flush()
            assert eng.recovered_rows == 0
        finally:
            eng.stop()
    assert len(_stored_positions(store, "a")) == 6
