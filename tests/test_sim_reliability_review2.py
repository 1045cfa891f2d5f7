"""The second review of ``robustloc simulate`` and ``robustloc reliability``: layouts
without a unique fix (anchors on one line, two anchors), a grid size printed with 300
digits, simulations whose memory or time grew without bound or sign of progress, and
GNSS epochs without a fix or with fewer satellites than --faults, all silent before."""

from __future__ import annotations

import argparse
import io
import os
import re
import subprocess
import sys

import numpy as np
import pandas as pd
import pytest

from robustloc.cli import main


def _anchors(tmp_path, rows: str, header: str = "anchor,x,y") -> str:
    path = tmp_path / "anchors.csv"
    path.write_text(header + "\n" + rows)
    return str(path)


# --- 1. reliability: layouts without a unique fix -------------------------------------


@pytest.mark.parametrize("header, rows, said", [
    ("anchor,x,y", "A1,0,0\nA2,10,0\nA3,20,0\nA4,30,0\n", "(4 anchors, all on one line;"),
    # heights are known offsets in 2-D: the mirror across the line still fits exactly
    ("anchor,x,y,z", "A1,0,0,3\nA2,10,0,2.5\nA3,20,0,3\n", "(3 anchors, all on one line;"),
    ("anchor,x,y", "A1,0,0\nA2,10,0\n", "(2 anchors; a 2-D fix needs 3 heard"),
])
def test_a_layout_of_anchors_on_one_line_or_of_two_anchors_is_refused(
        tmp_path, capsys, header, rows, said):
    """Exit 0 with finite DOP, CRLB and MDB maps before: every fix there fits its mirror
    image across the anchors' line as well, and `locate` gives none (ill_conditioned)."""
    out = tmp_path / "o"
    code = main(["reliability", "--anchors", _anchors(tmp_path, rows, header), "-o", str(out),
                 "--no-maps"])
    err = capsys.readouterr().err
    assert code == 2, err
    assert "error: " in err and "no point of the area has a fix " + said in err, err
    assert "Traceback" not in err and not out.exists()


def test_points_that_hear_only_anchors_on_a_line_have_no_fix_as_in_locate(tmp_path, capsys):
    """A layout with a fix somewhere: the points whose heard anchors (--max-range) lie on
    one line are blank and counted without a fix, as `locate` leaves such an epoch
    ill_conditioned (checked at one of them on exact ranges)."""
    from robustloc.integrity.planner import plan

    xy = np.array([[0.0, 0.0], [10.0, 0.0], [20.0, 0.0], [10.0, 30.0]])
    t = plan(xy, (0, 20, -10, 10), 5.0, 1.0, max_range_m=25.0).table
    below = t["y"] < 0  # hear A, B, C (on y = 0) only
    assert (t.loc[below, "n_heard"] == 3).all()
    assert t.loc[below, ["dop", "crlb_m", "max_mdb", "max_ext_m"]].isna().all().all()
    assert (t.loc[below, "dof"] == 0).all()
    assert np.isfinite(t.loc[t["n_heard"] == 4, "dop"]).all()

    a = _anchors(tmp_path, "".join(f"{k},{x},{y}\n" for k, (x, y) in zip("ABCD", xy)))
    p = np.array([10.0, -5.0])
    m = tmp_path / "m.csv"
    m.write_text("time,tag,anchor,range\n" + "".join(
        f"0,t,{k},{np.hypot(*(p - xy[i])):.9f}\n" for i, k in enumerate("ABC")))
    assert main(["locate", str(m), "--anchors", a, "--method", "nls", "-o",
                 str(tmp_path / "p.csv"), "-q"]) == 0
    assert pd.read_csv(tmp_path / "p.csv")["status"].tolist() == ["ill_conditioned"]
    capsys.readouterr()


def test_suggest_on_anchors_on_one_line_warns_and_ranks_anchors_off_the_line(tmp_path,
                                                                           capsys):
    """--suggest still answers where one more anchor goes (off the line): a warning says
    the maps are empty, the baseline is inf, a candidate on the line scores inf."""
    cand = tmp_path / "c.csv"
    cand.write_text("x,y\n40,0\n15,5\n15,-4\n")
    out = tmp_path / "o"
    code = main(["reliability", "--anchors",
                 _anchors(tmp_path, "A1,0,0\nA2,10,0\nA3,20,0\nA4,30,0\n"), "--area",
                 "0,30,-5,5", "--step", "1", "--suggest", "--candidates", str(cand), "-o",
                 str(out), "--no-maps", "--json"])
    got = capsys.readouterr()
    assert code == 0, got.err
    assert re.search(r"^warning: .*no point of the area has a fix \(4 anchors, all on one "
                     r"line.*the maps are empty", got.err, re.M), got.err
    s = pd.read_csv(out / "suggestions.csv")
    assert np.isinf(s["baseline"]).all()
    assert s.iloc[-1][["x", "y"]].tolist() == [40.0, 0.0] and np.isinf(s["score"].iloc[-1])
    assert np.isfinite(s["score"].iloc[:2]).all() and (s["y"].iloc[:2] != 0).all()
    assert pd.read_csv(out / "reliability.csv")["dop"].isna().all()


# --- 2. reliability: numbers in messages ----------------------------------------------


@pytest.mark.parametrize("step", ["1e-300", "5e-324"])
def test_an_absurd_step_is_refused_with_a_short_message(tmp_path, capsys, step):
    """--step 1e-300 printed the grid's size as a 302-digit integer; 5e-324 made it
    infinite, an OverflowError traceback."""
    code = main(["reliability", "--anchors",
                 _anchors(tmp_path, "A1,0,0\nA2,10,0\nA3,10,8\nA4,0,8\n"), "--step", step,
                 "-o", str(tmp_path / "o"), "--no-maps"])
    err = capsys.readouterr().err
    assert code == 2
    line = err.strip().splitlines()[-1]
    assert line.startswith("error: --step: a grid of ") and "increase --step" in line
    assert len(line) < 160 and not re.search(r"\d{12}", line), line


def test_the_planner_grid_message_formats_its_numbers():
    from robustloc.integrity.planner import grid_axes

    with pytest.raises(ValueError, match=r"grid of 1\.2e\+301 x 1e\+301 points") as e:
        grid_axes((0, 12, 0, 10), 1e-300)
    assert len(str(e.value)) < 120


# --- 3. simulate: bounded memory, streamed output, progress ----------------------------


@pytest.mark.parametrize("option, other", [("--samples-per-point", "--walk-epochs"),
                                           ("--walk-epochs", "--samples-per-point")])
def test_wifi_room_beyond_the_memory_budget_is_refused_naming_the_option_and_its_limit(
        tmp_path, capsys, monkeypatch, option, other):
    """The limit is rows x bytes per row against the budget (lowered here to 2 MB so the
    check runs on small numbers): the limit it names runs, one more is refused."""
    from robustloc.sim import _output, wifi_room

    monkeypatch.setattr(_output, "MEMORY_BUDGET_BYTES", 2_000_000)
    base = ["simulate", "wifi-room", "--seed", "2", other, "3"]
    assert main([*base, option, "100000", "-o", str(tmp_path / "big")]) == 2
    err = capsys.readouterr().err
    m = re.search(rf"^error: {option}: 100000 gives \d+ rows .*, about [\d.]+ [GM]iB of "
                  r"memory, over the 1.907 MiB a simulation may take: at most (\d+)$",
                  err, re.M)
    assert m, err
    limit = int(m.group(1))
    per = 80 if option == "--samples-per-point" else 4
    rows = 2_000_000 // wifi_room.BYTES_PER_ROW
    assert limit == (rows - 3 * (4 if per == 80 else 80) - 1600) // per > 0
    assert main([*base, option, str(limit + 1), "-o", str(tmp_path / "over")]) == 2
    assert f"at most {limit}" in capsys.readouterr().err
    assert not (tmp_path / "big").exists() and not (tmp_path / "over").exists()
    assert main([*base, option, str(limit), "-o", str(tmp_path / "ok")]) == 0
    meas = pd.read_csv(tmp_path / "ok" / "measurements.csv")
    assert len(meas) == (limit if per == 80 else 3) * 80 + (3 if per == 80 else limit) * 4


def test_wifi_room_a_million_samples_is_refused_before_any_allocation(tmp_path):
    """--samples-per-point 1000000 (within its documented range) ended in a MemoryError
    traceback; run under a 2 GB address-space limit, so the test never takes more."""
    import resource

    def limit() -> None:
        resource.setrlimit(resource.RLIMIT_AS, (2 * 1024**3, 2 * 1024**3))

    proc = subprocess.run(
        [sys.executable, "-m", "robustloc.cli", "simulate", "wifi-room",
         "--samples-per-point", "1000000", "-o", str(tmp_path / "w")],
        capture_output=True, text=True, preexec_fn=limit, timeout=120,
        env={**os.environ, "OPENBLAS_NUM_THREADS": "1"})
    assert proc.returncode == 2, proc.stderr[-500:]
    assert proc.stderr.startswith("error: --samples-per-point: 1000000 gives 80002800 rows")
    assert "at most 83851" in proc.stderr and "Traceback" not in proc.stderr


def _gnss_args(extra: list[str]) -> argparse.Namespace:
    from robustloc.sim import gnss

    p = argparse.ArgumentParser()
    gnss.add_arguments(p)
    return p.parse_args(extra)


def test_gnss_is_streamed_in_chunks_and_writes_the_files_of_one_piece(tmp_path, monkeypatch):
    """Every epoch's frame was held until the end (10**6 epochs: gigabytes, twenty
    minutes); now CHUNK_EPOCHS at a time, the files the same as the whole run's frames."""
    from robustloc.sim import gnss

    monkeypatch.setattr(gnss, "CHUNK_EPOCHS", 7)
    seen = []
    real = pd.DataFrame.to_csv

    def spy(self, *a, **k):  # noqa: ANN001, ANN002, ANN003, ANN202
        if "time" in self.columns:
            seen.append(self["time"].nunique())
        return real(self, *a, **k)

    monkeypatch.setattr(pd.DataFrame, "to_csv", spy)
    args = _gnss_args(["--epochs", "30", "--faults", "2", "--interval-s", "60"])
    paths = gnss.simulate(tmp_path, 5, args)
    monkeypatch.setattr(pd.DataFrame, "to_csv", real)
    assert seen and max(seen) <= 7
    whole = gnss.generate(5, epochs=30, interval_s=60.0, faults=2)
    for name, frame in (("pseudoranges", whole.pseudoranges),
                        ("truth", gnss.truth_csv_frame(whole.truth))):
        buf = io.StringIO()
        frame.to_csv(buf, index=False, float_format="%.4f")
        assert paths[name].read_text() == buf.getvalue()
    assert whole.truth["time"].tolist() == [60.0 * k for k in range(30)]


def _stderr_on_a_terminal(args: list[str]) -> str:
    """What the command line writes on stderr when stderr is a pseudo-terminal (the bars
    show only on a terminal)."""
    import fcntl
    import pty
    import struct
    import termios

    master, slave = pty.openpty()
    fcntl.ioctl(slave, termios.TIOCSWINSZ, struct.pack("HHHH", 24, 80, 0, 0))
    try:
        proc = subprocess.Popen([sys.executable, "-m", "robustloc.cli", *args],
                                stdout=subprocess.DEVNULL, stderr=slave,
                                stdin=subprocess.DEVNULL)
        os.close(slave)
        chunks = []
        while True:
            try:
                data = os.read(master, 65536)
            except OSError:  # EIO: the other end closed with the process
                break
            if not data:
                break
            chunks.append(data)
        assert proc.wait(timeout=120) == 0
    finally:
        os.close(master)
    return b"".join(chunks).decode(errors="replace")


@pytest.mark.parametrize("argv, unit", [
    (["simulate", "gnss", "--epochs", "4000"], "epochs"),
    (["simulate", "wifi-room", "--samples-per-point", "5"], "rows"),
    (["reliability", "--no-maps", "--suggest", "--step", "0.5"], "points"),
])
def test_long_work_shows_a_progress_bar_on_a_terminal_and_q_hides_it(tmp_path, argv, unit):
    """`simulate gnss --epochs 1000000` ran for twenty minutes without a sign; `reliability
    --suggest` runs one planner grid per candidate (31 s silent on a 40 m corridor at
    --step 0.02).  The bars count epochs, rows and grid points."""
    if argv[0] == "reliability":
        argv = [*argv, "--anchors", _anchors(tmp_path, "A1,0,0\nA2,10,0\nA3,10,8\nA4,0,8\n")]
    loud = _stderr_on_a_terminal([*argv, "-o", str(tmp_path / "a")])
    assert unit in loud and "100%" in loud, loud
    quiet = _stderr_on_a_terminal([*argv, "-o", str(tmp_path / "b"), "-q"])
    assert "%|" not in quiet and f"{unit}/s" not in quiet, quiet
    assert not quiet.strip() or quiet.startswith("wrote "), quiet  # (reliability's note)


# --- 4. simulate gnss: epochs that cannot be used ----------------------------------------


def _per_epoch(folder) -> pd.DataFrame:
    """Satellites and systems seen per epoch of a written run (epochs without any
    satellite, absent from pseudoranges.csv, as 0)."""
    pr = pd.read_csv(folder / "pseudoranges.csv")
    times = pd.read_csv(folder / "truth.csv")["time"]
    g = pr.groupby("time")
    return pd.DataFrame({"n": g.size(), "k": g["system"].nunique()}).reindex(
        times, fill_value=0)


def test_gnss_with_no_epoch_that_has_a_fix_is_refused(tmp_path, capsys):
    """--mask-deg 89 wrote a pseudoranges file without a row, exit 0."""
    out = tmp_path / "g"
    code = main(["simulate", "gnss", "--mask-deg", "89", "-o", str(out)])
    err = capsys.readouterr().err
    assert code == 2 and err.startswith("error: --mask-deg: no epoch sees enough "
                                        "satellites above 89 deg for a fix"), err
    assert not out.exists()


def test_gnss_warns_of_the_epochs_without_a_fix(tmp_path, capsys):
    out = tmp_path / "g"
    assert main(["simulate", "gnss", "--systems", "G", "--mask-deg", "40", "-o",
                 str(out)]) == 0
    err = capsys.readouterr().err
    e = _per_epoch(out)
    short = int((e["n"] < 3 + e["k"]).sum())
    assert 0 < short < len(e)
    assert f"warning: --mask-deg 40: {short} of {len(e)} epochs see too few satellites " \
           "for a fix" in err, err


def test_gnss_warns_when_faults_exceed_the_visible_satellites(tmp_path, capsys):
    out = tmp_path / "g"
    assert main(["simulate", "gnss", "--mask-deg", "35", "--faults", "12", "--epochs",
                 "20", "-o", str(out)]) == 0
    err = capsys.readouterr().err
    e = _per_epoch(out)
    short = int((e["n"] < 12).sum())
    assert short > 0
    assert f"warning: --faults 12: {short} of 20 epochs see fewer satellites than that" \
           in err, err
    pr = pd.read_csv(out / "pseudoranges.csv")
    assert (pr["fault_m"] != 0).all()  # (every satellite of those epochs faulty)
