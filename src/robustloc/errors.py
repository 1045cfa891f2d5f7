"""Errors raised for problems in a user's input.

Every problem that is the user's (a malformed file, a NaN, an unknown anchor id) raises
:class:`InputError`, a :class:`ValueError` that carries the file and line where it was
found.  The command line turns it into ``error: FILE:LINE: what`` on stderr and exit code 2.
"""

from __future__ import annotations

from os import PathLike

#: Exit codes: 2 user error, 130 interrupted (128 + SIGINT), 143 terminated (128 + SIGTERM),
#: 1 internal error (a bug).  (Here, below the commands, so that a command can return them
#: without importing the front end, :mod:`robustloc.cli`.)
EXIT_USER, EXIT_INTERNAL, EXIT_SIGINT, EXIT_SIGTERM = 2, 1, 130, 143


class InputError(ValueError):
    """A problem with user input, located by file and (optionally) line.

    Parameters
    ----------
    message : str
        What is wrong, in words a user understands.
    path : str or PathLike, optional
        The file where it was found.
    line : int, optional
        1-based line number in that file (the header is line 1 of a CSV file).
    """

    def __init__(
        self, message: str, path: str | PathLike[str] | None = None, line: int | None = None
    ) -> None:
        self.message = message
        self.path = None if path is None else str(path)
        self.line = line
        super().__init__(self.__str__())

    def __str__(self) -> str:
        where = ""
        if self.path is not None:
            where = self.path + (f":{self.line}" if self.line is not None else "") + ": "
        return where + self.message


class OutputError(InputError):
    """An output that cannot be written (no space, read-only, a parent that is a file, ...).

    Raised instead of a bare :class:`OSError` by the output writers, naming the final path
    the user gave; the command line prints ``error: PATH: what`` and exits with code 2.

    Parameters
    ----------
    message : str
        What went wrong, in words (``no space left on device``).
    path : str or PathLike, optional
        The output path as the user gave it.
    errno_ : int, optional
        The :mod:`errno` code of the underlying OS error, if any.
    """

    def __init__(
        self, message: str, path: str | PathLike[str] | None = None, *, errno_: int | None = None
    ) -> None:
        self.errno = errno_
        super().__init__(message, path)


class Terminated(BaseException):  # noqa: N818 - named after the signal, like KeyboardInterrupt
    """Raised by the command line's SIGTERM handler, so that ``finally`` blocks run and no
    partial output is left (exit code 143 = 128 + SIGTERM)."""
