"""Reliability (seed 003): redundancy numbers, MDB, external reliability, w-test correlation."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as hs

from robustloc.integrity import lambda0, reliability, whiten

H_LEVEL = np.array([[1.0, 0.0], [-1.0, 1.0], [0.0, 1.0], [1.0, 0.0]])


def test_levelling_by_hand():
    rel = reliability(H_LEVEL, 1.0)
    np.testing.assert_allclose(rel.redundancy[0], [0.6, 0.4, 0.4, 0.6], atol=1e-12)
    assert rel.redundancy_total[0] == pytest.approx(2.0)
    lam = lambda0()
    np.testing.assert_allclose(rel.mdb[0], np.sqrt(lam / np.array([0.6, 0.4, 0.4, 0.6])))
    # Q_vv by hand (see test_integrity_tests): rho_14 = (-2/5)/(3/5), rho_23 = -1
    assert rel.rho[0, 0, 3] == pytest.approx(-2 / 3)
    assert rel.rho[0, 1, 2] == pytest.approx(-1.0)
    assert rel.flagged_pairs(0) == [(1, 2, pytest.approx(-1.0))]
    assert rel.max_abs_rho[0] == pytest.approx(1.0)


def test_constructed_inseparable_pairs_are_flagged():
    # unknown 3 is seen only by observations 3 and 4: their errors cannot be told apart
    H = np.array(
        [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [1.0, 1.0, 0.0], [1.0, 0.0, 1.0], [0.0, 2.0, 1.0]]
    )
    rel = reliability(H, 1.0)
    assert abs(rel.rho[0, 3, 4]) == pytest.approx(1.0)
    assert rel.flagged[0, 3, 4] and rel.flagged[0, 4, 3]
    assert (3, 4) in [(i, j) for i, j, _ in rel.flagged_pairs(0)]
    # with a single redundant observation every pair of w-tests is perfectly correlated
    rel1 = reliability(np.random.default_rng(1).normal(size=(4, 3)), 1.0)
    off = ~np.eye(4, dtype=bool)
    np.testing.assert_allclose(np.abs(rel1.rho[0][off]), 1.0, atol=1e-9)
    assert rel1.flagged[0][off].all()
    # two identical design rows: rho = -u / (1 - u), u their hat-matrix element
    H2 = np.array([[1.0, 0.0], [0.0, 1.0], [1.0, 1.0], [1.0, 2.0], [1.0, 2.0]])
    u = H2[3] @ np.linalg.inv(H2.T @ H2) @ H2[3]
    assert reliability(H2, 1.0).rho[0, 3, 4] == pytest.approx(-u / (1 - u))
    # a well-spread design has no flagged pair
    rel2 = reliability(np.random.default_rng(0).normal(size=(20, 2)), 1.0)
    assert not rel2.flagged.any()


@settings(max_examples=40, deadline=None)
@given(n=hs.integers(3, 12), p=hs.integers(1, 4), seed=hs.integers(0, 10_000))
def test_redundancy_sums_to_n_minus_p(n, p, seed):
    if n <= p:
        return
    rng = np.random.default_rng(seed)
    H = rng.normal(size=(4, n, p))
    sig = rng.uniform(0.2, 3.0, size=(4, n))
    mask = rng.random((4, n)) > 0.2
    rel = reliability(H, sig, mask)
    nu = mask.sum(axis=1)
    good = rel.ok & (nu > p)
    np.testing.assert_allclose(rel.redundancy_total[good], (nu - p)[good], atol=1e-8)
    mk = mask & rel.ok[:, None]
    assert np.all((rel.redundancy[mk] >= 0) & (rel.redundancy[mk] <= 1))
    assert np.all(np.isnan(rel.redundancy[~mk]))


def test_external_reliability_equals_effect_of_injected_mdb():
    rng = np.random.default_rng(7)
    H = rng.normal(size=(9, 3))
    sig = rng.uniform(0.5, 2, size=9)
    rel = reliability(H, sig, horizontal=(0, 1))
    wh = whiten(H, sig)
    for i in range(9):
        e = np.zeros((1, 9))
        e[0, i] = rel.mdb[0, i]
        dx = wh.solve(e)[0]
        np.testing.assert_allclose(rel.external[0, i], dx, atol=1e-10)
        assert rel.external_horizontal[0, i] == pytest.approx(np.hypot(dx[0], dx[1]))
        # the expected w-test of the biased observation equals sqrt(lambda0)
        v = H @ dx - e[0]
        w = abs(v[i]) / (sig[i] * np.sqrt(rel.redundancy[0, i]))
        assert w == pytest.approx(np.sqrt(lambda0()))
    np.testing.assert_allclose(
        rel.bias_to_noise[0], np.sqrt(lambda0() * (1 - rel.redundancy[0]) / rel.redundancy[0])
    )
    assert rel.max_mdb[0] == pytest.approx(rel.mdb[0].max())


def test_zero_redundancy_gives_infinite_mdb():
    H = np.array([[1.0, 0.0], [0.0, 1.0], [0.0, 1.0]])  # x observed once: r_0 = 0
    rel = reliability(H, 1.0)
    assert rel.redundancy[0, 0] == pytest.approx(0.0, abs=1e-12)
    assert np.isinf(rel.mdb[0, 0])
    assert np.isfinite(rel.mdb[0, 1])


def test_bad_arguments():
    with pytest.raises(ValueError):
        reliability(H_LEVEL, 1.0, rho_threshold=0.0)
    with pytest.raises(ValueError):
        reliability(H_LEVEL, 1.0, horizontal=(0, 5))


def test_chunked_equals_unchunked():
    rng = np.random.default_rng(5)
    H = rng.normal(size=(50, 6, 2))
    sig = rng.uniform(0.5, 2.0, size=(50, 6))
    mask = rng.random((50, 6)) > 0.1
    a = reliability(H, sig, mask, chunk=7)
    b = reliability(H, sig, mask)
    for k in ("redundancy", "mdb", "external", "rho", "max_abs_rho", "flagged", "n_used"):
        np.testing.assert_array_equal(getattr(a, k), getattr(b, k))
