"""Path-loss models: hand values, round trips, equivalences, per-anchor arrays."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from robustloc.errors import InputError
from robustloc.models.pathloss import (
    AttenuationFactor,
    FreeSpace,
    LogDistance,
    log_distance_arrays,
    model_from_anchors,
)


def test_log_distance_hand_values():
    m = LogDistance(A=-59.0, n=2.0)
    np.testing.assert_allclose(m.rssi([1.0, 10.0, 100.0]), [-59.0, -79.0, -99.0])
    np.testing.assert_allclose(m.distance([-59.0, -79.0]), [1.0, 10.0])
    assert m.rssi(0.0) == np.inf


def test_attenuation_factor_paper_example():
    # seed 002: d0 = 1 m, P_r(d0) = -29 dBm, gamma = 2.275, FAF = -1.076
    m = AttenuationFactor(p0=-29.0, gamma=2.275, faf=-1.076, d0=1.0)
    np.testing.assert_allclose(m.rssi(1.0), -30.076)
    np.testing.assert_allclose(m.rssi(10.0), -29.0 - 22.75 - 1.076)
    # equivalence with log-distance: A = p0 + faf + 10 gamma lg d0, n = gamma
    m2 = AttenuationFactor(p0=-35.0, gamma=3.0, faf=-2.0, d0=2.0)
    A, n = m2.log_distance_params()
    d = np.linspace(0.5, 40, 50)
    np.testing.assert_allclose(LogDistance(A, n).rssi(d), -35 + 30 * np.log10(2 / d) - 2)


def test_friis_link_budget_hand_value():
    # 2.4 GHz, 0 dBm, isotropic: FSPL(1 m) = 20 lg(4 pi / lambda) = 40.05 dB
    lam = 299_792_458.0 / 2.4e9
    m = FreeSpace.from_link_budget(tx_power_dbm=0.0, frequency_hz=2.4e9)
    np.testing.assert_allclose(m.p0, -20 * np.log10(4 * np.pi / lam))
    np.testing.assert_allclose(m.p0, -40.05, atol=0.01)
    np.testing.assert_allclose(m.rssi(10.0) - m.rssi(1.0), -20.0)  # seed 002 eq. (4)
    # d0 != 1: P_r(d) = P_r(d0) + 20 lg(d0/d)
    f = FreeSpace(p0=-50.0, d0=2.0)
    np.testing.assert_allclose(f.rssi(8.0), -50 + 20 * np.log10(2 / 8))


@settings(max_examples=60, deadline=None)
@given(
    A=st.floats(-90, -20), n=st.floats(0.8, 5.0),
    d=st.lists(st.floats(0.05, 500), min_size=1, max_size=10),
)
def test_round_trip(A, n, d):
    for m in (LogDistance(A, n), AttenuationFactor(A, n, -1.5, 1.7), FreeSpace(A, 0.7)):
        np.testing.assert_allclose(m.distance(m.rssi(d)), d, rtol=1e-9)


def test_per_anchor_arrays_broadcast_over_epochs():
    m = LogDistance(A=np.array([-50.0, -60.0, -70.0]), n=np.array([2.0, 2.5, 3.0]))
    d = np.array([[1.0, 10.0, 100.0], [2.0, 2.0, 2.0]])
    out = m.rssi(d)
    assert out.shape == (2, 3)
    np.testing.assert_allclose(out[0], [-50.0, -85.0, -130.0])
    np.testing.assert_allclose(m.distance(out), d)
    assert np.isnan(m.distance(np.array([np.nan, -60, -70]))[0])


def test_slope_and_distance_sigma_numerically():
    m = LogDistance(-55.0, 2.7)
    d = np.array([1.0, 3.0, 12.0])
    h = 1e-6
    num = (m.rssi(d + h) - m.rssi(d - h)) / (2 * h)
    np.testing.assert_allclose(m.drssi_ddistance(d), num, rtol=1e-6)
    # sigma_d = sigma_dB / |d rssi / d d|
    np.testing.assert_allclose(m.distance_sigma(d, 3.0), 3.0 / np.abs(num), rtol=1e-6)


def test_model_from_anchors():
    a = pd.DataFrame({"anchor": ["1", "2"], "x": [0.0, 1], "y": [0.0, 1],
                      "A": [-50.0, -55.0], "n": [2.0, 2.2]})
    A, n = log_distance_arrays(a)
    np.testing.assert_array_equal(A, [-50, -55])
    b = pd.DataFrame({"anchor": ["1"], "x": [0.0], "y": [0.0], "p0": [-29.0], "gamma": [2.275]})
    m = model_from_anchors(b)
    assert isinstance(m, AttenuationFactor)
    np.testing.assert_allclose(m.rssi(1.0), [-29.0])  # faf defaults to 0, d0 to 1
    with pytest.raises(InputError, match="no path-loss parameters"):
        model_from_anchors(a[["anchor", "x", "y"]])
    a.loc[1, "n"] = np.nan
    a.index = pd.Index([2, 3], name="line")
    with pytest.raises(InputError, match="anchor '2' has no value for 'n'") as ei:
        model_from_anchors(a)
    assert ei.value.line == 3


def test_invalid_parameters():
    with pytest.raises(ValueError):
        LogDistance(-50, 0.0)
    with pytest.raises(ValueError):
        AttenuationFactor(d0=0.0)
