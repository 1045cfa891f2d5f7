"""RAIM FDE on real geometry with injected faults; protection levels; the spp command."""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from robustloc import status as st
from robustloc.cli import main
from robustloc.gnss.raim import RaimFde, inject_faults, protection_levels
from robustloc.gnss.rinex import read_nav, read_obs
from robustloc.gnss.sp3 import PreciseProducts, read_clk, read_sp3
from robustloc.gnss.spp import SppSolver, error_summary
from robustloc.integrity.reliability import reliability
from robustloc.paths import PACKAGE_DATA

GEONET = PACKAGE_DATA / "gnss-geonet"
SLAC = PACKAGE_DATA / "gnss-slac"
OBS = GEONET / "07590920.05o"
NAV = GEONET / "07590920_0000-0400.05n"


@pytest.fixture(scope="module")
def geonet():  # noqa: ANN201
    return read_obs(OBS), read_nav(NAV)


def _h_err(res, ref):  # noqa: ANN001, ANN202
    e = res.enu_errors(ref)
    return np.hypot(e[:, 0], e[:, 1])


def test_fault_free_geonet_no_alarm_and_pl_bounds_error(geonet) -> None:  # noqa: ANN001
    obs, nav = geonet
    res = RaimFde().solve(SppSolver(systems="G"), obs, nav)
    assert not res.extra["detected"].any()
    assert np.sum(res.status == st.OK) == 115 and not res.excluded.any()
    ok = res.ok
    h = _h_err(res, obs.approx_xyz_m)[ok]
    hpl = res.extra["hpl_m"][ok]
    assert np.all(np.isfinite(hpl)) and np.all(h <= hpl)
    assert np.all(res.extra["vpl_m"][ok] > 0)


def test_single_20m_fault_on_real_geometry_is_excluded(geonet) -> None:  # noqa: ANN001
    obs, nav = geonet
    win = np.zeros(obs.n_epochs, dtype=bool)
    win[40:80] = True  # 6 satellites in view: redundancy 2 (the G11 window)
    bad = inject_faults(obs, {"G11": 20.0}, obs.t_gps_s[40], obs.t_gps_s[79])
    solver = SppSolver(systems="G")
    plain = solver.solve(bad, nav)
    res = RaimFde().solve(solver, bad, nav)
    j = obs.sats.index("G11")
    assert res.extra["detected"][win].all()
    assert res.excluded[win, j].mean() >= 0.95
    others = np.delete(res.excluded, j, axis=1)
    assert not others[win].any()  # never a wrong satellite
    assert set(res.status[win]) <= {st.FAULT_EXCLUDED, st.UNAVAILABLE}
    good = win & (res.status == st.FAULT_EXCLUDED)
    assert good.sum() >= 15
    unav = win & (res.status == st.UNAVAILABLE)  # kept, but flagged and not `ok`
    assert np.all(np.isfinite(res.xyz_m[unav])) and not res.ok[unav].any()
    h_raim = _h_err(res, obs.approx_xyz_m)[good]
    h_plain = _h_err(plain, obs.approx_xyz_m)[good]
    assert np.sqrt(np.mean(h_raim**2)) < 2.5 < 15.0 < np.sqrt(np.mean(h_plain**2))
    # without the identifiability check every faulty epoch is excluded and delivered
    res2 = RaimFde(check_ambiguity=False).solve(solver, bad, nav)
    assert res2.excluded[win, j].all() and (res2.status[win] == st.FAULT_EXCLUDED).all()


def test_two_simultaneous_faults_multi_gnss() -> None:
    obs = read_obs(SLAC / "slac1180_1930-1940.21o")
    pp = PreciseProducts(read_sp3(SLAC / "COD0MGXFIN_20211181905_60M_05M_ORB.SP3"),
                         read_clk(SLAC / "COD0MGXFIN_20211181930_12M_30S_CLK.CLK"))
    solver = SppSolver(systems="GRE", iono="iflc")
    clean = RaimFde().solve(solver, obs, None, pp)
    bad = inject_faults(obs, {"G17": 20.0, "G19": 20.0})
    res = RaimFde().solve(solver, bad, None, pp)
    idx = [obs.sats.index("G17"), obs.sats.index("G19")]
    both = res.excluded[:, idx].all(axis=1)
    assert both.mean() >= 0.95
    assert res.extra["detected"].all()
    assert res.excluded.sum(axis=1).max() == 2  # nothing else
    ref = obs.approx_xyz_m
    rms = {k: error_summary(r, ref)["rms_3d_m"] for k, r in
           (("clean", clean), ("raim", res), ("plain", solver.solve(bad, None, pp)))}
    assert res.ok.sum() >= 20
    assert rms["raim"] < 1.5 * rms["clean"] and rms["plain"] > 3 * rms["clean"]


def test_protection_levels_when_a_constellation_is_missing_from_an_epoch() -> None:
    """The GNSS review (2026-12-04): with Galileo absent from some epochs of a GE run, the
    absent clock's zero column made those epochs' hpl, vpl and MDB NaN while their status
    was ok.  Such an epoch is a GPS-only epoch: its protection levels and MDBs are the
    GPS-only run's (same satellites, same sigmas)."""
    import dataclasses

    obs = read_obs(SLAC / "slac1180_1930-1940.21o")
    pp = PreciseProducts(read_sp3(SLAC / "COD0MGXFIN_20211181905_60M_05M_ORB.SP3"),
                         read_clk(SLAC / "COD0MGXFIN_20211181930_12M_30S_CLK.CLK"))
    e = np.array([s[0] == "E" for s in obs.sats])
    gone = np.zeros(obs.n_epochs, dtype=bool)
    gone[:6] = True
    no_e = dataclasses.replace(obs, obs={k: np.where(gone[:, None] & e[None, :], np.nan, v)
                                         for k, v in obs.obs.items()})
    ge = RaimFde().solve(SppSolver(systems="GE", iono="iflc"), no_e, None, pp)
    g = RaimFde().solve(SppSolver(systems="G", iono="iflc"), no_e, None, pp)
    ok = gone & (ge.status == st.OK)
    assert ok.sum() >= 3
    for k in ("hpl_m", "vpl_m"):
        assert np.all(np.isfinite(ge.extra[k][ok]))
        np.testing.assert_allclose(ge.extra[k][ok], g.extra[k][ok], rtol=1e-9)
    gi = [i for i, s in enumerate(obs.sats) if s[0] == "G"]
    mdb_ge, mdb_g = ge.extra["mdb_m"][ok][:, gi], g.extra["mdb_m"][ok][:, gi]
    assert np.all(np.isfinite(mdb_ge) == np.isfinite(mdb_g)) and np.isfinite(mdb_ge).any()
    np.testing.assert_allclose(mdb_ge[np.isfinite(mdb_ge)], mdb_g[np.isfinite(mdb_g)],
                               rtol=1e-9)
    # the epochs with both constellations keep their (smaller) levels
    both = ~gone & (ge.status == st.OK)
    assert both.any() and np.all(np.isfinite(ge.extra["hpl_m"][both]))


def test_protection_levels_equal_external_reliability() -> None:
    rng = np.random.default_rng(3)
    N, n = 5, 8
    H = np.concatenate([rng.normal(size=(N, n, 3)), np.ones((N, n, 1))], axis=2)
    sigma = rng.uniform(0.5, 2.0, size=(N, n))
    used = np.ones((N, n), dtype=bool)
    used[0, 7] = False
    # at lat = lon = 0, ENU = (y, z, x) of ECEF
    xyz = np.tile([6378137.0, 0.0, 0.0], (N, 1))
    hpl, vpl = protection_levels(H, sigma, used, xyz, lam0=20.9)  # bias term only
    Henu = H[..., [1, 2, 0, 3]]
    rel = reliability(Henu, np.where(used, sigma, np.nan), mask=used, horizontal=(0, 1))
    lam_ratio = np.sqrt(20.9 / rel.lambda0)
    np.testing.assert_allclose(hpl, np.nanmax(rel.external_horizontal, axis=1) * lam_ratio,
                               rtol=1e-9)
    np.testing.assert_allclose(vpl, np.nanmax(np.abs(rel.external[..., 2]), axis=1) * lam_ratio,
                               rtol=1e-9)
    # plus k times the fault-free sigma: the largest eigenvalue of the EN covariance
    hpl3, vpl3 = protection_levels(H, sigma, used, xyz, lam0=20.9, k_noise=3.0)
    A = Henu / sigma[..., None] * used[..., None]
    C = np.linalg.inv(np.swapaxes(A, 1, 2) @ A)
    np.testing.assert_allclose(hpl3 - hpl, 3.0 * np.sqrt(np.linalg.eigvalsh(C[:, :2, :2])[:, 1]),
                               rtol=1e-9)
    np.testing.assert_allclose(vpl3 - vpl, 3.0 * np.sqrt(C[:, 2, 2]), rtol=1e-9)


def test_inject_unknown_satellite(geonet) -> None:  # noqa: ANN001
    obs, _ = geonet
    with pytest.raises(ValueError, match="G99"):
        inject_faults(obs, {"G99": 10.0})


def test_cli_spp_raim_json(tmp_path: Path, capsys) -> None:  # noqa: ANN001
    out = tmp_path / "sol.csv"
    code = main(["spp", str(OBS), str(NAV), "--systems", "G", "--raim", "--inject", "G11:30",
                 "--inject-from", "2005-04-02T00:20:00", "--inject-until", "796436400.5", "-o",
                 str(out), "--json"])
    assert code == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["epochs"] == 120 and summary["raim"] is True
    assert summary["faults_detected"] == 1  # only the 00:20:00 epoch carries the fault
    df = pd.read_csv(out)
    assert len(df) == 120
    for col in ("time", "utc", "x", "lat", "h", "clock_G_m", "n_sats", "gdop", "hdop", "status",
                "excluded", "global_stat", "hpl", "vpl"):
        assert col in df.columns
    assert df.excluded.fillna("").str.contains("G11").sum() == 1
    # values: the excluded epoch is the injected one (00:20:00 = GPS 796436400), and the
    # protection levels bound the error at every solved epoch (errors from pymap3d's ENU
    # against the station coordinates; with a fault-free 1e-7-class integrity risk budget
    # a single violation in 115 epochs would already be a failure)
    import pymap3d

    t_exc = df.time[df.excluded.fillna("").str.contains("G11")].to_numpy()
    np.testing.assert_allclose(t_exc, [796436400.0], atol=0.01)  # epochs carry ms offsets
    ok = df.status.isin(["ok", "fault_excluded"])
    assert ok.sum() == 115  # RTKLIB: 115/120 (the 5 last epochs have GDOP > 30)
    lat0, lon0, h0 = pymap3d.ecef2geodetic(-3976219.5082, 3382372.5671, 3652512.9849)
    e, n, u = pymap3d.ecef2enu(df.x[ok], df.y[ok], df.z[ok], lat0, lon0, h0)
    assert np.all(np.hypot(e, n) < df.hpl[ok]) and np.all(np.abs(u) < df.vpl[ok])


def test_cli_spp_text_summary_and_reference(tmp_path: Path, capsys) -> None:  # noqa: ANN001
    out = tmp_path / "sol.parquet"
    ref = "-3976219.5082,3382372.5671,3652512.9849"
    assert main(["spp", str(OBS), str(NAV), f"--reference={ref}", "-o", str(out)]) == 0
    text = capsys.readouterr().out
    assert "115/120 epochs solved" in text  # RTKLIB 2.4.3: 115/120 at the 15 deg mask
    m = re.search(r"RMS horizontal ([0-9.]+) m", text)
    assert m is not None, text
    df = pd.read_parquet(out)
    assert len(df) == 120
    # the printed RMS is the output file's: recomputed with pymap3d's ENU (not robustloc's)
    import pymap3d

    ok = df.status == "ok"
    lat0, lon0, h0 = pymap3d.ecef2geodetic(*[float(v) for v in ref.split(",")])
    e, n, _ = pymap3d.ecef2enu(df.x[ok], df.y[ok], df.z[ok], lat0, lon0, h0)
    rms_h = float(np.sqrt(np.mean(np.asarray(e) ** 2 + np.asarray(n) ** 2)))
    assert float(m.group(1)) == pytest.approx(rms_h, abs=0.005)  # printed to 2 decimals
    # and it is RTKLIB's figure on the same files (rnx2rtkp -p 0: 0.67 m, data README),
    # within the README's 5 % regression tolerance
    assert rms_h <= 0.67 * 1.05


@pytest.mark.parametrize(
    "argv, message",
    [
        (["spp", str(OBS), "-o", "x.csv"], "navigation file or --sp3"),
        (["spp", str(OBS), str(NAV), "--inject", "G11", "-o", "x.csv"], "PRN:BIAS_M"),
        (["spp", str(OBS), str(NAV), "--reference", "1,2", "-o", "x.csv"], "X,Y,Z"),
        (["spp", str(OBS), str(NAV), "--systems", "GQ", "-o", "x.csv"], "constellation"),
        (["spp", "missing.05o", str(NAV), "-o", "x.csv"], "missing.05o"),
        (["spp", str(SLAC / "slac1180_1930-1940.21o"), str(SLAC / "brdc1180_1700-2200.21n"),
          "--systems", "E", "--raim", "-o", "x.csv"], "no usable pseudoranges"),
        (["spp", str(OBS), "--sp3", str(NAV), "-o", "x.csv"], "SP3"),
    ],
)
def test_cli_errors(tmp_path: Path, capsys, argv, message) -> None:  # noqa: ANN001
    argv = [a if a != "x.csv" else str(tmp_path / "x.csv") for a in argv]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert err.startswith("error:") and message in err


def test_cli_truncated_rinex(tmp_path: Path, capsys) -> None:  # noqa: ANN001
    lines = OBS.read_text().splitlines()
    cut = tmp_path / "cut.05o"
    cut.write_text("\n".join(lines[:500]) + "\n")
    assert main(["spp", str(cut), str(NAV), "-o", str(tmp_path / "s.csv")]) == 2
    err = capsys.readouterr().err
    assert f"error: {cut}:" in err and "ends inside" in err


def test_cli_spp_raim_counts_when_no_fix_is_usable(capsys) -> None:  # noqa: ANN001
    """With a reference (the header's position) and RAIM rejecting every epoch (a 50 m
    fault, no exclusion allowed), the summary still counts the faults: the text's
    ``RAIM:`` line and JSON's ``faults_detected`` vanished exactly then (the GNSS review,
    2026-12-07), while the same file without a reference printed them."""
    import tempfile

    with tempfile.TemporaryDirectory() as d:
        out = str(Path(d) / "sol.csv")
        args = ["spp", str(OBS), str(NAV), "--raim", "--inject", "G11:50",
                "--max-exclusions", "0", "-o", out]
        assert main([*args, "--json"]) == 0
        summary = json.loads(capsys.readouterr().out)
        assert summary["solved"] == 0
        assert summary["faults_detected"] > 100 and summary["epochs_with_exclusion"] == 0
        assert main(args) == 0
        text = capsys.readouterr().out
        assert f"RAIM: faults detected in {summary['faults_detected']} epochs" in text
