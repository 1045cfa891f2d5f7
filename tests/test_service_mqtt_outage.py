"""The service and a broker that is not there, goes away and comes back (real Mosquitto
brokers on one loopback port, a real ``robustloc serve``).

The service reconnected, but nothing said whether it was connected: ``/api/status`` and
``/metrics`` had no word on MQTT, and the log said nothing of a lost broker or of a
``--mqtt`` address where no broker listens.  An operator could not tell a service cut off
from its gateways from one they had nothing to send to.

Bounded: two broker starts, a few messages, about 40 s at most; every broker and server
is stopped by the test (the fixtures' teardown).
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest

pytest.importorskip("starlette")
pytest.importorskip("uvicorn")
httpx = pytest.importorskip("httpx")
mqtt = pytest.importorskip("paho.mqtt.client")

from _waiting import wait_until  # noqa: E402

from robustloc.service.launch import MosquittoProcess, free_port, read_metric  # noqa: E402

if not (shutil.which("mosquitto") or Path("/usr/sbin/mosquitto").exists()):
    pytest.skip("the mosquitto binary is missing (apt-get install mosquitto)",
                allow_module_level=True)

ANCHORS = {"A1": (0.0, 0.0), "A2": (10.0, 0.0), "A3": (10.0, 10.0), "A4": (0.0, 10.0)}
TOPIC = "robustloc/measurements/gw-1"


def _status(url: str) -> dict:
    return httpx.get(url + "/api/status", timeout=10).json()["mqtt"]


def _publish(port: int, t0: float) -> None:
    """One epoch of four ranges, QoS 1, acknowledged by the broker."""
    rows = [{"time": t0, "tag": "T", "anchor": a, "range": 5.0} for a in ANCHORS]
    pub = mqtt.Client(mqtt.CallbackAPIVersion.VERSION2)
    pub.connect("127.0.0.1", port)
    pub.loop_start()
    try:
        pub.publish(TOPIC, json.dumps(rows), qos=1).wait_for_publish(10)
    finally:
        pub.loop_stop()
        pub.disconnect()


def _accepted(url: str) -> float:
    return read_metric(url, 'robustloc_rows_accepted_total{source="mqtt"}', timeout_s=10.0)


def test_the_broker_missing_lost_and_back_is_said_and_survived(server_factory, tmp_path):
    anchors = tmp_path / "anchors.csv"
    anchors.write_text("anchor,x,y\n" + "".join(f"{a},{x},{y}\n"
                                                for a, (x, y) in ANCHORS.items()))
    port = free_port()
    brokers: list[MosquittoProcess] = []
    try:
        # 1. no broker where --mqtt points: the service serves, and says so
        srv = server_factory(["--anchors", str(anchors), "--mqtt", f"127.0.0.1:{port}",
                              "--idle-flush", "0.3"], startup_timeout_s=120)
        st = wait_until(lambda: (s := _status(srv.url))["last_reason"] and s, 15,
                   "the failed connection in /api/status")
        assert st["connected"] is False and st["connections"] == 0
        assert st["last_reason"] == "cannot reach the broker"
        assert st["broker"] == f"127.0.0.1:{port}" and st["topic"] == "robustloc/measurements/#"
        assert read_metric(srv.url, "robustloc_mqtt_connected", timeout_s=10.0) == 0
        assert "cannot reach the MQTT broker" in srv.log()
        # 2. the broker starts: the service connects (paho retries every 1-10 s)
        brokers.append(MosquittoProcess(port=port).start())
        wait_until(lambda: _status(srv.url)["connected"], 30, "the first connection")
        assert read_metric(srv.url, "robustloc_mqtt_connected", timeout_s=10.0) == 1
        _publish(port, 0.0)
        wait_until(lambda: _accepted(srv.url) >= 4, 20, "the first message's rows")
        # 3. the broker goes away: counted, said, the gauge drops
        brokers[0].stop()
        st = wait_until(lambda: (s := _status(srv.url))["disconnections"] and s, 15,
                   "the lost connection")
        assert st["connected"] is False and st["disconnections"] == 1
        assert read_metric(srv.url, "robustloc_mqtt_disconnections_total",
                           timeout_s=10.0) == 1
        assert "lost the MQTT broker" in srv.log()
        # 4. back on the same port: the service reconnects and subscribes again (the
        # broker, without persistence, forgot the subscription)
        brokers.append(MosquittoProcess(port=port).start())
        wait_until(lambda: _status(srv.url)["connected"], 30, "the reconnection")
        assert _status(srv.url)["connections"] == 2
        assert "connected again" in srv.log()
        _publish(port, 1.0)
        wait_until(lambda: _accepted(srv.url) >= 8, 20, "the rows sent after the reconnection")
        assert httpx.get(srv.url + "/healthz", timeout=10).json() == {"status": "ok"}
    finally:
        for b in brokers:
            b.stop()
