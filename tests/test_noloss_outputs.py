"""Issue 15, "nothing lost": atomic outputs, output over input, concurrent writers, signals,
full disk, unwritable targets, and the one error path of the command line."""

from __future__ import annotations

import errno
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from _stderr import without_jit_notice  # (tests/_stderr.py)

from robustloc.cli import main
from robustloc.errors import InputError, OutputError
from robustloc.io import PositionsWriter, read_positions, write_table
from robustloc.io.atomic import atomic_output, check_not_input

ENV = {**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[1] / "src")}
CLI = [sys.executable, "-m", "robustloc.cli"]
#: The command line with Python's SIGINT handler installed explicitly: a test run launched
#: in the background (``cmd &`` in a script, no job control) hands its children SIGINT
#: *ignored*, Python then installs no KeyboardInterrupt handler, and a SIGINT test saw the
#: command finish with exit 0 (measured: 2 of the 4 signal cases failed that way).
CLI_SIGINT = [sys.executable, "-c",
              "import runpy, signal, sys; signal.signal(signal.SIGINT, "
              "signal.default_int_handler); sys.argv[0] = 'robustloc'; "
              "runpy.run_module('robustloc.cli', run_name='__main__')"]
ANCHORS = "anchor,x,y\na,0,0\nb,20,0\nc,0,20\nd,20,20\n"


def _ranges(n_epochs: int, seed: int = 0, tags: int = 1) -> pd.DataFrame:
    """Noise-free-ish range rows (4 anchors per epoch), sorted by time then tag."""
    rng = np.random.default_rng(seed)
    anc = np.array([[0, 0], [20, 0], [0, 20], [20, 20]], float)
    k = np.repeat(np.arange(n_epochs), 4)
    pos = rng.uniform(2, 18, (n_epochs, 2))
    d = np.hypot(pos[k, 0] - anc[np.tile(np.arange(4), n_epochs), 0],
                 pos[k, 1] - anc[np.tile(np.arange(4), n_epochs), 1])
    return pd.DataFrame({
        "time": (k // tags) * 0.5, "tag": np.char.add("T", (k % tags).astype(str)),
        "anchor": np.tile(np.array(list("abcd")), n_epochs),
        "range": d + rng.normal(0, 0.05, d.size),
    })


@pytest.fixture()
def small(tmp_path):
    (tmp_path / "a.csv").write_text(ANCHORS)
    _ranges(50).to_csv(tmp_path / "m.csv", index=False)
    return tmp_path


def _no_temp_left(folder: Path) -> None:
    left = [p.name for p in folder.iterdir() if p.name.endswith(".tmp")]
    assert left == [], left


# ------------------------------------------------------------------ atomic writers


@pytest.mark.parametrize("ext", ["csv", "parquet"])
def test_writer_error_midway_leaves_nothing_and_keeps_previous(tmp_path, ext):
    out = tmp_path / f"p.{ext}"
    frame = pd.DataFrame({"time": [0.0], "tag": ["T"], "x": [1.0], "y": [2.0], "method": "ls",
                          "status": "ok", "n_used": 3, "sigma0": 0.1, "excluded": ""})
    with pytest.raises(RuntimeError, match="boom"):
        with PositionsWriter(out) as w:
            w.write(frame)
            raise RuntimeError("boom")
    assert not out.exists()
    _no_temp_left(tmp_path)
    write_table(frame.assign(x=7.0), out)  # a previous, complete file
    for exc in (KeyboardInterrupt(), RuntimeError("again")):
        with pytest.raises(type(exc)):
            with PositionsWriter(out) as w:
                w.write(frame)
                raise exc
        assert read_positions(out)["x"].tolist() == [7.0]  # untouched
        _no_temp_left(tmp_path)


@pytest.mark.parametrize("err", [errno.ENOSPC, errno.EROFS, errno.EDQUOT])
def test_full_disk_at_fsync_is_an_output_error(tmp_path, monkeypatch, err):
    """A disk that fills up (or turns read-only) while the file is finished: OutputError
    naming the final path, the temporary file removed, the previous file intact."""
    out = tmp_path / "t.csv"
    out.write_text("previous\n")

    def fail(fd):
        raise OSError(err, os.strerror(err))

    monkeypatch.setattr(os, "fsync", fail)
    with pytest.raises(OutputError) as ei:
        write_table(pd.DataFrame({"a": [1, 2]}), out)
    assert ei.value.path == str(out)
    assert out.read_text() == "previous\n"
    _no_temp_left(tmp_path)


def test_dev_full_and_unwritable_targets_via_cli(small, capsys):
    base = ["locate", str(small / "m.csv"), "--anchors", str(small / "a.csv"), "--method", "ls"]
    cases = [
        ("/dev/full", "error: /dev/full: no space left on device\n"),
        (str(small / "a.csv" / "p.csv"),
         f"error: {small / 'a.csv' / 'p.csv'}: a parent of this path is a file, not a folder\n"),
        # root may write anywhere on a normal file system; /sys refuses file creation
        ("/sys/p.csv", "error: /sys/p.csv: permission denied\n"),
        (str(small), f"error: {small}: is a directory, expected a file\n"),
    ]
    for out, message in cases:
        assert main(base + ["-o", out]) == 2, out
        assert without_jit_notice(capsys.readouterr().err) == message
    _no_temp_left(small)


def test_full_disk_real_process(small):
    """A real process writing positions to /dev/full: exit 2, the message, no traceback."""
    r = subprocess.run(CLI + ["locate", str(small / "m.csv"), "--anchors", str(small / "a.csv"),
                              "-o", "/dev/full", "--method", "ls", "--quiet"],
                       capture_output=True, text=True, env=ENV)
    assert r.returncode == 2
    assert r.stderr == "error: /dev/full: no space left on device\n"


# ------------------------------------------------------------------ output over input


def test_output_over_input_refused_before_writing(small, capsys):
    m = small / "m.csv"
    before = m.read_bytes()
    for out in (m, small / "." / "m.csv"):
        assert main(["locate", str(m), "--anchors", str(small / "a.csv"), "-o", str(out)]) == 2
        assert capsys.readouterr().err == f"error: {out}: output would overwrite an input\n"
    os.symlink(m, small / "link.csv")
    assert main(["locate", str(m), "--anchors", str(small / "a.csv"),
                 "-o", str(small / "link.csv")]) == 2
    assert "output would overwrite an input" in capsys.readouterr().err
    assert main(["locate", str(m), "--anchors", str(small / "a.csv"),
                 "-o", str(small / "a.csv")]) == 2
    assert "a.csv: output would overwrite an input" in capsys.readouterr().err
    assert m.read_bytes() == before
    # evaluate: the statistics table over the truth
    t = small / "t.csv"
    t.write_text("time,tag,x,y\n0,T0,1,1\n")
    p = small / "p.csv"
    p.write_text("time,tag,x,y\n0,T0,1,1\n")
    assert main(["evaluate", str(p), "--truth", str(t), "-o", str(t)]) == 2
    assert capsys.readouterr().err == f"error: {t}: output would overwrite an input\n"
    with pytest.raises(InputError, match="output would overwrite an input"):
        check_not_input(p, [t, p])


# ------------------------------------------------------------------ concurrent writers


@pytest.mark.parametrize("ext", ["csv", "parquet"])
def test_two_concurrent_writers_last_complete_file_wins(tmp_path, ext):
    (tmp_path / "a.csv").write_text(ANCHORS)
    n_epochs = 20_000
    _ranges(n_epochs).to_csv(tmp_path / "m.csv", index=False)
    out = tmp_path / f"same.{ext}"
    procs = []
    try:
        for meth in ("ls", "nls"):
            procs.append(subprocess.Popen(
                CLI + ["locate", str(tmp_path / "m.csv"), "--anchors", str(tmp_path / "a.csv"),
                       "-o", str(out), "--method", meth, "--chunk-rows", "4000", "--quiet"],
                stderr=subprocess.PIPE, text=True, env=ENV))
        for p in procs:
            _, err = p.communicate(timeout=300)
            assert p.returncode == 0, err
    finally:  # a failed assertion or a timeout leaves no writer running
        for p in procs:
            if p.poll() is None:
                p.kill()
                p.wait()
    pos = read_positions(out)
    assert len(pos) == n_epochs
    assert pos["method"].nunique() == 1  # one complete file, never a mix
    assert pos["time"].is_monotonic_increasing
    _no_temp_left(tmp_path)


# ------------------------------------------------------------------ signals


def _big_input(folder: Path, n_epochs: int = 150_000) -> None:
    (folder / "a.csv").write_text(ANCHORS)
    _ranges(n_epochs).to_csv(folder / "m.csv", index=False)


@pytest.fixture(scope="module")
def big(tmp_path_factory):
    d = tmp_path_factory.mktemp("big")
    _big_input(d)
    return d


@pytest.mark.parametrize(("sig", "code", "word", "ext", "previous"), [
    (signal.SIGINT, 130, "interrupted", "csv", False),
    (signal.SIGINT, 130, "interrupted", "parquet", True),
    (signal.SIGTERM, 143, "terminated", "parquet", False),
    (signal.SIGTERM, 143, "terminated", "csv", True),
])
def test_signal_mid_run_leaves_nothing(big, tmp_path, sig, code, word, ext, previous):
    """A real process, signalled while it writes (its temporary file exists): exit 130 /
    143, `error: interrupted|terminated`, no file at the final path (or the previous one
    intact) and no temporary file."""
    out = tmp_path / f"p.{ext}"
    if previous:
        out.write_bytes(b"previous")
    p = subprocess.Popen(CLI_SIGINT + ["locate", str(big / "m.csv"), "--anchors",
                                       str(big / "a.csv"), "-o", str(out), "--method", "nls",
                                       "--chunk-rows", "20000", "--quiet"],
                         stderr=subprocess.PIPE, text=True, env=ENV)
    try:
        deadline = time.monotonic() + 240
        while not any(f.name.endswith(".tmp") and f.stat().st_size > 0
                      for f in tmp_path.iterdir()):
            assert p.poll() is None, p.communicate()[1]
            assert time.monotonic() < deadline
            time.sleep(0.05)
        p.send_signal(sig)
        _, err = p.communicate(timeout=120)
    finally:  # a failed wait or a timeout leaves no process running
        if p.poll() is None:
            p.kill()
            p.wait()
    assert p.returncode == code, err
    assert err == f"error: {word}\n"
    if previous:
        assert out.read_bytes() == b"previous"
    else:
        assert not out.exists()
    _no_temp_left(tmp_path)


# ------------------------------------------------------------------ one error path


def test_internal_bug_is_exit_1_with_traceback_not_2(small, capsys, monkeypatch):
    import robustloc.commands.evaluate as ev

    def bug(args):
        return {}["missing key"]

    monkeypatch.setattr(ev, "run", bug)
    t = small / "t.csv"
    t.write_text("time,tag,x,y\n0,T0,1,1\n")
    assert main(["evaluate", str(t), "--truth", str(t)]) == 1
    err = capsys.readouterr().err
    assert err.startswith("internal error") and "Traceback" in err and "KeyError" in err

    def value_bug(args):
        raise ValueError("deep inside")

    monkeypatch.setattr(ev, "run", value_bug)
    assert main(["evaluate", str(t), "--truth", str(t)]) == 1
    assert "ValueError: deep inside" in capsys.readouterr().err

    def os_bug(args):
        raise OSError(errno.EIO, "no path")

    monkeypatch.setattr(ev, "run", os_bug)
    assert main(["evaluate", str(t), "--truth", str(t)]) == 1


def test_internal_bug_real_process_exit_1(tmp_path):
    """`--param` with a value the weight's own check refuses is a user error (2); a file
    error is 2; the process never prints a traceback for them."""
    (tmp_path / "a.csv").write_text(ANCHORS)
    _ranges(5).to_csv(tmp_path / "m.csv", index=False)
    r = subprocess.run(CLI + ["locate", str(tmp_path / "m.csv"), "--anchors",
                              str(tmp_path / "a.csv"), "-o", str(tmp_path / "p.csv"),
                              "--method", "huber", "--param", "c=-1"],
                       capture_output=True, text=True, env=ENV)
    assert r.returncode == 2 and r.stderr.startswith("error: ") and "Traceback" not in r.stderr


@pytest.mark.parametrize(("argv", "message"), [
    (["--method", ","], "argument --method: expected one or more of"),
    (["--method", "ls,ls"], "argument --method: method 'ls' given twice"),
    (["--method", "ls,,nls"], "argument --method: empty method name"),
    (["--param", "zz=3"], "error: --param 'zz' is not a threshold of the chosen method(s) "
                          "(known: auto: c)"),
    (["--method", "hampel,igg", "--param", "k0=x"], "error: --param expects NAME=NUMBER"),
    (["--method", "hampel", "--param", "c=nan"], "error: --param expects NAME=NUMBER"),
    (["--method", "ls", "--param", "c=1"], "apply only to the robust methods"),
    (["--tag-height", "nan"], "argument --tag-height: expected a finite number"),
    # (the range since 38d44b6: 1e-300 passed "> 0" and made every fix ill_conditioned)
    (["--sigma", "-1"], "argument --sigma: expected a number in [1e-06, 1e+06]"),
    (["--chunk-rows", "0"], "argument --chunk-rows: expected a whole number >= 1"),
    (["--alpha0", "inf"], "argument --alpha0: expected a finite number"),
])
def test_locate_option_values_refused(small, capsys, argv, message):
    rc = main(["locate", str(small / "m.csv"), "--anchors", str(small / "a.csv"),
               "-o", str(small / "p.csv")] + argv)
    err = capsys.readouterr().err
    assert rc == 2 and message in err and "Traceback" not in err
    assert not (small / "p.csv").exists()


def test_param_known_names_of_several_methods(small, capsys):
    rc = main(["locate", str(small / "m.csv"), "--anchors", str(small / "a.csv"),
               "-o", str(small / "p.csv"), "--method", "hampel,igg", "--param", "zz=1"])
    assert rc == 2
    assert ("(known: hampel: a, b, c; igg: k0, k1, c)" in capsys.readouterr().err)
    # a name one of them knows is applied to that one only
    assert main(["locate", str(small / "m.csv"), "--anchors", str(small / "a.csv"),
                 "-o", str(small / "p.csv"), "--method", "hampel,igg", "--param", "k0=2",
                 "--quiet"]) == 0


def test_evaluate_option_values_refused(small, capsys):
    t = small / "t.csv"
    t.write_text("time,tag,x,y\n0,T0,1,1\n")
    assert main(["evaluate", str(t), "--truth", str(t), "--time-tolerance", "-1"]) == 2
    assert "argument --time-tolerance: expected a number >= 0" in capsys.readouterr().err
    assert main(["evaluate", str(t), "--truth", str(t), "--time-tolerance", "nan"]) == 2
    assert "expected a finite number" in capsys.readouterr().err


def test_atomic_output_special_targets(tmp_path):
    with atomic_output("/dev/null") as (target, stream):
        assert target == Path("/dev/null") and stream is None
        target.write_text("x")
    assert Path("/dev/null").exists() and not Path("/dev/null").is_file()


def test_folder_output_that_is_a_file(small, capsys):
    """Issue 15: `-o` on an existing file where a folder is expected was a FileExistsError
    traceback; the OS error about the user's path is now `error: PATH: what`, exit 2."""
    f = small / "a.csv"
    assert main(["reliability", "--anchors", str(f), "-o", str(f), "--no-maps"]) == 2
    assert capsys.readouterr().err == (
        f"error: {f}: already exists and is not a folder (a folder was expected)\n")
    assert main(["simulate", "ble-corridor", "--seed", "1", "--out", str(f / "sub")]) == 2
    err = capsys.readouterr().err
    # the message names the file standing where a folder must be (the parent of `sub`)
    assert err.startswith(f"error: {f}") and "not a folder" in err and "Traceback" not in err


def test_dev_stdout_redirected_to_a_file(small):
    """`-o /dev/stdout > file`: the data go to the file, the summary to stderr, and the
    /dev/stdout symlink is never replaced by a temporary file."""
    link = os.readlink("/dev/stdout")
    with open(small / "out.csv", "wb") as fh:
        r = subprocess.run(CLI + ["locate", str(small / "m.csv"), "--anchors",
                                  str(small / "a.csv"), "-o", "/dev/stdout", "--method", "ls"],
                           stdout=fh, stderr=subprocess.PIPE, text=True, env=ENV)
    assert r.returncode == 0 and "50 epochs of range -> /dev/stdout" in r.stderr
    assert os.readlink("/dev/stdout") == link
    pos = pd.read_csv(small / "out.csv")
    assert len(pos) == 50 and list(pos.columns[:2]) == ["time", "tag"]


@pytest.mark.parametrize(("interrupt", "code", "word"), [
    (KeyboardInterrupt, 130, "interrupted"),
    ("terminated", 143, "terminated"),
])
@pytest.mark.parametrize("wrapper", [RuntimeError, OSError, ValueError])
def test_an_interrupt_a_library_wrapped_is_still_an_interrupt(monkeypatch, capsys, interrupt,
                                                              code, word, wrapper):
    """A signal handled inside a library's own Python code can reach the command wrapped
    in the library's error (seen: SIGINT while numba unpickled a cached kernel, reported
    as an internal error).  The command still exits 130 / 143 with ``error: interrupted``
    / ``terminated``, whether the interrupt is the cause or the context."""
    from robustloc.cli import main
    from robustloc.commands import locate
    from robustloc.errors import Terminated

    exc_type = Terminated if interrupt == "terminated" else interrupt

    def run(args):
        try:
            raise exc_type()
        except BaseException as inner:  # noqa: BLE001 - what a library's except does
            raise wrapper("failed while loading a kernel") from inner

    monkeypatch.setattr(locate, "run", run)
    assert main(["locate", "m.csv", "--anchors", "a.csv", "-o", "p.csv"]) == code
    err = capsys.readouterr().err
    assert err == f"error: {word}\n"


# ------------------------------------------------------------------ folder outputs over inputs


def test_stats_folder_never_replaces_an_input_of_the_same_name(tmp_path, capsys):
    """`stats st/per_anchor.csv -o st` replaced its input by the table of the same name
    (exit 0): refused, exit 2, the input byte for byte, nothing moved into the folder."""
    st = tmp_path / "st"
    st.mkdir()
    inp = st / "per_anchor.csv"
    inp.write_text("time,tag,anchor,rssi\n0,t,A1,-50\n1,t,A1,-52\n2,t,A1,-51\n")
    before = inp.read_bytes()
    assert main(["stats", str(inp), "-o", str(st)]) == 2
    assert capsys.readouterr().err == f"error: {inp}: output would overwrite an input\n"
    assert inp.read_bytes() == before
    assert sorted(p.name for p in st.iterdir()) == ["per_anchor.csv"]
    assert [p.name for p in tmp_path.iterdir() if p.name.endswith(".tmp")] == []
    # the same through another spelling of the folder and a symbolic link to the input
    os.symlink(inp, tmp_path / "link.csv")
    assert main(["stats", str(tmp_path / "link.csv"), "-o", str(st / ".")]) == 2
    assert "output would overwrite an input" in capsys.readouterr().err
    assert inp.read_bytes() == before
    # an input elsewhere is fine
    other = tmp_path / "m.csv"
    other.write_bytes(before)
    assert main(["stats", str(other), "-o", str(tmp_path / "st2")]) == 0
    capsys.readouterr()


def test_reliability_folder_never_replaces_its_anchors(small, capsys):
    rel = small / "rel"
    rel.mkdir()
    anchors = rel / "reliability.csv"
    anchors.write_text(ANCHORS)
    before = anchors.read_bytes()
    assert main(["reliability", "--anchors", str(anchors), "-o", str(rel), "--no-maps"]) == 2
    assert capsys.readouterr().err == f"error: {anchors}: output would overwrite an input\n"
    assert anchors.read_bytes() == before
    assert sorted(p.name for p in rel.iterdir()) == ["reliability.csv"]
    # --candidates is an input too
    cand = rel / "suggestions.csv"
    cand.write_text("x,y\n5,5\n15,15\n")
    cbefore = cand.read_bytes()
    assert main(["reliability", "--anchors", str(small / "a.csv"), "-o", str(rel),
                 "--no-maps", "--suggest", "--candidates", str(cand), "--step", "2"]) == 2
    assert capsys.readouterr().err == f"error: {cand}: output would overwrite an input\n"
    assert cand.read_bytes() == cbefore and anchors.read_bytes() == before


def test_write_folder_checks_every_file_before_moving_any(tmp_path):
    from robustloc.commands._folder import write_folder

    out = tmp_path / "out"
    out.mkdir()
    keep = out / "b.csv"
    keep.write_text("input\n")
    os.link(keep, tmp_path / "hard.csv")  # the input by another name (a hard link)

    def write(folder: Path) -> str:
        (folder / "a.csv").write_text("new a\n")  # sorted first: would be moved first
        (folder / "b.csv").write_text("new b\n")
        return "done"

    with pytest.raises(InputError, match="output would overwrite an input") as ei:
        write_folder(out, write, [tmp_path / "hard.csv", None])
    assert ei.value.path == str(out / "b.csv")
    assert sorted(p.name for p in out.iterdir()) == ["b.csv"]
    assert keep.read_text() == "input\n"
    assert write_folder(out, write, [tmp_path / "elsewhere.csv"]) == "done"
    assert keep.read_text() == "new b\n"


# ------------------------------------------------------------------ compressed outputs


def test_gz_output_is_gzip_for_every_writer(small, capsys):
    """`-o X.csv.gz` wrote plain CSV under a .gz name (`evaluate` then failed "Not a
    gzipped file"): locate (streamed), track, filter and evaluate write gzip now, read
    back equal to the plain output; no temporary file is left."""
    import gzip

    base = ["--anchors", str(small / "a.csv"), "--quiet"]
    m = str(small / "m.csv")
    assert main(["locate", m, *base, "-o", str(small / "p.csv"), "--method", "ls"]) == 0
    assert main(["locate", m, *base, "-o", str(small / "p.csv.gz"), "--method", "ls",
                 "--chunk-rows", "40"]) == 0
    assert main(["track", m, *base, "-o", str(small / "t.csv")]) == 0
    assert main(["track", m, *base, "-o", str(small / "t.csv.gz")]) == 0
    assert main(["track", m, *base, "-o", str(small / "ts.csv.gz"), "--smooth"]) == 0
    capsys.readouterr()
    for name in ("p.csv.gz", "t.csv.gz", "ts.csv.gz"):
        raw = (small / name).read_bytes()
        assert raw[:2] == b"\x1f\x8b", name
        assert gzip.decompress(raw).startswith(b"time,tag,x,y"), name
    assert gzip.decompress((small / "p.csv.gz").read_bytes()) == (small / "p.csv").read_bytes()
    assert gzip.decompress((small / "t.csv.gz").read_bytes()) == (small / "t.csv").read_bytes()
    pd.testing.assert_frame_equal(read_positions(small / "p.csv.gz"),
                                  read_positions(small / "p.csv"))
    truth = small / "truth.csv"
    truth.write_text("time,tag,x,y\n" + "".join(f"{0.5 * k},T0,10,10\n" for k in range(50)))
    assert main(["evaluate", str(small / "p.csv.gz"), "--truth", str(truth),
                 "-o", str(small / "e.csv.gz")]) == 0
    capsys.readouterr()
    assert gzip.decompress((small / "e.csv.gz").read_bytes()).startswith(b"tag,")
    write_table(pd.DataFrame({"a": [1.5, 2.5]}), small / "w.csv.gz")
    assert pd.read_csv(small / "w.csv.gz")["a"].tolist() == [1.5, 2.5]
    _no_temp_left(small)


@pytest.mark.parametrize("suffix", [".bz2", ".xz", ".zip", ".zst"])
def test_compressed_names_the_readers_cannot_read_back_are_refused(small, capsys, suffix):
    out = small / f"p.csv{suffix}"
    assert main(["locate", str(small / "m.csv"), "--anchors", str(small / "a.csv"),
                 "-o", str(out), "--method", "ls", "--quiet"]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"error: {out}: cannot write {suffix} compressed output"), err
    assert not out.exists()
    _no_temp_left(small)


def test_gz_output_interrupted_while_compressing_leaves_nothing(tmp_path, monkeypatch):
    """An error while compressing: no file at the final path (or the previous one intact)
    and neither temporary file left."""
    import shutil

    out = tmp_path / "p.csv.gz"
    out.write_bytes(b"previous")

    def boom(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(shutil, "copyfileobj", boom)
    with pytest.raises(KeyboardInterrupt):
        write_table(pd.DataFrame({"a": [1]}), out)
    assert out.read_bytes() == b"previous"
    _no_temp_left(tmp_path)


@pytest.mark.parametrize("cmd", ["locate", "track", "calibrate", "evaluate"])
@pytest.mark.parametrize("name", ["out.json", "out.xlsx", "out.tsv", "out.parquet.gz"])
def test_an_output_named_for_another_format_is_refused(small, capsys, cmd, name):
    """`-o out.json` (or .xlsx, .tsv) was written as CSV without a word: a script then
    reading it as JSON failed far from the cause.  Now exit 2 before any work, nothing
    written."""
    out = small / name
    m, a = str(small / "m.csv"), str(small / "a.csv")
    if cmd == "evaluate":
        assert main(["locate", m, "--anchors", a, "-o", str(small / "p.csv"), "--quiet"]) == 0
        truth = small / "truth.csv"
        pd.DataFrame({"time": [0.0], "tag": ["T0"], "x": [1.0], "y": [1.0]}).to_csv(
            truth, index=False)
        argv = ["evaluate", str(small / "p.csv"), "--truth", str(truth), "-o", str(out)]
    elif cmd == "calibrate":  # a command that writes its table at the end
        argv = ["calibrate", "--self", m, "--anchors", a, "-o", str(out)]
    else:
        argv = [cmd, m, "--anchors", a, "-o", str(out), "--quiet"]
    capsys.readouterr()
    assert main(argv) == 2
    suffix = ".parquet.gz" if name.endswith(".gz") else name[name.index("."):]
    assert capsys.readouterr().err.startswith(
        f"error: {out}: cannot write a table as '{suffix}': the output is CSV")
    assert not out.exists()
    _no_temp_left(small)


@pytest.mark.parametrize("name", ["out.txt", "out", "out.csv.gz", "out.pq"])
def test_table_outputs_named_as_csv_or_parquet_are_written(small, capsys, name):
    out = small / name
    assert main(["locate", str(small / "m.csv"), "--anchors", str(small / "a.csv"), "-o",
                 str(out), "--quiet"]) == 0
    got = pd.read_parquet(out) if name.endswith(".pq") else pd.read_csv(out)
    assert len(got) == 50


def test_an_output_that_cannot_be_created_is_not_called_missing(small, capsys):
    """`-o /proc/x.csv` said "file not found" (the words of a missing input) and `-o ""`
    ". is a directory"."""
    args = [str(small / "m.csv"), "--anchors", str(small / "a.csv"), "--quiet"]
    for cmd in ("locate", "track"):
        assert main([cmd, *args, "-o", "/proc/robustloc-no-such.csv"]) == 2
        assert capsys.readouterr().err == (
            "error: /proc/robustloc-no-such.csv: cannot create a file in /proc (no such "
            "file or directory)\n")
        assert main([cmd, *args, "-o", ""]) == 2
        assert capsys.readouterr().err.startswith("error: the output name is empty")


@pytest.mark.parametrize(("sig", "code", "words"), [
    (signal.SIGINT, 130, "error: interrupted"), (signal.SIGTERM, 143, "error: terminated")])
def test_an_interrupt_a_library_swallows_is_still_an_interrupt(monkeypatch, capsys, sig,
                                                              code, words):
    """DuckDB catches the KeyboardInterrupt (or the SIGTERM handler's exception) that
    lands in its query and raises ``RuntimeError: Query interrupted`` with no chain:
    Ctrl-C during the out-of-core sort or ``partition`` was reported as an internal error,
    exit 1 (the no-loss review).  The command's handlers note the signal."""
    import robustloc.commands.stats as stats_cmd

    def swallowing(args):
        caught = False
        try:
            os.kill(os.getpid(), sig)
            time.sleep(5)
        except BaseException:  # noqa: BLE001 - what the library does
            caught = True
        if caught:
            raise RuntimeError("Query interrupted")
        return 0

    monkeypatch.setattr(stats_cmd, "run", swallowing)
    assert main(["stats", "m.csv", "-o", "out"]) == code
    err = capsys.readouterr().err
    assert words in err and "internal error" not in err
    # the handlers are restored, and the next command starts with a clean slate
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler
    from robustloc import cli

    assert cli._received == []


@pytest.mark.parametrize("stage", ["PARTITION_BY", "ORDER BY time"])
def test_partition_onto_a_full_disk_names_the_output(tmp_path, monkeypatch, capsys, stage):
    """``partition`` onto a full disk: when the per-key sort's COPY failed it was an
    internal error with a traceback, and when the first COPY failed the input file was
    blamed (the no-loss review, on a 1-2 MiB tmpfs).  Both name the output; nothing is
    left behind.  (The disk is full here by a connection whose COPY fails as DuckDB's
    does, ``IOException ... No space left on device``.)"""
    import duckdb

    import robustloc.engines.partition as part

    class Full:
        def __init__(self, con):
            self.con = con

        def execute(self, sql, *a, **k):
            if sql.startswith("COPY") and stage in sql:
                raise duckdb.IOException('IO Error: Could not write file "x": No space '
                                         'left on device')
            return self.con.execute(sql, *a, **k)

        def __getattr__(self, name):
            return getattr(self.con, name)

    connect = part._connect
    monkeypatch.setattr(part, "_connect", lambda *a, **k: Full(connect(*a, **k)))
    m = tmp_path / "m.csv"
    _ranges(40, tags=2).to_csv(m, index=False)
    out = tmp_path / "pt"
    assert main(["partition", str(m), "-o", str(out), "--by", "time"]) == 2
    err = capsys.readouterr().err
    assert err == f"error: {out}: cannot write the partitions: no space left on device\n"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["m.csv"]


def test_an_output_through_a_symbolic_link_writes_its_target(tmp_path):
    """``-o latest.csv`` where ``latest.csv`` links to an archived file replaced the link
    by a regular file and left the target with its old content; and a file of mode 0640
    came back 0644 (the no-loss review).  The target is written (the link stays), and an
    existing file keeps its permissions."""
    archive = tmp_path / "archive"
    archive.mkdir()
    target = archive / "positions-1.csv"
    target.write_text("old\n")
    os.chmod(target, 0o640)
    link = tmp_path / "latest.csv"
    link.symlink_to(target)
    write_table(pd.DataFrame({"a": [1, 2]}), link)
    assert link.is_symlink() and os.path.realpath(link) == str(target)
    assert target.read_text() == "a\n1\n2\n"
    assert (target.stat().st_mode & 0o777) == 0o640
    assert sorted(p.name for p in archive.iterdir()) == ["positions-1.csv"]  # no temp
    # a link to a file not there yet: created where the link points, as a shell's ">"
    dangling = tmp_path / "next.csv"
    dangling.symlink_to(archive / "positions-2.csv")
    write_table(pd.DataFrame({"a": [3]}), dangling)
    assert (archive / "positions-2.csv").read_text() == "a\n3\n" and dangling.is_symlink()


def test_a_plot_that_cannot_be_written_says_the_rows_were(tmp_path, monkeypatch, capsys):
    """``--plot`` into a folder that cannot take it: exit 2 after ``-o`` was written whole,
    with a message that named only the figure, so the user could think nothing was written
    (the no-loss review).  The message says the rows are there."""
    import robustloc.eval.plots as plots

    def full(*a, **k):
        raise OutputError("no space left on device", tmp_path / "fig.png", errno_=28)

    monkeypatch.setattr(plots, "positions_figure", full)
    m = tmp_path / "m.csv"
    _ranges(5).to_csv(m, index=False)
    a = tmp_path / "a.csv"
    a.write_text("anchor,x,y\na,0,0\nb,10,0\nc,0,10\nd,10,10\n")
    out = tmp_path / "p.csv"
    assert main(["locate", str(m), "--anchors", str(a), "-o", str(out), "--plot",
                 str(tmp_path / "fig.png"), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert f"(the rows are written to {out}; only the figure is missing)" in err
    assert len(pd.read_csv(out)) == 5


def test_an_interrupt_while_the_libraries_load_is_an_interrupt(monkeypatch, capsys):
    """Ctrl-C in the first second (numpy, pandas and the command modules loading, before
    the command's handlers) printed a raw KeyboardInterrupt traceback, exit -2 (the
    no-loss review).  It is ``error: interrupted``, exit 130."""
    from robustloc import cli

    def loading(*a, **k):
        raise KeyboardInterrupt

    monkeypatch.setattr(cli, "build_parser", loading)
    assert main(["locate", "--help"]) == 130
    assert capsys.readouterr().err == "error: interrupted\n"


def test_a_killed_runs_temporary_file_is_removed_by_the_next_write(tmp_path):
    """``kill -9`` (the OOM killer) leaves the temporary file of the output being written:
    nothing runs to remove it, and each killed attempt left one more (a whole output's
    size each).  The temporary file names its process (``.NAME.HOST-PID.*.tmp``); the
    next write of NAME removes those of dead processes of this host, and keeps one of a
    process that runs or of another host (a shared filesystem)."""
    from robustloc.io.atomic import _HOST

    (tmp_path / "a.csv").write_text(ANCHORS)
    _ranges(400_000).to_csv(tmp_path / "m.csv", index=False)
    out = tmp_path / "p.csv"
    proc = subprocess.Popen([*CLI, "locate", str(tmp_path / "m.csv"), "--anchors",
                             str(tmp_path / "a.csv"), "-o", str(out), "-q"], env=ENV,
                            stderr=subprocess.DEVNULL)
    try:
        deadline = time.monotonic() + 120
        while not list(tmp_path.glob(".p.csv.*.tmp")):  # writing has started
            assert proc.poll() is None and time.monotonic() < deadline, "no output begun"
            time.sleep(0.01)
        proc.send_signal(signal.SIGKILL)
    finally:
        proc.wait(30)
    orphans = list(tmp_path.glob(".p.csv.*.tmp"))
    assert len(orphans) == 1 and f".p.csv.{_HOST}-{proc.pid}." in orphans[0].name
    assert not out.exists()
    # a live process's file and another host's are not the next write's to remove
    live = tmp_path / f".p.csv.{_HOST}-{os.getpid()}.x.tmp"
    other = tmp_path / f".p.csv.otherhost-{proc.pid}.x.tmp"
    for f in (live, other):
        f.write_text("in progress")
    _ranges(20).to_csv(tmp_path / "m2.csv", index=False)
    assert main(["locate", str(tmp_path / "m2.csv"), "--anchors", str(tmp_path / "a.csv"),
                 "-o", str(out), "-q"]) == 0
    assert sorted(tmp_path.glob(".p.csv.*.tmp")) == sorted([live, other])
    assert len(pd.read_csv(out)) == 20


def _dead_pid() -> int:
    """The pid of a process that has exited (and been waited for)."""
    p = subprocess.Popen([sys.executable, "-c", "pass"])
    p.wait(30)
    return p.pid


def test_a_killed_runs_staging_folders_are_removed_by_the_next_run(tmp_path):
    """Folder outputs (``simulate``, ``stats``, ``reliability``) and staged datasets
    (``--engine dask``, ``reproduce``) build in a hidden folder named after their
    process: the next run of the same output removes those of dead processes of this
    host, and keeps a live process's and another host's."""
    from robustloc.io.atomic import _HOST, sweep_orphans

    dead = _dead_pid()
    gone = [tmp_path / f".sim.{_HOST}-{dead}.abc.tmp",  # a folder output's staging
            tmp_path / f".sim.partial-{_HOST}-{dead}-0123abcd"]  # a dataset's, a report's
    kept = [tmp_path / f".sim.{_HOST}-{os.getppid()}.abc.tmp",  # a live process's
            tmp_path / f".sim.partial-otherhost-{dead}-0123abcd",  # another host's
            tmp_path / ".sim.partial-0123abcd",  # an older robustloc's: says no process
            tmp_path / f".other.partial-{_HOST}-{dead}-0123abcd"]  # another output's
    for d in gone + kept:
        d.mkdir()
        (d / "part-00000.parquet").write_bytes(b"x" * 1000)
    assert main(["simulate", "ble-corridor", "--seed", "1", "-o", str(tmp_path / "sim"),
                 "-q"]) == 0
    assert [d for d in gone if d.exists()] == []
    assert all(d.is_dir() for d in kept)
    assert sweep_orphans(tmp_path, "sim") == 0  # nothing more to remove


def test_a_container_sharing_the_host_name_keeps_its_temporary_files(tmp_path):
    """Two containers that share a folder and a host name but not their process ids
    (``docker run -v ... --hostname``) cannot probe each other's processes: one's sweep
    would take the other's live writer for dead and delete its temporary file.  The
    name carries the process-id namespace, so a file of another namespace is kept."""
    import socket

    from robustloc.io.atomic import _HOST, sweep_orphans

    if not os.path.exists("/proc/self/ns/pid"):
        pytest.skip("no process-id namespaces here")
    ns = os.stat("/proc/self/ns/pid").st_ino
    assert _HOST.endswith(f"~{ns:x}")
    host = _HOST.rsplit("~", 1)[0]
    assert host == re.sub(r"[^A-Za-z0-9_-]", "_", socket.gethostname())[:40]
    dead = _dead_pid()
    ours = tmp_path / f".p.csv.{_HOST}-{dead}.x.tmp"
    theirs = tmp_path / f".p.csv.{host}~{ns + 1:x}-{dead}.x.tmp"
    for f in (ours, theirs):
        f.write_text("partial")
    assert sweep_orphans(tmp_path, "p.csv") == 1
    assert not ours.exists() and theirs.exists()


def test_a_previous_report_set_aside_by_a_killed_run_is_removed_only_once_replaced(
        tmp_path):
    """``reproduce`` renames the previous report aside, the new one into place, then
    deletes the old one: a run killed in between leaves ``.NAME.old-*``.  It goes with
    the next run once the report exists; while the report is missing it may be the only
    copy of it, and is kept."""
    from robustloc.io.atomic import _HOST, aside_name, sweep_orphans

    assert aside_name("rep").startswith(f".rep.old-{_HOST}-{os.getpid()}-")
    dead = _dead_pid()
    old = tmp_path / f".rep.old-{_HOST}-{dead}-0123abcd"
    live = tmp_path / f".rep.old-{_HOST}-{os.getppid()}-0123abcd"
    for d in (old, live):
        d.mkdir()
        (d / "report.md").write_text("previous report")
    assert sweep_orphans(tmp_path, "rep") == 0  # no report: the old one may be the only copy
    assert old.is_dir()
    (tmp_path / "rep").mkdir()
    assert sweep_orphans(tmp_path, "rep") == 1
    assert not old.exists() and live.is_dir()
