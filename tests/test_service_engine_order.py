"""Live service engine: runs of a re-based tag across a restart, epochs solved in time
order under concurrent ingestion, the flush at a graceful stop, and the refusal of a store
whose rows name an anchor the anchors file lost.

Real components throughout: the :class:`~robustloc.service.engine.Engine` with its real
store and solver, and real ``robustloc serve`` processes on free loopback ports (stopped
in ``finally``/fixture teardown).  Every wait is bounded.
"""

from __future__ import annotations

import random
import subprocess
import threading
import time
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

pytest.importorskip("starlette")
pytest.importorskip("uvicorn")
httpx = pytest.importorskip("httpx")

from _waiting import wait_until  # noqa: E402

from robustloc.service.engine import Engine  # noqa: E402
from robustloc.service.launch import ROBUSTLOC, free_port  # noqa: E402
from robustloc.service.processor import LocateProcessor  # noqa: E402
from robustloc.service.store import SegmentLog  # noqa: E402

ANCHORS = pd.DataFrame({"anchor": ["A1", "A2", "A3", "A4", "A5"],
                        "x": [0.0, 10.0, 10.0, 0.0, 5.0], "y": [0.0, 0.0, 10.0, 10.0, 12.0]})


def _rows(times, tag: str = "V", at: tuple[float, float] = (3.0, 4.0),
          anchors: pd.DataFrame = ANCHORS) -> list[dict]:
    """Range rows of ``tag`` at ``at``, one epoch per time, every anchor."""
    xy = anchors[["x", "y"]].to_numpy(float)
    rng = np.hypot(*(xy - np.asarray(at)).T)
    return [{"time": float(t), "tag": tag, "anchor": a, "range": float(r)}
            for t in times for a, r in zip(anchors["anchor"], rng)]


def _engine(store: Path | None, **kw) -> Engine:
    opts = {"latency_window_s": 0.0, "idle_flush_s": 600.0, "fsync": False,
            "value": "range"}
    opts.update(kw)
    return Engine(ANCHORS, LocateProcessor(ANCHORS, method="nls"), store_dir=store, **opts)


@pytest.fixture
def anchors_csv(tmp_path) -> Path:
    p = tmp_path / "anchors.csv"
    ANCHORS.to_csv(p, index=False)
    return p


@pytest.fixture
def servers(server_factory):
    """conftest's ``server_factory``: started servers, stopped at teardown."""
    return server_factory


# --------------------------------------------------------------------------------------
# re-based tags: runs across a restart, and in /api/positions
# --------------------------------------------------------------------------------------


def test_rebased_tag_pending_epochs_are_solved_after_kill9(anchors_csv, servers, tmp_path):
    """A tag's device restarts its clock (re-based); the service is killed while the new
    run's epochs wait.  The restart re-queued only rows newer than the tag's latest stored
    position (the old run's, t = 110): epochs 0..3 never got a row.  Now every epoch of
    both runs has exactly one row, and the new run resumes (its next rows are not late)."""
    store = tmp_path / "store"
    args = ["--anchors", str(anchors_csv), "--store", str(store), "--latency-window", "5",
            "--idle-flush", "1", "--time-jump", "20"]
    s = servers(args)
    httpx.post(s.url + "/api/measurements", json=_rows(range(100, 111)), timeout=30)
    wait_until(lambda: len(httpx.get(s.url + "/api/positions?tag=V").json()) == 11,
              what="the first run solved")
    time.sleep(1.3)  # quiet longer than --idle-flush: the next far row re-bases the tag
    r = httpx.post(s.url + "/api/measurements", json=_rows(range(4)), timeout=30).json()
    assert r["accepted"] == 20 and r["late"] == 0
    s.kill9()  # epochs 0..3 wait for the latency window / the idle flush
    s2 = servers(args)
    u = s2.url
    pos = wait_until(lambda: (p := httpx.get(u + "/api/positions?tag=V").json())
                    and len(p) >= 15 and p, timeout=30, what="the new run's epochs solved")
    assert sorted(p["time"] for p in pos) == [0.0, 1.0, 2.0, 3.0, *map(float, range(100, 111))]
    r = httpx.post(u + "/api/measurements", json=_rows(range(4, 8)), timeout=30).json()
    assert r["late"] == 0  # the tag resumed at its new run (newest 3), not at t = 110
    wait_until(lambda: len(httpx.get(u + "/api/positions?tag=V").json()) == 19, timeout=30,
              what="the resumed run solved")
    s2.stop()
    log = SegmentLog(store / "positions", fsync=False)
    raw = log.scan(columns=["time", "tag"]).to_pandas()
    log.close()
    assert not raw.duplicated().any()  # no epoch solved twice
    assert len(raw) == 19


def test_earlier_run_released_at_a_crash_is_solved_once(tmp_path):
    """The re-base releases the old run's pending epochs (105..110) while the new run's
    wait; a crash before either is solved.  The restart solves both runs' epochs, each
    once (the released ones as they are, the new run's through the assembler)."""
    store = tmp_path / "store"
    eng = _engine(store, latency_window_s=5.0, idle_flush_s=0.2, time_jump_s=20.0)
    eng.ingest(_rows(range(100, 111)))
    assert eng.step() == 5  # 100..104 (older than the newest, 110, by the window)
    time.sleep(0.3)
    assert eng.ingest(_rows(range(4), at=(6.0, 2.0))).late == 0
    assert eng.metrics.tags_rebased == 1
    eng.stop()  # never started: nothing more solved, as at a crash
    eng = _engine(store, latency_window_s=5.0, idle_flush_s=0.2, time_jump_s=20.0)
    try:
        assert eng.recovered_rows == 10 * 5
        eng.flush()
        raw = eng.pos.scan(columns=["time", "tag", "x", "y"]).to_pandas()
        pos = eng.positions()
    finally:
        eng.stop()
    assert sorted(raw["time"]) == [0.0, 1.0, 2.0, 3.0, *map(float, range(100, 111))]
    assert sorted(pos["time"]) == sorted(raw["time"])
    new = raw[raw["time"] < 50]
    np.testing.assert_allclose(new[["x", "y"]].to_numpy(float), [[6.0, 2.0]] * 4, atol=1e-6)


def test_positions_keep_both_runs_of_a_rebased_tag(tmp_path):
    """A device sends t = 0..10, reboots and sends t = 0..16 (elsewhere).  Both runs were
    solved but /api/positions de-duplicated on (time, tag, method) and hid the first; and
    the old run's last epochs (7..10), released by the re-base, were pivoted together with
    the new run's epochs at the same times (one epoch of both runs' rows).  Now every
    epoch of both runs has its own row (28), and the API's rows have no ``run`` column."""
    eng = _engine(None, latency_window_s=3.0, idle_flush_s=0.2, time_jump_s=5.0)
    try:
        eng.ingest(_rows(range(11), at=(3.0, 4.0)))
        eng.step()  # 0..6 solved, 7..10 pending
        time.sleep(0.3)
        eng.ingest(_rows(range(17), at=(7.0, 6.0)))  # re-based: 7..10 released
        eng.step()  # the old 7..10 and the new 0..12, in one step
        eng.flush()
        pos = eng.positions(tag="V")
        solved = sum(eng.metrics.positions.values())
    finally:
        eng.stop()
    assert eng.metrics.tags_rebased == 1 and solved == 28
    assert len(pos) == 28 and "run" not in pos.columns
    n = pos.groupby("time").size()
    assert (n[n.index <= 10] == 2).all() and (n[n.index > 10] == 1).all()
    got = {(round(x, 6), round(y, 6)) for x, y in zip(pos["x"], pos["y"])}
    assert got == {(3.0, 4.0), (7.0, 6.0)}  # no epoch mixes the two runs' rows


# --------------------------------------------------------------------------------------
# order: concurrent ingestion of one tag
# --------------------------------------------------------------------------------------


def test_concurrent_ingest_solves_each_tag_in_time_order():
    """Ready blocks were queued after the ingest lock was released: under concurrent
    ingestion the solver could take a later block of a tag first and publish its epochs
    before earlier ones (a tracker then went back in time).  Four threads ingest one tag;
    the published epochs must never go back in time.  (A row that one thread delays past
    later epochs is a late epoch, solved apart and published with ``late``: those are
    left out of the order, and no epoch is published twice.)"""
    eng = _engine(None, latency_window_s=0.0, idle_flush_s=600.0)
    published: list[np.ndarray] = []
    late: list[np.ndarray] = []
    eng.add_listener(lambda f: (late if "late" in f else published).append(
        f["time"].to_numpy(float)))
    inner = eng.metrics.ingest
    rnd = random.Random(7)

    def ingest_slowly(*a, **kw):  # the work a handler does after the lock (counting)
        time.sleep(rnd.random() * 0.002)
        return inner(*a, **kw)

    eng.metrics.ingest = ingest_slowly
    counter = iter(range(10**9))
    take = threading.Lock()
    stop_at = time.monotonic() + 20.0
    errors: list[BaseException] = []

    def worker() -> None:
        try:
            for _ in range(250):
                if time.monotonic() > stop_at:
                    return
                with take:
                    t = next(counter)
                eng.ingest(_rows([t], tag="T"))
        except BaseException as exc:  # noqa: BLE001 - reported by the test
            errors.append(exc)

    eng.start()
    try:
        threads = [threading.Thread(target=worker, daemon=True) for _ in range(4)]
        for th in threads:
            th.start()
        for th in threads:
            th.join(timeout=60)
        assert not any(th.is_alive() for th in threads)
        eng.flush()
    finally:
        eng.stop()
    assert not errors
    times = np.concatenate(published)
    assert len(times) > 100
    back = int(np.sum(times < np.maximum.accumulate(times)))
    assert back == 0, f"{back} epochs solved after a later epoch of the same tag"
    every = np.concatenate([times, *late])
    assert len(np.unique(every)) == len(every)


# --------------------------------------------------------------------------------------
# graceful stop: pending epochs are solved
# --------------------------------------------------------------------------------------


def test_sigterm_solves_pending_epochs_with_store(anchors_csv, servers, tmp_path):
    """SIGTERM stopped the solver without solving: the last acknowledged epoch (waiting
    for a later one, --idle-flush 600) had no position row at shutdown."""
    store = tmp_path / "store"
    s = servers(["--anchors", str(anchors_csv), "--store", str(store),
                 "--latency-window", "0", "--idle-flush", "600"])
    r = httpx.post(s.url + "/api/measurements", json=_rows(range(10), tag="S"), timeout=30)
    assert r.json()["accepted"] == 50
    wait_until(lambda: len(httpx.get(s.url + "/api/positions").json()) == 9,
              what="the first 9 epochs solved")
    s.stop()  # SIGTERM
    assert s.proc.returncode is not None
    log = SegmentLog(store / "positions", fsync=False)
    times = sorted(log.scan(columns=["time"])["time"].to_pylist())
    log.close()
    assert times == [float(t) for t in range(10)]


def test_stop_solves_pending_epochs_without_store():
    """Without a store the epochs pending at a stop were never solved (no restart brings
    them back): the started engine's stop solves and publishes them."""
    eng = _engine(None, latency_window_s=0.0, idle_flush_s=600.0)
    published: list[pd.DataFrame] = []
    eng.add_listener(published.append)
    eng.start()
    try:
        eng.ingest(_rows(range(10), tag="S"))
        wait_until(lambda: sum(len(f) for f in published) == 9, timeout=30,
                  what="the first 9 epochs published")
    finally:
        eng.stop()
    times = sorted(np.concatenate([f["time"].to_numpy(float) for f in published]))
    assert times == [float(t) for t in range(10)]


# --------------------------------------------------------------------------------------
# a store whose rows name an anchor the anchors file lost
# --------------------------------------------------------------------------------------


def test_store_with_rows_of_a_removed_anchor_is_refused_by_name(anchors_csv, tmp_path):
    """Removing an anchor that the store has rows for made ``serve`` fail with numpy's
    "'list' argument must have no negative elements" (and the rows went into the
    assembler as the last anchor): now ``error: ANCHORS: ... 'A5' ...``, exit 2."""
    store = tmp_path / "store"
    eng = _engine(store, latency_window_s=5.0)
    eng.ingest(_rows([1.0], tag="T"))  # pending at the stop: to be recovered
    eng.stop()
    fewer = tmp_path / "anchors4.csv"
    ANCHORS[ANCHORS["anchor"] != "A5"].to_csv(fewer, index=False)
    p = subprocess.run([*ROBUSTLOC, "serve", "--anchors", str(fewer), "--store", str(store),
                        "--port", str(free_port())], capture_output=True, text=True,
                       timeout=120)
    assert p.returncode == 2, p.stderr
    err = p.stderr.strip().splitlines()[-1]
    assert err.startswith(f"error: {fewer}:"), err
    assert "'A5'" in err and "negative" not in err
    with pytest.raises(ValueError, match=r"anchor 'A5' missing from the anchors file"):
        Engine(ANCHORS.iloc[:4], LocateProcessor(ANCHORS.iloc[:4], method="nls"),
               store_dir=store, fsync=False).stop()  # (stopped if it wrongly opens)


# --------------------------------------------------------------------------------------
# a positions log that cannot be written (disk full), and meta.json likewise
# --------------------------------------------------------------------------------------


def test_positions_the_store_cannot_write_are_published_and_stored_later(tmp_path):
    """A failed append of solved positions (disk full) raised out of the solver: the
    block's rows were neither stored nor published.  Now they are published, kept in
    order, counted, and stored with the next append that succeeds."""
    from robustloc.service.store import StoreWriteError

    store = tmp_path / "store"
    eng = _engine(store)
    published: list[pd.DataFrame] = []
    eng.add_listener(published.append)
    real = eng.pos.append
    fail = {"n": 2}

    def flaky(table):
        if fail["n"]:
            fail["n"] -= 1
            raise StoreWriteError("store write failed: No space left on device",
                                  store / "positions", 28)
        return real(table)

    eng.pos.append = flaky
    try:
        eng.ingest(_rows(range(0, 4), tag="P"))
        eng.step()  # epochs 0..2 (3 waits for a later time): the append fails
        assert sum(len(f) for f in published) == 3
        assert eng.position_store_errors == 1 and eng.positions_not_stored == 3
        eng.ingest(_rows(range(4, 6), tag="P"))
        eng.step()  # fails again: both blocks kept, in order
        assert eng.position_store_errors == 2 and eng.positions_not_stored == 5
        eng.ingest(_rows(range(6, 8), tag="P"))
        eng.step()  # the disk has room again: the backlog first, then the new block
        assert eng.positions_not_stored == 0
        stored = eng.pos.scan(columns=["time"])["time"].to_pylist()
        assert stored == [float(t) for t in range(7)]  # in order, each once
    finally:
        eng.stop()
    times = sorted(np.concatenate([f["time"].to_numpy(float) for f in published]))
    assert times == [float(t) for t in range(7)]  # (epoch 7 waits: never started)


def test_meta_the_store_cannot_write_changes_nothing(tmp_path, monkeypatch):
    """The first rows set the kind of the store's values in meta.json; a failed write
    (disk full) raised a bare OSError (a 500) and left the engine's kind changed.  Now it
    is a StoreWriteError (the service answers 507) and the engine is as before."""
    from robustloc.service.store import StoreWriteError

    store = tmp_path / "store"
    eng = Engine(ANCHORS, LocateProcessor(ANCHORS, method="nls"), store_dir=store,
                 latency_window_s=0.0, idle_flush_s=600.0, fsync=False)
    try:
        assert eng.kind is None
        meta = (store / "meta.json").read_text()
        real_write_text = Path.write_text

        def full(self, *a, **k):
            if self.name == "meta.tmp":
                raise OSError(28, "No space left on device")
            return real_write_text(self, *a, **k)

        monkeypatch.setattr(Path, "write_text", full)
        with pytest.raises(StoreWriteError, match="No space left"):
            eng.ingest(_rows([0.0], tag="M"))
        assert eng.kind is None
        assert (store / "meta.json").read_text() == meta
        assert not (store / "meta.tmp").exists()
        monkeypatch.undo()
        res = eng.ingest(_rows([0.0], tag="M"))
        assert res.accepted == len(ANCHORS) and eng.kind == "range"
    finally:
        eng.stop()
