"""``--engine dask``: robustloc's commands over partitioned Parquet on dask.distributed.

Every runner plans on the client, sends one task per partition (or per tag group) to the
workers, and each task calls the command's own single-process function -- passed in by
the command module, so this layer never imports a command and never re-implements one:

* :func:`run_locate` -- snapshot methods: ``locate_file`` on each partition file (an epoch
  is never split: :func:`robustloc.engines.dataset.plan_snapshot`), one output file each.
* :func:`run_tagwise` -- filters and trackers: ``kernel(measurements, anchors, args) ->
  (frame, counts)`` on each tag group (:func:`robustloc.engines.dataset.plan_tagwise`).
  ``filter`` plugs in as ``run_filter(args, filter_partition)``; ``track`` as
  ``run_tagwise(args, track_partition, "track", file_fn=track_partition_file)``: a tag
  group of one file is streamed by ``track``'s own per-file function.
* :func:`run_spp` -- ``spp``'s ``run`` on each RINEX observation file.
* :func:`evaluate_dataset` -- per-row errors of each positions partition on the workers,
  statistics of the whole on the client (exact: pooled medians and percentiles).

The output is a dataset directory of ``part-NNNNN.parquet`` files, one per input
partition or tag group, in the order of the input's time (snapshot) or tags (tagwise),
plus ``_robustloc.json`` (command, partition files, counts).  It is written in a staging
directory next to the output and renamed into place only when every task succeeded, so a
failed run never leaves a half-written dataset, and never replaces a directory that is not
a robustloc dataset.  Workers must see the input, the anchors and the output's parent
directory at the same paths (a shared filesystem on a real cluster): every path handed to
them is made absolute on the client first (:func:`_settings`, ``discover(...,
absolute=True)``; a worker resolves a relative path in its own working directory), and
the run fails, writing nothing, if a part is not where the client looks for it
(:meth:`DatasetOutput.check_parts`).  ``-o -`` is refused: the output is a folder.
"""

from __future__ import annotations

import argparse
import glob
import io
import json
import os
import shutil
import sys
import tempfile
import threading
import time as _time
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import TYPE_CHECKING

import pandas as pd

from robustloc.engines.cluster import dask_client, gather_with_progress, submit_all
from robustloc.engines.dataset import (
    Partition,
    PartitionInfo,
    count_epochs,
    discover,
    inspect,
    materialize,
    overlapping,
    plan_snapshot,
    plan_tagwise,
    read_partition,
)
from robustloc.errors import InputError

if TYPE_CHECKING:
    from robustloc.pipelines.locate import LogSample

#: Per-partition function of a tag-partitioned command: (validated measurements of one
#: tag group, anchors, args) -> (output frame, integer counts summed over the groups).
TagKernel = Callable[[pd.DataFrame, pd.DataFrame, argparse.Namespace],
                     tuple[pd.DataFrame, dict[str, int]]]
META_FILE = "_robustloc.json"


# --------------------------------------------------------------------------------------
# output dataset
# --------------------------------------------------------------------------------------


#: Output names of a single text file, refused as a dataset's folder name (``.parquet``
#: stays allowed: a folder of Parquet parts is often named so).
FILE_ONLY_SUFFIXES = (".csv", ".csv.gz", ".csv.bz2", ".csv.xz", ".csv.zst", ".txt", ".tsv",
                      ".json", ".png")


class DatasetOutput:
    """A dataset directory written in a staging directory and renamed into place.

    Parameters
    ----------
    out : str or PathLike
        The dataset directory.  An existing robustloc dataset (it holds
        ``_robustloc.json``) or empty directory is replaced on :meth:`commit`; a file, or a
        non-empty directory that is not a robustloc dataset, is refused (exit 2).
    inputs : iterable of path, optional
        The run's inputs (datasets, their partition files, anchors; see
        :func:`input_paths`).  An ``out`` that is an input, holds one or lies inside one
        is refused before anything is written
        (:func:`robustloc.io.atomic.check_not_input_tree`): replacing it would delete
        the input.
    """

    def __init__(self, out: str | Path,
                 inputs: Iterable[str | os.PathLike | None] = (),
                 writer: str = "--engine dask") -> None:
        from robustloc.io.atomic import check_not_input_tree, is_stdio

        # (``writer``: who writes the dataset, for the messages -- ``partition`` has no
        # --engine option, so "leave out --engine dask" was advice it could not follow)
        if is_stdio(out):  # (a folder named "-" was written, exit 0, nothing on stdout)
            raise InputError(f"{writer} writes a dataset folder, not standard output", "-o")
        given = Path(out)  # as the user gave it, for messages
        # a file's name for a folder: `-o positions.csv` made a folder of that name that
        # `robustloc evaluate positions.csv` then refused as a directory (the Dask review)
        if given.name.lower().endswith(FILE_ONLY_SUFFIXES):
            raise InputError(f"{writer} writes a dataset (a folder of Parquet parts), "
                             "not one text file: give a folder name (e.g. positions/)"
                             + (", or leave out --engine dask for one CSV file"
                                if writer == "--engine dask" else ""), given)
        # absolute: the tasks write their parts on workers, which resolve a relative
        # path in their own working directory (the parts were lost, exit 0)
        self.out = Path(os.path.abspath(out))
        check_not_input_tree(self.out, inputs)
        if self.out.exists():
            if not self.out.is_dir():
                raise InputError(f"exists and is a file; {writer} writes a dataset "
                                 "directory (give a new or a dataset directory)", given)
            if any(self.out.iterdir()) and not (self.out / META_FILE).exists():
                raise InputError("directory exists and is not a robustloc dataset; refusing "
                                 "to replace it", given)
        self.given = given
        from robustloc.io.atomic import staging_name, sweep_orphans

        self.stage = self.out.parent / staging_name(self.out.name)
        try:
            self.out.parent.mkdir(parents=True, exist_ok=True)
            sweep_orphans(self.out.parent, self.out.name)  # a killed run's staging
            self.stage.mkdir()
        except OSError as exc:  # named as given (the staging folder's name meant nothing
            # to the user: "/proc/.xx.partial-cc3fd4a5: file not found", the Dask review)
            from robustloc.errors import OutputError

            raise OutputError(f"cannot create the dataset folder here "
                              f"({exc.strerror or exc})", given, errno_=exc.errno) from None

    def part(self, i: int) -> str:
        """Absolute path of output partition ``i`` (in the staging directory)."""
        return str(self.stage / f"part-{i:05d}.parquet")

    def check_parts(self, n: int, rows: list[int | None] | None = None) -> None:
        """Refuse to commit unless the tasks wrote every part ``0 .. n-1`` (and, where
        ``rows`` gives a task's row count, that many rows).

        Raises
        ------
        OutputError
            ``OUT: part-NNNNN.parquet was not written ...``: the workers wrote elsewhere
            (they do not see this folder at this path) or lost it.
        """
        import pyarrow.parquet as pq

        from robustloc.errors import OutputError

        for i in range(n):
            p = Path(self.part(i))
            if not p.is_file():
                raise OutputError(
                    f"{p.name} of this run is missing from {self.stage}: the dask workers "
                    "must see the output's folder at the same path as this machine (a "
                    "shared filesystem); nothing was written", self.given)
            want = None if rows is None else rows[i]
            if want is not None:
                got = pq.ParquetFile(p).metadata.num_rows
                if got != want:
                    raise OutputError(
                        f"{p.name} holds {got} rows where its task wrote {want}; nothing "
                        "was written", self.given)

    def commit(self, meta: dict, n_parts: int | None = None,
               rows: list[int | None] | None = None) -> None:
        """Check the parts (:meth:`check_parts`, when ``n_parts`` is given), write the
        metadata and move the dataset into place."""
        if n_parts is not None:
            self.check_parts(n_parts, rows)
        # a worker killed while writing its part left its temporary file (the task ran
        # again on another worker and wrote the part): it was committed with the
        # dataset, a hidden partial parquet file as large as the part (measured with a
        # SIGKILLed worker of a real LocalCluster)
        for tmp in self.stage.glob(".part-*.tmp"):
            tmp.unlink(missing_ok=True)
        (self.stage / META_FILE).write_text(json.dumps(meta, indent=2) + "\n")
        from robustloc.io.atomic import aside_name

        old = None
        if self.out.exists():
            # (named as sweep_orphans knows: a run killed between the two renames left
            # `.NAME.old-XXXXXXXX`, which no later run removed -- the Dask review)
            old = self.out.parent / aside_name(self.out.name)
            self.out.rename(old)
        self.stage.rename(self.out)
        if old is not None:
            shutil.rmtree(old, ignore_errors=True)

    def abort(self) -> None:
        """Remove the staging directory.

        A task still running when the run failed cannot re-create it (the tasks write
        with :func:`robustloc.io.atomic.parents_not_created`); one that was between
        creating its temporary file and renaming it may keep the folder from being
        removed at once, so the removal is tried again for a moment.
        """
        for k in range(_ABORT_TRIES):
            shutil.rmtree(self.stage, ignore_errors=True)
            if not self.stage.exists():
                return
            _time.sleep(0.1 * (k + 1))


#: Attempts to remove a failed run's staging directory (:meth:`DatasetOutput.abort`).
_ABORT_TRIES = 5
#: Attributes of a command's arguments that name files or datasets, made absolute before
#: they are handed to the workers (:func:`_settings`).
PATH_ARGS = ("measurements", "obs", "positions", "anchors", "truth", "nav", "sp3", "clk",
             "out")


def absolute_path(path: str | os.PathLike) -> str:
    """``path`` as an absolute path for a worker (``-``, standard input, kept).

    A worker resolves a relative path in its own working directory: with ``--scheduler``
    a relative ``--anchors`` silently read another file of the same name there.
    """
    from robustloc.io.atomic import is_stdio

    s = os.fspath(path)
    return s if is_stdio(s) else os.path.abspath(os.path.expanduser(s))


def input_paths(spec: str | os.PathLike | None, parts: Iterable[Partition] = (),
                *others: str | os.PathLike | None) -> list[str]:
    """The paths a run reads, for :class:`DatasetOutput`'s output-over-input check.

    Parameters
    ----------
    spec : str or PathLike, optional
        A dataset (directory, file or glob: a glob gives the paths it matches).
    parts : iterable of Partition
        Its partition files.
    *others : str or PathLike, optional
        Further input files (anchors, navigation files); None is skipped.
    """
    out: list[str] = []
    if spec is not None:
        s = str(spec)
        out.append(s)
        if not os.path.exists(s) and glob.has_magic(s):
            out += sorted(glob.glob(s, recursive=True))
    out += [p.path for p in parts]
    out += [str(o) for o in others if o is not None]
    return out


def _settings(args: argparse.Namespace) -> dict:
    """The command's settings, picklable (the dispatch function is dropped), every path
    of :data:`PATH_ARGS` absolute (:func:`absolute_path`)."""
    out = {k: v for k, v in vars(args).items() if not k.startswith("_")}
    for k in PATH_ARGS:
        v = out.get(k)
        if isinstance(v, (str, os.PathLike)):
            out[k] = absolute_path(v)
        elif isinstance(v, (list, tuple)):
            out[k] = [absolute_path(x) if isinstance(x, (str, os.PathLike)) else x
                      for x in v]
    return out


def _sum_counts(total: dict, part: dict) -> None:
    for k, v in part.items():
        if isinstance(v, dict):
            _sum_counts(total.setdefault(k, {}), v)
        elif isinstance(v, int) and not isinstance(v, bool):
            total[k] = total.get(k, 0) + v


# --------------------------------------------------------------------------------------
# tasks (run on the workers)
# --------------------------------------------------------------------------------------


def _inspect_task(part: Partition, need: tuple[str, ...], tags: bool) -> PartitionInfo:
    return inspect(part, need, tags)


def _value_column(info: PartitionInfo) -> str | None:
    present = [c for c in ("rssi", "range") if c in info.columns]
    return present[0] if len(present) == 1 else None


def _file_task(fn: Callable[[argparse.Namespace], dict], settings: dict, input_attr: str,
               part: Partition, out: str) -> dict:
    """``fn`` (a command's per-file function) on one partition file.  (Every task writes
    its part with :func:`~robustloc.io.atomic.parents_not_created`: only the client
    creates the staging directory, so a task still running after a failed run removed
    it cannot leave it behind.)"""
    from robustloc.io.atomic import parents_not_created

    with tempfile.TemporaryDirectory(prefix="robustloc-") as tmp, parents_not_created():
        path = materialize(part, tmp)
        ns = argparse.Namespace(**settings)
        setattr(ns, input_attr, path)
        ns.out = out
        ns.quiet = True
        try:
            return fn(ns)
        except InputError as exc:
            if path != part.path:  # the copy has the same rows: name the partition file
                raise InputError(exc.message, part.path, exc.line) from None
            raise


def _tag_task(kernel: TagKernel, settings: dict, parts: list[Partition], out: str
              ) -> dict[str, int]:
    """``kernel`` on one tag group: its partitions read, validated, concatenated."""
    from robustloc.io import read_anchors, write_table
    from robustloc.io.atomic import parents_not_created
    from robustloc.io.tables import validate_measurements

    ns = argparse.Namespace(**settings)
    anchors = read_anchors(ns.anchors)
    frames = []
    for p in parts:
        raw = read_partition(p)
        if len(raw) == 0:
            continue
        frames.append(validate_measurements(raw, p.path, anchors))
    meas = frames[0] if len(frames) == 1 else pd.concat(frames)
    meas.attrs = dict(frames[0].attrs)
    frame, counts = kernel(meas, anchors, ns)
    with parents_not_created():
        write_table(frame, out)
    return dict(counts, rows_out=int(len(frame)))


# --------------------------------------------------------------------------------------
# runners (on the client)
# --------------------------------------------------------------------------------------


def _plan_infos(client: object, parts: list[Partition], need: tuple[str, ...], show: bool,
                tags: str = "all") -> list[PartitionInfo]:
    """Inspect every partition on the workers.  ``tags``: "all" reads every partition's
    tags; "overlapping" only those of partitions whose time ranges meet (a snapshot
    method's check needs no more; the time ranges come from the Parquet statistics)."""
    futs = submit_all(client, _inspect_task, [(p, need, tags == "all") for p in parts])
    infos = gather_with_progress(client, futs, show)
    if tags == "overlapping":
        again = overlapping(infos)
        if again:
            futs = submit_all(client, _inspect_task, [(i.part, need, True) for i in again])
            redo = {i.part.path: i for i in gather_with_progress(client, futs, show)}
            infos = [redo.get(i.part.path, i) for i in infos]
    values = {}
    for info in infos:
        if info.n_rows and "anchor" in need:
            v = _value_column(info)
            if v is None:
                have = ", ".join(info.columns)
                raise InputError("partition needs exactly one of the columns rssi, range "
                                 f"(has: {have})", info.part.path, 1)
            values.setdefault(v, info.part.path)
    if len(values) > 1:
        (v1, p1), (v2, p2) = list(values.items())[:2]
        raise InputError(f"partition holds {v2} while {p1} holds {v1}; a dataset holds one "
                         "kind of measurement", p2, 1)
    if not any(i.n_rows for i in infos):
        # (line 2: where the first data row would be, as the in-memory reader says of a
        # file with a header and no data rows)
        raise InputError("every partition of this dataset is empty (no data rows)",
                         parts[0].path, 2)
    return infos


def _show(args: argparse.Namespace) -> bool:
    return not getattr(args, "quiet", False) and not getattr(args, "json", False)


def _say(args: argparse.Namespace, text: str) -> None:
    if _show(args):
        print(text, file=sys.stderr)


def run_locate(args: argparse.Namespace, locate_file: Callable[[argparse.Namespace], dict]
               ) -> int:
    """``locate --engine dask``: ``locate_file`` on every partition of the dataset."""
    return _run_snapshot(args, locate_file, "measurements", "locate")


def _run_snapshot(args: argparse.Namespace, fn: Callable[[argparse.Namespace], dict],
                  input_attr: str, name: str) -> int:
    t0 = _time.perf_counter()
    parts = discover(getattr(args, input_attr), what="measurements dataset", absolute=True)
    out = DatasetOutput(args.out, input_paths(getattr(args, input_attr), parts,
                                              getattr(args, "anchors", None)))
    try:
        with dask_client(args.scheduler, args.workers) as client:
            infos = _plan_infos(client, parts, ("time", "tag", "anchor"), False,
                                tags="overlapping")
            plan = plan_snapshot(infos)
            _say(args, f"{name}: {len(plan)} partitions on "
                       f"{len(client.scheduler_info()['workers'])} workers")
            settings = _settings(args)
            compiling = 0.0  # numba compiling kernels not cached: here and in the tasks
            if name == "locate" and getattr(args, "robust_scale", None) == "log":
                # the log's noise scale and gross share are the whole dataset's: one
                # first pass (an even sample of its epochs, in the partitions' order),
                # handed to every partition, as the single-process first pass does
                # (solved here: the notice if numba compiles its kernels for it)
                from robustloc._jitnotice import compile_watch

                with compile_watch("positioning",
                                   announce=not getattr(args, "quiet", False)) as jit:
                    settings.update(_log_scales(client, args, settings, plan))
                compiling += jit.seconds
            futs = submit_all(client, _file_task, [(fn, settings, input_attr, info.part,
                                                    out.part(i)) for i, info in enumerate(plan)])
            summaries = gather_with_progress(client, futs, _show(args))
            n_workers = len(client.scheduler_info()["workers"])
        wall = _time.perf_counter() - t0
        hpl = _merged_hpl(summaries)
        compiling += sum(float(s.get("compile_seconds") or 0.0) for s in summaries)
        total: dict = {}
        for s in summaries:
            _sum_counts(total, s)
        summary = {
            "command": name, "engine": "dask", "input": str(getattr(args, input_attr)),
            "out": str(args.out), "partitions": len(plan), "workers": n_workers,
            "value": summaries[0].get("value"), "methods": summaries[0].get("methods"),
            "epochs": total.get("epochs", 0), "status": total.get("status", {}),
            "hpl_histogram": total.get("hpl_histogram", {}),
            "hpl_quantiles": hpl,
            "side_from_log": total.get("side_from_log", {}),
            "duplicates_merged": total.get("duplicates_merged", 0),
            "invalid_measurement_rows": total.get("invalid_measurement_rows", 0),
            "seconds": round(wall, 3), "compile_seconds": round(compiling, 3),
            "epochs_per_second": round(total.get("epochs", 0) / max(wall, 1e-9), 1),
            "files": [{"input": info.part.path, "output": Path(out.part(i)).name}
                      for i, info in enumerate(plan)],
        }
        # the rest of the single-process summary's keys (a script reading them worked
        # with one engine only: the Dask review): the dataset's one first pass gives every
        # partition the same sides; a partition sorted first makes the run's flag; the
        # solving seconds are the tasks' summed, and the rate is per second of solving,
        # as the single process's (compiling, summed over the tasks, can exceed the wall
        # time: a rate over "wall less compiling" came out absurd)
        if name == "locate":  # (the single process names its input and output so)
            summary["measurements"] = str(getattr(args, input_attr))
            summary["positions"] = str(args.out)
        if summaries and "log_sides" in summaries[0]:
            summary["log_sides"] = summaries[0]["log_sides"]
        summary["sorted_first"] = any(bool(s.get("sorted_first")) for s in summaries)
        summary["solve_seconds"] = round(sum(float(s.get("solve_seconds") or 0.0)
                                             for s in summaries), 3)
        fixes = total.get("epochs", 0) * len(summary.get("methods") or [None])
        summary["fixes_per_second"] = round(fixes / max(summary["solve_seconds"], 1e-9), 1)
        from robustloc.pipelines.locate import ANCHOR_WARNING_KEYS

        for key in ANCHOR_WARNING_KEYS:
            # one anchors file and one first pass for every partition: the same lists
            if summaries and key in summaries[0]:
                summary[key] = summaries[0][key]
        cut = [s["lege_search_truncated"] for s in summaries if s.get("lege_search_truncated")]
        if cut:  # epochs of every partition
            summary["lege_search_truncated"] = {"epochs": sum(int(c["epochs"]) for c in cut),
                                                "max_sets": cut[0]["max_sets"]}
        out.commit(summary, len(plan))
    except BaseException:
        out.abort()
        raise
    _report(args, summary)
    return 0


def _count_task(part: Partition) -> int | None:
    return count_epochs(part)


def _log_sample_task(settings: dict, part: Partition, k: int) -> LogSample:
    """``locate``'s :func:`~robustloc.pipelines.locate.log_sample_of` on one partition
    file."""
    from robustloc.io import read_anchors
    from robustloc.pipelines.locate import LocateSettings, log_sample_of

    args = argparse.Namespace(**settings)
    with tempfile.TemporaryDirectory(prefix="robustloc-") as tmp:
        path = materialize(part, tmp)
        try:
            return log_sample_of(LocateSettings.from_namespace(args),
                                 read_anchors(args.anchors), path, k)
        except InputError as exc:
            if path != part.path:
                raise InputError(exc.message, part.path, exc.line) from None
            raise


def _log_scales(client: object, args: argparse.Namespace, settings: dict,
                plan: list[PartitionInfo]) -> dict:
    """``locate``'s first pass over the dataset, on the workers.

    The log's noise scale is the whole dataset's: the sample of its epochs that the
    single-process first pass takes (those whose ``epoch_hash`` is a multiple of the step
    ``k``, in the canonical order time, tag), fixed by the epoch count alone
    (``log_sample_step``).  So (1) each partition's epochs are counted quickly (runs of
    equal time and tag: exact for ``robustloc partition``'s files), (2) each worker
    samples its partitions with that ``k`` and returns its validated count, and (3) the
    client joins the samples and fits the scale.  Should a validated count differ from
    the quick one, step (2) runs again with the validated counts.  The result is the
    single-process one either way, whatever the partitions' order.
    """
    from robustloc.io import read_anchors
    from robustloc.pipelines.locate import (
        LocateSettings,
        LogSample,
        log_sample_step,
        log_scales_for,
    )

    locate_settings = LocateSettings.from_namespace(args)
    anchors = read_anchors(args.anchors)
    counts = gather_with_progress(client, submit_all(client, _count_task,
                                                     [(i.part,) for i in plan]), False)
    for _ in range(2):
        if any(c is None for c in counts):
            break
        k = log_sample_step(sum(counts))
        futs = submit_all(client, _log_sample_task, [(settings, i.part, k) for i in plan])
        res = gather_with_progress(client, futs, False)
        if all(r.n_epochs == c for r, c in zip(res, counts)):
            sample = LogSample.joined(res, len(anchors))
            if sample.kind is None:
                return {}
            return log_scales_for(locate_settings, anchors, [], sample=sample.values,
                                  kind=sample.kind)
        counts = [r.n_epochs for r in res]
    with tempfile.TemporaryDirectory(prefix="robustloc-") as tmp:  # pragma: no cover
        paths = [materialize(info.part, tmp) for info in plan]
        return log_scales_for(locate_settings, anchors, paths)


def _merged_hpl(parts: list[dict]) -> dict[str, dict]:
    """The dataset's ``hpl_quantiles`` from the partitions' ``hpl_tally`` (each method's
    :class:`~robustloc.pipelines.locate.HplTally`, removed from the partitions'
    summaries: it is no count to sum and no JSON)."""
    from robustloc.pipelines.locate import HplTally

    merged: dict[str, HplTally] = {}
    for part in parts:
        for m, t in (part.pop("hpl_tally", None) or {}).items():
            merged.setdefault(m, HplTally()).merge(t)
    return {m: t.quantiles() for m, t in merged.items()}


def _report(args: argparse.Namespace, summary: dict, skip: Iterable[str] = ()) -> None:
    """Print the run's summary: as JSON (``--json``), else its warnings and (unless
    ``--quiet``) its text.  ``skip``: keys the text leaves out (a tag-wise run's copies
    of its counts at the top level, printed from ``counts``).  ``locate`` and ``track``
    print the lines of the single-machine command
    (:func:`robustloc.pipelines.locate.locate_lines`,
    :func:`robustloc.pipelines.track.track_lines`) under a first line naming the
    partitions and workers."""
    if getattr(args, "json", False):
        print(json.dumps({k: v for k, v in summary.items() if k != "files"}, indent=2))
        return
    whole = summary
    from robustloc.pipelines.locate import WARNING_KEYS, anchor_warnings

    skip = set(skip) - set(WARNING_KEYS)
    summary = {k: v for k, v in summary.items() if k not in skip}
    if any(k in summary for k in WARNING_KEYS):
        for line in anchor_warnings(summary, getattr(args, "anchors", None)):
            print(f"warning: {line}", file=sys.stderr)  # as the command, even with --quiet
    if getattr(args, "quiet", False):  # no text summary, as the single-machine commands
        return
    where = (f"in {summary['partitions']} partitions -> {summary['out']} "
             f"({summary['seconds']:.2f} s on {summary['workers']} dask workers)")
    if whole.get("command") in ("locate", "track"):
        from robustloc.pipelines.locate import locate_lines
        from robustloc.pipelines.track import track_lines

        if whole["command"] == "track":  # the top-level keys are the command's summary
            print(f"{whole.get('epochs', 0)} epochs, {whole.get('tags', 0)} tags {where}")
            lines = track_lines(whole)
        else:
            print(f"{whole.get('epochs', 0)} epochs of {whole.get('value') or 'rows'} "
                  + where)
            lines = locate_lines(whole)
        for line in lines:
            print(line)
        return
    what = summary.get("value") or "rows"
    n = summary.get("epochs", summary.get("samples", summary.get("rows_out", 0)))
    print(f"{n} {'epochs of ' + what if 'epochs' in summary else 'rows'} in "
          f"{summary['partitions']} partitions -> {summary['out']} "
          f"({summary['seconds']:.2f} s on {summary['workers']} dask workers)")
    if summary.get("invalid_measurement_rows"):
        print(f"  invalid_measurement: {summary['invalid_measurement_rows']} rows (outside "
              "the physical limits of robustloc.io.limits; not used)")
    if summary.get("duplicates_merged"):
        print(f"  {summary['duplicates_merged']} duplicate rows (same epoch and anchor) "
              "averaged")
    from robustloc.pipelines.locate import status_text

    for k, v in summary.get("counts", {}).items():  # (filter's)
        print(f"  {k}: " + (status_text(v) if isinstance(v, dict) else f"{v}"))


def run_filter(args: argparse.Namespace, kernel: TagKernel,
               combine: Callable[[list[dict]], dict] | None = None) -> int:
    """``filter --engine dask``: ``kernel`` on every tag group of the dataset
    (``combine``: as :func:`run_tagwise`'s, the summary's non-additive keys)."""
    return run_tagwise(args, kernel, "filter", combine=combine)


def run_tagwise(args: argparse.Namespace, kernel: TagKernel, name: str,
                input_attr: str = "measurements",
                file_fn: Callable[[argparse.Namespace], dict] | None = None,
                local_keys: dict | None = None,
                combine: Callable[[list[dict]], dict] | None = None,
                prepare: Callable[[list[PartitionInfo]], dict] | None = None) -> int:
    """Apply ``kernel`` to each tag group of the dataset ``args.<input_attr>``.

    Parameters
    ----------
    args : argparse.Namespace
        The command's arguments (``anchors``, ``out``, ``scheduler``, ``workers``, ...).
    kernel : TagKernel
        A module-level function ``(measurements, anchors, args) -> (frame, counts)``:
        the command's single-process core on one tag group (every row of each of its
        tags, validated against the anchors; rows of a file in file order, files in time
        order).  ``counts`` values are summed over the groups, except ``counts["per_tag"]``
        (``{key: {tag: value}}``, e.g. ``track --range-offset``'s final offsets): the
        groups hold disjoint tags, so these are merged as one ``{tag: value}`` dict per key
        and go to the summary under ``key``, as in the single-process summary.
    name : str
        Command name for messages and the metadata.
    input_attr : str
        The attribute of ``args`` holding the input dataset.
    file_fn : callable, optional
        The command's per-file function (as ``locate_file``: ``args`` with
        ``<input_attr>`` and ``out`` set -> a summary of additive counts and
        ``rows_out``), used instead of ``kernel`` for a tag group of one file: it streams
        the file, so a worker's memory is bounded by the command's chunk and not by the
        partition.  Groups of several files (a tag's days in a ``tag=/date=`` tree, a
        dataset partitioned by time) go to ``kernel``, read whole.
    local_keys : dict, optional
        Further keys of the single-process summary (``track``: ``measurements``,
        ``track``), added at the top level of the summary.
    combine : callable, optional
        ``combine(counts_list) -> dict``: the single-process summary's keys that are not
        sums (``filter``: the share of down-weighted samples, the spread of raw minus
        filtered RSSI), from every group's counts before they are summed; it removes the
        private keys it used from each group's counts.
    prepare : callable, optional
        ``prepare(infos) -> dict``, called on the client once the partitions are planned
        (every planner check passed; ``infos`` in path order, empty files included): it
        may set ``args`` that every task then gets (``track``'s ``--link-offsets auto``,
        chosen once) and returns further keys of the summary.

    The summary (``--json``, ``_robustloc.json``) holds the Dask keys (``command``,
    ``engine``, ``input``, ``out``, ``partitions``, ``workers``, ``rows_out``,
    ``counts``, ``seconds``, ``files``) and the single-process summary's keys at the top
    level: the counts summed over the groups (``epochs``, ``tags``, ``status``,
    ``hpl_histogram``, ...), what every group shares (the kernels' ``counts["shared"]``:
    ``method``, ``anchors_not_used``, ...; a flag such as ``sorted_first`` is true if
    any group's is) and ``epochs_per_second``.
    """
    t0 = _time.perf_counter()
    parts = discover(getattr(args, input_attr), what="measurements dataset", absolute=True)
    out = DatasetOutput(args.out, input_paths(getattr(args, input_attr), parts,
                                              getattr(args, "anchors", None)))
    try:
        with dask_client(args.scheduler, args.workers) as client:
            infos = _plan_infos(client, parts, ("time", "tag", "anchor"), False)
            groups = plan_tagwise(infos)
            n_workers = len(client.scheduler_info()["workers"])
            biggest = max(len(g) for g in groups)
            if len(groups) < n_workers and biggest > 1:
                print(f"note: {name}: the tags' histories span partitions, giving only "
                      f"{len(groups)} task(s) for {n_workers} workers; partition the data "
                      "by tag first (robustloc partition INPUT -o DATASET --by tag)",
                      file=sys.stderr)
            _say(args, f"{name}: {len(groups)} tag groups on {n_workers} workers")
            if prepare is not None:  # (before the settings are handed to the tasks)
                local_keys = {**(local_keys or {}), **prepare(infos)}
            settings = _settings(args)
            futs = []
            for k, g in enumerate(groups):
                if file_fn is not None and len(g) == 1:
                    futs += submit_all(client, _file_task, [(file_fn, settings, input_attr,
                                                             g[0].part, out.part(k))])
                else:
                    futs += submit_all(client, _tag_task, [(kernel, settings,
                                                            [i.part for i in g], out.part(k))])
            counts_list = gather_with_progress(client, futs, _show(args))
        rows = [c.get("rows_out") for c in counts_list]
        hpl = _merged_hpl(counts_list)  # (track's: the groups' HplTally, merged)
        compiling = [float(c.pop("compile_seconds")) for c in counts_list
                     if "compile_seconds" in c]
        combined = combine(counts_list) if combine is not None else {}
        total: dict = {}
        per_tag: dict[str, dict] = {}
        shared: dict[str, object] = {}
        for c in counts_list:
            for key, values in c.pop("per_tag", {}).items():
                per_tag.setdefault(key, {}).update(values)
            for key, value in c.pop("shared", {}).items():
                if isinstance(value, bool):  # a flag of any group (sorted_first)
                    shared[key] = bool(shared.get(key, False)) or value
                else:  # one anchors file and one setting for every group: the same
                    shared.setdefault(key, value)
            _sum_counts(total, c)
        wall = _time.perf_counter() - t0
        summary = {
            "command": name, "engine": "dask", "input": str(getattr(args, input_attr)),
            "out": str(args.out), "partitions": len(groups), "workers": n_workers,
            "rows_out": total.pop("rows_out", 0), "counts": total,
            "seconds": round(wall, 3),
            "files": [{"inputs": [i.part.path for i in g], "output": Path(out.part(k)).name}
                      for k, g in enumerate(groups)],
            **{key: dict(sorted(v.items())) for key, v in per_tag.items()},
        }
        # the single-process summary's keys at the top level too (a script reading
        # summary["status"] works with either engine); "counts" stays as it was
        local = {**total, **shared, **(local_keys or {}), **combined}
        if hpl:
            local["hpl_quantiles"] = hpl
        if compiling:  # numba compiling kernels not cached, summed over the tasks
            local["compile_seconds"] = round(sum(compiling), 3)
        if "epochs" in total:
            local["epochs_per_second"] = round(total["epochs"] / max(wall, 1e-9), 1)
        top = [k for k in local if k not in summary]
        summary.update({k: local[k] for k in top})
        out.commit(summary, len(groups), rows)
    except BaseException:
        out.abort()
        raise
    _report(args, summary, skip=top)
    return 0


class _PerThreadStdout(io.TextIOBase):
    """``sys.stdout`` that a thread can redirect to its own buffer (a worker may run
    several tasks in threads; ``contextlib.redirect_stdout`` is process-wide)."""

    def __init__(self, real: object) -> None:
        self.real = real
        self.local = threading.local()

    def _target(self) -> object:
        buf = getattr(self.local, "buf", None)
        return self.real if buf is None else buf

    def write(self, s: str) -> int:
        return self._target().write(s)

    def flush(self) -> None:
        self._target().flush()

    def isatty(self) -> bool:
        return getattr(self.local, "buf", None) is None and self.real.isatty()


_STDOUT_LOCK = threading.Lock()


def _captured_stdout(fn: Callable[[], object]) -> str:
    """What ``fn()`` prints on stdout in this thread."""
    with _STDOUT_LOCK:
        if not isinstance(sys.stdout, _PerThreadStdout):
            sys.stdout = _PerThreadStdout(sys.stdout)
        proxy = sys.stdout
    proxy.local.buf = io.StringIO()
    try:
        fn()
        return proxy.local.buf.getvalue()
    finally:
        proxy.local.buf = None


def _spp_task(run: Callable[[argparse.Namespace], int], settings: dict, obs: str, out: str
              ) -> dict:
    """``spp``'s ``run`` on one observation file; its JSON summary."""
    from robustloc.io.atomic import parents_not_created

    ns = argparse.Namespace(**settings)
    ns.obs, ns.out, ns.json, ns.engine = obs, out, True, "local"
    with parents_not_created():
        return json.loads(_captured_stdout(lambda: run(ns)))


def run_spp(args: argparse.Namespace, run: Callable[[argparse.Namespace], int]) -> int:
    """``spp --engine dask``: ``spp``'s single-file ``run`` on every observation file.

    ``args.obs`` is a directory or a glob of RINEX observation files (one station-day
    each, typically); navigation and precise products are shared by all of them.  Each
    file is solved whole by one task (an epoch never splits, and the carrier smoothing
    runs over the file as it does in one process); output ``part-NNNNN.parquet`` per
    file, in the order of the file names.
    """
    t0 = _time.perf_counter()
    for f in [*args.nav, args.sp3, args.clk]:
        if f is not None and not Path(f).is_file():
            raise FileNotFoundError(2, "file not found", f)
    parts = discover(args.obs, parquet=False, what="observation files", absolute=True)
    out = DatasetOutput(args.out, input_paths(args.obs, parts, *args.nav, args.sp3, args.clk))
    try:
        with dask_client(args.scheduler, args.workers) as client:
            n_workers = len(client.scheduler_info()["workers"])
            _say(args, f"spp: {len(parts)} observation files on {n_workers} workers")
            settings = _settings(args)
            futs = submit_all(client, _spp_task, [(run, settings, p.path, out.part(i))
                                                  for i, p in enumerate(parts)])
            summaries = gather_with_progress(client, futs, _show(args))
        summary = {
            "command": "spp", "engine": "dask", "input": str(args.obs), "out": str(args.out),
            "partitions": len(parts), "workers": n_workers,
            "epochs": sum(int(s.get("epochs", 0)) for s in summaries),
            "solved": sum(int(s.get("solved", 0)) for s in summaries),
            "seconds": round(_time.perf_counter() - t0, 3),
            # a task's "out" is its part in the staging folder, gone once committed
            "files": [dict(s, out=str(Path(args.out) / Path(out.part(i)).name),
                           output=Path(out.part(i)).name) for i, s in enumerate(summaries)],
        }
        out.commit(summary, len(parts))
    except BaseException:
        out.abort()
        raise
    if args.json:
        print(json.dumps(summary, indent=2))
    else:
        print(f"{summary['solved']}/{summary['epochs']} epochs solved in {len(parts)} "
              f"observation files -> {args.out} ({summary['seconds']:.2f} s on {n_workers} "
              "dask workers)")
        for s in summaries:
            if "rms_h_m" in s:
                print(f"  {Path(s['obs']).name}: RMS horizontal {s['rms_h_m']:.2f} m, 3-D "
                      f"{s['rms_3d_m']:.2f} m vs {s['reference']}")
    return 0


_TRUTH_CACHE: dict[tuple[str, float], pd.DataFrame] = {}


def _truth(path: str) -> pd.DataFrame:
    """The truth file, read once per worker process."""
    from robustloc.io import read_truth

    key = (path, Path(path).stat().st_mtime)
    if key not in _TRUTH_CACHE:
        _TRUTH_CACHE.clear()
        _TRUTH_CACHE[key] = read_truth(path)
    return _TRUTH_CACHE[key]


def _errors_task(part: Partition, truth_path: str, tolerance_s: float) -> pd.DataFrame:
    """Per-row errors of one positions partition (the columns the statistics need, and
    ``time`` for the duplicate check across partitions)."""
    from robustloc.eval.metrics import epoch_errors
    from robustloc.io.tables import validate_positions

    raw = read_partition(part)
    if len(raw) == 0:
        return pd.DataFrame()
    pos = validate_positions(raw, part.path)
    e = epoch_errors(pos, _truth(truth_path), tolerance_s)
    cols = ["time", "tag", "method", "matched", "usable", "error_2d", "_truth_row"]
    cols += [c for c in ("error_3d", "error_v", "hpl", "vpl") if c in e.columns]
    return e[cols].reset_index(drop=True)


def _refuse_duplicates_across(frames: list[pd.DataFrame], paths: list[str],
                              dataset: object) -> None:
    """Two rows with the same ``(time, tag, method)`` count one epoch twice, in one
    partition (refused by the task) or in two: name both files."""
    e = pd.concat([f[["time", "tag", "method"]].assign(_part=k)
                   for k, f in enumerate(frames)], ignore_index=True)
    e["tag"] = e["tag"].astype(str)
    e["method"] = e["method"].astype(str)
    dup = e.duplicated(["time", "tag", "method"], keep=False).to_numpy()
    if dup.any():
        first = e[dup].iloc[0]
        where = sorted({paths[int(k)] for k in e.loc[
            dup & (e["time"] == first["time"]).to_numpy()
            & (e["tag"] == first["tag"]).to_numpy()
            & (e["method"] == first["method"]).to_numpy(), "_part"]})
        raise InputError(
            f"duplicate position for time {first['time']}, tag {first['tag']!r} and "
            f"method {first['method']!r} in {' and '.join(where)} (each epoch once per "
            "method)", dataset)


def evaluate_dataset(args: argparse.Namespace) -> pd.DataFrame:
    """``evaluate --engine dask``: the error table of a positions dataset.

    Each partition is matched to the truth on a worker; the per-row errors (about 20
    bytes a row) are concatenated in the dataset's order on the client, which computes
    the table exactly as the single-process ``evaluate`` does (pooled medians and 95th
    percentiles need every error).
    """
    from robustloc.eval.metrics import check_baseline, error_table_from_errors

    if args.time_tolerance < 0:
        raise ValueError(f"--time-tolerance must be >= 0, got {args.time_tolerance}")
    _truth(args.truth)  # a bad truth file fails here, before the cluster starts
    parts = discover(args.positions, what="positions dataset", absolute=True)
    with dask_client(args.scheduler, args.workers) as client:
        futs = submit_all(client, _errors_task, [(p, absolute_path(args.truth), args.time_tolerance)
                                                 for p in parts])
        frames = gather_with_progress(client, futs, _show(args))
    paths = [str(p.path) for p, f in zip(parts, frames) if len(f)]
    frames = [f for f in frames if len(f)]
    if not frames:
        raise InputError("every partition of this dataset is empty", args.positions)
    _refuse_duplicates_across(frames, paths, args.positions)
    e = pd.concat(frames, ignore_index=True)
    check_baseline(args.baseline, e["method"], args.positions)
    return error_table_from_errors(e, baseline=args.baseline, path=str(args.positions),
                                   truth=_truth(args.truth))
