"""Help text for the terminal from reStructuredText docstrings (``simulate SCENARIO --help``
shows the scenario module's docstring, which Sphinx renders for the documentation)."""

from __future__ import annotations

import re

#: An interpreted-text role, ``:func:`robustloc.x.y``` or ``:class:`~a.B```, with an
#: optional title (``:func:`the fit <robustloc.x.y>```).
_ROLE = re.compile(r":[a-z]+(?::[a-z]+)?:`([^`]+)`")
#: Inline literal, ````text```` (it may run over a line break).
_LITERAL = re.compile(r"``(.+?)``", re.DOTALL)
#: A rule of a simple table: columns of ``=`` separated by spaces.
_TABLE_RULE = re.compile(r"^\s*=+(?: +=+)+\s*$")


def _role(match: re.Match[str]) -> str:
    target = match.group(1)
    title = re.fullmatch(r"(.*?)\s*<([^>]+)>", target)
    if title and title.group(1):
        return title.group(1)
    name = (title.group(2) if title else target).lstrip("~!").rstrip("()")
    # a module keeps its dotted path: its last name alone ("ranging") names nothing one
    # could import or look up
    return name if match.group(0).startswith(":mod:") else name.rsplit(".", 1)[-1]


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
        return _LITERAL.sub(r"\1", _ROLE.sub(_role, s))

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
