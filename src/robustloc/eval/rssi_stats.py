"""Statistics of RSSI samples, per anchor and per distance bin (seed 002, sec. 2, Table 1).

The paper characterizes static RSSI at one AP by its mean, variance, skewness
``alpha = E(x - mu)^3 / sigma^3`` and kurtosis ``beta = E(x - mu)^4 / sigma^4`` (Pearson's,
``beta = 3`` for a normal law), the correlation of the variance with distance (0.578) and the
lag after which the autocorrelation falls below 0.2 (8 samples).  :class:`RssiStatistics`
computes the same quantities for every anchor of a measurements table and, when the truth
is known, for every (anchor, distance bin), plus a normality test.

Conventions
-----------
* ``variance`` is the sample variance (``ddof = 1``); skewness and kurtosis use the
  population moments of the paper's formulas (``scipy.stats.skew`` and
  ``scipy.stats.kurtosis(fisher=False)`` with their default ``bias=True``).
* The autocorrelation at lag ``k`` (in samples, not seconds: real logs are irregular) is
  the pooled biased estimator over the contiguous runs of a group,
  ``r(k) = sum_runs sum_t c_t c_{t+k} / sum c_t^2`` with ``c`` the values minus the group
  mean; for a single run it is ``statsmodels.tsa.stattools.acf(x, adjusted=False)``.
  Per anchor, when the truth is known, ``c`` is the RSSI minus the mean of its distance
  bin, so the distance trend of a moving tag does not pass for correlation.
* The residual variance per anchor divides the squared residuals about the bin means by
  ``n - (number of bins)``: each bin mean is fitted.  Only the bins of at least
  ``min_samples`` samples count (a 1-sample bin's residual is 0 whatever the noise).
* Normality: D'Agostino-Pearson ``scipy.stats.normaltest`` (needs 8 samples) and
  Shapiro-Wilk ``scipy.stats.shapiro`` (3 to 5000 samples); p-values, NaN when the group is
  too small.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd
from numpy.typing import ArrayLike, NDArray
from scipy import stats

from robustloc.errors import InputError
from robustloc.io.limits import LIMITS
from robustloc.io.tables import refuse_duplicate_truth
from robustloc.options import MAX_LAG

Array = NDArray[np.float64]


# ---------------------------------------------------------------------------------------
# building blocks
# ---------------------------------------------------------------------------------------


def moments(x: ArrayLike) -> dict[str, float]:
    """Mean, sample variance, Pearson skewness and kurtosis of ``x`` (seed 002, Table 1).

    Returns NaN entries when fewer than 2 finite values (skewness and kurtosis also NaN
    for a constant sample).
    """
    v = np.asarray(x, dtype=float)
    v = v[np.isfinite(v)]
    n = v.size
    if n < 2:
        mean = float(v.mean()) if n else float("nan")
        return {"n": n, "mean": mean, "variance": float("nan"), "skewness": float("nan"),
                "kurtosis": float("nan")}
    mu = v.mean()
    c = v - mu
    m2 = np.mean(c * c)
    with np.errstate(invalid="ignore", divide="ignore"):
        skew = np.mean(c**3) / m2**1.5 if m2 > 0 else np.nan  # alpha = E(x-mu)^3 / sigma^3
        kurt = np.mean(c**4) / m2**2 if m2 > 0 else np.nan  # beta = E(x-mu)^4 / sigma^4
    return {"n": n, "mean": float(mu), "variance": float(c @ c / (n - 1)),
            "skewness": float(skew), "kurtosis": float(kurt)}


def autocorrelation(
    x: ArrayLike, max_lag: int, runs: ArrayLike | None = None, center: float | None = None
) -> Array:
    """Pooled biased autocorrelation ``r(0..max_lag)`` of ``x`` over contiguous runs.

    Parameters
    ----------
    x : array_like, shape (n,)
        Values in time order (within each run).
    max_lag : int
        Largest lag (samples).
    runs : array_like, shape (n,), optional
        Run label of each value; products across two runs are not counted.  Default: one
        run (then ``r`` equals ``statsmodels`` ``acf(x, adjusted=False)``).
    center : float, optional
        Value subtracted before the products; default the mean of ``x``.

    Returns
    -------
    ndarray, shape (max_lag + 1,)
        ``r(0) = 1``; NaN beyond the longest run or for a constant sample.
    """
    v = np.asarray(x, dtype=float)
    if max_lag < 0:
        raise ValueError(f"max_lag must be >= 0, got {max_lag}")
    r = np.full(max_lag + 1, np.nan)
    if v.size == 0:
        return r
    c = v - (np.mean(v) if center is None else center)
    den = c @ c
    if not den > 0:
        return r
    lab = np.zeros(v.size, dtype=np.int64) if runs is None else pd.factorize(
        np.asarray(runs))[0]
    for k in range(min(max_lag, v.size - 1) + 1):
        same = lab[k:] == lab[: v.size - k]
        if k and not same.any():
            break
        r[k] = np.sum(c[: v.size - k] * c[k:] * same) / den
    return r


def decorrelation_lag(acf: ArrayLike, threshold: float = 0.2) -> float:
    """First lag where the autocorrelation drops below ``threshold`` (NaN if never).

    The paper finds 8 samples at 0.2 (seed 002, sec. 2): average more than that many.
    """
    r = np.asarray(acf, dtype=float)
    below = np.flatnonzero(r < threshold)
    return float(below[0]) if below.size else float("nan")


def normality(x: ArrayLike) -> dict[str, float]:
    """p-values of D'Agostino-Pearson (``normaltest``) and Shapiro-Wilk tests."""
    v = np.asarray(x, dtype=float)
    v = v[np.isfinite(v)]
    out = {"normaltest_p": float("nan"), "shapiro_p": float("nan")}
    if v.size < 3 or np.ptp(v) == 0:
        return out
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        if v.size >= 8:
            out["normaltest_p"] = float(stats.normaltest(v).pvalue)
        if v.size <= 5000:
            out["shapiro_p"] = float(stats.shapiro(v).pvalue)
    return out


def truth_distances(
    measurements: pd.DataFrame, anchors: pd.DataFrame, truth: pd.DataFrame
) -> Array:
    """True tag-anchor distance of every measurement row (truth interpolated in time).

    The truth position of the row's tag is linearly interpolated at the row's time, within
    the tag's truth time span ``[t_min, t_max]`` (ends included, no tolerance); 3-D when
    both anchors and truth have ``z``.  Rows outside that span get NaN (the truth is not
    extrapolated: a moving tag is not held at its last known position), as do rows whose
    tag has no truth.  A tag with a single truth row is a static point: that position
    applies at every time (a survey point; give two rows to bound it in time).

    Parameters
    ----------
    measurements : DataFrame
        ``time, tag, anchor`` per row.
    anchors : DataFrame
        ``anchor, x, y[, z]``.
    truth : DataFrame
        ``time, tag, x, y[, z]``.

    Returns
    -------
    ndarray, shape (n,)
        Distance in metres, NaN where the row has no truth.

    Raises
    ------
    InputError
        Duplicate ``(time, tag)`` in the truth (see
        :func:`robustloc.io.tables.refuse_duplicate_truth`), or an anchor id not in the
        anchors.
    """
    refuse_duplicate_truth(truth)
    n = len(measurements)
    pos = np.full((n, 3), np.nan)
    use_z = "z" in anchors.columns and "z" in truth.columns
    dims = ["x", "y", "z"] if use_z else ["x", "y"]
    mt = measurements["time"].to_numpy(dtype=float)
    mtag = measurements["tag"].astype(str).to_numpy()
    for tag, grp in truth.groupby(truth["tag"].astype(str), sort=False):
        rows = np.flatnonzero(mtag == tag)
        if rows.size == 0:
            continue
        g = grp.sort_values("time")
        tt = g["time"].to_numpy(dtype=float)
        if tt.size > 1:  # two rows or more: only within their span, never extrapolated
            rows = rows[(mt[rows] >= tt[0]) & (mt[rows] <= tt[-1])]
        for j, c in enumerate(dims):
            pos[rows, j] = np.interp(mt[rows], tt, g[c].to_numpy(dtype=float))
    idx = pd.Index(anchors["anchor"].astype(str)).get_indexer(
        measurements["anchor"].astype(str))
    if (idx < 0).any():
        i = int(np.argmax(idx < 0))
        raise InputError(
            f"unknown anchor id {measurements['anchor'].iloc[i]!r} (not in the anchors)",
            measurements.attrs.get("path"),
            int(measurements.index[i]) if measurements.index.name == "line" else None,
        )
    apos = anchors[dims].to_numpy(dtype=float)[idx]
    return np.sqrt(np.sum((pos[:, : len(dims)] - apos) ** 2, axis=1))


# ---------------------------------------------------------------------------------------
# the analysis
# ---------------------------------------------------------------------------------------


@dataclass(frozen=True)
class RssiStatsResult:
    """Tables of :meth:`RssiStatistics.compute`.

    Attributes
    ----------
    per_anchor : DataFrame
        One row per anchor: ``anchor, n, mean, variance, skewness, kurtosis,
        decorrelation_lag, normaltest_p, shapiro_p``; with truth also the moments of the
        residuals about their distance-bin means, over the anchor's bins in ``per_bin``
        (``resid_n`` samples in ``resid_bins`` bins; ``resid_variance`` divides by
        ``resid_n - resid_bins``, one degree of freedom per fitted bin mean;
        ``resid_skewness, resid_kurtosis``: the noise without the distance trend; NaN
        without a bin of ``min_samples``) and ``distance_min/max_m``.  The summary's
        skewness and kurtosis are the residual ones when present.
    per_bin : DataFrame or None
        With truth: one row per (anchor, distance bin) of at least ``min_samples``
        samples: ``anchor, distance_m`` (the bin's centre ``k w``; it holds the distances
        in ``[(k - 1/2) w, (k + 1/2) w)``, so the first bin, ``0``, those below ``w / 2``)
        and the same statistics.
    acf : DataFrame
        Autocorrelation per anchor: index lag, one column per anchor.
    variance_distance_corr : float
        Pearson correlation of the per-bin variance with the bin distance (paper: 0.578);
        NaN without truth or with fewer than 3 distinct bin distances in ``per_bin``.
    samples : DataFrame
        The samples analysed (``tag, anchor, time, rssi`` and ``distance_m`` with truth),
        for the histograms.
    invalid_measurement, n_without_truth, n_outside_truth_span : int
        Rows left out: RSSI outside the physical limits; with truth, rows of plausible RSSI
        whose tag has no truth, and those outside their tag's truth time span (see
        :func:`truth_distances`).  Disjoint counts.
    """

    per_anchor: pd.DataFrame
    per_bin: pd.DataFrame | None
    acf: pd.DataFrame
    variance_distance_corr: float
    samples: pd.DataFrame
    #: RSSI values outside the physical limits (-150 .. +30 dBm), left out and counted
    invalid_measurement: int = 0
    #: With truth: rows (of plausible RSSI) whose tag has no truth, left out and counted
    n_without_truth: int = 0
    #: With truth: rows (of plausible RSSI) outside their tag's truth time span, left out
    #: and counted (the truth is not extrapolated)
    n_outside_truth_span: int = 0

    def write_csv(self, out_dir: Path) -> list[Path]:
        """Write ``per_anchor.csv``, ``per_bin.csv`` (with truth) and ``acf.csv``."""
        out_dir = Path(out_dir)
        out_dir.mkdir(parents=True, exist_ok=True)
        paths = [out_dir / "per_anchor.csv"]
        self.per_anchor.to_csv(paths[0], index=False)
        if self.per_bin is not None:
            paths.append(out_dir / "per_bin.csv")
            self.per_bin.to_csv(paths[-1], index=False)
        paths.append(out_dir / "acf.csv")
        self.acf.to_csv(paths[-1], index_label="lag")
        return paths

    def summary(self) -> dict[str, object]:
        """Headline numbers (JSON-serializable; None where NaN).

        The shares of anchors (``share_anchors_left_skewed``,
        ``share_anchors_normal_rejected_5pct``) are over the anchors with a skewness and
        with a normality p-value (``n_anchors_normality_tested``: 8 samples or more, not
        constant), None without any.  ``median_skewness``, ``median_kurtosis`` and
        ``share_anchors_left_skewed`` are of the residuals about the bin means where there
        are bins (``moments_of``: ``residuals``), else of the RSSI values (``rssi``).
        """
        pa = self.per_anchor
        sk = "resid_skewness" if "resid_skewness" in pa.columns else "skewness"
        ku = "resid_kurtosis" if "resid_kurtosis" in pa.columns else "kurtosis"
        p = pa["normaltest_p"].to_numpy(dtype=float)
        return {
            # which moments the medians and the share are of (the per-anchor CSV has both)
            "moments_of": "residuals" if sk == "resid_skewness" else "rssi",
            "n_samples": int(pa["n"].sum()),
            "n_anchors": int(len(pa)),
            "median_skewness": _f(pa[sk].median()),
            "median_kurtosis": _f(pa[ku].median()),
            "median_decorrelation_lag": _f(pa["decorrelation_lag"].median()),
            # likewise over the anchors with a skewness (not constant, 2 samples or more)
            "share_anchors_left_skewed": _f((pa[sk][np.isfinite(pa[sk])] < 0).mean())
            if np.isfinite(pa[sk]).any() else None,
            # over the anchors the test could judge (8 samples, not constant): an untestable
            # one counted as not rejected
            "share_anchors_normal_rejected_5pct": _f((p[np.isfinite(p)] < 0.05).mean())
            if np.isfinite(p).any() else None,
            "n_anchors_normality_tested": int(np.isfinite(p).sum()),
            "variance_distance_corr": _f(self.variance_distance_corr),
            "n_bins": 0 if self.per_bin is None else int(len(self.per_bin)),
            "invalid_measurement": int(self.invalid_measurement),
            "n_without_truth": int(self.n_without_truth),
            "n_outside_truth_span": int(self.n_outside_truth_span),
        }


def _residual_moments(resid: Array, bins: NDArray[np.float64]) -> dict[str, float]:
    """Moments of one anchor's residuals about their distance-bin means (the bins of
    ``per_bin``): ``resid_n`` samples in ``resid_bins`` bins, ``resid_variance``
    ``sum r^2 / (n - bins)`` (one degree of freedom per fitted bin mean: ``ddof = 1`` was
    biased low, by half with 2-sample bins), ``resid_skewness`` and ``resid_kurtosis``
    the population moments as :func:`moments` (the residuals' mean is 0); NaN without a
    bin."""
    n, k = int(resid.size), int(np.unique(bins).size)
    mr = moments(resid)
    var = float(resid @ resid / (n - k)) if n > k else float("nan")
    return {"resid_n": n, "resid_bins": k, "resid_variance": var,
            "resid_skewness": mr["skewness"], "resid_kurtosis": mr["kurtosis"]}


def _f(v: object) -> float | None:
    v = float(v)  # type: ignore[arg-type]
    return None if not np.isfinite(v) else v


class RssiStatistics:
    """RSSI statistics per anchor and per distance bin (seed 002, sec. 2, Table 1).

    Parameters
    ----------
    max_lag : int
        Largest autocorrelation lag, in samples (default 30; at most :data:`MAX_LAG`).
    bin_width_m : float
        Width ``w`` of the distance bins (default 1 m, the paper's 1..8 m steps); bins are
        centred on multiples of the width, a distance ``d`` in the bin
        ``floor(d / w + 1/2) w`` (halves rounded up).
    threshold : float
        Autocorrelation level for the decorrelation lag (paper: 0.2).
    min_samples : int
        Bins with fewer samples are dropped from ``per_bin`` (default 10).
    """

    def __init__(
        self, max_lag: int = 30, bin_width_m: float = 1.0, threshold: float = 0.2,
        min_samples: int = 10,
    ) -> None:
        if not 1 <= max_lag <= MAX_LAG:
            raise ValueError(f"max_lag must lie in [1, {MAX_LAG}], got {max_lag}")
        if not (np.isfinite(bin_width_m) and bin_width_m > 0):
            raise ValueError(f"bin_width_m must be positive and finite, got {bin_width_m}")
        if min_samples < 2:
            raise ValueError(f"min_samples must be >= 2, got {min_samples}")
        if not 0.0 < threshold < 1.0:
            raise ValueError(f"threshold must lie in (0, 1), got {threshold}")
        self.max_lag = int(max_lag)
        self.bin_width_m = float(bin_width_m)
        self.threshold = float(threshold)
        self.min_samples = int(min_samples)

    def compute(
        self, measurements: pd.DataFrame, anchors: pd.DataFrame | None = None,
        truth: pd.DataFrame | None = None,
    ) -> RssiStatsResult:
        """Analyse a measurements frame (``time, tag, anchor, rssi``).

        ``truth`` requires ``anchors`` (for the distances).  With truth, only the rows with
        a true distance are analysed (:func:`truth_distances`: a tag in the truth, a time
        within its truth span); the others are counted in ``n_without_truth`` and
        ``n_outside_truth_span``.
        """
        if "rssi" not in measurements.columns:
            raise InputError("measurements have no 'rssi' column: statistics need RSSI",
                             measurements.attrs.get("path"))
        if truth is not None and anchors is None:
            raise InputError("--truth needs --anchors (anchor positions give the distances)")
        df = pd.DataFrame({
            "tag": measurements["tag"].astype(str).to_numpy(),
            "anchor": measurements["anchor"].astype(str).to_numpy(),
            "time": measurements["time"].to_numpy(dtype=float),
            "rssi": measurements["rssi"].to_numpy(dtype=float),
        })
        if truth is not None:
            df["distance_m"] = truth_distances(measurements, anchors, truth)
            truth_tags = set(truth["tag"].astype(str))
            df["_tag_in_truth"] = df["tag"].isin(truth_tags)
            if not np.isfinite(df["distance_m"]).any():
                mt = sorted(set(df["tag"]))[:5]
                tt = sorted(truth_tags)[:5]
                raise InputError(
                    "no measurement has a truth position: " + (
                        "none lies within its tag's truth time span (the truth is not "
                        "extrapolated)" if df["_tag_in_truth"].any() else
                        f"the measurements' tags {mt} and the truth's tags {tt} have none "
                        "in common"),
                    truth.attrs.get("path"))
        finite = np.isfinite(df["rssi"].to_numpy())
        plausible = LIMITS["rssi"].check(df["rssi"].to_numpy())
        n_invalid = int((finite & ~plausible).sum())
        df = df[plausible].sort_values(["anchor", "tag", "time"],
                                                     kind="mergesort").reset_index(drop=True)
        if df.empty:
            raise InputError("no RSSI sample within the physical limits to analyse ("
                             f"{LIMITS['rssi'].describe()}; {n_invalid} outside)"
                             if n_invalid else "no finite RSSI sample to analyse",
                             measurements.attrs.get("path"))

        per_bin = None
        corr = float("nan")
        n_no_tag = n_outside = 0
        if truth is not None:
            ok = np.isfinite(df["distance_m"].to_numpy())
            in_truth = df.pop("_tag_in_truth").to_numpy(dtype=bool)
            n_no_tag = int((~in_truth).sum())
            n_outside = int((in_truth & ~ok).sum())
            df = df[ok].reset_index(drop=True)
            if df.empty:
                raise InputError(
                    f"no RSSI sample within the physical limits has a truth position "
                    f"({n_no_tag} of tags without truth, {n_outside} outside their tag's "
                    f"truth time span, {n_invalid} outside the limits)",
                    measurements.attrs.get("path"))
            w = self.bin_width_m
            # bin k holds [(k - 1/2) w, (k + 1/2) w) and is labelled k w, half up: np.round
            # (half to even) with a floor of 1 put 3 m and 5 m into one "4 m" bin of width
            # 2, and 1 .. 7 m into "100 m" with --bin-width 100
            df["bin_m"] = np.floor(df["distance_m"].to_numpy() / w + 0.5) * w
            rows = []
            for (anchor, b), g in df.groupby(["anchor", "bin_m"], sort=True):
                if len(g) < self.min_samples:
                    continue
                # the label k w to 12 significant digits: 111 x 0.1 is 11.100000000000001
                rows.append({"anchor": anchor, "distance_m": float(f"{b:.12g}"),
                             **self._stats(g["rssi"].to_numpy(), None),
                             "decorrelation_lag": self._lag(*_series(g, g["rssi"]))})
            # no bin with min_samples: the table's columns all the same (its CSV was one
            # empty line, and `robustloc stats` ended in a KeyError printing it)
            per_bin = pd.DataFrame(rows, columns=[
                "anchor", "distance_m", *moments(np.empty(0)), "decorrelation_lag",
                *normality(np.empty(0))])
            # over 3 distinct distances at least: one bin's anchors alone made numpy divide
            # 0 by 0 (a warning on stderr) for a NaN
            if per_bin["distance_m"].nunique() >= 3 and per_bin["variance"].std() > 0:
                corr = float(np.corrcoef(per_bin["distance_m"], per_bin["variance"])[0, 1])
            by_bin = df.groupby(["anchor", "bin_m"])["rssi"]
            resid = (df["rssi"] - by_bin.transform("mean")).to_numpy()
            # the residual moments use the bins of per_bin only: a 1-sample bin's residual
            # is 0 whatever the noise
            kept = (by_bin.transform("size") >= self.min_samples).to_numpy()
        else:
            resid = df["rssi"].to_numpy()

        rows = []
        acfs = {}
        for anchor, g in df.groupby("anchor", sort=True):
            idx = g.index.to_numpy()
            row = {"anchor": anchor, **self._stats(g["rssi"].to_numpy(), None)}
            x, runs = _series(g, resid[idx], gaps=False)
            r = autocorrelation(x, self.max_lag, runs=runs,
                                center=None if truth is None else 0.0)
            row["decorrelation_lag"] = decorrelation_lag(r, self.threshold)
            if truth is not None:
                row.update(_residual_moments(resid[idx][kept[idx]],
                                             g["bin_m"].to_numpy()[kept[idx]]))
                row["distance_min_m"] = float(g["distance_m"].min())
                row["distance_max_m"] = float(g["distance_m"].max())
            rows.append(row)
            acfs[anchor] = r
        per_anchor = pd.DataFrame(rows)
        acf = pd.DataFrame(acfs, index=pd.RangeIndex(self.max_lag + 1, name="lag"))
        return RssiStatsResult(per_anchor, per_bin, acf, corr, df, n_invalid, n_no_tag,
                               n_outside)

    def _lag(self, x: Array, runs: ArrayLike) -> float:
        """The decorrelation lag of a series in runs."""
        return decorrelation_lag(autocorrelation(x, self.max_lag, runs=runs), self.threshold)

    def _stats(self, x: Array, runs: ArrayLike | None) -> dict[str, float]:
        out: dict[str, float] = dict(moments(x))
        if runs is not None:
            out["decorrelation_lag"] = self._lag(x, runs)
        out.update(normality(x))
        return out


def _series(g: pd.DataFrame, values: ArrayLike, gaps: bool = True
            ) -> tuple[Array, NDArray[np.int64]]:
    """One anchor's rows ``g`` (sorted by tag and time, indexed by their position in the
    anchor-sorted frame) as the time series the autocorrelation takes: one value per tag
    and time, the mean of the readings that share them (as every other command averages
    them, :func:`robustloc.io.to_epochs`), and its runs: a new run where the tag changes,
    and with ``gaps`` where rows of the frame were skipped (a bin that the tag left and
    entered again).  Readings of one link at one time were separate samples in file order,
    so the autocorrelation depended on the rows' order (the input-order review,
    2026-12-07: ``median_decorrelation_lag`` 2.0 or 2.5 for the same ble-tetam rows)."""
    v = np.asarray(values, dtype=float)
    tag = g["tag"].to_numpy()
    time = g["time"].to_numpy(dtype=float)
    pos = g.index.to_numpy()
    new = np.r_[True, (tag[1:] != tag[:-1]) | (time[1:] != time[:-1])]
    start = np.flatnonzero(new)
    x = np.add.reduceat(v, start) / np.diff(np.r_[start, v.size])
    run_start = tag[start][1:] != tag[start][:-1]
    if gaps:  # the first row of a series point must follow the last of the one before
        last = np.r_[start[1:] - 1, v.size - 1]
        run_start |= pos[start][1:] != pos[last][:-1] + 1
    return x, np.cumsum(np.r_[True, run_start])


# ---------------------------------------------------------------------------------------
# figures
# ---------------------------------------------------------------------------------------


#: ``histograms.png`` draws at most this many anchors (the first by name; it drew 16 and
#: did not say so): 8 rows of 6 panels.  ``per_anchor.csv`` has every anchor.
MAX_HISTOGRAMS = 48
#: ``autocorrelation.png`` names at most this many anchors in its legend (10 colours times
#: 4 line styles: every curve told apart; it named none beyond 12, silently).
MAX_ACF_LEGEND = 40


def plot_histograms(result: RssiStatsResult, path: Path,
                    max_panels: int = MAX_HISTOGRAMS) -> Path:
    """Histogram of the RSSI of each anchor with the fitted normal density (PNG).

    Every anchor up to ``max_panels`` (4 panels a row, 6 beyond 16 anchors); with more,
    the first ``max_panels`` by name, and the figure's title says so.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    every = list(result.per_anchor["anchor"])
    anchors = every[:max_panels]
    n = len(anchors)
    cols = min(4 if n <= 16 else 6, n)
    rows = int(np.ceil(n / cols))
    fig, axes = plt.subplots(rows, cols, figsize=(3.2 * cols, 2.6 * rows), squeeze=False)
    if len(every) > n:
        fig.suptitle(f"the first {n} of {len(every)} anchors (by name); per_anchor.csv "
                     "has every one", fontsize=10)
    s = result.samples
    for ax, a in zip(axes.ravel(), anchors):
        v = s.loc[s["anchor"] == a, "rssi"].to_numpy()
        lo, hi = np.floor(v.min()) - 0.5, np.ceil(v.max()) + 0.5
        ax.hist(v, bins=np.arange(lo, hi + 1.0), density=True, color="0.6")
        mu, sd = v.mean(), v.std()
        if sd > 0:
            t = np.linspace(lo, hi, 200)
            ax.plot(t, stats.norm.pdf(t, mu, sd), "r-", lw=1)
        row = result.per_anchor.set_index("anchor").loc[a]
        ax.set_title(f"{a}: skew {row['skewness']:.2f}, kurt {row['kurtosis']:.2f}",
                     fontsize=8)
        ax.set_xlabel("RSSI (dBm)", fontsize=8)
    for ax in axes.ravel()[n:]:
        ax.axis("off")
    fig.tight_layout()
    path = Path(path)
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path


def plot_autocorrelation(result: RssiStatsResult, path: Path, threshold: float = 0.2) -> Path:
    """Autocorrelation of each anchor's RSSI against the lag, with the threshold (PNG).

    The legend, beside the axes, names up to :data:`MAX_ACF_LEGEND` anchors; with more,
    the title says they are in ``acf.csv``.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    n = len(result.acf.columns)
    named = n <= MAX_ACF_LEGEND
    ncol = int(np.ceil(n / 20)) if named else 0  # a legend column per 20 anchors
    fig, ax = plt.subplots(figsize=(6.4 + 1.2 * ncol, 3.8))
    for i, a in enumerate(result.acf.columns):
        # 10 colours, then another line style: 40 curves told apart in the legend
        ax.plot(result.acf.index, result.acf[a], lw=1, label=str(a), color=f"C{i % 10}",
                ls=("-", "--", ":", "-.")[i // 10 % 4])
    ax.axhline(threshold, color="k", ls="--", lw=1)
    ax.set_xlabel("lag (samples)")
    ax.set_ylabel("autocorrelation")
    if named:  # beside the axes, not over the curves (it was left out beyond 12 anchors)
        ax.legend(fontsize=7, ncol=ncol, loc="upper left", bbox_to_anchor=(1.01, 1.0))
    else:
        ax.set_title(f"{n} anchors: too many to name (acf.csv has each)", fontsize=9)
    fig.tight_layout()
    path = Path(path)
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path
