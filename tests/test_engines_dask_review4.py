"""The Dask engine review of 2026-12-07: partitions behind symbolic links (followed, a
link loop walked once, a link to nothing refused), ..."""

from __future__ import annotations

import os

import pandas as pd
import pytest

pytest.importorskip("distributed")

from robustloc.cli import main  # noqa: E402
from robustloc.engines.dataset import discover  # noqa: E402
from robustloc.errors import InputError  # noqa: E402

ANCHORS = "anchor,x,y\na,0,0\nb,10,0\nc,10,10\nd,0,10\n"


def _epochs(path, tag: str, t0: float = 0.0, n: int = 3) -> None:
    pd.DataFrame({"time": [t0 + i for i in range(n) for _ in range(4)],
                  "tag": tag, "anchor": list("abcd") * n,
                  "range": [5.0, 8.1, 8.1, 5.0] * n}).to_parquet(path, index=False)


# --------------------------------------------------------------------------------------
# symbolic links
# --------------------------------------------------------------------------------------


def test_partitions_behind_linked_folders_are_found_and_a_loop_ends(tmp_path):
    real = tmp_path / "real"
    (real / "tag=T1").mkdir(parents=True)
    _epochs(real / "tag=T1" / "part-0.parquet", "T1")
    ds = tmp_path / "ds"
    (ds / "tag=T2").mkdir(parents=True)
    _epochs(ds / "tag=T2" / "part-0.parquet", "T2")
    os.symlink(real / "tag=T1", ds / "tag=T1")  # a linked folder
    os.symlink(real / "tag=T1" / "part-0.parquet", ds / "tag=T2" / "part-1.parquet")
    os.symlink(ds, ds / "tag=T2" / "loop")  # a link back up: walked once
    parts = discover(ds)
    assert [os.path.relpath(p.path, ds) for p in parts] == [
        os.path.join("tag=T1", "part-0.parquet"), os.path.join("tag=T2", "part-0.parquet"),
        os.path.join("tag=T2", "part-1.parquet")]
    assert parts[0].keys == (("tag", "T1"),)
    # the same through a glob
    assert len(discover(str(tmp_path / "d*"))) == 3


def test_a_link_to_nothing_is_refused(tmp_path, capsys):
    ds = tmp_path / "ds"
    ds.mkdir()
    _epochs(ds / "p0.parquet", "T1")
    os.symlink(tmp_path / "nowhere" / "part-0.parquet", ds / "p1.parquet")
    with pytest.raises(InputError, match="broken link"):
        discover(ds)
    with pytest.raises(InputError, match="broken link"):
        discover(ds / "p1.parquet")
    a = tmp_path / "a.csv"
    a.write_text(ANCHORS)
    # refused before any cluster starts
    assert main(["locate", str(ds), "--anchors", str(a), "-o", str(tmp_path / "o"),
                 "--engine", "dask", "--workers", "1"]) == 2
    assert capsys.readouterr().err.strip() == f"error: {ds / 'p1.parquet'}: broken link"
    assert not (tmp_path / "o").exists()
    assert main(["partition", str(ds), "-o", str(tmp_path / "o2"), "--by", "tag"]) == 2
    assert capsys.readouterr().err.strip() == f"error: {ds / 'p1.parquet'}: broken link"
