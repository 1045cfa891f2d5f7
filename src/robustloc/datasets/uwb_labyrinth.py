"""Loader for the Labyrinth indoor UWB data set (libRSF ``datasets/Indoor_UWB``, CC BY-SA 4.0).

Text lines, whitespace separated, typed by their first word (``readme.txt`` of the data):

* ``range2 t range var ax ay id snr`` -- one UWB range (m) with its variance and the
  anchor's position on every line;
* ``odom2diff t v_right v_left v_y wheel_base cov_r cov_l cov_y`` -- differential-drive
  odometry; the body speed is ``(v_right + v_left) / 2`` and the yaw rate
  ``(v_right - v_left) / wheel_base``;
* ``point2 t x y ...`` -- ground truth.

Ranges arrive round robin, one anchor per 0.128 s: a linearized fix never has three
anchors at once, which is what tight coupling is for.  The whole file ships with the
package (``robustloc/data/uwb-labyrinth``).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd

from robustloc.errors import InputError
from robustloc.paths import PACKAGE_DATA, DataDir, data_folder

FOLDER = "uwb-labyrinth"
INPUT = "Indoor_UWB_Input.txt"
TRUTH = "Indoor_UWB_GT.txt"
_FIELDS = {"range2": 8, "odom2diff": 9, "point2": 8}


@dataclass(frozen=True)
class LabyrinthRun:
    """The run as contract frames plus odometry.

    Attributes
    ----------
    anchors : ``anchor, x, y``.
    measurements : ``time, tag, anchor, range, var``.
    odometry : ``time, speed_mps, yaw_rate_rps``.
    truth : ``time, tag, x, y``.
    skipped : always empty (a malformed line is an :class:`InputError`); kept for
        callers that read it.
    """

    anchors: pd.DataFrame
    measurements: pd.DataFrame
    odometry: pd.DataFrame
    truth: pd.DataFrame
    skipped: list[int]


def _parse(path: Path) -> tuple[dict[str, list[list[float]]], list[int]]:
    """The lines of each type.  A line of another type, too few fields or a value that is
    not a finite number is an error naming its line: the data set has none, and such lines
    were skipped without a word (a file cut mid-line, or bytes damaged, changed the
    report's figures; the reproduce review)."""
    try:
        text = path.read_text(encoding="ascii", errors="replace")
    except OSError as exc:
        raise InputError(f"cannot read: {exc.strerror or exc}", path) from None
    rows: dict[str, list[list[float]]] = {k: [] for k in _FIELDS}
    for lineno, line in enumerate(text.splitlines(), start=1):
        parts = line.split()
        if not parts:
            continue
        n = _FIELDS.get(parts[0])
        if n is None:
            raise InputError(f"not a line of this data set (its first word is one of "
                             f"{', '.join(_FIELDS)})", path, lineno)
        if len(parts) < n:
            raise InputError(f"{parts[0]}: {n} fields expected, {len(parts)} found",
                             path, lineno)
        try:
            vals = [float(v) for v in parts[1:n]]
        except ValueError:
            vals = [np.nan]
        if not np.all(np.isfinite(vals)):
            raise InputError(f"{parts[0]}: a field that is not a finite number", path, lineno)
        rows[parts[0]].append(vals)
    return rows, []


def load(data_dir: DataDir | None = None) -> LabyrinthRun:
    """Load the run from ``data_dir/uwb-labyrinth`` (default: the shipped copy)."""
    folder = (data_folder(data_dir) / FOLDER) if data_dir is not None else PACKAGE_DATA / FOLDER
    rows, skipped = _parse(folder / INPUT)
    gt, skipped_gt = _parse(folder / TRUTH)
    r = np.asarray(rows["range2"], dtype=float).reshape(-1, 7)
    if not len(r):
        raise InputError("no range2 line", folder / INPUT)
    ids = np.array([f"{int(i)}" for i in r[:, 5]], dtype=object)
    meas = pd.DataFrame(
        {"time": r[:, 0], "tag": "robot", "anchor": ids, "range": r[:, 1], "var": r[:, 2]}
    )
    anc = (
        pd.DataFrame({"anchor": ids, "x": r[:, 3], "y": r[:, 4]})
        .groupby("anchor", sort=True)
        .median()
        .reset_index()
    )
    o = np.asarray(rows["odom2diff"], dtype=float).reshape(-1, 8)
    odo = pd.DataFrame(
        {
            "time": o[:, 0],
            "speed_mps": 0.5 * (o[:, 1] + o[:, 2]),
            "yaw_rate_rps": (o[:, 1] - o[:, 2]) / np.where(o[:, 4] > 0, o[:, 4], np.nan),
        }
    )
    g = np.asarray(gt["point2"], dtype=float).reshape(-1, 7)
    truth = pd.DataFrame({"time": g[:, 0], "tag": "robot", "x": g[:, 1], "y": g[:, 2]})
    return LabyrinthRun(anc, meas, odo, truth, skipped + skipped_gt)
