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


@pytest.mark.parametrize("method", ["huber", "igg3", "lege", "snooping"])
def test_a_fix_on_a_large_site_is_the_fix_from_the_anchors_heard(method):
    """Each epoch's fix from the whole site's anchors equals (1e-9 m: the same arithmetic)
    its fix from the anchors it hears alone -- the per-epoch scale, so that no other epoch
    enters.  The site's area (the start's disc, the rescue's grid) is the one thing the
    unheard anchors set; on this site it does not decide any epoch."""
    axy, r, p = _site()
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
