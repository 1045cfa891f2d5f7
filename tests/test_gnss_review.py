"""GNSS review (2026-12): observation time systems, the BeiDou ionosphere-free pair, the
GPS - UTC table.

References:
* RINEX 3.04 (IGS/RTCM, 2018) ``TIME OF FIRST OBS``: time system GPS, GLO (= UTC), GAL, QZS,
  BDT, IRN; compulsory in mixed files, default the system of a single-system file.  BDT =
  GPST - 14 s (BDS-SIS-ICD-B1I 3.0, sec. 4.2); RTKLIB ``rinex.c`` converts the epochs the
  same way (``bdt2gpst``, ``utc2gpst``).
* BDS-SIS-ICD B1I 1561.098 MHz, B2I 1207.140 MHz, B3I 1268.520 MHz.
* IERS Bulletin C: TAI - UTC; GPS - UTC = TAI - UTC - 19 s.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from robustloc.errors import InputError
from robustloc.gnss.rinex import ObsData, datetime64_to_gps_s, read_obs
from robustloc.gnss.spp import leap_seconds, pseudoranges

DATA = Path(__file__).resolve().parents[1] / "src" / "robustloc" / "data" / "gnss-geonet"
OBS2 = DATA / "07590920.05o"  # RINEX 2.10 GPS, GPS time, 2005-04-02 (GPS - UTC = 13 s)


def _as_rinex3(path: Path, time_system: str, shift_s: float) -> None:
    """The GEONET file as RINEX 3.04, its epochs moved to another time scale
    (``t - shift_s``) and ``time_system`` written in TIME OF FIRST OBS."""
    from robustloc.gnss.rinex import gps_s_to_datetime64

    o = read_obs(OBS2)
    names = {"C1": "C1C", "L1": "L1C", "P2": "C2W", "L2": "L2W"}
    types = [t for t in names if t in o.obs]
    dt = [str(d) for d in gps_s_to_datetime64(o.t_gps_s - shift_s)]

    def rec(body: str, label: str) -> str:
        return f"{body:<60}{label:<20}\n"

    d0 = dt[0]
    out = [rec("     3.04           OBSERVATION DATA    M", "RINEX VERSION / TYPE"),
           rec("".join(f"{v:14.4f}" for v in o.approx_xyz_m), "APPROX POSITION XYZ"),
           rec(f"G  {len(types):3d}" + "".join(f" {names[t]}" for t in types),
               "SYS / # / OBS TYPES"),
           rec("".join(f"{int(v):6d}" for v in (d0[:4], d0[5:7], d0[8:10], d0[11:13],
                                                  d0[14:16]))
               + f"{float(d0[17:]):13.7f}     {time_system:<3s}", "TIME OF FIRST OBS"),
           rec("", "END OF HEADER")]
    for k, s in enumerate(dt):
        have = [j for j in range(len(o.sats))
                if any(np.isfinite(o.obs[t][k, j]) for t in types)]
        out.append(f"> {s[:4]} {s[5:7]} {s[8:10]} {s[11:13]} {s[14:16]}"
                   f"{float(s[17:]):11.7f}  0{len(have):3d}\n")
        for j in have:
            line = o.sats[j] + "".join(
                " " * 16 if not np.isfinite(o.obs[t][k, j]) else f"{o.obs[t][k, j]:14.3f}  "
                for t in types)
            out.append(line.rstrip() + "\n")
    path.write_text("".join(out))


@pytest.mark.parametrize(("system", "shift_s"), [("GPS", 0.0), ("GAL", 0.0), ("BDT", 14.0),
                                                  ("GLO", 13.0)])
def test_obs_epochs_follow_the_time_system(tmp_path: Path, system: str, shift_s: float) -> None:
    """Epochs written in BDT (GPST - 14 s) or GLO (UTC = GPST - 13 s in 2005) are the same
    instants as the RINEX 2 file's GPS epochs (before: taken as GPS time, 14 s off, and the
    fixes kilometres off with status ok)."""
    ref = read_obs(OBS2)
    f = tmp_path / f"geo_{system}.rnx"
    _as_rinex3(f, system, shift_s)
    o = read_obs(f)
    np.testing.assert_allclose(o.t_gps_s, ref.t_gps_s, rtol=0, atol=1e-6)


def test_unknown_obs_time_system_is_an_input_error(tmp_path: Path) -> None:
    f = tmp_path / "geo_xyz.rnx"
    _as_rinex3(f, "XYZ", 0.0)
    with pytest.raises(InputError, match="time system 'XYZ'") as exc:
        read_obs(f)
    assert exc.value.line == 4  # the TIME OF FIRST OBS record


def test_bds_ionosphere_free_needs_b2i_not_b3i() -> None:
    """A BDS-3 satellite has B1I (C2I) and B3I (C6I), no B2I: the B1I/B2I coefficients
    applied to B3I leave 0.235 of the B1I ionospheric delay (2.3 m of 10 m); without a B2I
    code the satellite has no ionosphere-free pseudorange."""
    f1, f3 = 1561.098e6, 1268.52e6
    rho, iono = 2.2e7, 10.0
    obs = ObsData("syn", 3.04, np.array([0.0]), ["C25"],
                  {"C2I": np.array([[rho + iono]]),
                   "C6I": np.array([[rho + iono * (f1 / f3) ** 2]])},
                  np.zeros(3), np.zeros(1, dtype=np.int64), np.ones(1, dtype=np.int64))
    pif = pseudoranges(obs, "iflc")[0, 0]
    assert not np.isfinite(pif) or abs(pif - rho) < 1e-6


def test_leap_seconds_before_1999() -> None:
    """GPS - UTC: 0 before 1981-07-01, 12 s from 1997-07-01, 13 s from 1999-01-01 (the
    table started in 1999 and gave 13 s for every earlier date)."""
    days = ["1981-06-30T12:00", "1985-01-01", "1998-06-01", "1999-06-01", "2005-04-02"]
    t_utc = datetime64_to_gps_s(np.array([np.datetime64(d) for d in days]))
    want = np.array([0, 3, 12, 13, 13])
    assert leap_seconds(t_utc + want).tolist() == want.tolist()
