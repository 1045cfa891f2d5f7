"""What a new user met on the README's tour (the new-user walkthrough): ``reliability``
planned a calibrated BLE layout as a 1 m range sensor, ``--tag-z`` was named unlike every
other command's ``--tag-height``, ``simulate SCENARIO --help`` printed raw
reStructuredText, and ``simulate gnss`` wrote a ``pseudoranges.csv`` nothing said how to
use.  The real command line in-process; the planner checked against textbook formulas."""

from __future__ import annotations

import argparse
import json
import re

import numpy as np
import pandas as pd
import pytest
from scipy.stats import norm

from robustloc.cli import main

#: A 10 m x 8 m room with five anchors (two redundant ranges at every point).
ROOM = [("A1", 0.0, 0.0), ("A2", 10.0, 0.0), ("A3", 10.0, 8.0), ("A4", 0.0, 8.0),
        ("A5", 5.0, 4.5)]
#: Per-anchor sigmas, all different (dB for a path-loss fit, m for a range calibration).
SIGMAS = [1.8, 2.1, 2.4, 2.0, 3.0]


def _anchors(tmp_path, **columns) -> str:
    df = pd.DataFrame(ROOM, columns=["anchor", "x", "y"])
    for k, v in columns.items():
        df[k] = v
    path = tmp_path / "anchors.csv"
    df.to_csv(path, index=False)
    return str(path)


def _run(tmp_path, capsys, anchors: str, *extra: str, name: str = "o") -> tuple[dict, str]:
    out = tmp_path / name
    code = main(["reliability", "--anchors", anchors, "--step", "0.5", "--no-maps",
                 "--json", "-o", str(out), *extra])
    got = capsys.readouterr()
    assert code == 0, got.err
    return json.loads(got.out), got.err


# --- 1. reliability: --model and --sigma from the anchors file ---------------------------


def test_the_readme_tour_plans_the_calibrated_ble_layout_as_rssi(tmp_path, capsys):
    """`reliability --anchors corridor/calibrated.csv` printed `model range, sigma 1.0`
    although calibrate had written A, n and a sigma of about 2.1 dB per beacon."""
    d = tmp_path / "corridor"
    assert main(["simulate", "ble-corridor", "--seed", "1", "--out", str(d)]) == 0
    assert main(["calibrate", str(d / "survey.csv"), "--model", "log-distance", "--anchors",
                 str(d / "anchors.csv"), "-o", str(d / "calibrated.csv")]) == 0
    capsys.readouterr()
    cal = pd.read_csv(d / "calibrated.csv")
    s, err = _run(tmp_path, capsys, str(d / "calibrated.csv"), "--step", "1")
    assert s["model"] == "rssi" and s["unit"] == "dB"
    np.testing.assert_allclose(s["sigma_per_anchor"], cal["sigma"], rtol=1e-12)
    notes = [line for line in err.splitlines() if line.startswith("note: ")]
    assert len(notes) == 1, err
    assert "model rssi from its A, n columns" in notes[0]
    assert "sigma per anchor" in notes[0] and "dB" in notes[0]


def test_the_plan_is_the_planners_with_the_files_exponents_and_sigmas(tmp_path, capsys):
    from robustloc.integrity.planner import plan

    n = [2.0, 2.2, 1.9, 2.4, 2.1]
    anchors = _anchors(tmp_path, A=-60.0, n=n, sigma=SIGMAS)
    s, _ = _run(tmp_path, capsys, anchors)
    got = pd.read_csv(tmp_path / "o" / "reliability.csv")
    xy = np.array([r[1:] for r in ROOM])
    want = plan(xy, tuple(s["area"]), s["step_m"], np.array(SIGMAS), model="rssi",
                path_loss_n=np.array(n)).table
    for col in ("crlb_m", "max_mdb", "max_ext_m", "max_abs_rho", "min_redundancy"):
        # rounding: the CSV holds 6 significant digits
        np.testing.assert_allclose(got[col], want[col], rtol=1e-5, err_msg=col)
    # the scalar sigma 1 of before gives other figures
    one = plan(xy, tuple(s["area"]), s["step_m"], 1.0, model="rssi",
               path_loss_n=np.array(n)).table
    assert not np.allclose(got["max_mdb"], one["max_mdb"], rtol=0.1)


@pytest.mark.parametrize("extra, model, sigma, said", [
    (["--sigma", "2.5"], "rssi", 2.5, "model rssi from its A, n columns"),
    (["--model", "range"], "range", 1.0, "sigma 1 m, not its sigma column, which is a "
                                         "path-loss fit's (dB)"),
    (["--model", "rssi", "--sigma", "3"], "rssi", 3.0, None),
])
def test_options_given_win_over_the_file(tmp_path, capsys, extra, model, sigma, said):
    anchors = _anchors(tmp_path, A=-60.0, n=2.0, sigma=SIGMAS)
    s, err = _run(tmp_path, capsys, anchors, *extra)
    assert s["model"] == model and s["sigma"] == sigma and s["sigma_per_anchor"] is None
    assert s["unit"] == {"rssi": "dB", "range": "m"}[model]
    if said is None:
        assert "note:" not in err, err
    else:
        assert said in err and "sigma per anchor" not in err, err


def test_a_range_calibration_gives_range_with_its_sigmas_in_metres(tmp_path, capsys):
    anchors = _anchors(tmp_path, bias=0.1, scale=1.0, sigma=SIGMAS)
    s, err = _run(tmp_path, capsys, anchors)
    assert s["model"] == "range" and s["unit"] == "m"
    assert s["sigma_per_anchor"] == SIGMAS
    assert "model range from its bias, scale columns" in err and "m (median" in err, err


def test_a_file_with_both_calibrations_does_not_guess_the_sigmas_unit(tmp_path, capsys):
    anchors = _anchors(tmp_path, A=-60.0, n=2.0, bias=0.1, sigma=SIGMAS)
    s, err = _run(tmp_path, capsys, anchors)
    assert s["model"] == "range" and s["sigma"] == 1.0 and s["sigma_per_anchor"] is None
    assert "give --model rssi" in err and "not its sigma column" in err, err


def test_the_mdb_is_labelled_with_its_unit(tmp_path, capsys, monkeypatch):
    """The summary and the map said "largest MDB (observation units)": 512.9 of what?"""
    import matplotlib.axes

    titles: list[str] = []
    real = matplotlib.axes.Axes.set_title
    monkeypatch.setattr(matplotlib.axes.Axes, "set_title",
                        lambda self, t, *a, **k: (titles.append(t), real(self, t, *a, **k))[1])
    for model, unit in (("rssi", "dB"), ("range", "m")):
        titles.clear()
        code = main(["reliability", "--anchors", _anchors(tmp_path, A=-60.0, n=2.0),
                     "--model", model, "--step", "1", "-o", str(tmp_path / model)])
        out = capsys.readouterr().out
        assert code == 0
        line = next(x for x in out.splitlines() if x.strip().startswith("max_mdb"))
        assert line.endswith(f"largest MDB ({unit})"), line
        assert f", sigma 1 {unit}" in out.splitlines()[0]
        assert any(t.startswith(f"largest MDB ({unit})") for t in titles), titles
        assert not any("observation units" in t for t in titles)


def test_planner_per_anchor_sigma_against_the_textbook():
    """CRLB, MDB and external reliability of ranges with a different sigma per anchor, at
    one point, from the weighted least-squares formulas (seed 003 eqs. (2), (3))."""
    from robustloc.integrity.planner import plan

    a = np.array([r[1:] for r in ROOM])
    s = np.array(SIGMAS)
    x = np.array([2.0, 3.0])
    # (the grid's corners: the point is its first row; the grid reaches both edges)
    t = plan(a, (2.0, 2.5, 3.0, 3.5), 1.0, s).table
    assert len(t) == 4 and tuple(t[["x", "y"]].iloc[0]) == (2.0, 3.0)
    d = x - a
    G = d / np.linalg.norm(d, axis=1)[:, None]
    W = np.diag(1 / s**2)
    Q = np.linalg.inv(G.T @ W @ G)
    A = G / s[:, None]
    r = 1 - np.diag(A @ np.linalg.inv(A.T @ A) @ A.T)
    lam = (norm.ppf(1 - 0.001 / 2) + norm.ppf(1 - 0.10)) ** 2  # alpha0, beta0 defaults
    mdb = s * np.sqrt(lam / r)
    ext = np.array([np.linalg.norm(Q @ G.T @ W[:, i] * mdb[i]) for i in range(len(a))])
    # rounding: float64 closed forms
    np.testing.assert_allclose(t["crlb_m"].iloc[0], np.sqrt(np.trace(Q)), rtol=1e-9)
    np.testing.assert_allclose(t["max_mdb"].iloc[0], mdb.max(), rtol=1e-9)
    np.testing.assert_allclose(t["min_redundancy"].iloc[0], r.min(), rtol=1e-9)
    np.testing.assert_allclose(t["max_ext_m"].iloc[0], ext.max(), rtol=1e-9)
    with pytest.raises(ValueError, match="one per anchor"):
        plan(a, (2.0, 2.5, 3.0, 3.5), 1.0, s[:3])


def test_suggest_gives_the_candidate_the_median_sigma():
    from robustloc.integrity.planner import layout_score, plan, suggest_anchor

    a = np.array([r[1:] for r in ROOM])
    s = np.array(SIGMAS)
    area, cand = (0.0, 10.0, 0.0, 8.0), np.array([[5.0, 0.0], [0.0, 4.0]])
    ranked = suggest_anchor(a, area, 1.0, s, cand)
    for _, row in ranked.iterrows():
        g = plan(np.vstack([a, [row["x"], row["y"]]]), area, 1.0, np.append(s, np.median(s)))
        assert row["score"] == layout_score(g)


# --- 2. --tag-height, the name the other commands use -----------------------------------


def test_reliability_takes_tag_height_as_tag_z(tmp_path, capsys):
    anchors = _anchors(tmp_path, z=[2.5, 2.5, 3.0, 3.0, 2.8])

    def table(*opt: str) -> pd.DataFrame:
        name = "t" + "_".join(opt).replace("-", "").replace(".", "")
        _run(tmp_path, capsys, anchors, *opt, name=name)
        return pd.read_csv(tmp_path / name / "reliability.csv")

    z, h = table("--tag-z", "1.2"), table("--tag-height", "1.2")
    pd.testing.assert_frame_equal(z, h)
    assert not np.allclose(table()["dop"], h["dop"])  # (the height enters the plan)


@pytest.mark.parametrize("command, rest", [
    ("reliability", ["-o", "x"]),
    ("montecarlo", []),
])
def test_tag_height_is_an_alias_of_tag_z(command, rest):
    from robustloc.cli import build_parser

    p = build_parser()
    args = p.parse_args([command, "--anchors", "a.csv", *rest, "--tag-height", "1.5"])
    assert args.tag_z == 1.5
    assert p.parse_args([command, "--anchors", "a.csv", *rest, "--tag-z", "2"]).tag_z == 2
    assert "--tag-z M, --tag-height M" in _help(command)
    sub = next(a for a in p._actions if isinstance(a, argparse._SubParsersAction))
    opt = next(a for a in sub.choices[command]._actions if "--tag-z" in a.option_strings)
    assert opt.option_strings == ["--tag-z", "--tag-height"]
    assert "--tag-z and --tag-height" in opt.help and "same option" in opt.help


# --- 3. simulate SCENARIO --help: plain text, not reStructuredText ------------------------


def _help(*argv: str) -> str:
    import contextlib
    import io

    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        assert main([*argv, "--help"]) == 0
    return buf.getvalue()


@pytest.mark.parametrize("scenario", ["ble-corridor", "gnss", "uwb-cart", "wifi-room"])
def test_scenario_help_has_no_restructuredtext(scenario):
    text = _help("simulate", scenario)
    raw = [line for line in text.splitlines()
           if "``" in line or re.search(r":[a-z]+:`", line) or re.match(r"\s*={3,}", line)]
    assert not raw, raw
    assert len(text.splitlines()) > 20  # (the docstring is still there)


def test_scenario_help_keeps_the_tables_and_names():
    text = _help("simulate", "gnss")
    lines = text.splitlines()
    # the table: header, a rule of dashes, its rows aligned on the header's columns
    head = next(i for i, x in enumerate(lines) if x.startswith("system"))
    assert set(lines[head + 1]) == {"-", " "}
    rows = lines[head + 2 : head + 5]
    assert [r.split()[:3] for r in rows] == [["GPS", "G", "24/6/1"], ["Galileo", "E", "24/3/1"],
                                            ["BeiDou", "C", "24/3/1"]]
    col = lines[head].index("letter")
    assert all(r[col] in "GEC" for r in rows)
    assert "(constellation, visible_design) give the" in text
    assert "robustloc.integrity.montecarlo" in text  # (a module keeps its path)
    assert "Files written: anchors.csv (anchor, x, y, A, n), survey.csv (anchor, distance," \
           in _help("simulate", "ble-corridor")


def test_rst_to_text():
    from robustloc._rst import rst_to_text

    assert rst_to_text(":func:`robustloc.x.y` and :data:`X`, :class:`~a.B`") == "y and X, B"
    assert rst_to_text(":func:`the fit <robustloc.x.fit>`") == "the fit"
    assert rst_to_text(":mod:`robustloc.integrity.montecarlo`") == \
        "robustloc.integrity.montecarlo"
    assert rst_to_text("a ``b,\nc`` d") == "a b,\nc d"  # (a literal over a line break)
    table = ("====  ==========\n"
             "key   value\n"
             "====  ==========\n"
             "``a``   ``long one``\n"
             "bb    2\n"
             "====  ==========")
    assert rst_to_text(table).splitlines() == ["key  value", "---  --------",
                                               "a    long one", "bb   2"]


# --- 4. simulate gnss: what to do with pseudoranges.csv ----------------------------------


def test_gnss_help_and_run_say_how_to_use_pseudoranges(tmp_path, capsys):
    text = " ".join(_help("simulate", "gnss").split())
    assert "no robustloc command reads pseudoranges.csv" in text
    assert "robustloc.integrity.snooping.snoop_linear(H, y, sigma)" in text
    assert "no command reads (spp takes RINEX)" in " ".join(_help("simulate").split())
    out = tmp_path / "g"
    assert main(["simulate", "gnss", "--epochs", "3", "--out", str(out)]) == 0
    err = capsys.readouterr().err
    assert "note: no robustloc command reads pseudoranges.csv" in err and "snoop_linear" in err
    assert main(["simulate", "gnss", "--epochs", "3", "--out", str(tmp_path / "q"), "-q"]) == 0
    assert "note:" not in capsys.readouterr().err  # (-q: the list of files only)


def test_the_recipe_of_gnss_help_finds_the_simulated_faults(tmp_path, capsys):
    """The help's recipe, as written there, on a run with one gross error an epoch."""
    assert "snoop_linear" in _help("simulate", "gnss")
    from robustloc.integrity.snooping import snoop_linear

    out = tmp_path / "g"
    assert main(["simulate", "gnss", "--epochs", "40", "--faults", "1", "--out",
                 str(out)]) == 0
    pr = pd.read_csv(out / "pseudoranges.csv")
    truth = pd.read_csv(out / "truth.csv").set_index("time")
    systems = sorted(pr["system"].unique())
    epochs = list(pr.groupby("time"))
    n = max(len(e) for _, e in epochs)
    H = np.zeros((len(epochs), n, 3 + len(systems)))
    y = np.full((len(epochs), n), np.nan)
    sig = np.ones((len(epochs), n))
    fault = np.zeros((len(epochs), n), dtype=bool)
    for k, (t, e) in enumerate(epochs):
        rx = truth.loc[t, ["x", "y", "z"]].to_numpy(float)
        d = rx - e[["x_sat", "y_sat", "z_sat"]].to_numpy(float)  # satellite -> receiver
        rng = np.linalg.norm(d, axis=1)
        m = len(e)
        H[k, :m, :3] = d / rng[:, None]
        H[k, :m, 3:] = e["system"].to_numpy()[:, None] == np.array(systems)
        clock = truth.loc[t, [f"clock_{s}" for s in e["system"]]].to_numpy(float)
        y[k, :m] = e["pseudorange"].to_numpy(float) - rng - clock
        sig[k, :m] = e["sigma"].to_numpy(float)
        fault[k, :m] = e["fault_m"].to_numpy(float) != 0
    res = snoop_linear(H, y, sig)
    found = (res.excluded & fault).any(axis=1)
    # measurement (seed 1, 40 epochs): the faulty satellite excluded in 40 of 40 epochs
    # (faults of 20-40 m against sigmas below 2 m); margin: 36
    assert found.sum() >= 36, found.sum()
    assert (res.excluded & ~fault).sum() <= 4  # measured: 0 good satellites excluded


def test_montecarlo_names_both_spellings_of_the_tag_height(capsys):
    """The refusal named --tag-z although the user typed --tag-height."""
    from robustloc.cli import main

    assert main(["montecarlo", "--gnss", "--tag-height", "1", "-o", "unused"]) == 2
    assert "--tag-z/--tag-height applies to --anchors layouts only" in capsys.readouterr().err
