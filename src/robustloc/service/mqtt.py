"""MQTT ingest (paho-mqtt) for the live service.

Topic: ``robustloc/measurements/#`` by default (``--mqtt-topic``); any sub-topic works, e.g.
one per gateway ``robustloc/measurements/gw-7``.  Payload: UTF-8 JSON, the same rows as
``POST /api/measurements`` - a JSON array of rows, NDJSON, or one row object::

    [{"time": 12.5, "tag": "T1", "anchor": "A3", "rssi": -71.0}, ...]

Subscribed with QoS 1 and acknowledged by hand (paho's ``manual_ack``): a message is
acknowledged (PUBACK) only after its rows are synced to the store, or after it was refused
for good (counted).  Rejected rows and payloads that are not rows are counted in the
metrics (``source="mqtt"``, ``reason="mqtt_not_rows"``); a payload over
``--max-body-bytes`` or of more than :data:`~robustloc.service.defaults.MAX_ROWS_PER_BODY`
rows is refused as a body would be (``mqtt_too_large``, ``mqtt_too_many_rows``).
``--rate-limit`` is per client address and does not apply: the service's one MQTT client
is the broker (limit publishers there).

A message the store cannot write (disk full, I/O error) is **not** acknowledged: it is
counted (``mqtt_store_error``), one line is logged, and the client reconnects after
:data:`STORE_RETRY_S` seconds so that the broker delivers it again.

A message an internal error stops (a defect of the service, not of the message: sent
again it would fail again, forever) is counted (``mqtt_internal_error``) and logged; with a
store its payload is first written, whole and fsync-ed, to
``STORE/dead-letter/mqtt-<unix ns>-<n>.payload`` and the log line names the file, then the
message is acknowledged.  The file holds the message's bytes as published, a body that
``POST /api/measurements`` takes (``curl --data-binary @FILE URL/api/measurements``) once
the defect is fixed; an error after some rows were stored repeats those.  Where the file
cannot be written the message is not acknowledged (as a store failure).  Without a store
it is acknowledged and dropped: nothing would keep its rows anyway.

With a store (``--store``) the service connects with a stable client id,
:func:`client_id_for_store` (``robustloc-`` and a hash of the store's absolute path), and
a persistent session (``clean_session=False``): while the service is down (a restart, an
upgrade) the broker keeps its subscription and queues the QoS 1 messages for it (up to the
broker's ``max_queued_messages``), delivered when it reconnects.  Messages published
before the store's first connection are not queued (there was no session yet).
Without a store the session is clean and the client id random: nothing would keep the
rows anyway.

Retained messages: a message delivered with the retain flag set is the broker's copy of
the last message retained on a topic, re-sent at every (re)subscription - at each start of
the service - and not a measurement of now: it is acknowledged and not ingested, counted in
``robustloc_mqtt_retained_ignored_total`` (``retained_ignored`` in ``/api/status``), and
the first one is named in the log.  Its rows were stored, once, when the service received
the message live: the broker delivers a message published (retained or not) to a running
subscription, or queued for a persistent session while the service was down, with the
flag cleared (MQTT 3.1.1 section 3.3.1.3).  Each restart stored the same rows again, late
(the serve review: one 3-row retained message, three starts, 9 rows stored).  Only a
retained message published before the service's first subscription is never ingested.
"""

from __future__ import annotations

import hashlib
import os
import socket
import sys
import threading
import time
from pathlib import Path

from robustloc.service.defaults import MAX_ROWS_PER_BODY
from robustloc.service.engine import Engine
from robustloc.service.rows import BodyError, parse_body, rows_beyond
from robustloc.service.store import StoreWriteError
from robustloc.service.topics import check_topic_filter

#: Seconds after a store write failure before the client reconnects (and the broker
#: delivers the unacknowledged messages again).
STORE_RETRY_S = 5.0


def client_id_for_store(store: str | os.PathLike) -> str:
    """The MQTT client id of a service on ``store``: stable across restarts (the broker
    keeps its session), different for another store.

    Parameters
    ----------
    store : path
        The ``--store`` folder.

    Returns
    -------
    str
        ``robustloc-`` and 13 hex digits of the SHA-256 of the absolute path: 23
        characters, the longest client id every MQTT 3.1.1 broker must accept.
    """
    path = os.path.abspath(Path(store).expanduser())
    return "robustloc-" + hashlib.sha256(path.encode()).hexdigest()[:13]


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
    client_id : str
        The client id; default ``""`` (the library draws a random one).
    persistent : bool
        Ask the broker to keep the session (``clean_session=False``): its subscription
        and queued QoS 1 messages outlive a disconnection.  Needs a stable ``client_id``.
    """

    def __init__(self, engine: Engine, host: str, port: int,
                 topic: str = "robustloc/measurements/#", *,
                 max_payload_bytes: int = 32 * 1024 * 1024, qos: int = 1,
                 client_id: str = "", persistent: bool = False) -> None:
        import paho.mqtt.client as mqtt

        if persistent and not client_id:
            raise ValueError("a persistent MQTT session needs a stable client id")
        check_topic_filter(topic)
        self.engine = engine
        self.host, self.port, self.topic, self.qos = host, port, topic, qos
        self.max_payload = max_payload_bytes
        self.connected = threading.Event()
        self.messages = 0
        self.client_id = client_id
        #: where a payload stopped by an internal error is kept (module docstring)
        self.dead_letter_dir = (None if engine.store_dir is None
                                else Path(engine.store_dir) / "dead-letter")
        self._retry: threading.Timer | None = None
        self._retry_lock = threading.Lock()
        #: the connection's history, for ``/api/status`` and ``/metrics`` (:meth:`status`):
        #: an operator could not tell a service that lost its broker (or was given a
        #: wrong ``--mqtt`` address) from one nobody publishes to
        self.connections = 0
        self.disconnections = 0
        #: retained messages re-sent by the broker at a subscription, not ingested
        self.retained_ignored = 0
        self.since: float | None = None  # time of the last connect or disconnect
        self.last_reason: str | None = None  # why the last connection ended or failed
        self._stopping = False
        self._failure_said = False  # one line per outage, not one per retry
        self.client = mqtt.Client(mqtt.CallbackAPIVersion.VERSION2, client_id=client_id,
                                  clean_session=not persistent, manual_ack=True)
        self.client.on_connect = self._on_connect
        self.client.on_disconnect = self._on_disconnect
        self.client.on_connect_fail = self._on_connect_fail
        self.client.on_message = self._on_message
        self.client.reconnect_delay_set(min_delay=1, max_delay=10)

    @property
    def broker(self) -> str:
        """``host:port`` of the broker."""
        return f"{self.host}:{self.port}"

    def _on_connect(self, client, userdata, flags, reason_code, properties=None) -> None:
        if reason_code.is_failure:  # refused by the broker (bad credentials, client id)
            self.last_reason = f"connection refused: {reason_code}"
            print(f"error: MQTT broker {self.broker} refused the connection "
                  f"({reason_code}); retrying", file=sys.stderr, flush=True)
            return
        try:
            client.subscribe(self.topic, qos=self.qos)
        except ValueError as exc:  # (checked at start: a broker-side rule paho enforces)
            self.last_reason = f"cannot subscribe to {self.topic!r}: {exc}"
            print(f"error: MQTT: {self.last_reason}", file=sys.stderr, flush=True)
            return
        self.connections += 1
        self.since = time.time()
        self._failure_said = False
        again = "again " if self.connections > 1 else ""
        print(f"MQTT: connected {again}to {self.broker}, topic {self.topic}",
              file=sys.stderr, flush=True)
        self.connected.set()

    def _on_connect_fail(self, client, userdata) -> None:
        self.last_reason = "cannot reach the broker"
        if not self._failure_said and not self._stopping:
            self._failure_said = True
            print(f"warning: cannot reach the MQTT broker {self.broker}; retrying every "
                  "1-10 s (robustloc_mqtt_connected in /metrics, mqtt in /api/status)",
                  file=sys.stderr, flush=True)

    def _on_disconnect(self, client, userdata, flags, reason_code, properties=None) -> None:
        was = self.connected.is_set()
        self.connected.clear()
        if self._stopping:
            return
        if was:
            self.disconnections += 1
            self.since = time.time()
            self.last_reason = str(reason_code)
            self._failure_said = True  # (the retries that follow say nothing more)
            print(f"warning: lost the MQTT broker {self.broker} ({reason_code}); "
                  "reconnecting (rows published meanwhile arrive with a --store's "
                  "persistent session, QoS 1)", file=sys.stderr, flush=True)

    def status(self) -> dict[str, object]:
        """The connection's state for ``/api/status`` (key ``mqtt``): ``broker``,
        ``topic``, ``connected``, ``connections`` (successful ones), ``disconnections``
        (lost ones), ``since`` (Unix time of the last change; None before the first
        connection), ``last_reason`` (why the last one ended or failed) and
        ``messages`` (received), ``retained_ignored`` (retained messages re-sent at a
        subscription, not ingested: module docstring)."""
        return {"broker": self.broker, "topic": self.topic,
                "connected": self.connected.is_set(), "connections": self.connections,
                "disconnections": self.disconnections, "since": self.since,
                "last_reason": self.last_reason, "messages": self.messages,
                "retained_ignored": self.retained_ignored}

    def prometheus(self) -> str:
        """The connection's metrics in the Prometheus text format (``/metrics``)."""
        return (
            "# HELP robustloc_mqtt_connected 1 while the service is connected to its MQTT "
            "broker, else 0.\n# TYPE robustloc_mqtt_connected gauge\n"
            f"robustloc_mqtt_connected {int(self.connected.is_set())}\n"
            "# HELP robustloc_mqtt_disconnections_total Connections to the MQTT broker "
            "lost (the service reconnects).\n"
            "# TYPE robustloc_mqtt_disconnections_total counter\n"
            f"robustloc_mqtt_disconnections_total {self.disconnections}\n"
            "# HELP robustloc_mqtt_retained_ignored_total Retained MQTT messages the broker "
            "re-sent at a subscription (at each start), acknowledged and not ingested: their "
            "rows were stored when they were received live.\n"
            "# TYPE robustloc_mqtt_retained_ignored_total counter\n"
            f"robustloc_mqtt_retained_ignored_total {self.retained_ignored}\n")

    def _on_message(self, client, userdata, msg) -> None:
        self.messages += 1
        m = self.engine.metrics
        topic = getattr(msg, "topic", "?")
        if getattr(msg, "retain", False):
            # the broker's retained copy, re-sent at the subscription: not a measurement
            # of now (stored once when it came live; module docstring)
            self.retained_ignored += 1
            if self.retained_ignored == 1:
                print(f"MQTT: a retained message on {topic} ignored (the broker re-sends "
                      "a topic's retained message at each subscription; its rows were "
                      "stored when it came live; robustloc_mqtt_retained_ignored_total)",
                      file=sys.stderr, flush=True)
            if getattr(msg, "qos", 0) > 0:
                self.client.ack(msg.mid, msg.qos)
            return
        try:
            self._ingest(msg.payload)
        except StoreWriteError as exc:  # not acknowledged: the broker sends it again
            m.request_rejected("mqtt_store_error")
            print(f"error: MQTT message on {topic} not stored and not acknowledged "
                  f"({exc}); reconnecting in {STORE_RETRY_S:g} s to receive it again",
                  file=sys.stderr, flush=True)
            self._reconnect_later()
            return
        except Exception as exc:  # noqa: BLE001 - never let one message stop the loop
            # a defect of the service, not of the message: counted and logged; the
            # message is acknowledged (sent again, it would fail again, forever), its
            # payload first kept in the store's dead-letter folder
            m.request_rejected("mqtt_internal_error")
            what = f"{type(exc).__name__}: {exc}"
            try:
                kept = self._dead_letter(msg.payload)
            except OSError as err:  # not kept: not acknowledged, as a store failure
                print(f"error: MQTT message on {topic} stopped by an internal error "
                      f"({what}) and not kept in the dead-letter folder ({err}): not "
                      f"acknowledged; reconnecting in {STORE_RETRY_S:g} s",
                      file=sys.stderr, flush=True)
                self._reconnect_later()
                return
            where = (f"; its payload is kept in {kept}" if kept is not None
                     else " (no --store: dropped)")
            print(f"error: MQTT message on {topic} stopped by an internal error: {what}"
                  f"{where}", file=sys.stderr, flush=True)
        qos = getattr(msg, "qos", 0)  # (a message object without qos: nothing to ack)
        if qos > 0:
            self.client.ack(msg.mid, qos)

    def _dead_letter(self, payload: bytes) -> Path | None:
        """Write ``payload`` whole to a new file of :attr:`dead_letter_dir` (None without
        a store); raises ``OSError`` where it cannot."""
        if self.dead_letter_dir is None:
            return None
        from robustloc.errors import OutputError
        from robustloc.io.atomic import atomic_output

        self.dead_letter_dir.mkdir(parents=True, exist_ok=True)
        path = self.dead_letter_dir / f"mqtt-{time.time_ns()}-{self.messages}.payload"
        try:
            with atomic_output(path) as (tmp, _):
                Path(tmp).write_bytes(bytes(payload))
        except OutputError as exc:
            raise OSError(str(exc)) from None
        return path

    def _ingest(self, payload: bytes) -> None:
        """Ingest one payload; a refused payload is counted (and then acknowledged)."""
        m = self.engine.metrics
        if len(payload) > self.max_payload:
            m.request_rejected("mqtt_too_large")
            return
        batch = self.engine.decode(payload)  # the common payload, in one pass
        if batch is not None and len(batch) <= MAX_ROWS_PER_BODY:
            self.engine.ingest_batch(batch, "mqtt")
            return
        if batch is not None or rows_beyond(payload, MAX_ROWS_PER_BODY) is not None:
            m.request_rejected("mqtt_too_many_rows")  # as an HTTP body: refused (before
            return  # anything is decoded row by row)
        try:
            rows, _ = parse_body(payload)
        except BodyError:
            m.request_rejected("mqtt_not_rows")
            return
        self.engine.ingest(rows, "mqtt")

    def _reconnect_later(self) -> None:
        """After :data:`STORE_RETRY_S`, drop the connection (the network loop reconnects):
        the broker sends the unacknowledged messages again on the new connection.  The
        socket is shut down rather than ``disconnect()``-ed, which would end the loop."""
        with self._retry_lock:
            if self._retry is not None and self._retry.is_alive():
                return

            def drop() -> None:
                sock = self.client.socket()
                if sock is not None:
                    try:
                        sock.shutdown(socket.SHUT_RDWR)
                    except OSError:
                        pass

            self._retry = threading.Timer(STORE_RETRY_S, drop)
            self._retry.daemon = True
            self._retry.start()

    def start(self) -> None:
        """Connect (asynchronously; retried until the broker answers) and start the loop."""
        self.client.connect_async(self.host, self.port, keepalive=30)
        self.client.loop_start()

    def stop(self) -> None:
        """Disconnect and stop the network loop (unacknowledged messages stay with the
        broker's session)."""
        self._stopping = True
        with self._retry_lock:
            if self._retry is not None:
                self._retry.cancel()
        self.client.disconnect()
        self.client.loop_stop()


__all__ = ["MqttIngest", "STORE_RETRY_S", "client_id_for_store"]
