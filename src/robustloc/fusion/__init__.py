"""UWB + GPS fusion (seed 001) and beyond.

* :mod:`robustloc.fusion.uwb` -- per-epoch UWB fixes: the paper's linearized LS and WLS
  (documented distance-dependent weights) and a Gauss-Newton fix;
* :mod:`robustloc.fusion.align` -- time alignment of streams at different rates;
* :mod:`robustloc.fusion.pipeline` -- the fusion filter (EKF or UKF, CV or CA, robust
  update), loosely (fixes) or tightly (raw ranges) coupled, batched over tags;
* :mod:`robustloc.fusion.run` -- contract frames in, track frame out (``robustloc fuse``).
"""

from robustloc.fusion.pipeline import FusionFilter, FusionMeasurement, FusionTrack
from robustloc.fusion.run import FuseOptions, FuseResult, fuse
from robustloc.fusion.uwb import UwbFix, uwb_fix

__all__ = [
    "FuseOptions",
    "FuseResult",
    "FusionFilter",
    "FusionMeasurement",
    "FusionTrack",
    "UwbFix",
    "fuse",
    "uwb_fix",
]
