"""UWB + GPS fusion with the EKF or UKF, loosely or tightly coupled (seed 001, beyond).

Measurement vector (seed 001, EKF/UKF models), state ``[x, y, x', y'(, x'', y'')]``:

* loose coupling: ``z = [x, y, v, theta]`` -- ``x, y`` a UWB fix (LS/WLS, the diagonal
  of its covariance in ``R``, as seed 001's ``R = diag(...)``),
  ``v = sqrt(x'^2 + y'^2)`` the GPS speed and ``theta = atan2(x', y')`` the GPS course,
  clockwise from north (seed 001);
* tight coupling: ``z = [r_1 .. r_M, v, theta]`` -- the raw ranges
  ``r_i = sqrt((x - a_ix)^2 + (y - a_iy)^2 + dz_i^2)`` are filter measurements, so an epoch
  with one or two anchors still updates the filter and one bad range is one down-weighted
  component instead of a spoiled fix.

The course is left out (NaN) when the measured speed is below ``min_speed_mps``: a
heading is undefined at standstill and its Jacobian ``1/v`` explodes.

Filters (any with any motion model): ``ekf`` -- linear motion prediction, EKF update with the
analytic Jacobian; ``ukf`` -- unscented predict and update (seed 001 eqs. (20)-(23)).  Both
use the shared robust update of :mod:`robustloc.filters.core`.

Engines: :meth:`FusionFilter.step` runs the built-in model (``FusionMeasurement``, CV/CA
motion, ``mode="gain"`` or ``"variance"``, a built-in weight function) through one
compiled call per step (:mod:`robustloc.filters._compiled`, the same equations as the NumPy
core, tested against it); any other combination, or ``engine="numpy"``, uses the batched NumPy core.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Iterator
from dataclasses import dataclass, field
from typing import Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

from robustloc import status as st
from robustloc._stats import chi2_ppf
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
from robustloc.filters.motion import (
    ConstantAcceleration,
    ConstantVelocity,
    RandomWalkAugmented,
    _coefficients,
)
from robustloc.integrity.bmethod import ALPHA0, BETA0, global_critical

Array = NDArray[np.float64]
Motion = ConstantVelocity | ConstantAcceleration

#: Output arenas of the compiled step hold about this many floats (several steps of one
#: track, one step of many tracks).
_ARENA_FLOATS = 16384
#: From this many tracks a compiled step runs in numba's thread pool (all cores by default;
#: ``NUMBA_NUM_THREADS=1`` or ``numba.set_num_threads(1)`` for one); below, starting the
#: threads costs more than it saves.
_MT_MIN_TRACKS = 256


#: Largest magnitude of a state component (m, m/s, m/s^2) and root of a covariance entry
#: that a posterior may have: 1e9 m is 2.6 times the distance to the Moon, far beyond any
#: local east/north frame.  An update beyond it (an overflow, a near-singular innovation
#: covariance) is rejected and the track keeps its prior (:meth:`FusionFilter.run`).
STATE_LIMIT = 1e9
#: ``sqrt(eps)`` of float64 (``2^-26``): a variance ``r`` added to ``V`` keeps fewer than
#: half of its significant digits in ``V + r`` once ``sqrt(eps) V >= r`` (the rounding
#: error ``eps V`` of the sum is then ``>= sqrt(eps) r``); the tracker's rule
#: (:mod:`robustloc.tracking.tracker`, item 9) uses the same bound.
SQRT_EPS = 2.0**-26


def _threads() -> int:
    """numba's current thread count (numba is imported with the compiled engine anyway)."""
    from numba import get_num_threads

    return get_num_threads()
_new = object.__new__
_setattr = object.__setattr__


def _result(x: Array, P: Array, y: Array, e: Array, w: Array, nis: Array,
            n_used: NDArray[np.int64], gated: NDArray[np.bool_], status: NDArray[np.str_]
            ) -> UpdateResult:
    """An :class:`UpdateResult` without the frozen-dataclass ``__init__`` (hot path).

    ``UpdateResult`` has no ``__post_init__``; filling its instance dictionary at once is
    what its ``__init__`` does field by field, at a third of the cost.
    """
    r = _new(UpdateResult)
    _setattr(r, "__dict__", {
        "x": x, "P": P, "innovation": y, "standardized": e, "weights": w, "nis": nis,
        "n_used": n_used, "gated": gated, "status": status,
    })
    return r


def _arenas(K: int, n: int, m: int) -> Iterator[tuple]:
    """Output arena of the compiled step for ``K`` tracks and an iterator over its slots.

    A slot is one step's output: a row of the arena for the kernel and typed views of it
    shaped like the fields of :class:`UpdateResult`
    (:func:`robustloc.filters._compiled.layout`).  Slots are handed out once (results are
    never overwritten); the views of all slots are made in bulk here, so a step only takes
    the next slot.
    """
    from robustloc.filters._compiled import STATUS_CHARS, layout

    o = layout(K, n, m)
    W = o["size"]
    B = max(1, min(256, _ARENA_FLOATS // max(W, 1)))
    status = f"<U{STATUS_CHARS}"
    if B == 1:  # many tracks: one slot, views by slicing
        f = np.empty(W)

        def sl(name: str, size: int, shape: tuple[int, ...]) -> Array:
            return f[o[name] : o[name] + size].reshape(shape)

        return iter([(
            K, f, sl("x", K * n, (K, n)), sl("P", K * n * n, (K, n, n)),
            sl("innovation", K * m, (K, m)), sl("standardized", K * m, (K, m)),
            sl("weights", K * m, (K, m)), sl("nis", K, (K,)),
            f[o["n_used"] : o["status"]].view(np.int64),
            f[o["gated"] :].view(np.bool_)[:K],
            f[o["status"] : o["gated"]].view(status),
        )])
    f = np.empty((B, W))

    def block(name: str, shape: tuple[int, ...], dtype: type | str = np.float64) -> list:
        item = np.dtype(dtype).itemsize
        strides = [8 * W] + [item * math.prod(shape[d + 1 :]) for d in range(len(shape))]
        return list(np.ndarray((B, *shape), dtype=dtype, buffer=f, offset=8 * o[name],
                               strides=strides))

    return zip(
        itertools.repeat(K), list(f),
        block("x", (K, n)), block("P", (K, n, n)), block("innovation", (K, m)),
        block("standardized", (K, m)), block("weights", (K, m)), block("nis", (K,)),
        block("n_used", (K,), np.int64), block("gated", (K,), np.bool_),
        block("status", (K,), status),
    )


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
    cov_xy : (K, J) posterior covariance of ``x`` and ``y`` (the track contract's
        ``cov_xy``; NaN on padding).
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
    cov_xy: Array | None = None


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
    relock_var : variance (m^2 and (m/s)^2) set on re-lock, at least: the position's is
        raised to the event's largest squared range (position) innovation and the
        velocity's to its squared speed innovation where those are larger, so that what
        was being rejected is accepted; the acceleration states of the CA model are
        zeroed with a variance of ``relock_var / 100`` (m/s^2)^2.
    sigma_point_predict : UKF only -- propagate sigma points through the motion model
        (seed 001 eq. (21)).  The CV/CA models are linear, for which the unscented
        transform is exact and equals ``F x, F P F^T + Q`` (tested), so by default the UKF
        predicts with the matrices and uses sigma points in the update only (same result,
        half the work).  The compiled engine always predicts with the matrices (for the same
        reason; the difference is rounding).
    alpha0, beta0 : significance of the w-test and missed-detection probability of the
        B-method (seed 003): each updated event's ``NIS`` over its available components
        is tested against ``chi2(1 - alpha; dof)`` with the global ``alpha`` tied to
        ``alpha0, beta0`` (:func:`robustloc.integrity.bmethod.global_critical`, as
        ``track`` and ``locate`` test).  An event that fails with no component rejected
        is ``fault_detected``, not ``ok`` (:meth:`run`, Notes).
    max_failed : this many consecutive events of a track that fail the test with no
        component rejected, or whose update kept a strict minority of their three or
        more components (those rows are ``unavailable``), are counted as one divergence
        (``extra["diverged"]``): the filter no longer agrees with its measurements
        (:meth:`run`, Notes); a diverged UKF restarts at its next event's fix.  0
        disables.
    lost_pos_var : a prediction whose position variance ``V = var_x + var_y`` (m^2)
        exceeds this *and* is too wide to update, ``sqrt(eps) V >= r_min`` (``r_min`` the
        smallest variance ``R_ii`` of the event's components, :data:`SQRT_EPS`), is lost:
        the track restarts from the event's measurements (:meth:`run`).  The default
        1e4 m^2 is a 70 m standard deviation per axis, wider than any UWB cell; the second
        condition is the one that bites (with 0.15 m ranges ``V >= 1.5e6 m^2``: a
        settled CV track at ``q = 0.5`` after a gap of about 50 s without measurements, a
        CA track at ``q = 0.1`` after about 25 s -- predictions 0.9 km wide).  The UKF
        starts again from ``V > lost_pos_var`` alone at an event with ranges and a fix: its
        sigma points lie ``sqrt(n + lambda)`` standard deviations out (2 for CV with the
        paper's ``alpha = 1, kappa = 0``), 140 m and more at 1e4 m^2, across the anchors of
        any UWB cell, where the ranges fold and the unscented moments of the update say
        nothing (:meth:`run`, Notes).
    engine : ``"compiled"`` (default) -- :meth:`step` runs one compiled call per step
        (:mod:`robustloc.filters._compiled`) when the model is the built-in one:
        ``FusionMeasurement``, CV/CA motion, ``robust.mode == "gain"`` and a built-in weight
        function (or none); anything else uses the NumPy core.  ``"numpy"`` -- always the
        batched NumPy core of :mod:`robustloc.filters.core` (the reference the compiled
        path is tested against).
    """

    kind: Literal["ekf", "ukf"] = "ukf"
    motion: Motion = field(default_factory=ConstantVelocity)
    robust: RobustUpdate = PLAIN
    points: SigmaPoints = field(default_factory=SigmaPoints)
    min_speed_mps: float = 0.1
    max_rejected: int = 5
    relock_var: float = 4.0
    lost_pos_var: float = 1e4
    alpha0: float = ALPHA0
    beta0: float = BETA0
    max_failed: int = 5
    sigma_point_predict: bool = False
    engine: Literal["compiled", "numpy"] = "compiled"
    #: per-instance state of the compiled engine (settings vector, output arenas)
    _fast: dict = field(default_factory=dict, init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        if self.kind not in ("ekf", "ukf"):
            raise ValueError(f"filter must be 'ekf' or 'ukf', got {self.kind!r}")
        if self.motion.dim != 2:
            raise ValueError("fusion works in 2-D (east, north); use a motion model with dim=2")
        if self.engine not in ("compiled", "numpy"):
            raise ValueError(f"engine must be 'compiled' or 'numpy', got {self.engine!r}")
        if not (np.isfinite(self.lost_pos_var) and self.lost_pos_var > 0):
            raise ValueError("lost_pos_var must be positive and finite")
        for name in ("alpha0", "beta0"):
            v = getattr(self, name)
            if not 0.0 < v < 1.0:
                raise ValueError(f"{name} must be in (0, 1), got {v}")
        if self.max_failed < 0 or self.max_rejected < 0:
            raise ValueError("max_failed and max_rejected must be >= 0")

    def __getstate__(self) -> dict:
        """Pickle the settings only (the compiled engine's state is rebuilt on use)."""
        state = self.__dict__.copy()
        state["_fast"] = {}
        return state

    def _prepare(self, meas: FusionMeasurement) -> tuple:
        """Settings of the compiled step for ``meas``; ``state[1] is None``: use NumPy.

        ``state = (meas, kernel, prm, slots, [(R, R[None])], threaded kernel)``: the kernel
        (and its multi-threaded twin for many tracks) for the state
        and measurement sizes, its packed settings
        (:func:`robustloc.filters._compiled.pack_params`), an iterator over output slots and
        the last 2-D ``R`` with its 3-D view (one tuple, replaced at once: thread-safe).
        """
        state: tuple = (meas, None, None, iter(()), [(None, None)], None)
        self._fast["state"] = state
        prm = self.compiled_params(meas)
        if prm is not None:
            from robustloc.filters import _compiled

            n, m = self.motion.n_states, meas.m
            state = (meas, _compiled.kernel_for(n, m), prm, iter(()), [(None, None)],
                     _compiled.kernel_for(n, m, threaded=True))
            self._fast["state"] = state
        return state

    def compiled_params(self, meas: FusionMeasurement, kinematic: bool = True,
                        offsets: int = 0, link_n: Array | None = None) -> Array | None:
        """Settings vector of the compiled kernel for ``meas``
        (:func:`robustloc.filters._compiled.pack_params`), or ``None`` when this filter
        and model run on the NumPy core (other engine, model or weight).

        ``kinematic=False``: the ranges of ``meas`` only, without its speed and course
        components (``m = n_ranges``) -- for the range tracker's fused round
        (:mod:`robustloc.tracking._compiled`), which runs the kernel in its own loop.  Its
        motion may then carry offset states, ``offsets``
        (:data:`robustloc.filters._compiled.OFF_COMMON` ..): ``RandomWalkAugmented`` of a
        CV/CA model with one extra state added to every range (``Tracker(range_offset=
        True)``), or one per anchor (``Tracker(link_offsets=True)``; ``link_n``: the
        path-loss exponents of RSSI turned into ranges, ``OFF_LINKS_SCALED``).
        """
        from robustloc.filters import _compiled

        motion = self.motion
        roff = offsets != _compiled.OFF_NONE
        extra = 1 if offsets == _compiled.OFF_COMMON else meas.n_ranges
        if roff and (kinematic or type(motion) is not RandomWalkAugmented
                     or motion.extra != extra):
            return None
        base = motion.base if roff else motion
        if (
            self.engine != "compiled"
            or type(meas) is not FusionMeasurement
            or type(base) not in (ConstantVelocity, ConstantAcceleration)
            or base.dim != 2
            or meas.n_states != motion.n_states
            or self.robust.mode not in ("gain", "variance")
            or (not kinematic and meas.n_ranges == 0)
            or (roff and not base.q > 0)  # the offset's Q enters as a multiple of base.q
        ):
            return None
        from robustloc.robust._compiled import weight_spec

        spec = weight_spec(self.robust.weight)
        n, M = motion.n_states, meas.n_ranges
        m = meas.m if kinematic else M
        lam = self.points.lam(n)
        if spec is None or (self.kind == "ukf" and not n + lam > 0):
            return None
        anchors = np.zeros((0, 2)) if M == 0 else np.asarray(meas.anchors, dtype=float)
        if anchors.shape != (M, 2):
            return None
        wm, wc = self.points.weights(n) if n + lam > 0 else (np.zeros(2 * n + 1),) * 2
        chi = np.full(m + 1, np.inf)  # no gate: NIS > inf never holds
        if self.robust.gate_probability is not None:
            chi[1:] = chi2_ppf(self.robust.gate_probability, np.arange(1, m + 1))
        C = _coefficients(base.order, base.dim)
        cF, cQ = C[0], C[2] if base.noise == "discrete" else C[3]
        if roff:  # F = diag(F_base, I), Q = diag(Q_base, q_extra dt I): powers 0 and 1
            nb = base.n_states
            cF, cQ = (np.pad(c, ((0, 0), (0, extra), (0, extra))) for c in (cF, cQ))
            i = np.arange(nb, nb + extra)
            cF[0, i, i] = 1.0
            cQ[1, i, i] = motion.q_extra / base.q
        return _compiled.pack_params(
            _compiled.EKF if self.kind == "ekf" else _compiled.UKF, base.q,
            self.min_speed_mps, float(n + lam), wm, wc, spec[0], spec[1], chi,
            cF, cQ, anchors, meas._dz2(), kinematic=kinematic, offsets=offsets, link_n=link_n,
            variance=self.robust.mode == "variance",
        )

    @staticmethod
    def _R3(R: ArrayLike, cache: list) -> Array | None:
        """``R`` as ``(1, m, m)`` or ``(K, m, m)`` for the kernel (``None``: not usable)."""
        if type(R) is np.ndarray and R.dtype == np.float64 and R.ndim == 2:
            pair = (R, R[None])  # a view: follows in-place changes of R
            cache[0] = pair
            return pair[1]
        R = np.asarray(R, dtype=float)
        return R[None] if R.ndim == 2 else (R if R.ndim == 3 else None)

    def step(
        self,
        x: Array,
        P: Array,
        dt: Array,
        z: Array,
        R: Array,
        meas: FusionMeasurement,
    ) -> UpdateResult:
        """One vectorized predict + update of ``K`` tracks with per-track ``dt (K,)``.

        Parameters
        ----------
        x, P : ``(K, n)`` states and ``(K, n, n)`` covariances at the previous event.
        dt : ``(K,)`` time steps.
        z : ``(K, m)`` measurements (NaN = missing); the course is ignored where the
            measured speed is below ``min_speed_mps``.
        R : ``(m, m)`` or ``(K, m, m)`` measurement noise.
        meas : the measurement model.

        Returns
        -------
        UpdateResult
            Posterior states and covariances with the update diagnostics (the compiled
            engine's arrays are views of a shared output arena, written once).
        """
        state = self._fast.get("state")
        if state is None or state[0] is not meas:
            state = self._prepare(meas)
        kernel = state[1]
        if kernel is not None:  # compiled engine: one call, outputs into a fresh arena slot
            rc = state[4]
            last = rc[0]
            R3 = last[1] if last[0] is R else self._R3(R, rc)
            s = next(state[3], None)
            if s is None or s[0] != len(x):
                slots = _arenas(len(x), self.motion.n_states, meas.m)
                state = (meas, kernel, state[2], slots, rc, state[5])
                self._fast["state"] = state
                s = next(slots)
            _, fo, xo, Po, yo, eo, wo, nis, nu, gated, status = s
            if len(x) >= _MT_MIN_TRACKS and (nt := _threads()) > 1:  # many tracks: all cores
                done = R3 is not None and state[5](x, P, dt, z, R3, state[2], fo, 4 * nt) == 0
            else:
                done = R3 is not None and kernel(x, P, dt, z, R3, state[2], fo) == 0
            if done:
                return _result(xo, Po, yo, eo, wo, nis, nu, gated, status)
        return self._step_numpy(x, P, dt, z, R, meas)

    def _step_numpy(
        self,
        x: Array,
        P: Array,
        dt: Array,
        z: Array,
        R: Array,
        meas: FusionMeasurement,
    ) -> UpdateResult:
        """:meth:`step` with the batched NumPy core."""
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
        restart: ArrayLike | None = None,
        P_restart: ArrayLike | None = None,
        placed: ArrayLike | None = None,
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
        restart : (K, J, 2) a position fix from each event's measurements (NaN: none), where
            a lost track restarts (below); ``None``: no fixes.
        P_restart : (K, n, n) the covariance a track restarts with; ``None``: ``P0`` (a
            track that starts without a position has a wide ``P0``, and restarts at its
            first fix with this one).  Its velocity block is used where the restart's
            event has no GPS speed and course (at least ``min_speed_mps``): give it the
            velocity variance of a start without them (:func:`robustloc.fusion.run.fuse`
            does), not one fitted to a speed measured before the gap.
        placed : (K,) False for a track that starts without a position (its ``x0`` a
            guess, ``P0`` wide): at its first event with a fix its position is set there,
            with ``P_restart``'s position block, its velocity kept; ``None``: all placed.

        Notes
        -----
        A lost track starts again.  Over a long gap (a day without measurements, a clock
        jump) the prediction's position variance grows as ``q dt^4 / 4`` (CV) or faster
        (CA), and once ``sqrt(eps) V`` reaches the smallest measurement variance the
        innovation covariance ``S = H P- H^T + R`` keeps ``R`` to fewer than half of its
        digits: ``S`` turns singular or indefinite and the update fails (``LinAlgError``)
        or returns garbage.  Such a prediction (``lost_pos_var``) is meaningless, so before
        the update of an event with measurements it is dropped, in both engines alike (the
        test is NumPy, ahead of the step): the track restarts as a new one at the event's
        fix ``restart`` with the covariance ``P_restart``, and the event updates it with
        ``dt = 0`` (counted in ``extra["restarts"]``).  As a track starts: with the
        velocity of the event's GPS speed and course where it has both (speed at least
        ``min_speed_mps``; variance ``R_speed + v^2 R_course`` per axis, no correlation,
        :func:`gps_velocity`), else at rest.  (At rest, the speed and course rows of the
        Jacobian are 0 and the event's GPS speed and course were rejected: a track
        walking at 1 m/s restarted at 0 with a velocity variance of 0.0101 (m/s)^2 fitted
        to its first event's speed, 10 sd off, and the row said ``fault_excluded``.)
        Without a fix the event's measurements cannot place it (and a wide guess
        misleads the UKF's sigma points):
        the track is adrift until its next event with a fix, where it restarts; its rows
        till then coast (status ``predicted``, counted in ``extra["lost_coasts"]``) with
        the last estimate and the variances of its prediction to the row's time.  So does
        a track whose prediction passes ``STATE_LIMIT**2`` at an event without
        measurements.  An update that raises all the same (a near-singular ``S`` below the
        bound) restarts only its own track, or sets it adrift likewise.  The UKF also
        restarts at an event with ranges whose prediction has ``V > lost_pos_var`` (the
        parameter's note: its sigma points then straddle the anchors), when the event has
        a fix; without one it updates as before.

        Every updated event is tested: ``NIS`` over its ``dof`` available components
        against the B-method's ``chi2(1 - alpha; dof)`` (``alpha0``, ``beta0``).  An event
        that fails with every component kept (no robust weight 0, no gate) is
        ``fault_detected``: the filter trusted measurements that contradict it, and the
        row is not ``ok`` (one that rejected a component is ``fault_excluded`` as before;
        the re-lock rule above looks after those).  ``max_failed`` consecutive such events
        mean the filter has diverged -- on uwb-cart group B (``T = 10 s`` at the default
        ``q``) the UKF with the paper's ``alpha = 1`` drifted 15 km away with every row
        ``ok`` and ``NIS`` up to 5e5 (now ``fault_detected`` from its seventh event on).
        Such a run is counted in ``extra["diverged"]`` and ``robustloc fuse`` warns.  The
        EKF is not restarted: a restart at the event's fix, tried, hurt where a persistent
        NLOS range fails the test (uwb-dwm1001 NLOS plain EKF: largest error 24 to 80 m),
        since the fix holds the same range.  The UKF is: its divergence feeds itself
        (sigma points spread across the anchors inflate ``S``, so the test passes now and
        then while the state drifts away -- on group B with hampel weights rows 116 and
        399 m off said ``ok``, and the track came back only when its variance was lost),
        so a diverged UKF track restarts at the fix of its next event that has one
        (updating as before until then), counted in ``extra["restarts"]``.  Measured
        (``bench_fuse_defaults.py``, 8 seeds of group B, CV): RMS 4344 to 1024 m without
        weights, 398 to 58 m with hampel; on the shared uwb-dwm1001 NLOS run the plain UKF
        went from 4.89 to 3.57 m RMS, but its largest error from 24 to 58 m (the EKF's
        case above); with hampel weights the real runs are unchanged.  With a restart's
        GPS velocity (above) group B measured 57.1 m without weights and 27.5 m with
        hampel (the code before: 95.7 and 32.7 m).
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
        cxy = np.full((K, J), np.nan)
        stat = np.full((K, J), "", dtype=object)
        nu = np.zeros((K, J), dtype=np.int64)
        nis = np.full((K, J), np.nan)
        ws = np.full((K, J, m), np.nan)
        t_prev = np.where(np.isfinite(t[:, 0]), t[:, 0], 0.0)
        rejected = np.zeros(K, dtype=np.int64)
        relocks = np.zeros(K, dtype=np.int64)
        nonfinite = np.zeros(K, dtype=np.int64)
        restarts = np.zeros(K, dtype=np.int64)
        coasts = np.zeros(K, dtype=np.int64)
        adrift = np.zeros(K, dtype=bool)  # lost, waiting for a fix to restart at
        pending = np.zeros(K, dtype=bool)  # a diverged UKF, to restart at the next fix
        failed = np.zeros(K, dtype=np.int64)  # consecutive events failing the test
        diverged = np.zeros(K, dtype=np.int64)  # runs of max_failed such events
        gcrit = np.full(m + 1, np.inf)
        gcrit[1:] = global_critical(np.arange(1, m + 1), None, self.alpha0, self.beta0)
        P_init = (P.copy() if P_restart is None
                  else np.array(P_restart, dtype=float).reshape(K, n, n))
        unplaced = (np.zeros(K, dtype=bool) if placed is None
                    else ~np.asarray(placed, dtype=bool).reshape(K))
        fixes = (np.full((K, J, 2), np.nan) if restart is None
                 else np.asarray(restart, dtype=float).reshape(K, J, 2))
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
            # a lost track (Notes): restart at this event's fix, or coast until one comes
            if unplaced.any():  # a track's first fix places it (the ``placed`` notes)
                place = live & unplaced & np.isfinite(fixes[:, j]).all(axis=1)
                if place.any():
                    x, P = x.copy(), P.copy()
                    x[place, :2] = fixes[place, j]
                    P[place, :2, :] = 0.0
                    P[place, :, :2] = 0.0
                    P[place, :2, :2] = P_init[place, :2, :2]
                    dt = np.where(place, 0.0, dt)
                    unplaced &= ~place
            lost = live & (adrift | self._prediction_lost(x, P, dt, zj, Rj, meas))
            # a UKF that diverged, or whose sigma points would straddle the anchors, starts
            # again at this event's fix if it has one, else it updates as it is (Notes)
            redo = (live & ~lost & (pending | self._straddles(P, dt, zj, meas))
                    if self.kind == "ukf" else np.zeros(K, dtype=bool))
            coast = np.zeros(K, dtype=bool)
            if lost.any() or redo.any():
                fix = fixes[:, j]
                go = (lost | redo) & np.isfinite(fix).all(axis=1)
                coast = lost & ~go
                x, P = self._restart(go, x, P, P_init, fix, zj, Rj, meas)
                dt = np.where(go, 0.0, dt)
                zj = np.where(coast[:, None], np.nan, zj)
                restarts += go
                failed = np.where(go, 0, failed)  # a new track: no run of failures yet
                pending &= ~go
            try:
                r = self.step(x, P, dt, zj, Rj, meas)
            except np.linalg.LinAlgError:  # below the bound all the same: track by track
                r, x, P, dt, go, stuck = self._step_each(x, P, dt, zj, Rj, meas, P_init,
                                                         fixes[:, j])
                restarts += go
                coast |= stuck
            r_status, r_nu, r_nis, r_w = r.status, r.n_used, r.nis, r.weights
            r_innov = r.innovation
            x_prior, P_prior = x, P
            x, P = r.x, r.P
            var_row = np.diagonal(P, axis1=1, axis2=2)
            cxy_row = P[:, 0, 1]
            if coast.any():  # the row: the last estimate, with its prediction's variances
                x = np.where(coast[:, None], x_prior, x)
                P = np.where(coast[:, None, None], P_prior, P)
                r_status = np.where(coast, st.PREDICTED, r_status)
                coasts += coast
            adrift = coast | (adrift & ~live)
            with np.errstate(invalid="ignore"):
                sick = ~coast & ~((np.abs(x) <= STATE_LIMIT).all(axis=1)
                                  & (np.abs(P) <= STATE_LIMIT**2).all(axis=(1, 2)))
            if sick.any():  # an update that would poison the state is rejected: keep the prior
                x, P, r_status, r_nu, r_nis, r_w, r_innov = self._reject_update(
                    sick, x_prior, P_prior, dt, Rj, meas, x, P, r_status, r_nu, r_nis, r_w,
                    r_innov)
                nonfinite += sick
            avail = np.isfinite(r_innov).sum(axis=1)
            had = avail > 0
            # the test of the event (Notes): failed with every component kept
            with np.errstate(invalid="ignore"):
                fail = had & (r_nu >= avail) & (r_nis > gcrit[avail])
            kin = np.isfinite(r_innov[:, [meas.speed_index, meas.course_index]]).any(axis=1)
            if (fail & kin).any():  # speed and course linearized at an undetermined speed
                fail &= ~kin | self._speed_determined(x_prior, dt)
            r_status = np.where(fail & (r_status == st.OK), st.FAULT_DETECTED, r_status)
            # the posterior check (Notes): a usable row whose estimate contradicts the
            # measurements it kept is not usable, whatever its innovations said
            post = (had & ~coast & ~sick & st.among(r_status, (st.OK, st.FAULT_EXCLUDED))
                    & self._posterior_fails(x, zj, Rj, r_w, r_innov, meas, gcrit))
            r_status = np.where(post, st.FAULT_DETECTED, r_status)
            fail |= post
            # an update that kept a strict minority of the event's components, of three
            # or more, is no fix: nothing but the filter's own prediction supports it
            # against most of what it measured (locate's rule, robustloc.status.
            # UNAVAILABLE).  Such rows said fault_excluded -- "the rest passes" -- with
            # one component of five kept, hundreds of metres off (the fuse review of
            # 2026-12-06); they count toward divergence.  (One or two components, as in
            # a round-robin of ranges: a rejected range leaves the prediction, which
            # says `predicted`, or half the event, as robust weights should)
            minority = had & (avail >= 3) & (2 * r_nu < avail) & ~coast
            r_status = np.where(minority & st.among(r_status, st.USABLE), st.UNAVAILABLE,
                                r_status)
            if self.max_failed > 0:
                failed = np.where(fail | minority, failed + 1, np.where(had, 0, failed))
                gone = failed == self.max_failed
                diverged += gone  # once per run of failures
                if self.kind == "ukf":  # a diverged UKF restarts at its next fix (Notes)
                    pending |= gone
            if self.max_rejected > 0:
                some_rejected = had & (r_nu < avail)
                rejected = np.where(some_rejected, rejected + 1, np.where(had, 0, rejected))
                lock = rejected >= self.max_rejected
                if lock.any():  # re-lock: wide position/velocity, acceleration reset
                    P = P.copy()
                    x = x.copy()
                    P[lock] = 0.0
                    diag = np.full((int(lock.sum()), n), self.relock_var)
                    diag[:, 4:] = self.relock_var * 0.01
                    # at least as wide as the discrepancy that is being rejected: the
                    # event's largest squared range (or position) innovation for the
                    # position, its speed innovation for the velocity.  A fixed 4 m^2
                    # re-locked a track hundreds of metres off to a 2 m sd, its ranges
                    # were rejected again, and it re-locked every fifth event while it
                    # coasted away (UKF/CA with asymmetric-igg weights on a simulated
                    # cart: 589 m off, rows `predicted` with sd 2.8-12 m; the fuse
                    # review of 2026-12-06)
                    inn = r_innov[lock]
                    k_pos = [c for c in range(inn.shape[1])
                             if c not in (meas.speed_index, meas.course_index)]
                    with np.errstate(invalid="ignore"):
                        big = np.nanmax(np.where(np.isfinite(inn[:, k_pos]),
                                                 inn[:, k_pos] ** 2, 0.0), axis=1,
                                        initial=0.0)
                        sp = inn[:, meas.speed_index]
                        big_v = np.where(np.isfinite(sp), sp * sp, 0.0)
                    diag[:, :2] = np.maximum(diag[:, :2], big[:, None])
                    diag[:, 2:4] = np.maximum(diag[:, 2:4], big_v[:, None])
                    P[lock] = diag[:, :, None] * np.eye(n)[None]
                    x[np.ix_(lock, np.arange(4, n))] = 0.0
                    rejected[lock] = 0
                    relocks += lock
            t_prev = np.where(live & ~coast, tj, t_prev)  # a lost track's clock stops
            xs[:, j] = x
            vs[:, j] = np.where(coast[:, None], var_row, np.diagonal(P, axis1=1, axis2=2))
            cxy[:, j] = np.where(live, np.where(coast, cxy_row, P[:, 0, 1]), np.nan)
            stat[:, j] = np.where(live, r_status, "")
            nu[:, j] = r_nu
            nis[:, j] = r_nis
            ws[:, j] = r_w
        return FusionTrack(
            time_s=t, x=xs, var=vs, status=stat.astype(str), n_used=nu, nis=nis, weights=ws,
            P_last=P, extra={"relocks": relocks, "nonfinite": nonfinite,
                             "restarts": restarts, "lost_coasts": coasts,
                             "diverged": diverged},
            cov_xy=cxy,
        )

    def _prediction_lost(self, x: Array, P: Array, dt: Array, z: Array, R: Array,
                         meas: FusionMeasurement) -> NDArray[np.bool_]:
        """Tracks whose prediction over ``dt`` is too wide to update with ``z`` (the
        ``lost_pos_var`` rule, :meth:`run`): ``V = var_x + var_y`` of ``F P F^T + Q`` beyond
        ``lost_pos_var`` and ``sqrt(eps) V >= r_min``, the smallest ``R_ii`` of the
        components present (a course below ``min_speed_mps`` is not used).  NaN ``V`` is
        lost; without components only a ``V`` beyond ``STATE_LIMIT**2`` is."""
        K = x.shape[0]
        if R.ndim == 2:
            rd = np.broadcast_to(np.diagonal(R), (K, R.shape[0]))
        else:
            rd = np.diagonal(R, axis1=-2, axis2=-1)
        use = np.isfinite(z)
        ci, si = meas.course_index, meas.speed_index
        use[:, ci] &= np.abs(z[:, si]) >= self.min_speed_mps
        with np.errstate(invalid="ignore"):
            r_min = np.where(use, rd, np.inf).min(axis=1)
        avail = use.any(axis=1)
        V = self._predicted_pos_var(P, dt)
        with np.errstate(invalid="ignore", over="ignore"):
            fine = (V <= self.lost_pos_var) | (V * SQRT_EPS < r_min)
            # beyond what a posterior may hold (STATE_LIMIT): lost even without an update
            absurd = ~(V <= STATE_LIMIT**2)
        return (avail & ~fine) | absurd

    def _predicted_pos_var(self, P: Array, dt: Array) -> Array:
        """``V = var_x + var_y`` of the predictions ``F P F^T + Q`` over ``dt (K,)``."""
        with np.errstate(invalid="ignore", over="ignore"):
            if np.all(dt == dt[0]):
                F, Q = self.motion.FQ(float(dt[0]))
                Fp = F[:2]
                return np.einsum("ia,kab,ib->k", Fp, P, Fp) + (Q[0, 0] + Q[1, 1])
            F, Q = self.motion.F(dt), self.motion.Q(dt)
            Fp = F[:, :2]
            return np.einsum("kia,kab,kib->k", Fp, P, Fp) + (Q[:, 0, 0] + Q[:, 1, 1])

    def _straddles(self, P: Array, dt: Array, z: Array, meas: FusionMeasurement
                   ) -> NDArray[np.bool_]:
        """Tracks whose prediction over ``dt`` has ``V > lost_pos_var`` at an event with a
        range: the UKF's sigma points, ``sqrt(n + lambda)`` standard deviations out, then
        lie across the anchors (``lost_pos_var``, :meth:`run`)."""
        M = meas.n_ranges
        ranged = np.isfinite(z[:, :M]).any(axis=1) if M else np.zeros(len(z), dtype=bool)
        if not ranged.any():
            return ranged
        with np.errstate(invalid="ignore"):
            return ranged & (self._predicted_pos_var(P, dt) > self.lost_pos_var)

    @staticmethod
    def _posterior_fails(x: Array, z: Array, R: Array, w: Array, innov: Array,
                         meas: FusionMeasurement, gcrit: Array) -> NDArray[np.bool_]:
        """Rows whose posterior ``x`` contradicts the components the update kept.

        ``T = sum_i w_i (z_i - h_i(x+))^2 / R_ii`` over the components with an innovation
        and a weight ``w_i > 0`` (each at the variance ``R_ii / w_i`` the robust update
        gave it; a course wrapped to +-pi) against the event's critical value
        ``gcrit[dof]``.  A consistent posterior's residuals have covariance
        ``R - H P+ H^T <= R``, so the test is conservative (Teunissen 2006, sec. 4.2:
        the least-squares residual's cofactor) and its degrees of freedom are those of
        the components tested.  It catches what the innovation test
        cannot: a UKF whose sigma points straddle the anchors inflates ``S`` until every
        innovation looks small (rows 20-38 m off said ``ok``, NIS 3-9), and an update
        that rejected one component and kept the others 1.5 km off (``fault_excluded``,
        NIS 4e5) -- the fuse review of 2026-12-07.  The ranges (or the fix's position)
        only: speed and course near standstill are too nonlinear for the UKF's posterior
        mean (on the clean cart, CA: speeds 0.3-0.5 m/s where GPS said 0.2 +- 0.05, the
        positions 5-15 cm off; 27 of 51 rows failed when they took part)."""
        K, m = z.shape
        with np.errstate(invalid="ignore"):
            res = z - meas.predict(x)
        rd = (np.broadcast_to(np.diagonal(R), (K, m)) if R.ndim == 2
              else np.diagonal(R, axis1=-2, axis2=-1))
        use = np.isfinite(innov) & np.isfinite(res) & np.isfinite(w) & (w > 0) & (rd > 0)
        use[:, [meas.speed_index, meas.course_index]] = False
        with np.errstate(invalid="ignore", over="ignore", divide="ignore"):
            T = np.where(use, w * res * res / np.where(use, rd, 1.0), 0.0).sum(axis=1)
        dof = use.sum(axis=1)
        return (dof > 0) & (T > gcrit[dof])

    def _speed_determined(self, x: Array, dt: Array) -> NDArray[np.bool_]:
        """Tracks whose predicted speed over ``dt`` is at least ``min_speed_mps``.

        Speed ``|v|`` and course ``atan2(vx, vy)`` are linearized at the predicted
        velocity.  At standstill the heading is undefined (the reason a course below
        ``min_speed_mps`` is not used) and at ``v = 0`` -- a track started or re-locked at
        rest -- both rows of the Jacobian are 0 while the course innovation is the whole
        measured course: the ``NIS`` of an event with a GPS speed or course is then not
        chi-square, and the test (:meth:`run`, Notes) is not made on it.
        """
        if np.all(dt == dt[0]):
            v = x @ self.motion.F(float(dt[0]))[2:4].T
        else:
            v = np.einsum("kia,ka->ki", self.motion.F(dt)[:, 2:4], x)
        with np.errstate(invalid="ignore"):
            return np.hypot(v[:, 0], v[:, 1]) >= self.min_speed_mps

    def _restart(self, go: NDArray[np.bool_], x: Array, P: Array, P_init: Array, fix: Array,
                 z: Array, R: Array, meas: FusionMeasurement) -> tuple[Array, Array]:
        """States and covariances with the tracks ``go`` re-initialised at their event's
        ``fix (K, 2)`` with the covariance ``P_init``, as a track starts (:meth:`run`,
        Notes): with the velocity of the event's GPS speed and course ``z (K, m)`` where it
        has both (:func:`gps_velocity`, the variances of ``R``), else at rest.

        Parameters
        ----------
        go : (K,) the tracks that restart.
        x, P : (K, n) states and (K, n, n) covariances.
        P_init : (K, n, n) the covariance of a restarted track.
        fix : (K, 2) the event's position fix.
        z : (K, m) the event's measurements (NaN: missing).
        R : (m, m) or (K, m, m) their noise.
        meas : the measurement model (where speed and course are in ``z``).

        Returns
        -------
        x, P : the states and covariances, those of ``go`` restarted.
        """
        K = len(x)
        rd = (np.broadcast_to(np.diagonal(R), (K, R.shape[-1])) if R.ndim == 2
              else np.diagonal(R, axis1=-2, axis2=-1))
        si, ci = meas.speed_index, meas.course_index
        v, var_v, moving = gps_velocity(z[:, si], z[:, ci], rd[:, si], rd[:, ci],
                                        self.min_speed_mps)
        xr = np.zeros_like(x)
        xr[:, :2] = fix
        Pr = P_init
        if (go & moving).any():
            xr[moving, 2:4] = v[moving]
            Pr = P_init.copy()
            Pr[moving, 2:4, :] = 0.0
            Pr[moving, :, 2:4] = 0.0
            Pr[moving, 2, 2] = Pr[moving, 3, 3] = var_v[moving]
        return (np.where(go[:, None], xr, x), np.where(go[:, None, None], Pr, P))

    def _step_each(self, x: Array, P: Array, dt: Array, z: Array, R: Array,
                   meas: FusionMeasurement, P_init: Array, fix: Array) -> tuple:
        """:meth:`step` track by track after the batched step raised ``LinAlgError``: a
        track whose update raises restarts at its event's fix (:meth:`_restart`, ``dt =
        0``) and updates again; without a fix, or if that raises too, it coasts (the
        prediction, status ``predicted``).

        Returns the step's result, the priors and steps it started from (restarted where
        it restarted), and which tracks restarted and which coasted.
        """
        K, m = z.shape
        R3 = np.broadcast_to(R, (K, m, m)) if R.ndim == 2 else R
        has = np.isfinite(fix).all(axis=1)
        go = np.zeros(K, dtype=bool)
        coast = np.zeros(K, dtype=bool)
        parts = []
        for k in range(K):
            sl = slice(k, k + 1)
            try:
                rk = self.step(x[sl], P[sl], dt[sl], z[sl], R3[sl], meas)
            except np.linalg.LinAlgError:
                rk = None
                if has[k]:
                    xk, Pk = self._restart(np.ones(1, bool), x[sl], P[sl], P_init[sl],
                                           fix[sl], z[sl], R3[sl], meas)
                    try:
                        rk = self.step(xk, Pk, np.zeros(1), z[sl], R3[sl], meas)
                        go[k] = True
                    except np.linalg.LinAlgError:
                        pass
                if rk is None:  # nothing can be updated: coast
                    coast[k] = True
                    rk = self.step(x[sl], P[sl], dt[sl], np.full((1, m), np.nan), R3[sl],
                                   meas)
            parts.append([np.array(getattr(rk, f)) for f in (
                "x", "P", "innovation", "standardized", "weights", "nis", "n_used", "gated",
                "status")])
        cols = [np.concatenate([p[i] for p in parts]) for i in range(9)]
        x, P = self._restart(go, x, P, P_init, fix, z, R3, meas)
        return _result(*cols), x, P, np.where(go, 0.0, dt), go, coast

    def _reject_update(self, sick, x0, P0, dt, Rj, meas, x, P, status, n_used, nis, w,
                       innov) -> tuple:
        """Replace the non-finite or absurd (beyond :data:`STATE_LIMIT`) posteriors of tracks
        ``sick`` by their prediction.

        No input that reaches the filter should do this (absurd values are refused at the
        door), but a near-singular innovation covariance or an overflow in a user-supplied
        model must not poison a track for good: the update of such a track is rejected,
        its state is the prediction (status ``predicted``, no component used), or the
        previous state when even the prediction is not finite.
        """
        K, m = w.shape
        zn = np.full((K, m), np.nan)
        rp = self.step(x0, P0, dt, zn, Rj, meas)
        xp, Pp = np.array(rp.x), np.array(rp.P)
        with np.errstate(invalid="ignore"):
            pred_ok = ((np.abs(xp) <= STATE_LIMIT).all(axis=1)
                       & (np.abs(Pp) <= STATE_LIMIT**2).all(axis=(1, 2)))
        xp = np.where(pred_ok[:, None], xp, x0)
        Pp = np.where(pred_ok[:, None, None], Pp, P0)
        return (
            np.where(sick[:, None], xp, x), np.where(sick[:, None, None], Pp, P),
            np.where(sick, "predicted", status), np.where(sick, 0, n_used),
            np.where(sick, np.nan, nis), np.where(sick[:, None], np.nan, w),
            np.where(sick[:, None], np.nan, innov),
        )


def gps_velocity(speed: ArrayLike, course: ArrayLike, var_speed: ArrayLike,
                 var_course: ArrayLike, min_speed_mps: float
                 ) -> tuple[Array, Array, NDArray[np.bool_]]:
    """Velocity of a track that starts (or restarts) at an event with a GPS speed and course.

    Parameters
    ----------
    speed, course : (K,) measured speed (m/s) and course (rad, clockwise from north; NaN:
        none).
    var_speed, var_course : (K,) their variances (``R``).
    min_speed_mps : below this speed the course is undefined (no velocity).

    Returns
    -------
    v : (K, 2) ``[vx, vy] = v [sin c, cos c]`` (0 where not ``moving``).
    var_v : (K,) its variance per axis, the speed's plus the course's across the track,
        ``var_speed + v^2 var_course`` (NaN where not ``moving``).
    moving : (K,) a speed of at least ``min_speed_mps`` and a finite course.
    """
    spd = np.asarray(speed, dtype=float)
    crs = np.asarray(course, dtype=float)
    with np.errstate(invalid="ignore"):
        moving = (spd >= min_speed_mps) & np.isfinite(crs)
    s = np.where(moving, spd, 0.0)
    c = np.where(moving, crs, 0.0)
    v = np.stack([s * np.sin(c), s * np.cos(c)], axis=-1)
    var_v = np.where(moving, np.asarray(var_speed, dtype=float)
                     + s * s * np.asarray(var_course, dtype=float), np.nan)
    return v, var_v, moving


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
    return st.among(status, (st.OK, st.FAULT_EXCLUDED, st.FAULT_DETECTED, st.PREDICTED))
