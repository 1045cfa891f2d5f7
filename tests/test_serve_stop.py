"""``robustloc serve`` stopped by SIGTERM (a service manager's stop) or SIGINT: a normal
stop, exit code 0.  uvicorn re-raised the signal after its graceful shutdown and the
command line turned it into ``error: terminated`` and exit code 143 (the new-user walk:
systemd reports such a unit failed)."""

from __future__ import annotations

import signal

import httpx
import pytest


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT])
def test_a_signal_stops_the_service_normally(server_factory, tmp_path, sig):
    from robustloc.sim.ble_corridor import simulate_ble_corridor

    anchors = tmp_path / "anchors.csv"
    simulate_ble_corridor(seed=1)["anchors"].to_csv(anchors, index=False)
    store = tmp_path / "store"
    s = server_factory(["--anchors", str(anchors), "--store", str(store)])
    assert httpx.get(s.url + "/api/status", timeout=30).status_code == 200
    s.proc.send_signal(sig)
    assert s.proc.wait(timeout=30) == 0
    log = s.log()
    assert f"stopped ({sig.name}); every acknowledged row is in {store}" in log
    assert "error:" not in log and "Traceback" not in log
