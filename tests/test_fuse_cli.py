"""Options of the ``fuse`` command refused as user errors (exit 2, ``error: FILE:LINE: what``).

Every case runs the real command line in-process (``robustloc.cli.main``) on the simulated
cart of ``robustloc simulate uwb-cart`` (3 anchors ``anchor, x, y`` without ``z``, 51 epochs);
the robust update's covariance is checked on the shipped uwb-dwm1001 LOS excerpt.
"""

from __future__ import annotations

import pandas as pd

from robustloc.cli import main


def test_tag_height_without_anchor_z_is_refused(cart, tmp_path, capsys):
    anchors = cart / "anchors.csv"
    assert "z" not in pd.read_csv(anchors).columns
    out = tmp_path / "track.csv"
    rc = main(["fuse", "--ranges", str(cart / "measurements.csv"), "--anchors", str(anchors),
               "--tag-height", "1.0", "-o", str(out)])
    err = capsys.readouterr().err
    # the slant-range correction needs the anchors' heights: it was silently ignored
    assert rc == 2
    assert err.startswith(f"error: {anchors}:1: ")
    assert "--tag-height" in err and "z column" in err
    assert "Traceback" not in err
    assert not out.exists()  # refused before anything is written


def test_tag_height_with_anchor_z_corrects_the_slant_ranges(cart, tmp_path, capsys):
    a = pd.read_csv(cart / "anchors.csv").assign(z=2.5)
    anchors = tmp_path / "anchors.csv"
    a.to_csv(anchors, index=False)
    tracks = []
    for extra in ([], ["--tag-height", "1.0"]):
        out = tmp_path / f"track{len(tracks)}.csv"
        rc = main(["fuse", "--ranges", str(cart / "measurements.csv"), "--anchors",
                   str(anchors), "-o", str(out), *extra])
        assert rc == 0, capsys.readouterr().err
        tracks.append(pd.read_csv(out))
    assert len(tracks[0]) == len(tracks[1]) == 51  # every epoch a row
    # a 1.5 m height difference shortens every range: the positions move
    assert not tracks[0][["x", "y"]].equals(tracks[1][["x", "y"]])


def test_one_gps_log_and_several_tags(cart, tmp_path, capsys):
    """One NMEA log, the ranges of two tags: the GPS speed and course went into both
    tracks without a word (the CLI review).  Now a warning says so, and `--nmea-tag`
    names the tag that carries the receiver: the other tag is tracked from its ranges
    alone (its rows' source is `uwb`), the named tag's rows are those of a run on its
    ranges alone."""
    m = pd.read_csv(cart / "measurements.csv")
    two = tmp_path / "two.csv"
    pd.concat([m, m.assign(tag="other")]).to_csv(two, index=False)
    base = ["fuse", "--ranges", str(two), "--anchors", str(cart / "anchors.csv"),
            "--nmea", str(cart / "gps.nmea")]
    assert main([*base, "-o", str(tmp_path / "all.csv")]) == 0
    assert "one GPS log and 2 tags" in capsys.readouterr().err
    tag = str(m["tag"].iloc[0])
    assert main([*base, "--nmea-tag", tag, "-o", str(tmp_path / "one.csv")]) == 0
    assert "one GPS log" not in capsys.readouterr().err
    every, one = pd.read_csv(tmp_path / "all.csv"), pd.read_csv(tmp_path / "one.csv")
    assert set(every["source"]) == {"uwb+gps"}
    assert set(one.loc[one["tag"] == "other", "source"]) == {"uwb"}
    assert set(one.loc[one["tag"] == tag, "source"]) == {"uwb+gps"}
    alone = tmp_path / "alone.csv"
    assert main(["fuse", "--ranges", str(cart / "measurements.csv"), "--anchors",
                 str(cart / "anchors.csv"), "--nmea", str(cart / "gps.nmea"), "-o",
                 str(alone)]) == 0
    pd.testing.assert_frame_equal(one[one["tag"] == tag].reset_index(drop=True),
                                  pd.read_csv(alone))
    assert main([*base, "--nmea-tag", "nope", "-o", str(tmp_path / "x.csv")]) == 2
    assert "--nmea-tag nope: no such tag" in capsys.readouterr().err


def test_the_filter_default_follows_the_motion_model(cart, tmp_path, capsys):
    """Without ``--filter``, ``--motion cv`` runs the EKF and ``--motion ca`` the UKF
    (seed 001's pairs).  The EKF with CA linearized the GPS course at a predicted velocity
    whose spread exceeds the cart's 0.2 m/s and failed its own innovation test on 22 of the
    clean cart's 51 events (0.59 m RMS, against 0.12 m for the snapshot fixes).  On clean
    simulated data a consistent filter fails that test at its false-alarm rate, 0.001
    per event: more than 2 failures in 51 events has probability 2e-5."""
    import numpy as np

    base = ["fuse", "--ranges", str(cart / "measurements.csv"), "--anchors",
            str(cart / "anchors.csv"), "--nmea", str(cart / "gps.nmea")]
    truth = pd.read_csv(cart / "truth.csv")
    for motion, kind in (("cv", "ekf"), ("ca", "ukf")):
        out, explicit = tmp_path / f"{motion}.csv", tmp_path / f"{motion}-{kind}.csv"
        assert main([*base, "--motion", motion, "-o", str(out), "-q"]) == 0
        assert main([*base, "--motion", motion, "--filter", kind, "-o", str(explicit),
                     "-q"]) == 0
        capsys.readouterr()
        tr = pd.read_csv(out)
        pd.testing.assert_frame_equal(tr, pd.read_csv(explicit))
        assert set(tr["method"]) == {f"fuse-{motion}-{kind}"}
        assert (tr["status"] == "fault_detected").sum() <= 2, motion
        m = tr.merge(truth, on=["time", "tag"], suffixes=("", "_t"))
        assert len(m) == len(tr) == 51
        assert np.all(np.isfinite(m["x"]))


def test_the_robust_update_never_widens_the_prediction(tmp_path, monkeypatch):
    """``fuse --robust`` takes the equivalent-variance update (a component of weight ``w``
    enters with ``R / w``), whose covariance never exceeds the prediction's.  The
    command's every filter step is recorded here with its own prediction (the same step
    with nothing measured), on the shipped uwb-dwm1001 LOS excerpt with the default
    robust weight: no update's ``P+ - P-`` has an eigenvalue above rounding (1e-12 of the
    largest prior variance).  Seed 002's ``K D`` (the command before 2026-12-07) widened
    6 of its 611 updates, by up to 0.0053 of the largest prior variance."""
    import numpy as np

    import robustloc.fusion.pipeline as pipeline
    from robustloc.datasets import uwb_dwm1001

    run = uwb_dwm1001.load("LOS")
    ranges, anchors = tmp_path / "ranges.csv", tmp_path / "anchors.csv"
    run.measurements[["time", "tag", "anchor", "range"]].to_csv(ranges, index=False)
    run.anchors.to_csv(anchors, index=False)
    real = pipeline.FusionFilter.step
    grew, rejected = [], []

    def recorded(self, x, P, dt, z, R, meas):
        r = real(self, x, P, dt, z, R, meas)
        prior = real(self, x, P, dt, np.full_like(np.asarray(z, float), np.nan), R, meas).P
        scale = np.abs(prior).max(axis=(1, 2))
        grew.append((np.linalg.eigvalsh(r.P - prior)[:, -1] / scale).max())
        rejected.append(int((r.status == "fault_excluded").sum()))
        return r

    monkeypatch.setattr(pipeline.FusionFilter, "step", recorded)
    out = tmp_path / "track.csv"
    assert main(["fuse", "--ranges", str(ranges), "--anchors", str(anchors), "-o", str(out),
                 "--quiet"]) == 0
    assert len(pd.read_csv(out)) > 500 and len(grew) > 500
    assert sum(rejected) >= 5  # updates that rejected some ranges and kept others
    assert max(grew) <= 1e-12, max(grew)
