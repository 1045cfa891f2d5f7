"""Folder outputs written whole or not at all (``stats``, ``simulate``, ``reliability``).

Commands that write several files into an output folder build them in a temporary folder
beside it and move them in only when every file is complete, so an error or an interrupt
never leaves a half-written folder behind.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import TypeVar

T = TypeVar("T")


def write_folder(out: Path, write: Callable[[Path], T]) -> T:
    """Run ``write(folder)`` on a fresh temporary folder beside ``out``, then move its files
    into ``out`` (created if missing); returns what ``write`` returned.  After an error
    nothing is left behind: neither the temporary folder nor a new ``out`` (files already in
    an existing ``out`` stay as they were).
    """
    import os
    import shutil
    import tempfile

    from robustloc.errors import InputError

    out = Path(out)
    if out.exists() and not out.is_dir():
        raise InputError("already exists and is not a folder (a folder was expected)", out)
    parent = out.parent if str(out.parent) else Path(".")
    parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.", suffix=".tmp", dir=parent))
    try:
        result = write(tmp)
        if any(p.is_dir() for p in tmp.iterdir()):
            raise RuntimeError("write_folder moves files only, not sub-folders")
        out.mkdir(exist_ok=True)
        for f in sorted(tmp.iterdir()):
            os.replace(f, out / f.name)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return result
