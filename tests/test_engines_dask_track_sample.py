"""``track --engine dask --link-offsets auto`` (the default): the client's sample is the
single process's, the dataset's first epochs by time then tag over every partition file
(the dask review: it took the files in path order until it had its epochs, so a dataset
partitioned by tag, each file spanning the whole log, gave the first files' tags alone:
a walk of 30 tags chose ``off`` on dask where one process chose ``on``, 59 970 of 60 000
rows differing)."""

from __future__ import annotations

import json

import numpy as np
import pandas as pd
import pytest

pytest.importorskip("distributed")

import robustloc.tracking.select as sel  # noqa: E402
from robustloc.cli import build_parser, main  # noqa: E402
from robustloc.engines import dataset  # noqa: E402
from robustloc.engines.dataset import discover, inspect  # noqa: E402

#: The sample's epochs in these tests (20 000 by default: slow to track twice here).
K = 300


def _clean_then_biased(tmp_path) -> tuple[str, str]:
    """Eight tags walking in a ring of six anchors with no link offsets (tags ``at0``-``at7``)
    and eight more whose ranges carry per-anchor offsets of 6 to 12 sigma (``bt0``-``bt7``),
    both over the same 80 s: by tag, the clean tags' files come first in path order.  The
    log sorted by time (CSV) and the anchors."""
    from test_track_select import clean_and_biased_logs

    one, two, an = clean_and_biased_logs(tmp_path)
    one["tag"] = "a" + one["tag"].astype(str)  # (path order: the clean tags first)
    two["tag"] = "b" + two["tag"].astype(str)
    log = pd.concat([one, two], ignore_index=True).sort_values(["time", "tag"],
                                                               kind="stable")
    log.to_csv(tmp_path / "sorted.csv", index=False)
    return str(tmp_path / "sorted.csv"), an


def _capture_samples(monkeypatch) -> list:
    """Each trial's sample (its first :data:`K` epochs, as the choice uses them)."""
    seen: list = []
    choose = sel.choose_link_offsets

    def spy(anchors, epochs, *a, **k):
        seen.append(sel._head(epochs, sel.AUTO_SAMPLE_EPOCHS))
        return choose(anchors, epochs, *a, **k)

    monkeypatch.setattr(sel, "choose_link_offsets", spy)
    return seen


def _same_epochs(got, want) -> None:
    assert got.n_epochs == want.n_epochs == K
    np.testing.assert_array_equal(got.time, want.time)
    np.testing.assert_array_equal(got.tag.astype(str), want.tag.astype(str))
    assert list(got.anchor_ids) == list(want.anchor_ids)
    np.testing.assert_array_equal(got.values, want.values)  # (NaN where not heard)


def _client_choice(ds, log: str, an: str) -> tuple[dict, object]:
    from robustloc.commands.track import _resolve_auto_on_client

    args = build_parser().parse_args(["track", str(ds), "--anchors", an, "-o", "unused",
                                      "--q", "0.05"])
    infos = [inspect(p) for p in discover(ds, absolute=True)]
    return _resolve_auto_on_client(args, infos)["link_offsets_auto"], args


def test_by_tag_sample_is_the_single_process_sample(tmp_path, monkeypatch, capsys):
    """A dataset by tag (16 files, each a tag over the whole 80 s; 2 560 epochs, more
    than K): the client's sample is the single process's, epoch for epoch, and so is its
    choice (``on``, t = 12.9).  The files in path order gave the clean tags at0 and at1
    alone, which chose ``off`` (t = -4.0)."""
    log, an = _clean_then_biased(tmp_path)
    ds = tmp_path / "by_tag"
    assert main(["partition", log, "-o", str(ds), "--by", "tag", "-q"]) == 0
    monkeypatch.setattr(sel, "AUTO_SAMPLE_EPOCHS", K)
    samples = _capture_samples(monkeypatch)
    assert main(["track", log, "--anchors", an, "--q", "0.05",
                 "-o", str(tmp_path / "ref.parquet"), "--json", "-q"]) == 0
    want = json.loads(capsys.readouterr().out)["link_offsets_auto"]
    assert want["used"] is True and want["epochs"] == K
    got, args = _client_choice(ds, log, an)
    assert len(samples) == 2
    _same_epochs(samples[1], samples[0])
    files = got.pop("sample")
    assert got == want and args.link_offsets == "on"
    # the files holding the sample's epochs: all 16 tags are heard in its first second
    assert len(files) == 16 and files == sorted(files)


def test_by_tag_track_dask_equals_single_process(tmp_path, monkeypatch, capsys,
                                                 scheduler):
    """End to end on a LocalCluster: ``track --engine dask`` with the default writes the
    single process's choice and rows (the path-order sample chose ``off``: the biased
    tags' rows tracked without their links' offsets)."""
    from test_engines_dask import _dataset

    log, an = _clean_then_biased(tmp_path)
    ds = tmp_path / "by_tag"
    assert main(["partition", log, "-o", str(ds), "--by", "tag", "-q"]) == 0
    monkeypatch.setattr(sel, "AUTO_SAMPLE_EPOCHS", K)  # (the workers are threads here)
    opts = ["--anchors", an, "--q", "0.05", "--json", "-q"]
    assert main(["track", log, *opts, "-o", str(tmp_path / "ref.parquet")]) == 0
    want = json.loads(capsys.readouterr().out)
    out = tmp_path / "t-dask"
    assert main(["track", str(ds), *opts, "-o", str(out), "--engine", "dask",
                 "--scheduler", scheduler]) == 0
    got = json.loads(capsys.readouterr().out)
    auto = dict(got["link_offsets_auto"])
    auto.pop("sample")
    assert auto == want["link_offsets_auto"] and auto["used"] is True
    assert got["link_offset_m"] == want["link_offset_m"]
    ref = pd.read_parquet(tmp_path / "ref.parquet").sort_values(["time", "tag"])
    rows = _dataset(out).sort_values(["time", "tag"])
    # a tag is updated in batches of other tags in one process and alone on its worker:
    # equal to rounding, as in test_engines_dask (a model chosen differently moves rows
    # by metres)
    pd.testing.assert_frame_equal(rows.reset_index(drop=True), ref.reset_index(drop=True),
                                  check_exact=False, rtol=1e-12, atol=1e-12)


def test_by_time_later_files_are_not_read(tmp_path, monkeypatch):
    """A dataset by time (5 s bins, 160 epochs each): the sample fills from the
    first files and is the single process's; a file that starts after its last epoch is
    not read at all, and the one it ends in only up to that time."""
    log, an = _clean_then_biased(tmp_path)
    ds = tmp_path / "by_time"
    assert main(["partition", log, "-o", str(ds), "--by", "time", "--span", "5", "-q"]) == 0
    monkeypatch.setattr(sel, "AUTO_SAMPLE_EPOCHS", K)
    samples = _capture_samples(monkeypatch)
    from robustloc.io import iter_epochs, read_anchors
    from robustloc.io.tables import Epochs

    whole = Epochs.concat(list(iter_epochs(log, read_anchors(an), order="sort")))
    first = sel._head(whole, K)
    calls: list[tuple[str, float | None, pd.DataFrame]] = []
    read = dataset.read_first_epochs

    def counted(part, n, *a, **k):
        rows = read(part, n, *a, **k)
        calls.append((part.path, k.get("until"), rows))
        return rows

    monkeypatch.setattr(dataset, "read_first_epochs", counted)
    got, _ = _client_choice(ds, log, an)
    _same_epochs(samples[0], first)
    last = float(first.time[-1])
    infos = [inspect(p) for p in discover(ds, absolute=True)]
    assert len(infos) == 16
    starting_after = {i.part.path for i in infos if i.time_min > last}
    assert len(starting_after) >= 13  # (80 s, the sample's 300 epochs in its first 10 s)
    assert not starting_after & {p for p, _, _ in calls}
    assert all(rows["time"].max() <= u for _, u, rows in calls if u is not None)
    assert got["sample"] == sorted(p for p, _, _ in calls if p not in starting_after)


def test_first_epochs_until_a_time_keep_every_row_at_it(tmp_path):
    """``read_first_epochs(..., until=T)`` on a time-sorted file stops at the first batch
    past T and returns every row at or before T -- the rows at T of every tag, across a
    batch boundary (an epoch at T with a smaller tag than the caller's can be among the
    first epochs) -- and none after; the epoch count still stops it first when smaller."""
    from robustloc.engines.dataset import Partition, read_first_epochs, read_partition

    n = 200
    df = pd.DataFrame({"time": np.repeat(np.arange(n, dtype=float), 6),
                       "tag": np.tile(np.repeat(["A", "B", "C"], 2), n),
                       "anchor": np.tile(list("ab"), 3 * n),
                       "range": np.linspace(3, 9, 6 * n)})
    path = tmp_path / "p.parquet"
    df.to_parquet(path, index=False, row_group_size=64)
    part = Partition(str(path))
    whole = read_partition(part)
    for batch, until in ((7, 10.0), (5, 10.0), (64, 57.0), (64, 0.0), (13, 199.0)):
        got = read_first_epochs(part, 10_000, batch_rows=batch, until=until)
        pd.testing.assert_frame_equal(got, whole[whole["time"] <= until])
    # the epoch count first: its own rule (the rows before the latest time read)
    got = read_first_epochs(part, 30, batch_rows=64, until=150.0)
    assert got["time"].max() < 150.0 and got[["time", "tag"]].drop_duplicates().shape[0] >= 30
    pd.testing.assert_frame_equal(got, whole.iloc[:len(got)])
