"""Robust weight functions and robust scale estimators (shared by IRLS and Kalman filters)."""

from robustloc.robust.scale import mad_scale
from robustloc.robust.weights import (
    IGG,
    IGG3,
    AsymmetricIGG,
    Hampel,
    Huber,
    LeastSquares,
    WeightFunction,
    get_weight,
)

__all__ = [
    "IGG",
    "IGG3",
    "AsymmetricIGG",
    "Hampel",
    "Huber",
    "LeastSquares",
    "WeightFunction",
    "get_weight",
    "mad_scale",
]
