"""Anchor-layout planner: reliability maps over a grid of tag positions (seed 003).

For every grid position of the tag, the range (or RSSI) model is linearized at that position
and the figures an engineer needs to decide where one more beacon goes are computed:

* ``dop``: position dilution of precision of the range geometry, ``sqrt(trace (G^T G)^-1)``;
* ``crlb_m``: Cramer-Rao bound on the position RMSE for the given noise
  (:mod:`robustloc.eval.crlb`);
* ``max_mdb``: largest minimal detectable bias over the anchors heard (observation units:
  metres for ranges, dB for RSSI);
* ``max_ext_m``: largest horizontal position error an undetected MDB causes (external
  reliability);
* ``max_abs_rho``: largest correlation of two w-tests (values near 1: a fault is detected
  but cannot be attributed); ``n_flagged``: pairs above the threshold;
* ``min_redundancy``: smallest redundancy number ``r_i`` (0: an anchor not controlled at all);
  ``dof``: total redundancy ``n - p``; ``n_heard``: anchors in range.

Grid points without a unique fix get NaN in every figure (and ``dof = 0``), as ``locate``
gives no fix there: fewer than ``dim + 1`` anchors heard (with as many ranges as unknowns
the circles, or spheres, meet in two points: the fix and its mirror image), in 2-D heard
anchors that lie on one line (every fix fits its mirror image across the line exactly:
the test :func:`robustloc.models.geometry.collinear` by which ``locate`` marks such an
epoch ``ill_conditioned``, and ``calibrate --self`` finds no fix), or a singular geometry.
The local figures at such a point (a finite DOP two heard anchors give off their line)
hold only where the side of the line is known, which a plan cannot assume (the review of
``reliability``: a layout of anchors on one line, or of two anchors, was planned with finite
maps and ranked by ``--suggest``, exit 0).  An MDB of an uncontrolled observation
(``r_i = 0``) is ``inf``.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd
from numpy.typing import ArrayLike, NDArray

from robustloc.eval.crlb import crlb_range, crlb_rssi, dop
from robustloc.integrity.bmethod import ALPHA0, BETA0
from robustloc.integrity.reliability import RHO_THRESHOLD, check_chunk, reliability

Array = NDArray[np.float64]

#: Columns of the planner table, in order, with their captions.
MAPS = {
    "dop": "position DOP of the range geometry",
    "crlb_m": "CRLB of the position RMSE (m)",
    "max_mdb": "largest MDB (observation units)",
    "max_ext_m": "largest horizontal effect of an undetected MDB (m)",
    "max_abs_rho": "largest |rho_ij| of two w-tests",
    "min_redundancy": "smallest redundancy number r_i",
}


@dataclass(frozen=True)
class Grid:
    """A planner grid: coordinates and the per-point table (row-major over ``y`` then ``x``)."""

    x: Array
    y: Array
    table: pd.DataFrame

    def field(self, column: str) -> Array:
        """Column as a ``(ny, nx)`` array for plotting."""
        return self.table[column].to_numpy(dtype=float).reshape(self.y.size, self.x.size)


#: Largest number of points of a planner grid (:func:`grid_axes`).
MAX_GRID_POINTS = 2_000_000


def grid_shape(area: tuple[float, float, float, float], step: float) -> tuple[float, float]:
    """Number of grid points ``(nx, ny)`` :func:`grid_axes` lays over ``area`` with spacing
    ``step``, as floats: ``inf`` or numbers of hundreds of digits for an absurd ``step``
    (an ``int`` of them was printed whole, 300 digits, or raised ``OverflowError``: the
    second reliability review), so messages format them with ``%g``.

    Raises
    ------
    ValueError
        ``area`` is not four finite numbers with ``xmin < xmax`` and ``ymin < ymax``, or
        ``step`` is not positive and finite.
    """
    if np.shape(area) != (4,):  # ("not enough values to unpack": the API review)
        raise ValueError(f"area must be four numbers xmin, xmax, ymin, ymax, got {area!r}")
    xmin, xmax, ymin, ymax = map(float, area)
    if not (np.isfinite([xmin, xmax, ymin, ymax]).all() and xmax > xmin and ymax > ymin):
        raise ValueError(f"area must be xmin,xmax,ymin,ymax with xmin < xmax, ymin < ymax, "
                         f"got ({xmin:g}, {xmax:g}, {ymin:g}, {ymax:g})")
    if not (np.isfinite(step) and step > 0):
        raise ValueError(f"grid step must be positive, got {float(step):g}")
    # (spacing at most ``step``, so that the grid reaches both edges: with ``floor`` a
    # step that does not divide the extent left the far strip out, while the summary
    # still named the whole area: --area 0,10,0,8 --step 3 stopped at x 9, y 6; the
    # stats review)
    with np.errstate(over="ignore"):
        nx = float(np.ceil((xmax - xmin) / step - 1e-9)) + 1.0
        ny = float(np.ceil((ymax - ymin) / step - 1e-9)) + 1.0
    return nx, ny


def grid_axes(area: tuple[float, float, float, float], step: float) -> tuple[Array, Array]:
    """Grid coordinates covering ``area = (xmin, xmax, ymin, ymax)`` from edge to edge,
    evenly spaced at most ``step`` apart on each axis (``step`` exactly where it divides
    the extent).

    Raises
    ------
    ValueError
        As :func:`grid_shape`, or the grid has more than :data:`MAX_GRID_POINTS` points.
    """
    nx, ny = grid_shape(area, step)
    if nx * ny > MAX_GRID_POINTS:
        raise ValueError(f"grid of {nx:g} x {ny:g} points is too large; increase --step "
                         f"(at most {MAX_GRID_POINTS:g} points)")
    xmin, xmax, ymin, ymax = map(float, area)
    return np.linspace(xmin, xmax, int(nx)), np.linspace(ymin, ymax, int(ny))


def unique_fix(anchors: ArrayLike, heard: ArrayLike, dim: int = 2) -> NDArray[np.bool_]:
    """Which points (rows of ``heard``) have a unique fix from the anchors they hear.

    A unique fix needs ``dim + 1`` heard anchors (with ``dim`` ranges the circles, or
    spheres, meet in two points) and, in 2-D, heard anchors that do not lie on one line
    (every fix fits its mirror image across the line as well).  The line test is
    ``locate``'s (:func:`robustloc.models.geometry.collinear`, by which it marks such
    an epoch ``ill_conditioned``; ``calibrate --self`` says "the anchors heard lie on a
    line" when it leaves no fix), so a plan and the fixes agree.  In 3-D, heard anchors on
    one plane (ceiling-mounted) still give a fix: ``locate`` starts on their lower side.

    Parameters
    ----------
    anchors : array_like (m, 2) or (m, 3)
        Anchor coordinates, m (in 2-D only the first two columns are used).
    heard : array_like of bool (P, m)
        Anchors heard at each point.
    dim : 2 or 3
        Solved dimension.

    Returns
    -------
    ndarray of bool (P,)

    Examples
    --------
    >>> a = np.array([[0.0, 0.0], [10.0, 0.0], [20.0, 0.0], [0.0, 8.0]])
    >>> unique_fix(a, np.array([[1, 1, 1, 0], [1, 1, 1, 1], [1, 0, 0, 1]], bool))
    array([False,  True, False])
    """
    from robustloc.models.geometry import collinear

    a = np.asarray(anchors, dtype=float)
    h = np.asarray(heard, dtype=bool)
    ok = h.sum(axis=1) >= dim + 1
    if dim == 2 and ok.any():
        ok[ok] = ~collinear(a[:, :2], h[ok])
    return ok


#: Largest number of elements of one ``(points, m, m)`` matrix of a chunk of
#: :func:`plan` (2**22: 32 MB in float64).
CHUNK_ELEMENTS = 2**22


def plan(
    anchors: ArrayLike,
    area: tuple[float, float, float, float],
    step: float,
    sigma: ArrayLike,
    *,
    dim: int = 2,
    tag_z: float = 0.0,
    model: str = "range",
    path_loss_n: ArrayLike = 2.0,
    max_range_m: float | None = None,
    alpha0: float = ALPHA0,
    beta0: float = BETA0,
    rho_threshold: float = RHO_THRESHOLD,
    chunk: int = 4096,
    progress: Callable[[int], object] | None = None,
) -> Grid:
    """Reliability figures over a grid of tag positions.

    Parameters
    ----------
    anchors : array_like (m, 2) or (m, 3)
        Anchor coordinates, m.
    area : (xmin, xmax, ymin, ymax)
        Grid extent, m.
    step : float
        Largest grid spacing, m (:func:`grid_axes`: the grid reaches both edges).
    sigma : float or array_like (m,)
        A-priori standard deviation of one observation: metres (``model="range"``) or dB
        (``model="rssi"``); one number, or one per anchor (an anchors file's ``sigma``
        column, as ``calibrate`` writes it).
    dim : 2 or 3
        Solved dimension.  In 2-D, anchor heights (third column) enter as known offsets from
        the tag height ``tag_z``; in 3-D the grid lies at height ``tag_z``.
    model : "range" or "rssi"
        Observation type; ``rssi`` uses the log-distance model with exponent(s)
        ``path_loss_n`` (seed 000 eq. (1)).
    max_range_m : float, optional
        Anchors farther than this are not heard.
    alpha0, beta0, rho_threshold
        See :func:`robustloc.integrity.reliability.reliability`.
    chunk : int
        Grid points processed at once (bounds memory).
    progress : callable, optional
        Called with the number of grid points of each chunk done (e.g. a progress bar's
        ``update``).
    """
    from robustloc.models.ranging import RangeModel, RssiModel

    a = np.asarray(anchors, dtype=float)
    if a.ndim != 2 or a.shape[1] not in (2, 3) or a.shape[0] < 1:
        raise ValueError(f"anchors must have shape (m, 2) or (m, 3), got {a.shape}")
    if dim not in (2, 3):
        raise ValueError(f"dim must be 2 or 3, got {dim}")
    if dim == 3 and a.shape[1] != 3:
        raise ValueError("--dim 3 needs anchor heights (a z column)")
    if model not in ("range", "rssi"):
        raise ValueError(f"model must be 'range' or 'rssi', got {model!r}")
    sig = np.asarray(sigma, dtype=float)
    if sig.ndim > 1 or (sig.ndim == 1 and sig.size != a.shape[0]):
        raise ValueError(f"sigma must be one number or one per anchor ({a.shape[0]}), "
                         f"got shape {sig.shape}")
    if not (np.all(np.isfinite(sig)) and np.all(sig > 0)):
        raise ValueError(f"sigma must be positive, got {sigma}")
    sigma = sig  # (broadcast against the anchors of every grid point)
    check_chunk(chunk)
    gx, gy = grid_axes(area, step)
    X, Y = np.meshgrid(gx, gy)
    pts = np.column_stack([X.ravel(), Y.ravel()])
    if dim == 3:
        pts = np.column_stack([pts, np.full(len(pts), float(tag_z))])
        anc, hoff = a, None
    else:
        anc = a[:, :2]
        hoff = (a[:, 2] - tag_z) if a.shape[1] == 3 else None
    rmodel = RangeModel(anc, hoff)
    smodel = RssiModel(anc, A=0.0, n=path_loss_n, height_offset=hoff) if model == "rssi" else None
    out = {k: np.full(len(pts), np.nan) for k in
           ("dop", "crlb_m", "max_mdb", "max_ext_m", "max_abs_rho", "min_redundancy")}
    n_heard = np.zeros(len(pts), dtype=np.int64)
    dof = np.zeros(len(pts), dtype=np.int64)
    n_flag = np.zeros(len(pts), dtype=np.int64)
    # the reliability of a chunk holds (chunk, m, m) matrices (the residuals' projector,
    # the w-tests' correlations, their flags): at most CHUNK_ELEMENTS of them, whatever
    # the anchors' count m (300 anchors took 13 GB with 4096 points a chunk: the review)
    chunk = max(1, min(chunk, CHUNK_ELEMENTS // max(len(anc), 1) ** 2))
    for s in range(0, len(pts), chunk):
        P = pts[s : s + chunk]
        rng, G = rmodel.predict_jacobian(P)
        heard = np.ones(rng.shape, dtype=bool) if max_range_m is None else rng <= max_range_m
        heard &= rng > 1e-6  # the tag on an anchor: direction undefined
        Gm = np.where(heard[..., None], G, np.nan)
        out["dop"][s : s + len(P)] = dop(Gm, n_position=dim).pdop
        if smodel is None:
            Hm = Gm
            c = crlb_range(anc, P, sigma, hoff, mask=heard)
        else:
            Hm = np.where(heard[..., None], smodel.jacobian(P), np.nan)
            c = crlb_rssi(anc, P, sigma, path_loss_n, hoff, mask=heard)
        out["crlb_m"][s : s + len(P)] = c.rmse
        rel = reliability(Hm, sigma, mask=heard, alpha0=alpha0, beta0=beta0,
                          rho_threshold=rho_threshold)
        sl = slice(s, s + len(P))
        # a unique fix, as `locate` gives one (module docstring): dim + 1 heard, and in
        # 2-D not all of them on one line (locate's own test, shared, not copied)
        fix = unique_fix(anc, heard, dim)
        out["dop"][sl] = np.where(fix, out["dop"][sl], np.nan)
        out["crlb_m"][sl] = np.where(fix, out["crlb_m"][sl], np.nan)
        good = fix & rel.ok & (rel.n_used > dim)
        out["max_mdb"][sl] = np.where(good, rel.max_mdb, np.nan)
        out["max_ext_m"][sl] = np.where(good, rel.max_external_horizontal, np.nan)
        out["max_abs_rho"][sl] = np.where(good, rel.max_abs_rho, np.nan)
        out["min_redundancy"][sl] = np.where(good, rel.min_redundancy, np.nan)
        n_heard[sl] = heard.sum(axis=1)
        dof[sl] = np.where(fix & rel.ok, rel.n_used - dim, 0)
        n_flag[sl] = np.where(good, np.triu(rel.flagged, 1).sum(axis=(1, 2)), 0)
        if progress is not None:
            progress(len(P))
    table = pd.DataFrame({"x": pts[:, 0], "y": pts[:, 1], **out, "n_heard": n_heard, "dof": dof,
                          "n_flagged": n_flag})
    return Grid(gx, gy, table)


def plot_maps(
    grid: Grid,
    anchors: ArrayLike,
    out_dir: str | Path,
    anchor_ids: list[str] | None = None,
    prefix: str = "reliability",
    columns: tuple[str, ...] = tuple(MAPS),
    highlight: ArrayLike | None = None,
    captions: Mapping[str, str] | None = None,
) -> list[Path]:
    """Heat maps of the planner columns with the anchors drawn; returns the PNG paths.

    ``highlight`` (k, 2+): positions drawn as white stars (e.g. suggested new anchors).
    ``captions``: the maps' titles by column, over :data:`MAPS` (e.g. ``max_mdb`` with
    its unit, dB for RSSI or m for ranges).
    """
    titles = {**MAPS, **(captions or {})}
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    a = np.asarray(anchors, dtype=float)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    ids = anchor_ids if anchor_ids is not None else [str(i + 1) for i in range(len(a))]
    wx = grid.x[-1] - grid.x[0] if grid.x.size > 1 else 1.0
    wy = grid.y[-1] - grid.y[0] if grid.y.size > 1 else 1.0
    aspect = wy / wx
    figw = 9.0
    # very elongated areas (a corridor) are drawn stretched so the field stays readable
    equal = 0.2 <= aspect <= 5.0
    figh = float(np.clip(figw * aspect + 1.2, 3.0, 9.0)) if equal else 3.5
    paths = []
    for col in columns:
        f = grid.field(col)
        f = np.where(np.isfinite(f), f, np.nan)
        fig, ax = plt.subplots(figsize=(figw, figh))
        finite = f[np.isfinite(f)]
        vmax = float(np.percentile(finite, 98)) if finite.size else 1.0
        if col == "max_abs_rho":
            vmin, vmax = 0.0, 1.0
        elif col == "min_redundancy":
            vmin, vmax = 0.0, max(vmax, 1e-3)
        else:
            vmin = float(np.nanmin(finite)) if finite.size else 0.0
        hx = 0.5 * (grid.x[1] - grid.x[0]) if grid.x.size > 1 else 0.5
        hy = 0.5 * (grid.y[1] - grid.y[0]) if grid.y.size > 1 else 0.5
        im = ax.imshow(f, origin="lower", cmap="viridis", interpolation="nearest",
                       extent=(grid.x[0] - hx, grid.x[-1] + hx, grid.y[0] - hy, grid.y[-1] + hy),
                       vmin=vmin, vmax=max(vmax, vmin + 1e-9), aspect="auto")
        fig.colorbar(im, ax=ax, label=col, shrink=0.9)
        ax.plot(a[:, 0], a[:, 1], "r^", ms=8, mec="k", label="anchors")
        if highlight is not None and len(highlight):
            hl = np.atleast_2d(np.asarray(highlight, dtype=float))
            ax.plot(hl[:, 0], hl[:, 1], "w*", ms=13, mec="k", label="suggested anchor")
            ax.legend(loc="upper right", fontsize=7, framealpha=0.7)
        for (px, py), name in zip(a[:, :2], ids):
            ax.annotate(str(name), (px, py), textcoords="offset points", xytext=(3, 3),
                        fontsize=7, color="r")
        ax.set_title(titles.get(col, col), fontsize=10)
        ax.set_xlabel("x (m)")
        ax.set_ylabel("y (m)")
        if equal:
            ax.set_aspect("equal")
        else:
            ax.set_title(titles.get(col, col) + " (axes not to scale)", fontsize=10)
        fig.subplots_adjust(bottom=0.16 if not equal else 0.1, top=0.9)
        p = out / f"{prefix}_{col}.png"
        fig.savefig(p, dpi=100)
        plt.close(fig)
        paths.append(p)
    return paths


#: Planner columns a suggestion can minimize.
SUGGEST_METRICS = ("max_ext_m", "max_mdb", "crlb_m", "dop", "max_abs_rho")


def layout_score(grid: Grid, metric: str = "max_ext_m", quantile: float = 0.95) -> float:
    """One number for a layout: the ``quantile`` of ``metric`` over the grid points.

    Grid points without a fix, or without redundancy when the metric needs it (NaN in the
    table), count as ``+inf``, so coverage gaps dominate the score.
    """
    if metric not in SUGGEST_METRICS:
        raise ValueError(f"metric must be one of {', '.join(SUGGEST_METRICS)}, got {metric!r}")
    if not 0.0 < quantile <= 1.0:
        raise ValueError(f"quantile must be in (0, 1], got {quantile}")
    v = grid.table[metric].to_numpy(dtype=float)
    v = np.where(np.isnan(v), np.inf, v)
    return float(np.quantile(v, quantile, method="higher"))


def suggest_anchor(
    anchors: ArrayLike,
    area: tuple[float, float, float, float],
    step: float,
    sigma: ArrayLike,
    candidates: ArrayLike,
    *,
    metric: str = "max_ext_m",
    quantile: float = 0.95,
    **plan_kwargs: object,
) -> pd.DataFrame:
    """Rank candidate positions for one more anchor by the layout score they give.

    For each candidate the planner grid is recomputed with the candidate added, and the
    layout is scored by :func:`layout_score` (default: the 95th percentile over the area of
    the largest horizontal effect of an undetected MDB, i.e. the external reliability an
    engineer can promise almost everywhere).

    Parameters
    ----------
    anchors : (m, d) existing anchors.
    area, step, sigma : as in :func:`plan` (use a coarser ``step`` than for the maps: the
        cost is one planner run per candidate).
    candidates : (C, d) candidate positions (same columns as ``anchors``).
    metric, quantile : see :func:`layout_score`.
    **plan_kwargs : further options of :func:`plan` (``dim``, ``model``, ``max_range_m``...;
        ``progress`` counts the grid points of every run: ``len(candidates) + 1`` grids).
        Per-anchor path-loss exponents, and per-anchor sigmas, are extended with their
        median for the candidate.

    Returns
    -------
    pandas.DataFrame
        One row per candidate, best first: its coordinates, ``score``, ``baseline`` (score
        without a new anchor), ``improvement`` (``baseline - score``; ``inf`` when the
        candidate closes a coverage gap) and ``points_without_fix``.
    """
    a = np.asarray(anchors, dtype=float)
    c = np.atleast_2d(np.asarray(candidates, dtype=float))
    if c.shape[1] != a.shape[1]:
        raise ValueError(f"candidates need {a.shape[1]} columns like the anchors, got {c.shape}")
    if not np.all(np.isfinite(c)):
        raise ValueError("candidate coordinates must be finite")
    base = layout_score(plan(a, area, step, sigma, **plan_kwargs), metric, quantile)
    kw_new = dict(plan_kwargs)
    n_exp = np.asarray(plan_kwargs.get("path_loss_n", 2.0), dtype=float)
    if n_exp.ndim == 1 and n_exp.size == len(a):  # per-anchor exponents: the new one gets
        kw_new["path_loss_n"] = np.append(n_exp, np.median(n_exp))  # the median
    sig_new = np.asarray(sigma, dtype=float)
    if sig_new.ndim == 1 and sig_new.size == len(a):  # per-anchor sigmas: the same
        sig_new = np.append(sig_new, np.median(sig_new))
    rows = []
    for cand in c:
        g = plan(np.vstack([a, cand]), area, step, sig_new, **kw_new)
        sc = layout_score(g, metric, quantile)
        rows.append({**{k: float(v) for k, v in zip("xyz", cand)}, "score": sc,
                     "baseline": base,
                     "improvement": (base - sc) if np.isfinite(sc) else -np.inf,
                     "points_without_fix": int(g.table[metric].isna().sum())})
    out = pd.DataFrame(rows)
    return out.sort_values(["score", "points_without_fix"], kind="stable").reset_index(drop=True)


def default_candidates(
    area: tuple[float, float, float, float], n_per_side: int = 8, z: float | None = None
) -> Array:
    """Candidate anchor positions on the border of ``area`` (walls and ceiling edges are
    where anchors can be mounted), ``n_per_side`` per side; with ``z`` a third column."""
    xmin, xmax, ymin, ymax = map(float, area)
    t = np.linspace(0.0, 1.0, n_per_side, endpoint=False)
    pts = np.vstack([
        np.column_stack([xmin + t * (xmax - xmin), np.full_like(t, ymin)]),
        np.column_stack([np.full_like(t, xmax), ymin + t * (ymax - ymin)]),
        np.column_stack([xmax - t * (xmax - xmin), np.full_like(t, ymax)]),
        np.column_stack([np.full_like(t, xmin), ymax - t * (ymax - ymin)]),
    ])
    if z is not None:
        pts = np.column_stack([pts, np.full(len(pts), float(z))])
    return pts
