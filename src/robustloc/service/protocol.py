"""The HTTP protocol of ``robustloc serve``: uvicorn's, with a timeout on the headers.

uvicorn times out a connection idle between requests (``timeout_keep_alive``), and the
application times out a body (``--body-timeout``), but nothing timed out a request whose
header lines never end: 300 connections that each sent ``GET / HTTP/1.1`` and one header
and then nothing held their file descriptors for as long as they stayed open, and the
service refused everyone else (the service review: "slowloris").  Each connection here
must complete its request's headers within ``--header-timeout`` seconds of its start (or
of its next request's first byte); else it is closed and counted
(``robustloc_requests_rejected_total{reason="header_timeout"}``).

At shutdown uvicorn closes every WebSocket at once (code 1012): a message being stored
was stored without its answer, and a replay resumed from its last answer sent those rows
again (the partition/replay review, 2026-12-07: 3 604 rows stored for a log of 3 600).
:func:`answer_then_close_ws_protocol` lets the message in progress be answered first,
within ``--shutdown-grace``.
"""

from __future__ import annotations

import asyncio
from collections.abc import Callable
from typing import Any

__all__ = ["WS_STATE_KEY", "answer_then_close_ws_protocol", "header_timeout_protocol"]

#: The ASGI scope key of a ``/ws/measurements`` connection's state, shared by the
#: application's handler (which sets it) and :func:`answer_then_close_ws_protocol`:
#: ``{"busy": bool, "closing": bool, "idle": asyncio.Event}``.
WS_STATE_KEY = "robustloc.ws_state"


def answer_then_close_ws_protocol() -> type[asyncio.Protocol] | None:
    """uvicorn's WebSocket protocol whose shutdown waits for the message in progress to
    be answered (the handler's :data:`WS_STATE_KEY` state says one is), then closes with
    1012 as uvicorn does; uvicorn's graceful timeout still bounds the wait.  None where
    the ``websockets`` implementation is missing (uvicorn's default then serves)."""
    try:  # uvicorn's "auto" choice where websockets is installed
        from uvicorn.protocols.websockets.websockets_sansio_impl import (
            WebSocketsSansIOProtocol,
        )
    except ImportError:  # pragma: no cover - the [serve] extra brings websockets
        return None

    class AnswerThenClose(WebSocketsSansIOProtocol):  # type: ignore[misc]
        def shutdown(self) -> None:
            state = (getattr(self, "scope", None) or {}).get(WS_STATE_KEY)
            if state is not None:  # the handler takes no more messages (a message that
                # arrives now is not stored: it gets no answer, and a resume sends it)
                state["closing"] = True
            if state is None or not state["busy"]:
                super().shutdown()
                return

            async def after_the_answer() -> None:
                await state["idle"].wait()
                super(AnswerThenClose, self).shutdown()

            asyncio.get_running_loop().create_task(after_the_answer())

    return AnswerThenClose


def header_timeout_protocol(timeout_s: float, on_timeout: Callable[[], None]
                            ) -> type[asyncio.Protocol] | None:
    """uvicorn's httptools protocol with the header timeout, for ``uvicorn.Config(http=
    ...)``; ``on_timeout()`` is called (on the event loop) for each connection it closes.
    None where httptools is missing (uvicorn's h11 protocol then serves, without it)."""
    try:
        from uvicorn.protocols.http.httptools_impl import HttpToolsProtocol
    except ImportError:  # pragma: no cover - uvicorn[standard] brings httptools
        return None

    class HeaderTimeoutProtocol(HttpToolsProtocol):  # type: ignore[misc]
        _header_timer: asyncio.TimerHandle | None = None

        def _arm(self) -> None:
            self._disarm()
            self._header_timer = self.loop.call_later(timeout_s, self._header_timeout)

        def _disarm(self) -> None:
            if self._header_timer is not None:
                self._header_timer.cancel()
                self._header_timer = None

        def _header_timeout(self) -> None:
            self._header_timer = None
            if not self.transport.is_closing():
                on_timeout()
                self.transport.close()

        def connection_made(self, transport: Any) -> None:
            super().connection_made(transport)
            self._arm()

        def on_message_begin(self) -> None:
            super().on_message_begin()
            self._arm()

        def on_headers_complete(self) -> None:
            self._disarm()
            super().on_headers_complete()

        def connection_lost(self, exc: Exception | None) -> None:
            self._disarm()
            super().connection_lost(exc)

    return HeaderTimeoutProtocol
