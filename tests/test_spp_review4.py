"""The GNSS review of ``spp`` (epochs out of time order, options that did nothing)."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pandas as pd

from robustloc.cli import main
from robustloc.gnss.rinex import read_obs
from robustloc.gnss.spp import carrier_smooth_iflc, pseudoranges

DATA = Path(__file__).resolve().parents[1] / "src" / "robustloc" / "data"
GEONET_OBS = DATA / "gnss-geonet" / "07590920.05o"
GEONET_NAV = DATA / "gnss-geonet" / "07590920_0000-0400.05n"


def _swapped(tmp_path) -> Path:
    """The GEONET file with its first two epoch blocks swapped."""
    lines = GEONET_OBS.read_text().splitlines(keepends=True)
    h = next(i for i, s in enumerate(lines) if "END OF HEADER" in s)
    ep = [i for i in range(h + 1, len(lines))
          if re.match(r"^ \d\d [ \d]\d [ \d]\d [ \d]\d [ \d]\d [ \d]\d\.\d{7}  \d", lines[i])]
    a, b, c = ep[:3]
    p = tmp_path / "swapped.05o"
    p.write_text("".join(lines[:a] + lines[b:c] + lines[a:b] + lines[c:]))
    return p


# --- 5: epochs out of time order --------------------------------------------------------


def test_hatch_filter_restarts_at_a_backward_step():
    # in file order the filter smoothed across the step back: the second row's smoothed
    # code differed from its raw code.  A step backwards restarts it: raw code
    obs = read_obs(GEONET_OBS)
    swapped = obs.select(np.r_[1, 0, 2:obs.n_epochs])
    pr = pseudoranges(swapped, "iflc")
    out = carrier_smooth_iflc(swapped, pr, 100)
    ok = np.isfinite(pr[1])
    assert ok.sum() >= 4
    np.testing.assert_array_equal(out[1][ok], pr[1][ok])


def test_a_repeated_epoch_leaves_the_smoothing_as_it_was():
    # an epoch repeated (step 0): its copy gets the first copy's smoothed code and the
    # filter goes on as without it.  Restarted there, later epochs' fixes moved by up to
    # 2.3 m (the review of the fix); the smoothed codes equal those of the file without
    # the copy, exactly
    obs = read_obs(GEONET_OBS)
    k = 50
    again = obs.select(np.r_[0:k + 1, k, k + 1:obs.n_epochs])
    ref = carrier_smooth_iflc(obs, pseudoranges(obs, "iflc"), 100)
    got = carrier_smooth_iflc(again, pseudoranges(again, "iflc"), 100)
    np.testing.assert_array_equal(np.delete(got, k + 1, axis=0), ref)
    np.testing.assert_array_equal(got[k + 1], got[k])


def test_spp_solves_epochs_out_of_order_in_time_order(tmp_path, capsys):
    # exit 0, rows in file order, smoothed fixes 0.26 m from the sorted file's, no word
    p = _swapped(tmp_path)
    args = [str(GEONET_NAV), "--iono", "iflc", "--smooth", "100", "-q"]
    assert main(["spp", str(p), *args, "-o", str(tmp_path / "s.csv")]) == 0
    err = capsys.readouterr().err
    assert f"note: {p}:27: an epoch earlier than the one before it (1 such" in err
    assert main(["spp", str(GEONET_OBS), *args, "-o", str(tmp_path / "ref.csv")]) == 0
    capsys.readouterr()
    got = pd.read_csv(tmp_path / "s.csv")
    ref = pd.read_csv(tmp_path / "ref.csv")
    assert got["time"].is_monotonic_increasing
    pd.testing.assert_frame_equal(got, ref)


# --- 3: options that change nothing are refused ------------------------------------------


def test_options_that_need_raim_or_inject_are_refused(tmp_path, capsys):
    # each was accepted, exit 0, and the solution was that of the run without it
    base = ["spp", str(GEONET_OBS), str(GEONET_NAV), "-o", str(tmp_path / "s.csv")]
    for extra, need in ((["--alpha0", "0.01"], "--raim"), (["--beta0", "0.2"], "--raim"),
                        (["--max-exclusions", "1"], "--raim"),
                        (["--inject-from", "796436400"], "--inject"),
                        (["--inject-until", "796436400"], "--inject")):
        assert main([*base, *extra]) == 2, extra
        err = capsys.readouterr().err
        assert f"error: {extra[0]} goes with {need}" in err, err
        assert "Traceback" not in err
    # with them, as before
    assert main([*base, "--raim", "--alpha0", "0.01", "--beta0", "0.2",
                 "--max-exclusions", "1"]) == 0
    assert main([*base, "--inject", "G11:20", "--inject-from", "796436400"]) == 0
    # a window that covers no epoch: said (a note since the earlier review)
    capsys.readouterr()
    assert main([*base, "--inject", "G11:20", "--inject-from", "2030-01-01"]) == 0
    assert "nothing was injected" in capsys.readouterr().err


def test_settings_refuse_inject_window_without_inject(tmp_path):
    from robustloc.errors import InputError
    from robustloc.pipelines.spp import SppSettings, run_spp

    for kw, need in (({"inject_from": 0.0}, "--inject"), ({"max_exclusions": 1}, "--raim")):
        try:
            run_spp(GEONET_OBS, [GEONET_NAV], SppSettings(**kw))
        except InputError as e:
            assert f"goes with {need}" in str(e)
        else:
            raise AssertionError(kw)
