"""Tracks, not just fixes: a robust tight filter per tag (layer fusion/track).

:class:`Tracker` advances many tags epoch by epoch (see :mod:`robustloc.tracking.tracker`);
:mod:`robustloc.tracking.smooth` smooths a recorded forward pass (RTS, fixed lag).
"""

from robustloc.tracking.tracker import MODELS, Tracker, TrackerSettings, track_frame

__all__ = ["MODELS", "Tracker", "TrackerSettings", "track_frame"]
