"""The one elongation kernel (:mod:`robustloc.models.geometry`) that ``locate``'s
``ill_conditioned`` status, the planner, the ambiguity checks and ``calibrate --self``
share.  References: ``np.cov`` and ``eigvalsh`` row by row, and hand-made layouts."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st_

from robustloc.models.geometry import anchor_elongation, collinear, elongation_rows, unique_rows


def _reference(a: np.ndarray, row: np.ndarray) -> float:
    if row.sum() < 2:
        return np.nan
    ev = np.linalg.eigvalsh(np.atleast_2d(np.cov(a[row].T)))
    return np.nan if ev[-1] <= 0 else max(ev[0], 0.0) / ev[-1]


@settings(max_examples=40, deadline=None)
@given(seed=st_.integers(0, 10_000), shift=st_.sampled_from([0.0, 1e6, 1e12]),
       n_rows=st_.sampled_from([5, 5000]))
def test_collinear_is_the_scatter_ratio_test_at_any_offset(seed, shift, n_rows):
    """``collinear`` (``locate``'s ``ill_conditioned`` test) equals the per-row scatter
    eigenvalue ratio at most ``rel**2``; a layout 1e12 m from the origin gives the same
    answers as at the origin (each row's scatter about its own centroid: the raw-moment
    form lost every digit there, as the input review found).  5 000 rows take the
    hashed-pattern path of ``unique_rows``."""
    rng = np.random.default_rng(seed)
    m = 6
    a = rng.uniform(-20.0, 20.0, (m, 2))
    a[:3] = np.column_stack([np.linspace(-10, 10, 3), np.zeros(3)])  # three on a line
    keep = rng.random((n_rows, m)) < 0.6
    keep[0] = [True, True, True, False, False, False]
    got = collinear(a + shift, keep)
    ref = np.array([not (_reference(a, r) > 1e-6) for r in keep])
    np.testing.assert_array_equal(got, ref)
    assert got[0]


def test_elongation_of_hand_made_layouts():
    sq = np.array([[0.0, 0.0], [10.0, 0.0], [10.0, 10.0], [0.0, 10.0]])
    rows = np.array([[1, 1, 1, 1], [1, 1, 0, 0], [1, 0, 0, 0], [1, 1, 1, 0]], bool)
    e = anchor_elongation(sq, rows)
    assert e[0] == pytest.approx(1.0)  # a square spreads evenly
    assert e[1] == pytest.approx(0.0, abs=1e-15)  # two anchors: a line
    assert np.isnan(e[2])  # one anchor: undefined, and collinear says so
    # (0,0), (10,0), (10,10): centroid (20/3, 10/3), scatter [[600, 300], [300, 600]] / 9,
    # eigenvalues 900/9 and 300/9: ratio 1/3
    assert e[3] == pytest.approx(1 / 3, rel=1e-12)
    np.testing.assert_array_equal(collinear(sq, rows), [False, True, True, False])
    # 3-D: four anchors in one plane are "collinear" for a 3-D fix
    cube = np.array([[0, 0, 0], [10, 0, 0], [0, 10, 0], [10, 10, 0], [0, 0, 5]], float)
    e3 = anchor_elongation(cube, np.array([[1, 1, 1, 1, 0], [1, 1, 1, 1, 1]], bool))
    assert e3[0] == pytest.approx(0.0, abs=1e-15)
    assert e3[1] == pytest.approx(_reference(cube, np.ones(5, bool)), rel=1e-12)


def test_an_anchor_no_row_keeps_may_be_non_finite():
    # (a typo of 1e400 in an anchors file: locate leaves such an anchor out; its NaN
    # must not reach the other anchors' sums, 0 * inf is NaN)
    a = np.array([[0.0, 0.0], [10.0, 0.0], [0.0, 10.0], [np.inf, np.nan]])
    e = elongation_rows(a, np.array([[1, 1, 1, 0], [1, 1, 1, 1]], bool))
    assert e[0] == pytest.approx(_reference(a[:3], np.ones(3, bool)))
    assert np.isnan(e[1])


def test_unique_rows_round_trips_on_both_paths():
    rng = np.random.default_rng(3)
    for n_rows, m in ((10, 5), (5000, 10), (300, 70)):
        mask = rng.random((n_rows, m)) < 0.5
        mask[1::2] = mask[0]
        pats, inv = unique_rows(mask)
        np.testing.assert_array_equal(pats[inv], mask)
        assert len(np.unique(pats, axis=0)) == len(pats)


def test_the_commands_share_the_kernel():
    # one implementation: the names the other layers use are this module's functions
    from robustloc.estimators import ranging
    from robustloc.integrity import fixes
    from robustloc.models import geometry

    assert ranging._collinear is geometry.collinear
    assert ranging._unique_rows is geometry.unique_rows
    assert fixes.anchor_elongation is geometry.anchor_elongation
