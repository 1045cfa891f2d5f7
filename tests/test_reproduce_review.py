"""The reproduce review's cases (each failed on the code before its fix): damaged or
incomplete real data is the user's error or a note, never a traceback or a quiet change
of the report's figures; a rerun of one section does not replace a whole report in the
default folder; ``-o`` under a file says so."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest

from robustloc.cli import main
from robustloc.datasets import ble_tetam, uwb_labyrinth
from robustloc.errors import InputError
from robustloc.paths import PACKAGE_DATA

QUICK = ["reproduce", "--quick", "--only", "s40_integrity"]


@pytest.fixture
def tetam(tmp_path: Path) -> Path:
    """A copy of the shipped ble-tetam excerpt, as a data folder of its own."""
    shutil.copytree(PACKAGE_DATA / "ble-tetam", tmp_path / "data" / "ble-tetam")
    return tmp_path / "data"


def test_no_track_log_is_an_error_not_an_empty_list(tetam):
    """An empty trk/ folder gave [] and every user of the tracks a traceback
    ("need at least one array to concatenate")."""
    for f in (tetam / "ble-tetam" / "trk").iterdir():
        f.unlink()
    with pytest.raises(InputError, match="no track log"):
        ble_tetam.list_tracks(tetam)
    shutil.rmtree(tetam / "ble-tetam" / "trk")
    with pytest.raises(InputError, match="no track log"):
        ble_tetam.list_tracks(tetam)


def test_a_missing_upstream_walk_is_noted(tetam):
    """The shipped excerpt holds two walks (no note); a full folder that lacks some of the
    upstream's five says which (a deleted walk changed the figures without a word)."""
    assert ble_tetam.tracks_note(None) == ""
    assert ble_tetam.tracks_note(tetam) != ""  # a copy is a "full" folder of two walks
    note = ble_tetam.tracks_note(tetam)
    assert "2 of the upstream's 5 walks" in note and "straight_02" in note


def test_a_damaged_track_log_names_its_line(tetam):
    """Bytes that are not UTF-8: pandas' message named a byte of its buffer, no line; a
    value that is not a number showed NumPy's repr (np.float64(nan))."""
    import gzip

    gz = tetam / "ble-tetam" / "trk" / "straight_01_all_sensors.mbd.gz"
    text = gzip.decompress(gz.read_bytes())
    lines = text.split(b"\n")
    bad = bytearray(lines[31])
    bad[5] = 0xF1
    gz.write_bytes(gzip.compress(b"\n".join([*lines[:31], bytes(bad), *lines[32:]])))
    with pytest.raises(InputError, match=r"mbd\.gz:32: not UTF-8 text: byte 0xf1"):
        ble_tetam.load_track("straight_01", tetam)
    fields = lines[40].split(b",")
    fields[3] = b"nan"
    gz.write_bytes(gzip.compress(b"\n".join([*lines[:40], b",".join(fields), *lines[41:]])))
    with pytest.raises(InputError, match=r":41: non-numeric or non-finite rssi: nan$"):
        ble_tetam.load_track("straight_01", tetam)


@pytest.mark.parametrize(("file", "damage", "message"), [
    ("Indoor_UWB_GT.txt", "cut", "fields expected"),
    ("Indoor_UWB_Input.txt", "garbage", "not a line of this data set"),
    ("Indoor_UWB_Input.txt", "nan", "not a finite number"),
])
def test_a_damaged_labyrinth_file_is_an_error(tmp_path, file, damage, message):
    """Damaged lines were skipped into an attribute nothing read: a truth file cut
    mid-line kept 45 of its 233 rows and a missed target of the report became met."""
    d = tmp_path / "uwb-labyrinth"
    shutil.copytree(PACKAGE_DATA / "uwb-labyrinth", d)
    p = d / file
    lines = p.read_text().splitlines()
    k = len(lines) // 3
    if damage == "cut":
        lines = [*lines[:k], lines[k][: len(lines[k]) // 2]]
    elif damage == "garbage":
        lines[k] = "\x07#% garbage"
    else:
        f = lines[k].split()
        f[2] = "nan"
        lines[k] = " ".join(f)
    p.write_text("\n".join(lines) + "\n")
    with pytest.raises(InputError, match=message) as exc:
        uwb_labyrinth.load(tmp_path)
    assert f"{file}:{k + 1}:" in str(exc.value)
    assert uwb_labyrinth.load(None).skipped == []  # the shipped file has no such line


def test_s30_does_not_turn_a_damaged_data_set_into_text(tetam, tmp_path, capsys):
    """A corrupted tetam.dev was caught as "no data" by s30: "ble-tetam skipped: ..." in
    the report and exit 0 (s60 said error and exit 2)."""
    (tetam / "ble-tetam" / "cnf" / "tetam.dev").write_bytes(b"\xcb\x00garbage" * 40)
    rc = main(["reproduce", "--quick", "--only", "s30", "--data", str(tetam),
               "-o", str(tmp_path / "rep")])
    assert rc == 2
    assert "tetam.dev" in capsys.readouterr().err
    assert not (tmp_path / "rep").exists()


def test_out_under_a_file_says_so_before_any_work(tmp_path, capsys):
    (tmp_path / "afile").write_text("x")
    assert main([*QUICK, "-o", str(tmp_path / "afile" / "sub")]) == 2
    err = capsys.readouterr().err
    assert "a parent of this path is a file, not a folder" in err
    assert "real data" not in err and "note:" not in err  # (before any work)


def test_only_does_not_replace_a_fuller_default_report(tmp_path, monkeypatch, capsys):
    """`robustloc reproduce --only s60_tracks` (the report's own rerun advice) replaced
    the whole default report by one section.  Now refused without -o; with -o it is the
    user's choice, as before."""
    monkeypatch.chdir(tmp_path)
    rep = tmp_path / "report"
    rep.mkdir()
    (rep / "report.md").write_text("# robustloc reproduction report\n\nseed 1\n")
    (rep / "summary.json").write_text('{"s10_ble_ranging": {}, "s40_integrity": {}}')
    (rep / "seed000_ble_cdf.png").write_bytes(b"\x89PNG old figure")
    nodata = tmp_path / "nodata"
    nodata.mkdir()
    assert main([*QUICK, "--data", str(nodata)]) == 2
    err = capsys.readouterr().err
    assert "s10_ble_ranging" in err and "-o" in err
    assert (rep / "seed000_ble_cdf.png").exists()
    assert main([*QUICK, "--data", str(nodata), "-o", "report"]) == 0
    assert not (rep / "seed000_ble_cdf.png").exists()
    # a default report of exactly the sections run is replaced as before
    assert main([*QUICK, "--data", str(nodata)]) == 0


def test_the_report_says_first_which_data_it_used(tmp_path):
    """A fresh clone's report said only table by table that it used the excerpts."""
    nodata = tmp_path / "nodata"
    nodata.mkdir()
    assert main([*QUICK, "--data", str(nodata), "-o", str(tmp_path / "r")]) == 0
    lines = (tmp_path / "r" / "report.md").read_text().splitlines()
    assert lines[0] == "# robustloc reproduction report"
    assert lines[2].startswith(f"Real data: `{nodata}`") and "Seed 1; `--quick`" in lines[2]
    assert "<p>Real data: <code>" in (tmp_path / "r" / "report.html").read_text()
    # no data folder at all (a fresh clone): the report says it shows the excerpts
    import robustloc.paths

    mp = pytest.MonkeyPatch()
    try:
        mp.setattr(robustloc.paths, "default_data_dir", lambda: None)
        assert main([*QUICK, "-o", str(tmp_path / "r2")]) == 0
    finally:
        mp.undo()
    third = (tmp_path / "r2" / "report.md").read_text().splitlines()[2]
    assert third.startswith("Real data: the small excerpts shipped in the package")
