"""The Python API (robustloc.api) against the command line on the same input.

The API runs the commands' own parsers and ``run`` functions, so its frames must equal
the files the commands write, row for row.  Positions and calibration files are written
with full float precision (``repr``) by the commands, so the CSV round trip is exact and
the comparison tolerance is 1e-9 m (far below any fix's noise, above float round-off of
nothing); ``spp`` writes CSV with ``%.6f``, so there the tolerance is the 5e-7 of that
rounding.  Errors must carry the message the command prints after ``error:``.
"""

from __future__ import annotations

import doctest
import importlib.metadata
import subprocess
import sys
import warnings
from importlib.resources import files

import numpy as np
import pandas as pd
import pytest

import robustloc
from robustloc import InputError, api
from robustloc.cli import main

DATA = files("robustloc") / "data"


# ---------------------------------------------------------------- fixtures


@pytest.fixture(scope="module")
def corridor(tmp_path_factory):
    """Seed 000's simulated BLE corridor (RSSI), calibrated by the command line."""
    d = tmp_path_factory.mktemp("corridor")
    assert main(["simulate", "ble-corridor", "--seed", "3", "--out", str(d)]) == 0
    assert main(["calibrate", str(d / "survey.csv"), "--anchors", str(d / "anchors.csv"),
                 "-o", str(d / "cal.csv")]) == 0
    return d


@pytest.fixture(scope="module")
def ranges(tmp_path_factory):
    """A synthetic range log: 6 anchors, 2 tags x 60 epochs, noise 0.1 m, each anchor
    biased (0.2 m) and scaled (1 %), 5 % of the ranges with a +3 m NLOS excess."""
    d = tmp_path_factory.mktemp("ranges")
    rng = np.random.default_rng(7)
    anchors = pd.DataFrame({"anchor": [f"A{i}" for i in range(6)],
                            "x": [0.0, 20.0, 20.0, 0.0, 10.0, 10.0],
                            "y": [0.0, 0.0, 15.0, 15.0, -2.0, 17.0]})
    rows, truth = [], []
    for tag in ("t1", "t2"):
        for k in range(60):
            t = float(k)
            p = np.array([3.0 + 0.2 * k, 4.0 + 0.1 * k]) if tag == "t1" else \
                np.array([15.0 - 0.15 * k, 11.0 - 0.1 * k])
            truth.append((t, tag, p[0], p[1]))
            dist = np.hypot(anchors.x - p[0], anchors.y - p[1]).to_numpy()
            r = 1.01 * dist + 0.2 + rng.normal(0.0, 0.1, 6)
            r += np.where(rng.random(6) < 0.05, 3.0, 0.0)
            rows += [(t, tag, a, float(v)) for a, v in zip(anchors.anchor, r)]
    meas = pd.DataFrame(rows, columns=["time", "tag", "anchor", "range"])
    meas.to_csv(d / "measurements.csv", index=False)
    anchors.to_csv(d / "anchors.csv", index=False)
    pd.DataFrame(truth, columns=["time", "tag", "x", "y"]).to_csv(d / "truth.csv", index=False)
    return d


def assert_frames_equal(api_frame: pd.DataFrame, cli_frame: pd.DataFrame, atol: float = 1e-9):
    """Same columns, same rows; numbers within ``atol``, everything else equal."""
    assert list(api_frame.columns) == list(cli_frame.columns)
    assert len(api_frame) == len(cli_frame)
    for c in cli_frame.columns:
        a, b = api_frame[c], cli_frame[c]
        if pd.api.types.is_numeric_dtype(b) and pd.api.types.is_numeric_dtype(a):
            np.testing.assert_allclose(a.to_numpy(dtype=float), b.to_numpy(dtype=float),
                                       rtol=0, atol=atol, err_msg=c)
        else:
            sa = a.fillna("").astype(str).to_numpy()
            sb = b.fillna("").astype(str).to_numpy()
            np.testing.assert_array_equal(sa, sb, err_msg=c)


def cli_error(argv: list[str], capsys) -> str:
    """Run the command line, expect a user error; return its message after ``error: ``."""
    capsys.readouterr()
    assert main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()[-1]
    assert err.startswith("error: ")
    return err[len("error: "):]


# ---------------------------------------------------------------- locate


@pytest.mark.parametrize("method", ["auto", "ls,huber,igg"])
def test_locate_rssi_file_and_frame_equal_cli(corridor, tmp_path, method):
    out = tmp_path / "pos.csv"
    assert main(["locate", str(corridor / "measurements.csv"), "--anchors",
                 str(corridor / "cal.csv"), "--method", method, "-o", str(out), "--quiet"]) == 0
    cli = pd.read_csv(out, dtype={"tag": str, "excluded": str})
    methods = method.split(",")
    from_path = robustloc.locate(corridor / "measurements.csv", corridor / "cal.csv", methods)
    assert_frames_equal(from_path, cli)
    from_frames = robustloc.locate(pd.read_csv(corridor / "measurements.csv"),
                                   pd.read_csv(corridor / "cal.csv"), methods)
    assert_frames_equal(from_frames, cli)
    assert from_path.attrs["summary"]["epochs"] == len(pd.read_csv(corridor / "truth.csv"))


def test_locate_ranges_options_equal_cli(ranges, tmp_path):
    out = tmp_path / "pos.csv"
    assert main(["locate", str(ranges / "measurements.csv"), "--anchors",
                 str(ranges / "anchors.csv"), "--method", "nls,igg", "--sigma", "0.1",
                 "--param", "k0=1.2", "--alert-limit", "5", "-o", str(out), "--quiet"]) == 0
    cli = pd.read_csv(out, dtype={"tag": str, "excluded": str})
    got = robustloc.locate(pd.read_csv(ranges / "measurements.csv"), ranges / "anchors.csv",
                           ["nls", "igg"], sigma=0.1, params={"k0": 1.2}, alert_limit=5.0)
    assert_frames_equal(got, cli)
    # a shuffled frame is the same log: the command sorts it, so does the API
    shuffled = pd.read_csv(ranges / "measurements.csv").sample(frac=1.0, random_state=1)
    assert_frames_equal(robustloc.locate(shuffled, ranges / "anchors.csv", ["nls", "igg"],
                                         sigma=0.1, params={"k0": 1.2}, alert_limit=5.0), cli)


def test_locate_frame_from_read_measurements(ranges):
    anchors = robustloc.read_anchors(ranges / "anchors.csv")
    meas = robustloc.read_measurements(ranges / "measurements.csv", anchors)
    a = robustloc.locate(meas, anchors)
    b = robustloc.locate(ranges / "measurements.csv", ranges / "anchors.csv")
    assert_frames_equal(a, b)
    assert set(a["status"]) <= {"ok", "fault_excluded", "fault_detected", "low_redundancy"}


# ---------------------------------------------------------------- errors


def test_file_error_has_the_cli_message(ranges, tmp_path, capsys):
    bad = pd.read_csv(ranges / "measurements.csv")
    bad.loc[7, "range"] = np.nan
    path = tmp_path / "bad.csv"
    bad.to_csv(path, index=False)
    want = cli_error(["locate", str(path), "--anchors", str(ranges / "anchors.csv"),
                      "-o", str(tmp_path / "p.csv")], capsys)
    assert want == f"{path}:9: column 'range': missing or NaN value"
    with pytest.raises(InputError) as exc:
        robustloc.locate(path, ranges / "anchors.csv")
    assert str(exc.value) == want
    assert (exc.value.path, exc.value.line) == (str(path), 9)


def test_frame_error_names_the_frame_and_its_csv_line(ranges, tmp_path, capsys):
    bad = pd.read_csv(ranges / "measurements.csv")
    bad.loc[11, "anchor"] = "nowhere"
    path = tmp_path / "bad.csv"
    bad.to_csv(path, index=False)
    want = cli_error(["locate", str(path), "--anchors", str(ranges / "anchors.csv"),
                      "-o", str(tmp_path / "p.csv")], capsys)
    with pytest.raises(InputError) as exc:
        robustloc.locate(bad, ranges / "anchors.csv")
    assert str(exc.value) == want.replace(str(path), "<measurements DataFrame>")
    assert exc.value.line == 13


def test_anchor_frame_error(ranges, tmp_path, capsys):
    anchors = pd.read_csv(ranges / "anchors.csv")
    anchors.loc[2, "x"] = np.inf
    path = tmp_path / "an.csv"
    anchors.to_csv(path, index=False)
    want = cli_error(["locate", str(ranges / "measurements.csv"), "--anchors", str(path),
                      "-o", str(tmp_path / "p.csv")], capsys)
    with pytest.raises(InputError) as exc:
        robustloc.locate(ranges / "measurements.csv", anchors)
    assert str(exc.value) == want.replace(str(path), "<anchors DataFrame>")


@pytest.mark.parametrize(("options", "argv"), [
    ({"sigma": -1.0}, ["--sigma", "-1.0"]),
    ({"method": "nope"}, ["--method", "nope"]),
    ({"method": ["nls", "nls"]}, ["--method", "nls,nls"]),
    ({"dim": 3}, ["--dim", "3"]),
    ({"params": {"zz": 1.0}, "method": "huber"}, ["--param", "zz=1.0", "--method", "huber"]),
])
def test_refused_option_has_the_cli_message(ranges, tmp_path, capsys, options, argv):
    cmd = ["locate", str(ranges / "measurements.csv"), "--anchors",
           str(ranges / "anchors.csv"), "-o", str(tmp_path / "p.csv"), *argv]
    capsys.readouterr()
    assert main(cmd) == 2
    err = capsys.readouterr().err.strip().splitlines()[-1]
    with pytest.raises(InputError) as exc:
        robustloc.locate(ranges / "measurements.csv", ranges / "anchors.csv", **options)
    # argparse prefixes its refusals with "robustloc locate: error: "; our own with "error: "
    assert err.endswith(str(exc.value))


def test_missing_file_is_an_input_error(ranges, tmp_path, capsys):
    missing = tmp_path / "missing.csv"
    want = cli_error(["locate", str(missing), "--anchors", str(ranges / "anchors.csv"),
                      "-o", str(tmp_path / "p.csv")], capsys)
    with pytest.raises(InputError) as exc:
        robustloc.locate(missing, ranges / "anchors.csv")
    assert str(exc.value) == want


def test_wrong_type_is_a_type_error(ranges):
    with pytest.raises(TypeError, match="measurements: expected a DataFrame or a path"):
        robustloc.locate(42, ranges / "anchors.csv")  # type: ignore[arg-type]


# ---------------------------------------------------------------- calibrate


def test_calibrate_survey_equals_cli(corridor, tmp_path):
    out = tmp_path / "cal.csv"
    assert main(["calibrate", str(corridor / "survey.csv"), "--anchors",
                 str(corridor / "anchors.csv"), "--robust", "igg3", "-o", str(out)]) == 0
    cli = pd.read_csv(out, dtype={"anchor": str})
    got = robustloc.calibrate(corridor / "survey.csv", corridor / "anchors.csv", robust="igg3")
    assert_frames_equal(got, cli)
    got = robustloc.calibrate(pd.read_csv(corridor / "survey.csv"),
                              pd.read_csv(corridor / "anchors.csv"), robust="igg3")
    assert_frames_equal(got, cli)
    assert got.attrs["summary"]["robust"] == "igg3"


def test_self_calibration_equals_cli_and_recovers_the_bias(ranges, tmp_path):
    out = tmp_path / "self.csv"
    assert main(["calibrate", "--self", str(ranges / "measurements.csv"), "--anchors",
                 str(ranges / "anchors.csv"), "-o", str(out)]) == 0
    cli = pd.read_csv(out, dtype={"anchor": str})
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", api.RobustlocWarning)
        got = robustloc.calibrate(anchors=pd.read_csv(ranges / "anchors.csv"),
                                  self_log=pd.read_csv(ranges / "measurements.csv"))
    assert_frames_equal(got, cli)
    # the simulated 0.2 m bias and 1.01 scale, within 4 standard errors
    ok = np.isfinite(got["bias_se"])
    assert ok.any()
    assert np.all(np.abs(got.loc[ok, "bias"] - 0.2) < 4 * got.loc[ok, "bias_se"] + 1e-3)


def test_calibrate_combination_error(ranges):
    # the command's own check (a ValueError in commands/calibrate.py) becomes InputError
    with pytest.raises(InputError, match="--self needs --anchors"):
        robustloc.calibrate(self_log=ranges / "measurements.csv")


# ---------------------------------------------------------------- evaluate


def test_evaluate_equals_cli(ranges, tmp_path):
    pos = tmp_path / "pos.csv"
    assert main(["locate", str(ranges / "measurements.csv"), "--anchors",
                 str(ranges / "anchors.csv"), "--method", "ls,igg", "-o", str(pos),
                 "--quiet"]) == 0
    out = tmp_path / "err.csv"
    assert main(["evaluate", str(pos), "--truth", str(ranges / "truth.csv"), "-o", str(out)]) == 0
    cli = pd.read_csv(out, dtype={"tag": str})
    got = robustloc.evaluate(pos, ranges / "truth.csv")
    assert_frames_equal(got, cli)
    frames = robustloc.evaluate(
        robustloc.locate(ranges / "measurements.csv", ranges / "anchors.csv", ["ls", "igg"]),
        pd.read_csv(ranges / "truth.csv"))
    assert_frames_equal(frames, cli)


# ---------------------------------------------------------------- spp


def test_spp_equals_cli(tmp_path):
    obs = DATA / "gnss-geonet" / "07590920.05o"
    nav = DATA / "gnss-geonet" / "07590920_0000-0400.05n"
    out = tmp_path / "spp.csv"
    assert main(["spp", str(obs), str(nav), "--systems", "G", "--raim", "-o", str(out)]) == 0
    cli = pd.read_csv(out)
    got = robustloc.spp(obs, nav, systems="G", raim=True)
    # the command's CSV is written with %.6f: half a unit of the 6th decimal
    assert_frames_equal(got, cli, atol=5e-7 * (1 + 1e-9))
    assert got.attrs["summary"]["raim"] is True


def test_spp_without_navigation_is_an_input_error():
    with pytest.raises(InputError, match="give at least one navigation file or --sp3"):
        robustloc.spp(DATA / "gnss-geonet" / "07590920.05o")


# ---------------------------------------------------------------- module level


def test_docstring_examples():
    """Every public function's Examples section runs (doctest)."""
    res = doctest.testmod(api, optionflags=doctest.NORMALIZE_WHITESPACE | doctest.ELLIPSIS)
    assert res.attempted >= 20
    assert res.failed == 0


def test_every_public_function_has_an_example():
    for name in robustloc.__all__:
        obj = getattr(robustloc, name)
        if callable(obj) and name != "InputError":
            assert "Examples\n    --------" in (obj.__doc__ or ""), name


def test_import_is_lazy():
    code = ("import sys, robustloc; "
            "print(sorted(m for m in ('pandas', 'numpy', 'numba', 'scipy') if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True).stdout.strip()
    assert out == "[]"


def test_version_from_metadata(capsys):
    assert robustloc.__version__ == importlib.metadata.version("robustloc")
    assert main(["--version"]) == 0
    assert capsys.readouterr().out.strip() == f"robustloc {robustloc.__version__}"



def test_python_dash_m_runs_the_command(tmp_path):
    """``python -m robustloc`` is the ``robustloc`` command: its version, its exit code 2
    and ``error:`` line for a user's mistake (it said "No module named
    robustloc.__main__")."""
    import subprocess
    import sys

    def run(*args):
        return subprocess.run([sys.executable, "-m", "robustloc", *args], cwd=tmp_path,
                              capture_output=True, text=True, timeout=120)

    ver = run("--version")
    assert ver.returncode == 0 and ver.stdout.strip() == f"robustloc {robustloc.__version__}"
    bad = run("locate", "missing.csv", "--anchors", "missing_anchors.csv", "-o", "out.csv")
    assert bad.returncode == 2 and bad.stderr.startswith("error: ")
    assert "Traceback" not in bad.stderr

def test_track_equals_the_command_line(tmp_path):
    import numpy as np

    from robustloc.cli import main

    anchors = pd.DataFrame({"anchor": ["a", "b", "c", "d"],
                            "x": [0.0, 10.0, 10.0, 0.0], "y": [0.0, 0.0, 10.0, 10.0]})
    t = np.arange(30) * 0.5
    xy = np.c_[2.0 + 0.2 * t, 5.0 + 0.1 * t]
    d = np.hypot(anchors.x.to_numpy() - xy[:, :1], anchors.y.to_numpy() - xy[:, 1:])
    d = d + np.random.default_rng(3).normal(0, 0.05, d.shape)
    log = pd.DataFrame({"time": np.repeat(t, 4), "tag": "t1",
                        "anchor": np.tile(anchors.anchor, t.size), "range": d.ravel()})
    anchors.to_csv(tmp_path / "a.csv", index=False)
    log.to_csv(tmp_path / "m.csv", index=False)
    assert main(["track", str(tmp_path / "m.csv"), "--anchors", str(tmp_path / "a.csv"),
                 "-o", str(tmp_path / "t.parquet"), "--quiet"]) == 0
    cli = pd.read_parquet(tmp_path / "t.parquet")
    api = robustloc.track(log, anchors)
    pd.testing.assert_frame_equal(api.reset_index(drop=True), cli, check_dtype=False,
                                  atol=1e-9, rtol=0)


def test_locate_side_prior_equals_cli(tmp_path):
    """side_prior is --side-prior: on a log beside nearly collinear anchors the default
    moves ambiguous fixes to the log's side, "none" leaves them (the CLI's rows both)."""
    from _corridor import side_frames  # (tests/_corridor.py)

    log, anchors, _ = side_frames(n=300)
    log.to_csv(tmp_path / "m.csv", index=False)
    anchors.to_csv(tmp_path / "a.csv", index=False)
    got = {}
    for side in ("log", "none"):
        out = tmp_path / f"{side}.csv"
        assert main(["locate", str(tmp_path / "m.csv"), "--anchors", str(tmp_path / "a.csv"),
                     "--side-prior", side, "-o", str(out), "--quiet"]) == 0
        got[side] = robustloc.locate(log, anchors, side_prior=side)
        assert_frames_equal(got[side], pd.read_csv(out, dtype={"tag": str, "excluded": str}))
    moved = got["log"]["y"].to_numpy() != got["none"]["y"].to_numpy()
    moved &= np.isfinite(got["log"]["y"].to_numpy())
    assert moved.sum() >= 3 and (got["none"]["y"][moved] > 0).all()
    assert got["log"].attrs["summary"]["side_from_log"]["auto"] == moved.sum()


def test_track_takes_the_noise_scale_bounds_of_the_command_line():
    """``--noise-scale-min`` and ``--noise-scale-max`` had no ``api.track`` keyword (the
    tracker review): the adaptive noise scale of every row stays within them."""
    anchors = pd.DataFrame({"anchor": ["a", "b", "c", "d"], "x": [0, 10, 10, 0.0],
                            "y": [0, 0, 10, 10.0]})
    t = np.arange(40) * 0.5
    xy = np.c_[2 + 0.3 * t, np.full(t.size, 5.0)]
    d = (np.hypot(anchors.x.to_numpy() - xy[:, :1], anchors.y.to_numpy() - xy[:, 1:])
         + np.random.default_rng(0).normal(0, 0.5, (t.size, 4)))
    log = pd.DataFrame({"time": np.repeat(t, 4), "tag": "t1",
                        "anchor": np.tile(anchors.anchor, t.size), "range": d.ravel()})
    wide = robustloc.track(log, anchors)
    assert wide["noise_scale"].max() > 1.1  # (0.5 m of noise against sigma 0.3 m)
    capped = robustloc.track(log, anchors, noise_scale_max=1.0)
    assert np.nanmax(capped["noise_scale"]) <= 1.0 + 1e-12
    with pytest.raises(robustloc.InputError, match="--noise-scale-min"):
        robustloc.track(log, anchors, noise_scale_min=-1.0)


def test_track_link_offsets_takes_the_command_words(tmp_path):
    """``link_offsets="on"`` was refused (``expected True or False``) although the command
    takes ``--link-offsets on|off|auto`` and the API its words elsewhere: "on" / "off" /
    "auto" now mean what they mean to the command, row for row."""
    anchors = pd.DataFrame({"anchor": ["a", "b", "c", "d", "e"],
                            "x": [0.0, 10.0, 10.0, 0.0, 5.0], "y": [0.0, 0.0, 10.0, 10.0, 12.0]})
    t = np.arange(40) * 0.5
    xy = np.c_[2.0 + 0.2 * t, 5.0 + 0.1 * t]
    d = np.hypot(anchors.x.to_numpy() - xy[:, :1], anchors.y.to_numpy() - xy[:, 1:])
    d = d + np.random.default_rng(4).normal(0, 0.05, d.shape) + [0.3, 0, 0, -0.2, 0]
    log = pd.DataFrame({"time": np.repeat(t, 5), "tag": "t1",
                        "anchor": np.tile(anchors.anchor, t.size), "range": d.ravel()})
    anchors.to_csv(tmp_path / "a.csv", index=False)
    log.to_csv(tmp_path / "m.csv", index=False)
    for word, flag in (("on", True), ("off", False), ("auto", None)):
        out = tmp_path / f"{word}.parquet"
        assert main(["track", str(tmp_path / "m.csv"), "--anchors", str(tmp_path / "a.csv"),
                     "--link-offsets", word, "-o", str(out), "--quiet"]) == 0
        by_word = robustloc.track(log, anchors, link_offsets=word)
        pd.testing.assert_frame_equal(by_word.reset_index(drop=True), pd.read_parquet(out),
                                      check_dtype=False, atol=1e-9, rtol=0)
        if flag is not None:
            by_flag = robustloc.track(log, anchors, link_offsets=flag)
            pd.testing.assert_frame_equal(by_word, by_flag)
            assert ("link_offset_m" in by_word.attrs["summary"]) == flag
        else:
            assert "link_offsets_auto" in by_word.attrs["summary"]
    for bad in ("yes", "ON", 1, None):
        with pytest.raises(InputError, match="link_offsets: expected True, False, 'on', "
                                             "'off' or 'auto'"):
            robustloc.track(log, anchors, link_offsets=bad)


def test_locate_docstring_describes_auto_as_it_runs():
    """The docstring said ``auto`` is "Gauss-Newton where its test passes, huber where it
    finds a fault": it left out igg on every epoch of a log with more than 3.3 % gross
    residuals, and the Gauss-Newton fix kept (``fault_detected``) where the w-test names
    the faulty ranges.  The text now names both, with the constants the code uses."""
    import re

    from robustloc.integrity import fixes

    doc = " ".join(robustloc.locate.__doc__.split())
    auto = doc[doc.index("``auto`` is"):doc.index("dim, solver, reference")]
    share = re.search(r"more than ([\d.]+) % gross residuals", auto)
    assert share and float(share.group(1)) == pytest.approx(100 * fixes.AUTO_GROSS_SHARE)
    assert f"by ``{fixes.AUTO_HEAVY}`` on every epoch" in auto
    assert f"solved again by ``{fixes.AUTO_ROBUST}``" in auto
    assert "fault_detected" in auto and "w-test names" in auto
