"""The tracker's range-offset state (``Tracker(range_offset=True)``, ``track --range-offset``):
every range of a tag reads ``b`` long (a UWB antenna delay); the filter estimates ``b``."""

from __future__ import annotations

import json
import re
import subprocess
import sys

import numpy as np
import pandas as pd
import pytest
from scipy.stats import chi2

from robustloc.filters.motion import ConstantAcceleration, ConstantVelocity, RandomWalkAugmented
from robustloc.io.tables import Epochs
from robustloc.tracking import Tracker

SIGMA_M = 0.1
DT = 0.5


def _ring(M: int = 6, radius: float = 20.0) -> pd.DataFrame:
    ang = np.linspace(0, 2 * np.pi, M, endpoint=False)
    return pd.DataFrame({"anchor": [f"A{i}" for i in range(M)], "x": radius * np.cos(ang),
                         "y": radius * np.sin(ang)})


def _cv_truth(K: int, T: int, q: float, seed: int, centre: tuple[float, float] = (0.0, 0.0)
              ) -> list[np.ndarray]:
    """``T`` states ``(K, 4)`` of ``K`` tags moving exactly as the CV model with ``q``."""
    rng = np.random.default_rng(seed)
    F, Q = ConstantVelocity(q=q).FQ(DT)
    L = np.linalg.cholesky(Q + 1e-15 * np.eye(4))
    x = np.zeros((K, 4))
    x[:, :2] = np.asarray(centre) + rng.uniform(-3, 3, (K, 2))
    x[:, 2:] = rng.normal(0, 1.0, (K, 2))  # the tracker's starting velocity variance is 1
    out = [x.copy()]
    for _ in range(T - 1):
        x = x @ F.T + rng.standard_normal((K, 4)) @ L.T
        out.append(x.copy())
    return out


def _ranges(anchors: pd.DataFrame, truth: list[np.ndarray], offset: np.ndarray, seed: int
            ) -> list[Epochs]:
    """One epoch per step: Gaussian ranges (``SIGMA_M``) plus each tag's ``offset``."""
    rng = np.random.default_rng(seed)
    axy = anchors[["x", "y"]].to_numpy(float)
    K = len(offset)
    tags = np.array([f"t{k}" for k in range(K)], dtype=object)
    out = []
    for j, x in enumerate(truth):
        r = (np.linalg.norm(x[:, None, :2] - axy[None], axis=2) + offset[:, None]
             + rng.normal(0, SIGMA_M, (K, len(axy))))
        out.append(Epochs(np.full(K, j * DT), tags, r, tuple(anchors["anchor"]), "range",
                          np.zeros(K, dtype=np.int64)))
    return out


def _concat(blocks: list[Epochs]) -> Epochs:
    b0 = blocks[0]
    return Epochs(np.concatenate([b.time for b in blocks]), np.concatenate([b.tag for b in blocks]),
                  np.concatenate([b.values for b in blocks]), b0.anchor_ids, b0.value,
                  np.concatenate([b.line for b in blocks]))


def _cut(ep: Epochs, s: slice) -> Epochs:
    return Epochs(ep.time[s], ep.tag[s], ep.values[s], ep.anchor_ids, ep.value, ep.line[s])


def assert_chunks_and_saved_state_give_the_rows(a: pd.DataFrame, ep: Epochs, whole: pd.DataFrame,
                                                **kw) -> None:
    """``Tracker(a, **kw)`` stepped 7 epochs at a time, and through a saved state (JSON)
    half-way, gives ``whole`` (the rows of one step over ``ep``)."""
    trk = Tracker(a, **kw)
    parts = [trk.step(_cut(ep, slice(i, i + 7))) for i in range(0, ep.n_epochs, 7)]
    pd.testing.assert_frame_equal(whole, pd.concat(parts, ignore_index=True))
    h = ep.n_epochs // 2
    t1 = Tracker(a, **kw)
    first = t1.step(_cut(ep, slice(0, h)))
    t2 = Tracker(a, **kw)
    t2.load_state_dict(json.loads(json.dumps(t1.state_dict())))
    second = t2.step(_cut(ep, slice(h, None)))
    pd.testing.assert_frame_equal(whole, pd.concat([first, second], ignore_index=True))


def write_long(ep: Epochs, path) -> None:
    """``ep`` (ranges) as a measurements file: one row per epoch and anchor."""
    ids = list(ep.anchor_ids)
    pd.DataFrame({"time": np.repeat(ep.time, len(ids)), "tag": np.repeat(ep.tag, len(ids)),
                  "anchor": np.tile(ids, ep.n_epochs),
                  "range": ep.values.ravel()}).to_csv(path, index=False)


def test_random_walk_augmented_model_is_block_diagonal():
    for base in (ConstantVelocity(q=0.7), ConstantAcceleration(q=0.3)):
        m = RandomWalkAugmented(base, q_extra=0.02)
        assert m.n_states == base.n_states + 1
        dt = np.array([0.1, 0.5, 2.0])
        F, Q = m.F(dt), m.Q(dt)
        n = base.n_states
        np.testing.assert_array_equal(F[:, :n, :n], base.F(dt))
        np.testing.assert_array_equal(Q[:, :n, :n], base.Q(dt))
        np.testing.assert_array_equal(F[:, n, n], 1.0)
        np.testing.assert_allclose(Q[:, n, n], 0.02 * dt, rtol=1e-15)
        assert not F[:, n, :n].any() and not F[:, :n, n].any()
        assert not Q[:, n, :n].any() and not Q[:, :n, n].any()
        Fs, Qs = m.FQ(0.5)  # a scalar step: the batch's second matrix
        np.testing.assert_array_equal(Fs, F[1])
        np.testing.assert_array_equal(Qs, Q[1])
    with pytest.raises(ValueError):
        RandomWalkAugmented(ConstantVelocity(), q_extra=-1.0)


def test_offset_estimate_and_state_are_consistent():
    """Monte Carlo NEES of the whole state ``[x, y, vx, vy, b]`` after 120 epochs, over 100
    tags whose offsets are drawn from the filter's own prior (N(0, 0.3^2)), the motion from
    its own CV model, plain update and fixed noise: a consistent filter's mean NEES lies in
    the chi-square band of ``5 K`` degrees of freedom (99.9 %; measured 4.89 in [4.02,
    6.11]), and so does the offset's own normalized error (1 dof; measured 1.04)."""
    K, T, q = 100, 120, 0.5
    b = np.random.default_rng(5).normal(0, 0.3, K)
    a = _ring()
    truth = _cv_truth(K, T, q, seed=1)
    trk = Tracker(a, sigma=SIGMA_M, q=q, weight="ls", noise_scale_max=1.0, range_offset=True,
                  range_offset_sd=0.3, range_offset_q=0.0)
    for ep in _ranges(a, truth, b, seed=2):
        trk.step(ep)
    sl = [trk._slot[f"t{k}"] for k in range(K)]
    x, P = trk._x[sl], trk._P[sl]
    err = np.c_[x[:, :4] - truth[-1], x[:, 4] - b]
    nees = np.einsum("ki,ki->k", err, np.linalg.solve(P, err[..., None])[..., 0])
    lo, hi = chi2.ppf(0.0005, 5 * K) / K, chi2.ppf(0.9995, 5 * K) / K
    assert lo <= nees.mean() <= hi
    zb2 = (x[:, 4] - b) ** 2 / P[:, 4, 4]
    assert chi2.ppf(0.0005, K) / K <= zb2.mean() <= chi2.ppf(0.9995, K) / K


def test_offset_state_removes_the_position_bias_an_offset_causes():
    """Tags off the centre of a ring of anchors, every range 0.5 m long.  Without the state
    the track is biased by the least-squares response to a common offset,
    ``dp = (J^T J)^-1 J^T 1 b`` (J: the unit line-of-sight rows at the truth), about 0.2 m
    here; with it the bias goes.  Tolerance: a quarter of ``|dp|`` (0.05 m), more than ten
    standard errors of the mean error over 20 tags x 80 epochs (the CV filter's position
    sd ~0.05 m over some 8 independent windows per tag: ~0.004 m)."""
    K, T, q, b = 20, 120, 0.05, 0.5
    a = _ring()
    axy = a[["x", "y"]].to_numpy(float)
    truth = _cv_truth(K, T, q, seed=3, centre=(12.0, 0.0))
    eps = _ranges(a, truth, np.full(K, b), seed=4)
    dp = []
    for x in truth[40:]:
        d = x[:, None, :2] - axy[None]
        J = d / np.linalg.norm(d, axis=2)[..., None]
        dp.append(np.linalg.solve(np.einsum("kmi,kmj->kij", J, J),
                                  J.sum(axis=1)[..., None] * b)[..., 0])
    dp_mean = np.mean(np.concatenate(dp), axis=0)
    tol = 0.25 * np.linalg.norm(dp_mean)
    mean_err = {}
    for off in (False, True):
        trk = Tracker(a, sigma=SIGMA_M, q=q, range_offset=off)
        errs = []
        for j, ep in enumerate(eps):
            rows = trk.step(ep)
            if j >= 40:
                errs.append(rows[["x", "y"]].to_numpy(float) - truth[j][:, :2])
        mean_err[off] = np.mean(np.concatenate(errs), axis=0)
    assert np.linalg.norm(mean_err[False] - dp_mean) < tol  # the derivation holds
    assert np.linalg.norm(mean_err[True]) < tol
    assert "range_offset" in rows and np.all(np.abs(rows["range_offset"] - b) < 0.05)


def _labyrinth_like() -> tuple[pd.DataFrame, Epochs]:
    a = _ring(M=4, radius=5.0)
    truth = _cv_truth(3, 60, 0.5, seed=7)
    return a, _concat(_ranges(a, truth, np.array([0.3, -0.1, 0.0]), seed=8))


@pytest.mark.parametrize("filt", ["ekf", "ukf"])
@pytest.mark.parametrize("model", ["cv", "ca"])
def test_offset_runs_on_the_compiled_kernel_as_on_numpy(filt, model):
    """State sizes 5 and 7 (the kinematic states and ``b``) have fused kernels; they agree
    with the NumPy reference to rounding (other summation order, amplified by the
    recursion: 1e-9 m, as ``tests/test_track.py`` for the other states)."""
    a, ep = _labyrinth_like()
    trk = Tracker(a, sigma=SIGMA_M, range_offset=True, filter=filt, model=model)
    rc = trk.step(ep)
    assert trk._kernel is not None and trk.n == trk.n_motion + 1
    rn = Tracker(a, sigma=SIGMA_M, range_offset=True, filter=filt, model=model,
                 engine="numpy").step(ep)
    for c in ("status", "n_used", "reinit", "excluded"):
        assert (rc[c] == rn[c]).all(), c
    for c in ("x", "y", "vx", "vy", "var_x", "var_y", "cov_xy", "hpl", "nis", "noise_scale",
              "range_offset", "var_range_offset"):
        np.testing.assert_allclose(rc[c], rn[c], rtol=1e-9, atol=1e-9, err_msg=c)


def test_offset_steps_in_any_chunks():
    a, ep = _labyrinth_like()
    whole = Tracker(a, sigma=SIGMA_M, range_offset=True).step(ep)
    assert_chunks_and_saved_state_give_the_rows(a, ep, whole, sigma=SIGMA_M, range_offset=True)
    assert whole["var_range_offset"].iloc[-1] < 0.5**2  # the prior's variance shrank


def test_a_restart_keeps_the_offset():
    """A divergence re-start begins from a fix of the ranges with the offset removed and
    keeps the offset's estimate and variance."""
    a, ep = _labyrinth_like()
    trk = Tracker(a, sigma=SIGMA_M, range_offset=True, engine="numpy")
    trk.step(ep)
    sl = np.array([trk._slot["t0"]])
    b, vb = trk._x[sl[0], -1], trk._P[sl[0], -1, -1]
    from robustloc.tracking.tracker import _Rows

    out = _Rows(1, trk.n, 4)
    last = np.flatnonzero(ep.tag == "t0")[-1]
    z = ep.values[last:last + 1] - b
    assert trk._start(np.array([0]), sl, ep.time[last:last + 1], z, out, reinit=True).all()
    assert trk._x[sl[0], -1] == b and trk._P[sl[0], -1, -1] == vb


def _cli(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "robustloc.cli", *args], capture_output=True,
                          text=True)


def test_command_range_offset_columns_smoothing_and_refusal(tmp_path):
    a, ep = _labyrinth_like()
    a.to_csv(tmp_path / "a.csv", index=False)
    write_long(ep, tmp_path / "m.csv")
    long = pd.read_csv(tmp_path / "m.csv")
    got = {}
    for extra in ([], ["--smooth"]):
        r = _cli("track", str(tmp_path / "m.csv"), "--anchors", str(tmp_path / "a.csv"),
                 "-o", str(tmp_path / "o.csv"), "--sigma", "0.1", "--range-offset", "--quiet",
                 *extra)
        assert r.returncode == 0, r.stderr
        got[bool(extra)] = out = pd.read_csv(tmp_path / "o.csv")
        assert len(out) == ep.n_epochs and out["range_offset"].notna().all()
    last = got[False].groupby("tag").tail(1).set_index("tag")["range_offset"]
    # the summary names each tag's final offset, as --json and as text
    r = _cli("track", str(tmp_path / "m.csv"), "--anchors", str(tmp_path / "a.csv"),
             "-o", str(tmp_path / "o.csv"), "--sigma", "0.1", "--range-offset", "--json")
    off = json.loads(r.stdout)["range_offset_m"]
    assert sorted(off) == ["t0", "t1", "t2"]
    for tag in off:
        assert off[tag]["estimate"] == pytest.approx(last[tag], abs=1e-4)
        assert 0 < off[tag]["sd"] < 0.5
    r = _cli("track", str(tmp_path / "m.csv"), "--anchors", str(tmp_path / "a.csv"),
             "-o", str(tmp_path / "o.csv"), "--sigma", "0.1", "--range-offset")
    assert r.returncode == 0
    assert re.search(r"range offset of t0: \+0\.\d{3} m \(sd 0\.\d{3}\)", r.stdout)
    np.testing.assert_allclose(last.loc[["t0", "t1", "t2"]], [0.3, -0.1, 0.0], atol=0.05)
    # smoothing: the first rows' offset uses the whole log (its variance no larger)
    first = got[True].groupby("tag").head(1)
    assert (first["var_range_offset"].to_numpy()
            <= got[False].groupby("tag").head(1)["var_range_offset"].to_numpy()).all()
    np.testing.assert_allclose(first.set_index("tag").loc[["t0", "t1", "t2"], "range_offset"],
                               [0.3, -0.1, 0.0], atol=0.05)
    # RSSI has no range offset: a user's mistake, exit 2 with the anchors file's name
    rssi = long.rename(columns={"range": "rssi"}).assign(rssi=-60.0)
    rssi.to_csv(tmp_path / "r.csv", index=False)
    r = _cli("track", str(tmp_path / "r.csv"), "--anchors", str(tmp_path / "a.csv"),
             "-o", str(tmp_path / "o2.csv"), "--range-offset", "--quiet")
    assert r.returncode == 2 and "error:" in r.stderr and "r.csv:1" in r.stderr
    assert "--range-offset applies to ranges" in r.stderr
    assert "Traceback" not in r.stderr
