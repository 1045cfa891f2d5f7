"""DOP and CRLB (src/robustloc/eval/crlb.py) against closed forms and Monte Carlo."""

import numpy as np
import pytest

from robustloc.eval.crlb import crlb_range, crlb_rssi, dop, ranging_dop

SQUARE = np.array([[0.0, 0.0], [10.0, 0.0], [10.0, 10.0], [0.0, 10.0]])


def test_centre_of_square_closed_form():
    # unit vectors at 45 deg: G^T G = diag(2, 2) -> HDOP = 1, CRLB = sigma^2 / 2 per axis
    d = ranging_dop(SQUARE, [[5.0, 5.0]])
    assert d.hdop[0] == pytest.approx(1.0)
    assert d.pdop[0] == pytest.approx(1.0)
    assert np.isnan(d.vdop[0]) and np.isnan(d.tdop[0])
    c = crlb_range(SQUARE, [[5.0, 5.0]], 0.3)
    np.testing.assert_allclose(c.cov[0], np.eye(2) * 0.09 / 2, atol=1e-12)
    assert c.rmse[0] == pytest.approx(0.3)


def test_rssi_crlb_closed_form():
    # each anchor at distance r: J = sum (10 n / (s ln10 r))^2 u u^T = 2 (10 n/(s ln10 r))^2 I
    r = np.sqrt(50.0)
    n, s = 2.5, 4.0
    c = crlb_rssi(SQUARE, [[5.0, 5.0]], s, n)
    k = (10 * n / (s * np.log(10) * r)) ** 2
    np.testing.assert_allclose(c.cov[0], np.eye(2) / (2 * k), rtol=1e-12)


def test_gnss_dop_with_clock_column():
    # four satellites: zenith and three at 0 deg elevation 120 deg apart (classical example)
    az = np.deg2rad([0, 120, 240])
    los = np.vstack([[0, 0, 1], np.c_[np.sin(az), np.cos(az), np.zeros(3)]])
    H = np.c_[-los, np.ones(4)]
    d = dop(H)
    Q = np.linalg.inv(H.T @ H)
    assert d.gdop[0] == pytest.approx(np.sqrt(np.trace(Q)))
    assert d.hdop[0] == pytest.approx(np.sqrt(Q[0, 0] + Q[1, 1]))
    assert d.vdop[0] == pytest.approx(np.sqrt(Q[2, 2]))
    assert d.tdop[0] == pytest.approx(np.sqrt(Q[3, 3]))
    assert d.hdop[0] == pytest.approx(np.sqrt(4 / 3))


def test_crlb_is_attained_by_least_squares_in_monte_carlo():
    rng = np.random.default_rng(0)
    anchors = np.array([[0, 0], [12, 0], [12, 8], [0, 8], [6, -2]], float)
    x0 = np.array([4.0, 3.0])
    sigma = 0.05  # small: linearization exact to first order
    d = np.linalg.norm(x0 - anchors, axis=1)
    G = (x0 - anchors) / d[:, None]
    z = d + sigma * rng.normal(size=(20000, 5))
    # one Gauss-Newton step from the truth is the linearized LS estimate
    dx = np.linalg.lstsq(G, (z - d).T, rcond=None)[0].T
    emp = np.cov(dx.T)
    c = crlb_range(anchors, x0[None], sigma)
    np.testing.assert_allclose(emp, c.cov[0], rtol=0.05, atol=1e-6)


def test_height_offset_mask_and_singular():
    c3 = crlb_range(np.c_[SQUARE, np.full(4, 3.0)], [[5.0, 5.0, 0.0]], 1.0)
    c2 = crlb_range(SQUARE, [[5.0, 5.0]], 1.0, height_offset=np.full(4, 3.0))
    # horizontal information is the same with the height known
    assert c2.horizontal[0] < c3.horizontal[0] + 1e-12
    # slant d^2 = 25 + 25 + 9: J = 4 * 25/59 I, CRLB per axis 59/100
    assert c2.rmse[0] == pytest.approx(np.sqrt(2 * 59 / 100))
    mask = np.array([[True, True, False, False]])
    assert np.isfinite(crlb_range(SQUARE, [[5.0, 5.0]], 1.0, mask=mask).rmse[0])
    assert np.isnan(crlb_range(SQUARE, [[5.0, 0.0]], 1.0, mask=mask).rmse[0])  # collinear
    with pytest.raises(ValueError):
        crlb_range(SQUARE, [[1.0, 2.0, 3.0]], 1.0)
    with pytest.raises(ValueError):
        crlb_range(SQUARE, [[1.0, 2.0]], -1.0)
