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
* ``filter --robust none --max-rejected`` and ``--robust none --no-adaptive`` (the plain
  filter rejects nothing and takes no scale), ``--robust huber --max-rejected`` (Huber's
  weight is never 0); ``simulate gnss --fault-m`` without ``--faults``, ``simulate
  wifi-room --no-jumps --jump-db`` (the filter review).
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


@pytest.mark.parametrize("extra, said", [
    (["--robust", "none", "--max-rejected", "1"],
     "--max-rejected does not apply to --robust none"),
    (["--robust", "ls", "--max-rejected", "8"],  # the default, given: refused too
     "--max-rejected does not apply to --robust none"),
    (["--robust", "none", "--no-adaptive"], "--no-adaptive does not apply to --robust none"),
    (["--robust", "none", "--no-adaptive", "--max-rejected", "0"],
     "--max-rejected, --no-adaptive does not apply to --robust none"),
    (["--robust", "huber", "--max-rejected", "1"],
     "--max-rejected does not apply to --robust huber (Huber's weight c/|u| is never 0"),
])
def test_filter_refuses_the_options_its_weight_makes_idle(tmp_path, capsys, rssi_site,
                                                          extra, said):
    out = tmp_path / "f.csv"
    code = main(["filter", *rssi_site, *extra, "-o", str(out)])
    err = capsys.readouterr().err
    assert code == 2 and said in err and "Traceback" not in err, err
    assert not out.exists()


def test_the_refused_filter_options_change_nothing_there():
    """Why they are refused: with the plain filter, re-locks and the adaptive scale leave
    every value as it is (a fade and a level change included); Huber's weight stays above
    0 however large the innovation, so nothing is rejected and nothing re-locks."""
    from robustloc.filters.rssi import RobustRssiFilter
    from robustloc.robust.weights import Huber

    z = np.r_[np.full(5, -50.0), -80.0, np.full(12, -70.0)]
    args = (np.zeros(z.size, dtype=np.int64), np.arange(z.size, dtype=float), z)
    plain = RobustRssiFilter(None, robust=False).filter_samples(*args)
    other = RobustRssiFilter(None, robust=False, max_rejected=1,
                             adaptive=False).filter_samples(*args)
    for name in ("rssi_dbm", "distance_m", "speed_mps", "weight", "innovation_db"):
        np.testing.assert_array_equal(getattr(plain, name), getattr(other, name))
    assert np.all(Huber().weights(np.array([3.0, 1e6, -1e300])) > 0)
    huber = [RobustRssiFilter(Huber(), max_rejected=k).filter_samples(*args)
             for k in (1, 8)]
    assert not huber[0].relocked.any()
    np.testing.assert_array_equal(huber[0].rssi_dbm, huber[1].rssi_dbm)


@pytest.mark.parametrize("extra", [["--max-rejected", "1"], ["--no-adaptive"]])
def test_filter_takes_them_with_a_weight_that_rejects(tmp_path, extra):
    """With the default weight (asymmetric IGG, which rejects) each option is taken, and
    --no-adaptive with Huber too (its weight depends on the scale): noise of 4 dB (twice
    --sigma-rssi, so the adaptive scale matters) and a drop of 20 dB (re-locks)."""
    (tmp_path / "a.csv").write_text("anchor,x,y,A,n\nA1,0,0,-40,2\n")
    z = np.r_[np.full(30, -50.0), np.full(30, -70.0)] + np.random.default_rng(3).normal(
        0, 4, 60)
    pd.DataFrame({"time": np.arange(60.0), "tag": "T1", "anchor": "A1", "rssi": z}).to_csv(
        tmp_path / "m.csv", index=False)
    site = [str(tmp_path / "m.csv"), "--anchors", str(tmp_path / "a.csv"), "-q",
            "--static"]
    runs = {}
    for name, opts in {"base": [], "other": extra,
                       "huber": ["--robust", "huber"],
                       "huber_other": ["--robust", "huber", "--no-adaptive"]}.items():
        out = tmp_path / f"{name}.csv"
        if name != "huber_other" or extra == ["--no-adaptive"]:
            assert main(["filter", *site, *opts, "-o", str(out)]) == 0
            runs[name] = pd.read_csv(out)
    assert not runs["base"].equals(runs["other"])
    if "huber_other" in runs:
        assert not runs["huber"].equals(runs["huber_other"])


@pytest.mark.parametrize("argv, said", [
    (["gnss", "--epochs", "3", "--fault-m", "500"], "--fault-m does not apply without --faults"),
    (["gnss", "--epochs", "3", "--faults", "0", "--fault-m", "20"],
     "--fault-m does not apply without --faults"),
    (["wifi-room", "--no-jumps", "--jump-db", "50"],
     "--jump-db does not apply to --no-jumps"),
])
def test_simulate_refuses_what_it_would_ignore(tmp_path, capsys, argv, said):
    out = tmp_path / "sim"
    code = main(["simulate", *argv, "-o", str(out), "-q"])
    err = capsys.readouterr().err
    assert code == 2 and said in err and "Traceback" not in err, err
    assert not out.exists()


@pytest.mark.parametrize("base, extra", [
    (["gnss", "--epochs", "3", "--faults", "1"], ["--fault-m", "500"]),
    (["wifi-room", "--walk-epochs", "300", "--samples-per-point", "2"], ["--jump-db", "50"]),
])
def test_simulate_takes_them_where_they_apply(tmp_path, capsys, base, extra):
    files = []
    for name, opts in (("a", []), ("b", extra)):
        assert main(["simulate", *base, *opts, "-o", str(tmp_path / name), "-q"]) == 0
        capsys.readouterr()
        file = "pseudoranges.csv" if base[0] == "gnss" else "measurements.csv"
        files.append((tmp_path / name / file).read_bytes())
    assert files[0] != files[1]
