"""``robustloc montecarlo``: Monte Carlo of gross-error detection and robust estimation."""

from __future__ import annotations

import argparse
import json
import sys
import warnings
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pandas as pd

from robustloc.commands._layout import file_defaults
from robustloc.errors import InputError
from robustloc.options import (
    finite_float,
    float_in,
    int_in,
    nonnegative_int,
)

#: Largest --trials: 1e9 trials of a 30-satellite snapshot take days, not memory.
MAX_TRIALS = 10**9

NAME = "montecarlo"
HELP = "Monte Carlo of fault detection (snooping, LEGE, robust IRLS) against B-method theory"
DESCRIPTION = """\
Injects 0, 1, 2, 3 ... gross errors of a chosen size into random observations of a ranging
layout or a simulated multi-constellation GNSS snapshot, runs iterative w-test data
snooping, LEGE and robust IRLS (Huber, Hampel, IGG, IGG3) on every trial, and reports per
method: flag rate (with 0 faults: the false-alarm rate), correct-identification rate
(rejected set == faulty set), unavailability and horizontal position error (mean, RMS,
95th percentile), beside the theory: global-test rejection probability of the drawn faults
(alpha of the B-method with 0 faults, 1 - beta0 for one fault of MDB size) and the w-test
power for single faults. Trials are vectorized: 10 000 trials take 0.1-4 s per method and
experiment, LEGE (which solves candidate subsets) 5-20 s; the example below about a
minute.  They run in chunks of 10 000 with accumulated results, so memory stays that of one
chunk for any --trials (at most 1e9); a progress bar on stderr counts the trials.  Runs of
up to 10 000 trials give the same numbers as before chunking; larger runs draw one random
stream per chunk (see robustloc.integrity.montecarlo), so they depend on --seed alone.

The model is linearized at the true position (exactly the model the B-method theory is
derived for); with --nonlinear (ranging and RSSI layouts) the observations themselves are
simulated and solved by Gauss-Newton, re-linearized after each exclusion, as `robustloc
locate --robust-scale apriori --sigma S` does (the trials are independent draws with a
known sigma; a scale learnt from the whole batch would be inflated by the faults).
IRLS rejects an observation whose relative weight (the weight function's value, 1 for a
clean one) is below --reject-weight.  LEGE keeps at least 4 residual degrees of freedom
(as `locate` runs it): on a layout of redundancy n - p <= 4 it searches no gross error and
equals ls, and with n - p - 4 < --lege-max-order it searches fewer; a `note:` says so.
Layout, one of:
  --anchors FILE [--position X,Y[,Z]] [--sigma S]   ranging (sigma in metres; default
                                                     position: centroid of the anchors;
                                                     --model and --sigma: the file's, as
                                                     in reliability, else range and 1)
  --anchors FILE --model rssi [--n N] [--sigma S]   RSSI, log-distance model (sigma and
                                                     --unit m sizes in dB)
  --gnss [--systems GEC] [--mask-deg 10] [--lat --lon --height] [--time-s T]
                                                     simulated GPS/Galileo/BeiDou snapshot
                                                     (robustloc.sim.gnss), code noise of
                                                     the seed-003 table / sin(elevation)
Fault sizes: --size in multiples of each observation's MDB (--unit mdb, default) or in
metres (--unit m); each fault gets a random sign.  An observation of redundancy number 0
has no finite MDB: --unit mdb is then refused (use --unit m).

Example:
  robustloc montecarlo --gnss --trials 10000 --faults 0,1,2 --size 1,3 --json"""


#: Largest fault size accepted (MDB multiples or metres): beyond it the simulated
#: observations overflow (1e300 gave an all-NaN table).
MAX_FAULT_SIZE = 1e6


def _numbers_within(limit: float, what: str) -> Callable[[str], list[float]]:
    """A parser of comma-separated finite numbers within ``+-limit`` (``what`` names
    them in the message)."""

    def parse(text: str) -> list[float]:
        # an empty item (1,,2 or 1,2,) is refused, not skipped: a slip that lost a
        # value ran with the others without a word (the commands review)
        try:
            out = [finite_float(v) for v in text.split(",")]
        except argparse.ArgumentTypeError:
            out = []
        if not out or any(abs(v) > limit for v in out):
            raise argparse.ArgumentTypeError(
                f"expected comma-separated {what} within +-{limit:g}, got {text!r}")
        return out

    return parse


_floats = _numbers_within(MAX_FAULT_SIZE, "numbers")

#: ``--lege-max-order``'s default, by which a value given is told from none.
LEGE_MAX_ORDER_DEFAULT = 3  # (robustloc.integrity.montecarlo.LEGE_MAX_ORDER; imported late)

#: Largest coordinate (m) of ``--position``: a site, not a continent (as ``reliability``'s
#: ``--area``; projected coordinates such as UTM's reach 1e7 m).
MAX_POSITION_M = 1e7
_position = _numbers_within(MAX_POSITION_M, "coordinates (m)")


def _ints(text: str) -> list[int]:
    try:  # (an empty item refused, as _numbers_within's)
        out = [nonnegative_int(v) for v in text.split(",")]
    except argparse.ArgumentTypeError:
        out = []
    if not out:
        msg = f"expected comma-separated whole numbers >= 0, got {text!r}"
        raise argparse.ArgumentTypeError(msg)
    if len(set(out)) != len(out):
        raise argparse.ArgumentTypeError(f"duplicate values in {text!r}")
    return out


def _check_table_out(out: str | None) -> None:
    """Refuse an ``-o`` name :func:`robustloc.io.write_table` would refuse only after the
    work (``.png``, ``.xlsx``, ``.json``; a ``.bz2`` compression), before it."""
    if out is not None:
        from robustloc.io.tables import check_table_path

        check_table_path(out)


def add_arguments(p: argparse.ArgumentParser) -> None:
    lay = p.add_mutually_exclusive_group(required=True)
    lay.add_argument("--anchors", help="ranging layout: anchors file (anchor, x, y[, z])")
    lay.add_argument("--gnss", action="store_true", help="simulated GNSS snapshot layout")
    p.add_argument("--position", type=_position, default=None, metavar="X,Y[,Z]",
                   help="true tag position for --anchors (default: anchors' centroid)")
    p.add_argument("--dim", type=int, choices=(2, 3), default=None,
                   help="solved dimension for --anchors (default 2; z = known height offsets)")
    p.add_argument("--tag-z", "--tag-height", dest="tag_z", type=float_in(-1e5, 1e5),
                   default=None, metavar="M",
                   help="tag height in metres for --dim 2 (default 0); --tag-z and "
                        "--tag-height (the name locate, calibrate, track and fuse use) are "
                        "the same option")
    p.add_argument("--sigma", type=float_in(1e-6, 1e6), default=None,
                   help="observation standard deviation for --anchors: m for ranges, dB for "
                        "RSSI (default: the anchors file's sigma column in that unit, else 1)")
    p.add_argument("--model", choices=("range", "rssi"), default=None,
                   help="observation type for --anchors (default rssi when the file has a "
                        "path-loss model and no range calibration, else range)")
    p.add_argument("--n", type=float_in(0.1, 10.0), default=None,
                   help="path-loss exponent for --model rssi (default: anchors' n column, "
                        "else 2)")
    p.add_argument("--systems", default=None, help="GNSS systems among G, E, C (default GEC)")
    p.add_argument("--mask-deg", type=float_in(0.0, 90.0), default=None,
                   help="GNSS elevation mask (deg, 0 .. 90; default 10)")
    p.add_argument("--lat", type=float_in(-90.0, 90.0), default=None,
                   help="GNSS receiver latitude (deg; default 30.53)")
    p.add_argument("--lon", type=float_in(-180.0, 360.0), default=None,
                   help="GNSS receiver longitude (deg; default 114.36)")
    p.add_argument("--height", type=float_in(-1e3, 1e5), default=None,
                   help="GNSS receiver height (m; default 30)")
    p.add_argument("--time-s", type=float_in(-1e12, 1e12), default=None,
                   help="GNSS snapshot time (s; default 0)")
    p.add_argument("--trials", type=int_in(1, MAX_TRIALS), default=10_000,
                   help="trials per experiment (10000; run in chunks of 10000)")
    p.add_argument("--faults", type=_ints, default=[0, 1, 2], metavar="K[,K...]",
                   help="numbers of gross errors per trial (default 0,1,2)")
    p.add_argument("--size", type=_floats, default=[1.0, 3.0], metavar="S[,S...]",
                   help="fault sizes (default 1,3)")
    p.add_argument("--unit", choices=("mdb", "m"), default="mdb",
                   help="unit of --size: multiples of the MDB (default; refused when an "
                        "observation has redundancy number 0) or metres")
    p.add_argument("--methods", default="ls,snooping,lege,huber,igg3",
                   help="comma-separated among ls, snooping, raim-single (linearized "
                        "model only), lege, huber, hampel, igg, igg3 "
                        "(default ls,snooping,lege,huber,igg3)")
    p.add_argument("--alpha0", type=float_in(1e-15, 0.5), default=0.001,
                   help="w-test significance (0.001)")
    p.add_argument("--beta0", type=float_in(1e-15, 0.5), default=0.10,
                   help="B-method type II error (0.10)")
    p.add_argument("--alpha", type=float_in(1e-15, 0.5), default=None,
                   help="fixed global-test significance (default: B-method for each dof; "
                        "raim-single always tests at 0.001, RTKLIB's, and its "
                        "theory_global is at that)")
    p.add_argument("--reject-weight", type=float_in(0.0, 1.0), default=0.1,
                   help="IRLS: relative weight (1 = clean) below which an observation "
                        "counts as rejected (0.1)")
    p.add_argument("--lege-max-order", type=int_in(1, 6), default=LEGE_MAX_ORDER_DEFAULT,
                   help="largest number of gross errors LEGE searches (default 3; at most "
                        "n - p - 4, see above; linearized model and --methods lege only, "
                        "refused otherwise)")
    p.add_argument("--nonlinear", action="store_true",
                   help="--anchors only: simulate the observations and solve them by "
                        "Gauss-Newton (robustloc locate's solvers, with the a-priori --sigma "
                        "as the noise scale) instead of the linearized model")
    p.add_argument("--seed", type=nonnegative_int, default=1, help="random seed (default 1)")
    p.add_argument("-o", "--out", default=None, help="write the table as CSV here")
    p.add_argument("--json", action="store_true", help="print the table as JSON")
    p.add_argument("-q", "--quiet", action="store_true",
                   help="no progress bar (the table is still printed)")


#: Options of one layout only, with their defaults (None on the parser, so that an option
#: given with the other layout is told from its default: it was silently ignored).
_RANGING_OPTIONS = {"position": None, "dim": 2, "tag_z": 0.0, "sigma": None, "model": None,
                    "n": None}  # (sigma and model: the anchors file's, else 1 and range)
_GNSS_OPTIONS = {"systems": "GEC", "mask_deg": 10.0, "lat": 30.53, "lon": 114.36,
                 "height": 30.0, "time_s": 0.0}


def _layout_options(args: argparse.Namespace) -> None:
    """Refuse the options of the layout not chosen, then fill in the defaults."""
    mine, other, layout = ((_GNSS_OPTIONS, _RANGING_OPTIONS, "--anchors") if args.gnss
                           else (_RANGING_OPTIONS, _GNSS_OPTIONS, "--gnss"))
    spelled = {"tag_z": "--tag-z/--tag-height"}  # (one option, two names)
    given = [spelled.get(k, "--" + k.replace("_", "-")) for k in other
             if getattr(args, k) is not None]
    if given:
        verb = "applies" if len(given) == 1 else "apply"
        raise InputError(f"{', '.join(given)} {verb} to {layout} layouts only")
    if not args.gnss and args.dim == 3 and args.tag_z is not None:
        # (it was ignored: the same table as without it -- the montecarlo review)
        raise InputError("--tag-z/--tag-height applies to --dim 2 (with --dim 3 the tag's "
                         "z is the third coordinate of --position)")
    for k, default in mine.items():
        if getattr(args, k) is None:
            setattr(args, k, default)


def build_layout(args: argparse.Namespace):  # noqa: ANN201
    """The :class:`~robustloc.integrity.montecarlo.Layout` chosen on the command line."""
    from robustloc.integrity.montecarlo import gnss_layout, ranging_layout, rssi_layout

    if args.gnss:
        from robustloc.options import check_systems

        lay = gnss_layout(args.time_s, args.lat, args.lon, args.height,
                          check_systems(args.systems, "GEC"), args.mask_deg)
        if lay.n <= lay.p:
            raise InputError(f"only {lay.n} satellites visible for {lay.p} unknowns")
        return lay
    from robustloc.io import read_anchors

    df = read_anchors(args.anchors)
    path_loss, note = file_defaults(df, args)  # --model, --sigma left out: the file's
    if note is not None:
        print(f"note: {note}", file=sys.stderr)
    has_z = "z" in df.columns
    if args.dim == 3 and not has_z:
        raise InputError("--dim 3 needs a z column", args.anchors)
    if has_z and not np.all(np.isfinite(df["z"].to_numpy(float))):
        raise InputError("anchor heights (z) must all be given when the column exists",
                         args.anchors)
    xy = df[["x", "y"] + (["z"] if args.dim == 3 else [])].to_numpy(float)
    hoff = (df["z"].to_numpy(float) - args.tag_z) if (has_z and args.dim == 2) else None
    pos = np.asarray(args.position if args.position is not None else xy.mean(axis=0), float)
    if pos.size != args.dim:
        raise InputError(f"--position needs {args.dim} coordinates, got {pos.size}")
    # the tag on an anchor: that range's direction is 0/0 (the model's design row came
    # out [0, 0], a range that carries nothing with a redundancy number of 1 and the
    # smallest MDB: a table of a meaningless model, exit 0 -- the montecarlo review)
    rng_m = np.sqrt(np.sum((xy - pos[None]) ** 2, axis=1)
                    + (0.0 if hoff is None else hoff**2))
    on = np.flatnonzero(rng_m <= 1e-9 * max(1.0, float(np.max(np.abs(xy)))))
    if on.size:
        raise InputError(f"--position {tuple(float(v) for v in pos)} is on anchor "
                         f"{df['anchor'].iloc[on[0]]!s}: its range has no direction (move "
                         "the tag off the anchor)", args.anchors)
    sig = np.asarray(args.sigma, dtype=float)
    if not (np.all(np.isfinite(sig)) and np.all(sig > 0)):
        raise InputError(f"--sigma must be positive, got {args.sigma}")
    ids = [str(a) for a in df["anchor"]]
    if args.model == "rssi":
        if args.n is not None:
            n_exp = np.full(len(ids), float(args.n))
        elif path_loss is not None:  # n, or gamma (attenuation factor), or 2 (friis)
            n_exp = np.broadcast_to(np.asarray(path_loss.log_distance_params()[1], float),
                                    (len(ids),)).copy()
        elif "n" in df.columns and np.all(np.isfinite(df["n"].to_numpy(float))):
            n_exp = df["n"].to_numpy(float)
        else:
            n_exp = np.full(len(ids), 2.0)
        if np.any(n_exp <= 0):
            raise InputError("path-loss exponent n must be positive", args.anchors)
        lay = rssi_layout(xy, pos, args.sigma, n_exp, ids, hoff,
                          name=Path(args.anchors).stem + " (RSSI)")
    else:
        lay = ranging_layout(xy, pos, args.sigma, ids, hoff, name=Path(args.anchors).stem)
    if lay.n <= lay.p:
        raise InputError(f"{lay.n} anchors for {lay.p} unknowns: no redundancy", args.anchors)
    Hw = lay.H / lay.sigma[:, None]
    finite = bool(np.all(np.isfinite(Hw)))  # (a tag on an anchor: a 0/0 direction)
    sv = np.linalg.svd(Hw, compute_uv=False) if finite else np.zeros(1)
    if not (finite and sv[-1] > 1e-9 * sv[0]):
        # collinear (coplanar in 3-D) anchors fix no position: every row was NaN, exit 0
        at = tuple(round(float(v), 3) for v in pos)
        raise InputError(f"the anchors fix no position at {at} (they lie on one "
                         f"{'line' if args.dim == 2 else 'plane'}, or the tag "
                         "sits on an anchor): the geometry is singular", args.anchors)
    return lay


def run(args: argparse.Namespace) -> int:
    from tqdm import tqdm

    from robustloc.integrity.montecarlo import (
        METHODS,
        MonteCarloNote,
        check_fault_unit,
        lege_note,
        run_montecarlo,
    )
    from robustloc.io.atomic import check_not_input, writes_to_stdout

    # before any work: -o naming the anchors file replaced it with the table (exit 0)
    check_not_input(args.out, [getattr(args, "anchors", None)])
    # and its format: `-o mc.png` was refused after the whole simulation
    _check_table_out(args.out)
    methods = tuple(m.strip().lower() for m in args.methods.split(","))
    if "" in methods:  # (ls,,huber: an empty item, as --size's, is no method)
        raise InputError(f"--methods: an empty item in {args.methods!r}; give the "
                         f"methods separated by single commas, among {', '.join(METHODS)}")
    bad = [m for m in methods if m not in METHODS]
    if bad or not methods:
        raise InputError(f"--methods: unknown or no method(s) {', '.join(bad)!r}; choose "
                         f"among {', '.join(METHODS)}")
    if len(set(methods)) != len(methods):
        raise InputError(f"--methods: a method is listed twice in {args.methods!r}")
    if args.nonlinear and "raim-single" in methods:
        raise InputError("--methods raim-single is available on the linearized model only "
                         "(without --nonlinear)")
    _layout_options(args)
    if args.nonlinear and args.gnss:
        raise InputError("--nonlinear applies to --anchors layouts only")
    if args.nonlinear and args.alpha is not None:
        raise InputError("--alpha (fixed) is not available with --nonlinear")
    if args.lege_max_order != LEGE_MAX_ORDER_DEFAULT:  # (taken and ignored before)
        if args.nonlinear:
            raise InputError("--lege-max-order applies to the linearized model only: "
                             "--nonlinear runs locate's LEGE, which searches as many "
                             "gross errors as the redundancy allows")
        if "lege" not in methods:
            raise InputError("--lege-max-order applies to --methods lege, which "
                             f"{args.methods!r} does not list")
    lay = build_layout(args)
    if any(k < 0 or k > lay.n - lay.p for k in args.faults):
        raise InputError(f"--faults must be within 0..{lay.n - lay.p} (the redundancy)")
    if any(not np.isfinite(s) or s <= 0 for s in args.size):
        raise InputError("--size values must be positive")
    # before any work: --unit mdb on an observation of redundancy number 0 (infinite faults)
    check_fault_unit(lay, max(args.faults), args.unit, args.alpha0, args.beta0)
    notes = [n for n in [lege_note(lay, args.lege_max_order, args.nonlinear)]
             if n and "lege" in methods]
    for note in notes:  # before a possibly long run, and never silent
        print(f"note: {note}", file=sys.stderr)
    runs = [(0, 0.0)] if 0 in args.faults else []
    runs += [(k, s) for k in args.faults if k > 0 for s in args.size]
    frames = []
    with tqdm(total=len(runs) * args.trials, desc="montecarlo", unit="trial",
              unit_scale=True, file=sys.stderr,
              disable=args.quiet or not sys.stderr.isatty()) as bar, \
            warnings.catch_warnings():
        warnings.simplefilter("ignore", MonteCarloNote)  # printed once above as `note:`
        for i, (k, s) in enumerate(runs):
            frames.append(run_montecarlo(
                lay, n_faults=k, size=s, unit=args.unit, trials=args.trials,
                methods=methods, alpha=args.alpha, alpha0=args.alpha0, beta0=args.beta0,
                reject_weight=args.reject_weight,
                lege_max_order=None if args.nonlinear else args.lege_max_order,
                seed=args.seed + i, nonlinear=args.nonlinear, progress=bar.update,
            ))
    table = pd.concat(frames, ignore_index=True)
    table.insert(0, "layout", lay.name)
    if args.out:
        from robustloc.io import write_table

        write_table(table, args.out)  # atomic: all or nothing at -o
    # the summary never goes into a data stream: stderr when the table goes to stdout
    dest = sys.stderr if args.out and writes_to_stdout(args.out) else sys.stdout
    if args.json:
        print(json.dumps({
            "layout": lay.name, "n_obs": lay.n, "n_unknowns": lay.p, "notes": notes,
            "rows": json.loads(table.to_json(orient="records")),
        }, indent=2), file=dest)
    else:
        print(f"layout {lay.name}: {lay.n} observations, {lay.p} unknowns, "
              f"{args.trials} trials per row", file=dest)
        cols = ["n_faults", "size", "method", "flag_rate", "theory_global", "theory_w",
                "identified", "unavailable", "err_mean_m", "err_rms_m", "err_p95_m", "seconds"]
        print(table[cols].to_string(index=False, float_format=lambda v: f"{v:.4f}"),
              file=dest)
        if dest is not sys.stderr:  # (on stderr they were printed above)
            for note in notes:
                print(f"note: {note}", file=dest)
    return 0
