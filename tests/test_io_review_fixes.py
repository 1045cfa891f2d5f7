"""Fixes of the input-layer review (/work/review/iorev, defects D1-D3 and D5-D7): a blank
output name, filter's same-time duplicates and late rows, partition's CSV dialect, the
anchors' sigma column, and line numbers after a quoted line break in a number."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from robustloc.cli import main
from robustloc.errors import InputError

ANCHORS_RANGE = "anchor,x,y\nA1,0,0\nA2,10,0\nA3,0,10\n"
ANCHORS_RSSI = "anchor,x,y,A,n\nA1,0,0,-40,2\n"


def _write(path: Path, text: str) -> Path:
    path.write_text(text)
    return path


# --------------------------------------------------------------------------------------
# D1: a blank output folder name
# --------------------------------------------------------------------------------------


@pytest.mark.parametrize("name", ["", "  "])
def test_simulate_refuses_a_blank_output_name(tmp_path, monkeypatch, capsys, name):
    monkeypatch.chdir(tmp_path)
    _write(tmp_path / "measurements.csv", "my real data\n")
    assert main(["simulate", "uwb-cart", "--out", name]) == 2
    err = capsys.readouterr().err
    assert "error: --out: empty output name" in err and "Traceback" not in err
    assert (tmp_path / "measurements.csv").read_text() == "my real data\n"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["measurements.csv"]


def test_write_folder_refuses_a_blank_name_before_writing(tmp_path, monkeypatch):
    from robustloc.commands._folder import write_folder

    monkeypatch.chdir(tmp_path)
    called = []
    with pytest.raises(InputError, match="empty output name"):
        write_folder("", called.append)
    assert not called and not any(tmp_path.iterdir())


def test_a_folder_output_that_cannot_be_made_is_named_as_given(tmp_path, monkeypatch,
                                                               capsys):
    """A parent folder that refuses new entries (``chattr +i``: root ignores modes) made
    ``stats`` say ``error: ro/.st.js4z0ecj.tmp: permission denied``, naming the hidden
    temporary folder (the input review).  Now the folder the user asked for, and
    nothing is written."""
    import errno
    import tempfile

    def refuse(prefix="", suffix="", dir=None):  # noqa: A002 - mkdtemp's own name
        raise PermissionError(errno.EACCES, "Permission denied",
                              str(Path(dir) / f"{prefix}abcd1234{suffix}"))

    monkeypatch.chdir(tmp_path)
    rows = "".join(f"{t},T1,A{a},{-50 - a - (t % 3)}\n" for t in range(30) for a in (1, 2, 3))
    _write(tmp_path / "m.csv", "time,tag,anchor,rssi\n" + rows)
    (tmp_path / "ro").mkdir()
    monkeypatch.setattr(tempfile, "mkdtemp", refuse)
    assert main(["stats", "m.csv", "-o", "ro/st"]) == 2
    err = capsys.readouterr().err
    assert "error: ro/st: permission denied" in err and ".tmp" not in err
    assert not any((tmp_path / "ro").iterdir())


def test_stats_and_reliability_refuse_a_blank_output_name(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    _write(tmp_path / "a.csv", "anchor,x,y,A,n\nA1,0,0,-40,2\nA2,10,0,-40,2\nA3,0,10,-40,2\n")
    assert main(["reliability", "--anchors", "a.csv", "--model", "range", "--area",
                 "0,10,0,10", "--step", "5", "--no-maps", "-o", ""]) == 2
    assert "error: --out: empty output name" in capsys.readouterr().err
    rows = "".join(f"{t},T1,A{a},{-50 - a - (t % 3)}\n" for t in range(30) for a in (1, 2, 3))
    _write(tmp_path / "m.csv", "time,tag,anchor,rssi\n" + rows)
    _write(tmp_path / "truth.csv", "time,tag,x,y\n0,T1,3,3\n29,T1,4,4\n")
    assert main(["stats", "m.csv", "--anchors", "a.csv", "--truth", "truth.csv",
                 "-o", ""]) == 2
    assert "error: --out: empty output name" in capsys.readouterr().err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.csv", "m.csv", "truth.csv"]


def test_partition_refuses_a_blank_output_name(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    _write(tmp_path / "m.csv", "time,tag,anchor,range\n0,T1,A1,5\n")
    assert main(["partition", "m.csv", "-o", "", "--by", "tag"]) == 2
    assert "error: --out: empty output name" in capsys.readouterr().err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["m.csv"]


# --------------------------------------------------------------------------------------
# D2: filter with two rows of one link at one time
# --------------------------------------------------------------------------------------


def _filter(tmp_path: Path, name: str, text: str, *extra: str) -> tuple[pd.DataFrame, int]:
    a = _write(tmp_path / "a.csv", ANCHORS_RSSI)
    m = _write(tmp_path / f"{name}.csv", text)
    out = tmp_path / f"f_{name}.csv"
    rc = main(["filter", str(m), "--anchors", str(a), "-o", str(out), *extra])
    return pd.read_csv(out), rc


def test_filter_same_time_duplicates_do_not_depend_on_row_order(tmp_path, capsys):
    head = "time,tag,anchor,rssi\n"
    s, rc1 = _filter(tmp_path, "s", head + "0,T,A1,-60\n1,T,A1,-61\n1,T,A1,-75\n"
                                          "2,T,A1,-60\n3,T,A1,-62\n")
    u, rc2 = _filter(tmp_path, "u", head + "0,T,A1,-60\n1,T,A1,-75\n1,T,A1,-61\n"
                                          "2,T,A1,-60\n3,T,A1,-62\n")
    assert rc1 == rc2 == 0
    out = capsys.readouterr().out
    assert out.count("1 duplicate rows (same time, tag and anchor) averaged") == 2
    key = ["time", "rssi_raw"]
    s = s.sort_values(key).reset_index(drop=True)
    u = u.sort_values(key).reset_index(drop=True)
    pd.testing.assert_frame_equal(s, u)
    at1 = s[s["time"] == 1]
    # one sample of the filter: both rows carry its value, each its own raw value
    assert at1["rssi"].nunique() == 1 and sorted(at1["rssi_raw"]) == [-75.0, -61.0]


def test_filter_duplicates_shuffled_wifi_log_is_order_free(tmp_path, capsys):
    from robustloc.sim.wifi_room import WifiRoomConfig, generate

    data = generate(WifiRoomConfig(), 1)
    m = data.measurements[["time", "tag", "anchor", "rssi"]]
    dup = m.sample(frac=0.1, random_state=1).assign(rssi=lambda d: d["rssi"] - 6.0)
    both = pd.concat([m, dup]).sort_values(["time", "tag", "anchor"], kind="stable")
    data.anchors.to_csv(tmp_path / "a.csv", index=False)
    both.to_csv(tmp_path / "sorted.csv", index=False)
    both.sample(frac=1.0, random_state=2).to_csv(tmp_path / "shuffled.csv", index=False)
    frames = []
    for name in ("sorted", "shuffled"):
        assert main(["filter", str(tmp_path / f"{name}.csv"), "--anchors",
                     str(tmp_path / "a.csv"), "-o", str(tmp_path / f"f_{name}.csv"),
                     "--json"]) == 0
        summary = json.loads(capsys.readouterr().out)
        assert summary["duplicates_merged"] == len(dup)
        f = pd.read_csv(tmp_path / f"f_{name}.csv")
        frames.append(f.sort_values(["time", "tag", "anchor", "rssi_raw"])
                      .reset_index(drop=True))
    pd.testing.assert_frame_equal(frames[0], frames[1])


def test_filter_samples_merges_same_time_samples_of_a_link():
    from robustloc.filters.rssi import RobustRssiFilter

    f = RobustRssiFilter()
    link = np.array([0, 0, 0, 0, 1, 1])
    t = np.array([0.0, 1.0, 1.0, 2.0, 1.0, 1.0])
    z = np.array([-60.0, -61.0, -75.0, -60.0, -50.0, np.nan])
    a = f.filter_samples(link, t, z)
    perm = np.array([3, 2, 5, 0, 4, 1])
    b = f.filter_samples(link[perm], t[perm], z[perm])
    np.testing.assert_array_equal(a.rssi_dbm[perm], b.rssi_dbm)
    np.testing.assert_array_equal(a.weight[perm], b.weight)
    assert a.extra["duplicates_merged"] == b.extra["duplicates_merged"] == 1
    # the merged sample is the mean of the finite values
    merged = f.filter_samples(np.array([0, 0, 0, 1]), np.array([0.0, 1.0, 2.0, 1.0]),
                              np.array([-60.0, -68.0, -60.0, -50.0]))
    np.testing.assert_array_equal(a.rssi_dbm[:5], merged.rssi_dbm[[0, 1, 1, 2, 3]])
    # the NaN sample beside link 1's first one is no part of it: the prediction, and
    # the link has none before its first sample (it had taken the sample's -50: the
    # filter review)
    assert np.isnan(a.rssi_dbm[5]) and np.isnan(a.weight[5])


# --------------------------------------------------------------------------------------
# D3: filter keeps every column of a row whose time is beyond +-1e12 s
# --------------------------------------------------------------------------------------


@pytest.mark.parametrize("suffix", [".csv", ".parquet"])
def test_filter_late_row_keeps_every_input_column(tmp_path, capsys, suffix):
    a = _write(tmp_path / "a.csv", ANCHORS_RSSI)
    m = _write(tmp_path / "m.csv", "time,tag,anchor,rssi,note,k\n0,T,A1,-60,first,1\n"
                                   "2e12,T,A1,-62,third,3\n1,T,A1,-61,second,2\n")
    out = tmp_path / f"f{suffix}"
    assert main(["filter", str(m), "--anchors", str(a), "-o", str(out)]) == 0
    f = pd.read_csv(out) if suffix == ".csv" else pd.read_parquet(out)
    assert list(f["note"]) == ["first", "third", "second"]
    assert list(f["k"]) == [1, 3, 2]
    assert list(f["status"]) == ["ok", "invalid_measurement", "ok"]
    assert f["rssi"].iloc[1] == -62.0 and f["time"].iloc[1] == 2e12


# --------------------------------------------------------------------------------------
# D5: partition reads CSV as the other commands do
# --------------------------------------------------------------------------------------


def _partition(tmp_path: Path, text: str, by: str = "time") -> tuple[int, Path]:
    m = _write(tmp_path / "m.csv", text)
    out = tmp_path / "ds"
    return main(["partition", str(m), "-o", str(out), "--by", by]), out


HEAD = "time,tag,anchor,range\n"


@pytest.mark.parametrize("text, where, what", [
    (HEAD + "0,T1,A1,5\n0,T1,A2\n1,T1,A1,5\n", 3, "column 'range': missing or NaN value"),
    (HEAD + "0,T1,A1,5\nhello world\n1,T1,A1,5\n", 3, "column 'tag': empty id"),
    (HEAD + "0,T1,A1,5\n0,T1,A2,7,9\n1,T1,A1,5\n", 3, "expected 4 fields, found 5"),
    (HEAD + "0,T1,A1,5\n# note\n1,T1,A1,5\n", 3, "the line looks like a comment"),
    ("time,tag,anchor,range,range\n0,T1,A1,5,6\n", 1, "duplicate column 'range'"),
    ("time;tag;anchor;range\n0;T1;A1;5\n", 1, "separated by semicolons"),
])
def test_partition_refuses_what_the_reader_refuses_at_its_line(tmp_path, capsys, text,
                                                               where, what):
    rc, out = _partition(tmp_path, text)
    err = capsys.readouterr().err
    assert rc == 2 and f"m.csv:{where}: " in err and what in err, err
    assert not out.exists()
    # the reader of the other commands says the same
    _write(tmp_path / "a.csv", ANCHORS_RANGE)
    assert main(["locate", str(tmp_path / "m.csv"), "--anchors", str(tmp_path / "a.csv"),
                 "-o", str(tmp_path / "p.csv"), "--quiet"]) == 2
    assert f"m.csv:{where}: " in capsys.readouterr().err


def test_partition_trims_ids_as_the_readers_do(tmp_path, capsys):
    rc, out = _partition(tmp_path, HEAD + "0,T1,A1,5\n0,T1 ,A2,7\n0,T1,A3 ,7\n"
                                          "1,T1 ,A1,5\n1,T1,A2,7\n1, T1 ,A3,7\n", by="tag")
    assert rc == 0
    files = sorted(out.rglob("*.parquet"))
    assert [f.parent.name for f in files] == ["tag=T1"]
    t = pd.read_parquet(files[0])
    assert set(t["tag"]) == {"T1"} and set(t["anchor"]) == {"A1", "A2", "A3"}
    capsys.readouterr()
    _write(tmp_path / "a.csv", ANCHORS_RANGE)
    assert main(["locate", str(out), "--anchors", str(tmp_path / "a.csv"), "-o",
                 str(tmp_path / "pos"), "--engine", "dask", "--workers", "1",
                 "--quiet"]) == 0


# --------------------------------------------------------------------------------------
# D6: the anchors' sigma column
# --------------------------------------------------------------------------------------


@pytest.mark.parametrize("cells, line, bad", [
    (("0.1m", "0.5m", "0.1m"), 2, "0.1m"),
    (("0.1", "abc", "0.1"), 3, "abc"),
])
def test_anchor_sigma_text_is_not_a_number(tmp_path, capsys, cells, line, bad):
    a = _write(tmp_path / "a.csv", "anchor,x,y,sigma\n" + "".join(
        f"A{i + 1},{x},{y},{c}\n" for i, ((x, y), c) in
        enumerate(zip([(0, 0), (10, 0), (0, 10)], cells))))
    m = _write(tmp_path / "m.csv", HEAD + "0,T,A1,5\n0,T,A2,7\n0,T,A3,7\n")
    assert main(["locate", str(m), "--anchors", str(a), "-o", str(tmp_path / "p.csv"),
                 "--quiet"]) == 2
    err = capsys.readouterr().err
    assert f"a.csv:{line}: column 'sigma': {bad!r} is not a number" in err, err
    # an empty cell still means "not given" (no sigma for any anchor: unweighted)
    from robustloc.io import read_anchors
    from robustloc.io.tables import anchor_sigma

    a = read_anchors(_write(tmp_path / "b.csv", "anchor,x,y,sigma\nA1,0,0,\nA2,1,0,\n"))
    assert anchor_sigma(a) is None


# --------------------------------------------------------------------------------------
# D7: a quoted line break inside a number
# --------------------------------------------------------------------------------------


@pytest.mark.parametrize("chunk", [[], ["--chunk-rows", "1"], ["--chunk-rows", "2"]])
@pytest.mark.parametrize("text, line", [
    (HEAD + '0,T1,A1,"5\n"\n0,T1,A2,7\n1,T1,A9,7\n', 5),
    (HEAD + '0,T1,A1, "5\r\n"\r\n\r\n0,T1,A2,7\r\n1,T1,A9,7\r\n', 6),
    (HEAD + '0,"T\n1",A1,"5\n\n"\n0,T1,A2,7\n1,T1,A9,7\n', 7),
])
def test_quoted_break_in_a_number_keeps_later_lines(tmp_path, capsys, chunk, text, line):
    a = _write(tmp_path / "a.csv", ANCHORS_RANGE)
    m = tmp_path / "m.csv"
    m.write_bytes(text.encode())
    assert main(["locate", str(m), "--anchors", str(a), "-o", str(tmp_path / "p.csv"),
                 "--quiet", *chunk]) == 2
    err = capsys.readouterr().err
    assert f"m.csv:{line}: unknown anchor id 'A9'" in err, err


def test_read_measurements_lines_after_a_quoted_break_in_a_number(tmp_path):
    from robustloc.io import read_measurements

    m = tmp_path / "m.csv"
    m.write_text(HEAD + '0,T1,A1,"5\n"\n0,T1,A2,7\n"1\n\n",T1,A3,7\n2,T1,A1,8\n')
    df = read_measurements(m)
    assert list(df.index) == [2, 4, 5, 8]
    assert list(df["range"]) == [5.0, 7.0, 7.0, 8.0]


@pytest.mark.skipif(not Path("/proc/self/status").is_file(), reason="needs Linux /proc")
def test_a_file_that_reports_no_size_is_read_not_called_empty(tmp_path, capsys):
    """``/proc`` files report size 0 but have content: ``locate /proc/self/status`` said
    ``empty file`` (the input review).  Now it is read, and refused for what it is."""
    _write(tmp_path / "a.csv", "anchor,x,y\nA1,0,0\nA2,10,0\nA3,0,10\n")
    assert main(["locate", "/proc/self/status", "--anchors", str(tmp_path / "a.csv"),
                 "-o", str(tmp_path / "p.csv")]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: /proc/self/status:") and "empty file" not in err
    assert "Traceback" not in err
