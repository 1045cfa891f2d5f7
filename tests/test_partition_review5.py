"""`partition`: the commands review's defects, each failing on the code before its fix.

* A folder of an RSSI file and a range file was read as one table: the range file got
  the RSSI column, all missing, and the error named the folder (``gl3: column 'rssi':
  153 missing ...``).  It names the file and line 1 and says which value column it has.
* A dataset by tag could not be read by pandas or pyarrow as a whole (``tag`` is both
  the folder key and a column): the documented readers, without partitioning, read every
  layout.
"""

from __future__ import annotations

import pandas as pd
import pytest

pytest.importorskip("duckdb")

from robustloc.cli import main  # noqa: E402


def _log(value: str, n: int = 12) -> pd.DataFrame:
    return pd.DataFrame({"time": [i * 0.5 for i in range(n)],
                         "tag": [f"T{i % 2}" for i in range(n)],
                         "anchor": [f"A{i % 3}" for i in range(n)],
                         value: [-60.0 + i if value == "rssi" else 3.0 + i for i in range(n)]})


@pytest.mark.parametrize("fmt", ["csv", "parquet"])
@pytest.mark.parametrize("method", ["duckdb", "dask"])  # (dask: refused before a cluster)
@pytest.mark.parametrize("first, second", [("rssi", "range"), ("range", "rssi"),
                                           ("rssi", None)])
def test_a_folder_mixing_value_columns_names_the_file(tmp_path, capsys, fmt, method,
                                                      first, second):
    src = tmp_path / "in"
    src.mkdir()
    a, b = _log(first), _log(second or "x")
    if second is None:
        b = b.drop(columns="x")
    for name, frame in (("a", a), ("c", b)):
        path = src / f"{name}.{fmt}"
        frame.to_csv(path, index=False) if fmt == "csv" else frame.to_parquet(path)
    out = tmp_path / "ds"
    code = main(["partition", str(src), "-o", str(out), "--by", "tag", "--method", method,
                 "-q"])
    err = capsys.readouterr().err
    has = f"'{second}'" if second else "no 'rssi' or 'range'"
    assert code == 2 and err.startswith(f"error: {src / f'c.{fmt}'}:1: has {has}, not "
                                        f"'{first}' as {src / f'a.{fmt}'}"), err
    assert "Traceback" not in err and not out.exists()


@pytest.mark.parametrize("fmt", ["csv", "parquet"])
def test_a_folder_of_one_kind_is_partitioned(tmp_path, fmt):
    """Files of one value column (with other columns differing) are still one dataset."""
    src = tmp_path / "in"
    src.mkdir()
    for name, frame in (("a", _log("range")), ("c", _log("range").assign(extra=1.0))):
        path = src / f"{name}.{fmt}"
        frame.to_csv(path, index=False) if fmt == "csv" else frame.to_parquet(path)
    out = tmp_path / "ds"
    assert main(["partition", str(src), "-o", str(out), "--by", "tag", "-q"]) == 0
    assert sum(len(pd.read_parquet(f)) for f in out.rglob("*.parquet")) == 24


@pytest.mark.parametrize("layout", [["--by", "tag"], ["--by", "tag", "--buckets", "2"],
                                    ["--by", "time", "--span", "2"]])
def test_the_documented_readers_read_every_layout(tmp_path, layout):
    """docs/dask.md, formats.md and --help: pandas and pyarrow read a partitioned dataset
    without partitioning (read_parquet(DIR) stopped on a tag= tree with "Field tag has
    incompatible types"), DuckDB with hive_partitioning=false; each gives the input's
    rows and columns as written."""
    import duckdb
    import pyarrow.dataset as pads

    src = tmp_path / "m.csv"
    log = _log("rssi", 40)
    log.to_csv(src, index=False)
    out = tmp_path / "ds"
    assert main(["partition", str(src), "-o", str(out), "-q", *layout]) == 0
    key = ["time", "tag", "anchor"]
    want = log.sort_values(key, ignore_index=True)
    frames = [
        pd.read_parquet(out, partitioning=None),
        pads.dataset(out, format="parquet", partitioning=None).to_table().to_pandas(),
        duckdb.sql(f"SELECT * FROM read_parquet('{out}/**/*.parquet', "
                   "hive_partitioning=false)").df(),
    ]
    for got in frames:
        got = got.sort_values(key, ignore_index=True)
        assert list(got.columns) == list(log.columns)
        pd.testing.assert_frame_equal(got.astype({c: str for c in ("tag", "anchor")}), want,
                                      check_dtype=False)


def test_reading_a_tag_tree_with_its_folder_keys_is_what_the_docs_warn_of(tmp_path):
    """The failure the documentation steers around (pyarrow's; a guard that the advice is
    still needed and its quoted message right)."""
    import pyarrow as pa

    src = tmp_path / "m.csv"
    _log("rssi").to_csv(src, index=False)
    out = tmp_path / "ds"
    assert main(["partition", str(src), "-o", str(out), "-q", "--by", "tag"]) == 0
    with pytest.raises(pa.ArrowTypeError, match="Field tag has incompatible types"):
        pd.read_parquet(out)


def test_a_log_named_txt_is_partitioned_and_notes_are_named(tmp_path, capsys):
    """A folder's log named ``.txt`` is a table like any other (it was left out without
    a word, its rows missing from the dataset: the dask fixer); notes and metadata
    (``.md``, ``.json``) are left out, and the command says which."""
    src = tmp_path / "in"
    src.mkdir()
    a, b = _log("rssi"), _log("rssi")
    b["time"] += 100.0
    a.to_csv(src / "a.csv", index=False)
    b.to_csv(src / "b.txt", index=False)
    (src / "README.md").write_text("# a site's logs\n")
    (src / "meta.json").write_text("{}\n")
    out = tmp_path / "ds"
    assert main(["partition", str(src), "-o", str(out), "--by", "time", "-q"]) == 0
    err = capsys.readouterr().err
    assert "left out 2 file(s) that are notes" in err
    assert "README.md" in err and "meta.json" in err
    back = pd.read_parquet(out, partitioning=None)
    assert len(back) == len(a) + len(b)
    # a folder of notes only: the input's error, not a traceback
    notes = tmp_path / "notes"
    notes.mkdir()
    (notes / "README.md").write_text("# nothing yet\n")
    assert main(["partition", str(notes), "-o", str(tmp_path / "ds2"), "--by", "tag",
                 "-q"]) == 2
    assert "no table in this input, only notes" in capsys.readouterr().err
