"""Tests of the NMEA reader/writer (pynmea2-based)."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as hs

from robustloc.errors import InputError
from robustloc.io.nmea import (
    KNOT_MPS,
    make_gga,
    make_rmc,
    make_vtg,
    nmea_checksum,
    parse_nmea,
    read_nmea,
)
from robustloc.paths import PACKAGE_DATA

VOID = "GPRMC,000011.00,V,,,,,,,010124,,,N"
PIXEL6 = PACKAGE_DATA / "nmea-pixel6" / "pixel6.nmea"


def test_checksum_known_sentence():
    # from the pixel6 fixture: $GPRMC,...*4F
    body = "GPRMC,234321.00,A,3725.589246,N,12210.425073,W,002.2,199.1,071123,,,A"
    assert nmea_checksum(body) == "4F"


def test_pixel6_fixture():
    log = read_nmea(PIXEL6)
    assert log.summary.parsed == {"GGA": 48, "RMC": 48}
    assert log.summary.n_skipped == 0
    assert len(log.motion) == 48 and len(log.fixes) == 48
    # third RMC: 002.2 kn, 199.1 deg (true, clockwise from north)
    row = log.motion.iloc[2]
    assert row["speed_mps"] == pytest.approx(2.2 * 1852 / 3600)
    assert np.rad2deg(row["course_rad"]) % 360 == pytest.approx(199.1)
    # stationary: empty course -> NaN, speed 0
    assert np.isnan(log.motion["course_rad"].iloc[0]) and log.motion["speed_mps"].iloc[0] == 0
    # time of day 23:42:57 -> seconds
    assert log.fixes["time_s"].iloc[0] == pytest.approx(23 * 3600 + 42 * 60 + 57)
    # ENU about the first fix; first GGA: 51.9 m MSL + (-28.4) geoid = 23.5 m ellipsoidal
    assert log.origin == pytest.approx((37.426506616, -122.1737089, 23.5))
    assert log.fixes[["east_m", "north_m", "up_m"]].iloc[0].abs().max() < 1e-6
    # second fix: 0.000119' of latitude north = 0.22 m
    assert log.fixes["north_m"].iloc[1] == pytest.approx(0.000119 / 60 * 111_000, rel=0.01)


def test_malformed_sentences_counted_not_raised():
    good = make_rmc(10.0, 1.0, 90.0)
    lines = [
        good,
        good[:-2] + ("00" if not good.endswith("00") else "01"),  # bad checksum
        good.split("*")[0],  # missing checksum
        "$GPRMC,000010.00*" + nmea_checksum("GPRMC,000010.00"),  # truncated, valid checksum
        make_gga(10.0, 37.0, -122.0, 5.0, quality=0),  # invalid fix
        "$" + VOID + "*" + nmea_checksum(VOID),  # status V: invalid fix
        "$GPGSV,1,1,00*" + nmea_checksum("GPGSV,1,1,00"),  # unsupported
        "not nmea at all",
        "",
        "$GPGGA,1,2,3\x00\xff",
    ]
    log = parse_nmea(lines)
    s = log.summary
    assert s.parsed == {"RMC": 1}
    assert s.skipped["bad_checksum"] == 1
    assert s.skipped["missing_checksum"] == 2
    assert s.skipped["truncated"] == 1
    assert s.skipped["invalid_fix"] == 2
    assert s.skipped["unsupported"] == 1
    assert s.skipped["no_sentence"] == 1
    assert s.lines == 9
    assert "skipped" in s.text()


def test_writer_round_trip_and_vtg_gets_time():
    lines = []
    for k in range(5):
        t = 86395.0 + k * 2.0  # crosses midnight
        lines += [make_rmc(t, 0.2 * k, 350.0 + 5 * k), make_vtg(0.2 * k, 350.0 + 5 * k),
                  make_gga(t, 37.0, -122.0 + 1e-5 * k, 10.0)]
    log = parse_nmea(lines)
    rmc = log.motion[log.motion["sentence"] == "RMC"]
    vtg = log.motion[log.motion["sentence"] == "VTG"]
    np.testing.assert_allclose(rmc["time_s"], 86395.0 + 2.0 * np.arange(5))
    np.testing.assert_allclose(vtg["time_s"], rmc["time_s"])  # VTG inherits the RMC time
    np.testing.assert_allclose(rmc["speed_mps"], 0.2 * np.arange(5), atol=1e-4 * KNOT_MPS)
    np.testing.assert_allclose(vtg["speed_mps"], 0.2 * np.arange(5), atol=1e-3)
    course_deg = np.rad2deg(rmc["course_rad"].to_numpy())
    np.testing.assert_allclose(course_deg, [-10, -5, 0, 5, 10], atol=1e-6)  # wrapped
    assert np.all(np.diff(log.fixes["east_m"]) > 0.8)  # 1e-5 deg lon at 37 N ~ 0.89 m


def test_origin_option():
    lines = [make_gga(1.0, 37.0, -122.0, 0.0)]
    log = parse_nmea(lines, origin=(37.0, -122.0001, 0.0))
    phi = np.deg2rad(37.0)
    n_radius = 6378137.0 / np.sqrt(1 - 6.69437999014e-3 * np.sin(phi) ** 2)  # WGS84
    expected = n_radius * np.cos(phi) * np.deg2rad(0.0001)
    assert log.fixes["east_m"].iloc[0] == pytest.approx(expected, rel=1e-6)


def test_unreadable_and_empty_files(tmp_path):
    with pytest.raises(InputError, match="cannot read"):
        read_nmea(tmp_path / "missing.nmea")
    p = tmp_path / "junk.nmea"
    p.write_text("hello\n$GPRMC,bad*00\n")
    with pytest.raises(InputError, match="no usable"):
        read_nmea(p)


@settings(max_examples=200, deadline=None)
@given(hs.lists(hs.text(alphabet="$GPRMCVTGAS,.*0123456789ABCDEFNW-\x00", max_size=80),
                max_size=8))
def test_garbage_never_crashes(lines):
    log = parse_nmea(lines)
    sm = log.summary
    # no silent loss: every non-empty line is either used or counted as skipped
    assert sm.lines == sum(1 for ln in lines if ln.strip())
    assert sum(sm.parsed.values()) + sm.n_skipped == sm.lines


def test_gst_accuracy_rows():
    body = "GPGST,172814.0,0.006,0.023,0.020,273.6,0.023,0.020,0.031"
    log = parse_nmea(["$" + body + "*" + nmea_checksum(body), make_gga(62894.0, 1.0, 2.0, 3.0)])
    acc = log.accuracy
    assert len(acc) == 1 and log.summary.parsed["GST"] == 1
    row = acc.iloc[0]
    assert row["time_s"] == pytest.approx(17 * 3600 + 28 * 60 + 14)
    assert (row["rms_m"], row["sigma_lat_m"], row["sigma_lon_m"], row["sigma_alt_m"]) == (
        pytest.approx(0.006), pytest.approx(0.023), pytest.approx(0.020), pytest.approx(0.031))


@pytest.mark.parametrize(
    "body",
    [
        "GPVTG,1,T,,M,abc,N,x,K,A",
        "GPRMC,12x456,A,3725.5,N,12210.4,W,abc,1e999,071123,,,A",
        "GPGGA,123456,37xx.5,N,12210.4,W,1,08,zz,10,M,0,M,,",
        "GPGST,123456,a,b,c,d,e,f,g",
        "GPRMC,999999,A,3725.5,N,12210.4,W,1.0,2.0,991399,,,A",
    ],
)
def test_garbage_fields_with_valid_checksum_are_skipped(body):
    # a required number that is not one is "malformed" (37xx.5; it was counted as
    # "truncated" until the GNSS review), fields read as missing leave the sentence
    # "truncated", and a time or date that is not a calendar value (12x456, 999999, day 99)
    # is an "invalid_measurement": either way skipped and counted, once
    log = parse_nmea(["$" + body + "*" + nmea_checksum(body)])
    sk = log.summary.skipped
    assert log.summary.parsed == {}
    assert sk["truncated"] + sk["malformed"] + sk["invalid_measurement"] == 1


def test_posix_day_from_rmc_date():
    log = read_nmea(PIXEL6)  # 2023-11-07 23:42:57 UTC = 1699400577 (the logger's own ms)
    t0 = log.fixes["time_s"].iloc[0] + log.day0_posix_s
    assert t0 == pytest.approx(1699400577.0)
    # rolling over midnight keeps the same day 0
    log2 = parse_nmea([make_rmc(86399.0, 1.0, 0.0, date="311223"),
                       make_rmc(1.0, 1.0, 0.0, date="010124")])
    np.testing.assert_allclose(log2.motion["time_s"], [86399.0, 86401.0])
    assert log2.day0_posix_s == pytest.approx(1703980800.0)  # 2023-12-31 00:00 UTC
    assert parse_nmea([make_vtg(1.0, 0.0)]).day0_posix_s is None


def test_parse_nmea_of_a_string_reads_its_lines_and_refuses_a_file_name(tmp_path):
    """A string was iterated character by character: every character a ``no_sentence``
    line, no error (a path given to parse_nmea read as 41 empty 'lines')."""
    import pytest

    from robustloc.io.nmea import parse_nmea, read_nmea

    text = PIXEL6.read_text()
    from_text = parse_nmea(text)
    assert from_text.summary.parsed == read_nmea(PIXEL6).summary.parsed
    assert from_text.summary.parsed["GGA"] == 48
    assert parse_nmea(text.encode()).summary.parsed["RMC"] == 48
    with pytest.raises(TypeError, match="use read_nmea"):
        parse_nmea(str(PIXEL6))


def _sentence(body: str) -> str:
    return f"${body}*{nmea_checksum(body)}"


def test_rmc_with_faa_mode_n_is_an_invalid_fix_as_a_vtg_is():
    """RMC's mode indicator N (NMEA 2.3 on: data not valid) was read as a motion row while a
    VTG with mode N was skipped as invalid_fix (the spp review)."""
    rmc = "GNRMC,010000.00,A,3725.590397,N,12210.422534,W,010.0,90.0,071123,,,{}"
    vtg = "GPVTG,90.0,T,,M,10.0,N,18.5,K,N"
    log = parse_nmea([_sentence(rmc.format("N")), _sentence(vtg)])
    assert log.summary.parsed == {} and len(log.motion) == 0
    assert log.summary.skipped["invalid_fix"] == 2
    for mode in ("A", "D", "E", ""):  # autonomous, differential, estimated, no field
        log = parse_nmea([_sentence(rmc.format(mode))])
        assert log.summary.parsed == {"RMC": 1}, mode
        assert log.motion["speed_mps"].iloc[0] == pytest.approx(10.0 * KNOT_MPS)


@pytest.mark.parametrize("body", [
    "GPRMC,010016.00,A,3725.590397,N,12210.422534,W,1_0,90.0,071123,,,A",  # speed
    "GPRMC,010016.00,A,3725.590397,N,12210.422534,W,10.0,9_0,071123,,,A",  # course
    "GPVTG,9_0,T,,M,10.0,N,18.5,K,A",  # course
    "GPVTG,90.0,T,,M,10.0,N,1_8.5,K,A",  # speed
    "GPGGA,010018.00,3725.590397,N,12210.422534,W,1_0,24,0.4,51.9,M,-28.4,M,,",  # quality
    "GPGGA,010018.00,3725.5_90397,N,12210.422534,W,1,24,0.4,51.9,M,-28.4,M,,",  # latitude
    "GPGGA,010018.00,3725.590397,N,12210.422534,W,1,24,0.4,5_1.9,M,-28.4,M,,",  # altitude
    "GPGGA,010018.00,3725.590397,N,12210.422534,W,1,2_4,0.4,51.9,M,-28.4,M,,",  # satellites
    "GPGGA,0100_18.00,3725.590397,N,12210.422534,W,1,24,0.4,51.9,M,-28.4,M,,",  # time
    "GPGST,010018.00,0.0_06,0.023,0.020,273.6,0.023,0.020,0.031",  # rms
])
def test_a_number_with_an_underscore_is_malformed(body):
    """Python's float and int read ``1_0`` as 10: an RMC of 1_0 kn was a 10 kn motion row,
    a GGA of quality 1_0 a fix of quality 10, while the module docstring says such fields
    are malformed (and the RINEX reader refuses them)."""
    vtg_fix = [make_rmc(3616.0, 1.0, 0.0)] if body.startswith("GPVTG") else []
    log = parse_nmea([*vtg_fix, _sentence(body)])
    assert log.summary.skipped["malformed"] == 1, log.summary.text()
    assert log.summary.parsed == ({"RMC": 1} if vtg_fix else {})
