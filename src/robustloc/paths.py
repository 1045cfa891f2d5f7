"""Where data lives: the shared real-data folder and the excerpts shipped in the package."""

from __future__ import annotations

from pathlib import Path

#: Small real-data excerpts shipped inside the package (licence and source beside each).
PACKAGE_DATA = Path(__file__).resolve().parent / "data"


def default_data_dir() -> Path | None:
    """Return ``../shared/data`` relative to the working directory or the source tree.

    Looks beside the current directory first (a checkout run from its root), then beside
    the source checkout this package was installed from.  Returns ``None`` when neither
    exists (a user's fresh clone), so callers fall back to the shipped excerpts.
    """
    candidates = [
        Path.cwd() / ".." / "shared" / "data",
        Path(__file__).resolve().parents[3] / "shared" / "data",
    ]
    for c in candidates:
        if c.is_dir():
            return c.resolve()
    return None


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
