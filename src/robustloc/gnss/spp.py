"""Single-point positioning (SPP) from pseudoranges, batched over all epochs of a file.

Model of the code pseudorange of satellite ``s`` of constellation ``k`` at epoch ``t``::

    P = rho(r, r_s) + c dt_k - c dt_s + I + T + e,
    rho = |r_s - r| + omega_e (x_s y - y_s x) / c                 (Sagnac, RTKLIB geodist)

with one receiver clock ``dt_k`` per constellation (inter-system biases absorbed),
satellite positions and clocks at transmit time (:mod:`robustloc.gnss.ephemeris` or
:mod:`robustloc.gnss.sp3`), ``I`` from Klobuchar (or removed by the ionosphere-free
combination), ``T`` from Saastamoinen (:mod:`robustloc.gnss.corrections`).

Solved by iterated weighted least squares (Gauss-Newton) on stacked ``(N, S, p)`` design
matrices: all epochs at once, no loop over epochs.  Unknown clocks of constellations without
satellites in an epoch are pinned by a unit pseudo-observation (they do not change the
redundancy).

**Weights** (documented model, RTKLIB ``varerr`` style but with ``1/sin^2``)::

    sigma_i^2 = f^2 (a^2 + b^2 / sin^2(el_i))            code noise and multipath
              + sigma_eph^2                              orbit/clock: 0.8 m broadcast,
                                                         0.05 m SP3/CLK (with iflc;
                                                         0.8 m with a single frequency)
            [ + (0.5 I_i)^2 + (0.3 / (sin el_i + 0.1))^2   with atmosphere_variance=True ]

``a = b = 0.3 m`` by default (RTKLIB: ``err ratio 100 x 0.003 m``), ``f = 3`` for the
ionosphere-free combination (noise amplification), else 1.  The broadcast orbit/clock term
(0.8 m, below the nominal 2 m URA) was set so that the a-posteriori unit-weight error of the
residual tests is close to 1 on the shared GEONET and SLAC files (the RAIM tests use these
sigmas as a-priori standard deviations).
"""

from __future__ import annotations

import copy
from dataclasses import dataclass, field, replace

import numpy as np
import pandas as pd
from numpy.typing import NDArray

from robustloc import status as st
from robustloc.errors import InputError
from robustloc.gnss.corrections import (
    azimuth_elevation,
    enu_matrix,
    geodetic,
    klobuchar,
    saastamoinen,
)
from robustloc.gnss.ephemeris import BROADCAST_SIGMA_M, C_LIGHT, OMEGA_E, SatState, nav_state
from robustloc.gnss.rinex import NavData, ObsData, gps_s_to_datetime64
from robustloc.gnss.sp3 import PreciseProducts

#: Carrier frequencies (Hz) of the first and second signal used per constellation.
FREQ_HZ = {
    "G": (1575.42e6, 1227.60e6),
    "R": (1602.0e6, 1246.0e6),  # FDMA: the ratio 9/7 is the same for every channel
    "E": (1575.42e6, 1176.45e6),
    "C": (1561.098e6, 1207.14e6),
}
#: Code observation priority per constellation: (first signal, second signal), RINEX 2 and 3.
CODE_PRIORITY = {
    "G": (["C1", "P1", "C1C", "C1W", "C1P", "C1X"], ["P2", "C2", "C2W", "C2P", "C2X", "C2L"]),
    "R": (["C1", "P1", "C1C", "C1P"], ["P2", "C2", "C2P", "C2C"]),
    "E": (["C1", "C1C", "C1X", "C1B"], ["C5", "C5Q", "C5X", "C5I"]),
    # second signal: B2I only (1207.14 MHz, the frequency of FREQ_HZ and of TGD2); B3I
    # (C6I, 1268.52 MHz) combined with B2I coefficients left 0.235 I_B1 of ionosphere
    "C": (["C2", "C1", "C2I", "C1I", "C2X"], ["C7", "C7I", "C7Q", "C7X"]),
}
#: For the ionosphere-free combination with precise clocks (P1/P2 referenced), GPS prefers P1.
IFLC_FIRST = {"G": ["P1", "C1W", "C1P", "C1", "C1C", "C1X"]}

#: GPS - UTC leap seconds: (first GPS second it applies, value).
_LEAPS = [
    ("1981-07-01", 1), ("1982-07-01", 2), ("1983-07-01", 3), ("1985-07-01", 4),
    ("1988-01-01", 5), ("1990-01-01", 6), ("1991-01-01", 7), ("1992-07-01", 8),
    ("1993-07-01", 9), ("1994-07-01", 10), ("1996-01-01", 11), ("1997-07-01", 12),
    ("1999-01-01", 13), ("2006-01-01", 14), ("2009-01-01", 15), ("2012-07-01", 16),
    ("2015-07-01", 17), ("2017-01-01", 18),
]


def leap_seconds(t_gps_s: NDArray) -> NDArray[np.int64]:
    """GPS - UTC (s) at GPS times ``t_gps_s`` (IERS Bulletin C table since 1980)."""
    from robustloc.gnss.rinex import datetime64_to_gps_s

    t = np.asarray(t_gps_s, dtype=float)
    out = np.zeros(t.shape, dtype=np.int64)
    for day, ls in _LEAPS:
        t0 = datetime64_to_gps_s(np.array([np.datetime64(day)]))[0] + ls
        out = np.where(t >= t0, ls, out)
    return out


def pick_code(obs: ObsData, names_by_sys: dict[str, list[str]]) -> NDArray[np.float64]:
    """Per column, the first available code of the priority list of its constellation."""
    N, S = obs.n_epochs, len(obs.sats)
    out = np.full((N, S), np.nan)
    sysl = obs.system_of()
    for k, names in names_by_sys.items():
        cols = sysl == k
        if not cols.any():
            continue
        for name in reversed(names):  # later entries overwritten by earlier (preferred) ones
            if name in obs.obs:
                v = obs.obs[name][:, cols]
                out[:, cols] = np.where(np.isfinite(v), v, out[:, cols])
    return out


def pseudoranges(obs: ObsData, iono: str) -> NDArray[np.float64]:
    """Code pseudoranges (m) to use: single-frequency or ionosphere-free combination."""
    if iono == "iflc":
        first = {k: IFLC_FIRST.get(k, v[0]) for k, v in CODE_PRIORITY.items()}
        p1 = pick_code(obs, first)
        p2 = pick_code(obs, {k: v[1] for k, v in CODE_PRIORITY.items()})
        sysl = obs.system_of()
        f1 = np.array([FREQ_HZ.get(s, (1.0, 0.5))[0] for s in sysl])
        f2 = np.array([FREQ_HZ.get(s, (1.0, 0.5))[1] for s in sysl])
        g = f1**2 / (f1**2 - f2**2)
        return g * p1 + (1.0 - g) * p2
    return pick_code(obs, {k: v[0] for k, v in CODE_PRIORITY.items()})


#: Carrier-phase priority (first, second signal) for carrier smoothing; GLONASS (FDMA, channel
#: numbers not in RINEX 2) is not smoothed.
PHASE_PRIORITY = {
    "G": (["L1", "L1C", "L1W", "L1X"], ["L2", "L2W", "L2L", "L2X", "L2S"]),
    "E": (["L1", "L1C", "L1X"], ["L5", "L5Q", "L5X", "L5I"]),
    "C": (["L2", "L1", "L2I", "L1I"], ["L7", "L7I", "L7Q", "L7X"]),
}


def carrier_smooth_iflc(
    obs: ObsData, pr_if_m: NDArray[np.float64], window: int = 60,
    slip_gf_m: float = 0.15, slip_cmp_m: float = 15.0,
) -> NDArray[np.float64]:
    """Hatch filter of the ionosphere-free code with the ionosphere-free carrier phase.

    ``Ps_k = P_k / n + (n - 1) / n (Ps_{k-1} + Phi_k - Phi_{k-1})``, ``n = min(k, window)``
    epochs since the last reset (Hatch 1982).  The ionosphere-free combination has no
    code-carrier divergence, so long windows are safe.  The filter restarts for a
    satellite when its phase or code is missing, on a cycle slip -- a jump of the
    geometry-free phase ``lambda1 L1 - lambda2 L2`` by more than ``slip_gf_m`` or of the
    code-minus-phase by more than ``slip_cmp_m`` between epochs -- after a gap of more than
    two sampling intervals, or at a time step backwards; an epoch repeated (a step of 0)
    gets the smoothed code of its first copy and leaves the filter as it was.  Sequential
    in time (one vectorized step per epoch over all satellites); satellites without both carriers
    (GLONASS) keep the raw code.

    Parameters
    ----------
    obs : ObsData
    pr_if_m : ndarray (N, S)
        Ionosphere-free code (:func:`pseudoranges` with ``"iflc"``).
    window : int
        Maximum smoothing length in epochs.
    """
    if window < 1:
        raise ValueError("smoothing window must be >= 1 epoch")
    sysl = obs.system_of()
    l1 = pick_code(obs, {k: v[0] for k, v in PHASE_PRIORITY.items()})
    l2 = pick_code(obs, {k: v[1] for k, v in PHASE_PRIORITY.items()})
    f1 = np.array([FREQ_HZ.get(s, (np.nan, np.nan))[0] if s in PHASE_PRIORITY else np.nan
                   for s in sysl])
    f2 = np.array([FREQ_HZ.get(s, (np.nan, np.nan))[1] if s in PHASE_PRIORITY else np.nan
                   for s in sysl])
    lam1, lam2 = C_LIGHT / f1, C_LIGHT / f2
    g = f1**2 / (f1**2 - f2**2)
    phi = g * lam1 * l1 + (1.0 - g) * lam2 * l2  # IF phase (m), ambiguous
    gf = lam1 * l1 - lam2 * l2
    dt = np.diff(obs.t_gps_s)
    max_gap = 2.5 * (np.median(dt) if dt.size else 30.0)
    out = np.array(pr_if_m, dtype=float, copy=True)
    N, S = out.shape
    prev_phi = np.full(S, np.nan)
    prev_gf = np.full(S, np.nan)
    prev_ps = np.full(S, np.nan)
    n = np.zeros(S)
    t_prev = -np.inf
    for k in range(N):
        p, ph, gk = out[k], phi[k], gf[k]
        ok = np.isfinite(p) & np.isfinite(ph)
        if obs.t_gps_s[k] == t_prev:
            # the epoch repeated: its smoothed code where the satellite was smoothed, the
            # filter's state unchanged (a restart here moved later fixes by up to 2.3 m,
            # a second sample of one epoch weighed it twice: the review of the fix)
            out[k] = np.where(ok & np.isfinite(prev_ps) & (np.abs(ph - prev_phi) <= 1e-3),
                              prev_ps, p)
            continue
        with np.errstate(invalid="ignore"):
            # a step backwards (epochs out of time order) is no continuation: it
            # smoothed across it (0.26 m on GEONET with the first two epochs swapped; the
            # GNSS review)
            step = obs.t_gps_s[k] - t_prev
            cont = (ok & np.isfinite(prev_phi) & (step > 0) & (step <= max_gap)
                    & (np.abs(gk - prev_gf) <= slip_gf_m))
            pred = prev_ps + ph - prev_phi
            cont &= np.abs(p - pred) <= slip_cmp_m
        n = np.where(cont, np.minimum(n + 1, window), np.where(ok, 1, 0))
        ps = np.where(cont, p / np.maximum(n, 1) + (n - 1) / np.maximum(n, 1) * pred, p)
        out[k] = ps
        prev_phi = np.where(ok, ph, np.nan)
        prev_gf = np.where(ok, gk, np.nan)
        prev_ps = np.where(ok, ps, np.nan)
        t_prev = obs.t_gps_s[k]
    return out


@dataclass(frozen=True)
class SppResult:
    """Per-epoch SPP (and RAIM) results for ``N`` epochs and ``S`` satellites.

    Attributes
    ----------
    t_gps_s : ndarray (N,)
    xyz_m : ndarray (N, 3)
        ECEF position; NaN when unsolved.  Kept for ``unavailable`` epochs (RAIM could not
        verify or attribute a fault): check ``status`` / :attr:`ok`.
    clock_m : ndarray (N, K)
        Receiver clock bias of each constellation in ``systems`` (metres, ``c dt``).
    systems : str
        Constellations of the clock columns.
    sats : list of str (S,)
    residuals_m : ndarray (N, S)
        Post-fit residuals ``v = f(x) - P`` (NaN: not used).
    sigma_m : ndarray (N, S)
        A-priori standard deviation of each observation.
    elevation_rad, azimuth_rad : ndarray (N, S)
    used, excluded : ndarray of bool (N, S)
    n_sats : ndarray of int (N,)
        Satellites in the final solution.
    dop : ndarray (N, 4)
        GDOP, PDOP, HDOP, VDOP of the final geometry.
    sigma0 : ndarray (N,)
        A-posteriori unit-weight standard error.
    status : ndarray of str (N,)
    iterations : ndarray of int (N,)
    extra : dict
        RAIM outputs when run: ``global_stat``, ``global_crit``, ``global_stat_initial``,
        ``hpl_m``, ``vpl_m``, ``detected`` (N,), ``w`` (N, S).
    """

    t_gps_s: NDArray[np.float64]
    xyz_m: NDArray[np.float64]
    clock_m: NDArray[np.float64]
    systems: str
    sats: list[str]
    residuals_m: NDArray[np.float64]
    sigma_m: NDArray[np.float64]
    elevation_rad: NDArray[np.float64]
    azimuth_rad: NDArray[np.float64]
    used: NDArray[np.bool_]
    excluded: NDArray[np.bool_]
    n_sats: NDArray[np.int64]
    dop: NDArray[np.float64]
    sigma0: NDArray[np.float64]
    status: NDArray[np.object_]
    iterations: NDArray[np.int64]
    extra: dict = field(default_factory=dict)

    @property
    def n_epochs(self) -> int:
        return int(self.t_gps_s.shape[0])

    @property
    def ok(self) -> NDArray[np.bool_]:
        """Epochs with a usable fix."""
        return st.among(self.status, st.USABLE) & np.all(np.isfinite(self.xyz_m), axis=1)

    def enu_errors(self, ref_xyz_m: NDArray[np.float64]) -> NDArray[np.float64]:
        """East, north, up errors (m) of every epoch against a reference ECEF point."""
        ref = np.asarray(ref_xyz_m, dtype=float)
        lat, lon, _ = geodetic(ref)
        R = enu_matrix(lat, lon)
        return (self.xyz_m - ref) @ R.T

    def excluded_ids(self) -> list[str]:
        sats = np.asarray(self.sats, dtype=object)
        return [";".join(sats[row]) for row in self.excluded]

    def to_frame(self) -> pd.DataFrame:
        """The solution table written by ``robustloc spp`` (one row per epoch)."""
        t = self.t_gps_s
        lat, lon, h = geodetic(self.xyz_m)
        week = np.floor(t / 604800.0).astype(np.int64)
        utc = gps_s_to_datetime64(t - leap_seconds(t))
        df = pd.DataFrame(
            {
                "time": t,
                "gps_week": week,
                "tow_s": t - week * 604800.0,
                "utc": np.datetime_as_string(utc, unit="ms"),
                "x": self.xyz_m[:, 0], "y": self.xyz_m[:, 1], "z": self.xyz_m[:, 2],
                "lat": np.rad2deg(lat), "lon": np.rad2deg(lon), "h": h,
            }
        )
        for k, s in enumerate(self.systems):
            df[f"clock_{s}_m"] = self.clock_m[:, k]
        df["n_sats"] = self.n_sats
        for k, name in enumerate(("gdop", "pdop", "hdop", "vdop")):
            df[name] = self.dop[:, k]
        df["sigma0"] = self.sigma0
        df["status"] = self.status
        df["excluded"] = self.excluded_ids()
        for key in ("global_stat_initial", "global_stat", "global_crit", "hpl_m", "vpl_m"):
            if key in self.extra:
                df[key.replace("_m", "") if key.endswith("pl_m") else key] = self.extra[key]
        if "w" in self.extra:
            w = self.extra["w"]
            with np.errstate(all="ignore"):
                df["w_max"] = np.where(np.any(np.isfinite(w), axis=1),
                                       np.nanmax(np.where(np.isfinite(w), w, -1.0), axis=1),
                                       np.nan)
        return df


@dataclass
class _Prepared:
    obs: ObsData
    pr: NDArray[np.float64]  # (N, S)
    state: SatState
    avail: NDArray[np.bool_]  # (N, S)
    sys_idx: NDArray[np.int64]  # (S,) index into systems
    systems: str
    alpha: NDArray | None
    beta: NDArray | None
    iono_scale: NDArray[np.float64]  # (S,) (f_L1/f)^2

    def take(self, rows: NDArray[np.int64], pr_m: NDArray[np.float64] | None = None) -> _Prepared:
        """Epochs ``rows`` (repeats allowed), optionally with other pseudoranges (e.g. with
        injected faults: satellite states barely depend on the pseudorange)."""
        st_ = self.state
        pr = self.pr[rows] if pr_m is None else pr_m
        return _Prepared(
            self.obs.select(rows), pr,
            SatState(st_.pos_m[rows], st_.clock_s[rows], st_.var_m2[rows], st_.valid[rows]),
            self.avail[rows] & np.isfinite(pr), self.sys_idx, self.systems, self.alpha,
            self.beta, self.iono_scale,
        )


#: Largest height (m, above or below the ellipsoid) of a plausible receiver position: where
#: the elevation mask and the atmosphere's corrections apply (a ground receiver, an
#: aircraft); farther, the iteration has not yet reached the receiver.
PLAUSIBLE_HEIGHT_M = 1.0e5


class SppSolver:
    """Iterated weighted least-squares single-point positioning, all epochs at once.

    Parameters
    ----------
    systems : str
        Constellations to use (letters of ``GREC``); default all four.
    elevation_mask_deg : float
        Satellites below this elevation are not used (default 15 degrees as RTKLIB's test).
    iono : {"klobuchar", "iflc", "none"}
        Ionosphere: broadcast model, ionosphere-free code combination, or none.
    tropo : {"saastamoinen", "none"}
    tropo_mapping : {"cosz", "black"}
    sigma_a_m, sigma_b_m : float
        Elevation weight model ``a^2 + b^2 / sin^2 el`` (see module docstring).
    max_iter : int
        Gauss-Newton iterations (default 10).
    tol_m : float
        Convergence threshold on the position/clock update (m).
    max_gdop : float
        Epochs with a larger GDOP get status ``ill_conditioned`` (RTKLIB default 30).
    atmosphere_variance : bool
        Add the Klobuchar and Saastamoinen model-error variances to the weights (RTKLIB
        does; off by default because those errors are mostly common to all satellites and
        then make the a-priori sigmas about four times too large for the residual tests).
    smoothing_epochs : int
        With ``iono="iflc"``: Hatch-filter the code with the ionosphere-free carrier phase
        over up to this many epochs (:func:`carrier_smooth_iflc`); 0 = raw code (default).
        The weights are not changed (conservative: smoothed code is less noisy).
    """

    def __init__(
        self,
        systems: str = "GREC",
        elevation_mask_deg: float = 15.0,
        iono: str = "klobuchar",
        tropo: str = "saastamoinen",
        tropo_mapping: str = "cosz",
        sigma_a_m: float = 0.3,
        sigma_b_m: float = 0.3,
        max_iter: int = 10,
        tol_m: float = 1e-3,
        max_gdop: float = 30.0,
        atmosphere_variance: bool = False,
        smoothing_epochs: int = 0,
    ) -> None:
        systems = "".join(dict.fromkeys(systems.upper()))
        bad = set(systems) - set("GREC")
        if bad or not systems:
            raise ValueError(
                f"unknown constellation(s) {''.join(sorted(bad))!r}; use letters of GREC"
            )
        if iono not in ("klobuchar", "iflc", "none"):
            raise ValueError(f"iono must be klobuchar, iflc or none, got {iono!r}")
        if tropo not in ("saastamoinen", "none"):
            raise ValueError(f"tropo must be saastamoinen or none, got {tropo!r}")
        if not (sigma_a_m > 0 and sigma_b_m >= 0):
            raise ValueError("sigma_a_m must be > 0 and sigma_b_m >= 0")
        self.systems = systems
        self.elevation_mask_deg = float(elevation_mask_deg)
        self.iono = iono
        self.tropo = tropo
        self.tropo_mapping = tropo_mapping
        self.sigma_a_m = float(sigma_a_m)
        self.sigma_b_m = float(sigma_b_m)
        self.max_iter = int(max_iter)
        self.tol_m = float(tol_m)
        self.max_gdop = float(max_gdop)
        if smoothing_epochs and iono != "iflc":
            raise ValueError("carrier smoothing (smoothing_epochs > 0) needs iono='iflc'")
        self.smoothing_epochs = int(smoothing_epochs)
        self.atmosphere_variance = bool(atmosphere_variance)

    # ------------------------------------------------------------------ preparation
    def prepare(
        self, obs: ObsData, nav: NavData | None = None, precise: PreciseProducts | None = None
    ) -> _Prepared:
        """Pseudoranges and satellite states at transmit time for every (epoch, satellite)."""
        if nav is None and precise is None:
            raise ValueError("need broadcast navigation data or precise products (SP3)")
        pr = pseudoranges(obs, self.iono)
        if self.smoothing_epochs > 0:
            pr = carrier_smooth_iflc(obs, pr, self.smoothing_epochs)
        pr = np.where((pr > 1.0e7) & (pr < 6.0e7), pr, np.nan)  # plausible code range
        sysl = obs.system_of()
        present = [s for s in self.systems if np.any((sysl == s) & np.any(np.isfinite(pr), 0))]
        systems = "".join(present)
        sel = np.isin(sysl, list(systems)) if systems else np.zeros(len(obs.sats), bool)
        pr = np.where(sel[None, :], pr, np.nan)
        N, S = pr.shape
        pos = np.full((N, S, 3), np.nan)
        clk = np.full((N, S), np.nan)
        var = np.full((N, S), np.nan)
        iflc = self.iono == "iflc"
        if precise is not None:
            sp = precise.state_at_transmit(obs.sats, obs.t_gps_s, pr)
            pos, clk, var = sp.pos_m, sp.clock_s, sp.var_m2
            if not iflc and nav is not None:
                # precise clocks refer to the ionosphere-free pair (GPS P1/P2, Galileo
                # E1/E5a): a single-frequency code needs the broadcast group delay as well
                # (the review: C1 with SP3 and without it, up bias -6.3 m, 3-D RMS 8.1 m)
                gd = (nav_state(nav, obs.sats, obs.t_gps_s, pr, ionosphere_free=True).clock_s
                      - nav_state(nav, obs.sats, obs.t_gps_s, pr).clock_s)
                ge = np.isin(obs.system_of(), ["G", "E"])[None, :] & np.isfinite(gd)
                clk = np.where(ge, clk - gd, clk)
            if not iflc:
                # The broadcast term (0.8 m) was calibrated with the Klobuchar model: it
                # holds the model's residual ionosphere (and group-delay errors) as much as
                # orbit and clock errors, and precise orbits remove only the latter.  With
                # the precise 0.05 m, SLAC 2021-118 with SP3/CLK and Klobuchar (241 epochs):
                # RAIM found 140 (GPS) and 138 (GPS+Galileo) epochs unavailable, median
                # sigma0 1.38; with the broadcast term as the floor: 2 and 1 (sigma0 1.20
                # and 1.01), as with broadcast orbits (the spp review).
                var = np.where(np.isfinite(var), np.maximum(var, BROADCAST_SIGMA_M**2), var)
        if nav is not None:
            bs = nav_state(nav, obs.sats, obs.t_gps_s, pr, ionosphere_free=iflc)
            fill = ~np.isfinite(clk) & bs.valid
            pos = np.where(fill[..., None], bs.pos_m, pos)
            clk = np.where(fill, bs.clock_s, clk)
            var = np.where(fill, bs.var_m2, var)
        valid = np.all(np.isfinite(pos), axis=-1) & np.isfinite(clk)
        avail = valid & np.isfinite(pr)
        # keep only constellations with at least one satellite that has an orbit
        systems = "".join(s for s in systems if np.any(avail[:, sysl == s]))
        keep = np.isin(sysl, list(systems)) if systems else np.zeros(len(obs.sats), bool)
        pr = np.where(keep[None, :], pr, np.nan)
        avail &= keep[None, :]
        sys_idx = np.array([systems.find(s) for s in sysl])
        f1 = np.array([FREQ_HZ.get(s, (1575.42e6,))[0] for s in sysl])
        return _Prepared(
            obs, pr, SatState(pos, clk, var, valid), avail, sys_idx, systems,
            None if nav is None else nav.ion_alpha, None if nav is None else nav.ion_beta,
            (1575.42e6 / f1) ** 2,
        )

    # ------------------------------------------------------------------ model
    def _model(self, P: _Prepared, rows: NDArray, x: NDArray):
        """Predicted pseudoranges, design, elevations and sigmas at states ``x (K, p)``."""
        rr = x[:, :3]
        sp = P.state.pos_m[rows]
        d = sp - rr[:, None, :]
        geo = np.sqrt(np.einsum("ksd,ksd->ks", d, d))
        with np.errstate(invalid="ignore", divide="ignore"):
            e = d / geo[..., None]
        sag = OMEGA_E * (sp[..., 0] * rr[:, None, 1] - sp[..., 1] * rr[:, None, 0]) / C_LIGHT
        rho = geo + sag
        K = len(P.systems)
        lat, lon, h = geodetic(rr)
        # near the Earth's surface: elevations, the atmosphere's corrections and the mask
        # mean something there (a position at the centre, or hundreds of km up or down
        # after a step pulled by a gross pseudorange, is not yet a receiver's)
        pos_ok = (np.linalg.norm(rr, axis=1) > 6.0e6) & (np.abs(h) < PLAUSIBLE_HEIGHT_M)
        az, el = azimuth_elevation(rr, sp, lat, lon)
        el = np.where(pos_ok[:, None], el, np.pi / 2)
        corr = np.zeros_like(rho)
        var_corr = np.zeros_like(rho)
        if self.iono == "klobuchar":
            ion = klobuchar(P.obs.t_gps_s[rows][:, None], lat[:, None], lon[:, None], az, el,
                            P.alpha, P.beta) * P.iono_scale[None, :]
            ion = np.where(pos_ok[:, None], ion, 0.0)
            corr += ion
            var_corr += (0.5 * ion) ** 2
        if self.tropo == "saastamoinen":
            trp = saastamoinen(lat[:, None], h[:, None], el, mapping=self.tropo_mapping)
            trp = np.where(pos_ok[:, None], trp, 0.0)
            corr += trp
            var_corr += np.where(pos_ok[:, None], (0.3 / (np.sin(el) + 0.1)) ** 2, 0.0)
        clk_rx = x[:, 3:]
        sidx = P.sys_idx
        rx_clk_s = clk_rx[:, np.maximum(sidx, 0)]
        pred = rho + rx_clk_s - C_LIGHT * P.state.clock_s[rows] + corr
        H = np.zeros(rho.shape + (3 + K,))
        H[..., :3] = -e
        onehot = (sidx[:, None] == np.arange(K)[None, :]).astype(float)
        H[..., 3:] = onehot[None]
        fac = 3.0 if self.iono == "iflc" else 1.0
        sinel = np.clip(np.sin(el), 0.05, None)
        var = fac**2 * (self.sigma_a_m**2 + self.sigma_b_m**2 / sinel**2)
        if self.atmosphere_variance:
            var = var + var_corr
        var = var + np.nan_to_num(P.state.var_m2[rows])
        return pred, H, el, az, np.sqrt(var), pos_ok

    def _gauss_newton(self, P: _Prepared, rows, x, allowed, iters, apply_mask, sigma=None):
        """Iterate WLS for epochs ``rows`` from ``x``; ``allowed (K, S)`` observations.

        With ``apply_mask`` the elevation mask applies from a position the satellites
        themselves gave: first every allowed satellite, to convergence, then the mask
        there.  At the start position (the RINEX header's, possibly wrong: another
        receiver's coordinates, or 1e308) the mask dropped the satellites below that
        horizon, too few were left, the position never moved and every epoch was
        ``insufficient_anchors``, exit 0 (the spp review; RTKLIB's ``rescode`` skips
        the mask in its first iteration for the same reason)."""
        if apply_mask:
            x = self._gauss_newton(P, rows, x, allowed, iters, False, sigma)[0]
        K = len(P.systems)
        mask_rad = np.deg2rad(self.elevation_mask_deg)
        z = P.pr[rows]
        conv = np.zeros(len(rows), dtype=bool)
        n_it = np.zeros(len(rows), dtype=np.int64)
        for _ in range(iters):
            pred, H, el, az, sig, pos_ok = self._model(P, rows, x)
            use = allowed & np.isfinite(pred) & np.isfinite(z)
            if apply_mask:
                use &= ~pos_ok[:, None] | (el >= mask_rad)
            s = sig if sigma is None else sigma
            w = np.where(use, 1.0 / s**2, 0.0)
            lres = np.where(use, z - pred, 0.0)
            H = np.where(use[..., None], H, 0.0)
            HwT = np.swapaxes(H * w[..., None], 1, 2)
            Nm = HwT @ H
            bvec = (HwT @ lres[..., None])[..., 0]
            # pin clocks of constellations without satellites in this epoch
            nsys = use.astype(float) @ (P.sys_idx[:, None] == np.arange(K)[None, :])
            absent = nsys == 0
            idx = np.arange(3, 3 + K)
            Nm[:, idx, idx] += absent
            enough = use.sum(axis=1) >= 3 + (~absent).sum(axis=1)
            Nm[~enough] = np.eye(3 + K)
            bvec[~enough] = 0.0
            try:
                dx = np.linalg.solve(Nm, bvec[..., None])[..., 0]
            except np.linalg.LinAlgError:
                dx = np.stack([np.linalg.lstsq(a, b, rcond=None)[0] for a, b in zip(Nm, bvec)])
            dx = np.where(np.isfinite(dx), dx, 0.0)
            x = x + dx
            n_it += ~conv
            conv = conv | (np.linalg.norm(dx, axis=1) < self.tol_m)
            if conv.all():
                break
        pred, H, el, az, sig, pos_ok = self._model(P, rows, x)
        use = allowed & np.isfinite(pred) & np.isfinite(z)
        if apply_mask:
            # (at a position that is no receiver's -- pulled hundreds of km by a gross
            # pseudorange -- every satellite stays, for RAIM to find the one that pulled:
            # dropping them all made every epoch insufficient_anchors)
            use &= ~pos_ok[:, None] | (el >= mask_rad)
        absent = (use.astype(float) @ (P.sys_idx[:, None] == np.arange(K)[None, :])) == 0
        return x, H, np.where(use, pred - z, np.nan), use, el, az, sig, conv, n_it, absent

    def check_prepared(self, P: _Prepared) -> None:
        """Raise :class:`InputError` when no constellation has a usable satellite."""
        if len(P.systems) == 0:
            raise InputError(
                f"no usable pseudoranges of the requested constellations {self.systems!r} "
                "(no code observations, or no ephemeris / precise orbit for them)",
                P.obs.path,
            )

    def initial_state(self, P: _Prepared, x0: NDArray | None) -> NDArray[np.float64]:
        N = P.pr.shape[0]
        x = np.zeros((N, 3 + len(P.systems)))
        if x0 is not None:
            x[:, :3] = np.asarray(x0, dtype=float)
        elif np.linalg.norm(P.obs.approx_xyz_m) > 6.0e6:
            x[:, :3] = P.obs.approx_xyz_m
        return x

    def solve(
        self,
        obs: ObsData,
        nav: NavData | None = None,
        precise: PreciseProducts | None = None,
        x0: NDArray | None = None,
    ) -> SppResult:
        """Solve every epoch of ``obs`` (plain WLS, no fault exclusion)."""
        P = self.prepare(obs, nav, precise)
        return self._solve_prepared(P, x0)

    def _solve_prepared(self, P: _Prepared, x0: NDArray | None) -> SppResult:
        N, S = P.pr.shape
        rows = np.arange(N)
        x = self.initial_state(P, x0)
        self.check_prepared(P)
        x, H, v, use, el, az, sig, conv, n_it, absent = self._gauss_newton(
            P, rows, x, P.avail, self.max_iter + 5, True
        )
        return self._result(P, x, H, v, use, el, az, sig, conv, n_it, absent,
                            np.zeros((N, S), dtype=bool), {})

    def lost_to_invalid(
        self, obs: ObsData, nav: NavData | None, precise: PreciseProducts | None,
        xyz_m: NDArray[np.float64],
    ) -> NDArray[np.bool_]:
        """Epochs of ``obs`` that their implausible pseudoranges could have given a fix.

        The values set aside (:attr:`ObsData.invalid_cells`) matter to an epoch when a
        satellite would have been used with one (its code is the one this solver picks, of
        a constellation of :attr:`systems` with an orbit, above the elevation mask at
        ``xyz_m``) and the epoch's satellites, with those, would have made a usable set: at
        least one per unknown and a GDOP within :attr:`max_gdop`.  Otherwise the epoch's
        own status (too few satellites, a poor geometry) is the reason it has no fix: an
        implausible value of a satellite below the mask relabelled an ``ill_conditioned``
        epoch ``invalid_measurement`` (the spp review).

        Parameters
        ----------
        obs : ObsData
            The epochs to judge.
        nav, precise : NavData or None, PreciseProducts or None
            As for :meth:`solve`.
        xyz_m : ndarray (N, 3)
            Receiver position of each epoch for the elevations (its fix, or a neighbour's);
            a row of NaN counts every satellite as above the mask.

        Returns
        -------
        ndarray of bool (N,)
        """
        N = obs.n_epochs
        out = np.zeros(N, dtype=bool)
        if not obs.invalid_cells or N == 0:
            return out
        # a plausible code in place of each value set aside: it only sets the transmit
        # time, and the satellite moves some 100 m in the 0.05 s it may be off
        filled = {k: np.where(obs.invalid_cells[k], 2.2e7, v) if k in obs.invalid_cells
                  else v for k, v in obs.obs.items()}
        probe = copy.copy(self)
        probe.smoothing_epochs = 0
        withheld = (~np.isfinite(pseudoranges(obs, self.iono))
                    & np.isfinite(pseudoranges(replace(obs, obs=filled), self.iono)))
        if not withheld.any():
            return out
        P = probe.prepare(replace(obs, obs=filled), nav, precise)
        K = len(P.systems)
        if K == 0:
            return out
        x = np.zeros((N, 3 + K))
        xyz = np.asarray(xyz_m, dtype=float).reshape(N, 3)
        x[:, :3] = np.where(np.all(np.isfinite(xyz), axis=1)[:, None], xyz, 0.0)
        _, H, el, _, _, pos_ok = probe._model(P, np.arange(N), x)
        use = P.avail & (~pos_ok[:, None] | (el >= np.deg2rad(self.elevation_mask_deg)))
        absent = (use.astype(float) @ (P.sys_idx[:, None] == np.arange(K)[None, :])) == 0
        with np.errstate(invalid="ignore"):
            gdop = dops(H, use, x[:, :3], absent)[:, 0]
        return (use & withheld).any(axis=1) & (gdop <= self.max_gdop)

    def _result(self, P, x, H, v, use, el, az, sig, conv, n_it, absent, excluded, extra,
                status=None, dop=None) -> SppResult:
        N, S = P.pr.shape
        K = len(P.systems)
        p_eff = 3 + (~absent).sum(axis=1)
        n_used = use.sum(axis=1)
        if dop is None:
            dop = dops(H, use, x[:, :3], absent)
        with np.errstate(invalid="ignore", divide="ignore"):
            T = np.nansum(np.where(use, (v / sig) ** 2, 0.0), axis=1)
            s0 = np.sqrt(T / np.where(n_used > p_eff, n_used - p_eff, np.nan))
        if status is None:
            status = np.full(N, st.OK, dtype=object)
            status[~conv] = st.NOT_CONVERGED
            status[~(dop[:, 0] <= self.max_gdop)] = st.ILL_CONDITIONED
            status[n_used < p_eff] = st.INSUFFICIENT
            status[n_used == 0] = st.INSUFFICIENT
        # a solution no receiver can have (hundreds of km above or below the ellipsoid:
        # pulled there by a gross pseudorange that no test removed) is no fix (it was
        # `ok` without --raim, 560 km off: the spp review)
        with np.errstate(invalid="ignore"):
            h = geodetic(np.where(np.isfinite(x[:, :3]), x[:, :3], 0.0))[2]
        implausible = ~(np.abs(h) < PLAUSIBLE_HEIGHT_M) & st.among(status, st.USABLE)
        status = np.where(implausible, st.UNAVAILABLE, status).astype(object)
        # positions are kept for 'unavailable' (RAIM: a fix whose integrity could not be
        # established; the status says so and `ok` excludes it)
        bad = ~st.among(status, (*st.USABLE, st.UNAVAILABLE))
        xyz = np.where(bad[:, None], np.nan, x[:, :3])
        clk = np.where(bad[:, None] | absent, np.nan, x[:, 3:])
        return SppResult(
            t_gps_s=P.obs.t_gps_s.copy(), xyz_m=xyz, clock_m=clk.reshape(N, K),
            systems=P.systems, sats=list(P.obs.sats),
            residuals_m=np.where(use, v, np.nan), sigma_m=np.where(P.avail, sig, np.nan),
            elevation_rad=np.where(P.avail, el, np.nan), azimuth_rad=np.where(P.avail, az, np.nan),
            used=use, excluded=excluded, n_sats=n_used.astype(np.int64), dop=dop,
            sigma0=s0, status=status, iterations=n_it, extra=extra,
        )


def dops(H: NDArray, use: NDArray, xyz: NDArray, absent: NDArray) -> NDArray[np.float64]:
    """GDOP, PDOP, HDOP, VDOP from the (unweighted) design of the used satellites.

    Clocks of absent constellations are dropped (pinned with a unit diagonal, then removed
    from the trace).  NaN for singular geometry or fewer satellites than unknowns.
    """
    N, S, p = H.shape
    Hu = np.where(use[..., None], H, 0.0)
    Nm = np.swapaxes(Hu, 1, 2) @ Hu
    idx = np.arange(3, p)
    Nm[:, idx, idx] += absent
    p_eff = 3 + (~absent).sum(axis=1)
    ok = use.sum(axis=1) >= p_eff
    Nm[~ok] = np.eye(p)
    lam = np.linalg.eigvalsh(Nm)
    ok &= np.isfinite(lam[:, -1]) & (lam[:, 0] > 1e-12 * lam[:, -1])
    Q = np.linalg.inv(np.where(ok[:, None, None], Nm, np.eye(p)))
    lat, lon, _ = geodetic(np.where(np.isfinite(xyz), xyz, [6378137.0, 0, 0]))
    R = enu_matrix(lat, lon)
    Qenu = R @ Q[:, :3, :3] @ np.swapaxes(R, 1, 2)
    clk_tr = np.einsum("kii->k", Q[:, 3:, 3:]) - absent.sum(axis=1)
    pd_ = np.sqrt(np.einsum("kii->k", Q[:, :3, :3]))
    out = np.stack(
        [
            np.sqrt(pd_**2 + clk_tr),
            pd_,
            np.sqrt(Qenu[:, 0, 0] + Qenu[:, 1, 1]),
            np.sqrt(Qenu[:, 2, 2]),
        ],
        axis=1,
    )
    return np.where(ok[:, None], out, np.nan)


def error_summary(result: SppResult, ref_xyz_m: NDArray[np.float64]) -> dict:
    """ENU bias, RMS, 95th percentile and maximum errors of the usable fixes (metres).

    Horizontal = sqrt(E^2 + N^2); 3-D = sqrt(E^2 + N^2 + U^2).  Also the number of usable
    epochs and, when RAIM ran, the median protection levels.
    """
    ok = result.ok
    ref = np.asarray(ref_xyz_m, dtype=float)
    # without a reference (zeros: no --reference and no header position) there is no
    # error to state: the errors were against (6378137, 0, 0), hpl_bounds 0.0 (the review)
    has_ref = bool(np.all(np.isfinite(ref)) and np.linalg.norm(ref) > 6.0e6)
    e = result.enu_errors(ref)[ok] if has_ref else np.zeros((0, 3))
    out: dict = {"epochs": int(result.n_epochs), "solved": int(ok.sum())}
    statuses, counts = np.unique(result.status.astype(str), return_counts=True)
    out["status_counts"] = {str(k): int(c) for k, c in zip(statuses, counts)}
    if e.shape[0] == 0:
        if "hpl_m" in result.extra:  # the bounds, without errors (no reference, or no fix)
            hpl = result.extra["hpl_m"][ok]
            vpl = result.extra["vpl_m"][ok]
            if np.isfinite(hpl).any():
                out["median_hpl_m"] = float(np.median(hpl[np.isfinite(hpl)]))
                out["median_vpl_m"] = float(np.median(vpl[np.isfinite(vpl)]))
            # (also where RAIM left no usable fix against a reference: the counts
            # vanished exactly when RAIM rejected every epoch -- the GNSS review)
            out["faults_detected"] = int(np.sum(result.extra["detected"]))
            out["epochs_with_exclusion"] = int(np.sum(result.extra["n_excluded"] > 0))
        return out
    h = np.hypot(e[:, 0], e[:, 1])
    d3 = np.linalg.norm(e, axis=1)
    out.update(
        {
            "bias_e_m": float(e[:, 0].mean()), "bias_n_m": float(e[:, 1].mean()),
            "bias_u_m": float(e[:, 2].mean()),
            "rms_e_m": float(np.sqrt(np.mean(e[:, 0] ** 2))),
            "rms_n_m": float(np.sqrt(np.mean(e[:, 1] ** 2))),
            "rms_u_m": float(np.sqrt(np.mean(e[:, 2] ** 2))),
            "rms_h_m": float(np.sqrt(np.mean(h**2))),
            "rms_3d_m": float(np.sqrt(np.mean(d3**2))),
            "p95_h_m": float(np.percentile(h, 95)),
            "p95_3d_m": float(np.percentile(d3, 95)),
            "max_h_m": float(h.max()), "max_3d_m": float(d3.max()),
        }
    )
    if "hpl_m" in result.extra:
        hpl = result.extra["hpl_m"][ok]
        vpl = result.extra["vpl_m"][ok]
        fin = np.isfinite(hpl)
        if fin.any():
            out["median_hpl_m"] = float(np.median(hpl[fin]))
            out["median_vpl_m"] = float(np.median(vpl[np.isfinite(vpl)]))
            out["hpl_bounds_h_error_frac"] = float(np.mean(h[fin] <= hpl[fin]))
        out["faults_detected"] = int(np.sum(result.extra["detected"]))
        out["epochs_with_exclusion"] = int(np.sum(result.extra["n_excluded"] > 0))
    return out
