"""Issue 15, part B: option values, incompatible options, folder outputs and bounded
Monte Carlo memory of ``simulate``, ``stats``, ``reliability``, ``filter`` and
``montecarlo``."""

from __future__ import annotations

import json

import numpy as np
import pandas as pd
import pytest

from robustloc.cli import main


def _rc_err(argv, capsys):
    """Exit code and stderr of a run (argparse errors exit through SystemExit)."""
    try:
        rc = main(argv)
    except SystemExit as e:
        rc = e.code
    return rc, capsys.readouterr().err


@pytest.fixture(scope="module")
def corridor(tmp_path_factory):
    d = tmp_path_factory.mktemp("corridor")
    assert main(["simulate", "ble-corridor", "--seed", "1", "--out", str(d)]) == 0
    return d


def test_stats_truth_without_a_matching_tag_is_an_error_leaving_nothing(
        corridor, tmp_path, capsys):
    truth = pd.read_csv(corridor / "truth.csv")
    # (one new name per tag: all tags renamed to one name gave duplicate (time, tag)
    # rows, refused first since read_truth checks them)
    truth["tag"] = "nosuch_" + truth["tag"].astype(str)
    bad = tmp_path / "truth.csv"
    truth.to_csv(bad, index=False)
    out = tmp_path / "stats"
    rc, err = _rc_err(["stats", str(corridor / "measurements.csv"), "--anchors",
                       str(corridor / "anchors.csv"), "--truth", str(bad), "-o", str(out)],
                      capsys)
    assert rc == 2 and err.startswith(f"error: {bad}: no measurement has a truth position")
    assert not out.exists()
    assert [p.name for p in tmp_path.iterdir()] == ["truth.csv"]  # no temporary folder


def test_stats_counts_implausible_rssi(corridor, tmp_path, capsys):
    m = pd.read_csv(corridor / "measurements.csv")
    m.loc[[3, 7], "rssi"] = [-500.0, 50.0]
    bad = tmp_path / "m.csv"
    m.to_csv(bad, index=False)
    out = tmp_path / "stats"
    rc, err = _rc_err(["stats", str(bad), "-o", str(out)], capsys)
    if rc == 2:  # the table reader may refuse such values itself (io/tables.py)
        assert err.startswith("error:") and "Traceback" not in err
        return
    summary = pd.read_json(out / "summary.json", typ="series")
    assert summary["invalid_measurement"] == 2


def test_simulate_group_b_line_is_refused_not_silently_diagonal(tmp_path, capsys):
    out = tmp_path / "cart"
    rc, err = _rc_err(["simulate", "uwb-cart", "--group", "B", "--path", "line", "--out",
                       str(out)], capsys)
    assert rc == 2 and "group B" in err and "diagonal" in err
    assert not out.exists()
    assert main(["simulate", "uwb-cart", "--group", "B", "--out", str(out)]) == 0
    t = pd.read_csv(out / "truth.csv")
    assert np.allclose(t["x"], t["y"])  # the diagonal, as documented


@pytest.mark.parametrize("argv,opt", [
    (["simulate", "gnss", "--lat", "200"], "--lat"),
    (["simulate", "gnss", "--mask-deg", "nan"], "--mask-deg"),
    (["simulate", "gnss", "--epochs", "0"], "--epochs"),
    (["simulate", "uwb-cart", "--nlos-prob", "1.5"], "--nlos-prob"),
    (["simulate", "wifi-room", "--fade-prob", "nan"], "--fade-prob"),
    (["simulate", "wifi-room", "--ar-phi", "1"], "--ar-phi"),
    (["simulate", "ble-corridor", "--seed", "-1"], "--seed"),
    (["montecarlo", "--gnss", "--lat", "200"], "--lat"),
    (["montecarlo", "--gnss", "--trials", "0"], "--trials"),
    (["montecarlo", "--gnss", "--trials", "100000000000"], "--trials"),
    (["montecarlo", "--gnss", "--size", "nan"], "--size"),
    (["montecarlo", "--gnss", "--faults", "1,1"], "--faults"),
    (["montecarlo", "--gnss", "--alpha0", "inf"], "--alpha0"),
    (["montecarlo", "--gnss", "--systems", "GX"], "--systems"),
    (["montecarlo", "--gnss", "--methods", ","], "--methods"),  # was a KeyError traceback
    (["montecarlo", "--gnss", "--methods", "ls,ls"], "--methods"),
    (["simulate", "gnss", "--systems", "X"], "--systems"),
    # the tracker review: 0 and 1 passed argparse and were refused in the settings' own
    # words ("alpha0 must be ..."); a sigma of 1e-300 gave every fix ill_conditioned
    (["track", "m.csv", "--anchors", "a.csv", "--alpha0", "0"], "--alpha0"),
    (["track", "m.csv", "--anchors", "a.csv", "--integrity-risk", "1"], "--integrity-risk"),
    (["track", "m.csv", "--anchors", "a.csv", "--sigma", "1e-300"], "--sigma"),
    (["locate", "m.csv", "--anchors", "a.csv", "--sigma", "1e-300"], "--sigma"),
    # (the input review: every bound inf on fixes still called ok)
    (["locate", "m.csv", "--anchors", "a.csv", "--min-scale", "1e300"], "--min-scale"),
    # (DuckDB's "can't be cast" text: more time bins than an int64 holds)
    (["partition", "m.csv", "--by", "time", "--span", "1e-300"], "--span"),
])
def test_absurd_option_values_are_refused(tmp_path, capsys, argv, opt):
    out = tmp_path / "out"
    rc, err = _rc_err([*argv, "-o", str(out)], capsys)
    assert rc == 2 and "error" in err and opt in err and "Traceback" not in err
    assert not out.exists()


@pytest.mark.parametrize("cmd,opt,value", [
    ("reliability", "--sigma", "nan"), ("reliability", "--area", "0,0,1,2"),
    ("reliability", "--area", "0,1e300,0,1"),
    ("reliability", "--rho-threshold", "2"), ("reliability", "--step", "-1"),
    ("filter", "--sigma-rssi", "nan"), ("filter", "--exponent", "0"),
    ("filter", "--max-rejected", "-2"),
    # the input review: 1e300 raised OverflowError (a traceback), 1e-300 wrote NaN into
    # every filtered value with status ok, --q-rssi 1e300 into 19 of 70
    ("filter", "--sigma-rssi", "1e300"), ("filter", "--sigma-rssi", "1e-300"),
    ("filter", "--q-rssi", "1e300"), ("filter", "--sigma-accel", "1e300"),
])
def test_absurd_option_values_of_layout_commands(corridor, tmp_path, capsys, cmd, opt, value):
    out = tmp_path / "out"
    argv = [cmd, "--anchors", str(corridor / "anchors.csv"), "-o", str(out), f"{opt}={value}"]
    if cmd == "filter":
        argv.insert(1, str(corridor / "measurements.csv"))
    rc, err = _rc_err(argv, capsys)
    assert rc == 2 and "error" in err and opt in err and "Traceback" not in err
    assert not out.exists()


# ----------------------------------------------------------------------------- montecarlo
def test_montecarlo_up_to_one_chunk_draws_the_numbers_it_drew_before():
    """The pre-chunking algorithm, written out: one draw, one np.percentile."""
    from robustloc.integrity import montecarlo as mc

    lay = mc.gnss_layout()
    T = 2000
    got = mc.run_montecarlo(lay, n_faults=1, size=3.0, trials=T, methods=("ls", "huber"),
                            seed=7)
    tr = mc.draw_trials(lay, T, 1, 3.0, "mdb", 7)
    th = mc.theory(lay, tr)
    for row in got.itertuples():
        x, rej, flagged, usable = mc._run_method(row.method, lay, tr.y, None, mc.ALPHA0,
                                                 mc.BETA0, 0.1, 3)
        err = np.linalg.norm(x[:, [0, 1]], axis=1)
        e_ok = err[usable & np.isfinite(err)]
        assert row.flag_rate == np.mean(flagged)
        assert row.identified == np.mean(np.all(rej == tr.faulty, axis=1))
        assert row.unavailable == np.mean(~usable)
        assert row.err_mean_m == np.mean(e_ok)
        assert row.err_rms_m == np.sqrt(np.mean(e_ok**2))
        assert row.err_p95_m == np.percentile(e_ok, 95)
        assert row.theory_global == th["global_rejection"]


def test_montecarlo_chunks_accumulate_exactly(monkeypatch):
    """Several chunks: every figure equals the one computed over all chunks' trials at
    once, the 95th percentile included (from the kept tail only)."""
    from robustloc.integrity import montecarlo as mc

    monkeypatch.setattr(mc, "CHUNK_TRIALS", 700)
    lay = mc.gnss_layout()
    T = 2500  # chunks of 700, 700, 700, 400
    got = mc.run_montecarlo(lay, n_faults=1, size=1.0, trials=T, methods=("snooping",),
                            seed=3).iloc[0]
    errs, flags, usables = [], [], []
    for k, start in enumerate(range(0, T, 700)):
        tr = mc.draw_trials(lay, min(700, T - start), 1, 1.0, "mdb", 3 if k == 0 else [3, k])
        x, rej, flagged, usable = mc._run_method("snooping", lay, tr.y, None, mc.ALPHA0,
                                                 mc.BETA0, 0.1, 3)
        err = np.linalg.norm(x[:, [0, 1]], axis=1)
        errs.append(err[usable & np.isfinite(err)])
        flags.append(flagged)
        usables.append(usable)
    e = np.concatenate(errs)
    assert got["flag_rate"] == pytest.approx(np.mean(np.concatenate(flags)), rel=1e-15)
    assert got["unavailable"] == pytest.approx(np.mean(~np.concatenate(usables)), abs=1e-15)
    assert got["err_mean_m"] == pytest.approx(np.mean(e), rel=1e-12)  # summation order
    assert got["err_rms_m"] == pytest.approx(np.sqrt(np.mean(e**2)), rel=1e-12)
    assert got["err_p95_m"] == np.percentile(e, 95)


def test_montecarlo_tail_accumulator_gives_the_exact_percentile():
    from robustloc.integrity.montecarlo import _Accumulator

    rng = np.random.default_rng(0)
    for trials, usable_share in ((1, 1.0), (7, 1.0), (1000, 0.3), (5000, 1.0)):
        acc = _Accumulator(trials)
        parts = []
        left = trials
        while left:
            T = min(left, int(rng.integers(1, 400)))
            e = rng.exponential(size=T)
            keep = rng.random(T) < usable_share
            acc.add(np.zeros(T, bool), np.zeros(T, bool), keep, e[keep], 0.0)
            parts.append(e[keep])
            left -= T
        allv = np.concatenate(parts)
        if allv.size:
            assert acc.p95() == np.percentile(allv, 95)
        assert acc.tail.size <= np.ceil(0.05 * trials) + 2


def test_filter_keeps_implausible_rssi_out_of_the_filter(tmp_path, capsys):
    sim = tmp_path / "room"
    assert main(["simulate", "wifi-room", "--seed", "1", "--out", str(sim)]) == 0
    m = pd.read_csv(sim / "measurements.csv")
    m.loc[100, "rssi"] = -500.0
    m.loc[200, "rssi"] = 1e300
    bad = tmp_path / "m.csv"
    m.to_csv(bad, index=False)
    out = tmp_path / "f.csv"
    capsys.readouterr()
    rc, err = _rc_err(["filter", str(bad), "--anchors", str(sim / "anchors.csv"), "-o",
                       str(out)], capsys)
    if rc == 2:  # the table reader may refuse such values itself (io/tables.py)
        assert err.startswith("error:") and "Traceback" not in err
        return
    f = pd.read_csv(out)
    assert len(f) == len(m)  # every row kept
    assert list(f.index[f["status"] == "invalid_measurement"]) == [100, 200]
    assert f.loc[[100, 200], "rssi_raw"].tolist() == [-500.0, 1e300]
    # the raw value stays in 'rssi' too, so `locate` sets the row aside (the filter's
    # prediction there made `locate` count it as heard: the helper-24 report)
    assert f.loc[[100, 200], "rssi"].tolist() == [-500.0, 1e300]
    assert f.drop(index=[100, 200])["rssi"].between(-150, 30).all()
    assert np.isnan(f.loc[[100, 200], ["weight", "distance"]].to_numpy()).all()
    assert np.isfinite(f.loc[[100, 200], "distance_state"]).all()  # the prediction


def test_locate_on_the_filtered_file_sets_invalid_rows_aside_as_on_the_raw_file(
        tmp_path, capsys):
    """filter -> locate: an invalid row (RSSI or time out of limits) of the filtered file
    is not heard and is counted, exactly as in the raw file.  Before, the first row of a
    link became an empty 'rssi' (locate: "column 'rssi': missing or NaN value", exit 2)
    and a later one the filter's prediction, which locate counted as heard (n_used 4
    where the raw file gives 3)."""
    sim = tmp_path / "room"
    assert main(["simulate", "wifi-room", "--seed", "1", "--out", str(sim)]) == 0
    m = pd.read_csv(sim / "measurements.csv").iloc[:600].reset_index(drop=True)
    first = m.groupby("anchor").head(1).index[0]  # the first sample of its link
    bad_rows = [first, 300, 450]
    m.loc[first, "rssi"] = 500.0
    m.loc[300, "rssi"] = -500.0
    m.loc[450, "time"] = 5e12
    raw = tmp_path / "m.csv"
    m.to_csv(raw, index=False)
    anchors = str(sim / "anchors.csv")
    assert main(["filter", raw.as_posix(), "--anchors", anchors, "-o",
                 str(tmp_path / "f.csv")]) == 0
    capsys.readouterr()
    for name in ("m.csv", "f.csv"):
        assert main(["locate", str(tmp_path / name), "--anchors", anchors, "--json",
                     "-o", str(tmp_path / f"pos_{name}")]) == 0
        summary = json.loads(capsys.readouterr().out)
        assert summary["invalid_measurement_rows"] == 3, name
    a = pd.read_csv(tmp_path / "pos_m.csv")
    b = pd.read_csv(tmp_path / "pos_f.csv")
    assert len(a) == len(b)
    assert (a["n_used"].to_numpy() == b["n_used"].to_numpy()).all()
    # n_used counts the observations a fix kept; none of this walk's is excluded, so
    # the fixes keep every valid row and no invalid one
    assert int(b["n_used"].sum()) == len(m) - len(bad_rows)


def test_filter_keeps_implausible_times_out_of_the_filter(tmp_path, capsys):
    """A time of 1e300 s (or 2e12 s) passed through the filter: its prediction overflowed
    (numpy RuntimeWarnings) and the row came out `ok` with NaN values; `locate` and `track`
    give such rows `invalid_measurement`, and so does `filter` now, without a warning,
    and the other rows are filtered exactly as without them."""
    import warnings

    sim = tmp_path / "room"
    assert main(["simulate", "wifi-room", "--seed", "1", "--out", str(sim)]) == 0
    m = pd.read_csv(sim / "measurements.csv").iloc[:400].reset_index(drop=True)
    clean = tmp_path / "clean.csv"
    m.to_csv(clean, index=False)
    bad_rows = [100, 200]
    m2 = m.copy()
    m2.loc[100, "time"] = 1e300
    m2.loc[200, "time"] = 2e12
    bad = tmp_path / "m.csv"
    m2.to_csv(bad, index=False)
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)
        assert main(["filter", str(bad), "--anchors", str(sim / "anchors.csv"), "-o",
                     str(tmp_path / "f.csv")]) == 0
    keep = m.drop(index=bad_rows)
    keep.to_csv(clean, index=False)
    assert main(["filter", str(clean), "--anchors", str(sim / "anchors.csv"), "-o",
                 str(tmp_path / "g.csv")]) == 0
    capsys.readouterr()
    f, g = pd.read_csv(tmp_path / "f.csv"), pd.read_csv(tmp_path / "g.csv")
    assert len(f) == len(m)
    assert list(f.index[f["status"] == "invalid_measurement"]) == bad_rows
    assert f.loc[bad_rows, "rssi_raw"].tolist() == m.loc[bad_rows, "rssi"].tolist()
    assert f.loc[bad_rows, "rssi"].tolist() == m.loc[bad_rows, "rssi"].tolist()
    assert f.loc[bad_rows, "time"].tolist() == [1e300, 2e12]
    pd.testing.assert_frame_equal(f.drop(index=bad_rows).reset_index(drop=True), g)
