"""Folder outputs written whole or not at all (``stats``, ``simulate``, ``reliability``).

Commands that write several files into an output folder build them in a temporary folder
beside it and move them in only when every file is complete, so an error or an interrupt
never leaves a half-written folder behind, and a file of the folder that is one of the
command's inputs is never replaced.
"""

from __future__ import annotations

import os
import sys
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import TypeVar

T = TypeVar("T")


def write_folder(out: str | os.PathLike, write: Callable[[Path], T],
                 inputs: Iterable[str | os.PathLike | None] = (),
                 owns: Iterable[str] = ()) -> T:
    """Write files into the folder ``out``, whole or not at all.

    Runs ``write(folder)`` on a fresh temporary folder beside ``out``, then moves its files
    into ``out`` (created if missing).  After an error nothing is left behind: neither the
    temporary folder nor a new ``out`` (files already in an existing ``out`` stay as they
    were).

    Parameters
    ----------
    out : str or PathLike
        The output folder, as the user named it: pass the text, not ``Path(text)``
        (``Path("")`` is ``.``, so a blank name could no longer be told from ``.``).
    write : callable
        ``write(folder)`` writes the files (no sub-folders) into ``folder``.
    inputs : iterable of path, optional
        The command's input files (None entries are skipped).  A file ``write`` made that
        would replace one of them (the same file, by :func:`robustloc.io.atomic.
        check_not_input`: a path, a symbolic or a hard link) is refused before any file is
        moved.
    owns : iterable of str, optional
        Every file name the command can write.  One of them left in ``out`` by an earlier
        run that this run did not write (``per_bin.csv`` of a ``stats --truth`` run, the
        ``blocked.csv`` of ``simulate --disturbance``) gets a warning on stderr: it is not
        removed (it may be the user's), and it no longer belongs with the others (the
        no-loss review).

    Returns
    -------
    What ``write`` returned.

    Raises
    ------
    InputError
        ``out`` is empty or blank (``Path("")`` is the working folder, whose files would
        be replaced); ``out`` is a file; or ``OUT/NAME: output would overwrite an input``
        (nothing moved, ``out`` untouched).
    """
    import shutil
    import tempfile

    from robustloc.errors import InputError
    from robustloc.io.atomic import check_not_input

    if str(out) == "-":  # (a folder named "-" was created)
        raise InputError("standard output cannot hold a folder of files: give a folder name")
    if not str(out).strip():  # Path("") is "." (an unset $DIR): the files there replaced
        raise InputError("--out: empty output name (give a folder name)")
    out = Path(out)
    inputs = [i for i in inputs if i is not None]
    if out.exists() and not out.is_dir():
        raise InputError("already exists and is not a folder (a folder was expected)", out)
    parent = out.parent if str(out.parent) else Path(".")
    parent.mkdir(parents=True, exist_ok=True)
    from robustloc.io.atomic import sweep_orphans, temp_prefix

    sweep_orphans(parent, out.name)  # a killed run's staging folder
    try:
        tmp = Path(tempfile.mkdtemp(prefix=temp_prefix(out.name), suffix=".tmp", dir=parent))
    except OSError as exc:  # named as the folder asked for, not the hidden temporary one
        from robustloc.errors import OutputError
        from robustloc.io.atomic import describe_oserror

        raise OutputError(describe_oserror(exc), out, errno_=exc.errno) from None
    try:
        from robustloc.errors import OutputError

        try:
            result = write(tmp)
        except OutputError as exc:  # a writer's own, naming its file in the staging folder
            inside = exc.path is not None and Path(exc.path).parent == tmp
            if not inside:
                raise
            raise OutputError(exc.message, out / Path(exc.path).name,
                              errno_=exc.errno) from None
        except OSError as exc:
            # a write into the staging folder that the disk refused (full, quota): named
            # as the folder asked for, not a traceback (reliability, simulate wifi-room)
            # nor the hidden folder's file (simulate ble-corridor; the review)
            from robustloc.io.atomic import describe_oserror

            raise OutputError(describe_oserror(exc), out, errno_=exc.errno) from None
        files = sorted(tmp.iterdir())
        if any(p.is_dir() for p in files):
            raise RuntimeError("write_folder moves files only, not sub-folders")
        for f in files:  # every target checked before the first move
            check_not_input(out / f.name, inputs)
            if (out / f.name).is_dir():  # (os.replace failed there, files already moved)
                raise InputError("is a folder, where this command writes a file",
                                 out / f.name)
        out.mkdir(exist_ok=True)
        _move_all(files, out, tmp)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    written = {f.name for f in files}
    for name in sorted(set(owns) - written):
        if (out / name).is_file():
            print(f"warning: {out / name} is from an earlier run: this run wrote no {name} "
                  "(remove it, or write into a new folder)", file=sys.stderr)
    return result


def _move_all(files: list[Path], out: Path, tmp: Path) -> None:
    """Move ``files`` into ``out``, all or none: the files they replace are set aside in
    ``tmp`` first and put back if a move fails (a full disk, a permission), so a failed
    run never leaves ``out`` with some files new and some old."""
    aside = tmp / ".replaced"
    aside.mkdir()
    kept: list[tuple[Path, Path]] = []
    moved: list[Path] = []
    try:
        for f in files:
            target = out / f.name
            if target.exists():
                os.replace(target, aside / f.name)
                kept.append((aside / f.name, target))
        for f in files:
            os.replace(f, out / f.name)
            moved.append(out / f.name)
    except BaseException:
        for m in moved:
            m.unlink(missing_ok=True)
        for src, dst in kept:
            os.replace(src, dst)
        raise
