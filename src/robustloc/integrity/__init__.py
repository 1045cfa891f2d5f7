"""Integrity: global test, w-tests, B-method, data snooping and reliability (seed 003).

Import from here::

    from robustloc.integrity import (
        lambda0, global_alpha, global_critical, w_critical,      # B-method
        whiten, integrity_tests, global_and_w_tests,              # tests on one adjustment
        snoop, snoop_linear, SnoopingResult,                      # iterative data snooping
        reliability, Reliability,                                 # r_i, MDB, ext., rho_ij
    )

Conventions (all functions): batches of ``N`` epochs, ``n`` observations, ``p`` unknowns;
design ``H (N, n, p)``; observations / residuals ``(N, n)`` with NaN = missing; ``sigma`` the
a-priori standard deviation of each observation (scalar, ``(n,)`` or ``(N, n)``), weights
``P = diag(1 / sigma^2)`` and a-priori unit-weight sigma0 = 1.
"""

from robustloc.integrity.bmethod import (
    ALPHA0,
    BETA0,
    detection_power_global,
    detection_power_w,
    global_alpha,
    global_critical,
    lambda0,
    w_critical,
)
from robustloc.integrity.reliability import RHO_THRESHOLD, Reliability, reliability
from robustloc.integrity.snooping import SnoopingResult, snoop, snoop_linear
from robustloc.integrity.tests import (
    IntegrityTests,
    Whitened,
    global_and_w_tests,
    integrity_tests,
    whiten,
)

__all__ = [
    "ALPHA0",
    "BETA0",
    "RHO_THRESHOLD",
    "IntegrityTests",
    "Reliability",
    "SnoopingResult",
    "Whitened",
    "detection_power_global",
    "detection_power_w",
    "global_alpha",
    "global_and_w_tests",
    "global_critical",
    "integrity_tests",
    "lambda0",
    "reliability",
    "snoop",
    "snoop_linear",
    "w_critical",
    "whiten",
]
