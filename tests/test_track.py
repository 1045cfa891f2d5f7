"""robustloc.tracking: the robust tight tracker, its smoother and the ``track`` command."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pandas as pd
import pytest
from hypothesis import given, settings
from hypothesis import strategies as hst

from robustloc.io.tables import Epochs, to_epochs
from robustloc.tracking import Tracker
from robustloc.tracking.smooth import rts_segment

SIGMA_M = 0.1


def _anchors(M: int = 6) -> pd.DataFrame:
    ang = np.linspace(0, 2 * np.pi, M, endpoint=False)
    return pd.DataFrame({"anchor": [f"A{i}" for i in range(M)], "x": 10 + 12 * np.cos(ang),
                         "y": 10 + 12 * np.sin(ang)})


def _walk(K: int = 3, N: int = 80, seed: int = 0, dt: float = 0.5,
          anchors: pd.DataFrame | None = None) -> tuple[pd.DataFrame, pd.DataFrame]:
    """``K`` tags on smooth curves; ranges with ``SIGMA_M`` noise, long format."""
    rng = np.random.default_rng(seed)
    a = _anchors() if anchors is None else anchors
    xy = a[["x", "y"]].to_numpy()
    t = np.arange(N) * dt
    rows, truth = [], []
    for k in range(K):
        ph = rng.uniform(0, 2 * np.pi)
        p = np.stack([10 + 5 * np.cos(0.1 * t + ph), 10 + 4 * np.sin(0.13 * t + ph)], 1)
        r = np.linalg.norm(p[:, None] - xy[None], axis=2) + rng.normal(0, SIGMA_M, (N, len(a)))
        for j in range(N):
            truth.append((t[j], f"tag{k}", *p[j]))
            for i, an in enumerate(a["anchor"]):
                rows.append((t[j], f"tag{k}", an, r[j, i]))
    meas = pd.DataFrame(rows, columns=["time", "tag", "anchor", "range"]).sort_values(
        ["time", "tag"], kind="mergesort", ignore_index=True)
    return meas, pd.DataFrame(truth, columns=["time", "tag", "x", "y"])


def _epochs(meas: pd.DataFrame, anchors: pd.DataFrame):
    return to_epochs(meas, anchors["anchor"])


def _errors(rows: pd.DataFrame, truth: pd.DataFrame) -> np.ndarray:
    j = rows.merge(truth, on=["time", "tag"], suffixes=("", "_t"))
    return np.hypot(j.x - j.x_t, j.y - j.y_t).to_numpy()


def test_one_row_per_epoch_and_accuracy():
    a = _anchors()
    meas, truth = _walk()
    ep = _epochs(meas, a)
    rows = Tracker(a, sigma=SIGMA_M).step(ep)
    assert len(rows) == ep.n_epochs
    assert set(rows.status) <= {"ok", "fault_excluded", "fault_detected"}
    # fault_detected: the innovations' global test failed (unexplained) -- on clean data
    # only at its false-alarm rate, the B-method's alpha for 6 components (1.9 %): at most
    # the binomial 99.9 % quantile of 240 rows, 12 (measured: 3)
    from scipy import stats

    from robustloc.integrity.bmethod import global_alpha

    limit = stats.binom.ppf(0.999, len(rows), float(global_alpha(6)))
    assert (rows.status == "fault_detected").sum() <= limit
    e = _errors(rows, truth)
    # a CV filter on 6 ranges of 0.1 m: the error of one fix is about 0.1 m (GDOP ~1), the
    # filter must not be worse than 2 sigma in RMS (it averages; 2x covers the start)
    assert np.sqrt(np.mean(e**2)) < 2 * SIGMA_M


def test_batch_equals_one_epoch_at_a_time():
    a = _anchors()
    meas, _ = _walk(K=3, N=40, seed=1)
    ep = _epochs(meas, a)
    whole = Tracker(a, sigma=SIGMA_M).step(ep)
    trk = Tracker(a, sigma=SIGMA_M)
    parts = []
    for i in range(ep.n_epochs):
        one = type(ep)(ep.time[i:i + 1], ep.tag[i:i + 1], ep.values[i:i + 1], ep.anchor_ids,
                       ep.value, ep.line[i:i + 1])
        parts.append(trk.step(one))
    pd.testing.assert_frame_equal(whole, pd.concat(parts, ignore_index=True))


def test_state_dict_round_trip_through_json():
    a = _anchors()
    meas, _ = _walk(K=2, N=40, seed=2)
    ep = _epochs(meas, a)
    whole = Tracker(a, sigma=SIGMA_M).step(ep)
    h = ep.n_epochs // 2
    def cut(s):
        return (type(ep)(ep.time[s], ep.tag[s], ep.values[s], ep.anchor_ids, ep.value,
                                  ep.line[s]))
    t1 = Tracker(a, sigma=SIGMA_M)
    first = t1.step(cut(slice(0, h)))
    saved = json.loads(json.dumps(t1.state_dict()))
    t2 = Tracker(a, sigma=SIGMA_M)
    t2.load_state_dict(saved)
    second = t2.step(cut(slice(h, None)))
    pd.testing.assert_frame_equal(whole, pd.concat([first, second], ignore_index=True))


@pytest.mark.parametrize("filt", ["ekf", "ukf"])
def test_checkpoint_rollback_undoes_a_block_exactly(filt):
    """`serve --track` rolls a failed block back: after a wrong block and a rollback the
    tracker goes on exactly as one that never saw it (rows, saved state, and the recorded
    history that smoothing reads), and a checkpoint serves more than one rollback."""
    a = _anchors()
    meas, _ = _walk(K=3, N=60, seed=2)
    ep = _epochs(meas, a)

    def cut(s):
        return type(ep)(ep.time[s], ep.tag[s], ep.values[s], ep.anchor_ids, ep.value,
                        ep.line[s])

    n = ep.n_epochs
    parts = [slice(0, n // 3), slice(n // 3, 2 * n // 3), slice(2 * n // 3, None)]
    ref = Tracker(a, sigma=SIGMA_M, filter=filt, record=True)
    want = [ref.step(cut(p)) for p in parts]
    t = Tracker(a, sigma=SIGMA_M, filter=filt, record=True)
    got = [t.step(cut(parts[0]))]
    cp = t.checkpoint()
    for _ in range(2):  # a wrong block (the last one, early), undone twice
        t.step(cut(parts[2]))
        t.rollback(cp)
    got += [t.step(cut(parts[1])), t.step(cut(parts[2]))]
    for w, g in zip(want, got):
        pd.testing.assert_frame_equal(w, g)
    assert json.dumps(ref.state_dict(), sort_keys=True) == json.dumps(t.state_dict(),
                                                                     sort_keys=True)
    np.testing.assert_array_equal(ref.smoothed(n)[0], t.smoothed(n)[0])


@pytest.mark.parametrize("filt", ["ekf", "ukf"])
@pytest.mark.parametrize("model", ["cv", "ca"])
def test_compiled_agrees_with_numpy(filt, model):
    a = _anchors()
    meas, _ = _walk(K=3, N=40, seed=3)
    ep = _epochs(meas, a)
    rc = Tracker(a, model=model, filter=filt, sigma=SIGMA_M).step(ep)
    rn = Tracker(a, model=model, filter=filt, sigma=SIGMA_M, engine="numpy").step(ep)
    assert (rc.status == rn.status).all()
    # same equations, different summation order: agreement to rounding, amplified by
    # the recursion over 40 epochs (1e-9 m on coordinates of 10 m)
    for c in ("x", "y", "vx", "vy", "var_x", "var_y", "hpl"):
        np.testing.assert_allclose(rc[c], rn[c], rtol=1e-9, atol=1e-9)


def test_coasting_and_few_anchors():
    a = _anchors()
    meas, _ = _walk(K=1, N=30, seed=4)
    ep = _epochs(meas, a)
    v = ep.values.copy()
    v[10] = np.nan  # nothing heard: predicted
    v[12, 2:] = np.nan  # two anchors: still an update
    v[14, 1:] = np.nan  # one anchor
    ep2 = type(ep)(ep.time, ep.tag, v, ep.anchor_ids, ep.value, ep.line)
    rows = Tracker(a, sigma=SIGMA_M).step(ep2)
    assert rows.status[10] == "predicted" and rows.n_used[10] == 0
    assert rows.var_x[10] > rows.var_x[9]  # coasting: the covariance grows
    assert rows.status[12] == "ok" and rows.n_used[12] == 2
    assert rows.status[14] == "ok" and rows.n_used[14] == 1
    assert rows.var_x[12] < rows.var_x[12] + 1 and np.isfinite(rows.x).all()


def test_first_epochs_without_fix_keep_a_row():
    a = _anchors()
    meas, _ = _walk(K=1, N=10, seed=5)
    ep = _epochs(meas, a)
    v = ep.values.copy()
    v[0, 2:] = np.nan  # two anchors: no fix to start from
    v[1] = np.nan
    ep2 = type(ep)(ep.time, ep.tag, v, ep.anchor_ids, ep.value, ep.line)
    rows = Tracker(a, sigma=SIGMA_M, init_window_s=0.0).step(ep2)
    assert len(rows) == 10
    assert rows.status[0] == "insufficient_anchors" and np.isnan(rows.x[0])
    assert rows.status[1] == "invalid_measurement"
    assert rows.status[2] == "ok" and np.isfinite(rows.x[2])
    # asynchronous ranges: one anchor per epoch, the start combines the last second's
    v = np.full_like(ep.values, np.nan)
    v[np.arange(10), np.arange(10) % 6] = ep.values[np.arange(10), np.arange(10) % 6]
    ep3 = type(ep)(ep.time, ep.tag, v, ep.anchor_ids, ep.value, ep.line)
    rows = Tracker(a, sigma=SIGMA_M, init_window_s=1.0).step(ep3)
    assert list(rows.status[:2]) == ["insufficient_anchors"] * 2  # 1, then 2 anchors
    # 3 anchors within 1 s start it: redundancy 1, so the start row says what its
    # protected snapshot says, low_redundancy (it said ok; the track review)
    assert rows.status[2] == "low_redundancy" and rows.n_used[2] == 3
    assert (rows.status[3:] == "ok").all() and (rows.n_used[3:] == 1).all()


def test_link_step_is_held_out_and_readmitted_with_its_offset():
    a = _anchors()
    meas, truth = _walk(K=1, N=120, seed=6)
    ep = _epochs(meas, a)
    v = ep.values.copy()
    v[40:, 0] += 2.0  # anchor A0 reads 2 m long from epoch 40 on (a moved reflector)
    ep2 = type(ep)(ep.time, ep.tag, v, ep.anchor_ids, ep.value, ep.line)
    trk = Tracker(a, sigma=SIGMA_M, cusum_h=10.0)
    rows = trk.step(ep2)
    held = rows.excluded.str.contains("A0").to_numpy()
    assert held[40:60].any() and not held[100:].any()
    bias = trk.state_dict()["tags"]["tag0"]["bias"][0]
    # offset: mean of readmit_samples residuals of sigma ~0.1 m (plus the prediction's own
    # error): within 5 sigma / sqrt(6) + prediction error ~0.2 m
    assert abs(bias - 2.0) < 0.3
    e = _errors(rows, truth)
    assert np.sqrt(np.mean(e[100:] ** 2)) < 2 * SIGMA_M



@pytest.mark.parametrize("engine", ["compiled", "numpy"])
def test_link_offsets_stay_on_a_minority_of_the_links(engine):
    """The track review's walk (2026-12-06): a tag circling inside four corner anchors,
    0.3 m noise, and every 20 s each link has a 25 % chance of a +U(0, 3) m bias for the
    next 20 s.  With ``cusum_h=10`` each held link's offset, measured against the filter's
    own prediction, soaked up the filter's error; offsets came to stand on all four links
    (-10 to +5 m), the track drifted 6-12 m off with every test passing (RMS 6.45 m,
    75 % of rows beyond hpl, against 1.12 m without the detector).  A link whose offset
    is in force now counts as stepping in the ``moved`` rule (a majority stepping: the
    holds and offsets go), and a re-start clears them: RMS 1.28 m (max 3.7 m), and at no
    epoch do offsets stand on more than a minority (one of four) of the links."""
    rng = np.random.default_rng(1)
    a = pd.DataFrame({"anchor": [f"A{i}" for i in range(4)], "x": [0.0, 20.0, 20.0, 0.0],
                      "y": [0.0, 0.0, 20.0, 20.0]})
    xy = a[["x", "y"]].to_numpy()
    t = np.arange(1200) * 0.5
    th = 2 * np.pi * t / 120
    p = np.column_stack((10 + 6 * np.cos(th), 10 + 6 * np.sin(th)))
    r = np.linalg.norm(p[:, None] - xy[None], axis=2) + rng.normal(0.0, 0.3, (1200, 4))
    b = np.zeros(4)
    for k in range(1200):
        if k % 40 == 0:
            b = np.where(rng.random(4) < 0.25, 3 * rng.random(4), 0.0)
        r[k] += b
    meas = pd.DataFrame({"time": np.repeat(t, 4), "tag": "W",
                         "anchor": np.tile(a["anchor"], 1200), "range": r.ravel()})
    trk = Tracker(a, sigma=0.3, cusum_h=10.0, engine=engine)
    most = 0
    rows = []
    for k in range(0, 1200, 100):  # (the state between blocks: the offsets in force)
        block = meas[(meas["time"] >= t[k]) & (meas["time"] < t[k] + 50.0)]
        rows.append(trk.step(_epochs(block, a)))
        most = max(most, int(np.count_nonzero(trk.state_dict()["tags"]["W"]["bias"])))
    rows = pd.concat(rows, ignore_index=True)
    e = np.hypot(*(rows[["x", "y"]].to_numpy() - p).T)
    assert np.sqrt(np.mean(e**2)) < 1.5  # 1.28 measured; 6.45 before, 1.12 without
    assert e.max() < 5.0  # 3.70 measured; 11.7 before
    assert most <= 1

def test_divergence_restarts_from_a_fix():
    a = _anchors()
    meas, truth = _walk(K=1, N=80, seed=7)
    ep = _epochs(meas, a)
    xy = a[["x", "y"]].to_numpy()
    truth = truth.copy()
    # from epoch 40 the tag is 6 m away (a teleport the motion model cannot follow)
    p = truth[["x", "y"]].to_numpy().copy()
    p[40:] += [6.0, 0.0]
    truth[["x", "y"]] = p
    v = np.linalg.norm(p[:, None] - xy[None], axis=2)
    ep2 = type(ep)(ep.time, ep.tag, v, ep.anchor_ids, ep.value, ep.line)
    # IGG-III rejects every range of the jumped tag: only a re-start can recover (Huber
    # would follow the jump by itself)
    rows = Tracker(a, sigma=SIGMA_M, weight="igg3").step(ep2)
    assert rows.reinit.iloc[-1] >= 1
    assert _errors(rows.iloc[60:], truth).max() < 0.05


def test_rts_matches_filterpy():
    filterpy = pytest.importorskip("filterpy.kalman")
    from robustloc.filters.motion import ConstantVelocity

    rng = np.random.default_rng(8)
    cv = ConstantVelocity(q=0.3)
    F, Q = cv.FQ(1.0)
    H = np.eye(2, 4)
    R = np.eye(2) * 0.5
    kf = filterpy.KalmanFilter(dim_x=4, dim_z=2)
    kf.F, kf.Q, kf.H, kf.R = F, Q, H, R
    kf.x, kf.P = np.zeros(4), np.eye(4)
    xs, Ps, xps, Pps = [], [], [], []
    for k in range(30):
        kf.predict()
        xps.append(kf.x.copy())
        Pps.append(kf.P.copy())
        kf.update(rng.normal(0, 1, 2) + [k, 0.5 * k])
        xs.append(kf.x.copy())
        Ps.append(kf.P.copy())
    xs, Ps = np.array(xs), np.array(Ps)
    ref_x, ref_P, _, _ = kf.rts_smoother(xs, Ps, [F] * 30, [Q] * 30)
    sx, sP = rts_segment(xs, Ps, np.array(xps), np.array(Pps), np.array([F] * 30))
    np.testing.assert_allclose(sx, ref_x, rtol=1e-10, atol=1e-10)
    np.testing.assert_allclose(sP, ref_P, rtol=1e-10, atol=1e-10)
    # fixed lag >= length equals fixed interval; lag 0 is the filter
    lx, _ = rts_segment(xs, Ps, np.array(xps), np.array(Pps), np.array([F] * 30), lag=40)
    np.testing.assert_allclose(lx, ref_x, rtol=1e-10, atol=1e-10)
    l0, _ = rts_segment(xs, Ps, np.array(xps), np.array(Pps), np.array([F] * 30), lag=0)
    np.testing.assert_array_equal(l0, xs)


def _cli(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "robustloc.cli", *args], capture_output=True,
                          text=True)


def test_command_writes_a_track_that_evaluate_reads(tmp_path):
    a = _anchors()
    meas, truth = _walk(K=2, N=30, seed=9)
    a.to_csv(tmp_path / "a.csv", index=False)
    meas.to_csv(tmp_path / "m.csv", index=False)
    truth.to_csv(tmp_path / "t.csv", index=False)
    for extra in ([], ["--smooth"], ["--fixed-lag", "3"], ["--model", "static"]):
        r = _cli("track", str(tmp_path / "m.csv"), "--anchors", str(tmp_path / "a.csv"),
                 "-o", str(tmp_path / "trk.csv"), "--sigma", "0.1", "--quiet", *extra)
        assert r.returncode == 0, r.stderr
        out = pd.read_csv(tmp_path / "trk.csv")
        assert len(out) == 60
        for c in ("time", "tag", "x", "y", "vx", "vy", "status", "var_x", "var_y", "hpl"):
            assert c in out.columns
        r = _cli("evaluate", str(tmp_path / "trk.csv"), "--truth", str(tmp_path / "t.csv"),
                 "--json")
        assert r.returncode == 0, r.stderr
        rec = json.loads(r.stdout)["rows"]
        assert any(x["tag"] == "all" and x["n"] == 60 for x in rec)


def test_command_summary_gives_the_usable_rows_protection_levels(tmp_path):
    """``track --json``: the hpl histogram counts every usable row once, streamed in
    small chunks or smoothed, and the text summary states its median."""
    from robustloc import status as st
    from robustloc.pipelines.locate import hpl_counts

    a = _anchors()
    meas, _ = _walk(K=2, N=30, seed=9)
    a.to_csv(tmp_path / "a.csv", index=False)
    meas.to_csv(tmp_path / "m.csv", index=False)
    for extra in (["--chunk-rows", "17"], ["--smooth"]):
        r = _cli("track", str(tmp_path / "m.csv"), "--anchors", str(tmp_path / "a.csv"),
                 "-o", str(tmp_path / "trk.csv"), "--sigma", "0.1", "--json", *extra)
        assert r.returncode == 0, r.stderr
        (hist,) = json.loads(r.stdout)["hpl_histogram"].values()
        out = pd.read_csv(tmp_path / "trk.csv")
        want: dict = {}
        hpl_counts(out["hpl"].to_numpy(float), out["status"].isin(st.USABLE).to_numpy(), want)
        assert hist == want and sum(hist.values()) == out["status"].isin(st.USABLE).sum()
    r = _cli("track", str(tmp_path / "m.csv"), "--anchors", str(tmp_path / "a.csv"),
             "-o", str(tmp_path / "trk.csv"), "--sigma", "0.1")
    assert r.returncode == 0 and "hpl of the" in r.stdout and "usable rows" in r.stdout
    # --quiet: no progress bar and no text summary (as locate; it printed the summary)
    r = _cli("track", str(tmp_path / "m.csv"), "--anchors", str(tmp_path / "a.csv"),
             "-o", str(tmp_path / "trk.csv"), "--sigma", "0.1", "--quiet")
    assert r.returncode == 0 and r.stdout == "" and "epochs" not in r.stderr


def test_command_bad_input(tmp_path):
    a = _anchors()
    a.to_csv(tmp_path / "a.csv", index=False)
    (tmp_path / "m.csv").write_text("time,tag,anchor,range\n0,t,A0,1.0\n0,t,NOPE,2.0\n")
    r = _cli("track", str(tmp_path / "m.csv"), "--anchors", str(tmp_path / "a.csv"),
             "-o", str(tmp_path / "o.csv"))
    assert r.returncode == 2 and "error:" in r.stderr and "m.csv:3" in r.stderr


@pytest.mark.parametrize("extra", [["--smooth"], ["--fixed-lag", "4"]])
def test_smoothed_track_does_not_depend_on_chunks_or_other_tags(tmp_path, extra):
    # the smoother once indexed the recorded steps by their row within one block, so a
    # log read in several blocks smoothed later rows with earlier blocks' states
    from robustloc.cli import main

    a = _anchors()
    meas, _ = _walk(K=3, N=40, seed=4)
    a.to_csv(tmp_path / "a.csv", index=False)
    meas.to_csv(tmp_path / "m.csv", index=False)
    outs = []
    for chunk in ("1000000", "50"):  # one block, or many
        o = tmp_path / f"trk-{chunk}.parquet"
        assert main(["track", str(tmp_path / "m.csv"), "--anchors", str(tmp_path / "a.csv"),
                     "-o", str(o), "--sigma", "0.1", "--quiet", "--chunk-rows", chunk,
                     *extra]) == 0
        outs.append(pd.read_parquet(o))
    pd.testing.assert_frame_equal(outs[0], outs[1], check_exact=True)
    for tag, g in meas.groupby("tag"):  # a tag's track is its own: the same alone
        g.to_csv(tmp_path / "one.csv", index=False)
        o = tmp_path / "one.parquet"
        assert main(["track", str(tmp_path / "one.csv"), "--anchors", str(tmp_path / "a.csv"),
                     "-o", str(o), "--sigma", "0.1", "--quiet", "--chunk-rows", "50",
                     *extra]) == 0
        mine = outs[1][outs[1]["tag"].astype(str) == str(tag)].reset_index(drop=True)
        pd.testing.assert_frame_equal(pd.read_parquet(o), mine, check_exact=True)


# --------------------------------------------------------------------------- engines
_FLOAT_COLUMNS = ("x", "y", "vx", "vy", "var_x", "var_y", "cov_xy", "var_vx", "var_vy", "hpl",
                  "nis", "noise_scale")


def _assert_engines_agree(a: pd.DataFrame, kw: dict, epochs_list: list) -> pd.DataFrame:
    """Run the compiled and the NumPy engine on the same epochs; every row must agree."""
    out = {}
    for eng in ("compiled", "numpy"):
        trk = Tracker(a, engine=eng, **{"sigma": SIGMA_M, **kw})
        out[eng] = pd.concat([trk.step(e) for e in epochs_list], ignore_index=True)
    rc, rn = out["compiled"], out["numpy"]
    for c in ("time", "tag", "method", "status", "n_used", "reinit", "excluded"):
        assert (rc[c] == rn[c]).all(), c
    # the same formulas in another summation order (the kernel sums over links in order,
    # NumPy pairwise): agreement to rounding amplified by the recursion, 1e-9 m on
    # coordinates of 10 m (and 1e-9 relative on the NIS of outliers, ~1e4)
    assert list(rc.columns) == list(rn.columns)
    offset = ("range_offset", "var_range_offset") if "range_offset" in rc else ()
    for c in _FLOAT_COLUMNS + offset:
        np.testing.assert_allclose(rc[c], rn[c], rtol=1e-9, atol=1e-9, err_msg=c)
    return rc


def _bad_epochs(seed: int, K: int, M: int, N: int, p_out: float, p_miss: float,
                step_m: float):
    """Ranges of ``K`` walking tags with outliers (+1..5 m), missing ranges, a link step of
    ``step_m`` on anchor 0 from the middle on and a 6 m jump of tag 0 at 3/4."""
    a = _anchors(M)
    meas, _ = _walk(K=K, N=N, seed=seed, anchors=a)
    ep = _epochs(meas, a)
    rng = np.random.default_rng(seed)
    v = ep.values.copy()
    v += np.where(rng.random(v.shape) < p_out, rng.uniform(1.0, 5.0, v.shape), 0.0)
    v[rng.random(v.shape) < p_miss] = np.nan
    later = ep.time >= ep.time.max() / 2
    v[later, 0] += step_m
    jump = (ep.time >= 0.75 * ep.time.max()) & (ep.tag == "tag0")
    xy = a[["x", "y"]].to_numpy()
    v[jump] += 0.5 * np.linalg.norm(xy[None] - xy[None, :1], axis=2)  # an implausible jump
    return a, type(ep)(ep.time, ep.tag, v, ep.anchor_ids, ep.value, ep.line)


@pytest.mark.parametrize("filt", ["ekf", "ukf"])
@pytest.mark.parametrize("offsets", ["", "range_offset", "link_offsets"])
def test_engines_agree_with_holds_outliers_and_restarts(filt, offsets):
    a, ep = _bad_epochs(seed=11, K=3, M=8, N=60, p_out=0.05, p_miss=0.05, step_m=2.0)
    kw = {"filter": filt, "cusum_h": 6.0, "weight": "igg3", "max_bad_epochs": 2,
          **({offsets: True} if offsets else {})}
    rows = _assert_engines_agree(a, kw, [ep])
    # the workload reaches the paths the kernel covers: holds, rejected outliers,
    # suspicious epochs that fail (re-starts), coasting is covered by the next test
    assert rows.excluded.str.contains("A0").any()
    assert (rows.status == "fault_excluded").any()
    assert rows.reinit.max() >= 1


@pytest.mark.parametrize("offsets", ["", "range_offset", "link_offsets"])
def test_engines_agree_one_epoch_at_a_time_with_coasting(offsets):
    a, ep = _bad_epochs(seed=12, K=2, M=6, N=30, p_out=0.1, p_miss=0.2, step_m=0.0)
    v = ep.values.copy()
    v[10:14] = np.nan  # nothing heard: predicted rows
    ep = type(ep)(ep.time, ep.tag, v, ep.anchor_ids, ep.value, ep.line)
    parts = [type(ep)(ep.time[i:i + 1], ep.tag[i:i + 1], ep.values[i:i + 1], ep.anchor_ids,
                      ep.value, ep.line[i:i + 1]) for i in range(ep.n_epochs)]
    rows = _assert_engines_agree(a, {"model": "ca", "filter": "ukf",
                                     **({offsets: True} if offsets else {})}, parts)
    assert (rows.status == "predicted").any()


@pytest.mark.parametrize("filt", ["ekf", "ukf"])
@pytest.mark.parametrize("offsets", ["", "range_offset"])
def test_engines_agree_on_a_site_of_many_anchors_each_tag_hearing_a_few(filt, offsets):
    """A site of many anchors, each tag hearing a few: the compiled round works on the
    anchors heard (``filters._compiled.cholesky_at``, a diagonal ``R``); the NumPy
    engine on every anchor's row with the unheard ones masked.  40 anchors that no tag
    hears, interleaved with the 8 that are: every row agrees (as
    :func:`_assert_engines_agree`).  The workload has outliers, a link step (holds),
    re-starts and, with the UKF, the linearized gain of its hpl; the one-exclusion test
    of a failed epoch runs too.  (Rows with and without the 40 anchors are not compared:
    the robust start's minimal subsets and rescue grid are drawn over the whole site.)"""
    a, ep = _bad_epochs(seed=11, K=3, M=8, N=60, p_out=0.05, p_miss=0.05, step_m=2.0)
    kw = {"filter": filt, "cusum_h": 6.0, "weight": "igg3", "max_bad_epochs": 2,
          **({offsets: True} if offsets else {})}
    rng = np.random.default_rng(5)
    extra = pd.DataFrame({"anchor": [f"X{i}" for i in range(40)],
                          "x": rng.uniform(-2, 22, 40), "y": rng.uniform(-2, 22, 40)})
    order = np.r_[0, 8, 9, 10, 1, 11:24, 2, 3, 24:30, 4, 5, 6, 30:48, 7]  # interleaved
    big = pd.concat([a, extra], ignore_index=True).iloc[order].reset_index(drop=True)
    cols = {name: j for j, name in enumerate(big["anchor"])}
    v = np.full((ep.n_epochs, len(big)), np.nan)
    for i, name in enumerate(a["anchor"]):
        v[:, cols[name]] = ep.values[:, i]
    wide = type(ep)(ep.time, ep.tag, v, tuple(big["anchor"]), ep.value, ep.line)
    rows = _assert_engines_agree(big, kw, [wide])
    assert (rows.status == "fault_excluded").any() and rows.reinit.max() >= 1
    assert rows.excluded.str.contains("A0").any()


@settings(max_examples=16, deadline=None)
@given(seed=hst.integers(0, 10_000), K=hst.integers(1, 5), M=hst.integers(3, 9),
       filt=hst.sampled_from(["ekf", "ukf"]), model=hst.sampled_from(["cv", "ca"]),
       weight=hst.sampled_from(["huber", "igg3", "hampel"]),
       cusum_h=hst.sampled_from([None, 4.0, 10.0]), p_out=hst.sampled_from([0.0, 0.05, 0.2]),
       p_miss=hst.sampled_from([0.0, 0.1, 0.4]), step_m=hst.sampled_from([0.0, 1.0, 3.0]),
       offsets=hst.sampled_from(["", "range_offset", "link_offsets"]))
def test_engines_agree_on_random_workloads(seed, K, M, filt, model, weight, cusum_h, p_out,
                                           p_miss, step_m, offsets):
    a, ep = _bad_epochs(seed, K, M, 25, p_out, p_miss, step_m)
    kw = {"filter": filt, "model": model, "weight": weight, "cusum_h": cusum_h,
          "readmit_samples": 3, **({offsets: True} if offsets else {})}
    _assert_engines_agree(a, kw, [ep])


def test_engines_agree_on_the_recorded_moments_for_smoothing():
    a, ep = _bad_epochs(seed=13, K=2, M=6, N=30, p_out=0.05, p_miss=0.05, step_m=0.0)
    sm = {}
    for eng in ("compiled", "numpy"):
        trk = Tracker(a, sigma=SIGMA_M, engine=eng, record=True)
        trk.step(ep)
        sm[eng] = trk.smoothed(ep.n_epochs)
    for u, v in zip(sm["compiled"], sm["numpy"]):
        np.testing.assert_allclose(u, v, rtol=1e-9, atol=1e-9)  # as above: rounding


@pytest.mark.parametrize("domain", ["range", "rssi"])
@pytest.mark.parametrize("link_offsets", [False, True])
def test_engines_agree_on_rssi_with_holds(domain, link_offsets):
    """RSSI (log-distance, A = -40 dBm, n = 2): the compiled round runs the range domain
    (held links' offsets in dB through the path-loss model; with ``link_offsets`` each
    link's offset state scales its range), the dB domain is NumPy only."""
    a = _anchors(6).assign(A=-40.0, n=2.0)
    meas, _ = _walk(K=2, N=60, seed=14, anchors=a)
    rng = np.random.default_rng(14)
    d = meas["range"].to_numpy()
    rssi = -40.0 - 20.0 * np.log10(d) + rng.normal(0.0, 2.0, d.size)
    rssi -= np.where(rng.random(d.size) < 0.05, rng.uniform(5, 15, d.size), 0.0)  # fades
    rssi[(meas["anchor"] == "A0").to_numpy() & (meas["time"] >= 15).to_numpy()] -= 8.0
    meas = meas.drop(columns="range").assign(rssi=rssi)
    ep = to_epochs(meas, a["anchor"])
    assert ep.value == "rssi"
    rows = _assert_engines_agree(a, {"cusum_h": 5.0, "domain": domain, "sigma": 2.0,
                                     "link_offsets": link_offsets}, [ep])
    assert rows.excluded.str.contains("A0").any()


@pytest.mark.filterwarnings("ignore:invalid value:RuntimeWarning")  # sqrt of HPH < 0
def test_round_the_kernel_cannot_do_falls_back_to_numpy():
    """A covariance that is not positive definite (here loaded from a state) stops the
    compiled UKF's sigma points (NOT_PD): the round runs on the NumPy engine instead,
    which takes the eigen-clipped square root -- same rows as the NumPy engine."""
    a = _anchors()
    meas, _ = _walk(K=2, N=20, seed=15)
    ep = _epochs(meas, a)
    h = ep.n_epochs // 2

    def cut(s):
        return type(ep)(ep.time[s], ep.tag[s], ep.values[s], ep.anchor_ids, ep.value,
                        ep.line[s])

    trk = Tracker(a, filter="ukf", sigma=SIGMA_M)
    trk.step(cut(slice(0, h)))
    saved = json.loads(json.dumps(trk.state_dict()))
    P = np.array(saved["tags"]["tag0"]["P"]).reshape(4, 4)
    P[2, 2] = -1.0  # indefinite
    saved["tags"]["tag0"]["P"] = P.ravel().tolist()
    rows, calls = {}, []
    for eng in ("compiled", "numpy"):
        t2 = Tracker(a, filter="ukf", sigma=SIGMA_M, engine=eng)
        t2.load_state_dict({**saved, "settings": {**saved["settings"], "engine": eng}})
        if eng == "compiled":
            t2._filter_numpy = lambda *args, f=t2._filter_numpy: calls.append(1) or f(*args)
        rows[eng] = t2.step(cut(slice(h, None)))
    assert calls  # the fallback ran
    pd.testing.assert_frame_equal(rows["compiled"], rows["numpy"], rtol=1e-9, atol=1e-9)


@settings(max_examples=40, deadline=None)
@given(seed=hst.integers(0, 2**31 - 1), M=hst.integers(2, 9),
       offsets=hst.sampled_from(["", "common", "links"]))
def test_one_fault_explains_is_the_global_test_after_one_exclusion(seed, M, offsets):
    """Data snooping with one exclusion, checked by brute force: ``y^T S^-1 y - w_i^2``
    equals the quadratic form of the innovations with component ``i`` deleted (the Schur
    complement), and the compiled kernel decides as the NumPy reference.  Decisions within
    rounding (1e-9 relative) of a critical value are not compared.  ``offsets``: a fifth
    state, the range offset (a last column of ones in ``H``), or one state per link (row
    ``i`` has the entry ``hb_i``, any sign, in column ``4 + i``: the links' offsets of RSSI
    turned into ranges)."""
    from scipy.stats import chi2

    from robustloc.tracking import _compiled
    from robustloc.tracking.tracker import one_fault_explains

    rng = np.random.default_rng(seed)
    K = 30
    n = {"": 4, "common": 5, "links": 4 + M}[offsets]
    H = np.zeros((K, M, n))
    ang = rng.uniform(0, 2 * np.pi, (K, M))
    H[:, :, 0], H[:, :, 1] = np.cos(ang), np.sin(ang)
    hb, oc = np.zeros((K, M)), np.full(M, -1, dtype=np.int64)  # the kernel's offset entries
    if offsets == "common":
        hb[:], oc[:] = 1.0, 4
        H[:, :, 4] = 1.0
    elif offsets == "links":
        hb, oc = rng.uniform(-1.5, 0.5, (K, M)), 4 + np.arange(M)
        H[:, np.arange(M), oc] = hb
    B = rng.normal(0, 1, (K, n, n))
    Pp = B @ np.swapaxes(B, 1, 2) * rng.uniform(1e-3, 1.0, (K, 1, 1)) + 1e-6 * np.eye(n)
    Rd = rng.uniform(0.005, 0.5, (K, M))
    avail = rng.random((K, M)) < 0.85
    S = H @ Pp @ np.swapaxes(H, 1, 2) + Rd[:, :, None] * np.eye(M)
    y = np.einsum("kij,kj->ki", np.linalg.cholesky(S), rng.normal(0, 1, (K, M)))
    bad = rng.random(K) < 0.6  # one gross error
    j = rng.integers(0, M, K)
    y[bad, j[bad]] += rng.choice([-1, 1], bad.sum()) * rng.uniform(0, 30, bad.sum()) * np.sqrt(
        Rd[bad, j[bad]])
    two = bad & (rng.random(K) < 0.4)  # and a second one
    j2 = (j + 1) % M
    y[two, j2[two]] += 20.0 * np.sqrt(Rd[two, j2[two]])
    w2c = float(chi2.isf(1e-3, 1))
    crit = rng.uniform(0.5, 20.0, K)
    got = one_fault_explains(H, Pp, Rd, y, avail, w2c, crit)
    # brute force: delete each available component, quadratic forms of the rest
    margin = np.zeros(K, dtype=bool)
    for k in range(K):
        av = np.flatnonzero(avail[k])
        Sk = S[k][np.ix_(av, av)]
        yk = y[k, av]
        q = yk @ np.linalg.solve(Sk, yk)
        best, rest = 0.0, np.inf
        for t in range(av.size):
            keep = np.delete(np.arange(av.size), t)
            qr = yk[keep] @ np.linalg.solve(Sk[np.ix_(keep, keep)], yk[keep]) if keep.size else 0.0
            if q - qr > best:
                best, rest = q - qr, qr
        want = best > w2c and rest <= crit[k]
        margin[k] = (abs(best - w2c) < 1e-9 * max(w2c, best)
                     or abs(rest - crit[k]) < 1e-9 * max(q, 1.0))
        if not margin[k]:
            assert got[k] == want, k
        # the compiled kernel (position rows of H, as the tracker's round)
        Ssn, Lsn = np.empty((M, M)), np.empty((M, M))
        scratch = [np.empty(M) for _ in range(3)]
        comp = _compiled.one_fault_explains(
            M, np.ascontiguousarray(H[k, :, :2]), hb[k], oc, Pp[k], Rd[k], y[k], avail[k],
            w2c, crit[k], Ssn, Lsn, *scratch, np.empty(M, np.int64))
        if not margin[k]:
            assert (comp >= 0) == want, k
            # the component named is the one whose exclusion explains it (the largest w)
            _, at = one_fault_explains(H[k:k + 1], Pp[k:k + 1], Rd[k:k + 1], y[k:k + 1],
                                       avail[k:k + 1], w2c, crit[k:k + 1], return_index=True)
            assert at[0] == comp, k
    assert got.any() and not got.all()  # both outcomes are exercised


class _EagerChecks(Tracker):
    """The reference divergence counter: every suspicious epoch checked against its robust
    snapshot fix in its own round (the tracker before the checks were deferred)."""

    def _count_bad(self, sl, xn, z, moved, sus, dof):
        fail = moved.copy()
        if sus.any():
            fail[sus] |= self._disagrees(xn[sus], None, z[sus])
        bad = np.where(fail, self._bad[sl] + 1, np.where(dof > 0, 0, self._bad[sl]))
        self._bad[sl] = bad
        return bad


@settings(max_examples=15, deadline=None)
@given(seed=hst.integers(0, 10_000), K=hst.integers(1, 6), M=hst.integers(4, 9),
       max_bad=hst.integers(1, 5), engine=hst.sampled_from(["compiled", "numpy"]),
       cusum_h=hst.sampled_from([None, 4.0]), p_out=hst.sampled_from([0.05, 0.2, 0.4]),
       chunks=hst.sampled_from([1, 3, 25]))
def test_deferred_snapshot_checks_equal_checking_every_round(seed, K, M, max_bad, engine,
                                                             cusum_h, p_out, chunks):
    """Deferring the snapshot checks (``Tracker._count_bad``) changes no output and no
    state: same rows, same divergence counters after every step, same re-starts, for any
    ``max_bad_epochs``, with the CUSUM's "moved" epochs, heavy outliers, a jumping tag,
    and the log fed in 1, 3 or 25 steps (pending checks carried from step to step, settled
    by ``state_dict``)."""
    a, ep = _bad_epochs(seed, K, M, 25, p_out, 0.1, 1.0)
    kw = {"sigma": SIGMA_M, "weight": "igg3", "cusum_h": cusum_h, "max_bad_epochs": max_bad,
          "engine": engine}
    cuts = np.array_split(np.arange(ep.n_epochs), chunks)
    parts = [type(ep)(ep.time[c], ep.tag[c], ep.values[c], ep.anchor_ids, ep.value,
                      ep.line[c]) for c in cuts if c.size]
    lazy, eager = Tracker(a, **kw), _EagerChecks(a, **kw)
    for i, part in enumerate(parts):
        pd.testing.assert_frame_equal(lazy.step(part), eager.step(part))
        if i % 2:  # every other step settles its pending checks; the others carry them on
            assert lazy.state_dict() == eager.state_dict()
            assert not lazy._p_on.any()
            np.testing.assert_array_equal(lazy._bad, eager._bad)
    assert lazy.state_dict() == eager.state_dict()


def test_deferred_checks_decide_a_restart_on_the_round_it_happens():
    """The jumping tag of ``test_divergence_restarts_from_a_fix`` with every epoch in one
    step: the counter must be resolved in the round where it can reach
    ``max_bad_epochs`` (not at the step's end), so the re-start happens at the same epoch
    as with checks in every round, and few checks are solved."""
    a = _anchors()
    meas, truth = _walk(K=1, N=80, seed=7)
    ep = _epochs(meas, a)
    xy = a[["x", "y"]].to_numpy()
    p = truth[["x", "y"]].to_numpy().copy()
    p[40:] += [6.0, 0.0]
    v = np.linalg.norm(p[:, None] - xy[None], axis=2)
    ep2 = type(ep)(ep.time, ep.tag, v, ep.anchor_ids, ep.value, ep.line)
    solved = []

    class Counting(Tracker):
        def _disagrees(self, x, P, z):
            solved.append(len(z))
            return super()._disagrees(x, P, z)

    lazy = Counting(a, sigma=SIGMA_M, weight="igg3").step(ep2)
    eager = _EagerChecks(a, sigma=SIGMA_M, weight="igg3").step(ep2)
    pd.testing.assert_frame_equal(lazy, eager)
    first = int(np.argmax(lazy.reinit.to_numpy() >= 1))
    assert 40 < first < 40 + 10  # re-started soon after the jump, as the eager one
    assert sum(solved) <= 10  # the jump's checks, once, not one solve per round


@pytest.mark.parametrize("engine", ["compiled", "numpy"])
def test_hpl_covers_the_mirror_of_collinear_anchors(engine, monkeypatch):
    """Four anchors within 0.3 m of the x axis, one tag walking 3 m beside them, ranges
    with 5 cm noise and the filter's sigma 0.3 m: the tag's mirror image across the
    anchors' line (found independently by scipy from the reflected position) fits every
    epoch's ranges within the test, so every row's bound reaches beyond it, where the
    filter's own bound (the check switched off) stays below the distance.  With anchors
    that span the plane the rows are exactly those without the check."""
    from scipy.optimize import least_squares

    line = pd.DataFrame({"anchor": list("ABCD"), "x": [0.0, 10.0, 20.0, 30.0],
                         "y": [0.0, 0.3, -0.3, 0.1]})
    a = line[["x", "y"]].to_numpy()
    rng = np.random.default_rng(1)
    N = 60
    t = np.arange(N) * 0.5
    p = np.column_stack((5.0 + 0.4 * t, np.full(N, -3.0)))
    r = np.linalg.norm(p[:, None] - a[None], axis=2) + rng.normal(0, 0.05, (N, 4))
    meas = pd.DataFrame({"time": np.repeat(t, 4), "tag": "T",
                         "anchor": np.tile(list("ABCD"), N), "range": r.ravel()})
    rows = Tracker(line, sigma=0.3, engine=engine).step(_epochs(meas, line))
    assert (rows["status"] == "ok").all()
    xy = rows[["x", "y"]].to_numpy()
    mirror = np.array([least_squares(lambda q, k=k: np.linalg.norm(q - a, axis=1) - r[k],
                                     xy[k] * [1.0, -1.0]).x for k in range(N)])
    assert np.all(mirror[:, 1] > 2.0)  # the second minimum, across the line
    dist = np.hypot(*(xy - mirror).T)
    monkeypatch.setattr(Tracker, "_cover_mirror", lambda self, *args: None)
    off = Tracker(line, sigma=0.3, engine=engine).step(_epochs(meas, line))
    # (the start row is bounded by its protected snapshot fix, whose bound covers the
    # mirror on its own: the check is about the filtered rows after it)
    assert off["hpl"].iloc[0] >= dist[0]
    assert np.all(off["hpl"].to_numpy()[1:] < dist[1:])
    # the bound: the row's own plus the distance to the mirror (the filter is unchanged)
    np.testing.assert_array_equal(rows[["x", "y"]].to_numpy(), off[["x", "y"]].to_numpy())
    assert np.all(rows["hpl"].to_numpy() >= dist)
    # (the check's Gauss-Newton refinement and scipy's trust region reach the same
    # minimum: scipy stops at relative steps of 1e-8, ~1e-7 m here; 8e-7 m measured)
    np.testing.assert_allclose((rows["hpl"] - off["hpl"])[1:], dist[1:], atol=1e-5)
    monkeypatch.undo()
    meas2, _ = _walk(K=2, N=40)
    spread = _anchors()
    with_check = Tracker(spread, sigma=SIGMA_M, engine=engine).step(_epochs(meas2, spread))
    monkeypatch.setattr(Tracker, "_cover_mirror", lambda self, *args: None)
    without = Tracker(spread, sigma=SIGMA_M, engine=engine).step(_epochs(meas2, spread))
    pd.testing.assert_frame_equal(with_check, without)


# --------------------------------------------------------------------------- lost filters
#: Five anchors around a tag standing at (3, 4): noise-free ranges, so the robust fix of
#: every epoch with three or more of them is (3, 4) to the solver's rounding.
_STILL_ANCHORS = pd.DataFrame({"anchor": ["A1", "A2", "A3", "A4", "A5"],
                               "x": [0.0, 10.0, 10.0, 0.0, 5.0],
                               "y": [0.0, 0.0, 10.0, 10.0, 12.0]})
_STILL_XY = (3.0, 4.0)


def _still_epochs(times: dict[str, list[float]], heard: dict[float, list[str]] | None = None,
                  at: dict[str, tuple[float, float]] | None = None) -> Epochs:
    """Epochs of tags standing still (at ``_STILL_XY``, or ``at[tag]``): noise-free ranges
    to ``_STILL_ANCHORS`` at each tag's ``times``; ``heard`` limits the anchors of the
    epochs at the given times."""
    heard, at = heard or {}, at or {}
    rows = []
    for tag, ts in times.items():
        px, py = at.get(tag, _STILL_XY)
        for t in ts:
            for a, x, y in _STILL_ANCHORS[["anchor", "x", "y"]].itertuples(index=False):
                if t not in heard or a in heard[t]:
                    rows.append((t, tag, a, float(np.hypot(px - x, py - y))))
    meas = pd.DataFrame(rows, columns=["time", "tag", "anchor", "range"])
    return to_epochs(meas, _STILL_ANCHORS["anchor"])


def _one_by_one(trk: Tracker, ep: Epochs) -> pd.DataFrame:
    """``trk`` stepped one epoch per call (as the live service does)."""
    return pd.concat([trk.step(type(ep)(ep.time[i:i + 1], ep.tag[i:i + 1], ep.values[i:i + 1],
                                        ep.anchor_ids, ep.value, ep.line[i:i + 1]))
                      for i in range(ep.n_epochs)], ignore_index=True)


def _assert_rows_equal(a: pd.DataFrame, b: pd.DataFrame, exact: bool) -> None:
    """Equal rows; ``exact=False`` allows the last bits of NumPy's UKF, whose sigma-point
    sums are one BLAS product over all tags of a round (their blocking depends on the
    round's size: 1e-15 m between one tag alone and two, measured, also without any
    jump)."""
    a, b = a.reset_index(drop=True), b.reset_index(drop=True)
    if exact:
        pd.testing.assert_frame_equal(a, b, check_exact=True)
    else:
        pd.testing.assert_frame_equal(a, b, check_exact=False, rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("model", ["cv", "ca", "static"])
@pytest.mark.parametrize("filt", ["ekf", "ukf"])
@pytest.mark.parametrize("engine", ["compiled", "numpy"])
def test_a_clock_jump_restarts_the_tag_from_its_fix(engine, filt, model):
    """Tag G's clock jumps ahead by 1e5, 1e7 or 1e9 s after three epochs (tag V beside it
    keeps time).  Over such a gap G's prediction is meaningless (position variance 5e19
    m^2 and more for ``cv``, ``q dt^4 / 4`` per axis; 2e10 m^2 for ``static``, ``q dt^2``):
    the innovation covariance of its update kept little or nothing of the ranges' 0.09
    m^2, and the update raised LinAlgError (losing V's epochs of the same call) or
    returned garbage.  Now G's filter is dropped before its update and G starts again
    from the epoch's fix: one row per epoch, stepping all at once or one epoch per call;
    V's rows are those of V alone; G's rows after the jump are usable, count one
    re-start, and are those of a freshly started tag (V's first rows).  Their distance to
    (3, 4): rounding for the EKF (noise-free ranges: the fix is exact and the innovations
    stay zero); within 2 cm for the UKF, whose sigma points lie 1.6-2.5 m from the tag
    after the first 1-s prediction, where a 5 m range curves by ``s^2 / (2 d)``: the
    weighted predicted range is biased by 0.1-0.15 m, and 0.9-1.0 cm of position error
    remain (measured) -- V, started afresh, has the same."""
    kw = {"engine": engine, "filter": filt, "model": model}
    # the compiled kernel's sums and NumPy's EKF do not depend on the other tags of a round
    exact = filt == "ekf" or (engine == "compiled" and model != "static")
    alone = Tracker(_STILL_ANCHORS, **kw).step(_still_epochs({"V": list(range(8))}))
    for gap in (1e5, 1e7, 1e9):
        g_times = [0.0, 1.0, 2.0] + [gap + k for k in range(1, 6)]
        ep = _still_epochs({"G": g_times, "V": list(range(8))})
        rows = Tracker(_STILL_ANCHORS, **kw).step(ep)
        _assert_rows_equal(rows, _one_by_one(Tracker(_STILL_ANCHORS, **kw), ep), exact)
        # one row per epoch, in the order of the epochs
        assert len(rows) == ep.n_epochs
        np.testing.assert_array_equal(rows["time"], ep.time)
        np.testing.assert_array_equal(rows["tag"].astype(str), ep.tag.astype(str))
        # the jump of G does not touch V
        _assert_rows_equal(rows[rows["tag"] == "V"], alone, exact)
        g = rows[rows["tag"] == "G"].reset_index(drop=True)
        before, after = g.iloc[:3], g.iloc[3:].reset_index(drop=True)
        assert (before["status"] == "ok").all() and (before["reinit"] == 0).all()
        assert (after["status"] == "ok").all(), after["status"].tolist()
        assert (after["reinit"] == 1).all()
        assert np.isfinite(after[["x", "y", "var_x", "var_y", "hpl"]].to_numpy()).all()
        err = np.hypot(after["x"] - _STILL_XY[0], after["y"] - _STILL_XY[1])
        assert err.max() <= (1e-9 if filt == "ekf" else 0.02), (gap, err.tolist())
        cols = ["x", "y", "vx", "vy", "status", "var_x", "var_y", "cov_xy", "var_vx",
                "var_vy", "hpl", "n_used", "nis", "noise_scale", "excluded"]
        _assert_rows_equal(after[cols], alone.iloc[:5][cols], exact)


@pytest.mark.parametrize("filt", ["ekf", "ukf"])
@pytest.mark.parametrize("engine", ["compiled", "numpy"])
def test_a_clock_that_restarts_restarts_the_tag_from_its_fix(engine, filt):
    """Tag G stands at (3, 4) for times 0..9 s, then its device restarts: the clock
    begins again at 0 and the tag stands at (7, 6) (the live service's re-base solves the
    new run after the old one, through the same tracker).  The filter predicted over
    ``dt = max(t - t_last, 0) = 0`` and kept the old position: the first row of the new
    run was 3.9 m off, and the filter took several epochs to get back (statuses
    ``fault_detected`` meanwhile).  Now G starts again from the epoch's fix: its new-run
    rows count one re-start and are those of a tag standing at (7, 6) from the start
    (noise-free ranges: within rounding for the EKF, 2 cm for the UKF as in
    :func:`test_a_clock_jump_restarts_the_tag_from_its_fix`)."""
    kw = {"engine": engine, "filter": filt}
    exact = filt == "ekf" or engine == "compiled"
    trk = Tracker(_STILL_ANCHORS, **kw)
    old = trk.step(_still_epochs({"G": [float(k) for k in range(10)]}))
    assert (old["status"] == "ok").all() and (old["reinit"] == 0).all()
    new_run = _still_epochs({"G": [float(k) for k in range(5)]}, at={"G": (7.0, 6.0)})
    rows = trk.step(new_run)
    assert (rows["status"] == "ok").all(), rows["status"].tolist()
    assert (rows["reinit"] == 1).all()
    err = np.hypot(rows["x"] - 7.0, rows["y"] - 6.0)
    assert err.max() <= (1e-9 if filt == "ekf" else 0.02), err.tolist()
    fresh = Tracker(_STILL_ANCHORS, **kw).step(new_run)
    cols = ["x", "y", "vx", "vy", "status", "var_x", "var_y", "cov_xy", "hpl", "n_used"]
    _assert_rows_equal(rows[cols], fresh[cols], exact)


def test_the_lost_prediction_rule_is_the_same_in_both_engines():
    """The bound of item 9 (``V > lost_pos_var`` and ``sqrt(eps) V >= r_min``; NaN is
    lost) in the compiled kernel and its NumPy twin, on both sides of each bound."""
    from robustloc.tracking import _compiled
    from robustloc.tracking.tracker import _SQRT_EPS, _prediction_lost

    assert _SQRT_EPS == _compiled.SQRT_EPS == 2.0**-26
    r = 0.09
    edge = r / _SQRT_EPS  # exact: a power of two times r
    cases = [(30.0, r, False),  # beyond lost_pos_var, but updates fine
             (20.0, 1e-12, False),  # R lost in rounding, but within lost_pos_var (item 5)
             (edge, r, True), (np.nextafter(edge, 0.0), r, False), (1e27, r, True),
             (1e27, np.inf, False),  # (no component: nothing to update)
             (np.nan, r, True), (np.inf, r, True), (1e27, np.nan, True)]
    v, rm, want = (np.array(c) for c in zip(*cases))
    np.testing.assert_array_equal(_prediction_lost(v, rm, 25.0), want.astype(bool))
    got = [_compiled.prediction_lost(a, b, 25.0) for a, b in zip(v, rm)]
    assert got == want.tolist()


@pytest.mark.parametrize("filt", ["ekf", "ukf"])
@pytest.mark.parametrize("engine", ["compiled", "numpy"])
def test_a_lost_tag_without_a_fix_gets_the_fix_status_until_it_has_one(engine, filt):
    """After G's clock jumps, its first epoch hears two anchors (no fix: the row says
    ``insufficient_anchors``, no position, and counts the re-start), the next, 0.5 s later,
    three others: with the two of the previous epoch (``init_window_s = 1``) G starts
    again at (3, 4); V is as alone."""
    kw = {"engine": engine, "filter": filt}
    jump = 1e7
    heard = {jump + 1.0: ["A1", "A2"], jump + 1.5: ["A3", "A4", "A5"]}
    ep = _still_epochs({"G": [0.0, 1.0, 2.0, jump + 1.0, jump + 1.5, jump + 2.5],
                        "V": list(range(6))}, heard)
    alone = Tracker(_STILL_ANCHORS, **kw).step(_still_epochs({"V": list(range(6))}))
    for rows in (Tracker(_STILL_ANCHORS, **kw).step(ep),
                 _one_by_one(Tracker(_STILL_ANCHORS, **kw), ep)):
        assert len(rows) == ep.n_epochs
        g = rows[rows["tag"] == "G"].reset_index(drop=True)
        assert g["status"].tolist() == ["ok"] * 3 + ["insufficient_anchors", "ok", "ok"]
        assert g["reinit"].tolist() == [0, 0, 0, 1, 1, 1]
        assert np.isnan(g.loc[3, ["x", "y"]].astype(float)).all()
        np.testing.assert_allclose(g.loc[4, ["x", "y"]].astype(float), _STILL_XY, atol=1e-9)
        _assert_rows_equal(rows[rows["tag"] == "V"], alone,
                           exact=engine == "compiled" or filt == "ekf")


@pytest.mark.filterwarnings("ignore:invalid value:RuntimeWarning")  # sqrt of S_ii < 0
@pytest.mark.parametrize("filt", ["ekf", "ukf"])
@pytest.mark.parametrize("engine", ["compiled", "numpy"])
def test_a_tag_whose_filter_breaks_starts_again_and_the_others_go_on(engine, filt):
    """A saved state whose covariance of G is broken -- a null (NaN) position variance,
    or a negative velocity variance -- no longer leaves G ``predicted`` for ever (NaN) or
    with negative variances (the update's arithmetic on an indefinite ``P``): its filter
    is dropped at the next epoch and G starts again from that epoch's fix; V goes on as
    if G were fine.  (To rounding with the compiled engine: a round its kernel cannot do
    -- G's indefinite ``S`` stops a Cholesky factor -- goes to the NumPy engine whole, so
    V's row of that round is NumPy's; exact with NumPy's EKF.)"""
    kw = {"engine": engine, "filter": filt}
    first = _still_epochs({"G": [0.0, 1.0, 2.0], "V": [0.0, 1.0, 2.0]})
    later = _still_epochs({"G": [3.0, 4.0, 5.0], "V": [3.0, 4.0, 5.0]})
    trk = Tracker(_STILL_ANCHORS, **kw)
    trk.step(first)
    saved = json.loads(json.dumps(trk.state_dict()))
    reference = Tracker(_STILL_ANCHORS, **kw)
    reference.load_state_dict(saved)
    ref = reference.step(later)
    for i, value in ((0, None), (10, -1.0)):  # P[0, 0] null, P[2, 2] = -1
        P = list(saved["tags"]["G"]["P"])
        P[i] = value
        broken = Tracker(_STILL_ANCHORS, **kw)
        broken.load_state_dict({**saved, "tags": {**saved["tags"],
                                                  "G": {**saved["tags"]["G"], "P": P}}})
        rows = broken.step(later)
        g = rows[rows["tag"] == "G"]
        assert (g["status"] == "ok").all() and (g["reinit"] == 1).all()
        assert (g[["var_x", "var_y", "var_vx", "var_vy"]].to_numpy() >= 0).all()
        err = np.hypot(g["x"] - _STILL_XY[0], g["y"] - _STILL_XY[1])
        assert err.max() <= (1e-9 if filt == "ekf" else 0.02)  # as in the clock jump test
        _assert_rows_equal(rows[rows["tag"] == "V"], ref[ref["tag"] == "V"],
                           exact=engine == "numpy" and filt == "ekf")


def test_a_singular_update_of_one_tag_does_not_stop_the_others(monkeypatch):
    """Whatever makes one tag's update raise LinAlgError (here injected: the update of
    any batch holding G, which stands at x = 6 beside V at x = 3; the NumPy engine solves
    both in one batch), the round is redone tag by tag: G starts again from each epoch's
    fix (one re-start per epoch, usable rows at its place), V's rows are those of V
    alone."""
    from robustloc.tracking import tracker as tracker_mod

    real = tracker_mod.update_ekf

    def singular_for_g(x, *args, **kwargs):
        if np.any(x[:, 0] > 5.0):
            raise np.linalg.LinAlgError("Singular matrix")
        return real(x, *args, **kwargs)

    monkeypatch.setattr(tracker_mod, "update_ekf", singular_for_g)
    ep = _still_epochs({"G": list(range(6)), "V": list(range(6))}, at={"G": (6.0, 5.0)})
    alone = Tracker(_STILL_ANCHORS, engine="numpy").step(_still_epochs({"V": list(range(6))}))
    rows = Tracker(_STILL_ANCHORS, engine="numpy").step(ep)
    assert len(rows) == ep.n_epochs
    g = rows[rows["tag"] == "G"].reset_index(drop=True)
    assert (g["status"] == "ok").all()
    assert g["reinit"].tolist() == [0, 1, 2, 3, 4, 5]
    np.testing.assert_allclose(g[["x", "y"]].to_numpy(float), [[6.0, 5.0]] * 6, atol=1e-9)
    pd.testing.assert_frame_equal(rows[rows["tag"] == "V"].reset_index(drop=True), alone)


@pytest.mark.parametrize("engine", ["compiled", "numpy"])
def test_an_unexplained_test_failure_is_fault_detected_with_a_wider_hpl(engine):
    """Two ranges of one epoch 3 m long: the innovations' global test fails and no single
    exclusion explains it.  The row was `ok` with its usual bound (the helper's report:
    `ok` rows beyond their hpl with a failing NIS).  As `locate` labels a failed test, it
    is fault_detected now, its hpl widened by sqrt(NIS / dof) (the a-posteriori variance
    factor); clean epochs stay `ok` and keep their bounds."""
    from robustloc import status as st

    a = _anchors(6)
    meas, _ = _walk(K=1, N=60, seed=3, anchors=a)
    bad = meas.copy()
    hit = (bad["time"] == bad["time"].unique()[40]) & bad["anchor"].isin(["A1", "A2"])
    bad.loc[hit, "range"] += 3.0
    rows = {}
    for name, m in (("clean", meas), ("bad", bad)):
        rows[name] = Tracker(a, sigma=SIGMA_M, engine=engine).step(_epochs(m, a))
    clean, faulty = rows["clean"], rows["bad"]
    assert (clean["status"] == st.OK).all()
    row = faulty.iloc[40]
    assert row["status"] == st.FAULT_DETECTED, row["status"]
    dof = row["n_used"]  # every component kept: dof = n_used (one per range)
    assert row["nis"] > 30  # two 3 m errors on 0.1 m ranges: far beyond chi2(6)
    # the update that down-weighted two components is less certain than the clean one
    # (its P is larger), so its plain bound is at least the clean row's; widened by the
    # factor (measured: 1.79 m plain, 22.2 m widened, against 0.555 m clean)
    assert row["hpl"] >= clean["hpl"].iloc[40] * np.sqrt(row["nis"] / dof)
    assert (faulty["status"].iloc[:40] == st.OK).all()


@pytest.mark.parametrize("range_offset", [False, True])
def test_state_dict_holds_every_tags_arrays_as_json_values(range_offset):
    """Each tag's saved arrays are its state's values, flattened, as JSON types (Python
    float, int, bool; None for a non-finite float), and a tracker loaded from them goes
    on as the one that saved them."""
    a, ep = _bad_epochs(seed=21, K=4, M=6, N=40, p_out=0.1, p_miss=0.3, step_m=2.0)
    half = ep.n_epochs // 2

    def cut(s):
        return type(ep)(ep.time[s], ep.tag[s], ep.values[s], ep.anchor_ids, ep.value,
                        ep.line[s])
    trk = Tracker(a, sigma=SIGMA_M, cusum_h=6.0, range_offset=range_offset)
    trk.step(cut(slice(0, half)))
    state = trk.state_dict()
    assert json.loads(json.dumps(state, allow_nan=False)) == state  # strict JSON
    assert set(state["tags"]) == {str(t) for t in trk._slot}
    n_none = 0
    for tag, k in trk._slot.items():
        rec = state["tags"][str(tag)]
        for name in Tracker._ARRAYS:
            want = np.asarray(getattr(trk, name)[k])
            got = rec[name[1:]]
            vals = got if want.ndim else [got]
            assert len(vals) == want.size, name
            for v, w in zip(vals, want.ravel()):
                if want.dtype.kind == "f":
                    if np.isfinite(w):
                        assert type(v) is float and v == w, name
                    else:
                        assert v is None, name
                        n_none += 1
                else:
                    assert type(v) is type(w.item()) and v == w.item(), name
    assert n_none > 0  # the workload has unheard links (NaN last ranges)
    t2 = Tracker(a, sigma=SIGMA_M, cusum_h=6.0, range_offset=range_offset)
    t2.load_state_dict(state)
    pd.testing.assert_frame_equal(t2.step(cut(slice(half, None))),
                                  trk.step(cut(slice(half, None))))


def test_track_of_centimetre_rssi_ranges_writes_every_row(tmp_path):
    """Three anchors heard at -100, -114 and -10 dBm (path loss A = -61.4 dB, n = 1.48:
    the last a range of 0.3 mm) ended ``robustloc track`` in a LinAlgError traceback
    (the mirror check's normal matrix; the service review found it).  Now every epoch
    gets its row, and each row's covariance terms form a covariance: the start row
    clipped the fix's variances (to at most 100 m^2) and kept its cov_xy of -27 588 m^2,
    |cov_xy| > sqrt(var_x var_y)."""
    from robustloc.cli import main

    anchors = tmp_path / "anchors.csv"
    anchors.write_text("anchor,x,y,z,A,n\n"
                       "s11,7.18,0.68,2.3,-61.4,1.48\n"
                       "s30,13.14,12.33,1.22,-61.4,1.48\n"
                       "s31,12.82,16.83,2.3,-61.4,1.48\n"
                       "s42,12.76,0.27,2.3,-61.4,1.48\n")
    meas = tmp_path / "m.csv"
    meas.write_text("time,tag,anchor,rssi\n"
                    "100,evil,s11,-100\n100,evil,s30,-114.08\n100,evil,s31,-10\n"
                    "101,evil,s11,-149.9\n101,evil,s30,-114.08\n101,evil,s31,0\n"
                    "102,evil,s11,-100\n102,evil,s30,-100\n102,evil,s31,10\n")
    out = tmp_path / "t.csv"
    for engine in ("compiled", "numpy"):
        assert main(["track", str(meas), "--anchors", str(anchors), "-o", str(out),
                     "--kernel", engine]) == 0
        t = pd.read_csv(out)
        assert len(t) == 3 and t["status"].notna().all()
        assert t["status"].iloc[0] == "fault_detected"  # `locate`: unavailable
        assert np.isinf(t["hpl"].iloc[0])
        fixed = t["var_x"].notna()
        assert fixed.any()
        c = t.loc[fixed]
        assert (c["cov_xy"].abs() <= np.sqrt(c["var_x"] * c["var_y"]) * (1 + 1e-12)).all()


def test_track_names_an_anchor_far_outside_the_layout(tmp_path, capsys):
    """An anchor at y = 1e300 (a typo) is named by `locate` and was silently listed as
    excluded in every `track` row (the CLI review).  `track` now warns as `locate` does,
    and its summary lists it (``anchors_not_used``)."""
    from robustloc.cli import main

    a = tmp_path / "a.csv"
    a.write_text("anchor,x,y\nA1,0,0\nA2,10,0\nA3,0,1e300\nA4,10,10\nA5,0,10\n")
    xy = np.array([[0, 0], [10, 0], [0, 1e300], [10, 10], [0, 10]], float)
    lines = ["time,tag,anchor,range"]
    for t in range(4):
        for i in range(5):
            r = 5.0 if i == 2 else float(np.hypot(*(xy[i] - [3.0, 4.0])))
            lines.append(f"{t},T,A{i + 1},{r}")
    m = tmp_path / "m.csv"
    m.write_text("\n".join(lines) + "\n")
    assert main(["track", str(m), "--anchors", str(a), "-o", str(tmp_path / "t.csv"),
                 "--quiet"]) == 0
    err = capsys.readouterr().err
    assert f"warning: {a}: anchor(s) A3 lie far outside the others" in err
    assert main(["track", str(m), "--anchors", str(a), "-o", str(tmp_path / "t.csv"),
                 "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["anchors_not_used"] == ["A3"]
    t = pd.read_csv(tmp_path / "t.csv")
    assert len(t) == 4 and np.allclose(t[["x", "y"]].to_numpy(float), [3.0, 4.0], atol=1e-6)


def test_the_first_row_reports_the_covariance_the_filter_starts_from(tmp_path):
    """The first row of a tag gave the start fix's covariance with its ``cov_xy`` while
    the filter started from the diagonal alone, and the smoothed first row was not within
    the forward one (``P_f - P_s`` indefinite for 6 of 21 tags; the tracker review).  The
    row now gives the filter's own start (no correlation; the tracker's ``_start`` says
    why the start stays diagonal), and on the simulated room the smoothed covariance of
    every row is within the forward one."""
    from robustloc.cli import main

    assert main(["simulate", "wifi-room", "--seed", "1", "--out", str(tmp_path / "r")]) == 0
    r = tmp_path / "r"
    files = {}
    for name, extra in (("f", []), ("s", ["--smooth"])):
        files[name] = tmp_path / f"{name}.csv"
        assert main(["track", str(r / "measurements.csv"), "--anchors",
                     str(r / "anchors.csv"), "-o", str(files[name]), "--quiet", *extra]) == 0
    f, s = pd.read_csv(files["f"]), pd.read_csv(files["s"])

    def cov(df):
        return np.stack([np.stack([df.var_x, df.cov_xy], -1),
                         np.stack([df.cov_xy, df.var_y], -1)], -2)

    ok = f[["var_x", "var_y", "cov_xy"]].notna().all(axis=1).to_numpy()
    first = (~f.duplicated("tag")).to_numpy()
    assert first.sum() > 10 and np.all(f.cov_xy[first & ok] == 0.0)
    # (rounded to the written digits: a relative tolerance of 1e-9)
    low = np.linalg.eigvalsh(cov(f[ok]) - cov(s[ok])).min(axis=1)
    scale = f.loc[ok, ["var_x", "var_y"]].max(axis=1).to_numpy()
    assert np.all(low >= -1e-9 * scale), np.sort(low / scale)[:5]


def test_track_says_how_many_duplicate_rows_it_averaged(tmp_path, capsys):
    """An anchor heard twice in one epoch is averaged; ``locate`` says how many rows it
    merged, ``track`` said nothing (the tracker review)."""
    from robustloc.cli import main

    a = tmp_path / "a.csv"
    a.write_text("anchor,x,y\nA,0,0\nB,10,0\nC,0,10\nD,10,10\n")
    rows = [f"{t},T,{k},{r}" for t in range(5) for k, r in zip("ABCD", (5, 5.1, 4.9, 5))]
    m = tmp_path / "m.csv"
    m.write_text("time,tag,anchor,range\n" + "\n".join(rows + ["2,T,B,5.3", "3,T,C,4.7"])
                 + "\n")
    out = str(tmp_path / "t.csv")
    assert main(["track", str(m), "--anchors", str(a), "-o", out, "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["duplicates_merged"] == 2
    assert main(["track", str(m), "--anchors", str(a), "-o", out]) == 0
    assert "2 duplicate rows (same epoch and anchor) averaged" in capsys.readouterr().out
    assert len(pd.read_csv(out)) == 5  # one row per epoch


def test_an_anchor_far_outside_the_layout_is_not_used(tmp_path):
    """An anchor at y = 1e300 (a typo) was "heard": named in every row's ``excluded``
    while the status stayed ``ok`` (the tracker review).  It is not used, as by
    ``locate``: the track is the one without that anchor's rows."""
    from robustloc.cli import main

    a = tmp_path / "a.csv"
    a.write_text("anchor,x,y\nA1,0,0\nA2,10,0\nA3,10,1e300\nA4,0,10\n")
    b = tmp_path / "b.csv"
    b.write_text("anchor,x,y\nA1,0,0\nA2,10,0\nA3,10,10\nA4,0,10\n")
    rng = np.random.default_rng(3)
    xy = {"A1": (0, 0), "A2": (10, 0), "A4": (0, 10)}
    rows = [f"{t},T,{k},{np.hypot(2 - x, 5 - y) + rng.normal(0, 0.05):.4f}"
            for t in range(20) for k, (x, y) in xy.items()]
    m = tmp_path / "m.csv"
    m.write_text("time,tag,anchor,range\n" + "\n".join(rows + [f"{t},T,A3,7.0"
                                                               for t in range(20)]) + "\n")
    m3 = tmp_path / "m3.csv"
    m3.write_text("time,tag,anchor,range\n" + "\n".join(rows) + "\n")
    assert main(["track", str(m), "--anchors", str(a), "-o", str(tmp_path / "t.csv"),
                 "--quiet"]) == 0
    assert main(["track", str(m3), "--anchors", str(b), "-o", str(tmp_path / "u.csv"),
                 "--quiet"]) == 0
    t, u = pd.read_csv(tmp_path / "t.csv"), pd.read_csv(tmp_path / "u.csv")
    assert t["excluded"].isna().all() and (t["n_used"] == 3).all()
    pd.testing.assert_frame_equal(t, u)


@pytest.mark.parametrize("filt", ["ekf", "ukf"])
def test_an_update_never_widens_the_prediction(tmp_path, monkeypatch, filt):
    """Issue 11: "never inflate the covariance while rejecting".  The tracker's robust
    update is the equivalent-variance one (a link of weight ``w`` enters with ``R / w``),
    whose ``P+ = P- - G S' G^T`` never exceeds ``P-``.  Seed 002's ``K D`` (the gain of
    every heard link, rejected columns cut) did: on the simulated wifi-room walk in dB
    (``--domain rssi``, seed 1) six updates widened the position block by up to 0.07 m^2
    with the EKF, two by 5.5 m^2 with the UKF, and one ``--smooth`` row came out less
    certain than its forward row (the track review).  Every update of the run is
    recorded here (the NumPy core's; RSSI in dB has no compiled round) and its largest
    eigenvalue of ``P+ - P-`` over the whole state must be rounding: ``1e-12`` of the
    largest prior variance."""
    import robustloc.filters.core as core
    from robustloc.cli import main

    worst = []
    update = core.update_from_moments

    def recorded(x, P, y, S, Pxz, R, robust=core.PLAIN, H=None, x_angles=()):
        r = update(x, P, y, S, Pxz, R, robust, H, x_angles)
        P = np.asarray(P)
        grow = np.linalg.eigvalsh(r.P - P)[:, -1] / np.abs(P).max(axis=(1, 2))
        worst.append(np.nanmax(grow) if grow.size else -np.inf)
        return r

    monkeypatch.setattr(core, "update_from_moments", recorded)
    assert main(["simulate", "wifi-room", "--seed", "1", "--out", str(tmp_path / "r")]) == 0
    r = tmp_path / "r"
    out = {}
    for name, extra in (("f", []), ("s", ["--smooth"])):
        out[name] = tmp_path / f"{name}.csv"
        assert main(["track", str(r / "measurements.csv"), "--anchors", str(r / "anchors.csv"),
                     "--domain", "rssi", "--filter", filt, "-o", str(out[name]), "--quiet",
                     *extra]) == 0
    assert len(worst) > 1000 and max(worst) <= 1e-12, max(worst)
    f, s = pd.read_csv(out["f"]), pd.read_csv(out["s"])

    def cov(df):
        return np.stack([np.stack([df.var_x, df.cov_xy], -1),
                         np.stack([df.cov_xy, df.var_y], -1)], -2)

    ok = (f[["var_x", "var_y", "cov_xy"]].notna().all(axis=1)
          & s[["var_x", "var_y", "cov_xy"]].notna().all(axis=1)).to_numpy()
    assert ok.sum() > 800
    low = np.linalg.eigvalsh(cov(f[ok]) - cov(s[ok])).min(axis=1)  # smoothed within
    scale = f.loc[ok, ["var_x", "var_y"]].max(axis=1).to_numpy()
    assert np.all(low >= -1e-9 * scale), np.sort(low / scale)[:5]
