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
        Scale with ``axis`` removed; NaN where every entry is NaN.
    """
    v = np.asarray(residuals, dtype=float)
    if center:
        v = v - np.nanmedian(v, axis=axis, keepdims=True)
    with np.errstate(all="ignore"):
        import warnings

        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            s = np.nanmedian(np.abs(v), axis=axis) / MAD_NORMAL
    return np.maximum(s, floor) if floor > 0 else s
