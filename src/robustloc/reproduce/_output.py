"""The report folder of ``robustloc reproduce``, written whole or not at all.

A run writes its figures, tables and report into a hidden staging folder beside the
output (``.NAME.partial-XXXXXXXX``, the naming of :class:`robustloc.engines.dask.
DatasetOutput`) and puts it in place only when the report is complete: an error or an
interrupt (Ctrl-C, SIGTERM) removes the staging folder and leaves the output as it was
(absent, or the previous complete report).  A previous report is replaced whole (renamed
aside, the new one renamed in, the old one deleted), so no moment leaves a folder that
mixes two runs.  A folder that is not a robustloc report is never replaced.

(:func:`robustloc.commands._folder.write_folder` merges files into an existing folder,
which would keep the figures of an earlier run's other sections beside the new report,
and ``DatasetOutput`` marks its folder as a dataset and lives with the dask engine, so
neither fits as it is.)
"""

from __future__ import annotations

import os
import shutil
import signal
from pathlib import Path

from robustloc.errors import InputError, OutputError

#: First line of every ``report.md`` written by :func:`robustloc.reproduce.render`.
REPORT_HEADER = "# robustloc reproduction report"
#: Kinds of file a report folder holds (report.md, report.html, summary.json, CSV, PNG).
REPORT_SUFFIXES = frozenset({".md", ".html", ".json", ".csv", ".png"})


def check_out_text(text: str) -> None:
    """Refuse an empty or blank ``-o`` (``Path("")`` is ``.``: the report would land in the
    working folder), and ``-`` (a folder named ``-`` was written: a report is a folder,
    not standard output)."""
    if not str(text).strip():
        raise InputError("-o: empty path")
    if str(text).strip() == "-":
        raise InputError("-o -: reproduce writes a report folder, not standard output; "
                         "give a folder name")


def is_report(folder: Path) -> bool:
    """``folder`` holds a robustloc report and nothing else: a ``report.md`` written by
    ``reproduce`` and only plain files of the kinds a report holds."""
    md = folder / "report.md"
    try:
        if not md.is_file() or md.is_symlink():
            return False
        with md.open(encoding="utf-8", errors="replace") as fh:
            if fh.readline().rstrip("\n") != REPORT_HEADER:
                return False
        for p in folder.iterdir():
            if p.is_symlink() or not p.is_file() or p.suffix.lower() not in REPORT_SUFFIXES:
                return False
    except OSError:
        return False
    return True


def report_sections(folder: Path) -> list[str]:
    """The sections of the report in ``folder`` (the keys of its ``summary.json``); empty
    when it holds no report, or one whose summary cannot be read."""
    import json

    if not folder.is_dir() or not is_report(folder):
        return []
    try:
        summary = json.loads((folder / "summary.json").read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return []
    return [str(k) for k in summary] if isinstance(summary, dict) else []


def check_out(out: Path) -> None:
    """Refuse an output that cannot take a report, before any work: a file, a path under a
    file, or a folder that is neither empty nor a robustloc report (its files would be
    deleted)."""
    if out.exists() and not out.is_dir():
        raise InputError("exists and is not a folder (reproduce writes a report folder)",
                         out)
    for parent in out.absolute().parents:  # (it said "already exists" of a path that
        if parent.exists():                # did not: the reproduce review)
            if not parent.is_dir():
                raise InputError("a parent of this path is a file, not a folder", out)
            break
    if out.is_dir():
        try:
            empty = not any(out.iterdir())
        except OSError as exc:
            from robustloc.io.atomic import describe_oserror

            raise OutputError(describe_oserror(exc), out, errno_=exc.errno) from None
        if not empty and not is_report(out):
            raise InputError("folder exists and is not a robustloc report; refusing to "
                             "replace it (give a new folder, or a report folder)", out)


class ReportFolder:
    """A report folder built in a staging folder beside ``out`` and renamed into place.

    Parameters
    ----------
    out : Path
        The report folder.  Absent, empty or a previous robustloc report (replaced whole
        on :meth:`commit`); anything else is refused (:func:`check_out`).
    """

    def __init__(self, out: Path) -> None:
        check_out_text(str(out))
        self.given = Path(out)  # as the user gave it, for messages
        # the real path: ``-o .`` is the working folder, named beside it; a symbolic link
        # to a report folder has the new report staged beside (and renamed over) its target
        self.out = Path(os.path.realpath(out))
        check_out(self.given)
        parent = self.out.parent
        from robustloc.io.atomic import aside_name, staging_name, sweep_orphans

        self.stage = parent / staging_name(self.out.name)
        self._old = parent / aside_name(self.out.name)
        try:
            parent.mkdir(parents=True, exist_ok=True)
            sweep_orphans(parent, self.out.name)  # a killed run's staging folder
            self.stage.mkdir()
        except OSError as exc:  # named as the folder asked for, not the hidden one
            from robustloc.io.atomic import describe_oserror

            raise OutputError(describe_oserror(exc), self.given, errno_=exc.errno) from None

    def commit(self) -> None:
        """Put the complete report in place of ``out`` (its previous report deleted)."""
        check_out(self.given)  # (the folder may have changed during the run)
        blocked = _block_signals()
        try:
            moved_aside = False
            try:
                if self.out.is_dir():
                    os.rename(self.out, self._old)
                    moved_aside = True
                os.rename(self.stage, self.out)
            except OSError as exc:
                if moved_aside and not self.out.exists():
                    os.rename(self._old, self.out)  # the previous report back in place
                from robustloc.io.atomic import describe_oserror

                raise OutputError(describe_oserror(exc), self.given,
                                  errno_=exc.errno) from None
            shutil.rmtree(self._old, ignore_errors=True)  # (an interrupt held back till done)
        finally:
            _unblock_signals(blocked)

    def abort(self) -> None:
        """Remove the staging folder (after an error or an interrupt)."""
        shutil.rmtree(self.stage, ignore_errors=True)


_SIGNALS = tuple(s for s in (getattr(signal, "SIGINT", None), getattr(signal, "SIGTERM", None))
                 if s is not None)


def _block_signals() -> bool:
    """Hold Ctrl-C and SIGTERM back during :meth:`ReportFolder.commit` (delivered right
    after it), so an interrupt cannot fall between its two renames or leave the previous
    report half deleted."""
    if not hasattr(signal, "pthread_sigmask"):
        return False
    try:
        signal.pthread_sigmask(signal.SIG_BLOCK, _SIGNALS)
    except (OSError, ValueError):
        return False
    return True


def _unblock_signals(blocked: bool) -> None:
    if blocked:
        signal.pthread_sigmask(signal.SIG_UNBLOCK, _SIGNALS)
