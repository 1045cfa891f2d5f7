"""``robustloc spp`` and its readers: the rest of the spp review's findings.

Each test fails on the code before the fix: an SP3 of 3 epochs interpolated by a parabola,
repeated or swapped SP3 epochs, ``G7 `` read as G70, ``nan`` / ``1_000`` taken as
observations, a file cut inside its last value read with exit 0, a navigation file of
another day blamed on the observation file, a time zone in ``--inject-from`` that numpy
parsed with a UserWarning and without the leap seconds, and RAIM with precise orbits and
the Klobuchar model that called most epochs unavailable.
"""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from robustloc.cli import main
from robustloc.errors import InputError
from robustloc.gnss.rinex import read_obs
from robustloc.gnss.sp3 import read_sp3
from robustloc.pipelines.spp import parse_time

DATA = Path(__file__).resolve().parents[1] / "src" / "robustloc" / "data"
SLAC = DATA / "gnss-slac"
OBS = SLAC / "slac1180_1930-1940.21o"
NAV = SLAC / "brdc1180_1700-2200.21n"
SP3 = SLAC / "COD0MGXFIN_20211181905_60M_05M_ORB.SP3"
CLK = SLAC / "COD0MGXFIN_20211181930_12M_30S_CLK.CLK"
GEONET_NAV = DATA / "gnss-geonet" / "07590920_0000-0400.05n"

RINEX3_OBS = """\
     3.03           OBSERVATION DATA    M                   RINEX VERSION / TYPE
  -3976219.5082  3382372.5671  3652512.9849                  APPROX POSITION XYZ
G    2 C1C L1C                                              SYS / # / OBS TYPES
  2021     4    28    19    30    0.0000000     GPS         TIME OF FIRST OBS
                                                            END OF HEADER
> 2021 04 28 19 30  0.0000000  0  2
G05  20311445.258   106734567.123 8
G7   21565852.190
"""


def _sp3_lines() -> list[str]:
    return SP3.read_text().splitlines()


def _epoch_lines(lines: list[str]) -> list[int]:
    return [k for k, ln in enumerate(lines) if ln.startswith("* ")]


def _write(path: Path, lines: list[str]) -> Path:
    path.write_text("\n".join(lines) + "\n")
    return path


def test_repeated_or_swapped_sp3_epochs_are_refused_at_their_line(tmp_path):
    """A repeated epoch put two epochs' samples in one interpolation window (an orbit
    metres to kilometres off, no word)."""
    lines = _sp3_lines()
    ep = _epoch_lines(lines)
    repeated = list(lines)
    repeated[ep[5]] = lines[ep[4]]
    with pytest.raises(InputError, match="not later than the previous") as e:
        read_sp3(_write(tmp_path / "rep.sp3", repeated))
    assert e.value.line == ep[5] + 1
    swapped = list(lines)
    swapped[ep[5]], swapped[ep[6]] = lines[ep[6]], lines[ep[5]]
    with pytest.raises(InputError, match="must increase") as e:
        read_sp3(_write(tmp_path / "swap.sp3", swapped))
    assert e.value.line == ep[6] + 1


def test_left_aligned_satellite_ids_are_the_satellite_not_prn_70(tmp_path):
    """``G7 `` (left-aligned) was read as G70 by the SP3 and RINEX 3 readers: the satellite
    then had no orbit, or another's."""
    lines = _sp3_lines()
    k = next(i for i, ln in enumerate(lines) if ln.startswith("PG06"))
    lines[k] = "PG6 " + lines[k][4:]
    sp3 = read_sp3(_write(tmp_path / "id.sp3", lines))
    assert "G06" in sp3.sats and "G60" not in sp3.sats
    ref = read_sp3(SP3)
    j, i = ref.sats.index("G06"), sp3.sats.index("G06")
    np.testing.assert_array_equal(sp3.pos_m[i], ref.pos_m[j])
    o = read_obs(_write(tmp_path / "id.rnx", RINEX3_OBS.splitlines()))
    assert o.sats == ["G05", "G07"]
    assert o.obs["C1C"][0, 1] == 21565852.190


@pytest.mark.parametrize("text", ["           nan", "           inf", "      21_565.5"])
def test_values_no_rinex_writer_writes_are_refused(tmp_path, text):
    """Python's float() takes ``nan``, ``inf`` and ``1_000``; they were observations."""
    v3 = RINEX3_OBS.replace("  21565852.190", text.rjust(14))
    with pytest.raises(InputError, match="malformed C1C value") as e:
        read_obs(_write(tmp_path / "v3.rnx", v3.splitlines()))
    assert e.value.line == 8
    lines = OBS.read_text().splitlines()
    k = next(i for i, ln in enumerate(lines) if "END OF HEADER" in ln) + 3  # 1st record
    lines[k] = text.rjust(14) + lines[k][14:]
    with pytest.raises(InputError, match="malformed") as e:
        read_obs(_write(tmp_path / "v2.21o", lines))
    assert e.value.line == k + 1


def test_a_file_cut_inside_its_last_value_is_refused_and_a_whole_one_read(tmp_path):
    """Cut inside the last value, the file was read (``23619216.594`` as ``23619216.``, or
    ``236192``) with exit 0.  A file whose last line is whole but has no line end is
    read as before, RINEX 2 and 3 alike."""
    raw = OBS.read_bytes()
    assert raw.endswith(b"53.800\n")
    cut = tmp_path / "cut.21o"
    cut.write_bytes(raw[:-20])
    with pytest.raises(InputError, match="ends inside a value") as e:
        read_obs(cut)
    assert e.value.line == raw.count(b"\n")
    whole = tmp_path / "whole.21o"
    whole.write_bytes(raw[:-1])
    ref, got = read_obs(OBS), read_obs(whole)
    np.testing.assert_array_equal(got.obs["C1"], ref.obs["C1"])
    v3 = RINEX3_OBS.rstrip("\n").encode()
    (tmp_path / "whole.rnx").write_bytes(v3)
    assert read_obs(tmp_path / "whole.rnx").obs["C1C"][0, 1] == 21565852.190
    (tmp_path / "cut.rnx").write_bytes(v3[:-3])
    with pytest.raises(InputError, match="ends inside a value"):
        read_obs(tmp_path / "cut.rnx")


def test_a_navigation_file_of_another_day_is_named(tmp_path, capsys):
    """It gave 'no usable pseudoranges' naming the observation file."""
    rc = main(["spp", str(OBS), str(GEONET_NAV), "-o", str(tmp_path / "x.csv")])
    err = capsys.readouterr().err
    assert rc == 2
    assert err.startswith(f"error: {GEONET_NAV}:") and "another day" in err
    assert not (tmp_path / "x.csv").exists()


def test_a_short_sp3_is_refused_by_spp(tmp_path, capsys):
    """An SP3 of fewer than 11 epochs was interpolated by a lower-degree polynomial
    (3 epochs: hundreds of metres off), fixes ``ok``.  The reader still reads it (the value
    at a sample epoch is exact), spp refuses it."""
    lines = _sp3_lines()
    ep = _epoch_lines(lines)
    end = next(k for k, ln in enumerate(lines) if ln.startswith("EOF"))
    short = _write(tmp_path / "short.sp3", lines[: ep[10]] + lines[end:])
    assert read_sp3(short).t_gps_s.size == 10
    rc = main(["spp", str(OBS), str(NAV), "--sp3", str(short), "-o", str(tmp_path / "x.csv")])
    err = capsys.readouterr().err
    assert rc == 2 and f"error: {short}:" in err and "at least 11" in err


def test_a_time_zone_in_inject_from_is_a_civil_time():
    """``2021-04-28T19:05:00Z`` went through numpy with a UserWarning and came out as GPS
    time: 18 s early (GPS - UTC was 18 s in 2021)."""
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        gps = parse_time("2021-04-28T19:05:00", "--inject-from")
        utc = parse_time("2021-04-28T19:05:00Z", "--inject-from")
        east = parse_time("2021-04-28T21:05:00+02:00", "--inject-from")
    assert utc - gps == 18.0 and east == utc
    assert parse_time("2021-04", "--inject-from") == parse_time("2021-04-01", "x")
    with pytest.raises(InputError, match="expected GPS seconds or an ISO time"):
        parse_time("2021-04-28T25:00Z", "--inject-from")


def test_precise_orbits_with_klobuchar_keep_raim_available(tmp_path):
    """Precise orbits weighted at 0.05 m left the Klobuchar model's residual ionosphere out
    of the weights (the broadcast 0.8 m, calibrated with Klobuchar, had held it): RAIM
    called most epochs of the full SLAC day unavailable (140 of 241).  On the excerpt, with
    the orbit/clock term at the broadcast one for a single frequency, every epoch is a
    fix: the same count as with broadcast orbits."""
    out = tmp_path / "p.csv"
    args = ["spp", str(OBS), str(NAV), "--raim", "--systems", "G", "--iono", "klobuchar",
            "--sp3", str(SP3), "--clk", str(CLK), "-o", str(out), "--quiet"]
    assert main(args) == 0
    got = pd.read_csv(out)
    assert main(["spp", str(OBS), str(NAV), "--raim", "--systems", "G", "-o",
                 str(tmp_path / "b.csv"), "--quiet"]) == 0
    brdc = pd.read_csv(tmp_path / "b.csv")
    assert (brdc["status"] == "ok").all()
    assert got["status"].isin(["ok", "fault_excluded"]).all(), got["status"].value_counts()


def test_run_spp_takes_one_navigation_path_as_a_path():
    """One path was read character by character: "file not found" naming its first
    letter."""
    from robustloc.pipelines.spp import SppSettings, run_spp

    one, _ = run_spp(str(OBS), str(NAV), SppSettings())
    many, _ = run_spp(str(OBS), [str(NAV)], SppSettings())
    pd.testing.assert_frame_equal(one, many)
    assert (one["status"] == "ok").all()
