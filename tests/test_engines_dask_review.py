"""The Dask-engine review's defects (numbering of /work/review/daskrev/REPORT.md), each on
a real LocalCluster: relative paths with an external scheduler whose workers run in
another directory (D1), a malformed ``--scheduler`` (D3), huge ``track`` options (D4), a
failed run's staging folder re-created by a still-running task (D5), a scheduler without
workers (D6), ``track``'s far-anchor warning (D7), ``-o -`` (D8), the ``--json`` summary's
keys (D9) and messages in Python names or quoting a file's range (D10).

Every cluster a test starts is closed by the test; the one in another working directory
is a subprocess of this test, stopped (by its pid) at the end.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import threading
import time
from pathlib import Path

import pandas as pd
import pytest

distributed = pytest.importorskip("distributed")
pytest.importorskip("duckdb")

from robustloc.cli import main  # noqa: E402
from robustloc.errors import InputError, OutputError  # noqa: E402
from robustloc.sim.wifi_room import simulate  # noqa: E402


@pytest.fixture(scope="module")
def sim(tmp_path_factory) -> dict[str, Path]:
    out = tmp_path_factory.mktemp("wifi")
    return simulate(out, 4, argparse.Namespace(samples_per_point=5, walk_epochs=30))


@pytest.fixture(scope="module")
def by_tag(sim, tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("ds") / "by_tag"
    assert main(["partition", str(sim["measurements"]), "-o", str(out), "--by", "tag"]) == 0
    return out


def _dataset(out: Path) -> pd.DataFrame:
    files = sorted(out.glob("part-*.parquet"))
    assert files, f"no part in {out}"
    return pd.concat([pd.read_parquet(f) for f in files], ignore_index=True)


def _track_local(sim: dict[str, Path], out: Path, *opts: str) -> pd.DataFrame:
    assert main(["track", str(sim["measurements"]), "--anchors", str(sim["anchors"]),
                 "-o", str(out), "--quiet", *opts]) == 0
    return pd.read_parquet(out)


def _sorted(df: pd.DataFrame) -> pd.DataFrame:
    df = df.astype({"tag": str})
    return df.sort_values(["tag", "time"]).reset_index(drop=True)


# --------------------------------------------------------------------------------------
# D1: relative paths, an external scheduler whose workers run in another directory
# --------------------------------------------------------------------------------------

_CLUSTER_SCRIPT = """
import sys
import distributed
if __name__ == "__main__":
    cluster = distributed.LocalCluster(n_workers=1, threads_per_worker=1, processes=True,
                                       dashboard_address=":0")
    print(cluster.scheduler_address, flush=True)
    sys.stdin.read()  # until the test closes our stdin
    cluster.close()
"""


@pytest.fixture(scope="module")
def elsewhere_scheduler(tmp_path_factory):
    """A LocalCluster (worker processes) started by a subprocess whose working directory
    is not the test's: ``(address, its directory)``.  Stopped at the end: stdin closed,
    then killed by its pid if it outlives 60 s."""
    cwd = tmp_path_factory.mktemp("workers_cwd")
    script = cwd / "cluster.py"
    script.write_text(_CLUSTER_SCRIPT)
    proc = subprocess.Popen([sys.executable, str(script)], cwd=cwd, stdin=subprocess.PIPE,
                            stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
    try:
        line = ""
        got: list[str] = []
        reader = threading.Thread(target=lambda: got.append(proc.stdout.readline()),
                                  daemon=True)
        reader.start()
        reader.join(120)
        line = got[0].strip() if got else ""
        if not line:
            pytest.skip("the subprocess's LocalCluster did not start")
        yield line, cwd
    finally:
        try:
            proc.stdin.close()
            proc.wait(60)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(10)


def test_relative_paths_with_workers_in_another_directory(sim, by_tag, elsewhere_scheduler,
                                                          tmp_path, monkeypatch, capsys):
    """Relative -o, --anchors and dataset: the workers (in another directory, holding a
    different anchors file of the same name) wrote the parts into their own directory and
    read their own anchors; the run said exit 0 and the output held no part."""
    import shutil

    address, wcwd = elsewhere_scheduler
    ref = _track_local(sim, tmp_path / "local.parquet")
    client_dir = tmp_path / "client"
    client_dir.mkdir()
    shutil.copytree(by_tag, client_dir / "ds")
    shutil.copy(sim["anchors"], client_dir / "anch.csv")
    decoy = pd.read_csv(sim["anchors"])
    decoy["x"] += 3.0  # another layout under the same name, in the workers' directory
    decoy.to_csv(wcwd / "anch.csv", index=False)
    monkeypatch.chdir(client_dir)
    try:
        assert main(["track", "ds", "--anchors", "anch.csv", "-o", "out", "--engine",
                     "dask", "--scheduler", address, "--quiet"]) == 0, capsys.readouterr().err
    finally:
        (wcwd / "anch.csv").unlink()
    got = _dataset(client_dir / "out")
    pd.testing.assert_frame_equal(_sorted(got), _sorted(ref), check_exact=True)
    assert not list(wcwd.glob(".out.partial-*")) and not (wcwd / "out").exists()
    meta = json.loads((client_dir / "out" / "_robustloc.json").read_text())
    assert meta["out"] == "out" and meta["rows_out"] == len(ref)


def test_paths_handed_to_workers_are_absolute(tmp_path, monkeypatch):
    from robustloc.engines.dask import DatasetOutput, _settings
    from robustloc.engines.dataset import discover

    monkeypatch.chdir(tmp_path)
    (tmp_path / "ds" / "tag=a").mkdir(parents=True)
    pd.DataFrame({"time": [0.0], "anchor": ["A"], "rssi": [-50.0]}).to_parquet(
        tmp_path / "ds" / "tag=a" / "p.parquet", index=False)
    parts = discover("ds", absolute=True)
    assert parts[0].path == str(tmp_path / "ds" / "tag=a" / "p.parquet")
    assert parts[0].keys == (("tag", "a"),)
    assert discover("ds")[0].path == os.path.join("ds", "tag=a", "p.parquet")  # as before
    ns = argparse.Namespace(measurements="ds", anchors="a.csv", out="o", truth=None,
                            nav=["n1.05n", "sub/n2.05n"], sp3="x.sp3", clk="-",
                            method=["huber"], _run=print)
    s = _settings(ns)
    assert s["anchors"] == str(tmp_path / "a.csv") and s["out"] == str(tmp_path / "o")
    assert s["measurements"] == str(tmp_path / "ds") and s["sp3"] == str(tmp_path / "x.sp3")
    assert s["nav"] == [str(tmp_path / "n1.05n"), str(tmp_path / "sub" / "n2.05n")]
    assert s["clk"] == "-" and s["truth"] is None and s["method"] == ["huber"]
    assert "_run" not in s
    out = DatasetOutput("rel")
    try:
        assert Path(out.part(0)).is_absolute() and out.stage.parent == tmp_path
    finally:
        out.abort()
    assert not list(tmp_path.glob(".rel.partial-*"))


def test_a_missing_part_fails_the_run(sim, by_tag, scheduler, tmp_path, monkeypatch,
                                      capsys):
    """A part the workers did not write where the client looks: exit 2 and no output
    (the run said exit 0 with an output of no rows)."""
    import robustloc.commands.track as track_cmd

    real = track_cmd.track_partition_file

    def elsewhere(args: argparse.Namespace) -> dict:  # writes its part somewhere else
        args.out = str(Path(args.out).parent.parent / ("lost-" + Path(args.out).name))
        return real(args)

    monkeypatch.setattr(track_cmd, "track_partition_file", elsewhere)
    out = tmp_path / "out"
    assert main(["track", str(by_tag), "--anchors", str(sim["anchors"]), "-o", str(out),
                 "--engine", "dask", "--scheduler", scheduler, "--quiet"]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"error: {out}: part-00000.parquet of this run is missing"), err
    assert "shared filesystem" in err and "Traceback" not in err
    assert not out.exists() and not list(tmp_path.glob(".out.partial-*"))


def test_check_parts_counts_rows(tmp_path):
    from robustloc.engines.dask import DatasetOutput

    out = DatasetOutput(tmp_path / "o")
    try:
        pd.DataFrame({"a": [1, 2]}).to_parquet(out.part(0), index=False)
        out.check_parts(1, [2])
        with pytest.raises(OutputError, match="holds 2 rows where its task wrote 3"):
            out.check_parts(1, [3])
        with pytest.raises(OutputError, match="part-00001.parquet of this run is missing"):
            out.commit({}, 2)
    finally:
        out.abort()
    assert not (tmp_path / "o").exists() and not list(tmp_path.iterdir())


# --------------------------------------------------------------------------------------
# D3, D6: the scheduler's address, a scheduler without workers
# --------------------------------------------------------------------------------------


@pytest.mark.parametrize("address", ["127.0.0.1", "foo://h:1", "tcp://h:port"])
def test_a_malformed_scheduler_address_is_a_users_mistake(sim, by_tag, tmp_path, capsys,
                                                          address):
    assert main(["track", str(by_tag), "--anchors", str(sim["anchors"]), "-o",
                 str(tmp_path / "x"), "--engine", "dask", "--scheduler", address,
                 "--quiet"]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"error: --scheduler {address}: not a scheduler address"), err
    assert "Traceback" not in err and not (tmp_path / "x").exists()
    assert not list(tmp_path.glob(".x.partial-*"))


def test_a_scheduler_without_workers_is_refused_after_a_wait(sim, by_tag, tmp_path,
                                                             monkeypatch, capsys):
    """It waited forever, without a word."""
    import robustloc.engines.cluster as cluster_mod

    monkeypatch.setattr(cluster_mod, "WORKER_WAIT_SECONDS", 1.0, raising=False)
    cluster = distributed.LocalCluster(n_workers=0, processes=False, dashboard_address=":0")
    try:
        codes: list[int] = []
        run = threading.Thread(target=lambda: codes.append(main(
            ["track", str(by_tag), "--anchors", str(sim["anchors"]), "-o",
             str(tmp_path / "x"), "--engine", "dask", "--scheduler",
             cluster.scheduler_address, "--quiet"])), daemon=True)
        run.start()
        run.join(60)
        assert codes == [2], "still waiting for a worker after 60 s"
    finally:
        cluster.close()
    err = capsys.readouterr().err.splitlines()
    assert err == [f"note: --scheduler {cluster.scheduler_address} has no workers yet; "
                   "waiting up to 1 s",
                   f"error: --scheduler {cluster.scheduler_address}: no workers after 1 s "
                   f"(start workers: dask worker {cluster.scheduler_address})"], err
    assert not (tmp_path / "x").exists() and not list(tmp_path.glob(".x.partial-*"))


# --------------------------------------------------------------------------------------
# D4: huge (and tiny) values of track's squared options
# --------------------------------------------------------------------------------------


@pytest.mark.parametrize("flag, opts", [
    ("--noise-scale-max", ("--noise-scale-max", "1e200")),
    ("--noise-scale-min", ("--noise-scale-min", "1e-170", "--noise-scale-max", "1e-170")),
    ("--range-offset-sd", ("--range-offset", "--range-offset-sd", "1e200")),
    ("--link-offset-sd", ("--link-offsets", "--link-offset-sd", "1e200")),
])
def test_track_refuses_option_values_whose_square_overflows(sim, tmp_path, capsys, flag,
                                                            opts):
    """OverflowError / ZeroDivisionError tracebacks (exit 1) before."""
    if "--range-offset" in opts:  # ranges: the offset is one of the ranges'
        meas = pd.read_csv(sim["measurements"])
        anchors = pd.read_csv(sim["anchors"])
        xy = anchors.set_index("anchor")[["x", "y"]]
        truth = pd.read_csv(sim["truth"])
        m = meas.merge(truth[["time", "tag", "x", "y"]], on=["time", "tag"])
        a = xy.loc[m["anchor"]].to_numpy()
        m["range"] = ((m[["x", "y"]].to_numpy() - a) ** 2).sum(axis=1) ** 0.5 + 0.1
        src = tmp_path / "ranges.csv"
        m[["time", "tag", "anchor", "range"]].to_csv(src, index=False)
    else:
        src = sim["measurements"]
    assert main(["track", str(src), "--anchors", str(sim["anchors"]), "-o",
                 str(tmp_path / "t.csv"), "--quiet", *opts]) == 2
    err = capsys.readouterr().err
    assert f"argument {flag}: expected a number in [1e-06, 1e+06]" in err, err
    assert "Traceback" not in err and not (tmp_path / "t.csv").exists()


def test_tracker_api_refuses_what_it_cannot_square():
    from robustloc.tracking.tracker import TrackerSettings

    for kw in ({"noise_scale_max": 1e200}, {"range_offset_sd": 1e200},
               {"link_offset_sd": 1e200}, {"noise_scale_min": 1e-170,
                                           "noise_scale_max": 1e-170}):
        with pytest.raises(ValueError, match="must be in"):
            TrackerSettings(**kw)


# --------------------------------------------------------------------------------------
# D5: a failed run's staging folder, re-created by a task still running
# --------------------------------------------------------------------------------------


def test_parents_not_created_by_a_task_writer(tmp_path):
    from robustloc.io.atomic import atomic_output, parents_not_created

    target = tmp_path / "gone" / "part-00000.parquet"
    with parents_not_created():
        with pytest.raises(OutputError, match="the folder is gone"):
            with atomic_output(target) as (tmp, _):
                Path(tmp).write_text("x")
    assert not (tmp_path / "gone").exists()
    with atomic_output(target) as (tmp, _):  # the commands' writers still create it
        Path(tmp).write_text("x")
    assert target.read_text() == "x"


def test_a_task_still_running_after_a_failure_leaves_no_staging_folder(
        sim, by_tag, scheduler, tmp_path, monkeypatch, capsys):
    """One tag group fails at once while another is still running: the run is exit 2,
    and the running task, which writes its part 1.5 s later, re-created the removed
    ``.out.partial-*`` folder with its part (the atomic writer created missing
    parents)."""
    import robustloc.commands.track as track_cmd

    real = track_cmd.track_partition_file
    done = tmp_path / "slow-task-done"

    def slow_or_failing(args: argparse.Namespace) -> dict:
        if Path(args.out).name == "part-00000.parquet":
            raise InputError("bad row", args.measurements, 2)
        time.sleep(1.5)
        try:
            return real(args)
        finally:
            done.write_text("1")

    monkeypatch.setattr(track_cmd, "track_partition_file", slow_or_failing)
    out = tmp_path / "out"
    assert main(["track", str(by_tag), "--anchors", str(sim["anchors"]), "-o", str(out),
                 "--engine", "dask", "--scheduler", scheduler, "--quiet"]) == 2
    assert ": bad row" in capsys.readouterr().err
    deadline = time.monotonic() + 30
    while not done.exists() and time.monotonic() < deadline:
        time.sleep(0.1)
    time.sleep(0.5)
    assert done.exists()
    assert not out.exists()
    assert not list(tmp_path.glob(".out.partial-*"))


# --------------------------------------------------------------------------------------
# D7, D8, D9, D10: warnings, -o -, --json keys, messages
# --------------------------------------------------------------------------------------


def test_track_dask_warns_of_a_far_anchor_as_the_local_command(sim, by_tag, scheduler,
                                                               tmp_path, capsys):
    far = pd.read_csv(sim["anchors"])
    extra = far.iloc[:1].copy()
    extra["anchor"], extra["y"] = "APX", 1e300
    anchors = tmp_path / "anchors_far.csv"
    pd.concat([far, extra]).to_csv(anchors, index=False)
    assert main(["track", str(sim["measurements"]), "--anchors", str(anchors), "-o",
                 str(tmp_path / "t.csv"), "--quiet"]) == 0
    local = [ln for ln in capsys.readouterr().err.splitlines() if ln.startswith("warning")]
    assert local and "APX" in local[0]
    assert main(["track", str(by_tag), "--anchors", str(anchors), "-o", str(tmp_path / "d"),
                 "--engine", "dask", "--scheduler", scheduler, "--quiet"]) == 0
    dask = [ln for ln in capsys.readouterr().err.splitlines() if ln.startswith("warning")]
    assert dask == local


def test_stdout_is_refused_as_a_dask_output(sim, by_tag, scheduler, tmp_path, monkeypatch,
                                            capsys):
    monkeypatch.chdir(tmp_path)
    assert main(["track", str(by_tag), "--anchors", str(sim["anchors"]), "-o", "-",
                 "--engine", "dask", "--scheduler", scheduler, "--quiet"]) == 2
    cap = capsys.readouterr()
    assert cap.err == ("error: -o: --engine dask writes a dataset folder, not standard "
                       "output\n")
    assert cap.out == "" and list(tmp_path.iterdir()) == []


def test_track_json_summary_has_the_local_keys(sim, by_tag, scheduler, tmp_path, capsys):
    assert main(["track", str(sim["measurements"]), "--anchors", str(sim["anchors"]), "-o",
                 str(tmp_path / "t.csv"), "--json"]) == 0
    local = json.loads(capsys.readouterr().out)
    out = tmp_path / "d"
    assert main(["track", str(by_tag), "--anchors", str(sim["anchors"]), "-o", str(out),
                 "--engine", "dask", "--scheduler", scheduler, "--json"]) == 0
    dask = json.loads(capsys.readouterr().out)
    assert set(local) <= set(dask), set(local) - set(dask)
    for k in ("epochs", "tags", "method", "status", "anchors_not_used", "sorted_first",
              "smoother", "invalid_measurement_rows", "duplicates_merged",
              "hpl_histogram"):
        assert dask[k] == local[k], k
    assert dask["measurements"] == str(by_tag) and dask["track"] == str(out)
    # the Dask keys stay as they were
    assert dask["engine"] == "dask" and dask["counts"]["status"] == local["status"]
    assert dask["rows_out"] == local["epochs"] and "files" not in dask
    meta = json.loads((out / "_robustloc.json").read_text())
    assert meta["status"] == local["status"] and meta["counts"]["epochs"] == local["epochs"]


def test_track_messages_name_the_options(sim, by_tag, scheduler, tmp_path, capsys):
    # --tag-height with anchors without z: the tracker's Python name on the dask engine
    # (a tag group of several files, read whole: a dataset partitioned by time)
    by_time = tmp_path / "by_time"
    assert main(["partition", str(sim["measurements"]), "-o", str(by_time), "--by", "time",
                 "--span", "5"]) == 0
    capsys.readouterr()
    for ds in (by_time, by_tag):
        assert main(["track", str(ds), "--anchors", str(sim["anchors"]), "-o",
                     str(tmp_path / "d"), "--engine", "dask", "--scheduler", scheduler,
                     "--tag-height", "1", "--quiet"]) == 2
        err = capsys.readouterr().err.splitlines()
        assert err[-1] == (f"error: {sim['anchors']}:1: --tag-height needs a z column in "
                           "the anchors file")
    assert not (tmp_path / "d").exists()
    for engine in (["--engine", "local"],
                   ["--engine", "dask", "--scheduler", scheduler]):
        src = by_tag if "dask" in engine else sim["measurements"]
        assert main(["track", str(src), "--anchors", str(sim["anchors"]), "-o",
                     str(tmp_path / "n.csv"), "--noise-scale-min", "5",
                     "--noise-scale-max", "1", "--quiet", *engine]) == 2
        err = capsys.readouterr().err
        assert err.startswith("error: --noise-scale-min: 5 is above --noise-scale-max 1"), err
    assert not (tmp_path / "n.csv").exists()


def test_split_epoch_message_quotes_the_tags_own_times(tmp_path):
    from robustloc.engines.dataset import discover, inspect, plan_snapshot

    ds = tmp_path / "ds"
    ds.mkdir()

    def write(name: str, rows: list[tuple[float, str]]) -> None:
        pd.DataFrame({"time": [t for t, _ in rows], "tag": [g for _, g in rows],
                      "anchor": "A", "rssi": -50.0}).sort_values("time").to_parquet(
            ds / name, index=False)

    # a: tag x in [0, 10], tag y in [0, 100]; b: tag x in [5, 6]
    write("a.parquet", [(0.0, "x"), (10.0, "x"), (0.0, "y"), (100.0, "y")])
    write("b.parquet", [(5.0, "x"), (6.0, "x")])
    infos = [inspect(p) for p in discover(ds)]
    with pytest.raises(InputError) as exc:
        plan_snapshot(infos)
    assert exc.value.path == str(ds / "b.parquet")
    assert exc.value.message.startswith(
        "tag 'x' has rows in times [5.0, 6.0] here and in [0.0, 10.0] in "), exc.value
    # the partitions' ranges meet, the tag's own times do not: no epoch can be split
    write("b.parquet", [(20.0, "x"), (30.0, "x")])
    infos = [inspect(p) for p in discover(ds)]
    assert [Path(i.part.path).name for i in plan_snapshot(infos)] == ["a.parquet",
                                                                      "b.parquet"]


def test_filter_json_summary_has_the_local_keys(sim, scheduler, tmp_path, capsys):
    """``filter --engine dask --json`` lacked the single-process summary's ``filter``,
    ``share_downweighted`` and ``raw_minus_filtered_std_db``; they are now there, the
    spread from the partitions' exact moments (equal to the last digit), with invalid
    rows (kept raw, not filtered) left out as in the single process."""
    meas = pd.read_csv(sim["measurements"], dtype={"tag": str, "anchor": str})
    meas.loc[meas.index[::37], "rssi"] = 99.0  # outside -150 .. +30 dBm: invalid
    log = tmp_path / "m.csv"
    meas.to_csv(log, index=False)
    ds = tmp_path / "by_tag"
    assert main(["partition", str(log), "-o", str(ds), "--by", "tag"]) == 0
    capsys.readouterr()
    assert main(["filter", str(log), "--anchors", str(sim["anchors"]), "-o",
                 str(tmp_path / "f.csv"), "--json"]) == 0
    local = json.loads(capsys.readouterr().out)
    assert local["invalid_measurement"] > 0
    assert main(["filter", str(ds), "--anchors", str(sim["anchors"]), "-o",
                 str(tmp_path / "d"), "--engine", "dask", "--scheduler", scheduler,
                 "--json"]) == 0
    dask = json.loads(capsys.readouterr().out)
    assert set(local) - {"out"} <= set(dask), set(local) - set(dask)
    for k in ("filter", "samples", "links", "downweighted", "rejected", "relocked",
              "restarted", "invalid_measurement", "duplicates_merged"):
        assert dask[k] == local[k], k
    # exact sums: the same numbers, every key (the spread was 1.8999485505636962 here
    # against the single process's 1.899948550563696: float64 sums in another order)
    assert {k: dask[k] for k in local if k != "out"} == {
        k: v for k, v in local.items() if k != "out"}
    assert not any(k.startswith("_") for k in dask) and "_moments" not in dask["counts"]


def _worker_logger_view() -> tuple[bool, bool]:
    """On a worker: whether ``distributed.worker`` drops the heartbeat error of a closing
    cluster, and whether it still passes another error."""
    import logging

    lg = logging.getLogger("distributed.worker")

    def rec(msg: str) -> logging.LogRecord:
        return lg.makeRecord(lg.name, logging.ERROR, __file__, 1, msg, (), None)

    dropped = not lg.filter(rec("Failed to communicate with scheduler during heartbeat."))
    kept = bool(lg.filter(rec("Compute Failed")))
    return dropped, kept


def test_the_commands_workers_drop_only_the_heartbeat_error_of_their_closing_cluster():
    """On an interrupt the command closes its LocalCluster, and a worker whose heartbeat
    finds the scheduler gone logged "Failed to communicate with scheduler during
    heartbeat" with a traceback on the user's terminal (seen once under load in
    ``test_interrupt_while_the_local_cluster_starts_ends_cleanly``).  The command's own
    workers (real processes here) drop that record and keep every other error."""
    from robustloc.engines.cluster import dask_client

    with dask_client(None, workers=1) as client:
        views = client.run(_worker_logger_view)
    assert views and all(v == (True, True) for v in views.values()), views
