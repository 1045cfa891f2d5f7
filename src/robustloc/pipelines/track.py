"""The ``track`` workflow: a robust tight filter per tag, one track row per input epoch.

:func:`run_track` streams a measurements log (a file or an in-memory frame; rows in any
order) through a :class:`~robustloc.tracking.Tracker` and, with ``smooth`` or
``fixed_lag``, the Rauch-Tung-Striebel smoother over the forward pass.
:class:`TrackSettings` holds every setting, checked with the command line's wording.
``robustloc track``, :func:`robustloc.track` and the Dask engine run this code.
"""

from __future__ import annotations

import argparse
import sys
import time as _time
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import pandas as pd

from robustloc.errors import InputError
from robustloc.options import (
    check_settings,
    float_in,
    option,
    positive_float,
    positive_int,
    positive_process_noise,
    process_noise,
    sigma_value,
    tag_height_m,
)
from robustloc.robust.weights import weight_synonyms

if TYPE_CHECKING:
    from robustloc.pipelines.locate import HplTally

#: ``weight`` values (robust weight functions of :mod:`robustloc.robust.weights`).
WEIGHTS = ("ls", "huber", "hampel", "igg", "igg3", "asymmetric-igg")
#: Other names of ``WEIGHTS`` (``none``, ``asym``: as ``filter``/``fuse`` and ``locate``
#: spell them).
WEIGHT_SYNONYMS = weight_synonyms(WEIGHTS)
_PROBABILITY = float_in(1e-15, 0.5)  # as --alpha0 of locate and spp


@dataclass(frozen=True)
class TrackSettings:
    """Every setting of ``track`` (the ``robustloc track`` options of the same name).

    The filter's settings are those of :class:`robustloc.tracking.tracker.TrackerSettings`
    (same names and defaults; ``kernel`` is its ``engine``, the compiled kernels or the
    NumPy reference); ``smooth``, ``fixed_lag`` (RTS smoothing over the whole log, or over
    the next ``fixed_lag`` epochs of each tag) and ``chunk_rows`` (rows read per chunk)
    are the workflow's.  ``link_offsets="auto"`` (the default) lets the log choose
    (:func:`robustloc.tracking.select.choose_link_offsets`; :func:`run_track` resolves it
    before tracking); :class:`~robustloc.tracking.Tracker` itself, a filter fed epoch by
    epoch with no log to look at, has them off unless told.
    """

    model: str = option("cv", choices=("cv", "ca", "static"), flag="--model/--motion")
    filter: str = option("ekf", choices=("ekf", "ukf"))
    q: float = option(1.0, check=positive_process_noise)
    weight: str | None = option(None, choices=WEIGHTS, synonyms=WEIGHT_SYNONYMS,
                                flag="--weight/--robust")
    domain: str = option("range", choices=("range", "rssi"))
    sigma: float | None = option(None, check=sigma_value)
    smooth: bool = False
    fixed_lag: int | None = option(None, check=positive_int)
    kernel: str = option("compiled", choices=("compiled", "numpy"))
    noise_scale_min: float = option(1.0, check=positive_float)
    noise_scale_max: float = option(4.0, check=positive_float)
    cusum_h: float | None = option(None, check=positive_float)
    alpha0: float = option(0.001, check=_PROBABILITY)
    beta0: float = option(0.10, check=_PROBABILITY)
    integrity_risk: float = option(0.001, check=_PROBABILITY)
    tag_height: float | None = option(None, check=tag_height_m)
    range_offset: bool = False
    range_offset_sd: float = option(0.5, check=positive_float)
    range_offset_q: float = option(1e-4, check=process_noise)
    link_offsets: bool | str = option("auto", choices=(False, True, "auto"),
                                      synonyms={"on": True, "off": False})
    link_offset_sd: float | None = option(None, check=positive_float)
    link_offset_q: float = option(0.0, check=process_noise)
    chunk_rows: int = option(500_000, check=positive_int)

    def __post_init__(self) -> None:
        check_settings(self)
        # (``auto``, the default, with the common offset: the links' are left out)
        if self.range_offset and self.link_offsets is True:
            raise InputError("--range-offset and --link-offsets exclude each other: the "
                             "links' offsets include the common one (their mean); choose "
                             "one")

    @property
    def smoothing(self) -> bool:
        """RTS smoothing on (``smooth`` or ``fixed_lag``)."""
        return self.smooth or self.fixed_lag is not None

    def method_name(self, trk: Any) -> str:
        """The ``method`` column of ``trk``'s rows with these settings (the summary's
        ``method``, as ``evaluate`` reads it): ``track-cv-ekf``, ``track-cv-ekf-rts``,
        ``track-cv-ekf-lag5``, ... (:func:`smoother_suffix`)."""
        return trk.method + (smoother_suffix(self.fixed_lag) if self.smoothing else "")

    @classmethod
    def from_namespace(cls, args: argparse.Namespace) -> TrackSettings:
        """The settings of a parsed ``robustloc track`` command line."""
        from dataclasses import fields

        return cls(**{f.name: getattr(args, f.name) for f in fields(cls)})

    def tracker(self, anchors: pd.DataFrame) -> Any:
        """A fresh :class:`~robustloc.tracking.Tracker` with these settings (recording its
        history when smoothing)."""
        from robustloc.tracking import Tracker

        if self.link_offsets == "auto":
            raise ValueError("link_offsets='auto' is resolved on the log first "
                             "(resolve_link_offsets)")
        try:
            return Tracker(anchors, record=self.smoothing, **self.tracker_options())
        except (ValueError, TypeError) as exc:  # (the tracker's own checks)
            raise InputError(str(exc)) from None

    def tracker_options(self) -> dict[str, Any]:
        """The :class:`~robustloc.tracking.Tracker` keywords of these settings (``kernel``
        as ``engine``; the workflow's own settings left out)."""
        opts = asdict(self)
        for k in ("smooth", "fixed_lag", "chunk_rows"):
            opts.pop(k)
        opts["engine"] = opts.pop("kernel")
        return opts


def run_track(
    measurements: Any, anchors: pd.DataFrame, settings: TrackSettings,
    out: str | None = None, *, progress: bool = False, hpl_tally: HplTally | None = None,
) -> tuple[pd.DataFrame | None, dict[str, Any]]:
    """Track every tag of a log.

    Parameters
    ----------
    measurements : str, PathLike or DataFrame
        A measurements file or a frame of :func:`robustloc.io.tables.in_memory_source`;
        rows in any order.
    anchors : DataFrame
        Validated anchors (:func:`robustloc.io.read_anchors`).
    settings : TrackSettings
    out : str, optional
        Track file (CSV/Parquet, written atomically); ``None`` returns the frame.
    progress : bool
        Show a progress bar on a terminal.
    hpl_tally : HplTally, optional
        A :class:`robustloc.pipelines.locate.HplTally` the usable rows' ``hpl`` are added
        to (the Dask engine merges the partitions' into the dataset's ``hpl_quantiles``).

    Returns
    -------
    (DataFrame or None, dict)
        The track rows (``out=None``), and the run summary: ``method`` (the ``method``
        column's value, smoother suffix included), ``seconds`` (the whole run), of it
        ``compile_seconds`` (numba compiling kernels that were not cached:
        :func:`robustloc._jitnotice.compile_watch`), ``epochs_per_second`` (over the run
        without the compiling), ``hpl_quantiles``
        (:meth:`robustloc.pipelines.locate.HplTally.quantiles`), ``hpl_histogram``,
        the statuses, ...
    """
    from robustloc._jitnotice import compile_watch
    from robustloc.io.atomic import check_not_input
    from robustloc.io.tables import UnsortedInput, _display, check_table_path
    from robustloc.pipelines.locate import HplTally

    if settings.tag_height is not None and "z" not in anchors.columns:
        raise InputError("--tag-height needs a z column in the anchors file",
                         anchors.attrs.get("path"), 1)
    if out is not None:  # before any work: a format the name promises is refused now
        check_table_path(out)
    if out is not None and not isinstance(measurements, pd.DataFrame):
        # never overwrite an input (an anchors frame read from a file names that file)
        check_not_input(out, [src for src in (measurements, anchors.attrs.get("path"))
                              if src])
    t0 = _time.perf_counter()
    # the notice when numba starts compiling a kernel the cache lacks (any model, filter
    # or option: `--model ca` compiled 25 s unannounced), and the time it takes
    with compile_watch("tracker and filter", announce=progress) as jit:
        # (``auto`` is chosen inside each pass, on the first epochs of the very order it
        # tracks: a log whose disorder shows only after them is sorted, and chosen on
        # again -- the rows of several tags' logs one after another and of the same rows
        # sorted were tracked with two models: the default's review)
        hpl = HplTally()
        try:
            (trk, frame, n_epochs, counts, hist, resorted, tally, settings,
             choice) = _one_pass(measurements, anchors, settings, out, "auto", progress, hpl)
        except UnsortedInput:
            hpl = HplTally()
            (trk, frame, n_epochs, counts, hist, resorted, tally, settings,
             choice) = _one_pass(measurements, anchors, settings, out, "sort", progress, hpl)
    if hpl_tally is not None:
        hpl_tally.merge(hpl)
    wall = _time.perf_counter() - t0
    method = settings.method_name(trk)  # the method column's ("-rts" was left out)
    summary = {"measurements": _display(measurements),
               "track": "<DataFrame>" if out is None else str(out), "epochs": n_epochs,
               "tags": len(trk.tags), "method": method, "status": counts,
               "invalid_measurement_rows": tally.get("invalid_measurement_rows", 0),
               "duplicates_merged": tally.get("duplicates_merged", 0),
               "hpl_histogram": {method: hist},
               "hpl_quantiles": {method: hpl.quantiles()},
               "smoother": (("fixed-lag" if settings.fixed_lag else "rts")
                            if settings.smoothing else None),
               "sorted_first": resorted, "seconds": round(wall, 3),
               "compile_seconds": round(jit.seconds, 3),
               # the rate of the tracking: "0 epochs/s" after 238 s of compiling
               "epochs_per_second": round(n_epochs / max(wall - jit.seconds, 1e-9), 1)}
    from robustloc.estimators.ranging import _sane_anchors

    # as locate: an anchor far outside the layout (a typo such as y = 1e300) is named
    dims = [c for c in ("x", "y", "z") if c in anchors.columns]
    far = ~_sane_anchors(anchors[dims].to_numpy(dtype=float))
    summary["anchors_not_used"] = [str(a) for a, f in zip(anchors["anchor"], far) if f]
    if settings.range_offset:
        summary["range_offset_m"] = range_offsets(trk)
    if choice is not None:
        summary["link_offsets_auto"] = choice.as_dict()
    if settings.link_offsets:
        summary[link_offset_key(trk)] = link_offsets(trk)
    return frame, summary


def resolve_link_offsets(blocks: Any, anchors: pd.DataFrame, settings: TrackSettings,
                         source: Any = None, progress: bool = False,
                         ) -> tuple[TrackSettings, Any, list]:
    """``link_offsets="auto"``: the settings with the choice that the first epochs of
    ``blocks`` make (:func:`robustloc.tracking.select.choose_link_offsets`, at most
    :data:`~robustloc.tracking.select.AUTO_SAMPLE_EPOCHS`; the blocks as a pass reads
    them), that choice, and the blocks read for it (to be tracked first: the log is read
    once).  Other settings: unchanged, ``None`` and no blocks read.  ``progress``: a bar
    of the trial's epochs on a terminal.
    """
    from dataclasses import replace

    from robustloc.tracking.select import AUTO_SAMPLE_EPOCHS, choose_link_offsets

    if settings.link_offsets != "auto":
        return settings, None, []
    head, n = [], 0
    for block in blocks:
        head.append(block)
        n += block.n_epochs
        if n >= AUTO_SAMPLE_EPOCHS:
            break
    if not n:
        return replace(settings, link_offsets=False), None, head
    opts = settings.tracker_options()
    opts.pop("link_offsets")
    for block in head:  # as the tracking pass refuses them (track_blocks)
        _refuse_block_options(block, settings, source)
    from tqdm import tqdm

    from robustloc.io.tables import Epochs

    sample = Epochs.concat([b for b in head if b.n_epochs])
    with tqdm(total=2 * min(sample.n_epochs, AUTO_SAMPLE_EPOCHS), unit=" epochs",
              desc="--link-offsets auto (both ways)", file=sys.stderr,
              disable=not progress or not sys.stderr.isatty()) as bar:
        try:
            choice = choose_link_offsets(anchors, sample, progress=bar.update, **opts)
        except (ValueError, TypeError) as exc:  # (the tracker's own checks)
            raise InputError(str(exc)) from None
    return replace(settings, link_offsets=choice.use), choice, head


def link_offset_key(trk: Any) -> str:
    """The summary's key of :func:`link_offsets`: ``link_offset_db`` for RSSI,
    ``link_offset_m`` for ranges."""
    return "link_offset_db" if trk._kind == "rssi" else "link_offset_m"


def link_offsets(trk: Any) -> dict[str, dict[str, dict[str, float | None]]]:
    """Each started tag's links' offsets at the end of the log (``link_offsets``):
    ``{tag: {anchor: {"estimate": b_i, "sd": sqrt(var b_i)}}}`` in the measurement's unit
    (dB or m; None where not finite)."""
    out: dict[str, dict[str, dict[str, float | None]]] = {}
    for row in trk.link_offsets().itertuples(index=False):
        out.setdefault(str(row.tag), {})[str(row.anchor)] = {"estimate": _num(row.offset),
                                                             "sd": _num(row.sd)}
    return out


def _num(v: float) -> float | None:
    return round(float(v), 4) if np.isfinite(v) else None


def range_offsets(trk: Any) -> dict[str, dict[str, float | None]]:
    """Each started tag's range offset at the end of the log: ``{tag: {"estimate": b,
    "sd": sqrt(var b)}}`` (m; None where not finite)."""
    return {str(tag): {"estimate": _num(trk._x[k, -1]),
                       "sd": _num(np.sqrt(max(trk._P[k, -1, -1], 0.0)))}
            for tag, k in trk._slot.items() if trk._init[k]}


def offset_lines(summary: dict, most: int = 10) -> list[str]:
    """The text summary's lines of :func:`range_offsets` (``summary["range_offset_m"]``)
    and :func:`link_offsets`: the first ``most`` tags, then how many more (``--json``
    lists every one)."""
    offsets = summary.get("range_offset_m") or {}
    auto = summary.get("link_offsets_auto")
    lines = [] if not auto else [
        f"  --link-offsets auto: {'on' if auto['used'] else 'off'}, {auto['reason']}"
        + (f" (first {auto['epochs']} epochs)" if auto.get("epochs") else "")]
    lines += [f"  range offset of {tag}: {v['estimate']:+.3f} m (sd "
             + ("n/a" if v["sd"] is None else f"{v['sd']:.3f}") + ")"
             for tag, v in list(offsets.items())[:most] if v["estimate"] is not None]
    if len(offsets) > most:
        lines.append(f"  ... and {len(offsets) - most} more tags (--json lists every one)")
    for key, unit in (("link_offset_m", "m"), ("link_offset_db", "dB")):
        links = summary.get(key) or {}
        for tag, per in list(links.items())[:most]:
            lines.append(f"  link offsets of {tag} ({unit}): " + ", ".join(
                f"{a} {v['estimate']:+.2f}" for a, v in per.items()
                if v["estimate"] is not None))
        if len(links) > most:
            lines.append(f"  ... and {len(links) - most} more tags (--json lists every one)")
    return lines


def track_lines(summary: dict[str, Any]) -> list[str]:
    """``track``'s summary lines after the first, the same for every engine (the
    command's and the Dask engine's first lines differ): the notes on the input, the
    statuses, the protection levels and the tags' offsets."""
    from robustloc.pipelines.locate import hpl_lines, input_notes, status_text

    lines = input_notes(summary)
    lines.append("  " + status_text(summary.get("status", {})))
    return lines + hpl_lines(summary, "rows") + offset_lines(summary)


def _one_pass(measurements: Any, anchors: pd.DataFrame, settings: TrackSettings,
              out: str | None, order: str, progress: bool,
              hpl_tally: HplTally | None = None) -> tuple:
    """Every epoch through a fresh tracker; a file is written atomically (nothing at
    ``out`` after an error or an interrupt); raises UnsortedInput when rows turn out not
    to be in time order (the caller sorts and starts again).  ``hpl_tally``: as
    :func:`track_blocks`'."""
    import contextlib
    import itertools
    from dataclasses import replace

    from tqdm import tqdm

    from robustloc.io import iter_epochs, write_table
    from robustloc.io.atomic import atomic_output
    from robustloc.io.tables import is_parquet

    # the tracker's own checks before any reading, as without ``auto``
    trk = (replace(settings, link_offsets=False) if settings.link_offsets == "auto"
           else settings).tracker(anchors)
    hist: dict[str, int] = {}
    tally: dict[str, int] = {}
    resorted = [order == "sort"]
    choice = None
    bar = tqdm(unit=" epochs", disable=not progress or not sys.stderr.isatty(),
               file=sys.stderr)
    opened = atomic_output(out) if out is not None else contextlib.nullcontext((None, None))
    try:
        with opened as (target, _stream):
            stream = target is not None and not settings.smoothing
            writer = TrackWriter(target, parquet=is_parquet(out)) if stream else None
            try:
                blocks = _noting_sort(iter_epochs(
                    measurements, anchors, chunk_rows=settings.chunk_rows, order=order),
                    resorted)
                settings, choice, head = resolve_link_offsets(blocks, anchors, settings,
                                                              measurements, progress)
                blocks = itertools.chain(head, blocks)
                if settings.link_offsets:
                    trk = settings.tracker(anchors)
                table, n, status_counts = track_blocks(
                    trk, blocks, settings, None if writer is None else writer.write,
                    bar.update, hist, source=measurements, tally=tally,
                    hpl_tally=hpl_tally)
            finally:
                if writer is not None:
                    writer.close()
            if table is not None and out is not None:
                if target is None:
                    write_table(table, out)
                else:
                    write_table(table, target, parquet=is_parquet(out))
    finally:
        bar.close()
    return (trk, table if out is None else None, n, status_counts, hist, resorted[0], tally,
            settings, choice)


def _noting_sort(blocks: Any, resorted: list[bool]) -> Any:
    """``blocks``, setting ``resorted[0]`` when one comes from a log that was sorted."""
    for block in blocks:
        resorted[0] |= block.resorted
        yield block


def track_blocks(trk: Any, blocks: Any, settings: TrackSettings,
                 write: Callable[[pd.DataFrame], None] | None = None,
                 progress: Callable[[int], Any] | None = None,
                 hpl_histogram: dict[str, int] | None = None,
                 source: Any = None,
                 tally: dict[str, int] | None = None,
                 hpl_tally: HplTally | None = None,
                 ) -> tuple[pd.DataFrame | None, int, dict[str, int]]:
    """The single core of ``track``: every epoch block through ``trk`` in order.

    Parameters
    ----------
    trk : Tracker
        From :meth:`TrackSettings.tracker`.
    blocks : iterable of Epochs
        The log's epochs in time order (a file streamed by ``iter_epochs``, or one tag
        partition under ``--engine dask``).
    settings : TrackSettings
        ``smooth``, ``fixed_lag``.
    write : callable, optional
        Without smoothing, each block's rows are handed to ``write`` (streamed, bounded
        memory) and no table is returned; else they are kept and returned.
    progress : callable, optional
        Called with each block's epoch count.
    hpl_histogram : dict, optional
        Filled with the usable rows' ``hpl``
        (:func:`robustloc.pipelines.locate.hpl_counts`).
    source : path or DataFrame, optional
        The log, to name in errors: ``--domain rssi`` on a range log is refused
        (:func:`robustloc.pipelines.locate.refuse_rssi_options`), not ignored.
    tally : dict, optional
        Its ``invalid_measurement_rows`` is increased by the rows outside the physical
        limits (robustloc.io.limits), which no update uses, and ``duplicates_merged`` by
        the rows of an epoch's anchor heard twice (averaged, as ``locate`` does).
    hpl_tally : HplTally, optional
        Fills a :class:`robustloc.pipelines.locate.HplTally` with the usable rows'
        ``hpl`` (the summary's ``hpl_quantiles``).

    The work runs in a :func:`robustloc._jitnotice.compile_watch` (within the caller's
    when it opened one): the notice when numba starts compiling a kernel the cache lacks.

    Returns
    -------
    (table or None, epochs, status counts)
    """
    from robustloc._jitnotice import compile_watch

    with compile_watch("tracker and filter"):
        return _track_blocks(trk, blocks, settings, write, progress, hpl_histogram, source,
                             tally, hpl_tally)


def _track_blocks(trk: Any, blocks: Any, settings: TrackSettings,
                  write: Callable[[pd.DataFrame], None] | None,
                  progress: Callable[[int], Any] | None,
                  hpl_histogram: dict[str, int] | None, source: Any,
                  tally: dict[str, int] | None, hpl_tally: HplTally | None,
                  ) -> tuple[pd.DataFrame | None, int, dict[str, int]]:
    """:func:`track_blocks`, inside its compile watch."""
    from robustloc.pipelines.locate import hpl_counts
    from robustloc.status import USABLE, among

    hist: dict[str, int] = {} if hpl_histogram is None else hpl_histogram

    def count_hpl(rows: pd.DataFrame) -> None:
        if "hpl" not in rows:  # (an empty frame)
            return
        h = rows["hpl"].to_numpy(float)
        use = among(rows["status"].to_numpy(dtype=object), USABLE)
        hpl_counts(h, use, hist)
        if hpl_tally is not None:
            hpl_tally.add(h, use)

    smooth = settings.smoothing
    stream = write is not None and not smooth
    if smooth:
        # the smoother indexes the recorded steps by their row in one step's output, so
        # the whole log goes through the tracker in one step (the smoother holds every
        # epoch anyway); block by block, rows of later blocks were smoothed with the
        # states of earlier ones (the result depended on --chunk-rows)
        joined = list(blocks)
        from robustloc.io.tables import Epochs

        blocks = [Epochs.concat(joined)] if joined else []
    frames: list[pd.DataFrame] = []
    n = 0
    status_counts: dict[str, int] = {}
    for block in blocks:
        _refuse_block_options(block, settings, source)
        rows = trk.step(block)
        if tally is not None:
            tally["invalid_measurement_rows"] = (tally.get("invalid_measurement_rows", 0)
                                                 + int(np.sum(block.n_invalid)))
            tally["duplicates_merged"] = (tally.get("duplicates_merged", 0)
                                          + int(block.n_duplicates))
        for k, v in rows["status"].value_counts().items():
            status_counts[str(k)] = status_counts.get(str(k), 0) + int(v)
        if not smooth:
            count_hpl(rows)
        if stream and write is not None:
            write(rows)
        else:
            frames.append(rows)
        n += block.n_epochs
        if progress is not None:
            progress(block.n_epochs)
    if stream:
        return None, n, status_counts
    table = pd.concat(frames, ignore_index=True) if frames else pd.DataFrame()
    if smooth and len(table):
        table = apply_smoother(trk, table, settings.fixed_lag)
        status_counts = {str(k): int(v) for k, v in table["status"].value_counts().items()}
        count_hpl(table)
    return table, n, status_counts


def _refuse_block_options(block: Any, settings: TrackSettings, source: Any) -> None:
    """Options the log's kind refuses (:func:`track_blocks`): ``--domain rssi`` and
    ``--range-offset`` on RSSI-less / range-less logs."""
    from robustloc.pipelines.locate import refuse_rssi_options

    refuse_rssi_options(block.value, {"--domain rssi": settings.domain == "rssi"}, source)
    if settings.range_offset and block.value != "range":
        from robustloc.io.tables import _display

        raise InputError("--range-offset applies to ranges, but this log holds RSSI (an "
                         "rssi column): leave it out (a device's RSSI offset is the "
                         "path-loss model's A: calibrate it)",
                         None if source is None else _display(source),
                         None if source is None else 1)


class TrackWriter:
    """Append track rows chunk by chunk to a CSV or Parquet file (columns of the first)."""

    def __init__(self, path: Path, parquet: bool | None = None) -> None:
        from robustloc.io.tables import is_parquet

        self.path = Path(path)
        self.parquet = is_parquet(self.path) if parquet is None else parquet
        self._columns: list[str] | None = None
        self._pq: Any = None
        self._started = False

    def write(self, frame: pd.DataFrame) -> None:
        if self._columns is None:
            self._columns = list(frame.columns)
        out = frame[self._columns].reset_index(drop=True)
        out.attrs = {}
        if self.parquet:
            import pyarrow as pa
            import pyarrow.parquet as pq

            table = pa.Table.from_pandas(out, preserve_index=False)
            if self._pq is None:
                self._pq = pq.ParquetWriter(self.path, table.schema)
            self._pq.write_table(table.cast(self._pq.schema))
        else:
            out.to_csv(self.path, mode="a" if self._started else "w",
                       header=not self._started, index=False)
            self._started = True

    def close(self) -> None:
        if self._pq is not None:
            self._pq.close()
        elif self._columns is None:  # nothing written: an empty file with the header
            self.path.write_text("")


def smoother_suffix(lag: int | None) -> str:
    """What the smoother appends to the ``method`` column: ``-rts`` (over the whole log),
    ``-lagN`` (fixed lag ``N``)."""
    return "-rts" if lag is None else f"-lag{lag}"


def apply_smoother(trk: Any, table: pd.DataFrame, lag: int | None) -> pd.DataFrame:
    """Replace the filtered states of ``table`` (rows in step order) by smoothed ones."""
    xs, Ps = trk.smoothed(len(table), lag)
    have = np.all(np.isfinite(xs), axis=1)
    t = table.copy()
    t.loc[have, "x"], t.loc[have, "y"] = xs[have, 0], xs[have, 1]
    t.loc[have, "var_x"], t.loc[have, "var_y"] = Ps[have, 0, 0], Ps[have, 1, 1]
    t.loc[have, "cov_xy"] = Ps[have, 0, 1]
    n = trk.n_motion  # kinematic states
    if n >= 4:
        t.loc[have, "vx"], t.loc[have, "vy"] = xs[have, 2], xs[have, 3]
        t.loc[have, "var_vx"], t.loc[have, "var_vy"] = Ps[have, 2, 2], Ps[have, 3, 3]
    if n >= 6:
        t.loc[have, "ax"], t.loc[have, "ay"] = xs[have, 4], xs[have, 5]
    # the tag's range offset (--range-offset) follows them; link offsets (--link-offsets,
    # reported in the summary, not per row) were written here as a range offset
    if trk.settings.range_offset and xs.shape[1] > n:
        t.loc[have, "range_offset"] = xs[have, n]
        t.loc[have, "var_range_offset"] = Ps[have, n, n]
    # hpl: the forward row's bound plus the distance the smoother moved the position.  The
    # forward bound covers x_f (its tests saw the epoch); |x_s - x| <= |x_s - x_f| + |x_f - x|
    # carries it to x_s whatever the errors' correlation in time.  The smoothed covariance
    # alone does not: it assumes white noise, and a receiver's standing offset or slow
    # fading does not average out (ble-tetam, the forward slope term plus k sigma of the
    # smoothed covariance: 3.2 % of the rows beyond it, 8.3 % on one walk; forward 0.3 %)
    moved = np.hypot(xs[have, 0] - table.loc[have, "x"].to_numpy(float),
                     xs[have, 1] - table.loc[have, "y"].to_numpy(float))
    t.loc[have, "hpl"] = table.loc[have, "hpl"].to_numpy(float) + moved
    t["method"] = table["method"] + smoother_suffix(lag)
    return t
