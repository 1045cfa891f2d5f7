"""Standard input (``-``) feeds one input of a command (the input review).

Every input named ``-`` read the first one's spooled copy: ``evaluate - --truth -``
compared the positions with themselves and exited 0 with every error statistic 0;
``stats - --truth -`` and ``calibrate --self - --anchors -`` exited 2 blaming the wrong
file.  A second input named ``-`` is now refused, naming both options; one input read
twice (``locate``: the log's scale, then the fixes) still reads the same data.
"""

from __future__ import annotations

import io
import os
import subprocess
import sys
from pathlib import Path

import pandas as pd
import pytest
from test_noloss_inputs import ANCHORS, _ranges  # (a log of four anchors' ranges)

import robustloc
import robustloc.io.tables as tables
from robustloc.cli import main
from robustloc.errors import InputError

ENV = {**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[1] / "src")}
CLI = [sys.executable, "-m", "robustloc.cli"]
ONE_INPUT = ("one input per command can come from standard input: give the other one as "
             "a file")


@pytest.fixture()
def files(tmp_path):
    (tmp_path / "a.csv").write_text(ANCHORS)
    _ranges(20).to_csv(tmp_path / "m.csv", index=False)
    assert main(["locate", str(tmp_path / "m.csv"), "--anchors", str(tmp_path / "a.csv"),
                 "--method", "ls", "-o", str(tmp_path / "p.csv"), "-q"]) == 0
    return tmp_path


def _run(args: list[str], data: bytes) -> subprocess.CompletedProcess:
    return subprocess.run(CLI + args, input=data, capture_output=True, env=ENV, timeout=300)


def test_evaluate_refuses_stdin_for_positions_and_truth(files):
    """The review's case: exit 0 with every error statistic 0, an output written."""
    out = files / "e.csv"
    r = _run(["evaluate", "-", "--truth", "-", "-o", str(out)], (files / "p.csv").read_bytes())
    assert r.returncode == 2, r.stderr
    assert r.stderr.decode() == (
        "error: <stdin>: standard input is already read as another input of this command "
        f"(POSITIONS), so --truth cannot also be - ({ONE_INPUT})\n")
    assert not out.exists()


@pytest.mark.parametrize("args, first, second", [
    (["stats", "-", "--anchors", "{a}", "--truth", "-", "-o", "{d}/st"],
     "MEASUREMENTS", "--truth"),
    (["calibrate", "--self", "-", "--anchors", "-", "-o", "{d}/cal.csv"],
     "--anchors", "--self"),
    (["locate", "-", "--anchors", "-", "-o", "{d}/q.csv"], "MEASUREMENTS", "--anchors"),
    (["track", "-", "--anchors", "-", "-o", "{d}/q.csv"], "MEASUREMENTS", "--anchors"),
])
def test_second_stdin_input_names_both_options(files, args, first, second):
    """Refused before anything is read: the message names the options, not whichever
    file happened to be read first (``calibrate`` blamed the anchors for the
    measurements' columns)."""
    argv = [a.format(a=files / "a.csv", d=files) for a in args]
    r = _run(argv, (files / "m.csv").read_bytes())
    assert r.returncode == 2, r.stderr
    assert r.stderr.decode() == (
        "error: <stdin>: standard input is already read as another input of this command "
        f"({first}), so {second} cannot also be - ({ONE_INPUT})\n")


def test_library_refuses_stdin_for_two_inputs(files, monkeypatch):
    """The Python API: ``evaluate("-", truth="-")`` compared the positions with themselves
    too; the readers say what they read standard input as."""
    monkeypatch.setattr(sys, "stdin", io.TextIOWrapper(io.BytesIO(
        (files / "p.csv").read_bytes())))
    with pytest.raises(InputError) as err:
        robustloc.evaluate("-", truth="-")
    assert str(err.value) == (
        "<stdin>: standard input is already read as another input of this command (the "
        f"positions file), so the truth file cannot also be - ({ONE_INPUT})")
    assert not tables._SPOOLED and not tables._STDIN_READ_AS  # the scope cleaned up


def test_one_input_read_twice_from_stdin_is_the_same_data(files):
    """``locate`` reads its measurements twice (the log's scale, then the fixes: two
    spools of ``-`` as measurements); from standard input it gives what the file gives."""
    r = _run(["locate", "-", "--anchors", str(files / "a.csv"), "--method", "ls", "-o", "-",
              "-q"], (files / "m.csv").read_bytes())
    assert r.returncode == 0, r.stderr
    pd.testing.assert_frame_equal(pd.read_csv(io.BytesIO(r.stdout)),
                                  pd.read_csv(files / "p.csv"))


def test_locate_spools_stdin_twice_as_measurements(files, monkeypatch):
    """The two passes the previous test relies on, counted (so that it tests the case)."""
    calls: list[tuple[str, str | None]] = []
    orig = tables._spool

    def spy(path, what=None):
        calls.append((str(path), what))
        return orig(path, what)

    monkeypatch.setattr(tables, "_spool", spy)
    monkeypatch.setattr(sys, "stdin", io.TextIOWrapper(io.BytesIO(
        (files / "m.csv").read_bytes())))
    assert main(["locate", "-", "--anchors", str(files / "a.csv"), "--method", "ls",
                 "-o", str(files / "s.csv"), "-q"]) == 0
    assert calls == [("-", "measurements"), ("-", "measurements")]
    pd.testing.assert_frame_equal(pd.read_csv(files / "s.csv"), pd.read_csv(files / "p.csv"))
