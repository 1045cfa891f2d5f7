"""What the default ``auto`` does with a fix whose test flags an observation, measured.

``auto`` (:func:`robustloc.integrity.fixes.locate_protected`) solves every epoch by plain
Gauss-Newton with the log's per-anchor scale and tests it.  An epoch whose global test
fails is refitted by Huber.  An epoch whose w-test flags an observation while the test of
the rest passes (``extra["flags_kept"]``; status ``fault_detected`` since 2026-12-04,
``fault_excluded`` before) keeps the plain fix, flagged observation and all, with the
bound of that fix.  Two textbook alternatives for those epochs, measured
here on every shared real data set on the report's epochs (``s05``: every k-th epoch, at
most 1 500 per set), against the best scipy / statsmodels peer
(:func:`robustloc.eval.realdata.peer_fixes`):

* ``refit huber``: those epochs refitted by Huber with the log's scale,
  like the failed ones;
* ``snooping``: the flagged observations removed and the epoch re-solved by Gauss-Newton
  (data snooping, seed 003: exclude what the w-test identifies).

Every variant then takes the log's side of nearly collinear anchors (item 7 of
:mod:`robustloc.integrity.fixes`) as the default does, so the rows differ only in those
epochs.  Columns: RMS and p95 of the 2-D error over the usable fixes in metres
(``rms_m``, ``p95_m``), availability, the number of those epochs in the table's rows
(``n_flagged``).

Measured (2026-12-02, again 2026-12-03 with the same verdicts, ``../shared/data``):
snooping is worse on every WiFi room and on ble-tetam (the flagged range is rarely the
only wrong one, and dropping it leaves the others unaveraged); the Huber refit helps the
corridor and ble-tetam but costs the lecture theatre, the office and uwb-labyrinth
1-7 %.  Neither beats keeping the plain fix everywhere, so ``auto`` keeps it.

2026-12-06 (after the tests took each residual's variance under the fit's own equal
weights, and with the anchors' sigma column as ``robustloc locate`` reads it): 0-14
epochs of each range log flagged, the three within 0.5 % there; ble-tetam (54 of 342
flagged) 2.892 / 2.828 / 3.112 m (keep / huber / snooping).  The table is in
``docs/choosing-a-method.md``.

Usage::

    python benchmarks/bench_auto_refit.py                  # every data set
    python benchmarks/bench_auto_refit.py --sets "wifi-rtt office" --data ../shared/data
"""

from __future__ import annotations

import numpy as np
from _real_sets import cases, show  # (benchmarks/_real_sets.py)

from robustloc import status as st
from robustloc.estimators.ranging import Locator
from robustloc.eval.realdata import error_stats, peer_fixes
from robustloc.integrity import fixes as fx


def variants(case) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Positions and usable flags of the default and the two alternatives."""
    kw = dict(A=case.A, n=case.n, height_offset=case.height_offset)
    rm = fx.range_model_of(case.xy, case.height_offset)
    # (the anchors' sigma where they have one, as `robustloc locate` reads it)
    default = fx.locate_protected(Locator("auto", sigma=case.sigma), case.xy, case.values,
                                  case.kind, **kw)
    scale = default.extra["log_scale"]
    pk = dict(range_model=rm)
    nls = Locator("nls", sigma=case.sigma).with_method("nls", log_scale=scale)
    plain = fx.protect(nls.solve(case.xy, case.values, case.kind, **kw), **pk)
    out = {"auto (keep the plain fix)": default}
    flagged = plain.extra["flagged"]
    kept = plain.extra["flags_kept"]  # flagged, the rest passes: auto keeps the plain fix
    rows = np.flatnonzero(kept)
    failed = np.flatnonzero(st.among(plain.status, (st.FAULT_DETECTED, st.UNAVAILABLE))
                            & ~kept)
    huber = nls.with_method("huber", log_scale=scale)
    # refit huber: the failed epochs (as auto) and the flagged ones
    redo = np.union1d(failed, rows)
    rob = fx.protect(huber.solve(case.xy, case.values[redo], case.kind, **kw), **pk)
    out["refit huber"] = fx._merge_rows(plain, rob, redo)
    # snooping: the flagged observations removed, Gauss-Newton again; the failed epochs
    # refitted by huber as auto does
    vals = case.values[rows].copy()
    vals[flagged[rows]] = np.nan
    snoop = fx.protect(nls.solve(case.xy, vals, case.kind, **kw), **pk)
    sol = fx._merge_rows(plain, snoop, rows)
    rob_f = fx.protect(huber.solve(case.xy, case.values[failed], case.kind, **kw), **pk)
    out["snooping"] = fx._merge_rows(sol, rob_f, failed)
    res = {}
    for name, s in out.items():
        if name != "auto (keep the plain fix)" and rm is not None:  # the default's step 7
            s = fx.resolve_sides(s, fx.ambiguity_sides(s, rm), rm)
        res[name] = (s.position, st.among(s.status, st.USABLE))
    res["_n_flagged"] = (rows, failed)
    return res


def main(argv: list[str] | None = None) -> int:
    args, sets = cases(__doc__, argv)
    table = []
    for case, R in sets:
        res = variants(case)
        flagged_rows, _ = res.pop("_n_flagged")
        n_flag = int(np.isin(R, flagged_rows).sum())
        for name, (pos, use) in res.items():
            s = error_stats(pos[R], case.truth[R], use[R])
            table.append({"data set": f"{case.name} ({case.source})", "method": name,
                          "rms_m": s["rms"], "p95_m": s["p95"],
                          "availability": s["availability"], "n_flagged": n_flag})
        peers = peer_fixes(case, R)
        best = min(peers, key=lambda p: error_stats(peers[p][R], case.truth[R])["rms"])
        s = error_stats(peers[best][R], case.truth[R])
        table.append({"data set": f"{case.name} ({case.source})", "method": f"{best} (best peer)",
                      "rms_m": s["rms"], "p95_m": s["p95"], "availability": s["availability"],
                      "n_flagged": n_flag})
    show(table, args.out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
