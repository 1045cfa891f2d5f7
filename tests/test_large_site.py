"""A large site: many anchors in the file, a few heard per epoch (a warehouse of 100).

Anchors that an epoch does not hear must not change its fix, nor make the work grow with
the site: the robust start's minimal subsets come from the anchors the epoch hears
(``ranging._heard_groups``), and LEGE's candidate sets from its observed rows.  Before,
the start drew 24 subsets from the whole site's 161 700 triples (almost never all heard:
the start fell back to a fix that gross ranges had pulled, and huber's p95 on such a site
was 3.2 m against 0.38 m), and LEGE enumerated the site's C(100, 4) = 3.9e6 sets of
order 4 (66 GB per chunk).
"""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from robustloc.estimators.linear import lege
from robustloc.estimators.ranging import Locator


def _site(side: int = 10, heard: int = 10, N: int = 120, seed: int = 3):
    """Anchors on a ``side`` x ``side`` grid 10 m apart; each epoch hears its ``heard``
    nearest, 15 % of the ranges with a +3..15 m gross error."""
    rng = np.random.default_rng(seed)
    g = np.arange(side * side)
    axy = np.stack([10.0 * (g % side), 10.0 * (g // side)], 1)
    p = rng.uniform(10.0, 10.0 * (side - 2), (N, 2))
    d = np.linalg.norm(p[:, None] - axy[None], axis=2)
    r = d + rng.normal(0, 0.15, d.shape)
    r = np.where(rng.random(d.shape) < 0.15, r + rng.uniform(3, 15, d.shape), r)
    np.put_along_axis(r, np.argsort(d, axis=1)[:, heard:], np.nan, axis=1)
    return axy, r, p


@pytest.mark.parametrize("side", [10, 15])
@pytest.mark.parametrize("method", ["huber", "igg3", "lege", "snooping"])
def test_a_fix_on_a_large_site_is_the_fix_from_the_anchors_heard(method, side):
    """Each epoch's fix from the whole site's anchors equals (1e-9 m: the same arithmetic)
    its fix from the anchors it hears alone -- the per-epoch scale, so that no other epoch
    enters.  The site's area (the start's disc, the rescue's grid) is the one thing the
    unheard anchors set; on this site it does not decide any epoch.  Sites of 100 anchors
    (the site's subsets chosen among all 161 700) and 225 (among the local ones:
    C(225, 3) = 1.9e6 is above ``LARGE_ENUMERATION``)."""
    axy, r, p = _site(side=side)
    loc = Locator(method, sigma=0.15, robust_scale="mad")
    whole = loc.solve(axy, r, "range")
    for k in range(r.shape[0]):
        h = np.isfinite(r[k])
        alone = loc.solve(axy[h], r[k:k + 1, h], "range")
        np.testing.assert_allclose(whole.position[k], alone.position[0], rtol=0, atol=1e-9,
                                   err_msg=f"epoch {k}")
        assert whole.status[k] == alone.status[0], k
    if method in ("huber", "igg3"):  # and the robust fixes hold: 0.15 m noise, 1.5 m
        e = np.hypot(*(whole.position - p).T)
        assert np.percentile(e, 90) < 1.5


def test_lege_searches_the_observed_rows_only():
    """LEGE with 60 unobserved rows interleaved among 10 observed (a site where an epoch
    hears 10 of 70 anchors) finds the same gross errors and the same solution as with the
    10 rows alone: the candidate sets are the observed rows', in the same order."""
    rng = np.random.default_rng(0)
    N, n, p = 40, 10, 2
    H = rng.normal(size=(N, n, p))
    x = rng.normal(size=(N, p))
    y = np.einsum("knp,kp->kn", H, x) + rng.normal(0, 0.1, (N, n))
    y[:, 3] += np.where(rng.random(N) < 0.5, 2.0, 0.0)
    y[:, 7] -= np.where(rng.random(N) < 0.3, 1.5, 0.0)
    w0 = np.full((N, n), 100.0)
    small = lege(H, y, w0)
    wide_n = 70
    cols = np.sort(rng.choice(wide_n, n, replace=False))
    Hw = np.zeros((N, wide_n, p))
    yw = np.full((N, wide_n), np.nan)
    ww = np.zeros((N, wide_n))
    Hw[:, cols], yw[:, cols], ww[:, cols] = H, y, w0
    big = lege(Hw, yw, ww)
    np.testing.assert_allclose(big.x, small.x, rtol=0, atol=1e-12)
    np.testing.assert_array_equal(big.extra["order"], small.extra["order"])
    np.testing.assert_allclose(big.extra["gross_errors"][:, cols], small.extra["gross_errors"],
                               rtol=0, atol=1e-12)
    assert (small.extra["order"] >= 1).sum() >= N // 3  # the gross errors are found


def test_residual_cofactors_in_blocks_equal_the_whole(monkeypatch):
    """``sandwich_qvv`` forms its ``(K, m, m)`` products a block of epochs at a time: the
    same numbers (each epoch's are its own) whatever the block."""
    from robustloc.estimators import linear

    rng = np.random.default_rng(1)
    K, m, p = 50, 12, 2
    J = rng.normal(size=(K, m, p))
    w0 = np.where(rng.random((K, m)) < 0.7, 1.0 / rng.uniform(0.01, 0.1, (K, m)), 0.0)
    w = w0 * rng.uniform(0.0, 1.0, (K, m))
    fb = rng.uniform(size=(K, m))
    whole = linear.sandwich_qvv(J, w0, w, fb)
    monkeypatch.setattr(linear, "SANDWICH_BLOCK", 3 * m * m)  # blocks of 3 epochs
    np.testing.assert_array_equal(linear.sandwich_qvv(J, w0, w, fb), whole)


@pytest.mark.parametrize("seed", range(4))
def test_residual_cofactors_on_the_observed_rows_equal_the_whole(monkeypatch, seed):
    """On a site of 60 rows of which each epoch observes at most 12 (some rows weighted
    zero, some left out by the weights, a row in the fit with ``w0 = 0``, an epoch
    observing none, a singular epoch taking its fallback) the cofactors formed on each
    epoch's observed rows equal the ``(K, m, m)`` form's to 1e-12 (relative: the same sums
    without the exact zeros, grouped otherwise); the unobserved rows get the fallback."""
    from robustloc.estimators import linear

    rng = np.random.default_rng(seed)
    K, m, p = 40, 60, 3
    J = rng.normal(size=(K, m, p))
    w0 = np.zeros((K, m))
    for k in range(1, K):
        heard = rng.choice(m, rng.integers(2, 13), replace=False)
        w0[k, heard] = 1.0 / rng.uniform(0.01, 0.1, heard.size)
    w = w0 * np.where(rng.random((K, m)) < 0.2, 0.0, rng.uniform(0.2, 1.0, (K, m)))
    w[5, np.flatnonzero(w0[5] == 0)[0]] = 3.0  # in the fit, not in a sum
    J[7, np.flatnonzero(w0[7])] = J[7, np.flatnonzero(w0[7])[:1]]  # rank one: singular
    fb = rng.uniform(size=(K, m))
    fast = linear.sandwich_qvv(J, w0, w, fb)
    monkeypatch.setattr(linear, "SANDWICH_COMPACT_ROWS", 10**9)  # the plain form
    plain = linear.sandwich_qvv(J, w0, w, fb)
    np.testing.assert_allclose(fast, plain, rtol=1e-12, atol=0)
    np.testing.assert_array_equal(fast[w0 <= 0], fb[w0 <= 0])
    np.testing.assert_array_equal(fast[7], fb[7])


def test_the_default_on_a_large_site_stays_within_a_memory_bound():
    """The default ``locate`` of 2 000 epochs on a site of 100 anchors, 10 heard: the log
    scale's pass held three ``(K, 100, 100)`` products of its 2 000 epochs at once (480 MB
    of numpy memory, traced); in blocks of 4e6 values (32 MB) the peak is that of a few
    blocks plus the ``(K, m)`` arrays: under 250 MB."""
    import tracemalloc

    from robustloc.integrity.fixes import locate_protected

    axy, r, _ = _site(N=2000, seed=7)
    locate_protected(Locator("auto"), axy, r[:20], "range")  # compile outside the trace
    tracemalloc.start()
    try:
        sol = locate_protected(Locator("auto"), axy, r, "range")
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert sol.position.shape == (2000, 2)
    assert peak < 250e6, peak / 1e6


def test_self_calibration_on_a_large_site_keeps_each_epochs_anchors(monkeypatch):
    """``calibrate --self`` on a site of 36 anchors of which each epoch hears 8: its
    residual matrices are kept on the anchors each epoch observed (``selfcal._Residuals``;
    the rows of the others are the identity's), and the estimates equal those of the
    whole matrices (1e-9: the same sums in another order).  200 epochs of a site of 100
    took 4 min whole, 12 s compact."""
    import pandas as pd

    from robustloc.models import selfcal
    from robustloc.pipelines.calibrate import self_calibrate

    axy, r, _ = _site(side=6, heard=8, N=150, seed=4)
    r = np.where(np.isfinite(r), r + 0.2 * (np.arange(36) % 3 == 0), r)  # biased anchors
    anchors = pd.DataFrame({"anchor": [f"A{i}" for i in range(36)], "x": axy[:, 0],
                            "y": axy[:, 1]})
    compact, _ = self_calibrate(anchors, axy, r, "range")
    monkeypatch.setattr(selfcal, "_front", lambda keep: None)  # every anchor's row
    whole, _ = self_calibrate(anchors, axy, r, "range")
    for name in ("offset", "slope", "sigma", "offset_se", "slope_se"):
        np.testing.assert_allclose(getattr(compact, name), getattr(whole, name), rtol=1e-9,
                                   atol=1e-9, equal_nan=True, err_msg=name)


def _random_site(m: int, dim: int, seed: int) -> np.ndarray:
    return np.random.default_rng(seed).uniform(0.0, 10.0 * np.sqrt(m), (m, dim))


def _as_coordinates(a: np.ndarray, combos: np.ndarray) -> set:
    """Subsets as sets of anchor coordinates (rounded): comparable across listings."""
    return {frozenset(tuple(np.round(p, 6)) for p in a[c]) for c in combos}


@pytest.mark.parametrize("dim, m", [(2, 160), (3, 60)])
def test_a_large_sites_subsets_are_local_and_independent_of_order_and_frame(dim, m):
    """Above ``LARGE_ENUMERATION`` subsets (C(160, 3) = 669 920; C(60, 4) = 487 635) the
    site's subsets are chosen among each anchor with its nearest neighbours: every chosen
    subset lies within the pool of :func:`_local_subsets` (each anchor's
    ``LOCAL_NEIGHBOURS`` nearest, found here by brute force), the choice is the same set
    of anchors when the file lists them in another order, and when the frame is rotated
    and shifted."""
    from math import comb

    from scipy.spatial.transform import Rotation

    from robustloc.estimators import ranging

    assert comb(m, dim + 1) > ranging.LARGE_ENUMERATION
    a = _random_site(m, dim, seed=m)
    combos = ranging.minimal_subsets(a)[0]
    assert combos.shape[0] >= ranging.MAX_SUBSETS
    d = np.linalg.norm(a[:, None] - a[None], axis=2)
    near = np.argsort(d, axis=1)[:, 1:ranging.LOCAL_NEIGHBOURS + 1]  # no ties: random
    for c in combos:  # some anchor of the subset has the others among its nearest
        assert any(set(c) - {i} <= set(near[i]) for i in c), c
    want = _as_coordinates(a, combos)
    perm = np.random.default_rng(1).permutation(m)
    assert _as_coordinates(a[perm], ranging.minimal_subsets(a[perm])[0]) == want
    rot = Rotation.from_euler("z", 0.7).as_matrix()[:dim, :dim]
    moved = a @ rot.T + np.arange(1.0, dim + 1.0) * 123.0
    got = ranging.minimal_subsets(moved)[0]
    back = (moved - np.arange(1.0, dim + 1.0) * 123.0) @ rot  # the subsets' own anchors
    assert _as_coordinates(np.round(back, 6), got) == {
        frozenset(tuple(np.round(p, 6)) for p in s) for s in want}


def test_a_large_sites_subsets_do_not_enumerate_every_subset():
    """The site's subsets of 600 anchors (C(600, 3) = 3.6e7 triples: 0.86 GB as an index
    array, 7.7 GB of traced memory with the tuples they were listed from) stay within
    20 MB of traced memory; the pool is 15 triples per anchor."""
    import tracemalloc

    from robustloc.estimators import ranging

    a = _random_site(600, 2, seed=5)
    ranging._minimal_subsets_cached.cache_clear()
    tracemalloc.start()
    try:
        combos, ginv, c0 = ranging.minimal_subsets(a)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 20e6, peak
    assert combos.shape[0] >= ranging.MAX_SUBSETS
    sub = (a - c0)[combos]
    np.testing.assert_allclose(ginv @ (sub[:, 1:] - sub[:, :1]),
                               np.broadcast_to(np.eye(2), ginv.shape), atol=1e-9)


@pytest.mark.parametrize("method", ["auto", "huber", "lege"])
def test_a_block_solved_in_parts_gives_the_rows_of_one_solve(monkeypatch, method):
    """``robustloc locate`` solves a block in parts of ``SOLVE_CELLS`` epochs x anchors, and
    the log-scale pass its sample likewise (a site of 900 anchors held 3.0 GB, 1.8 GB in
    parts).  Each fix is its epoch's own, so parts of 7 epochs (a cell budget of 7 x 100)
    give the same positions file as one solve: every column equal (statuses, hpl and
    excluded anchors included), on a site of 100 anchors with gross ranges, an epoch
    hearing one anchor and one hearing two."""
    from robustloc.estimators import ranging
    from robustloc.io.tables import in_memory_source
    from robustloc.pipelines.locate import LocateSettings, run_locate

    axy, r, _ = _site(N=60, seed=11)
    r[5, np.flatnonzero(np.isfinite(r[5]))[1:]] = np.nan
    r[9, np.flatnonzero(np.isfinite(r[9]))[2:]] = np.nan
    anchors = pd.DataFrame({"anchor": [f"A{j}" for j in range(len(axy))],
                            "x": axy[:, 0], "y": axy[:, 1]})
    k, j = np.nonzero(np.isfinite(r))
    meas = pd.DataFrame({"time": k.astype(float), "tag": "t",
                         "anchor": anchors["anchor"].to_numpy()[j], "range": r[k, j]})
    settings = LocateSettings(method=(method,))
    whole, _ = run_locate(in_memory_source(meas), anchors, settings)
    monkeypatch.setattr(ranging, "SOLVE_CELLS", 7 * len(axy))
    parts, _ = run_locate(in_memory_source(meas), anchors, settings)
    assert len(whole) == 60
    pd.testing.assert_frame_equal(parts, whole)


def test_a_large_sites_local_subsets_leave_out_anchors_that_make_no_sense():
    """A typo in a large site's anchors file (an anchor at x = 1e200, one duplicated, one
    at x = 1e6): the local pool raised scipy's overflow error on the first; now the pool
    takes only the sane anchors (``_sane_anchors``), and no subset holds the bad ones."""
    from robustloc.estimators import ranging

    g = np.arange(169)
    base = np.stack([10.0 * (g % 13), 10.0 * (g // 13)], 1)
    for bad in ([1e200, 0.0], [1e6, 0.0]):
        a = base.copy()
        a[8] = bad
        a[5] = a[6]
        pool = ranging._local_subsets(a, ranging.canonical_rank(a), 3)
        assert pool.shape[0] > 0 and not (pool == 8).any()
