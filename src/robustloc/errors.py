"""Errors raised for problems in a user's input.

Every problem that is the user's (a malformed file, a NaN, an unknown anchor id) raises
:class:`InputError`, a :class:`ValueError` that carries the file and line where it was
found.  The command line turns it into ``error: FILE:LINE: what`` on stderr and exit code 2.
"""

from __future__ import annotations

from os import PathLike


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
