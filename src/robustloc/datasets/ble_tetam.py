"""Loader for the *Position-Annotated BLE RSSI Dataset* ("ble-tetam").

Source: philotuxo/Position-Annotated-BLE-RSSI-Dataset @77474b69 (CC0-1.0), Daniş et al.,
Pervasive and Mobile Computing 81 (2022).  Twelve fixed BLE receivers ("sensors", the
*anchors* here) hear one moving beacon (the *tag*) in an 18 m x 18 m area; every RSSI sample
of the track files is labelled with the beacon's position from an AR tracking system.

What the loaders return (contract frames, see ``docs/design.md``):

* :func:`load_anchors`: ``anchor, x, y, z, mac``; the anchor id is the sensor alias of
  ``cnf/tetam.dev`` (``"sensor10"`` ... ``"sensor42"``), never the MAC.
* :func:`load_track`: ``(measurements, truth)``.  The receivers report asynchronously
  (each about 2 samples/s), so samples are binned into epochs: windows of ``window_s``
  seconds (default 1 s) starting at the track's first sample; for each window and sensor
  one row with the mean (or median) RSSI of the samples it heard in that window
  (``n_samples`` says how many).  ``time`` is the window centre in seconds since the first
  sample of the track (``attrs["t0_unix_s"]`` keeps the Unix time of that sample), ``tag``
  is the track name.  The truth of a window is the mean of the labelled positions of all
  samples in it (any sensor).  Windows without any sample produce no epoch.  With
  ``window_s=None`` every raw sample is its own row (one anchor per epoch, for filters).
* :func:`load_histograms`: a calibration survey ``anchor, distance, rssi, weight`` built from
  the static fingerprint histograms ``hst/set_1/tetam_multi_rssi.hst`` (81 points x 12
  sensors, normalized histograms over integer RSSI; the ``Bins`` line lists 81 *edges*, the
  80 probabilities belong to the left edges -100 ... -21 dBm, checked against the raw logs).
  One row per non-empty bin, ``weight`` = probability.  :func:`load_survey_means` gives one
  row per point and sensor with the mean RSSI: a log-distance fit on it gives
  ``A = -61.43 dBm, n = 1.478``, residual s.d. 4.49 dB (the histogram-weighted fit has the
  same ``A, n``).  ``distance`` is the 3-D distance point-sensor in metres.
* :func:`load_static`: the raw 30-minute logs at the 3 static points of ``hst/set_1``
  (``sensorNN_x_y_z.mbd``, one file per sensor, overlapping in time), binned like a track.

When ``data_dir`` is None the full shared data (:func:`robustloc.paths.default_data_dir`)
is used if present, else the small excerpt shipped in ``robustloc/data/ble-tetam``; every
frame says which in ``frame.attrs["source"]`` (``"full"`` or ``"excerpt"``) and
``frame.attrs["path"]``, and :func:`resolve` returns it directly.
"""

from __future__ import annotations

import ast
import gzip
import json
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np
import pandas as pd

from robustloc import paths
from robustloc._arrays import to_number
from robustloc.errors import InputError
from robustloc.paths import PACKAGE_DATA, DataDir, data_folder

NAME = "ble-tetam"
#: Beacon MAC of the single transmitter in the data set.
BEACON_MAC = "e78f135624ce"
_TRACK_SUFFIX = "_all_sensors.mbd"
_STATIC_RE = re.compile(r"^(sensor\d+)_([-\d.]+)_([-\d.]+)_([-\d.]+)\.mbd(\.gz)?$")


# ---------------------------------------------------------------------------------------
# where the data is


@dataclass(frozen=True)
class DatasetSource:
    """Where a data set was loaded from.

    Attributes
    ----------
    path : Path
        The data set's own folder (e.g. ``.../shared/data/ble-tetam``).
    kind : str
        ``"full"`` (the shared data or a user folder) or ``"excerpt"`` (shipped in the
        package, a subset: see its ``SOURCE.md``).
    note : str
        Why the excerpt was used when a data folder was given (empty otherwise).
    """

    path: Path
    kind: str
    note: str = ""


def resolve_dataset(name: str, marker: str, data_dir: DataDir | None = None) -> DatasetSource:
    """Find the folder of data set ``name`` (shared by the dataset loaders).

    Parameters
    ----------
    name : str
        Folder name of the data set, e.g. ``"ble-tetam"``.
    marker : str
        A relative path that must exist inside the data set folder.
    data_dir : str, PathLike or Traversable, optional
        Either the root holding ``name/`` (like ``../shared/data``) or the data set folder
        itself.  None: the shared data if present, else the shipped excerpt.  An existing
        root without ``name/`` also falls back to the excerpt (``kind="excerpt"`` and a
        ``note`` say so); a missing folder, or a ``name/`` folder without ``marker``, is an
        :class:`InputError`.
    """
    if data_dir is None:
        root = paths.default_data_dir()
        if root is not None and (root / name / marker).exists():
            return DatasetSource(Path(root / name).resolve(), "full")
        pkg = PACKAGE_DATA / name
        if (pkg / marker).exists() or _gz(pkg / marker).exists():
            return DatasetSource(pkg, "excerpt")
        raise InputError(f"data set {name!r} not found: no shared data and no excerpt", pkg)
    d = data_folder(data_dir)
    for cand in (d / name, d):
        if (cand / marker).exists() or _gz(cand / marker).exists():
            cand = cand.resolve()
            kind = "excerpt" if cand == PACKAGE_DATA / name else "full"
            return DatasetSource(cand, kind)
    pkg = PACKAGE_DATA / name
    if (
        d.is_dir()
        and not (d / name).exists()
        and ((pkg / marker).exists() or _gz(pkg / marker).exists())
    ):
        return DatasetSource(pkg, "excerpt", f"{name} not in {d}: using the shipped excerpt")
    raise InputError(f"data set {name!r} not found (looked for {marker})", d)


def _gz(p: Path) -> Path:
    return p.with_name(p.name + ".gz")


def _existing(p: Path) -> Path:
    """``p`` or its gzip-compressed twin (the excerpts are gzip-compressed)."""
    if p.exists():
        return p
    if _gz(p).exists():
        return _gz(p)
    raise InputError("file not found", p)


def _read_text(p: Path) -> str:
    p = _existing(p)
    try:
        if p.suffix == ".gz":
            with gzip.open(p, "rt", encoding="utf-8") as f:
                return f.read()
        return p.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError, EOFError) as e:
        raise InputError(f"cannot read file: {e}", p) from None


def resolve(data_dir: DataDir | None = None) -> DatasetSource:
    """The ble-tetam folder used for ``data_dir`` (see module docstring)."""
    return resolve_dataset(NAME, "cnf/tetam.dev", data_dir)


def _tag(df: pd.DataFrame, src: DatasetSource, **more: object) -> pd.DataFrame:
    df.attrs["dataset"] = NAME
    df.attrs["source"] = src.kind
    df.attrs["path"] = str(src.path)
    df.attrs.update(more)
    return df


# ---------------------------------------------------------------------------------------
# devices


def _parse_dict_line(text: str, key: str, path: Path) -> dict:
    for i, line in enumerate(text.splitlines(), start=1):
        if line.startswith(key + ":"):
            body = line.split(":", 1)[1]
            try:
                return json.loads(body)
            except json.JSONDecodeError:
                try:
                    return ast.literal_eval(body)
                except (ValueError, SyntaxError) as e:
                    raise InputError(f"malformed {key} line: {e}", path, i) from None
    raise InputError(f"no line starting with {key!r}", path)


def _dongles(text: str, path: Path) -> pd.DataFrame:
    raw = _parse_dict_line(text, "Dongles", path)
    rows = []
    for mac, spec in raw.items():
        try:
            (x, y, z), _color, alias = spec
            rows.append((str(alias), float(x), float(y), float(z), str(mac).lower()))
        except (TypeError, ValueError):
            raise InputError(f"malformed sensor entry for {mac!r}", path) from None
    df = pd.DataFrame(rows, columns=["anchor", "x", "y", "z", "mac"])
    if df["anchor"].duplicated().any() or df["mac"].duplicated().any():
        raise InputError("duplicate sensor alias or MAC", path)
    return df.sort_values("anchor", kind="stable").reset_index(drop=True)


def load_anchors(data_dir: DataDir | None = None) -> pd.DataFrame:
    """The 12 receivers as an anchors frame ``anchor, x, y, z, mac`` (metres).

    Positions from ``cnf/tetam.dev``; ``anchor`` is the sensor alias (``"sensor10"``).
    """
    src = resolve(data_dir)
    p = src.path / "cnf" / "tetam.dev"
    return _tag(_dongles(_read_text(p), p), src)


def _mac_to_anchor(anchors: pd.DataFrame) -> dict[str, str]:
    return dict(zip(anchors["mac"], anchors["anchor"]))


# ---------------------------------------------------------------------------------------
# raw sample logs (.mbd)


def _read_mbd(path: Path, with_position: bool) -> pd.DataFrame:
    """Read an ``.mbd`` log: ``timestamp, sensorMAC, beaconMAC, rssi[, x, y, z, r11..r33]``.

    MACs are read as strings (``000000000101`` must not become the integer 101).
    """
    path = _existing(path)
    ncol = 16 if with_position else 4
    names = ["t_unix_s", "mac", "beacon", "rssi", "x", "y", "z"][: 7 if with_position else 4]
    try:
        df = pd.read_csv(
            path,
            header=None,
            usecols=range(len(names)),
            names=names,
            dtype={"mac": str, "beacon": str},
            compression="infer",
            skip_blank_lines=True,
        )
    except UnicodeDecodeError:
        # (pandas' message names a byte of its buffer, not of the file, and no line)
        from robustloc.io.tables import _decode_error, _format

        raise _decode_error(path, path, _format(path, path)) from None
    except (pd.errors.ParserError, ValueError, OSError, EOFError) as e:
        msg = f"malformed log ({ncol} comma-separated fields expected): {e}"
        raise InputError(msg, path) from None
    if df.empty:
        raise InputError("empty log", path)
    for c in [c for c in names if c not in ("mac", "beacon")]:
        num = to_number(df[c])
        bad = ~np.isfinite(num.to_numpy(dtype=float))
        if bad.any():
            i = int(np.flatnonzero(bad)[0])
            v = df[c].iloc[i]
            shown = f"{float(v):g}" if isinstance(v, float | np.floating) else repr(str(v))
            raise InputError(f"non-numeric or non-finite {c}: {shown}", path, i + 1)
        df[c] = num.astype(float)
    if df["mac"].isna().any():
        i = int(np.flatnonzero(df["mac"].isna().to_numpy())[0])
        raise InputError("missing sensor MAC", path, i + 1)
    df["mac"] = df["mac"].str.strip().str.lower()
    return df


def _check_binning(window_s: float | None, statistic: str) -> None:
    if statistic not in ("mean", "median"):
        raise ValueError(f"statistic must be 'mean' or 'median', got {statistic!r}")
    if window_s is not None and not (np.isfinite(window_s) and window_s > 0):
        raise ValueError(f"window_s must be a positive number or None, got {window_s}")


def _samples_to_frames(
    df: pd.DataFrame,
    anchors: pd.DataFrame,
    tag: str,
    path: Path,
    window_s: float | None,
    statistic: str,
    truth_xyz: tuple[float, float, float] | None = None,
) -> tuple[pd.DataFrame, pd.DataFrame, dict[str, float | int]]:
    """Bin raw samples (with ``x, y, z`` columns unless ``truth_xyz``) into epochs.

    Samples from a sensor not in ``cnf/tetam.dev`` are skipped and counted
    (``n_skipped_unknown_sensor`` in the returned info, copied to ``frame.attrs``).
    """
    m2a = _mac_to_anchor(anchors)
    anchor = df["mac"].map(m2a)
    unknown = anchor.isna()
    n_unknown = int(unknown.sum())
    if n_unknown == len(df):
        raise InputError(f"no sample comes from a known sensor (e.g. {df['mac'].iloc[0]})", path)
    df = df.loc[~unknown].assign(anchor=anchor[~unknown])
    df = df.sort_values("t_unix_s", kind="stable").reset_index(drop=True)
    t0 = float(df["t_unix_s"].iloc[0])
    t = df["t_unix_s"].to_numpy() - t0
    if truth_xyz is not None:
        df = df.assign(x=truth_xyz[0], y=truth_xyz[1], z=truth_xyz[2])
    if window_s is None:
        df = df.assign(time=t)
        meas = df[["time", "anchor", "rssi"]].assign(n_samples=1)
        truth = df.groupby("time", sort=True)[["x", "y", "z"]].mean().reset_index()
    else:
        k = np.floor(t / window_s).astype(np.int64)
        df = df.assign(time=(k + 0.5) * window_s)
        g = df.groupby(["time", "anchor"], sort=True)["rssi"]
        meas = g.agg(statistic).rename("rssi").to_frame()
        meas["n_samples"] = g.size()
        meas = meas.reset_index()
        truth = df.groupby("time", sort=True)[["x", "y", "z"]].mean().reset_index()
    if truth_xyz is not None:  # exact, not a mean of copies
        truth[["x", "y", "z"]] = np.broadcast_to(truth_xyz, (len(truth), 3))
    meas.insert(1, "tag", tag)
    truth.insert(1, "tag", tag)
    meas = meas[["time", "tag", "anchor", "rssi", "n_samples"]].reset_index(drop=True)
    info = {"t0_unix_s": t0, "n_skipped_unknown_sensor": n_unknown}
    return meas, truth.reset_index(drop=True), info


# ---------------------------------------------------------------------------------------
# tracks


#: The upstream data set's walks (``trk/<name>_all_sensors.mbd``).
UPSTREAM_TRACKS = ("rectangular_without_rotation", "straight_01", "straight_02",
                   "straight_03", "zigzagging_without_rotation")


def tracks_note(data_dir: DataDir | None = None) -> str:
    """A note naming the upstream walks a full data folder lacks (``""``: none, or the
    shipped excerpt, which holds two of them): a deleted walk changed a report's figures
    without a word (the reproduce review)."""
    src = resolve(data_dir)
    if src.kind != "full":
        return ""
    missing = sorted(set(UPSTREAM_TRACKS) - set(list_tracks(src.path)))
    if not missing:
        return ""
    return (f"{NAME}: {len(UPSTREAM_TRACKS) - len(missing)} of the upstream's "
            f"{len(UPSTREAM_TRACKS)} walks in {src.path / 'trk'} (missing: "
            f"{', '.join(missing)}); the figures cover those present")


def list_tracks(data_dir: DataDir | None = None) -> list[str]:
    """Names of the available tracks (e.g. ``"straight_01"``), sorted.

    Raises
    ------
    InputError
        No track log in the data set's ``trk/`` folder (or no such folder): every user
        of the tracks had a traceback on an empty list (the reproduce review).
    """
    src = resolve(data_dir)
    d = src.path / "trk"
    names = {
        p.name.split(_TRACK_SUFFIX)[0]
        for p in (d.iterdir() if d.is_dir() else ())
        if p.name.endswith(_TRACK_SUFFIX) or p.name.endswith(_TRACK_SUFFIX + ".gz")
    }
    if not names:
        raise InputError(f"no track log (*{_TRACK_SUFFIX}) in this folder", d)
    return sorted(names)


def load_track(
    name: str,
    data_dir: DataDir | None = None,
    *,
    window_s: float | None = 1.0,
    statistic: Literal["mean", "median"] = "mean",
) -> tuple[pd.DataFrame, pd.DataFrame]:
    """Load one trajectory as contract ``(measurements, truth)`` frames.

    Parameters
    ----------
    name : str
        Track name from :func:`list_tracks` (``trk/<name>_all_sensors.mbd``).
    data_dir : str, PathLike or Traversable, optional
        Shared data root or the data set folder; None: shared data, else the excerpt.
    window_s : float or None
        Epoch length in seconds (see the module docstring); None: one row per raw sample.
    statistic : {"mean", "median"}
        How the RSSI samples of one sensor in one window are combined.

    Returns
    -------
    measurements : DataFrame
        ``time, tag, anchor, rssi, n_samples``; ``time`` in s since the first sample.
    truth : DataFrame
        ``time, tag, x, y, z`` (metres), one row per epoch.
    """
    _check_binning(window_s, statistic)
    src = resolve(data_dir)
    tracks = list_tracks(src.path)
    if name not in tracks:
        raise InputError(f"unknown track {name!r}; available: {', '.join(tracks)}", src.path)
    anchors = load_anchors(src.path)
    path = src.path / "trk" / f"{name}{_TRACK_SUFFIX}"
    raw = _read_mbd(path, with_position=True)
    meas, truth, info = _samples_to_frames(raw, anchors, name, path, window_s, statistic)
    more = {**info, "window_s": window_s, "statistic": statistic}
    return _tag(meas, src, **more), _tag(truth, src, **more)


# ---------------------------------------------------------------------------------------
# static logs


def list_static_points(data_dir: DataDir | None = None) -> list[str]:
    """Static points with raw logs in ``hst/set_1`` (``"10.36_10.95_1.90"``); empty when
    only the excerpt is available (the raw logs are 6.5 MB and not shipped)."""
    src = resolve(data_dir)
    d = src.path / "hst" / "set_1"
    if not d.is_dir():
        return []
    pts = set()
    for p in d.iterdir():
        m = _STATIC_RE.match(p.name)
        if m:
            pts.add(f"{m.group(2)}_{m.group(3)}_{m.group(4)}")
    return sorted(pts)


def load_static(
    point: str,
    data_dir: DataDir | None = None,
    *,
    window_s: float | None = 1.0,
    statistic: Literal["mean", "median"] = "mean",
) -> tuple[pd.DataFrame, pd.DataFrame]:
    """Raw 30-minute logs at one static point, as ``(measurements, truth)`` like a track.

    The 12 per-sensor files ``hst/set_1/sensorNN_<point>.mbd`` overlap in time and are
    merged; the truth is the point's coordinates (from the file name) in every epoch.
    ``tag`` is ``"static_<point>"``.
    """
    _check_binning(window_s, statistic)
    src = resolve(data_dir)
    points = list_static_points(src.path)
    if point not in points:
        raise InputError(
            f"unknown static point {point!r}; available: {', '.join(points) or 'none'}",
            src.path / "hst" / "set_1",
        )
    anchors = load_anchors(src.path)
    files = sorted(
        p
        for p in (src.path / "hst" / "set_1").iterdir()
        if (m := _STATIC_RE.match(p.name)) and f"{m.group(2)}_{m.group(3)}_{m.group(4)}" == point
    )
    raw = pd.concat([_read_mbd(p, with_position=False) for p in files], ignore_index=True)
    xyz = tuple(float(v) for v in point.split("_"))
    meas, truth, info = _samples_to_frames(
        raw, anchors, f"static_{point}", files[0].parent, window_s, statistic, xyz
    )
    more = {**info, "window_s": window_s, "statistic": statistic}
    return _tag(meas, src, **more), _tag(truth, src, **more)


# ---------------------------------------------------------------------------------------
# fingerprint histograms -> calibration survey


@dataclass(frozen=True)
class _Histograms:
    points: np.ndarray  # (P, 3)
    anchor: np.ndarray  # (K,) anchor id per histogram
    point_index: np.ndarray  # (K,)
    distance_m: np.ndarray  # (K,)
    rssi_dbm: np.ndarray  # (B,) bin values
    prob: np.ndarray  # (K, B)


def _read_histograms(src: DatasetSource, set_name: str) -> _Histograms:
    path = src.path / "hst" / set_name / "tetam_multi_rssi.hst"
    text = _read_text(path)
    try:
        edges = np.asarray(_parse_dict_line(text, "Bins", path), dtype=float)
    except (TypeError, ValueError):
        raise InputError("Bins line is not a list of numbers", path) from None
    dongles = _dongles(text, path)
    mac2a = _mac_to_anchor(dongles)
    pos = {a: np.array([x, y, z]) for a, x, y, z in dongles[["anchor", "x", "y", "z"]].values}
    fp = _parse_dict_line(text, "Fingerprints", path)
    pts, anchor, pidx, prob = [], [], [], []
    for i, (key, sensors) in enumerate(fp.items()):
        try:
            xyz = np.asarray(ast.literal_eval(key), dtype=float).reshape(3)
        except (ValueError, SyntaxError, TypeError):
            raise InputError(f"malformed fingerprint position {key!r}", path) from None
        pts.append(xyz)
        for mac, beacons in sensors.items():
            a = mac2a.get(str(mac).lower())
            if a is None:
                raise InputError(f"unknown sensor MAC {mac!r} in fingerprint {key}", path)
            for _b, h in beacons.items():
                h = np.asarray(h, dtype=float)
                if h.ndim != 1 or h.size not in (edges.size, edges.size - 1):
                    raise InputError(f"histogram length {h.size} at {key}/{a}", path)
                if not np.all(np.isfinite(h)) or (h < 0).any():
                    raise InputError(f"negative or non-finite probability at {key}/{a}", path)
                if h.sum() <= 0:
                    continue
                anchor.append(a)
                pidx.append(i)
                prob.append(h[: edges.size - 1] / h.sum())
    if not prob:
        raise InputError("no histograms", path)
    points = np.array(pts)
    anchor_arr = np.array(anchor, dtype=object)
    pidx_arr = np.array(pidx)
    apos = np.stack([pos[a] for a in anchor_arr])
    dist = np.linalg.norm(points[pidx_arr] - apos, axis=1)
    # 81 edges, 80 probabilities: bin i holds the integer RSSI equal to its left edge
    # (checked: the histograms equal the relative frequencies of the raw logs' values).
    return _Histograms(points, anchor_arr, pidx_arr, dist, edges[:-1], np.array(prob))


def load_histograms(
    data_dir: DataDir | None = None,
    *,
    set_name: str = "set_1",
    expand_to: int | None = None,
) -> pd.DataFrame:
    """Calibration survey from the static RSSI histograms (81 points x 12 sensors).

    Parameters
    ----------
    set_name : str
        Fingerprint set folder under ``hst/`` (only ``set_1`` is in the shared copy).
    expand_to : int, optional
        The file stores normalized histograms (no counts).  None: one row per non-empty
        bin with ``weight`` = probability (weights of one histogram sum to 1).  An integer
        ``N``: each histogram is expanded to about ``N`` samples, one row per sample
        (``weight`` 1), rounding ``p * N``; use this for tools that take plain samples.

    Returns
    -------
    DataFrame
        ``anchor, distance, rssi, weight, point, x, y, z``: ``distance`` is the 3-D
        point-sensor distance in metres, ``point`` the fingerprint index, ``x, y, z`` its
        position.
    """
    src = resolve(data_dir)
    h = _read_histograms(src, set_name)
    k, b = np.nonzero(h.prob)
    w = h.prob[k, b]
    if expand_to is not None:
        if expand_to < 1:
            raise ValueError(f"expand_to must be >= 1, got {expand_to}")
        counts = np.rint(w * expand_to).astype(np.int64)
        k, b = np.repeat(k, counts), np.repeat(b, counts)
        w = np.ones(k.size)
    p = h.point_index[k]
    df = pd.DataFrame(
        {
            "anchor": h.anchor[k],
            "distance": h.distance_m[k],
            "rssi": h.rssi_dbm[b],
            "weight": w,
            "point": p,
            "x": h.points[p, 0],
            "y": h.points[p, 1],
            "z": h.points[p, 2],
        }
    )
    return _tag(df, src, set_name=set_name)


def load_survey_means(
    data_dir: DataDir | None = None, *, set_name: str = "set_1"
) -> pd.DataFrame:
    """One survey row per static point and sensor: the histogram's mean RSSI.

    Columns ``anchor, distance, rssi, rssi_std, point, x, y, z``.  A log-distance least-squares
    fit (seed 000, eq. (1)) pooled over these 972 rows gives ``A = -61.43 dBm``,
    ``n = 1.478`` and a residual standard deviation of 4.49 dB.
    """
    src = resolve(data_dir)
    h = _read_histograms(src, set_name)
    mean = h.prob @ h.rssi_dbm
    std = np.sqrt(np.maximum(h.prob @ h.rssi_dbm**2 - mean**2, 0.0))
    p = h.point_index
    df = pd.DataFrame(
        {
            "anchor": h.anchor,
            "distance": h.distance_m,
            "rssi": mean,
            "rssi_std": std,
            "point": p,
            "x": h.points[p, 0],
            "y": h.points[p, 1],
            "z": h.points[p, 2],
        }
    )
    return _tag(df, src, set_name=set_name)
