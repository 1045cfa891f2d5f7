"""The Dask engine review of 2026-12-07: partitions behind symbolic links (followed, a
link loop walked once, a link to nothing refused), Ctrl-C to the whole process group (one
line, exit 130, no process left), spp's summary naming the final parts, a hive tag at its
column's place, and ``track --link-offsets auto``'s sample read from the first epochs."""

from __future__ import annotations

import os

import pandas as pd
import pytest

pytest.importorskip("distributed")

from robustloc.cli import main  # noqa: E402
from robustloc.engines.dataset import discover  # noqa: E402
from robustloc.errors import InputError  # noqa: E402

ANCHORS = "anchor,x,y\na,0,0\nb,10,0\nc,10,10\nd,0,10\n"


def _epochs(path, tag: str, t0: float = 0.0, n: int = 3) -> None:
    pd.DataFrame({"time": [t0 + i for i in range(n) for _ in range(4)],
                  "tag": tag, "anchor": list("abcd") * n,
                  "range": [5.0, 8.1, 8.1, 5.0] * n}).to_parquet(path, index=False)


# --------------------------------------------------------------------------------------
# symbolic links
# --------------------------------------------------------------------------------------


def test_partitions_behind_linked_folders_are_found_and_a_loop_ends(tmp_path):
    real = tmp_path / "real"
    (real / "tag=T1").mkdir(parents=True)
    _epochs(real / "tag=T1" / "part-0.parquet", "T1")
    ds = tmp_path / "ds"
    (ds / "tag=T2").mkdir(parents=True)
    _epochs(ds / "tag=T2" / "part-0.parquet", "T2")
    os.symlink(real / "tag=T1", ds / "tag=T1")  # a linked folder
    os.symlink(real / "tag=T1" / "part-0.parquet", ds / "tag=T2" / "part-1.parquet")
    os.symlink(ds, ds / "tag=T2" / "loop")  # a link back up: walked once
    parts = discover(ds)
    assert [os.path.relpath(p.path, ds) for p in parts] == [
        os.path.join("tag=T1", "part-0.parquet"), os.path.join("tag=T2", "part-0.parquet"),
        os.path.join("tag=T2", "part-1.parquet")]
    assert parts[0].keys == (("tag", "T1"),)
    # the same through a glob
    assert len(discover(str(tmp_path / "d*"))) == 3


def test_a_link_to_nothing_is_refused(tmp_path, capsys):
    ds = tmp_path / "ds"
    ds.mkdir()
    _epochs(ds / "p0.parquet", "T1")
    os.symlink(tmp_path / "nowhere" / "part-0.parquet", ds / "p1.parquet")
    with pytest.raises(InputError, match="broken link"):
        discover(ds)
    with pytest.raises(InputError, match="broken link"):
        discover(ds / "p1.parquet")
    a = tmp_path / "a.csv"
    a.write_text(ANCHORS)
    # refused before any cluster starts
    assert main(["locate", str(ds), "--anchors", str(a), "-o", str(tmp_path / "o"),
                 "--engine", "dask", "--workers", "1"]) == 2
    assert capsys.readouterr().err.strip() == f"error: {ds / 'p1.parquet'}: broken link"
    assert not (tmp_path / "o").exists()
    assert main(["partition", str(ds), "-o", str(tmp_path / "o2"), "--by", "tag"]) == 2
    assert capsys.readouterr().err.strip() == f"error: {ds / 'p1.parquet'}: broken link"


# --------------------------------------------------------------------------------------
# Ctrl-C at a terminal: SIGINT to the whole process group, the cluster's workers too
# --------------------------------------------------------------------------------------


def _workers(pid: int) -> list[int]:
    """The worker processes ``pid`` spawned (multiprocessing's spawn, exec'd)."""
    out = []
    for d in os.listdir("/proc"):
        try:
            with open(f"/proc/{d}/stat") as f:
                ppid = int(f.read().rsplit(")", 1)[1].split()[1])
            with open(f"/proc/{d}/cmdline", "rb") as f:
                cmd = f.read()
        except (ValueError, OSError, IndexError):
            continue
        if ppid == pid and b"spawn_main" in cmd:
            out.append(int(d))
    return out


def _group_alive(pgid: int) -> bool:
    try:
        os.killpg(pgid, 0)
    except ProcessLookupError:
        return False
    return True


@pytest.mark.skipif(not hasattr(os, "killpg") or not os.path.isdir("/proc"),
                    reason="process groups and /proc")
@pytest.mark.parametrize("when", ["startup", "mid-run"])
def test_ctrl_c_is_one_line_and_exit_130_and_leaves_no_process(tmp_path, when):
    """Ctrl-C while the LocalCluster started gave ``internal error ... RuntimeError: Nanny
    failed to start`` (exit 1); mid-run, exit 130 under 2-5 worker tracebacks and
    ``distributed.worker - ERROR`` lines: the workers, in the terminal's process group,
    had the SIGINT too."""
    import signal
    import subprocess
    import sys
    import time

    ds = tmp_path / "ds"
    ds.mkdir()
    for k in range(4):
        _epochs(ds / f"part-{k}.parquet", f"T{k}", n=200)
    (tmp_path / "a.csv").write_text(ANCHORS)
    out = tmp_path / "out"
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(sys.path))
    proc = subprocess.Popen(
        [sys.executable, "-m", "robustloc.cli", "locate", str(ds), "--anchors",
         str(tmp_path / "a.csv"), "-o", str(out), "--engine", "dask", "--workers", "2"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env,
        start_new_session=True)
    first = ""
    try:
        if when == "startup":
            deadline = time.monotonic() + 120
            while (proc.poll() is None and not _workers(proc.pid)
                   and time.monotonic() < deadline):
                time.sleep(0.01)
            time.sleep(0.3)  # the worker importing distributed
        else:  # the cluster started, the tasks submitted
            first = proc.stderr.readline()
        running = proc.poll() is None
        os.killpg(proc.pid, signal.SIGINT)  # as a terminal's Ctrl-C
        so, err = proc.communicate(timeout=120)
        deadline = time.monotonic() + 30
        while _group_alive(proc.pid) and time.monotonic() < deadline:
            time.sleep(0.2)
        left = _group_alive(proc.pid)
    finally:
        if proc.poll() is None or _group_alive(proc.pid):
            os.killpg(proc.pid, signal.SIGKILL)
        proc.wait(10)
    if not running:
        pytest.skip(f"the run ended before the {when} was caught")
    if when == "mid-run":
        assert first.startswith("locate: 4 partitions on 2 workers"), first
    assert (proc.returncode, err.strip(), so) == (130, "error: interrupted", ""), err
    assert not left, "a process of the run was left"
    assert not out.exists() and not list(tmp_path.glob(".out*"))


# --------------------------------------------------------------------------------------
# spp's summary
# --------------------------------------------------------------------------------------


def test_spp_summary_names_the_parts_where_they_are(scheduler, tmp_path, capsys):
    """Each file's ``out`` was its part in the staging folder, gone after the run."""
    import json
    from pathlib import Path

    from test_engines_dask import geonet_obs_folder

    d, nav = geonet_obs_folder(tmp_path, ("a.05o",))
    out = tmp_path / "sol"
    assert main(["spp", str(d), str(nav), "--systems", "G", "-o", str(out), "--engine",
                 "dask", "--scheduler", scheduler, "--json", "-q"]) == 0
    printed = capsys.readouterr().out
    meta = (out / "_robustloc.json").read_text()
    assert ".partial" not in printed and ".partial" not in meta
    for text in (printed, meta):
        (f,) = json.loads(text)["files"]
        assert f["out"] == str(out / "part-00000.parquet") and Path(f["out"]).is_file()
        assert f["output"] == "part-00000.parquet"


# --------------------------------------------------------------------------------------
# a tag from the folder names: at its contract place, as in the single-process output
# --------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def wifi(tmp_path_factory):
    import argparse

    from robustloc.sim.wifi_room import simulate

    out = tmp_path_factory.mktemp("wifi")
    sim = simulate(out, 4, argparse.Namespace(samples_per_point=10, walk_epochs=60))
    m = pd.read_csv(sim["measurements"], dtype={"tag": str, "anchor": str})
    hive = out / "hive"
    for tag, g in m.groupby("tag"):
        (hive / f"tag={tag}").mkdir(parents=True)
        g.drop(columns="tag").to_parquet(hive / f"tag={tag}" / "part-0.parquet", index=False)
    return sim, m, hive


def test_a_tag_from_the_folders_is_read_at_its_place(wifi, tmp_path):
    from robustloc.engines.dataset import materialize, read_partition

    _, m, hive = wifi
    part = discover(hive)[0]
    assert list(read_partition(part).columns) == list(m.columns)
    assert list(pd.read_parquet(materialize(part, tmp_path)).columns) == list(m.columns)
    empty = tmp_path / "tag=E"
    empty.mkdir()
    m.drop(columns="tag").iloc[:0].to_parquet(empty / "part-0.parquet", index=False)
    (p,) = discover(empty / "part-0.parquet")
    p = type(p)(p.path, (("tag", "E"),))
    assert list(read_partition(p).columns) == list(m.columns)
    (tmp_path / "m").mkdir()
    assert list(pd.read_parquet(materialize(p, tmp_path / "m")).columns) == list(m.columns)


def test_filter_and_partition_by_dask_keep_the_local_column_order(wifi, scheduler,
                                                                  tmp_path):
    sim, m, hive = wifi
    local = tmp_path / "filtered.parquet"
    assert main(["filter", str(sim["measurements"]), "--anchors", str(sim["anchors"]),
                 "-o", str(local), "--quiet"]) == 0
    out = tmp_path / "f"
    assert main(["filter", str(hive), "--anchors", str(sim["anchors"]), "-o", str(out),
                 "--engine", "dask", "--scheduler", scheduler, "--quiet"]) == 0
    want = list(pd.read_parquet(local).columns)
    for p in discover(out):
        assert list(pd.read_parquet(p.path).columns) == want
    shuf = tmp_path / "shuf.csv"
    m.sample(frac=1.0, random_state=3).to_csv(shuf, index=False)
    for method in ("duckdb", "dask"):
        ds = tmp_path / f"p-{method}"
        assert main(["partition", str(shuf), "-o", str(ds), "--by", "tag", "--method",
                     method, *(["--scheduler", scheduler] if method == "dask" else [])]) == 0
        for p in discover(ds):
            assert list(pd.read_parquet(p.path).columns) == list(m.columns), method


# --------------------------------------------------------------------------------------
# track --link-offsets auto: the client's sample streamed
# --------------------------------------------------------------------------------------


def _ranges(path, tags, n: int, shuffle: bool = False, hive: bool = False) -> None:
    import numpy as np

    rng = np.random.default_rng(2)
    df = pd.concat([pd.DataFrame({
        "time": np.repeat(np.arange(n, dtype=float) * 0.1, 4), "tag": t,
        "anchor": np.tile(list("abcd"), n), "range": rng.uniform(3, 9, 4 * n)})
        for t in tags]).sort_values(["time", "tag"], kind="stable")
    if shuffle:
        df = df.sample(frac=1.0, random_state=1)
    if hive:
        df = df.drop(columns="tag")
    df.to_parquet(path, index=False, row_group_size=1000)


def test_first_epochs_of_a_time_sorted_partition_are_read_alone(tmp_path):
    from robustloc.engines.dataset import Partition, read_first_epochs, read_partition

    _ranges(tmp_path / "s.parquet", ["T1", "T2"], 5000)
    part = Partition(str(tmp_path / "s.parquet"))
    whole = read_partition(part)
    head = read_first_epochs(part, 300, batch_rows=512)
    assert 600 <= len(head) < len(whole)
    pd.testing.assert_frame_equal(head, whole.iloc[:len(head)])
    assert head[["time", "tag"]].drop_duplicates().shape[0] >= 300
    assert whole["time"].iloc[len(head)] > head["time"].max()  # no epoch cut
    assert head.attrs["path"] == part.path
    # a hive tag, and a file shorter than asked: all of it
    (tmp_path / "tag=T3").mkdir()
    _ranges(tmp_path / "tag=T3" / "p.parquet", ["T3"], 50, hive=True)
    (p,) = discover(tmp_path / "tag=T3")
    pd.testing.assert_frame_equal(read_first_epochs(p, 300, batch_rows=64),
                                  read_partition(p))
    # rows not in time order: the first epochs by time need the whole file
    _ranges(tmp_path / "u.parquet", ["T1"], 2000, shuffle=True)
    u = Partition(str(tmp_path / "u.parquet"))
    pd.testing.assert_frame_equal(read_first_epochs(u, 30, batch_rows=64),
                                  read_partition(u))


def test_track_auto_sample_reads_no_whole_sorted_partition(tmp_path, monkeypatch, capsys):
    """``--link-offsets auto`` read every sample file whole in the client (680 MB for a
    tag of 3 M rows, 165 MB with ``off``); the same choice from the first epochs."""
    import json

    from robustloc.cli import build_parser
    from robustloc.commands.track import _resolve_auto_on_client
    from robustloc.engines import dataset
    from robustloc.engines.dataset import inspect
    from robustloc.tracking.select import AUTO_SAMPLE_EPOCHS

    ds = tmp_path / "ds"
    ds.mkdir()
    _ranges(ds / "part-0.parquet", ["T1"], AUTO_SAMPLE_EPOCHS + 5000)
    (tmp_path / "a.csv").write_text(ANCHORS)
    local = tmp_path / "local.parquet"
    assert main(["track", str(ds / "part-0.parquet"), "--anchors", str(tmp_path / "a.csv"),
                 "-o", str(local), "--json", "-q"]) == 0
    want = json.loads(capsys.readouterr().out)["link_offsets_auto"]
    args = build_parser().parse_args(["track", str(ds), "--anchors",
                                      str(tmp_path / "a.csv"), "-o", str(tmp_path / "o")])
    infos = [inspect(p) for p in discover(ds, absolute=True)]

    def whole(*a, **k):
        raise AssertionError("a time-sorted partition read whole in the client")

    monkeypatch.setattr(dataset, "read_partition", whole)
    got = _resolve_auto_on_client(args, infos)["link_offsets_auto"]
    assert got.pop("sample") == [infos[0].part.path]
    assert got == want and want["epochs"] == AUTO_SAMPLE_EPOCHS
    assert args.link_offsets == ("on" if want["used"] else "off")


@pytest.mark.parametrize("seed", range(6))
def test_first_epochs_counted_batch_by_batch_as_over_the_whole_prefix(tmp_path, seed):
    """``read_first_epochs`` counts each batch's complete epochs once (it concatenated and
    deduplicated the whole prefix read at every batch: quadratic in the batches); the
    rows returned are those of the whole-prefix count: the shortest prefix of complete
    times (time < the latest time read) at a batch's end holding ``n`` epochs.  Random
    sorted logs with runs of equal times longer than a batch, several tags a time,
    repeated (time, tag) rows; checked against that rule computed here."""
    import numpy as np

    from robustloc.engines.dataset import Partition, read_first_epochs, read_partition

    rng = np.random.default_rng(seed)
    n = 400
    t = np.sort(rng.integers(0, 60, n)).astype(float)  # long runs of one time
    df = pd.DataFrame({"time": t, "tag": rng.choice(["A", "B", "C"], n),
                       "anchor": rng.choice(list("abcd"), n),
                       "range": rng.uniform(3, 9, n)}).sort_values(["time", "tag"],
                                                                  kind="stable")
    path = tmp_path / "p.parquet"
    df.to_parquet(path, index=False, row_group_size=50)
    part = Partition(str(path))
    whole = read_partition(part)
    for batch, want in ((7, 5), (7, 40), (16, 25), (33, 90), (64, 200)):
        got = read_first_epochs(part, want, batch_rows=batch)
        expect = len(whole)  # no batch end reaches it: everything
        for end in range(batch, len(whole) + batch, batch):
            pre = whole.iloc[:min(end, len(whole))]
            done = pre[pre["time"] < pre["time"].iloc[-1]]
            if len(done[["time", "tag"]].drop_duplicates()) >= want:
                expect = len(done)
                break
        assert len(got) == expect, (batch, want)
        pd.testing.assert_frame_equal(got, whole.iloc[:expect])
