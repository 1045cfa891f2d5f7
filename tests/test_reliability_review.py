"""``robustloc reliability``: layouts without any fix, anchors at one place, a correlation
above 1, and the memory of a site of many anchors (the reliability review)."""

from __future__ import annotations

import json
import re

import numpy as np
import pytest

from robustloc.cli import main


def _anchors(tmp_path, rows: str) -> str:
    path = tmp_path / "a.csv"
    path.write_text("anchor,x,y\n" + rows)
    return str(path)


@pytest.mark.parametrize("rows, extra, said", [
    ("A1,0,0\n", [], "no point of the area has a fix (1 anchor"),
    ("A1,0,0\nA2,10,0\nA3,10,8\nA4,0,8\n", ["--max-range", "0.5"], "within --max-range"),
])
def test_a_layout_without_any_fix_is_refused(tmp_path, capsys, rows, extra, said):
    """Exit 0 with an all-NaN table and six empty maps, before."""
    out = tmp_path / "o"
    code = main(["reliability", "--anchors", _anchors(tmp_path, rows), "-o", str(out),
                 "--no-maps", *extra])
    err = capsys.readouterr().err
    assert code == 2 and said in err and not out.exists()


def test_anchors_sharing_coordinates_are_refused_with_the_line(tmp_path, capsys):
    """Redundancy 0 and every correlation 1 everywhere, exit 0, before."""
    code = main(["reliability", "--anchors",
                 _anchors(tmp_path, "A1,0,0\nA2,10,0\nA3,5,8\nA4,5,8\n"), "-o",
                 str(tmp_path / "o"), "--no-maps"])
    err = capsys.readouterr().err
    assert code == 2 and ":5: anchors A3 and A4 share their coordinates" in err


def test_a_correlation_never_exceeds_one(tmp_path, capsys):
    """|rho| read 1.000000000000001 (rounding) and pairs were flagged above a threshold of
    1, which no correlation can pass."""
    code = main(["reliability", "--anchors",
                 _anchors(tmp_path, "A1,0,0\nA2,10,0\nA3,10,8\nA4,0,8\n"), "--area",
                 "0,10,0,8", "--step", "1", "--rho-threshold", "1", "-o",
                 str(tmp_path / "o"), "--json", "--no-maps"])
    summary = json.loads(capsys.readouterr().out)
    assert code == 0 and summary["max_abs_rho"]["max"] <= 1.0
    assert summary["points_with_flagged_pairs"] == 0


def test_the_planner_chunk_shrinks_with_the_anchors(monkeypatch):
    """300 anchors took 13 GB (chunks of 4096 points of 300 x 300 matrices): the chunk now
    holds at most CHUNK_ELEMENTS elements of such a matrix.  Checked on the chunks the
    planner hands to the reliability, with the same grid's result as in one chunk."""
    from robustloc.integrity import planner

    seen = []
    real = planner.reliability

    def spy(H, *a, **k):  # noqa: ANN001, ANN002, ANN003, ANN202
        seen.append(np.shape(H)[0] * np.shape(H)[1] ** 2)
        return real(H, *a, **k)

    monkeypatch.setattr(planner, "reliability", spy)
    monkeypatch.setattr(planner, "CHUNK_ELEMENTS", 50 * 30**2)
    xyz = np.random.default_rng(0).uniform(0, 50, (30, 2))
    small = planner.plan(xyz, (0, 50, 0, 50), 2.0, 0.3)
    assert max(seen) <= 50 * 30**2 and len(seen) > 1
    monkeypatch.setattr(planner, "CHUNK_ELEMENTS", 10**9)
    whole = planner.plan(xyz, (0, 50, 0, 50), 2.0, 0.3)
    np.testing.assert_allclose(small.table.to_numpy(float), whole.table.to_numpy(float),
                               rtol=1e-12, equal_nan=True)


def test_a_disk_that_refuses_a_write_is_named_as_the_folder_asked_for(tmp_path):
    """A full disk: `reliability` and `simulate wifi-room` ended in an OSError traceback,
    `simulate ble-corridor` named the hidden staging folder's file (the review).  The
    writers are stood in for by functions that fail as a full disk makes them fail."""
    import errno

    from robustloc.commands._folder import write_folder
    from robustloc.errors import OutputError

    def full(folder):  # noqa: ANN001, ANN202
        raise OSError(errno.ENOSPC, "No space left on device")

    def full_named(folder):  # noqa: ANN001, ANN202
        raise OutputError("no space left on device", folder / "measurements.csv",
                          errno_=errno.ENOSPC)

    out = tmp_path / "out"
    with pytest.raises(OutputError) as e:
        write_folder(out, full)
    assert e.value.path == str(out) and "no space" in e.value.message
    with pytest.raises(OutputError) as e:
        write_folder(out, full_named)
    assert e.value.path == str(out / "measurements.csv")
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]  # no staging left


def test_coordinates_beyond_the_area_limit_are_refused(tmp_path, capsys):
    """Anchors at 1e12 m were planned on a grid of 8e9 m steps, exit 0, and a candidate at
    1e300 m ended in a matplotlib traceback; --area already refused beyond 1e7 m."""
    code = main(["reliability", "--anchors",
                 _anchors(tmp_path, "A1,0,0\nA2,1e12,0\nA3,0,1e12\nA4,1e12,1e12\n"), "-o",
                 str(tmp_path / "o"), "--no-maps"])
    assert code == 2 and ":3: anchor A2: a coordinate beyond" in capsys.readouterr().err
    cand = tmp_path / "c.csv"
    cand.write_text("x,y\n5,1e300\n")
    code = main(["reliability", "--anchors",
                 _anchors(tmp_path, "A1,0,0\nA2,10,0\nA3,10,8\nA4,0,8\n"), "--suggest",
                 "--candidates", str(cand), "-o", str(tmp_path / "o2"), "--no-maps"])
    err = capsys.readouterr().err
    assert code == 2 and "c.csv:2: candidate coordinate beyond" in err


def test_the_summary_keeps_infinite_mdbs_as_the_table_has_them(tmp_path, capsys):
    """Three anchors on a line and one off it: on the line, the fourth anchor's range is
    controlled by no other (redundancy 0, MDB inf).  The summary said max_mdb max 16.8
    and nothing of them (inf dropped with the NaN: the commands review); checked
    against the written table, pandas' max and count of infinities."""
    import pandas as pd

    anchors = _anchors(tmp_path, "A,0,0\nB,10,0\nC,20,0\nD,5,20\n")
    out = tmp_path / "o"
    argv = ["reliability", "--anchors", anchors, "--area", "4,6,-1,1", "--step", "1",
            "-o", str(out), "-q", "--no-maps"]
    assert main(argv + ["--json"]) == 0
    summary = json.loads(capsys.readouterr().out)
    table = pd.read_csv(out / "reliability.csv")
    n_inf = int(np.isinf(table["max_mdb"]).sum())
    assert n_inf == 3  # the grid's row y = 0, on the line of A, B, C
    assert summary["points_with_undetectable_observation"] == n_inf
    for col in ("max_mdb", "max_ext_m"):
        v = table[col].dropna()
        assert np.isinf(v.max())
        assert summary[col]["max"] is None and "max" in summary[col]["infinite"]
        assert summary[col]["min"] == pytest.approx(v.min(), rel=1e-5)  # the CSV's %.6g
        assert summary[col]["median"] == pytest.approx(v.median(), rel=1e-5)
    assert summary["dop"]["infinite"] == []
    assert main(argv) == 0
    text = capsys.readouterr().out
    line = next(s for s in text.splitlines() if s.strip().startswith("max_mdb"))
    assert re.search(r"\bmax\s+inf\b", line), line
    assert "with an undetectable observation (MDB inf): 3" in text
