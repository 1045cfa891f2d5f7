"""Satellite positions and clocks from broadcast ephemerides (GPS, Galileo, BeiDou).

Implements the user algorithm of IS-GPS-200 table 20-IV (also Galileo OS SIS ICD sec. 5.1.1
and BeiDou ICD B1I sec. 5.2.4, including the BeiDou GEO rotation), vectorized over any array
of (satellite, time) pairs, with:

* the satellite clock polynomial ``af0 + af1 dt + af2 dt^2`` at transmit time,
* the relativistic clock term ``F e sqrt(A) sin(E)`` (IS-GPS-200 20.3.3.3.3.1),
* the group delay for single-frequency L1/E1/B1 users: GPS ``TGD``, Galileo ``BGD(E1,E5a)``,
  BeiDou ``TGD1`` (subtracted from the clock); for the ionosphere-free combination of the
  pair the clock refers to (GPS L1/L2, IS-GPS-200 20.3.3.3.3.2; Galileo E1/E5a, OS SIS
  ICD 5.1.5) none, and for BeiDou's B1I/B2I pair, whose clock refers to B3I (BDS-SIS-ICD-
  B1I 5.2.4.10), ``g TGD1 + (1 - g) TGD2`` with ``g = f1^2 / (f1^2 - f2^2)`` (as RTKLIB
  ``prange``),
* week rollover handled by working in continuous GPS seconds (``toe`` resolved from
  ``toc`` when the file is read) and wrapping ``t - toe`` into +-half a week.

GLONASS broadcast (numerical integration of the PZ-90 state vector) is not implemented:
GLONASS is supported through SP3/CLK precise products (:mod:`robustloc.gnss.sp3`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from robustloc.gnss.rinex import WEEK_S, NavData, plausible_records

#: Speed of light (m/s).
C_LIGHT = 299792458.0
#: BeiDou B1I and B2I carrier frequencies (Hz; BDS-SIS-ICD-B1I), the ionosphere-free pair.
BDS_B1I_HZ = 1561.098e6
BDS_B2I_HZ = 1207.14e6
#: WGS-84 / GPS Earth rotation rate (rad/s), also used by Galileo.
OMEGA_E = 7.2921151467e-5
#: BeiDou (CGCS2000) Earth rotation rate.
OMEGA_E_BDS = 7.292115e-5
#: Orbit + clock error of broadcast ephemerides used in the weights (m); see spp.
BROADCAST_SIGMA_M = 0.8
MU = {"G": 3.986005e14, "E": 3.986004418e14, "C": 3.986004418e14}
#: Maximum |t - toe| accepted (s): GPS/BDS 2 h + margin, Galileo 4 h (RTKLIB MAXDTOE*).
MAX_AGE_S = {"G": 7201.0, "E": 14401.0, "C": 21601.0}
#: Stand-in values (a circular GPS orbit at the reference time) computed in place of the
#: records an element has not got (``rec = -1``, or a record that cannot describe an
#: orbit): their results are replaced by NaN, the stand-in only keeps the arithmetic of
#: the masked elements finite.
_STAND_IN = {"sqrtA": 5153.7}


def is_bds_geo(sat: NDArray) -> NDArray[np.bool_]:
    """BeiDou GEO satellites (C01-C05, C59-C63)."""
    sat = np.asarray(sat)
    prn = np.array([int(s[1:]) if s[0] == "C" else 0 for s in sat.ravel()]).reshape(sat.shape)
    return (prn >= 1) & ((prn <= 5) | (prn >= 59))


@dataclass(frozen=True)
class SatState:
    """Satellite positions (ECEF at the given time, m), clocks (s), variances (m^2)."""

    pos_m: NDArray[np.float64]  # (..., 3)
    clock_s: NDArray[np.float64]  # (...)
    var_m2: NDArray[np.float64]  # (...)
    valid: NDArray[np.bool_]  # (...)


def select_ephemeris(
    nav: NavData, sats: list[str], t_gps_s: NDArray[np.float64]
) -> NDArray[np.int64]:
    """Index of the record to use for every (epoch, satellite): nearest ``toe``, healthy.

    Returns an ``(N, S)`` array of record indices, ``-1`` when none is valid (no record,
    unhealthy, older than :data:`MAX_AGE_S`, or values that cannot describe an orbit:
    :func:`~robustloc.gnss.rinex.nav_record_problems`).  Loops over satellites only.
    """
    t = np.asarray(t_gps_s, dtype=np.float64)
    out = np.full((t.size, len(sats)), -1, dtype=np.int64)
    healthy = (nav.params["health"] == 0) & plausible_records(nav.params)
    for j, s in enumerate(sats):
        rec = np.nonzero((nav.sat == s) & healthy)[0]
        if rec.size == 0:
            continue
        dt = np.abs(t[:, None] - nav.toe_gps_s[rec][None, :])
        k = np.argmin(dt, axis=1)
        ok = dt[np.arange(t.size), k] <= MAX_AGE_S.get(s[0], 7201.0)
        out[:, j] = np.where(ok, rec[k], -1)
    return out


def _wrap(dt: NDArray) -> NDArray:
    return dt - WEEK_S * np.round(dt / WEEK_S)


def _record_values(
    nav: NavData, rec: NDArray, t_gps_s: NDArray,
) -> tuple[NDArray[np.bool_], NDArray[np.int64], dict[str, NDArray], NDArray, NDArray]:
    """Parameters of the record of every element, ``rec`` any shape.

    Returns ``valid`` (a record that can describe an orbit: ``rec >= 0`` and
    :func:`~robustloc.gnss.rinex.plausible_records`), the record index (0 where not valid),
    the parameters, ``toe`` and ``toc`` (GPS s); where not valid the parameters are
    :data:`_STAND_IN` (0 otherwise) and both reference times ``t_gps_s``, so nothing
    computed from them can overflow; the caller sets those results to NaN.
    """
    rec = np.asarray(rec)
    valid = rec >= 0
    valid &= plausible_records(nav.params)[np.where(valid, rec, 0)]
    r = np.where(valid, rec, 0)
    p = {k: np.where(valid, v[r], _STAND_IN.get(k, 0.0)) for k, v in nav.params.items()}
    t = np.asarray(t_gps_s, dtype=np.float64)
    return valid, r, p, np.where(valid, nav.toe_gps_s[r], t), np.where(valid, nav.toc_gps_s[r], t)


def broadcast_clock(nav: NavData, rec: NDArray, t_gps_s: NDArray) -> NDArray[np.float64]:
    """Satellite clock polynomial (s) without relativity/TGD, to correct transmit time."""
    valid, _, p, _, toc = _record_values(nav, rec, t_gps_s)
    dt = _wrap(t_gps_s - toc)
    for _ in range(2):  # dt is in satellite time; iterate as in RTKLIB eph2clk
        dt = dt - (p["SVclockBias"] + p["SVclockDrift"] * dt + p["SVclockDriftRate"] * dt * dt)
    clk = p["SVclockBias"] + p["SVclockDrift"] * dt + p["SVclockDriftRate"] * dt * dt
    return np.where(valid, clk, np.nan)


def broadcast_state(
    nav: NavData, rec: NDArray[np.int64], t_gps_s: NDArray[np.float64],
    systems: NDArray[np.str_] | None = None, ionosphere_free: bool = False,
) -> SatState:
    """Position (ECEF at ``t``) and clock of satellites from their broadcast records.

    Parameters
    ----------
    nav : NavData
    rec : ndarray of int
        Record index per element (``-1`` = none), any shape.  A record whose values cannot
        describe an orbit (:func:`~robustloc.gnss.rinex.nav_record_problems`; not in a
        :func:`~robustloc.gnss.rinex.read_nav` result) counts as none.
    t_gps_s : ndarray
        Transmit time (GPS seconds), same shape as ``rec``.
    systems : ndarray of str, optional
        Constellation letter of each element (taken from the records when omitted).
    ionosphere_free : bool
        The clock for the ionosphere-free combination (:func:`group_delay_s`); default:
        for the single-frequency user.

    Returns
    -------
    SatState
        ``clock_s`` includes relativity and minus the group delay
        (:func:`group_delay_s`); ``var_m2`` is ``BROADCAST_SIGMA_M**2``.  NaN and
        ``valid`` False where there is no usable record.
    """
    rec = np.asarray(rec)
    t = np.asarray(t_gps_s, dtype=np.float64)
    valid, r, p, toe, toc = _record_values(nav, rec, t)
    sysl = np.asarray([s[0] for s in nav.sat])[r] if systems is None else np.asarray(systems)
    mu = np.where(sysl == "G", MU["G"], MU["E"])
    omge = np.where(sysl == "C", OMEGA_E_BDS, OMEGA_E)
    A = p["sqrtA"] ** 2
    tk = _wrap(t - toe)
    n = np.sqrt(mu / A**3) + p["DeltaN"]
    M = p["M0"] + n * tk
    e = p["Eccentricity"]
    E = M.copy()
    for _ in range(10):  # Kepler's equation by Newton iteration
        E = E - (E - e * np.sin(E) - M) / (1.0 - e * np.cos(E))
    sinE, cosE = np.sin(E), np.cos(E)
    nu = np.arctan2(np.sqrt(1.0 - e * e) * sinE, cosE - e)
    phi = nu + p["omega"]
    s2, c2 = np.sin(2 * phi), np.cos(2 * phi)
    u = phi + p["Cus"] * s2 + p["Cuc"] * c2
    rr = A * (1.0 - e * cosE) + p["Crs"] * s2 + p["Crc"] * c2
    inc = p["Io"] + p["IDOT"] * tk + p["Cis"] * s2 + p["Cic"] * c2
    xp, yp = rr * np.cos(u), rr * np.sin(u)
    cosi, sini = np.cos(inc), np.sin(inc)
    toe_sow = np.mod(toe - np.where(sysl == "C", 14.0, 0.0), WEEK_S)
    geo = is_bds_geo(np.asarray(nav.sat)[r]) & (sysl == "C")
    # MEO/IGSO (and GPS, Galileo): IS-GPS-200 table 20-IV
    Om = p["Omega0"] + (p["OmegaDot"] - omge) * tk - omge * toe_sow
    Om_geo = p["Omega0"] + p["OmegaDot"] * tk - omge * toe_sow
    Om = np.where(geo, Om_geo, Om)
    cO, sO = np.cos(Om), np.sin(Om)
    x = xp * cO - yp * cosi * sO
    y = xp * sO + yp * cosi * cO
    z = yp * sini
    if np.any(geo):  # BeiDou ICD: GEO in inertial-like frame rotated by -5 deg and omega*tk
        c5, s5 = np.cos(np.deg2rad(-5.0)), np.sin(np.deg2rad(-5.0))
        ang = OMEGA_E_BDS * tk
        ca, sa = np.cos(ang), np.sin(ang)
        yg = y * c5 + z * s5
        zg = -y * s5 + z * c5
        xg2 = x * ca + yg * sa
        yg2 = -x * sa + yg * ca
        x = np.where(geo, xg2, x)
        y = np.where(geo, yg2, y)
        z = np.where(geo, zg, z)
    pos = np.stack([x, y, z], axis=-1)
    # clock (IS-GPS-200 20.3.3.3.3.1): polynomial + relativistic term - group delay
    dt = _wrap(t - toc)
    clk = p["SVclockBias"] + p["SVclockDrift"] * dt + p["SVclockDriftRate"] * dt * dt
    F = -2.0 * np.sqrt(mu) / C_LIGHT**2
    clk = clk + F * e * p["sqrtA"] * sinE - group_delay_s(
        sysl, p["tgd"], p.get("tgd2", np.zeros_like(p["tgd"])), ionosphere_free)
    pos = np.where(valid[..., None], pos, np.nan)
    clk = np.where(valid, clk, np.nan)
    return SatState(pos, clk, np.where(valid, BROADCAST_SIGMA_M**2, np.nan), valid)


def group_delay_s(
    systems: NDArray[np.str_], tgd_s: NDArray[np.float64], tgd2_s: NDArray[np.float64],
    ionosphere_free: bool,
) -> NDArray[np.float64]:
    """The group delay (s) to subtract from a broadcast clock for the code in use.

    Single frequency (L1, E1, B1I): ``tgd`` (GPS TGD, IS-GPS-200 20.3.3.3.3.2; Galileo
    BGD(E1,E5a), OS SIS ICD 5.1.5; BeiDou TGD1).  Ionosphere-free combination
    ``g P1 + (1 - g) P2`` (``g = f1^2 / (f1^2 - f2^2)``): GPS L1/L2 and Galileo E1/E5a are
    the pairs their clocks refer to, so none; BeiDou B1I/B2I against its B3I clock,
    ``g TGD1 + (1 - g) TGD2`` (RTKLIB ``prange``).  (Galileo: the clock of an I/NAV record
    refers to E1/E5b, so that the E1/E5a pair would need ``BGD(E1,E5a) - BGD(E1,E5b)``,
    a few decimetres; only BGD(E1,E5a) is read, and it is taken as F/NAV's.)  Measured
    on the gnss-slac day (review, 2026-12-04): the broadcast GPS clocks against CODE's
    (referenced to P1/P2) spread 2.26 m with TGD subtracted, 0.46 m without, so the
    ionosphere-free fixes with it were 8.6 m 3-D RMS and 5.2 m without."""
    systems = np.asarray(systems)
    if not ionosphere_free:
        return np.asarray(tgd_s, dtype=np.float64)
    f1, f2 = BDS_B1I_HZ, BDS_B2I_HZ
    g = f1 * f1 / (f1 * f1 - f2 * f2)
    return np.where(systems == "C", g * tgd_s + (1.0 - g) * tgd2_s, 0.0)


def nav_state(
    nav: NavData, sats: list[str], t_rx_gps_s: NDArray[np.float64], pr_m: NDArray[np.float64],
    ionosphere_free: bool = False,
) -> SatState:
    """Satellite states at signal transmit time for observed pseudoranges.

    ``t_tx = t_rx - P / c - dt_sat`` (RTKLIB ``satposs``), the satellite clock evaluated at
    the transmit time; positions are in the ECEF frame of the transmit time (the Sagnac
    rotation is applied in the range model, :func:`robustloc.gnss.spp.geometric_range`).

    Parameters
    ----------
    nav : NavData
    sats : list of str, (S,)
    t_rx_gps_s : ndarray (N,)
    pr_m : ndarray (N, S)
        Pseudoranges (NaN where absent).
    ionosphere_free : bool
        Clocks for the ionosphere-free combination (:func:`group_delay_s`).
    """
    rec = select_ephemeris(nav, sats, t_rx_gps_s)
    t_tx = t_rx_gps_s[:, None] - np.nan_to_num(pr_m) / C_LIGHT
    t_tx = t_tx - broadcast_clock(nav, rec, t_tx)
    sysl = np.broadcast_to(np.array([s[0] for s in sats]), rec.shape)
    st = broadcast_state(nav, rec, t_tx, sysl, ionosphere_free)
    ok = st.valid & np.isfinite(pr_m)
    return SatState(
        np.where(ok[..., None], st.pos_m, np.nan), np.where(ok, st.clock_s, np.nan),
        np.where(ok, st.var_m2, np.nan), ok,
    )
