"""Global chi-square test and local w-tests of a (linearized) least-squares adjustment.

Batched over ``N`` epochs with ``n`` observations and ``p`` unknowns each.  Observation ``i`` of
epoch ``k`` has a-priori standard deviation ``sigma[k, i]``; the weight matrix is diagonal,
``P = diag(sigma0^2 / sigma_i^2)`` with a-priori unit-weight variance ``sigma0^2 = 1`` (so
``sigma`` carries the units of the observation: metres for ranges, dB for RSSI).  A missing
observation is NaN in ``y`` / ``v`` (or in ``sigma``, or False in ``mask``): it gets weight zero
and NaN statistics.

Everything is computed in the whitened model ``A = P^(1/2) H``, ``b = P^(1/2) y``:

* hat matrix ``U = A (A^T A)^-1 A^T``;
* cofactor of the residuals ``Q_vv = Q - H (H^T P H)^-1 H^T``      (seed 003, eq. (2)),
  i.e. ``(Q_vv)_ij = sigma_i sigma_j (I - U)_ij``;
* redundancy numbers ``r_i = (Q_vv P)_ii = 1 - U_ii``  (they sum to ``n - p``);
* w-test ``w_i = |v_i| / (sigma0 sqrt((Q_vv)_ii)) = |v_i / sigma_i| / sqrt(r_i)``
  (seed 003, eq. (1)), standard normal under the null hypothesis;
* global test statistic ``T = v^T P v / sigma0^2``, ``chi2(n - p)`` under the null hypothesis,
  rejected above ``chi2(1 - alpha, n - p)``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from robustloc.integrity.bmethod import (
    ALPHA0,
    BETA0,
    _check_prob,
    global_alpha,
    global_critical,
    w_critical,
)

Array = NDArray[np.float64]

#: Relative eigenvalue floor of ``A^T A`` below which an epoch is ill-conditioned.
RCOND = 1e-10
#: Redundancy numbers below this are treated as zero (observation not controllable).
R_MIN = 1e-9


def broadcast_sigma(sigma: ArrayLike, shape: tuple[int, int]) -> Array:
    """Broadcast a scalar, per-observation ``(n,)`` or per-epoch ``(N, n)`` sigma to ``(N, n)``.

    Raises ``ValueError`` for a zero or negative standard deviation (NaN = missing).
    """
    s = np.asarray(sigma, dtype=float)
    try:
        s = np.broadcast_to(s, shape)
    except ValueError:
        raise ValueError(
            f"sigma of shape {np.shape(sigma)} does not match observations of shape {shape}"
        ) from None
    if np.any(s <= 0):
        raise ValueError("a-priori standard deviations (sigma) must be positive")
    if np.any(np.isinf(s)):
        raise ValueError("a-priori standard deviations (sigma) must be finite")
    return s


def _observation_array(name: str, value: ArrayLike, shape: tuple[int, int],
                       dtype: type = float) -> NDArray[Any]:
    """``value`` broadcast to the observations' ``shape`` (N, n); a ``ValueError`` naming
    ``name`` when it does not fit (numpy's broadcast error named neither)."""
    a: NDArray[Any] = np.asarray(value, dtype=dtype)
    try:
        return np.broadcast_to(a, shape)
    except ValueError:
        raise ValueError(f"{name} has shape {a.shape}; expected {shape} (epochs, "
                         "observations) or one that broadcasts to it") from None


def as_design(H: ArrayLike) -> Array:
    """Return ``H`` as a float array of shape ``(N, n, p)`` (a 2-D ``(n, p)`` becomes N = 1)."""
    h = np.asarray(H, dtype=float)
    if h.ndim == 2:
        h = h[None]
    if h.ndim != 3:
        raise ValueError(f"design matrix must have shape (N, n, p) or (n, p), got {h.shape}")
    return h


def normal_inverse(A: Array, rcond: float = RCOND) -> tuple[Array, NDArray[np.bool_]]:
    """Batched inverse of ``A^T A`` by symmetric eigen-decomposition.

    Parameters
    ----------
    A : ndarray, shape (N, n, p)
        Whitened design, rows of unused observations zero.
    rcond : float
        Epochs whose smallest eigenvalue is below ``rcond`` times the largest (or whose normal
        matrix is zero) are ill-conditioned: their inverse is NaN.

    Returns
    -------
    Ninv : ndarray, shape (N, p, p)
    ok : ndarray of bool, shape (N,)
    """
    Nm = np.einsum("kip,kiq->kpq", A, A)
    lam, V = np.linalg.eigh(Nm)
    top = lam[:, -1]
    ok = np.isfinite(top) & (top > 0) & (lam[:, 0] > rcond * np.where(top > 0, top, 1.0))
    with np.errstate(divide="ignore", invalid="ignore"):
        inv_lam = np.where(ok[:, None], 1.0 / np.where(lam > 0, lam, 1.0), np.nan)
    Ninv = np.einsum("kpi,ki,kqi->kpq", V, inv_lam, V)
    return Ninv, ok


@dataclass(frozen=True)
class Whitened:
    """A batch of whitened linear(ized) models with their normal-matrix inverse.

    Attributes
    ----------
    A : ndarray (N, n, p)
        ``H / sigma`` with rows of unused observations set to zero.
    used : ndarray of bool (N, n)
    sigma : ndarray (N, n)
    Ninv : ndarray (N, p, p)
        ``(H^T P H)^-1``: the a-priori covariance of the estimate (``sigma0 = 1``).
    ok : ndarray of bool (N,)
        Normal matrix invertible.
    n_used : ndarray of int (N,)
    """

    A: Array
    used: NDArray[np.bool_]
    sigma: Array
    Ninv: Array
    ok: NDArray[np.bool_]
    n_used: NDArray[np.int64]

    @property
    def p(self) -> int:
        return int(self.A.shape[2])

    @property
    def dof(self) -> NDArray[np.int64]:
        """Redundancy ``n_used - p``."""
        return self.n_used - self.p

    def hat_diagonal(self) -> Array:
        """``U_ii`` of the whitened hat matrix, NaN for unused observations or bad epochs."""
        u = np.einsum("kip,kpq,kiq->ki", self.A, self.Ninv, self.A)
        return np.where(self.used & self.ok[:, None], u, np.nan)

    def redundancy(self) -> Array:
        """Redundancy numbers ``r_i = (Q_vv P)_ii = 1 - U_ii`` (seed 003, sec. reliability)."""
        r = 1.0 - self.hat_diagonal()
        return np.clip(r, 0.0, 1.0)

    def hat(self) -> Array:
        """Full whitened hat matrix ``U`` (N, n, n); NaN rows/columns for unused observations."""
        U = np.einsum("kip,kpq,kjq->kij", self.A, self.Ninv, self.A)
        m = self.used & self.ok[:, None]
        return np.where(m[:, :, None] & m[:, None, :], U, np.nan)

    def qvv(self) -> Array:
        """Full cofactor matrix of the residuals ``Q_vv`` (seed 003, eq. (2)), shape (N, n, n)."""
        n = self.A.shape[1]
        R = np.eye(n)[None] - self.hat()
        return self.sigma[:, :, None] * R * self.sigma[:, None, :]

    def solve(self, y: Array) -> Array:
        """Weighted least squares ``x = (H^T P H)^-1 H^T P y`` for observations ``y`` (N, n)."""
        b = np.where(self.used, y / self.sigma, 0.0)
        return np.einsum("kpq,kiq,ki->kp", self.Ninv, self.A, b)


def whiten(
    H: ArrayLike,
    sigma: ArrayLike,
    mask: ArrayLike | None = None,
    y: ArrayLike | None = None,
    rcond: float = RCOND,
) -> Whitened:
    """Build the whitened model of a batch.

    Parameters
    ----------
    H : array_like, shape (N, n, p) or (n, p)
        Design (Jacobian) matrix.
    sigma : float or array_like, broadcastable to (N, n)
        A-priori standard deviation of each observation.
    mask : array_like of bool, shape (N, n), optional
        Observations to use (default: all).  Observations with a non-finite design row,
        sigma, or ``y`` (when given) are dropped as well.
    y : array_like, shape (N, n), optional
        Observations or residuals, only to drop NaN entries.
    rcond : float
        Conditioning floor, see :func:`normal_inverse`.
    """
    Hm = as_design(H)
    N, n, _ = Hm.shape
    s = broadcast_sigma(sigma, (N, n))
    used = np.all(np.isfinite(Hm), axis=2) & np.isfinite(s)
    if mask is not None:
        used &= _observation_array("mask", mask, (N, n), bool)
    if y is not None:
        used &= np.isfinite(_observation_array("y", y, (N, n)))
    with np.errstate(invalid="ignore", divide="ignore"):
        A = np.where(used[:, :, None], Hm / s[:, :, None], 0.0)
    Ninv, ok = normal_inverse(A, rcond)
    return Whitened(A=A, used=used, sigma=np.asarray(s, dtype=float), Ninv=Ninv, ok=ok,
                    n_used=used.sum(axis=1).astype(np.int64))


@dataclass(frozen=True)
class IntegrityTests:
    """Global and local test statistics of a batch of epochs.

    Attributes
    ----------
    w : ndarray (N, n)
        w-test statistics ``|v_i| / (sigma0 sqrt(Q_vv,ii))`` (seed 003, eq. (1)); NaN for
        unused observations and for those with zero redundancy (not testable).
    redundancy : ndarray (N, n)
        ``r_i``.
    qvv_diag : ndarray (N, n)
        Diagonal of ``Q_vv`` (seed 003, eq. (2)), in squared observation units.
    global_stat : ndarray (N,)
        ``T = v^T P v / sigma0^2``.
    dof : ndarray of int (N,)
        ``n_used - p``.
    alpha : ndarray (N,)
        Significance of the global test (B-method value or the given one); NaN when dof < 1.
    global_crit : ndarray (N,)
        ``chi2(1 - alpha, dof)``.
    global_pass : ndarray of bool (N,)
        ``T <= global_crit`` (False where no test is possible, see ``testable``).
    testable : ndarray of bool (N,)
        dof >= 1 and the normal matrix invertible.
    w_crit : float
        ``N(1 - alpha0/2)``.
    sigma0_post : ndarray (N,)
        A-posteriori unit-weight standard error ``sqrt(T / dof)``.
    """

    w: Array
    redundancy: Array
    qvv_diag: Array
    global_stat: Array
    dof: NDArray[np.int64]
    alpha: Array
    global_crit: Array
    global_pass: NDArray[np.bool_]
    testable: NDArray[np.bool_]
    w_crit: float
    sigma0_post: Array


def integrity_tests(
    wh: Whitened,
    v: ArrayLike,
    alpha: float | None = None,
    alpha0: float = ALPHA0,
    beta0: float = BETA0,
) -> IntegrityTests:
    """Global test and w-tests for residuals ``v`` of the model ``wh`` (seed 003, eqs. (1)-(4)).

    Parameters
    ----------
    wh : Whitened
        The model (see :func:`whiten`); its ``used`` mask selects the tested observations.
    v : array_like, shape (N, n)
        Least-squares residuals (either sign convention).
    alpha : float, optional
        Fixed significance of the global test; default the B-method value per dof.
    alpha0, beta0 : float
        w-test significance and type II error.
    """
    if alpha is not None:  # (NaN failed every epoch's global test silently)
        alpha = _check_prob("alpha", alpha)
    _check_prob("beta0", beta0)  # (unused with a fixed alpha, but not to be wrong)
    vv = _observation_array("v", v, wh.used.shape)
    used = wh.used & np.isfinite(vv)
    r = wh.redundancy()
    with np.errstate(invalid="ignore", divide="ignore"):
        vs = np.where(used, vv / wh.sigma, np.nan)
        w = np.where(used & (r > R_MIN), np.abs(vs) / np.sqrt(r), np.nan)
    T = np.where(wh.ok, np.nansum(np.where(used, vs * vs, 0.0), axis=1), np.nan)
    dof = used.sum(axis=1).astype(np.int64) - wh.p
    testable = wh.ok & (dof >= 1)
    if alpha is None:
        a = global_alpha(dof, alpha0, beta0)
    else:
        a = np.where(dof >= 1, float(alpha), np.nan)
    crit = np.where(testable, global_critical(dof, np.where(dof >= 1, a, 0.5)), np.nan)
    with np.errstate(invalid="ignore", divide="ignore"):
        s0 = np.sqrt(T / np.where(dof >= 1, dof, np.nan))
    return IntegrityTests(
        w=w,
        redundancy=np.where(used, r, np.nan),
        qvv_diag=np.where(used, r * wh.sigma**2, np.nan),
        global_stat=T,
        dof=dof,
        alpha=np.where(testable, a, np.nan),
        global_crit=crit,
        global_pass=testable & (T <= crit),
        testable=testable,
        w_crit=w_critical(alpha0),
        sigma0_post=s0,
    )


def global_and_w_tests(
    H: ArrayLike,
    v: ArrayLike,
    sigma: ArrayLike,
    mask: ArrayLike | None = None,
    alpha: float | None = None,
    alpha0: float = ALPHA0,
    beta0: float = BETA0,
) -> IntegrityTests:
    """Convenience wrapper: :func:`whiten` then :func:`integrity_tests`.

    Parameters
    ----------
    H : array_like (N, n, p)
        Design matrix of the adjustment that produced ``v``.
    v : array_like (N, n)
        Residuals, NaN = missing observation.
    sigma : float or array_like
        A-priori standard deviations of the observations.
    mask : array_like of bool (N, n), optional
        Observations that took part in the adjustment.

    Examples
    --------
    >>> import numpy as np
    >>> H = np.ones((1, 3, 1))            # three measurements of one height
    >>> y = np.array([[1.0, 1.0, 4.0]])
    >>> x = y.mean(axis=1, keepdims=True)
    >>> t = global_and_w_tests(H, x - y, sigma=1.0)
    >>> np.round(t.w, 3).tolist()          # |v| / sqrt(2/3)
    [[1.225, 1.225, 2.449]]
    """
    Hm = as_design(H)
    v = _observation_array("v", v, Hm.shape[:2])  # (whiten would name it y)
    wh = whiten(Hm, sigma, mask=mask, y=v)
    return integrity_tests(wh, v, alpha=alpha, alpha0=alpha0, beta0=beta0)
