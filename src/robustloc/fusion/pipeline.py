"""UWB + GPS fusion with the EKF or UKF, loosely or tightly coupled (seed 001, beyond).

Measurement vector (seed 001, EKF/UKF models), state ``[x, y, x', y'(, x'', y'')]``:

* loose coupling: ``z = [x, y, v, theta]`` -- ``x, y`` a UWB fix (LS/WLS, with its
  covariance as ``R``), ``v = sqrt(x'^2 + y'^2)`` the GPS speed and
  ``theta = atan2(x', y')`` the GPS course, clockwise from north (seed 001);
* tight coupling: ``z = [r_1 .. r_M, v, theta]`` -- the raw ranges
  ``r_i = sqrt((x - a_ix)^2 + (y - a_iy)^2 + dz_i^2)`` are filter measurements, so an epoch
  with one or two anchors still updates the filter and one bad range is one down-weighted
  component instead of a spoiled fix.

The course is left out (NaN) when the measured speed is below ``min_speed_mps``: a
heading is undefined at standstill and its Jacobian ``1/v`` explodes.

Filters (any with any motion model): ``ekf`` -- linear motion prediction, EKF update with the
analytic Jacobian; ``ukf`` -- unscented predict and update (seed 001 eqs. (20)-(23)).  Both
use the shared robust update of :mod:`robustloc.filters.core`.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

from robustloc import status as st
from robustloc.filters.core import (
    PLAIN,
    RobustUpdate,
    SigmaPoints,
    UpdateResult,
    predict_linear,
    predict_ukf,
    update_ekf,
    update_ukf,
)
from robustloc.filters.motion import ConstantAcceleration, ConstantVelocity

Array = NDArray[np.float64]
Motion = ConstantVelocity | ConstantAcceleration


def _mT3(A: Array) -> Array:
    return np.swapaxes(A, -1, -2)


@dataclass(frozen=True)
class FusionMeasurement:
    """Measurement model ``h(x)`` and Jacobian for loose or tight coupling.

    Parameters
    ----------
    n_states : state dimension (4 for CV, 6 for CA; 2-D).
    anchors : (M, 2) anchor positions for tight coupling, ``None`` for loose coupling.
    height_offset_m : (M,) anchor-minus-tag heights (tight coupling, slant ranges).
    """

    n_states: int
    anchors: Array | None = None
    height_offset_m: Array | None = None

    @property
    def n_ranges(self) -> int:
        return 0 if self.anchors is None else int(np.asarray(self.anchors).shape[0])

    @property
    def m(self) -> int:
        return (2 if self.anchors is None else self.n_ranges) + 2

    @property
    def course_index(self) -> int:
        return self.m - 1

    @property
    def speed_index(self) -> int:
        return self.m - 2

    def _dz2(self) -> Array:
        if self.height_offset_m is None:
            return np.zeros(self.n_ranges)
        return np.broadcast_to(np.asarray(self.height_offset_m, float), (self.n_ranges,)) ** 2

    def predict(self, x: Array) -> Array:
        """``h(x)`` for stacked states ``(K, n) -> (K, m)``."""
        vx, vy = x[:, 2], x[:, 3]
        tail = np.stack([np.hypot(vx, vy), np.arctan2(vx, vy)], axis=-1)  # seed 001
        if self.anchors is None:
            return np.concatenate([x[:, :2], tail], axis=-1)
        a = np.asarray(self.anchors, float)
        diff = x[:, None, :2] - a[None]
        r = np.sqrt((diff * diff).sum(-1) + self._dz2()[None])
        return np.concatenate([r, tail], axis=-1)

    def jacobian(self, x: Array) -> Array:
        """``dh/dx`` ``(K, m, n)`` (seed 001 eq. (10) for the loose model)."""
        K = x.shape[0]
        J = np.zeros((K, self.m, self.n_states))
        if self.anchors is None:
            J[:, 0, 0] = J[:, 1, 1] = 1.0
        else:
            a = np.asarray(self.anchors, float)
            diff = x[:, None, :2] - a[None]
            r = np.sqrt((diff * diff).sum(-1) + self._dz2()[None])
            J[:, : self.n_ranges, :2] = diff / np.maximum(r, 1e-9)[..., None]
        vx, vy = x[:, 2], x[:, 3]
        v2 = np.maximum(vx * vx + vy * vy, 1e-12)
        v = np.sqrt(v2)
        i, c = self.speed_index, self.course_index
        J[:, i, 2], J[:, i, 3] = vx / v, vy / v
        J[:, c, 2], J[:, c, 3] = vy / v2, -vx / v2
        return J


@dataclass(frozen=True)
class FusionTrack:
    """Filtered tracks, event-indexed: ``K`` tags by ``J`` events.

    Attributes
    ----------
    time_s : (K, J) event times (NaN padding).
    x : (K, J, n) posterior states.
    var : (K, J, n) posterior variances (covariance diagonal).
    status : (K, J) ``ok`` / ``fault_excluded`` / ``predicted`` ('' on padding).
    n_used : (K, J) measurement components used.
    nis : (K, J) normalized innovation squared.
    weights : (K, J, m) equivalent weights of each component.
    P_last : (K, n, n) final covariances.
    """

    time_s: Array
    x: Array
    var: Array
    status: NDArray[np.str_]
    n_used: NDArray[np.int64]
    nis: Array
    weights: Array
    P_last: Array
    extra: dict = field(default_factory=dict)


@dataclass(frozen=True)
class FusionFilter:
    """Settings of a fusion filter run (data go to :meth:`run`).

    Parameters
    ----------
    kind : ``"ekf"`` or ``"ukf"``.
    motion : CV or CA motion model (independent of ``kind``).
    robust : robust update / gate settings.
    points : UKF sigma points (paper: ``alpha = 1, kappa = 0``).
    min_speed_mps : course measurements below this speed are ignored.
    max_rejected : after this many consecutive events of a track in which some measurement
        was rejected (robust weight 0 or gated), the track re-locks: its position and
        velocity variances are raised to ``relock_var`` so that the next measurements are
        standardized against a wide prior and accepted (a robust filter that drifted
        away would otherwise reject everything forever).  0 disables.
    relock_var : variance (m^2 and (m/s)^2) set on re-lock; the acceleration states of the
        CA model are zeroed with a variance of ``relock_var / 100`` (m/s^2)^2.
    sigma_point_predict : UKF only -- propagate sigma points through the motion model
        (seed 001 eq. (21)).  The CV/CA models are linear, for which the unscented
        transform is exact and equals ``F x, F P F^T + Q`` (tested), so by default the UKF
        predicts with the matrices and uses sigma points in the update only (same result,
        half the work).
    """

    kind: Literal["ekf", "ukf"] = "ukf"
    motion: Motion = field(default_factory=ConstantVelocity)
    robust: RobustUpdate = PLAIN
    points: SigmaPoints = field(default_factory=SigmaPoints)
    min_speed_mps: float = 0.1
    max_rejected: int = 5
    relock_var: float = 4.0
    sigma_point_predict: bool = False

    def __post_init__(self) -> None:
        if self.kind not in ("ekf", "ukf"):
            raise ValueError(f"filter must be 'ekf' or 'ukf', got {self.kind!r}")
        if self.motion.dim != 2:
            raise ValueError("fusion works in 2-D (east, north); use a motion model with dim=2")

    def step(
        self,
        x: Array,
        P: Array,
        dt: Array,
        z: Array,
        R: Array,
        meas: FusionMeasurement,
    ) -> UpdateResult:
        """One vectorized predict + update of ``K`` tracks with per-track ``dt (K,)``."""
        if np.all(dt == dt[0]):  # one step for all tracks (the usual case): cached 2-D F, Q
            F, Q = self.motion.FQ(float(dt[0]))
        else:
            F, Q = self.motion.F(dt), self.motion.Q(dt)
        if self.kind == "ekf" or not self.sigma_point_predict:
            x, P = predict_linear(x, P, F, Q)
        else:
            K, n = x.shape

            if F.ndim == 2:
                F2 = F

                def f(s: Array) -> Array:
                    return s @ F2.T
            else:

                def f(s: Array) -> Array:  # sigma points (S*K, n): track k uses F[k]
                    s3 = s.reshape(-1, K, n).transpose(1, 0, 2)  # (K, S, n)
                    return (s3 @ _mT3(F)).transpose(1, 0, 2).reshape(-1, n)

            x, P = predict_ukf(x, P, f, Q, self.points)
        z = z.copy()
        ci, si = meas.course_index, meas.speed_index
        slow = ~(np.abs(z[:, si]) >= self.min_speed_mps)
        z[slow, ci] = np.nan
        if self.kind == "ekf":
            r = update_ekf(x, P, z, meas.predict, R, jac=meas.jacobian, robust=self.robust,
                           z_angles=[ci])
        else:
            r = update_ukf(x, P, z, meas.predict, R, points=self.points, robust=self.robust,
                           z_angles=[ci])
        return r

    def run(
        self,
        time_s: ArrayLike,
        z: ArrayLike,
        R: ArrayLike,
        meas: FusionMeasurement,
        x0: ArrayLike,
        P0: ArrayLike,
        progress: bool = False,
    ) -> FusionTrack:
        """Filter ``K`` event-indexed tracks (see :mod:`robustloc.fusion.align`).

        Parameters
        ----------
        time_s : (K, J) event times, NaN padding.
        z : (K, J, m) measurements, NaN = missing.
        R : (m, m), (K, J, m, m) or (K, J, m) (diagonal variances) measurement noise.
        meas : the measurement model.
        x0, P0 : (K, n) and (K, n, n) initial states at each track's first event time.
        progress : show a tqdm bar on stderr (only when stderr is a terminal).
        """
        t = np.asarray(time_s, dtype=float)
        z = np.asarray(z, dtype=float)
        K, J, m = z.shape
        n = self.motion.n_states
        R = np.asarray(R, dtype=float)
        x = np.array(x0, dtype=float).reshape(K, n)
        P = np.array(P0, dtype=float).reshape(K, n, n)
        xs = np.full((K, J, n), np.nan)
        vs = np.full((K, J, n), np.nan)
        stat = np.full((K, J), "", dtype=object)
        nu = np.zeros((K, J), dtype=np.int64)
        nis = np.full((K, J), np.nan)
        ws = np.full((K, J, m), np.nan)
        t_prev = np.where(np.isfinite(t[:, 0]), t[:, 0], 0.0)
        rejected = np.zeros(K, dtype=np.int64)
        relocks = np.zeros(K, dtype=np.int64)
        eye_m = np.eye(m)
        steps = range(J)
        if progress:
            import sys

            from tqdm import tqdm

            steps = tqdm(steps, desc="filter", unit="step", file=sys.stderr,
                         disable=not sys.stderr.isatty())
        for j in steps:  # the recursion is sequential in time; tracks are vectorized
            tj = t[:, j]
            live = np.isfinite(tj)
            dt = np.where(live, tj - t_prev, 0.0)
            if R.ndim == 2:
                Rj = R
            elif R.ndim == 3:
                Rj = R[:, j, :, None] * eye_m
            else:
                Rj = R[:, j]
            zj = np.where(live[:, None], z[:, j], np.nan)
            r = self.step(x, P, dt, zj, Rj, meas)
            x, P = r.x, r.P
            if self.max_rejected > 0:
                avail = np.isfinite(r.innovation).sum(axis=1)
                had = avail > 0
                some_rejected = had & (r.n_used < avail)
                rejected = np.where(some_rejected, rejected + 1, np.where(had, 0, rejected))
                lock = rejected >= self.max_rejected
                if lock.any():  # re-lock: wide position/velocity, acceleration reset
                    P = P.copy()
                    x = x.copy()
                    P[lock] = 0.0
                    diag = np.full(n, self.relock_var)
                    diag[4:] = self.relock_var * 0.01
                    P[lock] = np.diag(diag)
                    x[np.ix_(lock, np.arange(4, n))] = 0.0
                    rejected[lock] = 0
                    relocks += lock
            t_prev = np.where(live, tj, t_prev)
            xs[:, j] = x
            vs[:, j] = np.diagonal(P, axis1=1, axis2=2)
            stat[:, j] = np.where(live, r.status, "")
            nu[:, j] = r.n_used
            nis[:, j] = r.nis
            ws[:, j] = r.weights
        return FusionTrack(
            time_s=t, x=xs, var=vs, status=stat.astype(str), n_used=nu, nis=nis, weights=ws,
            P_last=P, extra={"relocks": relocks},
        )


def initial_state(
    position: ArrayLike, n_states: int, pos_var_m2: float = 1.0, vel_var: float = 1.0,
    acc_var: float = 0.25,
) -> tuple[Array, Array]:
    """States ``(K, n)`` at rest at ``position (K, 2)`` and a diagonal ``P0``."""
    p = np.atleast_2d(np.asarray(position, dtype=float))
    K = p.shape[0]
    x0 = np.zeros((K, n_states))
    x0[:, :2] = p
    diag = [pos_var_m2] * 2 + [vel_var] * 2 + ([acc_var] * 2 if n_states > 4 else [])
    P0 = np.tile(np.diag(diag), (K, 1, 1))
    return x0, P0


def track_status_ok(status: ArrayLike) -> NDArray[np.bool_]:
    """Rows whose position is a usable estimate (every filtered row is)."""
    s = np.asarray(status)
    return np.isin(s, (st.OK, st.FAULT_EXCLUDED, "predicted"))
