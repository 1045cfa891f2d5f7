"""Fixtures shared by the service tests."""

from __future__ import annotations

from collections.abc import Callable, Iterator

import pytest


@pytest.fixture
def server_factory() -> Iterator[Callable[..., object]]:
    """``server_factory(args, **kw)``: a started ``robustloc serve``
    (:class:`robustloc.service.launch.ServerProcess` on a free loopback port, ``kw`` passed
    to it); every server started is stopped at teardown."""
    from robustloc.service.launch import ServerProcess

    started: list[ServerProcess] = []

    def make(args: list[str], **kw) -> ServerProcess:
        s = ServerProcess(args, **kw)
        started.append(s)
        return s.start()

    try:
        yield make
    finally:
        for s in started:
            s.stop()
