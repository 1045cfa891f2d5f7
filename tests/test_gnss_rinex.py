"""RINEX / SP3 / CLK readers: agreement with georinex, clear errors on bad files."""

from __future__ import annotations

import json
import subprocess
import sys
import warnings
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from robustloc.cli import main
from robustloc.errors import InputError
from robustloc.gnss.rinex import datetime64_to_gps_s, read_nav, read_obs
from robustloc.gnss.sp3 import read_clk, read_sp3
from robustloc.paths import PACKAGE_DATA

GEONET = PACKAGE_DATA / "gnss-geonet"
SLAC = PACKAGE_DATA / "gnss-slac"
OBS = GEONET / "07590920.05o"
NAV = GEONET / "07590920_0000-0400.05n"
SLAC_OBS = SLAC / "slac1180_1930-1940.21o"


def _georinex(path: Path):  # noqa: ANN202
    gr = pytest.importorskip("georinex")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return gr.load(path)


def _assert_matches_georinex(path: Path) -> None:
    """Our reader and georinex agree on ``path``: epochs, satellites, every value."""
    ours = read_obs(path)
    ref = _georinex(path)
    assert ours.n_epochs == ref.sizes["time"]
    np.testing.assert_allclose(ours.t_gps_s, datetime64_to_gps_s(ref.time.values), atol=1e-6)
    sv = [str(s) for s in ref.sv.values]
    assert sorted(ours.sats) == sorted(sv)
    cols = [sv.index(s) for s in ours.sats]
    n_compared = 0
    for name, arr in ours.obs.items():
        theirs = np.asarray(ref[name].values)[:, cols]
        theirs = np.where(theirs == 0.0, np.nan, theirs)  # we map 0.000 ("absent") to NaN
        np.testing.assert_array_equal(np.isnan(arr), np.isnan(theirs), err_msg=name)
        np.testing.assert_allclose(arr, theirs, rtol=0, atol=1e-9, equal_nan=True, err_msg=name)
        n_compared += int(np.isfinite(arr).sum())
    assert n_compared > 1000


@pytest.mark.parametrize("path", [OBS, SLAC_OBS])
def test_obs_reader_matches_georinex(path: Path) -> None:
    _assert_matches_georinex(path)


def test_obs_header_and_epochs() -> None:
    o = read_obs(OBS)
    np.testing.assert_allclose(o.approx_xyz_m, [-3976219.5082, 3382372.5671, 3652512.9849])
    assert o.n_epochs == 120
    np.testing.assert_allclose(np.diff(o.t_gps_s), 30.0, atol=2e-3)  # 1-ms clock steps
    # 2005-04-02 00:00:00 GPST = week 1316, day 6 (Saturday) 00:00
    assert o.t_gps_s[0] == 1316 * 604800 + 6 * 86400
    # first record of the file: G03 C1 = 24767686.375 (line 19)
    assert o.obs["C1"][0, o.sats.index("G03")] == pytest.approx(24767686.375)


def test_nav_reader_matches_georinex() -> None:
    nav = read_nav(NAV)
    ref = _georinex(NAV)
    assert nav.n_records == int(np.isfinite(ref["sqrtA"].values).sum())
    for k in range(nav.n_records):
        toc = np.datetime64("1980-01-06", "ns") + np.int64(round(nav.toc_gps_s[k] * 1e9))
        rec = ref.sel(sv=nav.sat[k], time=toc)
        for name in ("sqrtA", "M0", "Toe", "SVclockBias", "Eccentricity", "Omega0", "Crs"):
            assert nav.params[name][k] == float(rec[name])
        assert nav.params["tgd"][k] == float(rec["TGD"])
    np.testing.assert_allclose(nav.ion_alpha, [1.118e-08, 1.49e-08, -5.96e-08, -5.96e-08])
    np.testing.assert_allclose(nav.ion_beta, [8.806e04, 1.638e04, -1.966e05, -1.311e05])


def test_sp3_and_clk_values() -> None:
    sp3 = read_sp3(SLAC / "COD0MGXFIN_20211181905_60M_05M_ORB.SP3")
    clk = read_clk(SLAC / "COD0MGXFIN_20211181930_12M_30S_CLK.CLK")
    assert sp3.t_gps_s.size == 13 and np.all(np.diff(sp3.t_gps_s) == 300.0)
    assert {"G02", "R09", "E13"} <= set(sp3.sats)
    assert clk.t_gps_s.size == 23 and np.all(np.diff(clk.t_gps_s) == 30.0)
    # AS G02 2021 04 28 19 30 0.0: -0.599721550314E-03 s
    t = datetime64_to_gps_s(np.array([np.datetime64("2021-04-28T19:30:00")]))[0]
    j = list(clk.t_gps_s).index(t)
    assert clk.clock_s[clk.sats.index("G02"), j] == pytest.approx(-0.599721550314e-03, rel=1e-12)


def _write(tmp_path: Path, name: str, text: str) -> Path:
    p = tmp_path / name
    p.write_text(text)
    return p


def test_truncated_obs_names_file_and_line(tmp_path: Path) -> None:
    lines = OBS.read_text().splitlines()
    bad = _write(tmp_path, "cut.05o", "\n".join(lines[:-3]) + "\n")
    with pytest.raises(InputError) as e:
        read_obs(bad)
    assert e.value.path == str(bad)
    last_epoch = max(i for i, ln in enumerate(lines) if ln.startswith(" 05  4  2"))
    assert e.value.line == last_epoch + 1  # header line of the cut epoch
    assert "ends inside" in str(e.value)


def test_malformed_obs_number(tmp_path: Path) -> None:
    lines = OBS.read_text().splitlines()
    lines[18] = lines[18][:20] + "xx" + lines[18][22:]
    bad = _write(tmp_path, "bad.05o", "\n".join(lines) + "\n")
    with pytest.raises(InputError) as e:
        read_obs(bad)
    assert e.value.line == 19 and "C1" in str(e.value)


def test_malformed_epoch_header(tmp_path: Path) -> None:
    lines = OBS.read_text().splitlines()
    lines[17] = " 05  4  2  0  0  0.0000000  0 XG 3G 7G 8G11G19G20G24G28"
    bad = _write(tmp_path, "bad.05o", "\n".join(lines) + "\n")
    with pytest.raises(InputError) as e:
        read_obs(bad)
    assert e.value.line == 18


@pytest.mark.parametrize("version", ["1.00", "9.99", "0.50", "5.00"])
def test_unsupported_rinex_version_is_refused_on_line_1(tmp_path: Path, version: str) -> None:
    # the GNSS review (2026-12-04): 1.00 was read as RINEX 2 without a word, 9.99 as 3
    for path in (OBS, NAV):
        lines = path.read_text().splitlines()
        lines[0] = f"{version:>9}" + lines[0][9:]
        bad = _write(tmp_path, "v" + path.name, "\n".join(lines) + "\n")
        with pytest.raises(InputError) as e:
            (read_obs if path == OBS else read_nav)(bad)
        assert e.value.line == 1
        assert f"RINEX version {version} is not supported" in str(e.value)


def test_rinex2_content_under_a_version_4_line_names_the_header_end(tmp_path: Path) -> None:
    # the review: "missing 'SYS / # / OBS TYPES' header record" without a line
    lines = OBS.read_text().splitlines()
    lines[0] = "     4.01" + lines[0][9:]
    end = next(i for i, ln in enumerate(lines) if "END OF HEADER" in ln) + 1
    with pytest.raises(InputError) as e:
        read_obs(_write(tmp_path, "v4.05o", "\n".join(lines) + "\n"))
    assert e.value.line == end and "is the version on line 1 right?" in str(e.value)


def test_not_rinex_and_missing_header(tmp_path: Path) -> None:
    with pytest.raises(InputError, match="RINEX VERSION"):
        read_obs(_write(tmp_path, "x.05o", "hello\n"))
    head = OBS.read_text().splitlines()[:5]
    with pytest.raises(InputError, match="END OF HEADER"):
        read_obs(_write(tmp_path, "y.05o", "\n".join(head) + "\n"))
    with pytest.raises(InputError, match="not an observation file"):
        read_obs(NAV)


def test_truncated_and_malformed_nav(tmp_path: Path) -> None:
    lines = NAV.read_text().splitlines()
    with pytest.raises(InputError, match="truncated") as e:
        read_nav(_write(tmp_path, "cut.05n", "\n".join(lines[:-2]) + "\n"))
    assert e.value.path is not None
    bad = list(lines)
    k = next(i for i, ln in enumerate(lines) if "END OF HEADER" in ln) + 3
    bad[k] = bad[k][:5] + "1.2345X-08" + bad[k][15:]
    with pytest.raises(InputError) as e:
        read_nav(_write(tmp_path, "bad.05n", "\n".join(bad) + "\n"))
    assert e.value.line == k + 1


def test_bad_sp3_and_clk(tmp_path: Path) -> None:
    with pytest.raises(InputError, match="SP3"):
        read_sp3(_write(tmp_path, "a.sp3", "garbage\n"))
    lines = (SLAC / "COD0MGXFIN_20211181905_60M_05M_ORB.SP3").read_text().splitlines()
    k = next(i for i, ln in enumerate(lines) if ln.startswith("PG"))
    lines[k] = lines[k][:10] + "abc" + lines[k][13:]
    with pytest.raises(InputError) as e:
        read_sp3(_write(tmp_path, "b.sp3", "\n".join(lines) + "\n"))
    assert e.value.line == k + 1
    with pytest.raises(InputError, match="clock"):
        read_clk(OBS)


RINEX3_OBS = """\
     3.03           OBSERVATION DATA    M                   RINEX VERSION / TYPE
  -3976219.5082  3382372.5671  3652512.9849                  APPROX POSITION XYZ
G    3 C1C L1C C2W                                          SYS / # / OBS TYPES
E    2 C1C C5Q                                              SYS / # / OBS TYPES
  2021     4    28    19    30    0.0000000     GPS         TIME OF FIRST OBS
                                                            END OF HEADER
> 2021 04 28 19 30  0.0000000  0  3
G05  20311445.258   106734567.123 8  20311449.125
E11  23000001.500    23000004.750
G19  21565852.190
> 2021 04 28 19 30 30.0000000  0  2
G05  20311545.258   106735567.123 8  20311549.125
E11  23000101.500    23000104.750
"""


def test_rinex3_obs_through_georinex(tmp_path: Path) -> None:
    o = read_obs(_write(tmp_path, "x.rnx", RINEX3_OBS))
    assert o.version == 3.03 and o.n_epochs == 2
    assert o.sats == ["G05", "G19", "E11"]
    assert o.obs["C1C"][0].tolist() == [20311445.258, 21565852.190, 23000001.5]
    assert o.obs["C1C"][1, 0] == 20311545.258 and np.isnan(o.obs["C1C"][1, 1])
    assert o.obs["C5Q"][0, 2] == 23000004.75
    assert o.t_gps_s[1] - o.t_gps_s[0] == 30.0
    assert o.line.tolist() == [7, 11]


def _nav3_from_nav2(records: list[list[str]], sys_letter: str) -> list[str]:
    """Re-write RINEX 2 GPS records as RINEX 3 records of another constellation."""
    out = []
    for rec in records:
        prn = int(rec[0][:2])
        yy, mo, dd, hh, mi = (int(rec[0][c : c + 3]) for c in (2, 5, 8, 11, 14))
        ss = int(float(rec[0][17:22]))
        out.append(f"{sys_letter}{prn:02d} {2000 + yy:04d} {mo:02d} {dd:02d} {hh:02d} {mi:02d} "
                   f"{ss:02d}" + rec[0][22:79])
        orbit = ["    " + ln[3:79] for ln in rec[1:]]
        if sys_letter == "C":
            # the 7th line's fourth field is BeiDou's TGD2 (GPS: IODC, a count, not a delay)
            orbit[5] = orbit[5][:61].ljust(61) + f"{-2.9e-9:19.12E}"
        out += orbit
    return out


def test_rinex3_nav_gps_galileo_beidou(tmp_path: Path) -> None:
    nav2 = read_nav(NAV)
    lines = NAV.read_text().splitlines()
    i0 = next(i for i, ln in enumerate(lines) if "END OF HEADER" in ln) + 1
    recs = [lines[i : i + 8] for i in range(i0, i0 + 8 * 3, 8)]
    head = [
        "     3.03           N: GNSS NAV DATA    M: Mixed            RINEX VERSION / TYPE",
        "GPSA   1.1180E-08  1.4900E-08 -5.9600E-08 -5.9600E-08       IONOSPHERIC CORR",
        "GPSB   8.8060E+04  1.6380E+04 -1.9660E+05 -1.3110E+05       IONOSPHERIC CORR",
        "                                                            END OF HEADER",
    ]
    body = _nav3_from_nav2(recs, "G") + _nav3_from_nav2(recs, "E") + _nav3_from_nav2(recs, "C")
    path = _write(tmp_path, "mixed.rnx", "\n".join(head + body) + "\n")
    nav3 = read_nav(path)
    np.testing.assert_allclose(nav3.ion_alpha, nav2.ion_alpha)
    g3 = np.char.startswith(nav3.sat.astype(str), "G")
    e3 = np.char.startswith(nav3.sat.astype(str), "E")
    assert g3.sum() == 3 and e3.sum() == 3
    for k in range(3):
        j = int(np.flatnonzero((nav2.sat == nav3.sat[g3][k]) &
                               (nav2.toc_gps_s == nav3.toc_gps_s[g3][k]))[0])
        for name in ("sqrtA", "M0", "Omega0", "Crs", "SVclockBias", "tgd"):
            assert nav3.params[name][g3][k] == nav2.params[name][j]
        assert nav3.toe_gps_s[g3][k] == nav2.toe_gps_s[j]
    # Galileo: the 7th line's third field is BGD(E1,E5a), used as the group delay
    np.testing.assert_allclose(nav3.params["tgd"][e3], nav3.params["tgd"][g3])
    # BeiDou: epochs in BDT = GPST - 14 s; TGD1 in the third field of the 7th line, TGD2
    # in the fourth (the other systems have no second group delay: 0)
    c3 = np.char.startswith(nav3.sat.astype(str), "C")
    assert c3.sum() == 3
    np.testing.assert_allclose(nav3.params["tgd"][c3], nav3.params["tgd"][g3])
    assert np.all(nav3.params["tgd2"][c3] == -2.9e-9)
    assert np.all(nav3.params["tgd2"][~c3] == 0.0) and np.all(nav2.params["tgd2"] == 0.0)
    np.testing.assert_allclose(nav3.toc_gps_s[c3], nav3.toc_gps_s[g3] + 14.0)
    np.testing.assert_allclose(nav3.toe_gps_s[c3], nav3.toe_gps_s[g3] + 14.0)


_NAV3_HEAD = [
    "     3.04           N: GNSS NAV DATA    M: Mixed            RINEX VERSION / TYPE",
    "                                                            END OF HEADER",
]


def _nav3_body() -> list[str]:
    """Three Galileo and three BeiDou records (the GEONET GPS records rewritten), 8 lines
    each, every line padded to 80 columns."""
    lines = NAV.read_text().splitlines()
    i0 = next(i for i, ln in enumerate(lines) if "END OF HEADER" in ln) + 1
    recs = [lines[i : i + 8] for i in range(i0, i0 + 8 * 3, 8)]
    return [ln.ljust(80) for ln in _nav3_from_nav2(recs, "E") + _nav3_from_nav2(recs, "C")]


def _blank(line: str, field: int) -> str:
    """The line with its orbit field ``field`` (1-4, RINEX 3 columns 4 + 19 (field - 1))
    replaced by blanks."""
    c = 4 + 19 * (field - 1)
    return line[:c] + " " * 19 + line[c + 19 :]


def test_rinex3_nav_blank_spares_trimmed_lines_and_other_systems(tmp_path: Path) -> None:
    """Blank spare fields, right-trimmed lines and GLONASS (3 or, RINEX 3.05, 4 orbit lines)
    and SBAS records in between read as the padded, zero-filled file (georinex 1.16 turned
    a record with a blank field into NaN, and read_nav dropped it)."""
    body = _nav3_body()
    ref = read_nav(_write(tmp_path, "padded.rnx", "\n".join(_NAV3_HEAD + body) + "\n"))
    assert ref.sat.tolist() == ["E01", "E03", "E03", "C01", "C03", "C03"]
    mod = list(body)
    for r in range(6):
        bo5 = 8 * r + 5  # BROADCAST ORBIT 5: Galileo spare = field 4, BeiDou fields 2 and 4
        mod[bo5] = _blank(mod[bo5], 4) if r < 3 else _blank(_blank(mod[bo5], 2), 4)
    mod = [ln.rstrip() for ln in mod]
    glo = ["R01 2005 04 02 00 15 00 1.0E-04 0.0E+00 0.0E+00"] + ["     1.0E+00"] * 3
    glo305 = ["R02 2005 04 02 00 15 00 1.0E-04 0.0E+00 0.0E+00"] + ["     1.0E+00"] * 4
    sbas = ["S22 2005 04 02 00 15 00 1.0E-04 0.0E+00 0.0E+00"] + ["     1.0E+00"] * 3
    mod = glo + mod[:8] + glo305 + mod[8:24] + [""] + sbas + mod[24:]
    nav = read_nav(_write(tmp_path, "trimmed.rnx", "\n".join(_NAV3_HEAD + mod) + "\n"))
    assert nav.sat.tolist() == ref.sat.tolist() and nav.n_records == 6
    np.testing.assert_array_equal(nav.toc_gps_s, ref.toc_gps_s)
    np.testing.assert_array_equal(nav.toe_gps_s, ref.toe_gps_s)
    for k, v in ref.params.items():
        np.testing.assert_array_equal(nav.params[k], v, err_msg=k)


def _nav3_error(tmp_path: Path, body: list[str]) -> InputError:
    with pytest.raises(InputError) as e:
        read_nav(_write(tmp_path, "bad.rnx", "\n".join(_NAV3_HEAD + body) + "\n"))
    return e.value


def test_rinex3_nav_problems_name_the_line(tmp_path: Path) -> None:
    """A record is never dropped: its problem is reported with the file line (1-based;
    the header is 2 lines, so body line i is file line i + 3)."""
    body = _nav3_body()
    cut = body[:9] + body[10:]  # second Galileo record (lines 8-15) loses an orbit line
    e = _nav3_error(tmp_path, cut)
    assert "6 orbit lines, expected 7" in str(e) and e.line == 8 + 3
    assert e.path is not None and e.path.endswith("bad.rnx")
    e = _nav3_error(tmp_path, body[:-1])  # the file ends inside the last record
    assert "orbit lines" in str(e) and e.line == 40 + 3
    blank = list(body)
    blank[26] = _blank(blank[26], 4)  # BeiDou record 1, BROADCAST ORBIT 2: sqrtA
    e = _nav3_error(tmp_path, blank)
    assert "without sqrtA" in str(e) and e.line == 26 + 3
    bad = list(body)
    bad[19] = bad[19][:6] + "1.2345X-08" + bad[19][16:]
    e = _nav3_error(tmp_path, bad)
    assert "malformed number" in str(e) and e.line == 19 + 3
    unknown = list(body)
    unknown[16] = "X" + unknown[16][1:]
    e = _nav3_error(tmp_path, unknown)
    assert "unknown satellite system 'X'" in str(e) and e.line == 16 + 3
    month = list(body)
    month[32] = month[32][:9] + "13" + month[32][11:]
    e = _nav3_error(tmp_path, month)
    assert "impossible clock epoch" in str(e) and e.line == 32 + 3
    e = _nav3_error(tmp_path, body[1:])
    assert "orbit line without a record header" in str(e) and e.line == 0 + 3


def test_rinex2_nav_blank_orbit_parameter_is_an_error(tmp_path: Path) -> None:
    """A blank sqrtA used to make read_nav drop the record silently."""
    lines = NAV.read_text().splitlines()
    k = next(i for i, ln in enumerate(lines) if "END OF HEADER" in ln) + 1 + 8 + 2
    lines[k] = lines[k][:60] + " " * 19  # second record, BROADCAST ORBIT 2, field 4
    with pytest.raises(InputError, match="without sqrtA") as e:
        read_nav(_write(tmp_path, "blank.05n", "\n".join(lines) + "\n"))
    assert e.value.line == k + 1


#: Values no satellite can have: (orbit line of the record, field 0-3, text, message).
IMPOSSIBLE_NAV = [
    (2, 1, "1.5", "Eccentricity = 1.5 must lie in [0, 1)"),
    (2, 1, "-0.5", "Eccentricity = -0.5 must lie in [0, 1)"),
    (2, 1, "0.9", "perigee sqrtA^2 (1 - Eccentricity) below the Earth's surface"),
    (2, 3, "0.0", "sqrtA = 0 must lie in [1000, 100000]"),
    (2, 3, "1.0D+30", "sqrtA = 1e+30 must lie in [1000, 100000]"),
    (2, 3, "NaN", "sqrtA = nan must be a finite number"),
    (1, 2, "1.0D+300", "DeltaN = 1e+300 must lie within +-1e-05"),
    (3, 0, "1.0D+999", "Toe = inf must be a finite number"),
    (6, 2, "-1.0D+999", "tgd = -inf must be a finite number"),
]


def impossible_nav(tmp_path: Path, orbit_line: int, field: int, text: str,
                   record: int = 8) -> tuple[Path, Path, int]:
    """The GEONET navigation excerpt with one value of a record replaced by ``text``
    (record 8: G11 at 00:00, used by the observation excerpt's epochs), the same file
    without that record, and the 1-based file line of the value."""
    lines = NAV.read_text().splitlines()
    first = next(i for i, ln in enumerate(lines) if "END OF HEADER" in ln) + 1 + 8 * record
    k = first + orbit_line
    c = 3 + 19 * field  # RINEX 2.11 table A4: 3X,4D19.12
    lines[k] = lines[k].ljust(79)[:c] + text.rjust(19) + lines[k].ljust(79)[c + 19 :]
    bad = _write(tmp_path, "bad.05n", "\n".join(lines) + "\n")
    gone = _write(tmp_path, "gone.05n", "\n".join(lines[:first] + lines[first + 8 :]) + "\n")
    return bad, gone, k + 1


@pytest.mark.parametrize(("orbit_line", "field", "text", "what"), IMPOSSIBLE_NAV)
def test_rinex2_nav_impossible_record_is_set_aside_naming_file_and_line(
        tmp_path: Path, orbit_line: int, field: int, text: str, what: str) -> None:
    """A record no satellite can fly (its orbit or clock values) was read as it was and made
    numpy warn (overflow, invalid value) in the orbit arithmetic: it is set aside with a
    warning naming the file and line, and the file reads as if it were not there."""
    from robustloc.gnss.rinex import NavRecordWarning

    bad, gone, line = impossible_nav(tmp_path, orbit_line, field, text)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        nav = read_nav(bad)
    assert [w.category for w in caught] == [NavRecordWarning]
    message = str(caught[0].message)
    assert message.startswith(f"{bad}:{line}: G11 record set aside: "), message
    assert what in message and message.endswith("it is not used"), message
    assert nav.rejected == (message,)
    ref = read_nav(gone)
    assert ref.rejected == () and nav.n_records == ref.n_records
    np.testing.assert_array_equal(nav.sat, ref.sat)
    np.testing.assert_array_equal(nav.toe_gps_s, ref.toe_gps_s)
    np.testing.assert_array_equal(nav.toc_gps_s, ref.toc_gps_s)
    for k, v in ref.params.items():
        np.testing.assert_array_equal(nav.params[k], v, err_msg=k)


@pytest.mark.parametrize(("orbit_line", "field", "text", "what"), IMPOSSIBLE_NAV)
def test_spp_on_impossible_ephemeris_no_runtime_warning_same_solution_without_it(
        tmp_path: Path, capsys: pytest.CaptureFixture[str], orbit_line: int, field: int,
        text: str, what: str) -> None:
    """``spp`` with the impossible G11 record: no numpy RuntimeWarning (overflow, invalid
    value) reaches the user, ``warning: FILE:LINE: ...`` on stderr, every epoch has its
    row, and the solution is the one of the file without the record (the other
    satellites, and G11's next record, untouched)."""
    from robustloc import status as st

    bad, gone, line = impossible_nav(tmp_path, orbit_line, field, text)
    sols = []
    for nav in (bad, gone):
        out = tmp_path / f"{nav.stem}.csv"
        with warnings.catch_warnings():
            warnings.simplefilter("error", RuntimeWarning)
            rc = main(["spp", str(OBS), str(nav), "-o", str(out)])
        err = capsys.readouterr().err
        assert rc == 0, err
        sols.append(pd.read_csv(out))
        if nav == bad:
            assert err.startswith(f"warning: {bad}:{line}: G11 record set aside: "), err
            assert what in err and "Traceback" not in err
        else:
            assert "warning" not in err, err
    assert len(sols[0]) == read_obs(OBS).n_epochs  # every epoch a row
    assert set(sols[0]["status"]) <= set(st.ALL)
    pd.testing.assert_frame_equal(sols[0], sols[1])


def test_nav_every_record_impossible_is_an_error(tmp_path: Path) -> None:
    lines = NAV.read_text().splitlines()
    i0 = next(i for i, ln in enumerate(lines) if "END OF HEADER" in ln) + 1
    for k in range(i0 + 2, len(lines), 8):  # BROADCAST ORBIT 2 of every record: e = 2
        lines[k] = lines[k][:22] + "2.0".rjust(19) + lines[k][41:]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        with pytest.raises(InputError, match="all 26 records set aside"):
            read_nav(_write(tmp_path, "all.05n", "\n".join(lines) + "\n"))


# ------------------------------------------------ epochs without satellites, RINEX 3 reader


def _first_epoch(lines: list[str]) -> int:
    return next(k for k, ln in enumerate(lines) if "END OF HEADER" in ln) + 1


def _v2_epochs(lines: list[str], ntypes: int) -> list[tuple[str, list[str], list[str]]]:
    """Epochs of a RINEX 2 file: ``(epoch line, satellite ids, records)``; the records of an
    event (flags 2-5) are its special records."""
    nl = (ntypes + 4) // 5
    out = []
    i = _first_epoch(lines)
    while i < len(lines):
        e = lines[i]
        ns = int(e[29:32])
        if 2 <= int(e[26:29]) <= 5:  # event: ns special records
            out.append((e, [], lines[i + 1 : i + 1 + ns]))
            i += 1 + ns
            continue
        nh = (ns + 11) // 12
        svtxt = "".join(lines[i + k][32:68] for k in range(nh))
        sats = [svtxt[3 * k : 3 * k + 3].replace(" ", "0") for k in range(ns)]
        i += nh
        recs = []
        for _ in sats:
            recs.append("".join(lines[i + m][:80].ljust(80) for m in range(nl))[: 16 * ntypes])
            i += nl
        out.append((e, sats, recs))
    return out


def _rinex3_from_rinex2(src: Path, n_epochs: int | None = None,
                        rename: dict[str, str] | None = None) -> tuple[list[str], list[str]]:
    """The RINEX 2 file ``src`` rewritten as RINEX 3.03 (same values, every system with the
    same observation types, renamed by ``rename`` or else ``type + "X"``); returns the lines
    and the RINEX 3 types."""
    lines = src.read_text().splitlines()
    hdr = lines[: _first_epoch(lines)]
    types: list[str] = []
    for ln in hdr:
        if ln[60:].strip() == "# / TYPES OF OBSERV":
            types += ln[6:60].split()
    names = [(rename or {}).get(t, t + "X") for t in types]
    epochs = _v2_epochs(lines, len(types))[:n_epochs]
    systems = sorted({s[0] for _, sats, _ in epochs for s in sats})
    out = ["     3.03           OBSERVATION DATA    M".ljust(60) + "RINEX VERSION / TYPE",
           " -3976219.5082  3382372.5671  3652512.9849".ljust(60) + "APPROX POSITION XYZ"]
    for sysch in systems:
        for k in range(0, len(names), 13):
            head = f"{sysch}  {len(names):3d}" if k == 0 else " " * 6
            out.append((head + "".join(f" {t:3s}" for t in names[k : k + 13])).ljust(60)
                       + "SYS / # / OBS TYPES")
    e = next(e for e, sats, _ in epochs if sats)
    yy = int(e[1:3])
    out.append(f"  {yy + (2000 if yy < 80 else 1900):04d}{int(e[4:6]):6d}{int(e[7:9]):6d}"
               f"{int(e[10:12]):6d}{int(e[13:15]):6d}{float(e[15:26]):13.7f}     GPS".ljust(60)
               + "TIME OF FIRST OBS")
    out.append(" " * 60 + "END OF HEADER")
    for e, sats, recs in epochs:
        if 2 <= int(e[26:29]) <= 5:
            out += [f">{int(e[26:29]):31d}{len(recs):3d}", *recs]
            continue
        yy = int(e[1:3])
        out.append(f"> {yy + (2000 if yy < 80 else 1900):04d} {int(e[4:6]):02d} "
                   f"{int(e[7:9]):02d} {int(e[10:12]):02d} {int(e[13:15]):02d}"
                   f"{float(e[15:26]):11.7f}  {int(e[26:29])}{len(sats):3d}")
        out += [(s + r).rstrip() for s, r in zip(sats, recs)]
    return out, names


def _write_lines(tmp_path: Path, name: str, lines: list[str]) -> Path:
    return _write(tmp_path, name, "\n".join(lines) + "\n")


_RUN_CLI = "import sys; from robustloc.cli import main; sys.exit(main(sys.argv[1:]))"
_READ = ("import sys, json, numpy as np; from robustloc.gnss.rinex import read_obs; "
         "o = read_obs(sys.argv[1]); "
         "print(json.dumps([o.n_epochs, o.line.tolist(), o.epoch_flag.tolist(), "
         "[int(np.isfinite(o.obs['C1'][k]).sum()) for k in range(o.n_epochs)]]))")


def _subprocess(args: list[str]) -> subprocess.CompletedProcess:
    """Run a Python snippet in a child process; an endless loop fails after 60 s."""
    return subprocess.run([sys.executable, "-c", *args], capture_output=True, text=True,
                          timeout=60, check=False)


@pytest.mark.parametrize("flag", [0, 1, 6])
def test_rinex2_epoch_without_satellites_alone(tmp_path: Path, flag: int) -> None:
    """An epoch listing 0 satellites used to loop forever (its header took 0 lines).
    Flag 6 (cycle-slip records, RINEX 2.11 table A2: "same format as OBSERVATIONS
    records; slip instead of observation") is no observation epoch: alone after the
    header it leaves the file without one, which the reader says, at once."""
    lines = OBS.read_text().splitlines()
    i = _first_epoch(lines)
    p = _write_lines(tmp_path, "zero.05o", [*lines[:i], f" 05  4  2  0  0  0.0000000  {flag}  0"])
    r = _subprocess([_READ, str(p)])
    if flag == 6:
        assert r.returncode == 1 and "no observation epochs after the header" in r.stderr
        return
    assert r.returncode == 0, r.stderr
    assert json.loads(r.stdout) == [1, [i + 1], [flag], [0]]


def test_rinex2_epoch_without_satellites_in_the_middle(tmp_path: Path) -> None:
    """The empty epoch is a row of its own (non-usable status in spp), the rest unchanged."""
    lines = OBS.read_text().splitlines()
    ep = [k for k, ln in enumerate(lines) if ln.startswith(" 05  4  2")]
    k = ep[9]
    ns = int(lines[k][29:32])
    p = _write_lines(tmp_path, "zmid.05o", [*lines[:k], lines[k][:29] + "  0",
                                            *lines[k + 1 + ns :]])
    r = _subprocess([_READ, str(p)])
    assert r.returncode == 0, r.stderr
    n, ep_lines, flags, n_c1 = json.loads(r.stdout)
    assert n == 120 and n_c1[9] == 0 and min(n_c1[:9] + n_c1[10:]) >= 4
    assert ep_lines[9] == k + 1 and ep_lines[10] == k + 2
    o, ref = read_obs(p), read_obs(OBS)
    keep = np.arange(120) != 9
    np.testing.assert_array_equal(o.t_gps_s, ref.t_gps_s)
    for name in ref.obs:
        a = o.obs[name][:, [o.sats.index(s) for s in ref.sats]]
        np.testing.assert_array_equal(a[keep], ref.obs[name][keep])
        assert np.isnan(o.obs[name][9]).all()
    out = tmp_path / "sol.csv"
    r = _subprocess([_RUN_CLI, "spp", str(p), str(NAV), "-o", str(out), "--quiet"])
    assert r.returncode == 0, r.stderr
    sol = pd.read_csv(out)
    assert len(sol) == 120
    assert sol["status"][9] == "insufficient_anchors" and sol["n_sats"][9] == 0
    assert (sol["status"].drop(index=9) != "insufficient_anchors").all()


@pytest.mark.parametrize("src,n_epochs", [(OBS, 20), (OBS, None), (SLAC_OBS, None)])
def test_rinex3_reader_matches_rinex2_reader(tmp_path: Path, src: Path,
                                             n_epochs: int | None) -> None:
    """The same values written as RINEX 3 read the same (GPS and mixed files)."""
    lines, names = _rinex3_from_rinex2(src, n_epochs)
    o3 = read_obs(_write_lines(tmp_path, "x.rnx", lines))
    o2 = read_obs(src).select(slice(0, n_epochs))
    assert o3.version == 3.03 and o3.n_epochs == o2.n_epochs
    cols = [o2.sats.index(s) for s in o3.sats]  # the satellites of these epochs, in order
    assert cols == sorted(cols)
    assert all(np.isnan(a[:, np.setdiff1d(np.arange(len(o2.sats)), cols)]).all()
               for a in o2.obs.values())
    np.testing.assert_array_equal(o3.t_gps_s, o2.t_gps_s)
    np.testing.assert_array_equal(o3.epoch_flag, o2.epoch_flag)
    assert [lines[k - 1][0] for k in o3.line] == [">"] * o3.n_epochs
    np.testing.assert_array_equal(o3.invalid_per_epoch, o2.invalid_per_epoch)
    assert sorted(o3.obs) == sorted(names)
    for name in o2.obs:
        np.testing.assert_array_equal(o3.obs[name + "X"], o2.obs[name][:, cols], err_msg=name)


def _rinex3_geonet(tmp_path: Path) -> tuple[list[str], Path]:
    """The first 20 epochs of the GEONET excerpt as RINEX 3 (``C1C``, ``L1C`` ...)."""
    lines, _ = _rinex3_from_rinex2(OBS, 20, {"L1": "L1C", "C1": "C1C", "L2": "L2W",
                                             "P2": "C2W"})
    return lines, _write_lines(tmp_path, "v3.05o", lines)


def _spp_rc(capsys: pytest.CaptureFixture[str], obs: Path, out: Path) -> tuple[int, str]:
    rc = main(["spp", str(obs), str(NAV), "-o", str(out), "--quiet"])
    return rc, capsys.readouterr().err


@pytest.mark.parametrize("nth", [0, 9])
def test_rinex3_impossible_epoch_time_names_file_and_line(
        tmp_path: Path, capsys: pytest.CaptureFixture[str], nth: int) -> None:
    """georinex dropped the epoch and every later one (9/9 epochs solved, exit 0)."""
    lines, good = _rinex3_geonet(tmp_path)
    rc, err = _spp_rc(capsys, good, tmp_path / "ok.csv")
    assert rc == 0 and len(pd.read_csv(tmp_path / "ok.csv")) == 20
    k = [j for j, ln in enumerate(lines) if ln.startswith(">")][nth]
    assert lines[k].startswith("> 2005 04 02")
    for a, b, value in ((7, 9, "13"), (10, 12, "31"), (13, 15, "24"), (16, 18, "60")):
        bad = list(lines)
        bad[k] = bad[k][:a] + value + bad[k][b:]
        p = _write_lines(tmp_path, "m.05o", bad)
        with pytest.raises(InputError) as e:
            read_obs(p)
        assert e.value.line == k + 1 and "impossible epoch time" in str(e.value)
        out = tmp_path / "m.csv"
        rc, err = _spp_rc(capsys, p, out)
        assert rc == 2 and err.startswith(f"error: {p}:{k + 1}: impossible epoch time")
        assert "Traceback" not in err and not out.exists()


def test_rinex3_malformed_value_names_file_and_line(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """georinex dropped the satellite of a value that is not a number, silently."""
    lines, _ = _rinex3_geonet(tmp_path)
    k = next(j for j, ln in enumerate(lines) if ln.startswith("G07"))
    assert "24361933.475" in lines[k]
    bad = list(lines)
    bad[k] = bad[k].replace("24361933.475", "2436X933.475")
    p = _write_lines(tmp_path, "bad.05o", bad)
    with pytest.raises(InputError) as e:
        read_obs(p)
    assert e.value.line == k + 1 and "malformed C1C value '  2436X933.475'" in str(e.value)
    rc, err = _spp_rc(capsys, p, tmp_path / "b.csv")
    assert rc == 2 and err.startswith(f"error: {p}:{k + 1}: malformed C1C value")


def test_rinex3_epoch_without_satellites_gets_a_row(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """georinex left out an epoch listing 0 satellites (19 rows for 20 epochs)."""
    lines, _ = _rinex3_geonet(tmp_path)
    i = _first_epoch(lines)
    assert lines[i].endswith("  0  8")
    z = [*lines[:i], lines[i][:-3] + "  0", *lines[i + 9 :]]
    p = _write_lines(tmp_path, "z.05o", z)
    o = read_obs(p)
    assert o.n_epochs == 20 and o.line[0] == i + 1 and o.line[1] == i + 2
    assert all(np.isnan(a[0]).all() for a in o.obs.values())
    assert np.isfinite(o.obs["C1C"][1:]).sum(axis=1).min() >= 4
    out = tmp_path / "z.csv"
    rc, err = _spp_rc(capsys, p, out)
    assert rc == 0, err
    sol = pd.read_csv(out)
    assert len(sol) == 20 and sol["status"][0] == "insufficient_anchors"
    assert (sol["status"][1:] == "ok").all()


def test_rinex3_events_counts_and_truncation(tmp_path: Path) -> None:
    """Event records (flags 2-5) are skipped; wrong counts and truncation name the line."""
    lines, _ = _rinex3_geonet(tmp_path)
    i = _first_epoch(lines)
    ev = [*lines[: i + 9], "> 2005 04 02 00 00 15.0000000  4  1",
          "event comment".ljust(60) + "COMMENT", *lines[i + 9 :]]
    o = read_obs(_write_lines(tmp_path, "ev.05o", ev))
    assert o.n_epochs == 20 and o.line[1] == i + 12
    assert [ev[k - 1][0] for k in o.line] == [">"] * 20
    more = list(lines)
    more[i] = more[i][:-3] + "  9"  # announces 9, lists 8 (the next line is an epoch)
    with pytest.raises(InputError, match="announces 9 satellites but lists 8") as e:
        read_obs(_write_lines(tmp_path, "n.05o", more))
    assert e.value.line == i + 1
    last = max(k for k, ln in enumerate(lines) if ln.startswith(">"))
    with pytest.raises(InputError, match="ends inside") as e:
        read_obs(_write_lines(tmp_path, "cut.05o", lines[:-2]))
    assert e.value.line == last + 1
    garbage = [*lines[: i + 9], "G99 this is not an epoch line", *lines[i + 9 :]]
    with pytest.raises(InputError, match="expected an epoch line") as e:
        read_obs(_write_lines(tmp_path, "g.05o", garbage))
    assert e.value.line == i + 10


def test_rinex3_reader_matches_georinex_on_a_valid_file(tmp_path: Path) -> None:
    """The own RINEX 3 reader against the independent reference (georinex) on a valid
    mixed-system file without event records (georinex's losses are on bad input and
    events): the same epochs, satellites and values."""
    lines, _ = _rinex3_from_rinex2(SLAC_OBS, None)
    _assert_matches_georinex(_write_lines(tmp_path, "slac3.rnx", lines))


def test_cycle_slip_records_of_flag_6_are_not_epochs(tmp_path: Path) -> None:
    """An epoch flag 6 announces cycle-slip records of an epoch already given, in the
    format of observations (slips in the values' places).  They were read as an epoch:
    a second row at that time, its slip counts taken as pseudoranges (the review).
    Now they are skipped in both versions; every observation epoch reads as before."""
    v3 = RINEX3_OBS.replace(
        "> 2021 04 28 19 30 30.0000000  0  2\n",
        "> 2021 04 28 19 30  0.0000000  6  1\nG05         1.000\n"
        "> 2021 04 28 19 30 30.0000000  0  2\n")
    o = read_obs(_write(tmp_path, "s.rnx", v3))
    ref = read_obs(_write(tmp_path, "x.rnx", RINEX3_OBS))
    assert o.n_epochs == 2 and o.t_gps_s.tolist() == ref.t_gps_s.tolist()
    np.testing.assert_array_equal(o.obs["C1C"], ref.obs["C1C"])
    lines = OBS.read_text().splitlines(True)
    k = next(j for j, ln in enumerate(lines) if ln.startswith(" 05  4  2  0  0 30.0000000"))
    nsat = int(lines[k][29:32])
    ntypes = int(next(ln for ln in lines if "TYPES OF OBSERV" in ln)[:6])
    end = k + max(1, (nsat + 11) // 12) + nsat * ((ntypes + 4) // 5)
    slip = [" 05  4  2  0  0 30.0000000  6  1G03\n"] + ["         1.000\n"] * (
        (ntypes + 4) // 5)
    o2 = read_obs(_write(tmp_path, "s.05o", "".join(lines[:end] + slip + lines[end:])))
    ref2 = read_obs(OBS)
    assert o2.n_epochs == ref2.n_epochs and o2.sats == ref2.sats
    assert o2.t_gps_s.tolist() == ref2.t_gps_s.tolist()
    for name in ref2.obs:
        np.testing.assert_array_equal(o2.obs[name], ref2.obs[name])


def test_compact_or_compressed_rinex_is_named_with_what_to_do(tmp_path: Path) -> None:
    """A Compact RINEX (Hatanaka) file, or one compressed with .Z / bzip2 / xz / zip,
    says what it is and how to get the RINEX file (it said only "first line is not a
    RINEX VERSION / TYPE record": the GNSS review, 2026-12-07); gzip is read."""
    crx = _write(tmp_path, "a.05d", "1.0                 COMPACT RINEX FORMAT"
                 "                    CRINEX VERS   / TYPE\n")
    with pytest.raises(InputError, match="Compact RINEX.*crx2rnx") as e:
        read_obs(crx)
    assert e.value.line == 1
    for name, magic, tool in (("a.05o.Z", b"\x1f\x9d\x90", "uncompress"),
                              ("a.05o.bz2", b"BZh91AY", "bunzip2"),
                              ("a.05o.xz", b"\xfd7zXZ\x00", "unxz"),
                              ("a.zip", b"PK\x03\x04", "unzip")):
        p = tmp_path / name
        p.write_bytes(magic + b"\x00" * 64)
        with pytest.raises(InputError, match=f"compressed file.*{tool}"):
            read_obs(p)


def test_an_unknown_system_letter_in_a_rinex2_epoch_is_named(tmp_path: Path) -> None:
    """``X24`` in a RINEX 2 epoch header: the satellite was dropped without a word and its
    epoch said ill_conditioned; now ``FILE:LINE`` names it (exit 2 on the command line)."""
    lines = OBS.read_text().splitlines()
    i = _first_epoch(lines)
    ep = lines[i]
    ids = ep[32:68]
    k = next(j for j in range(0, len(ids), 3) if ids[j] == "G")
    lines[i] = ep[:32 + k] + "X" + ep[32 + k + 1:]
    p = _write(tmp_path, "x.05o", "\n".join(lines) + "\n")
    with pytest.raises(InputError, match="unknown satellite system 'X'") as e:
        read_obs(p)
    assert e.value.line == i + 1


def _v2_with_g07_twice(tmp_path: Path) -> tuple[Path, int, int, int]:
    """The GEONET excerpt with G07 listed twice in its second epoch (the second record
    1000 m off, appended as a ninth satellite); returns the file and the 1-based lines of
    the epoch, G07's first record and its second."""
    lines = OBS.read_text().splitlines()
    i = _first_epoch(lines) + 9  # the second epoch (8 satellites, one line each)
    assert lines[i].endswith("  8G 3G 7G 8G11G19G20G24G28")
    rec = lines[i + 2]  # G07
    bad = rec[:16] + f"{float(rec[16:30]) + 1000:14.3f}" + rec[30:]
    lines[i] = lines[i][:29] + "  9G 3G 7G 8G11G19G20G24G28G07"
    lines.insert(i + 9, bad)
    return _write_lines(tmp_path, "dup.05o", lines), i + 1, i + 3, i + 10


def _v3_with_g07_twice(tmp_path: Path) -> tuple[Path, int, int, int]:
    """The same in RINEX 3 (``> ... 9`` and a second ``G07`` line after the epoch's
    records)."""
    lines, _ = _rinex3_geonet(tmp_path)
    i = [j for j, ln in enumerate(lines) if ln.startswith(">")][1]
    assert lines[i].endswith("  0  8")
    g = next(j for j in range(i + 1, i + 9) if lines[j].startswith("G07"))
    rec = lines[g]
    bad = rec[:3] + f"{float(rec[3:17]) + 1000:14.3f}" + rec[17:]
    lines[i] = lines[i][:-3] + "  9"
    lines.insert(i + 9, bad)
    return _write_lines(tmp_path, "dup.rnx", lines), i + 1, g + 1, i + 10


@pytest.mark.parametrize("make", [_v2_with_g07_twice, _v3_with_g07_twice])
def test_a_satellite_listed_twice_in_an_epoch_is_an_error(
        tmp_path: Path, capsys: pytest.CaptureFixture[str], make) -> None:  # noqa: ANN001
    """Two records of G07 in one epoch: the later one silently replaced the earlier (with
    --raim the epoch was fault_excluded, G07 dropped; without, ``ok`` 315 m off: the spp
    review).  A receiver writes one record per satellite and epoch: the file is
    malformed, and the error names the second record, the epoch and the first."""
    p, epoch, first, second = make(tmp_path)
    with pytest.raises(InputError) as e:
        read_obs(p)
    assert e.value.line == second
    assert (f"satellite G07 listed twice in the epoch of line {epoch} (its first record "
            f"is line {first})") in str(e.value)
    out = tmp_path / "sol.csv"
    for extra in ([], ["--raim"]):
        rc = main(["spp", str(p), str(NAV), "-o", str(out), "--quiet", *extra])
        err = capsys.readouterr().err
        assert rc == 2 and err.startswith(f"error: {p}:{second}: satellite G07 listed twice")
        assert "Traceback" not in err and not out.exists()


def test_rinex4_navigation_is_refused_on_line_1_rinex4_observation_is_read(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """A RINEX 4 navigation file went to georinex, which refuses it ("unknown RINEX"), while
    the version error said 4.xx was supported and read_nav said RINEX 4 went through
    georinex.  Now: an error on line 1 saying so (exit 2); RINEX 4 observation files have
    RINEX 3's records and are read."""
    body = ["> EPH E01 INAV", *_nav3_body()[:8]]  # a Galileo record, framed as in RINEX 4
    head = ["     4.00           N: GNSS NAV DATA    M: Mixed            RINEX VERSION / TYPE",
            _NAV3_HEAD[1]]
    p = _write_lines(tmp_path, "v4.rnx", head + body)
    with pytest.raises(InputError) as e:
        read_nav(p)
    assert e.value.line == 1
    assert "RINEX 4.00 navigation files are not supported" in str(e.value)
    v4 = _write(tmp_path, "v4.obs", RINEX3_OBS.replace("     3.03", "     4.01", 1))
    o = read_obs(v4)
    assert o.version == 4.01 and o.n_epochs == 2 and o.sats == ["G05", "G19", "E11"]
    out = tmp_path / "sol.csv"
    assert main(["spp", str(v4), str(p), "-o", str(out), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"error: {p}:1: RINEX 4.00 navigation files are not supported")
    assert not out.exists()
    # the version error lists what is read
    bad = _write(tmp_path, "v5.obs", RINEX3_OBS.replace("     3.03", "     5.00", 1))
    with pytest.raises(InputError, match=r"not supported \(2.xx and 3.xx are, and 4.xx "
                                         r"observation files\)"):
        read_obs(bad)
