"""The tracker's links' offsets (``Tracker(link_offsets=True)``, ``track --link-offsets``):
each link of a tag reads its own offset ``b_i`` (m of ranges, dB of RSSI); the filter
estimates them as states."""

from __future__ import annotations

import json
import math
import subprocess
import sys

import numpy as np
import pandas as pd
import pytest
from scipy.stats import chi2
from test_track_offset import (
    _concat,
    _cv_truth,
    _ring,
    assert_chunks_and_saved_state_give_the_rows,
    write_long,
)

from robustloc.io.tables import Epochs
from robustloc.tracking import Tracker

SIGMA_M = 0.1
DT = 0.5
LINK_B_M = np.array([0.3, -0.2, 0.1, 0.25, -0.15, 0.0])  # per anchor of the ring of six


def _link_ranges(anchors: pd.DataFrame, truth: list[np.ndarray], b: np.ndarray, seed: int
                 ) -> list[Epochs]:
    """One epoch per step: Gaussian ranges (``SIGMA_M``) plus the offsets ``b (K, M)``."""
    rng = np.random.default_rng(seed)
    axy = anchors[["x", "y"]].to_numpy(float)
    K = b.shape[0]
    tags = np.array([f"t{k}" for k in range(K)], dtype=object)
    out = []
    for j, x in enumerate(truth):
        r = (np.linalg.norm(x[:, None, :2] - axy[None], axis=2) + b
             + rng.normal(0, SIGMA_M, b.shape))
        out.append(Epochs(np.full(K, j * DT), tags, r, tuple(anchors["anchor"]), "range",
                          np.zeros(K, dtype=np.int64)))
    return out


def test_link_offsets_estimate_and_state_are_consistent():
    """Monte Carlo NEES of the whole state ``[x, y, vx, vy, b_1 .. b_6]`` after 120 epochs,
    over 100 tags whose links' offsets are drawn from the filter's own prior (N(0, 0.2^2)
    each), the motion from its own CV model, plain update and fixed noise: a consistent
    filter's mean NEES lies in the chi-square band of ``10 K`` degrees of freedom (99.9 %),
    and so do the offsets' own normalized errors (``6 K`` dof)."""
    K, T, q = 100, 120, 0.5
    a = _ring()
    M = len(a)
    b = np.random.default_rng(5).normal(0, 0.2, (K, M))
    truth = _cv_truth(K, T, q, seed=1)
    trk = Tracker(a, sigma=SIGMA_M, q=q, weight="ls", noise_scale_max=1.0, link_offsets=True,
                  link_offset_sd=0.2)
    assert trk.n == 4 + M
    for ep in _link_ranges(a, truth, b, seed=2):
        trk.step(ep)
    sl = [trk._slot[f"t{k}"] for k in range(K)]
    x, P = trk._x[sl], trk._P[sl]
    err = np.c_[x[:, :4] - truth[-1], x[:, 4:] - b]
    nees = np.einsum("ki,ki->k", err, np.linalg.solve(P, err[..., None])[..., 0])
    n = 4 + M
    assert chi2.ppf(0.0005, n * K) / K <= nees.mean() <= chi2.ppf(0.9995, n * K) / K
    Pb = P[:, 4:, 4:]
    eb = err[:, 4:]
    nb = np.einsum("ki,ki->k", eb, np.linalg.solve(Pb, eb[..., None])[..., 0])
    assert chi2.ppf(0.0005, M * K) / K <= nb.mean() <= chi2.ppf(0.9995, M * K) / K
    # and the offsets were learned: the posterior sd well below the prior's 0.2 m
    assert np.sqrt(np.diagonal(Pb, axis1=1, axis2=2)).max() < 0.1


def _circles(K: int, T: int, centre: tuple[float, float], radius: float, speed: float
             ) -> list[np.ndarray]:
    """``T`` states ``(K, 4)``: ``K`` tags walking a circle at ``speed`` (m/s), each from
    its own phase."""
    ph = np.linspace(0, 2 * np.pi, K, endpoint=False)
    w = speed / radius
    out = []
    for j in range(T):
        a = ph + w * j * DT
        out.append(np.c_[centre[0] + radius * np.cos(a), centre[1] + radius * np.sin(a),
                         -speed * np.sin(a), speed * np.cos(a)])
    return out


def test_link_offsets_remove_the_position_bias_they_cause():
    """50 tags walking circles of 3 m off the centre of a ring of six anchors, each
    anchor's ranges offset by its own ``b_i`` (-0.8 .. 1.2 m).  Without the states the
    track is biased by about the least-squares response ``dp = (J^T J)^-1 J^T b`` (J: the
    unit line-of-sight rows at the truth; plain update ``weight="ls"``, fixed noise): the
    mean over the tags of the last epoch's error along each tag's ``dp`` exceeds half of
    the mean ``|dp|``; with them it lies within 4 standard errors of zero (the filter's
    own position sd along ``dp`` over ``sqrt(K)``), and every final offset within 4 of its
    own standard deviations of the truth."""
    K, T, q = 50, 200, 0.05
    a = _ring()
    axy = a[["x", "y"]].to_numpy(float)
    truth = _circles(K, T, centre=(6.0, 2.0), radius=3.0, speed=0.3)
    b = np.broadcast_to(4 * LINK_B_M, (K, len(a)))
    eps = _link_ranges(a, truth, b, seed=4)
    x = truth[-1]
    d = x[:, None, :2] - axy[None]
    J = d / np.linalg.norm(d, axis=2)[..., None]
    dp = np.linalg.solve(np.einsum("kmi,kmj->kij", J, J),
                         np.einsum("kmi,km->ki", J, b)[..., None])[..., 0]  # per tag
    size = np.linalg.norm(dp, axis=1)
    u = dp / size[:, None]
    assert size.mean() > 0.1  # the offsets do bias a plain fix here
    for links in (False, True):
        trk = Tracker(a, sigma=SIGMA_M, q=q, weight="ls", noise_scale_max=1.0,
                      link_offsets=links, link_offset_sd=0.6)
        for ep in eps:
            rows = trk.step(ep)
        e = rows[["x", "y"]].to_numpy(float) - x[:, :2]
        along = np.einsum("ki,ki->k", e, u).mean()  # the error along each tag's dp
        v = rows[["var_x", "var_y"]].to_numpy(float)
        se = np.sqrt(np.einsum("ki,ki->k", u * u, v).mean() / K)  # (ignoring cov_xy)
        if links:
            assert abs(along) < 4 * se, (along, se)
        else:
            assert along > 0.5 * size.mean() and along > 4 * se, (along, size.mean(), se)
    sl = [trk._slot[f"t{k}"] for k in range(K)]
    est = trk._x[sl, 4:]
    sd = np.sqrt(np.diagonal(trk._P[sl], axis1=1, axis2=2)[:, 4:])
    assert np.all(np.abs(est - b) < 4 * sd)


def _rssi_epochs(anchors: pd.DataFrame, truth: list[np.ndarray], b_db: np.ndarray,
                 sigma_db: float, seed: int) -> list[Epochs]:
    """RSSI of the log-distance model of ``anchors`` (``A``, ``n``) plus ``b_db (M,)``."""
    rng = np.random.default_rng(seed)
    axy = anchors[["x", "y"]].to_numpy(float)
    A, n = anchors["A"].to_numpy(float), anchors["n"].to_numpy(float)
    K = truth[0].shape[0]
    tags = np.array([f"t{k}" for k in range(K)], dtype=object)
    out = []
    for j, x in enumerate(truth):
        d = np.linalg.norm(x[:, None, :2] - axy[None], axis=2)
        z = A - 10 * n * np.log10(d) + b_db + rng.normal(0, sigma_db, d.shape)
        out.append(Epochs(np.full(K, j * DT), tags, z, tuple(anchors["anchor"]), "rssi",
                          np.zeros(K, dtype=np.int64)))
    return out


@pytest.mark.parametrize("domain", ["range", "rssi"])
def test_link_offsets_of_rssi_are_learned_in_db(domain):
    """RSSI whose receivers read ``b_i`` dB off their calibration (-2 .. +2 dB), 1 dB
    noise: the links' offsets are estimated in dB in both update domains (ranges turned
    from RSSI, where ``b_i`` scales the range by ``10^(-b_i / (10 n_i))``, and dB), the
    estimates are within 4 of their standard deviations of the truth (the common part
    of the offsets is the weakly observable one: the test takes it out), and the
    position RMS improves on the plain tracker's."""
    K, T, q = 10, 200, 0.05
    a = _ring(M=6, radius=10.0).assign(A=-45.0, n=2.0)
    b_db = np.array([2.0, -1.5, 1.0, -2.0, 0.5, 0.0])
    truth = _cv_truth(K, T, q, seed=11)
    eps = _rssi_epochs(a, truth, b_db, 1.0, seed=12)
    rms = {}
    for links in (False, True):
        trk = Tracker(a, sigma=1.0, q=q, domain=domain, link_offsets=links)
        sq = []
        for j, ep in enumerate(eps):
            rows = trk.step(ep)
            if j >= 100:
                sq.append(np.sum((rows[["x", "y"]].to_numpy(float) - truth[j][:, :2]) ** 2,
                                 axis=1))
        rms[links] = math.sqrt(np.mean(np.concatenate(sq)))
    sl = [trk._slot[f"t{k}"] for k in range(K)]
    est = trk._x[sl, 4:]
    sd = np.sqrt(np.diagonal(trk._P[sl], axis1=1, axis2=2)[:, 4:])
    dev = (est - est.mean(axis=1, keepdims=True)) - (b_db - b_db.mean())
    assert np.all(np.abs(dev) < 4 * sd), (dev, sd)
    assert rms[True] < 0.9 * rms[False], rms


def test_link_offsets_run_compiled_step_in_chunks_and_survive_a_saved_state():
    """The compiled round of state size ``4 + M`` (``track_round_n``) agrees with the NumPy
    reference to rounding (1e-9, as the other states: ``tests/test_track.py``, also on
    random workloads); chunks and a saved state give the same rows."""
    a = _ring(M=4, radius=5.0)
    truth = _cv_truth(3, 60, 0.5, seed=7)
    ep = _concat(_link_ranges(a, truth, np.tile([0.2, -0.1, 0.05, 0.0], (3, 1)), seed=8))
    whole = Tracker(a, sigma=SIGMA_M, link_offsets=True).step(ep)
    trk = Tracker(a, sigma=SIGMA_M, link_offsets=True)
    ref = Tracker(a, sigma=SIGMA_M, link_offsets=True, engine="numpy").step(ep)
    for c in ("status", "n_used", "reinit", "excluded"):
        assert (whole[c] == ref[c]).all(), c
    for c in ("x", "y", "vx", "vy", "var_x", "var_y", "cov_xy", "hpl", "nis", "noise_scale"):
        np.testing.assert_allclose(whole[c], ref[c], rtol=1e-9, atol=1e-9, err_msg=c)
    trk.step(ep)
    assert trk._kernel is not None and trk.n == 8
    assert_chunks_and_saved_state_give_the_rows(a, ep, whole, sigma=SIGMA_M, link_offsets=True)


def test_a_restart_keeps_the_links_offsets():
    a = _ring(M=4, radius=5.0)
    truth = _cv_truth(1, 40, 0.5, seed=7)
    ep = _concat(_link_ranges(a, truth, np.array([[0.2, -0.1, 0.05, 0.0]]), seed=8))
    trk = Tracker(a, sigma=SIGMA_M, link_offsets=True, engine="numpy")
    trk.step(ep)
    k = trk._slot["t0"]
    b, Pb = trk._x[k, 4:].copy(), trk._P[k, 4:, 4:].copy()
    from robustloc.tracking.tracker import _Rows

    out = _Rows(1, trk.n, 4)
    z = ep.values[-1:] - b
    assert trk._start(np.array([0]), np.array([k]), ep.time[-1:], z, out, reinit=True).all()
    np.testing.assert_array_equal(trk._x[k, 4:], b)
    np.testing.assert_array_equal(trk._P[k, 4:, 4:], Pb)


def test_link_offsets_settings_are_checked():
    a = _ring()
    with pytest.raises(ValueError, match="exclude each other"):
        Tracker(a, link_offsets=True, range_offset=True)
    with pytest.raises(ValueError, match="link_offset_sd"):
        Tracker(a, link_offsets=True, link_offset_sd=0.0)
    with pytest.raises(ValueError, match="link_offset_q"):
        Tracker(a, link_offsets=True, link_offset_q=-1.0)


def _cli(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "robustloc.cli", *args], capture_output=True,
                          text=True)


def test_command_link_offsets_summary_and_refusal(tmp_path):
    a = _ring(M=4, radius=5.0)
    truth = _cv_truth(2, 80, 0.5, seed=7)
    b = np.array([[0.2, -0.1, 0.05, 0.0], [0.0, 0.1, -0.2, 0.15]])
    ep = _concat(_link_ranges(a, truth, b, seed=8))
    a.to_csv(tmp_path / "a.csv", index=False)
    write_long(ep, tmp_path / "m.csv")
    ids = list(ep.anchor_ids)
    base = ["track", str(tmp_path / "m.csv"), "--anchors", str(tmp_path / "a.csv"),
            "-o", str(tmp_path / "o.csv"), "--sigma", "0.1", "--link-offsets"]
    r = _cli(*base, "--json")
    assert r.returncode == 0, r.stderr
    off = json.loads(r.stdout)["link_offset_m"]
    assert sorted(off) == ["t0", "t1"] and list(off["t0"]) == ids
    for k, tag in enumerate(("t0", "t1")):
        est = np.array([off[tag][i]["estimate"] for i in ids])
        sd = np.array([off[tag][i]["sd"] for i in ids])
        assert np.all((sd > 0) & (sd < 0.1))
        assert np.all(np.abs(est - b[k]) < 4 * sd + 1e-4)  # (rounded to 1e-4)
    out = pd.read_csv(tmp_path / "o.csv")
    assert len(out) == ep.n_epochs and (out["status"] == "ok").mean() > 0.9
    r = _cli(*base)
    assert r.returncode == 0 and "link offsets of t0 (m): A0 +0." in r.stdout
    # smoothed: the same columns (the smoother wrote the first link's offset as a
    # `range_offset` column, the tracker review)
    for smooth in (["--smooth"], ["--fixed-lag", "3"]):
        r = _cli(*[str(tmp_path / "s.csv") if a == str(tmp_path / "o.csv") else a
                   for a in base], *smooth)
        assert r.returncode == 0, r.stderr
        assert list(pd.read_csv(tmp_path / "s.csv").columns) == list(out.columns), smooth
    # with --range-offset: a user's mistake, exit 2, no traceback
    r = _cli(*base, "--range-offset")
    assert r.returncode == 2 and r.stderr.startswith("error: ")
    assert "exclude each other" in r.stderr and "Traceback" not in r.stderr


def test_link_offsets_table_is_the_state():
    a = _ring(M=4, radius=5.0)
    truth = _cv_truth(2, 30, 0.5, seed=7)
    ep = _concat(_link_ranges(a, truth, np.tile([0.2, -0.1, 0.05, 0.0], (2, 1)), seed=8))
    trk = Tracker(a, sigma=SIGMA_M, link_offsets=True)
    trk.step(ep)
    tab = trk.link_offsets()
    assert list(tab.columns) == ["tag", "anchor", "offset", "sd"] and len(tab) == 8
    for row in tab.itertuples():
        k, i = trk._slot[row.tag], list(trk.anchor_ids).index(row.anchor)
        assert row.offset == trk._x[k, 4 + i]
        assert row.sd == math.sqrt(trk._P[k, 4 + i, 4 + i])
    with pytest.raises(ValueError, match="link_offsets=False"):
        Tracker(a).link_offsets()
