"""Scenario ``gnss``: simulated multi-constellation pseudoranges for integrity studies (seed 003).

The template paper (seed 003) evaluates gross-error detection on "Monte Carlo simulated
multi-constellation navigation data".  This scenario produces such data:

Constellations (circular Walker orbits, nominal values):

======  ========  ==============  ===========  =======================================
system  letter    Walker T/P/F    radius (km)  inclination; code noise (seed 003 table)
======  ========  ==============  ===========  =======================================
GPS     ``G``     24/6/1          26 559.7     55 deg; 0.587 m (L1 row of the table)
Galileo ``E``     24/3/1          29 599.8     56 deg; 0.117 m (E5a row)
BeiDou  ``C``     24/3/1          27 906.1     55 deg; 0.300 m (B2 row; MEO satellites only)
======  ========  ==============  ===========  =======================================

Receiver: static at ``--lat --lon --height`` (default 30.53 N, 114.36 E, 30 m, Wuhan), one
epoch every ``--interval-s`` for ``--epochs`` epochs; satellites below ``--mask-deg``
elevation are not observed.  Each system has its own receiver clock term (metres;
GPS a random offset of up to 1e5 m drifting 0.1 m/s, Galileo and BeiDou the GPS term plus a
constant inter-system bias of a few metres), so a snapshot has ``p = 3 + (number of systems)``
unknowns.

Pseudorange of satellite ``s`` (``sigma_s = sigma_sys / sin(elevation)`` unless
``--no-elevation-weighting``):

``P = |r_s - r_rx| + clock_sys + N(0, sigma_s^2) + fault``

i.e. pseudoranges already corrected for satellite clock, ionosphere and troposphere, with
satellite positions (``x_sat, y_sat, z_sat``, ECEF metres) given at the epoch in the
Earth-fixed frame so no Sagnac / light-time correction is needed.  ``--faults K`` adds a
gross error of ``+-U(1, 2) --fault-m`` metres to ``K`` random satellites of every epoch
(column ``fault_m``, 0 for clean observations) for fault-detection studies.

Files written:

* ``pseudoranges.csv``: ``time, tag, sat, system, x_sat, y_sat, z_sat, pseudorange, sigma,
  elevation_deg, azimuth_deg, fault_m`` (one row per epoch and visible satellite);
* ``truth.csv``: ``time, tag, x, y, z, lat, lon, h`` (ECEF metres and geodetic degrees /
  metres) plus ``clock_G, clock_E, clock_C`` (metres).

The same geometry functions (:func:`constellation`, :func:`visible_design`) give the
linearized designs of :mod:`robustloc.integrity.montecarlo`.
"""

from __future__ import annotations

import argparse
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd
import pymap3d
from numpy.typing import NDArray

NAME = "gnss"
HELP = "multi-constellation (GPS/Galileo/BeiDou) pseudoranges with optional gross errors (seed 003)"

Array = NDArray[np.float64]

#: Earth rotation rate, rad/s (WGS-84).
OMEGA_E = 7.2921151467e-5
#: Earth gravitational parameter, m^3/s^2 (WGS-84).
MU = 3.986004418e14


@dataclass(frozen=True)
class Walker:
    """A Walker-delta constellation ``T/P/F`` of circular orbits."""

    system: str
    n_sats: int
    n_planes: int
    phasing: int
    radius_m: float
    inclination_deg: float
    code_sigma_m: float
    raan0_deg: float = 0.0


#: Nominal constellations (see the module docstring).
SYSTEMS: dict[str, Walker] = {
    "G": Walker("G", 24, 6, 1, 26_559_700.0, 55.0, 0.587, 0.0),
    "E": Walker("E", 24, 3, 1, 29_599_800.0, 56.0, 0.117, 20.0),
    "C": Walker("C", 24, 3, 1, 27_906_100.0, 55.0, 0.300, 40.0),
}


def constellation(t_s: float, systems: str = "GEC") -> tuple[list[str], Array, Array]:
    """ECEF positions of every satellite at time ``t_s``.

    Parameters
    ----------
    t_s : float
        Seconds since the simulation epoch (the Earth-fixed frame coincides with the
        inertial one at ``t_s = 0``).
    systems : str
        System letters among ``G``, ``E``, ``C``.

    Returns
    -------
    ids : list of str
        Satellite ids such as ``G01``.
    xyz : ndarray (S, 3)
        ECEF positions, m.
    sigma : ndarray (S,)
        Zenith code noise of each satellite's system, m.
    """
    ids: list[str] = []
    pos = []
    sig = []
    for letter in systems:
        if letter not in SYSTEMS:
            raise ValueError(f"unknown GNSS system {letter!r}; choose among G, E, C")
        w = SYSTEMS[letter]
        per = w.n_sats // w.n_planes
        k = np.arange(w.n_sats)
        plane = k // per
        slot = k % per
        raan = np.deg2rad(w.raan0_deg) + 2 * np.pi * plane / w.n_planes
        n_mean = np.sqrt(MU / w.radius_m**3)
        u = 2 * np.pi * slot / per + 2 * np.pi * w.phasing * plane / w.n_sats + n_mean * t_s
        inc = np.deg2rad(w.inclination_deg)
        x = np.cos(raan) * np.cos(u) - np.sin(raan) * np.sin(u) * np.cos(inc)
        y = np.sin(raan) * np.cos(u) + np.cos(raan) * np.sin(u) * np.cos(inc)
        z = np.sin(u) * np.sin(inc)
        th = OMEGA_E * t_s
        xe = np.cos(th) * x + np.sin(th) * y
        ye = -np.sin(th) * x + np.cos(th) * y
        pos.append(w.radius_m * np.stack([xe, ye, z], axis=1))
        sig.append(np.full(w.n_sats, w.code_sigma_m))
        ids += [f"{letter}{i + 1:02d}" for i in range(w.n_sats)]
    return ids, np.vstack(pos), np.concatenate(sig)


@dataclass(frozen=True)
class Snapshot:
    """Visible satellites of one epoch and the linearized design at the receiver.

    Attributes
    ----------
    ids : list of str
    systems : list of str
        System letter of each visible satellite.
    sat_xyz : ndarray (n, 3)
        ECEF positions, m.
    elevation_deg, azimuth_deg, range_m : ndarray (n,)
    sigma : ndarray (n,)
        Code noise of each observation, m.
    H_enu : ndarray (n, 3 + k)
        Design of the pseudoranges in local east, north, up (``-line of sight``) plus one
        clock column per system present.
    clock_systems : str
        Systems of the clock columns, in order.
    """

    ids: list[str]
    systems: list[str]
    sat_xyz: Array
    elevation_deg: Array
    azimuth_deg: Array
    range_m: Array
    sigma: Array
    H_enu: Array
    clock_systems: str


#: Elevation (deg) below which the elevation weighting ``1 / sin(el)`` stops growing.
MIN_WEIGHT_ELEVATION_DEG = 1.0


def visible_design(
    t_s: float,
    lat_deg: float = 30.53,
    lon_deg: float = 114.36,
    height_m: float = 30.0,
    systems: str = "GEC",
    mask_deg: float = 10.0,
    elevation_weighting: bool = True,
) -> Snapshot:
    """Visible satellites and the linearized pseudorange design at a receiver.

    ``sigma = sigma_sys / sin(max(elevation, 1 deg))`` when ``elevation_weighting``.
    """
    ids, xyz, sig0 = constellation(t_s, systems)
    az, el, rng = pymap3d.ecef2aer(xyz[:, 0], xyz[:, 1], xyz[:, 2], lat_deg, lon_deg, height_m)
    az, el, rng = np.asarray(az), np.asarray(el), np.asarray(rng)
    vis = el >= mask_deg
    az, el, rng, xyz, sig0 = az[vis], el[vis], rng[vis], xyz[vis], sig0[vis]
    ids_v = [i for i, v in zip(ids, vis) if v]
    sys_v = [i[0] for i in ids_v]
    present = "".join(s for s in systems if s in sys_v)
    ea, aa = np.deg2rad(el), np.deg2rad(az)
    los = np.stack([np.cos(ea) * np.sin(aa), np.cos(ea) * np.cos(aa), np.sin(ea)], axis=1)
    clocks = np.array([[1.0 if s == c else 0.0 for c in present] for s in sys_v]).reshape(
        len(sys_v), len(present)
    )
    # the weighting's elevation floored at 1 deg: at or below the horizon 1/sin(el) is
    # infinite or negative (a negative --mask-deg gave negative sigmas; now refused too)
    sin_el = np.sin(np.maximum(ea, np.deg2rad(MIN_WEIGHT_ELEVATION_DEG)))
    sigma = sig0 / sin_el if elevation_weighting else sig0
    return Snapshot(
        ids=ids_v, systems=sys_v, sat_xyz=xyz, elevation_deg=el, azimuth_deg=az, range_m=rng,
        sigma=sigma, H_enu=np.hstack([-los, clocks]), clock_systems=present,
    )


def add_arguments(p: argparse.ArgumentParser) -> None:
    from robustloc.options import (
        float_in,
        int_in,
    )

    p.add_argument("--epochs", type=int_in(1, 10**6), default=60,
                   help="number of epochs (default 60)")
    p.add_argument("--interval-s", type=float_in(1e-3, 86400.0), default=30.0,
                   help="epoch interval, s (default 30)")
    p.add_argument("--lat", type=float_in(-90.0, 90.0), default=30.53,
                   help="receiver latitude, deg (default %(default)s, Wuhan)")
    p.add_argument("--lon", type=float_in(-180.0, 360.0), default=114.36,
                   help="receiver longitude, deg (default %(default)s)")
    p.add_argument("--height", type=float_in(-1e3, 1e5), default=30.0,
                   help="receiver ellipsoidal height, m (default %(default)s)")
    p.add_argument("--systems", default="GEC", help="constellations among G, E, C (default GEC)")
    p.add_argument("--mask-deg", type=float_in(0.0, 90.0), default=10.0,
                   help="elevation mask, deg (default 10; 0 .. 90)")
    p.add_argument(
        "--no-elevation-weighting", action="store_true",
        help="constant code noise per system instead of sigma / sin(elevation)",
    )
    p.add_argument("--faults", type=int_in(0, 100), default=0,
                   help="gross errors per epoch (default 0)")
    p.add_argument("--fault-m", type=float_in(0.0, 1e6), default=20.0,
                   help="gross-error scale: size +-U(1, 2) times this, m (default 20)")


@dataclass(frozen=True)
class GnssSimData:
    """Simulated pseudoranges and truth (the frames written to CSV)."""

    pseudoranges: pd.DataFrame
    truth: pd.DataFrame


def generate(
    seed: int,
    epochs: int = 60,
    interval_s: float = 30.0,
    lat_deg: float = 30.53,
    lon_deg: float = 114.36,
    height_m: float = 30.0,
    systems: str = "GEC",
    mask_deg: float = 10.0,
    elevation_weighting: bool = True,
    faults: int = 0,
    fault_m: float = 20.0,
) -> GnssSimData:
    """Simulate the scenario (see the module docstring); returns the two frames."""
    if epochs < 1:
        raise ValueError("--epochs must be at least 1")
    if interval_s <= 0:
        raise ValueError("--interval-s must be positive")
    if faults < 0:
        raise ValueError("--faults must be >= 0")
    if not -90 <= lat_deg <= 90:
        raise ValueError("--lat must be within [-90, 90]")
    rng = np.random.default_rng(seed)
    rx = np.array(pymap3d.geodetic2ecef(lat_deg, lon_deg, height_m))
    clk0 = rng.uniform(-1e5, 1e5)
    isb = {s: (0.0 if s == "G" else rng.uniform(-10, 10)) for s in "GEC"}
    rows = []
    truth = []
    for k in range(epochs):
        t = k * interval_s
        snap = visible_design(t, lat_deg, lon_deg, height_m, systems, mask_deg,
                              elevation_weighting)
        n = len(snap.ids)
        clk_g = clk0 + 0.1 * t
        clk = np.array([clk_g + isb[s] for s in snap.systems])
        geo = np.linalg.norm(snap.sat_xyz - rx, axis=1)
        fault = np.zeros(n)
        if faults > 0 and n > 0:
            j = rng.choice(n, size=min(faults, n), replace=False)
            fault[j] = rng.choice([-1.0, 1.0], size=j.size) * rng.uniform(1, 2, j.size) * fault_m
        pr = geo + clk + snap.sigma * rng.normal(size=n) + fault
        rows.append(pd.DataFrame({
            "time": t, "tag": "rx", "sat": snap.ids, "system": snap.systems,
            "x_sat": snap.sat_xyz[:, 0], "y_sat": snap.sat_xyz[:, 1], "z_sat": snap.sat_xyz[:, 2],
            "pseudorange": pr, "sigma": snap.sigma, "elevation_deg": snap.elevation_deg,
            "azimuth_deg": snap.azimuth_deg, "fault_m": fault,
        }))
        truth.append({
            "time": t, "tag": "rx", "x": rx[0], "y": rx[1], "z": rx[2],
            "lat": lat_deg, "lon": lon_deg, "h": height_m,
            **{f"clock_{s}": clk_g + isb[s] for s in "GEC"},
        })
    return GnssSimData(pd.concat(rows, ignore_index=True), pd.DataFrame(truth))


def simulate(out_dir: Path, seed: int, args: argparse.Namespace) -> dict[str, Path]:
    """Write ``pseudoranges.csv`` and ``truth.csv`` into ``out_dir``."""
    from robustloc.options import check_systems

    check_systems(args.systems, "GEC")
    data = generate(
        seed,
        epochs=args.epochs,
        interval_s=args.interval_s,
        lat_deg=args.lat,
        lon_deg=args.lon,
        height_m=args.height,
        systems=args.systems.upper(),
        mask_deg=args.mask_deg,
        elevation_weighting=not args.no_elevation_weighting,
        faults=args.faults,
        fault_m=args.fault_m,
    )
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    paths = {"pseudoranges": out / "pseudoranges.csv", "truth": out / "truth.csv"}
    data.pseudoranges.to_csv(paths["pseudoranges"], index=False, float_format="%.4f")
    data.truth.to_csv(paths["truth"], index=False, float_format="%.4f")
    return paths
