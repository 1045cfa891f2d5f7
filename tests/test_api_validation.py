"""The Python API's checks of its arguments (robustloc.api): what the command line refuses,
the API refuses with the same words (an :class:`InputError`), and no argument makes it hang
or raise a raw pandas / NumPy error."""

from __future__ import annotations

import subprocess
import sys
import threading
from collections.abc import Callable
from importlib.resources import files
from typing import Any

import numpy as np
import pandas as pd
import pytest
from _stderr import without_jit_notice  # (tests/_stderr.py)

import robustloc
from robustloc import InputError
from robustloc.api import RobustlocWarning
from robustloc.cli import main

ANCHORS = pd.DataFrame({"anchor": list("abcd"), "x": [0.0, 10.0, 10.0, 0.0],
                        "y": [0.0, 0.0, 10.0, 10.0]})


def _walk(n: int = 30, seed: int = 0) -> pd.DataFrame:
    """A range log of one tag walking across the 10 m square, ``n`` epochs 0.5 s apart."""
    rng = np.random.default_rng(seed)
    t = np.arange(n) * 0.5
    xy = np.c_[2.0 + 0.2 * t, 5.0 + np.sin(0.3 * t)]
    d = np.hypot(ANCHORS.x.to_numpy() - xy[:, :1], ANCHORS.y.to_numpy() - xy[:, 1:])
    d = d + rng.normal(0.0, 0.05, d.shape)
    return pd.DataFrame({"time": np.repeat(t, 4), "tag": "t",
                         "anchor": np.tile(ANCHORS.anchor, n), "range": d.ravel()})


def _within(seconds: float, fn: Callable[[], Any]) -> Any:
    """``fn()``'s result, failing the test if it takes longer than ``seconds`` (the call
    is left running in a daemon thread: a hang fails instead of blocking the suite)."""
    out: dict[str, Any] = {}

    def run() -> None:
        try:
            out["value"] = fn()
        except BaseException as exc:  # noqa: BLE001 - re-raised below
            out["error"] = exc

    worker = threading.Thread(target=run, daemon=True)
    worker.start()
    worker.join(seconds)
    assert not worker.is_alive(), f"still running after {seconds} s"
    if "error" in out:
        raise out["error"]
    return out["value"]


def _states(frame: pd.DataFrame) -> np.ndarray:
    return frame[["x", "y", "vx", "vy", "var_x", "var_y", "cov_xy", "hpl"]].to_numpy(float)


# ---------------------------------------------------------------- track: smoothers


def test_fixed_lag_longer_than_the_log_is_the_fixed_interval_smoother_and_quick():
    """A lag beyond a segment's end is the RTS smoother over it; the work is bounded by
    the segment, not by the lag (a lag of 10**9 looped 10**9 times per segment)."""
    log = _walk(30)
    rts = robustloc.track(log, ANCHORS, smooth=True)
    full = robustloc.track(log, ANCHORS, fixed_lag=29)  # the segment's length - 1
    assert set(rts["status"]) == {"ok"}
    np.testing.assert_allclose(_states(full), _states(rts), rtol=0, atol=1e-9)
    huge = _within(30.0, lambda: robustloc.track(log, ANCHORS, fixed_lag=10**9))
    np.testing.assert_allclose(_states(huge), _states(rts), rtol=0, atol=1e-9)
    assert huge["method"].iloc[0] == "track-cv-ekf-lag1000000000"
    # a lag shorter than the log still smooths less than the whole log
    assert not np.allclose(_states(robustloc.track(log, ANCHORS, fixed_lag=2)), _states(rts))


def test_fixed_lag_longer_than_the_log_cli_is_quick(tmp_path):
    log = tmp_path / "m.csv"
    anchors = tmp_path / "a.csv"
    _walk(30).to_csv(log, index=False)
    ANCHORS.to_csv(anchors, index=False)
    # a child process, killed if it hangs
    cli = "import sys; from robustloc.cli import main; sys.exit(main(sys.argv[1:]))"
    subprocess.run([sys.executable, "-c", cli, "track", str(log), "--anchors",
                    str(anchors), "--fixed-lag", str(10**9), "-o", str(tmp_path / "t.csv")],
                   check=True, timeout=60, capture_output=True)
    assert len(pd.read_csv(tmp_path / "t.csv")) == 30


def test_smooth_and_fixed_lag_are_exclusive_as_on_the_command_line(tmp_path, capsys):
    log = tmp_path / "m.csv"
    anchors = tmp_path / "a.csv"
    _walk(10).to_csv(log, index=False)
    ANCHORS.to_csv(anchors, index=False)
    assert main(["track", str(log), "--anchors", str(anchors), "--smooth", "--fixed-lag",
                 "2", "-o", str(tmp_path / "t.csv")]) == 2
    err = capsys.readouterr().err.strip().splitlines()[-1]
    with pytest.raises(InputError) as exc:
        robustloc.track(log, anchors, smooth=True, fixed_lag=2)
    assert str(exc.value) == "argument --fixed-lag: not allowed with argument --smooth"
    assert err.endswith(str(exc.value))


# ---------------------------------------------------------------- frames: duplicate columns


def _twice(df: pd.DataFrame, column: str) -> pd.DataFrame:
    return pd.concat([df, df[[column]]], axis=1)


def _truth(log: pd.DataFrame) -> pd.DataFrame:
    t = np.unique(log["time"].to_numpy())
    return pd.DataFrame({"time": t, "tag": "t", "x": 2.0 + 0.2 * t,
                         "y": 5.0 + np.sin(0.3 * t)})


def _positions(log: pd.DataFrame) -> pd.DataFrame:
    return _truth(log).assign(method="nls", status="ok")


def _survey() -> pd.DataFrame:
    d = np.array([1.0, 2.0, 4.0, 6.0, 8.0])
    return pd.DataFrame({"anchor": np.repeat(["a", "b"], 5), "distance": np.tile(d, 2),
                         "range": np.tile(1.05 * d + 0.3 + [0.01, -0.02, 0.0, 0.02, -0.01],
                                          2)})


@pytest.mark.parametrize(("what", "column", "call"), [
    ("measurements", "range", lambda m: robustloc.locate(_twice(m, "range"), ANCHORS)),
    ("measurements", "tag", lambda m: robustloc.track(_twice(m, "tag"), ANCHORS)),
    ("measurements", "range", lambda m: robustloc.read_measurements(_twice(m, "range"))),
    ("anchors", "x", lambda m: robustloc.locate(m, _twice(ANCHORS, "x"))),
    ("anchors", "anchor", lambda m: robustloc.read_anchors(_twice(ANCHORS, "anchor"))),
    ("anchors", "y", lambda m: robustloc.read_measurements(m, _twice(ANCHORS, "y"))),
    ("truth", "x", lambda m: robustloc.evaluate(_positions(m), _twice(_truth(m), "x"))),
    ("positions", "time",
     lambda m: robustloc.evaluate(_twice(_positions(m), "time"), _truth(m))),
    ("positions", "status", lambda m: robustloc.read_positions(_twice(_positions(m), "status"))),
    ("survey", "range", lambda m: robustloc.calibrate(_twice(_survey(), "range"))),
    ("truth", "time", lambda m: robustloc.calibrate(measurements=m, anchors=ANCHORS,
                                                    truth=_twice(_truth(m), "time"))),
    ("measurements", "anchor",
     lambda m: robustloc.calibrate(measurements=_twice(m, "anchor"), anchors=ANCHORS,
                                   truth=_truth(m))),
    ("measurements", "range",
     lambda m: robustloc.calibrate(self_log=_twice(m, "range"), anchors=ANCHORS)),
])
def test_a_frame_naming_a_column_twice_is_an_input_error(what, column, call):
    """A file naming a column twice is refused on its header line; a frame was a raw
    pandas TypeError (or one of the two columns silently used)."""
    with pytest.raises(InputError) as exc:
        call(_walk(10))
    assert str(exc.value) == f"<{what} DataFrame>: duplicate column {column!r}"


def test_a_read_frame_naming_a_column_twice_names_its_file(tmp_path):
    path = tmp_path / "m.csv"
    _walk(10).to_csv(path, index=False)
    log = robustloc.read_measurements(path)
    with pytest.raises(InputError, match=f"^{path}: duplicate column 'range'$"):
        robustloc.locate(_twice(log, "range"), ANCHORS)


# ---------------------------------------------------------------- evaluate: options


@pytest.mark.parametrize(("options", "argv"), [
    ({"time_tolerance": -1}, ["--time-tolerance", "-1"]),
    ({"time_tolerance": -1.0}, ["--time-tolerance", "-1.0"]),
    ({"time_tolerance": float("nan")}, ["--time-tolerance", "nan"]),
    ({"time_tolerance": float("inf")}, ["--time-tolerance", "inf"]),
    ({"time_tolerance": "abc"}, ["--time-tolerance", "abc"]),
    ({"baseline": "zzz"}, ["--baseline", "zzz"]),
])
def test_evaluate_refuses_what_the_command_refuses(tmp_path, capsys, options, argv):
    """A negative tolerance was a raw ValueError, a NaN one matched every position to the
    nearest truth, an unknown baseline gave NaN improvements, silently."""
    log = _walk(10)
    pos, truth = tmp_path / "pos.csv", tmp_path / "truth.csv"
    _positions(log).assign(x=lambda f: f.x + 0.1).to_csv(pos, index=False)
    # truth 10 ms off the positions: matched only by a (wrongly) unbounded tolerance
    off = 0.01 if "time_tolerance" in options else 0.0
    _truth(log).assign(time=lambda f: f.time + off).to_csv(truth, index=False)
    assert main(["evaluate", str(pos), "--truth", str(truth), *argv]) == 2
    err = capsys.readouterr().err.strip().splitlines()[-1]
    for p in (pos, pd.read_csv(pos)):
        with pytest.raises(InputError) as exc:
            robustloc.evaluate(p, truth, **options)
        name = str(pos) if p is pos else "<positions DataFrame>"
        # argparse prefixes its refusals with "robustloc evaluate: error: ", ours "error: "
        assert err.endswith(str(exc.value).replace(name, str(pos)))
    assert "time_tolerance" not in options or str(exc.value).startswith(
        "argument --time-tolerance: expected a")


def test_evaluate_takes_a_baseline_of_the_file_or_ls():
    log = _walk(10)
    pos = pd.concat([_positions(log).assign(x=lambda f: f.x + 0.2),
                     _positions(log).assign(x=lambda f: f.x + 0.1, method="igg")])
    got = robustloc.evaluate(pos, _truth(log), baseline="nls")
    assert np.allclose(got.loc[got.method == "igg", "rms_impr_pct"], 50.0)
    no_ls = robustloc.evaluate(pos, _truth(log))  # the default, absent: NaN, no error
    assert no_ls["rms_impr_pct"].isna().all()


# ---------------------------------------------------------------- calibrate: truth


def _range_log() -> tuple[pd.DataFrame, pd.DataFrame]:
    """40 epochs of ranges 5 % long and 0.3 m late, and their truth."""
    rng = np.random.default_rng(0)
    xy = rng.uniform(1, 9, (40, 2))
    d = np.hypot(ANCHORS.x.to_numpy() - xy[:, :1], ANCHORS.y.to_numpy() - xy[:, 1:])
    d = d * 1.05 + 0.3 + rng.normal(0, 0.05, (40, 4))
    log = pd.DataFrame({"time": np.repeat(np.arange(40.0), 4), "tag": "t",
                        "anchor": np.tile(ANCHORS.anchor, 40), "range": d.ravel()})
    truth = pd.DataFrame({"time": np.arange(40.0), "tag": "t", "x": xy[:, 0], "y": xy[:, 1]})
    return log, truth


def test_calibrate_refuses_duplicate_truth_as_evaluate_does(tmp_path, capsys):
    """Two truth rows for one (time, tag) were used silently, the fit depending on their
    order; evaluate refused the same truth."""
    log, truth = _range_log()
    good = robustloc.calibrate(measurements=log, truth=truth, anchors=ANCHORS, scale=True)
    assert np.allclose(good["scale"], 1.05, atol=0.02)
    dup = pd.concat([truth, truth.assign(x=truth.x + 5)], ignore_index=True)
    want = "<truth DataFrame>:42: duplicate truth for time 0.0 and tag 't'"
    with pytest.raises(InputError) as exc:
        robustloc.calibrate(measurements=log, truth=dup, anchors=ANCHORS, scale=True)
    assert str(exc.value) == want
    with pytest.raises(InputError) as exc:  # the other order: the same refusal
        robustloc.calibrate(measurements=log, truth=dup[::-1], anchors=ANCHORS, scale=True)
    assert str(exc.value) == "<truth DataFrame>:42: duplicate truth for time 39.0 and tag 't'"
    with pytest.raises(InputError) as exc:
        robustloc.evaluate(truth.assign(method="nls", status="ok"), dup)
    assert str(exc.value) == want


def test_calibrate_command_refuses_duplicate_truth_naming_the_line(tmp_path, capsys):
    log, truth = _range_log()
    dup = pd.concat([truth, truth.assign(x=truth.x + 5)], ignore_index=True)
    paths = {k: tmp_path / f"{k}.csv" for k in ("m", "t", "a")}
    log.to_csv(paths["m"], index=False)
    dup.to_csv(paths["t"], index=False)
    ANCHORS.to_csv(paths["a"], index=False)
    assert main(["calibrate", "--measurements", str(paths["m"]), "--truth", str(paths["t"]),
                 "--anchors", str(paths["a"]), "--scale", "-o", str(tmp_path / "c.csv")]) == 2
    err = capsys.readouterr().err.strip().splitlines()[-1]
    assert err == f"error: {paths['t']}:42: duplicate truth for time 0.0 and tag 't'"
    with pytest.raises(InputError) as exc:
        robustloc.calibrate(measurements=paths["m"], truth=paths["t"], anchors=paths["a"],
                            scale=True)
    assert err == f"error: {exc.value}"


# ---------------------------------------------------------------- locate: warnings


def test_locate_warns_of_an_anchor_it_does_not_use_as_the_command_does(tmp_path, capsys):
    """An anchor far outside the layout (a typo) was dropped with only the summary's
    anchors_not_used; the command warns on stderr, the API now warns too."""
    log = pd.concat([_walk(10), _walk(10).query("anchor == 'a'").assign(anchor="far")])
    anchors = pd.concat([ANCHORS, pd.DataFrame({"anchor": ["far"], "x": [1e4], "y": [0.0]})])
    paths = {"m": tmp_path / "m.csv", "a": tmp_path / "a.csv"}
    log.to_csv(paths["m"], index=False)
    anchors.to_csv(paths["a"], index=False)
    assert main(["locate", str(paths["m"]), "--anchors", str(paths["a"]),
                 "-o", str(tmp_path / "p.csv"), "--quiet"]) == 0
    err = without_jit_notice(capsys.readouterr().err).strip().splitlines()
    assert len(err) == 1 and err[0].startswith("warning: ")
    for a, name in ((paths["a"], str(paths["a"])), (anchors, "<anchors DataFrame>")):
        with pytest.warns(RobustlocWarning) as rec:
            pos = robustloc.locate(paths["m"], a)
        assert [str(w.message) for w in rec] == [
            err[0][len("warning: "):].replace(str(paths["a"]), name)]
        assert rec[0].filename == __file__  # points at the caller
        assert pos.attrs["summary"]["anchors_not_used"] == ["far"]
        assert "far" not in ",".join(pos["excluded"])


def test_locate_without_a_far_anchor_does_not_warn():
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("error", RobustlocWarning)
        robustloc.locate(_walk(10), ANCHORS)


# ---------------------------------------------------------------- arguments of the wrong kind

GEONET = files("robustloc") / "data" / "gnss-geonet"
OBS, NAV = GEONET / "07590920.05o", GEONET / "07590920_0000-0400.05n"
METHODS = "auto, ls, wls, nls, huber, hampel, igg, igg3, asym, lege, snooping"


@pytest.mark.parametrize(("call", "message"), [
    (lambda m: robustloc.locate(m, ANCHORS, "huber", params={"c": "abc"}),
     "--param expects NAME=NUMBER (finite), got 'c=abc'"),
    (lambda m: robustloc.locate(m, ANCHORS, "huber", params=[("c", 1.0)]),
     "argument --param: expected a mapping of NAME to NUMBER, got list"),
    (lambda m: robustloc.locate(m, ANCHORS, method=None),
     f"argument --method: expected one or more of {METHODS}, got None"),
    (lambda m: robustloc.locate(m, ANCHORS, method=5),
     f"argument --method: expected one or more of {METHODS}, got 5"),
    (lambda m: robustloc.spp(OBS, NAV, reference="1,2,3"),
     "--reference: expected X,Y,Z ECEF metres of a point near the Earth's surface (norm "
     "6.2e6 .. 6.5e6 m), got '1,2,3'"),
    (lambda m: robustloc.spp(OBS, NAV, reference=("x", 1.0, 2.0)),
     "--reference: expected X,Y,Z ECEF metres of a point near the Earth's surface (norm "
     "6.2e6 .. 6.5e6 m), got ('x', 1.0, 2.0)"),
    (lambda m: robustloc.spp(OBS, NAV, inject={"G11": "x"}),
     "--inject: expected PRN:BIAS_M, got 'G11:x'"),
    (lambda m: robustloc.spp(OBS, NAV, inject=[("G11", 20.0)]),
     "--inject: expected a mapping of PRN to BIAS_M, got list"),
    (lambda m: robustloc.spp(OBS, None), "give at least one navigation file or --sp3"),
])
def test_a_misused_option_is_an_input_error(call, message):
    """Each raised a raw ValueError / TypeError / AttributeError."""
    with pytest.raises(InputError) as exc:
        call(_walk(4))
    assert str(exc.value) == message


@pytest.mark.parametrize(("call", "message"), [
    (lambda p: robustloc.read_positions(None),
     "positions: expected a DataFrame or a path, got NoneType"),
    (lambda p: robustloc.read_anchors(5), "anchors: expected a DataFrame or a path, got int"),
    (lambda p: robustloc.read_truth(b"truth.csv"),
     "truth: expected a DataFrame or a path, got bytes"),
    (lambda p: robustloc.read_measurements(_walk(4), 5),
     "anchors: expected a DataFrame, a path or a sequence of anchor ids, got int"),
    (lambda p: robustloc.evaluate(None, _truth(_walk(4))),
     "positions: expected a DataFrame or a path, got NoneType"),
    (lambda p: robustloc.evaluate(_positions(_walk(4)), 1.5),
     "truth: expected a DataFrame or a path, got float"),
    (lambda p: robustloc.write_positions(_positions(_walk(4)), None),
     "path: expected a path, got NoneType"),
    (lambda p: robustloc.write_positions(_positions(_walk(4))["x"], p),
     "positions: expected a DataFrame, got Series"),
    (lambda p: robustloc.calibrate(survey=[1, 2]),
     "survey: expected a DataFrame or a path, got list"),
    (lambda p: robustloc.calibrate(_survey(), anchors=3),
     "anchors: expected a DataFrame or a path, got int"),
    (lambda p: robustloc.track(_walk(4), None),
     "anchors: expected a DataFrame or a path, got NoneType"),
    (lambda p: robustloc.spp(None, NAV), "obs: expected a path, got NoneType"),
    (lambda p: robustloc.spp(OBS, [NAV, 3]), "nav: expected a path, got int"),
    (lambda p: robustloc.spp(OBS, sp3=1), "sp3: expected a path, got int"),
])
def test_an_argument_of_the_wrong_type_is_an_input_error_and_a_type_error(
        tmp_path, call, message):
    """Each raised a raw TypeError or AttributeError from pandas or os.fspath; now the
    InputError of every mistake, still a TypeError (as ``locate(42, ...)`` was)."""
    with pytest.raises(InputError) as exc:
        call(tmp_path / "p.csv")
    assert str(exc.value) == message
    assert isinstance(exc.value, TypeError)
    assert not (tmp_path / "p.csv").exists()


def test_spp_takes_the_command_lines_text_for_reference_and_inject():
    ref = (-3961904.9, 3348993.8, 3698211.9)
    a = robustloc.spp(OBS, NAV, systems="G", raim=True, reference=ref, inject={"G11": 20.0})
    b = robustloc.spp(OBS, NAV, systems="G", raim=True, reference=",".join(map(str, ref)),
                      inject="G11:20")
    assert a.attrs["summary"] == b.attrs["summary"]
    pd.testing.assert_frame_equal(a, b)  # every epoch's solution, not only the counts
    # and the injected bias is applied: without it the solutions differ
    c = robustloc.spp(OBS, NAV, systems="G", raim=True, reference=ref)
    assert not np.allclose(a[["x", "y", "z"]].to_numpy(float), c[["x", "y", "z"]].to_numpy(float),
                           equal_nan=True)


def test_write_positions_refuses_a_frame_naming_a_column_twice(tmp_path):
    """It wrote a header naming the column twice, a file read_positions refuses."""
    pos = robustloc.locate(_walk(4), ANCHORS)
    with pytest.raises(InputError) as exc:
        robustloc.write_positions(_twice(pos, "x"), tmp_path / "p.csv")
    assert str(exc.value) == "<positions DataFrame>: duplicate column 'x'"
    assert not (tmp_path / "p.csv").exists()
    robustloc.write_positions(pos, tmp_path / "p.csv")
    assert robustloc.read_positions(tmp_path / "p.csv")["x"].tolist() == pos["x"].tolist()


def test_empty_measurements_frame_is_refused_as_an_empty_file_is(tmp_path):
    """``read_measurements`` of an empty DataFrame returned 0 rows where an empty file,
    ``read_truth`` of an empty frame and ``locate`` refuse one ("no data rows")."""
    import robustloc

    empty = pd.DataFrame({"time": [], "tag": [], "anchor": [], "range": []})
    with pytest.raises(robustloc.InputError, match="no data rows"):
        robustloc.read_measurements(empty)
    f = tmp_path / "m.csv"
    f.write_text("time,tag,anchor,range\n")
    with pytest.raises(robustloc.InputError, match="no data rows"):
        robustloc.read_measurements(f)


def test_write_positions_writes_a_timestamp_time_as_the_readers_read_it(tmp_path):
    """A datetime ``time`` column was written as text that ``read_positions`` refuses; it
    is written as seconds since the Unix epoch, the value a Parquet timestamp column is
    read as, so the file reads back."""
    import robustloc

    t = pd.to_datetime(["2026-12-02T10:00:00", "2026-12-02T10:00:01.500"], utc=True,
                       format="ISO8601")
    pos = pd.DataFrame({"time": t, "tag": "t", "x": [1.0, 2.0], "y": [0.0, 0.5],
                        "method": "nls", "status": "ok", "n_used": 4, "sigma0": 0.1,
                        "excluded": ""})
    for name in ("p.csv", "p.parquet"):
        back = robustloc.read_positions(robustloc.write_positions(pos, tmp_path / name))
        np.testing.assert_array_equal(back["time"], [1796205600.0, 1796205601.5])


def test_yes_no_arguments_take_only_booleans(tmp_path):
    """``range_calibration="no"`` was taken as true (a non-empty string); a yes/no
    argument of another kind is now refused, NumPy booleans and ``scale=None`` (the
    default) accepted."""
    import robustloc

    a4 = pd.DataFrame({"anchor": list("abcd"), "x": [0.0, 10, 10, 0], "y": [0.0, 0, 10, 10]})
    d = np.hypot(a4.x - 3, a4.y - 4).to_numpy()
    log = pd.DataFrame({"time": 0.0, "tag": "t", "anchor": a4.anchor, "range": d})
    for bad in ("no", 0, [True]):
        with pytest.raises(InputError, match="range_calibration: expected True or False"):
            robustloc.locate(log, a4, range_calibration=bad)
        with pytest.raises(TypeError):
            robustloc.track(log, a4, smooth=bad)
    ok = robustloc.locate(log, a4, range_calibration=np.bool_(False))
    assert ok["status"].tolist() == robustloc.locate(log, a4, range_calibration=False)[
        "status"].tolist()


def test_frame_column_names_are_stripped_as_csv_headers_are(tmp_path):
    """A CSV header's names are stripped of surrounding spaces; a DataFrame column named
    ``" time"`` was "missing column time".  Both now give the same positions."""
    import robustloc

    a4 = pd.DataFrame({"anchor": list("abcd"), "x": [0.0, 10, 10, 0], "y": [0.0, 0, 10, 10]})
    d = np.hypot(a4.x - 3, a4.y - 4).to_numpy()
    log = pd.DataFrame({"time": 0.0, "tag": "t", "anchor": a4.anchor, "range": d})
    spaced = log.rename(columns={"time": " time", "range": "range "})
    pd.testing.assert_frame_equal(robustloc.locate(spaced, a4), robustloc.locate(log, a4))
    f = tmp_path / "m.csv"
    spaced.to_csv(f, index=False)
    pd.testing.assert_frame_equal(robustloc.locate(f, a4).drop(columns=[]),
                                  robustloc.locate(log, a4))


def test_a_partly_empty_sigma_column_is_refused_naming_the_anchor(tmp_path):
    """An anchors file giving ``sigma`` for some anchors and leaving it empty for others
    was refused without naming the anchor ("must be positive and finite") by locate, track
    and the service alike.  Now each names the first anchor without one and its line; an
    all-empty column means "not given" (equal weights), and ``--sigma`` overrides it."""
    from robustloc.io import read_anchors
    from robustloc.service.processor import LocateProcessor

    path = tmp_path / "anchors.csv"
    path.write_text("anchor,x,y,sigma\na,0,0,0.1\nb,10,0,\nc,10,10,0.1\nd,0,10,0.2\n")
    log = tmp_path / "m.csv"
    _walk().to_csv(log, index=False)
    want = f"{path}:3: anchor 'b' has no sigma while other anchors have one"
    for cmd in ("locate", "track"):
        with pytest.raises(InputError) as err:
            getattr(robustloc, cmd)(log, path)
        assert str(err.value).startswith(want)
        assert main([cmd, str(log), "--anchors", str(path), "-o", str(tmp_path / "o.csv")]) == 2
        assert not (tmp_path / "o.csv").exists()
    with pytest.raises(InputError, match="anchor 'b' has no sigma"):
        LocateProcessor(read_anchors(path))
    frame = ANCHORS.assign(sigma=[0.1, 0.1, np.nan, 0.1])
    with pytest.raises(InputError, match="anchor 'c' has no sigma"):
        robustloc.locate(_walk(), frame)
    # the whole column empty: not given, the fixes of no column at all; --sigma overrides
    empty = robustloc.locate(_walk(), ANCHORS.assign(sigma=np.nan))
    pd.testing.assert_frame_equal(empty, robustloc.locate(_walk(), ANCHORS))
    assert robustloc.locate(_walk(), path, sigma=0.1)["status"].isin(["ok"]).any()


@pytest.mark.parametrize(("cmd", "argv", "api", "words"), [
    ("locate", ["--domain", "rssi"], {"domain": "rssi"}, "--domain rssi applies"),
    ("locate", ["--model", "friis"], {"model": "friis"}, "--model friis applies"),
    ("locate", ["--domain", "rssi", "--model", "friis"], {"domain": "rssi", "model": "friis"},
     "--domain rssi and --model friis apply"),
    ("track", ["--domain", "rssi"], {"domain": "rssi"}, "--domain rssi applies"),
])
def test_rssi_only_options_on_a_range_log_are_refused(tmp_path, cmd, argv, api, words):
    """``--domain rssi`` and ``--model`` (path-loss columns) mean nothing for ranges; they
    were accepted and silently ignored (exit 0).  Now the command and the API refuse them,
    naming the log's header, and write nothing."""
    log = tmp_path / "m.csv"
    _walk().to_csv(log, index=False)
    anchors = tmp_path / "a.csv"
    ANCHORS.to_csv(anchors, index=False)
    out = tmp_path / "o.csv"
    assert main([cmd, str(log), "--anchors", str(anchors), "-o", str(out), *argv]) == 2
    assert not out.exists()
    with pytest.raises(InputError) as err:
        getattr(robustloc, cmd)(log, anchors, **api)
    pronoun = "them" if " and " in words else "it"
    assert str(err.value) == (f"{log}:1: {words} to RSSI measurements, but this log holds "
                              f"ranges (a range column): leave {pronoun} out")
    # without them, the same log runs
    assert main([cmd, str(log), "--anchors", str(anchors), "-o", str(out)]) == 0


def test_standard_input_is_read_anew_by_each_call(monkeypatch):
    """The copy of standard input (``-``) lived as long as the process: a program calling
    the API twice on ``-`` got the first call's data the second time.  Each call now
    reads its own input, and leaves no copy behind."""
    import glob
    import io
    import tempfile

    def spools() -> set[str]:
        return set(glob.glob(f"{tempfile.gettempdir()}/robustloc-stdin-*"))

    before = spools()
    for seed in (0, 1):
        log = _walk(seed=seed)
        monkeypatch.setattr(sys, "stdin", io.TextIOWrapper(io.BytesIO(
            log.to_csv(index=False).encode())))
        got = robustloc.read_measurements("-")
        np.testing.assert_allclose(got["range"].to_numpy(), log["range"].to_numpy())
        monkeypatch.setattr(sys, "stdin", io.TextIOWrapper(io.BytesIO(
            log.to_csv(index=False).encode())))
        pos = robustloc.locate("-", ANCHORS)
        pd.testing.assert_frame_equal(pos, robustloc.locate(log, ANCHORS))
        assert spools() == before


def test_complex_numbers_are_refused_not_cut_to_their_real_part():
    """Complex ranges (or anchor coordinates) were located by their real part, the only
    sign a ComplexWarning from pandas' insides (the review of 2026-12-06)."""
    from robustloc.estimators.ranging import Locator

    anchors = pd.DataFrame({"anchor": ["a", "b", "c"], "x": [0.0, 10.0, 0.0],
                            "y": [0.0, 0.0, 10.0]})
    meas = pd.DataFrame({"time": 0.0, "tag": "t", "anchor": ["a", "b", "c"],
                         "range": [5.0, 7.0, 7.0]})
    with pytest.raises(InputError, match="column 'range' holds complex numbers"):
        robustloc.locate(meas.assign(range=meas["range"] + 5j), anchors)
    with pytest.raises(InputError, match="column 'range' holds complex numbers"):
        robustloc.read_measurements(meas.assign(range=meas["range"].astype(object) + 1j))
    with pytest.raises(InputError, match="column 'x' holds complex numbers"):
        robustloc.locate(meas, anchors.assign(x=anchors["x"] + 100j))
    xy = anchors[["x", "y"]].to_numpy()
    with pytest.raises(TypeError, match="values holds complex numbers"):
        Locator("nls").solve(xy, np.array([[5.0, 7.0, 7.0]]) + 1j)
    with pytest.raises(TypeError, match="anchors holds complex numbers"):
        Locator("nls").solve(xy + 1j, np.array([[5.0, 7.0, 7.0]]))
    with pytest.raises(TypeError, match="values is None"):
        Locator("nls").solve(xy, None)


@pytest.mark.parametrize("engine", ["compiled", "numpy"])
def test_an_infinite_value_is_not_heard_as_documented(engine):
    """``Locator.solve``: NaN and infinite values mean "not heard" (a range of ``inf``, an
    RSSI of ``-inf`` dBm), on both engines: the fix of the four finite ranges, exactly as
    with the fifth cell NaN (the API review asked whether ``inf`` was dropped silently;
    the docstring now says so, and the files' readers refuse it with FILE:LINE)."""
    import numpy as np

    from robustloc.estimators.ranging import Locator

    a = np.array([[0.0, 0.0], [10.0, 0.0], [10.0, 10.0], [0.0, 10.0], [5.0, -3.0]])
    d = np.hypot(*(a - [4.0, 6.0]).T)
    vals = np.tile(d, (3, 1))
    vals[:, 4] = [np.inf, -np.inf, np.nan]
    for method in ("nls", "huber", "ls"):
        sol = Locator(method, engine=engine, sigma=0.1, robust_scale="apriori").solve(a, vals)
        assert list(sol.n_used) == [4, 4, 4]
        np.testing.assert_array_equal(sol.position[0], sol.position[2])
        np.testing.assert_array_equal(sol.position[1], sol.position[2])
        np.testing.assert_allclose(sol.position[2], [4.0, 6.0], atol=1e-6)
    rssi = np.tile(-40.0 - 20.0 * np.log10(d), (3, 1))
    rssi[:, 4] = [-np.inf, np.inf, np.nan]
    sol = Locator("nls", engine=engine).solve(a, rssi, "rssi", A=np.full(5, -40.0),
                                                  n=np.full(5, 2.0))
    assert list(sol.n_used) == [4, 4, 4]
