"""Command line: simulate -> calibrate -> evaluate, and bad input -> `error: FILE:LINE:`, exit 2."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pandas as pd
import pytest

from robustloc.cli import main
from robustloc.io import read_anchors, read_positions

ANCHORS = "anchor,x,y\n1,0,0\n2,10,0\n3,0,10\n"
SURVEY = "anchor,distance,rssi\n" + "".join(
    f"{a},{d},{-60 - 22 * np.log10(d) + (0.5 if d % 2 else -0.5):.2f}\n"
    for a in (1, 2, 3) for d in range(1, 11)
)


def _w(tmp_path, name, text):
    p = tmp_path / name
    p.write_text(text)
    return str(p)


def _fails(capsys, argv, path, line, words):
    code = main(argv)
    err = capsys.readouterr().err
    assert code == 2
    prefix = f"error: {path}:{line}: " if line is not None else f"error: {path}: "
    assert err.startswith(prefix), err
    assert words in err
    assert "Traceback" not in err


@pytest.mark.parametrize(
    ("name", "text", "line", "words"),
    [
        ("missing_col.csv", "anchor,distance\n1,2\n", 1, "rssi or range"),
        ("non_numeric.csv", "anchor,distance,rssi\n1,2,-50\n1,three,-60\n", 3, "not a number"),
        ("nan.csv", "anchor,distance,rssi\n1,2,-50\n1,3,nan\n", 3, "NaN"),
        ("inf.csv", "anchor,distance,rssi\n1,2,-50\n1,3,inf\n", 3, "infinite"),
        ("empty.csv", "", 1, "empty file"),
        ("header_only.csv", "anchor,distance,rssi\n", 2, "no data rows"),
        ("ragged.csv", "anchor,distance,rssi\n1,2,-50,7\n", 2, "expected 3 fields"),
        # outside the physical limits: fitted as if real before (A moved by 14 dB)
        ("loud.csv", "anchor,distance,rssi\n1,2,-50\n1,3,500\n", 3,
         "'rssi': 500 is implausible (rssi must lie in"),
        ("far.csv", "anchor,distance,range\n1,2,2.1\n1,3,1e7\n", 3,
         "'range': 1e+07 is implausible"),
        ("distant.csv", "anchor,distance,range\n1,2e6,2.1\n", 2,
         "'distance': 2e+06 is implausible (distance must lie in"),
    ],
)
def test_calibrate_bad_survey(tmp_path, capsys, name, text, line, words):
    p = _w(tmp_path, name, text)
    _fails(capsys, ["calibrate", p, "-o", str(tmp_path / "o.csv")], p, line, words)


def test_calibrate_duplicate_anchor(tmp_path, capsys):
    s = _w(tmp_path, "s.csv", SURVEY)
    a = _w(tmp_path, "a.csv", ANCHORS + "2,5,5\n")
    _fails(capsys, ["calibrate", s, "--anchors", a, "-o", str(tmp_path / "o.csv")], a, 5,
           "duplicate anchor id '2'")


def test_calibrate_unknown_anchor_in_measurements(tmp_path, capsys):
    a = _w(tmp_path, "a.csv", ANCHORS)
    m = _w(tmp_path, "m.csv", "time,tag,anchor,range\n0,T,1,5\n0,T,9,5\n")
    t = _w(tmp_path, "t.csv", "time,tag,x,y\n0,T,3,4\n")
    argv = ["calibrate", "--measurements", m, "--truth", t, "--anchors", a, "-o",
            str(tmp_path / "o.csv")]
    _fails(capsys, argv, m, 3, "unknown anchor id '9'")


def test_calibrate_unknown_anchor_in_survey(tmp_path, capsys):
    s = _w(tmp_path, "s.csv", SURVEY + "7,2,-70\n")
    a = _w(tmp_path, "a.csv", ANCHORS)
    _fails(capsys, ["calibrate", s, "--anchors", a, "-o", str(tmp_path / "o.csv")], s, 32,
           "unknown anchor id '7'")


def test_missing_file(tmp_path, capsys):
    p = str(tmp_path / "nope.csv")
    _fails(capsys, ["calibrate", p, "-o", str(tmp_path / "o.csv")], p, None, "file not found")
    _fails(capsys, ["evaluate", p, "--truth", p], p, None, "file not found")


@pytest.mark.parametrize(
    ("pos", "line", "words"),
    [
        ("time,tag,x\n0,T,1\n", 1, "missing column(s) y"),
        ("time,tag,x,y\n0,T,1,2\n0,T,a,2\n", 3, "not a number"),
        ("time,tag,x,y\n0,T,1,2\nnan,T,1,2\n", 3, "NaN"),
        ("time,tag,x,y,hpl\n0,T,1,2,abc\n", 2, "column 'hpl': 'abc' is not a number"),
        ("time,tag,x,y,hpl\n0,T,1,2,inf\n1,T,1,2,-3\n", 3, "negative protection level"),
        ("time,tag,x,y,z,vpl\n0,T,1,2,0,-1\n", 2, "column 'vpl': negative"),
        # a status decides the scoring: "OK" was counted as failed, an empty one as usable
        ("time,tag,x,y,status\n0,T,1,2,ok\n1,T,1,2,OK\n", 3, "unknown status 'OK'"),
        ("time,tag,x,y,status\n0,T,1,2,\n", 2, "empty status"),
    ],
)
def test_evaluate_bad_positions(tmp_path, capsys, pos, line, words):
    p = _w(tmp_path, "p.csv", pos)
    t = _w(tmp_path, "t.csv", "time,tag,x,y\n0,T,0,0\n")
    _fails(capsys, ["evaluate", p, "--truth", t], p, line, words)


def test_subprocess_exit_code_and_no_traceback(tmp_path):
    p = _w(tmp_path, "bad.csv", "anchor,distance,rssi\n1,2,loud\n")
    r = subprocess.run(
        [sys.executable, "-m", "robustloc.cli", "calibrate", p, "-o", str(tmp_path / "o.csv")],
        capture_output=True, text=True, check=False,
    )
    assert r.returncode == 2
    assert r.stderr.startswith(f"error: {p}:2: ") and "Traceback" not in r.stderr


def test_simulate_calibrate_evaluate_end_to_end(tmp_path, capsys):
    out = tmp_path / "sim"
    assert main(["simulate", "ble-corridor", "--seed", "2", "--out", str(out)]) == 0
    assert main(["simulate", "--list"]) == 0
    listing = capsys.readouterr().out
    assert "ble-corridor" in listing
    cal = tmp_path / "cal.csv"
    argv = ["calibrate", str(out / "survey.csv"), "--anchors", str(out / "anchors.csv"),
            "-o", str(cal), "--robust", "igg3", "--json"]
    assert main(argv) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["model"] == "log-distance" and summary["robust"] == "igg3"
    assert len(summary["parameters"]) == 11  # 10 beacons + pooled
    a = read_anchors(cal)
    assert np.all(np.isfinite(a["A"])) and np.all((a["n"] > 1.5) & (a["n"] < 3))
    # positions: truth plus a known offset per method, one failed epoch
    truth = pd.read_csv(out / "truth.csv")
    ls = truth.assign(x=truth["x"] + 3.0, method="ls", status="ok")
    igg = truth.assign(x=truth["x"] + 1.0, method="igg", status="ok")
    igg.loc[0, "status"] = "insufficient_anchors"
    pos = pd.concat([ls, igg]).assign(n_used=5, sigma0=1.0, excluded="")
    pos.to_parquet(tmp_path / "pos.parquet", index=False)
    read_positions(tmp_path / "pos.parquet")
    err_csv = tmp_path / "err.csv"
    argv = ["evaluate", str(tmp_path / "pos.parquet"), "--truth", str(out / "truth.csv"),
            "--json", "-o", str(err_csv)]
    assert main(argv) == 0
    rows = json.loads(capsys.readouterr().out)["rows"]
    by = {(r["tag"], r["method"]): r for r in rows}
    assert by[("all", "ls")]["mean"] == pytest.approx(3.0)
    assert by[("all", "igg")]["mean_impr_pct"] == pytest.approx(100 * 2 / 3)
    assert by[("S1", "igg")]["n_failed"] == 1
    assert err_csv.exists()
    assert main(["evaluate", str(tmp_path / "pos.parquet"), "--truth",
                 str(out / "truth.csv")]) == 0
    text = capsys.readouterr().out
    assert "rms" in text and "S3" in text


def test_calibrate_range_survey_text_output(tmp_path, capsys):
    s = _w(tmp_path, "r.csv", "anchor,distance,range\n" + "".join(
        f"{a},{d},{d + b + (0.01 if d % 2 else -0.01)}\n"
        for a, b in (("1", 0.5), ("2", -0.2)) for d in range(1, 9)))
    a = _w(tmp_path, "a.csv", ANCHORS)
    out = tmp_path / "o.parquet"
    assert main(["calibrate", s, "--anchors", a, "-o", str(out)]) == 0
    text = capsys.readouterr().out
    assert "range fit, least squares" in text and "bias" in text
    cal = read_anchors(out).set_index("anchor")
    assert cal.loc["1", "bias"] == pytest.approx(0.5)
    assert cal.loc["3", "calib_source"] == "pooled"  # anchor 3 not in the survey


def test_evaluate_json_is_strict_json(tmp_path, capsys):
    """An unbounded fix's infinite hpl gave ``"hpl_median": Infinity``, which JSON parsers
    (JavaScript's JSON.parse) reject: non-finite numbers are null."""
    t = _w(tmp_path, "t.csv", "time,tag,x,y\n0,t1,2,3\n1,t1,2,3\n")
    p = _w(tmp_path, "p.csv", "time,tag,x,y,method,status,hpl\n"
           "0,t1,2.1,3,nls,unverified,inf\n1,t1,2.0,3.1,nls,unverified,inf\n")
    assert main(["evaluate", p, "--truth", t, "--json"]) == 0

    def strict(token: str) -> None:
        raise AssertionError(f"non-JSON number {token}")

    doc = json.loads(capsys.readouterr().out, parse_constant=strict)
    assert doc["rows"][0]["hpl_median"] is None


RANGES_4 = ("time,tag,anchor,range\n" + "".join(
    f"{t},t1,{a},{r}\n" for t in (0, 1) for a, r in
    (("A1", 3.6056), ("A2", 8.5440), ("A3", 10.6301), ("A4", 7.2801))))
ANCHORS_4 = "anchor,x,y\nA1,0,0\nA2,10,0\nA3,10,10\nA4,0,10\n"


@pytest.mark.parametrize("command", ["track", "calibrate --self", "filter"])
def test_summaries_stay_out_of_stdout_data(tmp_path, command):
    """With ``-o -`` the run summary went to stdout after the table and corrupted the
    stream (track, filter, calibrate); it goes to stderr, as locate's does."""
    a = _w(tmp_path, "a.csv", ANCHORS_4 if command != "filter" else
           "anchor,x,y,A,n\nA1,0,0,-60,2\nA2,10,0,-60,2\nA3,10,10,-60,2\nA4,0,10,-60,2\n")
    m = _w(tmp_path, "m.csv", RANGES_4 if command != "filter" else
           "time,tag,anchor,rssi\n0,t,A1,-50\n1,t,A1,-52\n")
    argv = [*command.split(), m, "--anchors", a, "-o", "-"]
    r = subprocess.run([sys.executable, "-m", "robustloc.cli", *argv],
                       capture_output=True, text=True, check=False)
    assert r.returncode == 0, r.stderr
    lines = r.stdout.strip().splitlines()
    width = lines[0].count(",")
    assert len(lines) >= 3 and all(ln.count(",") == width for ln in lines), r.stdout
    assert r.stderr.strip()  # the summary is there


def test_filter_warns_without_path_loss(tmp_path, capsys):
    """Anchors without path-loss columns: the distance columns come from p0 = -40 dBm,
    gamma = 2; the run says so instead of writing them as if they were real."""
    a = _w(tmp_path, "a.csv", ANCHORS_4)
    m = _w(tmp_path, "m.csv", "time,tag,anchor,rssi\n0,t,A1,-50\n1,t,A1,-52\n")
    assert main(["filter", m, "--anchors", a, "-o", str(tmp_path / "f.csv")]) == 0
    err = capsys.readouterr().err
    assert err.startswith(f"warning: {a}: anchors have no path-loss parameters"), err


def test_evaluate_names_the_baseline_it_compares_with(tmp_path, capsys):
    """The text table said ``rms_vs_ls_%`` whatever ``--baseline`` was (the numbers were
    against the chosen one; ``-o`` and ``--json`` named them rightly)."""
    t = _w(tmp_path, "t.csv", "time,tag,x,y\n0,t1,2,3\n1,t1,2,3\n")
    p = _w(tmp_path, "p.csv", "time,tag,x,y,method,status\n0,t1,2.1,3,nls,ok\n"
           "1,t1,2.1,3,nls,ok\n0,t1,2.4,3,huber,ok\n1,t1,2.4,3,huber,ok\n")
    assert main(["evaluate", p, "--truth", t, "--baseline", "nls"]) == 0
    out = capsys.readouterr().out
    # (the text table now uses the CSV/JSON names; its title line names the baseline)
    title, header = out.splitlines()[:2]
    assert "over method nls" in title and "over method ls " not in title, out
    assert {"mean_impr_pct", "rms_impr_pct"} <= set(header.split()) and "_vs_" not in out, out


def test_options_that_would_be_ignored_are_refused(tmp_path, capsys):
    """`evaluate --baseline foo` (no such method) and `track --smooth --fixed-lag 3` (which
    smoother?) ran as if the option were not there."""
    t = _w(tmp_path, "t.csv", "time,tag,x,y\n0,t1,2,3\n1,t1,2,3\n")
    p = _w(tmp_path, "p.csv", "time,tag,x,y,method,status\n0,t1,2.1,3,nls,ok\n1,t1,2.1,3,nls,ok\n")
    _fails(capsys, ["evaluate", p, "--truth", t, "--baseline", "foo"], p, None,
           "--baseline 'foo' is not a method of this file (methods: nls)")
    a = _w(tmp_path, "a.csv", ANCHORS_4)
    m = _w(tmp_path, "m.csv", RANGES_4)
    try:  # argparse errors: exit 2, raised or returned
        code = main(["track", m, "--anchors", a, "-o", str(tmp_path / "o.csv"), "--smooth",
                     "--fixed-lag", "3"])
    except SystemExit as e:
        code = int(e.code)
    assert code == 2 and "not allowed with argument" in capsys.readouterr().err
    assert not (tmp_path / "o.csv").exists()


@pytest.mark.parametrize(("col", "value", "words"), [
    ("A", "1e300", "RSSI at 1 m A must lie in [-150, 30], got 1e+300"),
    ("n", "1e-300", "path-loss exponent n must lie in [0.01, 20], got 1e-300"),
    ("n", "50", "path-loss exponent n must lie in [0.01, 20], got 50"),
])
def test_absurd_path_loss_parameters_are_refused(tmp_path, capsys, col, value, words):
    """A = 1e300 or n = 1e-300 overflowed the path-loss model (RuntimeWarnings) and left
    every epoch `insufficient_anchors`; the anchors reader names the line instead."""
    vals = {"A": ["-60"] * 3, "n": ["2"] * 3}
    vals[col][1] = value
    a = _w(tmp_path, "a.csv", "anchor,x,y,A,n\n" + "".join(
        f"{i},{x},{y},{vals['A'][i - 1]},{vals['n'][i - 1]}\n"
        for i, (x, y) in enumerate(((0, 0), (10, 0), (0, 10)), start=1)))
    m = _w(tmp_path, "m.csv", "time,tag,anchor,rssi\n0,t,1,-70\n0,t,2,-70\n0,t,3,-70\n")
    _fails(capsys, ["locate", m, "--anchors", a, "-o", str(tmp_path / "o.csv")], a, 3, words)


@pytest.mark.parametrize(("opts", "where", "words"), [
    (["--step", "1e-6"], None, "points is too large; increase --step"),
    (["--dim", "3"], 1, "--dim 3 needs anchor heights (a z column)"),
])
def test_reliability_option_errors_are_user_errors(tmp_path, capsys, opts, where, words):
    """These ended in a traceback ("internal error"), exit 1."""
    a = _w(tmp_path, "a.csv", ANCHORS_4)
    argv = ["reliability", "--anchors", a, "-o", str(tmp_path / "r"), "--no-maps", *opts]
    if where is None:
        assert main(argv) == 2
        err = capsys.readouterr().err
        assert err.startswith("error: ") and words in err and "Traceback" not in err
    else:
        _fails(capsys, argv, a, where, words)
    assert not (tmp_path / "r").exists()
    try:  # argparse: (0, 1] was documented, 0 accepted, then refused inside
        code = main(["reliability", "--anchors", a, "-o", str(tmp_path / "r"), "--no-maps",
                     "--rho-threshold", "0"])
    except SystemExit as e:
        code = int(e.code)
    assert code == 2 and "--rho-threshold" in capsys.readouterr().err


def _code(argv: list[str]) -> int:
    """Exit code of the command line (argparse errors raise SystemExit(2))."""
    try:
        return main(argv)
    except SystemExit as e:
        return int(e.code)


def test_spp_never_writes_over_its_inputs(tmp_path, capsys):
    """`spp obs nav -o obs` replaced the observation file by the solution (exit 0)."""
    import shutil

    from robustloc.paths import PACKAGE_DATA

    g = PACKAGE_DATA / "gnss-geonet"
    obs, nav = tmp_path / "ip.05o", tmp_path / "ip.05n"
    shutil.copy(g / "07590920.05o", obs)
    shutil.copy(g / "07590920_0000-0400.05n", nav)
    before = {p: p.read_bytes() for p in (obs, nav)}
    for out in (str(obs), str(tmp_path / "x" / ".." / "ip.05n")):
        assert main(["spp", str(obs), str(nav), "-o", out, "--quiet"]) == 2
        assert "output would overwrite an input" in capsys.readouterr().err
    assert {p: p.read_bytes() for p in (obs, nav)} == before


def test_gnss_masks_below_the_horizon_and_absurd_montecarlo_options_are_refused(
        tmp_path, capsys):
    """A negative --mask-deg gave negative sigmas (simulate gnss: 372 of them) and a
    ValueError traceback (montecarlo --gnss); --sigma 1e160 or --size 1e300 an all-NaN
    table with exit 0."""
    for argv in (["montecarlo", "--gnss", "--trials", "50", "--mask-deg=-0.5"],
                 ["simulate", "gnss", "--mask-deg=-10", "-o", str(tmp_path / "sg")],
                 ["montecarlo", "--anchors", _w(tmp_path, "a.csv", ANCHORS_4), "--trials",
                  "50", "--sigma", "1e160"],
                 ["montecarlo", "--anchors", str(tmp_path / "a.csv"), "--trials", "50",
                  "--size", "1,1e300"]):
        assert _code(argv) == 2, argv
        err = capsys.readouterr().err
        assert "error: argument" in err and "Traceback" not in err
    assert not (tmp_path / "sg").exists()


def test_gnss_elevation_weighting_is_finite_at_the_horizon():
    """sigma / sin(elevation) is floored at 1 deg: positive and finite down to 0 deg."""
    import math

    from robustloc.sim.gnss import visible_design

    s = visible_design(0.0, 30.53, 114.36, 30.0, "GEC", 0.0)  # one satellite at 0.23 deg
    flat = visible_design(0.0, 30.53, 114.36, 30.0, "GEC", 0.0, elevation_weighting=False)
    assert np.all(np.isfinite(s.sigma)) and np.all(s.sigma > 0)
    low = s.elevation_deg < 1.0
    assert low.any()
    np.testing.assert_allclose(s.sigma[low], flat.sigma[low] / math.sin(math.radians(1.0)))
    np.testing.assert_allclose(s.sigma[~low],
                               flat.sigma[~low] / np.sin(np.deg2rad(s.elevation_deg[~low])))


def test_replay_refuses_bad_urls_speeds_and_times(tmp_path, capsys):
    """A malformed --url, --speed 1e-300 and a time of 1e15 ended in tracebacks (httpx
    InvalidURL, OverflowError in the pacing sleep); nothing is sent now."""
    m = _w(tmp_path, "m.csv", "time,tag,anchor,range\n0,T,A1,1\n")
    for url in ("http://[::1", "http://127.0.0.1:abc", "ftp://host"):
        _fails(capsys, ["replay", m, "--url", url, "--speed", "0"], url, None, "invalid URL")
    assert _code(["replay", m, "--url", "http://127.0.0.1:9", "--speed", "1e-300"]) == 2
    assert "--speed" in capsys.readouterr().err
    far = _w(tmp_path, "far.csv", "time,tag,anchor,range\n1e15,T,A1,1\n-5,T,A2,1\n")
    _fails(capsys, ["replay", far, "--url", "http://127.0.0.1:9", "--speed", "1"], far, 2,
           "column 'time': 1e+15 is implausible")


def test_dask_options_without_the_dask_engine_are_refused(tmp_path, capsys):
    """`locate --scheduler ADDRESS` (or --workers) without `--engine dask` ran locally
    and ignored them: the user meant the cluster."""
    a = _w(tmp_path, "a.csv", ANCHORS_4)
    m = _w(tmp_path, "m.csv", RANGES_4)
    for opts, words in ((["--scheduler", "tcp://head:8786"], "--scheduler only applies"),
                        (["--workers", "2"], "--workers only applies"),
                        (["--scheduler", "tcp://h:1", "--workers", "2"],
                         "--scheduler and --workers only apply")):
        for cmd in ("locate", "track"):
            assert main([cmd, m, "--anchors", a, "-o", str(tmp_path / "o.csv"), *opts]) == 2
            err = capsys.readouterr().err
            assert err == f"error: {words} with --engine dask\n", err
            assert not (tmp_path / "o.csv").exists()


def test_spp_inject_twice_and_stats_out_of_limits_say_what_is_wrong(tmp_path, capsys):
    """`spp --inject G11:20,G11:30` kept the last bias silently; `stats` on RSSI that is
    all outside the limits said "no finite RSSI sample" (-500 is finite)."""
    from robustloc.paths import PACKAGE_DATA

    g = PACKAGE_DATA / "gnss-geonet"
    assert main(["spp", str(g / "07590920.05o"), str(g / "07590920_0000-0400.05n"), "-o",
                 str(tmp_path / "s.csv"), "--inject", "G11:20,G11:30", "--quiet"]) == 2
    assert "--inject: G11 given twice" in capsys.readouterr().err
    m = _w(tmp_path, "st.csv", "time,tag,anchor,rssi\n0,t,A1,-500\n1,t,A1,-600\n")
    _fails(capsys, ["stats", m, "-o", str(tmp_path / "out")], m, None,
           "no RSSI sample within the physical limits to analyse (rssi must lie in "
           "[-150, 30] dBm; 2 outside)")


def test_evaluate_prints_and_writes_counts_as_integers(tmp_path, capsys):
    """`evaluate` printed n = 1500 as ``1.5e+03`` (``.3g``) and wrote ``1500.0``."""
    from robustloc.cli import main

    t = np.arange(1500, dtype=float)
    pd.DataFrame({"time": t, "tag": "T", "x": 0.0, "y": 0.0}).to_csv(tmp_path / "truth.csv",
                                                                     index=False)
    pd.DataFrame({"time": t, "tag": "T", "x": 0.1, "y": 0.0, "method": "nls",
                  "status": "ok"}).to_csv(tmp_path / "pos.csv", index=False)
    assert main(["evaluate", str(tmp_path / "pos.csv"), "--truth", str(tmp_path / "truth.csv"),
                 "-o", str(tmp_path / "ev.csv")]) == 0
    out = capsys.readouterr().out
    assert "1500" in out and "e+03" not in out
    text = (tmp_path / "ev.csv").read_text().splitlines()
    assert text[1].startswith("T,nls,1500,0,0,1500,"), text[1]


def test_a_capitalized_column_is_named_in_the_message(tmp_path, capsys):
    """`Time,Tag,Anchor,Range` or `anchor,X,Y`: the message listed the columns but did not
    say that names are lower case."""
    from robustloc.cli import main

    (tmp_path / "a.csv").write_text("anchor,X,Y\na0,0,0\n")
    (tmp_path / "m.csv").write_text("time,tag,anchor,range\n0,T,a0,5\n")
    assert main(["locate", str(tmp_path / "m.csv"), "--anchors", str(tmp_path / "a.csv"),
                 "-o", str(tmp_path / "p.csv")]) == 2
    assert capsys.readouterr().err.endswith(
        "(has: anchor, X, Y); column names are lower case without spaces: rename "
        "'X' -> 'x', 'Y' -> 'y'\n")


def test_calibrate_filter_and_fuse_never_write_over_their_inputs(tmp_path, capsys):
    """`-o` naming an input replaced it with exit 0 in `calibrate` (the survey, the log
    of --self, the truth, the anchors), `filter` (the RSSI log, or its anchors) and
    `fuse` (the range log), where `locate` and `track` refused (the CLI review found
    it).  Each is now refused before any work, the file unchanged."""
    import shutil

    for scen in ("uwb-cart", "ble-corridor"):
        assert main(["simulate", scen, "--seed", "1", "--out", str(tmp_path / scen)]) == 0
    u, b = tmp_path / "uwb-cart", tmp_path / "ble-corridor"
    cases = {
        "calibrate survey": (b / "survey.csv", ["calibrate", "{f}", "-o", "{f}"]),
        "calibrate --self log": (u / "measurements.csv",
                                 ["calibrate", "--self", "{f}", "--anchors",
                                  str(u / "anchors.csv"), "-o", "{f}"]),
        "calibrate --self anchors": (u / "anchors.csv",
                                     ["calibrate", "--self", str(u / "measurements.csv"),
                                      "--anchors", "{f}", "-o", "{f}"]),
        "calibrate truth": (b / "truth.csv",
                            ["calibrate", "--measurements", str(b / "measurements.csv"),
                             "--truth", "{f}", "--anchors", str(b / "anchors.csv"),
                             "-o", "{f}"]),
        "filter log": (b / "measurements.csv",
                       ["filter", "{f}", "--anchors", str(b / "anchors.csv"), "-o", "{f}"]),
        "filter anchors": (b / "anchors.csv",
                           ["filter", str(b / "measurements.csv"), "--anchors", "{f}",
                            "-o", "{f}"]),
        "fuse ranges": (u / "measurements.csv",
                        ["fuse", "--ranges", "{f}", "--anchors", str(u / "anchors.csv"),
                         "-o", "{f}"]),
        "fuse nmea": (u / "gps.nmea",
                      ["fuse", "--ranges", str(u / "measurements.csv"), "--anchors",
                       str(u / "anchors.csv"), "--nmea", "{f}", "-o", "{f}"]),
    }
    for name, (f, argv) in cases.items():
        copy = tmp_path / "copies" / name.replace(" ", "_") / f.name
        copy.parent.mkdir(parents=True)
        shutil.copy(f, copy)
        before = copy.read_bytes()
        args = [a.replace("{f}", str(copy)) for a in argv]
        assert _code(args) == 2, name
        assert f"error: {copy}: output would overwrite an input" in capsys.readouterr().err
        assert copy.read_bytes() == before, name


def test_an_output_named_like_a_folder_is_refused(tmp_path, capsys):
    """`-o new/` (a folder that does not exist yet) wrote a file named `new` with exit 0
    (`Path` drops the separator; the CLI review found it).  Refused before any work, by
    the commands that write one file; a Dask dataset's `-o positions/` stays a folder."""
    assert main(["simulate", "uwb-cart", "--seed", "1", "--out", str(tmp_path / "u")]) == 0
    u = tmp_path / "u"
    for argv in (["locate", str(u / "measurements.csv"), "--anchors", str(u / "anchors.csv")],
                 ["track", str(u / "measurements.csv"), "--anchors", str(u / "anchors.csv")],
                 ["fuse", "--ranges", str(u / "measurements.csv"), "--anchors",
                  str(u / "anchors.csv")]):
        out = str(tmp_path / "new") + "/"
        assert _code([*argv, "-o", out]) == 2, argv[0]
        assert (f"error: {out}: names a folder (ends with a separator), expected a file"
                in capsys.readouterr().err)
        assert not (tmp_path / "new").exists()
    from robustloc.errors import OutputError
    from robustloc.io.atomic import atomic_output

    with pytest.raises(OutputError, match="names a folder"):
        with atomic_output(str(tmp_path / "x") + "/"):
            pass


@pytest.mark.parametrize(("text", "line", "words"), [
    ("\n\ntime,tag,anchor,range\n0,T,a,5\n", 1, "line 1 is blank: the first line must be "
                                                "the header"),
    ("time,tag,anchor,range\n0,\"T,a,5\n0,T,b,6\n", 2, "a quoted field opens here and "
                                                       "is never closed"),
    ("time,tag,anchor,range\n0,T,a,5\n0,T,b,6\n1,\"T,a,5\n", 4, "a quoted field opens "
                                                                "here"),
    ("", 1, "empty file (expected a header line)"),
])
def test_a_blank_first_line_and_an_unclosed_quote_are_named(tmp_path, capsys, text, line,
                                                            words):
    """A file whose first line is blank was an "empty file"; an unclosed quote gave
    pandas' "EOF inside string starting at row N" without a line (N counts records).
    Both now name the line (the CLI review)."""
    a = _w(tmp_path, "a.csv", "anchor,x,y\na,0,0\nb,10,0\nc,0,10\n")
    m = _w(tmp_path, "m.csv", text)
    _fails(capsys, ["locate", m, "--anchors", a, "-o", str(tmp_path / "p.csv")], m, line,
           words)
    assert not (tmp_path / "p.csv").exists()


@pytest.mark.parametrize("command", ["locate", "track"])
@pytest.mark.parametrize("newline", ["\n", "\r\n"])
def test_a_line_after_a_quoted_line_break_is_named_by_its_line(tmp_path, capsys, command,
                                                               newline):
    """A quoted field may hold a line break (RFC 4180 section 2.6).  Rows were numbered as
    records, so every error after one named a line too early: here the bad value is on
    line 8 (header 1, then four records of two lines each), and it was named line 5."""
    a = _w(tmp_path, "a.csv", "anchor,x,y\nA,0,0\nB,10,0\nC,0,10\nD,10,10\n")
    rows = "".join(f'0,"t{newline}1",{k},{v}\n'
                   for k, v in zip("ABCD", ("5", "5", "5", "abc"), strict=True))
    m = _w(tmp_path, "m.csv", "time,tag,anchor,range\n" + rows)
    _fails(capsys, [command, m, "--anchors", a, "-o", str(tmp_path / "p.csv")], m, 8,
           "column 'range': 'abc' is not a number")


def test_quoted_line_breaks_keep_line_numbers_across_chunks(tmp_path):
    """The streaming reader numbers each chunk from where the previous one ended, counting
    the lines its quoted fields took, and reads the same lines as the whole-file reader."""
    from robustloc.io import tables

    rows = ["0,T,A,5", '0,"T\nx",B,5', "1,T,A,5", '1,"a\r\nb\nc",B,6', "2,T,A,7"]
    m = _w(tmp_path, "m.csv", "time,tag,anchor,range\n" + "\n".join(rows) + "\n")
    whole = tables._read_raw(m, ["tag", "anchor"])
    assert whole.index.tolist() == [2, 3, 5, 6, 9]
    for chunk in (1, 2, 3):
        lines = [i for df in tables._iter_raw(m, chunk, ["tag", "anchor"]) for i in df.index]
        assert lines == [2, 3, 5, 6, 9], chunk


def test_fuse_and_filter_on_the_other_kind_of_log_name_the_header(tmp_path, capsys):
    """`fuse` on an RSSI log and `filter` on a range log said so without a line, where
    `locate` names line 1 for a header problem (the CLI review)."""
    a = _w(tmp_path, "a.csv", "anchor,x,y,A,n\na,0,0,-40,2\nb,10,0,-40,2\nc,0,10,-40,2\n")
    rssi = _w(tmp_path, "rssi.csv", "time,tag,anchor,rssi\n0,T,a,-60\n0,T,b,-62\n")
    rng = _w(tmp_path, "rng.csv", "time,tag,anchor,range\n0,T,a,5\n0,T,b,6\n")
    _fails(capsys, ["fuse", "--ranges", rssi, "--anchors", a, "-o",
                    str(tmp_path / "f.csv")], rssi, 1, "no 'range' column")
    _fails(capsys, ["filter", rng, "--anchors", a, "-o", str(tmp_path / "g.csv")], rng, 1,
           "needs an 'rssi' column")


def test_evaluate_refuses_an_empty_method_cell(tmp_path, capsys):
    """An empty `method` cell was scored as a method named "unknown" beside the file's
    named ones, where an empty tag or status is an error (the CLI review)."""
    p = _w(tmp_path, "p.csv", "time,tag,x,y,method,status\n0,T,1,1,nls,ok\n1,T,1,1,,ok\n")
    t = _w(tmp_path, "t.csv", "time,tag,x,y\n0,T,0,0\n1,T,0,0\n")
    _fails(capsys, ["evaluate", p, "--truth", t], p, 3, "column 'method': empty value")


def test_a_folder_output_that_fails_leaves_the_folder_as_it_was(tmp_path, capsys,
                                                               monkeypatch):
    """`simulate -o part` with a folder `part/truth.csv` replaced anchors, measurements
    and survey, then failed on truth.csv naming its temporary folder (the review).
    Every target is now checked before the first move, and a move that fails puts back
    what it replaced."""
    import os
    from pathlib import Path

    import robustloc.commands._folder as folder

    part = tmp_path / "part"
    part.mkdir()
    for name in ("anchors.csv", "measurements.csv", "survey.csv"):
        (part / name).write_text("old\n")
    (part / "truth.csv").mkdir()
    assert _code(["simulate", "ble-corridor", "--out", str(part)]) == 2
    assert (f"error: {part / 'truth.csv'}: is a folder, where this command writes a file"
            in capsys.readouterr().err)
    assert sorted(p.name for p in part.iterdir()) == ["anchors.csv", "measurements.csv",
                                                     "survey.csv", "truth.csv"]
    assert all((part / n).read_text() == "old\n"
               for n in ("anchors.csv", "measurements.csv", "survey.csv"))
    (part / "truth.csv").rmdir()
    real = os.replace
    calls = []

    def flaky(src, dst):  # the third move into the folder fails (a full disk, say)
        if Path(dst).parent == part and not str(Path(src).parent).endswith(".replaced"):
            calls.append(dst)
            if len(calls) == 3:
                raise OSError(28, "No space left on device")
        return real(src, dst)

    monkeypatch.setattr(folder.os, "replace", flaky)
    with pytest.raises(OSError):
        folder.write_folder(part, lambda d: [(d / n).write_text("new\n") for n in
                                             ("anchors.csv", "measurements.csv",
                                              "survey.csv", "truth.csv")])
    assert sorted(p.name for p in part.iterdir()) == ["anchors.csv", "measurements.csv",
                                                     "survey.csv"]
    assert all((part / n).read_text() == "old\n"
               for n in ("anchors.csv", "measurements.csv", "survey.csv"))
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".part")]


def test_montecarlo_and_spp_keep_their_inputs_and_their_stdout_data(tmp_path, capsys):
    """`montecarlo --anchors A -o A` replaced the anchors with the table (exit 0), and
    `-o -` of `montecarlo` and `spp` appended the text summary to the CSV on standard
    output (the review).  The input is refused; the summary goes to stderr."""
    import io

    from robustloc.paths import PACKAGE_DATA

    a = tmp_path / "sq.csv"
    a.write_text("anchor,x,y\nA,0,0\nB,10,0\nC,10,10\nD,0,10\n")
    before = a.read_bytes()
    assert _code(["montecarlo", "--anchors", str(a), "--trials", "50", "-o", str(a)]) == 2
    assert "output would overwrite an input" in capsys.readouterr().err
    assert a.read_bytes() == before
    assert _code(["montecarlo", "--anchors", str(a), "--trials", "50", "-o", "-"]) == 0
    cap = capsys.readouterr()
    table = pd.read_csv(io.StringIO(cap.out))
    assert "layout" in table.columns and table["trials"].eq(50).all()
    assert "observations" in cap.err
    g = PACKAGE_DATA / "gnss-geonet"
    assert _code(["spp", str(g / "07590920.05o"), str(g / "07590920_0000-0400.05n"),
                  "-o", "-"]) == 0
    cap = capsys.readouterr()
    sol = pd.read_csv(io.StringIO(cap.out))
    assert len(sol) == 120 and sol["time"].notna().all()
    assert "epochs solved" in cap.err


def test_reproduce_seed_and_an_empty_candidates_file_are_users_mistakes(tmp_path, capsys):
    """`reproduce --seed -1` ended in a ValueError traceback from the Monte Carlo (and left
    an empty report folder); `reliability --suggest --candidates` of a header-only file
    in a KeyError traceback (the review)."""
    assert _code(["reproduce", "--seed", "-1", "--only", "s40_integrity", "-o",
                  str(tmp_path / "rp")]) == 2
    assert "--seed" in capsys.readouterr().err and not (tmp_path / "rp").exists()
    a = _w(tmp_path, "sq.csv", "anchor,x,y\nA,0,0\nB,10,0\nC,10,10\nD,0,10\n")
    c = _w(tmp_path, "c0.csv", "x,y\n")
    _fails(capsys, ["reliability", "--anchors", a, "--suggest", "--candidates", c, "-o",
                    str(tmp_path / "rc"), "--no-maps"], c, 2,
           "candidates file has a header but no data rows")


def test_gnss_systems_and_reliability_options_that_did_nothing_or_broke(tmp_path, capsys):
    """From the review of the other commands: `--systems GG` put every satellite in twice
    (montecarlo: every epoch unavailable; simulate gnss: each satellite twice per epoch);
    `reliability --sigma 1e300` overflowed into blank maps; `reliability -o -` made a
    folder named "-"; `--candidates` without `--suggest` was ignored."""
    from robustloc.paths import PACKAGE_DATA

    g = PACKAGE_DATA / "gnss-geonet"
    for argv in (["montecarlo", "--gnss", "--systems", "GG", "--trials", "10"],
                 ["simulate", "gnss", "--systems", "gEg", "--out", str(tmp_path / "s")],
                 ["spp", str(g / "07590920.05o"), str(g / "07590920_0000-0400.05n"),
                  "--systems", "GG", "-o", str(tmp_path / "x.csv")]):
        assert _code(argv) == 2, argv[0]
        assert "listed twice" in capsys.readouterr().err
    a = _w(tmp_path, "sq.csv", "anchor,x,y\nA,0,0\nB,10,0\nC,10,10\nD,0,10\n")
    c = _w(tmp_path, "c.csv", "x,y\n5,12\n")
    assert _code(["reliability", "--anchors", a, "-o", str(tmp_path / "r"), "--sigma",
                  "1e300", "--no-maps"]) == 2
    assert "--sigma" in capsys.readouterr().err
    assert _code(["reliability", "--anchors", a, "-o", "-", "--no-maps"]) == 2
    assert "standard output cannot hold a folder" in capsys.readouterr().err
    assert _code(["reliability", "--anchors", a, "--candidates", c, "-o",
                  str(tmp_path / "r"), "--no-maps"]) == 2
    assert "--candidates goes with --suggest" in capsys.readouterr().err
    assert not (tmp_path / "r").exists() and not (tmp_path / "s").exists()


def test_spp_refuses_a_clock_file_of_another_day(tmp_path, capsys):
    """A --clk of another day gave no clock value, and the SP3's clocks were used without
    a word: the solution was byte-identical to the run without --clk (the review).
    A precise product that shares no time with the observations is refused."""
    from robustloc.paths import PACKAGE_DATA

    s = PACKAGE_DATA / "gnss-slac"
    clk = s / "COD0MGXFIN_20211181930_12M_30S_CLK.CLK"
    other = tmp_path / "next_day.CLK"
    other.write_text(clk.read_text().replace(" 2021 04 28 ", " 2021 04 29 "))
    argv = ["spp", str(s / "slac1180_1930-1940.21o"), "--sp3",
            str(s / "COD0MGXFIN_20211181905_60M_05M_ORB.SP3"), "-o", str(tmp_path / "x.csv")]
    assert _code([*argv, "--clk", str(other)]) == 2
    assert f"error: {other}: covers GPS seconds" in capsys.readouterr().err
    assert _code([*argv, "--clk", str(clk)]) == 0


def test_spp_and_reproduce_options_that_did_nothing_or_spoke_internals(tmp_path, capsys):
    """From the review of the other commands: `--inject-from` later than `--inject-until`
    injected nothing without a word; `--smooth` without `--iono iflc` answered in the
    solver's terms (`iono='iflc'`); `reproduce --data FILE` said the folder did not
    exist."""
    from robustloc.paths import PACKAGE_DATA

    g = PACKAGE_DATA / "gnss-geonet"
    base = ["spp", str(g / "07590920.05o"), str(g / "07590920_0000-0400.05n"), "-o",
            str(tmp_path / "s.csv")]
    assert _code([*base, "--raim", "--inject", "G11:20", "--inject-from", "796436400",
                  "--inject-until", "796436000"]) == 2
    assert "--inject-from (796436400) is later than --inject-until" in capsys.readouterr().err
    assert _code([*base, "--smooth", "10"]) == 2
    assert "--smooth needs --iono iflc" in capsys.readouterr().err
    assert not (tmp_path / "s.csv").exists()
    assert _code(["reproduce", "--data", str(g / "07590920.05o"), "--only", "s05_out_of_box",
                  "-o", str(tmp_path / "r")]) == 2
    assert "is a file, not a data folder" in capsys.readouterr().err


def test_montecarlo_refuses_a_geometry_that_fixes_nothing(tmp_path, capsys):
    """Four anchors on a line with the tag on it (the default position is their centroid)
    gave an all-NaN table with exit 0 (the review); it is refused, while the same
    anchors with the tag off the line run."""
    a = _w(tmp_path, "col.csv", "anchor,x,y\nA,0,0\nB,5,0\nC,10,0\nD,15,0\n")
    assert _code(["montecarlo", "--anchors", a, "--trials", "20"]) == 2
    assert "the geometry is singular" in capsys.readouterr().err
    assert _code(["montecarlo", "--anchors", a, "--trials", "20", "--position", "7.5,3",
                  "-o", str(tmp_path / "t.csv")]) == 0
    t = pd.read_csv(tmp_path / "t.csv")
    assert t.loc[t["n_faults"] == 0, "err_rms_m"].notna().all()


def test_a_navigation_file_after_an_option_is_read(tmp_path, capsys):
    """`spp OBS --raim NAV` was refused as "unrecognized arguments: NAV" (argparse fills
    a positional from the first run of positionals only; review 5 of stop 32).  It now
    gives the same rows as `spp OBS NAV --raim`; a leftover that is not a positional
    still gets argparse's message."""
    from robustloc.paths import PACKAGE_DATA

    slac = PACKAGE_DATA / "gnss-slac"
    obs, nav = str(slac / "slac1180_1930-1940.21o"), str(slac / "brdc1180_1700-2200.21n")
    a, b = tmp_path / "a.csv", tmp_path / "b.csv"
    assert main(["spp", obs, nav, "--raim", "--quiet", "-o", str(a)]) == 0
    assert main(["spp", obs, "--raim", nav, "--quiet", "-o", str(b)]) == 0
    assert a.read_bytes() == b.read_bytes()
    assert len(a.read_text().splitlines()) > 10
    capsys.readouterr()
    assert _code(["spp", obs, "--raim", nav, "--bogus", "-o", str(b)]) == 2
    assert "unrecognized arguments: --bogus" in capsys.readouterr().err
    assert _code(["locate", "--anchors", nav, "-o", str(b), obs, "extra"]) == 2
    assert "unrecognized arguments: extra" in capsys.readouterr().err


def test_a_file_an_earlier_run_left_in_an_output_folder_is_named(tmp_path, capsys):
    """``simulate --disturbance`` then ``simulate`` without it into the same folder left
    the first run's ``blocked.csv`` beside the new files, without a word (the no-loss
    review; ``stats`` did the same with ``per_bin.csv``).  It is named on stderr, and
    kept: it may be the user's."""
    out = tmp_path / "sim"
    assert main(["simulate", "ble-corridor", "--seed", "1", "--disturbance", "--out",
                 str(out)]) == 0
    assert (out / "blocked.csv").is_file()
    old = (out / "blocked.csv").read_bytes()
    capsys.readouterr()
    assert main(["simulate", "ble-corridor", "--seed", "2", "--out", str(out)]) == 0
    err = capsys.readouterr().err
    assert (f"warning: {out / 'blocked.csv'} is from an earlier run: this run wrote no "
            "blocked.csv") in err
    assert (out / "blocked.csv").read_bytes() == old
    assert main(["simulate", "ble-corridor", "--seed", "2", "--disturbance", "--out",
                 str(out)]) == 0
    assert "earlier run" not in capsys.readouterr().err


@pytest.mark.parametrize(("sep", "name"), [(";", "semicolons"), ("\t", "tabs")])
def test_a_file_with_another_separator_is_named_so(tmp_path, capsys, sep, name):
    """A semicolon- or tab-separated file got "missing column(s) rssi or range (has:
    time;tag;...)" without a word on the separator (the no-loss review)."""
    a = _w(tmp_path, "a.csv", "anchor,x,y\na,0,0\nb,10,0\nc,0,10\n")
    m = _w(tmp_path, "m.csv", sep.join(["time", "tag", "anchor", "range"]) + "\n"
           + sep.join(["0", "T", "a", "5"]) + "\n")
    _fails(capsys, ["locate", m, "--anchors", a, "-o", str(tmp_path / "p.csv")], m, 1,
           f"the header is one column: its fields are separated by {name}, and robustloc "
           "reads commas (CSV)")


def test_a_line_of_white_space_is_a_blank_line(tmp_path):
    """Blank lines are skipped, but a line holding only a tab was an "empty id" error
    (the no-loss review): it is blank too.  A tab in a field of a real row is still
    refused with its line."""
    a = _w(tmp_path, "a.csv", "anchor,x,y\na,0,0\nb,10,0\nc,0,10\n")
    m = _w(tmp_path, "m.csv", "time,tag,anchor,range\n0,T,a,5\n0,T,b,6\n\t\n0,T,c,7\n \t \n")
    out = tmp_path / "p.csv"
    assert main(["locate", m, "--anchors", a, "-o", str(out), "--quiet"]) == 0
    assert len(pd.read_csv(out)) == 1
    bad = _w(tmp_path, "bad.csv", "time,tag,anchor,range\n0,T,a,5\n\t,T,b,6\n")
    assert _code(["locate", bad, "--anchors", a, "-o", str(out)]) == 2


def test_a_comment_line_between_data_lines_is_named(tmp_path, capsys):
    """A ``#`` line in the middle of a file was "column 'tag': empty id" (the no-loss
    review): it is named as a comment, with its line, in every reader that meets it."""
    a = _w(tmp_path, "a.csv", "anchor,x,y\na,0,0\nb,10,0\nc,0,10\n")
    m = _w(tmp_path, "m.csv", "time,tag,anchor,range\n0,T,a,5\n0,T,b,6\n"
           "  # tag restarted\n0,T,c,7\n")
    for extra in ([], ["--chunk-rows", "1"]):
        _fails(capsys, ["locate", m, "--anchors", a, "-o", str(tmp_path / "p.csv"), *extra],
               m, 4, "the line looks like a comment ('# tag restarted'): robustloc reads "
               "no comment lines")


def test_a_comment_line_above_the_header_is_named(tmp_path, capsys):
    """A ``#`` comment as line 1 became the header: "expected 1 fields, found 4" (the
    no-loss review).  The message says that line 1 looks like a comment."""
    a = _w(tmp_path, "a.csv", "anchor,x,y\na,0,0\nb,10,0\nc,0,10\n")
    m = _w(tmp_path, "m.csv", "# logged 2026-12-04\ntime,tag,anchor,range\n0,T,a,5\n")
    _fails(capsys, ["locate", m, "--anchors", a, "-o", str(tmp_path / "p.csv")], m, 2,
           "line 1 looks like a comment: robustloc reads no comment lines")
