"""Fixtures shared by several test modules: a started ``robustloc serve`` (the service
tests), a dask scheduler (the Dask engine tests) and the simulated uwb-cart (the fuse tests)."""

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


@pytest.fixture(scope="module")
def scheduler() -> Iterator[str]:
    """The address of a LocalCluster of two single-threaded thread workers (the engine is
    reached with ``--scheduler``, as a user's cluster); closed at the module's end."""
    distributed = pytest.importorskip("distributed")
    cluster = distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=False,
                                       dashboard_address=None)
    try:
        yield cluster.scheduler_address
    finally:
        cluster.close()


@pytest.fixture(scope="module")
def cart(tmp_path_factory):
    """The simulated ``uwb-cart`` scenario (seed 1), simulated once per test module: the
    fuse, filter and plausibility tests' common input."""
    from robustloc.cli import main

    d = tmp_path_factory.mktemp("cart")
    assert main(["simulate", "uwb-cart", "--seed", "1", "--out", str(d)]) == 0
    return d
