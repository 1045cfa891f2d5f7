"""Issue 15, part B: RINEX edge cases are ``error: FILE:LINE: what`` (exit 2, no traceback,
no output file) and implausible pseudoranges are invalid measurements, counted and unused.

Mutations of the shipped GEONET excerpt (RINEX 2.10 observation + GPS navigation).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from robustloc import status as st
from robustloc.cli import main
from robustloc.errors import InputError
from robustloc.gnss.rinex import read_nav, read_obs

DATA = Path(__file__).resolve().parents[1] / "src" / "robustloc" / "data" / "gnss-geonet"
OBS = DATA / "07590920.05o"
NAV = DATA / "07590920_0000-0400.05n"


def _lines(path: Path) -> tuple[list[str], int]:
    lines = path.read_text().splitlines()
    return lines, next(k for k, ln in enumerate(lines) if "END OF HEADER" in ln) + 1


def _write(tmp_path: Path, name: str, lines: list[str]) -> Path:
    p = tmp_path / name
    p.write_text("\n".join(lines) + "\n")
    return p


def _spp_error(capsys, obs: Path, nav: Path, tmp_path: Path) -> str:
    out = tmp_path / "sol.csv"
    rc = main(["spp", str(obs), str(nav), "--systems", "G", "-o", str(out)])
    err = capsys.readouterr().err
    assert rc == 2, err
    assert err.startswith("error:") and "Traceback" not in err
    assert not out.exists()
    return err


def test_epoch_announcing_9_satellites_listing_8(tmp_path, capsys):
    lines, i = _lines(OBS)
    assert "  8G 3G" in lines[i]
    lines[i] = lines[i].replace("  8G 3G", "  9G 3G")
    bad = _write(tmp_path, "nsat.05o", lines)
    err = _spp_error(capsys, bad, NAV, tmp_path)
    assert f"{bad}:{i + 1}:" in err and "announces 9 satellites but lists 8" in err


def test_negative_satellite_count_is_an_error_not_an_endless_loop(tmp_path):
    lines, i = _lines(OBS)
    lines[i] = lines[i].replace("  8G 3G", " -1G 3G")
    with pytest.raises(InputError, match="satellite count"):
        read_obs(_write(tmp_path, "neg.05o", lines))


@pytest.mark.parametrize("field,value,what", [
    ((4, 6), "13", "month"), ((7, 9), "31", "day"), ((10, 12), "24", "hour"),
    ((13, 15), "60", "minute"),
])
def test_impossible_epoch_time_names_file_and_line(tmp_path, capsys, field, value, what):
    lines, i = _lines(OBS)
    a, b = field
    lines[i] = lines[i][:a] + value.rjust(b - a) + lines[i][b:]  # April has 30 days
    bad = _write(tmp_path, "t.05o", lines)
    err = _spp_error(capsys, bad, NAV, tmp_path)
    assert f"{bad}:{i + 1}: impossible epoch time" in err


def test_nav_month_13_names_file_and_line(tmp_path, capsys):
    lines, i = _lines(NAV)
    lines[i] = lines[i][:5] + "13" + lines[i][7:]
    bad = _write(tmp_path, "m.05n", lines)
    err = _spp_error(capsys, OBS, bad, tmp_path)
    assert f"{bad}:{i + 1}: impossible clock epoch" in err


def test_nav_prn_0_is_an_error(tmp_path):
    lines, i = _lines(NAV)
    lines[i] = " 0" + lines[i][2:]
    with pytest.raises(InputError, match="PRN must be 1-32"):
        read_nav(_write(tmp_path, "p.05n", lines))


def test_implausible_pseudorange_is_invalid_counted_never_used(tmp_path, capsys):
    lines, i = _lines(OBS)
    # first record of the first epoch (G03): P2 (4th field) becomes 1e300 m
    lines[i + 1] = lines[i + 1][:48] + f"{1e300:14.3E}" + lines[i + 1][62:]
    bad = _write(tmp_path, "pr.05o", lines)
    obs = read_obs(bad)
    assert obs.invalid_per_epoch[0] == 1 and obs.invalid_per_epoch[1:].sum() == 0
    assert np.isnan(obs.obs["P2"][0, obs.sats.index("G03")])
    out = tmp_path / "sol.csv"
    assert main(["spp", str(bad), str(NAV), "--systems", "G", "-o", str(out)]) == 0
    cap = capsys.readouterr()
    assert "invalid_measurement: 1" in cap.out
    sol = pd.read_csv(out)
    assert len(sol) == obs.n_epochs


def test_epoch_whose_pseudoranges_are_all_implausible_gets_invalid_status(tmp_path, capsys):
    lines, i = _lines(OBS)
    for k in range(1, 9):  # the 8 records of epoch 1: C1 and P2 -> 1 m (not a pseudorange)
        ln = lines[i + k]
        lines[i + k] = ln[:16] + f"{1.0:14.3f}" + ln[30:48] + f"{1.0:14.3f}" + ln[62:]
    bad = _write(tmp_path, "all.05o", lines)
    out = tmp_path / "sol.csv"
    assert main(["spp", str(bad), str(NAV), "--systems", "G", "-o", str(out)]) == 0
    cap = capsys.readouterr()
    assert "invalid_measurement: 16" in cap.out
    sol = pd.read_csv(out)
    assert sol["status"].iloc[0] == st.INVALID
    assert sol["status"].iloc[1] == st.OK


@pytest.mark.parametrize("opt,value", [
    ("--elevation-mask", "nan"), ("--elevation-mask", "100"), ("--alpha0", "0"),
    ("--smooth", "-3"), ("--reference", "1,2,3"), ("--inject", "G11:inf"),
    ("--inject-from", "yesterday"),
])
def test_spp_refuses_absurd_option_values(tmp_path, capsys, opt, value):
    out = tmp_path / "sol.csv"
    argv = ["spp", str(OBS), str(NAV), "--systems", "G", "-o", str(out), f"{opt}={value}"]
    if opt.startswith("--inject-"):
        argv.append("--inject=G11:20")
    try:
        rc = main(argv)
    except SystemExit as e:  # argparse
        rc = e.code
    err = capsys.readouterr().err
    assert rc == 2 and "error" in err and opt in err and "Traceback" not in err
    assert not out.exists()


SLAC = DATA.parent / "gnss-slac"


def test_sp3_and_clock_epochs_must_be_calendar_times(tmp_path):
    from robustloc.gnss.sp3 import read_clk, read_sp3

    sp3 = (SLAC / "COD0MGXFIN_20211181905_60M_05M_ORB.SP3").read_text().splitlines()
    i = next(k for k, ln in enumerate(sp3) if ln.startswith("*"))
    sp3[i] = "*  2021 13 28 19  5  0.00000000"
    with pytest.raises(InputError, match=rf":{i + 1}: impossible epoch 2021-13-28"):
        read_sp3(_write(tmp_path, "bad.sp3", sp3))
    clk = (SLAC / "COD0MGXFIN_20211181930_12M_30S_CLK.CLK").read_text().splitlines()
    j = next(k for k, ln in enumerate(clk) if ln.startswith("AS "))
    parts = clk[j].split()
    parts[7] = "nan"  # seconds
    clk[j] = " ".join(parts)
    with pytest.raises(InputError, match=rf":{j + 1}: impossible epoch"):
        read_clk(_write(tmp_path, "bad.clk", clk))


@pytest.mark.parametrize("offset", [1, 4, 8, 12])
def test_a_stray_line_among_the_records_is_named_at_its_own_line(tmp_path, capsys, offset):
    # records are counted, not recognized: a stray line shifts the records after it and
    # the reader stumbled only at the line it took for the next epoch's header, up to an
    # epoch later (measured: stray at line 20 -> reported at 27, at 31 -> 36)
    lines, i = _lines(OBS)
    # lines[i] is the first epoch's header, 8 record lines follow, then the next epoch:
    # offsets 1-8 put the stray line among the first epoch's records, 12 the second's
    assert lines[i].startswith(" 05  4  2") and lines[i + 9].startswith(" 05  4  2")
    at = i + offset
    lines.insert(at, "this is a stray line of garbage")
    bad = _write(tmp_path, "stray.05o", lines)
    err = _spp_error(capsys, bad, NAV, tmp_path)
    assert f"{bad}:{at + 1}:" in err, err
    assert "not an observation record 'this is a stray line of garbage'" in err


def test_a_missing_record_line_names_the_epoch_header_read_as_a_record(tmp_path, capsys):
    lines, i = _lines(OBS)
    del lines[i + 3]  # one of the first epoch's 8 records: the next header is read as one
    bad = _write(tmp_path, "short.05o", lines)
    err = _spp_error(capsys, bad, NAV, tmp_path)
    assert f"{bad}:{i + 9}:" in err and "not an observation record ' 05  4  2" in err


def _implausible(line: str, first_col: int, fields: list[int]) -> str:
    """An observation record line with the given 16-character fields (0-based, from
    ``first_col``) set to 1 m (no pseudorange: an invalid measurement) where not blank."""
    for f in fields:
        c = first_col + 16 * f
        if line[c : c + 14].strip():
            line = line[:c] + f"{1.0:14.3f}" + line[c + 14 :]
    return line


def _spp_status(obs: Path, nav: Path, tmp_path: Path, *options: str) -> pd.Series:
    out = tmp_path / "sol.csv"
    assert main(["spp", str(obs), str(nav), "-o", str(out), "--quiet", *options]) == 0
    return pd.read_csv(out)["status"]


def test_invalid_value_of_a_satellite_below_the_mask_keeps_the_epochs_reason(tmp_path):
    """The review: an implausible C1 of G23 (7 deg, below the 15 deg mask, never used) in
    the last epoch relabelled that ill_conditioned epoch (5 satellites, GDOP 47)
    invalid_measurement.  The status says invalid_measurement only when the values set
    aside could have given the epoch a fix."""
    lines, i = _lines(OBS)
    k = max(j for j, ln in enumerate(lines) if "    26444999.610 " in ln)  # G23, last epoch
    assert lines[k - 7].startswith(" 05  4  2  0 59 30") and "G23" in lines[k - 7]
    clean = _spp_status(OBS, NAV, tmp_path, "--systems", "G")
    assert clean.iloc[-1] == st.ILL_CONDITIONED
    lines[k] = _implausible(lines[k], 0, [1])
    bad = _write(tmp_path, "g23.05o", lines)
    assert read_obs(bad).invalid_per_epoch[-1] == 1
    for raim in ([], ["--raim"]):
        assert _spp_status(bad, NAV, tmp_path, "--systems", "G", *raim).iloc[-1] \
            == st.ILL_CONDITIONED
    # the contrast: C1 and P2 of 5 of the first epoch's 8 satellites (all above the mask)
    lines, i = _lines(OBS)
    for r in range(1, 6):
        lines[i + r] = _implausible(lines[i + r], 0, [1, 3])
    status = _spp_status(_write(tmp_path, "five.05o", lines), NAV, tmp_path, "--systems", "G")
    assert status.iloc[0] == st.INVALID and status.iloc[1:].equals(clean.iloc[1:])


def test_invalid_value_of_a_constellation_not_requested_keeps_the_epochs_reason(tmp_path):
    """Implausible codes of every Galileo satellite of the SLAC excerpt's first epoch: with
    --systems G and a 50 deg mask (2 GPS satellites: insufficient_anchors) they could not
    have mattered (invalid_measurement before); with --systems E they took the epoch's
    every satellite."""
    obs = SLAC / "slac1180_1930-1940.21o"
    nav = SLAC / "brdc1180_1700-2200.21n"
    sp3 = ["--sp3", str(SLAC / "COD0MGXFIN_20211181905_60M_05M_ORB.SP3"),
           "--clk", str(SLAC / "COD0MGXFIN_20211181930_12M_30S_CLK.CLK")]
    lines, i = _lines(obs)
    types = read_obs(obs).obs.keys()
    codes = [t for t, name in enumerate(types) if name[0] in "CP"]
    nsat, per = int(lines[i][29:32]), (len(types) + 4) // 5
    head = lines[i][32:68] + lines[i + 1][32:68] if nsat > 12 else lines[i][32:68]
    sats = [head[3 * s : 3 * s + 3] for s in range(nsat)]
    first = i + (nsat + 11) // 12
    gal = [s for s in range(nsat) if sats[s].startswith("E")]
    assert len(gal) >= 4
    for s in gal:
        for li in range(per):
            j = first + s * per + li
            lines[j] = _implausible(lines[j].ljust(80), 0,
                                    [t % 5 for t in codes if t // 5 == li]).rstrip()
    bad = _write(tmp_path, "e.21o", lines)
    assert read_obs(bad).invalid_per_epoch[0] >= 2 * len(gal)
    status = _spp_status(bad, nav, tmp_path, "--systems", "G", "--elevation-mask", "50", *sp3)
    assert (status == st.INSUFFICIENT).all()
    status = _spp_status(bad, nav, tmp_path, "--systems", "E", *sp3)
    assert status.iloc[0] == st.INVALID and (status.iloc[1:] == st.OK).all()
