"""Rauch-Tung-Striebel smoothing of the tracker's forward pass (fixed interval, fixed lag).

For one tag's filtered states ``x_k|k, P_k|k`` and the predictions into the next epoch
``x_k+1|k = F_k+1 x_k|k``, ``P_k+1|k`` (Rauch, Tung & Striebel 1965):

``C_k = P_k|k F_k+1^T P_k+1|k^-1``
``x_k|N = x_k|k + C_k (x_k+1|N - x_k+1|k)``
``P_k|N = P_k|k + C_k (P_k+1|N - P_k+1|k) C_k^T``

The forward pass is the robust one: each ``x_k|k, P_k|k`` already carries the equivalent
weights of its update (a rejected range had weight 0, a held-out link was not used), so
the smoother inherits the forward pass's robust weights; outliers are not re-admitted by
smoothing.  A re-start of the filter (divergence) cuts the tag's history into independent
segments.

Fixed lag ``L``: the estimate of epoch ``k`` uses epochs up to ``k + L`` only (``L``
backward steps from the filtered state at ``k + L``), the near-real-time variant.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray

Array = NDArray[np.float64]


def _rts_steps(xf: Array, Pf: Array, xp: Array, Pp: Array, F: Array) -> Array:
    """Gains ``C_k (L-1, n, n)`` for a segment: ``Pf[k] F[k+1]^T Pp[k+1]^-1``."""
    A = Pf[:-1] @ np.swapaxes(F[1:], 1, 2)  # (L-1, n, n)
    # C = A Pp^-1  <=>  Pp^T C^T = A^T  (Pp symmetric)
    return np.swapaxes(np.linalg.solve(Pp[1:], np.swapaxes(A, 1, 2)), 1, 2)


def rts_segment(xf: Array, Pf: Array, xp: Array, Pp: Array, F: Array,
                lag: int | None = None) -> tuple[Array, Array]:
    """Smooth one segment (``L`` epochs).  ``xp[k], Pp[k], F[k]``: prediction into ``k``.

    ``lag=None``: fixed interval; ``lag=N``: fixed lag ``N`` epochs.  A lag of ``L - 1``
    epochs or more reaches the segment's end from every epoch: it is the fixed-interval
    smoother, at the same cost (the work is bounded by the segment, not by ``lag``).
    """
    L = len(xf)
    if L < 2 or lag == 0:
        return xf.copy(), Pf.copy()
    C = _rts_steps(xf, Pf, xp, Pp, F)
    if lag is not None and lag >= L - 1:
        # every epoch's window reaches the segment's end: the fixed-interval smoother
        # (the backward steps beyond the end would do nothing, ``lag`` times over)
        lag = None
    if lag is None:
        xs, Ps = xf.copy(), Pf.copy()
        for k in range(L - 2, -1, -1):
            Ck = C[k]
            xs[k] = xf[k] + Ck @ (xs[k + 1] - xp[k + 1])
            Ps[k] = Pf[k] + Ck @ (Ps[k + 1] - Pp[k + 1]) @ Ck.T
        return xs, 0.5 * (Ps + np.swapaxes(Ps, 1, 2))
    # fixed lag: every epoch k starts from the filtered state at e_k = min(k + lag, L - 1)
    k = np.arange(L)
    e = np.minimum(k + lag, L - 1)
    xs = xf[e].copy()
    Ps = Pf[e].copy()
    for j in range(lag - 1, -1, -1):
        pos = k + j  # smooth from pos + 1 to pos
        act = pos < e
        if not act.any():
            continue
        p = pos[act]
        Cp = C[p]
        xs[act] = xf[p] + np.einsum("kij,kj->ki", Cp, xs[act] - xp[p + 1])
        Ps[act] = Pf[p] + Cp @ (Ps[act] - Pp[p + 1]) @ np.swapaxes(Cp, 1, 2)
    return xs, 0.5 * (Ps + np.swapaxes(Ps, 1, 2))


def rts_rows(history: list[dict[str, Any]], n_rows: int, n: int, motion: Any,
             lag: int | None = None) -> tuple[Array, Array]:
    """Smooth the recorded steps of a :class:`~robustloc.tracking.Tracker` (by output row).

    ``history`` entries hold ``idx`` (rows), ``slot`` (tag), ``start`` (a (re)start: no
    link to the previous epoch), ``xf, Pf`` (filtered), ``xp, Pp`` (predicted into that
    epoch) and ``dt``.  Later entries for the same row replace earlier ones (a re-start
    replaces the filtered row that detected the divergence).
    """
    xs = np.full((n_rows, n), np.nan)
    Ps = np.full((n_rows, n, n), np.nan)
    if not history:
        return xs, Ps
    idx = np.concatenate([h["idx"] for h in history])
    seq = np.arange(len(idx))
    last = np.full(n_rows, -1)
    last[idx] = seq  # the last entry of each row wins
    keep = last[idx] == seq
    cat = {k: np.concatenate([h[k] for h in history])[keep]
           for k in ("idx", "slot", "start", "xf", "Pf", "xp", "Pp", "dt")}
    order = np.lexsort((seq[keep], cat["slot"]))  # by tag, then forward order
    c = {k: v[order] for k, v in cat.items()}
    F = motion.F(c["dt"])
    # segments: a new tag or a (re)start begins one
    new = np.r_[True, (c["slot"][1:] != c["slot"][:-1]) | c["start"][1:]]
    edges = np.r_[np.flatnonzero(new), len(new)]
    for a, b in zip(edges[:-1], edges[1:]):
        sx, sP = rts_segment(c["xf"][a:b], c["Pf"][a:b], c["xp"][a:b], c["Pp"][a:b],
                             F[a:b], lag)
        xs[c["idx"][a:b]] = sx
        Ps[c["idx"][a:b]] = sP
    return xs, Ps
