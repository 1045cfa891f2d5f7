"""Time alignment of measurement streams at different rates (UWB epochs, GPS sentences).

Policy (event-driven, no interpolation of measurements):

1. every stream is shifted onto the UWB clock by its own offset (``t + offset_s``; GPS
   sentences carry UTC time of day, UWB logs their own clock);
2. all measurement times of one tag are merged into one sorted timeline and cut into
   *events*, one per input epoch.  Values sharing one time stamp (an epoch of the log)
   always stay together.  The merge window groups what one ranging cycle reports
   asynchronously -- ranges of one TWR round stamped a few milliseconds apart, a GPS
   sentence arriving with them -- into one update: a time stamp joins the current event
   when it lies at most ``merge_window_s`` after the event's *first* time (so windows do
   not chain: a log sampled faster than the window still gives one event per sample)
   and brings no value of a ``distinct`` component the event already holds from an
   earlier time stamp (a second range of the same anchor is the next cycle: it starts a
   new event, whatever the window).  An event's time is its first time stamp;
3. the filter predicts from event to event with the actual ``dt`` and updates with whatever
   arrived -- missing components are NaN, so the update only uses what is there.  A value
   reported twice at one time stamp (a duplicate row of one anchor, an RMC and a VTG
   sentence of one GPS fix) is averaged.

Several tags are processed together by *event index*: row ``k`` of every output holds the
events of tag ``k`` padded with NaN times at the end, so the ``j``-th step of all tags is one
vectorized filter step with per-tag ``dt`` (see :func:`robustloc.fusion.pipeline.run_filter`).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

Array = NDArray[np.float64]


@dataclass(frozen=True)
class Stream:
    """One measurement stream of one or more tags.

    Attributes
    ----------
    time_s : (L,) measurement times on the stream's own clock.
    tag : (L,) tag ids (strings).
    values : (L, c) values, NaN for absent components.
    columns : (c,) indices of the fused measurement vector these values fill.
    offset_s : float, added to ``time_s`` to reach the common (UWB) clock.
    """

    time_s: Array
    tag: NDArray[np.object_]
    values: Array
    columns: Sequence[int]
    offset_s: float = 0.0


@dataclass(frozen=True)
class Timeline:
    """Fused, event-indexed measurements of ``K`` tags.

    Attributes
    ----------
    tags : (K,) tag ids.
    time_s : (K, J) event times, NaN padding after a tag's last event.
    z : (K, J, m) fused measurements, NaN = not measured at that event.
    """

    tags: NDArray[np.object_]
    time_s: Array
    z: Array

    @property
    def n_events(self) -> NDArray[np.int64]:
        return np.isfinite(self.time_s).sum(axis=1)


def merge_streams(
    streams: Sequence[Stream], m: int, merge_window_s: float = 0.0,
    distinct: Sequence[int] = (), angles: Sequence[int] = (),
) -> Timeline:
    """Merge streams into one event timeline per tag (module docstring, steps 1-2).

    Parameters
    ----------
    streams : the measurement streams; their ``columns`` index a vector of length ``m``.
    m : length of the fused measurement vector.
    merge_window_s : a time stamp at most this long after its event's first time joins the
        event (windows never chain).
    distinct : components an event holds from one time stamp only: a later value of one
        of them starts a new event (the ranges of the anchors, the GPS speed and course:
        the next cycle's measurement, not this one's).  Values at one time stamp are
        averaged whatever ``distinct`` says.
    angles : angular components (radians): their values at one time stamp are averaged
        on the circle, ``atan2(mean sin, mean cos)`` (an RMC course of 179.97 deg and a VTG
        course of 180.0 deg, wrapped to +3.1411 and -3.1416 rad, averaged to 0 deg, due
        north, with the arithmetic mean).
    """
    if not merge_window_s >= 0:
        raise ValueError("merge_window_s must be >= 0")
    ts, tags, cols, vals = [], [], [], []
    for s in streams:
        t = np.asarray(s.time_s, dtype=float) + s.offset_s
        v = np.atleast_2d(np.asarray(s.values, dtype=float))
        if v.shape[0] != t.shape[0]:
            v = v.reshape(t.shape[0], -1)
        c = np.asarray(list(s.columns), dtype=int)
        if v.shape[1] != c.size or (c.size and (c.min() < 0 or c.max() >= m)):
            raise ValueError("stream columns do not match its values or the vector size")
        L = t.shape[0]
        ts.append(np.repeat(t, c.size))
        tags.append(np.repeat(np.asarray(s.tag, dtype=object).astype(str), c.size))
        cols.append(np.tile(c, L))
        vals.append(v.reshape(-1))
    t = np.concatenate(ts) if ts else np.empty(0)
    tag = np.concatenate(tags) if tags else np.empty(0, dtype=object)
    col = np.concatenate(cols) if cols else np.empty(0, dtype=int)
    val = np.concatenate(vals) if vals else np.empty(0)
    keep = np.isfinite(t) & np.isfinite(val)
    t, tag, col, val = t[keep], tag[keep], col[keep], val[keep]
    tag_u, tag_i = np.unique(tag.astype(str), return_inverse=True)
    order = np.lexsort((t, tag_i))
    t, tag_i, col, val = t[order], tag_i[order], col[order], val[order]
    K = tag_u.size
    # time stamps (one tag, one time): the atoms of the event grouping
    stamp = np.r_[True, (tag_i[1:] != tag_i[:-1]) | (t[1:] != t[:-1])] if t.size else (
        np.zeros(0, dtype=bool))
    first_row = np.flatnonzero(stamp)
    new = _event_starts(t[first_row], tag_i[first_row], first_row, col,
                        np.asarray(list(distinct), dtype=int), merge_window_s)
    ev = (np.cumsum(new) - 1)[np.cumsum(stamp) - 1]  # global event id of every value
    ev_tag = tag_i[first_row][new]
    ev_time = t[first_row][new]
    first_ev = np.searchsorted(ev_tag, np.arange(K))
    j_of_ev = np.arange(ev.max() + 1 if ev.size else 0) - first_ev[ev_tag]
    J = int(j_of_ev.max() + 1) if j_of_ev.size else 0
    time_s = np.full((K, J), np.nan)
    time_s[ev_tag, j_of_ev] = ev_time
    sums = np.zeros((K, J, m))
    counts = np.zeros((K, J, m))
    np.add.at(sums, (tag_i, j_of_ev[ev], col), val)
    np.add.at(counts, (tag_i, j_of_ev[ev], col), 1.0)
    with np.errstate(invalid="ignore"):
        z = np.where(counts > 0, sums / np.maximum(counts, 1.0), np.nan)
    ang = np.unique(np.asarray(list(angles), dtype=int))
    if ang.size:  # circular mean of the angular components, (K, J) per angle only (a
        # (K, J, m, 2) sum over every component added 12 % to the merge's peak memory)
        a = np.isin(col, ang)
        slot = np.zeros(m, dtype=np.intp)
        slot[ang] = np.arange(ang.size)
        at = (tag_i[a], j_of_ev[ev[a]], slot[col[a]])
        sin_sum = np.zeros((K, J, ang.size))
        cos_sum = np.zeros((K, J, ang.size))
        np.add.at(sin_sum, at, np.sin(val[a]))
        np.add.at(cos_sum, at, np.cos(val[a]))
        z[..., ang] = np.where(counts[..., ang] > 0, np.arctan2(sin_sum, cos_sum), np.nan)
    return Timeline(tags=tag_u.astype(object), time_s=time_s, z=z)


def _event_starts(
    g_time: Array, g_tag: NDArray[np.int64], first_row: NDArray[np.int64],
    col: NDArray[np.int64], distinct: NDArray[np.int64], window_s: float,
) -> NDArray[np.bool_]:
    """Which time stamps start an event (module docstring, step 2).

    Parameters
    ----------
    g_time, g_tag : (G,) time and tag index of each time stamp, sorted by tag then time.
    first_row : (G,) first value of each time stamp in ``col`` (its values run to the next
        stamp's first value).
    col : (L,) component of every value.
    distinct : components an event may hold from one time stamp only.
    window_s : the merge window.
    """
    G = g_time.size
    # certain starts: a new tag, or the previous stamp already more than the window back
    # (the event's first time is no later than that stamp)
    start = np.ones(G, dtype=bool)
    if G > 1:
        start[1:] = (g_tag[1:] != g_tag[:-1]) | (np.diff(g_time) > window_s)
    maybe = np.flatnonzero(~start)
    if maybe.size == 0:
        return start
    # The rest depends on where the current event began, which depends on the earlier
    # decisions: a sequential pass, over the stamps that can join their predecessor's
    # event and those predecessors only (none when the window is below the sampling
    # interval).
    dcol = np.where(np.isin(col, distinct), col, -1)
    bounds = np.r_[first_row, col.size]
    visit = np.union1d(maybe - 1, maybe).tolist()
    is_start = start.tolist()
    times = g_time.tolist()
    t0 = 0.0
    held: set[int] = set()
    for g in visit:
        here = set(dcol[bounds[g] : bounds[g + 1]].tolist())
        here.discard(-1)
        if is_start[g] or times[g] - t0 > window_s or not held.isdisjoint(here):
            start[g] = True
            t0 = times[g]
            held = here
        else:
            held |= here
    return start


def interp_at(t_query: ArrayLike, t: ArrayLike, values: ArrayLike) -> Array:
    """Linear interpolation of ``values (L, c)`` at ``t_query``; NaN outside ``t``'s span."""
    t = np.asarray(t, dtype=float)
    v = np.asarray(values, dtype=float)
    q = np.asarray(t_query, dtype=float)
    v2 = v.reshape(len(t), -1)
    out = np.stack([np.interp(q, t, v2[:, i]) for i in range(v2.shape[1])], axis=-1)
    out[(q < t[0]) | (q > t[-1])] = np.nan
    return out.reshape(q.shape + v.shape[1:])
