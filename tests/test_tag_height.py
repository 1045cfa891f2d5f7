"""``--tag-height`` and ``tag_height``: one converter for every command and the Python
API (``robustloc.options.tag_height_m``, at most 10 km either way).  Needs no Dask: these
tests sat in the Dask review's module, skipped where ``distributed`` is missing."""

from __future__ import annotations

import argparse
from pathlib import Path

import pandas as pd
import pytest

from robustloc.cli import main
from robustloc.sim.wifi_room import simulate


@pytest.fixture(scope="module")
def sim(tmp_path_factory) -> dict[str, Path]:
    out = tmp_path_factory.mktemp("wifi")
    return simulate(out, 4, argparse.Namespace(samples_per_point=5, walk_epochs=30))


@pytest.mark.parametrize("command", ["locate", "track", "calibrate", "fuse"])
def test_a_tag_height_beyond_10_km_is_refused(sim, tmp_path, capsys, command):
    """``--tag-height 1e200`` (squared: inf) made every epoch of ``locate`` and ``track``
    ``ill_conditioned`` with exit code 0, and ``calibrate --self`` blamed the data; ``fuse``
    already refused it.  One converter now, ``robustloc.options.tag_height_m``."""
    anchors = pd.read_csv(sim["anchors"]).assign(z=2.5)
    src = tmp_path / "anchors_z.csv"
    anchors.to_csv(src, index=False)
    out = str(tmp_path / "o.csv")
    args = {"locate": ["locate", str(sim["measurements"]), "--anchors", str(src), "-o", out],
            "track": ["track", str(sim["measurements"]), "--anchors", str(src), "-o", out],
            "calibrate": ["calibrate", "--self", str(sim["measurements"]), "--anchors",
                          str(src), "-o", out],
            "fuse": ["fuse", "--ranges", str(sim["measurements"]), "--anchors", str(src),
                     "-o", out]}[command]
    assert main([*args, "--tag-height", "1e200"]) == 2
    err = capsys.readouterr().err
    assert "argument --tag-height: expected a number in [-10000, 10000]" in err, err
    assert not (tmp_path / "o.csv").exists()


def test_the_python_api_refuses_a_tag_height_beyond_10_km(sim):
    import robustloc
    from robustloc.errors import InputError
    from robustloc.tracking.tracker import TrackerSettings

    with pytest.raises(ValueError, match="tag_height must be in"):
        TrackerSettings(tag_height=1e200)
    anchors = pd.read_csv(sim["anchors"]).assign(z=2.5)
    for fn in (robustloc.locate, robustloc.track):
        with pytest.raises(InputError, match="--tag-height: expected a number in"):
            fn(str(sim["measurements"]), anchors, tag_height=1e200)
