"""The ``locate`` workflow: a fix, its test and its protection level for every epoch.

:func:`run_locate` streams a measurements log (a file, standard input or an in-memory
frame; rows in any order) through the configured locators
(:class:`~robustloc.estimators.ranging.Locator` via
:func:`~robustloc.integrity.fixes.locate_protected`) and writes one positions row per
epoch and method with a ``status``.  :class:`LocateSettings` holds every setting, checked
with the command line's wording.  ``robustloc locate``, :func:`robustloc.locate`, the
Dask engine and the live service all run this code.
"""

from __future__ import annotations

import argparse
import sys
import time as _time
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING, Any

import numpy as np
import pandas as pd
from numpy.typing import NDArray

from robustloc.errors import InputError
from robustloc.options import (
    check_settings,
    float_in,
    nonnegative_float,
    option,
    positive_float,
    positive_int,
    scale_floor,
    sigma_value,
    tag_height_m,
)

if TYPE_CHECKING:
    from robustloc._jitnotice import CompileWatch

#: ``model`` values: the path-loss models of :mod:`robustloc.models.pathloss`.
PATH_LOSS_MODELS = ("log-distance", "attenuation-factor", "friis")


def methods_known() -> tuple[str, ...]:
    """``auto`` and every method of :data:`robustloc.estimators.ranging.METHODS`."""
    from robustloc.estimators.ranging import METHODS

    return ("auto",) + tuple(METHODS)


def method_list(text: str | Sequence[str]) -> list[str]:
    """Check a ``--method`` value (comma-separated text, or a sequence of names): known
    methods, each once (a synonym, ``asymmetric-igg``, as the name it stands for: ``asym``);
    raises :class:`argparse.ArgumentTypeError` otherwise."""
    known = methods_known()
    if not isinstance(text, str):
        text = ",".join(str(m) for m in text)
    from robustloc.estimators.ranging import METHOD_SYNONYMS

    # (case-insensitive: the docs write IGG, LEGE, LS; `--method IGG` was refused)
    methods = [METHOD_SYNONYMS.get(m.strip().lower(), m.strip().lower())
               for m in text.split(",")]
    if not any(methods):
        raise argparse.ArgumentTypeError(
            f"expected one or more of {', '.join(known)}, got {text!r}")
    if "" in methods:
        raise argparse.ArgumentTypeError(f"empty method name in {text!r}")
    for m in methods:
        if m not in known:
            raise argparse.ArgumentTypeError(
                f"unknown method {m!r}; choose from {', '.join(known)}")
    dup = [m for i, m in enumerate(methods) if m in methods[:i]]
    if dup:
        raise argparse.ArgumentTypeError(f"method {dup[0]!r} given twice in {text!r}")
    return methods


@dataclass(frozen=True)
class LocateSettings:
    """Every setting of ``locate`` (the ``robustloc locate`` options of the same name).

    Parameters
    ----------
    method : tuple of str
        Methods, one output row per epoch each (``auto`` the default; see
        ``robustloc locate --help``).  A comma-separated str is accepted.
    dim : {2, 3}
        Solve in 2-D or 3-D.
    solver, reference, domain, robust_scale, model
        As the options of the same name.
    sigma : float, optional
        A-priori std of one observation (m or dB); default the anchors' ``sigma`` column.
    alert_limit : float, optional
        Horizontal alert limit (m): hpl above it -> ``protection_exceeded``.
    k_noise : float, optional
        Protection levels' multiplier of the fault-free noise (default 3.29).
    min_scale : float
        Floor of the estimated robust scale.
    param : tuple of str
        Weight-function thresholds as ``NAME=VALUE`` items (``--param``).
    tag_height : float, optional
        2-D: known tag height (m), to reduce slant ranges.
    range_calibration : bool
        Apply the anchors' ``bias``/``scale`` columns (``--no-range-calibration``: False).
    alpha0, beta0 : float
        w-test significance and B-method type II error.
    chunk_rows : int
        Rows read per chunk.
    log_scale_fixed : mapping of str to tuple of float, optional
        Per method, the per-anchor log scale to use as it is (the Dask engine computes it
        once for a whole dataset); default: estimated by a first pass over the log.
    log_gross_share : mapping of str to float, optional
        Per method, the log's gross-error share found with ``log_scale_fixed``
        (:meth:`~robustloc.estimators.ranging.Locator.log_statistics`).
    side_prior : {"log", "none"}
        ``log``: an ambiguous fix (nearly collinear anchors: it and its mirror image
        across their line pass the same test) is placed on the side of the line where the
        log's unambiguous fixes lie, when they lie there significantly more often
        (:func:`robustloc.integrity.fixes.ambiguity_sides`); ``none``: each fix stays
        where its estimator put it.  With ``robust_scale="log"`` only.
    log_sides : mapping of str to tuple, optional
        Per method, the sides found with ``log_scale_fixed``
        (:attr:`~robustloc.estimators.ranging.Locator.log_sides`).
    """

    method: tuple[str, ...] = option(("auto",), check=method_list)
    dim: int = option(2, choices=(2, 3))
    solver: str = option("nonlinear", choices=("nonlinear", "linearized"))
    reference: str = option("first", choices=("first", "nearest"))
    domain: str = option("range", choices=("range", "rssi"))
    sigma: float | None = option(None, check=sigma_value)
    robust_scale: str = option("log", choices=("log", "mad", "apriori"))
    alert_limit: float | None = option(None, check=positive_float)
    k_noise: float | None = option(None, check=nonnegative_float)
    min_scale: float = option(0.0, check=scale_floor)
    param: tuple[str, ...] = ()
    model: str | None = option(None, choices=PATH_LOSS_MODELS)
    tag_height: float | None = option(None, check=tag_height_m)
    range_calibration: bool = True
    alpha0: float = option(0.001, check=float_in(1e-12, 0.5))
    beta0: float = option(0.10, check=float_in(1e-6, 0.99))
    chunk_rows: int = option(500_000, check=positive_int)
    log_scale_fixed: Mapping[str, tuple[float, ...]] | None = None
    log_gross_share: Mapping[str, float] | None = None
    side_prior: str = option("log", choices=("log", "none"))
    log_sides: Mapping[str, tuple] | None = None

    def __post_init__(self) -> None:
        if isinstance(self.method, str):
            object.__setattr__(self, "method", tuple(m.strip() for m in self.method.split(",")))
        else:
            object.__setattr__(self, "method", tuple(self.method))
        object.__setattr__(self, "param", tuple(self.param))
        check_settings(self)
        object.__setattr__(self, "method", tuple(method_list(self.method)))

    @classmethod
    def from_namespace(cls, args: argparse.Namespace) -> LocateSettings:
        """The settings of a parsed ``robustloc locate`` command line."""
        return cls(
            method=tuple(args.method), dim=args.dim, solver=args.solver,
            reference=args.reference, domain=args.domain, sigma=args.sigma,
            robust_scale=args.robust_scale, alert_limit=args.alert_limit,
            k_noise=args.k_noise, min_scale=args.min_scale, param=tuple(args.param),
            model=args.model, tag_height=args.tag_height,
            range_calibration=not args.no_range_calibration, alpha0=args.alpha0,
            beta0=args.beta0, chunk_rows=args.chunk_rows,
            log_scale_fixed=getattr(args, "log_scale_fixed", None),
            log_gross_share=getattr(args, "log_gross_share", None),
            side_prior=getattr(args, "side_prior", "log"),
            log_sides=getattr(args, "log_sides", None),
        )


def weight_params(items: Sequence[str], methods: Sequence[str]) -> dict[str, dict[str, float]]:
    """``--param NAME=VALUE`` items -> per robust method, the thresholds it knows.

    A name that no chosen robust method has is an error naming the known ones."""
    import dataclasses
    import math

    from robustloc.estimators.ranging import ROBUST, method_weight
    from robustloc.integrity.fixes import AUTO, AUTO_ROBUST

    # 'auto' refits failing epochs with AUTO_ROBUST: its thresholds apply there
    robust = [m for m in methods if m in ROBUST or m == AUTO]
    known = {m: [f.name for f in dataclasses.fields(
        type(method_weight(AUTO_ROBUST if m == AUTO else m)))] for m in robust}
    out: dict[str, dict[str, float]] = {m: {} for m in robust}
    for it in items:
        name, sep, val = it.partition("=")
        name = name.strip()
        try:
            value = float(val) if sep and name else math.nan
        except ValueError:
            value = math.nan
        if not math.isfinite(value):
            raise InputError(f"--param expects NAME=NUMBER (finite), got {it!r}")
        if not robust:
            raise InputError(f"--param {name}: weight-function thresholds apply only to the "
                             f"robust methods {', '.join(ROBUST)}")
        users = [m for m in robust if name in known[m]]
        if not users:
            names = "; ".join(f"{m}: {', '.join(known[m])}" for m in robust)
            raise InputError(f"--param {name!r} is not a threshold of the chosen method(s) "
                             f"(known: {names})")
        for m in users:
            out[m][name] = value
    return out


@dataclass(frozen=True)
class Geometry:
    """The configured locators and the anchors as the solvers see them."""

    locators: list[Any]
    anchors: pd.DataFrame
    xyz: np.ndarray
    height: np.ndarray | None


def configure(settings: LocateSettings, anchors: pd.DataFrame) -> Geometry:
    """The locators of ``settings`` for ``anchors`` (a validated anchors frame; its
    ``attrs["path"]`` names it in errors)."""
    from robustloc.estimators.ranging import Locator
    from robustloc.io.tables import anchor_sigma

    where = anchors.attrs.get("path")
    if settings.dim == 3 and "z" not in anchors.columns:
        raise InputError("--dim 3 needs a z column in the anchors file", where, 1)
    cols = ["x", "y"] + (["z"] if settings.dim == 3 else [])
    xyz = anchors[cols].to_numpy(dtype=float)
    height = None
    if settings.tag_height is not None:
        if settings.dim != 2 or "z" not in anchors.columns:
            raise InputError("--tag-height needs --dim 2 and a z column in the anchors file",
                             where, 1)
        height = anchors["z"].to_numpy(dtype=float) - settings.tag_height
    methods = list(settings.method)
    params = weight_params(settings.param, methods)
    sigma: float | tuple[float, ...] | None = settings.sigma
    if sigma is None:
        sg = anchor_sigma(anchors)
        sigma = None if sg is None else tuple(float(v) for v in sg)
    try:  # the settings are the user's: a refused combination is a user error
        locators = [
            Locator(
                m, solver=settings.solver, domain=settings.domain, sigma=sigma,
                robust_scale=settings.robust_scale, reference=settings.reference,
                weight_params=params.get(m, {}),
                min_scale=settings.min_scale, alpha0=settings.alpha0, beta0=settings.beta0,
                log_sides=() if settings.side_prior == "none" else None,
            )
            for m in methods
        ]
    except (ValueError, TypeError) as exc:
        if isinstance(exc, InputError):
            raise
        raise InputError(f"invalid settings: {exc}") from None
    return Geometry(locators, anchors, xyz, height)


def refuse_rssi_options(kind: str, given: dict[str, bool], source: Any = None) -> None:
    """Refuse options that apply only to RSSI (``given``: each option's words and whether
    the user set it) on a log of ``kind`` ``"range"``, naming ``source`` (the log's file
    or frame) at its header, whose value column says what the log holds."""
    from robustloc.io.tables import _display

    opts = [opt for opt, on in given.items() if on]
    if kind != "range" or not opts:
        return
    one = len(opts) == 1
    raise InputError(f"{' and '.join(opts)} {'applies' if one else 'apply'} to RSSI "
                     "measurements, but this log holds ranges (a range column): leave "
                     f"{'it' if one else 'them'} out",
                     None if source is None else _display(source), None if source is None else 1)


def prepared_values(settings: LocateSettings, anchors: pd.DataFrame, block: Any,
                    source: Any = None) -> np.ndarray:
    """A block's observation matrix as the solvers see it (range calibration applied).

    Settings that apply only to RSSI (``--domain rssi``, ``--model``) are refused on a
    range log rather than ignored (``source``, the block's file or frame, names it): the
    user asked for something this log cannot give."""
    from robustloc.models.calibration import apply_range_calibration

    refuse_rssi_options(block.value, {"--domain rssi": settings.domain == "rssi",
                                      f"--model {settings.model}": settings.model is not None},
                        source)
    if block.value == "range" and settings.range_calibration:
        return apply_range_calibration(anchors, block.values)
    return block.values


#: The first pass keeps at most ``2 LOG_SAMPLE_CAP`` epochs of the log (an even sample).
LOG_SAMPLE_CAP = 5_000



def log_sample_step(n_epochs: int, cap: int | None = None) -> int:
    """The first pass's sampling step ``k``: the epochs whose :func:`epoch_hash` is a
    multiple of ``k`` are kept, ``k`` the smallest power of two with ``ceil(n / k) <= 2
    cap`` for a log of ``n_epochs`` epochs (about ``n / k`` of them are kept; all when
    ``k = 1``).  ``cap``: default :data:`LOG_SAMPLE_CAP`."""
    cap = LOG_SAMPLE_CAP if cap is None else cap
    k = 1
    while -(-n_epochs // k) > 2 * cap:
        k *= 2
    return k


def epoch_hash(time_s: np.ndarray, tags: Any) -> NDArray[np.uint64]:
    """A 64-bit hash of each epoch's ``(time, tag)`` (pandas' ``hash_array``: the same in
    every process and run).  The first pass samples epochs by it, not by their position
    in the log, so that the sample -- and the noise scale, and every fix -- is the same
    whatever the rows' order, the chunks (``--chunk-rows``: a time with more rows than a
    chunk is streamed in the file's order), or the files a dataset is split into."""
    h_time = pd.util.hash_array(np.asarray(time_s, dtype=np.float64) + 0.0)  # -0.0 as 0.0
    h_tag = pd.util.hash_array(np.asarray(tags, dtype=object), categorize=True)
    return pd.util.hash_array(h_time ^ (h_tag * np.uint64(0x9E3779B97F4A7C15)))


def _kept(h: NDArray[np.uint64], k: int) -> NDArray[np.bool_]:
    """Epochs of hash ``h`` in the sample of step ``k`` (a power of two: the samples of
    larger steps are subsets of smaller steps', so a streamed pass can thin as it goes)."""
    return (h & np.uint64(k - 1)) == 0


@dataclass
class LogSample:
    """The first pass's sample of a log (or of one of its files): the kept epochs'
    prepared values with their times and tags, and the epochs seen."""

    kind: str | None
    values: np.ndarray
    time_s: np.ndarray
    tags: np.ndarray
    hashes: NDArray[np.uint64]
    n_epochs: int

    @classmethod
    def empty(cls, m: int) -> LogSample:
        return cls(None, np.empty((0, m)), np.empty(0), np.empty(0, dtype=object),
                   np.empty(0, dtype=np.uint64), 0)

    def thinned(self, k: int) -> LogSample:
        """Only the epochs of the sample of step ``k``."""
        sel = _kept(self.hashes, k)
        return LogSample(self.kind, self.values[sel], self.time_s[sel], self.tags[sel],
                         self.hashes[sel], self.n_epochs)

    @classmethod
    def joined(cls, parts: Sequence[LogSample], m: int) -> LogSample:
        """The parts together, in the canonical order (time, then tag): the same sample
        whatever the order of the files or of the rows in them."""
        parts = [p for p in parts if len(p.values)] or [cls.empty(m)]
        kinds = [p.kind for p in parts if p.kind is not None]
        t = np.concatenate([p.time_s for p in parts])
        g = np.concatenate([p.tags for p in parts])
        order = np.asarray(pd.DataFrame({"t": t, "g": g.astype(str)}).sort_values(
            ["t", "g"], kind="stable").index)
        return cls(kinds[0] if kinds else None,
                   np.vstack([p.values for p in parts])[order], t[order], g[order],
                   np.concatenate([p.hashes for p in parts])[order],
                   sum(p.n_epochs for p in parts))


def _sample_blocks(settings: LocateSettings, anchors: pd.DataFrame,
                   blocks: Iterator[tuple[Any, Any]], k_min: int = 1,
                   cap: int | None = None) -> LogSample:
    """Stream ``(source, block)`` pairs, keeping the epochs of the sample of step
    ``max(k_min, log_sample_step(epochs seen so far))`` (memory: about ``2 cap`` epochs)."""
    keep: list[LogSample] = []
    kind, seen, k = None, 0, k_min
    for src, block in blocks:
        kind = block.value
        seen += block.n_epochs
        k = max(k, log_sample_step(seen, cap))
        h = epoch_hash(block.time, block.tag)
        sel = _kept(h, k)
        keep.append(LogSample(kind, prepared_values(settings, anchors, block, src)[sel],
                              np.asarray(block.time, dtype=float)[sel],
                              np.asarray(block.tag, dtype=object)[sel], h[sel],
                              block.n_epochs))
        if sum(len(p.values) for p in keep) > 4 * (LOG_SAMPLE_CAP if cap is None else cap):
            keep = [p.thinned(k) for p in keep]
    if not keep:
        return LogSample.empty(len(anchors))
    out = LogSample.joined([p.thinned(k) for p in keep], len(anchors))
    out.kind, out.n_epochs = kind, seen
    return out


def _epoch_major(frames: list[pd.DataFrame]) -> pd.DataFrame:
    """One block's rows of every method, epoch by epoch (each epoch's methods in the
    order given): the output stays in time order with several methods, whatever the
    chunking (block by block and method by method it was 0, 1, 0, 1, 2, 2)."""
    if len(frames) == 1:
        return frames[0]
    n = len(frames[0])
    both = pd.concat(frames, ignore_index=True)
    order = np.arange(n * len(frames)).reshape(len(frames), n).T.ravel()
    return both.iloc[order].reset_index(drop=True)


def fix_log_scale(settings: LocateSettings, geo: Geometry, sources: Sequence[Any],
                  order: str, cap: int | None = None) -> list[Any]:
    """First pass over the whole log: each locator's per-anchor noise scale and gross
    share from a sample of about ``2 cap`` epochs at most (those whose
    :func:`epoch_hash` is a multiple of :func:`log_sample_step`; every epoch of a log of
    up to ``2 cap``), taken in the canonical order (time, tag), so the scale, and every
    fix, is the same whatever ``chunk_rows``, the rows' order or the files' split.
    ``sources``: the log's files (or frames; a partitioned dataset: several).
    ``settings.log_scale_fixed`` (set by the Dask engine, which computes it once for the
    whole dataset) is used as it is."""
    from robustloc.io import iter_epochs

    cap = LOG_SAMPLE_CAP if cap is None else cap
    fixed = settings.log_scale_fixed
    if fixed is not None:
        shares = settings.log_gross_share or {}
        sides = settings.log_sides or {}
        return [replace(loc, log_scale_fixed=tuple(fixed[loc.method]),
                        log_gross_share=shares.get(loc.method),
                        log_sides=(loc.log_sides if loc.log_sides is not None
                                   else sides.get(loc.method, ())))
                if loc.robust_scale == "log" else loc for loc in geo.locators]
    blocks = ((src, b) for src in sources for b in iter_epochs(
        src, geo.anchors, chunk_rows=settings.chunk_rows, order=order))
    sample = _sample_blocks(settings, geo.anchors, blocks, cap=cap)
    if sample.kind is None:
        return geo.locators
    return log_scales_from_sample(settings, geo, sample.kind, sample.values, cap)


def log_scales_from_sample(settings: LocateSettings, geo: Geometry, kind: str,
                           sample: np.ndarray, cap: int | None = None) -> list[Any]:
    """The locators with their per-anchor log scale, gross share and ambiguity sides fixed
    from the first pass's ``sample`` (its epochs' prepared values, in log order).  The
    sides come from the sample's fixes with that scale (:func:`log_sides_of`)."""
    from robustloc.models.pathloss import log_distance_arrays

    cap = LOG_SAMPLE_CAP if cap is None else cap
    A = n = None
    if kind == "rssi":
        A, n = log_distance_arrays(geo.anchors, settings.model)
    out = []
    for loc in geo.locators:
        if loc.robust_scale != "log":
            out.append(loc)
            continue
        scale, share = loc.log_statistics(geo.xyz, sample, kind, A=A, n=n,
                                          height_offset=geo.height, max_epochs=2 * cap)
        loc = replace(loc, log_scale_fixed=tuple(float(v) for v in scale),
                      log_gross_share=share)
        if loc.log_sides is None:
            loc = replace(loc, log_sides=log_sides_of(loc, geo, kind, sample, A, n))
        out.append(loc)
    return out


def log_sides_of(locator: Any, geo: Geometry, kind: str, sample: np.ndarray,
                 A: np.ndarray | None, n: np.ndarray | None) -> tuple:
    """The ambiguity sides of the first pass's ``sample`` solved by ``locator`` (its log
    scale fixed): :func:`robustloc.integrity.fixes.ambiguity_sides`; ``()`` when no fix
    of the sample is ambiguous or none can be."""
    from robustloc.integrity.fixes import ambiguity_sides, locate_protected, range_model_of

    rm = range_model_of(geo.xyz, geo.height)
    if rm is None or not len(sample):
        return ()
    sol = locate_protected(replace(locator, log_sides=()), geo.xyz, sample, kind, A=A, n=n,
                           height_offset=geo.height)
    return ambiguity_sides(sol, rm)


def log_sample_of(settings: LocateSettings, anchors: pd.DataFrame, path: Any,
                  k: int) -> LogSample:
    """One file's share of the first pass when the log is split in files: its epochs in
    the sample of step ``k`` (:func:`log_sample_step` of the whole log's epoch count).

    The caller joins the files' samples (:meth:`LogSample.joined`: the Dask engine, on
    the workers' results) and checks each file's ``n_epochs`` against the count that
    gave ``k``."""
    from robustloc.io import iter_epochs
    from robustloc.io.tables import UnsortedInput

    def sample(order: str) -> LogSample:
        blocks = ((path, b) for b in iter_epochs(path, anchors,
                                                  chunk_rows=settings.chunk_rows,
                                                  order=order))
        return _sample_blocks(settings, anchors, blocks, k_min=k)

    try:
        return sample("auto")
    except UnsortedInput:  # as the whole pass does: sorted, the same epochs in order
        return sample("sort")


def _with_log_scale(settings: LocateSettings, geo: Geometry, sources: Sequence[Any]
                    ) -> list[Any]:
    from robustloc.io.tables import UnsortedInput

    try:
        return fix_log_scale(settings, geo, sources, "auto")
    except UnsortedInput:
        return fix_log_scale(settings, geo, sources, "sort")


def log_scales_for(settings: LocateSettings, anchors: pd.DataFrame, sources: Sequence[Any],
                   *, sample: np.ndarray | None = None, kind: str | None = None,
                   cap: int | None = None) -> dict[str, Any]:
    """Each method's per-anchor log scale and gross-error share over ``sources`` (files in
    order), as :func:`run_locate` estimates them in its first pass: what the Dask engine
    hands to every partition so that each solves with the whole dataset's.  With
    ``sample`` and ``kind`` (the files' :func:`log_sample_of` stacked in order, computed
    elsewhere), the files are not read again.

    Returns
    -------
    dict
        ``{"log_scale_fixed": {method: scale}, "log_gross_share": {method: share}}``,
        the :class:`LocateSettings` fields (empty mappings when the log had no epoch).
    """
    geo = configure(settings, anchors)
    if sample is not None:
        fixed = (log_scales_from_sample(settings, geo, kind, sample, cap)
                 if kind is not None else geo.locators)
    else:
        fixed = _with_log_scale(settings, geo, sources)
    done = [loc for loc in fixed if loc.log_scale_fixed is not None]
    return {"log_scale_fixed": {loc.method: loc.log_scale_fixed for loc in done},
            "log_gross_share": {loc.method: loc.log_gross_share for loc in done},
            "log_sides": {loc.method: loc.log_sides or () for loc in done}}


def run_locate(
    measurements: Any, anchors: pd.DataFrame, settings: LocateSettings,
    out: str | None = None, *, progress: bool = False,
    hpl_tallies: dict[str, HplTally] | None = None,
) -> tuple[pd.DataFrame | None, dict[str, Any]]:
    """Locate every epoch of a log.

    Parameters
    ----------
    measurements : str, PathLike or DataFrame
        A measurements file (CSV/Parquet; ``-`` standard input) or a frame of
        :func:`robustloc.io.tables.in_memory_source`; rows in any order.
    anchors : DataFrame
        Validated anchors (:func:`robustloc.io.read_anchors`).
    settings : LocateSettings
    out : str, optional
        Positions file (written atomically; ``-`` CSV on standard output); ``None``
        returns the positions as a frame.
    progress : bool
        Show a progress bar on a terminal.
    hpl_tallies : dict, optional
        Filled with each method's :class:`HplTally` (the Dask engine merges the
        partitions' into the dataset's ``hpl_quantiles``).

    Returns
    -------
    (DataFrame or None, dict)
        The positions (``out=None``), and the run summary: ``seconds`` (the whole run,
        the first pass included), ``compile_seconds`` (of it, numba compiling kernels
        that were not cached: :func:`robustloc._jitnotice.compile_watch`),
        ``solve_seconds`` and ``fixes_per_second`` (solving only, compiling left out),
        ``hpl_quantiles`` (:meth:`HplTally.quantiles` per method), ``hpl_histogram``
        (:func:`hpl_counts`), the statuses per method, ...
    """
    from robustloc._jitnotice import compile_watch
    from robustloc.io.atomic import check_not_input, is_stdio
    from robustloc.io.tables import UnsortedInput, _display, check_table_path

    if out is not None:  # before any work: a format the name promises is refused now
        check_table_path(out)
    if out is not None and not isinstance(measurements, pd.DataFrame):
        # never overwrite an input (an anchors frame read from a file names that file)
        check_not_input(out, [src for src in (measurements, anchors.attrs.get("path"))
                              if src])
    geo = configure(settings, anchors)
    t0 = _time.perf_counter()
    # the notice when numba starts compiling, whichever pass needs a kernel first (the
    # log-scale pass compiled them all before the notice was considered: 35 s unannounced)
    with compile_watch("positioning", announce=progress) as jit:
        if any(loc.robust_scale == "log" for loc in geo.locators):
            geo = replace(geo, locators=_with_log_scale(settings, geo, [measurements]))
        # a restartable output (a regular file: the temporary file is discarded; memory)
        # streams and restarts sorted if the rows turn out not to be in epoch order;
        # standard output or a device cannot be taken back, so the order is checked first.
        rewindable = out is None or (not is_stdio(out) and not _is_special(out))
        order = "auto" if rewindable else "check"
        while True:
            tallies: dict[str, HplTally] = {}
            try:
                frame, summary = _run_once(measurements, settings, geo, out, order,
                                           progress, jit, tallies)
                break
            except UnsortedInput:
                if order != "auto":
                    raise
                order = "sort"
    # the whole run (it was the second pass only: "0.04 s" after 35 s of compiling)
    summary["seconds"] = round(_time.perf_counter() - t0, 3)
    summary["compile_seconds"] = round(jit.seconds, 3)
    if hpl_tallies is not None:
        hpl_tallies.update(tallies)
    from robustloc.estimators.ranging import _sane_anchors

    # an anchor far outside the layout (a typo such as x = 1e30) is never used by any fix
    # (estimators.ranging._sane_anchors): say so, by id, instead of dropping it silently
    far = ~_sane_anchors(np.asarray(geo.xyz, dtype=float))
    ids = [str(a) for a in geo.anchors["anchor"].to_numpy()]
    summary = {"measurements": _display(measurements),
               "positions": "<DataFrame>" if out is None else str(out), **summary,
               "anchors_not_used": [a for a, f in zip(ids, far) if f],
               "anchors_suspect": suspect_anchors(geo.locators, ids)}
    xy = np.asarray(geo.xyz, dtype=float)
    # (three or more: two anchors are on a line by definition, and their fixes are
    # insufficient_anchors, not ill_conditioned, as the warning said; the locate review)
    if xy.shape[1] == 2 and (~far).sum() >= 3:
        from robustloc.models.geometry import collinear

        # every 2-D fix is then ambiguous (its mirror fits as well): all ill_conditioned,
        # with no word of why (the review of 2026-12-06: coordinates typed on one line)
        if bool(collinear(xy, (~far)[None])[0]):
            summary["anchors_collinear"] = True
    if any(loc.method == "lege" for loc in geo.locators):
        from robustloc.estimators.linear import LEGE_MIN_DOF

        # LEGE keeps LEGE_MIN_DOF degrees of freedom after its exclusions: with fewer
        # anchors it searches for nothing and its fixes are nls' (the review of
        # 2026-12-06: six anchors, a 80-sigma range in every fourth epoch, lege = nls)
        need = int(np.shape(geo.xyz)[1]) + 1 + LEGE_MIN_DOF
        if int((~far).sum()) < need:
            summary["lege_cannot_search"] = {"anchors": int((~far).sum()), "needs": need}
    return frame, summary


#: An anchor whose noise scale over the log (:meth:`Locator.log_scale`) exceeds this
#: multiple of the median anchor's is reported (:func:`suspect_anchors`): its ranges or
#: RSSI disagree with the fixes far more than the others'.  On the shared real logs the
#: largest anchor's scale is 1.05-1.92x the median (wifi-rtt-rss 1.24-1.53, uwb-dwm1001
#: 1.05-1.27, uwb-labyrinth 1.92, ble-tetam 1.18).  One anchor of eight in a simulated
#: 30 m room with 0.1 m range noise (``tests/test_cli_locate.py``): 1 360x placed 100 m
#: off, 20.8x 2 m off, not reported 0.5 m off.
SUSPECT_SCALE_RATIO = 5.0


def suspect_anchors(locators: Sequence[Any], ids: Sequence[str]) -> dict[str, float]:
    """Anchors whose log noise scale is more than :data:`SUSPECT_SCALE_RATIO` times the
    median anchor's, with that ratio (3 significant digits), largest over the locators
    that estimated a log scale; empty when none did.  The robust fits already give such
    an anchor little weight (the scale is its a-priori sigma); the report says which
    anchor to check: its coordinates, a range bias, an obstruction, or ``calibrate
    --self``."""
    out: dict[str, float] = {}
    for loc in locators:
        for a, r in suspect_of_scale(getattr(loc, "log_scale_fixed", None), ids).items():
            out[a] = max(out.get(a, 0.0), r)
    return out


def suspect_of_scale(scale: Sequence[float] | None, ids: Sequence[str]) -> dict[str, float]:
    """:func:`suspect_anchors` of one per-anchor log scale (``None``, or fewer than three
    anchors: none)."""
    if scale is None or len(scale) != len(ids) or len(scale) < 3:
        return {}
    sc = np.asarray(scale, dtype=float)
    ratio = sc / np.median(sc)
    return {a: float(f"{r:.3g}") for a, r in zip(ids, ratio) if r > SUSPECT_SCALE_RATIO}


#: The summary's keys that :func:`anchor_warnings` words (one anchors file for every
#: partition of a Dask run: the first partition's are the run's).
ANCHOR_WARNING_KEYS = ("anchors_not_used", "anchors_suspect", "anchors_collinear",
                       "lege_cannot_search")
#: Every key :func:`anchor_warnings` words: those above and the run's count of epochs
#: whose LEGE search went beyond its enumeration (summed over a Dask run's partitions).
WARNING_KEYS = ANCHOR_WARNING_KEYS + ("lege_search_truncated",)


def anchor_warnings(summary: dict[str, Any], anchors: object) -> list[str]:
    """The run's warnings about anchors (``anchors``: the anchors file's name), for every
    front end: unused ones (far outside the layout) and suspect ones
    (:func:`suspect_anchors`)."""
    lines = []
    if summary.get("anchors_not_used"):
        lines.append(f"{anchors}: anchor(s) {', '.join(summary['anchors_not_used'])} lie far "
                     "outside the others (more than 20 times their median spread: a typo?) "
                     "and are not used by any fix")
    if summary.get("anchors_collinear"):
        lines.append(f"{anchors}: the anchors lie on one line: a 2-D fix cannot tell the two "
                     "sides of it apart, and every fix is ill_conditioned.  Add an anchor "
                     "off the line (robustloc reliability --anchors ... plans where), or "
                     "check the coordinates")
    lege = summary.get("lege_cannot_search")
    if lege:
        lines.append(f"{anchors}: lege searches for gross errors only with {lege['needs']} "
                     f"or more anchors heard (it keeps 4 degrees of freedom after its "
                     f"exclusions); with {lege['anchors']} its fixes are nls' (use auto, "
                     "snooping or a robust weight to exclude faults)")
    cut = summary.get("lege_search_truncated")
    if cut:
        n_cut = int(cut.get("epochs", 0))
        lines.append(f"lege: {n_cut} epoch{'s' if n_cut != 1 else ''} heard more anchors "
                     f"than lege enumerates ({cut.get('max_sets')} sets of suspects per "
                     "epoch): the larger numbers of gross errors were searched by forward "
                     "selection (one anchor at a time), not over every set "
                     "(docs/choosing-a-method.md)")
    suspect = summary.get("anchors_suspect") or {}
    if suspect:
        each = ", ".join(f"{a} ({r:g}x)" for a, r in suspect.items())
        lines.append(f"{anchors}: the measurements of anchor(s) {each} disagree with the "
                     "fixes far more than the median anchor's (their noise scale over the "
                     "log, against the median's); the fixes give them little weight.  "
                     "Check their coordinates and ids, or estimate their range bias with "
                     "robustloc calibrate --self")
    return lines


#: Resolution of the run summary's ``hpl`` histogram: bins of 1/20 of a decade (12 %
#: wide), so a reported quantile is within 6 % of the exact one.
HPL_BINS_PER_DECADE = 20


def hpl_counts(hpl: NDArray[np.float64], usable: NDArray[np.bool_],
               into: dict[str, int]) -> None:
    """Add the usable fixes' protection levels to a histogram ``into`` (bin index of
    ``log10(hpl)`` as a string -> count; ``"inf"``: no finite bound).  A histogram of
    counts, so the summaries of chunks and of Dask partitions add up exactly."""
    h = np.asarray(hpl, dtype=float)[np.asarray(usable, dtype=bool)]
    n_inf = int(np.sum(~np.isfinite(h) | (h <= 0)))
    if n_inf:
        into["inf"] = into.get("inf", 0) + n_inf
    h = h[np.isfinite(h) & (h > 0)]
    if h.size:
        k, c = np.unique(np.floor(HPL_BINS_PER_DECADE * np.log10(h)).astype(np.int64),
                         return_counts=True)
        for k_, c_ in zip(k.tolist(), c.tolist()):
            into[str(k_)] = into.get(str(k_), 0) + int(c_)


def hpl_quantiles(hist: dict[str, int], qs: tuple[float, ...] = (0.5, 0.95)
                  ) -> dict[str, float]:
    """Quantiles (metres) of the protection levels of a :func:`hpl_counts` histogram,
    at the geometric centre of their bin (inf where they fall among unbounded fixes; NaN
    for an empty histogram), keyed ``"p50"``, ``"p95"``, ..."""
    finite = sorted((int(k), int(v)) for k, v in hist.items() if k != "inf")
    total = sum(v for _, v in finite) + int(hist.get("inf", 0))
    out = {}
    for q in qs:
        key = f"p{round(100 * q):d}"
        if total == 0:
            out[key] = float("nan")
            continue
        need, acc, val = q * total, 0, float("inf")
        for k, v in finite:
            acc += v
            if acc >= need:
                val = float(10.0 ** ((k + 0.5) / HPL_BINS_PER_DECADE))
                break
        out[key] = val
    return out


#: Usable fixes' protection levels kept exactly, per method, by :class:`HplTally` (8 MB
#: each at most); beyond, its quantiles come from its histogram of
#: :data:`HPL_FINE_BINS_PER_DECADE` bins per decade.
HPL_EXACT_CAP = 1_000_000

#: Resolution of :class:`HplTally`'s histogram: bins 0.23 % wide, so its median is within
#: 0.12 % of the exact one (printed as "about"), and the upper edge of the bin that
#: reaches 95 % is a true bound at most 0.23 % above the exact 95th percentile.
HPL_FINE_BINS_PER_DECADE = 1000


class HplTally:
    """The usable fixes' (or track rows') protection levels of one method, for the
    summary's true quantiles (:meth:`quantiles`) in bounded memory.

    The finite values are kept exactly while there are at most :data:`HPL_EXACT_CAP` of
    them; a histogram of :data:`HPL_FINE_BINS_PER_DECADE` bins per decade of ``hpl`` is
    kept always and takes over beyond.  Tallies of chunks, or of Dask partitions, merge
    (:meth:`merge`) into the tally of the whole, exactly as long as the whole is within
    the cap.  A non-finite ``hpl`` (no bound: ``unverified`` fixes) counts as unbounded,
    above every value.
    """

    def __init__(self) -> None:
        self.n_finite = 0  # (the unbounded ones apart)
        self.unbounded = 0
        self._values: list[np.ndarray] | None = []
        self._bins: dict[int, int] = {}

    @property
    def exact(self) -> bool:
        """The values are all kept: :meth:`quantiles` are exact."""
        return self._values is not None

    def add(self, hpl: NDArray[np.float64], usable: NDArray[np.bool_]) -> None:
        """Count the ``usable`` rows' ``hpl``."""
        h = np.asarray(hpl, dtype=float)[np.asarray(usable, dtype=bool)]
        fin = np.isfinite(h)
        self.unbounded += int(np.sum(~fin))
        h = h[fin]
        self.n_finite += int(h.size)
        if not h.size:
            return
        # a bound of 0 or below (never seen) falls in the lowest bin: its upper edge,
        # 1e-300 m, still bounds it
        k, c = np.unique(np.floor(HPL_FINE_BINS_PER_DECADE
                                  * np.log10(np.maximum(h, 1e-300))).astype(np.int64),
                         return_counts=True)
        for k_, c_ in zip(k.tolist(), c.tolist()):
            self._bins[k_] = self._bins.get(k_, 0) + int(c_)
        if self._values is not None:
            self._values.append(h)
            self._check_cap()

    def merge(self, other: HplTally) -> None:
        """Add the counts of ``other`` (another chunk's or partition's tally)."""
        self.n_finite += other.n_finite
        self.unbounded += other.unbounded
        for k, c in other._bins.items():
            self._bins[k] = self._bins.get(k, 0) + c
        if self._values is not None and other._values is not None:
            self._values.extend(other._values)
            self._check_cap()
        else:
            self._values = None

    def _check_cap(self) -> None:
        if self.n_finite > HPL_EXACT_CAP:
            self._values = None  # the histogram takes over
        elif self._values is not None and len(self._values) > 64:
            self._values = [np.concatenate(self._values)]

    def quantiles(self) -> dict[str, Any]:
        """The summary's ``hpl_quantiles`` entry of this method.

        Returns
        -------
        dict
            ``n`` (usable rows), ``unbounded`` (of them, without a finite ``hpl``),
            ``median_m`` (the median, as ``numpy.median``; None when it lies among the
            unbounded rows or there is no row), ``p95_bound_m`` (a value at or below
            which at least 95 % of the rows' ``hpl`` lie: the order statistic of rank
            ``ceil(0.95 N)``, or the upper edge of the histogram's bin that reaches that
            rank; None when that rank is among the unbounded rows) and ``exact`` (False:
            from the histogram, ``median_m`` within 0.12 % of the exact median and
            ``p95_bound_m`` at most 0.23 % above the exact order statistic).
        """
        total = self.n_finite + self.unbounded
        out: dict[str, Any] = {"n": total, "unbounded": self.unbounded, "median_m": None,
                               "p95_bound_m": None, "exact": self.exact}
        if total == 0:
            return out
        r50, r95 = (total + 1) // 2, -(-95 * total // 100)  # ranks: ceil(N/2), ceil(.95 N)
        if self._values is not None:
            # the unbounded rows sort after every value
            v = np.sort(np.concatenate(self._values)) if self._values else np.empty(0)
            lo, hi = (total - 1) // 2, total // 2  # the middle row(s), 0-based
            if hi < v.size:
                out["median_m"] = float((v[lo] + v[hi]) / 2)
            if r95 <= v.size:
                out["p95_bound_m"] = float(v[r95 - 1])
            return out
        acc, edges = 0, {}
        for k in sorted(self._bins):
            acc += self._bins[k]
            for key, r in (("median_m", r50), ("p95_bound_m", r95)):
                if key not in edges and acc >= r:
                    edges[key] = k
        if "median_m" in edges:  # the geometric centre of its bin
            out["median_m"] = float(10.0 ** ((edges["median_m"] + 0.5)
                                             / HPL_FINE_BINS_PER_DECADE))
        if "p95_bound_m" in edges:  # the bin's upper edge (and a hair: log10's rounding)
            out["p95_bound_m"] = float(10.0 ** ((edges["p95_bound_m"] + 1)
                                                / HPL_FINE_BINS_PER_DECADE) * (1 + 1e-12))
        return out


def bound_text(value: float, digits: int = 3) -> str:
    """``value`` rounded *up* to ``digits`` significant digits, as text: a bound that the
    printed number still is (19.345 -> ``19.4``; ``"%.3g"`` printed ``19.3``)."""
    from decimal import ROUND_CEILING, Decimal

    near = f"{value:.{digits}g}"
    if float(near) >= value:  # (as floats: 19.3 bounds the double 19.3 read from the CSV)
        return near
    d = Decimal(float(value))
    q = d.quantize(Decimal(1).scaleb(d.adjusted() - digits + 1), rounding=ROUND_CEILING)
    return f"{q:f}"


def hpl_lines(summary: dict, noun: str = "fixes") -> list[str]:
    """The summary's protection levels, one line per method: the median of the usable
    fixes' (``noun``: track rows') ``hpl`` and a bound at or below which 95 % of them lie
    (the summary's ``hpl_quantiles``, :meth:`HplTally.quantiles`: exact, or "about" the
    median from a histogram of 1/1000 decade; the bound is rounded up, so it holds as
    printed).  A summary without ``hpl_quantiles`` (one written before it) is read from
    its ``hpl_histogram`` of 1/20 decade: the median "about" (within 6 %), the bound the
    upper edge of its bin."""
    lines = []
    quant = summary.get("hpl_quantiles")
    if quant is None:
        quant = {m: _coarse_quantiles(h) for m, h in
                 (summary.get("hpl_histogram") or {}).items()}
    for m, q in quant.items():
        n, unb = int(q.get("n") or 0), int(q.get("unbounded") or 0)
        if not n:
            continue
        med = q.get("median_m")
        med_text = ("unbounded" if med is None
                    else f"{'' if q.get('exact') else 'about '}{med:.3g} m")
        p95 = q.get("p95_bound_m")
        p95_text = ("95 % without a finite bound" if p95 is None
                    else f"95 % at or below {bound_text(p95)} m")
        lines.append(f"  {m:9s} hpl of the {n} usable {noun}: median {med_text}, {p95_text}"
                     + (f" ({unb} unbounded)" if unb else ""))
    for m, k in (summary.get("side_from_log") or {}).items():
        if k:
            lines.append(f"  {m:9s} {k} ambiguous fix{'es' if k != 1 else ''} placed on "
                         "the log's side of their anchors' line (--side-prior log)")
    return lines


def status_text(counts: Mapping[str, int]) -> str:
    """A status count dict as every summary prints it: ``fault_detected: 1, ok: 179``
    (sorted by status; ``track --engine dask`` printed the Python dict)."""
    return ", ".join(f"{k}: {v}" for k, v in sorted(counts.items()))


def input_notes(summary: Mapping[str, Any]) -> list[str]:
    """The summary's lines on the input rows (each indented by two spaces)."""
    lines = []
    if summary.get("sorted_first"):  # (the Dask engine's summary has no such key)
        lines.append("  rows were not in epoch order: sorted by time and tag first")
    if summary.get("duplicates_merged"):
        lines.append(f"  {summary['duplicates_merged']} duplicate rows (same epoch and "
                     "anchor) averaged")
    if summary.get("invalid_measurement_rows"):
        lines.append(f"  invalid_measurement: {summary['invalid_measurement_rows']} rows "
                     "(outside the physical limits of robustloc.io.limits; not used)")
    return lines


def locate_lines(summary: Mapping[str, Any]) -> list[str]:
    """``locate``'s summary lines after the first, the same for every engine (the
    command's and the Dask engine's first lines differ): the notes on the input, each
    method's statuses and protection levels."""
    lines = input_notes(summary)
    lines += [f"  {m:9s} " + status_text(c) for m, c in summary.get("status", {}).items()]
    return lines + hpl_lines(dict(summary)) + mistake_hints(summary)


def mistake_hints(summary: Mapping[str, Any]) -> list[str]:
    """Lines that name the likely mistake when the statuses say the input is not what
    it seems (the new-user review, 2026-12-06: ranges in millimetres gave 51 of 51
    fixes `extrapolated` thousands of metres away with nothing said; RSSI written
    without its sign made every row `invalid_measurement`, exit 0, with no hint)."""
    from robustloc import status as st

    lines = []
    epochs = int(summary.get("epochs") or 0)
    status = summary.get("status", {})
    if epochs and any(2 * int(c.get(st.EXTRAPOLATED, 0)) > epochs for c in status.values()):
        lines.append("  hint: most fixes lie far outside the anchors (extrapolated): are the "
                     "ranges and the anchors' coordinates both in metres (ranges in mm read "
                     "1000x too long)?")
    invalid = all(int(c.get(st.INVALID, 0)) >= epochs for c in status.values())
    if epochs and status and invalid:
        what = ("RSSI is negative dBm, -150 .. +30 (a level written without its sign "
                "reads +79 for -79 dBm)" if summary.get("value") == "rssi" else
                "ranges are metres, -50 .. 1e5")
        lines.append(f"  hint: every epoch is invalid_measurement: {what}")
    return lines


def _coarse_quantiles(hist: dict[str, int]) -> dict[str, Any]:
    """:meth:`HplTally.quantiles` from a :func:`hpl_counts` histogram (1/20 decade): the
    median about (its bin's centre), the 95 % bound the upper edge of its bin."""
    total = sum(int(v) for v in hist.values())
    med = hpl_quantiles(hist, (0.5,))["p50"]
    finite = sorted((int(k), int(v)) for k, v in hist.items() if k != "inf")
    need, acc, bound = -(-95 * total // 100), 0, None
    for k, v in finite:
        acc += v
        if acc >= need:
            bound = float(10.0 ** ((k + 1) / HPL_BINS_PER_DECADE) * (1 + 1e-12))
            break
    return {"n": total, "unbounded": int(hist.get("inf", 0)),
            "median_m": med if np.isfinite(med) else None, "p95_bound_m": bound,
            "exact": False}


def _is_special(path: str) -> bool:
    import os
    import stat

    try:
        return not stat.S_ISREG(os.stat(path).st_mode)
    except OSError:
        return False


def _run_once(
    measurements: Any, settings: LocateSettings, geo: Geometry, out: str | None, order: str,
    progress: bool, jit: CompileWatch, tallies: dict[str, HplTally],
) -> tuple[pd.DataFrame | None, dict[str, Any]]:
    """One pass over the measurements; raises UnsortedInput (output discarded) when the
    streamed rows turn out not to be in epoch order.  ``jit``: the run's
    :class:`~robustloc._jitnotice.CompileWatch` (compiling is left out of the solving
    time); ``tallies`` is filled with each method's :class:`HplTally`."""
    from tqdm import tqdm

    from robustloc.estimators.ranging import SOLVE_CELLS
    from robustloc.integrity.fixes import locate_protected
    from robustloc.io import iter_epochs, positions_frame
    from robustloc.io.tables import PositionsWriter
    from robustloc.models.pathloss import log_distance_arrays
    from robustloc.status import INVALID, USABLE, among

    locators, anchors = geo.locators, geo.anchors
    methods = [loc.method for loc in locators]
    ids = [str(a) for a in anchors["anchor"]]
    counts: dict[str, dict[str, int]] = {m: {} for m in methods}
    hpl_hist: dict[str, dict[str, int]] = {m: {} for m in methods}
    tallies.update({m: HplTally() for m in methods})
    moved: dict[str, int] = {m: 0 for m in methods}
    n_epochs = n_dup = n_invalid = forward = 0
    resorted = order == "sort"
    A = n = None
    kind = None
    t0 = _time.perf_counter()
    solve_s = 0.0
    bar = tqdm(unit=" epochs", disable=not progress or not sys.stderr.isatty(),
               file=sys.stderr)
    try:
        with PositionsWriter(out) as writer:
            for block in iter_epochs(measurements, anchors, chunk_rows=settings.chunk_rows,
                                     order=order):
                if kind is None:  # the first block
                    kind = block.value
                    if kind == "rssi":
                        A, n = log_distance_arrays(anchors, settings.model)
                values = prepared_values(settings, anchors, block, measurements)
                bad = block.all_invalid
                frames = []
                # a site of many anchors: the fits' (epochs, anchors) arrays bounded
                # (robustloc.estimators.ranging.SOLVE_CELLS: each fix is its epoch's own,
                # so the rows are those of one solve)
                step = max(1, SOLVE_CELLS // max(values.shape[1], 1))
                for loc in locators:
                    parts = []
                    for s0 in range(0, max(block.n_epochs, 1), step):
                        sl = slice(s0, s0 + step)
                        ts, jit0 = _time.perf_counter(), jit.seconds
                        sol = locate_protected(
                            loc, geo.xyz, values[sl], kind, A=A, n=n,
                            height_offset=geo.height, alpha0=settings.alpha0,
                            beta0=settings.beta0, k_noise=settings.k_noise,
                            alert_limit=settings.alert_limit)
                        solve_s += _time.perf_counter() - ts - (jit.seconds - jit0)
                        side = sol.extra.get("side_from_log")
                        if side is not None:
                            moved[loc.method] += int(np.sum(side & ~bad[sl]))
                        cut = sol.extra.get("search_truncated")
                        if cut is not None:  # lege's orders beyond its enumeration
                            forward += int(np.sum(np.asarray(cut, dtype=bool) & ~bad[sl]))
                        parts.append(positions_frame(sol, block.time[sl], block.tag[sl], ids,
                                                     loc.method))
                    fr = parts[0] if len(parts) == 1 else pd.concat(parts, ignore_index=True)
                    if bad.any():  # every row of the epoch was outside the physical limits
                        fr.loc[bad, "status"] = INVALID
                        fr.loc[bad, [c for c in ("x", "y", "z", "sigma0") if c in fr]] = np.nan
                        fr.loc[bad, "n_used"] = 0
                    frames.append(fr)
                    st, c = np.unique(fr["status"].to_numpy(dtype=str), return_counts=True)
                    for s_, c_ in zip(st, c):
                        counts[loc.method][s_] = counts[loc.method].get(s_, 0) + int(c_)
                    if "hpl" in fr:
                        h = fr["hpl"].to_numpy(float)
                        use = among(fr["status"].to_numpy(dtype=object), USABLE)
                        hpl_counts(h, use, hpl_hist[loc.method])
                        tallies[loc.method].add(h, use)
                writer.write(_epoch_major(frames))
                n_epochs += block.n_epochs
                n_dup += block.n_duplicates
                n_invalid += int(block.n_invalid.sum())
                resorted |= block.resorted
                bar.update(block.n_epochs)
        frame = writer.frame() if out is None else None
    finally:
        bar.close()
    wall = _time.perf_counter() - t0
    more: dict[str, Any] = {}
    if forward:
        from robustloc.estimators.linear import LEGE_MAX_SETS

        more["lege_search_truncated"] = {"epochs": forward, "max_sets": LEGE_MAX_SETS}
    return frame, {
        "value": kind, "epochs": n_epochs, "methods": methods, "status": counts,
        "hpl_histogram": hpl_hist,
        "hpl_quantiles": {m: t.quantiles() for m, t in tallies.items()},
        "side_from_log": moved,
        "log_sides": {loc.method: [[list(i), s] for i, s in loc.log_sides or ()]
                      for loc in locators},
        "duplicates_merged": n_dup, "invalid_measurement_rows": n_invalid,
        "sorted_first": resorted, "seconds": round(wall, 3),
        "solve_seconds": round(max(solve_s, 0.0), 3),
        "fixes_per_second": round(n_epochs * len(methods) / max(solve_s, 1e-9), 1),
        **more,
    }
