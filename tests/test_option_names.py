"""One concept, the names every command spells it with (the new-user walk's option-naming
finding).

The robust weight is ``--robust`` in ``filter`` and ``fuse`` and ``--weight`` in
``track``; the asymmetric IGG weight is ``asym`` in ``locate`` and ``asymmetric-igg``
elsewhere; "no robust weight" is ``none`` in ``filter``/``fuse`` and ``ls`` in ``track``;
the motion model is ``--motion`` in ``fuse`` and ``--model`` in ``track``; the a-priori
sigma is ``--sigma`` except in ``filter`` (``--sigma-rssi``).  Each command now accepts the
other commands' names as well and keeps its own: the same settings, the same output.
Every test here failed before (an ``invalid choice`` or ``unrecognized arguments``).
"""

from __future__ import annotations

import argparse

import numpy as np
import pandas as pd
import pytest

from robustloc.cli import build_parser, main
from robustloc.robust.weights import AsymmetricIGG, LeastSquares, get_weight, weight_synonyms


def _ns(*argv: str) -> dict[str, object]:
    return vars(build_parser().parse_args(list(argv)))


FILES = ("m.csv", "--anchors", "a.csv", "-o", "o.csv")


@pytest.mark.parametrize(("alias", "canonical"), [
    (["track", *FILES, "--robust", "asym"], ["track", *FILES, "--weight", "asymmetric-igg"]),
    (["track", *FILES, "--weight", "none"], ["track", *FILES, "--weight", "ls"]),
    (["track", *FILES, "--motion", "ca"], ["track", *FILES, "--model", "ca"]),
    (["filter", *FILES, "--weight", "ls"], ["filter", *FILES, "--robust", "none"]),
    (["filter", *FILES, "--robust", "asym"], ["filter", *FILES, "--robust", "asymmetric-igg"]),
    (["filter", *FILES, "--sigma", "3"], ["filter", *FILES, "--sigma-rssi", "3"]),
    (["fuse", "--ranges", "m.csv", "--anchors", "a.csv", "-o", "o.csv", "--weight", "asym"],
     ["fuse", "--ranges", "m.csv", "--anchors", "a.csv", "-o", "o.csv", "--robust",
      "asymmetric-igg"]),
    (["locate", *FILES, "--method", "asymmetric-igg,nls"],
     ["locate", *FILES, "--method", "asym,nls"]),
    (["serve", "--anchors", "a.csv", "--method", "asymmetric-igg"],
     ["serve", "--anchors", "a.csv", "--method", "asym"]),
    (["serve", "--anchors", "a.csv", "--track", "--track-motion", "static"],
     ["serve", "--anchors", "a.csv", "--track", "--track-model", "static"]),
])
def test_each_command_reads_the_other_commands_names(alias, canonical):
    assert _ns(*alias) == _ns(*canonical)


def test_a_name_and_its_synonym_together_are_one_method_twice(capsys):
    with pytest.raises(SystemExit) as exc:
        build_parser().parse_args(["locate", *FILES, "--method", "asym,asymmetric-igg"])
    assert exc.value.code == 2
    assert "method 'asym' given twice" in capsys.readouterr().err


@pytest.mark.parametrize(("argv", "option"), [
    (["serve", "--anchors", "a.csv", "--track", "--track-model", "xyz"],
     "--track-model/--track-motion"),
    (["serve", "--anchors", "a.csv", "--track", "--track-filter", "kf"], "--track-filter"),
    (["track", *FILES, "--robust", "tukey"], "--weight/--robust"),
])
def test_an_unknown_name_is_refused_by_the_parser(argv, option, capsys):
    # serve's --track-model and --track-filter took any text and the tracker refused it
    # later, naming the anchors file ("anchors.csv: model must be one of ...")
    with pytest.raises(SystemExit) as exc:
        build_parser().parse_args(argv)
    assert exc.value.code == 2
    assert f"argument {option}: invalid choice" in capsys.readouterr().err


def test_weight_functions_by_any_name():
    assert isinstance(get_weight("none"), LeastSquares)
    assert isinstance(get_weight("ASYM", k0=1.5, k1=5.0, c=3.0), AsymmetricIGG)
    assert weight_synonyms(("ls", "asymmetric-igg")) == {"none": "ls", "asym": "asymmetric-igg"}
    # a vocabulary with both names of a weight needs no synonym for it
    assert weight_synonyms(("ls", "none")) == {}


def _walk() -> tuple[pd.DataFrame, pd.DataFrame]:
    """Four anchors on a 10 m square, a tag walking across it, ranges 0.1 m noisy with
    one in ten 3 m long."""
    rng = np.random.default_rng(4)
    anchors = pd.DataFrame({"anchor": list("abcd"), "x": [0.0, 10, 10, 0],
                            "y": [0.0, 0, 10, 10]})
    t = np.arange(40.0)
    xy = np.column_stack([1 + 0.2 * t, 2 + 0.15 * t])
    d = np.hypot(xy[:, None, 0] - anchors["x"].to_numpy(), xy[:, None, 1]
                 - anchors["y"].to_numpy())
    d = d + rng.normal(0, 0.1, d.shape) + 3.0 * (rng.random(d.shape) < 0.1)
    meas = pd.DataFrame({"time": np.repeat(t, 4), "tag": "T",
                         "anchor": np.tile(list("abcd"), t.size), "range": d.ravel()})
    return anchors, meas


def test_track_with_the_synonyms_writes_the_same_file(tmp_path):
    anchors, meas = _walk()
    anchors.to_csv(tmp_path / "a.csv", index=False)
    meas.to_csv(tmp_path / "m.csv", index=False)
    base = [str(tmp_path / "m.csv"), "--anchors", str(tmp_path / "a.csv"), "-q"]
    assert main(["track", *base, "-o", str(tmp_path / "one.csv"), "--weight",
                 "asymmetric-igg", "--model", "ca"]) == 0
    assert main(["track", *base, "-o", str(tmp_path / "two.csv"), "--robust", "asym",
                 "--motion", "ca"]) == 0
    one = (tmp_path / "one.csv").read_bytes()
    assert one == (tmp_path / "two.csv").read_bytes()
    assert b"track-ca-ekf" in one


def test_the_api_takes_the_synonyms():
    from robustloc import api

    anchors, meas = _walk()
    a = api.track(meas, anchors, weight="asym")
    b = api.track(meas, anchors, weight="asymmetric-igg")
    pd.testing.assert_frame_equal(a, b)
    la = api.locate(meas, anchors, method="asymmetric-igg")
    lb = api.locate(meas, anchors, method="asym")
    pd.testing.assert_frame_equal(la, lb)
    assert set(la["method"]) == {"asym"}  # the column keeps locate's own name


def test_evaluate_quiet_with_out_prints_no_table(tmp_path, capsys):
    anchors, meas = _walk()
    anchors.to_csv(tmp_path / "a.csv", index=False)
    meas.to_csv(tmp_path / "m.csv", index=False)
    truth = meas.drop_duplicates("time")[["time", "tag"]].assign(
        x=lambda f: 1 + 0.2 * f["time"], y=lambda f: 2 + 0.15 * f["time"])
    truth.to_csv(tmp_path / "t.csv", index=False)
    assert main(["locate", str(tmp_path / "m.csv"), "--anchors", str(tmp_path / "a.csv"),
                 "-o", str(tmp_path / "p.csv"), "-q"]) == 0
    capsys.readouterr()
    ev = ["evaluate", str(tmp_path / "p.csv"), "--truth", str(tmp_path / "t.csv")]
    assert main([*ev, "-o", str(tmp_path / "e.csv"), "-q"]) == 0
    out = capsys.readouterr()
    assert out.out == "" and out.err == ""
    assert len(pd.read_csv(tmp_path / "e.csv")) > 0
    # without -o the table is the output: -q does not hide it
    assert main([*ev, "-q"]) == 0
    assert "horizontal error (m)" in capsys.readouterr().out


def test_montecarlo_takes_model_and_sigma_from_the_anchors_file(tmp_path, capsys):
    # as reliability does since the walk: a self-calibrated RSSI file was planned as
    # 1 m ranges
    from robustloc.commands.montecarlo import _layout_options, build_layout

    sig = np.array([1.5, 2.0, 2.5, 3.0])
    pd.DataFrame({"anchor": list("abcd"), "x": [0.0, 10, 10, 0], "y": [0.0, 0, 10, 10],
                  "A": -40.0, "n": [2.0, 2.2, 2.4, 2.6], "sigma": sig}).to_csv(
        tmp_path / "a.csv", index=False)
    args = build_parser().parse_args(["montecarlo", "--anchors", str(tmp_path / "a.csv")])
    _layout_options(args)
    lay = build_layout(args)
    assert args.model == "rssi"
    np.testing.assert_array_equal(lay.sigma, sig)
    assert "sigma per anchor 1.5 .. 3 dB" in capsys.readouterr().err
    # the options still win over the file
    args = argparse.Namespace(**{**vars(args), "model": "range", "sigma": 0.5})
    lay = build_layout(args)
    np.testing.assert_array_equal(lay.sigma, np.full(4, 0.5))
