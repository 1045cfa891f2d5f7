"""The result object of every batched position estimator."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from robustloc import status as st


@dataclass(frozen=True)
class Solution:
    """Per-epoch solutions of a batch of ``N`` epochs with ``m`` observations each.

    Attributes
    ----------
    position : ndarray, shape (N, dim)
        Estimated position; NaN where no fix could be computed.
    covariance : ndarray, shape (N, dim, dim)
        Covariance of the position (a-posteriori, scaled by ``sigma0**2`` unless stated).
    residuals : ndarray, shape (N, m)
        Observation residuals ``v = f(x) - z`` at the solution (NaN: not observed).
    weights : ndarray, shape (N, m)
        Final weights of the observations, ``p / sigma^2`` in the fit's domain (``p`` the
        robust weight factor: 1 full, 0 rejected; NaN: not observed).  A robust nonlinear
        fit also gives ``p`` alone, ``extra["weight_factor"]``.
    excluded : ndarray of bool, shape (N, m)
        Observations rejected (weight zero) or excluded by a test.
    sigma0 : ndarray, shape (N,)
        A-posteriori unit-weight standard error ``sqrt(v^T P v / (n - p))``.
    iterations : ndarray of int, shape (N,)
    converged : ndarray of bool, shape (N,)
    status : ndarray of str, shape (N,)
        One of :mod:`robustloc.status`.
    n_used : ndarray of int, shape (N,)
        Observations with non-zero weight.
    method : str
    extra : dict
        Method-specific per-epoch arrays (e.g. LEGE's estimated gross errors, test
        statistics of data snooping).
    """

    position: NDArray[np.float64]
    covariance: NDArray[np.float64]
    residuals: NDArray[np.float64]
    weights: NDArray[np.float64]
    excluded: NDArray[np.bool_]
    sigma0: NDArray[np.float64]
    iterations: NDArray[np.int64]
    converged: NDArray[np.bool_]
    status: NDArray[np.object_]
    n_used: NDArray[np.int64]
    method: str
    extra: dict = field(default_factory=dict)

    @property
    def n_epochs(self) -> int:
        return int(self.position.shape[0])

    @property
    def ok(self) -> NDArray[np.bool_]:
        """Epochs with a usable position."""
        return st.among(self.status, st.USABLE) & np.all(np.isfinite(self.position), axis=1)

    def excluded_ids(self, anchor_ids: list[str] | NDArray) -> list[str]:
        """``;``-joined ids of the excluded observations of each epoch (positions file)."""
        ids = np.asarray(anchor_ids, dtype=object)
        exc = np.asarray(self.excluded, dtype=bool)
        if exc.shape[0] == 0:
            return []
        if exc.shape[1] > 62:
            return [";".join(str(a) for a in ids[row]) for row in exc]
        # one join per distinct exclusion pattern (few), not per epoch (many)
        bit = np.int64(1) << np.arange(exc.shape[1], dtype=np.int64)
        codes, which = np.unique(exc.astype(np.int64) @ bit, return_inverse=True)
        labels = np.array([";".join(str(a) for a in ids[(c & bit) != 0]) for c in codes],
                          dtype=object)
        return labels[which].tolist()
