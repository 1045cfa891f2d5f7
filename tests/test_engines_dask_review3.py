"""The Dask engine review of 2026-12-06: a previous dataset set aside under a name the
orphan sweep knows, an empty dataset's error with a line, a text file's name refused as
a dataset's folder."""

from __future__ import annotations

import os

import pandas as pd
import pytest

pytest.importorskip("distributed")

from robustloc.cli import main  # noqa: E402


def test_the_previous_dataset_is_set_aside_under_a_swept_name(tmp_path, monkeypatch):
    """The old dataset was renamed to ``.NAME.old-XXXXXXXX``: a run killed between the
    two renames left it for good (no process id: the sweep keeps such names)."""
    from robustloc.engines import dask as eng
    from robustloc.io.atomic import _HOST, sweep_orphans

    out = tmp_path / "ds"
    out.mkdir()
    (out / eng.META_FILE).write_text("{}\n")
    d = eng.DatasetOutput(str(out), [])
    monkeypatch.setattr(eng.shutil, "rmtree", lambda *a, **k: None)  # killed before it
    d.commit({"kind": "test"})
    left = [p.name for p in tmp_path.iterdir() if p.name.startswith(".ds.old-")]
    assert len(left) == 1
    assert left[0].startswith(f".ds.old-{_HOST}-{os.getpid()}-")
    monkeypatch.undo()
    # the name of a dead process's run: swept once the dataset exists again
    dead = tmp_path / left[0].replace(f"-{os.getpid()}-", "-999999999-")
    (tmp_path / left[0]).rename(dead)
    assert sweep_orphans(tmp_path, "ds") == 1
    assert not dead.exists() and (out / eng.META_FILE).exists()


@pytest.mark.parametrize("name", ["positions.csv", "p.CSV.gz", "p.txt"])
def test_a_text_files_name_is_refused_as_a_dataset(tmp_path, capsys, name):
    a = tmp_path / "a.csv"
    a.write_text("anchor,x,y\na,0,0\nb,10,0\nc,10,10\nd,0,10\n")
    m = tmp_path / "m"
    m.mkdir()
    pd.DataFrame({"time": [0.0] * 4, "tag": "T", "anchor": list("abcd"),
                  "range": [5.0, 8.1, 8.1, 5.0]}).to_parquet(m / "p0.parquet", index=False)
    assert main(["locate", str(m), "--anchors", str(a), "-o", str(tmp_path / name),
                 "--engine", "dask", "--workers", "1"]) == 2
    assert "not one text file" in capsys.readouterr().err
    assert not (tmp_path / name).exists()


def test_an_empty_dataset_names_a_line(scheduler, tmp_path, capsys):
    a = tmp_path / "a.csv"
    a.write_text("anchor,x,y\na,0,0\nb,10,0\nc,10,10\nd,0,10\n")
    m = tmp_path / "m"
    m.mkdir()
    pd.DataFrame({"time": pd.Series([], dtype=float), "tag": pd.Series([], dtype=str),
                  "anchor": pd.Series([], dtype=str), "range": pd.Series([], dtype=float)}
                 ).to_parquet(m / "p0.parquet", index=False)
    assert main(["locate", str(m), "--anchors", str(a), "-o", str(tmp_path / "o"),
                 "--engine", "dask", "--scheduler", scheduler]) == 2
    assert "p0.parquet:2: every partition of this dataset is empty" in (
        capsys.readouterr().err)
