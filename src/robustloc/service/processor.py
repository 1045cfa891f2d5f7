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

:class:`TrackProcessor` wraps ``robustloc.track.Tracker`` (imported lazily: the tracker is
an optional part of the library).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any, Protocol

import numpy as np
import pandas as pd

from robustloc.io.tables import Epochs, positions_frame


class Processor(Protocol):
    """A stateful consumer of ready epochs.

    ``name`` labels the output (the ``method`` column for locate).
    """

    name: str

    def process(self, epochs: Epochs) -> pd.DataFrame:
        """One output row per epoch of ``epochs`` (epochs come in time order per tag)."""
        ...

    def state_dict(self) -> dict:
        """Per-tag state to persist (empty for a stateless processor)."""
        ...

    def load_state_dict(self, state: dict) -> None:
        """Restore the state saved by :meth:`state_dict`."""
        ...


class LocateProcessor:
    """Per-epoch fixes with one :class:`~robustloc.estimators.ranging.Locator` method.

    Parameters
    ----------
    anchors : DataFrame
        From :func:`robustloc.io.read_anchors`.
    method : str
        One of :data:`robustloc.estimators.ranging.METHODS` (default ``huber``, as
        ``robustloc locate``).
    dim : {2, 3}
    solver, domain, reference, robust_scale, min_scale, alpha0, beta0, weight_params
        As the ``robustloc locate`` options of the same names.
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
        method: str = "huber",
        dim: int = 2,
        solver: str = "nonlinear",
        domain: str = "range",
        sigma: float | None = None,
        robust_scale: str = "mad",
        reference: str = "first",
        min_scale: float = 0.0,
        alpha0: float = 0.001,
        beta0: float = 0.10,
        weight_params: Mapping[str, float] | None = None,
        model: str | None = None,
        range_calibration: bool = True,
        tag_height: float | None = None,
    ) -> None:
        from robustloc.estimators.ranging import METHODS, ROBUST, Locator

        if method not in METHODS:
            raise ValueError(f"unknown method {method!r}; choose one of {', '.join(METHODS)}")
        if dim not in (2, 3):
            raise ValueError(f"dim must be 2 or 3, got {dim}")
        if dim == 3 and "z" not in anchors.columns:
            raise ValueError("dim 3 needs a z column in the anchors")
        self.anchors = anchors
        self.anchor_ids = [str(a) for a in anchors["anchor"]]
        self.name = method
        self.dim = dim
        self.model = model
        self.range_calibration = range_calibration
        self.xyz = anchors[["x", "y"] + (["z"] if dim == 3 else [])].to_numpy(dtype=float)
        self.height = None
        if tag_height is not None:
            if dim != 2 or "z" not in anchors.columns:
                raise ValueError("tag height needs dim 2 and a z column in the anchors")
            self.height = anchors["z"].to_numpy(dtype=float) - tag_height
        sig: float | tuple[float, ...] | None = sigma
        if sig is None and "sigma" in anchors.columns:
            sg = anchors["sigma"].to_numpy(dtype=float)
            if not np.all(np.isfinite(sg) & (sg > 0)):
                raise ValueError("anchors' sigma column must be positive and finite")
            sig = tuple(sg)
        self.locator = Locator(
            method, solver=solver, domain=domain, sigma=sig, robust_scale=robust_scale,
            reference=reference,
            weight_params=dict(weight_params or {}) if method in ROBUST else {},
            min_scale=min_scale, alpha0=alpha0, beta0=beta0,
        )
        self._pathloss: tuple[np.ndarray, np.ndarray] | None = None

    def process(self, epochs: Epochs) -> pd.DataFrame:
        from robustloc.models.calibration import apply_range_calibration
        from robustloc.models.pathloss import log_distance_arrays

        values = epochs.values
        A = n = None
        if epochs.value == "rssi":
            if self._pathloss is None:
                self._pathloss = log_distance_arrays(self.anchors, self.model)
            A, n = self._pathloss
        elif self.range_calibration:
            values = apply_range_calibration(self.anchors, values)
        sol = self.locator.solve(
            self.xyz, values, epochs.value, A=A, n=n, height_offset=self.height
        )
        frame = positions_frame(sol, epochs.time, epochs.tag, self.anchor_ids, self.name)
        cov = np.asarray(sol.covariance, dtype=float)
        frame["cov_xx"] = cov[:, 0, 0]
        frame["cov_xy"] = cov[:, 0, 1]
        frame["cov_yy"] = cov[:, 1, 1]
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


class TrackProcessor:
    """Tracks with ``robustloc.track.Tracker`` (motion model + filter per tag).

    Parameters
    ----------
    anchors : DataFrame
    model, filter : str
        Passed to ``Tracker``.
    **options
        Further ``Tracker`` settings.

    Raises
    ------
    RuntimeError
        When ``robustloc.track`` is not available in this installation.
    """

    def __init__(
        self, anchors: pd.DataFrame, *, model: str = "cv", filter: str = "ekf", **options: Any
    ) -> None:
        try:
            from robustloc.track import Tracker
        except ImportError as exc:
            raise RuntimeError(
                "--track needs robustloc.track (the tracker), which this installation lacks "
                f"({exc}); use --method instead"
            ) from None
        self.name = f"track-{model}-{filter}"
        self.tracker = Tracker(anchors, model=model, filter=filter, **options)

    def process(self, epochs: Epochs) -> pd.DataFrame:
        return self.tracker.step(epochs)

    def state_dict(self) -> dict:
        return self.tracker.state_dict()

    def load_state_dict(self, state: dict) -> None:
        self.tracker.load_state_dict(state)
