"""The service's core, independent of the transport: validate -> store -> assemble -> solve.

``Engine.ingest`` (called from HTTP, WebSocket and MQTT handlers, any thread) validates a
batch of rows, appends the accepted ones to the durable store (synced before it returns),
adds them to the :class:`~robustloc.service.assembly.EpochAssembler` and queues the epochs
that became ready.  One solver thread runs the :class:`~robustloc.service.processor.Processor`
on the queued epochs (all queued blocks in one batched call), stores the positions, updates
the metrics and hands the rows to the listeners (the WebSocket hub).

Runs: a tag whose clock jumped is re-based by the assembler (its device restarted, its
times start again, e.g. from 0).  Each re-base starts a new *run* of the tag, numbered 0, 1,
... per tag; the run is stored with every measurement row and every position row (column
``run`` of both logs, int64; rows of a store written before it are run 0).  Two runs of
a tag may hold epochs at the same times: they are two epochs, solved apart (never pivoted
into one) and both kept by :meth:`Engine.positions`.  The column stays in the store: the
rows of the API and the WebSocket have no ``run`` column.

Restart: the positions store gives each (tag, run)'s latest solved epoch; accepted rows
after it (acknowledged, not yet solved at the crash) are put back - the tag's latest run
into the assembler, an earlier run's rows (released by a re-base, not yet solved) straight
into the solver's queue - so every acknowledged row's epoch is solved exactly once.  With
a stateless processor, a not-late epoch at or before that latest time whose (tag, run,
time) has no stored position (a late epoch never solved, acknowledged, then a crash) is
queued too, solved as a late epoch.  A
stateful processor (the tracker) is snapshotted every ``snapshot_s`` seconds with the
per-(tag, run) watermarks it corresponds to; a restart loads the snapshot and re-solves the
epochs after it (positions queries keep the last row of a re-solved epoch).  Without a
snapshot (killed before the first, ``snapshot_s`` after the start) its state is that of no
epoch: a restart re-solves every stored epoch from the first (a tag silent for
``forget_after_s`` excepted: it is forgotten, solved up to its stored positions), so a
resumed replay's tracks equal ``robustloc track`` on the log, as after a snapshot.

Order: the ready blocks are queued for the solver under the ingest lock, in the order the
assembler released them, so the epochs of a (tag, run) are solved in time order whatever
the number of ingest threads (the restart's watermarks rely on it, and so does a tracker).
The one exception, with a stateless processor only: an epoch whose every row came late
(:mod:`robustloc.service.assembly`), solved in a pass of its own after the block's
others, stored, and published with a column ``late`` (true); it is not a tag's latest row
nor a watermark (the stored positions' watermark is each tag's latest time, not its last
row).

Forgetting: a tag with no accepted row for ``forget_after_s`` seconds of wall time (and
no epoch pending) is forgotten: its assembly watermarks, its run, its processor state
(the tracker's filter), its watermark and its row of :meth:`Engine.latest` go; its stored
rows stay (``GET /api/positions?tag=``).  Heard again, it is a new tag: a new run (above
every run of the forgotten tags, so its epochs are never taken for solved ones), and a
tracker starts it afresh.  A restart forgets again the tags of the store silent that long
(their last row's arrival tells), and takes their epochs as solved up to their stored
positions, not from a snapshot that no longer holds them.

Stop: :meth:`Engine.stop` solves every pending epoch before it closes the store, so every
acknowledged epoch has a position row at a graceful shutdown (with or without a store).
"""

from __future__ import annotations

import contextlib
import json
import math
import os
import pickle
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.dataset as ds

from robustloc.io.tables import Epochs
from robustloc.service.assembly import EpochAssembler
from robustloc.service.defaults import (
    DEFAULT_FORGET_AFTER_S,
    DEFAULT_IDLE_FLUSH_S,
    DEFAULT_LATENCY_WINDOW_S,
    DEFAULT_MAX_TAGS,
    DEFAULT_TIME_JUMP_S,
    MAX_REJECTED_LISTED,
)
from robustloc.service.metrics import Metrics
from robustloc.service.processor import Processor
from robustloc.service.rows import RowBatch, RowDecoder, validate_rows
from robustloc.service.store import SegmentLog, StoreWriteError, scan_table
from robustloc.status import SOLVER_ERROR

MEAS_SCHEMA = pa.schema([
    ("time", pa.float64()), ("tag", pa.string()), ("anchor", pa.string()),
    ("value", pa.float64()), ("arrival", pa.float64()), ("late", pa.bool_()),
    ("source", pa.string()), ("run", pa.int64()),
])


class _MemoryLog:
    """In-memory stand-in for :class:`SegmentLog` when the service runs without --store."""

    def __init__(self, tables: list[pa.Table] | None = None) -> None:
        self._tables: list[pa.Table] = [] if tables is None else tables
        self._lock = threading.Lock()

    def append(self, table: pa.Table) -> None:
        if table.num_rows:
            with self._lock:
                self._tables.append(table)

    def snapshot(self) -> _MemoryLog:
        """The rows held now, as :meth:`robustloc.service.store.SegmentLog.snapshot`."""
        with self._lock:
            return _MemoryLog(list(self._tables))

    def schemas(self) -> list[pa.Schema]:
        """The schema of each table held (not unified)."""
        with self._lock:
            return [t.schema for t in self._tables]

    def scan(self, columns: list[str] | None = None,
             expression: ds.Expression | None = None) -> pa.Table:
        with self._lock:
            tables = list(self._tables)
        if not tables:
            return pa.table({})
        # (the columns asked for and the expression's only: filtering every column
        # first copied them all for the rows kept, as the store's unsealed rows did)
        return scan_table(pa.concat_tables(tables, promote_options="default"), columns,
                          expression)

    def close(self) -> None:
        return None

    def wait_sealed(self) -> None:
        return None


class IngestResult:
    """Outcome of one ingested body: rows accepted, and ``(index, error)`` per rejected row."""

    __slots__ = ("accepted", "rejected", "late")

    def __init__(self, accepted: int, rejected: list[tuple[int, str]], late: int) -> None:
        self.accepted = accepted
        self.rejected = rejected
        self.late = late

    def to_json(self) -> dict:
        """``{"accepted", "rejected": [{"index", "error"}], "n_rejected", "late"}``: the
        first :data:`~robustloc.service.defaults.MAX_REJECTED_LISTED` rejected rows are
        listed (a reply stays small whatever the body), ``n_rejected`` counts them all;
        ``late`` counts the accepted rows whose epoch was already solved, or may have
        been (stored, not solved again; :mod:`robustloc.service.assembly`)."""
        return {"accepted": self.accepted,
                "rejected": [{"index": i, "error": e}
                             for i, e in self.rejected[:MAX_REJECTED_LISTED]],
                "n_rejected": len(self.rejected), "late": self.late}


def _run_key(key: object) -> tuple[str, int]:
    """A snapshot's watermark key as ``(tag, run)`` (a snapshot of an earlier version is
    keyed by tag alone: its run 0)."""
    if isinstance(key, tuple):
        return str(key[0]), int(key[1])
    return str(key), 0


def _runs_of(table: pa.Table) -> np.ndarray:
    """The ``run`` column of a stored table as int64 (0 where missing: rows of a store
    written before runs were stored)."""
    if "run" not in table.column_names:
        return np.zeros(table.num_rows, dtype=np.int64)
    return table["run"].to_pandas().fillna(0).to_numpy(np.int64)


def _answered_rows(keys: pd.DataFrame, runs: np.ndarray, limit: int
                   ) -> tuple[np.ndarray, int]:
    """Which stored rows a positions query answers, from their key columns.

    Parameters
    ----------
    keys : DataFrame
        The matching rows' ``time``, ``tag`` (and ``method``), in the log's order, with
        a default index.
    runs : ndarray
        Their runs (:func:`_runs_of`).
    limit : int
        Most rows answered (the latest).

    Returns
    -------
    rows : ndarray
        Positions in ``keys`` of the rows answered, sorted by time then tag: an epoch
        re-solved after a restart gives its last row; two runs of a re-based tag at the
        same time are two epochs, both kept.
    total : int
        Rows that match, each epoch once (before ``limit``).
    """
    by = [c for c in ("time", "tag", "method") if c in keys.columns]
    dup = pd.DataFrame({"run": runs, **{c: keys[c] for c in by}}).duplicated(keep="last")
    kept = keys.loc[~dup.to_numpy(), ["time", "tag"]].sort_values(["time", "tag"],
                                                                    kind="stable")
    return kept.index.to_numpy(np.int64)[-limit:], len(kept)


def _latest_rows(table: pa.Table, limit: int) -> tuple[pd.DataFrame, int]:
    """:meth:`Engine.positions_counted` from every column of every matching row."""
    rows, total = _answered_rows(table.select(
        [c for c in ("time", "tag", "method") if c in table.column_names]).to_pandas(),
        _runs_of(table), limit)
    df = table.to_pandas().drop(columns="run", errors="ignore")
    return df.iloc[rows].reset_index(drop=True), total


#: The columns of a tag's last fix (:meth:`Engine.latest_with_fixes`).
_FIX_COLUMNS = ("tag", "time", "x", "y", "status", "solved_at")


def _latest_by_run(table: pa.Table) -> dict[tuple[str, int], float]:
    """``{(tag, run): latest time}`` of stored rows (columns ``time, tag[, run]``)."""
    if table.num_rows == 0:
        return {}
    df = pd.DataFrame({"tag": table["tag"].to_pandas(), "run": _runs_of(table),
                       "time": table["time"].to_pandas()})
    g = df.groupby(["tag", "run"], sort=False)["time"].max()
    return {(str(k[0]), int(k[1])): float(v) for k, v in g.items()}


def _subset(epochs: Epochs, rows: np.ndarray) -> Epochs:
    """The epochs ``rows`` of ``epochs`` (same anchors and value)."""
    return Epochs(epochs.time[rows], epochs.tag[rows], epochs.values[rows],
                  epochs.anchor_ids, epochs.value, epochs.line[rows], 0,
                  None if epochs.n_invalid is None else epochs.n_invalid[rows])


def _epoch_rows(t: np.ndarray, code: np.ndarray, et: np.ndarray, ecode: np.ndarray
                ) -> np.ndarray:
    """Index of a row of each epoch ``(et, ecode)`` among the rows ``(t, code)`` (times
    compared exactly, as :func:`robustloc.io.tables.to_epochs` groups them)."""
    tc, tu = pd.factorize(np.concatenate([t, et]))
    key = tc.astype(np.int64) * (int(max(code.max(initial=0), ecode.max(initial=0))) + 1)
    key += np.concatenate([code, ecode])
    rk, ek = key[: len(t)], key[len(t):]
    order = np.argsort(rk, kind="stable")
    return order[np.searchsorted(rk[order], ek)]


class Engine:
    """Validate, store, assemble and solve live measurement rows.

    Parameters
    ----------
    anchors : DataFrame
        From :func:`robustloc.io.read_anchors`.
    processor : Processor
        What to do with ready epochs (locate or track).
    store_dir : path, optional
        Durable store (``measurements/``, ``positions/``, ``state/``); in memory when None.
    latency_window_s, idle_flush_s, time_jump_s : float
        See :mod:`robustloc.service.assembly`.
    value : {"rssi", "range"}, optional
        The value located; default: fixed by the first accepted row (and kept in the store).
    seal_rows : int
        Rows per write-ahead log before it becomes a Parquet segment.
    fsync : bool
        Sync each append (only tests of throw-away stores turn it off).
    snapshot_s : float
        Seconds between snapshots of a stateful processor.
    max_tags : int
        Most tags held (:data:`~robustloc.service.defaults.DEFAULT_MAX_TAGS`): the rows of
        a new tag beyond it are rejected with their reason (the tags a restart recovers
        from the store count, and are never refused).
    forget_after_s : float
        Wall-clock seconds without an accepted row after which a tag is forgotten (module
        doc; :data:`~robustloc.service.defaults.DEFAULT_FORGET_AFTER_S`); ``inf``: never.
    """

    def __init__(
        self, anchors: pd.DataFrame, processor: Processor, *,
        store_dir: str | os.PathLike | None = None,
        latency_window_s: float = DEFAULT_LATENCY_WINDOW_S,
        idle_flush_s: float = DEFAULT_IDLE_FLUSH_S,
        time_jump_s: float = DEFAULT_TIME_JUMP_S,
        value: str | None = None, seal_rows: int = 1_000_000, fsync: bool = True,
        snapshot_s: float = 10.0, max_tags: int = DEFAULT_MAX_TAGS,
        forget_after_s: float = DEFAULT_FORGET_AFTER_S,
    ) -> None:
        if not (isinstance(max_tags, int) and max_tags >= 1):
            raise ValueError(f"max_tags must be a whole number >= 1, got {max_tags!r}")
        if not (isinstance(forget_after_s, int | float) and forget_after_s > 0):
            raise ValueError(f"forget_after_s must be > 0 (inf: never), got {forget_after_s!r}")
        self.max_tags = max_tags
        self.forget_after_s = float(forget_after_s)
        #: wall-clock seconds between passes that forget silent tags
        self._forget_every = min(60.0, self.forget_after_s / 4)
        self._last_forget = -math.inf
        #: the run a new tag starts in: above every run of a forgotten tag (module doc)
        self._run_base = 0
        self.anchors = anchors
        self.anchor_ids = [str(a) for a in anchors["anchor"]]
        self._anchor_index = pd.Index(self.anchor_ids, dtype=object)
        self._anchor_arrow = pa.array(self.anchor_ids, pa.string())
        self.decoder = RowDecoder(self.anchor_ids)
        self.processor = processor
        #: the values the processor can locate (RSSI needs the anchors' path loss): a row
        #: of another value is rejected, and never fixes the service's value
        self.values: tuple[str, ...] = tuple(getattr(processor, "values", ("rssi", "range")))
        if value is not None and value not in self.values:
            raise ValueError(f"cannot locate from {value}: the anchors have no path-loss "
                             "parameters (columns A, n; run `robustloc calibrate`)")
        self.kind = value
        # (the epochs whose every row arrives late are solved by a stateless processor:
        # a filter cannot go back in time; robustloc.service.assembly)
        self.assembler = EpochAssembler(self.anchor_ids, latency_window_s, idle_flush_s,
                                        time_jump_s,
                                        live_late=getattr(processor, "stateless", False))
        self.metrics = Metrics(self.anchor_ids)
        self.store_dir = None if store_dir is None else Path(store_dir)
        self.snapshot_s = snapshot_s
        self._ingest_lock = threading.Lock()
        self._solve_lock = threading.Lock()
        self._cv = threading.Condition()
        self._queue: list[tuple[dict, float]] = []
        self._listeners: list[Callable[[pd.DataFrame], None]] = []
        self._latest_frames: list[pd.DataFrame] = []
        #: each tag's latest row with a position (:meth:`latest_with_fixes`), as
        #: ``_latest_frames`` (seeded from the store at a restart for the tags whose
        #: latest row has no position: :meth:`_seed_fixes`)
        self._fix_frames: list[pd.DataFrame] = []
        self._latest_lock = threading.Lock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.solver_errors = 0
        self.last_error: str | None = None
        #: snapshots of the processor's state that could not be written (disk full): the
        #: rows are in the store, and a restart replays them from the last snapshot
        self.snapshot_errors = 0
        self.last_snapshot_error: str | None = None
        #: per (tag, run), the latest epoch time the processor has processed (its state's
        #: watermark, saved with a snapshot)
        self._processed: dict[tuple[str, int], float] = {}
        #: each tag's current run, by the assembler's tag code (grown on demand; written
        #: under the ingest lock)
        self._run_arr = np.zeros(0, dtype=np.int64)
        self._last_snapshot = time.monotonic()
        self.recovered_rows = 0
        #: position tables solved but not yet in the positions log (its append failed:
        #: disk full), stored in order before the next ones (:meth:`_store_positions`)
        self._pos_backlog: list[pa.Table] = []
        #: failed appends of the positions log
        self.position_store_errors = 0
        if self.store_dir is None:
            self.meas: SegmentLog | _MemoryLog = _MemoryLog()
            self.pos: SegmentLog | _MemoryLog = _MemoryLog()
        else:
            self.store_dir.mkdir(parents=True, exist_ok=True)
            self.meas = SegmentLog(self.store_dir / "measurements", seal_rows, fsync)
            # positions are not synced per block: they are recomputable from the synced
            # measurements, and a restart re-solves every epoch after the last stored
            # position of its tag, so a position lost in a crash comes back (the sync
            # would sit in the latency path of every published position)
            try:
                self.pos = SegmentLog(self.store_dir / "positions", seal_rows, fsync=False,
                                      refuse_damage=False)
            except BaseException:  # (a damaged positions segment): the first log released
                self.meas.close()
                raise
            try:
                self._recover()
            except BaseException:  # a refused store: its logs closed, their sealing done
                self.meas.close()
                self.pos.close()
                raise
            self._write_meta()  # the kind of rows from the start (and the value if known)
            self._forget_idle(time.time())  # the store's tags silent for long: forgotten

    # -- persistence ---------------------------------------------------------------------
    def _meta_path(self) -> Path:
        assert self.store_dir is not None  # noqa: S101 - internal invariant
        return self.store_dir / "meta.json"

    def _write_meta(self, kind: str | None = None) -> None:
        """Write ``meta.json`` (atomically) with the kind of rows ``kind`` (default the
        engine's).

        Raises
        ------
        StoreWriteError
            The file could not be written (disk full): the old one stays.
        """
        if self.store_dir is None:
            return
        p = self._meta_path()
        tmp = p.with_suffix(".tmp")
        try:
            tmp.write_text(json.dumps({"value": self.kind if kind is None else kind,
                                       "anchors": self.anchor_ids,
                                       "rows": self._rows_kind()}))
            with open(tmp, "rb") as f:
                os.fsync(f.fileno())
            os.replace(tmp, p)
        except OSError as exc:
            with contextlib.suppress(OSError):
                tmp.unlink(missing_ok=True)
            raise StoreWriteError(f"store write failed: {exc.strerror or exc}", p,
                                  exc.errno) from None

    def _rows_kind(self) -> str:
        """``"locate"`` (position rows) or ``"track"`` (track rows, with a per-tag state)."""
        return "locate" if getattr(self.processor, "stateless", False) else "track"

    def _check_rows_kind(self, stored: str | None) -> None:
        """Refuse a store of the other kind of rows: a tracker started on a store of
        position rows (or the reverse) mixed two formats in one positions log (the track
        rows lost their velocity and covariance columns to the earlier rows' schema)."""
        if stored is None:  # a store of an earlier version: its rows tell
            cols = self.pos.scan(columns=["vx"]).column_names
            stored = "track" if "vx" in cols else None
        mine = self._rows_kind()
        if stored is not None and stored != mine:
            flag = "with --track" if stored == "track" else "without --track"
            raise ValueError(f"the store {self.store_dir} holds {stored} rows: start the "
                             f"service {flag}, or give another --store")

    def _recover(self) -> None:
        meta = self._meta_path()
        stored_rows = None
        if meta.exists():
            saved = json.loads(meta.read_text())
            stored_rows = saved.get("rows")
            stored = saved.get("value")
            if self.kind is not None and stored is not None and stored != self.kind:
                raise ValueError(f"the store holds {stored} measurements, not {self.kind}")
            self.kind = self.kind or stored
            if self.kind is not None and self.kind not in self.values:
                raise ValueError(f"the store holds {self.kind} measurements, which these "
                                 "anchors cannot locate (no path-loss parameters: columns "
                                 "A, n; run `robustloc calibrate`)")
        self._check_rows_kind(stored_rows)
        stored_pos = self.pos.scan(columns=["time", "tag", "run"])
        stored_solved = _latest_by_run(stored_pos)
        self._seed_latest(stored_solved)
        snap = self.store_dir / "state" / "processor.pkl" if self.store_dir else None
        snap_forget, snap_at = math.inf, math.nan
        if getattr(self.processor, "stateless", False):
            solved = stored_solved
        else:
            # a stateful processor (the tracker) without a snapshot (killed before its
            # first one): its state is that of no epoch, so every stored row is solved
            # again from the first, as ``robustloc track`` solves the log.  Taking the
            # stored positions as solved left the filters empty: a replay resumed after
            # ``kill -9`` restarted every tag (62-98 of 900 rows off by up to 2.45 m, the
            # serve review).  A tag silent for ``forget_after`` now would be forgotten at
            # once: solved up to its stored positions (the snapshot's rule below)
            solved = {}
            snap_forget, snap_at = self.forget_after_s, time.time()
        if snap is not None and snap.exists():
            with open(snap, "rb") as f:
                saved = pickle.load(f)  # noqa: S301 - our own file in the store
            self.processor.load_state_dict(saved["state"])
            solved = {_run_key(k): float(v) for k, v in saved["watermarks"].items()}
            self._processed = dict(solved)
            snap_forget = float(saved.get("forget_after", math.inf))
            snap_at = float(saved.get("saved_at", math.nan))
        meas = self.meas.scan(columns=["time", "tag", "anchor", "value", "late", "run",
                                       "arrival"])
        if meas.num_rows == 0:
            return
        self._check_anchors(meas)
        df = meas.select(["time", "tag", "anchor", "value", "late", "arrival"]).to_pandas()
        df["run"] = _runs_of(meas)
        # each tag's current run: the latest re-base the stored rows tell (late rows too)
        current = df.groupby("tag", sort=False)["run"].max()
        a = self.assembler
        codes = a.codes(current.index.to_numpy(object))
        self._runs_for(codes)[codes] = current.to_numpy(np.int64)
        a.set_heard(df.groupby("tag", sort=False)["arrival"].max().to_dict())
        if math.isfinite(snap_forget):
            # a (tag, run) the snapshot lacks, silent for forget_after when it was taken,
            # had been forgotten: solved up to its stored positions (not all re-solved)
            arrived = df.groupby(["tag", "run"], sort=False)["arrival"].max()
            for (tag, run), t in arrived.items():
                key = (str(tag), int(run))
                if key not in solved and key in stored_solved and t <= snap_at - snap_forget:
                    solved[key] = stored_solved[key]
                    # (and in the next snapshot: a restart after a restart with a longer
                    # --forget-after re-solved the tag's whole history, the forget review)
                    self._processed[key] = stored_solved[key]
        df = df[~df["late"].to_numpy(bool)]
        if solved:
            sol = (pd.Series(list(solved.values()), index=pd.MultiIndex.from_tuples(list(solved)))
                   .reindex(pd.MultiIndex.from_arrays([df["tag"], df["run"]]))
                   .to_numpy(float))
            sol = np.where(np.isnan(sol), -np.inf, sol)
        else:
            sol = np.full(len(df), -np.inf)
        above = df["time"].to_numpy(float) > sol
        # a stateless processor solves a late epoch never solved (assembly's live_late)
        # below its tag's latest solved time: the latest stored position is not a
        # watermark of what was solved, and such an epoch acknowledged but killed (-9)
        # before its solve had no position after the restart (the serve review).  The
        # exact rule: an epoch below it is unsolved when no stored position has its
        # (tag, run, time); it is solved at once, late, as it would have been
        gap = (self._unsolved_below(df[~above], stored_pos)
               if getattr(self.processor, "stateless", False) else df.iloc[:0])
        todo = df[above]
        is_cur = (todo["run"].to_numpy(np.int64)
                  == todo["tag"].map(current).to_numpy(np.int64))
        cur, old = todo[is_cur], todo[~is_cur]
        live = df[df["run"].to_numpy(np.int64) == df["tag"].map(current).to_numpy(np.int64)]
        # the tags' latest runs resume in the assembler (their solved and newest times)
        a.set_watermarks({tag: solved[(tag, int(r))] for tag, r in current.items()
                          if (tag, int(r)) in solved}, {})
        # put back the acknowledged rows whose epochs were not solved before the restart
        if len(cur):
            col = self._anchor_index.get_indexer(cur["anchor"].to_numpy(object))
            a.add(cur["time"].to_numpy(float), cur["tag"].to_numpy(object),
                  col.astype(np.int64), cur["value"].to_numpy(float), time.time())
        a.set_watermarks({}, live.groupby("tag")["time"].max().to_dict())
        # an earlier run's unsolved rows were released by its re-base: solved as they are
        if len(old):
            self._queue.append((self._solver_block(old), time.time()))
        if len(gap):  # (solved as the late epochs they were)
            self._queue.append((self._solver_block(gap, late=True), time.time()))
        self.recovered_rows = len(todo) + len(gap)
        heard = np.bincount(self._anchor_index.get_indexer(df["anchor"].to_numpy(object)),
                            minlength=len(self.anchor_ids))
        self.metrics.heard += heard

    def _solver_block(self, rows: pd.DataFrame, late: bool = False) -> dict:
        """Stored measurement rows as a block of the solver's queue (the assembler's
        release format), ``late`` marking them all as late epochs."""
        tags = rows["tag"].to_numpy(object)
        block = {"time": rows["time"].to_numpy(float), "tag": tags,
                 "tag_code": self.assembler.codes(tags),
                 "anchor_col": self._anchor_index.get_indexer(
                     rows["anchor"].to_numpy(object)).astype(np.int64),
                 "value": rows["value"].to_numpy(float),
                 "run": rows["run"].to_numpy(np.int64)}
        if late:
            block["late"] = np.ones(len(rows), dtype=bool)
        return block

    @staticmethod
    def _unsolved_below(rows: pd.DataFrame, positions: pa.Table) -> pd.DataFrame:
        """The stored rows (columns ``time, tag, run, ...``) whose epoch ``(tag, run,
        time)`` has no stored position (times compared exactly, as epochs are formed).

        Parameters
        ----------
        rows : pandas.DataFrame
            Not-late measurement rows at or below their (tag, run)'s latest stored
            position time.
        positions : pyarrow.Table
            The stored positions' ``time, tag[, run]`` columns.

        Returns
        -------
        pandas.DataFrame
            The subset of ``rows`` never solved.
        """
        if not len(rows):
            return rows
        if positions.num_rows == 0:
            return rows
        have = pd.MultiIndex.from_arrays([positions["tag"].to_pandas().astype(object),
                                          _runs_of(positions),
                                          positions["time"].to_numpy()])
        keys = pd.MultiIndex.from_arrays([rows["tag"].astype(object).to_numpy(),
                                          rows["run"].to_numpy(np.int64),
                                          rows["time"].to_numpy(float)])
        return rows[~keys.isin(have)]

    def _check_anchors(self, meas: pa.Table) -> None:
        """Refuse a store with rows of anchors the anchors file lacks (an anchor removed
        from the file): its rows could not be assembled (nor counted per anchor).

        Raises
        ------
        ValueError
            Naming the missing anchor ids and the store (``robustloc serve`` prefixes
            the anchors file: ``error: ANCHORS: anchor 'A5' missing ...``, exit 2).
        """
        stored = meas["anchor"].unique().drop_null().to_pylist()
        known = set(self.anchor_ids)
        missing = sorted({str(x) for x in stored} - known)
        if not missing:
            return
        listed = ", ".join(repr(m) for m in missing[:20])
        more = f" and {len(missing) - 20} more" if len(missing) > 20 else ""
        it = "them" if len(missing) > 1 else "it"
        # (not "the store ...": `robustloc serve` names the anchors file of such an error)
        raise ValueError(
            f"anchor{'s' if len(missing) > 1 else ''} {listed}{more} missing from the "
            f"anchors file: the store {self.store_dir} holds measurements of {it}; add {it} "
            "back to the anchors file, or give another --store")

    def _seed_latest(self, solved: dict[tuple[str, int], float]) -> None:
        """``/api/latest`` after a restart: each tag's latest stored row (of its latest
        run; it was empty until new rows came, and the map page started blank).  Only
        the rows at one of the tags' latest times are read (not everything since the
        oldest of them: a tag silent for a month made a restart read a month of rows)."""
        if not solved:
            return
        last: dict[str, tuple[int, float]] = {}
        for (tag, run), t in solved.items():
            if tag not in last or run > last[tag][0]:
                last[tag] = (run, t)
        times = sorted({t for _, t in last.values()})
        table = self.pos.scan(expression=ds.field("time").isin(times))
        runs = _runs_of(table)
        df = table.to_pandas()
        want = df["tag"].map(last)
        keep = np.array([w == (r, t) for w, r, t in
                         zip(want.tolist(), runs.tolist(), df["time"].tolist())], dtype=bool)
        df = df.loc[keep].drop(columns="run", errors="ignore")
        self._latest_frames = [df.drop_duplicates("tag", keep="last")
                               .sort_values("tag", kind="stable").reset_index(drop=True)]
        self._seed_fixes(self._latest_frames[0], last)

    def _seed_fixes(self, latest: pd.DataFrame, last: dict[str, tuple[int, float]]) -> None:
        """The last fix of each tag whose latest stored row has none (of its latest run),
        for :meth:`latest_with_fixes` after a restart: the map page drew such a tag
        hollow at its last fix until the restart, and "no fix yet" after it.  Only those
        tags' rows with a position are read."""
        if not {"x", "y"} <= set(latest.columns) or not len(latest):
            return
        nofix = ~(np.isfinite(latest["x"].to_numpy(float))
                  & np.isfinite(latest["y"].to_numpy(float)))
        if not nofix.any():
            return
        tags = latest.loc[nofix, "tag"].astype(str).tolist()
        table = self.pos.scan(
            columns=[*_FIX_COLUMNS, "run"],
            expression=ds.field("tag").isin(tags) & ~ds.field("x").is_nan()
            & ~ds.field("y").is_nan() & ds.field("x").is_valid() & ds.field("y").is_valid())
        if table.num_rows == 0:
            return
        runs = _runs_of(table)
        df = table.to_pandas().drop(columns="run", errors="ignore")
        want_run = df["tag"].map({t: r for t, (r, _) in last.items()}).to_numpy()
        df = df.loc[runs == want_run]
        if len(df):
            self._fix_frames = [df.sort_values("time", kind="stable")
                                .drop_duplicates("tag", keep="last").reset_index(drop=True)]

    def _snapshot(self) -> None:
        state = self.processor.state_dict()
        if self.store_dir is None or not state:
            return
        d = self.store_dir / "state"
        tmp = d / "processor.pkl.tmp"
        try:
            d.mkdir(exist_ok=True)
            with open(tmp, "wb") as f:
                # the state's watermarks are the epochs the processor has processed, not
                # the assembler's (which also count blocks queued meanwhile by the ingest
                # threads: a restart would then skip them, and a tracker would never give
                # them a row) (with the forgetting rule it was taken under: a restart
                # tells the tags it lacks because they were forgotten, see _recover)
                pickle.dump({"state": state, "watermarks": dict(self._processed),
                             "saved_at": time.time(), "forget_after": self.forget_after_s},
                            f)
                f.flush()
                os.fsync(f.fileno())
            os.replace(tmp, d / "processor.pkl")
        except OSError as exc:
            # a full disk at a snapshot (or at the stop's) raised out of the solver loop,
            # counted as a solver error, and at a stop left the store unclosed with a
            # traceback (the service review).  The previous snapshot stays; the rows are
            # in the store, and a restart replays them from it
            with contextlib.suppress(OSError):
                tmp.unlink()
            from robustloc.io.atomic import describe_oserror

            first = self.last_snapshot_error is None
            self.snapshot_errors += 1
            self.last_snapshot_error = describe_oserror(exc)
            if first:
                print(f"warning: {tmp.parent / 'processor.pkl'}: the state's snapshot was "
                      f"not written ({self.last_snapshot_error}); a restart replays the "
                      "stored rows since the previous one", file=sys.stderr, flush=True)
            return
        self.last_snapshot_error = None

    # -- ingest --------------------------------------------------------------------------
    def decode(self, body: bytes | str) -> RowBatch | None:
        """The rows of a body that is a JSON array of regular, valid rows (the common
        case, decoded in one pass), else None: then :func:`~robustloc.service.rows.parse_body`
        and :meth:`ingest` validate it row by row."""
        return self.decoder.decode(body, self.kind)

    def ingest(self, rows: list[Any], source: str = "http") -> IngestResult:
        """Validate and durably store rows; returns what was accepted and rejected.

        Thread-safe.  When it returns, the accepted rows are on disk (with a store).
        """
        with self._ingest_lock:
            kind0 = self.kind
            batch, kind, rejected = validate_rows(rows, self._anchor_index, self.kind,
                                                  self.values)
            if len(batch):
                batch, over = self._within_max_tags(batch, rejected)
                if over:
                    rejected = sorted(rejected + over)
            # the kind is fixed by a row accepted (none refused for --max-tags either); the
            # store's metadata first: a failed write changes nothing
            if kind != kind0 and len(batch):
                self._write_meta(kind)
                self.kind = kind
            n_late, wall = self._accept(batch, source)
        rej_cols = self._rejected_anchor_cols(rows, rejected)
        return self._finish(batch, rejected, rej_cols, n_late, wall, source)

    def ingest_batch(self, batch: RowBatch, source: str = "http") -> IngestResult:
        """Durably store rows already validated by :meth:`decode` (all accepted).

        Thread-safe.  When it returns, the rows are on disk (with a store).
        """
        with self._ingest_lock:
            batch, over = self._within_max_tags(batch, [])
            n_late, wall = self._accept(batch, source)
        return self._finish(batch, over, np.zeros(0, dtype=np.int64), n_late, wall, source)

    def _within_max_tags(self, batch: RowBatch, rejected: list[tuple[int, str]]
                         ) -> tuple[RowBatch, list[tuple[int, str]]]:
        """``batch`` without the rows of new tags beyond :attr:`max_tags` (new tags taken
        in order of appearance while there is room), and those rows as ``(index, reason)``
        with ``index`` their place in the body, whose ``rejected`` rows are not in
        ``batch`` (caller holds the ingest lock)."""
        known = self.assembler.known
        room = self.max_tags - len(known)
        tags = pd.unique(batch.tag)
        if len(tags) <= room:  # (the usual case: no look-up at all)
            return batch, []
        new = [t for t in tags.tolist() if t not in known]
        if len(new) <= room:
            return batch, []
        # the batch's rows' places in the body: the body's rows without the rejected ones
        index = np.delete(np.arange(len(batch) + len(rejected)),
                          np.array([i for i, _ in rejected], dtype=np.int64))
        refused = set(new[max(room, 0):])
        out = np.fromiter((t in refused for t in batch.tag.tolist()), bool, len(batch))
        with self.metrics._lock:
            self.metrics.tags_refused += len(refused)
        why = (f"the service holds at most {self.max_tags} tags (serve --max-tags); this "
               "tag is new")
        keep = ~out
        kept = RowBatch(batch.time[keep], batch.tag[keep], batch.anchor[keep],
                        batch.value[keep], batch.anchor_col[keep])
        return kept, [(int(i), f"tag {str(t)[:40]!r}: {why}")
                      for i, t in zip(index[out].tolist(), batch.tag[out].tolist())]

    def _runs_for(self, code: np.ndarray) -> np.ndarray:
        """The per-code run array, grown to cover ``code`` (caller holds the ingest lock,
        or is the constructor)."""
        need = int(code.max(initial=-1)) + 1
        if need > len(self._run_arr):  # new tags start in the run base (module doc)
            self._run_arr = np.concatenate(
                [self._run_arr, np.full(need - len(self._run_arr), self._run_base,
                                        dtype=np.int64)])
        return self._run_arr

    def _take(self, wall: float, *, flush_all: bool = False) -> dict | None:
        """The assembler's ready rows with each row's run (caller holds the ingest lock)."""
        ready = self.assembler.take_ready(wall, flush_all=flush_all)
        if ready is not None:
            ready["run"] = self._runs_for(ready["tag_code"])[ready["tag_code"]]
        return ready

    def _enqueue(self, blocks: list[dict | None], wall: float) -> None:
        """Queue ready blocks for the solver (caller holds the ingest lock: the queue's
        order is the order the assembler released them, so a (tag, run)'s epochs are
        solved in time order whatever the number of ingest threads)."""
        blocks = [b for b in blocks if b is not None]
        if blocks:
            with self._cv:
                self._queue.extend((b, wall) for b in blocks)
                self._cv.notify()

    def _accept(self, batch: RowBatch, source: str) -> tuple[int, float]:
        """Store (synced), assemble and queue accepted rows; caller holds the ingest lock.

        Returns the number of late rows and the wall time of the batch.
        """
        wall = time.time()
        n = len(batch)
        if not n:
            return 0, wall
        a = self.assembler
        code = a.codes(batch.tag)
        rebased = a.rebase(batch.time, code, wall)  # a tag's clock jumped: it restarts
        if rebased.size:
            with self.metrics._lock:
                self.metrics.tags_rebased += int(rebased.size)
            # the re-based tags' pending rows (their earlier run), released before this
            # batch's rows are added: queued now, with their run (queued even if the
            # append below fails), and a new run begins
            self._enqueue([self._take(-np.inf)], wall)
            self._runs_for(rebased)[rebased] += 1
        late = a.late(batch.time, code)
        # late rows of an epoch never solved are solved all the same (stateless solver)
        fresh = a.late_unsolved(batch.time, code, late)
        table = pa.table({
            "time": batch.time, "tag": pa.array(batch.tag, pa.string()),
            "anchor": self._anchor_arrow.take(batch.anchor_col), "value": batch.value,
            "arrival": np.full(n, wall), "late": late & ~fresh,
            "source": pa.repeat(pa.scalar(source, pa.string()), n),
            "run": self._runs_for(code)[code],
        }, schema=MEAS_SCHEMA)
        self.meas.append(table)  # durable before we answer
        a.add_coded(batch.time, code, batch.anchor_col, batch.value, wall, late, fresh)
        self._enqueue([self._take(wall)], wall)
        return int((late & ~fresh).sum()), wall

    def _finish(self, batch: RowBatch, rejected: list[tuple[int, str]],
                rej_cols: np.ndarray, n_late: int, wall: float,
                source: str) -> IngestResult:
        n = len(batch)
        self.metrics.ingest(source, n, len(rejected), n_late, batch.anchor_col, rej_cols, wall)
        return IngestResult(n, rejected, n_late)

    def _rejected_anchor_cols(self, rows: list[Any], rejected: list[tuple[int, str]]) -> np.ndarray:
        names = []
        for i, _ in rejected:
            r = rows[i]
            if type(r) is dict:
                a = r.get("anchor")
                if isinstance(a, str | int) and not isinstance(a, bool):
                    names.append(str(a).strip())
        if not names:
            return np.zeros(0, dtype=np.int64)
        col = self._anchor_index.get_indexer(pd.Index(names, dtype=object))
        return col[col >= 0]

    # -- solving -------------------------------------------------------------------------
    def add_listener(self, fn: Callable[[pd.DataFrame], None]) -> None:
        """Call ``fn(positions_frame)`` (from the solver thread) for every solved block."""
        self._listeners.append(fn)

    def start(self) -> None:
        """Warm the processor up (compiled kernels), then start the solver thread."""
        warm = getattr(self.processor, "warm_up", None)
        if warm is not None:
            warm()
        if self._thread is None:
            self._stop.clear()
            self._thread = threading.Thread(target=self._loop, name="robustloc-solver",
                                            daemon=True)
            self._thread.start()

    def stop(self) -> None:
        """Stop the solver, solve every pending epoch, close the store.

        Call it once the transports have stopped ingesting.  An engine whose solver was
        started (:meth:`start`, the service) solves what is queued or pending now, so
        every acknowledged epoch has a position row after a graceful stop (SIGTERM), with
        or without a store.  An engine never started (tests that :meth:`step` it by hand)
        solves nothing more: its pending epochs stay in the store for the next start, as
        after a crash.
        """
        started = self._thread is not None
        self._stop.set()
        with self._cv:
            self._cv.notify()
        if self._thread is not None:
            self._thread.join(timeout=30)
            self._thread = None
        if started:
            try:
                self.step(flush_all=True)
            except Exception as exc:  # noqa: BLE001 - counted; the rows stay in the store
                self.solver_errors += 1
                self.last_error = f"{type(exc).__name__}: {exc}"
        try:
            self._snapshot()
        finally:
            try:
                self.meas.close()
            finally:
                self.pos.close()

    def _loop(self) -> None:
        tick = min(0.25, self.assembler.idle / 4)
        while not self._stop.is_set():
            with self._cv:
                if not self._queue:
                    self._cv.wait(timeout=tick)
            try:
                self.step()
            except Exception as exc:  # never let one bad block stop the service
                self.solver_errors += 1
                self.last_error = f"{type(exc).__name__}: {exc}"

    def step(self, *, flush_all: bool = False) -> int:
        """Solve queued (and idle) epochs now; returns the number of position rows."""
        with self._solve_lock:
            # the ingest lock is held through each body's sync: take it only when a tag
            # may have gone idle, so that solving a queued block never waits for a sync;
            # the queue is taken with the idle rows, which come after it (the order the
            # assembler released them)
            if flush_all or self.assembler.may_have_idle(time.time()):
                with self._ingest_lock:
                    now = time.time()
                    self._enqueue([self._take(now, flush_all=flush_all)], now)
            with self._cv:
                blocks, self._queue = self._queue, []
            out = 0
            if blocks and self.kind is not None:
                out = self._solve(blocks)
                if (self.snapshot_s
                        and time.monotonic() - self._last_snapshot > self.snapshot_s):
                    self._snapshot()
                    self._last_snapshot = time.monotonic()
            now = time.time()
            if now - self._last_forget >= self._forget_every:
                self._forget_idle(now)
            return out

    def forget_idle(self, now: float | None = None) -> int:
        """Forget now the tags silent for ``forget_after_s`` at wall time ``now`` (default
        the clock's; the solver does it every minute at most); returns how many."""
        with self._solve_lock:
            return self._forget_idle(time.time() if now is None else now)

    def _forget_idle(self, now: float) -> int:
        """:meth:`forget_idle`, called by the solver (it holds the solve lock, or is the
        constructor): no block is being processed meanwhile."""
        self._last_forget = now
        if not math.isfinite(self.forget_after_s):
            return 0
        with self._ingest_lock:
            a = self.assembler
            codes = a.idle_tags(now - self.forget_after_s)
            if codes.size:
                with self._cv:  # (blocks queued since this step took the queue)
                    queued = [b["tag_code"] for b, _ in self._queue]
                if queued:
                    codes = codes[~np.isin(codes, np.concatenate(queued))]
            if not codes.size:
                return 0
            runs = self._runs_for(codes)[codes]
            self._run_base = max(self._run_base, int(runs.max()) + 1)
            names = a.forget(codes)
            # every free code's next tag starts in the new base: a code freed by an earlier
            # pass kept that pass's base, and a tag forgotten twice came back in a run it
            # had used (epochs solved twice; after a crash, rows never solved: the forget
            # review)
            self._run_arr[a.free_codes] = self._run_base
        gone = set(names)
        forget = getattr(self.processor, "forget", None)
        if forget is not None:
            forget(names)
        self._processed = {k: v for k, v in self._processed.items() if k[0] not in gone}
        with self._latest_lock:
            self._compact_latest()
            if self._latest_frames and len(self._latest_frames[0]):
                f = self._latest_frames[0]
                self._latest_frames = [f[~f["tag"].isin(gone).to_numpy()]
                                       .reset_index(drop=True)]
            if self._fix_frames and len(self._fix_frames[0]):
                f = self._fix_frames[0]
                self._fix_frames = [f[~f["tag"].isin(gone).to_numpy()].reset_index(drop=True)]
        with self.metrics._lock:
            self.metrics.tags_forgotten += len(names)
        return len(names)

    def flush(self) -> int:
        """Solve every pending epoch now (tests and benchmarks; not needed in service)."""
        return self.step(flush_all=True)

    def _solve(self, blocks: list[tuple[dict, float]]) -> int:
        keys = [k for k in blocks[0][0] if k != "late"]
        rows = {k: np.concatenate([b[k] for b, _ in blocks]) for k in keys}
        late = np.concatenate([b.get("late", np.zeros(len(b["time"]), dtype=bool))
                               for b, _ in blocks])
        row_wall = np.repeat([w for _, w in blocks], [len(b["time"]) for b, _ in blocks])
        out = 0
        # the epochs in time order first, then the late epochs never solved (assembly)
        for part in (~late, late):
            if not part.any():
                continue
            sub = rows if part.all() else {k: v[part] for k, v in rows.items()}
            wall = row_wall if part.all() else row_wall[part]
            out += sum(self._solve_rows(sub if idx is None else {k: v[idx]
                                                                 for k, v in sub.items()},
                                        wall if idx is None else wall[idx],
                                        late=part is late)
                       for idx in self._run_passes(sub))
        return out

    @staticmethod
    def _run_passes(rows: dict) -> list[np.ndarray | None]:
        """The rows of each solving pass: one pass (None: all rows) unless a tag has rows
        of two runs (a re-base), whose epochs may share times but are distinct: then pass
        ``k`` holds the rows of each tag's ``k``-th run present (earlier runs first)."""
        run = rows["run"]
        if not run.any():
            return [None]
        rank = (pd.DataFrame({"c": rows["tag_code"], "r": run}).groupby("c")["r"]
                .rank(method="dense").to_numpy(np.int64) - 1)
        if not rank.any():
            return [None]
        return [np.flatnonzero(rank == k) for k in range(int(rank.max()) + 1)]

    def _solve_rows(self, rows: dict, row_wall: np.ndarray, *, late: bool = False) -> int:
        """Solve ready rows (at most one run per tag), store, count and publish them.

        ``late``: the rows of late epochs never solved (:mod:`robustloc.service.assembly`):
        stored and published (with a column ``late``, true) like the others, but not a
        tag's latest row (``/api/latest``), nor a watermark of the processor's state."""
        epochs = self.assembler.epochs(rows, self.kind)
        if not len(row_wall) or (row_wall == row_wall[0]).all():
            ready_wall = np.full(epochs.n_epochs, row_wall[0] if len(row_wall) else time.time())
        else:  # each epoch lies in exactly one block: look its (time, tag) up in the rows
            # (the epochs' tag codes from the rows' own names: the assembler's registry is
            # the ingest threads', not to be read or grown here without their lock)
            names = pd.Index(pd.unique(rows["tag"]))
            ready_wall = row_wall[_epoch_rows(rows["time"], names.get_indexer(rows["tag"]),
                                              epochs.time, names.get_indexer(epochs.tag))]
        # each tag's run in this pass (one per tag)
        run = rows["run"]
        tag_run = (pd.Series(run, index=rows["tag"]).groupby(level=0).first()
                   if run.any() else pd.Series(dtype=np.int64))
        frame = self._process(epochs)
        if len(frame):
            # when each row was solved, on this server's clock (Unix seconds): the map
            # ages a tag by it (it aged them by the device's time: a gateway's clock 30 s
            # behind made a live tag "silent", a reloaded page a long-silent one fresh;
            # the map review)
            frame = frame.assign(solved_at=round(time.time(), 3))
        if epochs.n_epochs and not late:
            latest = pd.Series(epochs.time).groupby(epochs.tag).max()
            for tag, t in latest.items():
                key = (str(tag), int(tag_run.get(tag, 0)))
                self._processed[key] = max(self._processed.get(key, -np.inf), float(t))
        if len(frame):
            runs = (frame["tag"].map(tag_run).fillna(0).to_numpy(np.int64) if len(tag_run)
                    else np.zeros(len(frame), dtype=np.int64))
            self._pos_backlog.append(pa.Table.from_pandas(frame.assign(run=runs),
                                                          preserve_index=False))
        self._store_positions()
        done = time.time()
        status = frame["status"].to_numpy() if "status" in frame else np.array(["ok"] * len(frame))
        self.metrics.solved(status, done - ready_wall)
        if late:
            with self.metrics._lock:
                self.metrics.late_epochs_solved += len(frame)
            frame = frame.assign(late=True)
        else:
            with self._latest_lock:
                self._latest_frames.append(frame)
                if {"x", "y"} <= set(frame.columns):
                    has = np.isfinite(frame["x"].to_numpy(float)) & np.isfinite(
                        frame["y"].to_numpy(float))
                    if has.any():
                        self._fix_frames.append(frame.loc[has, [c for c in _FIX_COLUMNS
                                                                if c in frame.columns]])
                if len(self._latest_frames) > 64:
                    self._compact_latest()
        for fn in list(self._listeners):
            try:
                fn(frame)
            except Exception:  # a listener's failure must not lose the block
                self.solver_errors += 1
        return len(frame)

    @property
    def positions_not_stored(self) -> int:
        """Position rows solved and published but not yet in the positions log."""
        return sum(t.num_rows for t in list(self._pos_backlog))

    def _store_positions(self) -> None:
        """Append the solved position tables to the positions log, oldest first.  A
        failed append (disk full) keeps them, in order, for the next call: the rows were
        published all the same, and a stateful processor must not solve them twice.  Kept
        in order, the log's latest row per tag stays a true watermark: should the service
        stop before they are stored, a restart solves those epochs again."""
        while self._pos_backlog:
            try:
                self.pos.append(self._pos_backlog[0])
            except StoreWriteError as exc:
                self.position_store_errors += 1
                self.last_error = str(exc)
                return
            self._pos_backlog.pop(0)

    def _process(self, epochs: Epochs) -> pd.DataFrame:
        """The processor's rows of ``epochs``; never raises, never drops an epoch.

        A processor that raises is a defect, counted with its reason (``/api/status``,
        ``/metrics``).  A stateless one (``locate``) is retried on each half of the block's
        tags, then of the one tag's epochs, down to one epoch, so a failing epoch costs no
        other epoch its fix.  A stateful one with a ``checkpoint``/``rollback`` (the
        tracker) is rolled back to its state before the block and retried tag by tag, each
        tag rolled back again if it fails (its state stays as before the block), so a
        failing tag costs no other tag its rows.  The epochs that still fail, and the block
        of a stateful processor without a checkpoint (its state may have advanced
        part-way: not to be repeated), get one row each with status ``solver_error``.
        Their measurements are stored either way.
        """
        checkpoint = getattr(self.processor, "checkpoint", None)
        saved = (checkpoint() if checkpoint is not None
                 and not getattr(self.processor, "stateless", False) else None)
        try:
            return self.processor.process(epochs)
        except Exception as exc:  # noqa: BLE001 - counted, reported, rows kept
            self.solver_errors += 1
            self.last_error = f"{type(exc).__name__}: {exc}"
        tags = pd.unique(epochs.tag)
        if saved is not None:
            return self._retry_by_tag(epochs, tags, saved)
        if getattr(self.processor, "stateless", False) and epochs.n_epochs > 1:
            if len(tags) > 1:  # halves of the tags, then (one tag left) of its epochs
                first = pd.Index(tags[: len(tags) // 2]).get_indexer(epochs.tag) >= 0
            else:
                first = np.arange(epochs.n_epochs) < epochs.n_epochs // 2
            parts = [np.flatnonzero(first), np.flatnonzero(~first)]
            frames = [self._process(_subset(epochs, rows)) for rows in parts]
            order = np.argsort(np.concatenate(parts), kind="stable")
            both = pd.concat(frames, ignore_index=True)
            return both.iloc[order].reset_index(drop=True)
        return pd.DataFrame({"time": epochs.time, "tag": epochs.tag,
                             "method": self.processor.name, "x": np.nan, "y": np.nan,
                             "status": SOLVER_ERROR})

    def _retry_by_tag(self, epochs: Epochs, tags: np.ndarray, saved: object) -> pd.DataFrame:
        """A stateful processor's failed block, tag by tag from its state before the block
        (:meth:`_process`); a tag that fails again is rolled back and gets
        ``solver_error`` rows."""
        self.processor.rollback(saved)  # type: ignore[attr-defined]
        codes = pd.Index(tags).get_indexer(epochs.tag)
        parts, frames = [], []
        for k in range(len(tags)):
            rows = np.flatnonzero(codes == k)
            sub = _subset(epochs, rows)
            before = self.processor.checkpoint()  # type: ignore[attr-defined]
            try:
                frames.append(self.processor.process(sub))
            except Exception as exc:  # noqa: BLE001 - counted, reported, rows kept
                self.solver_errors += 1
                self.last_error = f"{type(exc).__name__}: {exc}"
                self.processor.rollback(before)  # type: ignore[attr-defined]
                frames.append(pd.DataFrame({"time": sub.time, "tag": sub.tag,
                                            "method": self.processor.name, "x": np.nan,
                                            "y": np.nan, "status": SOLVER_ERROR}))
            parts.append(rows)
        order = np.argsort(np.concatenate(parts), kind="stable")
        both = pd.concat(frames, ignore_index=True)
        # the failed tags' rows in the solved tags' column types (the store's blocks must
        # agree: an int64 ``n_used`` beside a float one cannot be read back as one table);
        # a count they lack is 0, a flag False
        solved = [f for f in frames if f["status"].ne(SOLVER_ERROR).any()]
        for col in both.columns:
            kinds = {f[col].dtype for f in solved if col in f}
            kind = kinds.pop() if len(kinds) == 1 else None
            if kind is not None and kind.kind in "iub" and both[col].dtype != kind:
                both[col] = both[col].fillna(False if kind.kind == "b" else 0).astype(kind)
        return both.iloc[order].reset_index(drop=True)

    def _compact_latest(self) -> None:
        """Reduce the recent frames to the latest row per tag (caller holds the lock)."""
        if self._latest_frames:
            both = pd.concat(self._latest_frames, ignore_index=True)
            self._latest_frames = [both.drop_duplicates("tag", keep="last")]
        if self._fix_frames:  # (one frame can hold several epochs of a tag: /api/latest
            # raised "Reindexing only valid with uniquely valued Index objects" on it)
            both = pd.concat(self._fix_frames, ignore_index=True)
            self._fix_frames = [both.drop_duplicates("tag", keep="last")]

    # -- queries -------------------------------------------------------------------------
    def latest(self) -> pd.DataFrame:
        """The latest position row of every tag solved since the start."""
        with self._latest_lock:
            self._compact_latest()
            return self._latest_frames[0].copy() if self._latest_frames else pd.DataFrame()

    def latest_with_fixes(self) -> pd.DataFrame:
        """:meth:`latest`, where a tag's latest row has no position with its last fix
        as ``fix_time``, ``fix_x``, ``fix_y``, ``fix_status``, ``fix_solved_at``: the map
        page draws such a tag hollow at its last fix, and a page opened then had nothing
        to draw ("no fix yet"; the map review).  After a restart, from the store."""
        with self._latest_lock:
            self._compact_latest()
            latest = self._latest_frames[0].copy() if self._latest_frames else pd.DataFrame()
            fixes = self._fix_frames[0].copy() if self._fix_frames else pd.DataFrame()
        if not len(latest) or not len(fixes) or not {"x", "y"} <= set(latest.columns):
            return latest
        nofix = ~(np.isfinite(latest["x"].to_numpy(float))
                  & np.isfinite(latest["y"].to_numpy(float)))
        if not nofix.any():
            return latest
        f = fixes.set_index("tag")
        for c in _FIX_COLUMNS[1:]:
            if c in f.columns:
                col = latest["tag"].map(f[c])
                latest["fix_" + c] = col.where(nofix, None)
        return latest

    def positions(self, tag: str | None = None, since: float | None = None,
                  until: float | None = None, limit: int = 100_000) -> pd.DataFrame:
        """Stored positions, filtered, sorted by time then tag (latest ``limit`` rows)."""
        return self.positions_counted(tag, since, until, limit)[0]

    def positions_counted(self, tag: str | None = None, since: float | None = None,
                          until: float | None = None, limit: int = 100_000
                          ) -> tuple[pd.DataFrame, int]:
        """:meth:`positions` and how many rows matched the filter before ``limit``.

        The rows are read in two passes over one snapshot of the positions log: the
        columns that decide which rows are answered (``time``, ``tag``, ``method``,
        ``run``, and the integer and boolean columns, whose nulls decide their type in
        the frame) of every matching row, then every column of the rows from the
        earliest time answered on only.  The whole log was read into a frame for each
        query (8 queries at once over 125 000 positions: 671 MiB more, the serve review).

        Returns
        -------
        frame : DataFrame
            The latest ``limit`` matching rows, sorted by time then tag.
        total : int
            Rows matching ``tag``, ``since`` and ``until``; more than ``len(frame)`` when
            ``limit`` left the earliest out.
        """
        expr = None
        for e in ((ds.field("tag") == tag) if tag is not None else None,
                  (ds.field("time") >= since) if since is not None else None,
                  (ds.field("time") <= until) if until is not None else None):
            if e is not None:
                expr = e if expr is None else expr & e
        snap = self.pos.snapshot()
        typed = sorted({f.name for sch in snap.schemas() for f in sch
                        if pa.types.is_integer(f.type) or pa.types.is_boolean(f.type)})
        keys = snap.scan(columns=list(dict.fromkeys(["time", "tag", "method", "run", *typed])),
                         expression=expr)
        if keys.num_rows == 0:
            return pd.DataFrame(columns=["time", "tag", "x", "y", "method", "status"]), 0
        kdf = keys.select([c for c in ("time", "tag", "method")
                           if c in keys.column_names]).to_pandas()
        # the type that every matching row gives a column with nulls (an int64 column is
        # float64 in the frame, also when the rows answered have none)
        null_typed = {c: keys.select([c]).to_pandas()[c].dtype for c in typed
                      if c in keys.column_names and keys[c].null_count}
        rows, total = _answered_rows(kdf, _runs_of(keys), limit)
        times = kdf["time"].to_numpy(np.float64)
        cut = float(times[rows[0]]) if len(rows) < keys.num_rows else math.nan
        read = np.flatnonzero(times >= cut) if math.isfinite(cut) else None
        # a time bound pushed down when it leaves most rows out (a filter copies the rows
        # it keeps: more than half kept cost more than reading them all)
        if read is None or 2 * len(read) > keys.num_rows or np.isnan(times[rows]).any():
            table, at, expect = snap.scan(expression=expr), rows, keys.num_rows
        else:  # the rows answered and the others of their times: the earlier not read
            bound = ds.field("time") >= cut
            table = snap.scan(expression=bound if expr is None else expr & bound)
            at, expect = np.searchsorted(read, rows), len(read)
        if table.num_rows != expect:  # (not the rows of the first pass: never seen)
            return _latest_rows(snap.scan(expression=expr), limit)
        if len(at) and (np.diff(at) == 1).all():  # the log's order is the answer's
            out = table.slice(int(at[0]), len(at))  # (no copy)
        else:
            out = table.take(pa.array(at, pa.int64()))
        want = keys.select(["time", "tag"]).take(pa.array(rows, pa.int64()))
        if not (out["time"].equals(want["time"]) and out["tag"].equals(want["tag"])):
            return _latest_rows(snap.scan(expression=expr), limit)  # (NaN times too)
        df = out.to_pandas().drop(columns="run", errors="ignore")
        for c, dtype in null_typed.items():
            if c in df.columns and df[c].dtype != dtype:
                df[c] = df[c].astype(dtype)
        return df, total
