"""LEGE on epochs of many observations: a bounded search (the API review of 2026-12-08).

One fault-free epoch of 25 ranges made ``lege`` enumerate every set of up to 19 suspects
(no ratio fires on clean data): a 2.4 GB block and a MemoryError traceback; 60 ranges
grew past 23 GB.  The orders are now enumerated up to ``LEGE_MAX_SETS`` sets per epoch
and searched by forward selection beyond."""

from __future__ import annotations

import itertools
import math
import os
import subprocess
import sys
import threading
import warnings

import numpy as np
import pandas as pd
import pytest

from robustloc.cli import main
from robustloc.estimators import linear
from robustloc.estimators.linear import lege
from robustloc.estimators.ranging import Locator

#: The sets one epoch may have enumerated (the default LEGE_MAX_SETS, literal: the test
#: must stop the old code's enumeration, which had no such bound, before it blows up).
BOUND = 20_000


def _circle(n: int, seed: int = 0, fault: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """``n`` anchors on a circle of 10 m, one epoch of ranges (0.1 m noise) from (1, 2)."""
    ang = np.linspace(0, 2 * np.pi, n, endpoint=False)
    a = np.column_stack([10 * np.cos(ang), 10 * np.sin(ang)])
    rng = np.random.default_rng(seed)
    r = np.hypot(a[:, 0] - 1, a[:, 1] - 2) + rng.normal(0, 0.1, n)
    r[0] += fault
    return a, r[None, :]


@pytest.fixture
def counted(monkeypatch):
    """Count the sets ``lege`` draws from ``itertools.combinations`` per call (one epoch,
    or epochs hearing as many); fail as soon as one call draws more than :data:`BOUND`
    (the old code drew millions: the guard that keeps it from filling the memory)."""
    drawn = {"most": 0}
    calls = threading.local()  # (the Dask engine's thread workers call it at once)
    real_lege = linear.lege

    def combinations(pool, k):  # noqa: ANN001, ANN202
        for item in itertools.combinations(pool, k):
            calls.sets = getattr(calls, "sets", 0) + 1
            if calls.sets > BOUND:
                raise AssertionError(f"lege enumerated more than {BOUND} sets for one epoch")
            yield item

    def spy(*args, **kwargs):  # noqa: ANN002, ANN003, ANN202
        calls.sets = 0
        try:
            return real_lege(*args, **kwargs)
        finally:
            drawn["most"] = max(drawn["most"], calls.sets)

    monkeypatch.setattr(linear, "combinations", combinations)
    monkeypatch.setattr(linear, "lege", spy)
    import robustloc.estimators.ranging as ranging

    monkeypatch.setattr(ranging, "lege", spy)
    return drawn


@pytest.mark.parametrize("n", [25, 60, 100])
@pytest.mark.parametrize("solver", ["nonlinear", "linearized"])
def test_a_clean_epoch_of_many_anchors_enumerates_a_bounded_number_of_sets(counted, n,
                                                                            solver):
    """Both solvers (the default Gauss-Newton linearization and the paper's difference
    system): at most BOUND sets per epoch, the fix found, nothing flagged, and the epoch
    marked as searched by forward selection beyond the enumerated orders."""
    a, r = _circle(n)
    sol = Locator("lege", solver=solver).solve(a, r)
    assert 0 < counted["most"] <= BOUND
    assert np.hypot(*(sol.position[0] - [1.0, 2.0])) < 0.1
    assert sol.extra["order"][0] == 0 and not sol.excluded.any()
    assert sol.extra["search_truncated"][0]


def test_the_enumerated_orders_follow_the_budget():
    """``C(n, 1) + ... + C(n, K) <= max_sets``: every order of seed 000's ten beacons."""
    for n in (10, 14, 15, 20, 25, 60, 100):
        k = linear.lege_exhaustive_order(n)
        assert sum(math.comb(n, j) for j in range(1, k + 1)) <= linear.LEGE_MAX_SETS
        assert k == n or sum(math.comb(n, j) for j in range(1, k + 2)) > linear.LEGE_MAX_SETS
    assert linear.lege_exhaustive_order(10) == 10
    H = np.random.default_rng(0).normal(size=(3, 25, 2))
    f = lege(H, H @ np.ones(2) + 0.01)
    np.testing.assert_array_equal(f.extra["exhaustive_order"], 4)


def _faulty(n: int, faults: list[int], N: int = 40, seed: int = 1):
    rng = np.random.default_rng(seed)
    H = rng.normal(size=(N, n, 2))
    x = rng.normal(size=(N, 2))
    y = np.einsum("knp,kp->kn", H, x) + rng.normal(0, 0.01, (N, n))
    for i, j in enumerate(faults):
        y[:, j] += (4.0 + i) * (-1) ** i
    return H, x, y


def test_forward_selection_finds_what_the_enumeration_finds():
    """Forward selection from order 1 (``max_sets=0``) on epochs of 16 observations with
    three gross errors: the same sets, estimates and fixes as the full enumeration, whose
    sigma0 it computes by rank-one updates."""
    H, x, y = _faulty(16, [2, 9, 13])
    full = lege(H, y, max_sets=10**6)
    fwd = lege(H, y, max_sets=0)
    assert not full.extra["search_truncated"].any() and fwd.extra["search_truncated"].all()
    np.testing.assert_array_equal(full.extra["order"], 3)
    np.testing.assert_array_equal(fwd.extra["order"], full.extra["order"])
    np.testing.assert_allclose(fwd.extra["gross_errors"], full.extra["gross_errors"],
                               atol=1e-9)
    np.testing.assert_allclose(fwd.x, full.x, atol=1e-12)
    # (the ratio differs where the best pair is not the forward one: both above 3)
    assert (fwd.extra["rho"] > 3).all() and (full.extra["rho"] > 3).all()
    np.testing.assert_allclose(fwd.x, x, atol=0.05)


def test_forward_selection_continues_from_the_last_enumerated_order(counted):
    """Six gross errors among 25 observations: orders 1-4 enumerated, 5 and 6 forward
    from the best set of order 4; every fault located and estimated."""
    H, x, y = _faulty(25, [0, 3, 7, 11, 18, 22])
    f = lege(H, y)
    np.testing.assert_array_equal(f.extra["exhaustive_order"], 4)
    np.testing.assert_array_equal(f.extra["order"], 6)
    assert f.extra["search_truncated"].all()
    flagged = f.extra["gross_errors"] != 0
    assert flagged[:, [0, 3, 7, 11, 18, 22]].all() and flagged.sum() == 6 * len(y)
    np.testing.assert_allclose(f.extra["gross_errors"][:, 0], 4.0, atol=0.1)
    np.testing.assert_allclose(f.x, x, atol=0.05)


def test_a_single_epoch_is_searched_in_memory_bounded_blocks(monkeypatch):
    """Within one epoch the sets are taken in blocks of at most ``_LEGE_BLOCK`` values:
    tiny blocks give the same numbers as one block (ties resolved as one block does)."""
    H, x, y = _faulty(12, [1, 5, 8], N=6)
    y[:, 10] = np.nan
    whole = lege(H, y)
    monkeypatch.setattr(linear, "_LEGE_BLOCK", 37)
    small = lege(H, y)
    for key in ("order", "gross_errors", "exhaustive_order"):
        np.testing.assert_array_equal(small.extra[key], whole.extra[key])
    np.testing.assert_array_equal(small.x, whole.x)


def _files(tmp_path, n: int) -> list[str]:
    a, r = _circle(n)
    ids = [f"a{i}" for i in range(n)]
    pd.DataFrame({"anchor": ids, "x": a[:, 0], "y": a[:, 1]}).to_csv(
        tmp_path / "a.csv", index=False)
    pd.DataFrame({"time": 0.0, "tag": "t", "anchor": ids, "range": r[0]}).to_csv(
        tmp_path / "m.csv", index=False)
    return [str(tmp_path / "m.csv"), "--anchors", str(tmp_path / "a.csv")]


def test_the_command_says_when_the_search_was_truncated(tmp_path, capsys, counted):
    """The reviewer's case: one clean epoch, 25 anchors, --method lege.  Exit 0, the fix,
    and a warning that the larger orders were searched by forward selection."""
    args = _files(tmp_path, 25)
    assert main(["locate", *args, "--method", "lege", "-o", str(tmp_path / "p.csv"),
                 "-q"]) == 0
    assert "searched by forward selection" in capsys.readouterr().err
    out = pd.read_csv(tmp_path / "p.csv")
    assert out["status"].tolist() == ["ok"]
    assert np.hypot(out.x[0] - 1, out.y[0] - 2) < 0.1
    # ten anchors: every order enumerated, nothing said
    args = _files(tmp_path, 10)
    assert main(["locate", *args, "--method", "lege", "-o", str(tmp_path / "q.csv"),
                 "-q"]) == 0
    assert "forward selection" not in capsys.readouterr().err


def test_the_library_warns_when_the_search_was_truncated(tmp_path, counted):
    import robustloc
    from robustloc.api import RobustlocWarning

    args = _files(tmp_path, 25)
    with warnings.catch_warnings(record=True) as seen:
        warnings.simplefilter("always")
        pos = robustloc.locate(args[0], args[2], "lege")
    assert any("forward selection" in str(w.message) and
               issubclass(w.category, RobustlocWarning) for w in seen)
    assert pos.attrs["summary"]["lege_search_truncated"]["epochs"] == 1


def test_sixty_anchors_in_a_bounded_address_space(tmp_path):
    """60 anchors, one clean epoch, under a 3 GB address-space limit (the command's
    threads reserve about 1.9 GB of it; the old code grew past 23 GB, and under this limit
    ended in a MemoryError traceback within seconds)."""
    import resource

    def limit() -> None:
        resource.setrlimit(resource.RLIMIT_AS, (3 * 1024**3, 3 * 1024**3))

    args = _files(tmp_path, 60)
    proc = subprocess.run(
        [sys.executable, "-m", "robustloc.cli", "locate", *args, "--method", "lege",
         "-o", str(tmp_path / "p.csv"), "-q"],
        capture_output=True, text=True, preexec_fn=limit, timeout=300,
        env={**os.environ, "OPENBLAS_NUM_THREADS": "1"})
    assert proc.returncode == 0, proc.stderr[-800:]
    assert "Traceback" not in proc.stderr
    assert pd.read_csv(tmp_path / "p.csv")["status"].tolist() == ["ok"]


def test_the_dask_engine_sums_the_partitions_epochs(tmp_path, capsys, scheduler, counted):
    """Two partitions of one epoch each: the run's count is their sum, and the warning
    is printed as the single-process command prints it."""
    pytest.importorskip("distributed")
    args = _files(tmp_path, 25)
    m = pd.read_csv(args[0])
    ds = tmp_path / "ds"
    ds.mkdir()
    m.to_parquet(ds / "p0.parquet", index=False)
    m.assign(time=1.0).to_parquet(ds / "p1.parquet", index=False)
    out = tmp_path / "pos"
    assert main(["locate", str(ds), "--anchors", args[2], "--method", "lege", "-o", str(out),
                 "--engine", "dask", "--scheduler", scheduler, "-q"]) == 0
    assert "lege: 2 epochs heard more anchors" in capsys.readouterr().err
    import json

    meta = json.loads((out / "_robustloc.json").read_text())
    assert meta["lege_search_truncated"] == {"epochs": 2, "max_sets": BOUND}
