"""Robust Kalman updates against outside references.

* variance mode (``R_ii / D_ii``, the equivalent-variance form) is, by definition, a plain
  Kalman update with an inflated ``R``: FilterPy's ``KalmanFilter`` and
  ``ExtendedKalmanFilter`` with that ``R`` are the reference (the weights ``D`` are computed
  here from the digest's IGG-III formula, seed 002 eq. (14), not from robustloc);
* gain mode (``K_hat = K D``, seed 002 eq. (12)): one step worked by hand, numbers below;
* the chi-square gate: the gated fraction of consistent innovations against the gate's
  probability, inside a binomial confidence interval.
"""

from __future__ import annotations

import numpy as np
import pytest
from filterpy.kalman import ExtendedKalmanFilter, KalmanFilter
from scipy.stats import binom, chi2

from robustloc.filters.core import RobustUpdate, update_ekf, update_linear
from robustloc.robust import IGG3, Huber


def igg3_weight(e: np.ndarray, k0: float = 1.5, k1: float = 3.0) -> np.ndarray:
    """IGG-III from the digest: 1 for |e| <= k0; (k0/|e|)((k1-|e|)/(k1-k0))^2 up to k1; 0."""
    a = np.abs(e)
    with np.errstate(divide="ignore", invalid="ignore"):
        mid = (k0 / a) * ((k1 - a) / (k1 - k0)) ** 2
    return np.where(a <= k0, 1.0, np.where(a <= k1, mid, 0.0))


def _case(seed: int, n: int = 4, m: int = 3):
    rng = np.random.default_rng(seed)
    A = rng.normal(size=(n, n))
    P = A @ A.T + 0.5 * np.eye(n)
    H = rng.normal(size=(m, n))
    R = np.diag(rng.uniform(0.2, 1.0, m))
    x = rng.normal(size=n)
    S = H @ P @ H.T + R
    # innovations whose standardized values fall on all three IGG-III branches
    e_target = np.array([0.7, 2.2, 2.7])[:m]
    z = H @ x + e_target * np.sqrt(np.diag(S))
    return x, P, H, R, z


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_variance_mode_equals_filterpy_kf_with_inflated_r(seed):
    x, P, H, R, z = _case(seed)
    S = H @ P @ H.T + R
    e = (z - H @ x) / np.sqrt(np.diag(S))
    D = igg3_weight(e)
    assert np.all((D > 0) & (D < 1.0 + 1e-12)) and D.min() < 0.5  # really down-weighted
    kf = KalmanFilter(dim_x=len(x), dim_z=len(z))
    kf.x, kf.P, kf.H = x.copy(), P.copy(), H.copy()
    kf.update(z, R=np.diag(np.diag(R) / D))  # FilterPy's update uses the Joseph form
    r = update_linear(x[None], P[None], z[None], H, R, robust=RobustUpdate(IGG3(1.5, 3.0),
                                                                          mode="variance"))
    np.testing.assert_allclose(r.weights[0], D, rtol=1e-12)
    # both are the same closed-form update in float64: agreement to rounding (1e-10 relative)
    np.testing.assert_allclose(r.x[0], kf.x, rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(r.P[0], kf.P, rtol=1e-10, atol=1e-12)


def test_variance_mode_rejected_component_equals_filterpy_without_it():
    """A weight of 0 (|e| > k1) is an infinite variance: the component drops out."""
    x, P, H, R, z = _case(3)
    S = H @ P @ H.T + R
    z = z.copy()
    z[1] = H[1] @ x + 5.0 * np.sqrt(S[1, 1])  # |e| = 5 > k1 = 3
    e = (z - H @ x) / np.sqrt(np.diag(S))
    D = igg3_weight(e)
    assert D[1] == 0.0
    keep = D > 0
    kf = KalmanFilter(dim_x=len(x), dim_z=int(keep.sum()))
    kf.x, kf.P, kf.H = x.copy(), P.copy(), H[keep]
    kf.update(z[keep], R=np.diag(np.diag(R)[keep] / D[keep]))
    r = update_linear(x[None], P[None], z[None], H, R, robust=RobustUpdate(IGG3(1.5, 3.0),
                                                                          mode="variance"))
    np.testing.assert_allclose(r.x[0], kf.x, rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(r.P[0], kf.P, rtol=1e-10, atol=1e-12)
    assert r.status[0] == "fault_excluded"


def _range_h(s: np.ndarray) -> np.ndarray:
    """Ranges from a 2-D position to three anchors (nonlinear measurement model)."""
    anchors = np.array([[0.0, 0.0], [10.0, 0.0], [0.0, 10.0]])
    return np.linalg.norm(s[..., None, :2] - anchors, axis=-1)


def _range_jac(s: np.ndarray) -> np.ndarray:
    anchors = np.array([[0.0, 0.0], [10.0, 0.0], [0.0, 10.0]])
    diff = s[..., None, :2] - anchors
    J = np.zeros(s.shape[:-1] + (3, s.shape[-1]))
    J[..., :2] = diff / np.linalg.norm(diff, axis=-1, keepdims=True)
    return J


def test_variance_mode_ekf_equals_filterpy_ekf_with_inflated_r():
    x = np.array([3.0, 4.0, 0.5, -0.2])
    P = np.diag([1.0, 0.8, 0.3, 0.3])
    P[0, 1] = P[1, 0] = 0.2
    R = np.diag([0.09, 0.16, 0.25])
    Hj = _range_jac(x)
    S = Hj @ P @ Hj.T + R
    z = _range_h(x) + np.array([0.3, 2.0, -2.6]) * np.sqrt(np.diag(S))
    D = igg3_weight((z - _range_h(x)) / np.sqrt(np.diag(S)))
    ekf = ExtendedKalmanFilter(dim_x=4, dim_z=3)
    ekf.x, ekf.P = x.copy(), P.copy()
    ekf.update(z, _range_jac, _range_h, R=np.diag(np.diag(R) / D))
    r = update_ekf(x[None], P[None], z[None], _range_h, R, jac=_range_jac,
                   robust=RobustUpdate(IGG3(1.5, 3.0), mode="variance"))
    np.testing.assert_allclose(r.x[0], ekf.x, rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(r.P[0], ekf.P, rtol=1e-10, atol=1e-12)


def test_gain_mode_one_step_by_hand():
    """Seed 002 eq. (12), worked with numbers.

    x = (0, 0), P = [[4, 1], [1, 2]], H = I, R = I, z = (1, 10), Huber c = 2:
    S = P + R = [[5, 1], [1, 3]], det S = 14, S^-1 = [[3, -1], [-1, 5]] / 14;
    e = (1/sqrt 5, 10/sqrt 3) = (0.44721, 5.77350): D = diag(1, 2/5.77350 = 0.346410);
    K = P S^-1 = [[11, 1], [1, 9]] / 14; K_hat = K D = [[0.785714, 0.024744],
    [0.071429, 0.222692]]; x+ = K_hat z = (1.033150, 2.298351);
    Joseph form (I - K_hat) P (I - K_hat)^T + K_hat R K_hat^T
    = [[0.792253, 0.130275], [0.130275, 1.172473]].
    """
    x = np.zeros((1, 2))
    P = np.array([[[4.0, 1.0], [1.0, 2.0]]])
    z = np.array([[1.0, 10.0]])
    r = update_linear(x, P, z, np.eye(2), np.eye(2), robust=RobustUpdate(Huber(2.0)))
    # the hand values are rounded to 6 decimals: tolerance 1e-6
    np.testing.assert_allclose(r.standardized[0], [0.447214, 5.773503], atol=1e-6)
    np.testing.assert_allclose(r.weights[0], [1.0, 0.346410], atol=1e-6)
    np.testing.assert_allclose(r.x[0], [1.033150, 2.298351], atol=1e-6)
    np.testing.assert_allclose(r.P[0], [[0.792253, 0.130275], [0.130275, 1.172473]], atol=1e-6)
    # not the variance mode: that one gives a different (larger) x+ for the same D
    rv = update_linear(x, P, z, np.eye(2), np.eye(2), robust=RobustUpdate(Huber(2.0),
                                                                        mode="variance"))
    assert abs(rv.x[0, 1] - 2.298351) > 0.1


def test_chi2_gate_rate_on_consistent_innovations():
    """Innovations drawn from N(0, S): the gate of probability p must reject a fraction
    1 - p, inside the two-sided 99.9 % binomial interval for 20 000 tracks; with one
    component missing the threshold must use 2 degrees of freedom, not 3."""
    rng = np.random.default_rng(8)
    n_tracks, p_gate = 20_000, 0.99
    x = np.zeros((n_tracks, 3))
    P = np.tile(np.diag([1.0, 2.0, 0.5]), (n_tracks, 1, 1))
    H, R = np.eye(3), np.diag([0.5, 0.5, 0.5])
    S = P[0] + R
    z = rng.multivariate_normal(np.zeros(3), S, n_tracks)
    lo, hi = binom.ppf([0.0005, 0.9995], n_tracks, 1 - p_gate)
    for missing in (False, True):
        zz = z.copy()
        if missing:
            zz[:, 2] = np.nan
        r = update_linear(x, P, zz, H, R, robust=RobustUpdate(gate_probability=p_gate))
        assert lo <= r.gated.sum() <= hi, (missing, r.gated.sum(), lo, hi)
        dof = 2 if missing else 3
        np.testing.assert_array_equal(r.gated, r.nis > chi2.ppf(p_gate, dof))
        # a gated track keeps its prior exactly
        np.testing.assert_array_equal(r.x[r.gated], 0.0)
