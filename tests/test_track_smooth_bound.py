"""The smoothed rows' protection level (``track --smooth`` / ``--fixed-lag``).

A smoothed row's ``hpl`` is its forward row's plus the distance smoothing moved the
position: wherever the forward bound covers the forward position, the triangle
inequality carries it to the smoothed one.  The smoothed covariance's own ``k sigma``
does not, where the errors are correlated in time (a receiver's standing offset, slow
fading): on the shipped ble-tetam walk the previous rule (the forward slope term plus
``k sigma`` of the smoothed covariance) left 7 of its 84 rows beyond their bound.
"""

from __future__ import annotations

import numpy as np
import pytest

from robustloc.datasets import ble_tetam as bt
from robustloc.io import to_epochs
from robustloc.models.calibration import calibrate_pathloss
from robustloc.pipelines.track import apply_smoother
from robustloc.tracking import Tracker


@pytest.fixture(scope="module")
def walk():
    src = bt.resolve(None)  # the shipped excerpt
    an = calibrate_pathloss(bt.load_survey_means(src.path),
                            "log-distance").apply_to_anchors(bt.load_anchors(src.path))
    meas, truth = bt.load_track("rectangular_without_rotation", src.path)
    ep = to_epochs(meas, [str(a) for a in an["anchor"]])
    # the report's settings for ble-tetam (section s60_tracks: q = 0.01)
    trk = Tracker(an, tag_height=float(truth["z"].mean()), record=True, q=0.01)
    rows = trk.step(ep)
    txy = truth.set_index("time").loc[ep.time, ["x", "y"]].to_numpy(float)
    return trk, rows, txy


@pytest.mark.parametrize("lag", [None, 3])
def test_smoothed_bound_covers_where_the_forward_bound_does(walk, lag):
    trk, rows, txy = walk
    sm = apply_smoother(trk, rows, lag)
    ef = np.hypot(*(rows[["x", "y"]].to_numpy(float) - txy).T)
    es = np.hypot(*(sm[["x", "y"]].to_numpy(float) - txy).T)
    hf, hs = rows["hpl"].to_numpy(float), sm["hpl"].to_numpy(float)
    assert np.isfinite(es).all() and (es < ef).mean() > 0.5  # smoothing does help here
    covered = ef <= hf
    assert covered.mean() > 0.95  # the forward pass: 1 of 84 rows beyond its bound
    # wherever the forward bound holds, the smoothed one holds (a guarantee, no tolerance)
    bad = covered & ~(es <= hs)
    assert not bad.any(), (f"{bad.sum()} rows beyond their smoothed hpl: errors "
                           f"{es[bad].round(2)}, hpl {hs[bad].round(2)}")
    # and the bound is the forward one moved by the smoother, not an inflated one
    moved = np.hypot(*(sm[["x", "y"]].to_numpy(float) - rows[["x", "y"]].to_numpy(float)).T)
    np.testing.assert_allclose(hs, hf + moved, rtol=1e-12)
