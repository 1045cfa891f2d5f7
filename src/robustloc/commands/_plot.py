"""``--plot FILE`` of ``locate`` and ``track``: the figure of the output just written
(:func:`robustloc.eval.plots.positions_figure`; no truth needed)."""

from __future__ import annotations

import argparse


def add_plot_argument(p: argparse.ArgumentParser, what: str) -> None:
    """The ``--plot FILE`` option; ``what``: the rows the command writes."""
    from robustloc.options import figure_path

    p.add_argument("--plot", type=figure_path, metavar="FILE",
                   help=f"also draw the anchors and the {what} on a map, the count of each "
                        "status and the hpl distribution into FILE (.png, .svg or .pdf; "
                        "read back from -o FILE; --engine local)")


def check_plot(args: argparse.Namespace, what: str) -> None:
    """``--plot``'s refusals, before any work (it reads the output back from ``-o FILE``)."""
    if getattr(args, "plot", None) is None:
        return
    from robustloc.errors import InputError
    from robustloc.io.atomic import check_not_input, written_in_place

    if args.engine == "dask":
        raise InputError("--plot draws from the one output file: use it with --engine local "
                         "(the default)")
    if written_in_place(args.out):
        raise InputError(f"--plot reads the {what} back from -o FILE: give a regular file, "
                         f"not - or a device ({args.out})")
    from pathlib import Path

    if Path(args.plot).resolve() == Path(args.out).resolve():
        raise InputError(f"--plot and -o name the same file ({args.plot}): the figure would "
                         "replace the rows")
    check_not_input(args.plot, [args.measurements, args.anchors])


def draw_plot(args: argparse.Namespace) -> None:
    """Draw ``--plot`` from the output file; says where unless ``--quiet`` or ``--json``."""
    if getattr(args, "plot", None) is None:
        return
    from robustloc.errors import OutputError
    from robustloc.eval.plots import positions_figure, read_positions_for_plot
    from robustloc.io import read_anchors

    try:
        positions_figure(read_positions_for_plot(args.out), read_anchors(args.anchors),
                         args.plot, title=f"{args.measurements}: anchors and usable fixes")
    except OutputError as exc:  # -o is complete: say so (the user may think nothing was)
        raise OutputError(f"{exc.message} (the rows are written to {args.out}; only the "
                          "figure is missing)", exc.path, errno_=exc.errno) from None
    if not args.quiet and not args.json:
        print(f"figure: {args.plot}")
