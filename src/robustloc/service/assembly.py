"""Live epoch assembly: rows arriving in any order become whole epochs ``(time, tag)``.

Rule (issue 12, "Epoch assembly").  Per tag, let ``newest`` be the latest measurement time
seen.  An epoch ``(t, tag)`` is *ready* (solved) once ``t < newest - window``: it is older
than the newest time of its tag by more than the latency window, so the rows of ``t`` that
were still in flight have had ``window`` seconds of measurement time to arrive.  With
``window = 0`` an epoch is solved as soon as any later epoch of its tag arrives (right for
gateways that report each epoch whole and in order).

A tag that stops reporting would keep its last epochs forever; they are also solved when no
row of the tag arrived for ``idle_flush_s`` seconds of wall-clock time.

A row that arrives *late* - its epoch already solved, or older than ``newest - window``
when it arrives - is stored and counted by the caller, but not solved live (the epoch's
fix has been published); the batch ``robustloc locate`` of the stored log includes it.

An epoch whose *every* row arrives late (a gateway that delivers whole epochs after
another gateway's later ones) has no fix published at all.  With ``live_late`` (a
stateless solver: ``serve`` without ``--track``) such an epoch is solved all the same:
each tag remembers its :data:`RECENT_SOLVED` latest solved epoch times, and a late row
whose time is newer than the oldest of them and none of them belongs to an epoch never
solved.  Its rows wait ``idle_flush_s`` of wall time from the first of them (for the rest
of the epoch), then are released with ``late`` set (:meth:`EpochAssembler.take_ready`).
A late row older than what the tag remembers is late as above: whether its epoch was
solved is not known.

A tag's clock can jump: a device restarts its time from 0, or one row carries a time far
ahead (9e11 s: a unit mistake).  Every later row of the tag was then late, stored and
never solved, for good.  So a row more than ``time_jump_s`` behind its tag's newest time,
while no row near that newest time has arrived for ``idle_flush_s`` of wall time (the
tag's stream has moved, not merely one delayed row arrived), **re-bases** the tag: its
pending epochs are released as they are, its watermarks restart, and the row is solved
as any other (:meth:`EpochAssembler.rebase`; counted).  A gateway that uploads rows
buffered for hours while another keeps the tag's newest time current re-bases nothing:
its rows stay late, as above.

A tag silent for long is *forgotten* (:meth:`EpochAssembler.idle_tags`,
:meth:`EpochAssembler.forget`): its watermarks go and its code is given to the next new
tag, so a service whose tags come and go holds only the tags heard lately.

The pending rows are kept as columns (NumPy), so one ``add``/``take_ready`` costs a few
vectorized passes over the pending rows, whatever the number of tags.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from types import MappingProxyType

import numpy as np
import pandas as pd
from numpy.typing import NDArray

from robustloc.io.tables import Epochs, pivot_epochs
from robustloc.service.defaults import DEFAULT_TIME_JUMP_S

#: Solved epoch times each tag remembers, to tell a late epoch never solved from the late
#: rows of one solved (module doc): 256 bytes per tag.
RECENT_SOLVED = 32


class EpochAssembler:
    """Pending rows per tag, released as ready :class:`~robustloc.io.tables.Epochs`.

    Parameters
    ----------
    anchor_ids : sequence of str
        Anchor order of the epochs' value columns.
    latency_window_s : float
        Measurement-time window (s) an epoch waits for late rows, see the module doc.
    idle_flush_s : float
        Wall-clock seconds without a row of a tag after which its pending epochs are solved.
    time_jump_s : float
        A row this far behind its tag's newest time, the tag silent near that time for
        ``idle_flush_s``, re-bases the tag (module doc); ``inf``: never.
    live_late : bool
        Solve the epochs whose every row arrives late (module doc); for a stateless
        solver only (a filter cannot go back in time).
    """

    def __init__(
        self, anchor_ids: Sequence[str], latency_window_s: float, idle_flush_s: float,
        time_jump_s: float = DEFAULT_TIME_JUMP_S, live_late: bool = False,
    ) -> None:
        if not (np.isfinite(latency_window_s) and latency_window_s >= 0):
            raise ValueError(f"latency window must be >= 0 s, got {latency_window_s}")
        if not (np.isfinite(idle_flush_s) and idle_flush_s > 0):
            raise ValueError(f"idle flush must be > 0 s, got {idle_flush_s}")
        if not (time_jump_s > latency_window_s):  # (NaN refused too)
            raise ValueError(f"time jump must be more than the latency window "
                             f"({latency_window_s:g} s), got {time_jump_s}")
        self.anchor_ids = tuple(str(a) for a in anchor_ids)
        self.window = float(latency_window_s)
        self.idle = float(idle_flush_s)
        self.time_jump = float(time_jump_s)
        #: tags re-based so far (:meth:`rebase`)
        self.rebased = 0
        self._released: list[tuple[NDArray, ...]] = []  # pending rows of re-based tags
        self._code: dict[str, int] = {}
        self._names: list[str | None] = []  # None: a forgotten tag's free code
        self._free: list[int] = []  # free codes, reused before new ones
        self._newest = np.empty(0)
        self._solved = np.empty(0)
        self._last_wall = np.empty(0)
        #: wall time of each tag's latest accepted row, late ones included (``-inf``: a
        #: tag whose code is free)
        self._heard = np.empty(0)
        self._chunks: list[tuple[NDArray, ...]] = []
        self._n_pending = 0
        self.live_late = bool(live_late)
        #: each tag's latest solved epoch times, ascending, -inf where none (module doc)
        self._width = RECENT_SOLVED if self.live_late else 0  # (nothing to remember)
        self._recent = np.empty((0, self._width))
        #: every solved epoch time of a tag later than this is in ``_recent``
        self._known_from = np.empty(0)
        #: rows of late epochs never solved, waiting for the rest of their epoch:
        #: (time, code, anchor_col, value, wall of arrival)
        self._late_chunks: list[tuple[NDArray, ...]] = []
        self._late_released: list[tuple[NDArray, ...]] = []  # of re-based tags
        #: late epochs released for solving so far
        self.late_epochs = 0
        #: solved epoch times not yet folded into ``_recent`` (:meth:`_remember`)
        self._unfolded: list[tuple[NDArray, NDArray]] = []
        self._n_unfolded = 0

    # -- tags ----------------------------------------------------------------------------
    def codes(self, tags: NDArray[np.object_]) -> NDArray[np.int64]:
        """Integer code of each tag (new tags are registered, in order of appearance,
        on the codes of forgotten tags first).

        One factorization of the rows, then a dict look-up per distinct tag (4x faster
        than a pandas index look-up per row, which converts the strings).
        """
        codes, uniq = pd.factorize(np.asarray(tags, dtype=object))
        ucode = np.empty(len(uniq), dtype=np.int64)
        for j, u in enumerate(uniq.tolist()):
            c = self._code.get(u)
            if c is None:
                if self._free:
                    c = self._free.pop()
                    self._names[c] = u
                else:
                    c = len(self._names)
                    self._names.append(u)
                self._code[u] = c
            ucode[j] = c
        if len(self._names) > len(self._newest):
            # capacity grown ahead, not by the tags added: each new tag copied every
            # per-tag array (4.6 ms per new tag at 100 000 tags held, under the ingest
            # lock; the late-epoch review).  Codes beyond the tags held are never read.
            n = len(self._newest)  # (doubled up to 65 536 spare codes, then by that)
            cap = max(len(self._names), n + min(n, 1 << 16), 64)

            def grown(a: NDArray, fill: float) -> NDArray:
                out = np.full((cap, *a.shape[1:]), fill)
                out[: len(a)] = a
                return out

            self._newest = grown(self._newest, -np.inf)
            self._solved = grown(self._solved, -np.inf)
            self._last_wall = grown(self._last_wall, 0.0)
            self._heard = grown(self._heard, -np.inf)
            self._recent = grown(self._recent, -np.inf)
            self._known_from = grown(self._known_from, -np.inf)
        return ucode[codes]

    @property
    def tags(self) -> list[str]:
        """The tags held (registered and not forgotten), in order of their codes."""
        return [n for n in self._names if n is not None]

    @property
    def n_tags(self) -> int:
        """The number of tags held."""
        return len(self._code)

    @property
    def free_codes(self) -> NDArray[np.int64]:
        """The codes of forgotten tags, not yet given to new tags."""
        return np.array(self._free, dtype=np.int64)

    def name(self, code: int) -> str:
        """The tag of a held ``code``."""
        n = self._names[code]
        if n is None:
            raise KeyError(f"tag code {code} is free")
        return n

    def set_heard(self, heard: Mapping[str, float]) -> None:
        """Each named tag's latest accepted row's wall time (a restart: the stored rows'
        latest arrival), at least as recent as what the assembler holds."""
        if not heard:
            return
        names = np.array(list(heard), dtype=object)
        codes = self.codes(names)
        np.maximum.at(self._heard, codes, np.array(list(heard.values()), dtype=float))

    def idle_tags(self, cutoff_wall: float) -> NDArray[np.int64]:
        """Codes of the held tags last heard at or before ``cutoff_wall`` (wall time) that
        hold no pending rows: the tags :meth:`forget` may drop."""
        # (free codes hold -inf: excluded below; codes beyond the tags held: cut off)
        idle = self._heard[: len(self._names)] <= cutoff_wall
        if not idle.any():
            return np.zeros(0, dtype=np.int64)
        held = np.fromiter((n is not None for n in self._names), bool, len(self._names))
        idle &= held
        for chunk in [*self._chunks, *self._released, *self._late_chunks,
                      *self._late_released]:
            idle[chunk[1]] = False
        return np.flatnonzero(idle)

    def forget(self, codes: NDArray[np.int64]) -> list[str]:
        """Forget the tags ``codes`` (from :meth:`idle_tags`): their watermarks go, their
        codes go to the next new tags; a forgotten tag heard again is a new tag.

        Returns their names.

        Raises
        ------
        ValueError
            A code that is free, or whose tag holds pending rows (its epochs unsolved).
        """
        self._fold()
        codes = np.unique(np.asarray(codes, dtype=np.int64))
        pending = np.zeros(len(self._names), dtype=bool)
        for chunk in [*self._chunks, *self._released, *self._late_chunks,
                      *self._late_released]:
            pending[chunk[1]] = True
        if codes.size and pending[codes].any():
            raise ValueError("cannot forget a tag with pending rows")
        names = [self.name(int(c)) for c in codes.tolist()]  # (KeyError before any change)
        for n, c in zip(names, codes.tolist()):
            del self._code[n]
            self._names[c] = None
            self._free.append(c)
        self._newest[codes] = -np.inf
        self._solved[codes] = -np.inf
        self._last_wall[codes] = 0.0
        self._heard[codes] = -np.inf
        self._recent[codes] = -np.inf
        self._known_from[codes] = -np.inf
        return names

    @property
    def known(self) -> Mapping[str, int]:
        """The tags registered so far and their codes (a read-only view, not a copy)."""
        return MappingProxyType(self._code)

    @property
    def n_pending(self) -> int:
        """Rows waiting for their epoch to be released (late epochs' rows included)."""
        return self._n_pending + sum(len(c[0]) for c in [*self._late_chunks,
                                                         *self._late_released])

    def watermarks(self) -> dict[str, float]:
        """Per tag held, the latest solved epoch time (``-inf``: none yet)."""
        return {n: float(self._solved[i]) for i, n in enumerate(self._names) if n is not None}

    def set_watermarks(self, solved: dict[str, float], newest: dict[str, float]) -> None:
        """Restore per-tag state (after a restart): solved and newest times."""
        self._fold()
        names = np.array(sorted(set(solved) | set(newest)), dtype=object)
        codes = self.codes(names)
        for name, c in zip(names.tolist(), codes.tolist()):
            self._solved[c] = max(self._solved[c], solved.get(name, -np.inf))
            self._newest[c] = max(self._newest[c], newest.get(name, -np.inf))
            # which epochs up to the restored solved time were solved is not known here
            self._known_from[c] = max(self._known_from[c], solved.get(name, -np.inf))

    # -- rows ----------------------------------------------------------------------------
    def add(
        self, time: NDArray[np.float64], tags: NDArray[np.object_],
        anchor_col: NDArray[np.int64], value: NDArray[np.float64], wall: float,
    ) -> NDArray[np.bool_]:
        """Add rows; returns the mask of *late* rows (not solved live, see the module
        doc)."""
        code = self.codes(tags)
        late = self.late(time, code)
        fresh = self.late_unsolved(time, code, late)
        self.add_coded(time, code, anchor_col, value, wall, late, fresh)
        return late & ~fresh

    def rebase(self, time: NDArray[np.float64], code: NDArray[np.int64], wall: float
               ) -> NDArray[np.int64]:
        """Re-base the tags whose clock jumped (module doc): rows more than
        ``time_jump_s`` behind their tag's newest time, no row of the tag added for
        ``idle_flush_s`` of wall time.  Their pending rows are released at the next
        :meth:`take_ready` (without advancing the solved time), their watermarks reset.
        Call before :meth:`late`; returns the codes of the re-based tags."""
        far = time < self._newest[code] - self.time_jump
        if not far.any():
            return np.zeros(0, dtype=np.int64)
        tags = np.unique(code[far])
        tags = tags[wall - self._last_wall[tags] >= self.idle]
        if not tags.size:
            return tags
        self._fold()
        p = self._pending()
        if p is not None:
            t, c, a, v = p
            out = np.isin(c, tags)
            if out.any():
                self._released.append((t[out], c[out], a[out], v[out]))
                rest = ~out
                self._chunks = [(t[rest], c[rest], a[rest], v[rest])] if rest.any() else []
                self._n_pending = int(rest.sum())
        if self._late_chunks:
            t, c, a, v, w = (np.concatenate(x) for x in zip(*self._late_chunks))
            out = np.isin(c, tags)
            if out.any():
                self._late_released.append((t[out], c[out], a[out], v[out], w[out]))
                rest = ~out
                self._late_chunks = [(t[rest], c[rest], a[rest], v[rest], w[rest])] \
                    if rest.any() else []
        self._newest[tags] = -np.inf
        self._solved[tags] = -np.inf
        self._recent[tags] = -np.inf
        self._known_from[tags] = -np.inf
        self.rebased += int(tags.size)
        return tags

    def late(self, time: NDArray[np.float64], code: NDArray[np.int64]) -> NDArray[np.bool_]:
        """Mask of the rows that would be late now (tags as :meth:`codes`).

        A row of an epoch still pending is not late: it joins its epoch.  (Pending epochs
        older than ``newest - window`` exist only between a restart putting rows back and
        the next :meth:`take_ready`; a row of one was late, and with ``live_late`` it was
        solved as a second, late epoch: the late-epoch review.)"""
        solved = time <= self._solved[code]
        late = solved | (time < self._newest[code] - self.window)
        # (a pending epoch is later than its tag's solved time: only such rows are looked
        # up, so a stream of ordinary late rows never indexes the pending rows)
        li = np.flatnonzero(late & ~solved)
        if li.size and self._n_pending:
            t, c, _, _ = self._pending()  # type: ignore[misc]
            pending = pd.MultiIndex.from_arrays([c, t])
            late[li[pd.MultiIndex.from_arrays([code[li], time[li]]).isin(pending)]] = False
        return late

    def late_unsolved(self, time: NDArray[np.float64], code: NDArray[np.int64],
                      late: NDArray[np.bool_]) -> NDArray[np.bool_]:
        """Mask of the ``late`` rows whose epoch was never solved, as far as their tag
        remembers (module doc); all False without ``live_late``."""
        fresh = np.zeros(len(time), dtype=bool)
        if not self.live_late or not late.any():
            return fresh
        self._fold()
        li = np.flatnonzero(late)
        for k in range(0, len(li), 65_536):  # (a bounded (rows, RECENT_SOLVED) compare)
            i = li[k:k + 65_536]
            t, c = time[i], code[i]
            fresh[i] = (t > self._known_from[c]) & ~(self._recent[c] == t[:, None]).any(axis=1)
        return fresh

    def _remember(self, time: NDArray[np.float64], code: NDArray[np.int64]) -> None:
        """Note solved epoch times for their tags' memory.  Kept as a log, folded in by
        :meth:`_fold` when the memory is read (a late row) or changed, or the log is long:
        folding each release cost 0.25 ms a body of 8 000 rows under the ingest lock (1.7
        ms with pandas; the late-epoch review); folded in bulk it costs a few percent."""
        if self._width and len(time):
            self._unfolded.append((time, code))
            self._n_unfolded += len(time)
            if self._n_unfolded >= 1 << 16:
                self._fold()

    def _fold(self) -> None:
        """Fold the noted solved times in, in the order noted."""
        if not self._unfolded:
            return
        t, c = (np.concatenate(x) for x in zip(*self._unfolded))
        self._unfolded, self._n_unfolded = [], 0
        self._fold_times(t, c)

    def _fold_times(self, time: NDArray[np.float64], code: NDArray[np.int64]) -> None:
        """Add solved epoch times to their tags' memory (the latest ``RECENT_SOLVED``
        kept; ``_known_from`` rises to the latest time let go).  NumPy only (runs under
        the ingest lock)."""
        R = self._width
        if not len(time) or not R:
            return
        order = np.lexsort((time, code))
        c, t = code[order], time[order]
        first = np.ones(len(c), dtype=bool)
        first[1:] = (c[1:] != c[:-1]) | (t[1:] != t[:-1])
        c, t = c[first], t[first]  # each (tag, time) once, by tag then time
        starts = np.flatnonzero(np.r_[True, c[1:] != c[:-1]])
        counts = np.diff(np.r_[starts, len(c)])
        tags = c[starts]
        if len(tags) == len(c):  # one new time per tag (each release of a live stream):
            last = self._recent[tags, -1]
            if (t > last).all():  # and its newest: the memory shifts by one, no sort
                rec = self._recent[tags]
                self._known_from[tags] = np.maximum(self._known_from[tags], rec[:, 0])
                rec[:, :-1] = rec[:, 1:]
                rec[:, -1] = t
                self._recent[tags] = rec
                return
        grp = np.repeat(np.arange(len(tags)), counts)
        from_end = counts[grp] - 1 - (np.arange(len(c)) - starts[grp])
        gone = from_end >= R  # more than R new times of a tag: its oldest let go now
        if gone.any():
            np.maximum.at(self._known_from, c[gone], t[gone])
        keep = ~gone
        new = np.full((len(tags), R), -np.inf)
        new[grp[keep], R - 1 - from_end[keep]] = t[keep]
        both = np.sort(np.concatenate([self._recent[tags], new], axis=1), axis=1)
        # a time remembered again (solved before, in an earlier fold) is one time: kept
        # twice it took a slot of the memory, and the oldest distinct times were let go
        # (``_known_from`` rose) while fewer than RECENT_SOLVED were remembered (found by
        # the property test against the memory's definition)
        dup = np.zeros(both.shape, dtype=bool)
        dup[:, 1:] = (both[:, 1:] == both[:, :-1]) & np.isfinite(both[:, 1:])
        if dup.any():
            both = np.sort(np.where(dup, -np.inf, both), axis=1)
        self._known_from[tags] = np.maximum(self._known_from[tags], both[:, R - 1])
        self._recent[tags] = both[:, R:]

    def add_coded(
        self, time: NDArray[np.float64], code: NDArray[np.int64],
        anchor_col: NDArray[np.int64], value: NDArray[np.float64], wall: float,
        late: NDArray[np.bool_], fresh: NDArray[np.bool_] | None = None,
    ) -> None:
        """:meth:`add` with the tags' :meth:`codes`, :meth:`late` and
        :meth:`late_unsolved` masks already computed (with no change of state in
        between); ``fresh`` rows wait for their epoch's other late rows."""
        keep = ~late
        if fresh is not None and fresh.any():
            self._late_chunks.append((time[fresh], code[fresh], anchor_col[fresh],
                                      value[fresh], np.full(int(fresh.sum()), wall)))
        if len(code):
            self._heard[code] = wall  # (late rows too: a tag uploading old rows is heard)
        if keep.any():
            c = code[keep]
            np.maximum.at(self._newest, c, time[keep])
            self._last_wall[c] = wall
            self._chunks.append((time[keep], c, anchor_col[keep], value[keep]))
            self._n_pending += int(keep.sum())

    def _pending(self) -> tuple[NDArray, ...] | None:
        if not self._chunks:
            return None
        if len(self._chunks) > 1:
            self._chunks = [tuple(np.concatenate(x) for x in zip(*self._chunks))]
        return self._chunks[0]

    def may_have_idle(self, wall: float) -> bool:
        """Whether a tag with pending rows may be idle at ``wall`` (see :meth:`take_ready`).

        Safe without the caller's lock (it only reads): a row added meanwhile can make it
        answer True when :meth:`take_ready` then finds nothing, never False when a tag
        was idle before the call.
        """
        chunks = list(self._chunks)
        last = self._last_wall
        if self._late_released or any(bool(np.any(wall - w >= self.idle))
                                      for *_, w in list(self._late_chunks)):
            return True
        try:
            return any(bool(np.any(wall - last[c] >= self.idle)) for _, c, _, _ in chunks)
        except IndexError:  # tags registered meanwhile: let take_ready decide
            return True

    def take_ready(self, wall: float, *, flush_all: bool = False) -> dict | None:
        """Remove and return the rows of the ready epochs, as columns.

        Ready: ``time < newest(tag) - window``, or the tag idle for ``idle_flush_s`` of wall
        time at ``wall``, or ``flush_all``; and a late epoch never solved (module doc)
        ``idle_flush_s`` after its first row arrived.  Returns ``{"time", "tag",
        "tag_code", "anchor_col", "value", "late"}`` arrays (``tag`` as str objects,
        ``tag_code`` as :meth:`codes`, ``late`` True for the rows of late epochs, which
        come last), or ``None`` when nothing is ready.
        """
        released, self._released = self._released, []
        late = self._take_late(wall, flush_all)
        p = self._pending()
        if p is None and not released and late is None:
            return None
        cols: list[tuple[NDArray, ...]] = []
        if p is not None:
            t, c, a, v = p
            if flush_all:
                ready = np.ones(len(t), bool)
            else:
                ready = ((t < self._newest[c] - self.window)
                         | (wall - self._last_wall[c] >= self.idle))
            if ready.any():
                np.maximum.at(self._solved, c[ready], t[ready])
                rest = ~ready
                self._chunks = [(t[rest], c[rest], a[rest], v[rest])] if rest.any() else []
                self._n_pending = int(rest.sum())
                cols.append((t[ready], c[ready], a[ready], v[ready]))
                if self.live_late:
                    self._remember(t[ready], c[ready])
        cols = released + cols  # a re-based tag's old epochs do not advance its solved time
        n_live = sum(len(x[0]) for x in cols)
        if late is not None:
            cols.append(late)
        if not cols:
            return None
        t, c, a, v = (np.concatenate(x) for x in zip(*cols))
        names = np.array(self._names, dtype=object)  # (the caller holds the ingest lock)
        return {"time": t, "tag": names[c], "tag_code": c, "anchor_col": a, "value": v,
                "late": np.arange(len(t)) >= n_live}

    def _take_late(self, wall: float, flush_all: bool) -> tuple[NDArray, ...] | None:
        """The rows of the late epochs ready (module doc), remembered as solved."""
        released, self._late_released = self._late_released, []
        if self._late_chunks:
            t, c, a, v, w = (np.concatenate(x) for x in zip(*self._late_chunks))
            if flush_all:
                ready = np.ones(len(t), bool)
            else:  # an epoch's rows wait idle_flush_s from its first row's arrival
                first = (pd.DataFrame({"c": c, "t": t, "w": w}).groupby(["c", "t"])["w"]
                         .transform("min").to_numpy())
                ready = wall - first >= self.idle
            if ready.any():
                rest = ~ready
                self._late_chunks = [(t[rest], c[rest], a[rest], v[rest], w[rest])] \
                    if rest.any() else []
                released.append((t[ready], c[ready], a[ready], v[ready], w[ready]))
                self._remember(t[ready], c[ready])
        if not released:
            return None
        t, c, a, v, _ = (np.concatenate(x) for x in zip(*released))
        self.late_epochs += len(pd.DataFrame({"c": c, "t": t}).drop_duplicates())
        return t, c, a, v

    def epochs(self, rows: dict, value: str) -> Epochs:
        """Pivot ready rows (from :meth:`take_ready`) with
        :func:`robustloc.io.tables.pivot_epochs`, the core of the batch path's
        :func:`~robustloc.io.tables.to_epochs`, in its order (time, then tag name).

        Reads only ``rows`` (their tag names and codes), never the registry of tags: the
        solver thread calls it while ingest threads register new tags under their lock.
        """
        code = rows["tag_code"]
        used, first = np.unique(code, return_index=True)
        names = np.asarray(rows["tag"], dtype=object)[first]
        order = np.argsort(names, kind="stable")  # str order, as to_epochs' factorize
        rank = np.empty(len(used), dtype=np.int64)
        rank[order] = np.arange(len(used))
        return pivot_epochs(rows["time"], rank[np.searchsorted(used, code)], names[order],
                            rows["anchor_col"], rows["value"], self.anchor_ids, value)
