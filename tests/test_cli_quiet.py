"""``-q`` / ``--quiet`` on every command with a progress bar: no bar and no text summary
(``montecarlo``: its table is the output and stays), the output written as without it,
warnings still on stderr.  The real command line in-process on simulated logs."""

from __future__ import annotations

import argparse
import json

import pandas as pd
import pytest

from robustloc.cli import main
from robustloc.sim.wifi_room import simulate


@pytest.fixture(scope="module")
def room(tmp_path_factory):
    out = tmp_path_factory.mktemp("wifi")
    return simulate(out, 4, argparse.Namespace(samples_per_point=5, walk_epochs=30))


@pytest.mark.parametrize("command", ["locate", "track", "filter", "fuse"])
@pytest.mark.parametrize("flag", ["-q", "--quiet"])
def test_quiet_writes_the_output_and_prints_no_summary(command, flag, room, cart, tmp_path,
                                                       capsys):
    out = tmp_path / "o.csv"
    if command == "fuse":
        args = ["fuse", "--ranges", str(cart / "measurements.csv"), "--anchors",
                str(cart / "anchors.csv")]
    else:
        args = [command, str(room["measurements"]), "--anchors", str(room["anchors"])]
    capsys.readouterr()
    assert main([*args, "-o", str(out)]) == 0
    loud = capsys.readouterr().out
    assert loud.strip()  # the summary, without the flag
    ref = pd.read_csv(out)
    out.unlink()
    assert main([*args, "-o", str(out), flag]) == 0
    got = capsys.readouterr()
    assert got.out == ""
    assert "Traceback" not in got.err
    pd.testing.assert_frame_equal(pd.read_csv(out), ref)


def test_montecarlo_quiet_keeps_its_table(capsys):
    """The same table (the same seed) but its ``seconds`` column, the run time."""
    args = ["montecarlo", "--gnss", "--trials", "200", "--faults", "0,1", "--seed", "3",
            "--json"]

    def table() -> list[dict]:
        return [{k: v for k, v in row.items() if k != "seconds"}
                for row in json.loads(capsys.readouterr().out)["rows"]]

    assert main(args) == 0
    loud = table()
    assert main([*args, "-q"]) == 0
    assert loud and table() == loud


def _stderr_on_a_terminal(args: list[str]) -> str:
    """Run the command line in a subprocess whose stderr is a pseudo-terminal (the bars
    show only on a terminal) and return what it wrote there."""
    import fcntl
    import os
    import pty
    import struct
    import subprocess
    import termios

    from robustloc.service.launch import ROBUSTLOC

    master, slave = pty.openpty()
    # an 80-column window (a new pty has 0 columns, and tqdm then draws an empty bar)
    fcntl.ioctl(slave, termios.TIOCSWINSZ, struct.pack("HHHH", 24, 80, 0, 0))
    try:
        proc = subprocess.Popen([*ROBUSTLOC, *args], stdout=subprocess.DEVNULL,
                                stderr=slave, stdin=subprocess.DEVNULL)
        os.close(slave)
        chunks = []
        while True:
            try:
                data = os.read(master, 65536)
            except OSError:  # EIO: the terminal's other end closed with the process
                break
            if not data:
                break
            chunks.append(data)
        assert proc.wait(timeout=300) == 0
    finally:
        os.close(master)
    return b"".join(chunks).decode(errors="replace")


@pytest.mark.parametrize("command", ["filter", "fuse", "locate"])
def test_quiet_silences_the_progress_bar_on_a_terminal(command, room, cart, tmp_path):
    """On a terminal each command draws its tqdm bar on stderr (``it/s`` or ``step/s``
    and a ``|`` gauge); with ``-q`` nothing is written there."""
    if command == "fuse":
        args = ["fuse", "--ranges", str(cart / "measurements.csv"), "--anchors",
                str(cart / "anchors.csv")]
    else:
        args = [command, str(room["measurements"]), "--anchors", str(room["anchors"])]
    loud = _stderr_on_a_terminal([*args, "-o", str(tmp_path / "a.csv")])
    assert "/s]" in loud or "|" in loud, loud
    quiet = _stderr_on_a_terminal([*args, "-o", str(tmp_path / "b.csv"), "-q"])
    assert quiet.strip() == "", quiet
