"""``robustloc filter`` / ``robustloc stats`` and the seed-002 report section."""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from unittest import mock

import numpy as np
import pandas as pd
import pytest

from robustloc.cli import main
from robustloc.filters.rssi import (
    LinkParams,
    RobustRssiFilter,
    filter_measurements,
    link_params_from_anchors,
)
from robustloc.models.pathloss import AttenuationFactor
from robustloc.sim.wifi_room import simulate


@pytest.fixture(scope="module")
def sim(tmp_path_factory) -> dict[str, Path]:
    out = tmp_path_factory.mktemp("wifi")
    ns = argparse.Namespace(samples_per_point=10, walk_epochs=60)
    return simulate(out, 4, ns)


def test_filter_cli_writes_locatable_measurements(sim, tmp_path, capsys):
    out = tmp_path / "filtered.csv"
    rc = main([
        "filter", str(sim["measurements"]), "--anchors", str(sim["anchors"]), "-o", str(out),
        "--json",
    ])
    assert rc == 0
    summary = json.loads(capsys.readouterr().out)
    raw = pd.read_csv(sim["measurements"])
    f = pd.read_csv(out)
    assert summary["samples"] == len(raw) == len(f)
    assert summary["links"] == 21 * 4  # 20 points + walk, 4 APs
    # same rows, same order; rssi filtered, raw kept
    pd.testing.assert_frame_equal(f[["time", "tag", "anchor"]], raw[["time", "tag", "anchor"]])
    np.testing.assert_allclose(f["rssi_raw"], raw["rssi"])
    assert not np.allclose(f["rssi"], raw["rssi"])
    # the distance column is the filtered RSSI through the anchor's model (eq. 5)
    a = pd.read_csv(sim["anchors"]).set_index("anchor").loc[f["anchor"]]
    np.testing.assert_allclose(
        f["distance"],
        AttenuationFactor(a["p0"], a["gamma"], a["faf"], a["d0"]).distance(f["rssi"]),
    )
    # contract readers accept it as a measurements file
    from robustloc.io import read_measurements

    back = read_measurements(out)
    assert back.attrs["value"] == "rssi"


def test_filter_then_locate_unchanged(sim, tmp_path):
    out = tmp_path / "f.csv"
    assert main(["filter", str(sim["measurements"]), "--anchors", str(sim["anchors"]),
                 "-o", str(out), "--static"]) == 0
    pos = tmp_path / "pos.csv"
    assert main(["locate", str(out), "--anchors", str(sim["anchors"]), "--method", "nls",
                 "-o", str(pos)]) == 0
    p = pd.read_csv(pos)
    assert len(p) == 20 * 10 + 60  # one row per epoch
    # every epoch a row with a known status; since issue 10 each fix is tested, and an
    # epoch whose flagged RSSI leaves nothing to confirm the rest is `unavailable`
    from robustloc import status as st

    assert p["status"].isin(st.ALL).all()
    assert p["status"].isin(st.USABLE).mean() > 0.95
    # values: at the 20 static reference points (10 samples each) the static filter's
    # averaging makes the fixes more accurate than locating the raw RSSI (measured: 0.98 m
    # against 1.16 m RMS for seed 4); on the walk the static model lags, so it is not
    # compared there
    raw_pos = tmp_path / "raw.csv"
    assert main(["locate", str(sim["measurements"]), "--anchors", str(sim["anchors"]),
                 "--method", "nls", "-o", str(raw_pos)]) == 0
    tru = pd.read_csv(sim["truth"])

    def rms_static(path):
        m = pd.read_csv(path).merge(tru, on=["time", "tag"], suffixes=("", "_t"))
        m = m[m.tag.str.startswith("rp")]
        assert len(m) == 200
        return np.sqrt(np.nanmean((m.x - m.x_t) ** 2 + (m.y - m.y_t) ** 2))

    assert rms_static(pos) < rms_static(raw_pos)


def test_filter_cli_plain_equals_library(sim, tmp_path):
    out = tmp_path / "plain.csv"
    assert main(["filter", str(sim["measurements"]), "--anchors", str(sim["anchors"]),
                 "-o", str(out), "--robust", "none"]) == 0
    f = pd.read_csv(out)
    lib = filter_measurements(pd.read_csv(sim["measurements"]), pd.read_csv(sim["anchors"]),
                              RobustRssiFilter(robust=False)).frame
    np.testing.assert_allclose(f["rssi"], lib["rssi"])
    assert (f["weight"].dropna() == 1).all()


def test_filter_cli_errors(sim, tmp_path, capsys):
    bad = tmp_path / "bad.csv"
    pd.read_csv(sim["measurements"]).rename(columns={"rssi": "range"}).to_csv(bad, index=False)
    assert main(["filter", str(bad), "--anchors", str(sim["anchors"]),
                 "-o", str(tmp_path / "x.csv")]) == 2
    assert "rssi" in capsys.readouterr().err
    unknown = tmp_path / "unknown.csv"
    m = pd.read_csv(sim["measurements"])
    m.loc[5, "anchor"] = "AP9"
    m.to_csv(unknown, index=False)
    assert main(["filter", str(unknown), "--anchors", str(sim["anchors"]),
                 "-o", str(tmp_path / "x.csv")]) == 2
    err = capsys.readouterr().err
    assert "AP9" in err and ":7" in err  # file line of the bad row
    assert main(["filter", str(tmp_path / "none.csv"), "--anchors", str(sim["anchors"]),
                 "-o", str(tmp_path / "x.csv")]) == 2


def test_link_params_fallbacks():
    anchors = pd.DataFrame({"anchor": ["a", "b", "c"], "x": 0.0, "y": 0.0,
                            "p0": [-30.0, np.nan, np.nan], "gamma": [2.5, np.nan, np.nan],
                            "faf": [1.0, np.nan, np.nan], "A": [np.nan, -45.0, np.nan],
                            "n": [np.nan, 2.2, np.nan]})
    p = link_params_from_anchors(anchors, ["c", "a", "b"])
    np.testing.assert_allclose(p.p0_dbm, [-40, -30, -45])
    np.testing.assert_allclose(p.gamma, [2.0, 2.5, 2.2])
    np.testing.assert_allclose(p.faf_db, [0, 1, 0])
    assert isinstance(LinkParams.broadcast(2).d0_m, np.ndarray)


def test_stats_cli(sim, tmp_path, capsys):
    out = tmp_path / "stats"
    rc = main(["stats", str(sim["measurements"]), "--anchors", str(sim["anchors"]),
               "--truth", str(sim["truth"]), "--max-lag", "10", "-o", str(out)])
    assert rc == 0
    text = capsys.readouterr().out
    assert "per distance bin" in text
    # the numbers, recomputed here with pandas/scipy from the input files (not the label
    # "0.578", which is the paper's value printed beside ours): true distance of each sample
    # (truth interpolated in time), 1 m bins (>= 1 m), bins of >= 10 samples, sample
    # variance (ddof 1) per (anchor, bin), Pearson r of variance against bin distance
    from scipy.stats import pearsonr

    meas = pd.read_csv(sim["measurements"])
    anc = pd.read_csv(sim["anchors"]).set_index("anchor")
    tru = pd.read_csv(sim["truth"])
    pos = np.column_stack([
        np.concatenate([np.interp(meas.time[meas.tag == g], tr.time, tr[c])
                        for g, tr in tru.groupby("tag")]) for c in ("x", "y")])
    meas = pd.concat([meas[meas.tag == g] for g, _ in tru.groupby("tag")])
    d = np.hypot(pos[:, 0] - anc.loc[meas.anchor, "x"].to_numpy(),
                 pos[:, 1] - anc.loc[meas.anchor, "y"].to_numpy())
    meas = meas.assign(bin_m=np.maximum(np.round(d), 1.0))
    meas = meas[np.isfinite(meas.rssi)]
    grp = meas.groupby(["anchor", "bin_m"])["rssi"].agg(["size", "var"]).reset_index()
    grp = grp[grp["size"] >= 10]
    per_bin = pd.read_csv(out / "per_bin.csv")
    np.testing.assert_allclose(per_bin["variance"].to_numpy(), grp["var"].to_numpy(), rtol=1e-9)
    r_ref = pearsonr(grp["bin_m"], grp["var"]).statistic
    assert f"correlation of variance with distance: {r_ref:.3f}" in text
    summary = json.loads((out / "summary.json").read_text())
    assert summary["variance_distance_corr"] == pytest.approx(r_ref, abs=1e-12)
    for name in ("per_anchor.csv", "per_bin.csv", "acf.csv", "histograms.png",
                 "autocorrelation.png", "summary.json"):
        assert (out / name).is_file(), name
    assert len(pd.read_csv(out / "acf.csv")) == 11
    assert main(["stats", str(sim["measurements"]), "--truth", str(sim["truth"]),
                 "-o", str(out)]) == 2
    assert "--anchors" in capsys.readouterr().err


def test_reproduce_section_quick_without_shared_data(tmp_path):
    from robustloc.reproduce import Context, fmt_num
    from robustloc.reproduce import s30_wifi_rssi as s30

    ctx = Context(out_dir=tmp_path, data_dir=None, seed=1, quick=True)
    with mock.patch("robustloc.paths.default_data_dir", return_value=None):
        sec = s30.run(ctx)
    s = sec.summary
    # the robust filter beats the raw attenuation model on the static points (paper: 0.544
    # vs 0.871 m), and the real-data parts ran on the shipped excerpts
    assert s["sim_static_robust_m"] < 0.8 * s["sim_static_raw_m"]
    assert s["sim_static_last_robust_m"] < s["sim_static_raw_m"]
    assert s["ble_source"] == "excerpt"
    assert np.isfinite(s["ble_raw_m"]) and np.isfinite(s["wifi_lecture_theatre_robust_m"])
    captions = [p[0] for k, p in sec.blocks if k == "table"]
    assert any("Table 3" in c for c in captions) and any("Table 1" in c for c in captions)
    figs = [p[1] for k, p in sec.blocks if k == "figure"]
    assert all((tmp_path / f).is_file() for f in figs) and len(figs) >= 2
    # seed 002's real-data results are in the report's summary (only its simulated
    # Table 3 rows were: the report review), with the run's numbers, said as excerpts
    heads = sec.headlines
    assert [h["headline"].split(",")[0] for h in heads] == ["ble-tetam tracks",
                                                           "wifi-rtt-rss RSS static test points"]
    assert all("(excerpts)" in h["headline"] and h["seed"] == "002" for h in heads)
    ble, wifi = heads
    assert ble["paper"].startswith("5.38 -> 1.41") and "its WiFi walk" in ble["paper"]
    assert ble["robustloc"].startswith(f"{fmt_num(s['ble_raw_m'])} -> "
                                       f"{fmt_num(s['ble_robust_m'])}")
    assert wifi["paper"].startswith("0.871 -> 0.544")
    assert wifi["robustloc"] == (f"{fmt_num(s['wifi_lecture_theatre_raw_m'])} -> "
                                 f"{fmt_num(s['wifi_lecture_theatre_robust_m'])}")
    assert all(h["verdict"].endswith(("a gain as large as the paper's",
                                      "a smaller gain than the paper's")) for h in heads)


def test_friis_anchors_from_calibrate_work_in_locate_track_and_filter(sim, tmp_path, capsys):
    """`calibrate --model friis` writes ``p0, d0`` and no ``gamma``.  Before, `locate`
    refused that file without ``--model friis`` ("anchors have no path-loss parameters"),
    `track` (which has no ``--model``) could not use it at all, and `filter` ignored
    ``p0`` for its distances (-40 dBm, the no-parameters default).  Friis is the
    attenuation-factor model with gamma = 2 and no FAF (seed 002, eqs. (1) and (5)), so
    each command must give exactly what it gives on that file."""
    fr = tmp_path / "friis.csv"
    assert main(["calibrate", str(sim["survey"]), "--model", "friis",
                 "--anchors", str(sim["anchors"]), "-o", str(fr)]) == 0
    a = pd.read_csv(fr)
    assert "p0" in a and "gamma" not in a
    att = tmp_path / "att.csv"
    a.assign(gamma=2.0, faf=0.0).to_csv(att, index=False)
    meas = str(sim["measurements"])
    for cmd, extra in (("locate", []), ("track", []), ("filter", [])):
        outs = []
        for anchors in (fr, att):
            out = tmp_path / f"{cmd}_{anchors.stem}.csv"
            assert main([cmd, meas, "--anchors", str(anchors), "-o", str(out), "--quiet"]
                        + extra) == 0, cmd
            outs.append(pd.read_csv(out))
        pd.testing.assert_frame_equal(outs[0], outs[1], obj=cmd)
    f = pd.read_csv(tmp_path / "filter_friis.csv")
    first = f.groupby(["tag", "anchor"]).head(1).iloc[0]
    p0 = float(a.set_index("anchor").loc[first["anchor"], "p0"])
    # the first sample of a link: its distance is the model's at its RSSI (gamma = 2)
    np.testing.assert_allclose(first["distance"], 10 ** ((p0 - first["rssi"]) / 20), rtol=1e-9)
    explicit = tmp_path / "locate_explicit.csv"
    assert main(["locate", meas, "--anchors", str(fr), "--model", "friis", "-o",
                 str(explicit), "--quiet"]) == 0
    pd.testing.assert_frame_equal(pd.read_csv(explicit),
                                  pd.read_csv(tmp_path / "locate_friis.csv"))
