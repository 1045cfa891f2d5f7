"""GNSS single-point positioning from RINEX with RAIM fault detection and exclusion.

Modules
-------
rinex
    ``read_obs`` (own fixed-width RINEX 2 and 3 readers, checked against georinex),
    ``read_nav`` (RINEX 2 GPS and RINEX 3 GPS/Galileo/BeiDou record readers, Klobuchar
    coefficients).
ephemeris
    Broadcast orbits and clocks at transmit time (IS-GPS-200 table 20-IV, relativity, TGD/BGD,
    BeiDou GEO, week rollover).
sp3
    ``read_sp3``, ``read_clk``, ``PreciseProducts`` (Lagrange orbit interpolation, CLK clocks,
    relativistic term).
corrections
    Klobuchar, Saastamoinen (+ mapping), geodetic coordinates, azimuth/elevation.
spp
    ``SppSolver`` (batched iterated WLS, one clock per constellation, DOPs, elevation
    weights), ``SppResult``, ``error_summary``.
raim
    ``RaimFde`` (B-method global test + w-test data snooping of the integrity layer, several
    exclusions, identifiability check, protection levels), ``inject_faults``.

Example
-------
>>> from robustloc.gnss import RaimFde, SppSolver, read_nav, read_obs  # doctest: +SKIP
>>> obs, nav = read_obs("07590920.05o"), read_nav("07590920.05n")      # doctest: +SKIP
>>> res = RaimFde().solve(SppSolver(systems="G"), obs, nav)             # doctest: +SKIP
>>> res.to_frame().to_csv("solution.csv")                               # doctest: +SKIP
"""

from robustloc.gnss.raim import RaimFde, inject_faults
from robustloc.gnss.rinex import NavData, ObsData, read_nav, read_obs
from robustloc.gnss.sp3 import PreciseProducts, read_clk, read_sp3
from robustloc.gnss.spp import SppResult, SppSolver, error_summary

__all__ = [
    "NavData", "ObsData", "PreciseProducts", "RaimFde", "SppResult", "SppSolver",
    "error_summary", "inject_faults", "read_clk", "read_nav", "read_obs", "read_sp3",
]
