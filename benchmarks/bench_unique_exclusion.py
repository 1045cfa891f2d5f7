"""Brown's unique-exclusion rule for the default ``auto``, measured (not adopted).

Snapshot RAIM's fault exclusion (Brown, Parkinson & Axelrad) excludes an observation only
when exactly one subset passes the test; when another exclusion of the same size passes
too, the fault is detected but not identified.  ``auto``
(:func:`robustloc.integrity.fixes.locate_protected`) calls a fix ``fault_excluded`` when
the test of the observations it kept passes, without asking whether another choice passes
as well.  This script finds, on every shared real data set (the report's epochs: every
k-th, at most 1 500 per set), the ``fault_excluded`` fixes for which some other subset of
the heard observations of the same size passes the same global test (Gauss-Newton on the
subset with the fix's per-anchor sigma, ``T = sum (v / sigma)^2`` against the fix's own
critical value), and scores two treatments of them:

* ``ambiguous -> unavailable``: the textbook rule, no usable fix;
* ``ambiguous -> all-in-view nls``: the plain fit of every heard observation kept as a
  usable fix (which the majority rule of the module, item 6, would refuse where half the
  heard observations are flagged).

Measured 2026-12-06 (``../shared/data``): ambiguous fixes on the corridor (4), uwb-dwm1001
LOS (3), uwb-labyrinth (1) and ble-tetam (3).  ``unavailable`` takes labyrinth's RMS from
0.2102 to 0.1973 m but its availability from 98.3 to 96.6 % (the best peer's: 98.3 %);
the all-in-view fit gives 0.2006 m at 98.3 %, only by calling usable a fix the majority
rule refuses.  Neither is adopted (the session note of 2026-12-06).  After the robust fits'
convergence test (later on 2026-12-06) the labyrinth's ambiguous epoch is no longer
``fault_excluded`` (the default gives 0.1973 m at 96.6 % there, with no ambiguous
epoch left).

Usage::

    python benchmarks/bench_unique_exclusion.py                     # every data set
    python benchmarks/bench_unique_exclusion.py --sets uwb-labyrinth --data ../shared/data
"""

from __future__ import annotations

import itertools

import numpy as np
from _real_sets import cases, show  # (benchmarks/_real_sets.py)

from robustloc import status as st
from robustloc.estimators.ranging import Locator
from robustloc.eval.realdata import error_stats
from robustloc.integrity.fixes import locate_protected


def ambiguous_rows(case, sol, rows: np.ndarray) -> list[int]:
    """The table's ``fault_excluded`` epochs where another exclusion of the same size
    passes the fix's own global test."""
    V = case.values
    sig = np.asarray(sol.extra["sigma_obs"], dtype=float)
    kept_all = np.asarray(sol.extra["test_kept"])
    out = []
    for i in np.intersect1d(np.flatnonzero(sol.status == st.FAULT_EXCLUDED), rows):
        heard = np.flatnonzero(np.isfinite(V[i]))
        kept = kept_all[i]
        k = int(kept[heard].sum())
        s_i = np.nan_to_num(sig[i], nan=1.0)
        loc = Locator("nls", sigma=tuple(s_i), robust_scale="apriori")
        ho = case.height_offset
        for sub in itertools.combinations(heard, k):
            mask = np.zeros(V.shape[1], dtype=bool)
            mask[list(sub)] = True
            if np.array_equal(mask[heard], kept[heard]):
                continue
            alt = loc.solve(case.xy, np.where(mask, V[i], np.nan)[None], case.kind,
                            A=case.A, n=case.n, height_offset=ho)
            v = np.asarray(alt.extra["range_residuals"])[0]
            T = np.nansum((v / s_i) ** 2)
            if np.isfinite(T) and T <= sol.extra["test_critical"][i]:
                out.append(int(i))
                break
    return out


def main(argv: list[str] | None = None) -> int:
    args, sets = cases(__doc__, argv)
    table = []
    for case, R in sets:
        kw = dict(A=case.A, n=case.n, height_offset=case.height_offset)
        sol = locate_protected(Locator("auto"), case.xy, case.values, case.kind, **kw)
        raw = Locator("nls").solve(case.xy, case.values, case.kind, **kw)
        amb = ambiguous_rows(case, sol, R)
        use = st.among(sol.status, st.USABLE)
        pos_all, use_all = sol.position.copy(), use.copy()
        pos_all[amb] = raw.position[amb]
        use_all[amb] = np.all(np.isfinite(raw.position[amb]), axis=1)
        use_none = use.copy()
        use_none[amb] = False
        n_fe = int(np.isin(R, np.flatnonzero(sol.status == st.FAULT_EXCLUDED)).sum())
        for name, pos, u in (("auto (as shipped)", sol.position, use),
                             ("ambiguous -> unavailable", sol.position, use_none),
                             ("ambiguous -> all-in-view nls", pos_all, use_all)):
            s = error_stats(pos[R], case.truth[R], u[R])
            table.append({"data set": f"{case.name} ({case.source})", "variant": name,
                          "rms_m": s["rms"], "p95_m": s["p95"],
                          "availability": s["availability"], "fault_excluded": n_fe,
                          "ambiguous": len(amb)})
    show(table, args.out, ".4f")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
