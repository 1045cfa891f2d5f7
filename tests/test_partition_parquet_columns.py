"""`partition` checks a Parquet input's columns as the commands' readers do (the input
review): a column named twice was written with the second renamed ``rssi_1`` (exit 0;
the same CSV header and ``locate`` on the file were refused), and an ``rssi`` of booleans
was partitioned (exit 0), refused only later by ``locate --engine dask``.  Both are now
refused at the input, with the readers' words, before anything is written (or a dask
cluster started)."""

from __future__ import annotations

import pytest

pa = pytest.importorskip("pyarrow")
pytest.importorskip("duckdb")

import pyarrow.parquet as pq  # noqa: E402

from robustloc.cli import main  # noqa: E402


def _table(names: list[str], last: list[object]) -> pa.Table:
    return pa.Table.from_arrays(
        [pa.array([0.0, 0.0, 0.0]), pa.array(["T"] * 3), pa.array(["1", "2", "3"]),
         pa.array([-60.0, -61.0, -62.0])][:len(names) - 1] + [pa.array(last)], names=names)


CASES = {
    "duplicate": (["time", "tag", "anchor", "rssi", "rssi"], [-10.0, -11.0, -12.0],
                  "duplicate column 'rssi' in the header"),
    "booleans": (["time", "tag", "anchor", "rssi"], [True, False, True],
                 "column 'rssi' holds booleans, expected numbers"),
}


@pytest.mark.parametrize("method", ["duckdb", "dask"])
@pytest.mark.parametrize("case", sorted(CASES))
def test_partition_refuses_what_the_readers_refuse_in_a_parquet_file(tmp_path, capsys,
                                                                     case, method):
    names, last, said = CASES[case]
    src = tmp_path / "in.parquet"
    pq.write_table(_table(names, last), src)
    out = tmp_path / "ds"
    code = main(["partition", str(src), "-o", str(out), "--by", "tag", "--method", method,
                 "-q"])
    err = capsys.readouterr().err
    assert code == 2 and err.strip() == f"error: {src}:1: {said}", err
    assert not out.exists()
    # the same words as the single-file reader's
    a = tmp_path / "anchors.csv"
    a.write_text("anchor,x,y\n1,0,0\n2,10,0\n3,0,10\n")
    assert main(["locate", str(src), "--anchors", str(a), "-o",
                 str(tmp_path / "p.csv"), "-q"]) == 2
    assert capsys.readouterr().err.strip() == f"error: {src}:1: {said}"


def test_a_boolean_time_is_refused_in_a_folder_of_parquet_files(tmp_path, capsys):
    src = tmp_path / "in"
    src.mkdir()
    good = _table(["time", "tag", "anchor", "rssi"], [-60.0, -61.0, -62.0])
    pq.write_table(good, src / "a.parquet")
    pq.write_table(good.set_column(0, "time", pa.array([True, True, False])),
                   src / "b.parquet")
    assert main(["partition", str(src), "-o", str(tmp_path / "ds"), "--by", "time",
                 "-q"]) == 2
    assert capsys.readouterr().err.strip() == (
        f"error: {src / 'b.parquet'}:1: column 'time' holds booleans, expected numbers")
