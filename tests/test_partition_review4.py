"""`partition`'s defects found by the partition review of 2026-12-07 (second pass), each
failing on the code before its fix:

* ``--method duckdb`` typed a CSV's extra columns from DuckDB's sample of the file: 1.5
  on line 55 002 of an integer column was written 2, two 20-digit ids one double,
  ``TRUE`` a boolean, ``1e3`` 1000.0 (exit 0); a word there stopped the run with
  DuckDB's "Conversion Error" (not ``FILE:LINE``), and ``--method dask`` with a
  traceback.
* ``--method dask`` made every integer column float64 (CSV and Parquet): ids and
  nanosecond stamps beyond 2**53 changed (1910 of 1917 stamps of a uwb-dwm1001 log).
* an input column named ``__key`` was replaced by the partition key (``--method
  duckdb``), one named ``time_bin``, ``tag_bucket`` or ``__robustloc_tag`` by the key or
  the raw tag (``--method dask``).
* partitioning a partitioned (hive) dataset added every folder key as a column: a stale
  ``time_bin`` of the earlier partitioning, and a column of that name in the files was
  hidden by its folder's value.  The rows are now the files' own, plus the ``tag`` and
  ``anchor`` of a file that lacks them from its path, as the commands' readers take them.
"""

from __future__ import annotations

import csv
import io
from pathlib import Path

import pandas as pd
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

pytest.importorskip("duckdb")

from robustloc.cli import main  # noqa: E402

#: Beyond DuckDB's sample of a CSV file (its type sniffing missed line 55 002).
LATE = 55_000
N_LATE = 60_000


def _rows(ds: Path) -> pa.Table:
    """Every row of a dataset as its files hold it (no hive keys), sorted by time."""
    tables = [pq.read_table(f, partitioning=None) for f in sorted(ds.rglob("*.parquet"))]
    t = pa.concat_tables(tables, promote_options="permissive")
    return t.sort_by([("time", "ascending"), ("anchor", "ascending")])


def _partition(src: Path, ds: Path, method: str, scheduler: str | None, *more: str) -> int:
    extra = ["--scheduler", scheduler] if method == "dask" else []
    return main(["partition", str(src), "-o", str(ds), "--method", method, "-q", *extra,
                 *more])


def _late_csv(path: Path, late: str) -> None:
    with open(path, "w") as fh:
        fh.write("time,tag,anchor,rssi,x\n")
        fh.writelines(f"{i * 0.01:.2f},T{i % 3},{i % 4},-60,{late if i == LATE else i}\n"
                      for i in range(N_LATE))


@pytest.fixture(params=["duckdb", "dask"])
def method(request) -> str:
    if request.param == "dask":
        pytest.importorskip("distributed")
    return request.param


@pytest.fixture
def sched(method, request) -> str | None:
    return request.getfixturevalue("scheduler") if method == "dask" else None


@pytest.mark.parametrize("late", ["1.5", "abc"])
def test_an_extra_csv_column_keeps_a_late_value_of_another_type(tmp_path, method, sched,
                                                                  late):
    src = tmp_path / "late.csv"
    _late_csv(src, late)
    assert _partition(src, tmp_path / "ds", method, sched, "--by", "tag") == 0
    t = _rows(tmp_path / "ds")
    assert t.num_rows == N_LATE
    x = t.column("x").to_pylist()
    assert x[LATE] == late and x[:3] == ["0", "1", "2"]


def test_extra_csv_columns_are_copied_value_for_value(tmp_path, method, sched):
    """Each extra field as written: 20-digit ids, TRUE, 1e3, 007, an empty field."""
    src = tmp_path / "m.csv"
    src.write_text("time,tag,anchor,rssi,imsi,flag,e,z\n"
                   "0,a,1,-50,18446744073709551616,TRUE,1e3,007\n"
                   "1,a,1,-50,18446744073709551617,false,2.50,\n"
                   "2,b,1,-50,12345678901234567890123,1,-0,x y\n")
    for by in ("tag", "time"):
        ds = tmp_path / f"ds-{by}"
        assert _partition(src, ds, method, sched, "--by", by) == 0
        t = _rows(ds)
        with open(src, newline="") as fh:
            want = list(csv.DictReader(fh))
        for c in ("imsi", "flag", "e", "z"):
            assert t.column(c).to_pylist() == [r[c] or None for r in want], (by, c)


def test_dask_keeps_each_parquet_column_in_its_type(tmp_path, scheduler):
    """Integers beyond 2**53 (one file without the column: missing there), booleans and
    timestamps as the DuckDB method and the input hold them."""
    src = tmp_path / "in"
    src.mkdir()
    stamps = [2**62 + 1, 2**62 + 3, 1_910_000_000_000_000_001]
    pd.DataFrame({"time": [0.0, 1.0, 2.0], "tag": ["T1", "T2", "T1"], "anchor": "A0",
                  "range": [5.0, 6.0, 7.0], "stamp": stamps, "ok": [True, False, True],
                  "at": pd.to_datetime(["2026-01-01 00:00:00.000000001"] * 3)}
                 ).to_parquet(src / "a.parquet", index=False)
    pd.DataFrame({"time": [3.0], "tag": ["T2"], "anchor": "A0", "range": [8.0],
                  "ok": [False]}).to_parquet(src / "b.parquet", index=False)
    got = {}
    for method in ("duckdb", "dask"):
        ds = tmp_path / f"ds-{method}"
        assert _partition(src, ds, method, scheduler if method == "dask" else None,
                          "--by", "tag") == 0
        got[method] = t = _rows(ds)
        assert t.column("stamp").to_pylist() == [*stamps, None], method
        assert t.schema.field("stamp").type == pa.int64(), method
        assert t.column("ok").to_pylist() == [True, False, True, False], method
        assert pa.types.is_timestamp(t.schema.field("at").type), method
    assert got["dask"].column("at").equals(got["duckdb"].column("at"))


def test_dask_keeps_integer_text_of_a_csv(tmp_path, scheduler):
    src = tmp_path / "m.csv"
    src.write_text("time,tag,anchor,range,stamp\n0,T,A3,5,1910000000000000001\n"
                   "1,T,A3,6,1910000000000000003\n")
    assert _partition(src, tmp_path / "ds", "dask", scheduler, "--by", "tag") == 0
    assert _rows(tmp_path / "ds").column("stamp").to_pylist() == [
        "1910000000000000001", "1910000000000000003"]


@pytest.mark.parametrize("by", [["--by", "time"], ["--by", "tag", "--buckets", "2"],
                                ["--by", "tag"]])
def test_input_columns_named_as_the_staged_key_are_kept(tmp_path, method, sched, by):
    names = ["__key", "time_bin", "tag_bucket", "__robustloc_tag", "__KEY_1"]
    src = tmp_path / "key.csv"
    src.write_text("time,tag,anchor,rssi," + ",".join(names) + "\n"
                   "0,a,1,-50,u1,b1,k1,r1,x1\n1,b,1,-51,u2,b2,k2,r2,x2\n")
    assert _partition(src, tmp_path / "ds", method, sched, *by) == 0
    t = _rows(tmp_path / "ds")
    assert sorted(t.column_names) == sorted(["time", "tag", "anchor", "rssi", *names])
    for c, v in zip(names, "ubkrx"):
        assert t.column(c).to_pylist() == [v + "1", v + "2"], c


@pytest.mark.parametrize("own", [False, True])
def test_a_partitioned_dataset_partitions_again_row_for_row(tmp_path, method, sched, own):
    """``own``: the files hold a column named ``time_bin`` too."""
    src = tmp_path / "m.csv"
    with open(src, "w") as fh:
        fh.write("time,tag,anchor,rssi" + (",time_bin" if own else "") + "\n")
        fh.writelines(f"{i},T{i % 3},{i % 4},-60" + (f",u{i}" if own else "") + "\n"
                      for i in range(300))
    cols = ["time", "tag", "anchor", "rssi"] + (["time_bin"] if own else [])
    assert _partition(src, tmp_path / "t1", "duckdb", None, "--by", "time", "--span",
                      "100") == 0
    steps = [("t1", "g", ["--by", "tag"]), ("g", "t2", ["--by", "time", "--span", "10"])]
    for a, b, by in steps:
        assert _partition(tmp_path / a, tmp_path / b, method, sched, *by) == 0
        t = _rows(tmp_path / b)
        assert sorted(t.column_names) == sorted(cols), (b, t.column_names)
        assert t.column("time").to_pylist() == list(range(300))
        if own:
            assert t.column("time_bin").to_pylist() == [f"u{i}" for i in range(300)], b


def test_ids_of_a_hive_path_fill_the_files_that_lack_them(tmp_path, method, sched):
    """A pandas ``partition_cols`` tree: ``day=/tag=/anchor=``, files without ``tag`` and
    ``anchor``: the ids from the path (text, ``007`` kept), the day not a column (the
    readers take only the ids from a path)."""
    src = tmp_path / "tree"
    pd.DataFrame({"time": [1.0, 2.0, 3.0], "day": ["d1", "d1", "d2"],
                  "tag": ["007", "7", "007"], "anchor": ["A1", "A2", "A1"],
                  "rssi": [-50.0, -51.0, -52.0]}
                 ).to_parquet(src, partition_cols=["day", "tag", "anchor"], index=False)
    assert _partition(src, tmp_path / "ds", method, sched, "--by", "tag") == 0
    t = _rows(tmp_path / "ds")
    assert sorted(t.column_names) == ["anchor", "rssi", "tag", "time"]
    assert t.column("tag").to_pylist() == ["007", "7", "007"]
    assert t.column("anchor").to_pylist() == ["A1", "A2", "A1"]


@pytest.mark.parametrize("tag", ["L" * 300, "/" * 84], ids=["300-bytes", "escaped"])
def test_a_tag_too_long_for_a_folder_is_named_by_its_line(tmp_path, method, sched, capsys,
                                                          tag):
    from robustloc.engines.partition import _name_max

    room = _name_max(tmp_path) - len("tag=")
    src = tmp_path / "long.csv"
    src.write_text(f"time,tag,anchor,rssi\n0,b,1,-50\n1,{'a' * room},1,-50\n"
                   f"2,{tag},1,-50\n3,{tag},1,-50\n")
    assert _partition(src, tmp_path / "ds", method, sched, "--by", "tag") == 2
    err = capsys.readouterr().err
    assert err.startswith(f"error: {src}:4: tag "), err
    assert "too long for a folder name" in err and "--buckets" in err
    assert "partial" not in err and not (tmp_path / "ds").exists()
    assert _partition(src, tmp_path / "ds", method, sched, "--by", "tag", "--buckets",
                      "2") == 0
    assert _rows(tmp_path / "ds").column("tag").to_pylist() == ["b", "a" * room, tag, tag]
    src.write_text(f"time,tag,anchor,rssi\n0,b,1,-50\n1,{'a' * room},1,-50\n")
    assert _partition(src, tmp_path / "ds2", method, sched, "--by", "tag") == 0


class _Terminal(io.StringIO):
    def isatty(self) -> bool:
        return True


def test_a_progress_bar_on_a_terminal_only_without_quiet(tmp_path, monkeypatch):
    src = tmp_path / "m.csv"
    src.write_text("time,tag,anchor,rssi\n" + "".join(f"{i},T{i % 3},A,-60\n"
                                                      for i in range(50)))
    for flags, shown in (([], True), (["-q"], False), (["--json"], False)):
        err = _Terminal()
        monkeypatch.setattr("sys.stderr", err)
        ds = tmp_path / f"ds{len(flags)}{shown}"
        assert main(["partition", str(src), "-o", str(ds), "--by", "tag", *flags]) == 0
        monkeypatch.undo()
        text = err.getvalue()
        for stage in ("checking", "writing", "sorting"):
            assert (f"partition, {stage}" in text) == shown, (flags, text)
        assert _rows(ds).num_rows == 50


def test_an_error_under_the_progress_bar_is_the_rows_line(tmp_path, monkeypatch):
    """The bar's queries run in a thread: DuckDB's error still reaches the reader's
    ``FILE:LINE`` (and nothing is written)."""
    src = tmp_path / "m.csv"
    src.write_text("time,tag,anchor,rssi\n0,T,A,-60\n1,T,A,-60\nabc,T,A,-60\n")
    err = _Terminal()
    monkeypatch.setattr("sys.stderr", err)
    rc = main(["partition", str(src), "-o", str(tmp_path / "ds"), "--by", "tag"])
    monkeypatch.undo()
    assert rc == 2 and f"error: {src}:4: column 'time'" in err.getvalue(), err.getvalue()
    assert not (tmp_path / "ds").exists()


def test_dask_keeps_a_parquet_column_named_with_spaces(tmp_path, scheduler):
    src = tmp_path / "sp.parquet"
    pd.DataFrame({"time": [0.0, 1.0], "tag": ["a", "b"], "anchor": "1",
                  "rssi": [-50.0, -51.0], " x ": [1, 2]}).to_parquet(src, index=False)
    for method in ("duckdb", "dask"):
        ds = tmp_path / f"ds-{method}"
        assert _partition(src, ds, method, scheduler if method == "dask" else None,
                          "--by", "tag") == 0
        assert _rows(ds).column(" x ").to_pylist() == [1, 2], method
