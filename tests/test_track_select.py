"""``track --link-offsets auto``: the log chooses whether the links' offsets are states
(:mod:`robustloc.tracking.select`), by the one-step-ahead predictive score of the
observations (:meth:`robustloc.tracking.Tracker.predictive_score`)."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pandas as pd
import pytest
from scipy.stats import norm, ttest_1samp
from scipy.stats import t as student_t
from test_track_link_offsets import LINK_B_M, _circles, _link_ranges
from test_track_offset import _concat, _ring

from robustloc.tracking import Tracker
from robustloc.tracking.select import (
    AUTO_ALPHA,
    AUTO_BATCHES,
    HUBER_C,
    choose_link_offsets,
    huber_log_score,
    paired_batch_t,
)


def test_huber_log_score_is_the_normal_log_density_inside_c_and_linear_beyond():
    """Inside ``|u| <= c`` the score is scipy's normal log density of ``nu`` with variance
    ``S``; beyond, ``rho(u) - rho(c) = c (|u| - c)`` (Huber's loss is linear there), so
    the score is the density's value at ``c sqrt(S)`` minus ``c (|u| - c)``."""
    S = np.array([0.01, 0.25, 4.0, 9.0])
    u = np.linspace(-6, 6, 121)
    for s in S:
        nu = u * np.sqrt(s)
        got = huber_log_score(nu, np.full_like(nu, s))
        inside = np.abs(u) <= HUBER_C
        np.testing.assert_allclose(got[inside], norm.logpdf(nu[inside], scale=np.sqrt(s)),
                                   rtol=0, atol=1e-12)
        edge = norm.logpdf(HUBER_C * np.sqrt(s), scale=np.sqrt(s))
        np.testing.assert_allclose(got[~inside],
                                   edge - HUBER_C * (np.abs(u[~inside]) - HUBER_C),
                                   rtol=0, atol=1e-12)


def test_paired_batch_t_is_the_one_sample_t_of_the_batch_means():
    """Rows of one observation each, cut into 20 batches of 10: the statistic is scipy's
    one-sample t of the 20 batch means, the critical value Student's ``t(0.95; 19)``;
    with unequal counts each batch's mean is per observation."""
    rng = np.random.default_rng(3)
    d = rng.normal(0.1, 1.0, 200)
    t, crit = paired_batch_t(d, np.ones(200))
    means = d.reshape(AUTO_BATCHES, -1).mean(axis=1)
    assert t == pytest.approx(ttest_1samp(means, 0.0).statistic, rel=1e-12)
    assert crit == pytest.approx(student_t.ppf(1 - AUTO_ALPHA, AUTO_BATCHES - 1), rel=1e-12)
    # rows of two observations (a sum each) in batches: the same means as the pairs' mean
    t2, _ = paired_batch_t(2 * d, np.full(200, 2))
    assert t2 == pytest.approx(t, rel=1e-12)
    # nothing to test on: no choice
    assert paired_batch_t(np.array([1.0]), np.array([1]))[1] == np.inf


def _walking_log(b: np.ndarray, seed: int):
    a = _ring()
    K, T = 8, 160
    truth = _circles(K, T, centre=(6.0, 2.0), radius=3.0, speed=0.3)
    return a, _concat(_link_ranges(a, truth, np.broadcast_to(b, (K, len(a))), seed))


@pytest.mark.parametrize("seed", [1, 2])
def test_auto_keeps_offsets_that_are_there_and_leaves_out_those_that_are_not(seed):
    """Eight tags walking circles in a ring of six anchors: with each anchor's ranges
    offset by its own ``b_i`` (-0.6 .. 1.2 m, 12 to 6 sigma) the offsets predict the
    ranges better and are kept; with none, the extra states only widen the predictions
    and are left out.  The rows are then those of the tracker with the choice made."""
    a, ep = _walking_log(4 * LINK_B_M, seed)
    c = choose_link_offsets(a, ep, sigma=0.1, q=0.05)
    assert c.use and c.t > c.t_critical and c.score_with > c.score_without, c
    assert c.observations == 6 * 8 * (160 - 1) and c.epochs == ep.n_epochs
    a, ep = _walking_log(0 * LINK_B_M, seed)
    c = choose_link_offsets(a, ep, sigma=0.1, q=0.05)
    assert not c.use and c.t <= c.t_critical, c


def test_auto_refuses_to_choose_where_it_cannot_tell():
    """The common range offset estimated instead, or too few observations per anchor:
    no offsets, and the reason says which."""
    a, ep = _walking_log(4 * LINK_B_M, 1)
    c = choose_link_offsets(a, ep, sigma=0.1, range_offset=True)
    assert not c.use and "range offset" in c.reason
    # a standing tag: its offsets stay confounded with its position (no trial run: the
    # walk with offsets to find, which a trial turns on above, is not scored)
    c = choose_link_offsets(a, ep, sigma=0.1, model="static")
    assert not c.use and "--model static" in c.reason and c.observations == 0
    short = type(ep)(ep.time[:16], ep.tag[:16], ep.values[:16], ep.anchor_ids, ep.value,
                     ep.line[:16])
    c = choose_link_offsets(a, short, sigma=0.1)
    # 16 epochs x 6 anchors heard, fewer than 20 per anchor: refused before any tracking
    assert not c.use and "96 observations heard, fewer than the 120" in c.reason
    assert c.observations == 0 and c.epochs == 16
    # enough heard, too few scored (each tag's start row scores nothing): 20 epochs of 8
    # tags give 120 heard but 6 x (20 - 8) = 72 scored
    short = type(ep)(ep.time[:20], ep.tag[:20], ep.values[:20], ep.anchor_ids, ep.value,
                     ep.line[:20])
    c = choose_link_offsets(a, short, sigma=0.1)
    assert not c.use and "72 observations scored, fewer than the 120" in c.reason, c
    assert c.observations == 72


def test_predictive_score_scores_every_heard_observation_of_every_filtered_row():
    """Per row, the observations scored are the finite ones of every row but a tag's
    start; a start row has none (NaN); without recording, or with values of another
    shape, it is refused."""
    a, ep = _walking_log(0 * LINK_B_M, 1)
    vals = ep.values.copy()
    vals[5:40:3, 2] = np.nan  # not heard
    ep = type(ep)(ep.time, ep.tag, vals, ep.anchor_ids, ep.value, ep.line)
    trk = Tracker(a, sigma=0.1, record=True)
    rows = trk.step(ep)
    score, count = trk.predictive_score(ep.values)
    start = rows.groupby("tag").cumcount().to_numpy() == 0
    assert np.all(np.isnan(score[start])) and np.all(count[start] == 0)
    np.testing.assert_array_equal(count[~start], np.isfinite(vals[~start]).sum(axis=1))
    assert np.all(np.isfinite(score[~start]))
    with pytest.raises(ValueError, match="record=True"):
        Tracker(a, sigma=0.1).predictive_score(ep.values)
    with pytest.raises(ValueError, match="recorded rows"):
        trk.predictive_score(ep.values[:-1])


def _write(tmp_path, a: pd.DataFrame, ep) -> tuple[str, str]:
    an = tmp_path / "anchors.csv"
    a.to_csv(an, index=False)
    t = np.repeat(ep.time, len(ep.anchor_ids))
    log = pd.DataFrame({"time": t, "tag": np.repeat(ep.tag, len(ep.anchor_ids)),
                        "anchor": np.tile(ep.anchor_ids, ep.n_epochs),
                        "range": ep.values.ravel()}).dropna()
    m = tmp_path / "ranges.csv"
    log.to_csv(m, index=False)
    return str(m), str(an)


def _cli(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "robustloc.cli", *args], capture_output=True,
                          text=True, timeout=300)


def test_track_link_offsets_auto_command_line(tmp_path):
    """``--link-offsets auto`` writes the rows of the tracker with the choice it names in
    the summary (``link_offsets_auto`` in JSON, a line of text); ``--link-offsets``
    alone is ``on``; without the option, the same (auto is the default); with
    ``--range-offset`` auto leaves them out and says why, and ``on`` is refused (exit 2)."""
    a, ep = _walking_log(4 * LINK_B_M, 1)
    a = a.assign(sigma=0.1)
    m, an = _write(tmp_path, a, ep)
    p = _cli("track", m, "--anchors", an, "-o", str(tmp_path / "auto.csv"), "--q", "0.05",
             "--link-offsets", "auto", "--json")
    assert p.returncode == 0, p.stderr
    s = json.loads(p.stdout)
    assert s["link_offsets_auto"]["used"] is True and s["link_offsets_auto"]["t"] > 0
    assert "link_offset_m" in s
    for flag in (["--link-offsets"], ["--link-offsets", "on"]):
        p = _cli("track", m, "--anchors", an, "-o", str(tmp_path / "on.csv"), "--q", "0.05",
                 *flag, "-q")
        assert p.returncode == 0, p.stderr
        pd.testing.assert_frame_equal(pd.read_csv(tmp_path / "auto.csv"),
                                      pd.read_csv(tmp_path / "on.csv"))
    p = _cli("track", m, "--anchors", an, "-o", str(tmp_path / "auto.csv"),
             "--link-offsets", "auto")
    assert p.returncode == 0 and "--link-offsets auto: on" in p.stdout + p.stderr
    # auto is the default: the same rows and choice without the option
    p = _cli("track", m, "--anchors", an, "-o", str(tmp_path / "default.csv"), "--q", "0.05",
             "--json")
    assert p.returncode == 0, p.stderr
    assert json.loads(p.stdout)["link_offsets_auto"] == s["link_offsets_auto"]
    pd.testing.assert_frame_equal(pd.read_csv(tmp_path / "default.csv"),
                                  pd.read_csv(tmp_path / "on.csv"))
    # with --range-offset auto leaves them out and says why; "on" with it is refused
    p = _cli("track", m, "--anchors", an, "-o", str(tmp_path / "x.csv"), "--range-offset",
             "--json")
    assert p.returncode == 0, p.stderr
    got = json.loads(p.stdout)
    assert got["link_offsets_auto"]["used"] is False and "range offset" in \
        got["link_offsets_auto"]["reason"] and "range_offset_m" in got
    p = _cli("track", m, "--anchors", an, "-o", str(tmp_path / "x.csv"), "--range-offset",
             "--link-offsets", "on")
    assert p.returncode == 2 and p.stderr.startswith("error: "), p.stderr
    assert "exclude each other" in p.stderr and "Traceback" not in p.stderr


def test_api_track_link_offsets_auto(tmp_path):
    """``robustloc.track(..., link_offsets="auto")``: the choice in the summary; a value
    other than True, False or "auto" is refused with the command line's words."""
    import robustloc
    from robustloc.errors import InputError

    a, ep = _walking_log(0 * LINK_B_M, 2)
    m, an = _write(tmp_path, a.assign(sigma=0.1), ep)
    got = robustloc.track(m, an, q=0.05, link_offsets="auto")
    auto = got.attrs["summary"]["link_offsets_auto"]
    assert auto["used"] is False and auto["observations"] > 0
    want = robustloc.track(m, an, q=0.05, link_offsets=False)  # (auto is the default)
    pd.testing.assert_frame_equal(got, want)
    assert "link_offsets_auto" not in want.attrs["summary"]
    with pytest.raises(InputError, match="link"):
        robustloc.track(m, an, link_offsets="sometimes")


def _cv_log(seed: int, n: int = 2000, q: float = 0.01, noise_m: float = 0.3,
            dt: float = 0.1, side_m: float = 60.0):
    """One tag moving as the tracker's CV model (white acceleration ``q``) inside a ring
    of six anchors, ranges with Gaussian noise ``noise_m``, no offsets."""
    from robustloc.io import to_epochs

    rng = np.random.default_rng(seed)
    ang = np.linspace(0, 2 * np.pi, 6, endpoint=False)
    ax, ay = side_m / 2 * (1 + np.cos(ang)), side_m / 2 * (1 + np.sin(ang))
    a = pd.DataFrame({"anchor": [f"A{i}" for i in range(6)], "x": ax, "y": ay})
    F = np.array([[1, 0, dt, 0], [0, 1, 0, dt], [0, 0, 1, 0], [0, 0, 0, 1]])
    q1 = q * np.array([[dt**3 / 3, dt**2 / 2], [dt**2 / 2, dt]])
    Q = np.zeros((4, 4))
    Q[np.ix_([0, 2], [0, 2])] = q1
    Q[np.ix_([1, 3], [1, 3])] = q1
    x = np.array([side_m / 2, side_m / 2, 0.0, 0.0])
    rows = []
    for k in range(n):
        x = F @ x + rng.multivariate_normal(np.zeros(4), Q)
        r = np.hypot(ax - x[0], ay - x[1]) + rng.normal(0, noise_m, 6)
        rows += [(k * dt, "T", f"A{i}", r[i]) for i in range(6)]
    log = pd.DataFrame(rows, columns=["time", "tag", "anchor", "range"])
    return a, to_epochs(log, list(a["anchor"]))


def test_auto_scores_with_the_noise_scale_the_filter_uses():
    """Ranges three times noisier than the stated sigma (0.3 m against 0.1), the motion
    exactly the tracker's model, no offsets: the tracker adapts its noise scale (item 6
    of the tracker's docstring), and the score must take it.  Scored with the stated
    sigma alone, the filter without offsets looked overconfident and the offsets' extra
    spread a gain: chosen on 9 of 10 such logs (the review of 2026-12-07)."""
    for seed in (0, 1, 2):
        a, ep = _cv_log(seed)
        c = choose_link_offsets(a, ep, sigma=0.1, q=0.01)
        assert not c.use, (seed, c)
        assert c.t < 0, (seed, c)


@pytest.mark.parametrize("seed", [6, 18])
def test_auto_leaves_out_offsets_that_only_absorb_a_stiff_models_lag(seed):
    """The seed-002 simulated walk (four access points, an exact path-loss model: no
    offsets to find) at the tracker's default q: a walker turning corners lags the stiff
    CV model, and the offsets absorb part of that lag, so they predict the RSSI a little
    better (t 3.24 and 3.28 on these seeds) while placing the tag worse (seed 6: 2.45 ->
    2.76 m, seed 18: 2.10 -> 2.40 m RMS; ``benchmarks/bench_link_choice.py``; the
    seeds of t between 2.5 and the critical value since the equivalent-variance update
    of 2026-12-07, which moved seed 13 from t 3.15 to -0.12).  At the
    level of 5 % both chose them; the default's 0.1 % (``t(0.999; 19)`` = 3.58) does
    not.  The critical value is Student's, from scipy."""
    from robustloc.io import to_epochs
    from robustloc.sim.wifi_room import WifiRoomConfig, generate

    data = generate(WifiRoomConfig(), seed)
    ep = to_epochs(data.measurements, [str(a) for a in data.anchors["anchor"]])
    c = choose_link_offsets(data.anchors, ep)
    assert c.t_critical == pytest.approx(student_t.ppf(0.999, 19), rel=1e-12)
    assert 2.5 < c.t < c.t_critical and not c.use, c


def clean_and_biased_logs(tmp_path) -> tuple[pd.DataFrame, pd.DataFrame, str]:
    """Eight tags walking without link offsets, and eight over the same times whose
    anchors read 6 to 12 sigma off (``4 LINK_B_M``), as read back from their files (both
    tagged ``0``-``7``), and the anchors file (sigma 0.1 m)."""
    a, clean = _walking_log(0 * LINK_B_M, 1)
    _, biased = _walking_log(4 * LINK_B_M, 2)
    m1, an = _write(tmp_path, a.assign(sigma=0.1), clean)
    (tmp_path / "b").mkdir()
    m2, _ = _write(tmp_path / "b", a.assign(sigma=0.1), biased)
    return pd.read_csv(m1), pd.read_csv(m2), an


def test_auto_chooses_on_the_order_it_tracks(tmp_path, monkeypatch):
    """Several logs one after another (each in time order) are sorted when the disorder
    shows, and ``auto`` chooses on the first epochs of the sorted log, as for the same
    rows sorted: the same choice and the same rows.  Eight tags without offsets, then
    the same times for eight tags whose anchors read 6 to 12 sigma off: with the sample
    shortened to 300 epochs and chunks of 600 rows (100 epochs), the first 300 epochs of
    the file as written are the clean tags' alone (the choice was made there, off at t
    -4.3, and kept after the sort: the default's review), those of the sorted log mix
    both (on, t 14.9)."""
    import robustloc
    import robustloc.tracking.select as sel

    one, two, an = clean_and_biased_logs(tmp_path)
    two["tag"] = "b" + two["tag"].astype(str)
    after = pd.concat([one, two], ignore_index=True)  # the clean log, then the other
    after.to_csv(tmp_path / "after.csv", index=False)
    after.sort_values(["time", "tag"], kind="stable").to_csv(tmp_path / "sorted.csv",
                                                             index=False)
    monkeypatch.setattr(sel, "AUTO_SAMPLE_EPOCHS", 300)
    got = {name: robustloc.track(tmp_path / f"{name}.csv", an, q=0.05, chunk_rows=600)
           for name in ("after", "sorted")}
    s = {k: v.attrs["summary"] for k, v in got.items()}
    assert s["after"]["sorted_first"] and not s["sorted"]["sorted_first"]
    assert s["sorted"]["link_offsets_auto"]["used"] is True
    assert s["after"]["link_offsets_auto"] == s["sorted"]["link_offsets_auto"]
    pd.testing.assert_frame_equal(got["after"], got["sorted"])


def test_the_sample_is_scored_in_pieces_with_the_same_scores(monkeypatch):
    """The trial tracks its sample in pieces and drops each piece's recorded history
    (``Tracker.forget_record``: bounded memory); the rows' scores are those of one
    recording over the whole sample, to the bit, and so is the choice.  After
    ``forget_record`` the score covers only the later steps, numbered from 0."""
    import robustloc.tracking.select as sel

    a, ep = _walking_log(4 * LINK_B_M, 1)
    whole = Tracker(a, sigma=0.1, q=0.05, record=True, link_offsets=True)
    whole.step(ep)
    r_all, c_all = whole.predictive_score(ep.values)
    cut = int(np.flatnonzero(np.diff(ep.time) > 0)[60]) + 1  # where the time changes
    trk = Tracker(a, sigma=0.1, q=0.05, record=True, link_offsets=True)
    first = type(ep)(ep.time[:cut], ep.tag[:cut], ep.values[:cut], ep.anchor_ids,
                     ep.value, ep.line[:cut])
    rest = type(ep)(ep.time[cut:], ep.tag[cut:], ep.values[cut:], ep.anchor_ids, ep.value,
                    ep.line[cut:])
    trk.step(first)
    trk.forget_record()
    trk.step(rest)
    r, c = trk.predictive_score(rest.values)
    np.testing.assert_array_equal(r, r_all[cut:])
    np.testing.assert_array_equal(c, c_all[cut:])
    with pytest.raises(ValueError, match="recorded rows"):
        trk.predictive_score(ep.values)
    choices = []
    for piece in (10**9, 97):
        monkeypatch.setattr(sel, "AUTO_SCORE_PIECE", piece)
        choices.append(choose_link_offsets(a, ep, sigma=0.1, q=0.05))
    assert choices[0] == choices[1] and choices[0].use, choices


def test_the_trial_reports_its_progress(tmp_path, monkeypatch):
    """The trial tracks its sample twice (without and with the offsets), in pieces: the
    progress callback is told each piece's epochs, twice the sample's in all; on a
    terminal ``track`` draws a bar named after the option, and ``-q`` silences it."""
    from test_cli_quiet import _stderr_on_a_terminal

    import robustloc.tracking.select as sel

    a, ep = _walking_log(4 * LINK_B_M, 1)
    monkeypatch.setattr(sel, "AUTO_SCORE_PIECE", 300)
    seen: list[int] = []
    choose_link_offsets(a, ep, progress=seen.append, sigma=0.1, q=0.05)
    assert sum(seen) == 2 * ep.n_epochs and len(seen) >= 2 * (ep.n_epochs // 300), seen
    m, an = _write(tmp_path, a.assign(sigma=0.1), ep)
    args = ["track", m, "--anchors", an, "--q", "0.05"]
    loud = _stderr_on_a_terminal([*args, "-o", str(tmp_path / "a.csv")])
    assert "--link-offsets auto (both ways)" in loud and f"{2 * ep.n_epochs}/" in loud, loud
    quiet = _stderr_on_a_terminal([*args, "-o", str(tmp_path / "b.csv"), "-q"])
    assert "link-offsets auto (both" not in quiet, quiet
