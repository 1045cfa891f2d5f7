"""Robust scale estimators."""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

#: Normal consistency constant of the MAD, ``Phi^-1(3/4)``.
MAD_NORMAL = 0.6744897501960817


def mad_scale(
    residuals: ArrayLike, axis: int = -1, center: bool = False, floor: float = 0.0
) -> NDArray[np.float64]:
    """Robust scale ``sigma = med|v| / 0.6745`` (seed 000, sec. 2.1), NaN-aware.

    Parameters
    ----------
    residuals : array_like
        Residuals; NaN entries (missing observations) are ignored.
    axis : int
        Axis along which the scale is computed (default: last, one scale per epoch).
    center : bool
        If True subtract the median first (the classical MAD); the paper uses ``med|v|``
        of least-squares residuals, which are already centred, so the default is False.
    floor : float
        Lower bound on the returned scale, to keep standardized residuals finite when
        most residuals are exactly zero (noise-free data).

    Returns
    -------
    ndarray
        Scale with ``axis`` removed; NaN where every entry is NaN or there is none.

    Raises
    ------
    ValueError
        For a 0-d ``residuals`` (a scalar has no axis to take the scale along).
    """
    v = np.asarray(residuals, dtype=float)
    if v.ndim == 0:  # (numpy's AxisError named neither residuals nor the cause)
        raise ValueError(f"residuals must be an array with an axis, got the scalar {v}")
    if center:
        v = v - nanmedian_fast(v, axis=axis)[..., None] if axis in (-1, v.ndim - 1) else (
            v - np.nanmedian(v, axis=axis, keepdims=True))
    s = nanmedian_fast(np.abs(v), axis=axis) / MAD_NORMAL
    return np.maximum(s, floor) if floor > 0 else s


def nanmedian_fast(a: ArrayLike, axis: int = -1) -> NDArray[np.float64]:
    """NaN-ignoring median along ``axis`` by one sort (much faster than ``np.nanmedian``
    on many short rows).  Rows with no finite value give NaN."""
    x = np.moveaxis(np.asarray(a, dtype=float), axis, -1)
    if x.shape[-1] == 0:  # rows with no value (take_along_axis had no index 0: IndexError)
        return np.full(x.shape[:-1], np.nan)
    nan = np.isnan(x)
    c = x.shape[-1] - nan.sum(axis=-1)
    srt = np.sort(np.where(nan, np.inf, x), axis=-1)
    lo = np.clip((c - 1) // 2, 0, None)[..., None]
    hi = np.clip(c // 2, 0, x.shape[-1] - 1)[..., None]
    with np.errstate(invalid="ignore"):
        med = 0.5 * (np.take_along_axis(srt, lo, -1) + np.take_along_axis(srt, hi, -1))[..., 0]
    return np.where(c > 0, med, np.nan)
