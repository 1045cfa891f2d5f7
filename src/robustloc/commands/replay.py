"""``robustloc replay``: drive a running ``robustloc serve`` from a measurements log."""

from __future__ import annotations

import argparse
import json
import sys
import time

import numpy as np

from robustloc.errors import InputError, Terminated
from robustloc.options import nonnegative_float, nonnegative_int, positive_int

#: Slowest replay (``--speed``): 1 000 times slower than real time; 0 means no pacing.
MIN_SPEED = 1e-3


def _speed(text: str) -> float:
    """``--speed``: 0 (no pacing) or at least :data:`MIN_SPEED` (1e-300 overflowed the
    pacing sleep; 1e-9 would wait decades)."""
    v = nonnegative_float(text)
    if 0 < v < MIN_SPEED:
        raise argparse.ArgumentTypeError(f"expected 0 (no pacing) or at least {MIN_SPEED:g}, "
                                         f"got {text!r}")
    return v


def check_url(url: str) -> None:
    """Refuse a service URL that is not ``http(s)://HOST[:PORT][/...]`` (a malformed
    one reached httpx / websockets and ended in a traceback)."""
    from urllib.parse import urlsplit

    try:
        parts = urlsplit(url)
        port = parts.port  # raises on a port that is not a number in 0..65535
    except ValueError as exc:
        raise InputError(f"invalid URL: {exc}", url) from None
    if parts.scheme not in ("http", "https") or not parts.hostname:
        raise InputError("invalid URL: expected http://HOST[:PORT] or https://...", url)
    if port == 0:
        raise InputError("invalid URL: port 0", url)

NAME = "replay"
HELP = "send a measurements log to a running robustloc serve (HTTP batches or WebSocket)"
DESCRIPTION = """\
Reads a measurements file (CSV or Parquet; any row order, sorted by time here) and sends
its rows to a running service, one batch per time step (or --batch-rows rows), paced at
--speed times real time (0: as fast as the server acknowledges). Every batch must be
acknowledged (202); rejected rows are reported with their file line. The exit code is 0
when every row was accepted, 1 when the server rejected some, 2 when the replay stopped:
a connection error or an error answer (401, 413, 5xx, ...); the message then says how
many rows the server had acknowledged before it stopped, and the --skip that resumes
the replay from there (the batch in flight when it stopped, if the server stored it
without answering, is sent again: its rows are then stored twice).

  robustloc replay meas.csv --url http://127.0.0.1:8080 --speed 10
  robustloc replay meas.csv --url http://127.0.0.1:8080 --speed 0 --transport ws
  robustloc replay meas.csv --url http://127.0.0.1:8080 --speed 0 --skip 120000
  ROBUSTLOC_TOKEN=secret robustloc replay meas.parquet --url http://host:8080"""


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("measurements", help="measurements file (time, tag, anchor, rssi|range)")
    p.add_argument("--url", required=True, help="service base URL, e.g. http://127.0.0.1:8080")
    p.add_argument("--speed", type=_speed, default=1.0,
                   help=f"times real time (default 1; 0 = no pacing; at least {MIN_SPEED:g})")
    p.add_argument("--token", default=None, help="bearer token (default $ROBUSTLOC_TOKEN)")
    p.add_argument("--transport", choices=("http", "ws"), default="http",
                   help="POST /api/measurements batches (default) or WebSocket "
                        "/ws/measurements")
    p.add_argument("--batch-rows", type=positive_int, default=None,
                   help="rows per batch (default: one time step per batch); with "
                        "--speed > 0 a batch also ends with its time step, so that no "
                        "row is sent before its time")
    p.add_argument("--skip", type=nonnegative_int, default=0, metavar="N",
                   help="leave out the first N rows of the replay's order (by time, the "
                        "file's order within a time): resumes a replay that stopped after "
                        "N rows (default 0)")
    p.add_argument("--retry-s", type=nonnegative_float, default=30.0, metavar="S",
                   help="when the connection is refused, or a WebSocket was closed before "
                        "a batch was sent (1012: a server restart), send the batch again "
                        "for up to S seconds, saying so on stderr (default 30; 0: stop "
                        "at once)")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bar")
    p.add_argument("--json", action="store_true",
                   help="print the summary as JSON (rows, accepted, n_rejected, the "
                        "rejected rows the server listed with their file line and "
                        "reason, seconds; a replay that stopped: rows, sent, accepted, "
                        "n_rejected, rejected and why); no progress bar")


def _batches(times: np.ndarray, batch_rows: int | None,
             paced: bool = False) -> list[tuple[int, int]]:
    """``(start, stop)`` row ranges of the batches: one per time step, or ``batch_rows``
    rows; ``paced`` (``--speed`` > 0), a batch of ``batch_rows`` also ends where a time
    step ends, so no row is sent before its time (a batch of 2000 rows went out at its
    first row's time: 59 s of a log in 0.56 s at --speed 1; the replay review)."""
    n = len(times)
    if n == 0:  # (--skip of every row: nothing to send)
        return []
    if batch_rows is not None and not paced:
        return [(i, min(i + batch_rows, n)) for i in range(0, n, batch_rows)]
    cuts = np.flatnonzero(np.diff(times) != 0) + 1
    edges = np.concatenate(([0], cuts, [n])).tolist()
    if batch_rows is None:
        return list(zip(edges[:-1], edges[1:]))
    return [(i, min(i + batch_rows, b)) for a, b in zip(edges[:-1], edges[1:])
            for i in range(a, b, batch_rows)]


def replay(path: str, url: str, *, speed: float = 1.0, token: str | None = None,
           transport: str = "http", batch_rows: int | None = None,
           progress: bool = False, skip: int = 0,
           retry_s: float = 30.0) -> dict:
    """Send a log to a service.

    ``skip`` leaves out the first rows of the replay's order (sorted by time, stable):
    :class:`ReplayStopped`'s ``sent`` is the ``skip`` that resumes a stopped replay.
    A batch that certainly did not reach the server (the connection refused, or a
    WebSocket closed before the send, e.g. 1012 at a restart) is sent again, for up to
    ``retry_s`` seconds (backoff 0.25 s doubling to 5 s), saying so on stderr.

    Returns
    -------
    dict
        ``{rows, skipped, accepted, n_rejected, rejected: [{line, error}], seconds}``:
        ``rejected`` lists the rows the server listed (at most
        :data:`~robustloc.service.defaults.MAX_REJECTED_LISTED` per batch), ``n_rejected``
        counts every rejected row; ``accepted`` and ``n_rejected`` count this run's rows.

    Raises
    ------
    ReplayStopped
        The connection failed or the server answered an error; ``accepted`` and ``sent``
        say how far the replay got.
    """
    import os

    from tqdm import tqdm

    from robustloc.io import read_measurements
    from robustloc.io.limits import limits_for

    df = read_measurements(path, engine_hint=False)  # (replay has no --engine)
    value = df.attrs["value"]
    lim = limits_for("time")  # the service refuses such rows; here they would set the pace
    out = ~lim.check(df["time"].to_numpy(float))
    if out.any():
        i = int(np.argmax(out))
        raise InputError(f"column 'time': {df['time'].iloc[i]:g} is implausible "
                         f"({lim.describe()})", path, int(df.index[i]))
    df = df.sort_values("time", kind="stable")
    if skip > len(df):
        raise InputError(f"--skip {skip}: the log has {len(df)} rows", path)
    n_rows = len(df)
    df = df.iloc[skip:]
    lines = df.index.to_numpy()
    times = df["time"].to_numpy(float)
    tags, anchors = df["tag"].to_numpy(), df["anchor"].to_numpy()
    values = df[value].to_numpy(float)

    def body_of(i0: int, i1: int) -> str:
        """The JSON rows ``[i0, i1)``, built for their batch only (the whole log as Python
        dicts first cost 450 bytes a row, 1.35 GB for 3 million: the replay review)."""
        return json.dumps([
            {"time": t, "tag": g, "anchor": a, value: v}
            for t, g, a, v in zip(times[i0:i1].tolist(), tags[i0:i1].tolist(),
                                  anchors[i0:i1].tolist(), values[i0:i1].tolist())
        ])

    token = token if token is not None else os.environ.get("ROBUSTLOC_TOKEN")
    if token and not (token.isascii() and token.isprintable()):
        # an HTTP header carries printable ASCII: 'sécret' was a UnicodeEncodeError
        # traceback (the replay review), as the map page refuses such a token
        raise InputError("--token (or $ROBUSTLOC_TOKEN): a token must be printable ASCII "
                         "(an HTTP header cannot carry it otherwise)")
    headers = {"Authorization": f"Bearer {token}"} if token else {}
    base = url.rstrip("/")
    accepted = 0
    n_rejected = 0
    sent = skip  # rows of the log acknowledged (or skipped): the --skip that resumes
    rejected: list[dict] = []
    t_start = time.monotonic()
    bar = tqdm(total=len(times), unit=" rows", disable=not progress, file=sys.stderr)
    conn = client = None
    i0 = i1 = 0
    # rows (of the replay's order: [start, stop)) sent and not yet answered: they may
    # have reached the server; ``too_large``: rows of a batch refused as too large
    in_flight: tuple[int, int] | None = None
    # a keepalive that fails in websockets' own thread logged a traceback before the
    # command's error line (the replay review): the command says what stopped it
    import logging

    ws_log = logging.getLogger("websockets")
    ws_level = ws_log.level
    ws_log.setLevel(logging.CRITICAL)
    try:
        # connecting inside: a refused or rejected connection also says how far the replay
        # got (none of it) and gives --json its summary (the replay review)
        if transport == "ws":
            from websockets.sync.client import connect

            ws_url = base.replace("http://", "ws://", 1).replace("https://", "wss://", 1)
        else:
            import httpx

            client = httpx.Client(headers=headers, timeout=ANSWER_TIMEOUT_S)
        for i0, i1 in _batches(times, batch_rows, paced=speed > 0):
            if speed > 0:
                due = (times[i0] - times[0]) / speed
                wait = due - (time.monotonic() - t_start)
                while wait > 0:  # in steps: one sleep of a long pause can overflow
                    time.sleep(min(wait, 60.0))
                    wait = due - (time.monotonic() - t_start)
            body = body_of(i0, i1)
            retry_until = None
            backoff = 0.25
            while True:
                try:
                    if transport == "ws" and conn is None:
                        conn = connect(ws_url + "/ws/measurements",
                                       additional_headers=headers, max_size=None).__enter__()
                    if conn is not None:
                        conn.send(body)
                    else:
                        assert client is not None
                        in_flight = (skip + i0, skip + i1)
                        r = client.post(base + "/api/measurements", content=body,
                                        headers={"Content-Type": "application/json"})
                        in_flight = None
                except _transport_errors() as exc:
                    # refused, or a WebSocket closed (1012: a restart) before the send:
                    # the batch certainly did not reach the server; send it again
                    # (a restart stopped the replay: the replay review)
                    if not _safe_to_retry(exc):
                        raise
                    in_flight = None
                    now = time.monotonic()
                    retry_until = now + retry_s if retry_until is None else retry_until
                    if now >= retry_until:
                        raise RuntimeError(f"{_reason(exc)} (retried for {retry_s:g} s)"
                                           if retry_s else _reason(exc)) from exc
                    wait = min(backoff, retry_until - now)
                    print(f"warning: {url}: {_reason(exc)}; rows {skip + i0 + 1} to "
                          f"{skip + i1} not sent: sending them again in {wait:.2g} s",
                          file=sys.stderr)
                    if conn is not None:
                        conn.__exit__(None, None, None)
                        conn = None
                    time.sleep(wait)
                    backoff = min(2 * backoff, 5.0)
                    continue
                if conn is not None:
                    in_flight = (skip + i0, skip + i1)
                    # (no answer within the timeout: a server that takes the rows and
                    # never acknowledges them hung the replay for good: the review)
                    text = conn.recv(timeout=ANSWER_TIMEOUT_S)
                    in_flight = None
                    res = _parsed(text)
                    status = res.pop("status", 202) if "error" in res or "status" in res else 202
                else:
                    status = r.status_code
                    res = _parsed(r.text) if r.headers.get("content-type", "").startswith(
                        "application/json") else {"error": r.text}
                if status == 429:  # rate limited: wait as told, resend the same batch
                    time.sleep(_retry_after(res))
                    continue
                break
            if status != 202:
                raise (_TooLarge if status == 413 else RuntimeError)(
                    f"server answered {status}: {res.get('error', res)}")
            n_acc, n_rej, listed = _acknowledged(res, i1 - i0)
            accepted += n_acc
            n_rejected += n_rej
            sent = skip + i1
            for index, error in listed:
                rejected.append({"line": int(lines[i0 + index]), "error": error})
            bar.update(i1 - i0)
    except _transport_errors() as exc:
        message, too_large = str(exc), 0
        if isinstance(exc, _TooLarge) or _close_code(exc) == WS_MESSAGE_TOO_BIG:
            too_large, in_flight = i1 - i0, None  # (refused: not stored)
        elif _not_connected(exc):
            in_flight = None
        if getattr(getattr(exc, "response", None), "status_code", None) in (401, 403):
            # (a WebSocket handshake said only "HTTP 403"; HTTP says the token: the
            # replay review)
            message += ": missing or wrong --token?"
        raise ReplayStopped(message, accepted=accepted, sent=sent, rows=n_rows,
                            skipped=skip, n_rejected=n_rejected, rejected=rejected,
                            in_flight=in_flight, too_large=too_large) from exc
    except (KeyboardInterrupt, Terminated) as exc:  # Ctrl-C: how far it got, to resume
        raise ReplayInterrupted("interrupted" if isinstance(exc, KeyboardInterrupt)
                                else "terminated", accepted=accepted, sent=sent,
                                rows=n_rows, skipped=skip, n_rejected=n_rejected,
                                rejected=rejected, in_flight=in_flight) from exc
    finally:
        bar.close()
        ws_log.setLevel(ws_level)
        if conn is not None:
            conn.__exit__(None, None, None)
        if client is not None:
            client.close()
    return {"rows": n_rows, "skipped": skip, "accepted": accepted,
            "n_rejected": n_rejected, "rejected": rejected,
            "seconds": round(time.monotonic() - t_start, 3)}


#: Seconds the replay waits for the server's answer to one batch (HTTP and WebSocket).
ANSWER_TIMEOUT_S = 60.0
#: Longest wait a 429 answer's ``retry_after_s`` can ask for (s).
MAX_RETRY_AFTER_S = 60.0
#: The WebSocket close code of a message over the server's size limit.
WS_MESSAGE_TOO_BIG = 1009
#: WebSocket close codes after which a batch not yet sent is sent again on a new
#: connection: going away (1001) and service restart (1012).
WS_RETRY_CODES = (1001, 1012)


class _TooLarge(RuntimeError):
    """A batch the server refused as too large (HTTP 413)."""


def _close_code(exc: BaseException) -> int | None:
    """The close code a WebSocket connection closed with (received, else sent), or None
    when ``exc`` is no closed connection."""
    for frame in (getattr(exc, "rcvd", None), getattr(exc, "sent", None)):
        if frame is not None and isinstance(getattr(frame, "code", None), int):
            return frame.code
    return None


def _safe_to_retry(exc: BaseException) -> bool:
    """True when ``exc`` (raised connecting or sending, before any answer) means the
    batch certainly did not reach the server: the connection was refused, or the
    WebSocket was closed for a restart (1012) or going away (1001) before the send (a
    message is not sent on a closed one)."""
    if _close_code(exc) in WS_RETRY_CODES:
        return True  # (raised by the send: closed before it)
    while exc is not None:  # httpx wraps the socket's error
        if isinstance(exc, ConnectionRefusedError):
            return True
        exc = exc.__cause__ or exc.__context__
    return False


def _reason(exc: BaseException) -> str:
    """A one-line reason for a retried failure."""
    code = _close_code(exc)
    if code is not None:
        return f"the WebSocket was closed (code {code})"
    return str(exc) or type(exc).__name__


def _not_connected(exc: BaseException) -> bool:
    """True when ``exc`` failed to connect (refused, no route, connect timeout): nothing
    of a batch was sent."""
    try:
        import httpx

        if isinstance(exc, (httpx.ConnectError, httpx.ConnectTimeout)):
            return True
    except ImportError:
        pass
    return isinstance(exc, ConnectionRefusedError)


def _parsed(text: str | bytes) -> dict:
    """A server's answer as a JSON object, or RuntimeError (the replay stops with the
    reason): a server other than ``robustloc serve`` answered ``{not json`` or ``[1, 2]``
    and the replay ended in a traceback (the review)."""
    try:
        res = json.loads(text)
    except ValueError:
        raise RuntimeError(f"unexpected answer from the server (not JSON): "
                           f"{str(text)[:120]!r}") from None
    if not isinstance(res, dict):
        raise RuntimeError(f"unexpected answer from the server (not a JSON object): "
                           f"{str(text)[:120]!r}")
    return res


def _retry_after(res: dict) -> float:
    """A 429 answer's wait, within ``[0.1, MAX_RETRY_AFTER_S]`` (``-1`` was a sleep
    error, ``1e9`` a replay that never resumed; 0.1 s at least, never a busy loop)."""
    try:
        wait = float(res.get("retry_after_s", 0.5))
    except (TypeError, ValueError):
        wait = 0.5
    return min(max(wait, 0.1), MAX_RETRY_AFTER_S) if np.isfinite(wait) else 0.5


def _acknowledged(res: dict, n_rows: int) -> tuple[int, int, list[tuple[int, str]]]:
    """``(accepted, rejected, [(index, error)])`` of a 202 answer to ``n_rows`` rows, or
    RuntimeError when it is not one ``robustloc serve`` gives (which accounts for every
    row: ``accepted + n_rejected == n_rows``)."""
    try:
        acc = int(res["accepted"])
        listed = [(int(r["index"]), str(r["error"])) for r in res.get("rejected", [])]
        n_rej = int(res.get("n_rejected", len(listed)))
    except (KeyError, TypeError, ValueError):
        raise RuntimeError(f"unexpected answer from the server: {str(res)[:120]}") from None
    # every row accepted or rejected: a 202 for half a batch (accepted + n_rejected <
    # rows) exited 0 with the other half nowhere (the replay review)
    if not (0 <= acc <= n_rows and 0 <= n_rej and acc + n_rej == n_rows
            and all(0 <= i < n_rows for i, _ in listed)):
        raise RuntimeError(f"unexpected answer from the server for {n_rows} rows: "
                           f"{str(res)[:120]}")
    return acc, n_rej, listed


class ReplayStopped(RuntimeError):
    """A replay that stopped before its end (connection error or an error answer).

    Attributes ``accepted`` (rows the server accepted in this run), ``sent`` (rows of the
    log acknowledged, accepted or rejected, or skipped: the ``--skip`` that resumes),
    ``rows`` (rows in the log), ``skipped`` (the run's ``--skip``), ``n_rejected`` (rows
    the server rejected in this run) and ``rejected`` (``[{line, error}]``, the rejected
    rows the server listed, as :func:`replay` returns them): a ``--skip`` resumes past
    the rejected rows, so they are reported here or never.  ``in_flight``: the rows
    ``(start, stop)`` of the replay's order sent and not answered (they may have reached
    the server), or None; ``too_large``: the rows of a batch the server refused as too
    large (413, WebSocket close 1009), else 0.
    """

    def __init__(self, message: str, *, accepted: int, sent: int, rows: int,
                 skipped: int = 0, n_rejected: int = 0,
                 rejected: list[dict] | None = None,
                 in_flight: tuple[int, int] | None = None, too_large: int = 0) -> None:
        super().__init__(message)
        self.accepted, self.sent, self.rows, self.skipped = accepted, sent, rows, skipped
        self.n_rejected = n_rejected
        self.rejected = list(rejected) if rejected is not None else []
        self.in_flight, self.too_large = in_flight, too_large


class ReplayInterrupted(ReplayStopped):
    """A replay stopped by Ctrl-C or SIGTERM (the message: ``interrupted`` or
    ``terminated``); its counts as :class:`ReplayStopped`'s.  A batch sent but not yet
    acknowledged may have reached the server: ``sent`` counts acknowledged rows only."""


def _transport_errors() -> tuple[type[BaseException], ...]:
    errs: list[type[BaseException]] = [OSError, RuntimeError]
    try:
        import httpx

        errs.append(httpx.HTTPError)
    except ImportError:
        pass
    try:
        from websockets.exceptions import WebSocketException

        errs.append(WebSocketException)
    except ImportError:
        pass
    return tuple(errs)


def run(args: argparse.Namespace) -> int:
    check_url(args.url)
    try:
        summary = replay(args.measurements, args.url, speed=args.speed, token=args.token,
                         transport=args.transport, batch_rows=args.batch_rows,
                         progress=not (args.quiet or args.json) and sys.stderr.isatty(),
                         skip=args.skip, retry_s=args.retry_s)
    except ReplayStopped as exc:
        first = f"the first {exc.skipped} skipped, " if exc.skipped else ""
        resume = (f"; resume with --skip {exc.sent}" if exc.sent < exc.rows else "")
        if exc.too_large > 1:  # (--skip alone failed again, for ever: the replay review)
            resume = (f"; the server refuses a batch of {exc.too_large} rows as too large: "
                      f"resume with --skip {exc.sent} and a --batch-rows below "
                      f"{exc.too_large}")
        if exc.in_flight is not None:  # (said on Ctrl-C only, without its rows: the
            # replay review; a timeout or a reset leaves a batch in flight as well)
            a, b = exc.in_flight
            rows = f"rows {a + 1} to {b}" if b > a + 1 else f"row {b}"
            resume += (f"; a batch in flight ({rows} of the replay's order) may have "
                       "reached the server")
        interrupted = isinstance(exc, ReplayInterrupted)
        # (Ctrl-C said only "error: interrupted": no --skip to resume from without
        # losing or repeating rows -- the replay review, 2026-12-07)
        where = "" if interrupted else f"{args.url}: "
        rej = f", {exc.n_rejected} rejected" if exc.n_rejected else ""
        print(f"error: {where}{exc} (stopped after {exc.sent} of {exc.rows} rows; "
              f"{first}{exc.accepted} accepted{rej}{resume})", file=sys.stderr)
        if args.json:  # how far it got, for a script that reads stdout
            print(json.dumps({"measurements": str(args.measurements), "url": args.url,
                              "rows": exc.rows, "skipped": exc.skipped, "sent": exc.sent,
                              "accepted": exc.accepted, "n_rejected": exc.n_rejected,
                              "rejected": exc.rejected, "stopped": str(exc)}, indent=2))
        else:  # (the rows rejected before it stopped: a --skip resumes past them --
            # they were never reported; the replay review)
            _print_rejected(args.measurements, exc.n_rejected, exc.rejected)
        if interrupted:
            from robustloc.errors import EXIT_SIGINT, EXIT_SIGTERM

            return EXIT_SIGINT if str(exc) == "interrupted" else EXIT_SIGTERM
        return 2
    except _transport_errors() as exc:
        print(f"error: {args.url}: {exc}", file=sys.stderr)
        return 2
    except ImportError as exc:
        print(f"error: robustloc replay needs the [serve] extra ({exc})", file=sys.stderr)
        return 2
    n_rej = summary["n_rejected"]
    if args.json:
        print(json.dumps({"measurements": str(args.measurements), "url": args.url,
                          **summary}, indent=2))
        return 1 if n_rej else 0
    first = f" (the first {summary['skipped']} skipped)" if summary["skipped"] else ""
    print(f"{summary['accepted']} of {summary['rows']} rows accepted{first} in "
          f"{summary['seconds']:.2f} s")
    _print_rejected(args.measurements, n_rej, summary["rejected"])
    return 1 if n_rej else 0


def _print_rejected(path: str, n_rejected: int, rejected: list[dict]) -> None:
    """On stderr: how many rows the server rejected and the first 20 it listed, as
    ``FILE:LINE: reason``."""
    if n_rejected:
        print(f"{n_rejected} rows rejected", file=sys.stderr)
    for r in rejected[:20]:
        print(f"  {path}:{r['line']}: {r['error']}", file=sys.stderr)
    if n_rejected > 20:
        print(f"  ... {n_rejected - min(len(rejected), 20)} more rejected rows",
              file=sys.stderr)
