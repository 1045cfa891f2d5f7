"""``robustloc reliability``: anchor-layout planner (reliability maps over a grid, seed 003)."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from robustloc._arrays import to_number
from robustloc.commands._layout import UNITS, file_defaults, sigma_text
from robustloc.errors import InputError
from robustloc.options import finite_float, float_in, positive_float

if TYPE_CHECKING:
    import pandas as pd

NAME = "reliability"
HELP = "anchor-layout planner: DOP, CRLB, MDB, external reliability, w-test correlation maps"
DESCRIPTION = """\
Linearizes the range (or RSSI) model at every point of a grid of tag positions and writes,
per point: DOP, the Cramer-Rao bound of the position RMSE, the largest minimal detectable
bias (MDB) over the anchors heard, the largest horizontal position error an undetected MDB
causes (external reliability), the largest correlation |rho_ij| of two w-tests (near 1: a
fault cannot be attributed to one anchor), the smallest redundancy number r_i and the total
redundancy. Output: DIR/reliability.csv and one heat-map PNG per figure with the anchors
drawn, plus a summary on stdout (--json for machine-readable).

Use it to decide where one more beacon goes: add it to the anchors file and compare maps,
or let --suggest rank candidate positions (default: 8 per side of the area's border, where
anchors are mounted; or --candidates FILE with columns x, y[, z]) by the 95th percentile
over the area of --suggest-metric (default max_ext_m: the largest position error an
undetected fault can cause) with that one anchor added; the best three are starred on the
maps and all are written to DIR/suggestions.csv.

A point has a fix where `locate` gives one: dim + 1 anchors heard and, in 2-D, not all of
them on one line (there every fix fits its mirror image across the line as well: locate
marks it ill_conditioned); elsewhere every figure is blank (NaN), counted as a point without
a fix. A layout with no fix anywhere (one or two anchors, all anchors on one line, a
--max-range that hears too few) is refused (exit 2), unless --suggest finds one more anchor
that gives fixes: then a warning says the maps are empty and the ranking is printed.

Anchors file: contract format `anchor, x, y[, z]` (CSV or Parquet). In 2-D, anchor heights
(z) are known offsets from the tag height --tag-z (--tag-height). For --model rssi the
path-loss exponent is --n, or the anchors' exponents (`n`; `gamma` of the
attenuation-factor model) when present. On a terminal a progress bar on stderr counts the
grid points (--suggest: one grid per candidate); -q hides it.

What the anchors file says sets what is left out: --model is rssi when it has path-loss
columns (A, n; p0, gamma; p0, as `calibrate` writes them) and no range calibration (bias,
scale), else range; --sigma is its per-anchor `sigma` column (calibrate's residual
standard deviation, dB or m) when that column is in the model's unit, else 1.  A `note:`
on stderr says what was taken from the file.  max_mdb is in the observation's unit: dB for
rssi, m for range.

The summary's median, min and max of each figure are over the points with a fix.  An
observation no other controls (redundancy number 0) has an infinite MDB and external
reliability: inf stays in the summary (--json: null, the figure's "infinite" lists which
of median, min, max it is), and such points are counted (points with an undetectable
observation).

Example:
  robustloc reliability --anchors anchors.csv --area 0,40,0,3 --step 0.25 --sigma 1 -o rel/"""


#: Largest coordinate (m) of the area, the anchors and the candidates a plan is drawn
#: for: a site, not a continent (10 000 km; larger values were typos or units).
MAX_COORDINATE_M = 1e7

def _area(text: str) -> tuple[float, float, float, float]:
    try:
        vals = tuple(finite_float(v) for v in text.split(","))
    except argparse.ArgumentTypeError:
        raise argparse.ArgumentTypeError(
            f"--area expects xmin,xmax,ymin,ymax (finite numbers), got {text!r}"
        ) from None
    if len(vals) != 4:
        raise argparse.ArgumentTypeError(f"--area expects 4 numbers, got {text!r}")
    if max(abs(v) for v in vals) > MAX_COORDINATE_M:
        raise argparse.ArgumentTypeError(f"--area: coordinates beyond {MAX_COORDINATE_M:g} m, "
                                         f"got {text!r}")
    if not (vals[0] < vals[1] and vals[2] < vals[3]):
        raise argparse.ArgumentTypeError(f"--area needs xmin < xmax and ymin < ymax, "
                                         f"got {text!r}")
    return vals  # type: ignore[return-value]


#: Format of the grid's and the suggestions' coordinates (12 significant digits: 0.01 mm
#: at 1e7 m); the figures keep 6.
COORDINATE_FORMAT = "{:.12g}"


def _coordinates_exact(frame: pd.DataFrame) -> pd.DataFrame:
    """``frame`` with its coordinate columns ``x, y[, z]`` as text of
    :data:`COORDINATE_FORMAT`: with the figures' 6 significant digits, projected
    coordinates (UTM: 4 498 765.432 m) were written as 4 498 770 and grid points merged
    (the reliability review, 2026-12-06)."""
    return frame.assign(**{c: frame[c].map(COORDINATE_FORMAT.format)
                           for c in ("x", "y", "z") if c in frame.columns})


def add_arguments(p: argparse.ArgumentParser) -> None:

    p.add_argument("--anchors", required=True, help="anchors file (anchor, x, y[, z])")
    p.add_argument("--area", type=_area, default=None, metavar="XMIN,XMAX,YMIN,YMAX",
                   help="grid extent in metres, covered edge to edge (default: the "
                        "anchors' bounding box widened by 10 %% of its size on each side, "
                        "at least 1 m)")
    p.add_argument("--step", type=positive_float, default=None,
                   help="largest grid spacing in metres: the points are spread evenly from "
                        "edge to edge of --area, STEP apart where STEP divides its size, a "
                        "little closer where it does not (default: 151 points along the "
                        "longer side)")
    p.add_argument("--sigma", type=float_in(1e-9, 1e9), default=None,
                   help="a-priori standard deviation of one observation: m for ranges, dB for "
                        "RSSI, 1e-9 .. 1e9 (default: the anchors' sigma column when it is in "
                        "the model's unit, else 1)")
    p.add_argument("--dim", type=int, choices=(2, 3), default=2,
                   help="solved dimension (default 2)")
    p.add_argument("--tag-z", "--tag-height", dest="tag_z", type=float_in(-1e5, 1e5),
                   default=0.0, metavar="M",
                   help="tag height in metres (default 0); --tag-z and --tag-height (the "
                        "name locate, calibrate, track and fuse use) are the same option")
    p.add_argument("--model", choices=("range", "rssi"), default=None,
                   help="observation type (default: rssi when the anchors file has path-loss "
                        "columns and no range calibration, else range)")
    p.add_argument("--n", type=float_in(0.1, 10.0), default=None,
                   help="path-loss exponent for --model rssi (default: the anchors' n, or "
                        "gamma, column, else 2)")
    p.add_argument("--max-range", type=positive_float, default=None,
                   help="anchors farther than this (m) are not heard (default: all heard)")
    p.add_argument("--alpha0", type=float_in(1e-15, 0.5), default=0.001,
                   help="w-test significance (default 0.001)")
    p.add_argument("--beta0", type=float_in(1e-15, 0.5), default=0.10,
                   help="w-test type II error (default 0.10)")
    p.add_argument("--rho-threshold", type=float_in(1e-9, 1.0), default=0.9,
                   help="|rho_ij| above which two anchors are flagged as not separable (0.9)")
    p.add_argument("--suggest", action="store_true",
                   help="rank candidate positions for one more anchor")
    p.add_argument("--candidates", default=None,
                   help="candidate positions file (columns x, y[, z]) for --suggest")
    p.add_argument("--suggest-metric", default="max_ext_m",
                   choices=("max_ext_m", "max_mdb", "crlb_m", "dop", "max_abs_rho"),
                   help="figure whose 95th percentile over the area --suggest minimizes "
                        "(default %(default)s)")
    p.add_argument("--no-maps", action="store_true", help="write the CSV only, no PNG maps")
    p.add_argument("-o", "--out", required=True, help="output folder")
    p.add_argument("--json", action="store_true", help="print the summary as JSON")
    p.add_argument("-q", "--quiet", action="store_true",
                   help="no progress bar (the summary is still printed)")


def _read(path: str):  # noqa: ANN202
    import pandas as pd

    from robustloc.io import read_anchors

    df = read_anchors(path)
    cols = ["x", "y"] + (["z"] if "z" in df.columns else [])
    xyz = df[cols].to_numpy(dtype=float)
    if "z" in df.columns and not np.all(np.isfinite(xyz[:, 2])):
        raise InputError("anchor heights (z) must all be given when the column exists", path)
    far = np.any(np.abs(xyz) > MAX_COORDINATE_M, axis=1)
    if far.any():  # (1e12 m gave a grid of 8e9 m steps, exit 0: the reliability review)
        i = int(np.argmax(far))
        raise InputError(f"anchor {df['anchor'].iloc[i]}: a coordinate beyond "
                         f"{MAX_COORDINATE_M:g} m (the limit of --area)", path,
                         int(df.index[i]) if df.index.name == "line" else i + 2)
    # two anchors at one place are one anchor counted twice: every point's redundancy
    # read 0 and every correlation 1, exit 0 (the reliability review)
    twice = pd.DataFrame(xyz).duplicated(keep="first").to_numpy()
    if twice.any():
        i = int(np.argmax(twice))
        first = int(np.flatnonzero((xyz == xyz[i]).all(axis=1))[0])
        line = df.index[i] if df.index.name == "line" else i + 2
        raise InputError(f"anchors {df['anchor'].iloc[first]} and {df['anchor'].iloc[i]} "
                         "share their coordinates", path, int(line))
    return df, xyz


def _candidates(args: argparse.Namespace, xyz: np.ndarray, area) -> np.ndarray:  # noqa: ANN001
    """The candidate positions of --suggest: the --candidates file's, else the area's
    border (:func:`robustloc.integrity.planner.default_candidates`)."""

    from robustloc.integrity.planner import default_candidates

    if args.candidates is not None:
        from robustloc.io.tables import read_table

        cdf = read_table(args.candidates, "candidates")
        cols = ["x", "y"] + (["z"] if xyz.shape[1] == 3 else [])
        missing = [c for c in cols if c not in cdf.columns]
        if missing:
            raise InputError(f"candidates file needs columns {', '.join(cols)}", args.candidates)
        if cdf.empty:  # (a KeyError traceback from the empty ranking)
            raise InputError("candidates file has a header but no data rows",
                             args.candidates, 2)
        cand = cdf[cols].apply(to_number).to_numpy(float)
        bad = ~np.all(np.isfinite(cand), axis=1)
        if bad.any():
            raise InputError("non-numeric or missing candidate coordinate", args.candidates,
                             int(np.argmax(bad)) + 2)
        far = np.any(np.abs(cand) > MAX_COORDINATE_M, axis=1)
        if far.any():  # (y = 1e300: a matplotlib traceback; the reliability review)
            raise InputError(f"candidate coordinate beyond {MAX_COORDINATE_M:g} m (the "
                             "limit of --area)", args.candidates, int(np.argmax(far)) + 2)
        return cand
    z = float(np.median(xyz[:, 2])) if xyz.shape[1] == 3 else None
    return default_candidates(area, 8, z)


def _check_grid(area, step: float, option: str) -> float:  # noqa: ANN001
    """Number of points of the grid over ``area`` with spacing ``step``; a grid beyond
    :data:`robustloc.integrity.planner.MAX_GRID_POINTS` is refused naming ``option``, its
    numbers in ``%g`` (--step 1e-300 printed a grid of a 302-digit number of points, and
    5e-324 was an OverflowError traceback: the second reliability review)."""
    from robustloc.integrity.planner import MAX_GRID_POINTS, grid_shape

    nx, ny = grid_shape(area, step)
    if not nx * ny <= MAX_GRID_POINTS:
        raise InputError(f"{option}: a grid of {nx:g} x {ny:g} points is too large; "
                         f"increase --step (at most {MAX_GRID_POINTS:g} points)")
    return nx * ny


def _no_fix(xyz: np.ndarray, args: argparse.Namespace) -> str:
    """Why no point of the area has a fix, in words (the anchors' count, and whether they
    lie on one line by the planner's test, :func:`robustloc.integrity.planner.unique_fix`)."""
    from robustloc.integrity.planner import unique_fix

    m, dim = len(xyz), args.dim
    what = f"{m} anchor{'s' if m != 1 else ''}"
    if m > dim and not unique_fix(xyz, np.ones((1, m), dtype=bool), dim)[0]:
        what += ", all on one line"
    # (3-D: anchors on one plane give fixes off it, and none in it)
    return (f"no point of the area has a fix ({what}; a {dim}-D fix needs {dim + 1} heard, "
            + ("not all on one line" if dim == 2 else "not all in one plane with the tag")
            + (f", within --max-range {args.max_range:g} m" if args.max_range is not None
               else "") + ")")


#: Unit of an observation, its sigma and its MDB, per --model.
def run(args: argparse.Namespace) -> int:
    from robustloc.integrity.planner import MAPS, plan, plot_maps

    if args.candidates is not None and not args.suggest:  # (it was silently ignored)
        raise InputError("--candidates goes with --suggest (the positions to try for one "
                         "more anchor)")
    df, xyz = _read(args.anchors)
    if args.area is None:
        lo, hi = xyz[:, :2].min(axis=0), xyz[:, :2].max(axis=0)
        pad = np.maximum(0.1 * (hi - lo), 1.0)
        area = (lo[0] - pad[0], hi[0] + pad[0], lo[1] - pad[1], hi[1] + pad[1])
    else:
        area = args.area
    step = args.step
    if step is None:
        step = max(area[1] - area[0], area[3] - area[2]) / 150.0
    path_loss, note = file_defaults(df, args)
    if note is not None:
        print(f"note: {note}", file=sys.stderr)
    n_exp: object = 2.0
    if args.model == "rssi":
        if args.n is not None:
            n_exp = args.n
        elif path_loss is not None:  # n, or gamma (attenuation factor), or 2 (friis)
            n_exp = path_loss.log_distance_params()[1]
        elif "n" in df.columns and np.all(np.isfinite(df["n"].to_numpy(float))):
            n_exp = df["n"].to_numpy(float)
    if args.dim == 3 and "z" not in df.columns:
        raise InputError("--dim 3 needs anchor heights (a z column)", args.anchors, 1)
    # both grids checked before any work: the maps' and --suggest's (twice as coarse: one
    # planner run per candidate)
    total = _check_grid(area, step, "--step" if args.step is not None else "--area")
    cand = None
    if args.suggest:
        cand = _candidates(args, xyz, area)
        total += (len(cand) + 1) * _check_grid(area, 2 * step, "--step")
    from tqdm import tqdm

    kw = dict(dim=args.dim, tag_z=args.tag_z, model=args.model, path_loss_n=n_exp,
              max_range_m=args.max_range, alpha0=args.alpha0, beta0=args.beta0)
    with tqdm(total=int(total), desc="reliability", unit=" points", unit_scale=True,
              file=sys.stderr,
              disable=getattr(args, "quiet", False) or not sys.stderr.isatty()) as bar:
        try:
            grid = plan(xyz, area, step, args.sigma, rho_threshold=args.rho_threshold,
                        progress=bar.update, **kw)
            sugg = None
            if cand is not None:
                from robustloc.integrity.planner import suggest_anchor

                sugg = suggest_anchor(xyz, area, 2 * step, args.sigma, cand,
                                      metric=args.suggest_metric, progress=bar.update, **kw)
        except ValueError as exc:  # an option the planner refuses
            raise InputError(str(exc)) from None
    if grid.table["dop"].isna().all():
        # one anchor, anchors on one point, a range that hears too few: six empty maps
        # and an all-NaN table, exit 0 (the reliability review); two anchors, or anchors
        # on one line, were planned as if their fixes were unique (the second review)
        why = _no_fix(xyz, args)
        if sugg is None or not np.isfinite(sugg["score"]).any():
            raise InputError(why, args.anchors)
        print(f"warning: {args.anchors}: {why}: the maps are empty; the ranking says "
              "where one more anchor gives fixes", file=sys.stderr)
    from robustloc.commands._folder import write_folder

    out = Path(args.out)
    csv = out / "reliability.csv"
    best = None if sugg is None else sugg[["x", "y"]].to_numpy(float)[:3]
    unit = UNITS[args.model]
    # the MDB is in the observation's unit (MAPS says "observation units")
    captions = {**MAPS, "max_mdb": f"largest MDB ({unit})"}

    def write(folder: Path) -> list:
        _coordinates_exact(grid.table).to_csv(folder / csv.name, index=False,
                                              float_format="%.6g")
        if sugg is not None:
            _coordinates_exact(sugg).to_csv(folder / "suggestions.csv", index=False,
                                            float_format="%.6g")
        if args.no_maps:
            return []
        maps = plot_maps(grid, xyz, folder, [str(a) for a in df["anchor"]], highlight=best,
                         captions=captions)
        return [out / Path(m).name for m in maps]

    # an input named like an output (rel/reliability.csv as --anchors) is refused
    pngs = write_folder(args.out, write, [args.anchors, args.candidates],
                        owns=("reliability.csv", "suggestions.csv",
                              *(f"reliability_{c}.png" for c in MAPS)))
    t = grid.table
    summary = {
        "anchors": int(len(xyz)),
        "grid_points": int(len(t)),
        "area": list(area),
        "step_m": step,
        "model": args.model,
        # one number (the median of per-anchor sigmas), as before; the anchors' below
        "sigma": float(np.median(args.sigma)),
        "sigma_per_anchor": (np.asarray(args.sigma, float).tolist()
                             if np.ndim(args.sigma) else None),
        "unit": unit,  # of sigma and max_mdb
        "points_without_fix": int(t["dop"].isna().sum()),
        "points_without_redundancy": int((t["dof"] < 1).sum()),
        # an observation with redundancy 0 at a point that has a fix: no test can see
        # its fault (MDB inf); the count of points with redundancy left above does not
        # show them (the commands review: 3 of 9 points, "without redundancy: 0")
        "points_with_undetectable_observation": int(np.isinf(t["max_mdb"]).sum()),
    }
    stats = {}
    for col in MAPS:
        v = t[col].to_numpy(float)
        # NaN is "no fix here" and is left out; inf (an MDB, or its effect, of an
        # uncontrolled observation) is a value and stays in max and median: dropped with
        # the NaN, the summary's largest MDB was that of the controlled points only
        v = v[~np.isnan(v)]
        stats[col] = {
            "median": float(np.median(v)) if v.size else None,
            "max": float(v.max()) if v.size else None,
            "min": float(v.min()) if v.size else None,
        }
        # JSON has no infinity: null, and "infinite" names the figures that are null for
        # being infinite, as evaluate --json does
        summary[col] = {k: (None if x is not None and np.isinf(x) else x)
                        for k, x in stats[col].items()}
        summary[col]["infinite"] = [k for k, x in stats[col].items()
                                    if x is not None and np.isinf(x)]
    summary["points_with_flagged_pairs"] = int((t["n_flagged"] > 0).sum())
    if sugg is not None:
        summary["suggestions"] = json.loads(sugg.head(5).to_json(orient="records"))
    summary["csv"] = str(csv)
    summary["figures"] = [str(p) for p in pngs]
    if args.json:
        print(json.dumps(summary, indent=2, allow_nan=False))
    else:
        print(f"{summary['grid_points']} grid points, {summary['anchors']} anchors, "
              f"model {args.model}, sigma {sigma_text(args.sigma, args.model)}")
        for col, cap in captions.items():
            s = stats[col]
            if s["median"] is None:
                continue
            print(f"  {col:15s} median {s['median']:9.3f}  min {s['min']:9.3f}  "
                  f"max {s['max']:9.3f}   {cap}")
        # (a fix needs dim + 1 anchors heard, so a point with a fix has redundancy: the
        # count of points without it repeated the count without a fix; the JSON keeps
        # points_without_redundancy for scripts; the stats review)
        print(f"  points without a fix: {summary['points_without_fix']}, "
              f"with an undetectable observation "
              f"(MDB inf): {summary['points_with_undetectable_observation']}, with flagged "
              f"pairs: {summary['points_with_flagged_pairs']}")
        if sugg is not None:
            print(f"one more anchor, ranked by the 95th percentile of {args.suggest_metric} "
                  f"(now {sugg['baseline'].iloc[0]:.3f}):")
            print(sugg.head(5).to_string(index=False, float_format=lambda v: f"{v:.3f}"))
        print(f"wrote {csv} and {len(pngs)} maps into {out}", file=sys.stderr)
    return 0
