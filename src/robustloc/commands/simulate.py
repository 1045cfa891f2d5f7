"""``robustloc simulate SCENARIO --seed N --out DIR``: write a scenario's contract files."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from robustloc.options import nonnegative_int

NAME = "simulate"
HELP = "simulate a scenario (ble-corridor, ...) into anchors/measurements/truth/survey files"
DESCRIPTION = """\
Writes the files of a simulated experiment (anchors.csv, measurements.csv, truth.csv and
survey.csv where calibration applies) into --out, in the same formats as real logs, so
that calibrate, locate and evaluate run on them unchanged.  gnss writes pseudoranges.csv
and truth.csv instead, which no command reads (spp takes RINEX): how to use them from
Python is at the end of robustloc simulate gnss --help.

  robustloc simulate --list
  robustloc simulate ble-corridor --seed 1 --out corridor
  robustloc simulate ble-corridor --seed 1 --out corridor-walk --disturbance

Every scenario documents its assumed numbers: robustloc simulate SCENARIO --help.

Long runs show a progress bar on stderr when it is a terminal (-q: none).  A scenario whose
output grows with an option streams it to disk in chunks (gnss --epochs: memory stays
bounded); one whose draws are whole arrays (wifi-room --samples-per-point, --walk-epochs)
refuses, before any work, a run whose memory would exceed 1 GiB, naming the option and
its largest value (exit code 2).  Epochs a run cannot use are counted in a `warning:`
(gnss: too few satellites for a fix, fewer satellites than --faults); a run with no
usable epoch at all is refused."""


def _common(p: argparse.ArgumentParser) -> None:
    p.add_argument("--seed", type=nonnegative_int, default=1, help="random seed (default 1)")
    p.add_argument("-o", "--out", required=True, help="output folder (created if missing)")
    p.add_argument("--json", action="store_true", help="print the written files as JSON")
    p.add_argument("-q", "--quiet", action="store_true",
                   help="no progress bar (the files written are still listed; warnings stay)")


def add_arguments(p: argparse.ArgumentParser) -> None:
    from robustloc.sim import scenario_modules

    p.add_argument("--list", action="store_true", help="list the scenarios and exit")
    sub = p.add_subparsers(dest="scenario", metavar="SCENARIO")
    from robustloc._rst import rst_to_text

    for name, mod in scenario_modules().items():
        # the module docstring is reStructuredText for Sphinx: plain text on a terminal
        doc = rst_to_text((mod.__doc__ or mod.HELP).strip())
        usage = getattr(mod, "USAGE", None)  # what to do with the files, after the options
        sp = sub.add_parser(
            name, help=mod.HELP, description=doc,
            epilog=None if usage is None else rst_to_text(usage),
            formatter_class=argparse.RawDescriptionHelpFormatter,
        )
        _common(sp)
        mod.add_arguments(sp)


def run(args: argparse.Namespace) -> int:
    from robustloc.sim import scenario_modules

    mods = scenario_modules()
    if args.list or not getattr(args, "scenario", None):
        if not args.list:
            print("error: give a SCENARIO (see --list)", file=sys.stderr)
        for name, mod in mods.items():
            print(f"{name:16s} {mod.HELP}")
        return 0 if args.list else 2
    refuse = getattr(mods[args.scenario], "refuse_idle_options", None)
    if refuse is not None:  # an option the others make idle: refused before any work
        refuse(args)
    from robustloc.commands._folder import write_folder

    out = Path(args.out)

    def write(folder: Path) -> dict[str, Path]:
        files = mods[args.scenario].simulate(folder, args.seed, args)
        return {k: out / Path(v).name for k, v in files.items()}

    # whole or not at all; reads no file.  The files of every scenario: one an earlier run
    # left (another scenario's survey, blocked.csv of --disturbance) is named
    # (the name as given: Path("") is ".", so the blank name is refused before Path)
    files = write_folder(args.out, write, inputs=(),
                         owns=("anchors.csv", "measurements.csv", "survey.csv", "truth.csv",
                               "blocked.csv", "pseudoranges.csv", "gps.nmea", "origin.txt"))
    if args.json:
        print(json.dumps({k: str(v) for k, v in files.items()}, indent=2))
    else:
        for k, v in files.items():
            print(f"{k:14s} {v}")
    note = getattr(mods[args.scenario], "FILES_NOTE", None)  # (gnss: no command reads them)
    if note is not None and not args.quiet:
        print(f"note: {note}", file=sys.stderr)
    return 0
