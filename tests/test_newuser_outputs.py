"""What a new user reads after ``locate``, ``track`` and ``evaluate`` agrees with the files
(the new-user walkthrough):

1. the printed ``hpl`` median and 95 % bound are true of the CSV (they came from a 1/20
   decade histogram: "95 % at or below 18.8 m" held for 94.4 % of the rows), on every
   engine;
2. numba compiling is announced when it starts, whichever pass or option needs a kernel
   first, and the timing line keeps it apart from the solving rate ("(0.04 s, ...)" after
   35 s of silent compiling, "0 epochs/s");
3. ``evaluate``'s text table uses the column names of its CSV and JSON, leaves out the
   improvement columns without a baseline, and marks the ``mean`` row's counts as per-tag
   means;
4. ``track``'s summary names the method as its CSV does, and ``--engine dask`` prints the
   local engine's lines (it printed a Python dict).
"""

from __future__ import annotations

import json
import math
import re
import time
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from robustloc import status as st
from robustloc.cli import main

HPL_LINE = re.compile(r"^\s*(\S+)\s+hpl of the (\d+) usable (?:fixes|rows): median (about )?"
                      r"([0-9.e+-]+) m, 95 % at or below ([0-9.e+-]+) m", re.M)


@pytest.fixture(scope="module")
def corridor(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The walkthrough's log: ``simulate ble-corridor --seed 1``, calibrated."""
    d = tmp_path_factory.mktemp("newuser")
    assert main(["simulate", "ble-corridor", "--seed", "1", "--out", str(d)]) == 0
    assert main(["calibrate", str(d / "survey.csv"), "--anchors", str(d / "anchors.csv"),
                 "-o", str(d / "cal.csv")]) == 0
    return d


def _hpl_claims(text: str) -> dict[str, tuple[int, bool, float, float]]:
    """method -> (n, approximate, median, 95 % bound) of the printed hpl lines."""
    return {m: (int(n), bool(about), float(med), float(p95))
            for m, n, about, med, p95 in HPL_LINE.findall(text)}


def _check_claims(text: str, rows: pd.DataFrame) -> None:
    """Each printed hpl line is true of ``rows`` (a positions or track file): its bound
    holds for at least 95 % of the method's usable rows, and its median is the rows'
    within the 3 significant digits printed (plus 0.12 % when marked "about")."""
    claims = _hpl_claims(text)
    assert claims and set(claims) == set(rows["method"].astype(str)), (text, claims)
    for m, (n, about, med, p95) in claims.items():
        g = rows[rows["method"].astype(str) == m]
        h = g.loc[g["status"].isin(st.USABLE), "hpl"].to_numpy(float)
        assert n == h.size
        assert np.mean(h <= p95) >= 0.95, (m, p95, np.mean(h <= p95))
        exact = float(np.median(h))
        tol = 0.5 * 10.0 ** (math.floor(math.log10(exact)) - 2) + (0.0012 * exact if about
                                                                   else 0.0)
        assert abs(med - exact) <= tol * (1 + 1e-9), (m, med, exact)


def test_locate_prints_hpl_numbers_true_of_its_csv(corridor: Path, tmp_path: Path,
                                                   capsys: pytest.CaptureFixture) -> None:
    """The walkthrough's run: "95 % at or below 18.8 m" held for 94.4 % of the rows and
    "median 6.68 m" was the CSV's 6.763; also with two methods and chunks of 53 rows."""
    out = tmp_path / "pos.csv"
    args = ["locate", str(corridor / "measurements.csv"), "--anchors",
            str(corridor / "cal.csv"), "-o", str(out)]
    assert main(args) == 0
    text = capsys.readouterr().out
    _check_claims(text, pd.read_csv(out))
    assert "about" not in text  # 180 fixes: exact
    assert main(args + ["--method", "auto,nls,igg", "--chunk-rows", "53"]) == 0
    _check_claims(capsys.readouterr().out, pd.read_csv(out))


def test_locate_json_hpl_quantiles_match_the_csv(corridor: Path, tmp_path: Path,
                                                 capsys: pytest.CaptureFixture) -> None:
    out = tmp_path / "pos.csv"
    assert main(["locate", str(corridor / "measurements.csv"), "--anchors",
                 str(corridor / "cal.csv"), "-o", str(out), "--json"]) == 0
    q = json.loads(capsys.readouterr().out)["hpl_quantiles"]["auto"]
    pos = pd.read_csv(out)
    h = np.sort(pos.loc[pos["status"].isin(st.USABLE), "hpl"].to_numpy(float))
    assert q["exact"] and q["n"] == h.size and q["unbounded"] == 0
    assert q["median_m"] == pytest.approx(np.median(h), rel=1e-12)
    assert q["p95_bound_m"] == h[math.ceil(0.95 * h.size) - 1]  # the order statistic


def test_hpl_tally_merges_and_bounds_beyond_the_exact_cap(monkeypatch) -> None:
    """Chunks merge into the whole; beyond the cap the histogram's bound still holds (the
    upper edge of its bin) and its median, marked about, is within 0.12 %."""
    from robustloc.pipelines import locate as pl

    rng = np.random.default_rng(5)
    h = 10 ** rng.uniform(-1, 2, 5001)
    h[:7] = np.inf  # unbounded: above every value
    whole, parts = pl.HplTally(), pl.HplTally()
    whole.add(h, np.ones(h.size, bool))
    for sl in (slice(0, 1000), slice(1000, 4000), slice(4000, None)):
        t = pl.HplTally()
        t.add(h[sl], np.ones(h[sl].size, bool))
        parts.merge(t)
    q = whole.quantiles()
    assert q == parts.quantiles() and q["exact"] and q["unbounded"] == 7
    w = np.sort(h)
    assert q["median_m"] == np.median(w) and q["p95_bound_m"] == w[math.ceil(0.95 * 5001) - 1]
    monkeypatch.setattr(pl, "HPL_EXACT_CAP", 1000)
    big = pl.HplTally()
    big.add(h, np.ones(h.size, bool))
    a = big.quantiles()
    assert not a["exact"] and a["n"] == 5001
    assert np.mean(h <= a["p95_bound_m"]) >= 0.95
    assert a["p95_bound_m"] <= w[math.ceil(0.95 * 5001) - 1] * 10 ** (1 / 1000) * (1 + 1e-9)
    assert abs(np.log10(a["median_m"] / np.median(w))) <= 0.5 / 1000 + 1e-12
    line = pl.hpl_lines({"hpl_quantiles": {"m": a}})[0]
    assert "median about" in line and "(7 unbounded)" in line
    # the printed bound is rounded up: it still holds as printed
    assert pl.bound_text(19.345) == "19.4" and pl.bound_text(19.3) == "19.3"
    assert float(pl.bound_text(a["p95_bound_m"])) >= a["p95_bound_m"]


@pytest.mark.parametrize("extra", [["--smooth"], ["--fixed-lag", "5"], []])
def test_track_summary_names_the_csvs_method_and_true_hpl(
        corridor: Path, tmp_path: Path, capsys: pytest.CaptureFixture, extra: list[str]
) -> None:
    """The summary said track-cv-ekf (and gave the filtered rows' hpl) where the CSV and
    evaluate say track-cv-ekf-rts / -lag5."""
    out = tmp_path / "trk.csv"
    args = ["track", str(corridor / "measurements.csv"), "--anchors",
            str(corridor / "cal.csv"), "-o", str(out), *extra]
    assert main(args) == 0
    text = capsys.readouterr().out
    rows = pd.read_csv(out)
    (method,) = set(rows["method"])
    _check_claims(text, rows)
    assert main(args + ["--json"]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["method"] == method
    assert set(summary["hpl_histogram"]) == set(summary["hpl_quantiles"]) == {method}
    if extra:  # the name evaluate reads: the same
        assert method.endswith("-rts" if extra == ["--smooth"] else "-lag5")


def _fake_compile(seconds: float, on_start: list | None = None, capsys=None) -> None:
    """What numba fires while it compiles a robustloc kernel the cache lacks (the events
    the notice listens to), lasting ``seconds``; ``on_start`` gets the stderr written by
    the time compiling started."""
    from numba.core import event

    def kernel() -> None:  # pragma: no cover - never called
        pass

    kernel.__module__ = "robustloc.estimators._compiled"

    class Dispatcher:
        py_func = kernel

    with event.trigger_event("numba:compile", data={"dispatcher": Dispatcher(),
                                                   "args": (), "return_type": None}):
        if on_start is not None and capsys is not None:
            on_start.append(capsys.readouterr())
        time.sleep(seconds)


def test_locate_jit_notice_before_the_log_scale_pass_compiles(
        corridor: Path, tmp_path: Path, capsys: pytest.CaptureFixture, monkeypatch) -> None:
    """The first pass (the log's noise scale) compiled every kernel before the notice was
    considered (35 s unannounced), and the timing line said 0.04 s."""
    from robustloc.pipelines import locate as pl

    first_pass = pl.log_scales_from_sample
    seen: list = []

    def compiling_first_pass(*a, **k):
        if not seen:
            # (2 s: the solve of 180 fixes must stay below it on a loaded machine; at 0.6 s
            # the assertion below failed once in a loaded run, 2026-12-06)
            _fake_compile(2.0, seen, capsys)
        return first_pass(*a, **k)

    monkeypatch.setattr(pl, "log_scales_from_sample", compiling_first_pass)
    out = tmp_path / "pos.csv"
    args = ["locate", str(corridor / "measurements.csv"), "--anchors",
            str(corridor / "cal.csv"), "-o", str(out)]
    assert main(args) == 0
    text = capsys.readouterr().out
    assert seen and "numba is compiling" in seen[0].err  # before compiling started
    m = re.search(r"\((\d+\.\d+) s, of which (\d+\.\d) s compiling kernels; (\d+) fixes/s "
                  r"solving\)", text)
    assert m, text
    assert float(m.group(1)) >= float(m.group(2)) >= 2.0
    seen.clear()
    assert main(args + ["--json"]) == 0
    s = json.loads(capsys.readouterr().out)
    assert s["seconds"] >= s["compile_seconds"] >= 2.0 > s["solve_seconds"]
    assert s["fixes_per_second"] == pytest.approx(180 / s["solve_seconds"], rel=0.05)


def test_track_jit_notice_for_a_kernel_the_cache_lacks_and_rate_without_it(
        corridor: Path, tmp_path: Path, capsys: pytest.CaptureFixture, monkeypatch) -> None:
    """``track --model ca`` (kernels not cached while cv's were) compiled 25 s without a
    notice; a compiling run printed "(238.18 s, 0 epochs/s)"."""
    from robustloc.tracking import Tracker

    step = Tracker.step
    seen: list = []

    def compiling_step(self, *a, **k):
        if not seen:
            _fake_compile(1.0, seen, capsys)
        return step(self, *a, **k)

    monkeypatch.setattr(Tracker, "step", compiling_step)
    args = ["track", str(corridor / "measurements.csv"), "--anchors",
            str(corridor / "cal.csv"), "-o", str(tmp_path / "t.csv"), "--model", "ca"]
    assert main(args + ["--json"]) == 0
    s = json.loads(capsys.readouterr().out)
    assert seen and "numba is compiling" in seen[0].err
    assert s["seconds"] >= s["compile_seconds"] >= 1.0
    # the rate of the tracking itself (it was epochs over the whole wall time)
    assert s["epochs_per_second"] == pytest.approx(
        s["epochs"] / (s["seconds"] - s["compile_seconds"]), rel=0.05)
    seen.clear()
    assert main(args) == 0
    text = capsys.readouterr().out
    m = re.search(r"of which (\d+\.\d) s compiling kernels; ([0-9.]+) epochs/s\)", text)
    assert m and float(m.group(1)) >= 1.0 and float(m.group(2)) > 0, text


def test_rate_text_never_shows_zero_for_work_done() -> None:
    from robustloc.commands._summary import rate_text

    assert rate_text(0.76) == "0.76" and rate_text(15746.2) == "15746"
    assert rate_text(0.0) == "0" and rate_text(9.96) == "10"


def _eval_text(tmp_path: Path, methods: dict[str, float], capsys, *extra: str) -> str:
    """``evaluate`` of two tags (3 and 4 epochs) and the given methods (error in x)."""
    t = pd.DataFrame({"time": [0, 1, 2, 0, 1, 2, 3], "tag": list("aaabbbb"),
                      "x": 0.0, "y": 0.0})
    rows = []
    for m, e in methods.items():
        p = t.assign(x=e, method=m, status="ok")
        if m != "ls":
            p.loc[3, "status"] = "insufficient_anchors"  # one failed epoch of tag b
        rows.append(p)
    t.to_csv(tmp_path / "t.csv", index=False)
    pd.concat(rows).to_csv(tmp_path / "p.csv", index=False)
    assert main(["evaluate", str(tmp_path / "p.csv"), "--truth", str(tmp_path / "t.csv"),
                 *extra]) == 0
    return capsys.readouterr().out


def test_evaluate_text_uses_the_csv_column_names(tmp_path: Path,
                                                 capsys: pytest.CaptureFixture) -> None:
    """The text table said mean_vs_ls_% / rms_vs_ls_% (the CSV: mean_impr_pct,
    rms_impr_pct), and with no ls row at all."""
    text = _eval_text(tmp_path, {"nls": 1.0, "igg": 0.5}, capsys,
                      "-o", str(tmp_path / "e.csv"))
    header = text.splitlines()[1].split()
    csv = pd.read_csv(tmp_path / "e.csv")
    assert set(header) <= set(csv.columns), set(header) - set(csv.columns)
    assert "_vs_" not in text and "impr" not in text  # no ls: nothing to improve on
    assert csv["mean_impr_pct"].isna().all()  # (the contract's columns stay, empty)
    text = _eval_text(tmp_path, {"ls": 2.0, "igg": 0.5}, capsys)
    header = text.splitlines()[1].split()
    assert {"mean_impr_pct", "rms_impr_pct"} <= set(header) and "_vs_" not in text
    assert "over method ls" in text.splitlines()[0]


def test_evaluate_text_marks_the_mean_rows_counts_as_per_tag(
        tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    """The mean row showed n 3.5 and n_failed 0.5 as if they were counts."""
    text = _eval_text(tmp_path, {"igg": 0.5}, capsys)
    lines = text.splitlines()
    cols = lines[1].split()
    (mean,) = [ln.split() for ln in lines[2:] if ln.split()[:1] == ["mean"]]
    cell = dict(zip(cols, mean))
    assert cell["n"] == "3.5/tag" and cell["n_failed"] == "0.5/tag", cell
    (all_,) = [ln.split() for ln in lines[2:] if ln.split()[:1] == ["all"]]
    assert dict(zip(cols, all_))["n"] == "7"  # the pooled row: a count
    assert "of the counts too (/tag)" in lines[0]


def test_track_dask_prints_the_local_lines(corridor: Path, tmp_path: Path, scheduler: str,
                                           capsys: pytest.CaptureFixture) -> None:
    """``track --engine dask`` printed ``status: {'ok': 179, 'fault_detected': 1}``; its
    lines are now the local command's (its hpl numbers true of its parts too)."""
    ds = tmp_path / "by_tag"
    assert main(["partition", str(corridor / "measurements.csv"), "-o", str(ds), "--by",
                 "tag", "--buckets", "2"]) == 0
    capsys.readouterr()
    common = ["--anchors", str(corridor / "cal.csv"), "--smooth"]
    assert main(["track", str(corridor / "measurements.csv"), "-o",
                 str(tmp_path / "t.csv"), *common]) == 0
    local = capsys.readouterr().out.splitlines()
    out = tmp_path / "d"
    assert main(["track", str(ds), "-o", str(out), *common, "--engine", "dask",
                 "--scheduler", scheduler]) == 0
    dask = capsys.readouterr().out.splitlines()
    assert "{" not in "\n".join(dask), dask
    assert dask[1:] == local[1:]
    assert dask[0].startswith("180 epochs, 3 tags in 2 partitions")
    rows = pd.concat([pd.read_parquet(p) for p in sorted(out.glob("*.parquet"))])
    _check_claims("\n".join(dask), rows)


def test_locate_dask_hpl_numbers_true_of_its_parts(corridor: Path, tmp_path: Path,
                                                   scheduler: str,
                                                   capsys: pytest.CaptureFixture) -> None:
    ds = tmp_path / "by_tag"
    assert main(["partition", str(corridor / "measurements.csv"), "-o", str(ds), "--by",
                 "tag", "--buckets", "2"]) == 0
    capsys.readouterr()
    out = tmp_path / "d"
    assert main(["locate", str(ds), "--anchors", str(corridor / "cal.csv"), "-o", str(out),
                 "--engine", "dask", "--scheduler", scheduler]) == 0
    text = capsys.readouterr().out
    rows = pd.concat([pd.read_parquet(p) for p in sorted(out.glob("*.parquet"))])
    _check_claims(text, rows)


def test_quiet_runs_and_library_calls_print_no_compile_notice(monkeypatch, capsys):
    """``-q`` (and the Python API) print no notice when numba compiles (a fresh clone's
    first ``locate --quiet`` in the suite printed it, and a test counting stderr lines
    failed): the seconds are still counted."""
    from robustloc import _jitnotice

    listener = _jitnotice._listener()
    if listener is None:
        pytest.skip("numba's event API is not available")

    class Event:
        data = {"dispatcher": None}

    with _jitnotice.compile_watch("positioning", announce=False) as jit:
        listener.on_start(Event())
        listener.on_end(Event())
    assert capsys.readouterr().err == "" and jit.seconds >= 0.0
    with _jitnotice.compile_watch("positioning") as jit:
        listener.on_start(Event())
        listener.on_end(Event())
    assert "numba is compiling the positioning kernels" in capsys.readouterr().err
