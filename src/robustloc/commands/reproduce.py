"""``robustloc reproduce``: regenerate every table and figure of the four papers."""

from __future__ import annotations

import argparse
from pathlib import Path

from robustloc.options import nonnegative_int
from robustloc.paths import default_data_help

NAME = "reproduce"
HELP = "reproduce every paper's experiment (simulation and real data) into a report"
DESCRIPTION = """\
Runs each paper's experiment on simulation built to the paper's setup and on the real
public data, prints the tables beside the published numbers, and writes report.md,
report.html, summary.json, CSV tables and PNG figures into --out.  The report is written
whole or not at all: a run that fails or is interrupted leaves --out as it was (absent,
or the previous report, which a complete run replaces whole); a folder that is not a
robustloc report is refused.  --only without -o refuses to replace the default folder
`report` when it holds other sections (a rerun of one section would drop the rest): give
-o a new folder, or -o report to replace it.

Real data: --data DIR; without it, ../shared/data from the working folder if it exists,
else the shared/data folder beside the source checkout robustloc runs from (see --data)
if it exists, else the small excerpts shipped in the package, and the report says so (a
data set missing from DIR is taken from its excerpt, with a note on stderr)."""


#: The report folder when -o is not given.
DEFAULT_OUT = "report"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("-o", "--out", default=None,
                   help=f"output folder (default: {DEFAULT_OUT})")
    p.add_argument("--data", default=None,
                   help=f"real-data folder (default: {default_data_help()})")
    p.add_argument("--seed", type=nonnegative_int, default=1,
                   help="seed for every simulation (default 1)")
    p.add_argument("--quick", action="store_true", help="fewer trials, for a fast smoke run")
    p.add_argument(
        "--only", action="append", default=None, metavar="SECTION",
        help="run only this section (repeatable); see --list",
    )
    p.add_argument("--list", action="store_true", help="list the report sections and exit")


def run(args: argparse.Namespace) -> int:
    from robustloc.errors import InputError
    from robustloc.paths import resolve_data_dir
    from robustloc.reproduce import Context, run_all, section_modules

    if args.list:
        for m in section_modules():
            print(f"{m.KEY:24s} {m.TITLE}")
        return 0
    from robustloc._jitnotice import compile_notice

    try:  # a mistyped --only is the user's mistake, found before any work
        section_modules(args.only)
    except ValueError as exc:
        raise InputError(f"argument --only: {exc}") from None
    from robustloc.reproduce._output import check_out, check_out_text, report_sections

    # the output checked before any work: an empty -o (``Path("")`` is the working
    # folder), a file, or a folder that is not a robustloc report (it is never replaced)
    given = args.out is not None
    if not given:
        args.out = DEFAULT_OUT
    check_out_text(args.out)
    check_out(Path(args.out))
    if args.only and not given:
        # the report's own advice ("Rerun: robustloc reproduce --only s60_tracks") replaced
        # a whole report by one section, 13 minutes of results gone (the reproduce review)
        keep = {m.KEY for m in section_modules(args.only)}
        other = sorted(set(report_sections(Path(args.out))) - keep)
        if other:
            raise InputError(
                f"holds the report of {', '.join(other)} as well, which --only would drop "
                "(a report folder is replaced whole): give -o a new folder, or -o "
                f"{args.out} to replace it", Path(args.out))
    compile_notice("positioning", "filter")
    data_dir = resolve_data_dir(args.data)
    ctx = Context(out_dir=Path(args.out), data_dir=data_dir, seed=args.seed, quick=args.quick)
    if data_dir is None:
        ctx.log("note: no --data and no ../shared/data (from the working folder or beside "
                "the source checkout); real-data sections use the shipped excerpts")
    else:
        ctx.log(f"real data: {data_dir}")
    run_all(ctx, args.only)
    ctx.log(f"report written to {ctx.out_dir / 'report.html'} and {ctx.out_dir / 'report.md'}")
    return 0
