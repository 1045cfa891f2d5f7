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

Size: the epochs are simulated and written :data:`CHUNK_EPOCHS` at a time (the geometry
of a chunk at once, the random draws epoch by epoch in the order of a whole run, so a seed
gives the same files whatever the chunking), so memory stays bounded whatever
``--epochs`` (a chunk's frames are a few MB); on a terminal a progress bar counts the
epochs (``-q``: none).  About 21 rows and 2.3 kB of ``pseudoranges.csv`` an epoch with
the defaults: 10**6 epochs (the largest ``--epochs``) write 2.3 GB in about five minutes
(measured: 302 s, 234 MB peak memory; before, every epoch's frame was held to the end,
at 1.2 ms an epoch: about twenty minutes).

Epochs that cannot be used are said, never silent: a ``warning:`` counts the epochs
that see fewer satellites than a fix needs (``3 +`` one clock per system seen, so at
least 4; a high ``--mask-deg``), and those that see fewer satellites than ``--faults``
(every visible satellite of them is faulty).  When no epoch at all sees enough
satellites for a fix the run is refused (exit code 2) and nothing is written.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pandas as pd
import pymap3d
from numpy.typing import NDArray

NAME = "gnss"
HELP = "multi-constellation (GPS/Galileo/BeiDou) pseudoranges with optional gross errors (seed 003)"
#: What to do with the files, the end of ``simulate gnss --help``: no command reads
#: ``pseudoranges.csv`` (``spp`` takes RINEX), so the help names the Python function that
#: tests it (the recipe checked in ``tests/test_newuser_reliability_sim.py``).
USAGE = """\
Using the files: no robustloc command reads pseudoranges.csv (`spp` solves RINEX
observation files with navigation files; `montecarlo --gnss` runs the seed-003 detection
study on this constellation without files).  From Python, read it with pandas and test
every epoch by data snooping on the pseudoranges linearized at the truth,
robustloc.integrity.snooping.snoop_linear(H, y, sigma), an epoch's rows padded with NaN:
  H      per satellite, the unit vector from the satellite to the receiver (truth.csv's
         x, y, z, ECEF) and one clock column per system (1 in its own system's);
  y      pseudorange - |r_s - r_rx| - clock_<system> (truth.csv);
  sigma  the sigma column.
Its `excluded` against fault_m != 0 gives the detection and identification rates, and
robustloc.integrity.reliability.reliability(H, sigma) the MDBs of every satellite."""
#: The note after the run's list of files.
FILES_NOTE = ("no robustloc command reads pseudoranges.csv (spp takes RINEX): from Python, "
              "robustloc.integrity.snooping.snoop_linear tests each epoch linearized at "
              "truth.csv (robustloc simulate gnss --help says how)")

Array = NDArray[np.float64]

#: Earth rotation rate, rad/s (WGS-84).
OMEGA_E = 7.2921151467e-5
#: Earth gravitational parameter, m^3/s^2 (WGS-84).
MU = 3.986004418e14
#: Epochs simulated and written at once (about 25 rows an epoch: a chunk's frame is a few
#: MB whatever ``--epochs``; the second simulate review: 10**6 epochs ran for twenty
#: minutes without a sign of progress, every epoch's frame held until the end).
CHUNK_EPOCHS = 2000
#: Columns of ``pseudoranges.csv``, in order.
PSEUDORANGE_COLUMNS = ("time", "tag", "sat", "system", "x_sat", "y_sat", "z_sat",
                       "pseudorange", "sigma", "elevation_deg", "azimuth_deg", "fault_m")


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
    sig = []
    for letter in systems:
        if letter not in SYSTEMS:
            raise ValueError(f"unknown GNSS system {letter!r}; choose among G, E, C")
        w = SYSTEMS[letter]
        sig.append(np.full(w.n_sats, w.code_sigma_m))
        ids += [f"{letter}{i + 1:02d}" for i in range(w.n_sats)]
    return ids, _positions(np.array([float(t_s)]), systems)[0], np.concatenate(sig)


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


#: ``--fault-m``'s default (the option's default is None: a value given is told from none).
FAULT_M_DEFAULT = 20.0


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
    p.add_argument("--fault-m", type=float_in(0.0, 1e6), default=None,
                   help=f"gross-error scale: size +-U(1, 2) times this, m (default "
                        f"{FAULT_M_DEFAULT:g}; refused without --faults)")


def refuse_idle_options(args: argparse.Namespace) -> None:
    """``--fault-m`` without ``--faults`` (0 gross errors: nothing to size) is refused with
    :class:`robustloc.errors.InputError`: it was taken and changed no byte of the files
    (the filter review)."""
    from robustloc.errors import InputError

    if getattr(args, "fault_m", None) is not None and not getattr(args, "faults", 0):
        raise InputError("--fault-m does not apply without --faults (no gross error to "
                         "size: the files have none)")


@dataclass(frozen=True)
class GnssSimData:
    """Simulated pseudoranges and truth (the frames written to CSV).

    ``warnings``: what :func:`usability` says of the run (epochs without a fix, fewer
    satellites than ``--faults``), as the command line prints them.
    """

    pseudoranges: pd.DataFrame
    truth: pd.DataFrame
    warnings: tuple[str, ...] = ()


@dataclass
class Usability:
    """Counts over the epochs of a run that say which ones are usable.

    Attributes
    ----------
    epochs : int
        Epochs simulated.
    without_fix : int
        Epochs that see fewer satellites than the ``3 +`` (one clock per system seen)
        unknowns of a fix (fewer than 4, or none).
    fewer_than_faults : int
        Epochs that see fewer satellites than ``faults`` (0 without faults).
    visible_min, visible_max : int
        Fewest and most satellites an epoch sees.
    """

    epochs: int = 0
    without_fix: int = 0
    fewer_than_faults: int = 0
    visible_min: int = field(default=10**9)
    visible_max: int = 0

    def add(self, n_visible: NDArray[np.int64], n_systems: NDArray[np.int64],
            faults: int) -> None:
        """Count a chunk's epochs: satellites seen, and systems among them."""
        if n_visible.size == 0:
            return
        self.epochs += int(n_visible.size)
        self.without_fix += int(np.sum(n_visible < 3 + n_systems))
        if faults > 0:
            self.fewer_than_faults += int(np.sum(n_visible < faults))
        self.visible_min = min(self.visible_min, int(n_visible.min()))
        self.visible_max = max(self.visible_max, int(n_visible.max()))


def usability(counts: Usability, mask_deg: float, faults: int) -> list[str]:
    """The warnings of a run (the second simulate review: both were silent, exit 0).

    Raises
    ------
    robustloc.errors.InputError
        No epoch sees enough satellites for a fix: nothing usable (``--mask-deg 89``
        wrote a pseudoranges file without a row).
    """
    from robustloc.errors import InputError

    seen = (f"{counts.visible_min}" if counts.visible_min == counts.visible_max
            else f"{counts.visible_min}-{counts.visible_max}")
    if counts.epochs and counts.without_fix == counts.epochs:
        raise InputError(
            f"--mask-deg: no epoch sees enough satellites above {mask_deg:g} deg for a fix "
            f"({seen} visible; a fix needs 3 + one clock per system seen, at least 4): "
            "lower --mask-deg (or add --systems)")
    out = []
    if counts.without_fix:
        out.append(f"--mask-deg {mask_deg:g}: {counts.without_fix} of {counts.epochs} epochs "
                   "see too few satellites for a fix (fewer than 3 + one clock per system "
                   f"seen, at least 4; {seen} visible): no position there")
    if counts.fewer_than_faults:
        out.append(f"--faults {faults}: {counts.fewer_than_faults} of {counts.epochs} epochs "
                   f"see fewer satellites than that ({seen} visible): every satellite of "
                   "those epochs is faulty, and they have fewer faults than asked")
    return out


def _positions(t_s: Array, systems: str) -> Array:
    """Satellite positions at every time of ``t_s`` at once: ``(T, S, 3)`` ECEF metres
    (circular Walker orbits of :data:`SYSTEMS`, Earth rotation ``OMEGA_E``; the satellites
    in :func:`constellation`'s order, which takes its positions from here)."""
    pos = []
    t = np.asarray(t_s, dtype=float)[:, None]
    for letter in systems:
        w = SYSTEMS[letter]
        per = w.n_sats // w.n_planes
        k = np.arange(w.n_sats)
        plane = k // per
        slot = k % per
        raan = np.deg2rad(w.raan0_deg) + 2 * np.pi * plane / w.n_planes
        n_mean = np.sqrt(MU / w.radius_m**3)
        u = 2 * np.pi * slot / per + 2 * np.pi * w.phasing * plane / w.n_sats + n_mean * t
        inc = np.deg2rad(w.inclination_deg)
        x = np.cos(raan) * np.cos(u) - np.sin(raan) * np.sin(u) * np.cos(inc)
        y = np.sin(raan) * np.cos(u) + np.cos(raan) * np.sin(u) * np.cos(inc)
        z = np.broadcast_to(np.sin(u) * np.sin(inc), x.shape)
        th = OMEGA_E * t
        xe = np.cos(th) * x + np.sin(th) * y
        ye = -np.sin(th) * x + np.cos(th) * y
        pos.append(w.radius_m * np.stack([xe, ye, z], axis=2))
    return np.concatenate(pos, axis=1)


def generate_chunks(
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
    counts: Usability | None = None,
    chunk_epochs: int | None = None,
) -> Iterator[tuple[pd.DataFrame, pd.DataFrame]]:
    """Simulate the scenario :data:`CHUNK_EPOCHS` epochs at a time (see the module
    docstring); yields ``(pseudoranges, truth)`` frames of consecutive epochs.

    The frames concatenated are those of a run in one piece, whatever ``chunk_epochs``
    (default :data:`CHUNK_EPOCHS`): the geometry of a chunk is computed at once, the
    random draws epoch by epoch in the order of the whole run.  ``counts`` (optional) is
    filled with the run's :class:`Usability` counts as the chunks are made.
    """
    if epochs < 1:
        raise ValueError("--epochs must be at least 1")
    if interval_s <= 0:
        raise ValueError("--interval-s must be positive")
    if faults < 0:
        raise ValueError("--faults must be >= 0")
    if not -90 <= lat_deg <= 90:
        raise ValueError("--lat must be within [-90, 90]")
    ids, _, sig0 = constellation(0.0, systems)  # (checks the letters)
    ids_a = np.asarray(ids, dtype=object)
    sys_a = np.asarray([i[0] for i in ids], dtype=object)
    step = CHUNK_EPOCHS if chunk_epochs is None else int(chunk_epochs)
    if step < 1:
        raise ValueError(f"chunk_epochs must be at least 1, got {step}")
    rng = np.random.default_rng(seed)
    rx = np.array(pymap3d.geodetic2ecef(lat_deg, lon_deg, height_m))
    clk0 = rng.uniform(-1e5, 1e5)
    isb = {s: (0.0 if s == "G" else rng.uniform(-10, 10)) for s in "GEC"}
    isb_sat = np.array([isb[s] for s in sys_a])
    letters = [s for s in systems if s in SYSTEMS]
    for start in range(0, epochs, step):
        k = np.arange(start, min(start + step, epochs))
        t = k * interval_s
        xyz = _positions(t, systems)  # (T, S, 3)
        az, el, _ = pymap3d.ecef2aer(xyz[..., 0], xyz[..., 1], xyz[..., 2], lat_deg, lon_deg,
                                     height_m)
        az, el = np.asarray(az), np.asarray(el)
        vis = el >= mask_deg  # (T, S)
        n_vis = vis.sum(axis=1)
        # rows in C order: epoch by epoch, satellites in the constellation's order (as
        # visible_design lists them)
        ti, si = np.nonzero(vis)
        el_v, az_v, xyz_v = el[ti, si], az[ti, si], xyz[ti, si]
        sin_el = np.sin(np.maximum(np.deg2rad(el_v), np.deg2rad(MIN_WEIGHT_ELEVATION_DEG)))
        sigma = sig0[si] / sin_el if elevation_weighting else sig0[si]
        clk_g = clk0 + 0.1 * t
        clk = clk_g[ti] + isb_sat[si]
        geo = np.linalg.norm(xyz_v - rx, axis=1)
        noise = np.empty(ti.size)
        fault = np.zeros(ti.size)
        lo = 0
        for n in n_vis.tolist():  # the draws of each epoch, in the order of a whole run
            n = int(n)
            if faults > 0 and n > 0:
                j = rng.choice(n, size=min(faults, n), replace=False)
                fault[lo + j] = (rng.choice([-1.0, 1.0], size=j.size)
                                 * rng.uniform(1, 2, j.size) * fault_m)
            noise[lo:lo + n] = rng.normal(size=n)
            lo += n
        pr = geo + clk + sigma * noise + fault
        if counts is not None:
            n_sys = np.zeros(len(k), dtype=np.int64)
            for letter in letters:
                n_sys += (vis & (sys_a == letter)[None, :]).any(axis=1)
            counts.add(n_vis, n_sys, faults)
        pseudo = pd.DataFrame({
            "time": t[ti], "tag": "rx", "sat": ids_a[si], "system": sys_a[si],
            "x_sat": xyz_v[:, 0], "y_sat": xyz_v[:, 1], "z_sat": xyz_v[:, 2],
            "pseudorange": pr, "sigma": sigma, "elevation_deg": el_v,
            "azimuth_deg": az_v, "fault_m": fault,
        }, columns=list(PSEUDORANGE_COLUMNS))
        truth = pd.DataFrame({
            "time": t, "tag": "rx", "x": rx[0], "y": rx[1], "z": rx[2],
            "lat": lat_deg, "lon": lon_deg, "h": height_m,
            **{f"clock_{s}": clk_g + isb[s] for s in "GEC"},
        })
        yield pseudo, truth


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
    """Simulate the scenario (see the module docstring); returns the two frames whole.

    Holds every epoch in memory (about 1 kB an epoch): the command line streams them
    instead (:func:`generate_chunks`, :func:`simulate`).  A run without any usable epoch
    raises :class:`robustloc.errors.InputError` (:func:`usability`).
    """
    counts = Usability()
    parts = list(generate_chunks(seed, epochs, interval_s, lat_deg, lon_deg, height_m,
                                 systems, mask_deg, elevation_weighting, faults, fault_m,
                                 counts))
    said = usability(counts, mask_deg, faults)
    return GnssSimData(pd.concat([p for p, _ in parts], ignore_index=True),
                       pd.concat([t for _, t in parts], ignore_index=True), tuple(said))


def simulate(out_dir: Path, seed: int, args: argparse.Namespace) -> dict[str, Path]:
    """Write ``pseudoranges.csv`` and ``truth.csv`` into ``out_dir``, streamed
    :data:`CHUNK_EPOCHS` epochs at a time with a progress bar on a terminal (not with
    ``args.quiet``); the run's warnings go to stderr as ``warning:`` lines, and a run
    without any usable epoch raises :class:`robustloc.errors.InputError`
    (:func:`usability`)."""
    from robustloc.options import check_systems
    from robustloc.sim._output import progress_bar

    check_systems(args.systems, "GEC")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    paths = {"pseudoranges": out / "pseudoranges.csv", "truth": out / "truth.csv"}
    counts = Usability()
    chunks = generate_chunks(
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
        fault_m=FAULT_M_DEFAULT if args.fault_m is None else args.fault_m,
        counts=counts,
    )
    with progress_bar(args, args.epochs, " epochs", "simulate gnss") as bar, \
            open(paths["pseudoranges"], "w", newline="", encoding="utf-8") as fp, \
            open(paths["truth"], "w", newline="", encoding="utf-8") as ft:
        _stream(chunks, fp, ft, bar.update)
    for said in usability(counts, args.mask_deg, args.faults):  # (raises: nothing usable)
        print(f"warning: {said}", file=sys.stderr)
    return paths


#: Format of the truth's latitude and longitude (degrees, 9 decimals: 0.1 mm).
TRUTH_DEGREES = "{:.9f}"


def truth_csv_frame(truth: pd.DataFrame) -> pd.DataFrame:
    """``truth`` as ``truth.csv`` writes it: ``lat, lon`` as text of
    :data:`TRUTH_DEGREES`, the other numbers through ``float_format="%.4f"``."""
    return truth.assign(**{c: truth[c].map(TRUTH_DEGREES.format)
                           for c in ("lat", "lon") if c in truth.columns})


def _stream(chunks: Iterator[tuple[pd.DataFrame, pd.DataFrame]], fp: object, ft: object,
            progress: Callable[[int], object]) -> None:
    """Append each chunk's frames to the open files (the header once), as one
    ``to_csv(float_format="%.4f")`` of the whole frames writes them; the truth's latitude
    and longitude with 9 decimals of a degree (0.1 mm: at 4, 47.123456 was written
    47.1235, 4.9 m from the row's own ECEF x, y, z -- the simulate review)."""
    for i, (pseudo, truth) in enumerate(chunks):
        pseudo.to_csv(fp, index=False, header=i == 0, float_format="%.4f")
        truth_csv_frame(truth).to_csv(ft, index=False, header=i == 0, float_format="%.4f")
        progress(len(truth))
