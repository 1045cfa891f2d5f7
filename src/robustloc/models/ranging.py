"""Measurement models of ranging: geometric range and log-distance RSSI.

Each model predicts the observations of ``N`` positions at once and gives their Jacobian,
so the same object simulates data (``predict`` plus noise) and estimates positions
(:func:`robustloc.estimators.nonlinear.gauss_newton`): the Stone Soup principle.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

Array = NDArray[np.float64]
LN10 = float(np.log(10.0))


def _anchors(a: ArrayLike) -> Array:
    a = np.asarray(a, dtype=float)
    if a.ndim != 2 or a.shape[1] not in (2, 3):
        raise ValueError(f"anchors must have shape (m, 2) or (m, 3), got {a.shape}")
    if not np.all(np.isfinite(a)):
        raise ValueError("anchor coordinates must be finite")
    return a


@dataclass(frozen=True)
class RangeModel:
    """Range from a tag at ``x`` to each anchor (seed 000 eq. (2)).

    ``d_i(x) = sqrt(|x - a_i|^2 + dz_i^2)``: in 2-D with ``height_offset`` given, ``dz_i`` is
    the known height difference between anchor ``i`` and the tag (slant ranges with a
    horizontal solution); otherwise 0.

    Parameters
    ----------
    anchors : (m, dim) anchor coordinates, dim = dimension of the solved position.
    height_offset : (m,) optional known vertical offsets (2-D solutions only).
    """

    anchors: Array
    height_offset: Array | None = None

    def __post_init__(self) -> None:
        object.__setattr__(self, "anchors", _anchors(self.anchors))
        if self.height_offset is not None:
            h = np.broadcast_to(np.asarray(self.height_offset, dtype=float), self.m).copy()
            object.__setattr__(self, "height_offset", h)

    @property
    def m(self) -> int:
        return int(self.anchors.shape[0])

    @property
    def dim(self) -> int:
        return int(self.anchors.shape[1])

    def _diff(self, x: ArrayLike) -> tuple[Array, Array]:
        x = np.atleast_2d(np.asarray(x, dtype=float))
        diff = x[:, None, :] - self.anchors[None, :, :]
        d2 = np.einsum("kmi,kmi->km", diff, diff)
        if self.height_offset is not None:
            d2 = d2 + self.height_offset[None, :] ** 2
        return diff, np.sqrt(d2)

    def predict(self, x: ArrayLike) -> Array:
        """Ranges ``(N, m)`` in metres from positions ``(N, dim)``."""
        return self._diff(x)[1]

    def jacobian(self, x: ArrayLike) -> Array:
        """``d range / d x``, shape ``(N, m, dim)``: unit vectors from the anchors."""
        return self.predict_jacobian(x)[1]

    def predict_jacobian(self, x: ArrayLike) -> tuple[Array, Array]:
        """Ranges and Jacobian in one pass."""
        diff, d = self._diff(x)
        return d, diff / np.maximum(d, 1e-9)[..., None]


@dataclass(frozen=True)
class RssiModel:
    """Log-distance RSSI ``A_i - 10 n_i lg d_i(x)`` (seed 000 eq. (1)) per anchor.

    Parameters
    ----------
    anchors : (m, dim) anchor coordinates.
    A : (m,) RSSI at 1 m (dBm).
    n : (m,) path-loss exponents.
    height_offset : (m,) optional known vertical offsets (see :class:`RangeModel`).
    min_distance_m : float
        Distances are floored here so the model stays finite at an anchor.
    """

    anchors: Array
    A: Array
    n: Array
    height_offset: Array | None = None
    min_distance_m: float = 0.1

    def __post_init__(self) -> None:
        a = _anchors(self.anchors)
        object.__setattr__(self, "anchors", a)
        object.__setattr__(self, "A", np.broadcast_to(np.asarray(self.A, float), a.shape[0]).copy())
        object.__setattr__(self, "n", np.broadcast_to(np.asarray(self.n, float), a.shape[0]).copy())
        if not (np.all(np.isfinite(self.A)) and np.all(np.isfinite(self.n)) and np.all(self.n > 0)):
            raise ValueError("path-loss parameters A must be finite and n positive")

    @property
    def ranges(self) -> RangeModel:
        return RangeModel(self.anchors, self.height_offset)

    def distance(self, rssi_dbm: ArrayLike) -> Array:
        """Invert eq. (1): ``d = 10^((A - RSSI) / (10 n))``."""
        r = np.asarray(rssi_dbm, dtype=float)
        return 10.0 ** ((self.A - r) / (10.0 * self.n))

    def predict(self, x: ArrayLike) -> Array:
        """RSSI ``(N, m)`` in dBm at positions ``(N, dim)``."""
        d = np.maximum(self.ranges.predict(x), self.min_distance_m)
        return self.A - 10.0 * self.n * np.log10(d)

    def jacobian(self, x: ArrayLike) -> Array:
        """``d RSSI / d x = -10 n / (ln 10 d^2) (x - a)``, shape ``(N, m, dim)``."""
        return self.predict_jacobian(x)[1]

    def predict_jacobian(self, x: ArrayLike) -> tuple[Array, Array]:
        """RSSI and Jacobian in one pass."""
        diff, d = self.ranges._diff(x)
        d = np.maximum(d, self.min_distance_m)
        pred = self.A - 10.0 * self.n * np.log10(d)
        return pred, (-10.0 * self.n / LN10 / (d * d))[..., None] * diff
