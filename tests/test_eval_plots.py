"""``robustloc evaluate --plot`` and the Stanford diagram (:mod:`robustloc.eval.plots`).

The regions are checked against hand-counted cases and against ``evaluate``'s own
``n_misleading`` (:func:`robustloc.eval.metrics.integrity_stats`, a separate code path), so
the figure cannot say something other than the table.
"""

import numpy as np
import pandas as pd
import pytest

import robustloc
from robustloc.cli import main
from robustloc.errors import InputError
from robustloc.eval.metrics import epoch_errors, error_table
from robustloc.eval.plots import evaluation_figure, stanford_counts


def test_stanford_counts_by_hand():
    # errors 1..6 against bounds: above, below, equal (bounded: error <= hpl), infinite,
    # missing (NaN: misleading, as evaluate counts it), and a NaN error (left out)
    e = np.array([1.0, 2.0, 3.0, 4.0, 5.0, np.nan])
    h = np.array([5.0, 1.0, 3.0, np.inf, np.nan, 1.0])
    c = stanford_counts(e, h)
    assert (c.n, c.bounded, c.unbounded, c.misleading) == (5, 3, 1, 2)
    assert c.misleading_pct == pytest.approx(40.0)
    assert np.isnan(stanford_counts(np.zeros(0), np.zeros(0)).misleading_pct)
    with pytest.raises(ValueError, match="shape"):
        stanford_counts(np.zeros(3), np.zeros(2))


def _files(tmp_path, with_hpl=True):
    """Two methods on one tag, errors and bounds chosen so that ``a`` has 2 misleading
    fixes of 6 usable (one with no bound) and ``b`` none; one unusable row each."""
    t = np.arange(7.0)
    truth = pd.DataFrame({"time": t, "tag": "T", "x": 0.0, "y": 0.0})
    err_a = np.array([0.5, 1.0, 2.0, 3.0, 0.2, 0.1, 9.0])
    hpl_a = np.array([5.0, 0.5, 4.0, np.nan, np.inf, 1.0, 1.0])
    err_b = np.array([0.3, 0.4, 0.5, 0.6, 0.7, 0.8, 0.9])
    hpl_b = np.full(7, 10.0)
    st_unusable = ["ok"] * 6 + ["unavailable"]
    rows = []
    for m, e, h in (("a", err_a, hpl_a), ("b", err_b, hpl_b)):
        d = pd.DataFrame({"time": t, "tag": "T", "x": e, "y": 0.0, "method": m,
                          "status": st_unusable})
        if with_hpl:
            d["hpl"] = h
        rows.append(d)
    pos = pd.concat(rows, ignore_index=True)
    pos.to_csv(tmp_path / "pos.csv", index=False)
    truth.to_csv(tmp_path / "truth.csv", index=False)
    return pos, truth


def test_figure_counts_agree_with_the_table(tmp_path):
    pos, truth = _files(tmp_path)
    counts = evaluation_figure(epoch_errors(pos, truth), tmp_path / "f.png")
    assert (tmp_path / "f.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    table = error_table(pos, truth)
    for m in ("a", "b"):
        row = table[(table["tag"] == "all") & (table["method"] == m)].iloc[0]
        assert counts[m].n == row["n_ok"] == 6
        assert counts[m].misleading == row["n_misleading"]
    assert (counts["a"].misleading, counts["a"].unbounded) == (2, 1)
    assert counts["b"].misleading == 0
    assert not list(tmp_path.glob("*.tmp*")) and sorted(p.name for p in tmp_path.iterdir()) == [
        "f.png", "pos.csv", "truth.csv"]  # written atomically: no temporary left


def test_figure_without_hpl_draws_the_cdf_only(tmp_path):
    pos, truth = _files(tmp_path, with_hpl=False)
    out = tmp_path / "f.svg"
    assert evaluation_figure(epoch_errors(pos, truth), out) == {}
    svg = out.read_text()
    assert "error distribution" in svg and "Stanford" not in svg
    assert "usable fixes and the truth" in svg


def test_figure_names_every_panel_up_to_the_limit(tmp_path):
    pos, truth = _files(tmp_path)
    a = pos[pos["method"] == "a"]
    many = pd.concat([a.assign(method=f"a{k}") for k in range(4)], ignore_index=True)
    out = tmp_path / "f.svg"
    counts = evaluation_figure(epoch_errors(many, truth), out, max_methods=3)
    assert list(counts) == ["a0", "a1", "a2"]
    assert "first 3 of 4" in out.read_text()


def test_evaluate_plot_cli(tmp_path, capsys):
    _files(tmp_path)
    rc = main(["evaluate", str(tmp_path / "pos.csv"), "--truth", str(tmp_path / "truth.csv"),
               "--plot", str(tmp_path / "ev.png")])
    assert rc == 0
    assert "figure:" in capsys.readouterr().out
    assert (tmp_path / "ev.png").stat().st_size > 10_000


@pytest.mark.parametrize("extra, message", [
    (["--plot", "ev.txt"], "must end in .png, .svg, .pdf"),
    (["--plot", "ev.png", "--engine", "dask"], "--engine local"),
    (["--plot", "{pos}"], "must end in"),
])
def test_evaluate_plot_mistakes_exit_2(tmp_path, capsys, extra, message):
    _files(tmp_path)
    before = (tmp_path / "pos.csv").read_bytes()
    extra = [a.replace("{pos}", str(tmp_path / "pos.csv")) if "{pos}" in a
             else (str(tmp_path / a) if a.startswith("ev.") else a) for a in extra]
    with pytest.raises(SystemExit) as exc:
        rc = main(["evaluate", str(tmp_path / "pos.csv"), "--truth",
                   str(tmp_path / "truth.csv"), *extra])
        raise SystemExit(rc)
    assert exc.value.code == 2
    assert message in capsys.readouterr().err
    assert (tmp_path / "pos.csv").read_bytes() == before  # the input is never written
    assert not (tmp_path / "ev.png").exists()


def test_the_library_draws_the_same_figure(tmp_path, capsys):
    pos, truth = _files(tmp_path)
    table = robustloc.evaluate(tmp_path / "pos.csv", tmp_path / "truth.csv",
                               plot=tmp_path / "lib.svg")
    svg = (tmp_path / "lib.svg").read_text()
    assert "Stanford diagram: a" in svg and "Stanford diagram: b" in svg
    pd.testing.assert_frame_equal(table, robustloc.evaluate(pos, truth), check_like=True)
    # refused as the command refuses it, in the same words
    assert main(["evaluate", str(tmp_path / "pos.csv"), "--truth", str(tmp_path / "truth.csv"),
                 "--plot", "ev.txt"]) == 2
    cli = capsys.readouterr().err.strip().splitlines()[-1]
    with pytest.raises(InputError) as exc:
        robustloc.evaluate(tmp_path / "pos.csv", tmp_path / "truth.csv", plot="ev.txt")
    assert cli.endswith(str(exc.value))
    assert str(exc.value).startswith("argument --plot: ")
    with pytest.raises(InputError, match="must end in"):
        robustloc.evaluate(pos, truth, plot=3.5)
    # a positions file that happens to bear a figure's name is never overwritten
    odd = tmp_path / "pos.svg"
    odd.write_bytes((tmp_path / "pos.csv").read_bytes())
    with pytest.raises(InputError, match="would overwrite an input"):
        robustloc.evaluate(odd, tmp_path / "truth.csv", plot=odd)
    assert main(["evaluate", str(odd), "--truth", str(tmp_path / "truth.csv"),
                 "--plot", str(odd)]) == 2
    assert "would overwrite an input" in capsys.readouterr().err
    assert odd.read_bytes() == (tmp_path / "pos.csv").read_bytes()


@pytest.mark.parametrize("err, hpl", [
    (np.zeros(5), np.full(5, 1.0)),  # exact fixes: nothing to put on log axes
    (np.full(5, 0.5), np.full(5, np.inf)),  # every fix unbounded
    (np.full(5, 0.5), np.full(5, np.nan)),  # no bound at all: every fix misleading
    (np.zeros(0), np.zeros(0)),  # no usable fix
    (np.array([1e-9, 1e6]), np.array([1e7, 1e-9])),  # twelve decades apart
])
def test_stanford_panel_draws_degenerate_sets(tmp_path, err, hpl):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from robustloc.eval.plots import plot_stanford

    fig, ax = plt.subplots()
    c = plot_stanford(ax, err, hpl, title="degenerate")
    fig.savefig(tmp_path / "p.png")
    plt.close(fig)
    assert c == stanford_counts(err, hpl)
    assert c.n == err.size and c.bounded + c.misleading == c.n


# ---------------------------------------------------------------- locate / track --plot
@pytest.fixture(scope="module")
def corridor_log(tmp_path_factory):
    d = tmp_path_factory.mktemp("sim")
    assert main(["simulate", "ble-corridor", "--seed", "1", "--out", str(d)]) == 0
    return d


def test_locate_plot_counts_every_row_as_the_summary(corridor_log, tmp_path, capsys):
    import json

    from robustloc.eval.plots import positions_figure, read_positions_for_plot
    from robustloc.io import read_anchors

    out, fig = tmp_path / "pos.csv", tmp_path / "loc.png"
    args = [str(corridor_log / "measurements.csv"), "--anchors",
            str(corridor_log / "anchors.csv"), "-o", str(out), "--method", "auto,nls"]
    assert main(["locate", *args, "--plot", str(fig), "--json"]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert fig.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    counts = positions_figure(read_positions_for_plot(out),
                              read_anchors(corridor_log / "anchors.csv"), tmp_path / "x.svg")
    assert counts == summary["status"]  # every row, per method and status
    assert sum(counts["auto"].values()) == summary["epochs"]
    svg = (tmp_path / "x.svg").read_text()
    assert "status of every row" in svg and "protection levels" in svg


def test_track_plot_and_its_refusals(corridor_log, tmp_path, capsys):
    base = ["track", str(corridor_log / "measurements.csv"), "--anchors",
            str(corridor_log / "anchors.csv")]
    out, fig = tmp_path / "t.parquet", tmp_path / "t.pdf"
    assert main([*base, "-o", str(out), "--plot", str(fig)]) == 0
    assert f"figure: {fig}" in capsys.readouterr().out
    assert fig.read_bytes()[:5] == b"%PDF-"
    refusals = [
        (["-o", "-", "--plot", str(tmp_path / "a.png")], "give a regular file"),
        # a device is written in place: nothing to read back (it was a pandas traceback)
        (["-o", "/dev/null", "--plot", str(tmp_path / "n.png")], "give a regular file"),
        (["-o", str(tmp_path / "b.csv"), "--plot", str(tmp_path / "b.png"), "--engine",
          "dask"], "--engine local"),
        (["-o", str(tmp_path / "c.svg"), "--plot", str(tmp_path / "c.svg")],
         "name the same file"),
        (["-o", str(tmp_path / "d.csv"), "--plot", str(corridor_log / "anchors.csv")],
         "must end in"),
    ]
    for extra, message in refusals:
        with pytest.raises(SystemExit) as exc:
            raise SystemExit(main([*base, *extra]))
        assert exc.value.code == 2, extra
        assert message in capsys.readouterr().err, extra
    # nothing was written by a refused run
    assert sorted(p.name for p in tmp_path.iterdir()) == ["t.parquet", "t.pdf"]


def test_figures_of_logs_without_a_usable_fix(tmp_path):
    """Every row unusable: the figures are drawn, with empty panels and no warning."""
    import warnings

    from robustloc.eval.plots import positions_figure

    pos, truth = _files(tmp_path)
    bad = pos.assign(status="insufficient_anchors", x=np.nan, y=np.nan)
    anchors = pd.DataFrame({"anchor": ["A", "B"], "x": [0.0, 5.0], "y": [0.0, 0.0]})
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        counts = evaluation_figure(epoch_errors(bad, truth), tmp_path / "e.png")
        rows = positions_figure(bad, anchors, tmp_path / "p.png")
    assert all(c.n == 0 and c.misleading == 0 for c in counts.values())
    assert rows == {"a": {"insufficient_anchors": 7}, "b": {"insufficient_anchors": 7}}
