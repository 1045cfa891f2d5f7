"""Physical plausibility limits for every measured quantity robustloc reads.

A value outside its limits is not data: it is a transmission error, a parser slip, a unit
mix-up or a sensor fault.  Readers flag such values as ``invalid_measurement`` (the row is
kept, counted in the run summary, and never used for a fix); they never let it reach an
estimator or a filter.

The limits are deliberately generous (a factor of several beyond any real device) so
that no genuine measurement is ever refused; they exist to catch the absurd, not the
unusual.  Each has a reason below.

===================  =====================  ===============================================
quantity             limits                 why
===================  =====================  ===============================================
range (m)            -50 .. 1e5             UWB and WiFi RTT report small negative ranges
                                            at very short distance (clock offsets, antenna
                                            delay); -50 m is far beyond any such bias.
                                            1e5 m (100 km) is beyond any terrestrial radio
                                            ranging link.
RSSI (dBm)           -150 .. +30            thermal noise in a 1 Hz bandwidth is -174 dBm,
                                            no receiver reports a usable signal below -150;
                                            +30 dBm (1 W) is the legal EIRP ceiling of
                                            2.4 GHz ISM transmitters, a received level above
                                            it is impossible.
speed (m/s)          0 .. 515               NMEA speed over ground; 515 m/s (1 000 kn) is
                                            the COCOM limit of civil GNSS receivers.
course (deg)         0 .. 360               course over ground, true (NMEA RMC/VTG).
pseudorange (m)      1.5e7 .. 5e7           GNSS satellites at 19 100 - 35 786 km altitude
                                            are 19 100 - 41 700 km from the Earth's
                                            surface; the bounds leave room for receiver
                                            clock offsets of several ms (1 ms = 300 km).
time (s)             finite, |t| <= 1e12    seconds since any epoch up to 31 700 years.
===================  =====================  ===============================================
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

__all__ = ["Limits", "LIMITS", "PATH_LOSS_EXPONENT_LIMITS", "RANGE_SCALE_LIMITS", "plausible",
           "limits_for"]


@dataclass(frozen=True)
class Limits:
    """Closed interval ``[low, high]`` of plausible values for one quantity.

    Parameters
    ----------
    name : str
        Quantity name as it appears in files (``range``, ``rssi``, ...).
    unit : str
        Unit of the values.
    low, high : float
        Smallest and largest plausible value (inclusive).
    """

    name: str
    unit: str
    low: float
    high: float

    def check(self, values: ArrayLike) -> NDArray[np.bool_]:
        """Boolean mask: ``True`` where a value is finite and inside the limits.

        NaN (a missing value) is *not* plausible; callers that treat NaN as "not heard"
        mask it separately before counting invalid values.
        """
        v = np.asarray(values, dtype=float)
        with np.errstate(invalid="ignore"):
            return np.isfinite(v) & (v >= self.low) & (v <= self.high)

    def describe(self) -> str:
        """``'range must lie in [-50, 100000] m'`` style text for messages."""
        return f"{self.name} must lie in [{self.low:g}, {self.high:g}] {self.unit}"


LIMITS: dict[str, Limits] = {
    "range": Limits("range", "m", -50.0, 1.0e5),
    "rssi": Limits("rssi", "dBm", -150.0, 30.0),
    "speed": Limits("speed", "m/s", 0.0, 515.0),
    "course": Limits("course", "deg", 0.0, 360.0),
    # a GGA altitude: the Dead Sea shore to a high-altitude balloon, with margin
    "height": Limits("height", "m", -1.5e3, 1.0e5),
    "pseudorange": Limits("pseudorange", "m", 1.5e7, 5.0e7),
    "time": Limits("time", "s", -1.0e12, 1.0e12),
}


#: The path-loss exponent (``n``, ``gamma``) an anchors file may hold, which every
#: command that reads anchors (``locate``, ``track``, ``filter``, ...) accepts.  Below
#: 0.01 the RSSI falls by less than 0.1 dB per decade of distance: 1 dB of noise moves
#: the range by a factor of 10^10 (a typo or a unit slip, not a link); above 20 (200 dB
#: per decade) no propagation falls so fast.  ``calibrate`` refuses a fit outside a
#: narrower interval inside this one (:data:`robustloc.models.calibration.MAX_EXPONENT`),
#: so that it never writes a file the other commands refuse (the input review).
PATH_LOSS_EXPONENT_LIMITS = (0.01, 20.0)

#: The range scale (``scale``: measured = scale * distance + bias) an anchors file may
#: hold: a clock or a propagation speed off by a factor of 1000 either way is a unit slip
#: (mm for m, km for m), not a calibration.  ``calibrate --self`` refuses a fit outside
#: it, so that it never writes a file the other commands refuse.
RANGE_SCALE_LIMITS = (1e-3, 1e3)


def limits_for(quantity: str) -> Limits:
    """The :class:`Limits` of ``quantity`` (``range``, ``rssi``, ``speed``, ...)."""
    try:
        return LIMITS[quantity]
    except KeyError:
        known = sorted(LIMITS)
        raise KeyError(f"no plausibility limits for {quantity!r}; known: {known}") from None


def plausible(quantity: str, values: ArrayLike) -> NDArray[np.bool_]:
    """Mask of values of ``quantity`` that are finite and inside its limits."""
    return limits_for(quantity).check(values)
