"""Robust RSSI Kalman filter (seed 002, eqs. (12)-(17))."""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from robustloc.filters.core import numerical_jacobian
from robustloc.filters.rssi import (
    LinkParams,
    RobustRssiFilter,
    StepLayout,
    process_noise,
    scalar_update,
    transition,
    transition_jacobian,
)
from robustloc.models.pathloss import AttenuationFactor
from robustloc.robust.weights import AsymmetricIGG
from robustloc.sim import wifi_room


def _full_transition(x, dt, n, a):
    """Eq. (15) with the acceleration: d' = d + v t + a t^2/2, P' = P + 10 n lg(d/d')."""
    p, d, v = x
    d1 = d + v * dt + 0.5 * a * dt * dt
    return np.array([p + 10 * n * np.log10(d / d1), d1, v + a * dt])


@settings(max_examples=40, deadline=None)
@given(
    p=st.floats(-90, -20), d=st.floats(0.5, 30), v=st.floats(-1.5, 1.5),
    dt=st.floats(0.01, 0.3), n=st.floats(1.5, 4.0),
)
def test_jacobian_matches_finite_differences(p, d, v, dt, n):
    # the transition clips the predicted distance at 0.1 m (the log is undefined at 0):
    # there it is flat in d and v, and not differentiable at the clip itself; compare the
    # analytic Jacobian where the model is smooth (the finite-difference step is 1e-6 rel.)
    assume(d + v * dt > 0.11)
    x = np.array([[p, d, v]])
    J = transition_jacobian(x, dt, n)
    Jn = numerical_jacobian(lambda s: transition(s, dt, n), x)
    np.testing.assert_allclose(J, Jn, rtol=1e-5, atol=1e-6)


def test_jacobian_hand_values():
    # d = 4, v = 1, t = 1, n = 2: d' = 5, c = 20 / ln 10
    c = 20 / np.log(10)
    J = transition_jacobian(np.array([-50.0, 4.0, 1.0]), 1.0, 2.0)
    np.testing.assert_allclose(J, [[1, c * (1 / 4 - 1 / 5), -c / 5], [0, 1, 1], [0, 0, 1]])
    # paper's transition literally: 20 lg(d / (d + v t))
    x1 = transition(np.array([-50.0, 4.0, 1.0]), 1.0, 2.0)
    np.testing.assert_allclose(x1, [-50 + 20 * np.log10(4 / 5), 5.0, 1.0])


def test_process_noise_is_acceleration_sensitivity():
    x = np.array([-60.0, 6.0, 0.7])
    dt, n, sa = 0.5, 2.6, 0.8
    h = 1e-6
    G = (_full_transition(x, dt, n, h) - _full_transition(x, dt, n, -h)) / (2 * h)
    Q = process_noise(x, dt, sa, 0.0, n)
    np.testing.assert_allclose(Q, sa**2 * np.outer(G, G), rtol=1e-6, atol=1e-12)
    Q2 = process_noise(x, dt, sa, 0.3, n)
    assert Q2[0, 0] - Q[0, 0] == pytest.approx(0.3 * dt)


def test_asymmetric_weight_eq14_breakpoints():
    w = AsymmetricIGG(k0=2.0, k1=3.0, c=3.0)
    e = np.array([-3.5, -3.0, -2.5, -2.0, 0.0, 1.99, 2.0, 2.5, 3.0, 4.0])
    # -C: (C + e) = 0; -K0 and K0: weight 1 (continuous); -2.5: (2/2.5)(0.5/1) = 0.4;
    # 2.5: (2/2.5)(0.5/1)^2 = 0.2; K1 and beyond: 0
    np.testing.assert_allclose(w.weights(e), [0, 0, 0.4, 1, 1, 1, 1, 0.2, 0, 0], atol=1e-12)
    # asymmetric for C > K1: the negative side keeps weight further out
    w2 = AsymmetricIGG(k0=1.5, k1=2.5, c=4.0)
    assert w2.weights(-3.0) == pytest.approx((1.5 / 3.0) * 1.0 / 2.5)
    assert w2.weights(3.0) == 0.0


@pytest.mark.parametrize("robust", [True, False])
def test_follows_noise_free_rssi_exactly(robust):
    T, dt = 400, 0.5
    t = np.arange(T) * dt
    d = np.stack([np.full(T, 3.0), 2.0 + 0.4 * t, 60.0 - 0.3 * t], axis=1)  # (T, 3)
    p0, g = np.array([-30.0, -35.0, -28.0]), np.array([2.0, 2.5, 3.0])
    z = AttenuationFactor(p0, g, 0.0, 1.0).rssi(d)
    f = RobustRssiFilter(robust=robust, sigma_rssi_db=1.0)
    res = f.run(z, np.full_like(z, dt), LinkParams.broadcast(3, p0, g))
    np.testing.assert_allclose(res.rssi_dbm[-100:], z[-100:], atol=1e-6)
    # the distance state follows the true distance to within 1 % (the model ties P and d;
    # the power random walk q_P lets them drift apart slightly)
    np.testing.assert_allclose(res.distance_m[-100:], d[-100:], rtol=1e-2)
    np.testing.assert_allclose(res.speed_mps[-1], [0.0, 0.4, -0.3], atol=5e-3)
    assert np.all(res.weight == 1.0)


def test_outlier_barely_moves_robust_but_drags_plain():
    rng = np.random.default_rng(3)
    T = 200
    z = -55.0 + rng.normal(0, 1.0, T)
    z_out = z.copy()
    z_out[120] -= 15.0
    dt = np.full((T, 1), 0.5)
    lp = LinkParams.broadcast(1, -35.0, 2.0)
    for robust, lo, hi in ((True, 0.0, 0.3), (False, 2.0, 15.0)):
        f = RobustRssiFilter(robust=robust, sigma_rssi_db=1.0)
        a = f.run(z[:, None], dt, lp).rssi_dbm[:, 0]
        b = f.run(z_out[:, None], dt, lp).rssi_dbm[:, 0]
        shift = abs(b[120] - a[120])
        assert lo <= shift <= hi, (robust, shift)
    r = RobustRssiFilter(sigma_rssi_db=1.0).run(z_out[:, None], dt, lp)
    assert r.weight[120, 0] == 0.0
    # the weight is eq. (14) of the standardized innovation
    np.testing.assert_allclose(
        r.weight[1:, 0], AsymmetricIGG().weights(r.standardized[1:, 0]), atol=1e-12
    )


def test_core_and_scalar_engines_agree():
    rng = np.random.default_rng(1)
    T, L = 250, 6
    Z = -55 + rng.normal(0, 2, (T, L))
    Z[rng.random((T, L)) < 0.05] -= 12
    Z[50:70, 2] -= 10
    Z[rng.random((T, L)) < 0.02] = np.nan
    DT = np.full((T, L), 0.5)
    lp = LinkParams.broadcast(L, -35, 2.3)
    for kw in ({}, {"robust": False}, {"adaptive": False}):
        a = RobustRssiFilter(max_rejected=5, **kw).run(Z, DT, lp)
        b = RobustRssiFilter(max_rejected=5, engine="core", **kw).run(Z, DT, lp)
        np.testing.assert_allclose(a.rssi_dbm, b.rssi_dbm, atol=1e-8)
        np.testing.assert_allclose(a.distance_m, b.distance_m, rtol=1e-9)
        np.testing.assert_allclose(a.rssi_var_db2, b.rssi_var_db2, rtol=1e-8)


def test_adaptive_scale_prevents_over_rejection():
    rng = np.random.default_rng(5)
    z = -60 + rng.normal(0, 2.0, (500, 1))  # true noise 2 dB, filter told 0.3 dB
    dt = np.full_like(z, 0.5)
    lp = LinkParams.broadcast(1, -35, 2.0)
    fixed = RobustRssiFilter(sigma_rssi_db=0.3, adaptive=False, max_rejected=0).run(z, dt, lp)
    adapt = RobustRssiFilter(sigma_rssi_db=0.3, max_rejected=0).run(z, dt, lp)
    assert np.mean(fixed.weight[100:] == 0) > 0.3
    assert np.mean(adapt.weight[100:] == 0) < 0.1
    # the running scale converges to the noise level (a coarse band, kept as it was:
    # the innovations' spread is the noise's and the prediction's, 2.36 dB here)
    assert np.median(adapt.scale_db[200:]) == pytest.approx(2.0, rel=0.25)
    # ... and it is the innovations' standard deviation: s_emp is an exponential average
    # (lambda = 1/20) of sqrt(pi/2) |e|, whose mean is sd(e) for Gaussian e (E|e| =
    # sd sqrt(2/pi)).  So median(scale) / rms(innovation) over samples 200-499 is near 1.
    # Its standard error, from an independent simulation of that average alone (4 000
    # runs of 500 N(0, 1) innovations, winsorized at 3 s as the filter does, also with
    # the lag-1 correlation -0.076 this filter's innovations have): mean 0.995, sd 0.023;
    # 3 standard errors, 0.07.  (Without the factor sqrt(pi/2) the ratio is sqrt(2/pi)
    # = 0.80 or below: 0.71 here.)
    e = adapt.innovation_db[200:, 0]
    ratio = np.median(adapt.scale_db[200:]) / np.sqrt(np.mean(e**2))
    assert ratio == pytest.approx(1.0, abs=0.07)


def test_relock_after_environment_change():
    rng = np.random.default_rng(7)
    z = -60 + rng.normal(0, 1.0, (300, 1))
    z[150:] -= 10.0  # a door closes for good
    dt = np.full_like(z, 0.5)
    lp = LinkParams.broadcast(1, -35, 2.0)
    r = RobustRssiFilter(sigma_rssi_db=1.0, max_rejected=8).run(z, dt, lp)
    assert r.relocked[:, 0].sum() >= 1
    assert abs(np.mean(r.rssi_dbm[200:, 0]) - (-70)) < 1.0
    locked = np.argmax(np.abs(r.rssi_dbm[150:, 0] + 70) < 2)
    assert locked == 7  # the 8th consecutive rejection is taken with weight 1
    # without re-locking only the growing innovation variance lets it through, later
    slow = RobustRssiFilter(sigma_rssi_db=1.0, max_rejected=0).run(z, dt, lp)
    assert not slow.relocked.any()
    assert np.argmax(np.abs(slow.rssi_dbm[150:, 0] + 70) < 2) > locked


def test_ragged_samples_equal_per_link_runs():
    rng = np.random.default_rng(11)
    links, times, vals = [], [], []
    for link, n in enumerate([40, 7, 25]):
        t = np.cumsum(rng.uniform(0.1, 1.0, n))
        links.append(np.full(n, link))
        times.append(t)
        vals.append(-50 - 3 * link + rng.normal(0, 2, n))
    link, t, z = map(np.concatenate, (links, times, vals))
    perm = rng.permutation(link.size)
    f = RobustRssiFilter()
    lp = LinkParams.broadcast(3, [-30, -35, -40], [2.0, 2.5, 3.0])
    out = f.filter_samples(link[perm], t[perm], z[perm], lp)
    for k in range(3):
        sel = link == k
        single = f.filter_samples(
            np.zeros(sel.sum(), dtype=int), t[sel], z[sel],
            LinkParams.broadcast(1, lp.p0_dbm[k], lp.gamma[k]),
        )
        got = np.empty(link.size)
        got[perm] = out.rssi_dbm
        np.testing.assert_allclose(got[sel], single.rssi_dbm, atol=1e-12)


def test_step_layout_roundtrip():
    lay = StepLayout.build([1, 0, 1, 1, 0], [3.0, 1.0, 1.0, 2.0, 0.5])
    assert (lay.n_steps, lay.n_links) == (3, 2)
    np.testing.assert_array_equal(lay.step, [2, 1, 0, 1, 0])
    grid = lay.scatter(np.arange(5.0))
    np.testing.assert_array_equal(lay.gather(grid), np.arange(5.0))
    dt = lay.intervals([3.0, 1.0, 1.0, 2.0, 0.5])
    np.testing.assert_allclose(dt[:, 1], [0, 1, 1])
    np.testing.assert_allclose(dt[:2, 0], [0, 0.5])


def test_missing_values_predict_only():
    z = np.array([[-50.0], [np.nan], [-50.0]])
    r = RobustRssiFilter().run(z, np.full_like(z, 1.0), LinkParams.broadcast(1))
    assert np.isnan(r.weight[1, 0]) and np.isfinite(r.rssi_dbm[1, 0])


def test_bad_settings_and_shapes():
    with pytest.raises(ValueError):
        RobustRssiFilter(sigma_rssi_db=0)
    for kw in ({"sigma_rssi_db": 1e300}, {"sigma_rssi_db": 1e-300},
               {"q_rssi_db2_per_s": 1e300}, {"sigma_accel_mps2": 1e300}):
        with pytest.raises(ValueError, match=next(iter(kw))):
            RobustRssiFilter(**kw)
    with pytest.raises(ValueError):
        RobustRssiFilter(engine="gpu")
    with pytest.raises(ValueError):
        RobustRssiFilter().run(np.zeros((3, 2)), np.zeros((3, 1)), LinkParams.broadcast(2))
    with pytest.raises(ValueError):
        RobustRssiFilter().filter_samples([0, 0], [0.0, np.nan], [-50.0, -51.0])


def test_static_plain_filter_matches_filterpy():
    """v = 0 and no acceleration: the power component is a 1-D random-walk Kalman filter."""
    from filterpy.kalman import KalmanFilter

    rng = np.random.default_rng(8)
    z = -62 + rng.normal(0, 2, 80)
    t = np.cumsum(rng.uniform(0.3, 1.5, 80))
    R, q = 4.0, 0.2
    ours = RobustRssiFilter(robust=False, sigma_rssi_db=2.0, sigma_accel_mps2=0.0,
                            init_speed_std_mps=0.0, q_rssi_db2_per_s=q)
    res = ours.filter_samples(np.zeros(80, dtype=int), t, z,
                              LinkParams.broadcast(1, -35.0, 2.0))
    kf = KalmanFilter(dim_x=1, dim_z=1)
    kf.x = np.array([[z[0]]])
    kf.P = np.array([[R]])
    kf.H = np.array([[1.0]])
    kf.R = np.array([[R]])
    ref = [z[0]]
    for k in range(1, 80):
        kf.Q = np.array([[q * (t[k] - t[k - 1])]])
        kf.predict()
        kf.update(z[k])
        ref.append(kf.x[0, 0])
    np.testing.assert_allclose(res.rssi_dbm, ref, atol=1e-9)
    np.testing.assert_allclose(res.speed_mps, 0.0)


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 10_000), D=st.floats(0.0, 1.0), R=st.floats(0.1, 25.0))
def test_scalar_update_matches_core_and_stays_psd(seed, D, R):
    from robustloc.filters import core

    rng = np.random.default_rng(seed)
    A = rng.normal(size=(1, 3, 3))
    P = A @ np.swapaxes(A, 1, 2) + 0.01 * np.eye(3)
    x = rng.normal(size=(1, 3))
    z = x[:, 0] + rng.normal(0, 3, 1)
    S = P[:, 0, 0] + R
    xs, Ps = scalar_update(x, P, z - x[:, 0], S, np.array([D]))
    fixed = type("Fixed", (AsymmetricIGG,), {"weights": lambda self, u: np.full_like(u, D)})
    ref = core.update_linear(x, P, z[:, None], np.array([[1.0, 0, 0]]), np.array([[R]]),
                             robust=core.RobustUpdate(weight=fixed()))
    np.testing.assert_allclose(xs, ref.x, atol=1e-9)
    np.testing.assert_allclose(Ps, ref.P, atol=1e-9)
    assert np.linalg.eigvalsh(Ps[0]).min() > -1e-9
    # down-weighting never shrinks the variance more than the full update
    full = P[0, 0, 0] - P[0, 0, 0] ** 2 / S[0]
    assert full - 1e-12 <= Ps[0, 0, 0] <= P[0, 0, 0] + 1e-12


def test_hot_path_model_terms_equal_public_functions():
    from robustloc.filters.rssi import _ModelTerms

    rng = np.random.default_rng(12)
    x = np.stack([rng.uniform(-90, -30, 50), rng.uniform(0.05, 30, 50),
                  rng.uniform(-2, 2, 50)], axis=1)
    dt = rng.uniform(0, 1, 50)
    n = rng.uniform(1.5, 3.5, 50)
    terms = _ModelTerms(50, n, 0.7, 0.2, 0.1)
    for _ in range(2):  # the buffers are reused between steps
        xp, phi, Q = terms(x, dt)
        np.testing.assert_allclose(xp, transition(x, dt, n, 0.1), atol=1e-12)
        np.testing.assert_allclose(phi, transition_jacobian(x, dt, n, 0.1), atol=1e-12)
        np.testing.assert_allclose(Q, process_noise(x, dt, 0.7, 0.2, n, 0.1), atol=1e-12)


def test_path_loss_tie_keeps_distance_state_on_the_model():
    rng = np.random.default_rng(21)
    T, dt = 600, 0.5
    t = np.arange(T) * dt
    d = 6.0 + 4.0 * np.sin(2 * np.pi * t / 60.0)  # walking to and from the anchor
    z = AttenuationFactor(-35.0, 2.5, 0.0, 1.0).rssi(d) + rng.normal(0, 2.0, T)
    lp = LinkParams.broadcast(1, -35.0, 2.5)
    free = RobustRssiFilter(model_sigma_db=None).run(z[:, None], np.full((T, 1), dt), lp)
    tied = RobustRssiFilter(model_sigma_db=3.0).run(z[:, None], np.full((T, 1), dt), lp)
    err_free = np.median(np.abs(free.distance_m[100:, 0] - d[100:]))
    err_tied = np.median(np.abs(tied.distance_m[100:, 0] - d[100:]))
    assert err_tied < 0.5 * err_free
    # and better than no filter at all: inverting each raw sample through the same model
    # (median |error| 0.56 m here, ~0.674 d ln10 sigma / (10 n) per sample); measured
    # 0.37 m tied (the old "< 1.5 m" was 2.7x the unfiltered error)
    d_raw = AttenuationFactor(-35.0, 2.5, 0.0, 1.0).distance(z)
    assert err_tied < np.median(np.abs(d_raw[100:] - d[100:]))
    with pytest.raises(ValueError):
        RobustRssiFilter(model_sigma_db=0.0)


def test_a_fade_on_the_first_sample_no_longer_rejects_the_good_ones():
    # first sample 12 dB weak, then the true -50 dBm: with one sample behind it the
    # filter rejected five good ones (re-lock only after max_rejected = 8; it drifted in
    # at sample 8).  Rejections that outnumber the samples a link has taken re-lock it:
    # at the second rejection here (sample 2), back on -50 dBm from there on
    z = np.full(20, -50.0)
    z[0] = -62.0
    r = RobustRssiFilter().filter_samples(np.zeros(20, dtype=np.int64), np.arange(20) * 0.5, z)
    assert r.weight[1] == 0.0 and r.relocked[2] and r.relocked.sum() == 1
    np.testing.assert_allclose(r.rssi_dbm[2:], -50.0, atol=0.6)  # measured: within 0.5 dB
    # a settled link is not young: 7 weak samples after 30 good ones re-lock nothing
    # (its first three are rejected; its prediction then widens and lets the level in,
    # as before this rule)
    z = np.r_[np.full(30, -50.0), np.full(7, -62.0), np.full(5, -50.0)]
    r = RobustRssiFilter().filter_samples(np.zeros(z.size, dtype=np.int64),
                                          np.arange(z.size) * 0.5, z)
    assert not r.relocked.any() and (r.weight[30:33] == 0.0).all()


def test_a_link_restarts_after_a_gap_that_leaves_nothing_of_its_prior():
    # the simulated walk's AP1 link with a 600 s gap after its 30th sample: the prediction
    # across it is far wider than 25 R, so the link starts again at sample 30 -- the
    # filtered power is the sample, the distance the path-loss model's for it, speed 0
    # (the speed carried across the gap put the distance state at its floor, 0.1 m, for
    # ~120 samples); before the gap the two runs are the same
    from robustloc.io import read_anchors
    from robustloc.models.pathloss import AttenuationFactor

    out = Path(tempfile.mkdtemp(prefix="robustloc-test-"))
    files = wifi_room.simulate(out, 1, argparse.Namespace(samples_per_point=5,
                                                          walk_epochs=120))
    m = pd.read_csv(files["measurements"])
    w = m[(m["tag"] == "walk") & (m["anchor"] == "AP1")]
    a = read_anchors(files["anchors"]).set_index("anchor").loc["AP1"]
    params = LinkParams.broadcast(1, p0_dbm=a["p0"], gamma=a["gamma"], faf_db=a["faf"],
                                  d0_m=a["d0"])
    t = w["time"].to_numpy(float)
    z = w["rssi"].to_numpy(float)
    filt = RobustRssiFilter()
    plain = filt.filter_samples(np.zeros(z.size, dtype=np.int64), t, z, params)
    assert not plain.restarted[28:32].any()
    tg = t + np.where(np.arange(z.size) >= 30, 600.0, 0.0)
    r = filt.filter_samples(np.zeros(z.size, dtype=np.int64), tg, z, params)
    assert r.restarted[30] and (r.restarted[:30] == plain.restarted[:30]).all()
    np.testing.assert_array_equal(r.rssi_dbm[:30], plain.rssi_dbm[:30])
    assert r.rssi_dbm[30] == z[30] and r.speed_mps[30] == 0.0 and r.weight[30] == 1.0
    d30 = AttenuationFactor(a["p0"], a["gamma"], a["faf"], a["d0"]).distance(z[30])
    np.testing.assert_allclose(r.distance_m[30], d30, rtol=1e-12)
    assert (r.distance_m[31:60] > 0.5).all()
    with pytest.raises(ValueError, match="restart_var_ratio"):
        RobustRssiFilter(restart_var_ratio=0.0)


@pytest.mark.parametrize("sigma", [1e-6, 1e6])
@pytest.mark.parametrize("q", [0.0, 1e6])
@pytest.mark.parametrize("accel", [0.0, 1e3])
def test_the_settings_ranges_corners_give_finite_values(sigma, q, accel):
    """Every corner of the accepted ranges of ``sigma_rssi_db``, ``q_rssi_db2_per_s`` and
    ``sigma_accel_mps2`` filters a log with gaps (0.1 s to 100 s), 20 dB jumps and samples
    next to the anchor into finite values: the ranges are where the filter works, not a
    guess (outside them it gave NaN or raised OverflowError)."""
    rng = np.random.default_rng(3)
    n = 120
    link = np.repeat([0, 1], n // 2)
    t = np.r_[np.cumsum(rng.choice([0.1, 1.0, 100.0], n // 2, p=[0.45, 0.5, 0.05])),
              np.cumsum(rng.choice([0.1, 1.0, 100.0], n // 2, p=[0.45, 0.5, 0.05]))]
    z = -60.0 + rng.normal(0.0, 3.0, n) + np.where(rng.random(n) < 0.1, -20.0, 0.0)
    z[::17] = -35.0  # within decimetres of the anchor
    res = RobustRssiFilter(sigma_rssi_db=sigma, q_rssi_db2_per_s=q,
                           sigma_accel_mps2=accel).filter_samples(link, t, z)
    assert np.all(np.isfinite(res.rssi_dbm))
    assert np.all(np.isfinite(res.distance_m))


def test_values_and_parameters_it_cannot_filter_are_refused_by_name():
    """The API review: one RSSI of -1e308 turned 18 of its link's 20 filtered values into
    NaN, one time of -1e308 19; ``p0 = NaN`` all 60, ``faf = inf`` most; a negative or
    NaN ``dt_s`` and ``exponent = inf`` passed.  Each is now a ValueError naming it (the
    command line sets implausible rows aside before, with status invalid_measurement)."""
    rng = np.random.default_rng(1)
    link = np.repeat([0, 1, 2], 20)
    t = np.tile(np.arange(20.0), 3)
    z = -60.0 + rng.normal(0, 2, 60)
    f = RobustRssiFilter()
    with pytest.raises(ValueError, match="rssi_dbm: 1 value"):
        f.filter_samples(link, t, np.r_[-1e308, z[1:]])
    with pytest.raises(ValueError, match="time_s: 1 value"):
        f.filter_samples(link, np.r_[-1e308, t[1:]], z)
    for kw, name in (({"p0_dbm": np.nan}, "p0_dbm"), ({"faf_db": np.inf}, "faf_db"),
                     ({"gamma": -1.0}, "gamma")):
        with pytest.raises(ValueError, match=name):
            f.filter_samples(link, t, z, LinkParams.broadcast(3, **kw))
    zz, dt = z.reshape(3, 20).T, np.ones((20, 3))
    for bad in (-1.0, np.nan):
        d = dt.copy()
        d[5, 1] = bad
        with pytest.raises(ValueError, match="dt_s"):
            f.run(zz, d, LinkParams.broadcast(3))
    with pytest.raises(ValueError, match="exponent"):
        RobustRssiFilter(exponent=np.inf)
    # NaN samples are "no sample", as before
    zn = z.copy()
    zn[::7] = np.nan
    assert np.isfinite(f.filter_samples(link, t, zn).rssi_dbm[~np.isnan(zn)]).all()


def test_link_ids_that_are_not_indices_are_refused():
    """A link id of 1e12 asked for (T, 1e12) arrays: MemoryError (the API review)."""
    f = RobustRssiFilter()
    with pytest.raises(ValueError, match="0 .. L-1"):
        f.filter_samples(np.array([0, 10**12]), np.array([0.0, 1.0]), np.array([-60.0, -61.0]))
    with pytest.raises(ValueError, match="for 2 links"):
        f.filter_samples(np.array([0, 2]), np.array([0.0, 1.0]), np.array([-60.0, -61.0]),
                         LinkParams.broadcast(2))
