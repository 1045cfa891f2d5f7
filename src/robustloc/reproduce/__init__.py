"""``robustloc reproduce``: every paper's experiment, on simulation and on real data.

The report is assembled from *sections*, one module each in this package.  A section module
exposes ``TITLE`` (str), ``ORDER`` (int, position in the report) and
``run(ctx: Context) -> Section``.  Modules are discovered automatically, so each paper's
experiment lives in its own file.
"""

from __future__ import annotations

import dataclasses
import html
import importlib
import json
import pkgutil
import re
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pandas as pd

from robustloc._rst import rst_markdown  # noqa: F401  (the sections' docstring texts)
from robustloc.reproduce._format import fmt_num, format_frame, text_table  # noqa: F401


@dataclass
class Context:
    """What a section needs to run.

    Attributes
    ----------
    out_dir : Path
        Report folder; sections write figures and CSV tables here.
    data_dir : Path or None
        The full real-data folder (``--data``, default
        :func:`robustloc.paths.default_data_dir`), or None when absent: sections then use
        the excerpts shipped in the package and say so.
    seed : int
        Seed for every simulation.
    quick : bool
        Fewer Monte Carlo trials / epochs (for tests).
    notes : set of str
        The data-source notes already printed (:meth:`note`), each said once per run.
    """

    out_dir: Path
    data_dir: Path | None
    seed: int = 1
    quick: bool = False
    notes: set[str] = field(default_factory=set, repr=False, compare=False)

    def log(self, message: str) -> None:
        print(message, file=sys.stderr, flush=True)

    def note(self, source: Any) -> None:
        """Say on stderr (once per run) that a data set fell back to its shipped excerpt.

        ``source`` is a :class:`robustloc.datasets.ble_tetam.DatasetSource` (its ``note``,
        empty when nothing fell back) or the note's text.
        """
        text = source if isinstance(source, str) else getattr(source, "note", "")
        if text and text not in self.notes:
            self.notes.add(text)
            self.log(f"note: {text}")

    def dataset_dir(self, name: str) -> Path | None:
        """``data_dir`` when it holds the data set ``name`` (its folder ``name/``), else
        None: the loaders then use the shipped excerpt, and a ``data_dir`` without it gets
        the note ``NAME not in DIR: using the shipped excerpt`` (the rule of
        :func:`robustloc.datasets.ble_tetam.resolve_dataset`)."""
        if self.data_dir is None:
            return None
        if (self.data_dir / name).is_dir():
            return self.data_dir
        self.note(f"{name} not in {self.data_dir}: using the shipped excerpt")
        return None


def data_label(sources: dict[str, str] | str) -> str:
    """The data a real-data headline ran on, said the same way by every section:
    ``(excerpts)`` when every data set came from the excerpts shipped in the package,
    ``(full data)`` when none did, else ``(full data; excerpts: NAME, ...)``.

    ``sources`` maps each data set's name to its source kind (``"full"`` or
    ``"excerpt"``, as :class:`robustloc.datasets.ble_tetam.DatasetSource` and
    :class:`robustloc.eval.realdata.Case` say it), or is one such kind.
    """
    kinds = {"": sources} if isinstance(sources, str) else dict(sources)
    excerpts = [name for name, kind in kinds.items() if kind != "full"]
    if not excerpts:
        return "(full data)"
    if len(excerpts) == len(kinds):
        return "(excerpts)"
    return f"(full data; excerpts: {', '.join(excerpts)})"


def _html_text(paragraph: str) -> str:
    """A text paragraph of the report in HTML: escaped, Markdown's `code` as <code>."""
    return re.sub(r"`([^`]+)`", r"<code>\1</code>", html.escape(paragraph))


@dataclass
class Section:
    """One part of the report: prose, tables and figures.

    ``blocks`` is an ordered list of ``("text", markdown)``, ``("table", (caption,
    DataFrame))`` or ``("figure", (caption, relative_png_path))``.  ``summary`` is a JSON
    serializable dict of headline numbers (written to ``summary.json``).
    """

    title: str
    blocks: list[tuple[str, Any]] = field(default_factory=list)
    summary: dict[str, Any] = field(default_factory=dict)
    headlines: list[dict[str, str]] = field(default_factory=list)

    def headline(self, seed: str, what: str, paper: str, ours: str, peer: str,
                 verdict: str) -> None:
        """One line of the report's one-screen summary: a paper's headline figure, ours,
        the best peer's, and a verdict (all as short text)."""
        self.headlines.append({"seed": seed, "headline": what, "paper": paper,
                               "robustloc": ours, "best peer": peer, "verdict": verdict})

    def text(self, markdown: str) -> None:
        self.blocks.append(("text", markdown))

    def table(self, caption: str, frame: pd.DataFrame) -> None:
        self.blocks.append(("table", (caption, frame)))

    def figure(self, caption: str, relpath: str) -> None:
        self.blocks.append(("figure", (caption, relpath)))


def section_modules(only: list[str] | None = None) -> list:
    """Discovered section modules, in report order; ``only`` filters by module name."""
    import robustloc.reproduce as pkg

    mods = []
    for info in pkgutil.iter_modules(pkg.__path__):
        if info.name.startswith("_"):
            continue
        mod = importlib.import_module(f"robustloc.reproduce.{info.name}")
        if hasattr(mod, "run") and hasattr(mod, "TITLE"):
            mod.KEY = getattr(mod, "KEY", info.name)
            mods.append(mod)
    mods.sort(key=lambda m: getattr(m, "ORDER", 100))
    if only:
        keys = [m.KEY for m in mods]
        # a section by its key or a unique prefix of it (``s60`` for ``s60_tracks``)
        chosen = {o: [k for k in keys if k == o] or [k for k in keys if k.startswith(o)]
                  for o in only}
        bad = sorted(o for o, ks in chosen.items() if len(ks) != 1)
        if bad:
            raise ValueError(
                f"unknown or ambiguous section(s) {', '.join(bad)}; "
                f"available: {', '.join(keys)}"
            )
        wanted = {ks[0] for ks in chosen.values()}
        mods = [m for m in mods if m.KEY in wanted]
    return mods


def _md_table(frame: pd.DataFrame) -> str:
    """Markdown pipe table of ``frame`` as the report prints it
    (:func:`robustloc.reproduce._format.format_frame`: 3 significant digits, counts as
    integers, no column of row numbers), without the optional ``tabulate`` dependency."""
    df = format_frame(frame)
    cols = [str(c) for c in df.columns]
    lines = ["| " + " | ".join(cols) + " |", "|" + "---|" * len(cols)]
    lines += ["| " + " | ".join(row) + " |" for row in df.itertuples(index=False)]
    return "\n".join(lines)


def run_preface(ctx: Context) -> str:
    """The report's first paragraph: which real data it used, the seed, ``--quick``, and
    the data-source notes of the run (a fresh clone's report said only table by table
    that it used the shipped excerpts: the reproduce review)."""
    if ctx.data_dir is None:
        data = ("Real data: the small excerpts shipped in the package (no `--data` and no "
                "`../shared/data`, from the working folder or beside the source checkout): "
                "the real-data figures are the excerpts', not the full data sets'.")
    else:
        data = f"Real data: `{ctx.data_dir}`."
    notes = "".join(f" Note: {n}." for n in sorted(ctx.notes))
    run = f" Seed {ctx.seed}{'; `--quick` (fewer trials and epochs)' if ctx.quick else ''}."
    return data + notes + run


def render(sections: list[Section], out_dir: Path, elapsed: dict[str, float],
           preface: str = "") -> tuple[Path, Path]:
    """Write ``report.md`` and ``report.html`` into ``out_dir`` (``preface``: a first
    paragraph, :func:`run_preface`)."""
    md = ["# robustloc reproduction report", ""]
    body = ["<h1>robustloc reproduction report</h1>"]
    if preface:
        md += [preface, ""]
        body.append(f"<p>{_html_text(preface)}</p>")
    # (by seed, "all" first, each seed's rows in section order: seed 002's real-data rows
    # of s30 and simulated rows of s60 together)
    heads = sorted((h for s in sections for h in s.headlines),
                   key=lambda h: (h["seed"] != "all", h["seed"]))
    if heads:  # the one-screen summary first: each headline, the paper's, ours, the peer's
        summ = pd.DataFrame(heads)
        md += ["## Summary", "", _md_table(summ), ""]
        body.append("<h2>Summary</h2>")
        body.append(format_frame(summ).to_html(index=False))
    for s in sections:
        md += [f"## {s.title}", ""]
        body.append(f"<h2>{html.escape(s.title)}</h2>")
        for kind, payload in s.blocks:
            if kind == "text":
                md += [payload, ""]
                body.append("".join(f"<p>{_html_text(p)}</p>" for p in payload.split("\n\n")))
            elif kind == "table":
                caption, frame = payload
                md += [f"**{caption}**", "", _md_table(frame), ""]
                body.append(f"<h4>{html.escape(caption)}</h4>")
                body.append(format_frame(frame).to_html(index=False))
            elif kind == "figure":
                caption, rel = payload
                md += [f"![{caption}]({rel})", "", f"*{caption}*", ""]
                body.append(
                    f'<figure><img src="{html.escape(rel)}" style="max-width:900px">'
                    f"<figcaption>{html.escape(caption)}</figcaption></figure>"
                )
        if s.title in elapsed:
            md += [f"_section run time: {elapsed[s.title]:.1f} s_", ""]
    md_path = out_dir / "report.md"
    md_path.write_text("\n".join(md), encoding="utf-8")
    style = (
        "body{font-family:sans-serif;max-width:1100px;margin:auto;padding:1em}"
        "table{border-collapse:collapse;font-size:0.85em;margin-bottom:1em}"
        "td,th{border:1px solid #ccc;padding:2px 6px;text-align:right}"
    )
    html_path = out_dir / "report.html"
    html_path.write_text(
        f"<!doctype html><html><head><meta charset='utf-8'><title>robustloc report</title>"
        f"<style>{style}</style></head><body>{''.join(body)}</body></html>",
        encoding="utf-8",
    )
    return md_path, html_path


def run_all(ctx: Context, only: list[str] | None = None) -> list[Section]:
    """Run every section (or ``only`` those), print their tables and write the report.

    The report is written whole or not at all: the sections write into a hidden staging
    folder beside ``ctx.out_dir``, which replaces it only once the report is complete
    (:class:`robustloc.reproduce._output.ReportFolder`).  An error or an interrupt leaves
    ``ctx.out_dir`` as it was: absent, or the previous complete report.

    Raises
    ------
    InputError
        ``ctx.out_dir`` is a file, or a folder that is neither empty nor a robustloc report
        (before any section runs).
    """
    from robustloc.reproduce._output import ReportFolder

    mods = section_modules(only)
    dest = ReportFolder(ctx.out_dir)
    run_ctx = dataclasses.replace(ctx, out_dir=dest.stage)  # (the notes set is shared)
    try:
        sections: list[Section] = []
        elapsed: dict[str, float] = {}
        summary: dict[str, Any] = {}
        for mod in mods:
            ctx.log(f"== {mod.TITLE}")
            t0 = time.perf_counter()
            sec = mod.run(run_ctx)
            elapsed[sec.title] = time.perf_counter() - t0
            sections.append(sec)
            summary[mod.KEY] = sec.summary
            for kind, payload in sec.blocks:
                if kind == "table":
                    caption, frame = payload
                    print(f"\n{caption}\n{text_table(frame)}")
        render(sections, dest.stage, elapsed, run_preface(ctx))
        (dest.stage / "summary.json").write_text(json.dumps(summary, indent=2, default=float))
        dest.commit()
    except BaseException:
        dest.abort()
        raise
    return sections
