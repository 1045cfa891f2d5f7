"""An interrupted command's process exits with the code it printed (130 / 143), even when
a signal arrives after the command has returned: the full suite saw a reproduce run print
``error: interrupted`` and then die of SIGINT (status -2), a signal handled by Python's own
handler during the exit (``robustloc.cli.entry``)."""

from __future__ import annotations

import signal
import subprocess
import sys
import textwrap

import pytest

SCRIPT = textwrap.dedent("""
    import os, signal, sys
    import robustloc.cli as cli

    def interrupted(args):
        raise {exc}()

    import robustloc.commands.stats as command

    command.run = interrupted  # (the parser takes the command module's run)
    sys.argv = ["robustloc", "stats", "m.csv", "-o", "out"]
    code = {call}
    # a signal after the command returned (one re-sent late, or a second Ctrl-C)
    os.kill(os.getpid(), signal.{sig})
    for _ in range(1000):
        pass
    print("exiting", code, flush=True)
    sys.exit(code)
""")


def _run(tmp_path, exc: str, sig: str, call: str) -> subprocess.CompletedProcess:
    (tmp_path / "m.csv").write_text("time,tag,anchor,rssi\n0,t,a,-60\n")
    return subprocess.run([sys.executable, "-c", SCRIPT.format(exc=exc, sig=sig, call=call)],
                          capture_output=True, text=True, timeout=120, cwd=tmp_path)


@pytest.mark.skipif(sys.platform == "win32", reason="POSIX signals")
@pytest.mark.parametrize("exc, sig, code, said", [
    ("KeyboardInterrupt", "SIGINT", 130, "error: interrupted"),
    ("cli.Terminated", "SIGTERM", 143, "error: terminated"),
])
def test_a_signal_after_an_interrupted_command_keeps_its_exit_code(tmp_path, exc, sig, code,
                                                                  said):
    """The entry point (``cli.entry``, the ``robustloc`` script): the late signal is ignored,
    the process exits with the code it printed.  (Before, ``main`` was the entry point:
    SIGINT killed it, status -2; SIGTERM, -15.)"""
    proc = _run(tmp_path, exc, sig, 'getattr(cli, "entry", cli.main)()')
    assert proc.returncode == code, (proc.returncode, proc.stderr)
    assert said in proc.stderr
    assert f"exiting {code}" in proc.stdout


@pytest.mark.skipif(sys.platform == "win32", reason="POSIX signals")
def test_a_program_calling_main_keeps_its_own_sigint_handler(tmp_path):
    """``main()`` called from a program (tests, notebooks) leaves its handlers alone (an
    ignored SIGINT would be inherited by every process it starts): the late SIGINT is
    that program's KeyboardInterrupt, as before."""
    proc = _run(tmp_path, "KeyboardInterrupt", "SIGINT", "cli.main()")
    assert proc.returncode == -signal.SIGINT, (proc.returncode, proc.stderr)
    assert "error: interrupted" in proc.stderr


SPY = textwrap.dedent("""
    import os, signal, sys
    import robustloc.cli as cli
    import robustloc.commands.stats as command

    def interrupted(args):
        os.kill(os.getpid(), signal.SIGINT)  # the command's handler raises, and notes it
        for _ in range(10**6):
            pass

    seen = []
    restore = cli._restore_handlers

    def spy(old):
        restore(old)
        seen.append(signal.getsignal(signal.SIGINT))

    cli._restore_handlers = spy
    command.run = interrupted
    sys.argv = ["robustloc", "stats", "m.csv", "-o", "out"]
    code = cli.{call}()
    print("restored", code, "ignored" if seen[0] is signal.SIG_IGN else
          "python's" if seen[0] is signal.default_int_handler else repr(seen[0]), flush=True)
""")


@pytest.mark.skipif(sys.platform == "win32", reason="POSIX signals")
@pytest.mark.parametrize("call, handler", [("entry", "ignored"), ("main", "python's")])
def test_an_interrupted_command_never_puts_pythons_handler_back_before_the_exit(
        tmp_path, call, handler):
    """Through ``entry`` (the process ends with the command), the end of an interrupted
    command ignores SIGINT at once instead of restoring Python's handler: no moment is
    left where a late signal kills the process (status -2 after ``error: interrupted``,
    the full suite a third time).  Through ``main`` (a program's call) its handler is
    restored."""
    (tmp_path / "m.csv").write_text("time,tag,anchor,rssi\n0,t,a,-60\n")
    proc = subprocess.run([sys.executable, "-c", SPY.format(call=call)], capture_output=True,
                          text=True, timeout=120, cwd=tmp_path)
    assert f"restored 130 {handler}" in proc.stdout, (proc.stdout, proc.stderr)
    assert "error: interrupted" in proc.stderr
