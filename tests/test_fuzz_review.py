"""Defects the fuzz review of 2026-12-06 found (a traceback where the contract says
``error: FILE:LINE: what`` and exit code 2), each with the case that raised."""

from __future__ import annotations

import bz2
import functools
import lzma
import zipfile

import numpy as np
import pandas as pd
import pytest

from robustloc.cli import main
from robustloc.io import read_measurements

ANCHORS = "anchor,x,y\nA,0,0\nB,10,0\nC,0,10\n"
MEAS = "time,tag,anchor,range\n0,t,A,5\n0,t,B,7\n0,t,C,7\n1,t,A,5\n1,t,B,7\n1,t,C,7\n"
BIG = "9" * 400  # a whole number beyond float's range (pandas keeps it a Python int)


def _w(tmp_path, name, text):
    p = tmp_path / name
    p.write_text(text)
    return str(p)


def _fails(capsys, argv, prefix, words):
    code = main(argv)
    err = capsys.readouterr().err
    assert code == 2, err
    assert err.startswith(prefix), err
    assert words in err, err
    assert "Traceback" not in err


@pytest.mark.parametrize("command", ["locate", "track"])
def test_whole_number_beyond_float_in_measurements(tmp_path, capsys, command):
    a = _w(tmp_path, "a.csv", ANCHORS)
    m = _w(tmp_path, "big.csv", MEAS.replace("1,t,C,7", f"1,t,C,{BIG}"))
    _fails(capsys, [command, m, "--anchors", a, "-o", str(tmp_path / "o.csv")],
           f"error: {m}:7: ", "column 'range': infinite value inf")


def test_whole_number_beyond_float_in_anchors_and_positions(tmp_path, capsys):
    m = _w(tmp_path, "m.csv", MEAS)
    a = _w(tmp_path, "a.csv", ANCHORS.replace("B,10,0", f"B,-{BIG},0"))
    _fails(capsys, ["locate", m, "--anchors", a, "-o", str(tmp_path / "o.csv")],
           f"error: {a}:3: ", "column 'x': infinite value -inf")
    pos = _w(tmp_path, "pos.csv", f"time,tag,x,y,method,status,n_used\n0,t,1,1,ls,ok,{BIG}\n")
    truth = _w(tmp_path, "truth.csv", "time,tag,x,y\n0,t,1,1\n")
    _fails(capsys, ["evaluate", pos, "--truth", truth], f"error: {pos}:2: ",
           "column 'n_used': infinite value inf")


def _compressed(tmp_path, kind: str, name: str) -> str:
    data = MEAS.encode()
    p = tmp_path / name
    if kind == "xz":
        p.write_bytes(lzma.compress(data))
    elif kind == "bz2":
        p.write_bytes(bz2.compress(data))
    elif kind == "zip":
        with zipfile.ZipFile(p, "w") as z:
            z.writestr("m.csv", data)
    else:
        p.write_bytes(data)
    return str(p)


@pytest.mark.parametrize(("kind", "name"), [
    ("xz", "m.csv.xz"), ("bz2", "m.csv.bz2"), ("zip", "m.csv.zip"),
    ("xz", "m.csv"),  # the content decides, not the name
    ("plain", "m.csv.zip"), ("plain", "m.csv.xz"), ("plain", "m.csv.tar"),
    ("plain", "m.csv.zst")])
def test_compressed_csv_is_read_by_its_content(tmp_path, kind, name):
    # a valid .xz was refused as "not UTF-8"; a plain file named .zip/.xz/.tar/.zst ended
    # in a BadZipFile / LZMAError / ReadError / ImportError traceback
    got = read_measurements(_compressed(tmp_path, kind, name))
    want = read_measurements(_compressed(tmp_path, "plain", "plain.csv"))
    pd.testing.assert_frame_equal(got.reset_index(drop=True), want.reset_index(drop=True))


def test_broken_archives_are_input_errors(tmp_path, capsys):
    a = _w(tmp_path, "a.csv", ANCHORS)
    bad = tmp_path / "bad.csv.zip"
    bad.write_bytes(b"PK\x03\x04garbage")
    _fails(capsys, ["locate", str(bad), "--anchors", a, "-o", "-"], f"error: {bad}: ",
           "cannot read the zip file")
    two = tmp_path / "two.zip"
    with zipfile.ZipFile(two, "w") as z:
        z.writestr("m.csv", MEAS)
        z.writestr("n.csv", MEAS)
    _fails(capsys, ["locate", str(two), "--anchors", a, "-o", "-"], f"error: {two}: ",
           "exactly one file")
    cut = tmp_path / "cut.csv.xz"
    cut.write_bytes(lzma.compress(MEAS.encode())[:30])
    _fails(capsys, ["locate", str(cut), "--anchors", a, "-o", "-"], f"error: {cut}", "")


def _nmea(body: str) -> str:
    c = functools.reduce(lambda a, x: a ^ x, body.encode(), 0)
    return f"${body}*{c:02X}\n"


@pytest.mark.parametrize("body", [
    "GPRMC,9999999999999,A,3000.002424,N,11959.999825,E,0.3538,88.65,010124,,,A",
    "GPGGA,99999999999999,3000.002424,N,11959.999825,E,1,08,0.9,10.0,M,0.0,M,,",
])
def test_nmea_time_of_thirteen_digits_is_skipped(tmp_path, capsys, body):
    # OverflowError from pynmea2's timestamp (a traceback); now the sentence is skipped
    # as every other bad time is, and a log with nothing else usable says so
    a = _w(tmp_path, "a.csv", ANCHORS)
    m = _w(tmp_path, "m.csv", MEAS)
    g = _w(tmp_path, "g.nmea", _nmea(body))
    _fails(capsys, ["fuse", "--ranges", m, "--anchors", a, "--nmea", g, "-o",
                    str(tmp_path / "f.csv")], f"error: {g}: ", "no usable RMC/VTG/GGA")


def test_auto_with_an_anchor_far_outside(tmp_path, capsys):
    # an anchors file's typo (x 7.5 -> 750): the fixes' log scale held NaN for the anchor
    # no fix uses, and `auto`'s refit refused it (ValueError traceback)
    assert main(["simulate", "ble-corridor", "--seed", "1", "--out", str(tmp_path / "s")]) == 0
    capsys.readouterr()
    an = pd.read_csv(tmp_path / "s" / "anchors.csv")
    an.loc[an["anchor"].astype(str) == "3", "x"] = 750.0
    an.to_csv(tmp_path / "typo.csv", index=False)
    m = pd.read_csv(tmp_path / "s" / "measurements.csv").iloc[:120]
    m.to_csv(tmp_path / "m.csv", index=False)
    out = tmp_path / "p.csv"
    assert main(["locate", str(tmp_path / "m.csv"), "--anchors", str(tmp_path / "typo.csv"),
                 "-o", str(out)]) == 0
    err = capsys.readouterr().err
    assert "anchor(s) 3 lie far outside" in err
    pos = pd.read_csv(out)
    assert len(pos) == m.groupby(["time", "tag"]).ngroups  # every epoch has its row
    assert np.isfinite(pos["x"]).all()


def test_stats_max_lag_is_bounded(tmp_path, capsys):
    r = _w(tmp_path, "r.csv", "time,tag,anchor,rssi\n0,t,A,-50\n1,t,A,-52\n")
    assert main(["stats", r, "-o", str(tmp_path / "st"), "--max-lag", "1000000000000"]) == 2
    assert "expected a whole number in [1, 86400]" in capsys.readouterr().err


def test_zstd_without_its_package_says_so(tmp_path, capsys):
    # the zstd branch of the reader: a file with zstd's magic bytes, read without the
    # optional zstandard package, is an input error naming it (pandas' ImportError was a
    # traceback); with the package installed the bytes below are not a valid frame
    try:
        import zstandard  # noqa: F401
    except ImportError:
        pass
    else:
        pytest.skip("zstandard is installed: the missing-package message is not reachable")
    a = _w(tmp_path, "a.csv", ANCHORS)
    z = tmp_path / "m.csv.zst"
    z.write_bytes(b"\x28\xb5\x2f\xfd" + b"\x00" * 16)
    _fails(capsys, ["locate", str(z), "--anchors", a, "-o", "-"], f"error: {z}: ",
           "zstandard")
