"""``serve --track --track-link-offsets auto``: a real server lets the stream's first
epochs choose the links' offsets (:class:`robustloc.tracking.AutoTracker`), as ``track``
chooses on a log's first epochs."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

pytest.importorskip("starlette")
pytest.importorskip("uvicorn")
httpx = pytest.importorskip("httpx")

from test_service import _cli, rows_equal, wait_for  # noqa: E402

from robustloc.io import read_anchors, read_measurements  # noqa: E402
from robustloc.io.tables import to_epochs  # noqa: E402
from robustloc.tracking import Tracker  # noqa: E402
from robustloc.tracking.select import choose_link_offsets  # noqa: E402


@pytest.fixture(scope="module")
def ble(tmp_path_factory):
    d = tmp_path_factory.mktemp("ble")
    _cli("simulate", "ble-corridor", "--seed", "1", "--out", str(d))
    return d


def _post(srv, rows: pd.DataFrame, n_positions: int) -> pd.DataFrame:
    """Send ``rows`` and wait until the service holds ``n_positions`` positions."""
    body = [{"time": float(r.time), "tag": str(r.tag), "anchor": str(r.anchor),
             "rssi": float(r.rssi)} for r in rows.itertuples()]
    r = httpx.post(srv.url + "/api/measurements", json=body)
    assert r.status_code == 202 and r.json()["accepted"] == len(body), r.text

    def got():
        d = pd.DataFrame(httpx.get(srv.url + "/api/positions").json())
        return d if len(d) == n_positions else None

    return wait_for(got, what=f"{n_positions} positions")


def _check(rows: pd.DataFrame, want: pd.DataFrame) -> None:
    rows_equal(rows, want, ("x", "y", "hpl"))


def test_the_stream_chooses_and_a_restart_keeps_the_trial(ble, server_factory, tmp_path):
    """The simulated corridor (3 tags, 180 epochs), the trial set to its first 90:
    the first 45 epochs, a restart on the same store, the next 45 (the trial's end: the
    choice, ``track``'s on the same 90 epochs), then the rest.  The rows are the plain
    tracker's up to the choice and the chosen tracker's after it (to 1e-9 m), as if the
    stream had not been interrupted; ``/api/status`` shows the trial, then the choice."""
    anchors = read_anchors(ble / "anchors.csv")
    meas = read_measurements(ble / "measurements.csv")
    ep = to_epochs(meas, anchors["anchor"])
    times = np.unique(ep.time)
    assert ep.n_epochs == 180 and len(times) == 60
    ref = choose_link_offsets(anchors, ep.take(slice(0, 90)))
    assert ref.use  # (the corridor's survey calibration leaves offsets to find)
    off, on = Tracker(anchors).step(ep), Tracker(anchors, link_offsets=True).step(ep)
    assert np.abs(off["x"] - on["x"]).max() > 1e-3
    args = ["--anchors", str(ble / "anchors.csv"), "--track", "--track-link-offsets",
            "auto", "--track-auto-sample", "90", "--store", str(tmp_path / "store"),
            "--idle-flush", "0.3"]
    cut = [times[15], times[30]]  # 45 and 90 epochs before these times
    srv = server_factory(args)
    _post(srv, meas[meas["time"] < cut[0]], 45)
    st = httpx.get(srv.url + "/api/status").json()["link_offsets"]
    assert st == {"mode": "auto", "phase": "trial", "epochs": 45, "sample_epochs": 90}
    srv.stop()
    srv = server_factory(args)  # the same store: the trial's state comes back
    assert httpx.get(srv.url + "/api/status").json()["link_offsets"]["epochs"] == 45
    _post(srv, meas[(meas["time"] >= cut[0]) & (meas["time"] < cut[1])], 90)
    st = httpx.get(srv.url + "/api/status").json()["link_offsets"]
    assert st["phase"] == "chosen" and st["used"] is True and st["epochs"] == 90
    assert st["t"] == round(ref.t, 4) and st["observations"] == ref.observations
    rows = _post(srv, meas[meas["time"] >= cut[1]], 180)
    early = rows["time"].astype(float) < cut[1]
    _check(rows[early], off.iloc[:90])
    _check(rows[~early], on.iloc[90:])


def test_serve_refuses_what_auto_cannot_go_with(ble):
    from robustloc.cli import main

    a = str(ble / "anchors.csv")
    assert main(["serve", "--anchors", a, "--track-link-offsets", "auto"]) == 2
    assert main(["serve", "--anchors", a, "--track", "--track-auto-sample", "50"]) == 2
    assert main(["serve", "--anchors", a, "--track", "--track-link-offsets", "on",
                 "--track-auto-sample", "50"]) == 2


def test_a_store_of_auto_restarted_with_its_choice_pinned(ble):
    """The processor behind ``--store``: a state written with ``auto`` after its choice
    (on) is taken over by ``--track-link-offsets on`` (the rows go on as the chosen
    tracker's) and refused by ``off``, saying what the store holds; one written mid-trial
    is refused by both; a plain tracker's state is refused by ``auto``."""
    from robustloc.service.processor import TrackProcessor

    anchors = read_anchors(ble / "anchors.csv")
    ep = to_epochs(read_measurements(ble / "measurements.csv"), anchors["anchor"])
    first, rest = ep.take(slice(0, 120)), ep.take(slice(120, ep.n_epochs))
    auto = TrackProcessor(anchors, link_offsets="auto", auto_sample_epochs=90)
    auto.process(first)
    assert auto.status()["link_offsets"]["used"] is True
    on = TrackProcessor(anchors, link_offsets="on")
    on.load_state_dict(auto.state_dict())
    pd.testing.assert_frame_equal(on.process(rest), auto.process(rest))
    with pytest.raises(ValueError, match="chose on: restart with --track-link-offsets "
                                         "auto or on.*new --store"):
        TrackProcessor(anchors).load_state_dict(auto.state_dict())
    trial = TrackProcessor(anchors, link_offsets="auto", auto_sample_epochs=150)
    trial.process(first)
    for other in ("on", "off"):
        with pytest.raises(ValueError, match="trial still running"):
            TrackProcessor(anchors, link_offsets=other).load_state_dict(trial.state_dict())
    with pytest.raises(ValueError, match="not an auto tracker's"):
        TrackProcessor(anchors, link_offsets="auto").load_state_dict(on.state_dict())
    with pytest.raises(ValueError, match="link_offsets must be"):
        TrackProcessor(anchors, link_offsets="yes")
