"""The compiled fusion step (robustloc.filters._compiled) against the NumPy core.

``FusionFilter(engine="numpy")`` runs the batched NumPy core of ``robustloc.filters.core``
(an independent implementation of the same equations); every output field of the compiled
step must agree with it to rounding, on data built to hit the edge cases: missing
components, speeds below ``min_speed_mps``, headings near +-pi, outliers for the robust
weights, the chi-square gate, tracks with nothing to update, per-track ``dt`` and ``R``.
A plain EKF is also checked against FilterPy's (Joseph-form) EKF.
"""

from __future__ import annotations

import pickle
import zlib

import numpy as np
import pytest

from robustloc.filters import ConstantAcceleration, ConstantVelocity, RobustUpdate, SigmaPoints
from robustloc.fusion.pipeline import FusionFilter, FusionMeasurement, initial_state
from robustloc.robust.weights import (
    IGG,
    IGG3,
    AsymmetricIGG,
    Hampel,
    Huber,
    LeastSquares,
    WeightFunction,
)

FIELDS = ("x", "P", "innovation", "standardized", "weights", "nis", "n_used", "gated", "status")
ANCHORS = np.array([[0.0, 0.0], [6.0, 0.0], [6.0, 5.0]])
HEIGHTS = np.array([1.2, 1.5, 0.4])
WEIGHTS = {
    "none": None,
    "ls": LeastSquares(),
    "huber": Huber(1.5),
    "igg": IGG(1.5, 3.0),
    "igg3": IGG3(1.5, 3.0),
    "asym": AsymmetricIGG(1.5, 3.0, 4.0),
    "hampel": Hampel(1.0, 2.0, 4.0),
}


def _assert_same(a, b, rtol: float = 1e-10, atol: float = 1e-10) -> None:
    for name in FIELDS:
        va, vb = getattr(a, name), getattr(b, name)
        assert va.shape == vb.shape, name
        if va.dtype.kind == "f":
            np.testing.assert_allclose(va, vb, rtol=rtol, atol=atol, equal_nan=True,
                                       err_msg=name)
        else:
            np.testing.assert_array_equal(va, vb, err_msg=name)


def _case(motion, tight: bool, K: int, seed: int, per_track: bool = False):
    """States, covariances, steps, measurements and noise that hit the edge cases."""
    rng = np.random.default_rng(seed)
    n = motion.n_states
    meas = FusionMeasurement(n, ANCHORS, HEIGHTS) if tight else FusionMeasurement(n)
    m = meas.m
    x = np.zeros((K, n))
    x[:, :2] = rng.uniform(0.5, 5.5, (K, 2))
    x[:, 2:4] = rng.normal(0.0, 1.0, (K, 2))
    if n > 4:
        x[:, 4:] = rng.normal(0.0, 0.2, (K, 2))
    A = rng.normal(size=(K, n, n))
    P = 0.02 * A @ np.swapaxes(A, 1, 2) + 0.05 * np.eye(n)
    P += 1e-13 * rng.normal(size=P.shape)  # not exactly symmetric, as a user's P0 may be
    dt = rng.uniform(0.2, 1.5, K) if per_track else np.full(K, 0.5)
    truth = motion.f(x, 0.5) + rng.normal(0.0, 0.05, (K, n))
    sig = np.sqrt(np.r_[np.full(m - 2, 0.04), 0.01, 0.003])
    z = meas.predict(truth) + rng.normal(size=(K, m)) * sig
    ci, si = meas.course_index, meas.speed_index
    # headings near +-pi: moving south, measured course just either side of the cut
    south = np.arange(K) % 7 == 3
    x[south, 2], x[south, 3] = rng.normal(0.0, 0.01, south.sum()), -1.0
    z[south, si] = 1.0
    z[south, ci] = np.where(rng.random(south.sum()) < 0.5, np.pi - 2e-3, -np.pi + 2e-3)
    z[np.arange(K) % 5 == 1, 0] += 3.0  # outliers in the first component
    z[np.arange(K) % 9 == 2, m - 3] -= 1.5
    z[np.arange(K) % 4 == 0, 1] = np.nan  # missing components
    z[np.arange(K) % 6 == 5, si] = 0.04  # slow: course ignored
    z[np.arange(K) % 11 == 7, si] = np.nan  # no speed: course ignored
    z[np.arange(K) % 13 == 12] = np.nan  # nothing to update with
    if per_track:
        B = rng.normal(size=(K, m, m)) * 0.02
        R = B @ np.swapaxes(B, 1, 2) + np.diag(sig**2)
    else:
        R = np.diag(sig**2)
        R[0, 1] = R[1, 0] = 0.3 * sig[0] * sig[1]  # correlated x-y (a UWB fix covariance)
    return meas, x, P, dt, z, R


def _both(kind, motion, robust, meas, x, P, dt, z, R, **kw):
    fc = FusionFilter(kind, motion, robust, **kw)
    fn = FusionFilter(kind, motion, robust, engine="numpy", **kw)
    a = fc.step(x, P, dt, z, R, meas)
    assert fc._fast["state"][1] is not None  # the compiled engine was used
    return a, fn.step(x, P, dt, z, R, meas)


@pytest.mark.parametrize("kind", ["ekf", "ukf"])
@pytest.mark.parametrize("motion", [ConstantVelocity(q=0.05), ConstantAcceleration(q=0.02)],
                         ids=["cv", "ca"])
@pytest.mark.parametrize("tight", [False, True], ids=["loose", "tight"])
@pytest.mark.parametrize("weight", list(WEIGHTS))
@pytest.mark.parametrize("gate", [None, 0.99])
@pytest.mark.parametrize("mode", ["gain", "variance"])
def test_compiled_step_matches_numpy(kind, motion, tight, weight, gate, mode):
    seed = zlib.crc32(f"{kind}{tight}{weight}".encode())
    meas, x, P, dt, z, R = _case(motion, tight, K=50, seed=seed)
    robust = RobustUpdate(WEIGHTS[weight], gate, mode=mode)
    a, b = _both(kind, motion, robust, meas, x, P, dt, z, R)
    _assert_same(a, b)
    # the data do reach the edge cases
    assert (a.status == "predicted").any() and (a.status == "ok").any()
    assert np.isnan(a.nis[a.status == "predicted"]).all()
    if weight not in ("none", "ls", "huber") or gate is not None:
        assert (a.status == "fault_excluded").any()


@pytest.mark.parametrize("kind", ["ekf", "ukf"])
@pytest.mark.parametrize("tight", [False, True], ids=["loose", "tight"])
def test_per_track_dt_and_R_and_single_track(kind, tight):
    motion = ConstantAcceleration(q=0.1, noise="continuous")
    meas, x, P, dt, z, R = _case(motion, tight, K=50, seed=7, per_track=True)
    robust = RobustUpdate(IGG3(1.5, 3.0), 0.999)
    _assert_same(*_both(kind, motion, robust, meas, x, P, dt, z, R))
    for k in (0, 3, 12):  # K = 1, shared R, one of them with nothing to update
        one = slice(k, k + 1)
        _assert_same(*_both(kind, motion, robust, meas, x[one], P[one], dt[one], z[one], R[k]))


@pytest.mark.parametrize("kind", ["ekf", "ukf"])
def test_gated_track_keeps_prediction(kind):
    motion = ConstantVelocity(q=0.05)
    meas, x, P, dt, z, R = _case(motion, False, K=20, seed=3)
    z[:, :2] = x[:, :2] + 0.01
    z[:, 2], z[:, 3] = np.hypot(x[:, 2], x[:, 3]), np.arctan2(x[:, 2], x[:, 3])
    z[5, 0] += 50.0  # far outside any gate
    a, b = _both(kind, motion, RobustUpdate(Huber(1.5), 0.99), meas, x, P, dt, z, R)
    _assert_same(a, b)
    assert a.gated[5] and a.status[5] == "fault_excluded" and a.n_used[5] == 0
    assert (a.weights[5] == 0).all() and a.nis[5] > 100
    F, Q = motion.F(dt[5]), motion.Q(dt[5])
    np.testing.assert_allclose(a.x[5], F @ x[5], rtol=1e-12)  # prediction only
    Ps = 0.5 * (P[5] + P[5].T)
    np.testing.assert_allclose(a.P[5], F @ Ps @ F.T + Q, rtol=1e-12, atol=1e-15)
    assert not a.gated[np.arange(20) != 5].any()


def test_ukf_sigma_point_predict_setting_and_alpha():
    # the kernel predicts with F either way (exact for a linear model, to rounding)
    motion = ConstantAcceleration(q=0.02)
    meas, x, P, dt, z, R = _case(motion, True, K=30, seed=11)
    robust = RobustUpdate(AsymmetricIGG(1.5, 3.0, 4.0))
    a, b = _both("ukf", motion, robust, meas, x, P, dt, z, R, sigma_point_predict=True)
    _assert_same(a, b, rtol=1e-9, atol=1e-10)
    a, b = _both("ukf", motion, robust, meas, x, P, dt, z, R,
                 points=SigmaPoints(alpha=0.5, beta=2.0, kappa=1.0))
    _assert_same(a, b)


def test_results_are_not_overwritten_and_fallbacks():
    motion = ConstantVelocity(q=0.05)
    meas, x, P, dt, z, R = _case(motion, False, K=1, seed=5)
    f = FusionFilter("ekf", motion, RobustUpdate(Huber(1.5)))
    first = f.step(x, P, dt, z, R, meas)
    kept = {name: getattr(first, name).copy() for name in FIELDS}
    xs, Ps = x, P
    for _ in range(600):  # more steps than one output arena holds
        r = f.step(xs, Ps, dt, z, R, meas)
        xs, Ps = r.x, r.P
    for name in FIELDS:
        np.testing.assert_array_equal(getattr(first, name), kept[name])

    class Custom(WeightFunction):
        def weights(self, u):
            return np.where(np.abs(u) < 2, 1.0, 0.5)

    for robust in (RobustUpdate(Custom()), RobustUpdate(Custom(), mode="variance")):
        g = FusionFilter("ekf", motion, robust)
        r = g.step(x, P, dt, z, R, meas)
        assert g._fast["state"][1] is None  # no compiled twin: NumPy path
        _assert_same(r, FusionFilter("ekf", motion, robust, engine="numpy").step(
            x, P, dt, z, R, meas))
    # an indefinite covariance: the kernel's Cholesky fails, the NumPy path takes over
    bad = P.copy()
    bad[0, 2, 2] = bad[0, 3, 3] = -1.0
    u = FusionFilter("ukf", motion)
    _assert_same(u.step(x, bad, dt, z, R, meas),
                 FusionFilter("ukf", motion, engine="numpy").step(x, bad, dt, z, R, meas))
    with pytest.raises(ValueError, match="engine"):
        FusionFilter("ekf", motion, engine="fast")
    # a used filter pickles (without its compiled-engine state) and steps the same
    g = pickle.loads(pickle.dumps(f))
    assert g == f and g._fast == {}
    _assert_same(g.step(x, P, dt, z, R, meas), f.step(x, P, dt, z, R, meas))


@pytest.mark.parametrize("kind", ["ekf", "ukf"])
def test_run_matches_numpy_engine(kind):
    rng = np.random.default_rng(21)
    K, J = 4, 60
    motion = ConstantVelocity(q=0.02)
    meas = FusionMeasurement(4, ANCHORS, HEIGHTS)
    t = np.cumsum(rng.uniform(0.1, 0.4, (K, J)), axis=1)
    t[1, 40:] = np.nan  # a shorter track
    pos = np.stack([2 + np.cos(0.2 * t), 2 + np.sin(0.2 * t)], axis=-1)
    vel = np.stack([-0.2 * np.sin(0.2 * t), 0.2 * np.cos(0.2 * t)], axis=-1)
    truth = np.concatenate([pos, vel], axis=-1)
    z = meas.predict(np.nan_to_num(truth).reshape(-1, 4)).reshape(K, J, -1)
    z += rng.normal(size=z.shape) * np.r_[0.05, 0.05, 0.05, 0.02, 0.05]
    z[rng.random(z.shape) < 0.1] = np.nan
    z[rng.random((K, J)) < 0.05, 0] += 4.0  # outliers: weights, relocks
    var = np.broadcast_to(np.r_[0.05, 0.05, 0.05, 0.02, 0.05] ** 2, z.shape).copy()
    x0, P0 = initial_state(pos[:, 0], 4)
    robust = RobustUpdate(IGG3(1.5, 2.5), 0.999)
    runs = [FusionFilter(kind, motion, robust, max_rejected=2, engine=e).run(t, z, var, meas,
                                                                             x0, P0)
            for e in ("compiled", "numpy")]
    a, b = runs
    for name in ("x", "var", "nis", "weights", "P_last"):
        np.testing.assert_allclose(getattr(a, name), getattr(b, name), rtol=1e-9, atol=1e-10,
                                   equal_nan=True, err_msg=name)
    np.testing.assert_array_equal(a.status, b.status)
    np.testing.assert_array_equal(a.n_used, b.n_used)
    np.testing.assert_array_equal(a.extra["relocks"], b.extra["relocks"])
    assert (a.status == "fault_excluded").any()


def test_plain_ekf_matches_filterpy():
    filterpy = pytest.importorskip("filterpy.kalman")
    motion = ConstantVelocity(q=1e-2)
    meas = FusionMeasurement(4)
    rng = np.random.default_rng(2)
    R = np.diag([0.01, 0.01, 4e-4, 1e-3])
    F, Q = motion.F(1.0), motion.Q(1.0)
    ref = filterpy.ExtendedKalmanFilter(4, 4)
    ref.x, ref.P, ref.F, ref.Q, ref.R = np.array([0.0, 0.0, 0.3, 0.4]), np.eye(4), F, Q, R

    def hx(s):
        return np.array([s[0], s[1], np.hypot(s[2], s[3]), np.arctan2(s[2], s[3])])

    def hjac(s):
        return meas.jacobian(s[None])[0]

    def res(a, b):
        d = np.subtract(a, b)
        d[3] = (d[3] + np.pi) % (2 * np.pi) - np.pi
        return d

    f = FusionFilter("ekf", motion, min_speed_mps=0.0)
    x, P = ref.x[None].copy(), ref.P[None].copy()
    for j in range(40):
        zj = np.array([0.3 * j, 0.4 * j, 0.5, np.arctan2(0.3, 0.4)]) + rng.normal(0, 0.02, 4)
        ref.predict()
        ref.update(zj, hjac, hx, residual=res)
        r = f.step(x, P, np.ones(1), zj[None], R, meas)
        x, P = r.x, r.P
        np.testing.assert_allclose(x[0], ref.x, rtol=1e-9, atol=1e-10)
        np.testing.assert_allclose(P[0], ref.P, rtol=1e-9, atol=1e-12)


@pytest.mark.parametrize("kind", ["ekf", "ukf"])
@pytest.mark.parametrize("motion", [ConstantVelocity(q=0.05), ConstantAcceleration(q=0.02)],
                         ids=["cv", "ca"])
@pytest.mark.parametrize("tight", [False, True], ids=["loose", "tight"])
def test_many_tracks_threaded_kernel(kind, motion, tight):
    """From 256 tracks the step splits the tracks into blocks over numba's threads: the
    threaded kernel (called with several blocks even on a one-core machine) gives the
    same outputs as the serial one and as the NumPy core."""
    from robustloc.filters import _compiled

    meas, x, P, dt, z, R = _case(motion, tight, K=300, seed=11, per_track=True)
    robust = RobustUpdate(IGG3(1.5, 3.0), 0.999)
    a, b = _both(kind, motion, robust, meas, x, P, dt, z, R)  # step: threaded if > 1 thread
    _assert_same(a, b)
    f = FusionFilter(kind, motion, robust=robust)
    f.step(x[:1], P[:1], dt[:1], z[:1], R[0], meas)  # prepares the packed settings
    prm = f._fast["state"][2]
    n, m = motion.n_states, meas.m
    layout = _compiled.layout(len(x), n, m)
    serial, threaded = np.empty(layout["size"]), np.empty(layout["size"])
    args = (x, P, dt, np.ascontiguousarray(z), np.ascontiguousarray(R))
    assert _compiled.kernel_for(n, m)(*args, prm, serial) == _compiled.DONE
    for blocks in (1, 7, 300, 1000):
        threaded[:] = np.nan
        assert _compiled.kernel_for(n, m, threaded=True)(*args, prm, threaded, blocks) == 0
        g = layout["gated"]  # the gate flags are bytes; the padding after them is unused
        np.testing.assert_array_equal(threaded[:g].view(np.uint64), serial[:g].view(np.uint64))
        np.testing.assert_array_equal(threaded[g:].view(np.uint8)[: len(x)],
                                      serial[g:].view(np.uint8)[: len(x)])
    np.testing.assert_allclose(serial[: len(x) * n].reshape(-1, n), a.x, rtol=1e-10,
                               atol=1e-10)


def test_fast_result_sets_every_field_of_update_result():
    """The compiled path builds UpdateResult without its __init__ (hot path): it must set
    exactly the dataclass's fields, so a field added later cannot go missing silently."""
    import dataclasses

    from robustloc.filters.core import UpdateResult
    from robustloc.fusion.pipeline import _result

    names = [f.name for f in dataclasses.fields(UpdateResult)]
    r = _result(*range(len(names)))
    assert list(vars(r)) == names
    assert [getattr(r, n) for n in names] == list(range(len(names)))
    assert r == UpdateResult(*range(len(names)))


@pytest.mark.parametrize("kind", ["ekf", "ukf"])
@pytest.mark.parametrize("motion", [ConstantVelocity(q=1.0), ConstantAcceleration(q=0.5)],
                         ids=["cv", "ca"])
def test_ranges_only_kernel_equals_missing_speed_and_course(kind, motion):
    """``pack_params(..., kinematic=False)`` (the range tracker's round) drops the speed and
    course rows; with them present but missing (identity rows of ``S``, zero gain) the
    kernel computes the same numbers: equal to the bit, outliers and gaps included."""
    from robustloc.filters import _compiled

    rng = np.random.default_rng(21)
    K, M, n = 200, 6, motion.n_states
    a = rng.uniform(0.0, 20.0, (M, 2))
    meas = FusionMeasurement(n, a, np.full(M, 0.5))
    f = FusionFilter(kind, motion, robust=RobustUpdate(Huber(1.5)))
    p_kin, p_rng = f.compiled_params(meas), f.compiled_params(meas, kinematic=False)
    assert p_kin is not None and p_rng is not None
    x = np.zeros((K, n))
    x[:, :2] = rng.uniform(5.0, 15.0, (K, 2))
    x[:, 2:4] = rng.normal(0.0, 1.0, (K, 2))
    A = rng.normal(size=(K, n, n))
    P = 0.1 * A @ np.swapaxes(A, 1, 2) + 0.1 * np.eye(n)
    dt = rng.uniform(0.2, 1.0, K)
    z = meas.predict(x)[:, :M] + rng.normal(0.0, 0.1, (K, M))
    z[rng.random((K, M)) < 0.2] = np.nan
    z[rng.random((K, M)) < 0.05] += 3.0
    R = np.zeros((K, M, M))
    R[:, range(M), range(M)] = rng.uniform(0.005, 0.02, (K, M))
    zk = np.concatenate([z, np.full((K, 2), np.nan)], axis=1)
    Rk = np.zeros((K, M + 2, M + 2))
    Rk[:, :M, :M] = R
    Rk[:, M, M] = Rk[:, M + 1, M + 1] = 1.0
    kern = _compiled.kernel_for(n, 0)
    lk, lr = _compiled.layout(K, n, M + 2), _compiled.layout(K, n, M)
    fk, fr = np.empty(lk["size"]), np.empty(lr["size"])
    assert kern(x, P, dt, zk, Rk, p_kin, fk) == _compiled.DONE
    assert kern(x, P, dt, z, R, p_rng, fr) == _compiled.DONE
    np.testing.assert_array_equal(fk[: lk["innovation"]], fr[: lr["innovation"]])  # x, P
    for name in ("innovation", "standardized", "weights"):
        nxt = {"innovation": "standardized", "standardized": "weights", "weights": "nis"}[name]
        np.testing.assert_array_equal(fk[lk[name]: lk[nxt]].reshape(K, M + 2)[:, :M],
                                      fr[lr[name]: lr[nxt]].reshape(K, M), err_msg=name)
    np.testing.assert_array_equal(fk[lk["nis"]: lk["gated"]], fr[lr["nis"]: lr["gated"]])
    # a ranges-only vector needs anchors; a mismatched measurement size is refused
    assert f.compiled_params(FusionMeasurement(n), kinematic=False) is None


@pytest.mark.parametrize("kind", ["ekf", "ukf"])
@pytest.mark.parametrize("engine", ["compiled", "numpy"])
@pytest.mark.parametrize("tight", [False, True], ids=["loose", "tight"])
def test_variance_mode_never_widens_the_prediction(kind, engine, tight):
    """``mode="variance"`` (the tracker's) has ``P+ <= P-`` for every track; ``K D`` not.

    The equivalent-variance gain ``G = P_xz S'^-1`` is the Kalman gain of the model with
    ``R' = R + diag(R_ii (1 / D_ii - 1)) >= R`` on the used components, so
    ``P+ = P- - G S' G^T <= P-``.  ``K D`` keeps the gain of all the components and cuts
    the rejected columns; Joseph's form then gives its true covariance, which exceeds the
    prediction's in some direction on these data (an outlier among correlated components).
    The bound is rounding: ``1e-12`` of the largest variance (the products are ``O(P)``).
    """
    motion = ConstantAcceleration(q=0.02)
    meas, x, P, dt, z, R = _case(motion, tight, K=200, seed=3)
    widest = {}
    for mode in ("gain", "variance"):
        f = FusionFilter(kind, motion, RobustUpdate(IGG(1.5, 3.0), mode=mode), engine=engine)
        prior = f.step(x, P, dt, np.full_like(z, np.nan), R, meas).P  # nothing heard
        post = f.step(x, P, dt, z, R, meas)
        assert (f._fast["state"][1] is not None) == (engine == "compiled")  # that engine
        assert (post.status == "fault_excluded").sum() >= 20  # outliers were rejected
        scale = np.abs(prior).max(axis=(1, 2))
        widest[mode] = (np.linalg.eigvalsh(post.P - prior)[:, -1] / scale).max()
    assert widest["variance"] <= 1e-12
    assert widest["gain"] > 1e-3  # the data do make K D widen the covariance


@pytest.mark.parametrize("engine", ["compiled", "numpy"])
def test_variance_mode_leaves_out_a_weight_whose_variance_overflows(engine):
    """A weight so small that ``R_ii / D_ii`` overflows is an infinite variance: the
    component is left out (weight 0), and the update equals that with the component
    missing.  Here the first range has ``R_ii = 1e300`` and reads 1e161 off, so its
    Huber weight is ``1.5 sqrt(1e300) / 1e161 = 1.5e-11`` and ``R_ii / D_ii = 6.7e310``
    overflows.  Before, the weight stayed 1.5e-11 and the covariance of those 16 tracks
    came out NaN (inf in the Joseph form).
    Tolerance: rounding of the same few operations (rtol 1e-12)."""
    motion = ConstantVelocity(q=0.05)
    meas, x, P, dt, z, R = _case(motion, True, K=50, seed=11)
    R = np.diag(np.diag(R))
    R[0, 0] = 1e300
    hit = np.isfinite(z[:, 0]) & (np.arange(50) % 3 == 0)
    z[hit, 0] += 1e161
    robust = RobustUpdate(Huber(1.5), mode="variance")
    f = FusionFilter("ekf", motion, robust, engine=engine)
    r = f.step(x, P, dt, z, R, meas)
    assert (f._fast["state"][1] is not None) == (engine == "compiled")
    assert hit.sum() >= 10 and np.all(r.weights[hit, 0] == 0.0)
    assert np.isfinite(r.x).all() and np.isfinite(r.P).all()
    ref = FusionFilter("ekf", motion, robust, engine="numpy").step(
        x, P, dt, np.where(hit[:, None] & (np.arange(z.shape[1]) == 0), np.nan, z), R, meas)
    np.testing.assert_allclose(r.x, ref.x, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(r.P, ref.P, rtol=1e-12, atol=1e-15)
