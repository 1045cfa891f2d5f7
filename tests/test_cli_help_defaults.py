"""Every option's ``--help`` says what it does when left out.

A demanding user reads ``--help`` to decide whether to set an option; an option whose
default the help does not state (``--sigma-course`` said "GPS course std, deg" and
silently used 5) makes them read the source.  Walks every command's parser (and the
sub-commands of ``simulate``): each option with a default other than None or False must
mention "default", or open a parenthesis with the default's value, in its help."""

from __future__ import annotations

import argparse
import re

from robustloc.cli import build_parser


def _parsers() -> list[tuple[str, argparse.ArgumentParser]]:
    top = build_parser()
    out = []
    for action in top._actions:
        if not isinstance(action, argparse._SubParsersAction):
            continue
        for name, sub in action.choices.items():
            out.append((name, sub))
            for inner in sub._actions:
                if isinstance(inner, argparse._SubParsersAction):
                    out.extend((f"{name} {n}", s) for n, s in inner.choices.items())
    return out


def test_every_option_with_a_default_states_it_in_its_help():
    parsers = _parsers()
    assert len(parsers) > 15  # every command, and simulate's scenarios
    silent = []
    for name, parser in parsers:
        for a in parser._actions:
            if isinstance(a, (argparse._HelpAction, argparse._VersionAction,
                              argparse._SubParsersAction)):
                continue
            if a.default in (None, False, argparse.SUPPRESS) or a.help in (
                    None, argparse.SUPPRESS):
                continue
            text = a.help % {"default": a.default} if "%(default)" in a.help else a.help
            # the word, or the value opening a parenthesis ("range std, m (0.15)"): a value
            # that only happens to occur in the text does not count ("--dim": "solve in
            # 2-D or 3-D" holds a 2 and said nothing about the default)
            value = re.escape(str(a.default))
            if "default" not in text.lower() and not re.search(r"\(" + value, text):
                silent.append(f"{name} {'/'.join(a.option_strings) or a.dest}")
    assert not silent, silent
