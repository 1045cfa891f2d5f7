"""Where data lives: the shared real-data folder and the excerpts shipped in the package."""

from __future__ import annotations

import os
import sys
from pathlib import Path
from typing import Union

if sys.version_info >= (3, 11):
    from importlib.resources.abc import Traversable
else:  # (the same protocol, under its older name)
    from importlib.abc import Traversable

#: A data folder as the dataset loaders take it (``data_dir``): a str, an
#: :class:`os.PathLike`, or an :mod:`importlib.resources` ``Traversable`` such as
#: ``files("robustloc") / "data" / "wifi-rtt-rss"`` (a :class:`pathlib.Path` for a
#: package installed as files: :func:`data_folder`).
DataDir = Union[str, "os.PathLike[str]", Traversable]

#: Small real-data excerpts shipped inside the package (licence and source beside each).
PACKAGE_DATA = Path(__file__).resolve().parent / "data"


def default_data_candidates() -> list[Path]:
    """The folders :func:`default_data_dir` tries, in order: ``../shared/data`` from the
    working directory (a checkout run from its root), then ``shared/data`` beside the
    source checkout this package was installed from (the checkout's ``../shared/data``)."""
    return [
        Path.cwd() / ".." / "shared" / "data",
        Path(__file__).resolve().parents[3] / "shared" / "data",
    ]


def default_data_dir() -> Path | None:
    """Return the first of :func:`default_data_candidates` that is a folder, resolved.

    Returns ``None`` when neither exists (a user's fresh clone), so callers fall back to
    the shipped excerpts.
    """
    for c in default_data_candidates():
        if c.is_dir():
            return c.resolve()
    return None


def default_data_help() -> str:
    """What :func:`default_data_dir` does, in words, for a command's ``--help``."""
    cwd, src = default_data_candidates()
    return (f"../shared/data from the working folder if it exists, else {src.resolve()} "
            "(the shared/data beside the source checkout robustloc runs from) if it exists, "
            "else the small excerpts shipped in the package")


def resolve_data_dir(data: str | Path | None) -> Path | None:
    """Resolve a ``--data DIR`` option: the given folder, else :func:`default_data_dir`."""
    if data is not None:
        p = Path(data)
        if not p.is_dir():
            from robustloc.errors import InputError

            raise InputError(f"--data: {p} is a file, not a data folder" if p.exists()
                             else f"data folder does not exist: {p}")
        return p.resolve()
    return default_data_dir()


def data_folder(data_dir: DataDir) -> Path:
    """``data_dir`` as a :class:`~pathlib.Path`.

    Parameters
    ----------
    data_dir : str, PathLike or Traversable
        A folder; ``importlib.resources.files(...)`` of a package installed as files is a
        :class:`pathlib.Path` already.

    Returns
    -------
    Path

    Raises
    ------
    InputError
        A ``Traversable`` that is no folder on the file system (a package inside a zip
        archive), or anything that is not a path.
    """
    if isinstance(data_dir, (str, os.PathLike)):
        path = os.fspath(data_dir)
        if isinstance(path, str):
            return Path(path)
    from robustloc.errors import InputError

    if isinstance(data_dir, Traversable):
        raise InputError(f"data_dir: {data_dir} ({type(data_dir).__name__}) is a resource, not "
                         "a folder on the file system: extract it first (`with "
                         "importlib.resources.as_file(resource) as folder:`, Python 3.12+)")
    raise InputError(f"data_dir: expected a folder path, got {type(data_dir).__name__}")
