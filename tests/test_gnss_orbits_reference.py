"""Galileo and BeiDou broadcast orbits against outside references.

Data: ``../shared/data/gnss-mgex`` (Stanford-NavLab/gnss_lib_py @be41b0b9, MIT): RINEX 3
broadcast navigation excerpts of 2023-03-14 (BRDC00WRD: E01, E02, BeiDou GEO C05 and IGSO
C06; BRDM00DLR: BeiDou GEO C01, C02) and CODE's rapid precise orbits (SP3, GPS + GLONASS +
Galileo, 00:00-00:10 at 5 min) of the same day.

References:

* Galileo (and GPS) against CODE's SP3, the precise orbit (centimetres).  Tolerance: the
  broadcast orbit's own error plus the antenna offset.  Published accuracy of the
  broadcast orbit: Galileo OS SDD (issue 1.2, 2021) specifies a signal-in-space range error
  <= 7 m (95 %); the measured SISE of 2023 is 0.2-0.3 m (95 %, EUSPA quarterly performance
  reports) and the 3-D orbit error a few decimetres (Montenbruck et al., GPS Solutions 22:36,
  2018, "Multi-GNSS signal-in-space range error assessment").  Broadcast orbits refer to the
  antenna phase centre, SP3 to the centre of mass: about 0.8-1.5 m, mostly radial (seen here
  as a radial difference of -0.7 to -1.4 m).  Bound: 2.0 m in 3-D (APC offset 1.5 m plus
  0.5 m orbit error).  A plausible bug (Omega_dot, a harmonic term, the wrong week second)
  moves the satellite by hundreds of metres to kilometres.
* BeiDou GEO and IGSO: no precise product in the excerpt, so RTKLIB's own ``eph2pos``
  (through the PyPI binding ``pyrtklib``, an implementation written independently of this
  project; its GEO branch is the BeiDou ICD's -5 degree rotation) on the same records.
  Both evaluate the same closed-form ICD equations in float64, so they agree to rounding:
  1 mm (|r| = 4.2e7 m times a few 1e-16 per operation is far below it; a wrong rotation
  sign or angle is metres to kilometres).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from robustloc.gnss.ephemeris import broadcast_state, select_ephemeris
from robustloc.gnss.rinex import NavData, read_nav
from robustloc.gnss.sp3 import PreciseProducts, read_clk, read_sp3
from robustloc.paths import default_data_dir

pyrtklib = pytest.importorskip("pyrtklib", reason="test-only reference, in the [test] extra")

_DATA = default_data_dir()  # ../shared/data beside the checkout (README "Real data")
MGEX = (Path(_DATA) if _DATA is not None else Path("missing")) / "gnss-mgex"
BRDC = MGEX / "BRDC00WRD_S_20230730000_01D_MN.rnx"
BRDM = MGEX / "BRDM00DLR_S_20230730000_01D_MN.rnx"
SP3 = MGEX / "COD0OPSRAP_20230730000_01D_05M_ORB.SP3"
CLK = MGEX / "COD0OPSRAP_20230730000_01D_30S_CLK.CLK"
GPS_EPOCH_UNIX = 315964800  # 1980-01-06 00:00:00 in Unix seconds (RTKLIB gtime_t.time)

pytestmark = pytest.mark.skipif(not MGEX.is_dir(), reason="needs ../shared/data/gnss-mgex")


def _rtklib_nav(path: Path):
    nav = pyrtklib.nav_t()
    assert pyrtklib.readrnx(str(path), 1, "", pyrtklib.obs_t(), nav, pyrtklib.sta_t()) == 1
    return nav


def _rtklib_sat_name(satno: int) -> str:
    prn = pyrtklib.Arr1Dint(1)
    sys = pyrtklib.satsys(satno, prn)
    letter = {pyrtklib.SYS_GPS: "G", pyrtklib.SYS_GAL: "E", pyrtklib.SYS_CMP: "C"}.get(sys)
    return f"{letter}{prn[0]:02d}" if letter else ""


def _rtklib_records(path: Path, sat: str, offsets_s: np.ndarray):
    """(toe GPS seconds, (T, 3) ECEF positions at toe + offsets, health word svh) for every
    record of sat that RTKLIB keeps."""
    nav = _rtklib_nav(path)
    out = []
    for i in range(nav.n):
        eph = nav.eph[i]
        if _rtklib_sat_name(eph.sat) != sat:
            continue
        toe = eph.toe.time + eph.toe.sec - GPS_EPOCH_UNIX
        pos = []
        for dt in offsets_s:
            rs, dts, var = pyrtklib.Arr1Ddouble(6), pyrtklib.Arr1Ddouble(2), pyrtklib.Arr1Ddouble(1)
            pyrtklib.eph2pos(pyrtklib.timeadd(eph.toe, float(dt)), eph, rs, dts, var)
            pos.append([rs[0], rs[1], rs[2]])
        out.append((float(toe), np.array(pos), int(eph.svh)))
    return out


def _rtklib_positions(path: Path, sat: str, offsets_s: np.ndarray):
    """(toe GPS seconds, (T, 3) ECEF positions at toe + offsets) for every record of sat."""
    return [(toe, pos) for toe, pos, _ in _rtklib_records(path, sat, offsets_s)]


_FIELDS = (  # RINEX 3.04 table A6 (GPS/Galileo) and A14 (BeiDou): broadcast orbits 1-6
    ("_iod", "Crs", "DeltaN", "M0"), ("Cuc", "Eccentricity", "Cus", "sqrtA"),
    ("Toe", "Cic", "Omega0", "Cis"), ("Io", "Crc", "omega", "OmegaDot"),
    ("IDOT", "_s1", "_week", "_s2"), ("_acc", "health", "tgd", "_s3"),
)


def _nav_from_rinex3_records(path: Path, sat: str) -> NavData:
    """The records of one satellite read by this test, independently of ``read_nav`` (so the
    orbit code is checked apart from the parser): 19-character fields."""
    lines = path.read_text().splitlines()
    start = next(i for i, ln in enumerate(lines) if "END OF HEADER" in ln) + 1
    recs = []
    for i in range(start, len(lines)):
        if not lines[i].startswith(sat + " "):
            continue
        ln = lines[i]
        y, mo, d, h, mi, s = (int(v) for v in ln[4:23].split())
        val = [float(ln[23 + 19 * k: 42 + 19 * k].replace("D", "E")) for k in range(3)]
        rec = dict(zip(("SVclockBias", "SVclockDrift", "SVclockDriftRate"), val))
        for j, names in enumerate(_FIELDS):
            body = lines[i + 1 + j]
            for k, name in enumerate(names):
                field = body[4 + 19 * k: 23 + 19 * k].strip()
                rec[name] = float(field.replace("D", "E")) if field else 0.0
        epoch = np.datetime64(f"{y:04d}-{mo:02d}-{d:02d}T{h:02d}:{mi:02d}:{s:02d}")
        toc = (epoch - np.datetime64("1980-01-06T00:00:00")) / np.timedelta64(1, "s")
        shift = 14.0 if sat[0] == "C" else 0.0  # BDT = GPST - 14 s; GST = GPST
        toc += shift
        dtoe = (rec["Toe"] + shift) - np.mod(toc, 604800.0)
        dtoe -= 604800.0 * np.round(dtoe / 604800.0)
        recs.append((toc, toc + dtoe, rec))
    keys = [k for k in recs[0][2] if not k.startswith("_")]
    return NavData(
        np.array([sat] * len(recs)), np.array([r[0] for r in recs]),
        np.array([r[1] for r in recs]),
        {k: np.array([r[2][k] for r in recs]) for k in keys}, None, None, [str(path)],
    )


def _offsets(sat: str) -> np.ndarray:
    """Times around toe compared: the records' validity (toe +- 1 h for BeiDou, +- 10 min
    shown for Galileo's 10-min updates)."""
    return np.arange(-3600.0, 3601.0, 600.0) if sat[0] == "C" else np.arange(-600, 601, 300.0)


def _assert_equals_rtklib(nav: NavData, path: Path, sat: str) -> None:
    """Every record RTKLIB reads for sat has a record of ``nav`` with the same toe whose
    positions agree to 1 mm (module docstring) and one with RTKLIB's health word."""
    offsets = _offsets(sat)
    ref = _rtklib_records(path, sat, offsets)
    assert ref, f"RTKLIB read no {sat} record from {path.name}"
    names = nav.sat.astype(str)
    n_checked = 0
    for toe, pos_ref, svh in ref:
        recs = np.flatnonzero((names == sat) & (np.abs(nav.toe_gps_s - toe) < 1e-3))
        assert recs.size >= 1, f"robustloc has no {sat} record with toe {toe}"
        t = toe + offsets
        # RTKLIB keeps one record per (sat, toe) source; compare with the closest of ours
        errs = [np.abs(broadcast_state(nav, np.full(t.size, r), t).pos_m - pos_ref).max()
                for r in recs]
        assert min(errs) < 1e-3, (sat, toe, errs)
        assert svh in nav.params["health"][recs], (sat, toe, svh, nav.params["health"][recs])
        n_checked += 1
    assert n_checked == len(ref) >= 2  # every record RTKLIB read was compared


@pytest.mark.parametrize(
    ("path", "sat"),
    [(BRDM, "C01"), (BRDM, "C02"), (BRDC, "C05"), (BRDC, "C06"), (BRDC, "E01"), (BRDC, "E02")],
)
def test_broadcast_orbit_equals_rtklib(path: Path, sat: str) -> None:
    """BeiDou GEO (C01, C02, C05), IGSO (C06) and Galileo against RTKLIB's eph2pos, on the
    records as this test reads them (checks the orbit code independently of read_nav)."""
    _assert_equals_rtklib(_nav_from_rinex3_records(path, sat), path, sat)


@pytest.mark.parametrize(
    ("path", "sat"),
    [(BRDM, "E01"), (BRDM, "E02"), (BRDC, "C05"), (BRDC, "C06"), (BRDC, "E01"), (BRDC, "E02"),
     (BRDM, "C01")],
)
def test_read_nav_orbits_equal_rtklib(path: Path, sat: str) -> None:
    """The same through read_nav, on the records georinex 1.16 used to drop (BRDM Galileo,
    BRDC BeiDou: blank spare fields) or file under a ghost satellite (BRDC E01_1, E02_1:
    a second record, I/NAV or F/NAV, of the same epoch).  RTKLIB's health word checks the
    BeiDou SatH1 mapping: C05's records carry SatH1 = 1 (unhealthy)."""
    _assert_equals_rtklib(read_nav(path), path, sat)


def test_geo_branch_is_exercised() -> None:
    """The GEO records really take the GEO branch: evaluated as MEO/IGSO they land
    kilometres away from RTKLIB's position (so the test above can fail)."""
    nav = read_nav(BRDM)
    names = nav.sat.astype(str)
    r = int(np.flatnonzero(names == "C01")[0])
    toe = float(nav.toe_gps_s[r])
    (toe_ref, pos_ref), = [x for x in _rtklib_positions(BRDM, "C01", np.array([1800.0]))
                           if abs(x[0] - toe) < 1e-3]
    fake = NavData(np.array(["C06"]), nav.toc_gps_s[[r]], nav.toe_gps_s[[r]],
                   {k: v[[r]] for k, v in nav.params.items()}, None, None, [])
    as_meo = broadcast_state(fake, np.array([0]), np.array([toe + 1800.0])).pos_m[0]
    assert np.linalg.norm(as_meo - pos_ref[0]) > 1e3


@pytest.mark.parametrize("sat", ["E01", "E02", "G01", "G02"])
def test_broadcast_orbit_within_published_accuracy_of_sp3(sat: str) -> None:
    sp3 = read_sp3(SP3)
    nav = read_nav(BRDC)
    t = sp3.t_gps_s
    rec = select_ephemeris(nav, [sat], t)[:, 0]
    assert np.all(rec >= 0)
    brd = broadcast_state(nav, rec, t).pos_m
    prec = PreciseProducts(sp3).state([sat], t[:, None]).pos_m[:, 0]
    diff = brd - prec
    # 2.0 m: published broadcast-orbit accuracy + APC-CoM offset (module docstring)
    assert np.all(np.linalg.norm(diff, axis=1) < 2.0), np.linalg.norm(diff, axis=1)
    # the offset is the antenna's: radial and towards the Earth (z axis points at the geocentre)
    radial = np.sum(diff * prec / np.linalg.norm(prec, axis=1, keepdims=True), axis=1)
    assert np.all((radial < 0.0) & (radial > -1.6)), radial


def test_rinex2_clock_file_of_code_is_read() -> None:
    """RINEX clock 2.00 writes the type as 'CLOCK DATA' from column 21 (CODE's rapid
    clocks); the reader used to reject it as 'not a RINEX clock file'."""
    clk = read_clk(CLK)
    assert "E01" in clk.sats and "G01" in clk.sats
    j = clk.sats.index("G01")
    # the excerpt's G01 AS record at 00:00:00 (file line 'AS G01  2023 03 14 00 00  0.000000')
    assert np.isfinite(clk.clock_s[j]).any()
    assert abs(np.nanmax(np.abs(clk.clock_s[j]))) < 1e-3  # a satellite clock offset, < 1 ms


def _record_headers(path: Path) -> list[tuple[str, np.datetime64]]:
    """(satellite, epoch) of every GPS, Galileo and BeiDou record header line, by regex."""
    import re

    text = path.read_text()
    body = text[text.index("END OF HEADER"):]
    pat = re.compile(r"^([GEC]\d\d) (\d{4}) (\d\d) (\d\d) (\d\d) (\d\d) (\d\d)", re.M)
    return [(m[1], np.datetime64(f"{m[2]}-{m[3]}-{m[4]}T{m[5]}:{m[6]}:{m[7]}"))
            for m in pat.finditer(body)]


@pytest.mark.parametrize(("path", "sats"), [(BRDM, {"E01", "E02"}), (BRDC, {"C05", "C06"})])
def test_read_nav_keeps_every_galileo_and_beidou_record(path: Path, sats: set) -> None:
    assert sats <= set(read_nav(path).sat.astype(str))


@pytest.mark.parametrize("path", [BRDM, BRDC])
def test_read_nav_has_one_row_per_record_header_line(path: Path) -> None:
    """As many rows per satellite as the file has record header lines (BRDC: 20 E01, 18
    E02 records, several pairs at the same epoch), in file order, with the header's epoch
    (BeiDou BDT + 14 s, Galileo GST = GPST)."""
    heads = _record_headers(path)
    nav = read_nav(path)
    assert nav.n_records == len(heads) > 0
    assert nav.sat.astype(str).tolist() == [s for s, _ in heads]
    toc = np.array([(t - np.datetime64("1980-01-06T00:00:00")) / np.timedelta64(1, "s")
                    + (14.0 if s[0] == "C" else 0.0) for s, t in heads])
    np.testing.assert_array_equal(nav.toc_gps_s, toc)


@pytest.mark.parametrize(
    ("path", "sat"),
    [(BRDM, "C01"), (BRDM, "E01"), (BRDM, "G01"), (BRDC, "C05"), (BRDC, "C06"), (BRDC, "E01")],
)
def test_read_nav_agrees_with_this_tests_record_reader(path: Path, sat: str) -> None:
    """read_nav reads every record as the test's reader does (field by field)."""
    nav = read_nav(path)
    mine = _nav_from_rinex3_records(path, sat)
    sel = nav.sat.astype(str) == sat
    np.testing.assert_array_equal(nav.toc_gps_s[sel], mine.toc_gps_s)
    np.testing.assert_allclose(nav.toe_gps_s[sel], mine.toe_gps_s)
    for k in ("SVclockBias", "SVclockDrift", "sqrtA", "M0", "Omega0", "OmegaDot", "Io",
              "omega", "Eccentricity", "DeltaN", "Cuc", "Cus", "Crc", "Crs", "Cic", "Cis",
              "IDOT", "Toe", "health", "tgd"):
        np.testing.assert_allclose(nav.params[k][sel], mine.params[k], rtol=1e-15, err_msg=k)
