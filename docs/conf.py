"""Sphinx configuration: numpydoc API pages, tutorials executed by myst-nb, and the CLI
reference generated from ``robustloc.cli.build_parser`` (built by ``.ci/docs``)."""

from __future__ import annotations

import os
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent
SRC = HERE.parent / "src"
sys.path.insert(0, str(SRC))
# the tutorials' kernels run in subprocesses: they import the same source tree
os.environ["PYTHONPATH"] = os.pathsep.join(
    [str(SRC), *filter(None, os.environ.get("PYTHONPATH", "").split(os.pathsep))])

import robustloc  # noqa: E402

project = "robustloc"
author = "robustloc developers"
release = robustloc.__version__
version = release

extensions = [
    "sphinx.ext.autodoc",
    "sphinx.ext.autosummary",
    "sphinx.ext.mathjax",
    "sphinx.ext.intersphinx",
    "numpydoc",
    "myst_nb",
]
source_suffix = {".rst": "restructuredtext", ".md": "myst-nb"}
exclude_patterns = ["_build", "jupyter_execute", ".jupyter_cache"]
html_theme = "alabaster"
html_static_path: list[str] = []
myst_enable_extensions = ["dollarmath"]

# tutorials: executed at every build; an error in a cell fails the build
nb_execution_mode = "force"
nb_execution_raise_on_error = True
nb_execution_timeout = 600
nb_execution_show_tb = True

numpydoc_show_class_members = False
numpydoc_validation_checks: set[str] = set()
autodoc_typehints = "none"  # numpydoc's Parameters sections carry the types
autosummary_generate = False
intersphinx_mapping: dict[str, tuple[str, None]] = {}  # offline build: no inventories
suppress_warnings = ["mystnb.unknown_mime_type"]


def _write_cli_reference(app: object) -> None:
    """docs/cli.md from the argparse parsers: every command's ``--help`` text, verbatim."""
    from robustloc.cli import _command_modules, build_parser

    parser = build_parser()
    parser.prog = "robustloc"
    lines = [
        "# Command-line reference",
        "",
        "Generated from the argument parsers (`robustloc.cli.build_parser`) when the",
        "documentation is built: each section is the command's `--help`.",
        "",
        "```text",
        parser.format_help().rstrip(),
        "```",
        "",
        "## One setting, the names the commands give it",
        "",
        "Each command keeps its own name and accepts the others' too (same settings,",
        "same output; the output's `method` column keeps the command's own name):",
        "",
        "| setting | `locate` / `serve` | `track` | `filter` | `fuse` |",
        "|---|---|---|---|---|",
        "| robust weight | `--method` (a method; `serve --track`: `--track-weight`, "
        "`--track-robust`) "
        "| `--weight`, `--robust` | `--robust`, `--weight` | `--robust`, `--weight` |",
        "| the asymmetric IGG weight (seed 002 eq. 14) | `asym`, `asymmetric-igg` "
        "| `asymmetric-igg`, `asym` | `asymmetric-igg`, `asym` | `asymmetric-igg`, `asym` |",
        "| no robust weight | `nls` (a method) | `ls`, `none` | `none`, `ls` | `none`, `ls` |",
        "| motion model | `serve --track-model`, `--track-motion` | `--model`, `--motion` "
        "| (none) | `--motion` |",
        "| a-priori sigma of one observation | `--sigma` | `--sigma` | `--sigma-rssi`, "
        "`--sigma` | `--sigma-range` (beside `--sigma-speed`, `--sigma-course`) |",
        "",
        "`--model` names a path-loss model in `locate`, `calibrate` and `serve`, the",
        "motion model in `track` (there `--motion` says the same), and the observation",
        "type (`range` or `rssi`) in `reliability` and `montecarlo`, which take it, and",
        "`--sigma`, from the anchors file when it is left out.  `--tag-z` and",
        "`--tag-height` are one option in `reliability` and `montecarlo`.",
        "",
    ]
    sub = next(a for a in parser._actions if a.__class__.__name__ == "_SubParsersAction")
    for mod in _command_modules():
        p = sub.choices[mod.NAME]  # type: ignore[attr-defined]
        p.prog = f"robustloc {mod.NAME}"
        lines += [f"## `robustloc {mod.NAME}`", "", mod.HELP[:1].upper() + mod.HELP[1:] + ".",
                  "", "```text", p.format_help().rstrip(), "```", ""]
    text = "\n".join(lines)
    out = HERE / "cli.md"
    if not out.exists() or out.read_text() != text:
        out.write_text(text)


def setup(app: object) -> None:
    os.environ.setdefault("COLUMNS", "100")  # argparse wraps the help at this width
    app.connect("builder-inited", _write_cli_reference)  # type: ignore[attr-defined]
