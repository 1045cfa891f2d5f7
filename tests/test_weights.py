"""Weight functions against their formulas, statsmodels' norms and psi = d rho / du."""

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as hst

from robustloc.robust import IGG, IGG3, AsymmetricIGG, Hampel, Huber, LeastSquares, get_weight
from robustloc.robust.scale import mad_scale, nanmedian_fast

ALL = [LeastSquares(), Huber(), Hampel(), IGG(), IGG3(), AsymmetricIGG(), AsymmetricIGG(1.5, 3, 5)]


def test_huber_formula_and_statsmodels():
    from statsmodels.robust.norms import HuberT

    u = np.array([-5.0, -2.0, -1.0, 0.3, 2.0, 2.5, 10.0])
    np.testing.assert_allclose(Huber(2.0).weights(u), [0.4, 1, 1, 1, 1, 0.8, 0.2])
    ref = HuberT(t=2.0)
    np.testing.assert_allclose(Huber(2.0).weights(u), ref.weights(u))
    np.testing.assert_allclose(Huber(2.0).rho(u), ref.rho(u))
    np.testing.assert_allclose(Huber(2.0).psi(u), ref.psi(u))


def test_hampel_matches_statsmodels():
    from statsmodels.robust.norms import Hampel as SMHampel

    u = np.linspace(-12, 12, 241)
    ours, ref = Hampel(1.7, 3.4, 8.5), SMHampel(a=1.7, b=3.4, c=8.5)
    np.testing.assert_allclose(ours.weights(u[u != 0]), ref.weights(u[u != 0]), atol=1e-12)
    np.testing.assert_allclose(ours.psi(u), ref.psi(u), atol=1e-12)
    np.testing.assert_allclose(ours.rho(u), ref.rho(u), atol=1e-12)


def test_hampel_paper_pieces():
    h = Hampel()  # a=1.7, b=3.4, c=8.5 (seed 000 eq. 6)
    np.testing.assert_allclose(h.weights([1.0, 2.0, 5.0, 9.0]),
                               [1.0, 1.7 / 2.0, 1.7 * (8.5 - 5) / (5.1 * 5), 0.0])


def test_igg_paper_pieces():
    g = IGG(1.5, 2.5, c=0.01)  # seed 000 eq. (7)
    np.testing.assert_allclose(g.weights([1.49, 1.5, 2.0, 2.49, 2.5, 7]),
                               [1, 1 / 1.51, 1 / 2.01, 1 / 2.5, 0, 0])


def test_igg3_formula():
    g = IGG3(1.5, 3.0)
    u = 2.0
    assert g.weights(u) == pytest.approx(1.5 / 2 * ((3 - 2) / 1.5) ** 2)
    assert g.weights(3.0) == 0 and g.weights(1.5) == 1


def test_asymmetric_igg_breakpoints():
    """seed 002 eq. (14) at and around its breakpoints."""
    k0, k1, c = 1.5, 3.0, 5.0
    d = AsymmetricIGG(k0, k1, c)
    e = np.array([-6, -5.0, -4.0, -1.5, 0.0, 1.49, 1.5, 2.0, 3.0, 4.0])
    expect = [0, 0, (-k0 / -4.0) * (c - 4.0) / (c - k0), 1, 1, 1, 1,
              (k0 / 2) * ((k1 - 2) / (k1 - k0)) ** 2, 0, 0]
    np.testing.assert_allclose(d.weights(e), expect)
    # continuous at -K0 and K0
    np.testing.assert_allclose(d.weights([-k0 - 1e-9, k0 + 1e-9]), [1, 1], atol=1e-6)
    assert d.weights(-3.0) != d.weights(3.0)  # asymmetric


@pytest.mark.parametrize("wf", ALL, ids=lambda w: repr(w))
def test_psi_is_derivative_of_rho(wf):
    u = np.linspace(-9.7, 9.7, 3881)
    h = 1e-6
    num = (wf.rho(u + h) - wf.rho(u - h)) / (2 * h)
    # skip the points next to a discontinuity of psi (IGG jumps at k0)
    near = np.zeros_like(u, dtype=bool)
    for b in (1.5, 2.5, 1.7, 3.4, 8.5, 2.0, 3.0, 5.0):
        near |= np.abs(np.abs(u) - b) < 1e-3
    np.testing.assert_allclose(num[~near], wf.psi(u)[~near], atol=1e-5)
    assert wf.rho(0.0) == 0


@pytest.mark.parametrize("wf", ALL, ids=lambda w: repr(w))
def test_weights_are_psi_over_u_and_bounded(wf):
    u = np.linspace(-20, 20, 401)
    u = u[u != 0]
    w = wf.weights(u)
    assert np.all((w >= 0) & (w <= 1 + 1e-12))
    np.testing.assert_allclose(wf.psi(u), u * w)
    assert np.isnan(wf.weights(np.nan))


@given(hst.floats(0.1, 50), hst.floats(-100, 100))
def test_huber_huge_threshold_is_least_squares(c, u):
    assert Huber(1e6 * c).weights(u) == 1.0


def test_get_weight_and_bad_parameters():
    assert get_weight("IGG3", k0=1.0, k1=4.0) == IGG3(1.0, 4.0)
    with pytest.raises(ValueError, match="unknown weight"):
        get_weight("tukey")
    with pytest.raises(ValueError):
        Hampel(3, 2, 1)
    with pytest.raises(ValueError):
        Huber(-1)
    # a parameter the weight has not: a ValueError naming the ones it has (was Python's
    # TypeError "__init__() got an unexpected keyword argument"), also through Locator
    with pytest.raises(ValueError, match="huber has no parameter 'k'; its parameters: c"):
        get_weight("huber", k=2.0)
    with pytest.raises(ValueError, match="ls has no parameter 'c'; its parameters: none"):
        get_weight("none", c=2.0)
    from robustloc.estimators.ranging import Locator

    with pytest.raises(ValueError, match="asymmetric-igg has no parameter 'a'"):
        Locator("asym", weight_params={"a": 1.0})


def test_mad_scale_and_fast_median():
    rng = np.random.default_rng(0)
    v = rng.normal(size=(500, 9))
    v[rng.random(v.shape) < 0.2] = np.nan
    np.testing.assert_allclose(nanmedian_fast(v, axis=1), np.nanmedian(v, axis=1))
    expect = np.nanmedian(np.abs(v), axis=1) / 0.6744897501960817
    np.testing.assert_allclose(mad_scale(v, axis=1), expect)
    big = rng.normal(0, 2.0, 200_000)
    assert mad_scale(big) == pytest.approx(2.0, rel=0.01)
    assert np.isnan(nanmedian_fast(np.full((1, 3), np.nan), axis=1))[0]


def test_all_covers_every_exported_weight_class():
    import robustloc.robust as rr
    from robustloc.robust.weights import WeightFunction

    exported = {c for c in (getattr(rr, n) for n in rr.__all__)
                if isinstance(c, type) and issubclass(c, WeightFunction)}
    exported.discard(WeightFunction)
    assert exported <= {type(w) for w in ALL}


@pytest.mark.parametrize("wf", ALL, ids=lambda w: repr(w))
def test_nan_in_gives_nan_out(wf):
    """Module docstring: NaN in gives NaN out, for weights, psi and rho alike (Hampel's and
    IGG's rho gave their value beyond the rejection threshold), compiled twins included."""
    from robustloc.robust import _compiled as rc

    u = np.array([[0.5, np.nan, -3.0], [np.nan, 10.0, -0.2]])
    for f in (wf.weights, wf.psi, wf.rho):
        assert np.isnan(f(np.nan))
        got = f(u)
        assert got.shape == u.shape
        np.testing.assert_array_equal(np.isnan(got), np.isnan(u))
    code, prm = rc.weight_spec(wf)
    assert np.isnan(rc.rho_value(code, prm, np.nan))
    assert np.isnan(rc.weight_value(code, prm, np.nan))


def test_mad_scale_empty_rows_and_scalar():
    """Rows with no value give NaN, as all-NaN rows do (numpy's IndexError before); a 0-d
    input has no axis: a ValueError naming ``residuals`` (numpy's AxisError before)."""
    assert np.isnan(mad_scale([]))
    out = mad_scale(np.empty((3, 0)))
    assert out.shape == (3,) and np.all(np.isnan(out))
    assert np.all(np.isnan(mad_scale(np.empty((3, 0)), center=True)))
    assert mad_scale(np.empty((0, 4))).shape == (0,)
    assert np.all(np.isnan(nanmedian_fast(np.empty((2, 0)), axis=1)))
    with pytest.raises(ValueError, match="residuals"):
        mad_scale(2.0)


@pytest.mark.parametrize(("cls", "key"), [(Huber, "c"), (Hampel, "a"), (Hampel, "c"),
                                          (IGG, "k0"), (IGG, "c"), (IGG3, "k1"),
                                          (AsymmetricIGG, "c")])
@pytest.mark.parametrize("bad", ["2", None, [3.0], True, np.nan, 1 + 2j])
def test_constructors_check_parameters_like_get_weight(cls, key, bad):
    """The exported classes refuse what get_weight refuses, naming the parameter (Python's
    "'>' not supported ..." before; ``Huber(c=True)`` was Huber(1))."""
    with pytest.raises(ValueError, match=f"^weight parameter {key} must be a real number"):
        cls(**{key: bad})
    assert cls(**{key: getattr(cls(), key)}) == cls()  # defaults and ints still taken
    assert Huber(2) == Huber(2.0) and IGG3(np.float32(1.0), 4) == IGG3(1.0, 4.0)
