"""Global test, w-tests and Q_vv on a hand-worked levelling network (seed 003, eqs. (1)-(2))."""

import numpy as np
import pytest
from statsmodels.regression.linear_model import OLS
from statsmodels.stats.outliers_influence import OLSInfluence

from robustloc.integrity import global_and_w_tests, whiten

# Levelling: A fixed (height 0), unknowns B, C.  Observed height differences
# h1 = B - A, h2 = C - B, h3 = C - A, h4 = B - A (repeated), sigma = 1.
H_LEVEL = np.array([[1.0, 0.0], [-1.0, 1.0], [0.0, 1.0], [1.0, 0.0]])
# By hand: N = [[3, -1], [-1, 2]], N^-1 = [[2, 1], [1, 3]] / 5, hat matrix U = H N^-1 H^T:
U_HAND = np.array(
    [[2, -1, 1, 2], [-1, 3, 2, -1], [1, 2, 3, 1], [2, -1, 1, 2]], dtype=float
) / 5.0
QVV_HAND = np.eye(4) - U_HAND


def test_qvv_and_redundancy_by_hand():
    wh = whiten(H_LEVEL, 1.0)
    np.testing.assert_allclose(wh.Ninv[0], np.array([[2, 1], [1, 3]]) / 5, atol=1e-12)
    np.testing.assert_allclose(wh.qvv()[0], QVV_HAND, atol=1e-12)
    np.testing.assert_allclose(wh.redundancy()[0], [0.6, 0.4, 0.4, 0.6], atol=1e-12)


def test_w_tests_and_global_by_hand():
    # truth B = 1, C = 3; an error of 0.5 on h3.  v = Hx - y = -Q_vv e = [.1, .2, -.2, .1]
    y = np.array([[1.0, 2.0, 3.5, 1.0]])
    wh = whiten(H_LEVEL, 1.0)
    x = wh.solve(y)
    v = x @ H_LEVEL.T - y
    np.testing.assert_allclose(v, [[0.1, 0.2, -0.2, 0.1]], atol=1e-12)
    t = global_and_w_tests(H_LEVEL[None], v, sigma=1.0)
    np.testing.assert_allclose(
        t.w, [[0.1 / np.sqrt(0.6), 0.2 / np.sqrt(0.4), 0.2 / np.sqrt(0.4), 0.1 / np.sqrt(0.6)]]
    )
    assert t.global_stat[0] == pytest.approx(0.1)
    assert t.dof[0] == 2
    assert t.alpha[0] == pytest.approx(0.0029, abs=5e-5)
    assert t.global_crit[0] == pytest.approx(11.68, abs=0.01)
    assert t.global_pass[0]
    assert t.sigma0_post[0] == pytest.approx(np.sqrt(0.05))


def test_sigma_scaling_matches_general_formula():
    """Q_vv = Q - H (H^T P H)^-1 H^T with unequal sigmas, against a dense numpy computation."""
    rng = np.random.default_rng(3)
    H = rng.normal(size=(7, 3))
    sig = rng.uniform(0.5, 2.0, size=7)
    Q = np.diag(sig**2)
    P = np.linalg.inv(Q)
    qvv = Q - H @ np.linalg.inv(H.T @ P @ H) @ H.T
    wh = whiten(H, sig)
    np.testing.assert_allclose(wh.qvv()[0], qvv, atol=1e-12)
    np.testing.assert_allclose(wh.redundancy()[0], np.diag(qvv @ P), atol=1e-12)
    y = rng.normal(size=7)
    x = np.linalg.solve(H.T @ P @ H, H.T @ P @ y)
    v = H @ x - y
    t = global_and_w_tests(H, v[None], sig)
    np.testing.assert_allclose(t.w[0], np.abs(v) / np.sqrt(np.diag(qvv)))
    assert t.global_stat[0] == pytest.approx(v @ P @ v)


def test_hat_diagonal_matches_statsmodels():
    rng = np.random.default_rng(4)
    H = rng.normal(size=(12, 4))
    y = rng.normal(size=12)
    infl = OLSInfluence(OLS(y, H).fit())
    wh = whiten(H, 1.0)
    np.testing.assert_allclose(wh.hat_diagonal()[0], infl.hat_matrix_diag, atol=1e-12)


def test_missing_observations_and_batch():
    y = np.array([[1.0, 2.0, 3.5, 1.0], [1.0, np.nan, 3.0, 1.2]])
    H = np.broadcast_to(H_LEVEL, (2, 4, 2))
    wh = whiten(H, 1.0, y=y)
    assert wh.n_used.tolist() == [4, 3]
    x = wh.solve(y)
    v = np.einsum("kip,kp->ki", H, x) - y
    t = global_and_w_tests(H, v, 1.0)
    assert np.isnan(t.w[1, 1])
    assert t.dof.tolist() == [2, 1]
    # epoch 2 without h2: r = 1 - diag(H (H^T H)^-1 H^T) for the remaining rows, numpy
    Hs = H_LEVEL[[0, 2, 3]]
    r = 1 - np.diag(Hs @ np.linalg.inv(Hs.T @ Hs) @ Hs.T)
    np.testing.assert_allclose(t.redundancy[1, [0, 2, 3]], r, atol=1e-12)


def test_ill_conditioned_and_bad_sigma():
    H = np.zeros((1, 3, 2))
    H[0, :, 0] = 1.0  # second unknown not observed
    wh = whiten(H, 1.0)
    assert not wh.ok[0]
    t = global_and_w_tests(H, np.zeros((1, 3)), 1.0)
    assert not t.testable[0] and not t.global_pass[0]
    with pytest.raises(ValueError):
        whiten(H_LEVEL, -1.0)
    with pytest.raises(ValueError):
        whiten(H_LEVEL, np.ones(3))


@pytest.mark.parametrize("bad", [float("nan"), 0.0, 1.0, 1.5])
def test_bad_alpha_beta0_raise_naming_them(bad):
    """alpha=NaN went through (every epoch failed its global test silently, also with no
    epoch testable), beta0 with a fixed alpha was not looked at; now ValueErrors."""
    from robustloc.integrity import detection_power_global, global_critical, snoop_linear

    y = np.array([[1.0, 2.0, 3.5, 1.0]])
    for kw in (dict(alpha=bad), dict(alpha=0.01, beta0=bad)):
        name = "beta0" if "beta0" in kw else "alpha"
        with pytest.raises(ValueError, match=f"^{name} must be strictly between 0 and 1"):
            global_and_w_tests(H_LEVEL, y, 1.0, **kw)
        with pytest.raises(ValueError, match=f"^{name} must be strictly between 0 and 1"):
            global_and_w_tests(H_LEVEL[:2], y[:, :2], 1.0, **kw)  # dof 0: nothing testable
        with pytest.raises(ValueError, match=f"^{name} must be strictly between 0 and 1"):
            global_critical(3, **kw)
        with pytest.raises(ValueError, match=f"^{name} must be strictly between 0 and 1"):
            snoop_linear(H_LEVEL, y, 1.0, **kw)
    with pytest.raises(ValueError, match="^alpha must be strictly between 0 and 1"):
        global_critical([3, 4], [0.01, bad])
    with pytest.raises(ValueError, match="^alpha must be strictly between 0 and 1"):
        detection_power_global(20.0, 3, bad)


def test_wrong_shapes_name_the_argument():
    """Residuals or a mask that do not fit the observations (N, n): a ValueError naming
    the argument and the expected shape (numpy's broadcast error named neither)."""
    from robustloc.integrity import integrity_tests, snoop_linear

    y = np.array([[1.0, 2.0, 3.5, 1.0]])
    expected = r"expected \(1, 4\) \(epochs, observations\)"
    with pytest.raises(ValueError, match=rf"^v has shape \(1, 3\); {expected}"):
        global_and_w_tests(H_LEVEL, y[:, :3], 1.0)
    with pytest.raises(ValueError, match=rf"^v has shape \(1, 3\); {expected}"):
        integrity_tests(whiten(H_LEVEL, 1.0), y[:, :3])
    with pytest.raises(ValueError, match=rf"^mask has shape \(3,\); {expected}"):
        global_and_w_tests(H_LEVEL, y, 1.0, mask=np.ones(3, bool))
    with pytest.raises(ValueError, match=rf"^mask has shape \(3,\); {expected}"):
        whiten(H_LEVEL, 1.0, mask=np.ones(3, bool))
    with pytest.raises(ValueError, match=rf"^y has shape \(1, 3\); {expected}"):
        whiten(H_LEVEL, 1.0, y=y[:, :3])
    with pytest.raises(ValueError, match=rf"^mask has shape \(3,\); {expected}"):
        snoop_linear(H_LEVEL, y, 1.0, mask=np.ones(3, bool))
    # shapes that broadcast are still taken: one mask row for every epoch
    t = global_and_w_tests(H_LEVEL, y, 1.0, mask=np.ones(4, bool))
    np.testing.assert_array_equal(t.w, global_and_w_tests(H_LEVEL, y, 1.0).w)
