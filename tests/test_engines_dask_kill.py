"""A worker killed mid-run (SIGKILL: the OOM killer, a node lost) on a real LocalCluster,
and the whole cluster killed mid-run.

``locate --engine dask --scheduler ADDRESS`` runs in a subprocess against a LocalCluster
of two worker processes (nannies) started by the test; once a task is writing its part,
the test kills that worker's process.  Dask runs the lost task again on the other
worker; the command must end with exit 0 and a dataset holding exactly the rows of a
local run, and nothing else: the killed task's temporary file had been committed with
the dataset (a hidden partial parquet file, as large as the part).

The whole cluster (scheduler and workers, a subprocess of the test) killed while a part
is written: exit 2 with one line, ``error: lost the dask scheduler ...`` (distributed's
client had logged three tracebacks, 40 lines, above it), the previous output kept as it
was, no staging folder left.

Bounded: 8 partitions of 100 000 epochs, one kill each, 300 s at most; the clusters and
the subprocesses are stopped by the tests.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

distributed = pytest.importorskip("distributed")

from robustloc.cli import main  # noqa: E402

EPOCHS = 100_000
PARTS = 8
ANCHORS = pd.DataFrame({"anchor": list("abcde"), "x": [0.0, 20, 20, 0, 10],
                        "y": [0.0, 0, 20, 20, 10]})


def _dataset(folder: Path) -> Path:
    """``PARTS`` parquet files of one tag each, ranges 0.1 m noisy from 5 anchors."""
    ds = folder / "ds"
    ds.mkdir()
    rng = np.random.default_rng(1)
    ax, ay = ANCHORS["x"].to_numpy(), ANCHORS["y"].to_numpy()
    for k in range(PARTS):
        xy = rng.uniform(2, 18, (EPOCHS, 2))
        d = np.hypot(xy[:, None, 0] - ax, xy[:, None, 1] - ay)
        d += rng.normal(0, 0.1, d.shape)
        pd.DataFrame({"time": np.repeat(np.arange(EPOCHS, dtype=float), 5), "tag": f"T{k}",
                      "anchor": np.tile(list("abcde"), EPOCHS), "range": d.ravel()}
                     ).to_parquet(ds / f"part-{k:05d}.parquet", index=False)
    return ds


def _rows(folder: Path) -> pd.DataFrame:
    files = sorted(folder.glob("part-*.parquet"))
    df = pd.concat([pd.read_parquet(f) for f in files], ignore_index=True)
    return df.sort_values(["tag", "time"]).reset_index(drop=True)


def test_a_worker_killed_while_writing_loses_nothing_and_leaves_nothing(tmp_path):
    ds = _dataset(tmp_path)
    ANCHORS.to_csv(tmp_path / "a.csv", index=False)
    out = tmp_path / "out"
    cluster = client = proc = None
    try:
        cluster = distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                                           dashboard_address=":0")
        client = distributed.Client(cluster)
        pids = client.run(os.getpid)
        proc = subprocess.Popen(
            [sys.executable, "-m", "robustloc.cli", "locate", str(ds), "--anchors",
             str(tmp_path / "a.csv"), "-o", str(out), "--engine", "dask", "--scheduler",
             cluster.scheduler_address, "-q"],
            stderr=subprocess.PIPE, text=True)
        killed = None
        deadline = time.monotonic() + 200
        while proc.poll() is None and killed is None and time.monotonic() < deadline:
            # a part being written: its temporary file in the run's staging folder
            writing = [p for d in tmp_path.glob(".out.partial-*") if d.is_dir()
                       for p in d.glob(".part-*.tmp")]
            busy = [w for w, keys in client.processing().items() if keys]
            if writing and busy:
                os.kill(pids[busy[0]], signal.SIGKILL)
                killed = busy[0]
            time.sleep(0.02)
        _, err = proc.communicate(timeout=max(1.0, deadline - time.monotonic()))
    finally:
        if proc is not None and proc.poll() is None:
            proc.kill()
            proc.wait(10)
        if client is not None:
            client.close()
        if cluster is not None:
            cluster.close()
    if killed is None:
        pytest.skip("no task was caught writing its part (the run was too quick)")
    assert proc.returncode == 0, err
    # nothing but the parts and the metadata: no temporary file of the killed task
    assert sorted(p.name for p in out.iterdir()) == (
        ["_robustloc.json"] + [f"part-{k:05d}.parquet" for k in range(PARTS)])
    assert not list(tmp_path.glob(".out*")), "a staging folder was left beside -o"
    # every epoch once, as a local run gives it
    got = _rows(out)
    assert len(got) == PARTS * EPOCHS
    whole = tmp_path / "whole.parquet"  # (a local run reads one file)
    pd.concat([pd.read_parquet(f) for f in sorted(ds.glob("*.parquet"))]).to_parquet(whole)
    assert main(["locate", str(whole), "--anchors", str(tmp_path / "a.csv"), "-o",
                 str(tmp_path / "local.parquet"), "-q"]) == 0
    ref = pd.read_parquet(tmp_path / "local.parquet").sort_values(["tag", "time"])
    pd.testing.assert_frame_equal(got[ref.columns.tolist()],
                                  ref.reset_index(drop=True), check_dtype=False)


_CLUSTER = """
import sys
import distributed
if __name__ == "__main__":
    cluster = distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                                       dashboard_address=":0")
    print(cluster.scheduler_address, flush=True)
    sys.stdin.read()  # until the test closes our stdin (or kills us)
"""


def test_a_cluster_killed_mid_run_is_one_error_line_and_the_old_output_stays(tmp_path):
    ds = _dataset(tmp_path)
    ANCHORS.to_csv(tmp_path / "a.csv", index=False)
    out = tmp_path / "out"
    out.mkdir()
    (out / "part-00000.parquet").write_bytes(b"an earlier run's output")
    (out / "_robustloc.json").write_text('{"command": "locate"}\n')  # (a dataset of ours)
    (tmp_path / "cluster.py").write_text(_CLUSTER)
    cluster = subprocess.Popen([sys.executable, str(tmp_path / "cluster.py")],
                               stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                               stderr=subprocess.DEVNULL, text=True, start_new_session=True)
    proc = None
    try:
        address = cluster.stdout.readline().strip()
        if not address:
            pytest.skip("the subprocess's LocalCluster did not start")
        proc = subprocess.Popen(
            [sys.executable, "-m", "robustloc.cli", "locate", str(ds), "--anchors",
             str(tmp_path / "a.csv"), "-o", str(out), "--engine", "dask", "--scheduler",
             address, "-q"], stderr=subprocess.PIPE, text=True)
        killed = False
        deadline = time.monotonic() + 200
        while proc.poll() is None and not killed and time.monotonic() < deadline:
            if any(d.is_dir() and any(d.glob(".part-*.tmp"))
                   for d in tmp_path.glob(".out.partial-*")):
                os.killpg(cluster.pid, signal.SIGKILL)  # the scheduler and its nannies
                killed = True
            time.sleep(0.02)
        _, err = proc.communicate(timeout=120)
    finally:
        if proc is not None and proc.poll() is None:
            proc.kill()
            proc.wait(10)
        if cluster.poll() is None:
            os.killpg(cluster.pid, signal.SIGKILL)
        cluster.wait(10)
    if not killed:
        pytest.skip("no task was caught writing its part (the run was too quick)")
    assert proc.returncode == 2, err
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: lost the dask scheduler"), err
    assert sorted(p.name for p in out.iterdir()) == ["_robustloc.json", "part-00000.parquet"]
    assert (out / "part-00000.parquet").read_bytes() == b"an earlier run's output"
    assert not list(tmp_path.glob(".out*")), "a staging folder was left beside -o"
