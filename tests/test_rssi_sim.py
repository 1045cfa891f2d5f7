"""Scenario wifi-room (seed 002, Table 2)."""

from __future__ import annotations

import argparse

import numpy as np
import pandas as pd
import pytest

from robustloc.eval.rssi_stats import RssiStatistics
from robustloc.sim import scenario_modules
from robustloc.sim.wifi_room import (
    AP_TABLE,
    WifiRoomConfig,
    generate,
    reference_points,
    simulate,
    walk_path,
)


def test_registered_and_writes_contract_files(tmp_path):
    mod = scenario_modules()["wifi-room"]
    p = argparse.ArgumentParser()
    mod.add_arguments(p)
    args = p.parse_args(["--walk-epochs", "40", "--samples-per-point", "5"])
    paths = simulate(tmp_path, 3, args)
    assert set(paths) == {"anchors", "measurements", "truth", "survey"}
    a = pd.read_csv(paths["anchors"])
    assert list(a["anchor"]) == ["AP1", "AP2", "AP3", "AP4"]
    np.testing.assert_allclose(a["gamma"], [r[3] for r in AP_TABLE])
    np.testing.assert_allclose(a["A"], a["p0"] + a["faf"])
    m = pd.read_csv(paths["measurements"])
    assert list(m.columns) == ["time", "tag", "anchor", "rssi"]
    assert len(m) == (20 * 5 + 40) * 4
    t = pd.read_csv(paths["truth"])
    assert set(t["tag"]) == {f"rp{i:02d}" for i in range(1, 21)} | {"walk"}


def test_geometry_and_walk():
    rp = reference_points()
    assert rp.shape == (20, 2)
    t, pos = walk_path(300, 2.0, 1.0)
    step = np.linalg.norm(np.diff(pos, axis=0), axis=1)
    assert np.all(step <= 0.5 + 1e-9) and np.median(step) == pytest.approx(0.5)
    assert pos[:, 0].min() >= 1 and pos[:, 0].max() <= 8


def test_noise_is_left_skewed_heavy_tailed_and_correlated():
    d = generate(WifiRoomConfig(samples_per_point=100, walk_epochs=10), seed=2)
    st = d.measurements[d.measurements["tag"] != "walk"]
    res = RssiStatistics(max_lag=20).compute(st, d.anchors, d.truth)
    s = res.summary()
    assert s["median_skewness"] < -0.3
    assert s["median_kurtosis"] > 3.5
    assert 4 <= s["median_decorrelation_lag"] <= 14
    assert res.variance_distance_corr > 0.1


def test_jumps_on_walk_and_reproducible():
    a = generate(WifiRoomConfig(walk_epochs=300), seed=5)
    b = generate(WifiRoomConfig(walk_epochs=300, jumps=False), seed=5)
    pd.testing.assert_frame_equal(a.truth, b.truth)
    wa = a.measurements[a.measurements["tag"] == "walk"].reset_index(drop=True)
    wb = b.measurements[b.measurements["tag"] == "walk"].reset_index(drop=True)
    diff = (wa["rssi"] - wb["rssi"]).to_numpy().reshape(300, 4)
    np.testing.assert_allclose(diff[50:70, 0], -8.0)
    np.testing.assert_allclose(diff[190:210, 2], -8.0)
    np.testing.assert_allclose(diff[240:260, 1], -8.0)
    assert np.count_nonzero(diff) == 60
    c = generate(WifiRoomConfig(walk_epochs=300), seed=5)
    pd.testing.assert_frame_equal(a.measurements, c.measurements)


def test_bad_config():
    with pytest.raises(ValueError):
        WifiRoomConfig(fade_prob=2.0)
    with pytest.raises(ValueError):
        WifiRoomConfig(walk_epochs=0)
