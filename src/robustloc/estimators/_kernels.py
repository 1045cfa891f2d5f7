"""Small dense kernels for stacks of tiny systems (the hot path of every estimator)."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

Array = NDArray[np.float64]

#: Normal matrices with a (Frobenius) condition number above this are ill-conditioned.
COND_LIMIT = 1e10
#: A 3 x 3 matrix whose adjugate (its 2 x 2 minors) is below this times ``||A||_F^2`` is
#: of numerical rank one: its minors are rounding noise, ``~eps ||A||^2``, and so is its
#: determinant, and the closed-form inverse, noise over noise, can look well conditioned
#: (45 % of random rank-one matrices ``w j j^T`` passed the condition test).  A matrix
#: of condition number below ``COND_LIMIT`` has minors of at least ``||A||^2 / 1e10``
#: (its two largest eigenvalues' product), so none is refused that passed before.
ADJUGATE_RANK = 1e-12


def normal_matrix(J: Array, w: Array) -> Array:
    """``J^T diag(w) J`` for stacks: ``J (K, n, p)``, ``w (K, n)`` -> ``(K, p, p)``."""
    return np.matmul(np.swapaxes(J * w[..., None], 1, 2), J)


def inv_spd(Nm: Array) -> tuple[Array, NDArray[np.bool_]]:
    """Inverse of a stack of small symmetric matrices and a well-conditioned mask.

    Closed-form adjugate inverses for 1x1, 2x2 and 3x3 (the ranging cases), LAPACK
    otherwise.  A matrix is *good* when it is finite, has a positive determinant and its
    Frobenius condition number ``||A|| ||A^-1||`` is below :data:`COND_LIMIT`; bad
    matrices get an identity-sized NaN-free placeholder inverse so callers can mask them.
    """
    K, p, _ = Nm.shape
    with np.errstate(all="ignore"):
        if p == 1:
            det = Nm[:, 0, 0]
            inv = (1.0 / np.where(det != 0, det, 1.0))[:, None, None]
        elif p == 2:
            a, b, d = Nm[:, 0, 0], Nm[:, 0, 1], Nm[:, 1, 1]
            c = Nm[:, 1, 0]
            det = a * d - b * c
            s = 1.0 / np.where(det != 0, det, 1.0)
            inv = np.empty_like(Nm)
            inv[:, 0, 0] = d * s
            inv[:, 0, 1] = -b * s
            inv[:, 1, 0] = -c * s
            inv[:, 1, 1] = a * s
        elif p == 3:
            m = Nm
            c00 = m[:, 1, 1] * m[:, 2, 2] - m[:, 1, 2] * m[:, 2, 1]
            c01 = m[:, 1, 2] * m[:, 2, 0] - m[:, 1, 0] * m[:, 2, 2]
            c02 = m[:, 1, 0] * m[:, 2, 1] - m[:, 1, 1] * m[:, 2, 0]
            det = m[:, 0, 0] * c00 + m[:, 0, 1] * c01 + m[:, 0, 2] * c02
            s = 1.0 / np.where(det != 0, det, 1.0)
            inv = np.empty_like(Nm)
            inv[:, 0, 0] = c00 * s
            inv[:, 1, 0] = c01 * s
            inv[:, 2, 0] = c02 * s
            inv[:, 0, 1] = (m[:, 0, 2] * m[:, 2, 1] - m[:, 0, 1] * m[:, 2, 2]) * s
            inv[:, 1, 1] = (m[:, 0, 0] * m[:, 2, 2] - m[:, 0, 2] * m[:, 2, 0]) * s
            inv[:, 2, 1] = (m[:, 0, 1] * m[:, 2, 0] - m[:, 0, 0] * m[:, 2, 1]) * s
            inv[:, 0, 2] = (m[:, 0, 1] * m[:, 1, 2] - m[:, 0, 2] * m[:, 1, 1]) * s
            inv[:, 1, 2] = (m[:, 0, 2] * m[:, 1, 0] - m[:, 0, 0] * m[:, 1, 2]) * s
            inv[:, 2, 2] = (m[:, 0, 0] * m[:, 1, 1] - m[:, 0, 1] * m[:, 1, 0]) * s
        else:
            det = np.linalg.det(Nm)
            safe = np.where((np.isfinite(det) & (det != 0))[:, None, None], Nm, np.eye(p))
            inv = np.linalg.inv(safe)
        fro = np.sqrt(np.sum(Nm * Nm, axis=(1, 2)))
        fro_inv = np.sqrt(np.sum(inv * inv, axis=(1, 2)))
        cond = fro * fro_inv
        good = np.isfinite(cond) & (det > 0) & (cond < COND_LIMIT)
        if p == 3:  # numerical rank one (ADJUGATE_RANK)
            good &= fro_inv * np.abs(det) > ADJUGATE_RANK * fro * fro
    if not np.all(good):
        inv = np.where(good[:, None, None], inv, np.eye(p))
    return inv, good
