"""The reproduction report's sentences carry the run's numbers, not numbers typed in
from another run (the report review: "removes the 3.6 m vertical bias ... cuts the 3-D RMS
by about a third" beside excerpt tables of -3.31 m and -44 %; "a common +0.12 m bias
(measured)" computed nowhere; "one file of the five tracks" on a two-track excerpt)."""

from __future__ import annotations

import numpy as np
import pandas as pd

from robustloc.reproduce import Context, Section


def test_s50_precise_text_is_the_tables():
    from robustloc.reproduce.s50_gnss import PRECISE_ROWS, _precise_text

    rows = {"SLAC, GPS broadcast (ours)": (0.5, -3.31, 2.5, 4.16)}
    for k, row in enumerate(PRECISE_ROWS):
        rows[row] = (2.01 + 0.01 * k, 0.2, 2.1, 2.33 + k)
    acc = pd.DataFrame.from_dict(rows, orient="index",
                                 columns=["bias_e_m", "bias_u_m", "rms_h_m", "rms_3d_m"])
    text = _precise_text(acc)
    smoothed = list(PRECISE_ROWS)[-1]
    assert "from -3.31 m to +0.20 m" in text
    assert f"from 4.16 m to {acc.loc[smoothed, 'rms_3d_m']:.2f} m" in text
    assert f"({100 * (acc.loc[smoothed, 'rms_3d_m'] / 4.16 - 1):+.0f} %)" in text
    assert "GPS +2.01" in text and "3.6 m" not in text and "a third" not in text


def test_s20_labyrinth_bias_is_measured_in_the_run(tmp_path):
    from robustloc.datasets import uwb_labyrinth
    from robustloc.reproduce import s20_uwb_gps

    sec = Section("s20")
    s20_uwb_gps._labyrinth_experiment(Context(out_dir=tmp_path, data_dir=None, quick=True),
                                      sec)
    (caption,) = [p[0] for k, p in sec.blocks if k == "table"]
    r = uwb_labyrinth.load(None)
    m, tt = r.measurements, r.truth["time"].to_numpy(float)
    t = m["time"].to_numpy(float)
    a = r.anchors.set_index(r.anchors["anchor"].astype(str)).loc[m["anchor"].astype(str)]
    d = np.hypot(a["x"].to_numpy(float) - np.interp(t, tt, r.truth["x"]),
                 a["y"].to_numpy(float) - np.interp(t, tt, r.truth["y"]))
    inside = (t >= tt[0]) & (t <= tt[-1])
    mean = float(np.mean((m["range"].to_numpy(float) - d)[inside]))
    assert f"by {mean:+.2f} m on average" in caption, caption
    assert "(measured)" not in caption
