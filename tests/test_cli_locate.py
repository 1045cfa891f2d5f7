"""`robustloc locate` end to end: simulate -> calibrate -> locate -> evaluate, streaming,
bad input."""

import json

import numpy as np
import pandas as pd
import pytest
from _corridor import write_side_files  # (tests/_corridor.py)

from robustloc.cli import main


@pytest.fixture(scope="module")
def corridor(tmp_path_factory):
    d = tmp_path_factory.mktemp("corridor")
    assert main(["simulate", "ble-corridor", "--seed", "3", "--out", str(d)]) == 0
    assert main(["calibrate", str(d / "survey.csv"), "--model", "log-distance",
                 "--anchors", str(d / "anchors.csv"), "-o", str(d / "cal.csv")]) == 0
    return d


def test_locate_every_epoch_gets_a_row(corridor, capsys):
    out = corridor / "pos.csv"
    rc = main(["locate", str(corridor / "measurements.csv"), "--anchors", str(corridor / "cal.csv"),
               "--method", "ls,igg", "-o", str(out), "--json"])
    assert rc == 0
    summary = json.loads(capsys.readouterr().out)
    pos = pd.read_csv(out)
    truth = pd.read_csv(corridor / "truth.csv")
    assert summary["epochs"] == len(truth)
    assert len(pos) == 2 * len(truth)
    assert list(pos.columns[:9]) == ["time", "tag", "x", "y", "method", "status", "n_used",
                                     "sigma0", "excluded"]
    # robust beats the paper's LS on the simulated corridor
    m = pos.merge(truth, on=["time", "tag"], suffixes=("", "_t"))
    m["e"] = np.hypot(m.x - m.x_t, m.y - m.y_t)
    rms = m.groupby("method")["e"].apply(lambda e: np.sqrt(np.nanmean(e**2)))
    assert rms["igg"] < 0.6 * rms["ls"]


def test_summary_gives_the_usable_fixes_protection_levels(corridor, tmp_path, capsys):
    """The run summary's hpl histogram counts every usable fix once (also over chunks of
    the stream), and its quantiles are within the bins' 6 % of the exact ones."""
    from robustloc import status as st
    from robustloc.pipelines.locate import hpl_quantiles

    out = tmp_path / "pos.csv"
    args = ["locate", str(corridor / "measurements.csv"), "--anchors", str(corridor / "cal.csv"),
            "--method", "auto,nls", "-o", str(out)]
    assert main(args + ["--json", "--chunk-rows", "53"]) == 0
    summary = json.loads(capsys.readouterr().out)
    pos = pd.read_csv(out)
    for m, g in pos.groupby("method"):
        use = g["status"].isin(st.USABLE)
        hist = summary["hpl_histogram"][m]
        assert sum(hist.values()) == use.sum()
        q = hpl_quantiles(hist)
        h = g.loc[use, "hpl"].to_numpy(float)
        for key, pct in (("p50", 50), ("p95", 95)):
            exact = np.percentile(h, pct, method="inverted_cdf")
            assert abs(np.log10(q[key] / exact)) <= 0.5 / 20 + 1e-12, (m, key)
    assert main(args) == 0  # the text summary says it
    text = capsys.readouterr().out
    assert "hpl of the" in text and "median" in text


def test_hpl_histogram_quantiles_and_unbounded_fixes():
    from robustloc.pipelines.locate import hpl_counts, hpl_quantiles

    rng = np.random.default_rng(2)
    h = 10 ** rng.uniform(-1, 2, 5000)
    a, b = {}, {}
    hpl_counts(h[:2000], np.ones(2000, bool), a)
    hpl_counts(h[2000:], np.ones(3000, bool), a)
    hpl_counts(h, np.ones(5000, bool), b)
    assert a == b  # chunks (and Dask partitions) add up exactly
    q = hpl_quantiles(b, (0.5, 0.95))
    for key, pct in (("p50", 50), ("p95", 95)):
        exact = np.percentile(h, pct, method="inverted_cdf")
        assert abs(np.log10(q[key] / exact)) <= 0.5 / 20 + 1e-12
    # unusable rows are left out; unbounded usable fixes count as infinite
    c = {}
    hpl_counts(np.array([1.0, np.nan, np.inf, np.inf, np.inf]),
               np.array([True, False, True, True, True]), c)
    assert c == {"0": 1, "inf": 3}
    assert hpl_quantiles(c)["p50"] == np.inf
    assert np.isnan(hpl_quantiles({})["p50"])


def test_streaming_in_small_chunks_matches_whole(corridor, tmp_path):
    args = ["locate", str(corridor / "measurements.csv"), "--anchors", str(corridor / "cal.csv"),
            "--method", "nls", "--quiet"]
    assert main(args + ["-o", str(tmp_path / "a.csv")]) == 0
    assert main(args + ["-o", str(tmp_path / "b.parquet"), "--chunk-rows", "37"]) == 0
    a = pd.read_csv(tmp_path / "a.csv")
    b = pd.read_parquet(tmp_path / "b.parquet")
    assert len(a) == len(b)
    np.testing.assert_allclose(a[["x", "y"]].to_numpy(), b[["x", "y"]].to_numpy(), atol=1e-9)


def test_range_calibration_applied(tmp_path):
    anchors = pd.DataFrame({"anchor": ["a", "b", "c", "d"], "x": [0, 10, 0, 10],
                            "y": [0, 0, 10, 10], "bias": [1.0, -0.5, 0.0, 2.0]})
    x = np.array([3.0, 4.0])
    d = np.hypot(anchors.x - x[0], anchors.y - x[1]) + anchors.bias
    meas = pd.DataFrame({"time": 0.0, "tag": "t", "anchor": anchors.anchor, "range": d})
    anchors.to_csv(tmp_path / "an.csv", index=False)
    meas.to_csv(tmp_path / "m.csv", index=False)
    assert main(["locate", str(tmp_path / "m.csv"), "--anchors", str(tmp_path / "an.csv"),
                 "--method", "nls", "-o", str(tmp_path / "p.csv")]) == 0
    p = pd.read_csv(tmp_path / "p.csv")
    np.testing.assert_allclose(p[["x", "y"]].to_numpy()[0], x, atol=1e-4)


@pytest.mark.parametrize(
    "meas, message",
    [
        ("time,tag,anchor,range\n0,t,a,1\n0,t,zz,2\n", "unknown anchor"),
        ("time,tag,anchor,range\n0,t,a,nan\n", ":2:"),
        ("time,tag,anchor\n0,t,a\n", "rssi"),
        ("time,tag,anchor,range\n0,t,a,abc\n", ":2:"),
        ("time,tag,anchor,range,range\n0,t,a,1,1\n", "duplicate column 'range'"),
        ("time,tag,anchor,range\n0,t,a,1\n0,t\n", ":3: column 'anchor': empty id"),
    ],
)
def test_locate_bad_input_exit_2(tmp_path, capsys, meas, message):
    (tmp_path / "an.csv").write_text("anchor,x,y\na,0,0\nb,1,0\nc,0,1\n")
    (tmp_path / "m.csv").write_text(meas)
    rc = main(["locate", str(tmp_path / "m.csv"), "--anchors", str(tmp_path / "an.csv"),
               "--method", "ls", "-o", str(tmp_path / "p.csv")])
    err = capsys.readouterr().err
    assert rc == 2
    assert err.startswith("error: ") and message in err
    assert "Traceback" not in err


def test_locate_cli_settings_errors(tmp_path, capsys, corridor):
    base = ["locate", str(corridor / "measurements.csv"), "--anchors",
            str(corridor / "cal.csv"), "-o", str(tmp_path / "p.csv")]
    # snooping needs sigma: the calibrated anchors carry a per-anchor `sigma` column...
    assert main(base + ["--method", "snooping"]) == 0
    # ...anchors without it take the log's per-anchor scale (the default --robust-scale)...
    nosig = pd.read_csv(corridor / "cal.csv").drop(columns=["sigma"])
    nosig.to_csv(tmp_path / "nosig.csv", index=False)
    assert main(["locate", str(corridor / "measurements.csv"), "--anchors",
                 str(tmp_path / "nosig.csv"), "-o", str(tmp_path / "s.csv"),
                 "--method", "snooping"]) == 0
    capsys.readouterr()
    # ...and with the per-epoch scale they need --sigma
    assert main(["locate", str(corridor / "measurements.csv"), "--anchors",
                 str(tmp_path / "nosig.csv"), "-o", str(tmp_path / "s2.csv"),
                 "--method", "snooping", "--robust-scale", "mad"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: invalid settings:") and "--sigma" in err
    assert main(base + ["--method", "nope"]) == 2
    assert "argument --method: unknown method 'nope'" in capsys.readouterr().err
    assert main(base + ["--method", "huber", "--param", "c"]) == 2
    assert "error: --param expects NAME=NUMBER" in capsys.readouterr().err
    assert main(base[:-2] + ["-o", str(tmp_path / "p.csv"), "--anchors",
                             str(tmp_path / "missing.csv")]) == 2
    assert capsys.readouterr().err == f"error: {tmp_path / 'missing.csv'}: file not found\n"
    # RSSI with anchors lacking path-loss parameters
    assert main(["locate", str(corridor / "measurements.csv"), "--anchors",
                 str(corridor / "anchors.csv"), "--method", "ls",
                 "-o", str(tmp_path / "q.csv")]) == 0  # simulated anchors carry true A, n
    raw = pd.read_csv(corridor / "anchors.csv")[["anchor", "x", "y"]]
    raw.to_csv(tmp_path / "bare.csv", index=False)
    assert main(["locate", str(corridor / "measurements.csv"), "--anchors",
                 str(tmp_path / "bare.csv"), "--method", "ls", "-o", str(tmp_path / "r.csv")]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"error: {tmp_path / 'bare.csv'}") and "calibrate" in err


def test_side_prior_is_the_logs_whatever_the_chunks(tmp_path, capsys):
    """The side comes from the first pass over the whole log, so streaming the log in
    chunks of 37 rows moves the same fixes as reading it at once; the summary counts
    them; --side-prior none leaves them on the wrong side."""
    truth = write_side_files(tmp_path)
    base = ["locate", str(tmp_path / "measurements.csv"), "--anchors",
            str(tmp_path / "anchors.csv")]
    assert main(base + ["-o", str(tmp_path / "whole.csv"), "--json"]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert main(base + ["-o", str(tmp_path / "chunked.csv"), "--chunk-rows", "37",
                        "--quiet"]) == 0
    assert main(base + ["-o", str(tmp_path / "none.csv"), "--side-prior", "none"]) == 0
    text = capsys.readouterr().out
    assert "placed on the log's side" not in text
    whole, chunked, none = (pd.read_csv(tmp_path / f"{k}.csv")
                            for k in ("whole", "chunked", "none"))
    pd.testing.assert_frame_equal(whole, chunked)
    moved = summary["side_from_log"]["auto"]
    assert moved >= 3 and summary["log_sides"]["auto"] == [[[0, 1, 2, 3], -1]]
    w, o = whole[["x", "y"]].to_numpy(), none[["x", "y"]].to_numpy()
    changed = ((w != o) & ~(np.isnan(w) & np.isnan(o))).any(axis=1)
    assert changed.sum() == moved and (none.y[changed] > 0).all()
    assert (whole.y[changed] < 0).all()
    pd.testing.assert_series_equal(whole.status, none.status)
    err = np.hypot(whole.x - truth[:, 0], whole.y - truth[:, 1])
    assert (err[changed] < 1.0).all()  # 10 cm ranges: back beside the truth
    # the text summary says so
    assert main(base + ["-o", str(tmp_path / "whole.csv")]) == 0
    assert f"{moved} ambiguous fixes placed on the log's side" in capsys.readouterr().out


def test_an_anchor_far_outside_the_layout_is_named(tmp_path, capsys):
    """An anchor at x = 1e30 (a typo) was left out of every fix without a word (status
    `ok`, `excluded` empty); the run now names it on stderr, even with --quiet, and the
    fixes are those of the file without it."""
    from robustloc.cli import main

    a = tmp_path / "a.csv"
    a.write_text("anchor,x,y\nA1,0,0\nA2,10,0\nA3,10,10\nA4,0,10\nA5,1e30,0\n")
    b = tmp_path / "b.csv"
    b.write_text("anchor,x,y\nA1,0,0\nA2,10,0\nA3,10,10\nA4,0,10\n")
    m = tmp_path / "m.csv"
    m.write_text("time,tag,anchor,range\n" + "".join(
        f"{t},t1,{k},{r}\n" for t in (0, 1) for k, r in
        (("A1", 3.6056), ("A2", 8.5440), ("A3", 10.6301), ("A4", 7.2801))))
    assert main(["locate", str(m), "--anchors", str(a), "-o", str(tmp_path / "o.csv"),
                 "--quiet"]) == 0
    err = capsys.readouterr().err
    assert f"warning: {a}: anchor(s) A5 lie far outside the others" in err
    assert main(["locate", str(m), "--anchors", str(b), "-o", str(tmp_path / "p.csv"),
                 "--quiet"]) == 0
    assert "warning" not in capsys.readouterr().err
    got, want = (pd.read_csv(tmp_path / n) for n in ("o.csv", "p.csv"))
    pd.testing.assert_frame_equal(got[["x", "y", "status"]], want[["x", "y", "status"]])


def _room_with_a_misplaced_anchor(tmp_path, dx_m: float):
    """Eight anchors around a 30 m room, 300 epochs of ranges with 0.1 m noise, and an
    anchors file with anchor A2 moved ``dx_m`` along x (the measurements are not)."""
    rng = np.random.default_rng(3)
    A = np.array([[0, 0], [30, 0], [30, 30], [0, 30], [15, 0], [30, 15], [15, 30], [0, 15]],
                 dtype=float)
    x = rng.uniform(5, 25, (300, 2))
    d = np.linalg.norm(x[:, None] - A[None], axis=2) + rng.normal(0, 0.1, (300, 8))
    m = tmp_path / "m.csv"
    pd.DataFrame([(t, "t1", f"A{j}", d[t, j]) for t in range(300) for j in range(8)],
                 columns=["time", "tag", "anchor", "range"]).to_csv(m, index=False)
    an = pd.DataFrame({"anchor": [f"A{j}" for j in range(8)], "x": A[:, 0], "y": A[:, 1]})
    an.loc[2, "x"] += dx_m
    a = tmp_path / f"anchors_{dx_m:g}.csv"
    an.to_csv(a, index=False)
    return m, a, x


@pytest.mark.parametrize(("dx_m", "named"), [(100.0, True), (2.0, True), (0.5, False)])
def test_an_anchor_whose_ranges_disagree_with_the_fixes_is_named(tmp_path, capsys, dx_m,
                                                                  named):
    """An anchor 100 m (or 2 m) from where its ranges say it is was given little weight by
    the log's scale and the fixes stayed good, without a word to the user.  The run now
    names it on stderr (even with --quiet) with its scale against the median anchor's, and
    in the summary's ``anchors_suspect``; 0.5 m off (5 noise sigmas) it is not named.  The
    threshold (SUSPECT_SCALE_RATIO = 5) lies above every shared real log's largest ratio
    (1.92) and below the 2 m case's 20.8."""
    m, a, truth = _room_with_a_misplaced_anchor(tmp_path, dx_m)
    out = tmp_path / "o.csv"
    assert main(["locate", str(m), "--anchors", str(a), "-o", str(out), "--quiet"]) == 0
    err = capsys.readouterr().err
    assert ("warning: " in err and "anchor(s) A2 (" in err
            and "calibrate --self" in err) is named
    assert main(["locate", str(m), "--anchors", str(a), "-o", str(out), "--json"]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert list(summary["anchors_suspect"]) == (["A2"] if named else [])
    if dx_m == 100.0:  # the fixes were, and stay, good: the anchor has little weight
        pos = pd.read_csv(out)
        err_m = np.hypot(pos["x"] - truth[:, 0], pos["y"] - truth[:, 1])
        assert np.sqrt(np.mean(err_m**2)) < 0.3


def test_the_library_warns_about_a_suspect_anchor(tmp_path):
    import robustloc
    from robustloc.api import RobustlocWarning

    m, a, _ = _room_with_a_misplaced_anchor(tmp_path, 100.0)
    with pytest.warns(RobustlocWarning, match=r"anchor\(s\) A2 \("):
        robustloc.locate(str(m), str(a))


def test_one_sigma_value_moves_nothing_under_the_log_scale(tmp_path, capsys):
    """--robust-scale log measures the noise in units of --sigma, so one value for every
    anchor changes no fix, status or hpl; sigma0, the ratio of the residuals to it,
    scales by 1/sigma (the help says so: the helper found --sigma "had no effect")."""
    rng = np.random.default_rng(8)
    anchors = pd.DataFrame({"anchor": list("abcde"), "x": [0, 20, 0, 20, 10],
                            "y": [0, 0, 20, 20, -5]})
    anchors.to_csv(tmp_path / "a.csv", index=False)
    xy = anchors[["x", "y"]].to_numpy(float)
    pos = rng.uniform(2, 18, (60, 2))
    d = np.linalg.norm(pos[:, None] - xy[None], axis=2) + rng.normal(0, 0.2, (60, 5))
    d[::7, 1] += 3.0
    k, j = np.nonzero(np.isfinite(d))
    pd.DataFrame({"time": k.astype(float), "tag": "T", "anchor": anchors["anchor"].to_numpy()[j],
                  "range": d[k, j]}).to_csv(tmp_path / "m.csv", index=False)
    out = {}
    for s in ("0.1", "1.0"):
        assert main(["locate", str(tmp_path / "m.csv"), "--anchors", str(tmp_path / "a.csv"),
                     "--method", "auto,nls,igg", "--sigma", s, "-o",
                     str(tmp_path / f"p{s}.csv"), "--quiet"]) == 0
        out[s] = pd.read_csv(tmp_path / f"p{s}.csv")
    a, b = out["0.1"], out["1.0"]
    pd.testing.assert_frame_equal(a.drop(columns="sigma0"), b.drop(columns="sigma0"),
                                  rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(a["sigma0"], 10 * b["sigma0"], rtol=1e-9)


@pytest.mark.parametrize("n_anchors, warned", [(6, True), (7, False)])
def test_lege_says_when_it_cannot_search(tmp_path, capsys, n_anchors, warned):
    """LEGE keeps 4 degrees of freedom after its exclusions: with six anchors in 2-D it
    searched for nothing, and its fixes equalled nls' to the last column, without a word
    (the review of 2026-12-06: an 80-sigma range in every fourth epoch, 50 unavailable
    fixes either way).  The run now says so; with seven it searches, and finds the fault."""
    ang = np.linspace(0, 2 * np.pi, n_anchors, endpoint=False)
    xy = np.column_stack([10 + 10 * np.cos(ang), 10 + 10 * np.sin(ang)])
    ids = [f"a{i}" for i in range(n_anchors)]
    pd.DataFrame({"anchor": ids, "x": xy[:, 0], "y": xy[:, 1]}).to_csv(
        tmp_path / "a.csv", index=False)
    rng = np.random.default_rng(2)
    rows = []
    for t in range(40):
        p = rng.uniform(6, 14, 2)
        d = np.hypot(*(xy - p).T) + rng.normal(0, 0.1, n_anchors)
        if t % 4 == 0:
            d[1] += 8.0  # 80 sigma
        rows += [{"time": float(t), "tag": "t", "anchor": a, "range": float(r)}
                 for a, r in zip(ids, d)]
    pd.DataFrame(rows).to_csv(tmp_path / "m.csv", index=False)
    assert main(["locate", str(tmp_path / "m.csv"), "--anchors", str(tmp_path / "a.csv"),
                 "--method", "lege", "--sigma", "0.1", "-o", str(tmp_path / "p.csv"),
                 "-q"]) == 0
    err = capsys.readouterr().err
    assert ("lege searches for gross errors only with 7 or more anchors heard" in err) \
        == warned, err
    out = pd.read_csv(tmp_path / "p.csv")
    faulty = out[out["time"] % 4 == 0]
    if not warned:
        assert (faulty["status"] == "fault_excluded").all()
        assert (faulty["excluded"] == "a1").all()


def test_anchors_on_one_line_are_named_as_the_reason(tmp_path, capsys):
    """Four anchors typed on one line gave every fix ``ill_conditioned`` and no word of
    why (the review of 2026-12-06); the run now says it, with what to do."""
    xy = np.array([[0.0, 0.0], [5.0, 0.0], [10.0, 0.0], [15.0, 0.0]])
    pd.DataFrame({"anchor": list("abcd"), "x": xy[:, 0], "y": xy[:, 1]}).to_csv(
        tmp_path / "a.csv", index=False)
    p = np.array([6.0, 4.0])
    d = np.hypot(*(xy - p).T)
    pd.DataFrame({"time": 0.0, "tag": "t", "anchor": list("abcd"), "range": d}).to_csv(
        tmp_path / "m.csv", index=False)
    assert main(["locate", str(tmp_path / "m.csv"), "--anchors", str(tmp_path / "a.csv"),
                 "-o", str(tmp_path / "p.csv"), "-q"]) == 0
    assert "the anchors lie on one line" in capsys.readouterr().err
    assert (pd.read_csv(tmp_path / "p.csv")["status"] == "ill_conditioned").all()
    # off the line by 5 %: no warning
    xy[1, 1] = 0.75
    pd.DataFrame({"anchor": list("abcd"), "x": xy[:, 0], "y": xy[:, 1]}).to_csv(
        tmp_path / "a.csv", index=False)
    assert main(["locate", str(tmp_path / "m.csv"), "--anchors", str(tmp_path / "a.csv"),
                 "-o", str(tmp_path / "p.csv"), "-q"]) == 0
    assert "one line" not in capsys.readouterr().err
