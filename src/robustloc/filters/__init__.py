"""Batched Kalman filters (KF, EKF, UKF) with robust updates, and motion models.

See :mod:`robustloc.filters.core` for the step functions and how to plug in a custom
transition or measurement function, and :mod:`robustloc.filters.motion` for the CV/CA models
of seed 001.
"""

from robustloc.filters.core import (
    PLAIN,
    PREDICTED,
    RobustUpdate,
    SigmaPoints,
    UpdateResult,
    make_residual,
    numerical_jacobian,
    predict_ekf,
    predict_linear,
    predict_ukf,
    symmetrize,
    update_ekf,
    update_from_moments,
    update_linear,
    update_ukf,
    wrap_angle,
)
from robustloc.filters.motion import ConstantAcceleration, ConstantVelocity, motion_model

__all__ = [
    "PLAIN",
    "PREDICTED",
    "ConstantAcceleration",
    "ConstantVelocity",
    "RobustUpdate",
    "SigmaPoints",
    "UpdateResult",
    "make_residual",
    "motion_model",
    "numerical_jacobian",
    "predict_ekf",
    "predict_linear",
    "predict_ukf",
    "symmetrize",
    "update_ekf",
    "update_from_moments",
    "update_linear",
    "update_ukf",
    "wrap_angle",
]
