"""How close the tracker comes to what is reachable on the seed-002 simulated walk.

Issue 11's walk target is a track RMS of at most 0.6x the raw snapshot ``nls`` RMS.  This
script prints, over several seeds of the ``wifi-room`` scenario (walk tag only), the ratio
to the raw ``nls`` walk RMS of:

* ``robustloc track`` as the report runs it (UKF, q = 3) and its RTS smoothing;
* the same with the CUSUM step detector on (``cusum_h``);
* the same with the stepped links held out exactly during their environment changes (the
  simulator's own step epochs: an *oracle hold*, what a perfect step detector could give);
* the same on the walk without the AR(1) correlation (``ar_phi = 0``, white noise);
* the oracle Kalman filters of :func:`robustloc.sim.wifi_room.oracle_walk_track` (the
  simulator's exact noise model, no fades or steps, linearized at the truth), with the
  AR(1) component as states and taken as white, over the process noise ``q``.

Measured 2026-12-02 (5 seeds; mean, min-max): track 0.897 (0.869-0.930), RTS 0.718;
CUSUM h = 3 / 5 / 10: 1.055 / 1.055 / 0.954; oracle hold 0.785 (0.723-0.912); white
noise 0.775; oracle KF with the AR(1) states 0.617 / 0.633 / 0.653 at q = 0.3 / 1 / 3
(0.518-0.714 over seeds and q), taken as white 0.691-0.709.  The 0.6x target lies below
the oracle's mean: reachable on a lucky seed by a filter that knows everything but the
noise draws, not by a causal tracker on average.

Usage::

    python benchmarks/bench_walk.py              # 5 seeds (about 10 s)
    python benchmarks/bench_walk.py --seeds 3
"""

from __future__ import annotations

import argparse
from dataclasses import replace

import numpy as np
import pandas as pd

from robustloc.estimators.ranging import Locator
from robustloc.io import to_epochs
from robustloc.models.pathloss import log_distance_arrays
from robustloc.sim.wifi_room import (
    JUMP_LENGTH,
    JUMPS,
    WifiRoomConfig,
    generate,
    oracle_walk_track,
)
from robustloc.tracking import Tracker

#: The report's walk settings (``reproduce/s60_tracks.py`` WALK_OPTS).
TRACK = {"q": 3.0, "filter": "ukf"}


def _rms(p: np.ndarray, truth: np.ndarray) -> float:
    return float(np.sqrt(np.nanmean(np.sum((p - truth) ** 2, axis=1))))


def _walk(cfg: WifiRoomConfig, seed: int):
    data = generate(cfg, seed)
    an = data.anchors
    ids = [str(a) for a in an["anchor"]]
    m = data.measurements
    ep = to_epochs(m[m["tag"] == "walk"], ids)
    truth = data.truth.set_index(["time", "tag"]).loc[list(zip(ep.time, ep.tag))]
    A, n = log_distance_arrays(an)
    nls = Locator("nls").solve(an[["x", "y"]].to_numpy(float), ep.values, "rssi", A=A,
                               n=n).position
    return an, ids, ep, truth[["x", "y"]].to_numpy(float), nls


def _track(an, ep, truth, **opts) -> tuple[float, float]:
    trk = Tracker(an, record=True, **{**TRACK, **opts})
    rows = trk.step(ep)
    xs, _ = trk.smoothed(len(rows))
    return _rms(rows[["x", "y"]].to_numpy(float), truth), _rms(xs[:, :2], truth)


def run_seed(seed: int, qs: tuple[float, ...]) -> dict[str, float]:
    an, ids, ep, truth, nls = _walk(WifiRoomConfig(), seed)
    raw = _rms(nls, truth)
    out: dict[str, float] = {}
    out["track"], out["track + RTS"] = (v / raw for v in _track(an, ep, truth))
    for h in (3.0, 5.0, 10.0):
        out[f"track, CUSUM h = {h:g}"] = _track(an, ep, truth, cusum_h=h)[0] / raw
    held = ep.values.copy()
    for epoch, ap in JUMPS:
        held[epoch: epoch + JUMP_LENGTH, ids.index(ap)] = np.nan
    out["track, oracle hold of the stepped links"] = _track(
        an, replace(ep, values=held), truth)[0] / raw
    an_w, _, ep_w, truth_w, nls_w = _walk(WifiRoomConfig(ar_phi=0.0), seed)
    out["track, white noise (ar_phi = 0; ratio to its own nls)"] = (
        _track(an_w, ep_w, truth_w)[0] / _rms(nls_w, truth_w))
    for q in qs:
        for aware, label in ((True, "AR(1) as states"), (False, "noise as white")):
            est, tr = oracle_walk_track(WifiRoomConfig(), seed, q, ar_aware=aware)
            out[f"oracle KF, {label}, q = {q:g}"] = _rms(est, tr) / raw
    out["raw nls RMS (m)"] = raw
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--seeds", type=int, default=5, help="seeds 0 .. N-1 (default 5)")
    p.add_argument("--q", default="0.3,1,3", help="oracle process noises (default 0.3,1,3)")
    a = p.parse_args(argv)
    if a.seeds < 1:
        p.error("--seeds must be >= 1")
    try:
        qs = tuple(float(v) for v in a.q.split(","))
    except ValueError:
        p.error(f"--q: not a comma list of numbers: {a.q!r}")
    if not all(np.isfinite(q) and q >= 0 for q in qs):
        p.error("--q: process noises must be finite and >= 0")
    res = pd.DataFrame([run_seed(s, qs) for s in range(a.seeds)])
    tab = pd.DataFrame({"mean over seeds": res.mean(), "min": res.min(), "max": res.max()})
    print(f"seed-002 walk, {a.seeds} seeds: RMS over the raw nls walk RMS (target 0.6)")
    with pd.option_context("display.width", 200, "display.float_format", "{:.3f}".format):
        print(tab.to_string())
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
