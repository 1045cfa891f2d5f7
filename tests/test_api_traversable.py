"""The documented data-loading pattern: ``importlib.resources.files("robustloc") / "data" /
...`` (a ``Traversable``) passed where the API and the dataset loaders read a path (the
API review of 2026-12-08: the examples and tutorials failed ``mypy --strict`` with seven
errors, as the hints said ``str | PathLike[str]`` and ``str | Path``)."""

from __future__ import annotations

import sys
import typing
import zipfile
from importlib.resources import as_file, files

import pandas as pd
import pytest

import robustloc
from robustloc import api
from robustloc.datasets import ble_tetam, uwb_dwm1001, uwb_labyrinth, wifi_rtt
from robustloc.errors import InputError

if sys.version_info >= (3, 11):
    from importlib.resources.abc import Traversable
else:
    from importlib.abc import Traversable


def _accepts_traversable(hint: object) -> bool:
    """Whether a parameter's type hint takes a Traversable (directly, within a Union, or
    as the item of a sequence in it)."""
    if hint is Traversable:
        return True
    return any(_accepts_traversable(a) for a in typing.get_args(hint))


READERS = [
    (api.spp, ("obs", "nav", "sp3", "clk")),
    (api.locate, ("measurements", "anchors")),
    (api.track, ("measurements", "anchors")),
    (api.calibrate, ("survey", "anchors", "measurements", "truth", "self_log")),
    (api.evaluate, ("positions", "truth")),
    (api.read_anchors, ("source",)),
    (api.read_measurements, ("source", "anchors")),
    (api.read_truth, ("source",)),
    (api.read_positions, ("source",)),
    (wifi_rtt.load_room, ("data_dir",)),
    (wifi_rtt.load_anchors, ("data_dir",)),
    (ble_tetam.load_anchors, ("data_dir",)),
    (uwb_dwm1001.load, ("data_dir",)),
    (uwb_labyrinth.load, ("data_dir",)),
]


@pytest.mark.parametrize("fn, params", READERS, ids=[
    f"{f.__module__.rsplit('.', 1)[-1]}.{f.__name__}" for f, _ in READERS])
def test_every_path_read_is_typed_to_take_a_traversable(fn, params):
    hints = typing.get_type_hints(fn)
    for name in params:
        assert _accepts_traversable(hints[name]), (fn.__qualname__, name, hints[name])


def test_the_shipped_data_through_importlib_resources():
    """What the examples do, at run time: a Traversable of the installed package."""
    excerpt = files("robustloc") / "data" / "wifi-rtt-rss"
    room = wifi_rtt.load_room("office", "test", data_dir=excerpt)
    assert room.source.kind == "excerpt" and len(room.truth) > 0
    data = files("robustloc") / "data" / "gnss-geonet"
    sol = robustloc.spp(data / "07590920.05o", [data / "07590920_0000-0400.05n"],
                        systems="G")
    assert len(sol) > 100


@pytest.fixture
def zipped(tmp_path):
    """A zip archive holding an anchors file and a measurements file (resources that are
    not files on the file system: ``zipfile.Path`` is a Traversable, not a PathLike)."""
    anchors = pd.DataFrame({"anchor": ["a", "b", "c", "d"], "x": [0.0, 10, 10, 0],
                            "y": [0.0, 0, 10, 10]})
    log = pd.DataFrame({"time": 0.0, "tag": "t", "anchor": anchors.anchor,
                        "range": [5.0, 8.06, 9.22, 6.71]})
    path = tmp_path / "site.zip"
    with zipfile.ZipFile(path, "w") as z:
        z.writestr("site/anchors.csv", anchors.to_csv(index=False))
        z.writestr("site/meas.csv", log.to_csv(index=False))
    with zipfile.ZipFile(path) as z:
        yield zipfile.Path(z) / "site"


def test_a_resource_inside_an_archive_is_refused_with_the_way_to_a_file(zipped):
    """Not a traceback (``Path(resource)`` raised TypeError in the dataset loaders): an
    InputError naming ``importlib.resources.as_file``, which then works."""
    assert isinstance(zipped, Traversable)
    with pytest.raises(InputError, match="importlib.resources.as_file"):
        robustloc.read_anchors(zipped / "anchors.csv")
    with pytest.raises(InputError, match="importlib.resources.as_file"):
        robustloc.locate(zipped / "meas.csv", zipped / "anchors.csv")
    with pytest.raises(InputError, match="importlib.resources.as_file"):
        robustloc.read_measurements(pd.DataFrame(), zipped / "anchors.csv")
    with pytest.raises(InputError, match="importlib.resources.as_file"):
        robustloc.spp(zipped / "meas.csv", zipped / "anchors.csv")
    with pytest.raises(InputError, match="importlib.resources.as_file"):
        wifi_rtt.load_room("office", "test", data_dir=zipped)
    with pytest.raises(InputError, match="importlib.resources.as_file"):
        uwb_labyrinth.load(data_dir=zipped)
    with as_file(zipped / "meas.csv") as m, as_file(zipped / "anchors.csv") as a:
        pos = robustloc.locate(m, a, "nls")
    assert pos["status"].tolist() == ["ok"]
