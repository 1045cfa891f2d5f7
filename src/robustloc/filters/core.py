"""One batched core for the linear Kalman filter, the EKF and the UKF, with a robust update.

Every function works on ``K`` independent tracks at once: states ``x (K, n)``, covariances
``P (K, n, n)``, measurements ``z (K, m)``.  One vectorized call advances all tracks; a single
track is ``K = 1``.  ``NaN`` in ``z`` marks a missing component: it is left out of that
track's update (a track with no component left is only predicted).

Predict
-------
* :func:`predict_linear` -- ``x = F x``, ``P = F P F^T + Q`` (seed 002, eq. (13)).
* :func:`predict_ekf` -- ``x = f(x)``, ``P = J P J^T + Q`` with ``J`` the user's Jacobian of
  ``f`` or a central-difference one.
* :func:`predict_ukf` -- unscented transform of ``f`` with scaled sigma points (seed 001,
  eqs. (20)-(21)).

Update
------
* :func:`update_linear`, :func:`update_ekf`, :func:`update_ukf` build the predicted
  measurement, innovation covariance ``S`` and cross covariance ``P_xz``, then share one
  update (:func:`update_from_moments`):

  1. innovation ``y = z - h(x)`` through ``residual_z`` (angles wrapped to ``[-pi, pi)``);
  2. chi-square gate (optional): ``NIS = y^T S^-1 y`` over the available components;
     the whole update of a track is skipped when ``NIS > chi2.ppf(gate_probability, m)``;
  3. robust equivalent weights (optional): each component's standardized innovation
     ``e_i = y_i / sqrt(S_ii)`` gives ``D = diag(p(e_i))`` from a weight object of
     :mod:`robustloc.robust.weights` (Huber, IGG, IGG3, AsymmetricIGG, ...);
  4. gain ``K = P_xz S^-1`` re-weighted ``K_hat = K D`` (seed 002, eq. (12)) -- or, with
     ``mode="variance"``, ``R_ii`` inflated to ``R_ii / D_ii`` (equivalent-variance form;
     ``D_ii = 0`` leaves the component out) and ``K_hat`` the Kalman gain of that model.
     Only the variance form guarantees ``P+ <= P-``: ``K D`` keeps the gain of every
     component and cuts the rejected columns, and its true covariance (step 5) can exceed
     the prediction's when some components are rejected and others kept (the tracker
     uses the variance form; ``docs/limits.md``);
  5. ``x+ = x + K_hat y``; covariance of that estimator for *any* gain ``G``:
     ``P+ = P - G P_xz^T - P_xz G^T + G S G^T``, which equals the Joseph form
     ``(I - G H) P (I - G H)^T + G R G^T`` for a linear(ized) ``H`` (used then), and
     ``P - K S K^T`` for the optimal gain.  ``P+`` is symmetrized.

Plugging in your own model
--------------------------
Transitions and measurement functions are plain vectorized callables on stacked states:
``f(x (K, n)) -> (K, n)`` and ``h(x (K, n)) -> (K, m)``; Jacobians
``jac(x (K, n)) -> (K, n, n)`` / ``(K, m, n)``.  Pass ``None`` as a Jacobian to get a
central-difference one.  For example, a custom nonlinear transition with its Jacobian and a
scalar measurement (``m = 1``)::

    def f(x):                       # x (K, 3)
        p, d, v = x.T
        return np.stack([p + 20 * np.log10(d / (d + v * dt)), d + v * dt, v], axis=-1)

    def f_jac(x):                   # (K, 3, 3), or pass None for a numerical one
        ...

    h = lambda x: x[:, :1]          # measure the first state, (K, 1)
    H = np.array([[1.0, 0.0, 0.0]])
    robust = RobustUpdate(weight=AsymmetricIGG(k0=2, k1=3, c=3))
    x, P = predict_ekf(x, P, f, Q, jac=f_jac)
    res = update_linear(x, P, z[:, None], H, R=np.array([[sigma**2]]), robust=robust)
    x, P = res.x, res.P             # res.weights, res.nis, res.status per track

``Q``, ``R``, ``F`` and ``H`` are either shared ``(n, n)`` / ``(m, m)`` arrays or one per
track ``(K, n, n)``.  Angles: list the angular components in ``z_angles`` (measurement) and
``x_angles`` (state) -- residuals are wrapped and UKF means are circular means.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from functools import lru_cache
from typing import Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

from robustloc import status as st
from robustloc._stats import chi2_ppf
from robustloc.robust.weights import WeightFunction

Array = NDArray[np.float64]
StateFn = Callable[[Array], Array]

#: Status of a track whose update used no measurement (all missing): prediction only.
PREDICTED = st.PREDICTED


# --------------------------------------------------------------------------- helpers
def wrap_angle(a: ArrayLike) -> Array:
    """Wrap angles (radians) to ``[-pi, pi)``."""
    a = np.asarray(a, dtype=float)
    return (a + np.pi) % (2.0 * np.pi) - np.pi


def make_residual(angles: Sequence[int] = ()) -> Callable[[Array, Array], Array]:
    """Residual ``a - b`` with the listed components wrapped to ``[-pi, pi)``."""
    idx = np.asarray(list(angles), dtype=int)

    def residual(a: Array, b: Array) -> Array:
        d = a - b
        if idx.size:
            d[..., idx] = wrap_angle(d[..., idx])
        return d

    return residual


def _weighted_mean(pts: Array, wm: Array, angles: Array) -> Array:
    """Weighted mean of sigma points ``pts (s, K, d)``; circular for ``angles``."""
    S = pts.shape[0]
    mean = (wm @ pts.reshape(S, -1)).reshape(pts.shape[1:])
    if angles.size:
        a = pts[..., angles].reshape(S, -1)
        shape = mean[..., angles].shape
        mean[..., angles] = np.arctan2(
            (wm @ np.sin(a)).reshape(shape), (wm @ np.cos(a)).reshape(shape)
        )
    return mean


def _weighted_cov(wc: Array, a: Array, b: Array) -> Array:
    """``sum_s wc[s] a[s, k]^T b[s, k]`` for ``a (s, K, i)``, ``b (s, K, j)`` -> ``(K, i, j)``."""
    at = np.transpose(a * wc[:, None, None], (1, 2, 0))  # (K, i, s)
    return at @ np.transpose(b, (1, 0, 2))


@lru_cache(maxsize=32)
def _eye(n: int) -> Array:
    e = np.eye(n)
    e.flags.writeable = False
    return e


def _as_batch(A: ArrayLike, K: int) -> Array:
    A = np.asarray(A, dtype=float)
    return A if A.ndim == 3 else np.broadcast_to(A, (K, *A.shape))


def _mT(A: Array) -> Array:
    return np.swapaxes(A, -1, -2)


def symmetrize(P: Array) -> Array:
    """Return ``(P + P^T) / 2``."""
    return 0.5 * (P + _mT(P))


def spd_solve(S: Array, B: Array) -> Array:
    """Solve ``S X = B`` for a stack of symmetric positive-definite ``S (K, m, m)``.

    LAPACK's batched ``solve`` pays a fixed cost per matrix; for many small systems the
    batched Cholesky factor followed by forward/back substitution vectorized over the batch
    axis (a Python loop over the ``m`` rows only) is faster.  Used when ``K >= 32``; falls
    back to :func:`numpy.linalg.solve` if ``S`` is not positive definite.
    """
    K, m, _ = S.shape
    if K < 32 or m > 12:
        return np.linalg.solve(S, B)
    try:
        L = np.linalg.cholesky(S)
    except np.linalg.LinAlgError:
        return np.linalg.solve(S, B)
    Y = np.empty_like(B, dtype=float)
    for j in range(m):  # forward: L Y = B
        Y[:, j] = (B[:, j] - (L[:, j, None, :j] @ Y[:, :j])[:, 0]) / L[:, j, j, None]
    X = np.empty_like(Y)
    for j in range(m - 1, -1, -1):  # backward: L^T X = Y
        X[:, j] = (Y[:, j] - (L[:, j + 1 :, j][:, None, :] @ X[:, j + 1 :])[:, 0]) / L[
            :, j, j, None
        ]
    return X


def _sqrt_psd(P: Array) -> Array:
    """Lower square roots ``L L^T = P`` for a stack; eigen-clipping if Cholesky fails."""
    try:
        return np.linalg.cholesky(P)
    except np.linalg.LinAlgError:
        w, V = np.linalg.eigh(symmetrize(P))
        return V * np.sqrt(np.clip(w, 0.0, None))[..., None, :]


def numerical_jacobian(fun: StateFn, x: ArrayLike, rel_step: float = 1e-6) -> Array:
    """Central-difference Jacobian of a vectorized ``fun`` at each row of ``x (K, n)``.

    All ``2 n`` perturbed copies of the ``K`` states go through ``fun`` in one call.
    Returns ``(K, m, n)``.
    """
    x = np.asarray(x, dtype=float)
    K, n = x.shape
    h = rel_step * np.maximum(1.0, np.abs(x))  # (K, n)
    E = np.eye(n)
    xp = x[None, :, :] + E[:, None, :] * h[None, :, :]  # (n, K, n)
    xm = x[None, :, :] - E[:, None, :] * h[None, :, :]
    fx = fun(np.concatenate([xp, xm]).reshape(2 * n * K, n))
    fx = np.asarray(fx, dtype=float).reshape(2, n, K, -1)
    d = (fx[0] - fx[1]) / (2.0 * h.T[:, :, None])  # (n, K, m)
    return np.transpose(d, (1, 2, 0))


# --------------------------------------------------------------------------- settings
@dataclass(frozen=True)
class RobustUpdate:
    """How measurements are screened in every filter's update.

    Parameters
    ----------
    weight : WeightFunction, optional
        Equivalent-weight function applied to each standardized innovation component
        (seed 002, eqs. (11)-(12)); ``None`` for the plain (non-robust) update.
    gate_probability : float, optional
        Chi-square gate on the normalized innovation squared: a track's update is skipped
        when ``NIS > chi2.ppf(gate_probability, m_available)``.  ``None``: no gate.
    mode : {"gain", "variance"}
        ``"gain"``: ``K_hat = K D`` as in seed 002 eq. (12).  ``"variance"``: equivalent
        variance ``R_ii / D_ii`` and the optimal gain for it (IGG-style equivalent weights;
        ``S`` is then recomputed, which shrinks the covariance less for a down-weighted
        component).
    """

    weight: WeightFunction | None = None
    gate_probability: float | None = None
    mode: Literal["gain", "variance"] = "gain"

    def __post_init__(self) -> None:
        if self.gate_probability is not None and not 0.0 < self.gate_probability < 1.0:
            raise ValueError(f"gate_probability must be in (0, 1), got {self.gate_probability}")
        if self.mode not in ("gain", "variance"):
            raise ValueError(f"mode must be 'gain' or 'variance', got {self.mode!r}")


PLAIN = RobustUpdate()


@dataclass(frozen=True)
class SigmaPoints:
    """Scaled (Merwe) sigma points, seed 001 eq. (20).

    ``lambda = alpha^2 (n + kappa) - n``; points ``x``, ``x +- sqrt(n + lambda) L_i`` with
    ``L L^T = P``; mean weights ``W_m0 = lambda / (n + lambda)``, covariance weights
    ``W_c0 = W_m0 + 1 - alpha^2 + beta``, others ``1 / (2 (n + lambda))``.  The paper takes
    ``alpha = 1, kappa = 0`` (the default here); ``beta = 2`` is optimal for Gaussians.
    """

    alpha: float = 1.0
    beta: float = 2.0
    kappa: float = 0.0

    def lam(self, n: int) -> float:
        return self.alpha**2 * (n + self.kappa) - n

    def weights(self, n: int) -> tuple[Array, Array]:
        """Mean and covariance weights ``(2n + 1,)`` each (cached, read-only)."""
        return _sigma_weights(self.alpha, self.beta, self.kappa, n)

    def _weights(self, n: int) -> tuple[Array, Array]:
        lam = self.lam(n)
        if n + lam <= 0:
            raise ValueError(f"sigma-point scaling n + lambda = {n + lam} must be positive")
        wm = np.full(2 * n + 1, 0.5 / (n + lam))
        wc = wm.copy()
        wm[0] = lam / (n + lam)
        wc[0] = wm[0] + 1.0 - self.alpha**2 + self.beta
        wm.flags.writeable = False
        wc.flags.writeable = False
        return wm, wc

    def points(self, x: Array, P: Array) -> Array:
        """Sigma points ``(2n + 1, K, n)`` for states ``x (K, n)`` and ``P (K, n, n)``."""
        K, n = x.shape
        L = _sqrt_psd((n + self.lam(n)) * P)  # columns are the spreads
        spread = np.transpose(L, (2, 0, 1))  # (n, K, n): column i of each L
        out = np.empty((2 * n + 1, K, n))
        out[0] = x
        np.add(x, spread, out=out[1 : n + 1])
        np.subtract(x, spread, out=out[n + 1 :])
        return out


@lru_cache(maxsize=64)
def _sigma_weights(alpha: float, beta: float, kappa: float, n: int) -> tuple[Array, Array]:
    return SigmaPoints(alpha, beta, kappa)._weights(n)


# --------------------------------------------------------------------------- result
@dataclass(frozen=True)
class UpdateResult:
    """Outcome of one update for ``K`` tracks.

    Attributes
    ----------
    x, P : posterior states ``(K, n)`` and covariances ``(K, n, n)``.
    innovation : ``(K, m)`` innovations ``z - h(x-)`` (NaN where missing).
    standardized : ``(K, m)`` ``y_i / sqrt(S_ii)``.
    weights : ``(K, m)`` equivalent weights used (0 for missing or gated components).
    nis : ``(K,)`` normalized innovation squared over available components.
    n_used : ``(K,)`` number of components with a non-zero weight.
    gated : ``(K,)`` True where the chi-square gate rejected the whole update.
    status : ``(K,)`` ``ok``; ``fault_excluded`` (gated or some component weighted 0);
        ``predicted`` (nothing to update with).
    """

    x: Array
    P: Array
    innovation: Array
    standardized: Array
    weights: Array
    nis: Array
    n_used: Array
    gated: Array
    status: NDArray[np.str_] = field(repr=False)


# --------------------------------------------------------------------------- predict
def predict_linear(x: ArrayLike, P: ArrayLike, F: ArrayLike, Q: ArrayLike) -> tuple[Array, Array]:
    """Linear Kalman prediction ``x = F x``, ``P = F P F^T + Q`` (seed 002, eq. (13))."""
    x = np.asarray(x, dtype=float)
    P = np.asarray(P, dtype=float)
    F = np.asarray(F, dtype=float)
    if F.ndim == 2:
        K, n = x.shape
        xp = x @ F.T
        # F P F^T for the whole stack as two plain (K n x n) @ (n x n) products (BLAS)
        PFt = (P.reshape(K * n, n) @ F.T).reshape(K, n, n)  # P F^T
        Pp = (_mT(PFt).reshape(K * n, n) @ F.T).reshape(K, n, n)  # (F P^T F^T)^T
        Pp = _mT(Pp) + Q
    else:
        xp = np.einsum("kij,kj->ki", F, x)
        Pp = F @ P @ _mT(F) + Q
    return xp, symmetrize(Pp)


def predict_ekf(
    x: ArrayLike,
    P: ArrayLike,
    f: StateFn,
    Q: ArrayLike,
    jac: StateFn | None = None,
    x_angles: Sequence[int] = (),
) -> tuple[Array, Array]:
    """EKF prediction ``x = f(x)``, ``P = J P J^T + Q``, ``J = df/dx`` at the prior state.

    ``jac=None`` uses :func:`numerical_jacobian`.  Angular state components listed in
    ``x_angles`` are wrapped after the prediction.
    """
    x = np.asarray(x, dtype=float)
    P = np.asarray(P, dtype=float)
    J = numerical_jacobian(f, x) if jac is None else np.asarray(jac(x), dtype=float)
    xp = np.asarray(f(x), dtype=float).copy()
    if x_angles:
        xp[:, list(x_angles)] = wrap_angle(xp[:, list(x_angles)])
    return xp, symmetrize(J @ P @ _mT(J) + Q)


def predict_ukf(
    x: ArrayLike,
    P: ArrayLike,
    f: StateFn,
    Q: ArrayLike,
    points: SigmaPoints = SigmaPoints(),
    x_angles: Sequence[int] = (),
) -> tuple[Array, Array]:
    """UKF prediction: sigma points through ``f``, weighted mean and covariance plus ``Q``.

    Seed 001, eqs. (20)-(21).  ``f`` sees all ``(2n + 1) K`` sigma points in one call.
    """
    x = np.asarray(x, dtype=float)
    P = np.asarray(P, dtype=float)
    K, n = x.shape
    wm, wc = points.weights(n)
    sig = points.points(x, P)
    fs = np.asarray(f(sig.reshape(-1, n)), dtype=float).reshape(2 * n + 1, K, n)
    ang = np.asarray(list(x_angles), dtype=int)
    xp = _weighted_mean(fs, wm, ang)
    d = make_residual(x_angles)(fs, xp[None])
    Pp = _weighted_cov(wc, d, d) + Q
    return xp, symmetrize(Pp)


# --------------------------------------------------------------------------- update
def update_from_moments(
    x: Array,
    P: Array,
    y: Array,
    S: Array,
    Pxz: Array,
    R: ArrayLike,
    robust: RobustUpdate = PLAIN,
    H: Array | None = None,
    x_angles: Sequence[int] = (),
) -> UpdateResult:
    """Shared update from innovation moments (see the module docstring, steps 2-5).

    Parameters
    ----------
    x, P : prior ``(K, n)``, ``(K, n, n)``.
    y : innovations ``(K, m)``, NaN where the measurement is missing.
    S : innovation covariances ``(K, m, m)`` (including ``R``).
    Pxz : state-measurement cross covariances ``(K, n, m)``.
    R : measurement noise ``(m, m)`` or ``(K, m, m)`` (for the variance mode and Joseph form).
    robust : screening settings.
    H : linear(ized) measurement matrices ``(K, m, n)``; when given the Joseph form is used.
    x_angles : angular state components, wrapped after the update.
    """
    K, n = x.shape
    m = y.shape[1]
    R = np.asarray(R, dtype=float)
    Sdiag = np.diagonal(S, axis1=1, axis2=2)
    avail = np.isfinite(y) & np.isfinite(Sdiag)
    full = bool(avail.all())
    if full:  # fast path: nothing missing
        y0, Sm = y, S
    else:
        y0 = np.where(avail, y, 0.0)
        pair = avail[:, :, None] & avail[:, None, :]
        Sm = np.where(pair, S, _eye(m))
        Pxz = np.where(avail[:, None, :], Pxz, 0.0)
        Sdiag = np.where(avail, Sdiag, 1.0)

    # one factorization: S^-1 [P_xz^T | y]
    sol = spd_solve(Sm, np.concatenate([_mT(Pxz), y0[..., None]], axis=-1))
    nis = np.sum(y0 * sol[..., n], axis=1)
    dof = avail.sum(axis=1)
    e = y0 / np.sqrt(Sdiag)
    if not full:
        e = np.where(avail, e, np.nan)

    gated = np.zeros(K, dtype=bool)
    if robust.gate_probability is not None:
        thr = chi2_ppf(robust.gate_probability, np.maximum(dof, 1))
        gated = (dof > 0) & (nis > thr)

    if robust.weight is not None:
        D = robust.weight.weights(e)  # seed 002 eq. (11): p(e_i)
        D = np.where(avail & np.isfinite(D), D, 0.0)
    else:
        D = avail.astype(float)
    if gated.any():
        D = np.where(gated[:, None], 0.0, D)

    if robust.mode == "variance" and robust.weight is not None:
        # equivalent variance R_ii / D_ii: S gains R_ii (1/D_ii - 1) on its diagonal
        eye_m = np.eye(m)
        R = _as_batch(R, K)
        rdiag = np.diagonal(R, axis1=1, axis2=2)
        # a weight so small that the added variance R_ii (1 / D_ii - 1) overflows (1 / D
        # does below 5.6e-309 whatever R) is an infinite variance: left out, D_ii = 0
        with np.errstate(divide="ignore", over="ignore", invalid="ignore"):
            D = np.where((D > 0) & ~np.isfinite(rdiag * (1.0 / D - 1.0)), 0.0, D)
        use = D > 0
        with np.errstate(divide="ignore"):
            extra = np.where(use, rdiag * (1.0 / np.where(use, D, 1.0) - 1.0), 0.0)
        pair_u = use[:, :, None] & use[:, None, :]
        Sm = np.where(pair_u, np.nan_to_num(Sm) + extra[:, :, None] * eye_m, eye_m)
        Pxz = np.where(use[:, None, :], Pxz, 0.0)
        G = _mT(spd_solve(Sm, _mT(Pxz)))
        Reff = R + extra[:, :, None] * eye_m
        Dg = use.astype(float)
    else:
        G = _mT(sol[..., :n])  # K = P_xz S^-1
        if robust.weight is not None or gated.any() or not full:
            G = G * D[:, None, :]  # seed 002 eq. (12): K_hat = K D
        Reff = R
        Dg = D

    xn = x + (G @ y0[..., None])[..., 0]
    if x_angles:
        xn[:, list(x_angles)] = wrap_angle(xn[:, list(x_angles)])
    if H is not None:
        H = _as_batch(H, K)
        if not full or robust.weight is not None or gated.any():
            H = np.where(Dg[:, :, None] > 0, H, 0.0)
            Reff = np.where(avail[:, :, None] & avail[:, None, :], _as_batch(Reff, K), 0.0)
        IKH = _eye(n) - G @ H
        Pn = IKH @ P @ _mT(IKH) + G @ Reff @ _mT(G)  # Joseph form
    else:
        GPxz = G @ _mT(Pxz)
        Pn = P - GPxz - _mT(GPxz) + G @ Sm @ _mT(G)
    Pn = symmetrize(Pn)

    n_used = (D > 0).sum(axis=1)
    status = np.where(
        dof == 0, PREDICTED, np.where(gated | (n_used < dof), st.FAULT_EXCLUDED, st.OK)
    )
    return UpdateResult(
        x=xn,
        P=Pn,
        innovation=y if full else np.where(avail, y, np.nan),
        standardized=e,
        weights=D,
        nis=nis if full else np.where(dof > 0, nis, np.nan),
        n_used=n_used,
        gated=gated,
        status=status,
    )


def update_linear(
    x: ArrayLike,
    P: ArrayLike,
    z: ArrayLike,
    H: ArrayLike,
    R: ArrayLike,
    robust: RobustUpdate = PLAIN,
    z_angles: Sequence[int] = (),
    x_angles: Sequence[int] = (),
) -> UpdateResult:
    """Linear Kalman update with ``z = H x + r`` (seed 002, eqs. (12)-(13), Joseph form).

    ``H`` is ``(m, n)`` or ``(K, m, n)``; ``z (K, m)`` with NaN for missing components.
    """
    x = np.asarray(x, dtype=float)
    P = np.asarray(P, dtype=float)
    z = np.asarray(z, dtype=float)
    K = x.shape[0]
    Hb = _as_batch(H, K)
    Rb = np.asarray(R, dtype=float)
    zhat = np.einsum("kmn,kn->km", Hb, x)
    y = make_residual(z_angles)(z.copy(), zhat)
    PHt = P @ _mT(Hb)
    S = Hb @ PHt + Rb
    return update_from_moments(x, P, y, S, PHt, Rb, robust, H=Hb, x_angles=x_angles)


def update_ekf(
    x: ArrayLike,
    P: ArrayLike,
    z: ArrayLike,
    h: StateFn,
    R: ArrayLike,
    jac: StateFn | None = None,
    robust: RobustUpdate = PLAIN,
    z_angles: Sequence[int] = (),
    x_angles: Sequence[int] = (),
) -> UpdateResult:
    """EKF update: ``H = dh/dx`` at the prior (user ``jac`` or numerical), then the shared
    robust update with the Joseph form (seed 001, eq. (10) for the fusion model)."""
    x = np.asarray(x, dtype=float)
    P = np.asarray(P, dtype=float)
    z = np.asarray(z, dtype=float)
    Hb = numerical_jacobian(h, x) if jac is None else np.asarray(jac(x), dtype=float)
    Rb = np.asarray(R, dtype=float)
    zhat = np.asarray(h(x), dtype=float)
    y = make_residual(z_angles)(z.copy(), zhat)
    PHt = P @ _mT(Hb)
    S = Hb @ PHt + Rb
    return update_from_moments(x, P, y, S, PHt, Rb, robust, H=Hb, x_angles=x_angles)


def update_ukf(
    x: ArrayLike,
    P: ArrayLike,
    z: ArrayLike,
    h: StateFn,
    R: ArrayLike,
    points: SigmaPoints = SigmaPoints(),
    robust: RobustUpdate = PLAIN,
    z_angles: Sequence[int] = (),
    x_angles: Sequence[int] = (),
) -> UpdateResult:
    """UKF update (seed 001, eqs. (22)-(23)): sigma points of the prior through ``h``,
    ``P_Z = sum W_c dz dz^T + R``, ``P_XZ = sum W_c dx dz^T``, ``K = P_XZ P_Z^-1``; then the
    shared robust update."""
    x = np.asarray(x, dtype=float)
    P = np.asarray(P, dtype=float)
    z = np.asarray(z, dtype=float)
    K, n = x.shape
    wm, wc = points.weights(n)
    sig = points.points(x, P)
    zs = np.asarray(h(sig.reshape(-1, n)), dtype=float)
    m = zs.shape[-1]
    zs = zs.reshape(2 * n + 1, K, m)
    zang = np.asarray(list(z_angles), dtype=int)
    zhat = _weighted_mean(zs, wm, zang)
    res_z = make_residual(z_angles)
    dz = res_z(zs, zhat[None])
    dx = make_residual(x_angles)(sig, x[None])
    Rb = np.asarray(R, dtype=float)
    S = _weighted_cov(wc, dz, dz) + Rb
    Pxz = _weighted_cov(wc, dx, dz)
    y = res_z(z.copy(), zhat)
    return update_from_moments(x, P, y, S, Pxz, Rb, robust, x_angles=x_angles)
