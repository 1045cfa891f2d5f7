"""`partition`: the commands review's defects, each failing on the code before its fix.

* A folder of an RSSI file and a range file was read as one table: the range file got
  the RSSI column, all missing, and the error named the folder (``gl3: column 'rssi':
  153 missing ...``).  It names the file and line 1 and says which value column it has.
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

