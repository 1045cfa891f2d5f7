"""Choosing the tracker's model from the log itself: the links' offsets, or none.

Links' offsets as states (``Tracker(link_offsets=True)``, item 11 of
:mod:`robustloc.tracking.tracker`) gain where the anchors' calibration misses what each
link reads where the tags walk, and cost where it does not (``M`` more states confounded
with the position until the tag has moved).  Which holds is a question of the log, and
the log answers it without truth: run the tracker both ways over (a sample of) the log
and keep the one whose one-step-ahead predictions of the observations score better
(prequential model choice, Dawid 1984: each prediction uses only the past, so a model's
extra states earn nothing unless they predict the next observation better).

The score of one observation with innovation ``nu = y - h(x-)`` and predicted variance
``S = (H P- H^T)_ii + sigma_i^2`` is the log density of a Huber-tailed distribution,
``-log(2 pi S) / 2 - rho(nu / sqrt(S))`` with ``rho`` Huber's loss at ``c = 1.345``
(95 % efficiency at the normal; Holland & Welsch 1977): a gross error costs linearly,
not quadratically, so a few blunders do not decide the choice.

The gain must hold beyond chance: the rows' score differences, in time order, are cut
into batches whose means are compared with zero by a one-sided t-test
(:func:`paired_batch_t`), since a filter's innovations are serially correlated.

Measured (``python benchmarks/bench_link_choice.py --seeds 20``, 2026-12-07, the
tracker's equivalent-variance update; the report's settings per data set, section
``s60_tracks``): the score per observation with the offsets minus without, t, and the
track RMS with the offsets over without -- simulated wifi-room walk (no offsets to find),
20 seeds: -0.10 to -0.12, t -6.0 to -9.0, 1.22-1.52x: off on every seed; ble-tetam
+0.23, t 10.6, 0.91x: on; uwb-dwm1001 LOS +0.002, t 1.0, 0.72x: off (a gain missed) and
NLOS +0.026, t 4.5, 0.83x: on; uwb-labyrinth +0.22, t 9.9, 0.81x: on.  Where the motion
model is too stiff for the motion the offsets also absorb its lag, which predicts the
observations better without placing the tag better: the walk at the default q = 1 (a
walker turning corners at 1 m/s) scored t up to 3.28 for them, 4 of 20 seeds 1.13-1.50x
worse with them; the test's level (:data:`AUTO_ALPHA`, 0.1 %) leaves
them out on every seed.  A ``q`` chosen for the motion (the report's per data set) keeps
the lag out of the comparison.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
import pandas as pd
from numpy.typing import ArrayLike, NDArray

Array = NDArray[np.float64]

#: Huber's constant of the score's loss: 95 % efficiency at the normal (Holland & Welsch
#: 1977), as the ``huber`` weight of :mod:`robustloc.robust`.
HUBER_C = 1.345
#: ``auto`` chooses only on sites of at most this many anchors: the offsets add one state
#: per anchor to every tag (``bench_track.py``: 85 k tag-epochs/s with 8 anchors, 370 with
#: 100), which a large site should choose knowingly (or calibrate by zones).
AUTO_MAX_ANCHORS = 24
#: ``auto`` runs both trackers over the log's first epochs, at most this many (the
#: choice's cost is bounded; the rest of the log is tracked once).
AUTO_SAMPLE_EPOCHS = 20_000
#: Fewer scored observations than this many per anchor cannot tell the models apart (a
#: link's offset needs the tag to move between its observations): no offsets.
AUTO_MIN_OBS_PER_ANCHOR = 20
#: Batches of the batch-means test (Schmeiser 1982: 10 to 30) and its one-sided level:
#: the offsets are kept only when they predict better beyond chance.  The level is 0.1 %
#: (``t(0.999; 19)`` = 3.58), not 5 % (1.73): ``auto`` is the default of ``track``, and
#: a wrong "on" costs more than a wrong "off" (M states that absorb a stiff model's lag:
#: up to 1.49x the RMS; a missed gain is at most the offsets' 8-28 %).  Measured with
#: ``benchmarks/bench_link_choice.py --seeds 20`` (2026-12-07, the equivalent-variance
#: update): the simulated walk at the default q (1) reached t 1.75-3.28 on the 6 of 20
#: seeds it chose the offsets on at 5 % (4 of them 1.13-1.50x worse), 0 of 20 at 0.1 %;
#: the real logs' choices at the report's settings are unchanged (ble-tetam t 10.6,
#: uwb-labyrinth 9.9, dwm1001 NLOS 4.5: on; dwm1001 LOS 1.0: off), and at the defaults
#: ble-tetam (10.6) and uwb-labyrinth (4.4) stay on while dwm1001 NLOS (2.5; 0.98x) goes
#: off.
AUTO_BATCHES = 20
AUTO_ALPHA = 0.001
#: The sample is tracked and scored in pieces of about this many epochs (cut where the
#: time changes), the recorded history dropped after each (``Tracker.forget_record``):
#: the same scores, in bounded memory (at 24 anchors the whole sample's history took the
#: trial from 370 MB to 1.07 GB).
AUTO_SCORE_PIECE = 2_000


def huber_log_score(nu: ArrayLike, S: ArrayLike, c: float = HUBER_C) -> Array:
    """The log score of innovations ``nu`` with predicted variances ``S`` (elementwise):
    ``-log(2 pi S) / 2 - rho(u)``, ``u = nu / sqrt(S)``, ``rho(u) = u^2 / 2`` for
    ``|u| <= c`` and ``c |u| - c^2 / 2`` beyond (Huber 1964, eq. (7)).  For ``|u| <= c``
    it is the Gaussian log density."""
    nu = np.asarray(nu, dtype=float)
    S = np.asarray(S, dtype=float)
    u = np.abs(nu) / np.sqrt(S)
    rho = np.where(u <= c, 0.5 * u * u, c * u - 0.5 * c * c)
    return -0.5 * np.log(2.0 * np.pi * S) - rho


@dataclass(frozen=True)
class LinkOffsetChoice:
    """What ``link_offsets="auto"`` chose, and on what.

    Attributes
    ----------
    use : estimate the links' offsets.
    reason : one line saying why.
    score_without, score_with : predictive score per observation of the tracker without
        and with the offsets (NaN where not run).
    observations : observations scored; epochs : epochs of the sample.
    t, t_critical : the batch-means t statistic of the score difference
        (:func:`paired_batch_t`) and its one-sided critical value (NaN where not run).
    """

    use: bool
    reason: str
    score_without: float = float("nan")
    score_with: float = float("nan")
    observations: int = 0
    epochs: int = 0
    t: float = float("nan")
    t_critical: float = float("nan")

    def as_dict(self) -> dict[str, Any]:
        """The choice for a JSON summary (NaN scores as None)."""
        def num(v: float) -> float | None:
            return round(v, 4) if np.isfinite(v) else None

        return {"used": self.use, "reason": self.reason,
                "score_without": num(self.score_without),
                "score_with": num(self.score_with),
                "observations": self.observations, "epochs": self.epochs,
                "t": num(self.t), "t_critical": num(self.t_critical)}


def _head(epochs: Any, n: int) -> Any:
    """The first ``n`` epochs of ``epochs`` (an :class:`robustloc.io.tables.Epochs`)."""
    return epochs if epochs.n_epochs <= n else epochs.take(slice(0, n))


def _pieces(time: NDArray[np.float64], size: int) -> list[int]:
    """Row boundaries ``[0, ..., N]`` of pieces of about ``size`` rows, each cut where
    the time changes (an epoch time's rows stay in one piece, as in a streamed block)."""
    N = len(time)
    cuts = [0]
    while N - cuts[-1] > size:
        k = cuts[-1] + size
        k += int(np.argmax(time[k:] != time[k - 1])) if np.any(time[k:] != time[k - 1]) \
            else N - k
        if k >= N:
            break
        cuts.append(k)
    return cuts + [N]


def choose_link_offsets(anchors: pd.DataFrame, epochs: Any,
                        progress: Callable[[int], Any] | None = None, **options: Any,
                        ) -> LinkOffsetChoice:
    """Track the log's first epochs without and with the links' offsets and keep the
    model whose one-step predictions score better (the module docstring).

    Parameters
    ----------
    anchors : DataFrame
        The anchors, as for :class:`~robustloc.tracking.Tracker`.
    epochs : :class:`robustloc.io.tables.Epochs`
        The log (time-sorted per tag); its first :data:`AUTO_SAMPLE_EPOCHS` are used.
    progress : callable, optional
        Called with the epochs of each piece tracked (both runs: twice the sample's
        epochs in all), for a progress bar.
    **options
        The tracker's other settings (``model``, ``filter``, ``q``, ...), the same for
        both runs; ``link_offsets`` is not one of them.

    Returns
    -------
    LinkOffsetChoice
    """
    from robustloc.tracking.tracker import Tracker

    opts = {k: v for k, v in options.items() if k != "link_offsets"}
    M = len(anchors)
    refused = refusal(M, opts)
    if refused is not None:
        return refused
    sample = _head(epochs, AUTO_SAMPLE_EPOCHS)
    need = AUTO_MIN_OBS_PER_ANCHOR * M
    heard = int(np.isfinite(sample.values).sum())  # at least the observations scored
    if heard < need:  # (without running the trackers: the default's cost on short logs)
        return LinkOffsetChoice(False, f"{heard} observations heard, fewer than the {need} "
                                       "that tell the models apart",
                                epochs=int(sample.n_epochs))
    cuts = _pieces(sample.time, AUTO_SCORE_PIECE)
    scores = []
    for links in (False, True):
        trk = Tracker(anchors, record=True, link_offsets=links, **opts)
        parts = []
        for lo, hi in zip(cuts[:-1], cuts[1:]):
            piece = sample.take(slice(lo, hi))
            trk.step(piece)
            parts.append(trk.predictive_score(piece.values))
            trk.forget_record()
            if progress is not None:
                progress(piece.n_epochs)
        scores.append((np.concatenate([r for r, _ in parts]),
                       np.concatenate([c for _, c in parts])))
    (r0, c0), (r1, c1) = scores
    return decide_link_offsets(r0, c0, r1, c1, M, int(sample.n_epochs))


def refusal(n_anchors: int, options: dict[str, Any]) -> LinkOffsetChoice | None:
    """The choice made without a trial (``off``, and why), or None when a trial decides:
    a tag's common range offset estimated instead, a standing tag (``model="static"``),
    or more than :data:`AUTO_MAX_ANCHORS` anchors.

    A standing tag never moves between a link's observations, so its links' offsets stay
    confounded with its position for the whole log (the module docstring): through
    bursts of attenuation they predict the observations better while placing the tag
    worse.  Measured (``python benchmarks/bench_blockage.py``: simulated ble-corridor
    with people walking, 5 runs, mean error): a trial chose them in 4 of 5 runs and they
    helped in 1; 0.950 m with the trial's choice against 0.896 m without them (0.891
    against 0.787 m smoothed)."""
    if options.get("range_offset"):
        return LinkOffsetChoice(False, "the tag's common range offset is estimated "
                                       "instead (--range-offset)")
    if options.get("model") == "static":
        return LinkOffsetChoice(False, "a standing tag (--model static): its links' "
                                       "offsets stay confounded with its position")
    if n_anchors > AUTO_MAX_ANCHORS:
        return LinkOffsetChoice(False, f"{n_anchors} anchors (auto chooses on sites of at "
                                       f"most {AUTO_MAX_ANCHORS}: one state per anchor and "
                                       "tag)")
    return None


def decide_link_offsets(r0: ArrayLike, c0: ArrayLike, r1: ArrayLike, c1: ArrayLike,
                        n_anchors: int, epochs: int) -> LinkOffsetChoice:
    """The choice from the two trackers' per-row predictive scores over the same rows in
    time order (:meth:`~robustloc.tracking.Tracker.predictive_score`: ``r0, c0`` without
    the offsets, ``r1, c1`` with them): rows scored alike by both are compared, at least
    :data:`AUTO_MIN_OBS_PER_ANCHOR` observations per anchor, by :func:`paired_batch_t` at
    :data:`AUTO_ALPHA`.  Shared by :func:`choose_link_offsets` (a log's first epochs) and
    :class:`robustloc.tracking.auto.AutoTracker` (a stream's)."""
    r0, r1 = np.asarray(r0, dtype=float), np.asarray(r1, dtype=float)
    c0, c1 = np.asarray(c0, dtype=np.int64), np.asarray(c1, dtype=np.int64)
    need = AUTO_MIN_OBS_PER_ANCHOR * n_anchors
    both = np.isfinite(r0) & np.isfinite(r1) & (c0 == c1)
    n_obs = int(c0[both].sum())
    s0 = float(r0[both].sum() / n_obs) if n_obs else float("nan")
    s1 = float(r1[both].sum() / n_obs) if n_obs else float("nan")
    base: dict[str, Any] = {"score_without": s0, "score_with": s1, "observations": n_obs,
                            "epochs": int(epochs)}
    if n_obs < need:
        return LinkOffsetChoice(False, f"{n_obs} observations scored, fewer than the {need} "
                                       "that tell the models apart", **base)
    t, crit = paired_batch_t(r1[both] - r0[both], c0[both])
    base.update(t=t, t_critical=crit)
    if not t > crit:
        return LinkOffsetChoice(False, "the links' offsets did not predict the "
                                       f"observations clearly better ({s1:.4f} against "
                                       f"{s0:.4f} per observation, t = {t:.2f} <= {crit:.2f})",
                                **base)
    return LinkOffsetChoice(True, "the links' offsets predicted the observations better "
                                  f"({s1:.4f} against {s0:.4f} per observation, t = "
                                  f"{t:.2f} > {crit:.2f})", **base)


def paired_batch_t(diff: ArrayLike, count: ArrayLike, batches: int = AUTO_BATCHES,
                   alpha: float = AUTO_ALPHA) -> tuple[float, float]:
    """Batch-means t statistic of a score difference, and its one-sided critical value.

    The rows (in time order) are cut into ``batches`` contiguous batches of about equal
    observation counts; each batch's mean difference per observation is one sample, so
    that the serial correlation of a filter's innovations (which makes the rows far from
    independent) stays inside the batches (batch means: Schmeiser 1982, 10 to 30
    batches).  ``t = mean / (sd / sqrt(B))`` against Student's ``t(1 - alpha; B - 1)``.

    Parameters
    ----------
    diff : per row, the score with the offsets minus without (sums over the row's
        observations); count : per row, its observations.
    """
    from scipy.stats import t as student_t

    d = np.asarray(diff, dtype=float)
    c = np.asarray(count, dtype=float)
    B = int(min(batches, d.size))
    if B < 2:
        return float("nan"), float("inf")
    edges = np.searchsorted(np.cumsum(c), np.linspace(0.0, c.sum(), B + 1)[1:-1],
                            side="right")
    means = np.array([ds.sum() / cs.sum() for ds, cs in
                      zip(np.split(d, edges), np.split(c, edges)) if cs.sum() > 0])
    B = means.size
    crit = float(student_t.ppf(1.0 - alpha, B - 1)) if B >= 2 else float("inf")
    sd = float(np.std(means, ddof=1)) if B >= 2 else float("nan")
    if not sd > 0:
        return float("nan"), crit
    return float(means.mean() / (sd / np.sqrt(B))), crit
