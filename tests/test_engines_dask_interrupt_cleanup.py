"""Ctrl-C during ``--engine dask`` / ``partition --method dask``: the cleanup prints no
traceback (the dask review: ``ClosedClientError`` from the watch thread of
``gather_with_progress``, which cancelled the tasks on the client the interrupted main
thread had closed; ``NameError: cannot access free variable 'future'`` from
distributed's ``sync()`` when the next signal landed in the cleanup's calls)."""

from __future__ import annotations

import os
import signal
import time

import pytest

pytest.importorskip("distributed")

from robustloc.engines import cluster  # noqa: E402


class _Client:
    """A client whose ``cancel`` fails as distributed's does once it is closed."""

    def __init__(self, status: str, closes_meanwhile: bool = False) -> None:
        self.status = status
        self.closes_meanwhile = closes_meanwhile
        self.cancelled = 0

    def cancel(self, futures) -> None:
        from distributed.client import ClosedClientError

        if self.closes_meanwhile:
            self.status = "closed"
        if self.status != "running":
            raise ClosedClientError(f"Client is {self.status}. Can't send cancel-keys "
                                    "message.")
        self.cancelled += 1


@pytest.mark.parametrize("status", ["closing", "closed"])
def test_no_cancel_on_a_client_no_longer_running(status):
    c = _Client(status)
    cluster._cancel(c, [])
    assert c.cancelled == 0


def test_a_client_closing_during_the_cancel_is_tolerated_and_a_running_ones_error_raised():
    cluster._cancel(_Client("running", closes_meanwhile=True), [])
    c = _Client("running")
    cluster._cancel(c, [])
    assert c.cancelled == 1

    class Broken(_Client):
        def cancel(self, futures) -> None:
            raise RuntimeError("not a closed client")

    with pytest.raises(RuntimeError, match="not a closed client"):
        cluster._cancel(Broken("running"), [])


def test_a_signal_in_the_cleanup_of_an_interrupt_is_held_and_dropped(monkeypatch):
    """The cleanup after Ctrl-C (the tasks cancelled, the client and cluster closed, all
    in distributed's ``sync()``) is not interrupted again: a second Ctrl-C, or the SIGINT
    ``timeout`` forwards, is noted and dropped (the command ends interrupted already); a
    signal during the cleanup of a normal end is delivered after it."""
    monkeypatch.setattr(cluster, "SIGNAL_HOLD_SECONDS", 5.0)
    old = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        with cluster._cleanup_signals_held(KeyboardInterrupt()):
            os.kill(os.getpid(), signal.SIGINT)
            os.kill(os.getpid(), signal.SIGINT)
            time.sleep(0.1)  # (a handler runs between bytecodes: here)
        with pytest.raises(KeyboardInterrupt):
            with cluster._cleanup_signals_held(None):
                os.kill(os.getpid(), signal.SIGINT)
                time.sleep(0.1)
                finished = True  # the block ran to its end first
        assert finished
    finally:
        signal.signal(signal.SIGINT, old)
