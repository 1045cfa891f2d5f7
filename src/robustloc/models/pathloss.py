"""Path-loss models: received power (dBm) <-> distance (m), vectorized both ways.

Three models, each a frozen dataclass whose parameters may be scalars (one model for all
anchors) or arrays of shape ``(m,)`` (one per anchor; they broadcast against the last axis
of ``(N, m)`` data):

* :class:`LogDistance` -- ``RSSI = A - 10 n lg d`` (seed 000, eq. (1)); ``A`` is the RSSI at
  1 m, ``n`` the path-loss exponent.
* :class:`AttenuationFactor` -- ``P_r(d) = P_r(d0) + 10 gamma lg(d0/d) + FAF``
  (seed 002, eq. (5)); paper's example ``d0 = 1 m, P_r(d0) = -29 dBm, gamma = 2.275,
  FAF = -1.076``.
* :class:`FreeSpace` -- Friis, ``P_r = P_t G_t G_r lambda^2 / ((4 pi)^2 d^2)`` (seed 002,
  eq. (1)), i.e. in dB ``P_r(d) = P_r(d0) + 20 lg(d0/d)`` (seed 002, eq. (4)).

All three are the same straight line in ``lg d``: ``rssi = A - 10 n lg d`` with

* attenuation factor: ``A = p0 + faf + 10 gamma lg d0``, ``n = gamma``;
* free space: ``A = p0 + 20 lg d0``, ``n = 2``.

:meth:`PathLossModel.log_distance_params` returns that ``(A, n)`` pair, which is what the
RSSI ranging estimators use.  Distances at or below zero give ``+inf`` dBm (``rssi``);
``distance`` of a NaN RSSI is NaN.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pandas as pd
from numpy.typing import ArrayLike, NDArray

from robustloc.errors import InputError

Array = NDArray[np.float64]

#: Speed of light (m/s), for the Friis wavelength.
SPEED_OF_LIGHT_M_S = 299_792_458.0
_LN10 = np.log(10.0)


def _arr(x: ArrayLike) -> Array:
    return np.asarray(x, dtype=float)


def _log10_pos(d: ArrayLike) -> Array:
    d = _arr(d)
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(d > 0, np.log10(np.where(d > 0, d, 1.0)), -np.inf)


class PathLossModel:
    """Common interface: ``rssi(distance_m)``, ``distance(rssi_dbm)`` and their slopes."""

    #: Name used on the command line (``--model``).
    name: str = "path-loss"

    def log_distance_params(self) -> tuple[Array, Array]:  # pragma: no cover - abstract
        """Equivalent ``(A, n)`` of ``rssi = A - 10 n lg d``."""
        raise NotImplementedError

    def rssi(self, distance_m: ArrayLike) -> Array:
        """Expected received power (dBm) at ``distance_m``; broadcasts over anchors."""
        A, n = self.log_distance_params()
        return A - 10.0 * n * _log10_pos(distance_m)

    def distance(self, rssi_dbm: ArrayLike) -> Array:
        """Distance (m) at which the model predicts ``rssi_dbm`` (the inverse of :meth:`rssi`)."""
        A, n = self.log_distance_params()
        return 10.0 ** ((A - _arr(rssi_dbm)) / (10.0 * n))

    def drssi_ddistance(self, distance_m: ArrayLike) -> Array:
        """Slope ``d rssi / d d = -10 n / (d ln 10)`` (dB per metre), for Jacobians."""
        _, n = self.log_distance_params()
        with np.errstate(divide="ignore"):
            return -10.0 * n / (_arr(distance_m) * _LN10)

    def distance_sigma(self, distance_m: ArrayLike, sigma_db: ArrayLike) -> Array:
        """First-order range standard deviation ``sigma_d = d ln10 sigma_dB / (10 n)``.

        The log-normal shadowing of ``sigma_dB`` maps to a distance error that grows in
        proportion to the distance (useful as WLS weights or a CRLB input).
        """
        _, n = self.log_distance_params()
        return _arr(distance_m) * _LN10 * _arr(sigma_db) / (10.0 * n)


@dataclass(frozen=True)
class LogDistance(PathLossModel):
    """Log-distance model ``RSSI = A - 10 n lg d`` (seed 000, eq. (1)).

    Parameters
    ----------
    A : float or array (m,)
        RSSI at 1 m (dBm).
    n : float or array (m,)
        Path-loss exponent (2 in free space, typically 1.5-4 indoors).
    """

    A: ArrayLike = -59.0
    n: ArrayLike = 2.0
    name = "log-distance"

    def __post_init__(self) -> None:
        n = _arr(self.n)
        if np.any(n[np.isfinite(n)] <= 0):
            raise ValueError(f"path-loss exponent n must be positive, got {self.n}")

    def log_distance_params(self) -> tuple[Array, Array]:
        return _arr(self.A), _arr(self.n)


@dataclass(frozen=True)
class AttenuationFactor(PathLossModel):
    """Attenuation-factor model ``P_r(d) = P_r(d0) + 10 gamma lg(d0/d) + FAF`` (seed 002, eq. (5)).

    Parameters
    ----------
    p0 : float or array (m,)
        Reference power ``P_r(d0)`` (dBm).
    gamma : float or array (m,)
        Same-floor path-loss exponent ``gamma_SF``.
    faf : float or array (m,)
        Floor/obstacle attenuation factor (dB).
    d0 : float or array (m,)
        Reference distance (m), default 1.

    Notes
    -----
    Only ``p0 + faf`` is identifiable from RSSI alone; the paper fixes ``p0`` as the
    measured reference power and fits ``gamma`` and ``FAF`` (see
    :mod:`robustloc.models.calibration`).
    """

    p0: ArrayLike = -29.0
    gamma: ArrayLike = 2.275
    faf: ArrayLike = -1.076
    d0: ArrayLike = 1.0
    name = "attenuation-factor"

    def __post_init__(self) -> None:
        g = _arr(self.gamma)
        d0 = _arr(self.d0)
        if np.any(g[np.isfinite(g)] <= 0):
            raise ValueError(f"gamma must be positive, got {self.gamma}")
        if np.any(d0[np.isfinite(d0)] <= 0):
            raise ValueError(f"d0 must be positive, got {self.d0}")

    def log_distance_params(self) -> tuple[Array, Array]:
        g = _arr(self.gamma)
        # seed 002 eq. (5) rewritten as A - 10 n lg d
        return _arr(self.p0) + _arr(self.faf) + 10.0 * g * np.log10(_arr(self.d0)), g


@dataclass(frozen=True)
class FreeSpace(PathLossModel):
    """Free-space (Friis) model, ``P_r(d) = P_r(d0) + 20 lg(d0/d)`` (seed 002, eqs. (1), (4)).

    Parameters
    ----------
    p0 : float or array (m,)
        Received power at ``d0`` (dBm).  Use :meth:`from_link_budget` to compute it from
        transmit power, antenna gains and frequency (eq. (1)).
    d0 : float or array (m,)
        Reference distance (m), default 1.
    """

    p0: ArrayLike = -40.0
    d0: ArrayLike = 1.0
    name = "friis"

    @classmethod
    def from_link_budget(
        cls,
        tx_power_dbm: ArrayLike,
        frequency_hz: ArrayLike,
        gain_tx_dbi: ArrayLike = 0.0,
        gain_rx_dbi: ArrayLike = 0.0,
        d0: ArrayLike = 1.0,
    ) -> FreeSpace:
        """Friis equation (seed 002, eq. (1)) in dB:
        ``P_r(d0) = P_t + G_t + G_r + 20 lg(lambda / (4 pi d0))``, ``lambda = c / f``."""
        lam = SPEED_OF_LIGHT_M_S / _arr(frequency_hz)
        p0 = (
            _arr(tx_power_dbm) + _arr(gain_tx_dbi) + _arr(gain_rx_dbi)
            + 20.0 * np.log10(lam / (4.0 * np.pi * _arr(d0)))
        )
        return cls(p0=p0, d0=d0)

    def log_distance_params(self) -> tuple[Array, Array]:
        p0 = _arr(self.p0)
        return p0 + 20.0 * np.log10(_arr(self.d0)), np.full_like(p0, 2.0)


MODELS: dict[str, type[PathLossModel]] = {
    "log-distance": LogDistance,
    "attenuation-factor": AttenuationFactor,
    "friis": FreeSpace,
}

#: Anchor-file columns of each model's parameters.
MODEL_COLUMNS: dict[str, tuple[str, ...]] = {
    "log-distance": ("A", "n"),
    "attenuation-factor": ("p0", "gamma", "faf", "d0"),
    "friis": ("p0", "d0"),
}


def model_from_anchors(anchors: pd.DataFrame, model: str | None = None) -> PathLossModel:
    """Build a per-anchor path-loss model (parameter arrays of shape ``(m,)``).

    Parameters
    ----------
    anchors : DataFrame
        Anchors frame (:func:`robustloc.io.read_anchors`), rows in the anchor order the
        estimator uses.
    model : {"log-distance", "attenuation-factor", "friis"}, optional
        Which columns to use.  Default: ``log-distance`` if ``A`` and ``n`` are present,
        else ``attenuation-factor`` if ``p0`` and ``gamma`` are (``faf`` defaults to 0 and
        ``d0`` to 1 when absent), else ``friis`` if ``p0`` is (the columns
        ``calibrate --model friis`` writes).

    Raises
    ------
    InputError
        A needed column is absent or has an empty value (naming the anchor and line).
    """
    cols = set(anchors.columns)
    if model is None:
        if {"A", "n"} <= cols:
            model = "log-distance"
        elif {"p0", "gamma"} <= cols:
            model = "attenuation-factor"
        elif "p0" in cols:  # as `calibrate --model friis` writes them
            model = "friis"
        else:
            raise InputError(
                "anchors have no path-loss parameters: need columns A, n (log-distance), "
                "p0, gamma[, faf, d0] (attenuation factor) or p0[, d0] (friis); run "
                "`robustloc calibrate`",
                anchors.attrs.get("path"),
                1,
            )
    if model not in MODELS:
        raise ValueError(f"unknown path-loss model {model!r}; one of {', '.join(MODELS)}")
    defaults = {"faf": 0.0, "d0": 1.0}
    params: dict[str, Array] = {}
    for c in MODEL_COLUMNS[model]:
        if c not in cols:
            if c in defaults:
                params[c] = np.full(len(anchors), defaults[c])
                continue
            raise InputError(
                f"anchors file has no column {c!r} needed by the {model} model",
                anchors.attrs.get("path"),
                1,
            )
        v = anchors[c].to_numpy(dtype=float)
        bad = ~np.isfinite(v)
        if bad.any():
            i = int(np.argmax(bad))
            line = int(anchors.index[i]) if anchors.index.name == "line" else None
            raise InputError(
                f"anchor {anchors['anchor'].iloc[i]!r} has no value for {c!r} "
                f"({model} model)",
                anchors.attrs.get("path"),
                line,
            )
        params[c] = v
    if model == "log-distance":
        return LogDistance(A=params["A"], n=params["n"])
    if model == "attenuation-factor":
        return AttenuationFactor(**params)
    return FreeSpace(**params)


def log_distance_arrays(anchors: pd.DataFrame, model: str | None = None) -> tuple[Array, Array]:
    """Per-anchor ``A (m,), n (m,)`` for the ranging estimators (see :func:`model_from_anchors`)."""
    return model_from_anchors(anchors, model).log_distance_params()
