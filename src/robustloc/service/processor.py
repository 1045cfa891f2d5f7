"""What the service does with a block of ready epochs: locate them, or track them.

Both modes implement one small interface, :class:`Processor`: ``process(epochs)`` returns
one output row per epoch (the positions format of ``robustloc locate``, or the track format
of ``robustloc track``), and ``state_dict``/``load_state_dict`` carry per-tag state across
a restart.

:class:`LocateProcessor` prepares the anchors exactly as ``robustloc locate`` does (the same
:class:`~robustloc.estimators.ranging.Locator`, range calibration, path-loss arrays and
per-anchor sigma) and builds rows with :func:`robustloc.io.tables.positions_frame`, so a
log replayed through the service gives the batch command's positions.  It appends the
horizontal covariance (``cov_xx, cov_xy, cov_yy``, m^2) for the map's uncertainty ellipse.

:class:`TrackProcessor` wraps ``robustloc.tracking.Tracker`` (imported lazily: the tracker is
an optional part of the library).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import replace
from typing import Any, Protocol

import numpy as np
import pandas as pd

from robustloc.io.tables import Epochs, anchor_sigma, positions_frame


def solvable_values(anchors: pd.DataFrame, model: str | None = None) -> tuple[str, ...]:
    """The measurement values these anchors can be located from: ranges always, RSSI only
    when they carry path-loss parameters (:func:`robustloc.models.pathloss.
    log_distance_arrays` accepts them)."""
    from robustloc.errors import InputError
    from robustloc.models.pathloss import log_distance_arrays

    try:
        log_distance_arrays(anchors, model)
    except (InputError, ValueError, KeyError):
        return ("range",)
    return ("rssi", "range")


class Processor(Protocol):
    """A stateful consumer of ready epochs.

    ``name`` labels the output (the ``method`` column for locate); ``values`` the
    measurement values it can process (:func:`solvable_values`).
    """

    name: str
    values: tuple[str, ...]

    def process(self, epochs: Epochs) -> pd.DataFrame:
        """One output row per epoch of ``epochs`` (epochs come in time order per tag)."""
        ...

    def state_dict(self) -> dict:
        """Per-tag state to persist (empty for a stateless processor)."""
        ...

    def load_state_dict(self, state: dict) -> None:
        """Restore the state saved by :meth:`state_dict`."""
        ...

    def forget(self, tags: list[str]) -> None:
        """Drop the state of ``tags`` (silent for long): heard again, each starts afresh."""
        ...

    def status(self) -> dict:
        """Fields the service's ``/api/status`` adds (empty for the per-epoch fixes)."""
        ...


class LocateProcessor:
    """Per-epoch fixes, each tested with its protection level, as ``robustloc locate``.

    The fixes come from :func:`robustloc.integrity.fixes.locate_protected` (the one entry
    point of every front end) with a :class:`~robustloc.estimators.ranging.Locator`
    prepared as ``robustloc locate`` prepares it.

    Parameters
    ----------
    anchors : DataFrame
        From :func:`robustloc.io.read_anchors`.
    method : str
        ``auto`` (default, as ``robustloc locate``) or one of
        :data:`robustloc.estimators.ranging.METHODS`.
    dim : {2, 3}
    solver, domain, reference, min_scale, alpha0, beta0, k_noise, alert_limit, weight_params
        As the ``robustloc locate`` options of the same names.
    robust_scale : {"mad", "log", "apriori"}
        Noise scale of the robust methods and of every fix's test.  ``mad`` (default here):
        per epoch from its own residuals.  ``log`` (``robustloc locate``'s default, a first
        pass over the whole log) needs ``log_scale``: a live service has no whole log, so
        the scale comes from a recorded one (:meth:`log_statistics_from`).
    log_scale : sequence of float, optional
        Per-anchor noise scale for ``robust_scale="log"``.
    log_gross_share : float, optional
        The recorded log's gross-error share (method ``auto`` solves every epoch with
        ``igg`` above :data:`robustloc.integrity.fixes.AUTO_GROSS_SHARE`).
    log_sides : tuple, optional
        The recorded log's ambiguity sides (:attr:`Locator.log_sides`, from
        :meth:`log_statistics_from` with ``sides=True``).  With ``log_scale`` and without
        it no side is preferred: a request is no log.
    sigma : float, optional
        A-priori observation std (m or dB); default the anchors' ``sigma`` column if present.
    model : str, optional
        Path-loss columns to use for RSSI (default: what the anchors have).
    range_calibration : bool
        Correct ranges with the anchors' ``bias``/``scale`` columns (default True).
    tag_height : float, optional
        2-D only: known tag height to reduce slant ranges (m).
    """

    def __init__(
        self,
        anchors: pd.DataFrame,
        *,
        method: str | None = None,
        dim: int = 2,
        solver: str = "nonlinear",
        domain: str = "range",
        sigma: float | None = None,
        robust_scale: str = "mad",
        log_scale: Sequence[float] | None = None,
        log_gross_share: float | None = None,
        log_sides: tuple | None = None,
        reference: str = "first",
        min_scale: float = 0.0,
        alpha0: float = 0.001,
        beta0: float = 0.10,
        k_noise: float | None = None,
        alert_limit: float | None = None,
        weight_params: Mapping[str, float] | None = None,
        model: str | None = None,
        range_calibration: bool = True,
        tag_height: float | None = None,
    ) -> None:
        from robustloc.estimators.ranging import (
            DEFAULT_METHOD,
            METHOD_SYNONYMS,
            METHODS,
            ROBUST,
            Locator,
        )

        method = DEFAULT_METHOD if method is None else METHOD_SYNONYMS.get(method, method)
        if method not in METHODS + ("auto",):
            raise ValueError(f"unknown method {method!r}; choose one of auto, "
                             f"{', '.join(METHODS)}")
        if dim not in (2, 3):
            raise ValueError(f"dim must be 2 or 3, got {dim}")
        if dim == 3 and "z" not in anchors.columns:
            raise ValueError("dim 3 needs a z column in the anchors")
        if robust_scale == "log" and log_scale is None:
            raise ValueError("robust scale 'log' needs the noise scale of a recorded log "
                             "(--scale-from LOG); or use --robust-scale mad")
        self.anchors = anchors
        self.anchor_ids = [str(a) for a in anchors["anchor"]]
        self.name = method
        self.values = solvable_values(anchors, model)
        #: each epoch is solved on its own: a block may be split and retried (the engine)
        self.stateless = True
        self.dim = dim
        self.model = model
        self.range_calibration = range_calibration
        self.alpha0, self.beta0 = alpha0, beta0
        self.k_noise, self.alert_limit = k_noise, alert_limit
        self.xyz = anchors[["x", "y"] + (["z"] if dim == 3 else [])].to_numpy(dtype=float)
        self.height = None
        if tag_height is not None:
            if dim != 2 or "z" not in anchors.columns:
                raise ValueError("tag height needs dim 2 and a z column in the anchors")
            self.height = anchors["z"].to_numpy(dtype=float) - tag_height
        sig: float | tuple[float, ...] | None = sigma
        if sig is None:
            sg = anchor_sigma(anchors)  # an InputError (a ValueError) names the anchor
            sig = None if sg is None else tuple(float(v) for v in sg)
        self.locator = Locator(
            method, solver=solver, domain=domain, sigma=sig, robust_scale=robust_scale,
            reference=reference,
            weight_params=dict(weight_params or {}) if method in ROBUST else {},
            min_scale=min_scale, alpha0=alpha0, beta0=beta0,
        )
        if log_scale is not None:
            self.locator = replace(self.locator,
                                   log_scale_fixed=tuple(float(v) for v in log_scale),
                                   log_gross_share=log_gross_share,
                                   log_sides=() if log_sides is None else log_sides)
        self._pathloss: tuple[np.ndarray, np.ndarray] | None = None

    @staticmethod
    def log_scale_from(path: str, anchors: pd.DataFrame, *, method: str | None = None,
                       dim: int = 2, chunk_rows: int = 500_000, **settings: Any
                       ) -> tuple[float, ...]:
        """Per-anchor noise scale of a recorded log (see :meth:`log_statistics_from`)."""
        return LocateProcessor.log_statistics_from(path, anchors, method=method, dim=dim,
                                                   chunk_rows=chunk_rows, **settings)[0]

    @staticmethod
    def log_value(path: str) -> str:
        """``"rssi"`` or ``"range"``: the values a recorded log holds (its header)."""
        from robustloc.io.tables import _iter_raw, _value_column

        first = next(_iter_raw(path, 1))
        return _value_column(first, "measurements", path)

    @staticmethod
    def log_statistics_from(path: str, anchors: pd.DataFrame, *, method: str | None = None,
                            dim: int = 2, chunk_rows: int = 500_000, sides: bool = False,
                            **settings: Any) -> tuple:
        """Per-anchor noise scale and gross-error share of a recorded log, by
        ``robustloc locate``'s first pass (with ``sides=True`` also its ambiguity sides,
        :attr:`Locator.log_sides`, as a third item).

        ``settings`` are the other :class:`LocateProcessor` settings (``solver``, ``model``,
        ``range_calibration``, ...).  Runs ``locate``'s own first pass
        (:func:`robustloc.pipelines.locate.fix_log_scale`), so a log replayed through a
        service started with them (``log_scale``, ``log_gross_share``) gives the positions
        ``robustloc locate`` gives on the file.
        """
        from robustloc.io.tables import UnsortedInput
        from robustloc.pipelines.locate import Geometry, LocateSettings, fix_log_scale

        proto = LocateProcessor(anchors, method=method, dim=dim, robust_scale="log",
                                log_scale=(1.0,) * len(anchors), **settings)
        loc = replace(proto.locator, log_scale_fixed=None, log_sides=None)
        first_pass = LocateSettings(chunk_rows=chunk_rows, model=proto.model,
                                    range_calibration=proto.range_calibration)
        geo = Geometry([loc], anchors, proto.xyz, proto.height)
        try:
            (out,) = fix_log_scale(first_pass, geo, [str(path)], "auto")
        except UnsortedInput:
            (out,) = fix_log_scale(first_pass, geo, [str(path)], "sort")
        if out.log_scale_fixed is None:
            raise ValueError(f"{path}: no epochs to take the noise scale from")
        if sides:
            return tuple(out.log_scale_fixed), out.log_gross_share, out.log_sides or ()
        return tuple(out.log_scale_fixed), out.log_gross_share

    def process(self, epochs: Epochs) -> pd.DataFrame:
        from robustloc.integrity.fixes import locate_protected
        from robustloc.models.calibration import apply_range_calibration
        from robustloc.models.pathloss import log_distance_arrays
        from robustloc.status import INVALID

        values = epochs.values
        A = n = None
        if epochs.value == "rssi":
            if self._pathloss is None:
                self._pathloss = log_distance_arrays(self.anchors, self.model)
            A, n = self._pathloss
        elif self.range_calibration:
            values = apply_range_calibration(self.anchors, values)
        sol = locate_protected(
            self.locator, self.xyz, values, epochs.value, A=A, n=n,
            height_offset=self.height, alpha0=self.alpha0, beta0=self.beta0,
            k_noise=self.k_noise, alert_limit=self.alert_limit)
        cov = np.asarray(sol.covariance, dtype=float)
        frame = positions_frame(sol, epochs.time, epochs.tag, self.anchor_ids, self.name,
                                columns={"cov_xx": cov[:, 0, 0], "cov_xy": cov[:, 0, 1],
                                       "cov_yy": cov[:, 1, 1]})
        bad = epochs.all_invalid
        if bad.any():  # as robustloc locate: every row of the epoch outside the limits
            frame.loc[bad, "status"] = INVALID
            frame.loc[bad, [c for c in ("x", "y", "z", "sigma0") if c in frame]] = np.nan
            frame.loc[bad, "n_used"] = 0
        return frame

    def warm_up(self) -> None:
        """Solve one synthetic epoch per value kind, so the compiled kernels are loaded
        (or compiled) before the first live epoch rather than during it."""
        centre = self.xyz.mean(axis=0)
        rng = np.linalg.norm(self.xyz - centre, axis=1)[None, :] + 1.0
        kinds = [("range", rng)]
        try:
            from robustloc.models.pathloss import log_distance_arrays

            A, n = log_distance_arrays(self.anchors, self.model)
            kinds.append(("rssi", A - 10.0 * n * np.log10(rng)))
        except (ValueError, KeyError):
            pass  # no path-loss columns: this service will only see ranges
        m = len(self.anchor_ids)
        for kind, vals in kinds:
            ep = Epochs(np.zeros(1), np.array(["warm-up"], dtype=object), vals.reshape(1, m),
                        tuple(self.anchor_ids), kind, np.zeros(1, dtype=np.int64))
            self.process(ep)

    def state_dict(self) -> dict:
        return {}

    def load_state_dict(self, state: dict) -> None:
        return None

    def forget(self, tags: list[str]) -> None:
        """Nothing to drop: a fix uses no state of its tag."""
        return None

    def status(self) -> dict:
        """Nothing to add to ``/api/status``."""
        return {}


class TrackProcessor:
    """Tracks with ``robustloc.tracking.Tracker`` (motion model + filter per tag).

    Parameters
    ----------
    anchors : DataFrame
    model, filter : str
        Passed to ``Tracker``.
    link_offsets : ``"off"``, ``"on"`` or ``"auto"``
        The links' offsets as states (``Tracker(link_offsets=...)``), or chosen by the
        stream's first ``auto_sample_epochs`` epochs
        (:class:`robustloc.tracking.AutoTracker`, ``serve --track-link-offsets auto``).
    auto_sample_epochs : int, optional
        The trial's epochs with ``"auto"`` (default: ``track``'s sample, 20 000).
    **options
        Further ``Tracker`` settings.

    Raises
    ------
    RuntimeError
        When ``robustloc.tracking`` is not available in this installation.
    """

    def __init__(
        self, anchors: pd.DataFrame, *, model: str = "cv", filter: str = "ekf",
        link_offsets: str = "off", auto_sample_epochs: int | None = None, **options: Any
    ) -> None:
        if link_offsets not in ("off", "on", "auto"):
            raise ValueError(f"link_offsets must be 'off', 'on' or 'auto', got "
                             f"{link_offsets!r}")
        try:
            from robustloc.tracking import AutoTracker, Tracker
        except ImportError as exc:
            raise RuntimeError(
                "--track needs robustloc.tracking (the tracker), which this installation lacks "
                f"({exc}); use --method instead"
            ) from None
        self.name = f"track-{model}-{filter}"
        self.values = solvable_values(anchors)
        self.stateless = False  # per-tag filter state: a block is never processed twice
        self.tracker: Any
        if link_offsets == "auto":
            sample = {} if auto_sample_epochs is None else {
                "sample_epochs": auto_sample_epochs}
            self.tracker = AutoTracker(anchors, model=model, filter=filter, **sample,
                                       **options)
        else:
            self.tracker = Tracker(anchors, model=model, filter=filter,
                                   link_offsets=link_offsets == "on", **options)

    def process(self, epochs: Epochs) -> pd.DataFrame:
        return self.tracker.step(epochs)

    def status(self) -> dict:
        """``link_offsets``: ``{"mode": "on" | "off"}``, or with ``auto`` the trial's
        progress and then its choice (:meth:`robustloc.tracking.AutoTracker.status`)."""
        if hasattr(self.tracker, "status"):
            return {"link_offsets": self.tracker.status()}
        return {"link_offsets": {"mode": "on" if self.tracker.settings.link_offsets
                                 else "off"}}

    def checkpoint(self) -> object:
        """The tracker's in-memory state before a block (``Tracker.checkpoint``)."""
        return self.tracker.checkpoint()

    def rollback(self, checkpoint: object) -> None:
        """Back to a :meth:`checkpoint` (a block the tracker failed on is undone)."""
        self.tracker.rollback(checkpoint)  # type: ignore[arg-type]

    def state_dict(self) -> dict:
        return self.tracker.state_dict()

    def forget(self, tags: list[str]) -> None:
        """Drop the filters of ``tags`` (``Tracker.forget``)."""
        self.tracker.forget(tags)

    def _load_auto_choice(self, state: dict) -> None:
        """A store written with ``--track-link-offsets auto``, restarted with ``on`` or
        ``off``: its tracker is taken over when the trial had chosen the same (the
        operator pins the choice; the next snapshot is the plain tracker's), refused
        otherwise, saying what the store holds."""
        choice = state.get("choice")
        want = "on" if self.tracker.settings.link_offsets else "off"
        if not isinstance(choice, dict):
            raise ValueError("saved tracker state is a --track-link-offsets auto trial "
                             "still running (no choice yet): restart with "
                             "--track-link-offsets auto")
        chose = "on" if choice.get("use") else "off"
        if chose != want:
            raise ValueError("saved tracker state is --track-link-offsets auto's, which "
                             f"chose {chose}: restart with --track-link-offsets auto or "
                             f"{chose}")
        live = state.get("live")
        if not isinstance(live, dict):
            raise ValueError("saved tracker state of --track-link-offsets auto lacks its "
                             "tracker")
        self.tracker.load_state_dict(live)

    def load_state_dict(self, state: dict) -> None:
        try:
            if (isinstance(state, dict) and state.get("kind") == "auto-link-offsets"
                    and not hasattr(self.tracker, "status")):
                self._load_auto_choice(state)
            else:
                self.tracker.load_state_dict(state)
        except ValueError as exc:  # the store was written by a tracker set up otherwise
            raise ValueError(f"the store's {exc}: start with the --track options it was "
                             "written with, or with a new --store") from None
