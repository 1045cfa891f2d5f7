"""Scenario ``uwb-cart``: the UWB + GPS cart of seed 001 (groups A and B).

Geometry (seed 001, experiments): group A, a 10 m x 10 m field with anchors BS.A (0, 10),
BS.B (10, 0), BS.C (10, 10), the cart moving straight along ``y = 5`` (``--path line``) or
``y = x`` (``--path diagonal``) at 0.2 m/s, ``T = 1 s``; group B, 100 m x 100 m, anchors
(0, 100), (100, 0), (100, 100), along ``y = x``, ``T = 10 s``.  The cart crosses the field
(``y = 5``: from x = 0 to 10 m in 51 epochs; ``y = x``: from (0, 0) in the 71 epochs whose
whole steps fit in the diagonal, so it stops short of the far corner, at (9.90, 9.90) in
group A and (98.99, 98.99) in group B).

Noise (our documented choice; the paper gives none for the experiments):

* UWB range: Gaussian, ``sigma_r = 0.10 m + 0.001 d`` (the paper's simulation uses
  ``sigma^2 = 0.01 m^2``; DW1000 range noise grows slowly with distance), plus, with
  ``--nlos-prob p``, a positive NLOS excess ``U(0.5, 3) m`` on a fraction ``p`` of ranges;
* GPS (RMC + VTG every epoch, GGA position): speed ``sigma_v = 0.02 m/s``, course
  ``sigma_theta = 2 deg``, position ``sigma = 0.6 m`` per axis (a consumer receiver; the
  paper's GPS/IMU mean error is 84 cm).

Files: ``anchors.csv`` (``anchor, x, y``), ``measurements.csv`` (``time, tag, anchor, range``),
``truth.csv`` (``time, tag, x, y, vx, vy``), ``gps.nmea`` (real NMEA with checksums: GGA, RMC
with speed in knots and course true from north, VTG), ``origin.txt`` (the ENU origin of the
GGA positions, ``lat lon h``).  NMEA time of day starts at 00:00:00 UTC = time 0 of the ranges.
"""

from __future__ import annotations

import argparse
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd
import pymap3d
from numpy.typing import NDArray

from robustloc.io.nmea import make_gga, make_rmc, make_vtg

NAME = "uwb-cart"
HELP = "UWB + GPS cart of seed 001 (groups A and B), GPS as real NMEA"

Array = NDArray[np.float64]

#: ENU origin used for the GGA sentences (lat, lon, h).
ORIGIN = (30.0, 120.0, 10.0)

GROUPS = {
    "A": {"anchors": np.array([[0.0, 10.0], [10.0, 0.0], [10.0, 10.0]]), "size": 10.0,
          "dt": 1.0},
    "B": {"anchors": np.array([[0.0, 100.0], [100.0, 0.0], [100.0, 100.0]]), "size": 100.0,
          "dt": 10.0},
}
SPEED_MPS = 0.2
SIGMA_R0_M = 0.10
SIGMA_R_K = 0.001
SIGMA_V_MPS = 0.02
SIGMA_COURSE_DEG = 2.0
SIGMA_GPS_M = 0.6


@dataclass(frozen=True)
class CartData:
    """``K`` simulated trials of one group/path, epoch-aligned.

    Attributes
    ----------
    time_s : (J,) epoch times.
    truth : (K, J, 4) true ``[x, y, vx, vy]``.
    ranges : (K, J, M) measured ranges.
    speed_mps, course_rad : (K, J) GPS speed and course (clockwise from north).
    gps_xy : (K, J, 2) GPS positions (ENU).
    anchors : (M, 2).
    sigma_r : (K, J, M) the true range standard deviations.
    """

    time_s: Array
    truth: Array
    ranges: Array
    speed_mps: Array
    course_rad: Array
    gps_xy: Array
    anchors: Array
    sigma_r: Array


def simulate_cart(
    group: str = "A",
    path: str = "line",
    n_trials: int = 1,
    seed: int = 0,
    nlos_prob: float = 0.0,
) -> CartData:
    """Simulate ``n_trials`` independent runs of the cart (vectorized over trials)."""
    g = GROUPS.get(group.upper())
    if g is None:
        raise ValueError(f"group must be A or B, got {group!r}")
    if path not in ("line", "diagonal"):
        raise ValueError(f"path must be 'line' or 'diagonal', got {path!r}")
    if path == "line" and group.upper() == "B":
        raise ValueError("group B uses the diagonal path only (seed 001)")
    rng = np.random.default_rng(seed)
    L, dt = g["size"], g["dt"]
    if path == "line":
        start, direction = np.array([0.0, L / 2]), np.array([1.0, 0.0])
        length = L
    else:
        start, direction = np.array([0.0, 0.0]), np.array([1.0, 1.0]) / np.sqrt(2.0)
        length = L * np.sqrt(2.0)
    J = int(np.floor(length / (SPEED_MPS * dt))) + 1
    t = np.arange(J) * dt
    pos = start + (SPEED_MPS * t)[:, None] * direction
    vel = np.broadcast_to(SPEED_MPS * direction, (J, 2))
    truth = np.broadcast_to(np.concatenate([pos, vel], axis=1), (n_trials, J, 4)).copy()
    a = g["anchors"]
    d = np.linalg.norm(pos[:, None, :] - a[None], axis=-1)  # (J, M)
    sig = np.broadcast_to(SIGMA_R0_M + SIGMA_R_K * d, (n_trials, J, len(a)))
    ranges = d[None] + rng.normal(size=sig.shape) * sig
    if nlos_prob > 0:
        hit = rng.random(sig.shape) < nlos_prob
        ranges = ranges + hit * rng.uniform(0.5, 3.0, sig.shape)
    speed = SPEED_MPS + rng.normal(0, SIGMA_V_MPS, (n_trials, J))
    course = np.arctan2(direction[0], direction[1]) + np.deg2rad(
        rng.normal(0, SIGMA_COURSE_DEG, (n_trials, J))
    )
    course = (course + np.pi) % (2 * np.pi) - np.pi
    gps_xy = pos[None] + rng.normal(0, SIGMA_GPS_M, (n_trials, J, 2))
    return CartData(t, truth, ranges, speed, course, gps_xy, a, np.asarray(sig))


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from robustloc.options import float_in

    parser.add_argument("--group", choices=["A", "B"], default="A",
                        help="paper's experiment group (default A: 10 m field, T = 1 s)")
    parser.add_argument("--path", choices=["line", "diagonal"], default=None,
                        help="cart path: y = 5 (line, group A only; default for A) or y = x "
                             "(diagonal; group B's only path)")
    parser.add_argument("--nlos-prob", type=float_in(0.0, 1.0), default=0.0,
                        help="fraction of ranges with a positive NLOS excess U(0.5, 3) m")


def simulate(out_dir: Path, seed: int, args: argparse.Namespace) -> dict[str, Path]:
    """Write the scenario files (see the module docstring)."""
    group = getattr(args, "group", "A")
    path = getattr(args, "path", None) or ("line" if group == "A" else "diagonal")
    if group == "B" and path != "diagonal":
        from robustloc.errors import InputError

        raise InputError("--group B runs the cart along the diagonal y = x only (seed 001); "
                         "drop --path or give --path diagonal")
    nlos = float(getattr(args, "nlos_prob", 0.0) or 0.0)
    if not 0.0 <= nlos <= 1.0:
        raise ValueError(f"--nlos-prob must be in [0, 1], got {nlos}")
    data = simulate_cart(group, path, 1, seed, nlos)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    ids = ["BS.A", "BS.B", "BS.C"]
    anchors = pd.DataFrame({"anchor": ids, "x": data.anchors[:, 0], "y": data.anchors[:, 1]})
    J, M = data.ranges.shape[1:]
    meas = pd.DataFrame(
        {
            "time": np.repeat(data.time_s, M),
            "tag": "cart",
            "anchor": np.tile(ids, J),
            "range": data.ranges[0].reshape(-1),
        }
    )
    truth = pd.DataFrame(
        {"time": data.time_s, "tag": "cart", "x": data.truth[0, :, 0], "y": data.truth[0, :, 1],
         "vx": data.truth[0, :, 2], "vy": data.truth[0, :, 3]}
    )
    lat, lon, h = pymap3d.enu2geodetic(
        data.gps_xy[0, :, 0], data.gps_xy[0, :, 1], np.zeros(J), *ORIGIN
    )
    lines = []
    for j in range(J):  # one set of sentences per epoch (file writing, not a hot path)
        cdeg = float(np.rad2deg(data.course_rad[0, j]))
        lines.append(make_gga(data.time_s[j], float(lat[j]), float(lon[j]), float(h[j])))
        lines.append(make_rmc(data.time_s[j], float(data.speed_mps[0, j]), cdeg,
                              float(lat[j]), float(lon[j])))
        lines.append(make_vtg(float(data.speed_mps[0, j]), cdeg))
    files = {
        "anchors": out / "anchors.csv",
        "measurements": out / "measurements.csv",
        "truth": out / "truth.csv",
        "nmea": out / "gps.nmea",
        "origin": out / "origin.txt",
    }
    anchors.to_csv(files["anchors"], index=False)
    meas.to_csv(files["measurements"], index=False)
    truth.to_csv(files["truth"], index=False)
    files["nmea"].write_text("\r\n".join(lines) + "\r\n", encoding="ascii")
    files["origin"].write_text(f"{ORIGIN[0]} {ORIGIN[1]} {ORIGIN[2]}\n")
    return files
