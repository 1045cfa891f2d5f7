"""The compiled (numba) kernels reproduce the NumPy implementation they replace.

``Locator(engine="compiled")`` (the default) runs the robust start and the Gauss-Newton fits
of ranges per epoch in :mod:`robustloc.estimators._compiled`; ``engine="numpy"`` runs the
batched NumPy path.  Both must give the same fixes, statuses, weights and statistics on
logs with missing anchors, slant ranges, 3-D, per-anchor sigma and every robust weight.
"""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as hs

from robustloc import status as st
from robustloc.estimators.ranging import Locator
from robustloc.robust import _compiled as rc
from robustloc.robust.weights import (
    IGG,
    IGG3,
    AsymmetricIGG,
    Hampel,
    Huber,
    LeastSquares,
    WeightFunction,
)

WEIGHTS = [LeastSquares(), Huber(), Huber(1.345), Hampel(), IGG(), IGG3(), AsymmetricIGG(),
           Hampel(2.0, 4.0, 8.0), IGG3(1.0, 2.5)]


@pytest.mark.parametrize("w", WEIGHTS, ids=lambda w: repr(w))
def test_compiled_weights_match_numpy(w: WeightFunction) -> None:
    u = np.concatenate([np.linspace(-12, 12, 2401), [np.nan, 0.0, -0.0, 1.5, -2.0, 2.5, 3.0,
                                                      8.5, -3.0, 1e300, -np.inf]])
    code, prm = rc.weight_spec(w)
    got_w = np.array([rc.weight_value(code, prm, x) for x in u])
    got_r = np.array([rc.rho_value(code, prm, x) for x in u[:-11]])
    np.testing.assert_allclose(got_w, w.weights(u), rtol=1e-13, atol=0, equal_nan=True)
    np.testing.assert_allclose(got_r, w.rho(u[:-11]), rtol=1e-12, atol=1e-15)


def test_weight_spec_none_for_custom_weight() -> None:
    class Cauchy(WeightFunction):
        def weights(self, u):
            return 1.0 / (1.0 + np.asarray(u) ** 2)

        def rho(self, u):
            return 0.5 * np.log1p(np.asarray(u) ** 2)

    assert rc.weight_spec(Cauchy()) is None
    assert rc.weight_spec(None)[0] == rc.LS


def _log(rng: np.random.Generator, N: int, anchors: np.ndarray, miss: float = 0.1,
         outliers: float = 0.2, dz: np.ndarray | None = None) -> np.ndarray:
    dim = anchors.shape[1]
    lo, hi = anchors.min(axis=0), anchors.max(axis=0)
    x = rng.uniform(lo + 0.1 * (hi - lo), hi - 0.1 * (hi - lo), size=(N, dim))
    d2 = np.sum((x[:, None, :] - anchors[None]) ** 2, axis=2)
    if dz is not None:
        d2 = d2 + dz**2
    d = np.sqrt(d2) + rng.normal(0, 0.3, d2.shape)
    d += np.where(rng.random(d.shape) < outliers, rng.uniform(3, 15, d.shape), 0.0)
    d[rng.random(d.shape) < miss] = np.nan
    d[:3, 2:] = np.nan  # too few anchors
    d[3] = np.nan  # nothing heard
    return d


A2 = np.array([[0, 0], [30, 0], [30, 30], [0, 30], [15, 0], [30, 15], [15, 30], [0, 15],
               [10, 20], [20, 10]], dtype=float)
A3 = np.array([[0, 0, 0], [20, 0, 3], [20, 20, 0], [0, 20, 3], [10, 0, 1.5], [10, 20, 2],
               [0, 10, 0.5], [20, 10, 2.5]], dtype=float)


def _compare(loc_kw: dict, anchors: np.ndarray, values: np.ndarray, **solve_kw) -> None:
    a = Locator(engine="numpy", **loc_kw).solve(anchors, values, **solve_kw)
    b = Locator(engine="compiled", **loc_kw).solve(anchors, values, **solve_kw)
    np.testing.assert_array_equal(a.status, b.status)
    # the two sum in different orders: fixes agree to rounding amplified by the iterations
    np.testing.assert_allclose(b.position, a.position, rtol=0, atol=1e-6, equal_nan=True)
    np.testing.assert_allclose(b.sigma0, a.sigma0, rtol=1e-5, atol=1e-9, equal_nan=True)
    np.testing.assert_allclose(b.covariance, a.covariance, rtol=1e-4, atol=1e-9,
                               equal_nan=True)
    np.testing.assert_allclose(b.residuals, a.residuals, rtol=0, atol=1e-6, equal_nan=True)
    # the integrity statistics' inputs: the compiled fit's own Jacobian at its fix against
    # NumPy's predict_jacobian (unit vectors: a 1e-6 m fix difference moves them by
    # about 1e-6 / distance)
    for key in ("jacobian", "range_residuals"):
        np.testing.assert_allclose(b.extra[key], a.extra[key], rtol=0, atol=1e-6,
                                   equal_nan=True)
    np.testing.assert_array_equal(np.isnan(a.weights), np.isnan(b.weights))
    np.testing.assert_allclose(b.weights, a.weights, rtol=1e-4, atol=1e-12, equal_nan=True)
    np.testing.assert_array_equal(a.excluded, b.excluded)
    np.testing.assert_array_equal(a.n_used, b.n_used)
    assert np.mean(a.iterations == b.iterations) > 0.99
    assert np.all(np.isin(b.status, [st.OK, st.NOT_CONVERGED, st.INSUFFICIENT, st.INVALID,
                                     st.ILL_CONDITIONED]))


@pytest.mark.parametrize("method", ["nls", "huber", "hampel", "igg", "igg3"])
def test_locator_engines_agree_2d(method: str) -> None:
    rng = np.random.default_rng(11)
    _compare({"method": method, "sigma": 0.3}, A2, _log(rng, 400, A2))


@pytest.mark.parametrize("method", ["huber", "igg"])
def test_locator_engines_agree_3d_nearest_apriori(method: str) -> None:
    rng = np.random.default_rng(12)
    kw = {"method": method, "sigma": 0.3, "robust_scale": "apriori", "reference": "nearest"}
    _compare(kw, A3, _log(rng, 300, A3, outliers=0.1))


def test_locator_engines_agree_slant_ranges_per_anchor_sigma() -> None:
    rng = np.random.default_rng(13)
    dz = rng.uniform(1.0, 3.0, A2.shape[0])
    sig = tuple(rng.uniform(0.2, 0.5, A2.shape[0]))
    values = _log(rng, 300, A2, dz=dz)
    _compare({"method": "igg3", "sigma": sig}, A2, values, height_offset=dz)
    _compare({"method": "huber"}, A2, values, height_offset=dz)


def test_locator_engines_agree_rssi_range_domain() -> None:
    rng = np.random.default_rng(14)
    A_dbm, n = np.full(A2.shape[0], -59.0), np.full(A2.shape[0], 2.2)
    x = rng.uniform(5, 25, (300, 2))
    d = np.linalg.norm(x[:, None] - A2[None], axis=2)
    rssi = A_dbm - 10 * n * np.log10(d) + rng.normal(0, 2.0, d.shape)
    rssi[rng.random(rssi.shape) < 0.1] -= 12.0  # body-blockage fades
    _compare({"method": "hampel", "sigma": 2.0}, A2, rssi, kind="rssi", A=A_dbm, n=n)


def test_custom_weight_falls_back_to_numpy() -> None:
    from robustloc.estimators.nonlinear import gauss_newton
    from robustloc.estimators.ranging import _compiled_gn
    from robustloc.models.ranging import RangeModel

    class Tukeyish(Huber):  # a subclass is not the built-in: no compiled twin
        pass

    rng = np.random.default_rng(15)
    z = _log(rng, 50, A2, miss=0.0)[10:]
    model = RangeModel(A2)
    kw = dict(scale=None, min_scale=0.0, max_iter=50, tol=1e-3, min_obs=3, rel_tol=1e-2)
    assert _compiled_gn(model, z, np.full((z.shape[0], 2), 15.0), np.ones_like(z),
                        Tukeyish(), kw) is None
    fit = gauss_newton(model, z, np.full((z.shape[0], 2), 15.0), 1.0, weight=Tukeyish(),
                       warmup=False, **kw)
    assert np.all(np.isfinite(fit.x))


def test_compile_notice_only_before_the_first_compilation(tmp_path) -> None:
    import os
    import subprocess
    import sys

    from robustloc._jitnotice import needs_compile

    Locator("igg").solve(A2, _log(np.random.default_rng(1), 5, A2, miss=0.0)[4:])
    assert not needs_compile("positioning")  # compiled (or loaded) above: cached on disk
    env = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path)}  # an empty cache: first run
    code = ("from robustloc._jitnotice import needs_compile, compile_notice;"
            "print(needs_compile('positioning'), needs_compile('filter'));"
            "compile_notice('positioning', 'filter')")
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True,
                         check=True)
    assert out.stdout.split() == ["True", "True"]
    assert "compiling the positioning and filter kernels" in out.stderr


@pytest.mark.parametrize("dim", [2, 3])
def test_grid_lms_equals_the_numpy_scoring_of_every_grid_point(dim: int) -> None:
    """The rescue's compiled grid search returns, per epoch, the first grid point of least
    :func:`lms_score` over the whole grid (an independent brute-force argmin here), with
    unheard anchors (NaN), exact ties (a duplicated grid point) and an epoch with nothing
    heard (index -1, score inf)."""
    from robustloc.estimators import _compiled
    from robustloc.estimators.ranging import lms_score
    from robustloc.models.ranging import RangeModel

    rng = np.random.default_rng(21 + dim)
    a = A2 if dim == 2 else A3
    grid = rng.uniform(-5.0, 35.0, (300, dim))
    grid = np.vstack([grid, grid[:7]])  # ties: the first copy must win
    pred = RangeModel(a).predict(grid)
    z = _log(rng, 60, a)
    sig = rng.uniform(0.2, 0.6, z.shape)
    idx, score = _compiled.grid_lms(pred, z, sig, dim)
    ref = lms_score(np.abs(pred[None] - z[:, None]) / sig[:, None], dim, axis=2)  # (S, G)
    np.testing.assert_array_equal(score, ref.min(axis=1))
    finite = np.isfinite(ref.min(axis=1))
    np.testing.assert_array_equal(idx[finite], np.argmin(ref, axis=1)[finite])
    assert np.all(idx[~finite] == -1) and (~finite).sum() == 1  # the epoch hearing nothing


@pytest.mark.parametrize("method", ["nls", "huber"])
def test_locator_engines_agree_3d_coplanar_anchors(method: str) -> None:
    """Ceiling anchors (one plane): both engines move the start off the plane the same way
    (``_off_plane`` runs after either start) and agree fix for fix."""
    rng = np.random.default_rng(15)
    a = np.c_[A3[:, :2], np.full(len(A3), 3.0)]
    x = np.c_[rng.uniform(2, 18, (300, 2)), rng.uniform(0.5, 1.8, 300)]  # tags below
    values = np.linalg.norm(x[:, None] - a[None], axis=2) + rng.normal(0, 0.1, (300, 8))
    values += np.where(rng.random(values.shape) < 0.05, rng.uniform(1, 5, values.shape), 0)
    values[rng.random(values.shape) < 0.1] = np.nan
    _compare({"method": method, "sigma": 0.3, "robust_scale": "apriori"}, a, values)
    # and both found the tags on the lower side (in the plane they would be ill-conditioned)
    sol = Locator(method, sigma=0.3, robust_scale="apriori").solve(a, values)
    fixed = st.among(sol.status, st.USABLE)
    assert fixed.mean() > 0.95 and np.median(sol.position[fixed, 2]) < 2.0


# ------------------------------------------------------------------------------ threads
@given(n=hs.integers(0, 100_000), threads=hs.integers(1, 64))
@settings(max_examples=200, deadline=None)
def test_thread_spans_cover_the_batch_once(n: int, threads: int) -> None:
    from robustloc.estimators._compiled import MIN_CHUNK, thread_spans

    spans = thread_spans(n, threads)
    assert spans[0][0] == 0 and spans[-1][1] == n
    assert all(a[1] == b[0] for a, b in zip(spans, spans[1:]))  # contiguous, no gap
    assert 1 <= len(spans) <= threads
    if len(spans) > 1:  # a span is worth a thread
        assert min(hi - lo for lo, hi in spans) >= MIN_CHUNK
    assert max(hi - lo for lo, hi in spans) - min(hi - lo for lo, hi in spans) <= 1


@pytest.mark.parametrize("method", ["nls", "huber", "igg", "auto"])
def test_the_fixes_do_not_depend_on_the_thread_count(method: str, monkeypatch) -> None:
    """Every epoch is solved and tested by the same code on its own scratch, whichever
    thread takes it: one thread and three (each span at least MIN_CHUNK epochs) give bit-identical
    outputs, with the threads really used (the spans of three)."""
    import numba

    from robustloc.estimators import _compiled
    from robustloc.integrity.fixes import locate_protected

    rng = np.random.default_rng(21)
    n = 3 * _compiled.MIN_CHUNK + 37
    values = _log(rng, n, A2)
    seen: list[int] = []
    spans = _compiled.thread_spans

    def counted(n_: int, threads: int | None = None) -> list[tuple[int, int]]:
        out = spans(n_, threads)
        seen.append(len(out))
        return out

    monkeypatch.setattr(_compiled, "thread_spans", counted)
    runs = []
    for threads in (1, 3):
        monkeypatch.setattr(numba, "get_num_threads", lambda t=threads: t)
        loc = Locator(method)
        runs.append(locate_protected(loc, A2, values, "range"))
    assert max(seen) == 3
    a, b = runs
    np.testing.assert_array_equal(a.status, b.status)
    for name in ("position", "covariance", "residuals", "weights", "sigma0", "iterations"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)
    np.testing.assert_array_equal(a.extra["jacobian"], b.extra["jacobian"])
    # the integrity tests' kernels (protection levels, a robust fit's own cofactors, the
    # re-solution's statistic) run in the same spans
    for name in ("hpl", "test_statistic", "flagged"):
        np.testing.assert_array_equal(a.extra[name], b.extra[name], err_msg=name)


def test_an_error_in_one_span_is_raised_after_every_span_ends() -> None:
    from robustloc.estimators._compiled import MIN_CHUNK, in_threads

    done: list[int] = []

    def run(lo: int, hi: int) -> None:
        if lo > 0:
            raise RuntimeError(f"span {lo}")
        done.append(lo)

    with pytest.raises(RuntimeError, match="span"):
        in_threads(run, 3 * MIN_CHUNK, 3)
    assert done == [0]  # the calling thread's span ran to its end


# --------------------------------------------------------------- small inverses' rank
def test_a_rank_one_3x3_normal_matrix_is_never_good() -> None:
    """``w j j^T`` (one weighted row of a 3-D fit): its 2 x 2 minors and determinant are
    rounding noise, and the closed-form inverse, noise over noise, passed the condition
    test for 45 % of them (found comparing the compiled robust cofactors with NumPy: the
    two summation orders gave different noise, one of them a garbage inverse).  Both
    inverses refuse every one now, and still accept every matrix of condition number
    up to 1e9 (LAPACK's), at any scale."""
    from robustloc.estimators._compiled import _inv_small
    from robustloc.estimators._kernels import inv_spd

    rng = np.random.default_rng(4)
    j = rng.normal(size=(5000, 3)) * 10.0 ** rng.uniform(-4, 4, (5000, 1))
    rank1 = rng.uniform(0.01, 1.0, (5000, 1, 1)) * j[:, :, None] * j[:, None, :]
    assert not inv_spd(rank1)[1].any()
    out = np.zeros((3, 3))
    assert not any(_inv_small(m, out, (0.0, 0.0, 0.0)) for m in rank1)
    q, _ = np.linalg.qr(rng.normal(size=(5000, 3, 3)))
    lam = 10.0 ** rng.uniform(0, 9, (5000, 3)) * 10.0 ** rng.uniform(-6, 6, (5000, 1))
    full = np.einsum("kij,kj,klj->kil", q, lam, q)
    full = 0.5 * (full + np.swapaxes(full, 1, 2))
    fine = np.linalg.cond(full) < 1e9
    assert fine.sum() > 4000
    assert inv_spd(full[fine])[1].all()
    assert all(_inv_small(m, out, (0.0, 0.0, 0.0)) for m in full[fine])
