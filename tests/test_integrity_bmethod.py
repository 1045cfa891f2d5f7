"""B-method constants (seed 003, eqs. (3)-(4)) against the published reference values."""

import numpy as np
import pytest
from scipy import stats

from robustloc.integrity import (
    detection_power_global,
    detection_power_w,
    global_alpha,
    global_critical,
    lambda0,
    w_critical,
)


def test_lambda0_reference_value():
    assert lambda0() == pytest.approx(20.90, abs=0.005)
    # independent: (3.2905 + 1.2816)^2
    assert lambda0(0.001, 0.10) == pytest.approx((3.290527 + 1.281552) ** 2, rel=1e-6)
    assert w_critical() == pytest.approx(3.2905, abs=1e-4)


@pytest.mark.parametrize(
    ("dof", "alpha"), [(1, 0.0010), (2, 0.0029), (3, 0.0057), (4, 0.0095), (6, 0.0193)]
)
def test_global_alpha_reference_values(dof, alpha):
    assert float(global_alpha(dof)) == pytest.approx(alpha, abs=0.00005)


def test_global_alpha_vectorized_and_invalid_dof():
    a = global_alpha(np.array([[1, 2], [0, 6]]))
    assert a.shape == (2, 2)
    assert np.isnan(a[1, 0])
    assert a[0, 0] == pytest.approx(0.001, abs=2e-6)
    assert a[1, 1] == pytest.approx(0.0193, abs=5e-5)


@pytest.mark.parametrize("dof", [1, 3, 10, 25])
def test_b_method_condition_holds(dof):
    """chi2(beta0; dof, lambda0) == chi2(1 - alpha; dof), checked by scipy directly."""
    a = float(global_alpha(dof))
    crit = float(global_critical(dof))
    assert crit == pytest.approx(stats.chi2.ppf(1 - a, dof), rel=1e-9)
    assert stats.ncx2.cdf(crit, dof, lambda0()) == pytest.approx(0.10, abs=1e-9)
    # the global test detects a bias of the MDB with power 1 - beta0
    assert float(detection_power_global(lambda0(), dof)) == pytest.approx(0.90, abs=1e-9)


def test_w_test_power_at_mdb_is_one_minus_beta0():
    assert float(detection_power_w(np.sqrt(lambda0()))) == pytest.approx(0.90, abs=1e-6)
    assert float(detection_power_w(0.0)) == pytest.approx(0.001, rel=1e-6)


def test_other_alpha0_beta0():
    lam = lambda0(0.05, 0.2)
    assert lam == pytest.approx((1.959964 + 0.841621) ** 2, rel=1e-6)
    # with dof = 1 the global test is the w-test: alpha == alpha0 (up to the far tail)
    assert float(global_alpha(1, 0.05, 0.2)) == pytest.approx(0.05, rel=1e-4)


@pytest.mark.parametrize("bad", [0.0, 1.0, -0.1, 2.0])
def test_invalid_probabilities_raise(bad):
    with pytest.raises(ValueError):
        lambda0(bad, 0.1)
    with pytest.raises(ValueError):
        global_alpha(3, 0.001, bad)


@pytest.mark.parametrize("dof", [2.5, 2.99, 3.7])
def test_global_alpha_non_integer_dof_is_exact(dof):
    """A non-integer dof is eq. (4) at that dof; it was rounded down to the integer below.

    scipy.stats evaluates the same quantile (``special.chndtrix``) and tail, so the two
    agree to rounding (rel 1e-12).  The critical value is checked through the independent
    non-central cdf at the 1e-9 of :func:`test_b_method_condition_holds`."""
    lam = lambda0()
    exact = stats.chi2.sf(stats.ncx2.ppf(0.10, dof, lam), dof)
    a = float(global_alpha(dof))
    assert a == pytest.approx(exact, rel=1e-12)
    assert float(global_alpha(np.floor(dof))) < a < float(global_alpha(np.ceil(dof)))
    crit = float(global_critical(dof))
    assert crit == pytest.approx(stats.chi2.isf(exact, dof), rel=1e-9)
    assert stats.ncx2.cdf(crit, dof, lam) == pytest.approx(0.10, abs=1e-9)
    assert float(detection_power_global(lam, dof)) == pytest.approx(0.90, abs=1e-9)
    # mixed with whole numbers in one array: each entry as asked alone
    both = global_alpha(np.array([2.0, dof, 6.0]))
    assert both[1] == a
    assert both[0] == float(global_alpha(2)) and both[2] == float(global_alpha(6))


@pytest.mark.parametrize("bad", ["0.1", None, True, b"0.1"])
def test_a_probability_that_is_not_a_real_number_is_refused_by_name(bad):
    """``alpha0="0.1"`` was taken as 0.1 (float() parses strings) and ``True`` as 1.0;
    ``None`` gave float()'s message without the parameter's name (left open by the API
    review).  A NumPy scalar is a real number and still taken."""
    from robustloc.integrity.bmethod import global_alpha, lambda0, w_critical

    for call in (lambda: lambda0(bad), lambda: lambda0(0.001, bad),
                 lambda: global_alpha(3, bad), lambda: w_critical(bad)):
        with pytest.raises(TypeError, match="(alpha0|beta0) must be a real number"):
            call()
    assert lambda0(np.float64(0.001)) == lambda0(0.001)
