"""``robustloc serve``: the live positioning service (HTTP, WebSocket, MQTT, map page)."""

from __future__ import annotations

import argparse
import logging
import os
import sys
from pathlib import Path
from typing import Any

from robustloc.options import (
    nonnegative_float,
    positive_float,
    positive_int,
    positive_process_noise,
    sigma_value,
)

NAME = "serve"
HELP = "live positioning service: HTTP/WebSocket/MQTT ingest, positions API, live map page"
DESCRIPTION = """\
Runs an ASGI service (Starlette on uvicorn) that accepts measurement rows as they arrive,
assembles them into epochs per tag, solves each epoch with the same estimators as
`robustloc locate` (or tracks with `robustloc.tracking` under --track), stores rows and
positions durably, and publishes positions over HTTP, WebSocket and a live map page at /.

Ingest: POST /api/measurements (JSON array, NDJSON or one object of {"time","tag","anchor","rssi"|
"range"}), WebSocket /ws/measurements, or MQTT (--mqtt HOST:PORT, topic --mqtt-topic,
payload = the same JSON). Reads: GET /api/positions?tag=&since=&until=, /api/anchors,
/metrics (Prometheus), WebSocket /ws/positions[?tag=][&batch=1] (a subscriber too slow to
keep up holds at most 20 000 messages and 32 MiB; past either its oldest are dropped,
counted in robustloc_ws_messages_dropped_total). /healthz needs no token.

Epoch assembly: an epoch (time, tag) is solved once it is older than the newest time seen
for its tag by more than --latency-window seconds (default 0.5 s), or when its tag has been
silent for --idle-flush seconds of wall time. A later row is stored and counted as late
(metric robustloc_rows_late_total), never dropped silently. A row more than --time-jump
seconds behind its tag's newest time, nothing near that time for --idle-flush, means the
tag's clock jumped: the tag restarts from the new time (metric robustloc_tags_rebased_total).
A tag silent for --forget-after (default 7 days) is forgotten: its state goes, its stored
rows stay, and heard again it starts afresh (metric robustloc_tags_forgotten_total); so
--max-tags bounds the tags heard within that time, not every tag ever heard.

Durability (--store DIR): every accepted row is synced to a write-ahead log
(DIR/measurements/seg-*.wal) before the 202. A log is sealed into a Parquet segment
(DIR/measurements/*.parquet, DIR/positions/*.parquet) once it holds 1 000 000 rows, and the
logs a stop or a crash left are sealed at the next start: after a stop the newest rows are
still in the .wal files (read them through the service). After a crash (even kill -9) and a
restart on the same DIR, nothing acknowledged is lost and each tag resumes where it stopped
(with --track, its filter from the snapshot in DIR/state/, every 10 s, or from its first
stored row: the epochs since are solved again, so a resumed replay gives the tracks of
robustloc track). Without --store the service keeps everything in memory (a warning says
so). One service per store: the service locks DIR/.lock while it runs, and a second one on
the same DIR exits with an error (2) before serving. A body the store cannot write (disk
full) is answered 507 and nothing of it is stored (counted as store_error in /metrics):
send it again later. A damaged store file (meta.json, a Parquet segment, a write-ahead log
damaged before intact frames) is named in the error at start-up (exit 2).

MQTT with --store: the service connects with a stable client id (--mqtt-client-id; by
default robustloc- and a hash of the store's absolute path) and a persistent session,
subscribed with QoS 1, so the broker queues the messages published while the service is
down (restart, upgrade) and delivers them when it is back. A message is acknowledged only
once its rows are stored; one the store cannot write is delivered again later. A retained
message the broker re-sends at each subscription is acknowledged and not ingested (it was
stored when it came live; metric robustloc_mqtt_retained_ignored_total).
A broker that is not there, or goes away, does not stop the service: it retries every
1-10 s, says so in its log (once per outage), and reports the connection in /api/status
("mqtt": connected, connections, disconnections, last_reason) and /metrics
(robustloc_mqtt_connected, robustloc_mqtt_disconnections_total): alert on them.

Shutdown (SIGTERM, SIGINT): requests in progress get up to --shutdown-grace seconds
(default 5) to finish, then they are cancelled (a client still sending a body gets 503
with Retry-After: nothing of that body is stored); the pending epochs are solved, and the
service says "stopped (SIGTERM)" and exits 0: a normal stop.

Security: binds 127.0.0.1 unless --host says otherwise; --token (or ROBUSTLOC_TOKEN)
guards ingest and reads (Authorization: Bearer TOKEN; WebSockets may use ?token=);
body size (--max-body-bytes) and per-client rate (--rate-limit) limits; CORS off unless
--cors-origin is given.

  robustloc serve --anchors anchors.csv --store live-store
  robustloc serve --anchors anchors.csv --method igg --latency-window 0.2 --mqtt 127.0.0.1:1883
  ROBUSTLOC_TOKEN=secret robustloc serve --anchors a.csv --host 0.0.0.0 --floorplan plan.png \\
      --floorplan-extent 0,0,40,25"""


#: Seconds requests in progress get to finish at shutdown (uvicorn's graceful timeout):
#: a client that sent half a body kept the service alive for --body-timeout (60 s).
DEFAULT_SHUTDOWN_GRACE_S = 5.0


def _extent(text: str) -> tuple[float, float, float, float]:
    try:
        v = tuple(float(x) for x in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected XMIN,YMIN,XMAX,YMAX, got {text!r}") from None
    if len(v) != 4 or not all(map(lambda x: x == x and abs(x) != float("inf"), v)):
        raise argparse.ArgumentTypeError(f"expected 4 finite numbers, got {text!r}")
    if not (v[0] < v[2] and v[1] < v[3]):
        raise argparse.ArgumentTypeError("extent needs XMIN < XMAX and YMIN < YMAX")
    return v  # type: ignore[return-value]


def _hostport(text: str) -> tuple[str, int]:
    host, sep, port = text.rpartition(":")
    if not sep or not host or not port.isdigit() or not 0 < int(port) < 65536:
        raise argparse.ArgumentTypeError(f"expected HOST:PORT, got {text!r}")
    return host, int(port)


def _topic(text: str) -> str:
    """``--mqtt-topic``: a valid MQTT subscription filter (checked before serving)."""
    from robustloc.service.topics import check_topic_filter

    try:
        return check_topic_filter(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def _port(text: str) -> int:
    """``--port``: 0 (any free port: the one bound is announced) to 65535."""
    try:
        port = int(text)
    except ValueError:
        port = -1
    if not 0 <= port <= 65535:
        raise argparse.ArgumentTypeError(
            f"expected a TCP port 1-65535 (0: any free one), got {text!r}")
    return port


def _forget_after(text: str) -> float:
    """``--forget-after``: seconds > 0, or ``never`` (infinity)."""
    if text.strip().lower() in ("never", "inf"):
        return float("inf")
    return positive_float(text)


#: Options of the per-epoch fixes that ``--track`` has no use for, with their defaults
#: (given with --track they were ignored without a word: the tracker is 2-D, tests its
#: innovations with its own scale and has no alert limit).
FIX_ONLY_OPTIONS = {"dim": 2, "solver": "nonlinear", "robust_scale": "mad",
                    "scale_from": None, "side_prior": "log", "alert_limit": None,
                    "k_noise": None, "model": None, "no_range_calibration": False}
#: The tracker's options, which the per-epoch fixes have no use for.
TRACK_ONLY_OPTIONS = {"track_model": "cv", "track_filter": "ekf", "track_q": None,
                      "track_weight": None}


def _check_mode_options(args: argparse.Namespace) -> None:
    """Refuse the options of the mode not chosen (fixes or ``--track``)."""
    from robustloc.errors import InputError

    other = FIX_ONLY_OPTIONS if args.track else TRACK_ONLY_OPTIONS
    given = ["--" + k.replace("_", "-") for k, d in other.items() if getattr(args, k) != d]
    if given:
        verb = "applies" if len(given) == 1 else "apply"
        raise InputError(f"{', '.join(given)} {verb} to the "
                         + ("per-epoch fixes, not to --track" if args.track
                            else "tracker: add --track"))


def add_arguments(p: argparse.ArgumentParser) -> None:
    from robustloc.estimators.ranging import DEFAULT_METHOD, METHOD_SYNONYMS, METHODS
    from robustloc.options import choice
    from robustloc.pipelines.track import WEIGHT_SYNONYMS as TRACK_WEIGHT_SYNONYMS
    from robustloc.pipelines.track import WEIGHTS as TRACK_WEIGHTS
    from robustloc.service.defaults import (
        DEFAULT_BODY_TIMEOUT_S,
        DEFAULT_FORGET_AFTER_S,
        DEFAULT_HEADER_TIMEOUT_S,
        DEFAULT_IDLE_FLUSH_S,
        DEFAULT_LATENCY_WINDOW_S,
        DEFAULT_MAX_BODY_BYTES,
        DEFAULT_MAX_TAGS,
        DEFAULT_RATE_LIMIT_ROWS,
        DEFAULT_TIME_JUMP_S,
    )
    from robustloc.tracking.select import AUTO_SAMPLE_EPOCHS

    p.add_argument("--anchors", required=True, help="anchors file (anchor, x, y[, z], ...)")
    p.add_argument("--host", default="127.0.0.1",
                   help="address to bind (default 127.0.0.1: this machine only)")
    p.add_argument("--port", type=_port, default=8080,
                   help="TCP port (default 8080; 0: any free port, announced at start)")
    p.add_argument("--token", default=None,
                   help="bearer token for ingest and reads (default: $ROBUSTLOC_TOKEN; none)")
    p.add_argument("--store", default=None, metavar="DIR",
                   help="durable store folder (default: memory only, lost on exit)")
    mode = p.add_mutually_exclusive_group()
    mode.add_argument("--method", default=DEFAULT_METHOD, choices=("auto",) + METHODS,
                      type=choice(METHOD_SYNONYMS),
                      help=f"positioning method, as robustloc locate (default {DEFAULT_METHOD}"
                           "; asymmetric-igg = asym)")
    mode.add_argument("--track", action="store_true",
                      help="track with robustloc.tracking.Tracker instead of per-epoch fixes")
    p.add_argument("--track-model", "--track-motion", dest="track_model",
                   choices=("cv", "ca", "static"), default="cv",
                   help="--track: motion model, as robustloc track --model (default cv)")
    p.add_argument("--track-filter", choices=("ekf", "ukf"), default="ekf",
                   help="--track: filter (default ekf)")
    # (as track --q: 1e308 overflowed the covariance -- the input review)
    p.add_argument("--track-q", type=positive_process_noise, default=None, metavar="Q",
                   help="--track: process noise, as robustloc track --q (default 1)")
    p.add_argument("--track-weight", "--track-robust", dest="track_weight", default=None,
                   choices=TRACK_WEIGHTS, type=choice(TRACK_WEIGHT_SYNONYMS),
                   help="--track: robust weight, as robustloc track --weight (default "
                        "huber for ranges, asymmetric-igg with --domain rssi)")
    p.add_argument("--track-range-offset", action="store_true",
                   help="--track on ranges: estimate each tag's common range offset (a UWB "
                        "antenna delay) as a state, as robustloc track --range-offset; "
                        "the service then locates from ranges only")
    p.add_argument("--track-link-offsets", nargs="?", const="on", default="off",
                   choices=("off", "on", "auto"), metavar="{off,on,auto}",
                   help="--track: estimate an offset of each link of each tag (dB of RSSI, m "
                        "of ranges) as states, as robustloc track --link-offsets.  The "
                        "option alone is 'on'; 'auto' runs the tracker without and with "
                        "the offsets over the stream's first --track-auto-sample epochs "
                        "(its rows without them meanwhile; about 4x the plain tracker's CPU "
                        "time per epoch), then "
                        "keeps the one whose predictions scored better, as track chooses "
                        "on a log (GET /api/status shows the trial and the choice).  Default "
                        "off: a live stream has no log to look at before its first fix")
    p.add_argument("--track-auto-sample", type=positive_int, default=None,
                   metavar="EPOCHS",
                   help="--track-link-offsets auto: epochs of the trial (default "
                        f"{AUTO_SAMPLE_EPOCHS}, track's sample)")
    p.add_argument("--dim", type=int, choices=(2, 3), default=2,
                   help="solve in 2-D or 3-D (default %(default)s)")
    p.add_argument("--solver", choices=("nonlinear", "linearized"), default="nonlinear",
                   help="as robustloc locate --solver (default %(default)s)")
    p.add_argument("--domain", choices=("range", "rssi"), default="range",
                   help="as robustloc locate --domain, and track --domain with --track "
                        "(default %(default)s)")
    # (as track's and locate's --sigma: a sigma of 1e308 squared overflows -- the input
    # review)
    p.add_argument("--sigma", type=sigma_value, default=None,
                   help="a-priori observation std (m or dB); default the anchors' sigma "
                        "(with --track too, as robustloc track --sigma)")
    p.add_argument("--robust-scale", choices=("mad", "log", "apriori"), default="mad",
                   help="noise scale of the robust methods and of every fix's test: per "
                        "epoch from its residuals (mad, default: a live service has no whole "
                        "log; without --sigma or the anchors' sigma, hpl uses Student's t "
                        "for that estimated scale, a wider bound), per anchor from a "
                        "recorded log (log, needs --scale-from; robustloc locate's default), "
                        "or --sigma (apriori)")
    p.add_argument("--scale-from", default=None, metavar="LOG",
                   help="recorded measurements log whose per-anchor noise scale (robustloc "
                        "locate's first pass) the service uses; implies --robust-scale log")
    p.add_argument("--side-prior", choices=("log", "none"), default="log",
                   help="with --scale-from: place a fix that fits either side of nearly "
                        "collinear anchors on the side where the recorded log's "
                        "unambiguous fixes lie (log, default, as robustloc locate), or "
                        "leave it (none)")
    p.add_argument("--alert-limit", type=positive_float, default=None, metavar="L",
                   help="horizontal alert limit (m), as robustloc locate")
    p.add_argument("--k-noise", type=nonnegative_float, default=None, metavar="K",
                   help="protection levels' noise multiplier, as robustloc locate")
    p.add_argument("--model", choices=("log-distance", "attenuation-factor", "friis"),
                   default=None, help="path-loss columns to use (default: what anchors have)")
    p.add_argument("--no-range-calibration", action="store_true",
                   help="ignore the anchors' bias/scale columns")
    p.add_argument("--value", choices=("rssi", "range"), default=None,
                   help="value the service locates (default: fixed by the first row)")
    p.add_argument("--latency-window", type=nonnegative_float,
                   default=DEFAULT_LATENCY_WINDOW_S, metavar="S",
                   help="seconds (measurement time) an epoch waits for late rows "
                        f"(default {DEFAULT_LATENCY_WINDOW_S})")
    p.add_argument("--idle-flush", type=positive_float, default=DEFAULT_IDLE_FLUSH_S,
                   metavar="S", help="wall-clock seconds after which a silent tag's pending "
                                     f"epochs are solved (default {DEFAULT_IDLE_FLUSH_S})")
    p.add_argument("--time-jump", type=positive_float, default=DEFAULT_TIME_JUMP_S,
                   metavar="S", help="a tag's row more than S seconds (measurement time) "
                                     "behind its newest time, nothing near that time for "
                                     "--idle-flush, means its clock jumped (a restart from "
                                     "0, or one row far ahead): the tag restarts from the "
                                     "new time instead of every later row being late "
                                     f"(default {DEFAULT_TIME_JUMP_S:g})")
    p.add_argument("--mqtt", type=_hostport, default=None, metavar="HOST:PORT",
                   help="also ingest from this MQTT broker")
    p.add_argument("--mqtt-topic", type=_topic, default="robustloc/measurements/#",
                   help="MQTT topic filter (default robustloc/measurements/#); payload: a "
                        "JSON array, NDJSON or one object of rows, as POST /api/measurements")
    p.add_argument("--mqtt-client-id", default=None, metavar="ID",
                   help="MQTT client id (default with --store: robustloc- and a hash "
                        "of the store's absolute path, so the broker keeps the service's "
                        "session and queues messages while it is down; without --store a "
                        "random id and a clean session)")
    p.add_argument("--floorplan", default=None, metavar="IMAGE",
                   help="floor-plan image shown under the map")
    p.add_argument("--floorplan-extent", type=_extent, default=None,
                   metavar="XMIN,YMIN,XMAX,YMAX",
                   help="the image's extent in anchor metres (write --floorplan-extent=-1,... "
                        "when XMIN is negative)")
    p.add_argument("--max-body-bytes", type=positive_int, default=DEFAULT_MAX_BODY_BYTES,
                   help=f"largest body or message (default {DEFAULT_MAX_BODY_BYTES})")
    p.add_argument("--body-timeout", type=positive_float, default=DEFAULT_BODY_TIMEOUT_S,
                   metavar="S",
                   help="seconds a client may take to send a body; then 408 and the "
                        f"connection is closed (default {DEFAULT_BODY_TIMEOUT_S:g})")
    p.add_argument("--header-timeout", type=positive_float,
                   default=DEFAULT_HEADER_TIMEOUT_S, metavar="S",
                   help="seconds a connection may take to send its request's headers; then "
                        "it is closed and counted (a client that never finishes them held "
                        f"a connection for ever; default {DEFAULT_HEADER_TIMEOUT_S:g})")
    p.add_argument("--rate-limit", type=positive_float, default=DEFAULT_RATE_LIMIT_ROWS,
                   metavar="ROWS_PER_S",
                   help=f"ingest rows/s per client address (default {DEFAULT_RATE_LIMIT_ROWS:g})")
    p.add_argument("--max-tags", type=positive_int, default=DEFAULT_MAX_TAGS, metavar="N",
                   help="most tags the service holds state for; the rows of a new tag beyond "
                        "it are rejected with their reason and the tag counted "
                        "(robustloc_tags_refused_total).  Each tag costs some 1.8 kB, 4 kB "
                        "with --track, while it is held (see --forget-after; default "
                        f"{DEFAULT_MAX_TAGS})")
    p.add_argument("--forget-after", type=_forget_after, default=DEFAULT_FORGET_AFTER_S,
                   metavar="S",
                   help="wall-clock seconds without a row after which a tag is forgotten: "
                        "its state (filter, watermarks, row of /api/latest and the map) "
                        "goes, its stored rows stay (GET /api/positions?tag=), and heard "
                        "again it starts afresh; counted in robustloc_tags_forgotten_total "
                        f"(default {DEFAULT_FORGET_AFTER_S:g}: 7 days; 'never' keeps every "
                        "tag while the service runs)")
    p.add_argument("--shutdown-grace", type=positive_float, default=DEFAULT_SHUTDOWN_GRACE_S,
                   metavar="S",
                   help="seconds requests in progress get to finish at SIGTERM/SIGINT, then "
                        "they are cancelled (a body still arriving is not stored; default "
                        f"{DEFAULT_SHUTDOWN_GRACE_S:g}, under a container's usual 10 s)")
    p.add_argument("--cors-origin", action="append", default=[],
                   help="allow this browser origin (repeatable; default: CORS off)")
    p.add_argument("--log-level", default="warning",
                   choices=("critical", "error", "warning", "info", "debug"))


def _check_anchor_ids(anchors, path: str) -> None:
    """Refuse an anchor id longer than the service accepts in a row: no row could name it,
    so the anchor would never be heard, silently (the map review: a 3 000-character id)."""
    from robustloc.errors import InputError
    from robustloc.service.rows import MAX_ID_CHARS

    for a in anchors["anchor"].astype(str):
        if len(a) > MAX_ID_CHARS:
            line = None
            try:
                with open(path, encoding="utf-8", errors="replace") as f:
                    line = next((i for i, ln in enumerate(f, 1) if a in ln), None)
            except OSError:
                pass
            raise InputError(f"anchor id of {len(a)} characters ({a[:24]!r}...): the service "
                             f"accepts ids of at most {MAX_ID_CHARS} characters, so no row "
                             "could name this anchor; shorten it", path, line)


def build(args: argparse.Namespace):
    """The engine, app config and app for ``args`` (used by ``run`` and the tests)."""
    from robustloc.errors import InputError
    from robustloc.io import read_anchors
    from robustloc.service.app import LOOPBACK_HOSTS, ServiceConfig, create_app
    from robustloc.service.processor import LocateProcessor, TrackProcessor

    anchors = read_anchors(args.anchors)
    _check_anchor_ids(anchors, args.anchors)
    if (args.floorplan is None) != (args.floorplan_extent is None):
        raise InputError("--floorplan and --floorplan-extent go together")
    if args.floorplan is not None and not Path(args.floorplan).is_file():
        raise InputError("floor-plan image not found", args.floorplan)
    value = args.value
    if args.time_jump <= args.latency_window:
        raise InputError(f"--time-jump ({args.time_jump:g} s) must be more than "
                         f"--latency-window ({args.latency_window:g} s)")
    if args.track_range_offset:
        if not args.track:
            raise InputError("--track-range-offset goes with --track")
        if value == "rssi":
            raise InputError("--track-range-offset is for ranges: not with --value rssi")
        value = "range"  # an RSSI row is refused: "this service locates from range"
    if args.domain == "rssi" and value == "range":
        # (the tracker and the fixes fit RSSI in dB only: with ranges the option did
        # nothing, and --track-range-offset --domain rssi refused every RSSI row as "this
        # service locates from range": the service review, 2026-12-06; `track` and
        # `locate` refuse it alike)
        raise InputError("--domain rssi fits RSSI in dB: not with "
                         + ("--track-range-offset (ranges)" if args.track_range_offset
                            else "--value range"))
    _check_mode_options(args)
    if args.track_link_offsets != "off":
        if not args.track:
            raise InputError("--track-link-offsets goes with --track")
        if args.track_range_offset and args.track_link_offsets == "on":
            raise InputError("--track-range-offset and --track-link-offsets exclude each "
                             "other: the links' offsets include the common one; choose one")
    if args.track_auto_sample is not None and args.track_link_offsets != "auto":
        raise InputError("--track-auto-sample goes with --track-link-offsets auto")
    try:
        if args.track:
            opts: dict[str, object] = {"sigma": args.sigma, "domain": args.domain}
            if args.track_q is not None:
                opts["q"] = args.track_q
            if args.track_weight is not None:
                opts["weight"] = args.track_weight
            if args.track_range_offset:
                opts["range_offset"] = True
            opts["link_offsets"] = args.track_link_offsets
            if args.track_auto_sample is not None:
                opts["auto_sample_epochs"] = args.track_auto_sample
            processor = TrackProcessor(anchors, model=args.track_model, filter=args.track_filter,
                                       **opts)
        else:
            settings = dict(dim=args.dim, solver=args.solver, domain=args.domain,
                            sigma=args.sigma, model=args.model,
                            range_calibration=not args.no_range_calibration,
                            k_noise=args.k_noise, alert_limit=args.alert_limit)
            scale = share = sides = None
            robust_scale = args.robust_scale
            if args.scale_from is not None:
                # a log of the other values: its noise scale (m against dB) was applied
                # without a word, and ``--value`` said nothing (the service review)
                logged = LocateProcessor.log_value(args.scale_from)
                if value is not None and logged != value:
                    raise InputError(f"holds {logged} rows; this service locates from "
                                     f"{value} (--value): give a log of {value} rows",
                                     args.scale_from)
                value = logged  # (the service locates what its scale was measured on)
                scale, share, sides = LocateProcessor.log_statistics_from(
                    args.scale_from, anchors, method=args.method, sides=True, **settings)
                robust_scale = "log"
                if args.side_prior == "none":
                    sides = ()
                from robustloc.pipelines.locate import anchor_warnings, suspect_of_scale

                suspect = suspect_of_scale(scale, [str(a) for a in anchors["anchor"]])
                for line in anchor_warnings({"anchors_suspect": suspect}, args.anchors):
                    print(f"warning: {line}", file=sys.stderr, flush=True)
            processor = LocateProcessor(anchors, method=args.method,
                                        robust_scale=robust_scale, log_scale=scale,
                                        log_gross_share=share, log_sides=sides, **settings)
    except InputError:
        raise
    except ValueError as exc:
        raise InputError(str(exc), args.anchors) from None
    lock = _lock_store(args.store)
    try:
        engine = _open_engine(args, anchors, processor, value)
        mqtt = None
        if args.mqtt is not None:
            from robustloc.service.mqtt import MqttIngest, client_id_for_store

            client_id = args.mqtt_client_id
            if client_id is None and args.store is not None:
                client_id = client_id_for_store(args.store)
            mqtt = MqttIngest(engine, args.mqtt[0], args.mqtt[1], args.mqtt_topic,
                              max_payload_bytes=args.max_body_bytes,
                              client_id=client_id or "",
                              persistent=bool(client_id) and args.store is not None)
        token = args.token if args.token is not None else os.environ.get("ROBUSTLOC_TOKEN")
        cfg = ServiceConfig(
            token=token or None, max_body_bytes=args.max_body_bytes,
            body_timeout_s=args.body_timeout,
            rate_limit_rows=args.rate_limit, cors_origins=tuple(args.cors_origin),
            floorplan=None if args.floorplan is None else Path(args.floorplan),
            floorplan_extent=args.floorplan_extent, mqtt=mqtt, store_lock=lock,
            allowed_hosts=LOOPBACK_HOSTS if args.host in LOOPBACK_HOSTS else None,
        )
        return engine, cfg, create_app(engine, cfg)
    except BaseException:
        if lock is not None:
            lock.release()
        raise


def _lock_store(store: str | None):
    """The store's lock (``DIR/.lock``, held for the service's life), or None without a
    store.  Taken before the store is opened: opening seals the logs it finds, and two
    services on one store lost the first one's acknowledged rows."""
    from robustloc.errors import InputError
    from robustloc.service.store import StoreError, StoreLock

    if store is None:
        return None
    try:
        return StoreLock(store, what="server")
    except StoreError as exc:
        raise InputError(exc.message, exc.path) from None


def _open_engine(args: argparse.Namespace, anchors, processor, value: str | None):
    """The :class:`Engine`, its start-up errors named by the file they concern: a damaged
    store file by that file (they were all named the anchors file)."""
    import json
    import pickle

    import pyarrow as pa

    from robustloc.errors import InputError
    from robustloc.service.engine import Engine
    from robustloc.service.store import StoreError

    store = None if args.store is None else Path(args.store)
    if store is not None:
        _check_meta(store / "meta.json")
    try:
        return Engine(anchors, processor, store_dir=args.store,
                      latency_window_s=args.latency_window, idle_flush_s=args.idle_flush,
                      time_jump_s=args.time_jump, value=value, max_tags=args.max_tags,
                      forget_after_s=args.forget_after)
    except StoreError as exc:  # in use, or a damaged segment: named by its file
        raise InputError(exc.message, exc.path) from None
    except (pickle.UnpicklingError, EOFError, AttributeError, ImportError) as exc:
        if store is None:
            raise
        raise InputError(f"damaged tracker snapshot ({type(exc).__name__}: {exc}); move it "
                         "aside to start the tracks anew",
                         store / "state" / "processor.pkl") from None
    except pa.ArrowException as exc:  # a segment whose footer reads but whose data do not
        if store is None:
            raise
        raise InputError(f"damaged store: {exc}", store) from None
    except json.JSONDecodeError as exc:
        raise InputError(f"damaged store metadata (not JSON: {exc})",
                         store / "meta.json" if store else args.anchors) from None
    except ValueError as exc:  # --value the anchors cannot locate, or a store of another
        # kind of rows or values ("the store ..."): named by the store
        where = store if store is not None and str(exc).startswith("the store") else None
        raise InputError(str(exc), where or args.anchors) from None


def _check_meta(meta: Path) -> None:
    """Refuse a damaged ``meta.json`` by name (a truncated file gave a JSON message
    attributed to the anchors file)."""
    import json

    from robustloc.errors import InputError

    try:
        text = meta.read_text(encoding="utf-8")
    except FileNotFoundError:
        return
    except UnicodeDecodeError:
        raise InputError("damaged store metadata (not UTF-8 text)", meta) from None
    try:
        saved = json.loads(text)
    except json.JSONDecodeError as exc:
        raise InputError(f"damaged store metadata (not JSON: {exc})", meta) from None
    if not isinstance(saved, dict):
        raise InputError("damaged store metadata (not a JSON object)", meta)


def _listen(host: str, port: int) -> list[Any]:
    """Listening sockets for ``host`` (every address it resolves to, as asyncio's server
    binds) on ``port`` (0: a free port, the same on each address); ``OSError`` (address
    in use, no such host, not this machine's address) before anything else starts.

    uvicorn bound after the service had started: a port in use, a bad host or port ended
    it with uvicorn's own log line and exit 3, after the "serving at" line, and ``--port
    0`` was announced as port 0 (the service review)."""
    import socket

    infos = socket.getaddrinfo(host or None, port, type=socket.SOCK_STREAM,
                               flags=socket.AI_PASSIVE)
    socks: list[socket.socket] = []
    seen: set[tuple] = set()
    try:
        for family, kind, proto, _, addr in infos:
            if (family, addr[:2]) in seen:
                continue
            seen.add((family, addr[:2]))
            s = socket.socket(family, kind, proto)
            socks.append(s)
            s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            if family == socket.AF_INET6 and len(infos) > 1:
                s.setsockopt(socket.IPPROTO_IPV6, socket.IPV6_V6ONLY, 1)
            if port == 0 and len(socks) > 1:  # the first's free port on every address
                addr = (addr[0], socks[0].getsockname()[1], *addr[2:])
            s.bind(addr)
            s.listen(2048)
            s.set_inheritable(True)
    except OSError:
        for s in socks:
            s.close()
        raise
    return socks


def _url(host: str, port: int) -> str:
    """``http://HOST:PORT/``, an IPv6 address in brackets."""
    return f"http://[{host}]:{port}/" if ":" in host else f"http://{host}:{port}/"


def run(args: argparse.Namespace) -> int:
    try:
        import uvicorn
    except ImportError:
        print("error: robustloc serve needs the [serve] extra: pip install 'robustloc[serve]'",
              file=sys.stderr)
        return 2
    token = args.token if args.token is not None else os.environ.get("ROBUSTLOC_TOKEN")
    if token and not (token.isascii() and token.isprintable() and token == token.strip()):
        # an HTTP header carries bytes that servers read as Latin-1: a token of other
        # characters, sent as UTF-8 (curl from a UTF-8 terminal), never matched (the
        # service review: 401 for the right token)
        where = "--token" if args.token is not None else "ROBUSTLOC_TOKEN"
        print(f"error: {where}: use printable ASCII characters without surrounding "
              "spaces (an HTTP header cannot carry others the same way from every client)",
              file=sys.stderr)
        return 2
    try:
        engine, cfg, app = build(args)
    except RuntimeError as exc:  # --track without robustloc.tracking
        print(f"error: {exc}", file=sys.stderr)
        return 2
    try:  # bound now, the inputs checked: a port in use or a bad host is the user's
        sockets = _listen(args.host, args.port)
    except OSError as exc:  # (socket.gaierror for a host that does not resolve)
        import errno

        engine.stop()  # (never started: closes the store, solves nothing)
        if cfg.store_lock is not None:
            cfg.store_lock.release()
        why = (exc.strerror or str(exc)).rstrip(".").lower()
        if exc.errno == errno.EADDRINUSE:
            why += " (give another --port, or --port 0 for any free one)"
        print(f"error: cannot listen on {_url(args.host, args.port)[7:-1]}: {why}",
              file=sys.stderr)
        return 2
    try:
        return _serve(args, uvicorn, sockets, engine, cfg, app)
    finally:
        for s in sockets:
            s.close()


def _serve(args: argparse.Namespace, uvicorn: Any, sockets: list[Any], engine: Any,
           cfg: Any, app: Any) -> int:
    """``run`` on bound ``sockets``, with what :func:`build` made."""
    if args.store is None:
        print("warning: no --store: rows and positions are kept in memory only and are lost "
              "when the service stops", file=sys.stderr)
    if args.host not in ("127.0.0.1", "::1", "localhost") and not cfg.token:
        print(f"warning: listening on {args.host} without a token: anyone who can reach "
              "this port can send and read data (set --token or ROBUSTLOC_TOKEN)",
              file=sys.stderr)
    if engine.recovered_rows:
        print(f"resumed from {args.store}: {engine.recovered_rows} stored rows not yet solved",
              file=sys.stderr)
    # timeout_graceful_shutdown: at SIGTERM a request still receiving its body (a client
    # that stopped sending) held the process for --body-timeout; now it is cancelled
    from robustloc.service.protocol import answer_then_close_ws_protocol, header_timeout_protocol

    http = header_timeout_protocol(
        args.header_timeout, lambda: engine.metrics.request_rejected("header_timeout"))
    config = uvicorn.Config(app, host=args.host, port=args.port, log_level=args.log_level,
                            ws_max_size=args.max_body_bytes, lifespan="on",
                            timeout_keep_alive=30, access_log=False,
                            timeout_graceful_shutdown=args.shutdown_grace,
                            http=http or "auto", ws=answer_then_close_ws_protocol() or "auto")
    from robustloc.service.serverlog import count_server_refusals

    # (after the Config: it configures the loggers)
    count_server_refusals(engine.metrics, logging.getLevelName(args.log_level.upper()))
    server = uvicorn.Server(config)
    port = sockets[0].getsockname()[1]  # (--port 0: the one the system gave)
    print(f"robustloc serve: {_url(args.host, port)} ({engine.processor.name}, "
          f"latency window {args.latency_window:g} s)", file=sys.stderr, flush=True)
    stopped_by = _run_until_stopped(server, sockets)
    if cfg.store_lock is not None:
        cfg.store_lock.release()
    if stopped_by:
        kept = (f"; every acknowledged row is in {args.store}" if args.store is not None
                else " (no --store: its rows are gone)")
        print(f"robustloc serve: stopped ({stopped_by}){kept}", file=sys.stderr, flush=True)
    return 0


def _run_until_stopped(server: Any, sockets: list[Any] | None = None) -> str:
    """Run ``server`` (a ``uvicorn.Server``) to its graceful shutdown; returns the name of
    the signal that stopped it ("" if none did).

    uvicorn catches SIGTERM and SIGINT, shuts down, then raises the signal again for the
    handlers it found: the command line's turned that normal stop into ``error:
    terminated`` and exit code 143 (a service manager then reports the unit failed).  The
    handlers it finds here only note the signal, and restore the command line's after.
    """
    import signal

    got: list[int] = []

    def note(signum: int, frame: object) -> None:
        got.append(signum)

    old = {sig: signal.signal(sig, note) for sig in (signal.SIGTERM, signal.SIGINT)}
    try:
        server.run(sockets=sockets)
    finally:
        for sig, handler in old.items():
            signal.signal(sig, handler)
    return signal.Signals(got[0]).name if got else ""
