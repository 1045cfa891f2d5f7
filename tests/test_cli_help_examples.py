"""The examples that ``--help`` prints are commands that work.

A user copies an example from ``robustloc COMMAND --help`` before reading anything else;
an example with a renamed option, a value the command refuses or an output that the next
line cannot read fails them on their first try.  Two checks over every command's help
(and ``simulate``'s scenarios):

* every example line parses: its options exist and take the values it gives;
* every block of examples that starts from ``robustloc simulate`` (so needs no file of
  the user's) runs, line after line, in an empty folder: each line exits 0 and writes
  the output it names.

The same for the command lines in the README's and the documentation's code blocks
(``docs/cli.md`` is generated from the helps; ``robustloc reproduce``, minutes long, is
parsed, not run).
"""

from __future__ import annotations

import re
import shlex
from pathlib import Path

import pytest

from robustloc.cli import build_parser, main


def _help_texts() -> dict[str, str]:
    import argparse

    top = build_parser()
    out = {"robustloc": top.format_help()}
    for action in top._actions:
        if not isinstance(action, argparse._SubParsersAction):
            continue
        for name, sub in action.choices.items():
            out[name] = sub.format_help()
            for inner in sub._actions:
                if isinstance(inner, argparse._SubParsersAction):
                    out.update({f"{name} {n}": s.format_help()
                                for n, s in inner.choices.items()})
    return out


#: An example: a line of the description or epilog (indented a few spaces; an option's
#: wrapped help is indented ~24 and may start a line with "robustloc" in prose).
_EXAMPLE = re.compile(r"^ {1,8}robustloc\s")


def _blocks(text: str) -> list[list[str]]:
    """The example lines of a help text, in blocks of consecutive lines (a line ending in
    a backslash continues on the next)."""
    blocks: list[list[str]] = []
    current: list[str] = []
    lines = text.splitlines()
    i = 0
    while i < len(lines):
        line = lines[i]
        if _EXAMPLE.match(line):
            cmd = line.strip()
            while cmd.endswith("\\") and i + 1 < len(lines):
                i += 1
                cmd = cmd[:-1].rstrip() + " " + lines[i].strip()
            current.append(cmd)
        elif current:
            blocks.append(current)
            current = []
        i += 1
    if current:
        blocks.append(current)
    return blocks


def _argv(cmd: str) -> list[str]:
    """The example as an argument list, without its optional ``[--opt VALUE]`` parts."""
    cmd = re.sub(r"\[[^\]]*\]", " ", cmd)
    return shlex.split(cmd)[1:]


ROOT = Path(__file__).resolve().parents[1]
_FENCE = re.compile(r"^```")


def _doc_blocks(path: Path) -> list[list[str]]:
    """The ``robustloc`` command lines of a Markdown file's fenced code blocks, one list
    per block (continuations joined, ``# comments`` dropped)."""
    blocks: list[list[str]] = []
    inside = False
    lines = path.read_text(encoding="utf-8").splitlines()
    i = 0
    while i < len(lines):
        line = lines[i]
        if _FENCE.match(line.strip()):
            inside = not inside
            if inside:
                blocks.append([])
        elif inside and re.match(r"^\s*(\$ )?robustloc\s", line):
            cmd = re.sub(r"^\s*(\$ )?", "", line).rstrip()
            while cmd.endswith("\\") and i + 1 < len(lines):
                i += 1
                cmd = cmd[:-1].rstrip() + " " + lines[i].strip()
            blocks[-1].append(" ".join(shlex.split(cmd, comments=True)) if "#" in cmd
                              else cmd)
        i += 1
    return [b for b in blocks if b]


def _doc_texts() -> dict[str, list[list[str]]]:
    files = [ROOT / "README.md", *sorted((ROOT / "docs").rglob("*.md"))]
    return {str(f.relative_to(ROOT)): _doc_blocks(f) for f in files
            if f.name != "cli.md" and "_build" not in f.parts}


HELP = _help_texts()
BLOCKS = {**{name: _blocks(text) for name, text in HELP.items()}, **_doc_texts()}
EXAMPLES = [(name, cmd) for name, blocks in BLOCKS.items() for block in blocks
            for cmd in block]
RUNNABLE = [(name, block) for name, blocks in BLOCKS.items() for block in blocks
            if block[0].startswith("robustloc simulate ")]


def test_the_helps_hold_examples():
    # the walk found them: the commands whose help shows how to use them
    named = {name for name, _ in EXAMPLES}
    assert {"simulate", "calibrate", "locate", "evaluate", "stats", "filter", "fuse",
            "spp", "reliability", "montecarlo", "partition", "replay", "serve",
            "track"} <= named
    assert {name for name, _ in RUNNABLE} >= {"filter", "fuse", "track", "README.md",
                                              "docs/getting-started.md"}


@pytest.mark.parametrize("name, cmd", EXAMPLES, ids=[f"{n}: {c}" for n, c in EXAMPLES])
def test_every_example_parses(name, cmd):
    argv = _argv(cmd)
    parser = build_parser(argv[0] if argv and not argv[0].startswith("-") else None)
    try:
        args = parser.parse_args(argv)
    except SystemExit as exc:  # argparse refused it (its message is on stderr)
        if cmd.endswith(" --list") and exc.code == 0:
            return
        pytest.fail(f"{name}: `{cmd}` does not parse (exit {exc.code})")
    assert getattr(args, "_run", None) is not None, cmd


def _outputs(argv: list[str]) -> list[str]:
    """The files or folders a command line names as its output."""
    out = []
    for flag in ("-o", "--out"):
        if flag in argv:
            out.append(argv[argv.index(flag) + 1])
    return out


@pytest.mark.parametrize("name, block", RUNNABLE,
                         ids=[f"{n}: {b[0]}" for n, b in RUNNABLE])
def test_examples_that_start_from_a_simulation_run(name, block, tmp_path, monkeypatch,
                                                   capsys):
    monkeypatch.chdir(tmp_path)
    for cmd in block:
        argv = _argv(cmd)
        if argv[0] == "reproduce":  # minutes long: parsed above, run by its own tests
            continue
        code = main(argv)
        err = capsys.readouterr().err
        assert code == 0, f"{name}: `{cmd}` exited {code}: {err}"
        assert "Traceback" not in err
        for path in _outputs(argv):
            assert Path(path).exists(), f"{name}: `{cmd}` wrote no {path}"
