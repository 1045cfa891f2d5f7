"""Position error statistics against truth (seed 000 sec. 3, Table 1).

For each epoch the horizontal error ``Δd = |(x, y) - (x_true, y_true)|`` (and the 3-D error
when both files have ``z``).  Per tag and method, over the epochs with a usable fix:

* ``max``, ``min``, ``mean`` ``Δd̄ = (1/n) Σ Δd_i``;
* ``rms`` -- the paper's "positioning standard error" ``σ0 = sqrt((1/n) Σ Δd_i^2)``;
* ``sigma1`` -- the paper's spread ``σ1 = sqrt((1/n) Σ (Δd_i - Δd̄)^2)`` (population form,
  divisor ``n``, as in the paper; note ``σ0^2 = Δd̄^2 + σ1^2``);
* ``median`` and ``p95`` (95th percentile, linear interpolation between order statistics,
  numpy's default);
* ``n`` (the epochs scored: matched positions rows plus missing truth epochs; with a
  ``time_tolerance_s`` wider than the positions' spacing several positions rows can match
  one truth row, and each is scored), ``n_missing``
  (truth epochs of the tag with no positions row of the method: they count as failed),
  ``n_failed`` (missing, status not usable -- see :data:`robustloc.status.USABLE` -- or a
  non-finite coordinate), ``n_ok = n - n_failed``, ``failed_pct`` (availability is
  ``100 - failed_pct``).

The 3-D statistics (suffix ``_3d``) and the vertical bound's (``n_misleading_v``,
``misleading_pct_v``, ``vpl_median``, ``vpl_over_error``) are over the ``n_ok_3d`` usable
fixes that have a vertical solution (finite ``z``, and a truth ``z``): a usable fix
without one -- a 2-D method in a file that also holds a 3-D one, or a row whose ``z`` is
empty -- counts in the horizontal statistics only, and a method without any has NaN 3-D
and vertical statistics.

Rows: per tag (by name) the methods, ``baseline`` first and the others by name, then the
aggregates per method in the same order; the order of the positions' rows does not
matter.  Aggregate rows per method: ``tag = "all"`` pools the epochs of every tag (its counts are
the tags' sums); ``tag = "mean"`` is the mean of the per-tag statistics, which is how the
paper's Table 1 forms its "average over the points" rows, its counts (``n``,
``n_missing``, ``n_failed``, ``n_ok``, ...) included: per-tag means, which may be
fractional (``robustloc evaluate`` shows them as ``42.9/tag``); an error statistic of
that row is NaN when the method has no usable fix on some tag (the mean skipped those
tags, so methods were averaged over different tags: the self-calibration review).
Column ``aggregate`` is True on those rows only, so a real tag named ``all`` or ``mean``
stays apart from them.  ``mean_impr_pct`` and ``rms_impr_pct`` give the improvement over
the ``ls`` row (``baseline``) of the same tag, ``100 (ls - method) / ls``, when the
positions contain method ``ls``; NaN otherwise (``robustloc evaluate`` uses these names in
every output, and leaves them out of its text report when they are all NaN).

Matching: each positions row is paired with the truth row of the same ``tag`` whose
``time`` is nearest, if within ``time_tolerance_s`` (default 1e-6 s, i.e. equal times
written by the same program; raise it for logs whose fixes are stamped differently from
the truth).  Positions rows without truth are not scored; their count is in
``table.attrs["n_unmatched"]``.  Every truth epoch is scored for every method: one that no
positions row of the method matched is ``missing`` and failed.  Two positions rows with
the same ``(time, tag, method)`` are an error naming the second one's line, as duplicate
truth is.
"""

from __future__ import annotations

import numpy as np
import pandas as pd
from numpy.typing import NDArray

from robustloc import status as st
from robustloc.errors import InputError
from robustloc.io.tables import refuse_duplicate_truth

STAT_COLUMNS = ("max", "min", "mean", "rms", "sigma1", "median", "p95")
#: Integrity columns, when the positions carry ``hpl``: usable fixes whose horizontal
#: error exceeds their protection level (a NaN bound counts as exceeded), their share of
#: the usable fixes, the median ``hpl`` and its ratio to the median error (issue 10's
#: targets: at most 1 % misleading, a median bound at most 12x the median error).
INTEGRITY_COLUMNS = ("n_misleading", "misleading_pct", "hpl_median", "hpl_over_error")
#: Statistics of a tag's usable fixes (NaN without one): horizontal, 3-D, integrity and
#: the vertical bound's (the ``mean`` row averages them over every tag or none).
_USABLE_STATS = frozenset(
    (*STAT_COLUMNS, *(f"{c}_3d" for c in STAT_COLUMNS), *INTEGRITY_COLUMNS,
     "n_misleading_v", "misleading_pct_v", "vpl_median", "vpl_over_error"))


def match_truth(
    positions: pd.DataFrame, truth: pd.DataFrame, time_tolerance_s: float = 1e-6
) -> pd.DataFrame:
    """Positions with the matched truth columns ``x_true, y_true[, z_true]`` (NaN: none)
    and the matched truth row's number ``_truth_row``.  A positions column of one of
    those names (``z_true`` too, when the truth has no ``z``) is replaced: it ended the
    match in a KeyError, and a ``z_true`` of the positions would pass for the truth's.

    Raises
    ------
    InputError
        Duplicate ``(time, tag)`` in the truth, or duplicate ``(time, tag, method)`` in the
        positions, naming the line.
    """
    if time_tolerance_s < 0:
        raise ValueError(f"time tolerance must be >= 0, got {time_tolerance_s}")
    refuse_duplicate_truth(truth)  # a frame given directly, not through read_truth
    t = truth.copy()
    t["tag"] = t["tag"].astype(str)
    _refuse_duplicate_positions(positions)
    cols = ["x", "y"] + (["z"] if "z" in t.columns else [])
    t["_truth_row"] = np.arange(len(t))
    right = t[["time", "tag", "_truth_row"] + cols].rename(
        columns={c: f"{c}_true" for c in cols})
    right = right.sort_values("time", kind="stable").reset_index(drop=True)
    left = positions.drop(columns=[c for c in ("x_true", "y_true", "z_true", "_truth_row")
                                   if c in positions.columns])
    left["tag"] = left["tag"].astype(str)
    # the helper columns under names no positions column bears (an extra column _t_true
    # or _row was merged beside them, or overwritten)
    t_true, row = _free_name("_t_true", left.columns), _free_name("_row", left.columns)
    right[t_true] = right["time"]
    left[row] = np.arange(len(left))
    left = left.sort_values("time", kind="stable").reset_index(drop=True)
    merged = pd.merge_asof(
        left, right, on="time", by="tag", direction="nearest",
        tolerance=float(time_tolerance_s) if time_tolerance_s > 0 else None,
        allow_exact_matches=True,
    )
    if time_tolerance_s == 0:
        off = merged[t_true].to_numpy() != merged["time"].to_numpy()
        for c in cols:
            merged.loc[off, f"{c}_true"] = np.nan
        merged.loc[off, "_truth_row"] = np.nan
    merged = merged.sort_values(row).drop(columns=[row, t_true])
    merged.index = positions.index
    return merged


def _free_name(name: str, taken: pd.Index) -> str:
    """``name``, with underscores before it until no column of ``taken`` bears it."""
    while name in taken:
        name = "_" + name
    return name


def method_order(methods: object, baseline: str = "ls") -> list[str]:
    """The distinct ``methods`` in the order of the table's rows: ``baseline`` first when
    it is one of them, the others by name (it was the order of the file's rows, so the
    same rows in another order gave another table)."""
    names = sorted({str(m) for m in methods})  # type: ignore[attr-defined]
    return [baseline] * (baseline in names) + [m for m in names if m != baseline]


def check_baseline(baseline: str, methods: object, path: object = None) -> None:
    """Refuse a ``--baseline`` that is not one of the positions' ``methods`` (``ls``, the
    default, may be absent: its improvement columns are then empty)."""
    found = sorted({str(m) for m in methods})  # type: ignore[attr-defined]
    if baseline != "ls" and baseline not in found:
        raise InputError(f"--baseline {baseline!r} is not a method of this file "
                         f"(methods: {', '.join(found)})", path)


def _refuse_duplicate_positions(positions: pd.DataFrame) -> None:
    """Two rows with the same ``(time, tag, method)`` would count one epoch twice."""
    keys = ["time", "tag"] + (["method"] if "method" in positions.columns else [])
    k = positions[keys].copy()
    k["tag"] = k["tag"].astype(str)
    dup = k.duplicated().to_numpy()
    if dup.any():
        i = int(np.argmax(dup))
        line = int(positions.index[i]) if positions.index.name == "line" else None
        meth = f" and method {str(k['method'].iloc[i])!r}" if "method" in k else ""
        raise InputError(
            f"duplicate position for time {k['time'].iloc[i]}, tag {k['tag'].iloc[i]!r}"
            f"{meth} (each epoch once per method)", positions.attrs.get("path"), line,
        )


def epoch_errors(
    positions: pd.DataFrame, truth: pd.DataFrame, time_tolerance_s: float = 1e-6
) -> pd.DataFrame:
    """Per-row errors: the positions frame plus ``error_2d`` (m), ``error_3d`` and the
    vertical ``error_v`` (when both have ``z``), ``usable`` (bool) and ``matched`` (bool)."""
    m = match_truth(positions, truth, time_tolerance_s)
    x, y = m["x"].to_numpy(dtype=float), m["y"].to_numpy(dtype=float)
    xt, yt = m["x_true"].to_numpy(dtype=float), m["y_true"].to_numpy(dtype=float)
    # a fix of 1e308 against a truth of -1e308: a difference beyond the floats, inf (it
    # was counted failed, with a RuntimeWarning on stderr), the fix usable all the same
    with np.errstate(over="ignore"):
        dx, dy = x - xt, y - yt
        m["error_2d"] = np.hypot(dx, dy)
        if "z" in m.columns and "z_true" in m.columns:
            dz = m["z"].to_numpy(dtype=float) - m["z_true"].to_numpy(dtype=float)
            # NaN without a vertical solution (hypot(inf, NaN) is inf); hypot: the sum of
            # the squares of errors of 1e200 m overflowed
            m["error_3d"] = np.where(np.isnan(dz), np.nan, np.hypot(m["error_2d"], dz))
            m["error_v"] = np.abs(dz)
    status = m["status"].astype(str) if "status" in m.columns else pd.Series("ok", index=m.index)
    m["matched"] = np.isfinite(xt)
    m["usable"] = (status.isin(st.USABLE).to_numpy() & np.isfinite(x) & np.isfinite(y)
                   & np.isfinite(xt) & np.isfinite(yt))
    return m


def error_stats(errors: NDArray[np.float64]) -> dict[str, float]:
    """The statistics of :data:`STAT_COLUMNS` of one set of errors (NaN if empty).

    NaN errors are left out; an infinite one (a fix whose difference from the truth is
    beyond the floats) makes ``max``, ``mean``, ``rms`` and ``sigma1`` infinite, and
    ``median`` and ``p95`` where they reach it.

    The errors are sorted first, so each statistic depends on the set of errors and not
    on their order: ``evaluate --engine dask`` joins its partitions' errors in the
    dataset's order (by tag), the single process takes the file's, and their means
    differed in the last digit (2.403925181162548 against ...477, the Dask review).
    """
    e = np.asarray(errors, dtype=float)
    e = np.sort(e[~np.isnan(e)])
    if e.size == 0:
        return {k: float("nan") for k in STAT_COLUMNS}
    # every sum over the errors divided by the power of two at or below the largest (exact:
    # the digits of the unscaled formulas), then multiplied back: errors of 1e300 m
    # squared, and two of 1.4e308 m summed, overflowed (a RuntimeWarning on stderr, an
    # infinite mean, median or rms beside a finite max), where each is at most the max
    scale = _scale(e)
    u = e / scale
    mean = float(np.mean(u))
    inf = bool(np.isinf(e).any())  # (inf - inf: a NaN sigma1, and a warning)
    return {
        "max": float(e.max()),
        "min": float(e.min()),
        "mean": scale * mean,
        "rms": scale * float(np.sqrt(np.mean(u * u))),  # seed 000: sigma0
        "sigma1": np.inf if inf else scale * float(np.sqrt(np.mean((u - mean) ** 2))),
        "median": _median(e),
        "p95": _p95(e),
    }


def _p95(e: NDArray[np.float64]) -> float:
    """The 95th percentile of sorted errors ``e`` (none NaN), numpy's linear
    interpolation between the order statistics at ``h = 0.95 (n - 1)``; infinite where it
    reaches an infinite error (numpy's ``inf - inf`` made it NaN, with a warning)."""
    h = 0.95 * (e.size - 1)
    i = int(np.floor(h))
    if np.isinf(e[i]) or (h > i and np.isinf(e[i + 1])):
        return float("inf")
    return float(np.percentile(e, 95))  # (the order statistics it takes are finite)


def _scale(values: NDArray[np.float64]) -> float:
    """The power of two at or below the largest finite ``|value|`` (1 without one): the
    values divided by it are at most 2 in size, and exactly the values' digits."""
    v = np.abs(values[np.isfinite(values)])
    top = float(v.max()) if v.size else 0.0
    return float(np.ldexp(1.0, np.frexp(top)[1] - 1)) if top > 0 else 1.0


def _median(values: NDArray[np.float64]) -> float:
    """``np.median`` of the values scaled by :func:`_scale` (the mean of two middle values
    of 1.4e308 overflowed)."""
    scale = _scale(values)
    return scale * float(np.median(values / scale))


def _mean(values: NDArray[np.float64], skipna: bool = False) -> float:
    """The mean of the values scaled by :func:`_scale` (two of 1.4e308 overflowed); NaN
    if one is NaN, or with ``skipna`` if all are."""
    v = values[~np.isnan(values)] if skipna else values
    if v.size == 0 or np.isnan(v).any():
        return float("nan")
    scale = _scale(v)
    return scale * float(np.mean(v / scale))


def integrity_stats(errors: NDArray[np.float64], hpl: NDArray[np.float64]
                    ) -> dict[str, float]:
    """:data:`INTEGRITY_COLUMNS` of the usable fixes' horizontal errors and their
    ``hpl``.  A missing (NaN) bound counts as exceeded and an infinite one never is; the
    median takes a missing bound as infinite.  NaN statistics without usable fixes."""
    e = np.asarray(errors, dtype=float)
    h = np.asarray(hpl, dtype=float)
    if e.size == 0:
        return {k: float("nan") for k in INTEGRITY_COLUMNS}
    with np.errstate(invalid="ignore"):
        mis = int(np.sum(~(e <= h)))  # NaN: exceeded
    h = np.where(np.isnan(h), np.inf, h)
    med_h, med_e = _median(h), _median(e)
    with np.errstate(invalid="ignore", divide="ignore"):
        ratio = np.float64(med_h) / np.float64(med_e)  # a zero median error: inf (or NaN)
    return {"n_misleading": float(mis), "misleading_pct": 100.0 * mis / e.size,
            "hpl_median": float(med_h), "hpl_over_error": float(ratio)}


def _group_rows(df: pd.DataFrame, keys: dict[str, str], has3d: bool) -> dict[str, object]:
    ok = df["usable"].to_numpy()
    row: dict[str, object] = dict(keys)
    row["n"] = int(len(df))
    row["n_missing"] = int(df["missing"].sum()) if "missing" in df.columns else 0
    row["n_failed"] = int((~ok).sum())
    row["n_ok"] = int(ok.sum())
    row["failed_pct"] = 100.0 * row["n_failed"] / max(len(df), 1)
    row.update(error_stats(df["error_2d"].to_numpy()[ok]))
    if "hpl" in df.columns:
        row.update(integrity_stats(df["error_2d"].to_numpy()[ok],
                                   df["hpl"].to_numpy(dtype=float)[ok]))
    if has3d:
        # only the usable fixes with a vertical solution: one without z (a 2-D method
        # beside 3-D ones, or a row with z empty) has no 3-D error, and its NaN vertical
        # error was counted misleading (NaN <= vpl is false) while error_stats dropped it
        # from the 3-D statistics of the same row
        ok3 = ok & ~np.isnan(df["error_3d"].to_numpy(dtype=float))  # (inf: an overflow)
        row["n_ok_3d"] = int(ok3.sum())
        s3 = error_stats(df["error_3d"].to_numpy()[ok3])
        row.update({f"{k}_3d": v for k, v in s3.items()})
        if "vpl" in df.columns and "error_v" in df.columns:  # the vertical bound likewise
            iv = integrity_stats(df["error_v"].to_numpy()[ok3],
                                 df["vpl"].to_numpy(dtype=float)[ok3])
            row.update({k.replace("hpl", "vpl") + ("" if "hpl" in k else "_v"): v
                        for k, v in iv.items()})
    return row


def _missing_rows(e: pd.DataFrame, truth: pd.DataFrame, methods: list[str]) -> pd.DataFrame:
    """One failed row per (truth epoch, method) that no positions row of the matched rows
    ``e`` hit; ``methods``: every method of the positions, matched or not (a method whose
    rows all missed the truth has every truth epoch missing)."""
    t = truth.reset_index(drop=True)
    rows = []
    ids_of = {str(m): g["_truth_row"].to_numpy(dtype=float)
              for m, g in e.groupby("method", sort=False)}
    for meth in methods:
        hit = np.zeros(len(t), dtype=bool)
        ids = ids_of.get(meth, np.zeros(0))
        hit[ids[np.isfinite(ids)].astype(np.int64)] = True
        if (~hit).any():
            miss = t.loc[~hit, ["time", "tag"]].copy()
            miss["tag"] = miss["tag"].astype(str)
            miss["method"] = meth
            miss["status"] = "missing"
            rows.append(miss)
    if not rows:
        return e.iloc[:0].assign(missing=pd.Series(dtype=bool))
    out = pd.concat(rows, ignore_index=True)
    out["error_2d"] = np.nan
    for c in ("error_3d", "error_v"):
        if c in e.columns:
            out[c] = np.nan
    out["usable"] = False
    out["matched"] = True
    out["missing"] = True
    return out


def error_table(
    positions: pd.DataFrame,
    truth: pd.DataFrame,
    *,
    time_tolerance_s: float = 1e-6,
    baseline: str = "ls",
) -> pd.DataFrame:
    """Error statistics per tag and method, with aggregates and improvement over ``ls``.

    Parameters
    ----------
    positions : DataFrame
        Contract positions (``time, tag, x, y[, z], method, status, ...``); ``method``
        defaults to ``"unknown"``, ``status`` to ``"ok"`` when absent.
    truth : DataFrame
        Contract truth (``time, tag, x, y[, z]``).
    time_tolerance_s : float
        Largest time difference for a positions row to match a truth row of its tag.
    baseline : str
        Method the improvements are measured against (default ``ls``).

    Returns
    -------
    DataFrame
        One row per (tag, method) (tags by name, methods in :func:`method_order`: the
        baseline first), then per method ``tag = "all"`` (pooled epochs) and
        ``tag = "mean"`` (mean of the per-tag statistics, the paper's average rows).
        Columns: ``tag, method, n, n_missing, n_failed, n_ok, failed_pct, max, min, mean,
        rms, sigma1,
        median, p95`` (metres, horizontal), :data:`INTEGRITY_COLUMNS` when the positions
        have ``hpl``, ``n_ok_3d`` and the statistics with suffix ``_3d`` when both files
        have ``z`` (and then, with ``vpl``, the vertical bound's ``n_misleading_v,
        misleading_pct_v, vpl_median, vpl_over_error``; all over the ``n_ok_3d`` usable
        fixes with a vertical solution), ``mean_impr_pct, rms_impr_pct`` and
        ``aggregate`` (True on the ``all`` and ``mean`` rows: a tag may bear those names).
        ``attrs["n_unmatched"]``: rows without truth (not scored).
    """
    pos = positions.copy()
    if "method" not in pos.columns:
        pos["method"] = "unknown"
    if "status" not in pos.columns:
        pos["status"] = st.OK
    e = epoch_errors(pos, truth, time_tolerance_s)
    return error_table_from_errors(e, baseline=baseline, path=positions.attrs.get("path"),
                                   truth=truth)


def error_table_from_errors(
    errors: pd.DataFrame, *, baseline: str = "ls", path: str | None = None,
    truth: pd.DataFrame | None = None,
) -> pd.DataFrame:
    """The statistics of :func:`error_table` from the rows of :func:`epoch_errors`.

    Only ``tag, method, matched, usable, error_2d[, error_3d, error_v, hpl, vpl]`` are
    used, so per-row errors computed elsewhere (each partition of a dataset on a worker,
    then concatenated in the dataset's order) give the table of the whole.  ``path``
    names the positions in the error raised when no row matched.  With ``truth`` (the
    frame the errors were matched against), every truth epoch without a positions row
    counts as a failed, missing epoch.
    """
    e = errors
    n_unmatched = int((~e["matched"]).sum())
    # every method of the positions, also one none of whose rows met the truth (it was
    # left out of the table: its epochs all failed, not absent)
    all_methods = method_order(e["method"], baseline)
    e = e[e["matched"].to_numpy()].copy()
    if len(e) > 0 and truth is not None:
        e = pd.concat([e.assign(missing=False), _missing_rows(e, truth, all_methods)],
                      ignore_index=True)
    if len(e) == 0:
        raise InputError(
            "no positions row matches the truth by (time, tag); check the tags, or raise "
            "the time tolerance",
            path,
        )
    has3d = "error_3d" in e.columns
    e["method"] = e["method"].astype(str)
    rows = []
    methods = method_order(e["method"], baseline)
    tags = sorted(set(e["tag"]))
    for (tag, meth), grp in e.groupby(["tag", "method"], sort=False):
        rows.append(_group_rows(grp, {"tag": tag, "method": meth}, has3d))
    per = pd.DataFrame(rows)
    per["_m"] = per["method"].map({m: i for i, m in enumerate(methods)})
    per["_t"] = per["tag"].map({t: i for i, t in enumerate(tags)})
    per = per.sort_values(["_t", "_m"]).drop(columns=["_m", "_t"])
    agg = []
    for meth in methods:
        grp = e[e["method"] == meth]
        agg.append(_group_rows(grp, {"tag": "all", "method": meth}, has3d))
    for meth in methods:
        sub = per[per["method"] == meth]
        row: dict[str, object] = {"tag": "mean", "method": meth}
        for c in sub.columns:
            if c in ("tag", "method"):
                continue
            # an error statistic over every tag or none: a tag without a usable fix would
            # drop out of this method's mean only (apples to oranges with the others'),
            # horizontal, 3-D, and the protection levels' alike
            row[c] = _mean(sub[c].to_numpy(dtype=float), skipna=c not in _USABLE_STATS)
        agg.append(row)
    table = pd.concat([per, pd.DataFrame(agg)], ignore_index=True)
    for c in ("n", "n_missing", "n_failed", "n_ok", "n_ok_3d"):
        if c in table.columns:
            table[c] = table[c].astype(float)
    aggregate = np.r_[np.zeros(len(per), dtype=bool), np.ones(len(agg), dtype=bool)]
    # each row against the baseline's row of the same tag, aggregates against aggregates
    # (a real tag named "all" is not the pooled row)
    key = pd.MultiIndex.from_arrays([table["tag"].astype(str), aggregate])
    is_base = (table["method"] == baseline).to_numpy()
    for stat in ("mean", "rms"):
        ref = (pd.Series(table[stat].to_numpy()[is_base], index=key[is_base])
               .reindex(key).to_numpy(dtype=float))
        with np.errstate(invalid="ignore", divide="ignore"):
            table[f"{stat}_impr_pct"] = 100.0 * (ref - table[stat].to_numpy()) / ref
    table["aggregate"] = aggregate
    table.attrs["n_unmatched"] = n_unmatched
    return table
