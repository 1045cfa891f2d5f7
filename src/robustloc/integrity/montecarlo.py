"""Monte Carlo evaluation of gross-error detection and robust estimation (seed 003).

A *layout* is a linearized observation model at the true position: a ranging layout (anchors
and a tag position, design = unit vectors from the anchors) or a simulated GNSS snapshot
(design = ``-line of sight`` in east/north/up plus one clock column per system, from
:mod:`robustloc.sim.gnss`).  Every trial draws Gaussian noise ``e ~ N(0, sigma^2)``, adds
``n_faults`` gross errors of random sign to distinct random observations, and hands
``y = e + f`` (the truth is the origin of the linearized model) to each method.  Trials are
the batch axis of every estimator, so 10 000 trials take seconds.

The linear(ized) model is exactly the one the B-method theory is derived for, so the
measured rates can be put beside the theoretical ones:

* false alarm of the global test (no fault): ``alpha`` of the B-method for ``n - p`` dof;
* detection (global test) of faults ``f``: ``P(chi2'(n - p, lambda) > chi2(1 - alpha))``,
  ``lambda = f^T P Q_vv P f``; for a single fault of the size of its MDB, ``1 - beta0``;
* local w-test of a single fault ``f_i``: ``Phi(delta - k) + Phi(-delta - k)``,
  ``delta = |f_i| sqrt(r_i) / sigma_i``.

Methods: ``ls`` (no fault handling, reference), ``snooping`` (iterative w-test data snooping),
``raim-single`` (the classical RAIM policy of RTKLIB's ``rnx2rtkp``, emulated on the same
model: global chi-square test at a fixed ``alpha = 0.001``, at most one exclusion, of the
observation whose removal lowers ``v^T P v`` most -- for one exclusion that is the largest
w-test, since the drop is ``w_i^2`` -- and ``unavailable`` if the test still fails),
``lege`` (seed 000 sec. 2.4, :func:`robustloc.estimators.linear.lege` with its default
``min_dof``, as ``robustloc locate`` runs it: on a layout of redundancy ``n - p <= min_dof``
it searches no gross error and equals ``ls``, which :func:`lege_note` reports) and IRLS with the
weight functions of :mod:`robustloc.robust.weights` (``huber``, ``hampel``, ``igg``,
``igg3``; :func:`robustloc.estimators.linear.irls` with the known a-priori scale).  An
observation counts as *rejected* by snooping when excluded, by LEGE when a gross error was
estimated for it, by IRLS when its relative equivalent weight (the weight function's value,
``w sigma_i^2``) fell below ``reject_weight``
(default 0.1).  Per method and trial set:

* ``flag_rate``: share of trials with at least one rejection (with ``n_faults = 0`` the
  false-alarm rate; for snooping the global test's rejection);
* ``identified``: share of faulty trials whose rejected set equals the faulty set;
* ``unavailable``: share of trials without a usable fix (snooping: ``unavailable``);
* horizontal position error: mean, RMS, 95th percentile (metres).

Memory: trials run in chunks of :data:`CHUNK_TRIALS`, whose results are accumulated
(counts, sums, sums of squares and the largest 5 % of the errors, which is all the exact
95th percentile needs), so memory stays bounded by that of one chunk whatever the number
of trials (peak RSS about 0.9 GB for the 23-satellite GNSS snapshot with the default
methods, LEGE of order 3 being the largest).
Random numbers: a run of at most ``CHUNK_TRIALS`` trials draws exactly what it drew before
chunking (``numpy.random.default_rng(seed)``), so those results are unchanged bit for bit.
A larger run gives chunk 0 that same stream and chunk ``k >= 1`` its own stream
``default_rng([seed, k])``: one array's stream of normal deviates cannot be cut into
chunks (the ziggurat sampler consumes a variable number of bits), so such runs differ from
the unchunked ones within the Monte Carlo noise only.  Results depend on the seed alone,
never on memory or machine.
"""

from __future__ import annotations

import time
import warnings
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import pandas as pd
from numpy.typing import ArrayLike, NDArray

from robustloc import status as st
from robustloc.errors import InputError
from robustloc.estimators.linear import LEGE_MIN_DOF
from robustloc.integrity.bmethod import (
    ALPHA0,
    BETA0,
    detection_power_global,
    detection_power_w,
    global_alpha,
)
from robustloc.integrity.reliability import reliability
from robustloc.integrity.snooping import snoop_linear
from robustloc.integrity.tests import whiten

Array = NDArray[np.float64]

#: Fixed global-test significance of the ``raim-single`` policy (RTKLIB's chi-square test).
RAIM_SINGLE_ALPHA = 0.001

#: Trials per chunk of :func:`run_montecarlo` (the default trial count, so that default runs
#: draw exactly the numbers they drew before chunking).
CHUNK_TRIALS = 10_000

#: LEGE's largest number of gross errors searched on the linearized model, by default.
LEGE_MAX_ORDER = 3

#: Methods understood by :func:`run_montecarlo`.
METHODS = ("ls", "snooping", "raim-single", "lege", "huber", "hampel", "igg", "igg3")


@dataclass(frozen=True)
class Layout:
    """A linearized observation model at the true position.

    Attributes
    ----------
    name : str
    H : ndarray (n, p)
        Design; the first ``position_dims`` unknowns are the position, ``horizontal`` of
        them the horizontal ones.
    sigma : ndarray (n,)
        A-priori standard deviations of the observations.
    obs_ids : list of str
    position_dims : int
    horizontal : tuple of int
    """

    name: str
    H: Array
    sigma: Array
    obs_ids: list[str]
    position_dims: int
    horizontal: tuple[int, ...] = (0, 1)
    #: Ranging layouts only: anchors, true position and height offsets, for nonlinear runs.
    anchors: Array | None = None
    truth: Array | None = None
    height_offset: Array | None = None
    #: ``"range"`` or ``"rssi"`` (then ``path_loss_n`` holds the exponents).
    kind: str = "range"
    path_loss_n: Array | None = None

    @property
    def n(self) -> int:
        return int(self.H.shape[0])

    @property
    def p(self) -> int:
        return int(self.H.shape[1])


def ranging_layout(
    anchors: ArrayLike,
    position: ArrayLike,
    sigma_m: float | ArrayLike,
    anchor_ids: list[str] | None = None,
    height_offset: ArrayLike | None = None,
    name: str = "ranging",
) -> Layout:
    """Layout of range positioning: unit-vector design at ``position`` (seed 000 eq. (2)).

    Parameters
    ----------
    anchors : (m, d) anchor coordinates, m (d = 2 or 3, the solved dimension).
    position : (d,) true tag position.
    sigma_m : range standard deviation, m (scalar or (m,)).
    anchor_ids : names of the anchors (default ``a1 ... am``).
    height_offset : (m,) known anchor-tag height differences for a 2-D solution.
    """
    from robustloc.models.ranging import RangeModel

    a = np.asarray(anchors, dtype=float)
    model = RangeModel(a, height_offset)
    x = np.asarray(position, dtype=float).reshape(1, -1)
    if x.shape[1] != model.dim:
        raise ValueError(f"position must have {model.dim} coordinates like the anchors")
    H = model.jacobian(x)[0]
    sig = np.broadcast_to(np.asarray(sigma_m, dtype=float), (a.shape[0],)).copy()
    if np.any(~np.isfinite(sig)) or np.any(sig <= 0):
        raise ValueError("range sigma must be positive and finite")
    ids = anchor_ids if anchor_ids is not None else [f"a{i + 1}" for i in range(a.shape[0])]
    return Layout(name, H, sig, list(map(str, ids)), model.dim, tuple(range(min(2, model.dim))),
                  anchors=a, truth=x[0], height_offset=model.height_offset)


def rssi_layout(
    anchors: ArrayLike,
    position: ArrayLike,
    sigma_db: float | ArrayLike,
    n: float | ArrayLike,
    anchor_ids: list[str] | None = None,
    height_offset: ArrayLike | None = None,
    name: str = "rssi",
) -> Layout:
    """Layout of RSSI positioning with the log-distance model (seed 000 eq. (1)).

    The design is ``d RSSI / d x`` at ``position``; observations and faults are in dB
    (a body blocking a beacon is a gross error of 6-18 dB), position errors in metres.
    """
    from robustloc.models.ranging import RssiModel

    a = np.asarray(anchors, dtype=float)
    model = RssiModel(a, A=0.0, n=n, height_offset=height_offset)
    x = np.asarray(position, dtype=float).reshape(1, -1)
    if x.shape[1] != a.shape[1]:
        raise ValueError(f"position must have {a.shape[1]} coordinates like the anchors")
    H = model.jacobian(x)[0]
    sig = np.broadcast_to(np.asarray(sigma_db, dtype=float), (a.shape[0],)).copy()
    if np.any(~np.isfinite(sig)) or np.any(sig <= 0):
        raise ValueError("RSSI sigma must be positive and finite")
    ids = anchor_ids if anchor_ids is not None else [f"a{i + 1}" for i in range(a.shape[0])]
    return Layout(name, H, sig, list(map(str, ids)), a.shape[1], tuple(range(min(2, a.shape[1]))),
                  anchors=a, truth=x[0], height_offset=model.height_offset, kind="rssi",
                  path_loss_n=model.n)


def gnss_layout(
    t_s: float = 0.0,
    lat_deg: float = 30.53,
    lon_deg: float = 114.36,
    height_m: float = 30.0,
    systems: str = "GEC",
    mask_deg: float = 10.0,
    elevation_weighting: bool = True,
) -> Layout:
    """Layout of a simulated multi-constellation snapshot (see :mod:`robustloc.sim.gnss`)."""
    from robustloc.sim.gnss import visible_design

    snap = visible_design(t_s, lat_deg, lon_deg, height_m, systems, mask_deg,
                          elevation_weighting)
    return Layout(f"gnss-{systems}", snap.H_enu, snap.sigma, snap.ids, 3, (0, 1))


class MonteCarloNote(UserWarning):
    """A property of the layout that changes what a method's row means (e.g. LEGE searching
    no gross error at a low redundancy, :func:`lege_note`)."""


def uncontrolled_observations(
    layout: Layout, alpha0: float = ALPHA0, beta0: float = BETA0,
) -> list[tuple[str, float]]:
    """Observations whose MDB is infinite: redundancy number ``r_i = 0`` (no other
    observation controls them, so no fault on them shows in any residual).

    Returns
    -------
    list of (observation id, r_i)
    """
    rel = reliability(layout.H, layout.sigma, alpha0=alpha0, beta0=beta0)
    bad = np.flatnonzero(~np.isfinite(rel.mdb[0]))
    return [(layout.obs_ids[i], float(np.nan_to_num(rel.redundancy[0, i]))) for i in bad]


def check_fault_unit(
    layout: Layout, n_faults: int, unit: str, alpha0: float = ALPHA0, beta0: float = BETA0,
) -> None:
    """Refuse fault sizes in MDB multiples when some observation has no finite MDB.

    ``size * MDB_i`` would inject an infinite gross error on an observation with
    redundancy number ``r_i = 0`` (every method then fails on those trials and the theory
    columns are NaN).

    Raises
    ------
    InputError
        ``n_faults > 0``, ``unit == "mdb"`` and an observation has ``r_i = 0``.
    """
    if n_faults < 1 or unit != "mdb":
        return
    bad = uncontrolled_observations(layout, alpha0, beta0)
    if bad:
        which = ", ".join(f"{name} (r = {max(r, 0.0):.2g})" for name, r in bad)
        raise InputError(
            f"fault sizes in multiples of the MDB are infinite for {len(bad)} uncontrolled "
            f"observation(s) of layout {layout.name}: {which}; redundancy number 0 means no "
            "other observation checks it, so no fault on it is detectable (MDB = inf).  Give "
            "the fault sizes in metres (dB for RSSI) instead: --unit m (unit='m')"
        )


def lege_orders(layout: Layout, lege_max_order: int = 3, nonlinear: bool = False) -> int:
    """Largest number of gross errors LEGE searches for on ``layout``.

    ``min(r - 1, r - min_dof)`` with ``r = n - p`` the redundancy and ``min_dof`` LEGE's
    default (:data:`robustloc.estimators.linear.LEGE_MIN_DOF`), capped by
    ``lege_max_order`` on the linearized model (the nonlinear runs use the
    :class:`~robustloc.estimators.ranging.Locator`'s own setting, no cap).  0 means LEGE
    equals plain least squares on this layout.
    """
    r = layout.n - layout.p
    k = max(min(r - 1, r - LEGE_MIN_DOF), 0)
    return k if nonlinear else min(k, int(lege_max_order))


def lege_note(layout: Layout, lege_max_order: int = 3, nonlinear: bool = False) -> str | None:
    """Why ``lege``'s row is not what was asked on this layout, or None.

    LEGE keeps ``min_dof`` residual degrees of freedom (:func:`lege_orders`): on a layout of
    redundancy ``r <= min_dof`` it searches no gross error at all and equals ``ls``; with
    ``r - min_dof < lege_max_order`` (linearized model) it searches fewer than asked.
    """
    m = LEGE_MIN_DOF
    r = layout.n - layout.p
    k = lege_orders(layout, lege_max_order, nonlinear)
    if k == 0:
        return (f"lege searches no gross error on layout {layout.name}: its redundancy "
                f"n - p = {layout.n} - {layout.p} = {r} is below {m + 1} (LEGE keeps at least "
                f"{m} residual degrees of freedom, as robustloc locate runs it: see "
                "robustloc.estimators.linear.lege), so lege equals ls (plain least squares) "
                "here and flags nothing")
    if not nonlinear and k < lege_max_order:
        return (f"lege searches at most {k} gross error(s) on layout {layout.name}, not the "
                f"{lege_max_order} asked (redundancy {r}; LEGE keeps at least {m} residual "
                "degrees of freedom)")
    return None


@dataclass(frozen=True)
class Trials:
    """Simulated observations of a Monte Carlo batch (truth at the origin)."""

    y: Array  # (T, n)
    faults: Array  # (T, n) injected gross errors (0 = clean)
    faulty: NDArray[np.bool_]  # (T, n)


def draw_trials(
    layout: Layout,
    trials: int,
    n_faults: int,
    size: float,
    unit: str = "m",
    seed: int | list[int] = 1,
    alpha0: float = ALPHA0,
    beta0: float = BETA0,
) -> Trials:
    """Draw noise and inject ``n_faults`` gross errors per trial.

    Parameters
    ----------
    size : float
        Fault magnitude (random sign): metres (``unit="m"``) or multiples of each
        observation's MDB (``unit="mdb"``).
    seed : int or list of int
        Seed of ``numpy.random.default_rng`` (a list: ``[seed, chunk]``, see the module
        docstring).

    Raises
    ------
    InputError
        ``unit="mdb"`` with faults on a layout where an observation has redundancy number
        0 (its MDB is infinite, :func:`check_fault_unit`).
    """
    if trials < 1:
        raise ValueError("number of trials must be at least 1")
    if not 0 <= n_faults <= layout.n:
        raise ValueError(f"n_faults must be in 0..{layout.n}")
    if unit not in ("m", "mdb"):
        raise ValueError("fault size unit must be 'm' or 'mdb'")
    check_fault_unit(layout, n_faults, unit, alpha0, beta0)
    rng = np.random.default_rng(seed)
    e = rng.normal(size=(trials, layout.n)) * layout.sigma
    idx = np.argsort(rng.random((trials, layout.n)), axis=1)[:, :n_faults]
    faulty = np.zeros((trials, layout.n), dtype=bool)
    np.put_along_axis(faulty, idx, True, axis=1)
    sign = rng.choice([-1.0, 1.0], size=(trials, layout.n))
    if unit == "mdb" and n_faults > 0:  # (no fault: no MDB needed, inf where r_i = 0)
        mdb = reliability(layout.H, layout.sigma, alpha0=alpha0, beta0=beta0).mdb[0]
        mag = size * mdb
    else:
        mag = np.full(layout.n, float(size))
    f = np.where(faulty, sign * mag, 0.0)
    return Trials(y=e + f, faults=f, faulty=faulty)


def theory(
    layout: Layout, tr: Trials, alpha: float | None = None,
    alpha0: float = ALPHA0, beta0: float = BETA0,
) -> dict[str, float]:
    """Theoretical global-test rejection rate (averaged over the drawn faults) and, for single
    faults, the w-test power of the faulty observation."""
    wh = whiten(layout.H, layout.sigma)
    dof = wh.n_used[0] - layout.p
    fw = tr.faults / layout.sigma
    U = wh.hat()[0]
    R = np.eye(layout.n) - U
    lam = np.einsum("ti,ij,tj->t", fw, R, fw)
    out = {
        "dof": float(dof),
        "alpha": float(global_alpha(dof, alpha0, beta0)) if alpha is None else float(alpha),
        "global_rejection": float(np.mean(detection_power_global(lam, dof, alpha, alpha0, beta0))),
    }
    nf = tr.faulty.sum(axis=1)
    if np.all(nf == 1):
        r = np.clip(np.diag(R), 0.0, 1.0)  # (an uncontrolled observation: -1e-17)
        delta = np.abs(fw[tr.faulty]) * np.sqrt(r[np.argmax(tr.faulty, axis=1)])
        out["w_test_power"] = float(np.mean(detection_power_w(delta, alpha0)))
    else:
        out["w_test_power"] = float("nan")
    return out


def _weight(name: str):  # noqa: ANN202
    from robustloc.robust.weights import get_weight

    return get_weight(name)


def _run_method(
    method: str, layout: Layout, y: Array, alpha: float | None, alpha0: float, beta0: float,
    reject_weight: float, lege_max_order: int,
) -> tuple[Array, NDArray[np.bool_], NDArray[np.bool_], NDArray[np.bool_]]:
    """Return (x (T, p), rejected (T, n), flagged (T,), usable (T,))."""
    T = y.shape[0]
    H = np.broadcast_to(layout.H, (T,) + layout.H.shape)
    w0 = np.broadcast_to(1.0 / layout.sigma**2, y.shape)
    if method in ("snooping", "raim-single"):
        if method == "snooping":
            res = snoop_linear(H, y, layout.sigma, alpha=alpha, alpha0=alpha0, beta0=beta0)
        else:  # the classical single-exclusion RAIM policy (see module docstring)
            res = snoop_linear(H, y, layout.sigma, alpha=RAIM_SINGLE_ALPHA, alpha0=alpha0,
                               beta0=beta0, require_local=False, max_exclusions=1)
        usable = st.among(res.status, (st.OK, st.FAULT_EXCLUDED))
        return res.x, res.excluded, res.detected, usable
    from robustloc.estimators import linear

    if method == "ls":
        fit = linear.solve_wls(H, y, w0)
        rej = np.zeros(y.shape, dtype=bool)
        return fit.x, rej, np.zeros(T, dtype=bool), fit.status == st.OK
    if method == "lege":
        # min_dof: LEGE's default, the one `robustloc locate` runs.  It is no requirement
        # of a test statistic: the digest (seed 000, LEGE) searches k = 1 .. r - 1, and the
        # ratio of eq. (12) needs only r - k >= 1.  It is robustloc's guard against that
        # ratio firing on pure noise when few residual dof remain; on the 5-anchor layout of
        # the review (r = 3) the paper's full search (min_dof=1) flagged 61 % of fault-free
        # trials, min_dof=2 19 % (4000 trials).  The Monte Carlo measures the method
        # robustloc ships (and --nonlinear's Locator keeps the default too), so it keeps
        # the guard and says where it binds (lege_note).
        fit = linear.lege(H, y, w0, max_order=lege_max_order, min_dof=LEGE_MIN_DOF)
        ge = np.asarray(fit.extra.get("gross_errors", np.zeros(y.shape)))
        rej = np.nan_to_num(ge) != 0
    else:
        fit = linear.irls(H, y, _weight(method), w0, scale=1.0)
        rel = np.nan_to_num(fit.w / w0, nan=1.0)
        rej = rel < reject_weight
    usable = st.among(fit.status, st.USABLE)
    return fit.x, rej, rej.any(axis=1), usable


#: Locator method used for each Monte Carlo method in nonlinear runs.
_LOCATOR_METHOD = {"ls": "nls", "snooping": "snooping", "lege": "lege", "huber": "huber",
                   "raim-single": "",
                   "hampel": "hampel", "igg": "igg", "igg3": "igg3"}


def _run_method_nonlinear(
    method: str, layout: Layout, y: Array, alpha0: float, beta0: float, reject_weight: float,
) -> tuple[Array, NDArray[np.bool_], NDArray[np.bool_], NDArray[np.bool_]]:
    """Ranges (or RSSI) ``model value + noise + faults`` solved by the Gauss-Newton based
    :class:`robustloc.estimators.ranging.Locator`; returns (dx, rejected, flagged, usable).

    The Locator trusts the layout's a-priori sigma (``robust_scale="apriori"``), as the
    linearized IRLS does (``scale=1``): the trials are independent draws of one layout whose
    noise is known.  Its default ``"log"`` would estimate one scale per anchor from the
    whole batch of trials as if it were one log, and the injected faults inflate that scale
    (about 5x for one 3-MDB fault on 5 anchors), so the robust weights down-weighted
    nothing.  An observation counts as rejected when its *relative* weight, the weight
    function's value ``w * sigma_i^2`` (the Locator's weights are ``p / sigma_i^2``, in the
    domain it fits: metres for ranges, dB for RSSI), is below ``reject_weight``.
    """
    from robustloc.estimators.ranging import Locator
    from robustloc.models.ranging import RangeModel, RssiModel

    sig = np.asarray(layout.sigma, dtype=float)
    loc = Locator(method=_LOCATOR_METHOD[method], domain=layout.kind,
                  sigma=tuple(float(v) for v in sig), robust_scale="apriori",
                  alpha0=alpha0, beta0=beta0)
    if layout.kind == "rssi":
        A = np.zeros(len(layout.anchors))
        model = RssiModel(layout.anchors, A, layout.path_loss_n, layout.height_offset)
        z = model.predict(layout.truth[None])[0] + y
        sol = loc.solve(layout.anchors, z, "rssi", A=A, n=layout.path_loss_n,
                        height_offset=layout.height_offset)
    else:
        model = RangeModel(layout.anchors, layout.height_offset)
        z = model.predict(layout.truth[None])[0] + y
        sol = loc.solve(layout.anchors, z, "range", height_offset=layout.height_offset)
    dx = sol.position - layout.truth[None]
    rel = np.nan_to_num(np.asarray(sol.weights, dtype=float) * sig**2, nan=1.0)
    rej = np.asarray(sol.excluded, dtype=bool) | (rel < reject_weight)
    if method == "snooping":
        flagged = np.asarray(sol.extra.get("detected", rej.any(axis=1)), dtype=bool)
    else:
        flagged = rej.any(axis=1)
    return dx, rej, flagged, sol.ok


def run_montecarlo(
    layout: Layout,
    *,
    n_faults: int = 1,
    size: float = 1.0,
    unit: str = "mdb",
    trials: int = 10_000,
    methods: tuple[str, ...] = ("ls", "snooping", "lege", "huber", "igg3"),
    alpha: float | None = None,
    alpha0: float = ALPHA0,
    beta0: float = BETA0,
    reject_weight: float = 0.1,
    lege_max_order: int | None = None,
    seed: int = 1,
    nonlinear: bool = False,
    progress: Callable[[int], None] | None = None,
) -> pd.DataFrame:
    """Run one Monte Carlo experiment; one row per method.

    Parameters
    ----------
    layout : Layout
        From :func:`ranging_layout` or :func:`gnss_layout`.
    n_faults : int
        Gross errors injected per trial (0 for the false-alarm experiment).
    size : float
        Fault size in ``unit`` (``"m"`` metres or ``"mdb"`` multiples of the MDB).
    trials : int
        Number of trials (the batch size of every estimator).
    methods : tuple of str
        Among :data:`METHODS`.
    alpha : float, optional
        Fixed global-test significance (default: B-method).
    alpha0, beta0 : float
        w-test significance and B-method type II error.
    reject_weight : float
        IRLS: equivalent weight below which an observation counts as rejected.
    lege_max_order : int, optional
        Largest number of gross errors LEGE searches for (cost grows as ``C(n, k)``);
        default 3.  Linearized model only: with ``nonlinear`` it is refused
        (``ValueError``), since the Locator's LEGE searches as many as the redundancy
        allows.
    seed : int
    nonlinear : bool
        Ranging / RSSI layouts only: simulate the observations themselves (model value +
        noise + faults)
        and solve them with the Gauss-Newton based
        :class:`~robustloc.estimators.ranging.Locator` (``ls`` is its ``nls``), which
        re-linearizes after each exclusion, instead of the linearized model.  The Locator
        trusts the layout's sigma (``robust_scale="apriori"``, like the linearized IRLS:
        its default ``"log"`` would learn a scale from the batch of trials, inflated by the
        injected faults) and an observation counts as rejected by its relative weight (see
        :func:`_run_method_nonlinear`).  The theory columns stay those of the linearized
        model: the gap is the effect of the linearization and of the Locator's own
        iteration (robust start, cofactor updates of redescending weights).
        A fixed ``alpha`` and ``lege_max_order`` do not apply (Locator's own settings):
        either given is refused with ``ValueError`` (they were taken and ignored).
    progress : callable, optional
        Called with the number of trials of each finished chunk (e.g. a progress bar's
        ``update``).

    Returns
    -------
    pandas.DataFrame
        Columns ``method, trials, n_faults, size, unit, flag_rate, identified, unavailable,
        err_mean_m, err_rms_m, err_p95_m, theory_global, theory_w, seconds``;
        ``attrs["notes"]``: what changes the meaning of a row on this layout (LEGE
        searching fewer gross errors than asked, or none: :func:`lege_note`), each also
        issued as a :class:`MonteCarloNote` warning.

    Raises
    ------
    InputError
        Fault sizes in MDB multiples with an observation of redundancy number 0
        (:func:`check_fault_unit`).
    """
    bad = [m for m in methods if m not in METHODS]
    if bad:
        raise ValueError(f"unknown method(s) {', '.join(bad)}; choose among {', '.join(METHODS)}")
    if nonlinear and layout.anchors is None:
        raise ValueError("nonlinear Monte Carlo needs a ranging or RSSI layout (anchors file)")
    if nonlinear and "raim-single" in methods:
        raise ValueError("method 'raim-single' is available on the linearized model only")
    if nonlinear and alpha is not None:
        raise ValueError("a fixed alpha is not available for nonlinear runs (B-method only)")
    if nonlinear and lege_max_order is not None:  # (taken and ignored before)
        raise ValueError("lege_max_order applies to the linearized model only: nonlinear "
                         "runs use the Locator's LEGE, which searches as many gross errors "
                         "as the redundancy allows")
    if lege_max_order is None:
        lege_max_order = LEGE_MAX_ORDER
    if trials < 1:
        raise ValueError("number of trials must be at least 1")
    notes = []
    if "lege" in methods:
        note = lege_note(layout, lege_max_order, nonlinear)
        if note:
            notes.append(note)
            warnings.warn(note, MonteCarloNote, stacklevel=2)
    hz = list(layout.horizontal)
    acc = {m: _Accumulator(trials) for m in methods}
    # each method's theory at its own global-test significance: raim-single always tests
    # at RAIM_SINGLE_ALPHA (its row showed the B-method's or --alpha's rate beside a
    # measured 0.001: the montecarlo review, 2026-12-06)
    alphas = {m: RAIM_SINGLE_ALPHA if m == "raim-single" else alpha for m in methods}
    th_sum = {a: {"global_rejection": 0.0, "w_test_power": 0.0}
              for a in dict.fromkeys(alphas.values())}
    th1: dict = {}
    for k, start in enumerate(range(0, trials, CHUNK_TRIALS)):
        T = min(CHUNK_TRIALS, trials - start)
        tr = draw_trials(layout, T, n_faults, size, unit, seed if k == 0 else [seed, k],
                         alpha0, beta0)
        for a_m, sums in th_sum.items():
            th = theory(layout, tr, a_m, alpha0, beta0)
            if trials <= CHUNK_TRIALS:  # one chunk: exactly as before
                th1[a_m] = th
            for key in sums:
                sums[key] += th[key] * T
        for m in methods:
            t0 = time.perf_counter()
            if nonlinear:
                x, rej, flagged, usable = _run_method_nonlinear(
                    m, layout, tr.y, alpha0, beta0, reject_weight
                )
            else:
                x, rej, flagged, usable = _run_method(
                    m, layout, tr.y, alpha, alpha0, beta0, reject_weight, lege_max_order
                )
            err = np.linalg.norm(x[:, hz], axis=1)
            acc[m].add(flagged, np.all(rej == tr.faulty, axis=1), usable,
                       err[usable & np.isfinite(err)], time.perf_counter() - t0)
        if progress is not None:
            progress(T)
    rows = []
    for m in methods:
        a = acc[m]
        rows.append({
            "method": m,
            "trials": trials,
            "n_faults": n_faults,
            "size": size,
            "unit": unit,
            "flag_rate": a.flagged / trials,
            "identified": a.identified / trials if n_faults > 0 else float("nan"),
            "unavailable": 1.0 - a.usable / trials,
            "err_mean_m": a.err_sum / a.usable if a.usable else float("nan"),
            "err_rms_m": float(np.sqrt(a.err_sq / a.usable)) if a.usable else float("nan"),
            "err_p95_m": a.p95(),
            "theory_global": th1[alphas[m]]["global_rejection"] if th1 else
            th_sum[alphas[m]]["global_rejection"] / trials,
            "theory_w": th1[alphas[m]]["w_test_power"] if th1 else
            th_sum[alphas[m]]["w_test_power"] / trials,
            "model": "nonlinear" if nonlinear else "linearized",
            "seconds": a.seconds,
        })
    out = pd.DataFrame(rows)
    out.attrs["notes"] = notes
    return out


class _Accumulator:
    """Counts, sums and the tail of the errors of one method over the chunks of a run.

    The exact 95th percentile of ``n`` errors (``numpy.percentile``'s linear
    interpolation between the sorted values of ranks ``floor(q)`` and ``ceil(q)``,
    ``q = 0.95 (n - 1)``) needs only the ``n - floor(q)`` largest of them; ``n`` is at most
    the number of trials, so the largest ``ceil(0.05 trials) + 2`` are kept.
    """

    def __init__(self, trials: int) -> None:
        self.keep = int(np.ceil(0.05 * trials)) + 2
        self.flagged = 0
        self.identified = 0
        self.usable = 0
        self.err_sum = 0.0
        self.err_sq = 0.0
        self.seconds = 0.0
        self.tail = np.empty(0)

    def add(self, flagged: NDArray[np.bool_], identified: NDArray[np.bool_],
            usable: NDArray[np.bool_], err_ok: Array, seconds: float) -> None:
        self.flagged += int(np.count_nonzero(flagged))
        self.identified += int(np.count_nonzero(identified))
        self.usable += int(err_ok.size)
        self.err_sum += float(np.sum(err_ok))
        self.err_sq += float(np.sum(err_ok**2))
        self.seconds += seconds
        tail = np.concatenate([self.tail, err_ok])
        if tail.size > self.keep:
            tail = np.partition(tail, tail.size - self.keep)[tail.size - self.keep :]
        self.tail = tail

    def p95(self) -> float:
        n = self.usable
        if n == 0:
            return float("nan")
        tail = np.sort(self.tail)  # the largest min(n, keep) errors, ascending
        q = 0.95 * (n - 1)
        lo, hi = int(np.floor(q)), int(np.ceil(q))
        off = n - tail.size  # rank of tail[0] among all n errors
        a, b = tail[lo - off], tail[hi - off]
        return float(a + (b - a) * (q - lo))
