"""Issue 15 / issue 10 item 6: input from anywhere and in any order, nothing absurd taken
as data -- standard input and output, FIFOs, gzip and non-UTF-8 files, duplicate headers,
Parquet timestamps, rows in any order (sorted in memory or out of core), streaming by
epoch key, plausibility limits."""

from __future__ import annotations

import io
import json
import os
import subprocess
import sys
import threading
from pathlib import Path

import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.parquet as pq
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import robustloc.io.tables as tables
from robustloc.cli import main
from robustloc.errors import InputError
from robustloc.io import iter_epochs, iter_measurements, read_measurements, to_epochs

ENV = {**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[1] / "src")}
CLI = [sys.executable, "-m", "robustloc.cli"]
ANCHORS = "anchor,x,y\na,0,0\nb,20,0\nc,0,20\nd,20,20\n"
IDS = ["a", "b", "c", "d"]


def _ranges(n_epochs: int, tags: int = 1, seed: int = 0) -> pd.DataFrame:
    rng = np.random.default_rng(seed)
    anc = np.array([[0, 0], [20, 0], [0, 20], [20, 20]], float)
    k = np.repeat(np.arange(n_epochs), 4)
    j = np.tile(np.arange(4), n_epochs)
    pos = rng.uniform(2, 18, (n_epochs, 2))
    d = np.hypot(pos[k, 0] - anc[j, 0], pos[k, 1] - anc[j, 1])
    return pd.DataFrame({
        "time": (k // tags) * 0.5, "tag": np.char.add("T", (k % tags).astype(str)),
        "anchor": np.array(IDS)[j], "range": d + rng.normal(0, 0.05, d.size),
    })


@pytest.fixture()
def files(tmp_path):
    (tmp_path / "a.csv").write_text(ANCHORS)
    _ranges(30, tags=2).to_csv(tmp_path / "m.csv", index=False)
    return tmp_path


def _locate(meas, anchors, out, *more) -> int:
    return main(["locate", str(meas), "--anchors", str(anchors), "-o", str(out), "--quiet",
                 *more])


def _sorted(pos: pd.DataFrame) -> pd.DataFrame:
    return pos.sort_values(["time", "tag", "method"], kind="stable").reset_index(drop=True)


# ------------------------------------------------------------------ stdin / stdout / FIFO


def test_stdin_to_stdout_real_process(files):
    ref = files / "ref.csv"
    assert _locate(files / "m.csv", files / "a.csv", ref, "--method", "ls") == 0
    data = (files / "m.csv").read_bytes()
    r = subprocess.run(CLI + ["locate", "-", "--anchors", str(files / "a.csv"), "-o", "-",
                              "--method", "ls"], input=data, capture_output=True, env=ENV)
    assert r.returncode == 0, r.stderr
    got = pd.read_csv(io.BytesIO(r.stdout))  # pure CSV: the summary is not in it
    pd.testing.assert_frame_equal(got, pd.read_csv(ref))
    assert b"30 epochs of range -> -" in r.stderr  # 15 times x 2 tags
    # --quiet silences the summary; --json goes to stderr when the data go to stdout
    r = subprocess.run(CLI + ["locate", "-", "--anchors", str(files / "a.csv"), "-o", "-",
                              "--method", "ls", "--quiet"], input=data, capture_output=True,
                       env=ENV)
    assert r.returncode == 0 and r.stderr == b""
    r = subprocess.run(CLI + ["locate", "-", "--anchors", str(files / "a.csv"), "-o",
                              "/dev/stdout", "--method", "ls", "--json"], input=data,
                       capture_output=True, env=ENV)
    assert r.returncode == 0
    pd.testing.assert_frame_equal(pd.read_csv(io.BytesIO(r.stdout)), pd.read_csv(ref))
    assert json.loads(r.stderr)["epochs"] == 30


def test_stdin_errors_name_stdin(files):
    r = subprocess.run(CLI + ["locate", "-", "--anchors", str(files / "a.csv"), "-o", "-"],
                       input=b"time,tag,anchor,range\n0,T,a,1\n0,T,zz,1\n", capture_output=True,
                       env=ENV)
    assert r.returncode == 2 and r.stdout == b""
    assert r.stderr.decode() == ("error: <stdin>:3: unknown anchor id 'zz' (not in the anchors"
                                 " file)\n")
    r = subprocess.run(CLI + ["locate", "-", "--anchors", str(files / "a.csv"), "-o", "-"],
                       input=b"", capture_output=True, env=ENV)
    assert r.returncode == 2
    assert r.stderr.decode() == "error: <stdin>:1: empty file (expected a header line)\n"


def test_fifo_is_read_not_stat_as_empty(files, capsys):
    """`locate <(cat m.csv)`: a FIFO has size 0 to stat; it is read."""
    fifo = files / "pipe.csv"
    os.mkfifo(fifo)
    data = (files / "m.csv").read_bytes()

    def feed():
        with open(fifo, "wb") as fh:
            fh.write(data)

    th = threading.Thread(target=feed)
    th.start()
    try:
        assert _locate(fifo, files / "a.csv", files / "p.csv", "--method", "ls") == 0
    finally:
        th.join(timeout=30)
    assert _locate(files / "m.csv", files / "a.csv", files / "q.csv", "--method", "ls") == 0
    pd.testing.assert_frame_equal(pd.read_csv(files / "p.csv"), pd.read_csv(files / "q.csv"))


def test_process_substitution_real_shell(files):
    cmd = (f"{sys.executable} -m robustloc.cli locate <(cat {files / 'm.csv'}) --anchors "
           f"{files / 'a.csv'} -o - --method ls --quiet")
    r = subprocess.run(["bash", "-c", cmd], capture_output=True, env=ENV)
    assert r.returncode == 0, r.stderr
    assert len(pd.read_csv(io.BytesIO(r.stdout))) == 30


# ------------------------------------------------------------------ odd files


def test_gzip_named_csv_is_read(files):
    """Choice: a gzip file is decompressed whatever its name (pandas, told so)."""
    import gzip

    (files / "gz.csv").write_bytes(gzip.compress((files / "m.csv").read_bytes()))
    a = read_measurements(files / "gz.csv")
    b = read_measurements(files / "m.csv")
    np.testing.assert_array_equal(a["range"].to_numpy(), b["range"].to_numpy())
    assert list(a.index) == list(b.index)
    chunks = list(iter_measurements(files / "gz.csv", chunk_rows=7))
    assert sum(len(c) for c in chunks) == len(b)


def test_non_utf8_byte_names_line_and_column(tmp_path):
    p = tmp_path / "m.csv"
    p.write_bytes(b"time,tag,anchor,range\n0,T,a,1\n0,T,\xffb,1\n")
    with pytest.raises(InputError) as ei:
        read_measurements(p)
    assert ei.value.line == 3 and "not UTF-8 text: byte 0xff at column 5" in str(ei.value)
    with pytest.raises(InputError) as ei:
        list(iter_measurements(p, chunk_rows=1))
    assert ei.value.line == 3


def test_duplicate_header_column_refused(tmp_path):
    p = tmp_path / "m.csv"
    p.write_text("time,tag,anchor,range,range\n0,T,a,1,2\n")
    with pytest.raises(InputError, match="duplicate column 'range' in the header") as ei:
        read_measurements(p)
    assert ei.value.line == 1
    t = pa.table([pa.array([0.0]), pa.array(["T"]), pa.array(["a"]), pa.array([1.0]),
                  pa.array([2.0])], names=["time", "tag", "anchor", "range", "range"])
    pq.write_table(t, tmp_path / "m.parquet")
    for reader in (read_measurements, lambda q: list(iter_measurements(q))):
        with pytest.raises(InputError, match="duplicate column 'range'"):
            reader(tmp_path / "m.parquet")


@pytest.mark.parametrize("unit", ["s", "ms", "us", "ns"])
@pytest.mark.parametrize("tz", [None, "UTC", "Europe/Berlin"])
def test_parquet_timestamp_time_is_unix_seconds(tmp_path, unit, tz):
    """Issue 15: a timestamp `time` was taken as microseconds (1 s -> 1e6)."""
    secs = np.array([1.0, 1.0, 2.5, 1_700_000_000.25])
    if unit == "s":
        secs = np.floor(secs)
    ts = pd.to_datetime(secs, unit="s", utc=True)
    if tz is not None:
        ts = ts.tz_convert(tz)
    else:
        ts = ts.tz_localize(None)
    arr = pa.array(ts, type=pa.timestamp(unit, tz=tz))
    t = pa.table({"time": arr, "tag": ["T"] * 4, "anchor": ["a", "b", "a", "a"],
                  "range": [1.0, 2.0, 3.0, 4.0]})
    pq.write_table(t, tmp_path / "m.parquet")
    for m in (read_measurements(tmp_path / "m.parquet"),
              pd.concat(list(iter_measurements(tmp_path / "m.parquet", chunk_rows=2)))):
        np.testing.assert_array_equal(m["time"].to_numpy(), secs)


def test_parquet_duration_time_is_seconds(tmp_path):
    t = pa.table({"time": pa.array(pd.to_timedelta([0.0, 0.5, 90.0], unit="s"),
                                   type=pa.duration("ms")),
                  "tag": ["T"] * 3, "anchor": ["a"] * 3, "range": [1.0, 2.0, 3.0]})
    pq.write_table(t, tmp_path / "m.parquet")
    np.testing.assert_array_equal(read_measurements(tmp_path / "m.parquet")["time"],
                                  [0.0, 0.5, 90.0])


def test_timestamp_parquet_through_locate(files):
    m = _ranges(6)
    m["time"] = pd.to_datetime(1_600_000_000 + m["time"], unit="s")
    m.to_parquet(files / "m.parquet", index=False)
    assert _locate(files / "m.parquet", files / "a.csv", files / "p.csv", "--method", "ls") == 0
    pos = pd.read_csv(files / "p.csv")
    np.testing.assert_array_equal(pos["time"], 1_600_000_000 + 0.5 * np.arange(6))


# ------------------------------------------------------------------ any order


@settings(max_examples=12, deadline=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(seed=st.integers(0, 2**32 - 1), chunk_rows=st.sampled_from([5, 37, 500_000]))
def test_shuffled_rows_give_the_same_positions(files, seed, chunk_rows):
    """Issue 10 item 6: rows permuted (hypothesis-chosen) -> the same positions."""
    ref = files / "ref.csv"
    if not ref.exists():
        assert _locate(files / "m.csv", files / "a.csv", ref, "--method", "ls,nls") == 0
    m = pd.read_csv(files / "m.csv")
    perm = np.random.default_rng(seed).permutation(len(m))
    m.iloc[perm].to_csv(files / "shuffled.csv", index=False)
    assert _locate(files / "shuffled.csv", files / "a.csv", files / "p.csv",
                   "--method", "ls,nls", "--chunk-rows", str(chunk_rows)) == 0
    a, b = _sorted(pd.read_csv(ref)), _sorted(pd.read_csv(files / "p.csv"))
    pd.testing.assert_frame_equal(a, b, check_exact=False, rtol=1e-12, atol=1e-12)


def test_tracks_one_after_another_restart_sorted(files, capsys):
    """Several tags' logs one after another: the disorder shows only after chunks were
    written; locate discards them and sorts (summary says so)."""
    m = _ranges(40, tags=2)
    logs = pd.concat([m[m["tag"] == "T0"], m[m["tag"] == "T1"]])
    logs.to_csv(files / "logs.csv", index=False)
    m.to_csv(files / "sorted.csv", index=False)
    assert _locate(files / "sorted.csv", files / "a.csv", files / "ref.csv",
                   "--method", "ls") == 0
    assert main(["locate", str(files / "logs.csv"), "--anchors", str(files / "a.csv"),
                 "-o", str(files / "p.csv"), "--method", "ls", "--chunk-rows", "16",
                 "--json"]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["sorted_first"] and summary["epochs"] == 40
    pd.testing.assert_frame_equal(pd.read_csv(files / "ref.csv"), pd.read_csv(files / "p.csv"))
    # standard output cannot be taken back: the order is checked first, same result
    r = subprocess.run(CLI + ["locate", str(files / "logs.csv"), "--anchors",
                              str(files / "a.csv"), "-o", "-", "--method", "ls",
                              "--chunk-rows", "16", "--quiet"], capture_output=True, env=ENV)
    assert r.returncode == 0
    pd.testing.assert_frame_equal(pd.read_csv(io.BytesIO(r.stdout)),
                                  pd.read_csv(files / "ref.csv"))


@pytest.mark.parametrize("cmd", ["locate", "track"])
def test_the_summary_says_when_rows_were_sorted_in_memory(files, capsys, cmd):
    """A shuffled log that fits in memory is sorted before anything is written (no
    restart): ``sorted_first`` was false then, and the "rows were not in epoch order" line
    missing; ``track``'s summary had no such key.  Sorted input: false, no line."""
    m = _ranges(12, tags=2)
    m.to_csv(files / "sorted.csv", index=False)
    m.sample(frac=1.0, random_state=3).to_csv(files / "shuffled.csv", index=False)
    line = "rows were not in epoch order: sorted by time and tag first"
    for name, want in (("shuffled.csv", True), ("sorted.csv", False)):
        argv = [cmd, str(files / name), "--anchors", str(files / "a.csv"),
                "-o", str(files / "p.csv")]
        assert main([*argv, "--json"]) == 0
        assert json.loads(capsys.readouterr().out)["sorted_first"] is want
        assert main(argv) == 0
        assert (line in capsys.readouterr().out) is want


def test_out_of_core_sort_equals_in_memory(tmp_path):
    m = _ranges(60, tags=3)
    m["extra"] = 1
    m.sample(frac=1, random_state=3).to_csv(tmp_path / "m.csv", index=False)
    mem = list(iter_epochs(tmp_path / "m.csv", IDS, chunk_rows=50, order="sort"))
    ooc = list(iter_epochs(tmp_path / "m.csv", IDS, chunk_rows=50, order="sort",
                           memory_budget_bytes=0))
    for f in ("time", "values", "line", "n_invalid"):
        np.testing.assert_array_equal(np.concatenate([getattr(e, f) for e in mem]),
                                      np.concatenate([getattr(e, f) for e in ooc]))
    np.testing.assert_array_equal(np.concatenate([e.tag for e in mem]),
                                  np.concatenate([e.tag for e in ooc]))
    whole = to_epochs(read_measurements(tmp_path / "m.csv"), IDS)
    np.testing.assert_array_equal(np.concatenate([e.values for e in ooc]), whole.values)
    np.testing.assert_array_equal(np.concatenate([e.time for e in ooc]), whole.time)


def test_one_time_many_tags_streams_in_bounded_chunks(tmp_path, monkeypatch):
    """Issue 15 memory case in small: every row time 0, each epoch its own tag (tags not
    in sorted order): streamed, each chunk bounded, nothing sorted in memory."""
    monkeypatch.setattr(tables, "_MIN_GROUP_ROWS", 8)
    n = 200
    m = _ranges(n)
    m["tag"] = np.repeat([f"t{(i * 7919) % n}" for i in range(n)], 4)
    m["time"] = 0.0
    m.to_csv(tmp_path / "m.csv", index=False)

    def no_sort(*a, **k):
        raise AssertionError("the sorting path must not be used")

    monkeypatch.setattr(tables, "_iter_sorted_in_memory", no_sort)
    monkeypatch.setattr(tables, "_iter_sorted_out_of_core", no_sort)
    chunks = list(iter_measurements(tmp_path / "m.csv", chunk_rows=10))
    assert max(len(c) for c in chunks) <= 10 + 8 + 4
    assert sum(len(c) for c in chunks) == len(m)
    keys = pd.concat(chunks).groupby(["time", "tag"]).size()
    assert len(keys) == n and (keys == 4).all()
    # an epoch interrupted by another of the same time, beyond one chunk: not streamable
    bad = pd.concat([m.iloc[:2], m.iloc[4:40], m.iloc[2:4], m.iloc[40:]])
    bad.to_csv(tmp_path / "bad.csv", index=False)
    with pytest.raises(tables.UnsortedInput, match="rows not grouped by epoch"):
        list(iter_measurements(tmp_path / "bad.csv", chunk_rows=10, order="auto"))


def test_ble_tetam_tracks_one_after_another(tmp_path, capsys):
    """The real example of issue 10: several tracks of ble-tetam one after another."""
    from robustloc.datasets import ble_tetam

    anchors = ble_tetam.load_anchors()
    anchors = anchors.assign(A=-61.43, n=1.478)[["anchor", "x", "y", "A", "n"]]
    anchors.to_csv(tmp_path / "a.csv", index=False)
    tracks = ble_tetam.list_tracks()[:3]
    meas = pd.concat([ble_tetam.load_track(t)[0][["time", "tag", "anchor", "rssi"]]
                      for t in tracks], ignore_index=True)
    meas.to_csv(tmp_path / "logs.csv", index=False)
    meas.sort_values(["time", "tag"], kind="stable").to_csv(tmp_path / "sorted.csv",
                                                            index=False)
    assert _locate(tmp_path / "sorted.csv", tmp_path / "a.csv", tmp_path / "ref.csv",
                   "--method", "ls,nls") == 0
    assert _locate(tmp_path / "logs.csv", tmp_path / "a.csv", tmp_path / "p.csv",
                   "--method", "ls,nls", "--chunk-rows", "200") == 0
    a, b = pd.read_csv(tmp_path / "ref.csv"), pd.read_csv(tmp_path / "p.csv")
    n_epochs = len(meas.groupby(["time", "tag"]))
    assert len(b) == 2 * n_epochs
    pd.testing.assert_frame_equal(_sorted(a), _sorted(b))


# ------------------------------------------------------------------ plausibility


def test_absurd_values_are_invalid_measurements_counted(files, capsys):
    rows = _ranges(5)
    rows.loc[0, "range"] = 1e308  # epoch 0: one absurd range among four
    rows.loc[4:7, "range"] = [1e200, -1e3, 2e5, 1e308]  # epoch 1: every range absurd
    rows.to_csv(files / "bad.csv", index=False)
    assert main(["locate", str(files / "bad.csv"), "--anchors", str(files / "a.csv"),
                 "-o", str(files / "p.csv"), "--method", "ls,nls", "--json"]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["invalid_measurement_rows"] == 5
    pos = pd.read_csv(files / "p.csv")
    assert len(pos) == 2 * 5
    e1 = pos[pos["time"] == 0.5]
    assert (e1["status"] == "invalid_measurement").all() and e1["x"].isna().all()
    assert (pos[pos["time"] != 0.5]["status"] != "invalid_measurement").all()
    e0 = pos[pos["time"] == 0.0]
    assert (e0["n_used"] == 3).all()  # the 1e308 range is not used
    # text summary
    assert main(["locate", str(files / "bad.csv"), "--anchors", str(files / "a.csv"),
                 "-o", str(files / "p.csv"), "--method", "ls"]) == 0
    assert "invalid_measurement: 5 rows" in capsys.readouterr().out


def test_epoch_with_only_absurd_rows_gets_status_invalid(files, capsys):
    rows = pd.DataFrame({"time": [0, 0, 0, 1, 1, 1, 1e13], "tag": "T",
                         "anchor": ["a", "b", "c", "a", "b", "c", "a"],
                         "range": [1e308, -500.0, 1e6, 10, 10, 10, 10]})
    rows.to_csv(files / "bad.csv", index=False)
    assert main(["locate", str(files / "bad.csv"), "--anchors", str(files / "a.csv"),
                 "-o", str(files / "p.csv"), "--method", "ls,huber", "--json"]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["invalid_measurement_rows"] == 4
    assert summary["status"]["ls"]["invalid_measurement"] == 2
    pos = pd.read_csv(files / "p.csv")
    bad = pos[pos["time"] != 1]
    assert (bad["status"] == "invalid_measurement").all() and bad["x"].isna().all()
    assert (pos[pos["time"] == 1]["status"] != "invalid_measurement").all()
    e = to_epochs(read_measurements(files / "bad.csv"), IDS)
    np.testing.assert_array_equal(e.n_invalid, [3, 0, 1])
    np.testing.assert_array_equal(e.all_invalid, [True, False, True])


def test_track_sets_absurd_rows_aside_and_counts_them(files, capsys):
    """``track``: an epoch at a time of 1e13 s (after the last fix, and -1e13 s before the
    first) went through the filter's prediction: a `predicted` row at x ~ 1e12 m with an
    hpl of 1e26 m, counted usable; and rows outside the limits were never counted.  Now
    such an epoch is invalid_measurement with no state (as in ``locate``), the others are
    tracked exactly as without it, and the summary counts the rows."""
    rows = _ranges(12)
    clean = rows.copy()
    rows.loc[len(rows)] = [1e13, "T0", "a", 10.0]  # a whole epoch beyond the limits
    rows.loc[len(rows)] = [-1e13, "T0", "b", 10.0]
    rows.loc[9, "range"] = 2e5  # one absurd range in an epoch of four
    rows.to_csv(files / "bad.csv", index=False)
    clean.loc[9, "range"] = np.nan
    clean.dropna().to_csv(files / "clean.csv", index=False)
    for name in ("bad", "clean"):
        assert main(["track", str(files / f"{name}.csv"), "--anchors", str(files / "a.csv"),
                     "-o", str(files / f"t_{name}.csv"), "--json"]) == 0
        summary = json.loads(capsys.readouterr().out)
        assert summary["invalid_measurement_rows"] == (3 if name == "bad" else 0)
    # (the clean run's 12 rows; the tag jumps at random from epoch to epoch, so the
    # tracker's innovation test flags most as fault_detected: the same in both runs)
    assert sum(summary["status"].values()) == 12
    assert "invalid_measurement" not in summary["status"]
    t = pd.read_csv(files / "t_bad.csv")
    assert len(t) == 14
    far = t[t["time"].abs() > 1e12]
    assert (far["status"] == "invalid_measurement").all()
    assert far[["x", "y", "hpl"]].isna().all().all()
    ref = pd.read_csv(files / "t_clean.csv")
    pd.testing.assert_frame_equal(t[t["time"].abs() < 1e12].reset_index(drop=True), ref)
    assert main(["track", str(files / "bad.csv"), "--anchors", str(files / "a.csv"),
                 "-o", str(files / "t_bad.csv")]) == 0
    assert "invalid_measurement: 3 rows" in capsys.readouterr().out


def test_rssi_limits(tmp_path):
    p = tmp_path / "m.csv"
    p.write_text("time,tag,anchor,rssi\n0,T,a,-500\n0,T,b,50\n0,T,c,-60\n0,T,d,-150\n")
    e = to_epochs(read_measurements(p), IDS)
    np.testing.assert_array_equal(e.n_invalid, [2])
    np.testing.assert_array_equal(np.isfinite(e.values[0]), [False, False, True, True])


@pytest.mark.parametrize("dtype", ["float", "object", "category"])
def test_a_numeric_id_is_the_same_text_whatever_its_column_dtype(dtype):
    """A tag of 1.0 was "1" in a float column and "1.0" in an object or categorical one
    (after a concat, say); an object column of float anchor ids then failed against the
    anchors "1", "2" (the API review).  Every dtype now names it "1"."""
    from robustloc import locate

    anchors = pd.DataFrame({"anchor": [1, 2, 3], "x": [0, 10, 0.0], "y": [0, 0, 10.0]})
    m = pd.DataFrame({"time": [0.0] * 3, "tag": [1.0] * 3, "anchor": [1.0, 2.0, 3.0],
                      "range": [5.0, np.hypot(7, 4), np.hypot(3, 6)]})
    m = m.astype({"tag": dtype, "anchor": dtype})
    got = read_measurements(m)
    assert got["tag"].tolist() == ["1"] * 3 and got["anchor"].tolist() == ["1", "2", "3"]
    pos = locate(m, anchors)
    assert pos["tag"].tolist() == ["1"]
    mixed = pd.DataFrame({"time": [0.0, 0.0], "tag": pd.Series([1.5, "x"], dtype=object),
                          "anchor": ["1", "2"], "range": [1.0, 2.0]})
    assert read_measurements(mixed)["tag"].tolist() == ["1.5", "x"]


def test_a_period_time_is_its_start_in_seconds():
    """A Period time column was read as its ordinal (milliseconds since 1970 for "ms",
    minutes for "min": times in the wrong unit, silently for coarse ones)."""
    ts = pd.to_datetime([0.0, 0.0, 120.0], unit="s")
    m = pd.DataFrame({"time": ts, "tag": ["T"] * 3, "anchor": ["a", "b", "a"],
                      "range": [1.0, 2.0, 3.0]})
    for unit in ("ms", "s", "min"):
        got = read_measurements(m.assign(time=m["time"].dt.to_period(unit)))
        assert got["time"].tolist() == [0.0, 0.0, 120.0], unit


def test_a_file_that_grows_while_it_is_read_is_refused(tmp_path):
    """A log still being written was read up to its half-written last line, silently: the
    epoch was solved on part of its rows, or a cut value ("-7" of "-79.0") was used as a
    measurement, exit 0 (the no-loss review).  A file whose size or time changes while it
    is read is refused once read (the outputs are atomic: nothing is written)."""
    from robustloc.errors import InputError
    from robustloc.io import tables

    m = tmp_path / "m.csv"
    m.write_text("time,tag,anchor,rssi\n0,T,a,-60\n0,T,b,-61\n1,T,a,-7")
    chunks = tables._iter_raw(m, 1, ["tag", "anchor"])
    next(chunks)
    with open(m, "a") as fh:  # the logger finishes its line, and writes another
        fh.write("9.0\n1,T,b,-62\n")
    with pytest.raises(InputError, match="the file changed while it was read"):
        list(chunks)
    # read whole: the same (the size is compared at the end of the read)
    assert len(tables._read_raw(m, ["tag", "anchor"])) == 4
