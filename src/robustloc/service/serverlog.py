"""What the ASGI server (uvicorn) refuses before the application sees it, counted.

A request line or header that is not HTTP (``Content-Length: abc``, a method such as
``BREW``) is answered ``400 Invalid HTTP request received.`` by uvicorn itself, and a
WebSocket text frame that is not UTF-8 is closed with code 1007; the application never
sees either, so neither was counted, and the second printed a traceback on the service's
stderr (the service review).  uvicorn logs both on its error logger: this filter counts
them under a reason of their own and keeps a one-line warning, without the traceback.
"""

from __future__ import annotations

import logging
import re
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from robustloc.service.metrics import Metrics

#: uvicorn's log message (0.30-0.55) -> the reason counted in
#: ``robustloc_requests_rejected_total``.
REFUSED_BY_SERVER = {
    "Invalid HTTP request received.": "invalid_http",
    "Invalid UTF-8 sequence received from client.": "invalid_utf8",
}


class CountRefused(logging.Filter):
    """Count uvicorn's own refusals (:data:`REFUSED_BY_SERVER`) in ``metrics`` and log
    each as one warning line (no traceback)."""

    def __init__(self, metrics: Metrics) -> None:
        super().__init__()
        self.metrics = metrics

    def filter(self, record: logging.LogRecord) -> bool:
        message = record.getMessage()
        reason = REFUSED_BY_SERVER.get(message)
        if reason is not None:
            self.metrics.request_rejected(reason)
            _warning(record)
        elif message.startswith("Cancel ") and "timeout graceful shutdown exceeded" in message:
            # the requests still receiving a body, or positions queries still waiting
            # for a read slot, when --shutdown-grace ran out: each is answered 503 and
            # counted (``shutting_down``) by the application; a query reading finishes
            _warning(record, "stopping: " + message.replace(
                "timeout graceful shutdown exceeded",
                "still running after --shutdown-grace (a body not complete is answered "
                "503, not stored; a positions query not yet read 503)"))
        elif (message.startswith("Traceback") and message.rstrip().endswith("CancelledError")
              and "lifespan" in message):
            # a second Ctrl-C cuts the graceful stop short: the lifespan is cancelled
            # (a traceback of 10 lines, the service review); acknowledged rows are stored
            _warning(record, "stop forced by a second signal: the graceful stop was cut "
                             "short")
        if "token=" in message:  # (the map page's WebSocket carries its token in the
            # query: uvicorn logged "WebSocket /ws/positions?token=..." in clear at info)
            record.msg, record.args = _TOKEN_IN_QUERY.sub(r"\1***", message), ()
        return True


#: A ``token=`` query parameter's value, redacted from the log.
_TOKEN_IN_QUERY = re.compile(r"([?&]token=)[^&\s\"']*")


def _warning(record: logging.LogRecord, message: str | None = None) -> None:
    """Make ``record`` a one-line warning (``message`` if given), without its traceback."""
    record.exc_info = None
    record.exc_text = None
    record.levelno, record.levelname = logging.WARNING, "WARNING"
    if message is not None:
        record.msg, record.args = message, ()


def count_server_refusals(metrics: Metrics, level: int = logging.WARNING) -> CountRefused:
    """Install :class:`CountRefused` on uvicorn's error logger; returns it.

    ``level`` is the log level the user asked for (``serve --log-level``).  uvicorn logs
    a request that is not HTTP as a warning, which a logger at ``error`` would not even
    create, so the logger is kept at ``warning`` at least and the level is applied by the
    ``uvicorn`` logger's handlers instead: the refusal is counted, and shown only if the
    level lets warnings through.
    """
    f = CountRefused(metrics)
    err = logging.getLogger("uvicorn.error")
    err.addFilter(f)
    if err.getEffectiveLevel() > logging.WARNING:
        err.setLevel(logging.WARNING)
    for h in logging.getLogger("uvicorn").handlers + err.handlers:
        h.setLevel(max(h.level, level))
    return f
