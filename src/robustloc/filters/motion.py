"""Kinematic motion models: constant velocity (CV) and constant acceleration (CA).

State ordering follows seed 001 sec. 2: blocks by derivative order, axes inside a block,
``[x, y, x', y']`` for CV and ``[x, y, x', y', x'', y'']`` for CA (``dim = 2``; ``dim = 3``
appends ``z`` to each block).  ``x`` is east, ``y`` north.

Process noise
-------------
Two standard choices, selected by ``noise``:

* ``"discrete"`` (the paper's form): ``X(k+1) = F X(k) + Gamma W(k)`` with ``W`` a piecewise
  constant acceleration (CV) or jerk (CA) of variance ``q`` per axis, so
  ``Q = q Gamma Gamma^T`` (seed 001, EKF and UKF models).
* ``"continuous"``: white-noise acceleration (CV) or jerk (CA) of spectral density ``q``
  integrated over the step (Bar-Shalom, Li, Kirubarajan 2001, sec. 6.2), e.g. for CV
  ``Q = q [[T^3/3, T^2/2], [T^2/2, T]]`` per axis.

``dt`` may be a scalar or one step per track, shape ``(K,)``; matrices then have shape
``(K, n, n)``.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache
from math import factorial
from typing import Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

Array = NDArray[np.float64]


def _kinematic_1d(order: int, dt: Array) -> tuple[Array, Array, Array]:
    """1-D blocks of a kinematic chain of ``s = order + 1`` states for one ``dt``.

    Returns ``F (s, s)``, ``Gamma (s,)`` and the continuous ``Q`` per unit intensity.
    """
    s = order + 1
    F = np.zeros((s, s))
    for i in range(s):
        for j in range(i, s):
            F[i, j] = dt ** (j - i) / factorial(j - i)
    # Gamma: effect of a constant highest derivative + 1 over the step (seed 001)
    G = np.array([dt ** (s - i) / factorial(s - i) for i in range(s)])
    Qc = np.zeros((s, s))
    for i in range(s):
        for j in range(s):
            a, b = s - 1 - i, s - 1 - j  # powers of dt in each entry of F's last column
            p = a + b + 1
            Qc[i, j] = dt**p / (p * factorial(a) * factorial(b))
    return F, G, Qc


@lru_cache(maxsize=32)
def _coefficients(order: int, dim: int) -> tuple[Array, Array, Array, Array]:
    """Polynomial coefficients in ``dt`` of ``F``, ``Gamma``, ``Gamma Gamma^T`` and the
    continuous ``Q``: ``M(dt) = sum_p dt^p C[p]``, expanded to ``dim`` axes.

    Every entry of these matrices is a monomial in ``dt``; evaluating them at ``dt = 1``
    gives the coefficient, and the power is read from the structure.  This makes a stack of
    ``K`` different steps cost one small matrix product.
    """
    s = order + 1
    P = 2 * s + 1
    F1, G1, Qc1 = _kinematic_1d(order, 1.0)
    CF = np.zeros((P, s, s))
    CG = np.zeros((P, s))
    CQd = np.zeros((P, s, s))
    CQc = np.zeros((P, s, s))
    for i in range(s):
        CG[s - i, i] = G1[i]
        for j in range(s):
            if j >= i:
                CF[j - i, i, j] = F1[i, j]
            CQd[(s - i) + (s - j), i, j] = G1[i] * G1[j]
            CQc[(s - 1 - i) + (s - 1 - j) + 1, i, j] = Qc1[i, j]
    eye = np.eye(dim)
    n = s * dim

    def ex(C: Array) -> Array:
        return np.einsum("pij,ab->piajb", C, eye).reshape(P, n, n)

    CGx = np.einsum("pi,ab->piab", CG, eye).reshape(P, n, dim)
    return ex(CF), CGx, ex(CQd), ex(CQc)


def _evaluate(C: Array, dt: ArrayLike) -> Array:
    d = np.asarray(dt, dtype=float)
    P = C.shape[0]
    powers = d[..., None] ** np.arange(P)  # (..., P)
    return (powers.reshape(-1, P) @ C.reshape(P, -1)).reshape(d.shape + C.shape[1:])


@dataclass(frozen=True)
class _Kinematic:
    q: float = 1.0
    dim: int = 2
    noise: Literal["discrete", "continuous"] = "discrete"
    order: int = 1
    name: str = "kinematic"

    def __post_init__(self) -> None:
        if self.dim not in (1, 2, 3):
            raise ValueError(f"dim must be 1, 2 or 3, got {self.dim}")
        if not self.q >= 0:
            raise ValueError(f"process noise intensity q must be >= 0, got {self.q}")
        if self.noise not in ("discrete", "continuous"):
            raise ValueError(f"noise must be 'discrete' or 'continuous', got {self.noise!r}")

    @property
    def n_states(self) -> int:
        """State dimension ``(order + 1) * dim``."""
        return (self.order + 1) * self.dim

    def index(self, derivative: int, axis: int) -> int:
        """Position of ``d^derivative / dt`` of ``axis`` in the state vector."""
        return derivative * self.dim + axis

    def FQ(self, dt: float) -> tuple[Array, Array]:
        """``(F(dt), Q(dt))`` for a scalar step, cached (read-only arrays; hot path)."""
        return _fq_cached(self, float(dt))

    def F(self, dt: ArrayLike) -> Array:
        """Transition matrix (seed 001: CV ``F`` of the EKF model, CA of the UKF model)."""
        return _evaluate(_coefficients(self.order, self.dim)[0], dt)

    def Gamma(self, dt: ArrayLike) -> Array:
        """Noise input matrix ``Gamma``, shape ``(n, dim)`` (or ``(K, n, dim)``)."""
        return _evaluate(_coefficients(self.order, self.dim)[1], dt)

    def Q(self, dt: ArrayLike) -> Array:
        """Process noise covariance for a step ``dt`` (see module docstring)."""
        C = _coefficients(self.order, self.dim)
        return self.q * _evaluate(C[2] if self.noise == "discrete" else C[3], dt)

    def f(self, x: ArrayLike, dt: ArrayLike) -> Array:
        """Propagate states ``x (K, n)`` by ``dt`` (linear: ``F x``)."""
        x = np.asarray(x, dtype=float)
        F = self.F(dt)
        if F.ndim == 2:
            return x @ F.T
        return np.einsum("kij,kj->ki", F, x)


@dataclass(frozen=True)
class ConstantVelocity(_Kinematic):
    """Constant velocity model, state ``[p, v]`` per axis (seed 001, EKF model).

    ``F = [[1, T], [0, 1]]`` and ``Gamma = [T^2/2, T]`` per axis, ``q`` the variance of the
    white acceleration (``noise="discrete"``, ``(m/s^2)^2``) or its spectral density
    (``noise="continuous"``, ``m^2/s^3``).
    """

    order: int = 1
    name: str = "cv"


@dataclass(frozen=True)
class ConstantAcceleration(_Kinematic):
    """Constant acceleration model, state ``[p, v, a]`` per axis (seed 001, UKF model).

    ``F = [[1, T, T^2/2], [0, 1, T], [0, 0, 1]]`` and ``Gamma = [T^3/6, T^2/2, T]`` per axis
    (jerk input), ``q`` the jerk variance (discrete) or spectral density (continuous).
    """

    order: int = 2
    name: str = "ca"


@dataclass(frozen=True)
class RandomWalkAugmented:
    """A kinematic model with ``extra`` random-walk states appended to its state vector.

    ``x = [kinematic states, c_1 .. c_extra]``: the kinematic block moves as ``base``, each
    appended state is a random walk ``c(k+1) = c(k) + w``, ``w ~ N(0, q_extra dt)`` (a
    slowly drifting constant such as a receiver's range offset; Brown & Hwang 2012,
    sec. 9.2, the clock-bias state of GNSS filters).  ``F = diag(F_base, I)``,
    ``Q = diag(Q_base, q_extra dt I)``.

    Parameters
    ----------
    base : the kinematic model (``cv``, ``ca`` or a position random walk).
    q_extra : variance growth of each appended state per second (unit^2 / s).
    extra : number of appended states.
    """

    base: _Kinematic
    q_extra: float = 0.0
    extra: int = 1

    def __post_init__(self) -> None:
        if not (np.isfinite(self.q_extra) and self.q_extra >= 0):
            raise ValueError(f"q_extra must be finite and >= 0, got {self.q_extra}")
        if self.extra < 1:
            raise ValueError(f"extra must be >= 1, got {self.extra}")

    @property
    def n_states(self) -> int:
        """State dimension: the base model's plus ``extra``."""
        return self.base.n_states + self.extra

    @property
    def dim(self) -> int:
        """Spatial axes of the kinematic block (the base model's)."""
        return self.base.dim

    def _pad(self, A: Array, diag: Array) -> Array:
        nb = A.shape[-1]
        out = np.zeros(A.shape[:-2] + (nb + self.extra, nb + self.extra))
        out[..., :nb, :nb] = A
        i = np.arange(nb, nb + self.extra)
        out[..., i, i] = diag[..., None]
        return out

    def F(self, dt: ArrayLike) -> Array:
        """``diag(F_base(dt), I)``."""
        dt = np.asarray(dt, dtype=float)
        return self._pad(self.base.F(dt), np.ones_like(dt))

    def Q(self, dt: ArrayLike) -> Array:
        """``diag(Q_base(dt), q_extra |dt| I)``."""
        dt = np.asarray(dt, dtype=float)
        return self._pad(self.base.Q(dt), self.q_extra * np.abs(dt))

    def FQ(self, dt: float) -> tuple[Array, Array]:
        """``(F(dt), Q(dt))`` for a scalar step."""
        return self.F(float(dt)), self.Q(float(dt))


@lru_cache(maxsize=256)
def _fq_cached(model: _Kinematic, dt: float) -> tuple[Array, Array]:
    F, Q = model.F(dt), model.Q(dt)
    F.flags.writeable = False
    Q.flags.writeable = False
    return F, Q


def motion_model(
    name: str, q: float = 1.0, dim: int = 2, noise: Literal["discrete", "continuous"] = "discrete"
) -> ConstantVelocity | ConstantAcceleration:
    """Build a motion model by its command-line name, ``cv`` or ``ca``."""
    key = name.lower()
    if key == "cv":
        return ConstantVelocity(q=q, dim=dim, noise=noise)
    if key == "ca":
        return ConstantAcceleration(q=q, dim=dim, noise=noise)
    raise ValueError(f"unknown motion model {name!r}; choose cv or ca")
