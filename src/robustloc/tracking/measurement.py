"""Tight measurement models of the tracker: each anchor's observation is one component.

* ranges: ``h_i(x) = sqrt((x - a_ix)^2 + (y - a_iy)^2 + dz_i^2) + b_i`` (m), the anchors'
  ``bias``/``scale`` calibration applied to the measured range beforehand exactly as
  ``robustloc locate`` does (``(range - bias) / scale``);
* RSSI: the anchor's log-distance model (seed 000 eq. (1); seed 002 eq. (5) with
  ``A = P_r(d0) + FAF``, ``n = gamma`` at ``d0 = 1 m``)
  ``h_i(x) = A_i - 10 n_i lg(max(d_i(x), d_min)) + b_i`` (dB).

``b_i`` is the link's offset (an environment change detected by the step detector of
:mod:`robustloc.tracking.tracker`); 0 until a step is found.  Jacobians are analytic:
``dd_i/dp = (p - a_i) / d_i``; ``dh_i/dp = -10 n_i / (ln 10 d_i^2) (p - a_i)`` for RSSI
(zero inside ``d_min``, where the model is clamped).  The state is ``[x, y, (vx, vy, ...)]``:
only the position columns of ``H`` are non-zero.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

Array = NDArray[np.float64]
LN10 = float(np.log(10.0))


@dataclass(frozen=True)
class LinkModel:
    """The anchors as seen by the tracker.

    Parameters
    ----------
    anchors_xy : (M, 2) anchor positions (m).
    kind : ``"range"`` or ``"rssi"``.
    dz2 : (M,) squared anchor-minus-tag height differences (slant ranges; 0 in the plane).
    A, n : (M,) log-distance parameters (RSSI only).
    sigma : (M,) a-priori standard deviation of one observation (m or dB).
    d_min_m : the RSSI model is clamped inside this distance (log of 0 otherwise).
    """

    anchors_xy: Array
    kind: str
    dz2: Array
    sigma: Array
    A: Array | None = None
    n: Array | None = None
    d_min_m: float = 0.3

    @property
    def M(self) -> int:
        return int(self.anchors_xy.shape[0])

    def distances(self, pos: Array) -> tuple[Array, Array]:
        """``d (K, M)`` and the differences ``p - a (K, M, 2)`` for positions ``(K, 2)``."""
        diff = pos[:, None, :2] - self.anchors_xy[None]
        with np.errstate(over="ignore"):  # an anchor at 1e300 (not used: inf is harmless)
            d = np.sqrt((diff * diff).sum(-1) + self.dz2[None])
        return d, diff

    def rssi(self, x: Array) -> Array:
        """The path-loss model's RSSI ``(K, M)`` at the positions of ``x`` (needs ``A, n``)."""
        d, _ = self.distances(x)
        return self.A[None] - 10.0 * self.n[None] * np.log10(np.maximum(d, self.d_min_m))

    def predict(self, x: Array) -> Array:
        """``h(x)`` without link offsets, ``(K, M)`` for states ``(K, n)``."""
        d, _ = self.distances(x)
        if self.kind == "range":
            return d
        return self.A[None] - 10.0 * self.n[None] * np.log10(np.maximum(d, self.d_min_m))

    def jacobian(self, x: Array) -> Array:
        """``dh/dx (K, M, n)``."""
        K, nst = x.shape
        d, diff = self.distances(x)
        J = np.zeros((K, self.M, nst))
        if self.kind == "range":
            J[:, :, :2] = diff / np.maximum(d, 1e-9)[..., None]
        else:
            g = np.where(d > self.d_min_m, -10.0 * self.n[None] / (LN10 * d * d), 0.0)
            J[:, :, :2] = g[..., None] * diff
        return J
