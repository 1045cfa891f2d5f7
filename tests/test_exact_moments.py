"""Exact, mergeable moments (:mod:`robustloc._exact`): the spread of ``filter``'s summary
is the same number whichever way the values are split or ordered (the Dask review: the
tag groups' pooled moments differed from the single process in the last digits)."""

from __future__ import annotations

from fractions import Fraction

import numpy as np
import pytest

from robustloc import _exact
from robustloc._exact import Moments, exact_sum


def _values(rng: np.random.Generator) -> np.ndarray:
    x = rng.normal(3.0, 1.0, int(rng.integers(1, 400))) * 10.0 ** rng.integers(-150, 150)
    return np.r_[x, 0.0, -0.0, 5e-324, -2.5e-310, 1e300, -1.7e308]


@pytest.mark.parametrize("chunk", [1 << 24, 7])  # (7: several blocks of values)
def test_sums_are_exact_and_split_anyhow_add_up_to_the_same(monkeypatch, chunk):
    monkeypatch.setattr(_exact, "_CHUNK", chunk)
    rng = np.random.default_rng(0)
    for _ in range(20):
        x = _values(rng)
        m = Moments.of(x)
        assert m.n == x.size
        assert m.s1 == exact_sum(x) == sum(map(Fraction, x))
        assert m.s2 == sum(Fraction(v) ** 2 for v in x)
        y = rng.permutation(x)
        k = int(rng.integers(0, y.size))
        assert Moments.of(y[:k]) + Moments.of(y[k:]) == m


def test_std_is_numpys_and_independent_of_the_order():
    rng = np.random.default_rng(1)
    x = rng.normal(-4.0, 3.5, 200_000)
    s = Moments.of(x).std()
    assert s == pytest.approx(np.std(x), rel=1e-14)
    # numpy's sums in another order give other last digits; these do not
    parts = np.array_split(rng.permutation(x), 13)
    assert sum((Moments.of(p) for p in parts), Moments()).std() == s
    assert Moments().std() is None and Moments.of([2.0, 2.0]).std() == 0.0
    assert Moments.of([1e300, -1e300]).std() == pytest.approx(1e300)  # no overflow
    with pytest.raises(ValueError, match="finite"):
        Moments.of([1.0, np.nan])
