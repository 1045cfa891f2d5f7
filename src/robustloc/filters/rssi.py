"""Robust RSSI Kalman filter, one filter per (tag, anchor) link (seed 002, sec. 2-3).

Every link (one receiver hearing one transmitter) carries the state
``X = [P_r, d, v]``: the received power (dBm), the distance (m) and the radial speed
(m/s, positive moving away).  All links of all tags are filtered together: the links are the
batch axis, the loop runs over the *k-th sample of every link* (a ragged log is laid out as a
``(T, L)`` array, NaN-padded), so the cost is ``T`` vectorized steps whatever ``L`` is.

State model (seed 002, eq. (15)), near-constant radial acceleration ``a`` over the
sampling interval ``t``::

    d_{k+1}   = d_k + v_k t + a t^2 / 2
    v_{k+1}   = v_k + a t
    P_{k+1}   = P_k + 10 n lg(d_k / d_{k+1})

The paper writes ``20 lg(d_k / (d_k + v_k t))``, the free-space exponent ``n = 2``.  Here
``n`` is the link's path-loss exponent (``gamma`` of the attenuation-factor model, seed 002
eq. (5)) so that the predicted power stays on the calibrated model curve when the distance
changes; ``RobustRssiFilter(exponent=2.0)`` is the paper's equation literally, and it is
also the fallback when the anchor has no exponent.

Measurement (eq. (16)): ``RSSI = [1 0 0] X + r``, ``r ~ N(0, R)``.

Observability: the power changes by ``-c v t / d`` per step, so the RSSI sequence fixes
only the ratio ``v / d``; the distance state is anchored by its initial value (the inverse
of eq. (5) at the first sample, with the matching ``cov(P, d)``) and by that correlation,
and it random-walks with the speed errors afterwards (on the simulated walk its median
error is several metres; it can collapse to the floor, where the transition becomes so
sensitive that the filter stops smoothing).  The fix used here (``model_sigma_db``,
default 3 dB, ``None`` for the paper's model literally) ties the two through eq. (5): after
each update the pseudo-observation ``0 = P_r - (A - c ln d) + w``, ``w ~ N(0, sigma_m^2)``
(``sigma_m`` the path-loss model's misfit, 1.59 dB in the paper's calibration), linearized
as ``h = [1, c/d, 0]``, keeps ``d`` on the model curve through ``P_r``.  Only ``d`` and
``v`` are corrected (the power component of the tie's gain is zero, a Schmidt "consider"
update): the tie re-uses information the power already holds and must not count it twice.
For a static link (``v = 0``) the power row of ``Phi`` does not involve ``d``, so the
filtered power is exactly that of the paper's filter there.  Distances for positioning are
taken from the filtered power through the path-loss model (the ``distance`` column of
:func:`filter_measurements`); the state ``d`` is reported as ``distance_state``.

Jacobian (eq. (17), garbled in the source; derived here).  With ``c = 10 n / ln 10`` and
``d' = d + v t`` (the mean prediction, ``a = 0``)::

    dP'/dP = 1
    dP'/dd = c (1/d - 1/d') = c v t / (d d')
    dP'/dv = -c t / d'
    dd'/dd = 1,  dd'/dv = t,  dv'/dv = 1,  all other entries 0

so ``Phi = [[1, c v t/(d d'), -c t/d'], [0, 1, t], [0, 0, 1]]``.  At ``v = 0`` the power
row is ``[1, 0, -c t/d]``: a radial speed changes the power, a distance alone does not.

Process noise: the acceleration enters every component through
``G = dX'/da = [-c (t^2/2) / d', t^2/2, t]`` (the power term follows from
``P' = P + 10 n lg(d/d')`` with ``d' = d + v t + a t^2/2``), so
``Q = sigma_a^2 G G^T + diag(q_P t, 0, 0)``; the second term is a random walk of the power
itself (shadowing and environment changes that are not a distance change).

Robust update (seed 002, eqs. (12)-(13)): the gain is re-weighted by the equivalent weight
``D`` of the standardized innovation, ``K^ = K D``, ``X+ = X- + K^ (Z - H X-)``; ``D`` is
any :class:`~robustloc.robust.weights.WeightFunction`, by default the asymmetric weight of
eq. (14), :class:`~robustloc.robust.weights.AsymmetricIGG` with ``K0 = 2, K1 = C = 3``.
The covariance is the Joseph form of the shared core, ``P- - D (2 - D) h h^T / S``
(``h = P- H^T``): the paper's ``(I - K^ H) P-`` for ``D`` = 0 or 1, and the true
covariance of the down-weighted estimate in between (see :func:`scalar_update`).

Shared core: the prediction runs through :func:`robustloc.filters.core.predict_ekf` with the
transition and Jacobian above; the update is either the core's
:func:`~robustloc.filters.core.update_linear` (``engine="core"``) or its closed form for
``H = [1 0 0]`` (``engine="scalar"``, default, several times faster); both give the same
numbers (tested).

Adaptive thresholds.  The paper sets ``K0 = 2 s`` and ``K1 = C = 3 s`` with ``s`` "the
standard error of the residuals".  Dividing the innovation by ``s`` and using the fixed
``K0 = 2, K1 = C = 3`` is the same thing.  ``s`` is, per link,

``s_k = max(s_emp, sqrt(S_k))``

where ``S_k = P-_PP + R`` is the innovation variance the filter predicts and ``s_emp`` a
running, outlier-proof estimate of the spread of the innovations actually seen: an
exponentially weighted mean of ``|e|`` winsorized at ``C s`` and scaled by ``sqrt(pi/2)``
(``E|e| = s sqrt(2/pi)`` for normal ``e``)::

    s_emp <- (1 - lambda) s_emp + lambda sqrt(pi/2) min(|e|, C s)

with ``lambda = 1/scale_window`` (default 20 samples) and ``s_emp`` starting at
``sqrt(R)``.  Winsorizing keeps a burst of outliers from inflating the scale it is judged
by; the ``max`` keeps the test from rejecting the legitimately large innovations of a
filter that has just started or is mis-tuned with too small an ``R``.

Environment changes (a door closing, a person standing still in the path) shift the power
level for good: every later innovation is then rejected, and only the slowly growing
predicted variance would let the new level in.  When a link would reject its
``max_rejected``-th consecutive sample (default 8, the paper's decorrelation lag), that
sample is taken with weight one and the power variance is first inflated by ``e^2``, so the
filter re-locks to the new level at once.  A young link re-locks sooner: at the rejection
that makes its consecutive rejections outnumber the samples it has taken (weight above
zero, its first one included) since it started or restarted, as when its first sample was
a fade and the good samples after it were rejected (3 samples taken, then re-locked at
the 4th rejection in a row).  ``max_rejected=0`` disables both.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray

from robustloc._arrays import to_number
from robustloc.filters import core
from robustloc.models.pathloss import AttenuationFactor
from robustloc.robust.weights import AsymmetricIGG, WeightFunction

Array = NDArray[np.float64]

LN10 = float(np.log(10.0))
#: Measurement matrix of seed 002 eq. (16): the filter observes the power only.
_H = np.array([[1.0, 0.0, 0.0]])


def _attenuation(params: LinkParams, idx: ArrayLike | slice = slice(None)) -> AttenuationFactor:
    """The shared attenuation-factor model (seed 002 eq. (5)) of the links ``idx``."""
    return AttenuationFactor(p0=params.p0_dbm[idx], gamma=params.gamma[idx],
                             faf=params.faf_db[idx], d0=params.d0_m[idx])


# ---------------------------------------------------------------------------------------
# State model (seed 002 eq. (15)), its Jacobian (eq. (17), derived) and process noise
# ---------------------------------------------------------------------------------------


def transition(
    x: ArrayLike, dt_s: ArrayLike, exponent: ArrayLike = 2.0, min_distance_m: float = 0.1
) -> Array:
    """Mean state prediction of seed 002 eq. (15) (``a = 0``), batched over ``x (..., 3)``.

    Distances are kept at or above ``min_distance_m`` (the log is undefined at zero).
    """
    x = np.asarray(x, dtype=float)
    dt = np.asarray(dt_s, dtype=float)
    d = np.maximum(x[..., 1], min_distance_m)
    d1 = np.maximum(d + x[..., 2] * dt, min_distance_m)
    out = np.empty(np.broadcast_shapes(x.shape, dt.shape + (3,)))
    out[..., 0] = x[..., 0] + 10.0 * np.asarray(exponent) * np.log10(d / d1)  # eq. (15)
    out[..., 1] = d1
    out[..., 2] = x[..., 2]
    return out


def transition_jacobian(
    x: ArrayLike, dt_s: ArrayLike, exponent: ArrayLike = 2.0, min_distance_m: float = 0.1
) -> Array:
    """``Phi = d f / d X`` of eq. (15) at ``x`` (eq. (17), derived in the module docstring).

    Returns an array of shape ``(..., 3, 3)``.
    """
    x = np.asarray(x, dtype=float)
    dt = np.asarray(dt_s, dtype=float)
    c = 10.0 * np.asarray(exponent, dtype=float) / LN10
    d = np.maximum(x[..., 1], min_distance_m)
    d1 = np.maximum(d + x[..., 2] * dt, min_distance_m)
    shape = np.broadcast_shapes(x.shape[:-1], dt.shape)
    phi = np.zeros(shape + (3, 3))
    phi[..., 0, 0] = 1.0
    phi[..., 0, 1] = c * (1.0 / d - 1.0 / d1)
    phi[..., 0, 2] = -c * dt / d1
    phi[..., 1, 1] = 1.0
    phi[..., 1, 2] = dt
    phi[..., 2, 2] = 1.0
    return phi


def process_noise(
    x: ArrayLike, dt_s: ArrayLike, sigma_accel_mps2: float, q_rssi_db2_per_s: float,
    exponent: ArrayLike = 2.0, min_distance_m: float = 0.1,
) -> Array:
    """``Q = sigma_a^2 G G^T + diag(q_P t, 0, 0)``, ``G = [-c t^2/(2 d'), t^2/2, t]``."""
    x = np.asarray(x, dtype=float)
    dt = np.asarray(dt_s, dtype=float)
    c = 10.0 * np.asarray(exponent, dtype=float) / LN10
    d = np.maximum(x[..., 1], min_distance_m)
    d1 = np.maximum(d + x[..., 2] * dt, min_distance_m)
    g = np.stack(np.broadcast_arrays(-c * 0.5 * dt * dt / d1, 0.5 * dt * dt, dt), axis=-1)
    q = sigma_accel_mps2**2 * g[..., :, None] * g[..., None, :]
    q[..., 0, 0] += q_rssi_db2_per_s * dt
    return q


def scalar_update(
    x: Array, P: Array, innovation: Array, S: Array, D: Array
) -> tuple[Array, Array]:
    """Robust update with ``H = [1 0 0]`` in closed form, batched over links.

    ``K = P- H^T / S``, ``K^ = K D`` (seed 002, eq. (12)), ``X+ = X- + K^ e`` (eq. (13)).
    The covariance is the Joseph form the shared core uses
    (:func:`robustloc.filters.core.update_from_moments`),
    ``(I - K^ H) P- (I - K^ H)^T + K^ R K^^T = P- - D (2 - D) h h^T / S`` with ``h = P- H^T``;
    for ``D`` in ``{0, 1}`` this is the paper's ``(I - K^ H) P-``, and for ``0 < D < 1`` it is
    the actual covariance of the down-weighted estimate.  This is the ``m = 1`` case of
    :func:`robustloc.filters.core.update_linear` written out, to run at millions of
    samples per second (the generic update solves ``(K, m, m)`` systems and builds status
    strings each step); ``RobustRssiFilter(engine="core")`` runs the core's update instead
    and the tests check both agree.
    """
    h = P[:, :, 0]
    x = x + (D * innovation / S)[:, None] * h
    P = P - (D * (2.0 - D) / S)[:, None, None] * (h[:, :, None] * h[:, None, :])
    return x, P


class _Rescaled(WeightFunction):
    """``p(e r)``: a weight function applied to innovations re-standardized by ``r``.

    The shared core standardizes each innovation by ``sqrt(S)``; the adaptive filter
    standardizes by ``s = max(s_emp, sqrt(S))`` (module docstring), i.e. multiplies the
    core's ``e`` by ``r = sqrt(S) / s``.  ``force`` marks links whose weight is 1 (re-lock).
    """

    def __init__(self, inner: WeightFunction, ratio: Array, force: Array) -> None:
        self.inner = inner
        self.ratio = ratio
        self.force = force
        self.name = inner.name

    def weights(self, u: ArrayLike) -> Array:
        return np.where(self.force, 1.0, self.inner.weights(np.asarray(u) * self.ratio))

    def rho(self, u: ArrayLike) -> Array:
        return self.inner.rho(np.asarray(u) * self.ratio)


class _ModelTerms:
    """:func:`transition`, :func:`transition_jacobian` and :func:`process_noise` at once for
    ``x (L, 3)``: the hot path computes ``d, d'`` once and fills preallocated ``Phi`` and
    ``Q`` buffers (same formulas; the buffers are consumed by the prediction each step)."""

    def __init__(self, n_links: int, exponent: Array, sigma_a: float, q_p: float,
                 min_distance_m: float) -> None:
        self.c = 10.0 * exponent / LN10
        self.sa2 = sigma_a * sigma_a
        self.q_p = q_p
        self.dmin = min_distance_m
        self.phi = np.zeros((n_links, 3, 3))
        self.phi[:, 0, 0] = self.phi[:, 1, 1] = self.phi[:, 2, 2] = 1.0
        self.Q = np.zeros((n_links, 3, 3))

    def __call__(self, x: Array, dt: Array) -> tuple[Array, Array, Array]:
        c = self.c
        d = np.maximum(x[:, 1], self.dmin)
        d1 = np.maximum(d + x[:, 2] * dt, self.dmin)
        xp = np.empty_like(x)
        xp[:, 0] = x[:, 0] + c * np.log(d / d1)  # eq. (15): 10 n lg(d / d')
        xp[:, 1] = d1
        xp[:, 2] = x[:, 2]
        phi = self.phi
        phi[:, 0, 1] = c * (1.0 / d - 1.0 / d1)  # eq. (17), derived
        phi[:, 0, 2] = -c * dt / d1
        phi[:, 1, 2] = dt
        half = 0.5 * dt * dt
        g0, g1, g2 = -c * half / d1, half, dt  # G = dX'/da
        Q, s = self.Q, self.sa2
        Q[:, 0, 0] = s * g0 * g0 + self.q_p * dt
        Q[:, 1, 1] = s * g1 * g1
        Q[:, 2, 2] = s * g2 * g2
        Q[:, 0, 1] = Q[:, 1, 0] = s * g0 * g1
        Q[:, 0, 2] = Q[:, 2, 0] = s * g0 * g2
        Q[:, 1, 2] = Q[:, 2, 1] = s * g1 * g2
        return xp, phi, Q


# ---------------------------------------------------------------------------------------
# Ragged log <-> (T, L) step layout
# ---------------------------------------------------------------------------------------


@dataclass(frozen=True)
class StepLayout:
    """Where each sample of a ragged multi-link log sits in the ``(T, L)`` step array.

    Attributes
    ----------
    link : ndarray of int, shape (n,)
        Link index (column) of each sample.
    step : ndarray of int, shape (n,)
        Rank of the sample within its link in time order (row).
    n_steps, n_links : int
    """

    link: NDArray[np.int64]
    step: NDArray[np.int64]
    n_steps: int
    n_links: int

    @classmethod
    def build(cls, link: ArrayLike, time_s: ArrayLike) -> StepLayout:
        """Rank samples within each link by time (stable for equal times)."""
        link = np.asarray(link, dtype=np.int64)
        t = np.asarray(time_s, dtype=float)
        n = link.size
        if n == 0:
            return cls(link, np.zeros(0, dtype=np.int64), 0, 0)
        order = np.lexsort((np.arange(n), t, link))
        sl = link[order]
        start = np.r_[0, np.flatnonzero(np.diff(sl)) + 1]
        counts = np.diff(np.r_[start, n])
        rank = np.arange(n) - np.repeat(start, counts)
        step = np.empty(n, dtype=np.int64)
        step[order] = rank
        return cls(link, step, int(counts.max()), int(link.max()) + 1)

    def scatter(self, values: ArrayLike, fill: float = np.nan) -> Array:
        """Per-sample values into a ``(T, L)`` array (``fill`` where no sample)."""
        out = np.full((self.n_steps, self.n_links), fill)
        out[self.step, self.link] = values
        return out

    def gather(self, grid: ArrayLike) -> Array:
        """``(T, L)`` array back to per-sample values, in the input order."""
        return np.asarray(grid)[self.step, self.link]

    def intervals(self, time_s: ArrayLike) -> Array:
        """``(T, L)`` sampling intervals ``t_k - t_{k-1}`` (0 at a link's first sample)."""
        tg = self.scatter(time_s)
        dt = np.zeros_like(tg)
        dt[1:] = np.diff(tg, axis=0)
        return np.where(np.isfinite(dt), dt, 0.0)


def _merge_same_time(
    link: NDArray[np.int64], t: Array, z: Array,
) -> tuple[NDArray[np.int64] | None, NDArray[np.int64], Array, Array, int]:
    """Samples of one link at one time merged into one, whatever their input order.

    Returns ``(group, link_g, t_g, z_g, n_dup)``: the merged sample of each input sample
    (None when no two samples share a link and a time: the inputs are returned as they
    are), the merged samples' link, time and value (the mean of the finite values, NaN
    if none), and the number of finite values beyond the first of each merged sample.
    The values of a merged sample are summed in value order, so its mean does not depend
    on the input order even in the last bit.
    """
    n = link.size
    if n < 2:
        return None, link, t, z, 0
    order = np.lexsort((z, t, link))
    sl, st, sz = link[order], t[order], z[order]
    first = np.r_[True, (np.diff(sl) != 0) | (st[1:] != st[:-1])]
    if first.all():
        return None, link, t, z, 0
    g_sorted = np.cumsum(first) - 1
    n_g = int(g_sorted[-1]) + 1
    ok = np.isfinite(sz)
    sums = np.bincount(g_sorted[ok], weights=sz[ok], minlength=n_g)
    counts = np.bincount(g_sorted[ok], minlength=n_g)
    with np.errstate(invalid="ignore", divide="ignore"):
        z_g = np.where(counts > 0, sums / np.maximum(counts, 1), np.nan)
    group = np.empty(n, dtype=np.int64)
    group[order] = g_sorted
    n_dup = int(np.sum(np.maximum(counts - 1, 0)))
    return group, sl[first], st[first], z_g, n_dup


# ---------------------------------------------------------------------------------------
# The filter
# ---------------------------------------------------------------------------------------


@dataclass(frozen=True)
class RssiFilterResult:
    """Output of :meth:`RobustRssiFilter.run`, arrays of shape ``(T, L)`` (or ``(n,)``).

    Attributes
    ----------
    rssi_dbm : filtered power ``P_r`` (a-posteriori state); NaN where no sample.
    distance_m : filtered distance state ``d``.
    speed_mps : radial speed state ``v``.
    rssi_var_db2 : a-posteriori variance of ``P_r``.
    innovation_db : ``Z - H X-`` (NaN for a missing measurement).
    standardized : innovation divided by the adaptive standard error ``s``.
    scale_db : the standard error ``s`` used (see module docstring).
    weight : equivalent weight ``D`` applied to the gain (1 for the plain filter; NaN for a
        missing measurement).
    relocked : the sample re-locked the link after ``max_rejected`` rejections in a row, or
        after fewer that outnumber the samples the link has taken (module docstring).
    restarted : the sample started the link again (``restart_var_ratio``): its weight is
        1, it has no innovation.
    """

    rssi_dbm: Array
    distance_m: Array
    speed_mps: Array
    rssi_var_db2: Array
    innovation_db: Array
    standardized: Array
    scale_db: Array
    weight: Array
    relocked: NDArray[np.bool_]
    extra: dict = field(default_factory=dict)
    restarted: NDArray[np.bool_] | None = None

    def take(self, index: ArrayLike) -> RssiFilterResult:
        """The per-sample result of samples ``index`` (of a per-sample result)."""
        i = np.asarray(index, dtype=np.int64)
        return RssiFilterResult(
            self.rssi_dbm[i], self.distance_m[i], self.speed_mps[i], self.rssi_var_db2[i],
            self.innovation_db[i], self.standardized[i], self.scale_db[i], self.weight[i],
            self.relocked[i], dict(self.extra),
            None if self.restarted is None else self.restarted[i],
        )

    def gather(self, layout: StepLayout) -> RssiFilterResult:
        """The same result per sample (input order) from the ``(T, L)`` layout."""
        g = layout.gather
        return RssiFilterResult(
            g(self.rssi_dbm), g(self.distance_m), g(self.speed_mps), g(self.rssi_var_db2),
            g(self.innovation_db), g(self.standardized), g(self.scale_db), g(self.weight),
            g(self.relocked).astype(bool), dict(self.extra),
            None if self.restarted is None else g(self.restarted).astype(bool),
        )


def _check_limits(name: str, values: Array, quantity: str) -> None:
    """``ValueError`` naming ``name`` when a value lies outside the physical limits of
    ``quantity`` (:mod:`robustloc.io.limits`)."""
    from robustloc.io.limits import limits_for

    lim = limits_for(quantity)
    bad = ~lim.check(values)
    if bad.any():
        raise ValueError(f"{name}: {int(bad.sum())} value(s) outside [{lim.low:g}, "
                         f"{lim.high:g}] {lim.unit}, the first {values[bad][0]:g} (set a "
                         "sample that is not one to NaN)")


def _check_link_params(p: LinkParams) -> None:
    """Each link's path loss usable: ``p0`` within the RSSI limits, ``gamma`` positive
    (NaN: the default 2), ``faf`` finite, ``d0`` positive (``p0 = NaN`` made all 60
    filtered values NaN, ``faf = inf`` most -- the API review)."""
    from robustloc.io.limits import limits_for

    rssi = limits_for("rssi")
    checks = (("p0_dbm", rssi.check(p.p0_dbm), f"within [{rssi.low:g}, {rssi.high:g}] dBm"),
              ("gamma", np.isnan(p.gamma) | ((p.gamma > 0) & np.isfinite(p.gamma)),
               "positive and finite (or NaN)"),
              ("faf_db", np.isfinite(p.faf_db), "finite"),
              ("d0_m", np.isfinite(p.d0_m) & (p.d0_m > 0), "positive and finite"))
    for name, ok, what in checks:
        if not np.all(ok):
            i = int(np.argmin(ok))
            raise ValueError(f"link {i}: {name} must be {what}, got "
                             f"{np.asarray(getattr(p, name))[i]!r}")


@dataclass(frozen=True)
class LinkParams:
    """Attenuation-factor path-loss parameters of each link (seed 002 eq. (5)), shape ``(L,)``.

    ``gamma`` is also the exponent of the state transition unless the filter forces one.
    """

    p0_dbm: Array
    gamma: Array
    faf_db: Array
    d0_m: Array

    @classmethod
    def broadcast(
        cls, n_links: int, p0_dbm: ArrayLike = -40.0, gamma: ArrayLike = 2.0,
        faf_db: ArrayLike = 0.0, d0_m: ArrayLike = 1.0,
    ) -> LinkParams:
        def arr(v: ArrayLike) -> Array:
            return np.broadcast_to(np.asarray(v, dtype=float), (n_links,)).copy()

        return cls(arr(p0_dbm), arr(gamma), arr(faf_db), arr(d0_m))


class RobustRssiFilter:
    """Robust (M-estimation) Kalman filter on RSSI, batched over links (seed 002).

    Parameters
    ----------
    weight : WeightFunction or None
        Equivalent weight ``D`` of the standardized innovation (eq. (12)); default
        :class:`AsymmetricIGG` ``(K0=2, K1=3, C=3)`` (eq. (14)).  ``None``: the plain
        Kalman filter (``D = 1``).
    sigma_rssi_db : float
        Measurement noise standard deviation ``sqrt(R)`` (eq. (16)), 1e-6 to 1e6 dB.
    sigma_accel_mps2 : float
        Standard deviation of the radial acceleration ``a`` of eq. (15), 0 to 1e3 m/s^2.
    q_rssi_db2_per_s : float
        Random-walk intensity of the power level (environment changes), 0 to 1e6 dB^2/s.
        (Outside these ranges the covariances overflow or underflow: ``sigma_rssi_db =
        1e300`` raised ``OverflowError``, ``1e-300`` and ``q_rssi_db2_per_s = 1e300`` gave
        NaN filtered values.)
    exponent : float or None
        Path-loss exponent of the transition; ``None``: each link's ``gamma`` (see module
        docstring); ``2.0``: the paper's ``20 lg`` literally.
    init_speed_std_mps : float
        Prior standard deviation of the radial speed.
    adaptive : bool
        Standardize by ``max(s_emp, sqrt(S))`` (True) or by ``sqrt(S)`` alone (False).
    scale_window : float
        ``1/lambda`` of the running scale ``s_emp``, in samples.
    max_rejected : int
        Consecutive zero-weight samples after which a link re-locks (0: never); a link
        re-locks sooner when its consecutive rejections outnumber the samples it has taken
        (weight above zero) since it started (module docstring).
    model_sigma_db : float or None
        Standard deviation (dB) of the path-loss tie ``P_r = P_r(d)`` (eq. (5)) applied as a
        pseudo-observation after each update (see the module docstring); ``None``: the
        paper's model literally, the distance state then drifts.
    min_distance_m : float
        Floor on the distance state.
    restart_var_ratio : float or None
        A link whose prediction knows nothing any more starts again at the sample, as at
        its first one (``None``: never): its power variance exceeds this many times ``R``
        and its distance's standard deviation exceeds the distance.  The prior then
        weighs less than ``1 / (1 + ratio)`` of the update (under 4 % at the default 25):
        the filtered power is the sample's to within that share either way, but the
        distance and speed are re-drawn from it instead of carried across the gap that
        made the prediction this wide (a speed of -0.5 m/s over 600 s put the distance
        state at its floor for the next 60 s).  The distance condition keeps a link that
        approaches an anchor tracked (its power prediction is wide there, ``G_P = c
        (t^2/2) / d'``, but its distance and speed are known); a static link within
        decimetres of one, with its distance near the floor, restarts at every sample
        (two of the 84 links of a simulated wifi-room, RSSI -13 to -21 dBm), which
        changes its filtered power by under 4 % of the innovation, as above.  A
        :attr:`static` filter's distance never moves (its variance does not grow), so the
        power's variance alone decides: it grows with the random walk ``q_rssi_db2_per_s``
        only, past ``ratio R`` after ``(ratio R - P) / q`` seconds without a sample (about
        2000 s at the defaults), and the link then starts again with the distance of its
        sample (with the distance condition a static link never restarted: 10 000 s
        after -50 dBm, a sample of -60 dBm left the distance state at 3.3 m where the
        sample says 10 m).
    engine : {"scalar", "core"}
        Measurement update: the closed-form ``m = 1`` update (:func:`scalar_update`,
        fast) or the shared core's :func:`~robustloc.filters.core.update_linear` (same
        result, several times slower).  The prediction always runs through
        :func:`~robustloc.filters.core.predict_ekf`.
    """

    def __init__(
        self,
        weight: WeightFunction | None = None,
        *,
        robust: bool = True,
        sigma_rssi_db: float = 2.0,
        sigma_accel_mps2: float = 0.5,
        q_rssi_db2_per_s: float = 0.05,
        exponent: float | None = None,
        init_speed_std_mps: float = 1.0,
        adaptive: bool = True,
        scale_window: float = 20.0,
        max_rejected: int = 8,
        model_sigma_db: float | None = 3.0,
        min_distance_m: float = 0.1,
        restart_var_ratio: float | None = 25.0,
        engine: str = "scalar",
    ) -> None:
        if engine not in ("scalar", "core"):
            raise ValueError(f"engine must be 'scalar' or 'core', got {engine!r}")
        self.engine = engine
        if weight is None and robust:
            weight = AsymmetricIGG(k0=2.0, k1=3.0, c=3.0)
        self.weight = weight if robust else None
        for name, val in [
            ("sigma_rssi_db", sigma_rssi_db), ("scale_window", scale_window),
            ("min_distance_m", min_distance_m),
        ]:
            if not (np.isfinite(val) and val > 0):
                raise ValueError(f"{name} must be positive, got {val}")
        for name, val in [
            ("sigma_accel_mps2", sigma_accel_mps2), ("q_rssi_db2_per_s", q_rssi_db2_per_s),
            ("init_speed_std_mps", init_speed_std_mps),
        ]:
            if not (np.isfinite(val) and val >= 0):
                raise ValueError(f"{name} must be >= 0, got {val}")
        from robustloc.options import SIGMA_RANGE

        for name, val, lo, hi in [
            ("sigma_rssi_db", sigma_rssi_db, *SIGMA_RANGE),
            ("sigma_accel_mps2", sigma_accel_mps2, 0.0, 1e3),
            ("q_rssi_db2_per_s", q_rssi_db2_per_s, 0.0, 1e6),
        ]:
            if not lo <= val <= hi:
                raise ValueError(f"{name} must lie in [{lo:g}, {hi:g}], got {val}")
        if exponent is not None and not (np.isfinite(exponent) and exponent > 0):
            raise ValueError(f"exponent must be positive and finite, got {exponent}")
        if max_rejected < 0:
            raise ValueError(f"max_rejected must be >= 0, got {max_rejected}")
        if restart_var_ratio is not None and not (np.isfinite(restart_var_ratio)
                                                  and restart_var_ratio > 0):
            raise ValueError(f"restart_var_ratio must be positive or None, got "
                             f"{restart_var_ratio}")
        self.restart_var_ratio = restart_var_ratio
        self.sigma_rssi_db = float(sigma_rssi_db)
        self.sigma_accel_mps2 = float(sigma_accel_mps2)
        self.q_rssi_db2_per_s = float(q_rssi_db2_per_s)
        self.exponent = exponent
        self.init_speed_std_mps = float(init_speed_std_mps)
        self.adaptive = bool(adaptive)
        self.scale_window = float(scale_window)
        self.max_rejected = int(max_rejected)
        self.min_distance_m = float(min_distance_m)
        if model_sigma_db is not None and not (np.isfinite(model_sigma_db) and model_sigma_db > 0):
            raise ValueError(f"model_sigma_db must be positive or None, got {model_sigma_db}")
        self.model_sigma_db = model_sigma_db

    @property
    def name(self) -> str:
        return "plain" if self.weight is None else self.weight.name

    @property
    def static(self) -> bool:
        """Whether the links cannot move: no acceleration (``sigma_accel_mps2 = 0``) and a
        speed fixed at 0 (``init_speed_std_mps = 0``; ``robustloc filter --static``).  The
        prediction then never moves the distance, and its power's variance grows with the
        power's random walk alone (``restart_var_ratio``)."""
        return self.sigma_accel_mps2 == 0.0 and self.init_speed_std_mps == 0.0

    # -- the path-loss tie ------------------------------------------------------------

    def _model_tie(self, x: Array, P: Array, active: NDArray[np.bool_], a_db: Array,
                   c_db: Array) -> tuple[Array, Array]:
        """Path-loss tie ``0 = P_r - (A - c ln d) + w``, ``w ~ N(0, model_sigma^2)``, that
        corrects ``d`` and ``v`` only.

        Linearized row ``h = [1, c/d, 0]``, gain ``K = P h / S`` with its power component
        set to zero (a Schmidt "consider" update: the tie re-uses information the power
        already carries, so it must not feed back into the filtered RSSI), covariance
        ``P - K (P h)^T - (P h) K^T + S K K^T`` (valid for any gain, as in the core).
        """
        d = np.maximum(x[:, 1], self.min_distance_m)
        h1 = c_db / d
        resid = np.where(active, -(x[:, 0] - a_db + c_db * np.log(d)), 0.0)
        ph = P[:, :, 0] + P[:, :, 1] * h1[:, None]  # P h with h = [1, c/d, 0]
        S = ph[:, 0] + h1 * ph[:, 1] + self.model_sigma_db**2
        K = np.where(active[:, None], ph / S[:, None], 0.0)
        K[:, 0] = 0.0
        x = x + K * resid[:, None]
        KPh = K[:, :, None] * ph[:, None, :]
        P = P - KPh - np.swapaxes(KPh, 1, 2) + S[:, None, None] * (K[:, :, None] * K[:, None, :])
        return x, P

    # -- public entry points ---------------------------------------------------------

    def filter_samples(
        self, link: ArrayLike, time_s: ArrayLike, rssi_dbm: ArrayLike,
        params: LinkParams | None = None, progress: bool = False,
    ) -> RssiFilterResult:
        """Filter a ragged log: per-sample ``link`` index, ``time_s``, ``rssi_dbm``.

        Returns per-sample results in the input order.  Non-finite RSSI values are
        missing measurements (prediction only, weight NaN).  ``progress`` shows a bar on
        stderr when it is a terminal.

        Samples of one link at the same time are one sample, their finite values averaged
        (as :func:`robustloc.io.to_epochs` merges an epoch's duplicates for ``locate``):
        each gets that merged sample's result, whatever their order in the input (ranked
        by input order, their filtered values depended on which came first).  How many
        were merged is ``extra["duplicates_merged"]`` (finite values beyond the first of
        each time and link).  A NaN sample at the time of a finite one of its link is no
        part of it: it gets the prediction (before that sample's update), weight and
        innovation NaN, not re-locked nor restarted, as a missing measurement does.
        """
        link = np.asarray(link, dtype=np.int64)
        t = np.asarray(time_s, dtype=float)
        z = np.asarray(rssi_dbm, dtype=float)
        if not (link.shape == t.shape == z.shape) or link.ndim != 1:
            raise ValueError("link, time_s and rssi_dbm must be 1-D arrays of equal length")
        if link.size and link.min() < 0:
            raise ValueError("link indices must be >= 0")
        # links are indices 0 .. L-1 into (T, L) arrays: a link id of 1e12 asked for
        # 7 TiB (MemoryError: the API review)
        n_links = None if params is None else len(params.p0_dbm)
        if link.size and n_links is not None and link.max() >= n_links:
            raise ValueError(f"link index {int(link.max())} for {n_links} links' parameters: "
                             "links are numbered 0 .. L-1")
        if link.size and n_links is None and link.max() >= max(4 * link.size, 1024):
            raise ValueError(f"link indices run to {int(link.max())} for {link.size} samples: "
                             "number the links 0 .. L-1 (np.unique(ids, return_inverse=True))")
        if not np.all(np.isfinite(t)):
            raise ValueError("time_s must be finite")
        # values a receiver cannot report, and times a clock cannot read: one RSSI of
        # -1e308 turned 18 of its link's 20 filtered values into NaN, a time of -1e308
        # 19 (the API review); the command line sets such rows aside before (status
        # invalid_measurement), a caller of this method says which
        _check_limits("rssi_dbm", z[~np.isnan(z)], "rssi")
        _check_limits("time_s", t, "time")
        group, link_g, t_g, z_g, n_dup = _merge_same_time(link, t, z)
        layout = StepLayout.build(link_g, t_g)
        if params is None:
            params = LinkParams.broadcast(layout.n_links)
        # NaN samples merged with a finite one: they had taken its update, weight and
        # innovation (a -500 dBm row set aside by `robustloc filter` showed the weight 0
        # of the valid row beside it: the filter review); they get the prediction
        lone = None if group is None else np.isnan(z) & ~np.isnan(z_g[group])
        res, prior = self._run(layout.scatter(z_g), layout.intervals(t_g), params,
                               progress=progress, prior=lone is not None and lone.any())
        res = res.gather(layout)
        if group is not None:
            res = res.take(group)
        if prior is not None and lone is not None:
            where = group[lone]
            for values, key in ((res.rssi_dbm, "p"), (res.distance_m, "d"),
                                (res.speed_mps, "v"), (res.rssi_var_db2, "var")):
                values[lone] = layout.gather(prior[key])[where]
            for values in (res.innovation_db, res.standardized, res.scale_db, res.weight):
                values[lone] = np.nan
            res.relocked[lone] = False
            if res.restarted is not None:
                res.restarted[lone] = False
        res.extra["duplicates_merged"] = n_dup
        return res

    def run(
        self, rssi_dbm: ArrayLike, dt_s: ArrayLike, params: LinkParams, progress: bool = False
    ) -> RssiFilterResult:
        """Filter ``(T, L)`` RSSI (NaN: no sample) with intervals ``dt_s (T, L)``.

        One vectorized step per row; every link is an independent filter.  ``progress``
        shows a bar on stderr when it is a terminal.
        """
        return self._run(rssi_dbm, dt_s, params, progress=progress)[0]

    def _run(
        self, rssi_dbm: ArrayLike, dt_s: ArrayLike, params: LinkParams, progress: bool = False,
        prior: bool = False,
    ) -> tuple[RssiFilterResult, dict[str, Array] | None]:
        """:meth:`run`, and with ``prior`` the prediction of each step before its update
        (``(T, L)`` arrays ``p, d, v, var``; NaN where the link has not started or starts
        at that step), else ``None``."""
        z_all = np.asarray(rssi_dbm, dtype=float)
        dt_all = np.asarray(dt_s, dtype=float)
        if z_all.ndim != 2 or dt_all.shape != z_all.shape:
            raise ValueError("rssi_dbm and dt_s must both have shape (T, L)")
        T, L = z_all.shape
        p = params
        if not isinstance(p, LinkParams):
            raise TypeError(f"params must be LinkParams, got {type(p).__name__}")
        if p.p0_dbm.shape != (L,):
            raise ValueError(f"link parameters must have shape ({L},), got {p.p0_dbm.shape}")
        _check_link_params(p)
        with np.errstate(invalid="ignore"):
            if not np.all((dt_all >= 0) & np.isfinite(dt_all)):
                raise ValueError("dt_s must be finite and >= 0 (a sample's interval since "
                                 "its link's previous one)")
        # the anchors' calibrated exponent: the measurement model (eq. (5): the tie, the
        # start's distance); the transition's (eq. (15)) is it too unless forced
        # (``exponent``: it replaced the calibrated one in the model as well, and the
        # distance state's median error went from 1.04 to 4.77 m with --exponent 2 --
        # the fuse/filter review, 2026-12-07)
        gamma = np.where(np.isfinite(p.gamma) & (p.gamma > 0), p.gamma, 2.0)
        expo = np.full(L, float(self.exponent)) if self.exponent is not None else gamma
        c_db = 10.0 * gamma / LN10  # dP/d(ln d) of the model
        R = self.sigma_rssi_db**2
        lam = 1.0 / self.scale_window
        wf = self.weight
        c_win = wf.rejection_threshold if wf is not None else np.inf
        if not np.isfinite(c_win):
            c_win = 3.0

        out = {k: np.full((T, L), np.nan) for k in
               ("p", "d", "v", "var", "innov", "u", "scale", "w")}
        relocked = np.zeros((T, L), dtype=bool)
        restarted = np.zeros((T, L), dtype=bool)
        pred = ({k: np.full((T, L), np.nan) for k in ("p", "d", "v", "var")} if prior
                else None)

        x = np.zeros((L, 3))
        P = np.zeros((L, 3, 3))
        started = np.zeros(L, dtype=bool)
        s_emp = np.full(L, self.sigma_rssi_db)
        n_rej = np.zeros(L, dtype=np.int64)
        n_acc = np.zeros(L, dtype=np.int64)  # samples taken since the link (re)started
        sqrt_half_pi = np.sqrt(np.pi / 2.0)
        all_started = False
        terms = _ModelTerms(L, expo, self.sigma_accel_mps2, self.q_rssi_db2_per_s,
                            self.min_distance_m)
        # eq. (5) as P = A - c ln d with A = p0 + FAF + 10 n lg d0 (the tie's intercept)
        tie_a = AttenuationFactor(p.p0_dbm, gamma, p.faf_db, p.d0_m).log_distance_params()[0]
        static = self.static

        steps = range(T)
        if progress and T > 1:
            import sys

            from tqdm import tqdm

            steps = tqdm(steps, desc="filter", unit="step", file=sys.stderr,
                         disable=not sys.stderr.isatty())
        for k in steps:
            z = z_all[k]
            present = np.isfinite(z)
            # links starting now: state from the first finite sample (model-consistent
            # prior: d from the inverse of eq. (5), cov(P, d) through dd/dP)
            new = present & ~started
            if new.any():
                x[new], P[new] = self._start(z[new], p, gamma, c_db, new, R)
                started |= new
                n_acc[new] = 1
            run_now = started & ~new
            dt = np.where(run_now, dt_all[k], 0.0)
            # prediction, eq. (13) first line, through the shared EKF core with the
            # transition of eq. (15) and its Jacobian (eq. (17), derived above)
            # (f and its Jacobian are evaluated once at the prior state x, which is where
            # predict_ekf evaluates them)
            x_pred, phi, Q = terms(x, dt)
            x, P = core.predict_ekf(x, P, lambda _s, xp=x_pred: xp, Q,
                                    jac=lambda _s, jp=phi: jp)
            if pred is not None:
                for key, col in (("p", 0), ("d", 1), ("v", 2)):
                    pred[key][k] = np.where(run_now, x[:, col], np.nan)
                pred["var"][k] = np.where(run_now, P[:, 0, 0], np.nan)
            # a prediction too wide to carry anything (restart_var_ratio): start again
            upd = present & run_now
            if self.restart_var_ratio is not None:
                # (a static filter's distance never moves, so only the power's variance
                # can say so: with the distance condition, --static never restarted)
                stale = upd & (P[:, 0, 0] > self.restart_var_ratio * R)
                if not static:
                    stale &= P[:, 1, 1] > x[:, 1] ** 2
                if stale.any():
                    x[stale], P[stale] = self._start(z[stale], p, gamma, c_db, stale, R)
                    n_rej[stale] = 0
                    n_acc[stale] = 1
                    restarted[k] = stale
                    new = new | stale
                    upd = upd & ~stale
            # measurement update, eqs. (12)-(13) with H = [1 0 0] (eq. (16))
            S = P[:, 0, 0] + R
            e = np.where(upd, z - x[:, 0], np.nan)
            scale = np.sqrt(np.maximum(s_emp**2, S)) if self.adaptive else np.sqrt(S)
            u = e / scale
            D = np.where(upd, 1.0, np.nan) if wf is None else wf.weights(u)  # eq. (14)
            rejected = upd & (D <= 0.0)
            n_rej = np.where(rejected, n_rej + 1, np.where(upd, 0, n_rej))
            # re-lock after max_rejected rejections in a row, or sooner on a young link
            # whose rejections outnumber the samples it has taken (a fade on its first
            # sample rejected the good ones after it)
            relock = rejected & ((n_rej >= self.max_rejected) | (n_rej > n_acc)) if (
                self.max_rejected) else np.zeros(L, dtype=bool)
            if relock.any():
                P[relock, 0, 0] += e[relock] ** 2
                D = np.where(relock, 1.0, D)
                n_rej[relock] = 0
                S = P[:, 0, 0] + R
            n_acc += upd & (D > 0.0)
            if self.engine == "core":
                robust = core.PLAIN if wf is None else core.RobustUpdate(
                    weight=_Rescaled(wf, (np.sqrt(S) / scale)[:, None], relock[:, None]))
                res = core.update_linear(x, P, np.where(upd, z, np.nan)[:, None], _H,
                                         np.array([[R]]), robust=robust)
                x, P = res.x, res.P
            else:
                x, P = scalar_update(x, P, np.where(upd, e, 0.0), S, np.where(upd, D, 0.0))
            if self.model_sigma_db is not None:
                x, P = self._model_tie(x, P, upd, tie_a, c_db)
            # running standard error of the innovations (winsorized at C s)
            a_e = np.minimum(np.abs(e), c_win * scale)
            s_emp = np.where(upd, (1 - lam) * s_emp + lam * sqrt_half_pi * a_e, s_emp)
            x[:, 1] = np.maximum(x[:, 1], self.min_distance_m)

            if all_started or started.all():
                all_started = True
                out["p"][k] = x[:, 0]
                out["d"][k] = x[:, 1]
                out["v"][k] = x[:, 2]
                out["var"][k] = P[:, 0, 0]
            else:
                out["p"][k] = np.where(started, x[:, 0], np.nan)
                out["d"][k] = np.where(started, x[:, 1], np.nan)
                out["v"][k] = np.where(started, x[:, 2], np.nan)
                out["var"][k] = np.where(started, P[:, 0, 0], np.nan)
            out["innov"][k] = e
            out["u"][k] = u
            out["scale"][k] = np.where(upd, scale, np.nan)
            out["w"][k] = np.where(new, 1.0, np.where(upd, D, np.nan))
            relocked[k] = relock
        return RssiFilterResult(
            out["p"], out["d"], out["v"], out["var"], out["innov"], out["u"], out["scale"],
            out["w"], relocked, {"exponent": expo}, restarted,
        ), pred

    def _start(self, z: Array, p: LinkParams, expo: Array, c_db: Array,
               which: NDArray[np.bool_], R: float) -> tuple[Array, Array]:
        """State and covariance of links ``which`` starting at their samples ``z``: the
        power, the distance from the inverse of eq. (5) with the matching ``cov(P, d)``
        (through ``dd/dP``), speed 0 with ``init_speed_std_mps``."""
        model = AttenuationFactor(p.p0_dbm[which], expo[which], p.faf_db[which],
                                  p.d0_m[which])
        d_init = np.clip(model.distance(z), self.min_distance_m, 1e4)
        n = z.size
        x0 = np.stack([z, d_init, np.zeros(n)], axis=1)
        dd_dp = -d_init / c_db[which]
        J = np.stack([np.ones(n), dd_dp, np.zeros(n)], axis=1)
        P0 = R * J[:, :, None] * J[:, None, :]
        P0[:, 1, 1] += (0.05 * d_init) ** 2
        P0[:, 2, 2] += self.init_speed_std_mps**2
        return x0, P0


# ---------------------------------------------------------------------------------------
# Tables: contract measurements in, filtered measurements out
# ---------------------------------------------------------------------------------------


def link_params_from_anchors(anchors: object, anchor_of_link: ArrayLike) -> LinkParams:
    """Path-loss parameters of each link from an anchors table.

    The model ``locate`` takes from the same columns, by the same code
    (:func:`robustloc.models.pathloss.model_from_anchors`): log-distance ``A, n`` (``p0 =
    A, gamma = n, FAF = 0, d0 = 1 m``) when the anchor has them, else the attenuation
    factor ``p0, gamma, faf, d0`` (seed 002 eq. (5); ``faf`` 0 and ``d0`` 1 when absent),
    else free space ``p0[, d0]`` (``gamma = 2``, as ``calibrate --model friis`` writes
    it), else ``p0 = -40 dBm, gamma = 2`` (the distance state is then only indicative;
    the filtered RSSI does not depend on it much).  An anchor with both ``A, n`` and
    ``p0, gamma`` takes ``A, n``, as ``locate`` does (``robustloc filter`` notes it when
    they disagree, :func:`robustloc.commands.filter.pathloss_note`); it had taken ``p0,
    gamma``.  The choice is made per anchor on the parameters it has (an empty cell, which
    ``robustloc filter`` refuses as ``locate`` does, falls back to the next model here).
    """
    import pandas as pd

    from robustloc.models.pathloss import (
        MODEL_COLUMNS,
        AttenuationFactor,
        FreeSpace,
        LogDistance,
        model_from_anchors,
    )

    a = pd.DataFrame(anchors).reset_index(drop=True)
    names = [c for c in dict.fromkeys(c for m in MODEL_COLUMNS.values() for c in m)
             if c in a.columns]
    k = len(a)
    p0, g, faf, d0 = np.full(k, -40.0), np.full(k, 2.0), np.zeros(k), np.ones(k)
    have = np.isfinite(a[names].apply(to_number).to_numpy(dtype=float))
    # anchors with the same parameters present share one model_from_anchors call
    patterns, which = (np.unique(have, axis=0, return_inverse=True) if names and k
                       else (np.zeros((0, 0), bool), np.zeros(k, np.int64)))
    for i, pattern in enumerate(patterns):
        rows = np.flatnonzero(which.reshape(-1) == i)
        cols = [c for c, h in zip(names, pattern) if h]
        try:
            model = model_from_anchors(a.iloc[rows][["anchor", *cols]])
        except ValueError:  # no usable parameters (InputError included): the defaults
            continue
        if isinstance(model, LogDistance):
            p0[rows], g[rows] = model.log_distance_params()
        elif isinstance(model, AttenuationFactor):
            p0[rows], g[rows] = model.p0, model.gamma
            faf[rows], d0[rows] = model.faf, model.d0
        elif isinstance(model, FreeSpace):
            p0[rows], d0[rows] = model.p0, model.d0
    idx = pd.Index(a["anchor"].astype(str)).get_indexer(np.asarray(anchor_of_link).astype(str))
    known = idx >= 0

    def per_link(v: Array, default: float) -> Array:
        return np.where(known, v[np.maximum(idx, 0)] if k else default, default)

    return LinkParams(p0_dbm=per_link(p0, -40.0), gamma=per_link(g, 2.0),
                      faf_db=per_link(faf, 0.0), d0_m=per_link(d0, 1.0))


def one_row_per_sample(link: ArrayLike, time_s: ArrayLike, fed: ArrayLike) -> NDArray[np.bool_]:
    """The first row fed to the filter (``fed``: it has a value) of each sample of the
    filter, rows of one link at one time being one sample; the filter's counts are over
    these rows."""
    import pandas as pd

    fed = np.asarray(fed, dtype=bool)
    idx = np.flatnonzero(fed)
    keys = pd.DataFrame({"link": np.asarray(link)[idx], "time": np.asarray(time_s)[idx]})
    one = np.zeros(fed.size, dtype=bool)
    one[idx[~keys.duplicated().to_numpy()]] = True
    return one


@dataclass(frozen=True)
class FilteredTable:
    """Result of :func:`filter_measurements`.

    ``frame`` has the input rows in the input order, ``rssi`` replaced by the filtered
    value and extra columns ``rssi_raw``, ``distance`` (m: the filtered RSSI through the
    inverse of the link's path-loss model, eq. (5) -- what positioning uses),
    ``distance_state`` (the filter's own ``d``, see the module docstring on its weak
    observability), ``speed`` (radial speed state, m/s), ``weight`` (equivalent weight
    ``D``), ``innovation`` (dB) and ``relocked``.  Rows of one link at one time are one
    sample of the filter (their RSSI averaged, as ``locate`` averages an epoch's
    duplicates): each such row has the merged sample's filtered columns and its own
    ``rssi_raw``.  ``summary`` holds the counts (``samples``: rows;
    ``filtered_samples``: samples of the filter, rows without a value left out; the
    weights, re-locks and restarts are counted over these; ``duplicates_merged``: rows
    merged into another's sample).
    """

    frame: object
    summary: dict


def filter_measurements(
    measurements: object, anchors: object | None, filt: RobustRssiFilter,
    progress: bool = False,
) -> FilteredTable:
    """Filter every (tag, anchor) link of a contract measurements frame in one pass.

    Parameters
    ----------
    measurements : DataFrame
        ``time, tag, anchor, rssi`` (from :func:`robustloc.io.read_measurements`).
    anchors : DataFrame, optional
        Anchors with path-loss columns (see :func:`link_params_from_anchors`).
    filt : RobustRssiFilter
    progress : bool
        Progress bar on stderr (only on a terminal).
    """
    import pandas as pd

    from robustloc._exact import Moments
    from robustloc.errors import InputError

    m = pd.DataFrame(measurements)
    if "rssi" not in m.columns:
        raise InputError("the filter needs an 'rssi' column (this file has none)",
                         getattr(measurements, "attrs", {}).get("path"), 1)  # the header
    # the links (tag, anchor) as pairs: a key joined by a separator split a tag id that
    # held the separator at the wrong place, and its anchor then took the default path
    # loss silently (a tag "t\x1f2"; the filter review of 2026-12-06)
    key = pd.MultiIndex.from_arrays([m["tag"].astype(str), m["anchor"].astype(str)])
    link, uniq = key.factorize(sort=True)
    anchor_of_link = np.asarray(uniq.get_level_values(1), dtype=object)
    params = (link_params_from_anchors(anchors, anchor_of_link) if anchors is not None
              else LinkParams.broadcast(len(uniq)))
    res = filt.filter_samples(link, m["time"].to_numpy(dtype=float),
                              m["rssi"].to_numpy(dtype=float), params, progress=progress)
    out = m.copy()
    out["rssi_raw"] = m["rssi"].to_numpy(dtype=float)
    out["rssi"] = res.rssi_dbm
    out["distance"] = _attenuation(params, link).distance(res.rssi_dbm)
    out["distance_state"] = res.distance_m
    out["speed"] = res.speed_mps
    out["weight"] = res.weight
    out["innovation"] = res.innovation_db
    out["relocked"] = res.relocked
    # the counts are of the filter's samples: one row of each merged sample, none without
    # a value (a merged rejected sample of two rows counted 2 rejections, and rows set
    # aside counted as filtered: the filter review)
    one = one_row_per_sample(link, m["time"].to_numpy(dtype=float),
                             np.isfinite(out["rssi_raw"].to_numpy(dtype=float)))
    w = res.weight[one & np.isfinite(res.innovation_db)]
    diff = (out["rssi_raw"] - out["rssi"]).to_numpy(dtype=float)
    summary = {
        "filter": filt.name,
        "samples": int(len(m)),
        "filtered_samples": int(one.sum()),
        "links": int(len(uniq)),
        "downweighted": int(np.sum(w < 1)),
        "rejected": int(np.sum(w == 0)),
        "relocked": int(res.relocked[one].sum()),
        "restarted": int(0 if res.restarted is None else res.restarted[one].sum()),
        "duplicates_merged": int(res.extra.get("duplicates_merged", 0)),
        "share_downweighted": float(np.mean(w < 1)) if w.size else 0.0,
        # None (JSON null) without any filtered value: a bare NaN is no JSON (the
        # filter/fuse review: every row outside the limits printed NaN with --json);
        # from exact sums, so that --engine dask, which adds its tag groups' moments,
        # gives the same number (np.nanstd's rounding depends on the rows' order)
        "raw_minus_filtered_std_db": Moments.of(diff[np.isfinite(diff)]).std(),
    }
    return FilteredTable(out, summary)
