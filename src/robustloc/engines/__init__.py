"""Engines that run robustloc's commands beyond one process (layer service/engines).

An engine never re-implements a method: it splits the input into partitions, applies the
command's own single-process function to each partition on a worker, and collects the
per-partition outputs into a partitioned Parquet dataset.

* :mod:`robustloc.engines.dataset` -- Parquet datasets (a directory, a glob, or a
  hive-partitioned tree): discovery, reading a partition with its hive keys, and the
  partitioning rules (an epoch never split; a tag's history in one task).
* :mod:`robustloc.engines.cluster` -- a dask.distributed client on ``--scheduler ADDRESS``
  or on a LocalCluster sized to the machine, always closed at the end.
* :mod:`robustloc.engines.dask` -- ``run_locate``, ``run_filter``, ``run_spp``,
  ``run_evaluate`` and the generic ``run_tagwise`` (a function applied to each tag
  partition), which the command modules dispatch to on ``--engine dask``.

The commands only call :func:`add_engine_arguments` in their ``add_arguments`` and dispatch
early in ``run``; dask is imported only when ``--engine dask`` is chosen (it is the optional
extra ``robustloc[dask]``).
"""

from __future__ import annotations

import argparse

from robustloc.options import local_workers

ENGINES = ("local", "dask")


def add_engine_arguments(p: argparse.ArgumentParser, *, what: str = "a Parquet dataset",
                         output: str = "a partitioned Parquet dataset (directory)") -> None:
    """Add ``--engine``, ``--scheduler``, ``--workers`` (and ``--quiet`` if absent) to ``p``.

    Parameters
    ----------
    p : argparse.ArgumentParser
        A command's parser.
    what : str
        What the command's input is under ``--engine dask`` (for the help text).
    output : str
        What it writes then (for the help text).
    """
    g = p.add_argument_group("distributed engine (needs robustloc[dask])")
    g.add_argument(
        "--engine", choices=ENGINES, default="local",
        help=f"local: this process (default); dask: every partition of {what} on a "
             f"dask.distributed cluster, output {output}",
    )
    g.add_argument(
        "--scheduler", default=None, metavar="ADDRESS",
        help="--engine dask: address of a running dask scheduler (e.g. tcp://head:8786); "
             "default: start a LocalCluster on this machine and close it at the end",
    )
    g.add_argument(
        "--workers", type=local_workers, default=None, metavar="N",
        help="--engine dask without --scheduler: LocalCluster worker processes (default: "
             "the CPU cores available; one thread each)",
    )
    if "--quiet" not in p._option_string_actions:  # locate already has it
        # -q too, as every command that has --quiet (spp, calibrate ... took only the
        # long form)
        names = ["--quiet"] if "-q" in p._option_string_actions else ["-q", "--quiet"]
        g.add_argument(*names, action="store_true", help="no progress bar")



