"""Scenario ``wifi-room``: the WiFi RSSI experiment of seed 002 (sec. 4, Table 2, Fig. 5).

Geometry (seed 002, sec. 4): a 10 m x 9 m room with four access points calibrated with the
attenuation-factor model ``P_r(d) = P_r(d0) + 10 gamma lg(d0/d) + FAF`` (eq. (5),
``d0 = 1 m``), parameters of the paper's Table 2:

====  =====  ====  =======  =======  ============
AP    X (m)  Y (m) gamma    FAF (dB) P_r(1 m) dBm
====  =====  ====  =======  =======  ============
AP1   9.0    7.8   2.556    0.647    -27
AP2   0.0    0.6   2.275    -1.076   -30
AP3   9.0    1.8   2.970    0.572    -21
AP4   -1.2   7.8   2.7518   1.3147   -28
====  =====  ====  =======  =======  ============

Static part: 20 reference points on a 5 x 4 grid, ``x = 0.5, 2.5, 4.5, 6.5, 8.5`` m,
``y = 1.5, 3.5, 5.5, 7.5`` m; each is its own tag (``rp01`` ... ``rp20``) with
``--samples-per-point`` (default 30) scans at 1 Hz.

Walking part: tag ``walk`` loops the rectangle ``x in [1, 8], y in [1.5, 7.5]``
anticlockwise from ``(1, 1.5)`` at ``--speed`` (default 1.0 m/s, walking pace), scanned at
``--rate-hz`` (default 2 Hz) for ``--walk-epochs`` (default 300) epochs.

RSSI noise, in dB, added to the model value of every scan (the paper's RSSI is left-skewed,
heavy-tailed and correlated up to lag 8, sec. 2):

* an AR(1) Gaussian component, ``phi = 0.88`` per scan (``--ar-phi``; 0 makes it
  white), stationary standard deviation
  ``--noise-db`` (default 1.5 dB): with the white parts below, the autocorrelation of the
  total falls below 0.2 after about 8 lags, as in the paper;
* a left-skewed component: skew-normal with shape ``-4``, scale ``0.8 --noise-db``,
  centred to zero mean (skewness about -0.8 on its own);
* fades: with probability ``--fade-prob`` (default 0.03) a scan loses an extra
  ``U(4, 10)`` dB (body shadowing, multipath) -- the heavy left tail;
* the two continuous components are multiplied by ``0.7 + 0.075 d`` (``d`` in metres), so
  the spread grows with distance (the paper finds a variance-distance correlation of
  0.578);
* environment changes on the walk (seed 002 Fig. 5 shows jumps at epochs 50, 190 and 240):
  from those epochs the level of AP1, AP3 and AP2 respectively drops by ``--jump-db``
  (default 8 dB) for 20 epochs (a person or door in the path); ``--no-jumps`` disables.

The survey (``survey.csv``) has 50 scans at each of 1, 2, ..., 8 m from every AP (the
paper's Table 1 distances), same noise without jumps: input of ``robustloc calibrate``.

Samples are drawn from :class:`robustloc.models.ranging.RssiModel` (``A = p0 + FAF``,
``n = gamma`` for ``d0 = 1 m``), the model the estimators use.

Size: the draws are whole arrays (the AR(1) noise runs along each link, the log is sorted
by time), about 160 bytes (:data:`BYTES_PER_ROW`) of memory per row of ``measurements.csv``
(``(20 --samples-per-point + --walk-epochs) x 4`` rows, plus the survey's 1600).  A run
beyond the simulation budget, :data:`robustloc.sim._output.MEMORY_BUDGET_BYTES` (1 GiB:
about 6.7 million rows, e.g. ``--samples-per-point 83000`` with the default walk), is
refused before any work, naming the larger of the two options and its limit (exit code
2); on a terminal a progress bar counts the rows written (``-q``: none).
"""

from __future__ import annotations

import argparse
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd
from scipy import stats

from robustloc.models.ranging import RssiModel

NAME = "wifi-room"
HELP = "seed 002: 10 m x 9 m room, 4 WiFi APs (Table 2), 20 static points and a walk"

#: Table 2 of seed 002: AP, X, Y, gamma_SF, FAF, RSSI at 1 m.
AP_TABLE = (
    ("AP1", 9.0, 7.8, 2.556, 0.647, -27.0),
    ("AP2", 0.0, 0.6, 2.275, -1.076, -30.0),
    ("AP3", 9.0, 1.8, 2.970, 0.572, -21.0),
    ("AP4", -1.2, 7.8, 2.7518, 1.3147, -28.0),
)
#: Environment-change epochs of the walk (seed 002, Fig. 5) and the AP each one hits.
JUMPS = ((50, "AP1"), (190, "AP3"), (240, "AP2"))
JUMP_LENGTH = 20
AR_PHI = 0.88
SKEW_SHAPE = -4.0
#: Peak memory of a run per row of ``measurements.csv``, bytes: the noise arrays, the
#: frames with their text columns (a Python string per tag and anchor cell), the time
#: sort's copy and the truth rows that go with them (measured 145-150 from 0.8 to 3.2
#: million rows, either option; the budget check of :func:`check_size`).
BYTES_PER_ROW = 160
#: Distances (m) of the calibration survey (the paper's Table 1).
SURVEY_DISTANCES_M = np.arange(1.0, 9.0)


@dataclass(frozen=True)
class WifiRoomConfig:
    """Settings of the scenario (defaults: the documented numbers above)."""

    samples_per_point: int = 30
    walk_epochs: int = 300
    rate_hz: float = 2.0
    speed_mps: float = 1.0
    noise_db: float = 1.5
    fade_prob: float = 0.03
    jump_db: float = 8.0
    jumps: bool = True
    survey_samples: int = 50
    ar_phi: float = AR_PHI

    def __post_init__(self) -> None:
        for name in ("samples_per_point", "walk_epochs", "survey_samples"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)}")
        for name in ("rate_hz", "speed_mps"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be positive, got {getattr(self, name)}")
        if self.noise_db < 0 or self.jump_db < 0:
            raise ValueError("noise_db and jump_db must be >= 0")
        if not 0 <= self.ar_phi < 1:
            raise ValueError(f"ar_phi must be in [0, 1), got {self.ar_phi}")
        if not 0 <= self.fade_prob <= 1:
            raise ValueError(f"fade_prob must be in [0, 1], got {self.fade_prob}")


@dataclass(frozen=True)
class WifiRoomData:
    """The generated tables (contract columns)."""

    anchors: pd.DataFrame
    measurements: pd.DataFrame
    truth: pd.DataFrame
    survey: pd.DataFrame


def anchors_frame() -> pd.DataFrame:
    """The four APs of Table 2 with attenuation-factor and equivalent log-distance columns."""
    rows = []
    for name, x, y, g, faf, p0 in AP_TABLE:
        rows.append({"anchor": name, "x": x, "y": y, "p0": p0, "gamma": g, "faf": faf,
                     "d0": 1.0, "A": p0 + faf, "n": g})
    return pd.DataFrame(rows)


def reference_points() -> np.ndarray:
    """The 20 static reference points ``(20, 2)``, row-major over y then x."""
    xs = np.array([0.5, 2.5, 4.5, 6.5, 8.5])
    ys = np.array([1.5, 3.5, 5.5, 7.5])
    gx, gy = np.meshgrid(xs, ys)
    return np.stack([gx.ravel(), gy.ravel()], axis=1)


def walk_path(n: int, rate_hz: float, speed_mps: float) -> tuple[np.ndarray, np.ndarray]:
    """Times ``(n,)`` and positions ``(n, 2)`` around the rectangle ``[1, 8] x [1.5, 7.5]``."""
    corners = np.array([[1.0, 1.5], [8.0, 1.5], [8.0, 7.5], [1.0, 7.5], [1.0, 1.5]])
    seg = np.linalg.norm(np.diff(corners, axis=0), axis=1)
    cum = np.r_[0.0, np.cumsum(seg)]
    t = np.arange(n) / rate_hz
    s = (speed_mps * t) % cum[-1]
    pos = np.stack([np.interp(s, cum, corners[:, 0]), np.interp(s, cum, corners[:, 1])], axis=1)
    return t, pos


def _noise(
    rng: np.random.Generator, shape: tuple[int, ...], cfg: WifiRoomConfig, distance_m: np.ndarray
) -> np.ndarray:
    """Left-skewed, heavy-tailed, AR(1)-correlated noise along axis 0 (see module doc).

    ``distance_m`` broadcasts to ``shape`` and scales the continuous components.
    """
    s_ar = cfg.noise_db
    phi = cfg.ar_phi
    eps = rng.normal(0.0, s_ar * np.sqrt(1 - phi**2), shape)
    ar = np.empty(shape)
    ar[0] = rng.normal(0.0, s_ar, shape[1:])
    # AR(1) recursion along time; lfilter is the vectorized form of a_k = phi a_{k-1} + e_k
    from scipy.signal import lfilter

    ar[1:] = lfilter([1.0], [1.0, -phi], eps[1:], axis=0, zi=phi * ar[:1])[0]
    sk = stats.skewnorm(SKEW_SHAPE, scale=0.8 * cfg.noise_db)
    skew = sk.rvs(size=shape, random_state=rng) - sk.mean()
    fade = np.where(rng.random(shape) < cfg.fade_prob, -rng.uniform(4.0, 10.0, shape), 0.0)
    return (ar + skew) * (0.7 + 0.075 * np.asarray(distance_m)) + fade


def generate(cfg: WifiRoomConfig, seed: int) -> WifiRoomData:
    """Draw the scenario (all numbers in the module docstring)."""
    rng = np.random.default_rng(seed)
    anchors = anchors_frame()
    ids = anchors["anchor"].to_numpy()
    m = len(ids)
    model = RssiModel(anchors[["x", "y"]].to_numpy(), anchors["A"].to_numpy(),
                      anchors["n"].to_numpy())

    # static reference points: (samples, 20 points, m)
    rp = reference_points()
    k = cfg.samples_per_point
    clean = model.predict(rp)  # (20, m)
    d_rp = model.ranges.predict(rp)  # (20, m)
    rs = clean[None] + _noise(rng, (k, len(rp), m), cfg, d_rp[None])
    t_s = np.arange(k, dtype=float)
    tags = np.array([f"rp{i + 1:02d}" for i in range(len(rp))])
    static = pd.DataFrame({
        "time": np.repeat(t_s, len(rp) * m),
        "tag": np.tile(np.repeat(tags, m), k),
        "anchor": np.tile(ids, k * len(rp)),
        "rssi": rs.ravel(),
    })
    truth_static = pd.DataFrame({
        "time": np.repeat(t_s, len(rp)), "tag": np.tile(tags, k),
        "x": np.tile(rp[:, 0], k), "y": np.tile(rp[:, 1], k),
    })

    # walk: (epochs, m)
    t_w, pos = walk_path(cfg.walk_epochs, cfg.rate_hz, cfg.speed_mps)
    rw = model.predict(pos) + _noise(rng, (cfg.walk_epochs, m), cfg, model.ranges.predict(pos))
    if cfg.jumps:
        for epoch, ap in JUMPS:
            j = int(np.flatnonzero(ids == ap)[0])
            rw[epoch: epoch + JUMP_LENGTH, j] -= cfg.jump_db
    walk = pd.DataFrame({
        "time": np.repeat(t_w, m), "tag": "walk", "anchor": np.tile(ids, cfg.walk_epochs),
        "rssi": rw.ravel(),
    })
    truth_walk = pd.DataFrame({"time": t_w, "tag": "walk", "x": pos[:, 0], "y": pos[:, 1]})

    # survey at 1..8 m (Table 1 distances)
    dist = SURVEY_DISTANCES_M
    n_s = cfg.survey_samples
    sv = (anchors["A"].to_numpy()[None, None, :]
          - 10 * anchors["n"].to_numpy()[None, None, :] * np.log10(dist)[None, :, None]
          + _noise(rng, (n_s, len(dist), m), cfg, dist[None, :, None]))
    survey = pd.DataFrame({
        "anchor": np.tile(ids, n_s * len(dist)),
        "distance": np.tile(np.repeat(dist, m), n_s),
        "rssi": sv.ravel(),
    })
    # time-sorted (the static points and the walk share the clock), as logs are streamed
    meas = pd.concat([static, walk], ignore_index=True).sort_values(
        "time", kind="mergesort", ignore_index=True)
    truth = pd.concat([truth_static, truth_walk], ignore_index=True).sort_values(
        "time", kind="mergesort", ignore_index=True)
    return WifiRoomData(anchors, meas, truth, survey)


def oracle_walk_track(cfg: WifiRoomConfig, seed: int, q: float,
                      ar_aware: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """The walk tracked by an oracle Kalman filter: a yardstick for real trackers.

    What a filter achieves that knows everything except the noise draws (the report
    prints it beside seed 002's Table 3):

    * linearized at the true positions: no linearization error, no divergence;
    * the fades and environment changes removed: the walk of ``seed`` drawn again with
      ``fade_prob = 0`` and no jumps (:func:`generate` consumes the same random numbers
      whatever those settings, so the AR(1) and skewed draws are the same);
    * the noise model exact: with ``ar_aware`` the AR(1) component is one state per AP,
      ``a_k = phi a_{k-1} + e_k`` with ``var e = (1 - phi^2) noise_db^2`` (stationary start),
      the skewed component white noise of its variance; both enter scaled by
      ``0.7 + 0.075 d`` at the true distance, as :func:`_noise` draws them.  Without
      ``ar_aware`` both components are taken as white (what a tracker without per-link
      bias states assumes);
    * a constant-velocity motion model, white acceleration of spectral density ``q``
      (m^2 s^-3): ``Q = q [[dt^3/3, dt^2/2], [dt^2/2, dt]]`` per axis (Bar-Shalom, Li and
      Kirubarajan 2001, sec. 6.2.2), started at the true position and velocity with unit
      variances.

    The measurement ``z_k - h(p_k) + H_k p_k = H_k x_k + noise`` is linear in the state at
    the truth ``p_k``; ``h`` the log-distance model of :func:`anchors_frame`.

    Returns
    -------
    estimates, truth : ``(walk_epochs, 2)`` positions, metres.
    """
    if not q >= 0:
        raise ValueError(f"q must be >= 0, got {q}")
    clean = WifiRoomConfig(**{**cfg.__dict__, "fade_prob": 0.0, "jumps": False})
    data = generate(clean, seed)
    an = data.anchors
    axy = an[["x", "y"]].to_numpy(float)
    A, n_exp = an["A"].to_numpy(float), an["n"].to_numpy(float)
    walk = data.measurements[data.measurements["tag"] == "walk"]
    z = walk.pivot(index="time", columns="anchor", values="rssi")[an["anchor"]].to_numpy()
    tr = data.truth[data.truth["tag"] == "walk"].sort_values("time")
    p = tr[["x", "y"]].to_numpy(float)
    dt = 1.0 / cfg.rate_hz
    M = len(axy)
    N = 4 + (M if ar_aware else 0)
    s_ar = cfg.noise_db
    s_sk = float(stats.skewnorm(SKEW_SHAPE, scale=0.8 * cfg.noise_db).std())
    F = np.eye(N)
    F[0, 2] = F[1, 3] = dt
    Q = np.zeros((N, N))
    for i in (0, 1):
        Q[i, i], Q[i, i + 2] = q * dt**3 / 3, q * dt**2 / 2
        Q[i + 2, i], Q[i + 2, i + 2] = q * dt**2 / 2, q * dt
    if ar_aware:
        F[4:, 4:] = cfg.ar_phi * np.eye(M)
        Q[4:, 4:] = (1.0 - cfg.ar_phi**2) * s_ar**2 * np.eye(M)
    x = np.zeros(N)
    x[:2] = p[0]
    if len(p) > 1:
        x[2:4] = (p[1] - p[0]) / dt
    P = np.diag([1.0] * 4 + [s_ar**2] * (N - 4))
    out = np.empty_like(p)
    for k in range(len(p)):
        if k:
            x = F @ x
            P = F @ P @ F.T + Q
        d = np.hypot(p[k, 0] - axy[:, 0], p[k, 1] - axy[:, 1])
        sc = 0.7 + 0.075 * d
        g = -10.0 * n_exp / (np.log(10.0) * d**2)
        H = np.zeros((M, N))
        H[:, :2] = g[:, None] * (p[k] - axy)
        y = z[k] - (A - 10.0 * n_exp * np.log10(d)) + H[:, :2] @ p[k]
        if ar_aware:
            H[:, 4:] = np.diag(sc)
            R = np.diag((sc * s_sk) ** 2)
        else:
            R = np.diag(sc**2 * (s_ar**2 + s_sk**2))
        S = H @ P @ H.T + R
        K = np.linalg.solve(S, H @ P).T
        x = x + K @ (y - H @ x)
        P = P - K @ S @ K.T
        out[k] = x[:2]
    return out, p


def add_arguments(p: argparse.ArgumentParser) -> None:
    from robustloc.options import (
        float_in,
        int_in,
    )

    d = WifiRoomConfig()
    p.add_argument("--samples-per-point", type=int_in(1, 10**6), default=d.samples_per_point,
                   help=f"scans at each of the 20 static points (default {d.samples_per_point})")
    p.add_argument("--walk-epochs", type=int_in(1, 10**7), default=d.walk_epochs,
                   help=f"epochs of the walk (default {d.walk_epochs})")
    p.add_argument("--rate-hz", type=float_in(1e-3, 1e4), default=d.rate_hz,
                   help=f"scan rate of the walk (default {d.rate_hz})")
    p.add_argument("--speed", type=float_in(0.01, 515.0), default=d.speed_mps,
                   help=f"walking speed m/s (default {d.speed_mps})")
    p.add_argument("--noise-db", type=float_in(0.0, 100.0), default=d.noise_db,
                   help=f"scale of the skewed RSSI noise, dB (default {d.noise_db})")
    p.add_argument("--fade-prob", type=float_in(0.0, 1.0), default=d.fade_prob,
                   help=f"probability of a 4-10 dB fade per scan (default {d.fade_prob})")
    p.add_argument("--jump-db", type=float_in(0.0, 100.0), default=None,
                   help=f"environment-change drop on the walk, dB (default {d.jump_db}; "
                        "refused with --no-jumps)")
    p.add_argument("--ar-phi", type=float_in(0.0, 0.999999), default=d.ar_phi,
                   help=f"AR(1) coefficient of the correlated noise per scan (default {d.ar_phi})")
    p.add_argument("--no-jumps", action="store_true", help="no environment changes")


def refuse_idle_options(args: argparse.Namespace) -> None:
    """``--jump-db`` with ``--no-jumps`` (no environment change to size) is refused with
    :class:`robustloc.errors.InputError`: it was taken and changed no byte of the files
    (the filter review)."""
    from robustloc.errors import InputError

    if getattr(args, "jump_db", None) is not None and getattr(args, "no_jumps", False):
        raise InputError("--jump-db does not apply to --no-jumps (no environment change "
                         "on the walk to size)")


def measurement_rows(cfg: WifiRoomConfig) -> tuple[int, int, int]:
    """Rows of ``measurements.csv`` from the static points and from the walk, and of
    ``survey.csv``, that :func:`generate` draws for ``cfg``."""
    m = len(AP_TABLE)
    return (cfg.samples_per_point * len(reference_points()) * m, cfg.walk_epochs * m,
            cfg.survey_samples * len(SURVEY_DISTANCES_M) * m)


def check_size(cfg: WifiRoomConfig, budget: float | None = None) -> None:
    """Refuse, before any work, a run whose memory (:data:`BYTES_PER_ROW` per row)
    exceeds the simulation budget (default
    :data:`robustloc.sim._output.MEMORY_BUDGET_BYTES`).

    The message names the option with the larger share of the rows, ``--samples-per-point``
    or ``--walk-epochs``, and its largest value within the budget, the other as given.

    Raises
    ------
    robustloc.errors.InputError
        The run does not fit (exit code 2 on the command line).
    """
    from robustloc.sim import _output

    static, walk, survey = measurement_rows(cfg)
    total = static + walk + survey
    need = total * BYTES_PER_ROW
    budget = _output.MEMORY_BUDGET_BYTES if budget is None else budget
    rows_max = budget / BYTES_PER_ROW
    m = len(AP_TABLE)
    if static >= walk:
        per = len(reference_points()) * m
        _output.check_memory(
            need, "--samples-per-point", cfg.samples_per_point,
            (rows_max - walk - survey) // per,
            f"{total} rows ({len(reference_points())} points x {m} APs x "
            f"{cfg.samples_per_point} scans, the walk's {walk} and the survey's {survey})",
            budget)
    else:
        _output.check_memory(
            need, "--walk-epochs", cfg.walk_epochs, (rows_max - static - survey) // m,
            f"{total} rows ({m} APs x {cfg.walk_epochs} walk epochs, the static points' "
            f"{static} and the survey's {survey})", budget)


def simulate(out_dir: Path, seed: int, args: argparse.Namespace) -> dict[str, Path]:
    """Write ``anchors.csv, measurements.csv, truth.csv, survey.csv`` into ``out_dir``.

    A run beyond the memory budget is refused first (:func:`check_size`); on a terminal
    a progress bar counts the rows written (not with ``args.quiet``).
    """
    from robustloc.sim._output import progress_bar, write_csv

    cfg = WifiRoomConfig(
        samples_per_point=getattr(args, "samples_per_point", 30),
        walk_epochs=getattr(args, "walk_epochs", 300),
        rate_hz=getattr(args, "rate_hz", 2.0),
        speed_mps=getattr(args, "speed", 1.0),
        noise_db=getattr(args, "noise_db", 1.5),
        fade_prob=getattr(args, "fade_prob", 0.03),
        jump_db=8.0 if getattr(args, "jump_db", None) is None else args.jump_db,
        jumps=not getattr(args, "no_jumps", False),
        ar_phi=getattr(args, "ar_phi", AR_PHI),
    )
    check_size(cfg)
    static, walk, survey = measurement_rows(cfg)
    n_truth = cfg.samples_per_point * len(reference_points()) + cfg.walk_epochs
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    paths = {}
    with progress_bar(args, len(AP_TABLE) + static + walk + n_truth + survey, " rows",
                      "simulate") as bar:
        data = generate(cfg, seed)
        for name, frame in (("anchors", data.anchors), ("measurements", data.measurements),
                            ("truth", data.truth), ("survey", data.survey)):
            paths[name] = write_csv(frame, out / f"{name}.csv", bar)
    return paths
