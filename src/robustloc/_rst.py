"""reStructuredText docstrings for people: plain text for the terminal
(``simulate SCENARIO --help`` shows a scenario module's docstring) and Markdown for the
report (section introductions taken from module docstrings).  Sphinx renders the same
docstrings for the documentation; these functions only make them readable elsewhere."""

from __future__ import annotations

import re

#: A Sphinx role, ``:func:`robustloc.x.f```, ``:py:data:`~a.B```, with an optional title
#: (``:func:`the fit <robustloc.x.fit>```): group 1 the title or target, group 2 the target
#: when a title is given.
_ROLE = re.compile(r":(?:[a-z]+:)?[a-z]+:`([^`<]*?)\s*(?:<([^`>]+)>)?`")
#: Inline literal, ````text```` (it may run over a line break).
_LITERAL = re.compile(r"``(.+?)``", re.DOTALL)
#: A rule of a simple table: columns of ``=`` separated by spaces.
_TABLE_RULE = re.compile(r"^\s*=+(?: +=+)+\s*$")


def inline_rst(text: str, code: str = "", module_path: bool = False) -> str:
    """Roles and inline literals of ``text`` as plain words, each wrapped in ``code``.

    A role becomes its title when it has one, else the last dotted part of its target
    (``:func:`robustloc.x.y``` -> ``y``; with ``module_path`` a ``:mod:`` role keeps the
    whole dotted path, which is what one could import or look up); an inline literal
    loses its double backticks.  ``code="`"`` gives Markdown's inline code.

    >>> inline_rst(":func:`robustloc.x.y` and ``--epochs``")
    'y and --epochs'
    >>> inline_rst(":data:`robustloc.a.B` (:func:`the peers <robustloc.c.d>`)", code="`")
    '`B` (`the peers`)'
    """

    def role(m: re.Match[str]) -> str:
        title, target = m.group(1).strip(), m.group(2)
        if target is not None and title:
            return f"{code}{title}{code}"
        name = (target or title).strip().lstrip("~!").rstrip("()")
        keep = module_path and (m.group(0).startswith(":mod:")
                                or m.group(0).startswith(":py:mod:"))
        return f"{code}{name if keep else name.rsplit('.', 1)[-1]}{code}"

    return _LITERAL.sub(lambda m: f"{code}{m.group(1)}{code}", _ROLE.sub(role, text))


def rst_markdown(text: str) -> str:
    """Docstring text as Markdown for the report: roles and inline literals in single
    backticks (:func:`inline_rst`), the rest as it is (the report showed the roles and
    the double backticks raw).

    >>> rst_markdown("the default (:data:`robustloc.estimators.ranging.DEFAULT_METHOD`, "
    ...              ":mod:`~robustloc.integrity.fixes`) and scipy ``least_squares``")
    'the default (`DEFAULT_METHOD`, `fixes`) and scipy `least_squares`'
    """
    return inline_rst(text, code="`")


def rst_to_text(text: str) -> str:
    """Render a reStructuredText docstring as plain text for a terminal.

    Roles become their target's last name (``:func:`robustloc.x.y``` -> ``y``, a title
    given as ``:func:`title <target>``` -> ``title``; ``:mod:`` keeps the dotted module
    path), inline literals lose their double backticks, and a simple table (rows between
    ``=====  ===`` rules) is re-aligned to its cells' new widths, its rules dropped but
    the one under the header, drawn with ``-``.  Everything else (paragraphs, bullet
    lists, section underlines) is already readable and is kept as it is.

    Parameters
    ----------
    text : str
        The docstring.

    Returns
    -------
    str
        The text, line breaks kept except for the dropped table rules.

    Examples
    --------
    >>> rst_to_text("From :func:`robustloc.sim.gnss.constellation`, ``--epochs`` long.")
    'From constellation, --epochs long.'
    """

    def inline(s: str) -> str:
        return inline_rst(s, module_path=True)

    lines = text.splitlines()
    out: list[str] = []
    prose: list[str] = []  # lines outside tables, rendered together (a literal may wrap)
    i = 0
    while i <= len(lines):
        if i < len(lines) and not _TABLE_RULE.match(lines[i]):
            prose.append(lines[i])
            i += 1
            continue
        if prose:
            out.extend(inline("\n".join(prose)).split("\n"))
            prose = []
        if i == len(lines):
            break
        # a simple table: its rules and rows up to the blank line (or the text's end)
        rule = lines[i]
        indent = rule[: len(rule) - len(rule.lstrip())]
        starts = [m.start() for m in re.finditer(r"=+", rule)]
        block = []
        while i < len(lines) and lines[i].strip():
            block.append(lines[i])
            i += 1
        rows: list[list[str] | None] = []  # None: a rule
        for line in block:
            if _TABLE_RULE.match(line):
                rows.append(None)
                continue
            bounds = [*starts[1:], None]
            rows.append([inline(line[a:b].strip()) for a, b in zip(starts, bounds)])
        cells = [r for r in rows if r is not None]
        widths = [max((len(r[k]) for r in cells), default=0) for k in range(len(starts))]
        rules = [k for k, r in enumerate(rows) if r is None]
        # three rules: the second is the header's (two: the table has no header)
        header = rules[1] if len(rules) >= 3 else None
        for k, r in enumerate(rows):
            if r is None:
                if k == header:
                    out.append(indent + "  ".join("-" * w for w in widths))
                continue
            out.append((indent + "  ".join(c.ljust(w) for c, w in zip(r, widths))).rstrip())
    return "\n".join(out)
