"""Dataset discovery (the dask review): which files are partitions, and hive folders.

* A file of a Parquet dataset that is not Parquet (a CSV beside a Parquet file) was left
  out without a word (exit 0, 1 914 of 7 800 epochs); Parquet files named as Hive names
  them (``000000_0``) or ``.parq`` were left out too, and ``partition`` said such a
  folder "mixes CSV and Parquet files".  A file is Parquet by its first bytes (or its
  name); any other non-hidden file is refused by name.
* dask's ``to_parquet(partition_on=["tag"])`` does not escape a tag's folder name: tag
  ``a/b`` was read as tag ``a`` (two walks merged into one track, exit 0), and folders
  ``tag=A`` and ``tag=%41`` were both read as tag ``A``.  Both are refused when the
  files lack the tag column; pyarrow's escaped trees (``tag=a%2Fb``) still read.

Discovery alone shows each: no cluster is started.
"""

from __future__ import annotations

import os

import pandas as pd
import pytest

from robustloc.cli import main
from robustloc.engines.dataset import discover, inspect
from robustloc.errors import InputError

ANCHORS = "anchor,x,y\na,0,0\nb,10,0\nc,10,10\nd,0,10\n"


def _epochs(t0: float = 0.0, n: int = 3, tag: str | None = "T1") -> pd.DataFrame:
    """``n`` epochs of four ranges; without a ``tag`` column when ``tag`` is None (as
    dask's ``partition_on`` writes a file)."""
    df = pd.DataFrame({"time": [t0 + i for i in range(n) for _ in range(4)],
                       "tag": tag, "anchor": list("abcd") * n,
                       "range": [5.0, 8.1, 8.1, 5.0] * n})
    return df.drop(columns="tag") if tag is None else df


def _anchors(tmp_path) -> str:
    a = tmp_path / "anchors.csv"
    a.write_text(ANCHORS)
    return str(a)


# --------------------------------------------------------------------------------------
# bug 1: every non-hidden file of a dataset is a partition, Parquet by its bytes
# --------------------------------------------------------------------------------------


def test_parquet_files_named_as_hive_names_them_are_partitions(tmp_path):
    ds = tmp_path / "ds"
    ds.mkdir()
    names = ["000000_0", "000001_0.parq", "000002_0.PARQUET", "000003_0.parquet"]
    for i, name in enumerate(names):
        _epochs(t0=10.0 * i).to_parquet(ds / name, index=False)
    (ds / "_notes.csv").write_text("a side file\n")  # hidden names: not data
    (ds / ".crc").write_text("x")
    parts = discover(ds)
    assert sorted(os.path.basename(p.path) for p in parts) == sorted(names)
    assert sum(inspect(p).n_rows for p in parts) == 4 * 12


@pytest.mark.parametrize("command", ["locate", "track"])
def test_a_csv_beside_parquet_files_is_refused_not_left_out(tmp_path, capsys, command):
    ds = tmp_path / "ds"
    ds.mkdir()
    _epochs().to_parquet(ds / "p0.parquet", index=False)
    _epochs(t0=10.0).to_csv(ds / "p1.csv", index=False)  # most of the rows
    with pytest.raises(InputError, match="not a Parquet file") as exc:
        discover(ds)
    assert exc.value.path == str(ds / "p1.csv")
    out = tmp_path / "out"
    # refused at discovery, before a cluster starts
    assert main([command, str(ds), "--anchors", _anchors(tmp_path), "-o", str(out),
                 "--engine", "dask", "--workers", "1", "-q"]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"error: {ds / 'p1.csv'}: not a Parquet file"), err
    assert "robustloc partition" in err and "'_' or '.'" in err
    assert "Traceback" not in err and not out.exists()


def test_one_csv_file_for_the_dask_engine_is_refused_by_name(tmp_path):
    f = tmp_path / "log.csv"
    _epochs().to_csv(f, index=False)
    with pytest.raises(InputError, match="without --engine dask") as exc:
        discover(f)
    assert exc.value.path == str(f)


def test_partition_reads_hive_named_parquet_and_names_the_file_of_another_kind(
        tmp_path, capsys):
    pytest.importorskip("duckdb")
    src = tmp_path / "in"
    src.mkdir()
    _epochs().to_parquet(src / "000000_0", index=False)
    _epochs(t0=10.0).to_parquet(src / "000001_0.parq", index=False)
    out = tmp_path / "by_tag"
    assert main(["partition", str(src), "-o", str(out), "--by", "tag", "-q"]) == 0
    assert sum(len(pd.read_parquet(p.path)) for p in discover(out)) == 24
    capsys.readouterr()
    (src / "extra.csv").write_text(_epochs(t0=20.0).to_csv(index=False))
    assert main(["partition", str(src), "-o", str(tmp_path / "o2"), "--by", "tag",
                 "-q"]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"error: {src}: input mixes Parquet files and others "
                          f"({src / 'extra.csv'} is not Parquet"), err


# --------------------------------------------------------------------------------------
# bug 2: hive folders of an id that dask wrote unescaped
# --------------------------------------------------------------------------------------


def _dask_tree(path, tags: list[str]) -> None:
    """Two walks under ``tags``, written by dask's ``partition_on`` (which drops the tag
    from the files and names the folders by the raw tags); dask's local threads, no
    cluster."""
    dd = pytest.importorskip("dask.dataframe")
    d = pd.concat([_epochs(t0=10.0 * i, tag=t) for i, t in enumerate(tags)])
    dd.from_pandas(d, npartitions=1, sort=False).to_parquet(
        str(path), partition_on=["tag"], write_index=False)


def test_a_tag_holding_a_slash_under_dask_partition_on_is_refused(tmp_path, capsys):
    ds = tmp_path / "ds"
    _dask_tree(ds, ["a", "a/b"])
    nested = [p for p in (ds / "tag=a" / "b").iterdir() if p.suffix == ".parquet"]
    assert len(nested) == 1  # dask's layout: tag=a/b/part.0.parquet
    with pytest.raises(InputError, match="not key=value") as exc:
        discover(ds)
    assert exc.value.path == str(nested[0])
    assert "'a/b'" in exc.value.message and "robustloc partition" in exc.value.message
    # the commands refuse it before a cluster starts (it was one track of both walks)
    out = tmp_path / "out"
    assert main(["track", str(ds), "--anchors", _anchors(tmp_path), "-o", str(out),
                 "--engine", "dask", "--workers", "1", "-q"]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"error: {nested[0]}: folder 'b' below 'tag=a' is not "
                          "key=value"), err
    assert not out.exists()
    assert main(["partition", str(ds), "-o", str(out), "--by", "tag", "-q"]) == 2
    assert "is not key=value" in capsys.readouterr().err


def test_a_folder_below_a_tag_is_fine_when_the_files_hold_the_tag(tmp_path):
    ds = tmp_path / "ds"
    (ds / "tag=a" / "b").mkdir(parents=True)
    _epochs(tag="a").to_parquet(ds / "tag=a" / "p.parquet", index=False)
    _epochs(tag="a/b").to_parquet(ds / "tag=a" / "b" / "p.parquet", index=False)
    assert sorted(t for p in discover(ds) for t in inspect(p).tags) == ["a", "a/b"]


def test_two_spellings_of_one_tag_folder_are_refused_as_ambiguous(tmp_path):
    ds = tmp_path / "ds"
    _dask_tree(ds, ["A", "%41"])  # folders tag=A and tag=%41, both unescaping to 'A'
    with pytest.raises(InputError, match="both read as tag 'A'") as exc:
        discover(ds)
    assert exc.value.path == str(ds / "tag=A")
    assert "'tag=%41' and 'tag=A'" in exc.value.message


def test_pyarrows_escaped_tree_is_read_as_its_tags(tmp_path):
    """pyarrow escapes a folder's value as in a URL (``tag=a%2Fb``, ``tag=%2541``):
    those read back as the tags written."""
    pa = pytest.importorskip("pyarrow")
    import pyarrow.parquet as pq

    tags = ["a", "a/b", "A", "%41"]
    d = pd.concat([_epochs(t0=10.0 * i, tag=t) for i, t in enumerate(tags)])
    pq.write_to_dataset(pa.Table.from_pandas(d, preserve_index=False), str(tmp_path / "ds"),
                        partition_cols=["tag"])
    assert {p.name for p in (tmp_path / "ds").iterdir()} >= {"tag=a%2Fb", "tag=%2541"}
    parts = discover(tmp_path / "ds")
    assert sorted(t for p in parts for t in inspect(p).tags) == sorted(tags)
