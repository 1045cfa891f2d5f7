"""``robustloc reproduce`` writes its report folder whole or not at all (the review).

* Ctrl-C mid-run left ``-o`` holding a figure and no report, or -- over a previous
  report -- the old report.md/summary.json beside the new run's figures; a section that
  failed left an empty (or half-filled) folder.  The run now builds the report in a hidden
  ``.NAME.partial-XXXX`` folder beside ``-o`` and renames it into place only when
  complete: ``-o`` is absent, or still the previous complete report, after any failure.
* ``--data DIR`` without a data set silently used the shipped excerpt while the log said
  ``real data: DIR``; the fallback is now said on stderr, and the captions say "full runs"
  only when the full runs were used.
* ``-o ''`` wrote the report into the working folder.

The sections run are the quickest (``--quick --only s40_integrity``, a few seconds); every
subprocess is bounded by a timeout.
"""

from __future__ import annotations

import hashlib
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from robustloc.cli import main

QUICK = ["reproduce", "--quick", "--only", "s40_integrity"]


def _snapshot(folder: Path) -> dict[str, str]:
    """File name -> content hash of every entry of ``folder``."""
    return {p.name: hashlib.sha256(p.read_bytes()).hexdigest() for p in folder.iterdir()}


def _previous_report(folder: Path) -> dict[str, str]:
    """A complete report of an earlier run (another section's figure among its files)."""
    folder.mkdir()
    (folder / "report.md").write_text("# robustloc reproduction report\n\nseed 1\n")
    (folder / "report.html").write_text("<html>seed 1</html>")
    (folder / "summary.json").write_text('{"s10_ble_ranging": {}}')
    (folder / "seed000_ble_cdf.png").write_bytes(b"\x89PNG old figure")
    (folder / "s40_detection_curve.png").write_bytes(b"\x89PNG old figure of seed 1")
    return _snapshot(folder)


def _leftovers(parent: Path, name: str) -> list[str]:
    """Hidden staging / set-aside folders of ``name`` left in ``parent``."""
    return sorted(p.name for p in parent.iterdir() if p.name.startswith(f".{name}."))


@pytest.fixture
def nodata(tmp_path: Path) -> Path:
    """A data folder holding no data set: every section uses the shipped excerpts."""
    d = tmp_path / "nodata"
    d.mkdir()
    return d


def test_empty_out_is_refused(tmp_path, monkeypatch, capsys, nodata):
    """``-o ''`` is ``Path("")``, the working folder: the report landed there."""
    work = tmp_path / "work"
    work.mkdir()
    monkeypatch.chdir(work)
    assert main([*QUICK, "--data", str(nodata), "-o", ""]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: -o: empty path"), err
    assert "Traceback" not in err
    assert list(work.iterdir()) == []


def test_stdout_is_refused(tmp_path, monkeypatch, capsys, nodata):
    """``-o -`` wrote a report folder named ``-``: a report is a folder."""
    monkeypatch.chdir(tmp_path)
    assert main([*QUICK, "--data", str(nodata), "-o", "-"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: -o -: reproduce writes a report folder"), err
    assert not (tmp_path / "-").exists()


def test_a_folder_that_is_not_a_report_is_refused(tmp_path, capsys, nodata):
    """Replacing it whole would delete the user's files: refused before any work."""
    out = tmp_path / "mine"
    out.mkdir()
    (out / "notes.txt").write_text("keep me")
    assert main([*QUICK, "--data", str(nodata), "-o", str(out)]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"error: {out}: folder exists and is not a robustloc report"), err
    assert _snapshot(out) == {"notes.txt": hashlib.sha256(b"keep me").hexdigest()}
    assert _leftovers(tmp_path, "mine") == []


def test_a_failing_section_leaves_nothing_and_keeps_the_previous_report(tmp_path, capsys):
    """A data folder whose ``wifi-rtt-rss/`` lacks its files fails s40 after its first
    figures: no folder is left, and a previous report stays as it was."""
    bad = tmp_path / "bad"
    (bad / "wifi-rtt-rss").mkdir(parents=True)
    out = tmp_path / "rep"
    assert main([*QUICK, "--data", str(bad), "-o", str(out)]) == 2
    assert "data set 'wifi-rtt-rss' not found" in capsys.readouterr().err
    assert not out.exists()
    assert _leftovers(tmp_path, "rep") == []

    before = _previous_report(out)
    assert main([*QUICK, "--seed", "7", "--data", str(bad), "-o", str(out)]) == 2
    assert _snapshot(out) == before
    assert _leftovers(tmp_path, "rep") == []


def test_a_complete_run_replaces_the_previous_report_whole(tmp_path, nodata):
    """No file of the earlier run (another section's figure) is left beside the new
    report."""
    out = tmp_path / "rep"
    _previous_report(out)
    assert main([*QUICK, "--data", str(nodata), "-o", str(out)]) == 0
    names = {p.name for p in out.iterdir()}
    assert {"report.md", "report.html", "summary.json", "s40_detection_curve.png"} <= names
    assert "seed000_ble_cdf.png" not in names
    assert "s40_integrity" in (out / "summary.json").read_text()
    assert _leftovers(tmp_path, "rep") == []


def _interrupt(tmp_path: Path, out: Path, nodata: Path, seed: int) -> tuple[int, str]:
    """Start ``reproduce`` in a subprocess, send SIGINT once its first figure is written
    (in the staging folder, or -- the old behaviour -- a new file in ``out``), and return
    its exit code and stderr."""
    before = set(os.listdir(out)) if out.is_dir() else set()
    log = tmp_path / "stderr.txt"
    with open(log, "w") as err:
        proc = subprocess.Popen(
            [sys.executable, "-m", "robustloc.cli", *QUICK, "--seed", str(seed),
             "--data", str(nodata), "-o", str(out)],
            cwd=tmp_path, stdout=subprocess.DEVNULL, stderr=err,
            env={**os.environ, "MPLBACKEND": "Agg"},
        )
        try:
            deadline = time.monotonic() + 120
            while True:
                staged = [f for d in tmp_path.glob(f".{out.name}.partial-*") if d.is_dir()
                          for f in d.iterdir()]
                fresh = set(os.listdir(out)) - before if out.is_dir() else set()
                if staged or fresh:
                    break
                assert proc.poll() is None, f"ended before a figure: {log.read_text()}"
                assert time.monotonic() < deadline, "no figure within 120 s"
                time.sleep(0.02)
            proc.send_signal(signal.SIGINT)
            rc = proc.wait(timeout=60)
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.wait(timeout=10)
    return rc, log.read_text()


@pytest.mark.skipif(sys.platform == "win32", reason="SIGINT to a subprocess")
def test_an_interrupted_run_leaves_no_folder(tmp_path, nodata):
    out = tmp_path / "rep_int"
    rc, err = _interrupt(tmp_path, out, nodata, seed=1)
    assert rc == 130, err
    assert "error: interrupted" in err
    assert not out.exists(), sorted(os.listdir(out))
    assert _leftovers(tmp_path, "rep_int") == []


@pytest.mark.skipif(sys.platform == "win32", reason="SIGINT to a subprocess")
def test_an_interrupted_rerun_keeps_the_previous_report(tmp_path, nodata):
    """The seed-1 report.md beside a seed-7 figure was the review's mixed folder."""
    out = tmp_path / "rep_st"
    before = _previous_report(out)
    rc, err = _interrupt(tmp_path, out, nodata, seed=7)
    assert rc == 130, err
    assert _snapshot(out) == before
    assert _leftovers(tmp_path, "rep_st") == []


def test_a_data_set_missing_from_data_is_said(tmp_path, capsys, nodata):
    """``--data DIR`` without ``wifi-rtt-rss/``: the shipped excerpt is used, and said."""
    out = tmp_path / "rep"
    assert main([*QUICK, "--data", str(nodata), "-o", str(out)]) == 0
    err = capsys.readouterr().err
    assert f"real data: {nodata}" in err
    assert f"note: wifi-rtt-rss not in {nodata}: using the shipped excerpt" in err
    assert err.count("note: wifi-rtt-rss") == 1  # once, not once per room


def test_full_runs_are_named_only_when_used(tmp_path, capsys, nodata):
    """s20 and s60 (not quick) with a ``--data`` lacking ``uwb-dwm1001/``: the excerpts are
    used (it was a "run folder does not exist" error), the captions say so, and the
    fallback is said on stderr."""
    from robustloc.reproduce import Context, Section, s20_uwb_gps, s60_tracks

    ctx = Context(out_dir=tmp_path, data_dir=nodata, seed=1, quick=False)
    sec = Section("s20")
    s20_uwb_gps._dwm_experiment(ctx, sec)
    sec60 = Section("s60")
    s60_tracks._dwm(ctx, sec60, [], [])
    captions = [p[0] for s in (sec, sec60) for k, p in s.blocks if k == "table"]
    assert captions and all("full runs" not in c for c in captions), captions
    assert any(c.startswith("uwb-dwm1001 (shipped 60 s excerpts)") for c in captions)
    assert any(c.startswith("uwb-dwm1001 (shipped excerpts)") for c in captions)
    err = capsys.readouterr().err
    assert err.count(f"note: uwb-dwm1001 not in {nodata}: using the shipped excerpt") == 1
