"""Floating-point operation counts per filter step (seed 001, complexity section).

Counting rules of the paper: ``A +- B`` (n x m): ``nm``; ``A B`` (n x m by m x l):
``2mnl - nl``; ``A^-1`` (n x n): ``n^3``; Cholesky: about ``n^3 / 3``.  ``n`` is the state
dimension, ``l`` the measurement dimension.

UKF terms are the paper's (seed 001, listed in the digest).  The paper gives no EKF terms;
:func:`ekf_flops` applies the same rules to the EKF equations (linear prediction with the
transition matrix, Jacobian evaluation not counted, plain ``(I - K H) P`` update), so the two
are comparable.  Nonlinear function evaluations (``f``, ``h`` on sigma points) are not
counted by the paper either.
"""

from __future__ import annotations


def matmul(n: int, m: int, l: int) -> int:
    """Flops of an ``(n x m) (m x l)`` product: ``2 m n l - n l``."""
    return 2 * m * n * l - n * l


def ukf_flops(n: int, l: int) -> dict[str, int]:
    """The paper's UKF flop terms for state dimension ``n`` and measurement dimension ``l``.

    Returns the terms and their ``total``.
    """
    terms = {
        "gain": l**3 + 2 * n * l**2 - n * l,
        "state update": 2 * n * l + l,
        "covariance update": 2 * n * l**2 - n * l + 2 * n**2 * l,
        "state prediction": 2 * n**2 + 2 * n,
        "covariance prediction": 4 * n**3 + 5 * n**2 + 2 * n,
        "predicted sigma points": 4 * n**2 * l - l,
        "measurement mean": 2 * n * l + 2 * l,
        "P_Z": 4 * n * l**2 + 2 * n * l + 3 * l**2 + 2 * l,
        "P_XZ": 4 * n**2 * l + 2 * n**2 + 2 * n * l + 2 * n,
    }
    terms["total"] = sum(terms.values())
    return terms


def ekf_flops(n: int, l: int) -> dict[str, int]:
    """EKF flops by the paper's rules (see the module docstring)."""
    terms = {
        "state prediction": matmul(n, n, 1),
        "covariance prediction": 2 * matmul(n, n, n) + n * n,  # F P F^T + Q
        "innovation covariance": matmul(l, n, n) + matmul(l, n, l) + l * l,  # H P H^T + R
        "gain": matmul(n, n, l) + l**3 + matmul(n, l, l),  # P H^T S^-1
        "state update": l + matmul(n, l, 1) + n,  # x + K (z - h)
        "covariance update": matmul(n, l, n) + n * n + matmul(n, n, n),  # (I - K H) P
    }
    terms["total"] = sum(terms.values())
    return terms
