"""The workflow layer (robustloc.pipelines): one implementation under the CLI and the API.

* layering: nothing below the front ends imports them (the CLI is a layer over the API's
  workflows, never the other way round);
* the settings dataclasses refuse what the command line refuses, with its words;
* the command line and the settings have the same defaults;
* an in-memory frame streams like the file it would be written to.
"""

from __future__ import annotations

import argparse
import ast
import dataclasses
import pathlib
import subprocess
import sys

import numpy as np
import pandas as pd
import pytest

import robustloc
from robustloc.cli import main
from robustloc.errors import InputError

SRC = pathlib.Path(robustloc.__file__).parent

#: Front ends, highest first: a package may import only packages to its right, and the
#: cores (everything not listed) import none of them.  ``__main__`` (``python -m
#: robustloc``) is the process's entry, above the command line it runs.
FRONT = ["__main__", "cli", "commands", "reproduce", "api", "engines", "service",
         "pipelines"]


def _imports(path: pathlib.Path) -> set[str]:
    out: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            parts = node.module.split(".")
            if parts[0] == "robustloc" and len(parts) > 1:
                out.add(parts[1])
            elif node.module == "robustloc":
                out.update(a.name for a in node.names)
        elif isinstance(node, ast.Import):
            out.update(a.name.split(".")[1] for a in node.names
                       if a.name.startswith("robustloc."))
    return out


def test_front_ends_are_layered():
    bad = []
    for f in SRC.rglob("*.py"):
        top = f.relative_to(SRC).parts[0].removesuffix(".py")
        if top == "__init__":  # robustloc/__init__.py: the lazy re-export of the API
            continue
        allowed_front = FRONT[FRONT.index(top) + 1:] if top in FRONT else []
        for imp in _imports(f):
            if imp in FRONT and imp != top and imp not in allowed_front:
                bad.append(f"{f.relative_to(SRC)} imports robustloc.{imp}")
    assert not bad, "layering violations:\n" + "\n".join(sorted(bad))


def test_the_api_runs_without_the_command_line(tmp_path):
    """A locate and a track through the API never load robustloc.commands or argparse
    parsers (they call the workflows directly)."""
    code = (
        "import sys, numpy as np, pandas as pd, robustloc\n"
        "a = pd.DataFrame({'anchor': list('abcd'), 'x': [0., 10, 10, 0], 'y': [0., 0, 10, 10]})\n"
        "d = np.hypot(a.x - 3, a.y - 4)\n"
        "log = pd.DataFrame({'time': 0.0, 'tag': 't', 'anchor': a.anchor, 'range': d})\n"
        "robustloc.locate(log, a); robustloc.track(log, a)\n"
        "print(sorted(m for m in sys.modules if m.startswith('robustloc.commands')))\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True)
    assert out.stdout.strip() == "[]"


# ------------------------------------------------------------------ settings = options


def _parser(command: str) -> argparse.ArgumentParser:
    import importlib

    mod = importlib.import_module(f"robustloc.commands.{command}")
    p = argparse.ArgumentParser()
    mod.add_arguments(p)
    return p


@pytest.mark.parametrize(("command", "cls", "positional", "renamed"), [
    ("locate", "robustloc.pipelines.locate:LocateSettings", ["m.csv", "--anchors", "a.csv"],
     {"range_calibration": None}),
    ("track", "robustloc.pipelines.track:TrackSettings", ["m.csv", "--anchors", "a.csv"], {}),
    ("calibrate", "robustloc.pipelines.calibrate:CalibrateSettings", ["s.csv"], {}),
    ("spp", "robustloc.pipelines.spp:SppSettings", ["o.obs", "n.nav"], {}),
])
def test_settings_defaults_are_the_command_lines(command, cls, positional, renamed):
    import importlib

    mod, name = cls.split(":")
    settings_cls = getattr(importlib.import_module(mod), name)
    args = _parser(command).parse_args([*positional, "-o", "out.csv"])
    from_cli = settings_cls.from_namespace(args)
    assert from_cli == settings_cls(), f"{command}: defaults differ"
    # every field of the settings is an option of the command (or a documented rename)
    for f in dataclasses.fields(settings_cls):
        # (the first pass's results, set by the Dask engine: no command-line option)
        if f.name in renamed or f.name in ("log_scale_fixed", "log_gross_share", "log_sides"):
            continue
        assert hasattr(args, f.name), f"{command}: no option for {f.name}"


def test_track_settings_defaults_are_the_trackers():
    from robustloc.pipelines.track import TrackSettings
    from robustloc.tracking.tracker import TrackerSettings

    tracker = {f.name: f.default for f in dataclasses.fields(TrackerSettings)}
    for f in dataclasses.fields(TrackSettings):
        if f.name == "link_offsets":  # the one documented difference: the workflow's
            # default lets the log choose (it reads the log first); the filter, fed epoch
            # by epoch with no log to look at, has them off
            assert (f.default, tracker[f.name]) == ("auto", False)
        elif f.name in tracker:
            assert f.default == tracker[f.name], f.name


@pytest.mark.parametrize(("call", "argv"), [
    (lambda: robustloc.track("m.csv", "a.csv", q=-1.0), ["track", "--q", "-1.0"]),
    (lambda: robustloc.track("m.csv", "a.csv", model="cvv"), ["track", "--model", "cvv"]),
    (lambda: robustloc.track("m.csv", "a.csv", fixed_lag=0), ["track", "--fixed-lag", "0"]),
    (lambda: robustloc.spp("o.obs", "n.nav", elevation_mask=95.0),
     ["spp", "--elevation-mask", "95.0"]),
    (lambda: robustloc.calibrate("s.csv", d0=0.0), ["calibrate", "--d0", "0.0"]),
    (lambda: robustloc.locate("m.csv", "a.csv", alpha0=0.9), ["locate", "--alpha0", "0.9"]),
])
def test_refused_settings_say_what_the_command_line_says(call, argv, capsys, tmp_path):
    positional = {"track": ["m.csv", "--anchors", "a.csv"], "spp": ["o.obs", "n.nav"],
                  "calibrate": ["s.csv"], "locate": ["m.csv", "--anchors", "a.csv"]}
    capsys.readouterr()
    assert main([argv[0], *positional[argv[0]], *argv[1:], "-o",
                 str(tmp_path / "o.csv")]) == 2
    err = capsys.readouterr().err.strip().splitlines()[-1]
    with pytest.raises(InputError) as exc:
        call()
    assert str(exc.value).startswith("argument --")
    assert err.endswith(str(exc.value))


# ------------------------------------------------------------------ frames as sources


def test_a_frame_streams_like_its_file(tmp_path):
    """iter_epochs over a frame gives the blocks of the same rows written to CSV, at any
    chunk size, also when the rows are shuffled (then both are sorted first)."""
    from robustloc.io import iter_epochs
    from robustloc.io.tables import in_memory_source

    rng = np.random.default_rng(2)
    rows = [(float(t), f"t{k}", a, float(rng.normal(10, 1)))
            for t in range(30) for k in range(3) for a in "abc" if rng.random() > 0.2]
    log = pd.DataFrame(rows, columns=["time", "tag", "anchor", "range"])
    for frame in (log, log.sample(frac=1.0, random_state=3)):
        frame.to_csv(tmp_path / "m.csv", index=False)
        for chunk in (1, 7, 1000):
            a = list(iter_epochs(in_memory_source(frame), list("abc"), chunk_rows=chunk))
            b = list(iter_epochs(tmp_path / "m.csv", list("abc"), chunk_rows=chunk))
            assert len(a) == len(b)
            for x, y in zip(a, b):
                np.testing.assert_array_equal(x.time, y.time)
                np.testing.assert_array_equal(x.tag, y.tag)
                np.testing.assert_array_equal(x.values, y.values)


def test_a_frame_error_names_its_row():
    from robustloc.io import iter_epochs
    from robustloc.io.tables import in_memory_source

    log = pd.DataFrame({"time": [0.0, 0.0, 1.0], "tag": "t", "anchor": ["a", "b", "z"],
                        "range": [1.0, 2.0, 3.0]})
    with pytest.raises(InputError) as exc:
        list(iter_epochs(in_memory_source(log), ["a", "b"]))
    assert (exc.value.path, exc.value.line) == ("<measurements DataFrame>", 4)


def test_several_methods_come_out_in_time_order_whatever_the_chunking():
    """With several methods the rows were grouped method by method inside each block, so
    the output was out of time order and its order depended on --chunk-rows (0, 1, 0, 1,
    2, 2 against 0, 0, 1, 1, 2, 2); now each epoch's methods follow each other."""
    import robustloc

    a4 = pd.DataFrame({"anchor": list("abcd"), "x": [0.0, 10, 10, 0], "y": [0.0, 0, 10, 10]})
    d = np.hypot(a4.x - 3, a4.y - 4).to_numpy()
    log = pd.DataFrame({"time": np.repeat([0.0, 1.0, 2.0], 4), "tag": "t",
                        "anchor": np.tile(a4.anchor, 3),
                        "range": np.tile(d, 3) + np.random.default_rng(0).normal(0, 0.05, 12)})
    whole = robustloc.locate(log, a4, ["nls", "ls"])
    assert whole["time"].tolist() == [0.0, 0.0, 1.0, 1.0, 2.0, 2.0]
    assert whole["method"].tolist() == ["nls", "ls"] * 3
    for rows in (1, 5, 7):
        pd.testing.assert_frame_equal(robustloc.locate(log, a4, ["nls", "ls"], chunk_rows=rows),
                                      whole)
    # the values are each method's own, as when solved alone
    alone = robustloc.locate(log, a4, "ls")
    np.testing.assert_array_equal(whole.loc[whole.method == "ls", "x"], alone["x"])
