"""Options that were taken and did nothing (the commands review): each is refused now,
exit 2 with a message saying why, before any work, where it has no effect; and still
taken where it has one.

* ``montecarlo --nonlinear --lege-max-order K`` (the nonlinear runs use locate's LEGE),
  ``--lege-max-order`` without ``lege`` among ``--methods``; ``--size 1,,2`` (an empty
  item skipped), likewise ``--faults`` and ``--methods``.
* ``partition --by time --buckets N``, ``--by tag --span S``, ``--rows-per-partition``
  where the DuckDB method never reads it, ``--scheduler``/``--workers`` with
  ``--method duckdb``.
* ``filter --static --sigma-accel`` and ``--static --exponent``: the output was byte for
  byte that of ``--static`` alone (checked here on the option taken without
  ``--static``, where it changes the output).
"""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from robustloc.cli import main


@pytest.fixture()
def anchors(tmp_path):
    path = tmp_path / "a.csv"
    path.write_text("anchor,x,y\nA1,0,0\nA2,20,0\nA3,20,20\nA4,0,20\nA5,10,-5\n"
                    "A6,25,10\nA7,-5,10\nA8,10,25\nA9,12,9\n")
    return str(path)


@pytest.mark.parametrize("extra, said", [
    (["--nonlinear", "--lege-max-order", "2"], "--lege-max-order applies to the linearized"),
    (["--methods", "ls,huber", "--lege-max-order", "2"],
     "--lege-max-order applies to --methods lege"),
    (["--size", "1,,2"], "argument --size: expected comma-separated numbers"),
    (["--size", "1,2,"], "argument --size: expected comma-separated numbers"),
    (["--faults", "0,,1"], "argument --faults: expected comma-separated whole numbers"),
    (["--methods", "ls,,huber"], "--methods: an empty item"),
])
def test_montecarlo_refuses_what_it_would_ignore(tmp_path, capsys, anchors, extra, said):
    out = tmp_path / "mc.csv"
    code = main(["montecarlo", "--anchors", anchors, "--trials", "20", "-q", "-o",
                 str(out), *extra])
    err = capsys.readouterr().err
    assert code == 2 and said in err, err
    assert "Traceback" not in err and not out.exists()


def test_montecarlo_takes_lege_max_order_where_it_applies(tmp_path, anchors):
    """The linearized model with lege: two faults, and LEGE allowed to exclude one (order
    1) or up to three (the default): the tables differ."""
    tables = []
    for order in ("1", "3"):
        out = tmp_path / f"mc{order}.csv"
        assert main(["montecarlo", "--anchors", anchors, "--trials", "200", "-q", "-o",
                     str(out), "--methods", "lege", "--lege-max-order", order, "--faults",
                     "2", "--size", "3"]) == 0
        tables.append(pd.read_csv(out).select_dtypes("number"))
    assert not tables[0].equals(tables[1])


def test_run_montecarlo_refuses_lege_max_order_with_nonlinear(tmp_path, anchors):
    """The library's ``run_montecarlo(nonlinear=True, lege_max_order=K)`` took K and ignored
    it (the Locator's LEGE has no cap), where the command line refused it: it is refused
    here too, and left out it still runs (nonlinear and linearized)."""
    from robustloc.integrity.montecarlo import ranging_layout, run_montecarlo
    xy = pd.read_csv(anchors)[["x", "y"]].to_numpy(float)
    lay = ranging_layout(xy, np.array([10.0, 10.0]), sigma_m=0.1)
    with pytest.raises(ValueError, match="lege_max_order applies to the linearized"):
        run_montecarlo(lay, trials=5, methods=("lege",), nonlinear=True, lege_max_order=1)
    for nonlinear in (True, False):
        t = run_montecarlo(lay, trials=5, methods=("lege",), nonlinear=nonlinear)
        assert t["trials"].tolist() == [5]
    one = run_montecarlo(lay, trials=200, methods=("lege",), n_faults=2, size=3.0,
                         lege_max_order=1)
    three = run_montecarlo(lay, trials=200, methods=("lege",), n_faults=2, size=3.0)
    assert one["identified"].iloc[0] != three["identified"].iloc[0]


def _measurements(tmp_path) -> str:
    path = tmp_path / "m.csv"
    rng = np.random.default_rng(0)
    rows = [(t * 0.5, f"T{t % 3}", f"A{a}", float(-60 + rng.normal(0, 2)))
            for t in range(60) for a in (1, 2, 3)]
    pd.DataFrame(rows, columns=["time", "tag", "anchor", "rssi"]).to_csv(path, index=False)
    return str(path)


@pytest.mark.parametrize("extra, said", [
    (["--by", "time", "--buckets", "3"], "--buckets applies to --by tag only"),
    (["--by", "tag", "--span", "5"], "--span applies to --by time only"),
    (["--by", "tag", "--rows-per-partition", "10"],
     "--rows-per-partition applies to --by time without --span, or --method dask only"),
    (["--by", "time", "--span", "5", "--rows-per-partition", "10"],
     "--rows-per-partition applies to --by time without --span"),
    (["--by", "tag", "--workers", "2"], "--workers applies to --method dask only"),
    (["--by", "tag", "--scheduler", "tcp://127.0.0.1:1"],
     "--scheduler applies to --method dask only"),
])
def test_partition_refuses_what_it_would_ignore(tmp_path, capsys, extra, said):
    out = tmp_path / "ds"
    code = main(["partition", _measurements(tmp_path), "-o", str(out), "-q", *extra])
    err = capsys.readouterr().err
    assert code == 2 and err.startswith(f"error: {said}"), err
    assert not out.exists()


def test_partition_takes_rows_per_partition_where_it_sets_the_span(tmp_path):
    """--by time without --span: 180 rows over 29.5 s at 60 rows a file give bins of
    29.5 * 60 / 180 s, so three files (the default gives one)."""
    out = tmp_path / "ds"
    assert main(["partition", _measurements(tmp_path), "-o", str(out), "-q", "--by", "time",
                 "--rows-per-partition", "60"]) == 0
    assert len(list(out.rglob("*.parquet"))) >= 3


@pytest.fixture()
def rssi_site(tmp_path):
    (tmp_path / "a.csv").write_text("anchor,x,y,A,n\nA1,0,0,-40,2\nA2,10,0,-40,2\n")
    rng = np.random.default_rng(1)
    t = np.arange(80) * 0.5
    d = np.abs(np.c_[2 + 0.1 * t, 8 - 0.1 * t])  # a tag walking between the anchors
    rows = [(ti, "T1", f"A{j + 1}", float(-40 - 20 * np.log10(dj) + rng.normal(0, 2)))
            for ti, di in zip(t, d) for j, dj in enumerate(di)]
    pd.DataFrame(rows, columns=["time", "tag", "anchor", "rssi"]).to_csv(
        tmp_path / "m.csv", index=False)
    return [str(tmp_path / "m.csv"), "--anchors", str(tmp_path / "a.csv"), "-q"]


@pytest.mark.parametrize("extra", [["--sigma-accel", "5"], ["--exponent", "4"],
                                   ["--sigma-accel", "0", "--exponent", "3"]])
def test_filter_static_refuses_the_options_of_a_moving_receiver(tmp_path, capsys,
                                                                 rssi_site, extra):
    out = tmp_path / "f.csv"
    code = main(["filter", *rssi_site, "--static", *extra, "-o", str(out)])
    err = capsys.readouterr().err
    assert code == 2 and "does not apply to --static" in err and extra[0] in err, err
    assert not out.exists()


@pytest.mark.parametrize("extra", [["--sigma-accel", "5"], ["--exponent", "4"]])
def test_filter_takes_them_for_a_moving_receiver(tmp_path, rssi_site, extra):
    """Without --static each option changes the filtered RSSI: it is one of the filter's
    settings there, not an idle one."""
    base, other = tmp_path / "base.csv", tmp_path / "other.csv"
    assert main(["filter", *rssi_site, "-o", str(base)]) == 0
    assert main(["filter", *rssi_site, *extra, "-o", str(other)]) == 0
    assert not np.allclose(pd.read_csv(base)["rssi"], pd.read_csv(other)["rssi"])
