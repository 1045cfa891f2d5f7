"""The fifth filter/fuse review: a fused row that kept no component is ``predicted``
whatever its anchors, a lost track restarts as a track starts (with its event's GPS
velocity, or the uninformative velocity variance), and ``filter --static`` restarts a link
after a gap as its help says.

The command line runs in-process (``robustloc.cli.main``) on ``robustloc simulate
uwb-cart`` (3 anchors in a 10 m field, 51 epochs at 1 Hz) and on small logs built here.
"""

from __future__ import annotations

import json

import numpy as np
import pandas as pd
import pytest

from robustloc import status as st
from robustloc.cli import main


@pytest.fixture(scope="module")
def cart(tmp_path_factory):
    d = tmp_path_factory.mktemp("cart")
    assert main(["simulate", "uwb-cart", "--seed", "1", "--out", str(d)]) == 0
    return d


def _fuse(tmp_path, capsys, ranges, anchors, *extra):
    out = tmp_path / "track.csv"
    rc = main(["fuse", "--ranges", str(ranges), "--anchors", str(anchors), "-o", str(out),
               "--json", *extra])
    cap = capsys.readouterr()
    assert rc == 0, cap.err
    return pd.read_csv(out), json.loads(cap.out)


# --- 1: an event whose every component was rejected is predicted, whatever its anchors ----


@pytest.mark.parametrize("layout", [st.INSUFFICIENT, st.ILL_CONDITIONED])
def test_fuse_row_that_kept_nothing_is_predicted_whatever_the_anchors(cart, tmp_path, capsys,
                                                                      layout):
    # two anchors per event; both ranges of t = 20 are 8 m long: the update rejects both
    # (n_used 0) and the row is the prediction.  It said insufficient_anchors (or
    # ill_conditioned), statuses of an *updated* row (fuse --help)
    m = pd.read_csv(cart / "measurements.csv")
    two = m[m["anchor"] != "BS.C"].copy()
    pa = cart / "anchors.csv"
    if layout == st.ILL_CONDITIONED:
        # BS.C at BS.A's place, heard half a second after each epoch (its own event of one
        # range): the anchors heard within the 1 s window are three at two points
        a = pd.read_csv(pa)
        a.loc[a["anchor"] == "BS.C", ["x", "y"]] = a.loc[a["anchor"] == "BS.A",
                                                         ["x", "y"]].to_numpy()
        pa = tmp_path / "anchors.csv"
        a.to_csv(pa, index=False)
        c = two[two["anchor"] == "BS.A"].assign(anchor="BS.C")
        c["time"] += 0.5
        two = pd.concat([two, c], ignore_index=True).sort_values("time", kind="stable")
    two.loc[two["time"] == 20.0, "range"] += 8.0
    pm = tmp_path / "ranges.csv"
    two.to_csv(pm, index=False)
    tr, summary = _fuse(tmp_path, capsys, pm, pa)
    row = tr.loc[tr["time"] == 20.0].iloc[0]
    assert row["n_used"] == 0
    assert row["status"] == st.PREDICTED
    # the other updated rows keep the layout's status (the first event, before BS.C is
    # heard, has two anchors); none that kept nothing does
    updated = tr["n_used"] > 0
    assert (tr.loc[updated & (tr["time"] >= 0.5), "status"] == layout).all()
    assert (tr.loc[~updated, "status"] == st.PREDICTED).all()


# --- 3: filter --static restarts a link after a gap, as its help says ------------------------


@pytest.mark.parametrize("static", [False, True], ids=["moving", "static"])
def test_filter_restarts_a_link_after_a_gap(tmp_path, capsys, static):
    # one link at -50 dBm (3.16 m from an anchor of A = -40, n = 2), then 10 000 s later at
    # -60 dBm (10 m).  The help: a link whose predicted RSSI variance exceeds 25 times the
    # measurement's starts again, its distance drawn from the sample.  --static never did
    # (its distance variance does not grow, and the rule also wanted it beyond d^2): its
    # distance state stayed at 3.3 m
    pa, pm, out = tmp_path / "a.csv", tmp_path / "m.csv", tmp_path / "f.csv"
    pa.write_text("anchor,x,y,A,n\nAP1,0,0,-40,2\n")
    rows = ([f"{t},t,AP1,-50" for t in range(20)]
            + [f"{10000 + t},t,AP1,-60" for t in range(20)])
    pm.write_text("time,tag,anchor,rssi\n" + "\n".join(rows) + "\n")
    rc = main(["filter", str(pm), "--anchors", str(pa), "-o", str(out), "--json",
               *(["--static"] if static else [])])
    cap = capsys.readouterr()
    assert rc == 0, cap.err
    assert json.loads(cap.out)["restarted"] == 1
    f = pd.read_csv(out)
    after = f.iloc[20]
    assert after["distance_state"] == pytest.approx(10.0, rel=1e-9)
    assert after["rssi"] == pytest.approx(-60.0, abs=1e-9)
    assert f.iloc[21:]["distance_state"].sub(10.0).abs().max() < 0.5


def test_static_filter_restarts_after_its_random_walk_passes_the_ratio():
    # a static link's power variance grows by q_rssi per second only: past 25 R after about
    # (25 R - P) / q = (100 - 0.43) / 0.05 = 1990 s at the defaults (filter --help)
    from robustloc.filters.rssi import RobustRssiFilter

    f = RobustRssiFilter(sigma_accel_mps2=0.0, init_speed_std_mps=0.0)
    for gap, want in ((1900.0, 0), (2100.0, 1)):
        t = np.r_[np.arange(20.0), gap + 19.0 + np.arange(5.0)]
        z = np.r_[np.full(20, -50.0), np.full(5, -60.0)]
        r = f.filter_samples(np.zeros(len(t), dtype=np.int64), t, z)
        assert int(r.restarted.sum()) == want, gap
    assert f.static and not RobustRssiFilter().static
