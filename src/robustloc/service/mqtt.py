"""MQTT ingest (paho-mqtt) for the live service.

Topic: ``robustloc/measurements/#`` by default (``--mqtt-topic``); any sub-topic works, e.g.
one per gateway ``robustloc/measurements/gw-7``.  Payload: UTF-8 JSON, the same rows as
``POST /api/measurements`` - a JSON array of rows, NDJSON, or one row object::

    [{"time": 12.5, "tag": "T1", "anchor": "A3", "rssi": -71.0}, ...]

Subscribed with QoS 1.  paho acknowledges a QoS 1 message (PUBACK) only after the message
callback returns, and the callback returns after the rows are synced to the store, so a
message the broker considers delivered is on disk.  Rejected rows and payloads that are not
rows are counted in the metrics (``source="mqtt"``, ``reason="mqtt_not_rows"``); a
payload over ``--max-body-bytes`` or of more than
:data:`~robustloc.service.defaults.MAX_ROWS_PER_BODY` rows is refused as a body would be
(``mqtt_too_large``, ``mqtt_too_many_rows``).  ``--rate-limit`` is per client address
and does not apply: the service's one MQTT client is the broker (limit publishers there).
"""

from __future__ import annotations

import threading

from robustloc.service.defaults import MAX_ROWS_PER_BODY
from robustloc.service.engine import Engine
from robustloc.service.rows import BodyError, parse_body


class MqttIngest:
    """Subscribe to a broker and feed the rows to an :class:`Engine`.

    Parameters
    ----------
    engine : Engine
    host, port : str, int
        The broker.
    topic : str
        Topic filter to subscribe to.
    max_payload_bytes : int
        Larger payloads are refused (counted).
    qos : int
        Subscription QoS (default 1: at least once, acknowledged after storing).
    """

    def __init__(self, engine: Engine, host: str, port: int,
                 topic: str = "robustloc/measurements/#", *,
                 max_payload_bytes: int = 32 * 1024 * 1024, qos: int = 1,
                 client_id: str = "") -> None:
        import paho.mqtt.client as mqtt

        self.engine = engine
        self.host, self.port, self.topic, self.qos = host, port, topic, qos
        self.max_payload = max_payload_bytes
        self.connected = threading.Event()
        self.messages = 0
        self.client = mqtt.Client(mqtt.CallbackAPIVersion.VERSION2, client_id=client_id,
                                  clean_session=True)
        self.client.on_connect = self._on_connect
        self.client.on_disconnect = self._on_disconnect
        self.client.on_message = self._on_message
        self.client.reconnect_delay_set(min_delay=1, max_delay=10)

    def _on_connect(self, client, userdata, flags, reason_code, properties=None) -> None:
        if not reason_code.is_failure:
            client.subscribe(self.topic, qos=self.qos)
            self.connected.set()

    def _on_disconnect(self, client, userdata, flags, reason_code, properties=None) -> None:
        self.connected.clear()

    def _on_message(self, client, userdata, msg) -> None:
        self.messages += 1
        m = self.engine.metrics
        try:
            if len(msg.payload) > self.max_payload:
                m.request_rejected("mqtt_too_large")
                return
            batch = self.engine.decode(msg.payload)  # the common payload, in one pass
            if batch is not None:
                self.engine.ingest_batch(batch, "mqtt")
                return
            try:
                rows, _ = parse_body(msg.payload)
            except BodyError:
                m.request_rejected("mqtt_not_rows")
                return
            if len(rows) > MAX_ROWS_PER_BODY:  # as an HTTP body: refused before the rows
                m.request_rejected("mqtt_too_many_rows")
                return
            self.engine.ingest(rows, "mqtt")
        except Exception:  # never let one message stop the network loop
            m.request_rejected("mqtt_internal_error")

    def start(self) -> None:
        """Connect (asynchronously; retried until the broker answers) and start the loop."""
        self.client.connect_async(self.host, self.port, keepalive=30)
        self.client.loop_start()

    def stop(self) -> None:
        self.client.disconnect()
        self.client.loop_stop()
