"""``robustloc._stats`` (the pipelines' chi-square and normal functions from
``scipy.special``, without importing ``scipy.stats``) against ``scipy.stats`` itself."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest
from scipy import stats

from robustloc import _stats

P = np.array([1e-12, 1e-7, 1e-3, 0.01, 0.1, 0.5, 0.8, 0.9, 0.95, 0.999, 1 - 1e-9])
DF = np.array([1, 2, 3, 4, 6, 10, 37])
X = np.array([0.0, 1e-6, 0.3, 1.0, 3.84, 10.0, 60.0, 400.0, np.inf])


@pytest.mark.parametrize("df", DF)
def test_chi2_functions_equal_scipy_stats(df):
    np.testing.assert_array_equal(_stats.chi2_sf(X, df), stats.chi2.sf(X, df))
    np.testing.assert_array_equal(_stats.chi2_isf(P, df), stats.chi2.isf(P, df))
    np.testing.assert_array_equal(_stats.chi2_ppf(P, df), stats.chi2.ppf(P, df))


@pytest.mark.parametrize("df", DF)
@pytest.mark.parametrize("nc", [1e-3, 1.0, 17.07, 20.9, 80.0])
def test_noncentral_chi2_quantile_equals_scipy_stats(df, nc):
    np.testing.assert_array_equal(_stats.ncx2_ppf(P, df, nc), stats.ncx2.ppf(P, df, nc))


def test_normal_functions_equal_scipy_stats():
    np.testing.assert_array_equal(_stats.norm_ppf(P), stats.norm.ppf(P))
    x = np.array([-np.inf, -40.0, -3.29, -1.0, 0.0, 0.5, 3.29, 9.0, np.inf])
    np.testing.assert_array_equal(_stats.norm_cdf(x), stats.norm.cdf(x))


@pytest.mark.parametrize("df", [1, 2, 3, 7, 30.5, 1e4])
def test_student_t_quantile_equals_scipy_stats(df):
    np.testing.assert_array_equal(_stats.t_ppf(P, df), stats.t.ppf(P, df))


def test_nan_and_out_of_range_arguments_give_nan():
    assert np.isnan(_stats.chi2_isf(0.5, np.nan))
    assert np.isnan(_stats.chi2_sf(np.nan, 3))
    assert np.isnan(_stats.norm_ppf(1.5))


def test_the_locate_pipeline_does_not_import_scipy_stats():
    """The reason for the module: ``import scipy.stats`` costs ~1 s per command-line run."""
    code = ("import sys; import robustloc.integrity.fixes, robustloc.tracking, "
            "robustloc.fusion.pipeline, robustloc.pipelines.locate; "
            "print('scipy.stats' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True)
    assert out.stdout.strip() == "False", out.stdout + out.stderr
