"""Start and stop a real ``robustloc serve`` (and a Mosquitto broker) as subprocesses.

Used by the tests and ``benchmarks/bench_serve.py``: loopback only, a free port, and
``stop()`` always called (context managers), so nothing outlives its user.
"""

from __future__ import annotations

import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
import urllib.request
from pathlib import Path

#: Command prefix running the robustloc CLI with this interpreter.
ROBUSTLOC = [sys.executable, "-c", "import sys; from robustloc.cli import main; sys.exit(main())"]


def read_metric(url: str, name: str, headers: dict | None = None,
                timeout_s: float = 30.0) -> float:
    """The value of the metric ``name`` of a running service's ``/metrics`` at ``url``,
    summed over its labels (``name{...}`` lines); 0 when absent."""
    req = urllib.request.Request(url + "/metrics", headers=headers or {})
    with urllib.request.urlopen(req, timeout=timeout_s) as r:  # noqa: S310 - http://127.0.0.1
        text = r.read().decode()
    total = 0.0
    for ln in text.splitlines():
        if ln.startswith(name + " ") or ln.startswith(name + "{"):
            total += float(ln.rsplit(" ", 1)[1])
    return total


def free_port() -> int:
    """A TCP port free on 127.0.0.1 right now."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


class ServerProcess:
    """``python -m robustloc serve ARGS --host 127.0.0.1 --port PORT`` in a subprocess.

    Parameters
    ----------
    args : list of str
        Arguments after ``serve`` (``--anchors`` etc.); host and port are added.
    port : int, optional
        Default: a free port.
    env : dict, optional
        Extra environment variables.
    startup_timeout_s : float
        Seconds to wait for ``/healthz`` (the first start compiles kernels).
    """

    def __init__(self, args: list[str], port: int | None = None, env: dict | None = None,
                 startup_timeout_s: float = 240.0) -> None:
        self.args = list(args)
        self.port = port or free_port()
        self.url = f"http://127.0.0.1:{self.port}"
        self.env = {**os.environ, **(env or {})}
        self.timeout = startup_timeout_s
        self.proc: subprocess.Popen | None = None
        self._log = tempfile.TemporaryFile()

    def start(self) -> ServerProcess:
        cmd = [*ROBUSTLOC, "serve", *self.args,
               "--host", "127.0.0.1", "--port", str(self.port)]
        self.proc = subprocess.Popen(cmd, stdout=self._log, stderr=subprocess.STDOUT,
                                     env=self.env)
        deadline = time.monotonic() + self.timeout
        while time.monotonic() < deadline:
            if self.proc.poll() is not None:
                raise RuntimeError(f"server exited with {self.proc.returncode}:\n{self.log()}")
            try:
                with urllib.request.urlopen(self.url + "/healthz", timeout=2) as r:
                    if r.status == 200:
                        return self
            except OSError:
                time.sleep(0.2)
        self.stop()
        raise RuntimeError(f"server did not answer /healthz in {self.timeout} s:\n{self.log()}")

    def log(self) -> str:
        self._log.seek(0)
        return self._log.read().decode(errors="replace")

    def kill9(self) -> None:
        """``kill -9`` the server (no shutdown code runs)."""
        if self.proc is not None and self.proc.poll() is None:
            self.proc.send_signal(signal.SIGKILL)
            self.proc.wait(timeout=30)

    def stop(self) -> None:
        """Graceful stop (SIGTERM), then SIGKILL after 20 s."""
        if self.proc is None or self.proc.poll() is not None:
            return
        self.proc.send_signal(signal.SIGTERM)
        try:
            self.proc.wait(timeout=20)
        except subprocess.TimeoutExpired:
            self.kill9()

    def __enter__(self) -> ServerProcess:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()


class MosquittoProcess:
    """A Mosquitto broker on a free loopback port (anonymous, no persistence)."""

    def __init__(self, port: int | None = None) -> None:
        self.binary = shutil.which("mosquitto") or (
            "/usr/sbin/mosquitto" if Path("/usr/sbin/mosquitto").exists() else None)
        self.port = port or free_port()
        self.proc: subprocess.Popen | None = None
        self._dir = tempfile.TemporaryDirectory()

    def start(self) -> MosquittoProcess:
        if self.binary is None:
            raise FileNotFoundError("mosquitto binary not found (apt-get install mosquitto)")
        conf = Path(self._dir.name) / "mosquitto.conf"
        conf.write_text(f"listener {self.port} 127.0.0.1\nallow_anonymous true\n"
                        "persistence false\nmax_queued_messages 100000\n")
        self.proc = subprocess.Popen([self.binary, "-c", str(conf)],
                                     stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        deadline = time.monotonic() + 20
        while time.monotonic() < deadline:
            try:
                with socket.create_connection(("127.0.0.1", self.port), timeout=1):
                    return self
            except OSError:
                if self.proc.poll() is not None:
                    raise RuntimeError("mosquitto exited at start") from None
                time.sleep(0.1)
        self.stop()
        raise RuntimeError("mosquitto did not open its port")

    def stop(self) -> None:
        if self.proc is not None and self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(timeout=10)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        self._dir.cleanup()

    def __enter__(self) -> MosquittoProcess:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()
