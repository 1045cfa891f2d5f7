"""`partition`'s defects found by the review of `locate`, `partition` and the library
(2026-12-06), each failing on the code before its fix: time bins of 10^6 and more cut to
six digits (bins twelve days apart became one partition, which `locate --engine dask`
refused, and the advice it gave rebuilt the same dataset), a time beyond the documented
limits stopping the partitioning with DuckDB's text and no line, and hexadecimal text
that the readers refuse taken as a number."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
import pytest

pytest.importorskip("duckdb")

from robustloc.cli import main  # noqa: E402

ANCHORS = pd.DataFrame({"anchor": ["A1", "A2", "A3", "A4"], "x": [0.0, 10.0, 10.0, 0.0],
                        "y": [0.0, 0.0, 10.0, 10.0]})
#: six epochs over twelve days: with 1 s bins, bin numbers up to 1 000 005
TIMES = [0.5, 100_000.5, 200_000.5, 1_000_000.5, 1_000_001.5, 1_000_005.5]


def _log(times: list[float]) -> pd.DataFrame:
    rng = np.random.default_rng(5)
    xy = ANCHORS[["x", "y"]].to_numpy()
    rows = []
    for tag, p in (("t1", np.array([3.0, 4.0])), ("t2", np.array([6.0, 2.0]))):
        for t in times:
            d = np.hypot(*(xy - p).T) + rng.normal(0, 0.05, 4)
            rows += [{"time": t, "tag": tag, "anchor": a, "range": float(r)}
                     for a, r in zip(ANCHORS["anchor"], d)]
    return pd.DataFrame(rows)


def _bins(ds: Path) -> dict[str, list[float]]:
    return {f.parent.name: sorted(set(pd.read_parquet(f)["time"].tolist()))
            for f in sorted(ds.rglob("*.parquet"))}


@pytest.mark.parametrize("method", ["duckdb", "dask"])
def test_time_bins_beyond_a_million_stay_apart(tmp_path, method):
    """Each 1 s bin its own partition, the folders in time order (one key width)."""
    _log(TIMES).to_csv(tmp_path / "m.csv", index=False)
    ds = tmp_path / "ds"
    assert main(["partition", str(tmp_path / "m.csv"), "-o", str(ds), "--by", "time",
                 "--span", "1", "--method", method]) == 0
    bins = _bins(ds)
    assert sorted(bins.values()) == [[t] for t in TIMES]
    # (dask named its folders by the number, unpadded, until the review of 2026-12-07)
    names = list(bins)
    assert len({len(n) for n in names}) == 1 and names == sorted(names)
    assert [v[0] for v in bins.values()] == sorted(TIMES)
    assert {f.name for f in ds.rglob("*.parquet")} == {"part-0.parquet"}


def test_the_dataset_of_far_apart_bins_is_located_by_dask(tmp_path, scheduler):
    """`locate --engine dask` refused the dataset of the cut bins ("an epoch's rows could
    be split between partitions"); it now gives the rows of a local `locate`."""
    _log(TIMES).to_csv(tmp_path / "m.csv", index=False)
    ANCHORS.to_csv(tmp_path / "a.csv", index=False)
    ds = tmp_path / "ds"
    assert main(["partition", str(tmp_path / "m.csv"), "-o", str(ds), "--by", "time",
                 "--span", "1"]) == 0
    assert main(["locate", str(ds), "--anchors", str(tmp_path / "a.csv"), "-o",
                 str(tmp_path / "pd"), "--engine", "dask", "--scheduler", scheduler,
                 "-q"]) == 0
    assert main(["locate", str(tmp_path / "m.csv"), "--anchors", str(tmp_path / "a.csv"),
                 "-o", str(tmp_path / "local.csv"), "-q"]) == 0
    got = pd.read_parquet(tmp_path / "pd").sort_values(["tag", "time"], ignore_index=True)
    want = pd.read_csv(tmp_path / "local.csv").sort_values(["tag", "time"],
                                                           ignore_index=True)
    assert len(got) == len(want) == 2 * len(TIMES)
    np.testing.assert_allclose(got[["x", "y"]], want[["x", "y"]], atol=1e-6)


def test_many_tag_buckets_keep_their_numbers(tmp_path):
    """`--buckets` over 10 000 were cut to four digits (bucket 12345 named 1234)."""
    rows = pd.DataFrame({"time": 0.0, "tag": [f"tag{i}" for i in range(3000)],
                         "anchor": "A1", "range": 5.0})
    rows.to_csv(tmp_path / "m.csv", index=False)
    ds = tmp_path / "ds"
    assert main(["partition", str(tmp_path / "m.csv"), "-o", str(ds), "--by", "tag",
                 "--buckets", "20000"]) == 0
    names = [f.parent.name.split("=", 1)[1] for f in ds.rglob("*.parquet")]
    assert {len(n) for n in names} == {5}
    n_tags = sum(pd.read_parquet(f)["tag"].nunique() for f in ds.rglob("*.parquet"))
    assert n_tags == 3000 and len(names) == len(set(names))


def test_a_time_beyond_the_limits_is_named_by_its_line(tmp_path, capsys):
    m = _log(TIMES[:2])
    m.loc[5, "time"] = 1e20  # data line 6, file line 7
    m.to_csv(tmp_path / "m.csv", index=False)
    assert main(["partition", str(tmp_path / "m.csv"), "-o", str(tmp_path / "ds"),
                 "--by", "time"]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"error: {tmp_path / 'm.csv'}:7: time 1e+20 s is beyond"), err
    assert not (tmp_path / "ds").exists()
    # --by tag has no bins to compute: the row is kept (locate counts it invalid)
    assert main(["partition", str(tmp_path / "m.csv"), "-o", str(tmp_path / "ds"),
                 "--by", "tag"]) == 0


def test_hexadecimal_text_is_refused_as_the_readers_refuse_it(tmp_path, capsys):
    (tmp_path / "m.csv").write_text("time,tag,anchor,range\n0x10,t1,a,5\n")
    assert main(["partition", str(tmp_path / "m.csv"), "-o", str(tmp_path / "ds"),
                 "--by", "time"]) == 2
    assert "m.csv:2: column 'time': '0x10' is not a number" in capsys.readouterr().err


def test_quiet_prints_nothing_as_the_other_commands(tmp_path, capsys):
    """Every other command takes ``-q``; ``partition -q`` was an argparse error (exit 2)."""
    _log(TIMES[:2]).to_csv(tmp_path / "m.csv", index=False)
    for flag in ("-q", "--quiet"):
        out = tmp_path / f"ds{flag}"
        assert main(["partition", str(tmp_path / "m.csv"), "-o", str(out), "--by", "tag",
                     flag]) == 0
        assert capsys.readouterr().out == ""
        assert sum(len(pd.read_parquet(f)) for f in out.rglob("*.parquet")) == 16
