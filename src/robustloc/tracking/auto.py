"""A tracker that lets a stream's first epochs choose the links' offsets.

``robustloc track`` (``--link-offsets auto``, its default) chooses before it tracks: it
runs :class:`~robustloc.tracking.Tracker` without and with the links' offsets over the
log's first :data:`~robustloc.tracking.select.AUTO_SAMPLE_EPOCHS` epochs and keeps the
model whose one-step-ahead predictions of the observations score better
(:func:`~robustloc.tracking.select.choose_link_offsets`).  A live stream has no log to
look at before its first row.  :class:`AutoTracker` makes the same choice as the epochs
come:

* **Trial.**  Both trackers advance on every epoch; the rows given back are those of the
  tracker without the offsets (the default's rows until the log has spoken).  A block is
  tracked in pieces of at most :data:`~robustloc.tracking.select.AUTO_SCORE_PIECE`
  epochs, after each of which both trackers' predictive scores of its rows are kept
  (:meth:`~robustloc.tracking.Tracker.predictive_score`, then
  :meth:`~robustloc.tracking.Tracker.forget_record`): memory stays that of the scores,
  four numbers per epoch, however large a block the service hands over (a backlog, a
  replay after a restart).
* **Choice.**  After exactly ``sample_epochs`` epochs (a block that crosses the count is
  cut there: the choice does not depend on how the stream was cut into blocks, nor on a
  restart that replays it in other blocks), the scores are compared by the same test as
  ``track``'s (:func:`~robustloc.tracking.select.decide_link_offsets`: batch means,
  one-sided level :data:`~robustloc.tracking.select.AUTO_ALPHA`).  The chosen tracker has
  followed every epoch of the trial, so it continues without a restart (the rest of the
  block included); the other is dropped.
* **A failing trial.**  Should the tracker with the offsets fail on a block (a numerical
  failure: both trackers refuse bad input alike, before anything changes), the trial
  ends there with the offsets off and the error as the reason; the rows given back,
  those of the tracker without them, are unaffected.  A failure of that tracker leaves
  both as they were before the block (:meth:`AutoTracker.step` is all or nothing).
* **No trial** where ``track`` runs none: with ``range_offset`` (the tag's common offset
  is estimated instead) or more than :data:`~robustloc.tracking.select.AUTO_MAX_ANCHORS`
  anchors, the offsets are off from the start.

On the same epochs, in the same order, the choice is ``track``'s on the first
``sample_epochs`` epochs (the same scores, in the same rows: ``tests/test_track_auto.py``),
and after the choice the rows are the chosen tracker's.
The rows before the choice are the tracker's without the offsets: the price of a choice
made on data not yet seen.  The trial runs both trackers and scores both on every step,
for ``sample_epochs`` epochs only: ``benchmarks/bench_track.py`` (300 tags x 8 anchors
of ranges, CV, one core, 2026-12-07) measured 43 k tag-epochs per second during the
trial against 157 k for the plain tracker (EKF) and 85 k with the offsets; UKF 34 k
against 140 k and 55 k.

Example
-------
>>> trk = AutoTracker(anchors, model="cv", sample_epochs=5_000)   # doctest: +SKIP
>>> rows = trk.step(epochs)                                      # doctest: +SKIP
>>> trk.status()                                                 # doctest: +SKIP
{'mode': 'auto', 'phase': 'trial', 'epochs': 1200, 'sample_epochs': 5000}
"""

from __future__ import annotations

import math
from dataclasses import asdict, fields
from typing import Any

import numpy as np
import pandas as pd

from robustloc.tracking.select import (
    AUTO_SAMPLE_EPOCHS,
    AUTO_SCORE_PIECE,
    LinkOffsetChoice,
    decide_link_offsets,
    refusal,
)
from robustloc.tracking.tracker import Tracker

#: Version of :meth:`AutoTracker.state_dict`'s format.
STATE_VERSION = 1


def _floats(a: np.ndarray) -> list[float | None]:
    """JSON-safe floats (NaN as None)."""
    return [None if not math.isfinite(v) else float(v) for v in a.tolist()]


def _array(v: Any, name: str, dtype: type) -> np.ndarray:
    if not isinstance(v, list):
        raise ValueError(f"saved auto tracker state's {name} must be a list")
    return np.array([np.nan if u is None else u for u in v], dtype=dtype)


class AutoTracker:
    """:class:`~robustloc.tracking.Tracker` with ``link_offsets`` chosen by the stream's
    first ``sample_epochs`` epochs (the module docstring).

    Parameters
    ----------
    anchors : DataFrame
        The anchors, as for :class:`~robustloc.tracking.Tracker`.
    model, filter : str
        Motion model and filter, as for :class:`~robustloc.tracking.Tracker`.
    sample_epochs : int
        Epochs of the trial (default :data:`~robustloc.tracking.select.AUTO_SAMPLE_EPOCHS`,
        ``track``'s sample).
    **options
        The tracker's other settings (``q``, ``sigma``, ...); not ``link_offsets`` (this
        class chooses it) nor ``record``.

    Attributes
    ----------
    choice : LinkOffsetChoice or None
        What was chosen and why; None while the trial runs.
    """

    def __init__(self, anchors: pd.DataFrame, *, model: str = "cv", filter: str = "ekf",
                 sample_epochs: int = AUTO_SAMPLE_EPOCHS, **options: Any) -> None:
        for name in ("link_offsets", "record"):
            if name in options:
                raise TypeError(f"AutoTracker chooses {name} itself; use Tracker to set it"
                                if name == "link_offsets" else
                                "AutoTracker does not record (use Tracker(record=True))")
        if isinstance(sample_epochs, bool) or not isinstance(sample_epochs,
                                                             (int, np.integer)) \
                or sample_epochs < 1:
            raise ValueError(f"sample_epochs must be a positive integer, got {sample_epochs!r}")
        self.sample_epochs = int(sample_epochs)
        self._options: dict[str, Any] = {"model": model, "filter": filter, **options}
        live = Tracker(anchors, **self._options)  # the options checked once, here
        choice = refusal(len(live.anchor_ids), self._options)
        #: (epochs of the trial so far, the choice or None): one attribute, replaced
        #: whole, so that a reader on another thread (the service's /api/status) never
        #: sees the count of one moment with the choice of another
        self._progress: tuple[int, LinkOffsetChoice | None] = (0, choice)
        self._anchors = anchors
        self._live = live
        self._shadow: Tracker | None = None
        if choice is None:
            from scipy.stats import t as _student_t  # noqa: F401  (the test's, imported
            # now: lazily inside the step that chooses, it held /api/status's view of a
            # half-made choice open for a second)

            live.record = True
            self._shadow = Tracker(anchors, record=True, link_offsets=True, **self._options)
        self._scores: list[tuple[np.ndarray, ...]] = []

    # ------------------------------------------------------------------ properties
    @property
    def tracker(self) -> Tracker:
        """The tracker whose rows :meth:`step` gives (without the offsets until chosen)."""
        return self._live

    @property
    def anchor_ids(self) -> tuple[str, ...]:
        """The anchors' ids, in the epochs' column order."""
        return self._live.anchor_ids

    @property
    def tags(self) -> list[str]:
        """Tags seen so far (and not forgotten)."""
        return self._live.tags

    @property
    def choice(self) -> LinkOffsetChoice | None:
        """What was chosen and why; None while the trial runs."""
        return self._progress[1]

    @property
    def trial_epochs(self) -> int:
        """Epochs the trial has scored so far."""
        return self._progress[0]

    def status(self) -> dict[str, Any]:
        """What a service shows: the trial's progress, or the choice (``as_dict``)."""
        epochs, choice = self._progress
        if choice is None:
            return {"mode": "auto", "phase": "trial", "epochs": epochs,
                    "sample_epochs": self.sample_epochs}
        return {"mode": "auto", "phase": "chosen", "sample_epochs": self.sample_epochs,
                **choice.as_dict()}

    def link_offsets(self) -> pd.DataFrame:
        """The chosen tracker's links' offsets (:meth:`Tracker.link_offsets`; empty while
        the trial runs or when the offsets were left out)."""
        return self._live.link_offsets()

    # ------------------------------------------------------------------ tracking
    def step(self, epochs: Any) -> pd.DataFrame:
        """Advance each tag by ``epochs`` (as :meth:`Tracker.step`); one track row per
        epoch, in the order of ``epochs``.  During the trial, all or nothing: a block
        that raises leaves both trackers, the scores and the count as they were."""
        N = getattr(epochs, "n_epochs", None)
        if self._shadow is None or not N:  # (not Epochs: the tracker's own TypeError)
            return self._live.step(epochs)
        N = int(N)
        cut = min(N, self.sample_epochs - self._progress[0])  # the trial's epochs of it
        saved = self.checkpoint()
        try:
            frames = []
            for lo in range(0, cut, AUTO_SCORE_PIECE):
                hi = min(lo + AUTO_SCORE_PIECE, cut)
                frames.append(self._trial_piece(epochs if (lo, hi) == (0, N)
                                                else epochs.take(slice(lo, hi))))
            if self._shadow is not None and self._progress[0] >= self.sample_epochs:
                self._choose(self.sample_epochs)
            if cut < N:  # the rest of the block: the chosen tracker's alone
                frames.append(self._live.step(epochs.take(slice(cut, N))))
        except BaseException:
            self.rollback(saved)
            raise
        return frames[0] if len(frames) == 1 else pd.concat(frames, ignore_index=True)

    def _trial_piece(self, piece: Any) -> pd.DataFrame:
        """One piece of the trial: both trackers stepped and scored, their records
        dropped.  The tracker with the offsets failing ends the trial (offsets off, the
        error as the reason); the rows are the other's either way."""
        rows = self._live.step(piece)
        if self._shadow is None:  # (the trial ended on an earlier piece of this block)
            return rows
        try:
            self._shadow.step(piece)
            scored = self._shadow.predictive_score(piece.values)
        except Exception as exc:  # noqa: BLE001 - a numerical failure of the trial alone
            self._end_trial(LinkOffsetChoice(
                False, "the tracker with the links' offsets failed during the trial "
                       f"({type(exc).__name__}: {exc}); the offsets stay off",
                epochs=self._progress[0]))
            return rows
        self._scores.append((*self._live.predictive_score(piece.values), *scored))
        self._live.forget_record()
        self._shadow.forget_record()
        self._progress = (self._progress[0] + int(piece.n_epochs), None)
        return rows

    def _choose(self, epochs: int) -> None:
        """The trial's verdict on its first ``epochs`` (the sample): keep one tracker,
        drop the other and the scores."""
        r0, c0, r1, c1 = (np.concatenate([s[k] for s in self._scores])[:epochs]
                          for k in range(4))
        self._end_trial(decide_link_offsets(r0, c0, r1, c1, len(self.anchor_ids), epochs))

    def _end_trial(self, choice: LinkOffsetChoice) -> None:
        if choice.use and self._shadow is not None:
            self._live = self._shadow
        self._live.forget_record()
        self._live.record = False
        self._shadow = None
        self._scores = []
        self._progress = (choice.epochs, choice)

    def forget(self, tags: Any) -> int:
        """Drop every state of ``tags`` (:meth:`Tracker.forget`), in both trackers while
        the trial runs; returns the number of tags forgotten."""
        if self._shadow is not None:
            self._shadow.forget(tags)
        return self._live.forget(tags)

    # ------------------------------------------------------------------ state
    def checkpoint(self) -> dict[str, Any]:
        """An in-memory copy for :meth:`rollback` (both trackers', and the scores)."""
        return {"live": (self._live, self._live.checkpoint()),
                "shadow": None if self._shadow is None else (self._shadow,
                                                             self._shadow.checkpoint()),
                "progress": self._progress, "scores": list(self._scores)}

    def rollback(self, checkpoint: dict[str, Any]) -> None:
        """Return to a :meth:`checkpoint` (a block that failed is undone in both trackers,
        the choice included when the block had made it)."""
        if not isinstance(checkpoint, dict) or not {"live", "shadow", "progress",
                                                    "scores"} <= set(checkpoint):
            raise TypeError("rollback() takes what checkpoint() returned, got "
                            f"{type(checkpoint).__name__}")
        live, saved = checkpoint["live"]
        live.rollback(saved)
        shadow = None
        if checkpoint["shadow"] is not None:
            shadow, saved = checkpoint["shadow"]
            shadow.rollback(saved)
        self._live, self._shadow = live, shadow
        self._scores = list(checkpoint["scores"])
        self._progress = checkpoint["progress"]

    def _tracker_for(self, choice: LinkOffsetChoice | None) -> Tracker:
        """A fresh tracker of the model the live rows come from under ``choice``."""
        on = choice is not None and choice.use
        trk = Tracker(self._anchors, link_offsets=on, **self._options)
        trk.record = choice is None
        return trk

    def state_dict(self) -> dict:
        """JSON-serialisable state: the trial's scores or the choice, and the trackers'
        :meth:`Tracker.state_dict` (both while the trial runs)."""
        scores = None
        if self.choice is None:
            if self._scores:
                arrays = [np.concatenate([s[k] for s in self._scores]) for k in range(4)]
            else:
                arrays = [np.zeros(0), np.zeros(0, np.int64), np.zeros(0),
                          np.zeros(0, np.int64)]
            scores = {"without": _floats(arrays[0]), "count_without": arrays[1].tolist(),
                      "with": _floats(arrays[2]), "count_with": arrays[3].tolist()}
        choice = None
        if self.choice is not None:
            choice = {k: (None if isinstance(v, float) and not math.isfinite(v) else v)
                      for k, v in asdict(self.choice).items()}
        return {"version": STATE_VERSION, "kind": "auto-link-offsets",
                "sample_epochs": self.sample_epochs, "epochs": self._progress[0],
                "choice": choice, "scores": scores, "live": self._live.state_dict(),
                "shadow": None if self._shadow is None else self._shadow.state_dict()}

    def load_state_dict(self, state: dict) -> None:
        """Restore a :meth:`state_dict` (settings and anchors must match).  All or
        nothing: a state that cannot be loaded raises ``ValueError`` (``TypeError`` for
        one that is not a dict) and leaves this tracker as it was.

        A choice already made keeps the sample it was made on (``sample_epochs`` becomes
        the saved one); a trial still running goes on to this tracker's
        ``sample_epochs``, and one that has passed it chooses at once on its first
        ``sample_epochs`` epochs."""
        if not isinstance(state, dict):
            raise TypeError(f"state must be a dict from state_dict(), got "
                            f"{type(state).__name__}")
        if state.get("kind") != "auto-link-offsets":
            raise ValueError("saved tracker state is not an auto tracker's (link offsets "
                             "on or off, not auto)")
        if state.get("version") != STATE_VERSION:
            raise ValueError(f"unsupported auto tracker state version "
                             f"{state.get('version')!r}")
        try:
            epochs = state["epochs"]
            if isinstance(epochs, bool) or not isinstance(epochs, int) or epochs < 0:
                raise ValueError(f"saved auto tracker state's epochs must be a count, got "
                                 f"{epochs!r}")
            sample = state["sample_epochs"]
            if isinstance(sample, bool) or not isinstance(sample, int) or sample < 1:
                raise ValueError(f"saved auto tracker state's sample_epochs must be a "
                                 f"positive count, got {sample!r}")
            choice = None
            if state["choice"] is not None:
                names = {f.name for f in fields(LinkOffsetChoice)}
                c = dict(state["choice"])
                if set(c) != names:
                    raise ValueError("saved auto tracker choice has other fields")
                c = {k: (float("nan") if v is None else v) for k, v in c.items()}
                choice = LinkOffsetChoice(**c)
            live = self._tracker_for(choice)
            live.load_state_dict(state["live"])
            shadow, scores = None, []
            if choice is None:
                if state["shadow"] is None or state["scores"] is None:
                    raise ValueError("saved auto tracker state in trial lacks its "
                                     "shadow tracker or scores")
                shadow = Tracker(self._anchors, record=True, link_offsets=True,
                                 **self._options)
                shadow.load_state_dict(state["shadow"])
                s = state["scores"]
                arrays = (_array(s["without"], "scores", float),
                          _array(s["count_without"], "counts", np.int64),
                          _array(s["with"], "scores", float),
                          _array(s["count_with"], "counts", np.int64))
                if {a.size for a in arrays} != {epochs}:
                    raise ValueError(f"saved auto tracker scores do not cover its {epochs} "
                                     "epochs")
                scores = [arrays]
        except KeyError as exc:
            raise ValueError(f"saved auto tracker state lacks {exc}") from None
        except TypeError as exc:
            raise ValueError(f"saved auto tracker state is malformed ({exc})") from None
        self._live, self._shadow, self._scores = live, shadow, scores
        self._progress = (epochs, choice)
        if choice is not None:
            self.sample_epochs = sample  # (the sample the choice was made on)
        elif epochs >= self.sample_epochs:
            self._choose(self.sample_epochs)  # (restarted with a shorter sample)
