"""Contract readers/writers: parsing, validation with file and line, streaming, pivot."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from robustloc.errors import InputError
from robustloc.estimators.solution import Solution
from robustloc.io import (
    PositionsWriter,
    iter_epochs,
    iter_measurements,
    positions_frame,
    read_anchors,
    read_measurements,
    read_positions,
    read_survey,
    read_truth,
    to_epochs,
    write_positions,
    write_table,
)


def _write(tmp_path, name, text):
    p = tmp_path / name
    p.write_text(text)
    return p


ANCHORS = "anchor,x,y,A,n,note\n1,0,0,-59,2,door\n2,10,0,,,\nB3,0,10,-60,2.2,x\n"


def test_read_anchors_types_and_extra_columns(tmp_path):
    a = read_anchors(_write(tmp_path, "a.csv", ANCHORS))
    assert list(a["anchor"]) == ["1", "2", "B3"]
    assert a["x"].dtype == float and a["A"].dtype == float
    assert np.isnan(a["A"].iloc[1])  # empty parameter = not set
    assert list(a["note"].fillna("")) == ["door", "", "x"]  # extra column carried
    assert list(a.index) == [2, 3, 4]  # index = source line


@pytest.mark.parametrize(
    ("text", "line", "words"),
    [
        ("anchor,x\n1,0\n", 1, "missing column(s) y"),
        ("anchor,x,y\n1,0,0\n2,abc,0\n", 3, "'abc' is not a number"),
        ("anchor,x,y\n1,0,0\n1,5,0\n", 3, "duplicate anchor id '1'"),
        ("anchor,x,y\n1,0,0\n2,nan,0\n", 3, "NaN"),
        ("anchor,x,y\n1,0,0\n\n2,inf,0\n", 4, "infinite"),
        ("anchor,x,y\n,0,0\n", 2, "empty id"),
        ("anchor,x,y\n", 2, "no data rows"),
        ("anchor,x,y\n1,0,0\n2,1,2,3,4\n", 3, "expected 3 fields"),
    ],
)
def test_read_anchors_errors_name_file_and_line(tmp_path, text, line, words):
    p = _write(tmp_path, "a.csv", text)
    with pytest.raises(InputError) as ei:
        read_anchors(p)
    assert ei.value.line == line
    assert ei.value.path == str(p)
    assert words in str(ei.value)
    assert str(ei.value).startswith(f"{p}:{line}: ")


def test_empty_and_missing_file(tmp_path):
    p = _write(tmp_path, "empty.csv", "")
    with pytest.raises(InputError, match="empty file") as ei:
        read_anchors(p)
    assert ei.value.line == 1
    with pytest.raises(InputError, match="file not found"):
        read_measurements(tmp_path / "nope.csv")


def test_parquet_same_as_csv_and_line_numbers(tmp_path):
    a = read_anchors(_write(tmp_path, "a.csv", ANCHORS))
    pq = write_table(a, tmp_path / "a.parquet")
    b = read_anchors(pq)
    pd.testing.assert_frame_equal(
        a.reset_index(drop=True)[["anchor", "x", "y", "A", "n"]],
        b.reset_index(drop=True)[["anchor", "x", "y", "A", "n"]],
    )
    bad = pd.DataFrame({"anchor": ["1", "2", "2"], "x": [0.0, 1, 2], "y": [0.0, 0, 0]})
    write_table(bad, tmp_path / "bad.parquet")
    with pytest.raises(InputError) as ei:
        read_anchors(tmp_path / "bad.parquet")
    assert ei.value.line == 4  # row 2 (0-based) = CSV-equivalent line 4


def test_integer_anchor_ids_from_parquet_become_strings(tmp_path):
    df = pd.DataFrame({"anchor": [1, 2], "x": [0.0, 1.0], "y": [0.0, 1.0]})
    write_table(df, tmp_path / "a.parquet")
    assert list(read_anchors(tmp_path / "a.parquet")["anchor"]) == ["1", "2"]



def test_float_ids_do_not_depend_on_their_chunk(tmp_path):
    """Float tag and anchor ids are named value by value: a whole-column rule named the tag
    1.0 "1" in a chunk of whole numbers and "1.0" in a chunk holding 1.5, so one tag
    became two and the epoch across the chunks two epochs of two ranges each (found by
    fuzzing the API; the CLI on Parquet did the same with --chunk-rows)."""
    import robustloc
    from robustloc.cli import main

    anchors = pd.DataFrame({"anchor": [1.0, 2.0, 3.0, 4.5], "x": [0.0, 10, 10, 0],
                            "y": [0.0, 0, 10, 10]})
    d = np.hypot(anchors.x - 3, anchors.y - 4).to_numpy()
    log = pd.DataFrame({"time": np.repeat([0.0, 1.0, 2.0], 4),
                        "tag": np.repeat([1.0, 1.0, 1.5], 4),
                        "anchor": np.tile(anchors.anchor, 3), "range": np.tile(d, 3)})
    whole = robustloc.locate(log, anchors)
    assert list(whole["tag"]) == ["1", "1", "1.5"]
    assert list(whole["status"]) == ["ok"] * 3
    for rows in (1, 5, 6, 7):
        pd.testing.assert_frame_equal(robustloc.locate(log, anchors, chunk_rows=rows), whole)
    # the anchors' float ids meet the measurements' whole ones (1.0 in both: "1")
    first = log[log.anchor != 4.5].iloc[:3]
    assert robustloc.locate(first, anchors)["status"].tolist() == ["low_redundancy"]
    # the command line on Parquet, read in chunks
    write_table(anchors, tmp_path / "a.parquet")
    write_table(log, tmp_path / "m.parquet")
    out = tmp_path / "p.csv"
    assert main(["locate", str(tmp_path / "m.parquet"), "--anchors", str(tmp_path / "a.parquet"),
                 "--chunk-rows", "6", "-o", str(out), "--quiet"]) == 0
    got = pd.read_csv(out, dtype={"tag": str})
    assert list(got["tag"]) == ["1", "1", "1.5"] and list(got["status"]) == ["ok"] * 3


MEAS = (
    "time,tag,anchor,rssi\n"
    "0,S1,1,-60\n0,S1,2,-70\n0,S1,2,-72\n0,S2,1,-50\n"
    "1,S1,1,-61\n1.5,S2,B3,-65\n"
)


def test_read_measurements_and_unknown_anchor(tmp_path):
    a = read_anchors(_write(tmp_path, "a.csv", ANCHORS))
    m = read_measurements(_write(tmp_path, "m.csv", MEAS), a)
    assert m.attrs["value"] == "rssi"
    assert m["rssi"].dtype == float and m["tag"].iloc[0] == "S1"
    bad = _write(tmp_path, "m2.csv", MEAS + "2,S1,9,-70\n")
    with pytest.raises(InputError, match="unknown anchor id '9'") as ei:
        read_measurements(bad, a)
    assert ei.value.line == 8


@pytest.mark.parametrize(
    ("row", "words"),
    [
        ("2,S1,1,nan", "NaN"),
        ("2,S1,1,", "NaN"),
        ("2,S1,1,-inf", "infinite"),
        ("2,S1,1,loud", "not a number"),
        ("x,S1,1,-60", "not a number"),
    ],
)
def test_measurement_bad_value_names_its_line(tmp_path, row, words):
    p = _write(tmp_path, "m.csv", MEAS + row + "\n1,S1,1,-60\n")
    with pytest.raises(InputError, match=words) as ei:
        read_measurements(p)
    assert ei.value.line == 8


def test_measurements_need_exactly_one_value_column(tmp_path):
    with pytest.raises(InputError, match="rssi or range"):
        read_measurements(_write(tmp_path, "m.csv", "time,tag,anchor\n0,S1,1\n"))
    with pytest.raises(InputError, match="both"):
        read_measurements(_write(tmp_path, "m.csv", "time,tag,anchor,rssi,range\n0,S1,1,1,1\n"))


def test_negative_ranges_are_data(tmp_path):
    m = read_measurements(_write(tmp_path, "m.csv", "time,tag,anchor,range\n0,T,1,-0.3\n"))
    assert m["range"].iloc[0] == -0.3


def test_to_epochs_pivot_and_duplicates(tmp_path):
    a = read_anchors(_write(tmp_path, "a.csv", ANCHORS))
    m = read_measurements(_write(tmp_path, "m.csv", MEAS), a)
    e = to_epochs(m, a["anchor"])
    assert e.anchor_ids == ("1", "2", "B3")
    np.testing.assert_array_equal(e.time, [0, 0, 1, 1.5])
    assert list(e.tag) == ["S1", "S2", "S1", "S2"]
    expect = np.array(
        [[-60, -71, np.nan], [-50, np.nan, np.nan], [-61, np.nan, np.nan],
         [np.nan, np.nan, -65]]
    )
    np.testing.assert_array_equal(e.values, expect)
    assert e.n_duplicates == 1
    np.testing.assert_array_equal(e.line, [2, 5, 6, 7])
    with pytest.raises(InputError, match="unknown anchor id 'B3'"):
        to_epochs(m, ["1", "2"])


@settings(max_examples=40, deadline=None)
@given(
    rows=st.lists(
        st.tuples(st.integers(0, 6), st.sampled_from(["a", "b"]), st.integers(0, 3),
                  st.floats(-90, -30)),
        min_size=1, max_size=60,
    )
)
def test_to_epochs_matches_pandas_pivot(rows):
    df = pd.DataFrame(rows, columns=["time", "tag", "anchor", "rssi"])
    df["time"] = df["time"].astype(float)
    df["anchor"] = df["anchor"].astype(str)
    ids = ["0", "1", "2", "3"]
    e = to_epochs(df, ids, "rssi")
    ref = df.pivot_table(index=["time", "tag"], columns="anchor", values="rssi",
                         aggfunc="mean").reindex(columns=ids)
    np.testing.assert_allclose(e.values, ref.to_numpy(), rtol=1e-12, equal_nan=True)
    np.testing.assert_array_equal(e.time, ref.index.get_level_values(0))


def _sorted_measurements(n_epochs=200, seed=0):
    rng = np.random.default_rng(seed)
    rows = []
    for k in range(n_epochs):
        for tag in ("A", "B"):
            for anc in rng.permutation(4)[: rng.integers(1, 5)]:
                rows.append((0.5 * k, tag, str(anc), rng.normal(-60, 3)))
    df = pd.DataFrame(rows, columns=["time", "tag", "anchor", "rssi"])
    return df.sample(frac=1, random_state=1).sort_values("time", kind="stable")


@pytest.mark.parametrize("ext", ["csv", "parquet"])
@pytest.mark.parametrize("chunk_rows", [1, 7, 64, 10_000])
def test_iter_measurements_never_splits_an_epoch(tmp_path, ext, chunk_rows):
    df = _sorted_measurements(n_epochs=12 if chunk_rows < 10 else 200)
    p = write_table(df, tmp_path / f"m.{ext}")
    chunks = list(iter_measurements(p, chunk_rows=chunk_rows))
    assert sum(len(c) for c in chunks) == len(df)
    keys = [set(zip(c["time"], c["tag"])) for c in chunks]
    for i in range(len(keys)):
        for j in range(i + 1, len(keys)):
            assert not keys[i] & keys[j]
    whole = to_epochs(read_measurements(p), ["0", "1", "2", "3"])
    streamed = list(iter_epochs(p, ["0", "1", "2", "3"], chunk_rows=chunk_rows))
    np.testing.assert_array_equal(np.concatenate([e.values for e in streamed]), whole.values)
    np.testing.assert_array_equal(np.concatenate([e.line for e in streamed]), whole.line)


def test_iter_measurements_detects_unsorted_time(tmp_path):
    p = _write(tmp_path, "m.csv", "time,tag,anchor,rssi\n0,A,1,-1\n2,A,1,-1\n1,A,1,-1\n")
    with pytest.raises(InputError, match="sorted by time") as ei:
        list(iter_measurements(p, chunk_rows=1))
    assert ei.value.line == 4


def test_iter_measurements_unknown_anchor_and_empty(tmp_path):
    p = _write(tmp_path, "m.csv", "time,tag,anchor,rssi\n0,A,1,-1\n1,A,7,-1\n")
    with pytest.raises(InputError, match="unknown anchor") as ei:
        list(iter_measurements(p, chunk_rows=1, anchors=["1"]))
    assert ei.value.line == 3
    with pytest.raises(InputError, match="no data rows"):
        list(iter_measurements(_write(tmp_path, "e.csv", "time,tag,anchor,rssi\n")))


def test_survey_truth_positions(tmp_path):
    s = read_survey(_write(tmp_path, "s.csv", "anchor,distance,rssi\n1,1,-40\n1,2,-46\n"))
    assert s.attrs["value"] == "rssi"
    with pytest.raises(InputError, match="must be positive") as ei:
        read_survey(_write(tmp_path, "s.csv", "anchor,distance,rssi\n1,1,-40\n1,0,-46\n"))
    assert ei.value.line == 3
    r = read_survey(_write(tmp_path, "r.csv", "anchor,distance,range\n1,0,0.2\n"))
    assert r.attrs["value"] == "range"
    t = read_truth(_write(tmp_path, "t.csv", "time,tag,x,y,z\n0,A,1,2,3\n"))
    assert t["z"].iloc[0] == 3.0
    p = read_positions(_write(tmp_path, "p.csv", "time,tag,x,y\n0,A,,\n1,A,1,2\n"))
    assert np.isnan(p["x"].iloc[0]) and list(p["status"]) == ["ok", "ok"]


def test_positions_frame_and_writer_round_trip(tmp_path):
    n = 3
    sol = Solution(
        position=np.array([[1.0, 2.0], [np.nan, np.nan], [3.0, 4.0]]),
        covariance=np.zeros((n, 2, 2)),
        residuals=np.zeros((n, 3)),
        weights=np.ones((n, 3)),
        excluded=np.array([[False, True, False], [False, False, False], [True, True, False]]),
        sigma0=np.array([0.5, np.nan, 0.1]),
        iterations=np.array([3, 0, 4]),
        converged=np.array([True, False, True]),
        status=np.array(["ok", "insufficient_anchors", "fault_excluded"], dtype=object),
        n_used=np.array([2, 1, 1]),
        method="igg",
    )
    f = positions_frame(sol, np.array([0.0, 1.0, 2.0]), ["A", "A", "A"], ["a1", "a2", "a3"])
    assert list(f["excluded"]) == ["a2", "", "a1;a2"]
    out = write_positions(f, tmp_path / "p.csv")
    back = read_positions(out)
    assert list(back.columns[:9]) == [
        "time", "tag", "x", "y", "method", "status", "n_used", "sigma0", "excluded"
    ]
    np.testing.assert_array_equal(back["x"].to_numpy(), [1.0, np.nan, 3.0])
    assert list(back["status"]) == ["ok", "insufficient_anchors", "fault_excluded"]
    assert list(back["excluded"]) == ["a2", "", "a1;a2"]
    with pytest.raises(ValueError, match="missing column"):
        write_positions(f.drop(columns="status"), tmp_path / "q.csv")


@pytest.mark.parametrize(
    ("text", "line", "words"),
    [
        ("anchor,x,y\n1,0,0,7\n2,1,1\n", 2, "expected 3 fields, found 4"),  # not an index
        ("anchor,x,y\n1,0,0\n2,1\n", 3, "column 'y': missing"),  # short row: empty field
        ("anchor,x,y\n1,0,0\n2,1,1,9\n", 3, "expected 3 fields, found 4"),
        # a short row before a long one: the first to fix (pandas named the long one)
        ("anchor,x,y\n1,0,0\n2,1\n3,1,1,9\n", 3, "expected 3 fields, found 2"),
    ],
)
def test_ragged_rows_are_errors_not_shifted_columns(tmp_path, text, line, words):
    p = _write(tmp_path, "a.csv", text)
    with pytest.raises(InputError, match=words) as ei:
        read_anchors(p)
    assert ei.value.line == line
    m = _write(tmp_path, "m.csv", "time,tag,anchor,rssi\n0,A,1,-50,3\n1,A,1,-50\n")
    with pytest.raises(InputError, match="expected 4 fields, found 5") as ei:
        list(iter_measurements(m, chunk_rows=1))
    assert ei.value.line == 2
    m = _write(tmp_path, "m.csv", "time,tag,anchor,rssi\n0,A,1,-50\n1,A,1\n2,A,1,-50,3\n")
    with pytest.raises(InputError, match="expected 4 fields, found 3") as ei:
        list(iter_measurements(m))
    assert ei.value.line == 3


@pytest.mark.parametrize("ext", ["csv", "parquet"])
def test_positions_writer_chunks_equal_one_write(tmp_path, ext):
    f = pd.DataFrame({
        "time": np.arange(7.0), "tag": "T", "x": np.r_[1.0, np.nan, 3, 4, 5, 6, 7], "y": 0.5,
        "method": "igg", "status": "ok", "n_used": 4, "sigma0": 0.1, "excluded": "",
        "iterations": 3,
    })
    with PositionsWriter(tmp_path / f"p.{ext}") as w:
        for part in (f.iloc[:3], f.iloc[3:4], f.iloc[4:]):
            w.write(part)
    assert w.n_rows == 7
    write_positions(f, tmp_path / f"q.{ext}")
    a = read_positions(tmp_path / f"p.{ext}")
    b = read_positions(tmp_path / f"q.{ext}")
    pd.testing.assert_frame_equal(a.reset_index(drop=True), b.reset_index(drop=True))
    with pytest.raises(ValueError, match="first chunk"):
        with PositionsWriter(tmp_path / f"r.{ext}") as w:
            w.write(f)
            w.write(f.drop(columns="iterations"))


def test_ids_may_be_na_words_but_numbers_may_not(tmp_path):
    a = read_anchors(_write(tmp_path, "a.csv", "anchor,x,y\nNA,0,0\nNone,1,1\n"))
    assert list(a["anchor"]) == ["NA", "None"]
    with pytest.raises(InputError, match="'y': missing or NaN") as ei:
        read_anchors(_write(tmp_path, "b.csv", "anchor,x,y\nNA,0,NA\n"))
    assert ei.value.line == 2
    with pytest.raises(InputError, match="empty id"):
        read_anchors(_write(tmp_path, "c.csv", "anchor,x,y\n,0,0\n"))
    m = read_measurements(_write(tmp_path, "m.csv", " time, tag, anchor, rssi\n0, A, NA, -50\n"))
    assert list(m.columns) == ["time", "tag", "anchor", "rssi"] and m["anchor"].iloc[0] == "NA"


def test_parquet_is_streamed_without_pre_buffering(tmp_path, monkeypatch):
    """The streamed Parquet readers (measurements, Dask partitions) open their files with
    ``pre_buffer=False``.  Measured: pyarrow's default pre-buffering keeps the pre-read
    column chunks of every row group iterated so far, so a reader's resident memory grew
    ~8 MiB per million rows (147 -> 615 MiB over 60 M rows; flat at ~150 MiB without), and
    a 100 M-row tag partition pushed both 2 GiB Dask workers of the benchmark over their
    limit.  Every chunk still arrives, in order."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    from robustloc.engines.dataset import Partition, _parquet_file
    from robustloc.io.tables import iter_measurements

    n = 40_000
    df = pd.DataFrame({"time": np.repeat(np.arange(n // 4, dtype=float), 4), "tag": "T1",
                       "anchor": np.tile(["A0", "A1", "A2", "A3"], n // 4),
                       "range": np.linspace(1.0, 9.0, n)})
    path = tmp_path / "m.parquet"
    pq.write_table(pa.Table.from_pandas(df, preserve_index=False), path, row_group_size=3_000)
    opened: list[object] = []
    real = pq.ParquetFile

    class Recording(real):  # type: ignore[misc, valid-type]
        def __init__(self, *a, **kw):
            opened.append(kw.get("pre_buffer", "default"))
            super().__init__(*a, **kw)

    monkeypatch.setattr(pq, "ParquetFile", Recording)
    chunks = list(iter_measurements(path, chunk_rows=5_000))
    assert sum(len(c) for c in chunks) == n
    assert np.array_equal(np.concatenate([c["range"].to_numpy() for c in chunks]),
                          df["range"].to_numpy())
    _parquet_file(Partition(str(path)))
    assert opened and all(v is False for v in opened), opened


def test_epochs_take_and_concat_keep_every_row_field_together():
    """``Epochs.take`` reorders (or slices) time, tag, values, line and n_invalid alike;
    ``Epochs.concat`` joins blocks in order, sums ``n_duplicates`` and keeps ``resorted``
    if any block has it.  Checked against the frame the epochs came from."""
    import numpy as np

    from robustloc.io.tables import Epochs, to_epochs

    log = pd.DataFrame({"time": [0.0, 0.0, 1.0, 1.0, 2.0, 2.0, 2.0],
                        "tag": ["a", "a", "b", "b", "a", "a", "a"],
                        "anchor": ["x", "y", "x", "y", "x", "y", "y"],
                        "range": [1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 8.0]})
    ep = to_epochs(log, ["x", "y"])
    assert ep.n_duplicates == 1 and ep.values[2, 1] == 7.0  # (6 + 8) / 2
    k = np.array([2, 0, 1])
    got = ep.take(k)
    np.testing.assert_array_equal(got.time, [2.0, 0.0, 1.0])
    np.testing.assert_array_equal(got.tag, ["a", "a", "b"])
    np.testing.assert_array_equal(got.values, [[5.0, 7.0], [1.0, 2.0], [3.0, 4.0]])
    np.testing.assert_array_equal(got.line, ep.line[k])
    np.testing.assert_array_equal(got.n_invalid, ep.n_invalid[k])
    head, tail = ep.take(slice(0, 1)), ep.take(slice(1, 3))
    from dataclasses import replace

    both = Epochs.concat([head, replace(tail, n_duplicates=2, resorted=True)])
    np.testing.assert_array_equal(both.values, ep.values)
    np.testing.assert_array_equal(both.time, ep.time)
    assert both.n_duplicates == 3 and both.resorted
    assert Epochs.concat([ep]) is ep
    with pytest.raises(ValueError, match="no epoch blocks"):
        Epochs.concat([])
