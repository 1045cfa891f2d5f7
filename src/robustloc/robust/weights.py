"""Robust weight functions, one class each, in the style of statsmodels' ``robust.norms``.

Every function takes *standardized* residuals ``u`` (residual divided by its standard
error, seed 000 sec. 2.1: ``u = v / (sigma sqrt(Q_vv,ii))``) and exposes

* ``weights(u)``: the equivalent weight ``p(u) = psi(u) / u`` used by IRLS and by the robust
  Kalman gain ``K D`` (seed 002 eq. 12);
* ``psi(u)``: the influence function ``d rho / du``;
* ``rho(u)``: the objective function, ``rho(0) = 0``.

All methods are vectorized and accept any array shape; NaN in gives NaN out.
The same objects serve robust trilateration and the robust Kalman filters.
"""

from __future__ import annotations

from dataclasses import dataclass, fields

import numpy as np
from numpy.typing import ArrayLike, NDArray

Array = NDArray[np.float64]


class WeightFunction:
    """Base class: subclasses implement :meth:`weights` and :meth:`rho`.

    ``psi`` defaults to ``u * weights(u)``, which is its definition.
    """

    #: Short name used on the command line and in output files.
    name: str = "weight"

    def weights(self, u: ArrayLike) -> Array:  # pragma: no cover - abstract
        raise NotImplementedError

    def rho(self, u: ArrayLike) -> Array:  # pragma: no cover - abstract
        raise NotImplementedError

    def psi(self, u: ArrayLike) -> Array:
        """Influence function ``psi(u) = u p(u) = d rho / du``."""
        u = _real(u)
        return u * self.weights(u)

    def __call__(self, u: ArrayLike) -> Array:
        return self.weights(u)

    @property
    def rejection_threshold(self) -> float:
        """``|u|`` beyond which the weight is zero (``inf`` if never)."""
        return float("inf")


def _real(u: ArrayLike) -> Array:
    """``u`` as floats; ``TypeError`` for complex numbers (whose imaginary part
    ``np.asarray(u, dtype=float)`` drops with only a warning: the API review)."""
    a = np.asarray(u)
    if np.iscomplexobj(a):
        raise TypeError("standardized residuals must be real numbers, got complex ones")
    return a.astype(float, copy=False)


def _abs(u: ArrayLike) -> Array:
    return np.abs(_real(u))


def _check_real(key: str, value: object) -> None:
    """``ValueError`` naming the parameter ``key`` unless ``value`` is a real number (not a
    bool, a string, None, a list or NaN): the constructors' and :func:`get_weight`'s check."""
    if isinstance(value, bool | np.bool_ | np.complexfloating) or not isinstance(
            value, int | float | np.number) or np.isnan(value):
        raise ValueError(f"weight parameter {key} must be a real number, got {value!r}")


def _check_fields(wf: WeightFunction) -> None:
    """:func:`_check_real` on every parameter of the dataclass ``wf`` (a string, None or a
    list gave Python's "'>' not supported ..."; ``True`` was taken as 1)."""
    for f in fields(wf):  # type: ignore[arg-type]
        _check_real(f.name, getattr(wf, f.name))


@dataclass(frozen=True)
class LeastSquares(WeightFunction):
    """Ordinary least squares: ``p(u) = 1``, ``rho(u) = u^2 / 2``."""

    name = "ls"

    def weights(self, u: ArrayLike) -> Array:
        u = _real(u)
        return np.where(np.isnan(u), np.nan, 1.0)

    def rho(self, u: ArrayLike) -> Array:
        u = _real(u)
        return 0.5 * u * u


@dataclass(frozen=True)
class Huber(WeightFunction):
    """Huber's weight function (seed 000, eq. (5)).

    ``p(u) = 1`` for ``|u| <= c``, ``c / |u|`` otherwise; ``rho(u) = u^2/2`` inside,
    ``c |u| - c^2/2`` outside.  The paper uses ``c = 2`` (statsmodels' ``HuberT`` uses
    ``t = 1.345`` for 95 % efficiency; the formula is the same).
    """

    c: float = 2.0
    name = "huber"

    def __post_init__(self) -> None:
        _check_fields(self)
        if not self.c > 0:
            raise ValueError(f"Huber threshold c must be positive, got {self.c}")

    def weights(self, u: ArrayLike) -> Array:
        a = _abs(u)
        with np.errstate(all="ignore"):
            return np.where(a <= self.c, 1.0, self.c / a) * np.where(np.isnan(a), np.nan, 1.0)

    def rho(self, u: ArrayLike) -> Array:
        a = _abs(u)
        return np.where(a <= self.c, 0.5 * a * a, self.c * a - 0.5 * self.c**2)


@dataclass(frozen=True)
class Hampel(WeightFunction):
    """Hampel's three-part redescending function (seed 000, eq. (6)).

    ``p(u) = 1`` for ``|u| <= a``; ``a/|u|`` for ``a < |u| <= b``;
    ``a (c - |u|) / ((c - b) |u|)`` for ``b < |u| <= c``; ``0`` beyond ``c``.
    Paper's defaults ``a = 1.7, b = 3.4, c = 8.5`` (statsmodels' ``Hampel`` has the same
    form with ``a = 2, b = 4, c = 8``).
    """

    a: float = 1.7
    b: float = 3.4
    c: float = 8.5
    name = "hampel"

    def __post_init__(self) -> None:
        _check_fields(self)
        if not 0 < self.a <= self.b < self.c:
            raise ValueError(f"Hampel needs 0 < a <= b < c, got {self.a}, {self.b}, {self.c}")

    @property
    def rejection_threshold(self) -> float:
        return self.c

    def weights(self, u: ArrayLike) -> Array:
        x = _abs(u)
        a, b, c = self.a, self.b, self.c
        with np.errstate(all="ignore"):
            w = np.select(
                [x <= a, x <= b, x <= c],
                [np.ones_like(x), a / x, a * (c - x) / ((c - b) * x)],
                0.0,
            )
        return np.where(np.isnan(x), np.nan, w)

    def rho(self, u: ArrayLike) -> Array:
        x = _abs(u)
        a, b, c = self.a, self.b, self.c
        r_b = a * b - 0.5 * a * a
        r_mid = r_b + a / (c - b) * (c * x - 0.5 * x * x - c * b + 0.5 * b * b)
        r_c = r_b + 0.5 * a * (c - b)
        r = np.select([x <= a, x <= b, x <= c], [0.5 * x * x, a * x - 0.5 * a * a, r_mid], r_c)
        return np.where(np.isnan(x), np.nan, r)  # (select's default took NaN: r_c)


@dataclass(frozen=True)
class IGG(WeightFunction):
    """Zhou Jiangwen's IGG scheme (seed 000, eq. (7)).

    ``p(u) = 1`` for ``|u| < k0``; ``1 / (|u| + C)`` for ``k0 <= |u| < k1``; ``0`` for
    ``|u| >= k1``.  Paper: ``k0 = 1.5, k1 = 2.5``, ``C`` "a quantity small relative to
    ``|u|``" (default ``1e-3``).  The weight jumps at ``k0`` (to about ``1/k0``): this is
    the paper's function, kept as written; :class:`IGG3` is the continuous variant.
    """

    k0: float = 1.5
    k1: float = 2.5
    c: float = 1e-3
    name = "igg"

    def __post_init__(self) -> None:
        _check_fields(self)
        if not 0 < self.k0 < self.k1 or not self.c >= 0:  # (NaN refused)
            raise ValueError(
                f"IGG needs 0 < k0 < k1 and c >= 0, got {self.k0}, {self.k1}, {self.c}"
            )

    @property
    def rejection_threshold(self) -> float:
        return self.k1

    def weights(self, u: ArrayLike) -> Array:
        x = _abs(u)
        with np.errstate(all="ignore"):
            w = np.select([x < self.k0, x < self.k1], [np.ones_like(x), 1.0 / (x + self.c)], 0.0)
        return np.where(np.isnan(x), np.nan, w)

    def rho(self, u: ArrayLike) -> Array:
        x = _abs(u)
        k0, k1, c = self.k0, self.k1, self.c

        def mid(t: Array) -> Array:  # integral of t / (t + C) from k0
            return 0.5 * k0 * k0 + (t - k0) - c * np.log((t + c) / (k0 + c))

        with np.errstate(all="ignore"):
            r = np.select(
                [x < k0, x < k1], [0.5 * x * x, mid(x)], mid(np.asarray(k1, dtype=float))
            )
        return np.where(np.isnan(x), np.nan, r)  # (select's default took NaN: rho(k1))


@dataclass(frozen=True)
class IGG3(WeightFunction):
    """Yang Yuanxi's IGG-III scheme (ref. [14] of seed 000), continuous and redescending.

    ``p(u) = 1`` for ``|u| <= k0``; ``(k0/|u|) ((k1 - |u|)/(k1 - k0))^2`` for
    ``k0 < |u| <= k1``; ``0`` beyond.  Usual ``k0 = 1.0..1.5``, ``k1 = 2.5..8.0``.
    """

    k0: float = 1.5
    k1: float = 3.0
    name = "igg3"

    def __post_init__(self) -> None:
        _check_fields(self)
        if not 0 < self.k0 < self.k1:
            raise ValueError(f"IGG3 needs 0 < k0 < k1, got {self.k0}, {self.k1}")

    @property
    def rejection_threshold(self) -> float:
        return self.k1

    def weights(self, u: ArrayLike) -> Array:
        x = _abs(u)
        k0, k1 = self.k0, self.k1
        with np.errstate(all="ignore"):
            w = np.select(
                [x <= k0, x <= k1], [np.ones_like(x), (k0 / x) * ((k1 - x) / (k1 - k0)) ** 2], 0.0
            )
        return np.where(np.isnan(x), np.nan, w)

    def rho(self, u: ArrayLike) -> Array:
        x = _abs(u)
        k0, k1 = self.k0, self.k1
        g = k0 / (3.0 * (k1 - k0) ** 2)
        mid = 0.5 * k0 * k0 + g * ((k1 - k0) ** 3 - (k1 - np.minimum(x, k1)) ** 3)
        return np.where(x <= k0, 0.5 * x * x, mid)


@dataclass(frozen=True)
class AsymmetricIGG(WeightFunction):
    """Asymmetric equivalent weight for left-skewed errors (seed 002, eq. (14)).

    With ``e`` the standardized innovation::

        D(e) = 0                                  e < -C
             = (-K0/e) (C + e)/(C - K0)           -C <= e < -K0
             = 1                                  -K0 <= e < K0
             = (K0/e) ((K1 - e)/(K1 - K0))^2      K0 <= e < K1
             = 0                                  e >= K1

    The negative side decays linearly in ``psi`` down to zero at ``-C``; the positive side
    is IGG-III.  The paper's adaptive choice is ``K0 = 2 s``, ``K1 = C = 3 s`` with ``s`` the
    standard error of the residuals; with standardized ``e`` that is ``K0 = 2, K1 = C = 3``.
    """

    k0: float = 2.0
    k1: float = 3.0
    c: float = 3.0
    name = "asymmetric-igg"

    def __post_init__(self) -> None:
        _check_fields(self)
        if not (0 < self.k0 < self.k1 and self.k0 < self.c):
            raise ValueError(
                f"AsymmetricIGG needs 0 < k0 < k1 and k0 < c, got {self.k0}, {self.k1}, {self.c}"
            )

    @property
    def rejection_threshold(self) -> float:
        return min(self.k1, self.c)

    def weights(self, u: ArrayLike) -> Array:
        e = _real(u)
        k0, k1, c = self.k0, self.k1, self.c
        with np.errstate(all="ignore"):
            w = np.select(
                [e < -c, e < -k0, e < k0, e < k1],
                [
                    np.zeros_like(e),
                    (-k0 / e) * (c + e) / (c - k0),  # seed 002 eq. (14), negative branch
                    np.ones_like(e),
                    (k0 / e) * ((k1 - e) / (k1 - k0)) ** 2,  # eq. (14), positive branch
                ],
                0.0,
            )
        return np.where(np.isnan(e), np.nan, w)

    def rho(self, u: ArrayLike) -> Array:
        e = _real(u)
        k0, k1, c = self.k0, self.k1, self.c
        g = k0 / (3.0 * (k1 - k0) ** 2)
        pos = 0.5 * k0 * k0 + g * ((k1 - k0) ** 3 - (k1 - np.minimum(e, k1)) ** 3)
        en = np.maximum(e, -c)
        neg = 0.5 * k0 * k0 + k0 / (2.0 * (c - k0)) * ((c - k0) ** 2 - (c + en) ** 2)
        return np.select([e < -k0, e < k0], [neg, 0.5 * e * e], pos)


_REGISTRY: dict[str, type[WeightFunction]] = {
    "ls": LeastSquares,
    "huber": Huber,
    "hampel": Hampel,
    "igg": IGG,
    "igg3": IGG3,
    "asymmetric-igg": AsymmetricIGG,
}


#: Names that mean the same weight, as the commands spell them: ``none`` (``filter``,
#: ``fuse``: no robust weight) is ``ls``; ``asym`` (``locate``'s method) is
#: ``asymmetric-igg``.  Each command accepts every name of a set and keeps its own.
WEIGHT_EQUIVALENTS: tuple[tuple[str, ...], ...] = (("ls", "none"), ("asymmetric-igg", "asym"))


def weight_synonyms(names: tuple[str, ...] | list[str]) -> dict[str, str]:
    """The other spellings of ``names``' weights (:data:`WEIGHT_EQUIVALENTS`), each mapped
    to the one in ``names``.

    Examples
    --------
    >>> weight_synonyms(("none", "huber", "asymmetric-igg"))
    {'ls': 'none', 'asym': 'asymmetric-igg'}
    """
    out: dict[str, str] = {}
    for group in WEIGHT_EQUIVALENTS:
        own = [g for g in group if g in names]
        if len(own) == 1:
            out.update({g: own[0] for g in group if g != own[0]})
    return out


def get_weight(name: str, **params: float) -> WeightFunction:
    """Build a weight function by its command-line name (``huber``, ``igg3``, ...).

    Parameters
    ----------
    name : str
        One of ``ls, huber, hampel, igg, igg3, asymmetric-igg`` (or ``none``, ``asym``:
        :data:`WEIGHT_EQUIVALENTS`).
    **params : float
        Constructor arguments overriding the paper's defaults.
    """
    if not isinstance(name, str):  # (None or 3: AttributeError 'lower', the API review)
        raise TypeError(f"a weight function's name must be a string, got {name!r}")
    try:
        low = name.lower()
        cls = _REGISTRY[weight_synonyms(tuple(_REGISTRY)).get(low, low)]
    except KeyError:
        raise ValueError(
            f"unknown weight function {name!r}; choose one of {', '.join(_REGISTRY)}"
        ) from None
    known = [f.name for f in fields(cls)]
    for key, value in params.items():  # ({'c': 'x'} said "'<' not supported ...")
        if key not in known:  # (was Python's "__init__() got an unexpected keyword")
            raise ValueError(f"{cls.name} has no parameter {key!r}; its parameters: "
                             + (", ".join(known) or "none"))
        _check_real(key, value)
    return cls(**params)
