"""The seed-000 report section runs on the shipped excerpts alone (a fresh clone)."""

import json

import pytest

import robustloc.paths
from robustloc.datasets import ble_tetam
from robustloc.reproduce import Context, run_all


@pytest.fixture
def no_shared_data(monkeypatch):
    monkeypatch.setattr(robustloc.paths, "default_data_dir", lambda: None)
    import robustloc.datasets.ble_tetam as bt

    if hasattr(bt, "default_data_dir"):
        monkeypatch.setattr(bt, "default_data_dir", lambda: None)


def test_s10_quick_on_excerpts(tmp_path, no_shared_data):
    ctx = Context(out_dir=tmp_path, data_dir=None, seed=1, quick=True)
    (sec,) = run_all(ctx, ["s10_ble_ranging"])
    summary = json.loads((tmp_path / "summary.json").read_text())["s10_ble_ranging"]
    # the paper's Table 1 rows exist for both schemes, and the nonlinear solvers beat LS
    assert set(summary["table1_scheme1_rms"]) == {"ls", "huber", "hampel", "igg", "lege"}
    assert summary["table1_best_nonlinear_rms"]["1"] < 0.5 * summary["table1_scheme1_rms"]["ls"]
    # real-data parts ran on the excerpts and calibrated huber beats raw Gauss-Newton
    for room in ("lecture_theatre", "office", "corridor"):
        w = summary[f"wifi_{room}"]
        assert w["source"] == "excerpt"
        assert w["huber_calibrated_rms"] < w["issue_best_peer_rms"]
    assert summary["ble_tetam_rms"]["huber"] < summary["ble_tetam_rms"]["ls"]
    # the summary's rows (the report review): the best peer is a peer tool's run on the
    # same epochs with its number (it was our own LS, the worst method), the paper's
    # column is the paper's published figure or "-" (it held our run of its method), the
    # simulated corridor says so and the excerpt says so
    heads = sec.headlines
    assert len(heads) == 3
    for h in heads:
        name, value = h["best peer"].rsplit(" ", 1)
        assert name.split()[0] in ("scipy", "statsmodels"), h
        assert float(value) > 0
    t1 = [h for h in heads if h["headline"].startswith("Table 1")]
    assert len(t1) == 2
    for h in t1:
        assert "(simulated corridor)" in h["headline"] and h["verdict"].endswith("(simulation)")
    assert [h["paper"] for h in t1] == ["IGG 2.2", "IGG 2.6"]
    (ble,) = [h for h in heads if h["headline"].startswith("ble-tetam")]
    assert ble["paper"] == "-" and "(excerpts)" in ble["headline"]
    assert "linearized IGG, run here" in ble["verdict"]
    # the prose counts the tracks it ran (it said "five" on the two-track excerpt)
    text = " ".join(p for k, p in sec.blocks if k == "text")
    n_tracks = len(ble_tetam.list_tracks(None))
    assert f"one file of the {n_tracks} tracks" in text and "five tracks" not in text
    html = (tmp_path / "report.html").read_text()
    assert "Table 1" in html and "seed000_ble_cdf.png" in html
    assert (tmp_path / "seed000_wifi_office_cdf.png").stat().st_size > 1000


def test_only_takes_a_unique_prefix_and_refuses_unknown_sections(tmp_path, capsys):
    """``--only s60`` names ``s60_tracks``; an unknown or ambiguous name is the user's
    mistake: ``error: argument --only: ...`` and exit code 2, before any work."""
    from robustloc.cli import main
    from robustloc.reproduce import section_modules

    assert [m.KEY for m in section_modules(["s60"])] == ["s60_tracks"]
    assert [m.KEY for m in section_modules(["s10_ble_ranging", "s6"])] == [
        "s10_ble_ranging", "s60_tracks"]
    for bad in ("s99", "s"):  # unknown; a prefix of every section
        assert main(["reproduce", "--only", bad, "-o", str(tmp_path / "r")]) == 2
        err = capsys.readouterr().err
        assert err.startswith("error: argument --only: unknown or ambiguous section(s) "
                              f"{bad};"), err
        assert "Traceback" not in err
    assert not (tmp_path / "r").exists()
