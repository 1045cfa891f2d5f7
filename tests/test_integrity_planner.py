"""Anchor-layout planner (integrity.planner) and the reliability command."""

import json

import numpy as np
import pandas as pd
import pytest

from robustloc.cli import main
from robustloc.eval.crlb import crlb_range
from robustloc.integrity import reliability
from robustloc.integrity.planner import grid_axes, plan
from robustloc.models.ranging import RangeModel

SQUARE = np.array([[0.0, 0.0], [10.0, 0.0], [10.0, 10.0], [0.0, 10.0], [5.0, -2.0]])


def test_plan_matches_direct_computation():
    g = plan(SQUARE, (1, 9, 1, 9), 2.0, 0.5)
    assert len(g.table) == 25
    row = g.table[(g.table.x == 5.0) & (g.table.y == 5.0)].iloc[0]
    H = RangeModel(SQUARE).jacobian(np.array([[5.0, 5.0]]))
    rel = reliability(H, 0.5)
    assert row["max_mdb"] == pytest.approx(rel.max_mdb[0])
    assert row["max_ext_m"] == pytest.approx(rel.max_external_horizontal[0])
    assert row["max_abs_rho"] == pytest.approx(rel.max_abs_rho[0])
    assert row["min_redundancy"] == pytest.approx(rel.min_redundancy[0])
    assert row["crlb_m"] == pytest.approx(crlb_range(SQUARE, [[5.0, 5.0]], 0.5).rmse[0])
    assert row["dop"] == pytest.approx(row["crlb_m"] / 0.5)
    assert row["dof"] == 3 and row["n_heard"] == 5
    assert g.field("dop").shape == (5, 5)


def test_plan_max_range_and_rssi():
    g = plan(SQUARE, (0, 10, 0, 10), 5.0, 1.0, max_range_m=6.0)
    # at (0, 10) only the corner anchor is in range: no fix
    r = g.table[(g.table.x == 0) & (g.table.y == 10)].iloc[0]
    assert r["n_heard"] < 3 and np.isnan(r["max_mdb"])
    g2 = plan(SQUARE, (1, 9, 1, 9), 4.0, 4.0, model="rssi", path_loss_n=2.0)
    assert np.all(np.isfinite(g2.table["crlb_m"]))
    with pytest.raises(ValueError):
        plan(SQUARE, (1, 9, 1, 9), 4.0, 1.0, dim=3)
    with pytest.raises(ValueError):
        grid_axes((0, -1, 0, 1), 1.0)


def test_grid_reaches_both_edges():
    # a step that divides the extent is kept exactly
    gx, gy = grid_axes((0, 10, -2, 4), 2.0)
    np.testing.assert_array_equal(gx, [0, 2, 4, 6, 8, 10])
    np.testing.assert_array_equal(gy, [-2, 0, 2, 4])
    # one that does not: the far strip is covered (floor stopped at x 9, y 6; the
    # stats review), evenly, no two points more than the step apart
    gx, gy = grid_axes((0, 10, 0, 8), 3.0)
    assert gx[0] == 0 and gx[-1] == 10 and gy[0] == 0 and gy[-1] == 8
    assert len(gx) == 5 and len(gy) == 4  # ceil(10 / 3) + 1, ceil(8 / 3) + 1
    for g in (gx, gy):
        d = np.diff(g)
        assert d.max() <= 3.0 and d.max() - d.min() < 1e-12
    g = plan(SQUARE, (0, 10, 0, 8), 3.0, 0.5)
    assert g.table["x"].max() == 10 and g.table["y"].max() == 8


def test_cli_reliability(tmp_path, capsys):
    anchors = tmp_path / "anchors.csv"
    pd.DataFrame({"anchor": list("ABCDE"), "x": SQUARE[:, 0], "y": SQUARE[:, 1],
                  "z": [2.5] * 5}).to_csv(anchors, index=False)
    out = tmp_path / "rel"
    rc = main(["reliability", "--anchors", str(anchors), "--area", "0,10,0,10", "--step", "1",
               "--sigma", "0.3", "-o", str(out), "--json"])
    assert rc == 0
    js = json.loads(capsys.readouterr().out)
    assert js["grid_points"] == 121
    t = pd.read_csv(out / "reliability.csv")
    assert {"x", "y", "dop", "crlb_m", "max_mdb", "max_ext_m", "max_abs_rho",
            "min_redundancy", "dof"} <= set(t.columns)
    for name in ("dop", "crlb_m", "max_mdb", "max_ext_m", "max_abs_rho", "min_redundancy"):
        assert (out / f"reliability_{name}.png").stat().st_size > 1000
    # the values, at one grid point, from the textbook formulas in numpy: 2-D position from
    # slant ranges (anchors 2.5 m above the tag), unit line-of-sight rows H, N = H^T H,
    # DOP = sqrt(tr N^-1), CRLB = sigma DOP, redundancy r_i = (I - H N^-1 H^T)_ii,
    # rho_ij = R_ij / sqrt(R_ii R_jj), MDB_i = sqrt(lambda0) sigma / sqrt(r_i) with
    # lambda0 from scipy's ncx2 (alpha0 = 0.1 %, power 90 %)
    from scipy.optimize import brentq
    from scipy.stats import chi2, ncx2

    r = t[(t.x == 3) & (t.y == 6)].iloc[0]
    v = np.c_[np.array([3.0, 6.0]) - SQUARE, np.full(5, -2.5)]
    H = (v / np.linalg.norm(v, axis=1)[:, None])[:, :2]
    Ni = np.linalg.inv(H.T @ H)
    R = np.eye(5) - H @ Ni @ H.T
    rho = R / np.sqrt(np.outer(np.diag(R), np.diag(R)))
    lam0 = brentq(lambda L: ncx2.sf(chi2.ppf(0.999, 1), 1, L) - 0.9, 1.0, 100.0)
    ref = {"dop": np.sqrt(np.trace(Ni)), "crlb_m": 0.3 * np.sqrt(np.trace(Ni)),
           "min_redundancy": np.diag(R).min(),
           "max_abs_rho": np.abs(rho[~np.eye(5, dtype=bool)]).max(),
           "max_mdb": (np.sqrt(lam0) * 0.3 / np.sqrt(np.diag(R))).max()}
    for k, val in ref.items():  # the CSV holds 6 significant digits
        assert r[k] == pytest.approx(val, rel=1e-5), (k, r[k], val)
    # refused by the option's type (argparse's exit code 2, which cli.main returns)
    assert main(["reliability", "--anchors", str(anchors), "--step", "-1", "-o", str(out)]) == 2
    assert "--step" in capsys.readouterr().err
    assert main(["reliability", "--anchors", str(tmp_path / "none.csv"), "-o", str(out)]) == 2


def test_suggest_anchor_finds_the_missing_corner():
    from robustloc.integrity.planner import default_candidates, layout_score, suggest_anchor

    three = np.array([[0.0, 0.0], [10.0, 0.0], [10.0, 10.0]])
    cand = default_candidates((0, 10, 0, 10), 4)
    assert len(cand) == 16
    df = suggest_anchor(three, (0, 10, 0, 10), 1.0, 1.0, cand)
    assert (df.loc[0, "x"], df.loc[0, "y"]) == (0.0, 10.0)
    assert df["score"].is_monotonic_increasing
    g4 = plan(np.vstack([three, [0.0, 10.0]]), (0, 10, 0, 10), 1.0, 1.0)
    assert df.loc[0, "score"] == pytest.approx(layout_score(g4))
    with pytest.raises(ValueError):
        layout_score(g4, metric="nope")
    with pytest.raises(ValueError):
        suggest_anchor(three, (0, 10, 0, 10), 1.0, 1.0, [[1.0, 2.0, 3.0]])


def test_cli_reliability_suggest(tmp_path, capsys):
    anchors = tmp_path / "anchors.csv"
    pd.DataFrame({"anchor": ["A", "B", "C"], "x": [0.0, 10.0, 10.0],
                  "y": [0.0, 0.0, 10.0]}).to_csv(anchors, index=False)
    cand = tmp_path / "cand.csv"
    pd.DataFrame({"x": [5.0, 0.0], "y": [5.0, 10.0]}).to_csv(cand, index=False)
    out = tmp_path / "rel"
    rc = main(["reliability", "--anchors", str(anchors), "--area", "0,10,0,10", "--step", "2",
               "-o", str(out), "--suggest", "--candidates", str(cand), "--json", "--no-maps"])
    assert rc == 0
    js = json.loads(capsys.readouterr().out)
    assert js["suggestions"][0]["x"] == 0.0 and js["suggestions"][0]["y"] == 10.0
    assert len(pd.read_csv(out / "suggestions.csv")) == 2
    assert js["figures"] == [] and not list(out.glob("*.png"))


def test_suggest_with_per_anchor_path_loss_exponents():
    from robustloc.integrity.planner import default_candidates, suggest_anchor

    four = np.array([[0.0, 0.0], [10.0, 0.0], [10.0, 10.0], [0.0, 10.0]])
    df = suggest_anchor(four, (0, 10, 0, 10), 2.5, 3.0, default_candidates((0, 10, 0, 10), 2),
                        model="rssi", path_loss_n=np.array([2.0, 2.1, 2.2, 2.3]))
    assert len(df) == 8 and np.isfinite(df["score"]).all()
    assert (df["improvement"] > 0).all()


def test_plan_and_reliability_refuse_bad_settings_by_name():
    """The API review: chunk=0 said "range() arg 3 must not be zero", an area of three
    numbers "not enough values to unpack", a mask of the wrong width "operands could not
    be broadcast"."""
    a = np.array([[0, 0], [10, 0], [10, 10], [0, 10]], float)
    with pytest.raises(ValueError, match="chunk"):
        plan(a, (0, 10, 0, 10), 1.0, 0.1, chunk=0)
    with pytest.raises(ValueError, match="four numbers"):
        plan(a, (0, 10, 0), 1.0, 0.1)
    H = np.random.default_rng(0).normal(size=(10, 4, 2))
    with pytest.raises(ValueError, match="chunk"):
        reliability(H, 1.0, chunk=0)
    with pytest.raises(ValueError, match="mask has shape"):
        reliability(H, 1.0, np.ones((10, 3), bool))
