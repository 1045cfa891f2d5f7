"""``robustloc.status.among``: the same answer as ``np.isin`` on either of its paths."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st_

from robustloc import status as st

#: statuses, a foreign string, None and a number: what an object column may hold
POOL = st.ALL + ("not-a-status", None, 3)


@settings(max_examples=40, deadline=None)
@given(seed=st_.integers(0, 2**32 - 1), n=st_.sampled_from([0, 1, 7, 4095, 4096, 20_000]),
       k=st_.integers(0, len(st.ALL)), two_d=st_.booleans())
def test_among_equals_isin_on_both_paths(seed, n, k, two_d):
    rng = np.random.default_rng(seed)
    status = np.empty(n, dtype=object)
    status[:] = [POOL[i] for i in rng.integers(0, len(POOL), n)]
    if two_d and n % 2 == 0:
        status = status.reshape(2, -1)
    values = tuple(rng.choice(np.array(st.ALL, dtype=object), k, replace=False))
    expected = np.isin(status.astype(str), np.array(values, dtype=str)) & \
        np.vectorize(lambda v: isinstance(v, str), otypes=[bool])(status) if n else \
        np.zeros(status.shape, bool)
    got = st.among(status, values)
    assert got.dtype == bool and got.shape == status.shape
    np.testing.assert_array_equal(got, expected)
