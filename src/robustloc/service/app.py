"""The ASGI application (Starlette) of ``robustloc serve``.

Endpoints (the API is a contract; see the README's "Live service" section)::

    POST /api/measurements      JSON array or NDJSON of rows -> 202 {accepted, rejected}
                                (no query parameter but ``token``)
    GET  /api/positions         ?tag=&since=&until=&limit=  -> JSON array of position rows,
                                sorted by time then tag: the *latest* ``limit`` (100 000)
                                matching rows; header ``X-Total-Count`` the rows matching,
                                ``X-Truncated: true`` when the earliest were left out
                                (fetch them with a narrower ``since``/``until``)
    GET  /api/anchors           anchors with per-anchor health
    GET  /api/latest            latest position row per tag
    GET  /api/status            service settings and counters (for the map page)
    GET  /healthz               liveness ({"status": "ok"}; no token needed, no data)
    GET  /metrics               Prometheus text format
    WS   /ws/positions[?tag=T]  every position row as one JSON text message; with
                                ?batch=1 one message per solved block: a JSON array of
                                its rows (what the map page uses: one message per row
                                costs the server as much as solving the row)
    WS   /ws/measurements       ingest: each message a body as POST; answered like POST
                                (a store write failure: the 507 answer, then the socket
                                is closed with 1013 "try again later")
    WS   any other path         accepted, then closed with 1008 and a reason (counted as
                                ``not_found``, as an HTTP request to an unknown path)

A query parameter an endpoint does not take (:data:`QUERY_PARAMS`; ``token`` on every
endpoint behind the token), or one given twice, is answered ``400`` naming it and counted
as ``bad_query`` (a WebSocket: HTTP 400 at the handshake, before it is accepted).

A body the store cannot write (disk full, I/O error) is answered ``507 Insufficient
Storage`` with the reason and counted as ``store_error``; none of its rows is stored, so
the client may resend it whole.  A positions query the store cannot read (a segment
damaged while the service runs) is answered ``500`` with the store's reason, naming the
file, counted as ``store_error`` alike.  A positions query still waiting for its read slot
when the stop's ``--shutdown-grace`` runs out is answered ``503`` with ``Retry-After`` (as
a body still arriving), counted as ``shutting_down``; one whose client left while it
waited is not read (``client_disconnect``).
    GET  /                      the live map page (static; data come with the token)

When a token is set, every endpoint except ``/``, ``/static`` and ``/healthz`` needs
``Authorization: Bearer TOKEN`` (WebSockets may send ``?token=TOKEN`` instead, since
browsers cannot set headers on a WebSocket).  An HTTP request without it gets ``401``; a
WebSocket without it is refused at the handshake with HTTP ``403`` (closed before it is
accepted, so no close code is ever sent), counted as ``unauthorized`` alike.
"""

from __future__ import annotations

import asyncio
import collections
import contextlib
import gc
import hmac
import json
import math
import sys
import threading
import time
from collections.abc import AsyncIterator, Callable
from contextlib import asynccontextmanager
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path
from typing import TYPE_CHECKING

import anyio
import pandas as pd
from starlette.applications import Starlette
from starlette.exceptions import HTTPException
from starlette.requests import ClientDisconnect, Request
from starlette.responses import FileResponse, JSONResponse, PlainTextResponse, Response
from starlette.routing import Mount, Route, WebSocketRoute
from starlette.staticfiles import StaticFiles
from starlette.types import ASGIApp, Receive, Scope, Send
from starlette.websockets import WebSocket, WebSocketDisconnect

from robustloc.service.defaults import (
    DEFAULT_BODY_TIMEOUT_S,
    DEFAULT_MAX_BODY_BYTES,
    DEFAULT_RATE_LIMIT_ROWS,
    MAX_CONCURRENT_POSITION_READS,
    MAX_CONCURRENT_ROW_PARSES,
    MAX_ROWS_PER_BODY,
)
from robustloc.service.engine import Engine
from robustloc.service.protocol import WS_STATE_KEY
from robustloc.service.rows import BodyError, RowBatch, parse_body, rows_beyond
from robustloc.service.store import StoreError, StoreLock, StoreWriteError

if TYPE_CHECKING:  # (paho-mqtt is imported only with --mqtt)
    from robustloc.service.mqtt import MqttIngest

#: Queued messages per position subscriber before the oldest are dropped (and counted).
WS_QUEUE = 20_000
#: Queued characters (bytes of the ASCII JSON) per position subscriber before the oldest
#: messages are dropped (and counted): 32 MiB, some 100 000 rows, 5 s of a 10 Hz service's
#: blocks at 2 000 tags.  The count alone let a ``batch=1`` subscriber that never reads
#: hold 20 000 whole blocks (some 13 GB at 2 000 tags; the serve review).
WS_QUEUE_BYTES = 32 * 1024 * 1024
#: WebSocket close code "message too big" (RFC 6455 sec. 7.4.1).
WS_MESSAGE_TOO_BIG = 1009
#: WebSocket close code "policy violation" (RFC 6455 sec. 7.4.1).
WS_POLICY_VIOLATION = 1008
#: WebSocket close code "internal error" (RFC 6455 sec. 7.4.1, IANA registry).
WS_INTERNAL_ERROR = 1011
#: WebSocket close code "try again later" (IANA registry): the store cannot write now.
WS_TRY_AGAIN_LATER = 1013
#: HTTP status of a body the store could not write (RFC 4918 sec. 11.5).
INSUFFICIENT_STORAGE = 507
#: Seconds a client is told to wait after a store write failure (``Retry-After``).
STORE_RETRY_AFTER_S = 5
#: Status of a query whose client left before it was read (nginx's "client closed
#: request"): never sent, it is for the access log.
CLIENT_CLOSED_REQUEST = 499


def _close_reason(text: str) -> str:
    """``text`` cut to fit a close frame's reason (at most 123 bytes of UTF-8)."""
    data = text.encode()
    return text if len(data) <= 123 else data[:120].decode(errors="ignore") + "..."


@dataclass
class ServiceConfig:
    """Settings of the HTTP layer (the engine holds the rest)."""

    token: str | None = None
    max_body_bytes: int = DEFAULT_MAX_BODY_BYTES
    body_timeout_s: float = DEFAULT_BODY_TIMEOUT_S
    rate_limit_rows: float = DEFAULT_RATE_LIMIT_ROWS
    cors_origins: tuple[str, ...] = ()
    floorplan: Path | None = None
    floorplan_extent: tuple[float, float, float, float] | None = None
    mqtt: MqttIngest | None = None  # a started/stoppable MQTT ingest
    info: dict = field(default_factory=dict)
    #: the store's lock (``robustloc serve --store``), released when the app shuts down
    store_lock: StoreLock | None = None
    #: host names a request's ``Host`` must name (None: any); ``robustloc serve`` bound
    #: to a loopback address answers only those of this machine (:class:`SameSiteGuard`)
    allowed_hosts: tuple[str, ...] | None = None


#: What a page of a ``--cors-origin`` may ask for: its methods, and the request headers
#: (Starlette's CORSMiddleware adds the CORS-safelisted ones to ``allow_headers``).
CORS_METHODS = ("GET", "POST")
CORS_HEADERS = ("accept", "accept-language", "authorization", "content-language",
                "content-type")

#: The host names of this machine's loopback interface.
LOOPBACK_HOSTS = ("127.0.0.1", "localhost", "::1")


class SameSiteGuard:
    """ASGI middleware: what a web page of another site must not do through the user's
    browser (the map review: with no token, any page the user had open could add rows by
    a ``no-cors`` POST and read every live position over a WebSocket; CORS, which
    browsers do not apply to either, did not stop them).

    * A POST or a WebSocket handshake whose ``Origin`` is neither the service's own
      (``http(s)://`` its ``Host``) nor one of ``--cors-origin`` is refused (403),
      counted as ``cross_origin``.  Clients that are not browsers send no ``Origin``.
    * With ``allowed_hosts`` (a service bound to a loopback address), a browser's request
      (one with ``Origin`` or ``Sec-Fetch-*`` headers) whose ``Host`` names another host
      is refused (403, ``foreign_host``): a page of a name that an attacker's DNS points
      at 127.0.0.1 ("DNS rebinding") is then of the same origin as the service, and only
      its ``Host`` tells it apart.
    """

    def __init__(self, app: ASGIApp, cors_origins: tuple[str, ...],
                 allowed_hosts: tuple[str, ...] | None,
                 on_refuse: Callable[[str], None]) -> None:
        self.app = app
        self.cors_origins = set(cors_origins)
        self.allowed_hosts = None if allowed_hosts is None else {
            h.lower().strip("[]") for h in allowed_hosts}
        self.on_refuse = on_refuse

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        kind = scope["type"]
        if kind not in ("http", "websocket"):
            await self.app(scope, receive, send)
            return
        host = origin = pre_method = pre_headers = None
        browser = False
        for k, v in scope.get("headers") or ():
            if k == b"host":
                host = v.decode("latin-1")
            elif k == b"origin":
                origin = v.decode("latin-1")
            elif k.startswith(b"sec-fetch-"):
                browser = True
            elif k == b"access-control-request-method":
                pre_method = v.decode("latin-1")
            elif k == b"access-control-request-headers":
                pre_headers = v.decode("latin-1")
        why = None
        status = 403
        # (the Host is checked on a browser's requests, which name it from the page's
        # address: tools and gateways on this machine may name it as they like)
        if self.allowed_hosts is not None and (browser or origin is not None):
            if _host_name(host or "") not in self.allowed_hosts:
                why = ("foreign_host", f"Host {host!r} is not this machine's: the service "
                       "listens on a loopback address (open it as 127.0.0.1 or localhost)")
        if why is None and origin is not None and (
                kind == "websocket" or scope.get("method") not in ("GET", "HEAD", "OPTIONS")):
            own = {f"http://{host}", f"https://{host}"} if host else set()
            if origin not in own and origin not in self.cors_origins \
                    and "*" not in self.cors_origins:
                why = ("cross_origin", f"a page of {origin} may not send to or listen to "
                       "this service (allow it with --cors-origin)")
        if (why is None and self.cors_origins and origin is not None and pre_method is not None
                and scope.get("method") == "OPTIONS"):
            # a CORS preflight that --cors-origin does not allow: refused here, with a
            # reason and counted (Starlette's CORSMiddleware answered it in plain text,
            # uncounted; the serve review of 2026-12-06)
            status = 400
            asked = {h.strip().lower() for h in (pre_headers or "").split(",") if h.strip()}
            if origin not in self.cors_origins and "*" not in self.cors_origins:
                why = ("cors_preflight", f"a page of {origin} may not send to this service "
                       "(allow it with --cors-origin)")
            elif pre_method.upper() not in CORS_METHODS:
                why = ("cors_preflight", f"method {pre_method[:20]!r} is not allowed across "
                       f"origins ({', '.join(CORS_METHODS)})")
            elif not asked <= set(CORS_HEADERS):
                why = ("cors_preflight", "headers "
                       f"{', '.join(sorted(asked - set(CORS_HEADERS)))[:80]!r} are not "
                       f"allowed across origins ({', '.join(CORS_HEADERS)})")
        if why is None:
            await self.app(scope, receive, send)
            return
        self.on_refuse(why[0])
        if kind == "websocket":  # (before the accept: uvicorn answers the handshake 403)
            await send({"type": "websocket.close", "code": 1008, "reason": why[1][:120]})
            return
        body = json.dumps({"error": why[1]}).encode()
        await send({"type": "http.response.start", "status": status,
                    "headers": [(b"content-type", b"application/json"),
                                (b"content-length", str(len(body)).encode())]})
        await send({"type": "http.response.body", "body": body})


def _host_name(host: str) -> str:
    """The name of a ``Host`` header, without its port and brackets, in lower case
    (``[::1]:8080`` -> ``::1``, ``LocalHost:80`` -> ``localhost``)."""
    name = host.split("]", 1)[0] if host.startswith("[") else host.rsplit(":", 1)[0]
    return name.lower().strip("[]")


class _Bucket:
    __slots__ = ("tokens", "t")

    def __init__(self, tokens: float) -> None:
        self.tokens = tokens
        self.t = time.monotonic()


class RateLimiter:
    """Token bucket per client address: ``rate`` rows/s on average, bursts of ``2 * rate``.

    A body is admitted while the client's bucket is not in debt, and its rows are then
    taken (the bucket may go negative), so a body larger than the burst still passes once
    and the client then waits until the debt is repaid at ``rate`` rows/s.
    """

    def __init__(self, rate: float) -> None:
        self.rate = rate
        self.buckets: dict[str, _Bucket] = {}
        self.lock = threading.Lock()

    def take(self, client: str, n: int) -> float:
        """0 when ``n`` rows may pass (and they are taken), else the seconds to wait."""
        if not math.isfinite(self.rate):
            return 0.0
        cap = 2 * self.rate
        b = self.buckets.get(client)
        if b is None:
            if len(self.buckets) > 10_000:
                self.buckets.clear()
            b = self.buckets[client] = _Bucket(cap)
        now = time.monotonic()
        b.tokens = min(cap, b.tokens + (now - b.t) * self.rate)
        b.t = now
        if b.tokens <= 0:
            return max(-b.tokens / self.rate, 1e-3)
        b.tokens -= n
        return 0.0


class Outbox:
    """A position subscriber's messages waiting to be sent, bounded by their number and
    their size: past either bound the oldest are dropped, the newest always kept (one
    message larger than ``max_chars`` is held alone).  Used from the event loop only.

    Parameters
    ----------
    max_messages : int
        Most messages held (:data:`WS_QUEUE`).
    max_chars : int
        Most characters held, summed over the messages (:data:`WS_QUEUE_BYTES`; the
        messages are ASCII JSON: characters are bytes).
    """

    def __init__(self, max_messages: int = WS_QUEUE, max_chars: int = WS_QUEUE_BYTES) -> None:
        self.max_messages = max_messages
        self.max_chars = max_chars
        self._items: collections.deque[str] = collections.deque()
        #: characters held
        self.chars = 0
        self._ready = asyncio.Event()

    def __len__(self) -> int:
        return len(self._items)

    def put(self, msg: str) -> int:
        """Append ``msg``; returns how many of the oldest messages were dropped for it."""
        self._items.append(msg)
        self.chars += len(msg)
        dropped = 0
        while len(self._items) > 1 and (len(self._items) > self.max_messages
                                        or self.chars > self.max_chars):
            self.chars -= len(self._items.popleft())
            dropped += 1
        self._ready.set()
        return dropped

    async def get(self) -> str:
        """The oldest message (waits for one)."""
        while not self._items:
            self._ready.clear()
            await self._ready.wait()
        msg = self._items.popleft()
        self.chars -= len(msg)
        return msg


class Hub:
    """Fan-out of position rows to WebSocket subscribers (one bounded :class:`Outbox`
    each, by messages and by size).

    A subscriber gets every row as one message, or (``batch``) one message per solved
    block, the JSON array of its rows; ``tag`` keeps one tag's rows only.
    """

    def __init__(self, engine: Engine) -> None:
        self.engine = engine
        self.loop: asyncio.AbstractEventLoop | None = None
        self.subs: dict[int, tuple[Outbox, str | None, bool]] = {}

    @property
    def queued_chars(self) -> int:
        """Characters queued for every subscriber (``robustloc_ws_queued_bytes``)."""
        return sum(q.chars for q, _, _ in list(self.subs.values()))

    def publish(self, frame: pd.DataFrame) -> None:
        """Called from the solver thread."""
        if not self.subs or self.loop is None or len(frame) == 0:
            return
        lines = records_json(frame)
        tags = frame["tag"].astype(str).tolist()
        whole = ("[" + ",".join(lines) + "]"
                 if any(b and t is None for _, t, b in list(self.subs.values())) else None)
        self.loop.call_soon_threadsafe(self._deliver, tags, lines, whole)

    def _deliver(self, tags: list[str], lines: list[str], whole: str | None) -> None:
        for q, tag, batch in list(self.subs.values()):
            if tag is None:
                mine = lines
            else:
                mine = [ln for t, ln in zip(tags, lines) if t == tag]
            if batch:
                if not mine:
                    continue
                self._put(q, whole if tag is None and whole is not None
                          else "[" + ",".join(mine) + "]")
            else:
                for ln in mine:
                    self._put(q, ln)

    def _put(self, q: Outbox, msg: str) -> None:
        dropped = q.put(msg)
        if dropped:
            self.engine.metrics.ws_dropped += dropped


try:  # round-trip float formatting (shortest repr), NaN and infinities as null
    from msgspec.json import encode as _encode
except ImportError:  # pragma: no cover - depends on the environment
    def _encode(obj: object) -> bytes:
        return json.dumps(_nan_to_none(obj), separators=(",", ":")).encode()


def _nan_to_none(obj: object) -> object:
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, dict):
        return {k: _nan_to_none(v) for k, v in obj.items()}
    if isinstance(obj, list):
        return [_nan_to_none(v) for v in obj]
    return obj


def records_json(frame: pd.DataFrame) -> list[str]:
    """One JSON object per row of ``frame``, every float written so that it reads back
    exactly (``time`` 3.3000000000000003 stays that; pandas' ``to_json`` keeps at most 15
    decimals), NaN and infinities as ``null`` (JSON has neither)."""
    cols = [str(c) for c in frame.columns]
    data = [frame[c].tolist() for c in frame.columns]  # native Python scalars per column
    # (row dicts from the columns: 4x faster than to_dict("records"), 2x than to_json)
    return [_encode(dict(zip(cols, row))).decode() for row in zip(*data)]


def _array_json(frame: pd.DataFrame) -> str:
    return "[" + ",".join(records_json(frame)) + "]"


def _array_json_bytes(frame: pd.DataFrame, chunk: int = 8192) -> bytes:
    """:func:`_array_json` of ``frame`` as UTF-8 bytes (the same bytes), encoded
    ``chunk`` rows at a time: the Python objects of one chunk are held at once, not
    those of every row (100 000 rows held some 100 MB of them besides the body).

    Parameters
    ----------
    frame : DataFrame
        The rows.
    chunk : int
        Rows encoded at once.

    Returns
    -------
    bytes
        The JSON array of the rows' objects.
    """
    cols = [str(c) for c in frame.columns]
    parts = []
    for i in range(0, len(frame), chunk):
        part = frame.iloc[i:i + chunk]
        data = [part[c].tolist() for c in part.columns]
        parts.append(b",".join([_encode(dict(zip(cols, row))) for row in zip(*data)]))
    # (rows without columns encode to nothing: ``[,,]`` over 8 192 of them, not ``[]``)
    return b"[" + b",".join([p for p in parts if p]) + b"]"


def _static_dir() -> Path:
    return Path(str(resources.files("robustloc.service") / "static"))


def _json(obj: object, status: int = 200) -> JSONResponse:
    return JSONResponse(obj, status_code=status)


#: Query parameters each endpoint takes (``token``: the token may come in the query).
#: Any other, or one given twice, is refused ``400`` and counted as ``bad_query``: a
#: misspelled ``tags=A`` or ``from=5`` answered everything, ``tag=A&tag=B`` only B, and
#: nothing said so (the API review).
QUERY_PARAMS: dict[str, frozenset[str]] = {
    "/api/positions": frozenset({"tag", "since", "until", "limit", "token"}),
    "/ws/positions": frozenset({"tag", "batch", "token"}),
}
#: What every other endpoint behind the token takes.
TOKEN_ONLY = frozenset({"token"})


def query_problem(items: list[tuple[str, str]], allowed: frozenset[str]) -> str | None:
    """Why a query string is refused, or None when it is fine.

    Parameters
    ----------
    items : list of (str, str)
        The query's ``(name, value)`` pairs, in order, repeats included.
    allowed : frozenset of str
        The names the endpoint takes.

    Returns
    -------
    str or None
        The reason naming the parameter (unknown, or given more than once).
    """
    seen: set[str] = set()
    for name, _ in items:
        if name not in allowed:
            takes = ", ".join(sorted(allowed))
            return f"unknown query parameter {name!r} (this endpoint takes {takes})"
        if name in seen:
            return f"query parameter {name!r} given more than once"
        seen.add(name)
    return None


def create_app(engine: Engine, config: ServiceConfig | None = None) -> Starlette:
    """Build the Starlette app around a (not yet started) :class:`Engine`."""
    cfg = config or ServiceConfig()
    hub = Hub(engine)
    limiter = RateLimiter(cfg.rate_limit_rows)
    engine.add_listener(hub.publish)

    def authorized(headers, query) -> bool:
        if not cfg.token:
            return True
        auth = headers.get("authorization", "")
        given = auth[7:] if auth[:7].lower() == "bearer " else query.get("token", "")
        return hmac.compare_digest(given.encode(), cfg.token.encode())

    def refuse(reason: str, status: int, message: str, **headers: str) -> JSONResponse:
        engine.metrics.request_rejected(reason)
        return JSONResponse({"error": message}, status_code=status, headers=headers or None)

    def unauthorized() -> JSONResponse:
        return refuse("unauthorized", 401, "missing or wrong bearer token",
                      **{"WWW-Authenticate": "Bearer"})

    def bad_params(request: Request) -> JSONResponse | None:
        """The ``400`` for a query parameter the endpoint does not take, or given twice."""
        allowed = QUERY_PARAMS.get(request.url.path, TOKEN_ONLY)
        why = query_problem(request.query_params.multi_items(), allowed)
        return None if why is None else refuse("bad_query", 400, f"bad query: {why}")

    parse_slots = threading.BoundedSemaphore(MAX_CONCURRENT_ROW_PARSES)
    #: the slots of ``GET /api/positions``: at most this many queries read the store and
    #: build their body at once (each in a worker thread, not of anyio's default pool,
    #: which ingest (POST, WebSocket) and the shutdown use), the others wait holding no
    #: thread (:func:`read_positions`)
    position_reads = anyio.CapacityLimiter(MAX_CONCURRENT_POSITION_READS)

    def positions_body(tag: str | None, since: float | None, until: float | None,
                       limit: int) -> tuple[bytes, int, int]:
        """The JSON body of a positions query, its rows and the rows matching (in a
        worker thread of ``position_reads``)."""
        df, total = engine.positions_counted(tag, since, until, limit)
        return _array_json_bytes(df), len(df), total

    def ingest_sync(data: bytes | str, source: str, client: str) -> tuple[int, dict]:
        """Parse, rate-limit and ingest one body (in a worker thread, off the event loop)."""
        batch = engine.decode(data)  # a JSON array of valid rows (the common case)
        # refused before anything is decoded row by row: parsing first cost 1.5 GB for a
        # 32 MiB body of `{}` lines, refused after (the serve review); a body the fast
        # decoder took is refused alike (it went through above --max-body-bytes 44 MB:
        # the review of the fix)
        n = (rows_beyond(data, MAX_ROWS_PER_BODY) if batch is None
             else len(batch) if len(batch) > MAX_ROWS_PER_BODY else None)
        if n is not None:
            engine.metrics.request_rejected("too_many_rows")
            return 413, {"error": f"body holds {n} rows, more than "
                                  f"{MAX_ROWS_PER_BODY}: send it in parts"}
        if batch is None:
            with parse_slots:  # (a bound on the memory of bodies decoded row by row)
                return ingest_rows(data, source, client)
        return ingest_rows(batch, source, client)

    def ingest_rows(data: bytes | str | RowBatch, source: str, client: str
                    ) -> tuple[int, dict]:
        """Rate-limit and ingest the rows of a :class:`RowBatch`, or of a body decoded
        row by row here."""
        batch = data if isinstance(data, RowBatch) else None
        if batch is None:
            try:
                rows, _ = parse_body(data)
            except BodyError as exc:
                engine.metrics.request_rejected("not_rows")
                return exc.status, {"error": str(exc)}
        with limiter.lock:
            wait = limiter.take(client, len(rows) if batch is None else len(batch))
        if wait > 0:
            engine.metrics.request_rejected("rate_limited")
            return 429, {"error": f"rate limit of {cfg.rate_limit_rows:g} rows/s exceeded",
                         "retry_after_s": round(wait, 3)}
        try:
            if batch is None:
                return 202, engine.ingest(rows, source).to_json()
            return 202, engine.ingest_batch(batch, source).to_json()
        except StoreWriteError as exc:  # disk full, I/O error: nothing of the body stored
            engine.metrics.request_rejected("store_error")
            return INSUFFICIENT_STORAGE, {
                "error": f"{exc.message}: none of the body's rows was stored; send it "
                         "again later", "retry_after_s": STORE_RETRY_AFTER_S}

    async def post_measurements(request: Request) -> Response:
        if not authorized(request.headers, request.query_params):
            return unauthorized()
        # (refused before the body is read, as a body too large is; ``?tags=...`` or a
        # misspelled option was accepted silently, while every GET refused it)
        if (bad := bad_params(request)) is not None:
            return bad
        length = request.headers.get("content-length")
        if length is not None and (not length.isdigit() or int(length) > cfg.max_body_bytes):
            return refuse("too_large", 413, f"body larger than {cfg.max_body_bytes} bytes")
        chunks, size = [], 0
        try:
            with anyio.fail_after(cfg.body_timeout_s):
                async for chunk in request.stream():
                    size += len(chunk)
                    if size > cfg.max_body_bytes:
                        return refuse("too_large", 413,
                                      f"body larger than {cfg.max_body_bytes} bytes")
                    chunks.append(chunk)
        except TimeoutError:  # a client that stops sending holds no connection forever
            return refuse("body_timeout", 408, f"body not received within "
                                               f"{cfg.body_timeout_s:g} s", Connection="close")
        except ClientDisconnect:  # the client left mid-body: its mistake, nothing stored
            return refuse("client_disconnect", 400, "the client disconnected before the "
                                                    "body was complete")
        except asyncio.CancelledError:
            # the stop's --shutdown-grace ran out while the body came in: uvicorn cancels
            # the request, which answered 500 with a traceback in the log (the service
            # review); nothing of the body is stored, and the client is told so
            return refuse("shutting_down", 503, "the service is stopping; none of the "
                          "body's rows was stored: send it again later",
                          Connection="close", **{"Retry-After": "5"})
        client = request.client.host if request.client else "?"
        ingest = asyncio.ensure_future(anyio.to_thread.run_sync(
            ingest_sync, b"".join(chunks), "http", client))
        try:
            status, body = await asyncio.shield(ingest)
        except asyncio.CancelledError:  # (the grace ran out while the rows are stored:
            status, body = await ingest  # the client gets their answer, not a 500)
        headers = ({"Retry-After": str(math.ceil(body["retry_after_s"]))}
                   if status in (429, INSUFFICIENT_STORAGE) else None)
        return JSONResponse(body, status_code=status, headers=headers)

    def _float_param(request: Request, name: str) -> float | None:
        v = request.query_params.get(name)
        if v is None or v == "":
            return None
        x = float(v)
        if not math.isfinite(x):
            raise ValueError(f"{name} must be a finite number")
        return x

    def stopping() -> JSONResponse:
        """The ``503`` of a request the stop's ``--shutdown-grace`` cut short before it
        held anything (counted as ``shutting_down``)."""
        return refuse("shutting_down", 503, "the service is stopping: send the query "
                      "again later", Connection="close", **{"Retry-After": "5"})

    async def read_positions(request: Request, tag: str | None, since: float | None,
                             until: float | None, limit: int
                             ) -> tuple[bytes, int, int] | Response:
        """The body of a positions query, its rows and the rows matching, read in a
        worker thread once one of ``position_reads``' slots is free; or the answer to a
        query that waited for its slot in vain.

        * The stop's ``--shutdown-grace`` ran out while it waited (uvicorn cancels the
          request): ``503`` with ``Retry-After``, as a body still arriving is answered
          (it was a plain-text 500 and a ``CancelledError`` traceback per query).
        * Its client left while it waited: not read (it was read and encoded for nobody,
          and the queries behind it waited for that); counted as ``client_disconnect``.

        A query already reading when the grace runs out is read to the end and answered,
        unless the event loop ends first (uvicorn does not wait for the requests it
        cancelled; the loop ends after the application's shutdown): then ``503`` too.

        Raises
        ------
        StoreError
            A segment of the store cannot be read.
        """
        try:
            await position_reads.acquire()
        except asyncio.CancelledError:  # (waiting, it held nothing)
            return stopping()
        try:
            try:
                gone = await request.is_disconnected()
            except asyncio.CancelledError:
                return stopping()
            if gone:  # (nobody to answer: the status is for the access log only)
                engine.metrics.request_rejected("client_disconnect")
                return Response(status_code=CLIENT_CLOSED_REQUEST)
            # (the body is built in the worker thread too: encoding 100 000 rows on the
            # event loop held /healthz and ingest for a second per query; the slot is
            # held here, so the thread's own limiter never makes it wait)
            read = asyncio.ensure_future(anyio.to_thread.run_sync(
                positions_body, tag, since, until, limit, limiter=anyio.CapacityLimiter(1)))
            try:
                return await asyncio.shield(read)
            except asyncio.CancelledError:  # (the grace ran out while it reads: the
                pass  # client gets its answer, not a 500)
            try:
                return await read
            except asyncio.CancelledError:  # (cancelled again: the event loop itself
                return stopping()  # ends, after the application's shutdown)
        finally:
            position_reads.release()

    last_read_error = [""]  # (each store read error logged once, not per query)

    def store_read_error(exc: StoreError) -> JSONResponse:
        """The ``500`` of a positions query the store could not answer (a segment
        damaged while the service runs): the store's reason, which names the file and
        what is wrong (it was ``internal error: StoreError`` and a traceback per
        query); counted as ``store_error``, logged once per reason."""
        why = str(exc)
        if why != last_read_error[0]:
            last_read_error[0] = why
            print(f"warning: GET /api/positions: {why}", file=sys.stderr, flush=True)
        return refuse("store_error", 500, why)

    async def get_positions(request: Request) -> Response:
        if not authorized(request.headers, request.query_params):
            return unauthorized()
        if (bad := bad_params(request)) is not None:
            return bad
        try:
            since = _float_param(request, "since")
            until = _float_param(request, "until")
            limit = int(request.query_params.get("limit", "100000"))
            if not 1 <= limit <= 10_000_000:
                raise ValueError("limit must be in 1 .. 10000000")
        except ValueError as exc:
            return refuse("bad_query", 400, f"bad query: {exc}")
        # trimmed as ingest trims a row's tag (rows.py): ``?tag=%20C`` found nothing
        tag = request.query_params.get("tag", "").strip() or None
        try:
            answer = await read_positions(request, tag, since, until, limit)
        except StoreError as exc:  # a segment damaged while the service runs: named
            return store_read_error(exc)
        if isinstance(answer, Response):  # (stopping, or the client left)
            return answer
        body, n, total = answer
        # the body keeps the latest ``limit`` rows (as before); the headers say how many
        # matched and that the earliest were left out (it was silent: the API review)
        headers = {"X-Total-Count": str(total)}
        if total > n:
            headers["X-Truncated"] = "true"
        return Response(body, media_type="application/json", headers=headers)

    async def get_anchors(request: Request) -> Response:
        if not authorized(request.headers, request.query_params):
            return unauthorized()
        if (bad := bad_params(request)) is not None:
            return bad
        rows = json.loads(engine.anchors.reset_index(drop=True).to_json(orient="records"))
        for r, h in zip(rows, engine.metrics.anchor_health()):
            r["anchor"] = h["anchor"]
            r.update({k: v for k, v in h.items() if k != "anchor"})
        return _json(rows)

    async def get_latest(request: Request) -> Response:
        if not authorized(request.headers, request.query_params):
            return unauthorized()
        if (bad := bad_params(request)) is not None:
            return bad
        df = engine.latest_with_fixes()
        return Response(_array_json(df), media_type="application/json")

    async def get_status(request: Request) -> Response:
        if not authorized(request.headers, request.query_params):
            return unauthorized()
        if (bad := bad_params(request)) is not None:
            return bad
        ext = cfg.floorplan_extent
        return _json({
            "processor": engine.processor.name, "value": engine.kind,
            "latency_window_s": engine.assembler.window,
            "idle_flush_s": engine.assembler.idle,
            "store": None if engine.store_dir is None else str(engine.store_dir),
            "floorplan": None if cfg.floorplan is None else {
                "url": "/floorplan", "extent": list(ext) if ext else None},
            "tags": engine.assembler.n_tags, "pending_rows": engine.assembler.n_pending,
            "solver_errors": engine.solver_errors, "last_solver_error": engine.last_error,
            "position_store_errors": engine.position_store_errors,
            "snapshot_errors": engine.snapshot_errors,
            "last_snapshot_error": engine.last_snapshot_error,
            "positions_not_stored": engine.positions_not_stored,
            "server_time": time.time(),
            "mqtt": None if cfg.mqtt is None else cfg.mqtt.status(),
            **engine.processor.status(), **engine.metrics.summary(), **cfg.info,
        })

    async def get_floorplan(request: Request) -> Response:
        if not authorized(request.headers, request.query_params):
            return unauthorized()
        if (bad := bad_params(request)) is not None:
            return bad
        if cfg.floorplan is None:  # (counted as every refused request is)
            return refuse("not_found", 404, "no floor plan configured (serve --floorplan)")
        try:  # the image may have gone since the start (a 500 with a traceback, every 2 s)
            if not cfg.floorplan.is_file():
                raise FileNotFoundError("not a file any more")
            with open(cfg.floorplan, "rb"):
                pass
        except OSError as exc:
            why = exc.strerror or str(exc)
            return refuse("not_found", 404, f"the floor-plan image {cfg.floorplan.name} "
                          f"cannot be read ({why}): it was there when the service started")
        return FileResponse(cfg.floorplan)

    async def healthz(request: Request) -> Response:
        return _json({"status": "ok"})

    async def metrics(request: Request) -> Response:
        if not authorized(request.headers, request.query_params):
            return unauthorized()
        if (bad := bad_params(request)) is not None:
            return bad
        text = engine.metrics.render(engine.assembler.n_pending, engine.assembler.n_tags,
                                     engine.solver_errors, engine.position_store_errors)
        text += ("# HELP robustloc_ws_queued_bytes Position messages queued for the "
                 "WebSocket subscribers, in bytes (each subscriber holds at most "
                 f"{WS_QUEUE_BYTES} and {WS_QUEUE} messages; past either the oldest are "
                 "dropped).\n# TYPE robustloc_ws_queued_bytes gauge\n"
                 f"robustloc_ws_queued_bytes {hub.queued_chars}\n")
        if cfg.mqtt is not None:
            text += cfg.mqtt.prometheus()
        return PlainTextResponse(text, media_type="text/plain; version=0.0.4")

    async def index(request: Request) -> Response:
        return FileResponse(_static_dir() / "index.html", media_type="text/html")

    async def refused_ws_query(ws: WebSocket) -> bool:
        """Refuse a WebSocket whose query has a parameter its endpoint does not take (or
        one twice) at the handshake, with HTTP 400 and the reason, as a bad HTTP query
        is (counted as ``bad_query``); True when it was refused."""
        why = query_problem(ws.query_params.multi_items(),
                            QUERY_PARAMS.get(ws.url.path, TOKEN_ONLY))
        if why is None:
            return False
        engine.metrics.request_rejected("bad_query")
        if "websocket.http.response" in ws.scope.get("extensions", {}):
            await ws.send_denial_response(
                JSONResponse({"error": f"bad query: {why}"}, status_code=400))
        else:  # (a server without the denial extension: HTTP 403, no reason)
            await ws.close(code=WS_POLICY_VIOLATION)
        return True

    async def ws_positions(ws: WebSocket) -> None:
        if not authorized(ws.headers, ws.query_params):
            engine.metrics.request_rejected("unauthorized")
            # closed before the accept: uvicorn answers the handshake HTTP 403 (the
            # client sees that status, not this code)
            await ws.close(code=1008)
            return
        if await refused_ws_query(ws):
            return
        await ws.accept()
        q = Outbox()
        key = id(q)
        hub.subs[key] = (q, ws.query_params.get("tag", "").strip() or None,
                         ws.query_params.get("batch", "0").lower() in ("1", "true", "yes"))

        async def pump() -> None:
            while True:
                await ws.send_text(await q.get())

        async def drain() -> None:  # returns when the client disconnects
            try:
                while True:
                    msg = await ws.receive()
                    if msg["type"] == "websocket.disconnect":
                        if msg.get("code") == WS_MESSAGE_TOO_BIG:
                            engine.metrics.request_rejected("too_large")
                        return
            except (WebSocketDisconnect, RuntimeError):
                return

        try:
            sender = asyncio.ensure_future(pump())
            receiver = asyncio.ensure_future(drain())
            done, pend = await asyncio.wait({sender, receiver},
                                            return_when=asyncio.FIRST_COMPLETED)
            for t in pend:
                t.cancel()
            # a send to a client that left ends ``pump`` with WebSocketDisconnect: read
            # it, or asyncio prints "Task exception was never retrieved" with a traceback
            # on the service's stderr for every such subscriber (the service review)
            for t in done:
                if not t.cancelled():
                    t.exception()
        except Exception:  # a broken socket ends this subscriber only
            pass
        finally:
            hub.subs.pop(key, None)

    async def ws_measurements(ws: WebSocket) -> None:
        if not authorized(ws.headers, ws.query_params):
            engine.metrics.request_rejected("unauthorized")
            # closed before the accept: uvicorn answers the handshake HTTP 403 (the
            # client sees that status, not this code)
            await ws.close(code=1008)
            return
        if await refused_ws_query(ws):  # (``?token=`` only; a misspelled one was ignored)
            return
        await ws.accept()
        client = ws.client.host if ws.client else "?"
        # a message in progress at shutdown is answered before the close
        # (robustloc.service.protocol.answer_then_close_ws_protocol)
        state = {"busy": False, "closing": False, "idle": asyncio.Event()}
        state["idle"].set()
        ws.scope[WS_STATE_KEY] = state
        try:
            while True:
                msg = await ws.receive()
                if msg["type"] == "websocket.disconnect":
                    # 1009: uvicorn closed a frame over --max-body-bytes (ws_max_size)
                    # before it reached this handler; counted as an HTTP body that size is
                    if msg.get("code") == WS_MESSAGE_TOO_BIG:
                        engine.metrics.request_rejected("too_large")
                    return
                if state["closing"]:  # (shutting down: not taken, so not stored)
                    return
                data = msg.get("text")
                if data is None:
                    data = msg.get("bytes") or b""
                state["busy"] = True
                state["idle"].clear()
                try:
                    status, body = await anyio.to_thread.run_sync(ingest_sync, data, "ws",
                                                                  client)
                    if status != 202:
                        body["status"] = status
                    await ws.send_text(json.dumps(body))
                finally:
                    state["busy"] = False
                    state["idle"].set()
                if state["closing"]:  # answered: the shutdown closes the socket (1012)
                    return
                if status == INSUFFICIENT_STORAGE:  # answered (counted); then the close
                    await ws.close(code=WS_TRY_AGAIN_LATER,
                                   reason=_close_reason(body["error"]))
                    return
        except WebSocketDisconnect:
            return
        except Exception as exc:  # noqa: BLE001 - a defect: counted, closed with a reason
            engine.metrics.request_rejected("internal_error")
            with contextlib.suppress(Exception):  # the socket may be gone already
                await ws.close(code=WS_INTERNAL_ERROR,
                               reason=_close_reason(f"internal error: {type(exc).__name__}"))

    async def ws_not_found(ws: WebSocket) -> None:
        """A WebSocket to a path that is no WebSocket endpoint: counted as an HTTP request
        to an unknown path is, and closed with a reason (a bare 403 said nothing)."""
        engine.metrics.request_rejected("not_found")
        await ws.accept()
        await ws.close(code=WS_POLICY_VIOLATION, reason=_close_reason(
            f"no such WebSocket endpoint: {ws.url.path} (/ws/positions, /ws/measurements)"))

    async def on_error(request: Request, exc: Exception) -> Response:
        engine.metrics.request_rejected("internal_error")
        return _json({"error": f"internal error: {type(exc).__name__}"}, 500)

    async def on_http_error(request: Request, exc: Exception) -> Response:
        """404 (no such route), 405 (method) and other HTTP errors: a JSON reason, counted."""
        code = int(getattr(exc, "status_code", 400))
        reason = {404: "not_found", 405: "method_not_allowed"}.get(code, f"http_{code}")
        headers = dict(getattr(exc, "headers", None) or {})
        if code == 404 and request.url.path in ("/ws/positions", "/ws/measurements"):
            # a plain HTTP request to a WebSocket endpoint: it exists, it needs the upgrade
            code, reason, headers = 426, "upgrade_required", {**headers, "Upgrade": "websocket"}
            msg = f"{request.url.path} is a WebSocket endpoint: connect with ws:// or wss://"
        elif code == 404:
            msg = f"no such endpoint: {request.url.path} (see the README's live service API)"
        elif code == 405:
            msg = (f"method {request.method} not allowed on {request.url.path}"
                   + "".join(f"; allowed: {v}" for k, v in headers.items()
                             if k.lower() == "allow"))
        else:
            msg = str(getattr(exc, "detail", "")) or "bad request"
        return refuse(reason, code, msg, **headers)

    @asynccontextmanager
    async def lifespan(app: Starlette) -> AsyncIterator[None]:
        hub.loop = asyncio.get_running_loop()
        engine.start()
        if cfg.mqtt is not None:
            cfg.mqtt.start()
        # what is alive now (modules, compiled kernels, the engine) lives as long as the
        # service: move it out of the collector's generations, so that a full collection
        # scans the service's live data only, not ~80 000 import-time objects (it paused
        # the service for 50-150 ms each time under the benchmark's load)
        gc.collect()
        gc.freeze()
        try:
            yield
        finally:
            if cfg.mqtt is not None:
                cfg.mqtt.stop()
            await anyio.to_thread.run_sync(engine.stop)
            if cfg.store_lock is not None:  # the store is closed: another may open it
                cfg.store_lock.release()

    routes = [
        Route("/", index),
        Route("/healthz", healthz),
        Route("/metrics", metrics),
        Route("/api/measurements", post_measurements, methods=["POST"]),
        Route("/api/positions", get_positions),
        Route("/api/anchors", get_anchors),
        Route("/api/latest", get_latest),
        Route("/api/status", get_status),
        Route("/floorplan", get_floorplan),
        WebSocketRoute("/ws/positions", ws_positions),
        WebSocketRoute("/ws/measurements", ws_measurements),
        # before the Mount: a Mount takes WebSockets too (StaticFiles then failed)
        WebSocketRoute("/{path:path}", ws_not_found),
        Mount("/static", StaticFiles(directory=_static_dir()), name="static"),
    ]
    from starlette.middleware import Middleware

    middleware = [Middleware(SameSiteGuard, cors_origins=cfg.cors_origins,
                             allowed_hosts=cfg.allowed_hosts,
                             on_refuse=engine.metrics.request_rejected)]
    if cfg.cors_origins:
        from starlette.middleware.cors import CORSMiddleware

        middleware.append(Middleware(CORSMiddleware, allow_origins=list(cfg.cors_origins),
                                     allow_headers=["Authorization", "Content-Type"],
                                     allow_methods=list(CORS_METHODS)))
    app = Starlette(routes=routes, middleware=middleware, lifespan=lifespan,
                    exception_handlers={Exception: on_error, HTTPException: on_http_error})
    app.state.engine = engine
    app.state.hub = hub
    return app


__all__ = ["ServiceConfig", "create_app", "DEFAULT_MAX_BODY_BYTES"]
