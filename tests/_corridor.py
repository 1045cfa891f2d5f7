"""A log beside nearly collinear anchors (the wifi-rtt-rss corridor's situation), shared by
the tests of the side prior (``locate --side-prior``) in every front end."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd

#: Four anchors within 0.6 m of the x axis (elongation 0.001: below the 0.05 gate).
NEAR_LINE = np.array([[0.0, 0.0], [10.0, 0.6], [20.0, -0.5], [30.0, 0.3]])
IDS = list("ABCD")


def side_log(seed: int = 3, n: int = 400, sides: tuple[float, ...] = (-1.0,),
             sigma_m: float = 0.1) -> tuple[np.ndarray, np.ndarray]:
    """``(truth (n, 2), ranges (n, 4))``: tags 1.5-4 m off the anchors' line on the given
    sides (one side each, in turn), along 2-28 m, ranges with ``sigma_m`` Gaussian
    noise."""
    rng = np.random.default_rng(seed)
    along = rng.uniform(2.0, 28.0, n)
    off = rng.uniform(1.5, 4.0, n) * np.resize(np.asarray(sides), n)
    truth = np.column_stack((along, off))
    r = np.linalg.norm(truth[:, None, :] - NEAR_LINE[None], axis=2)
    return truth, r + rng.normal(0.0, sigma_m, r.shape)


def side_frames(seed: int = 3, n: int = 400, tag: str = "t1"
                ) -> tuple[pd.DataFrame, pd.DataFrame, np.ndarray]:
    """The :func:`side_log` as contract frames: ``(measurements, anchors, truth)``, one
    epoch per second."""
    truth, r = side_log(seed, n)
    meas = pd.DataFrame({"time": np.repeat(np.arange(n, dtype=float), 4), "tag": tag,
                         "anchor": np.tile(IDS, n), "range": r.ravel()})
    anchors = pd.DataFrame({"anchor": IDS, "x": NEAR_LINE[:, 0], "y": NEAR_LINE[:, 1]})
    return meas, anchors, truth


def write_side_files(directory: Path, seed: int = 3, n: int = 400, tag: str = "t1"
                     ) -> np.ndarray:
    """Write :func:`side_frames` as ``measurements.csv`` and ``anchors.csv`` in
    ``directory``; returns the truth."""
    meas, anchors, truth = side_frames(seed, n, tag)
    meas.to_csv(Path(directory) / "measurements.csv", index=False)
    anchors.to_csv(Path(directory) / "anchors.csv", index=False)
    return truth
