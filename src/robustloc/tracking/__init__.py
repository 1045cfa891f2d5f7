"""Tracks, not just fixes: a robust tight filter per tag (layer fusion/track).

:class:`Tracker` advances many tags epoch by epoch (see :mod:`robustloc.tracking.tracker`);
:mod:`robustloc.tracking.smooth` smooths a recorded forward pass (RTS, fixed lag);
:class:`AutoTracker` lets a stream's first epochs choose the links' offsets
(:mod:`robustloc.tracking.auto`).
"""

from robustloc.tracking.auto import AutoTracker
from robustloc.tracking.tracker import MODELS, Tracker, TrackerSettings, track_frame

__all__ = ["MODELS", "AutoTracker", "Tracker", "TrackerSettings", "track_frame"]
