"""Readers and writers of the contract tables (design.md, "File formats (contract)").

Every table is CSV with a header, or Parquet with the same columns; the format is chosen by
the file extension (``.parquet``/``.pq`` is Parquet, anything else is read as CSV, with
pandas' compression by extension such as ``.csv.gz``).  Extra columns are carried through,
unknown ones are ignored by the consumers.

Validation
----------
Every problem in a file raises :class:`~robustloc.errors.InputError` naming the file and the
1-based line (the CSV header is line 1, the first data row line 2).  For Parquet files the
"line" is the same number the row would have in the equivalent CSV (data row ``i``, counted
from 0, is line ``i + 2``).  Checked: missing file, empty file, missing required column,
non-numeric value, NaN/inf in a numeric field, empty id, duplicate anchor id, duplicate
``(time, tag)`` truth row, unknown anchor id (when the anchors are given), malformed rows.
Blank lines are skipped.

The frames returned keep the source line numbers as their index (named ``line``), so a
consumer can still point at a line after filtering; ``frame.attrs["path"]`` holds the file.

Ids (``anchor``, ``tag``) are strings.  ``time`` is seconds (float).  A range may be negative
or shorter than the height difference: that is data, not an error.
"""

from __future__ import annotations

import contextlib
import lzma
import os
import re
import stat
import threading
import warnings
import zipfile
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
from numpy.typing import ArrayLike, NDArray

from robustloc._arrays import to_number
from robustloc.errors import InputError
from robustloc.io.limits import plausible
from robustloc.options import SIGMA_RANGE

PathLike = str | os.PathLike

#: Optional numeric columns of an anchors file: path-loss parameters (log-distance ``A, n``;
#: attenuation factor ``p0, gamma, faf, d0``) and range calibration (``bias, scale``).
ANCHOR_PARAM_COLUMNS = ("A", "n", "p0", "gamma", "faf", "d0", "bias", "scale")
#: Measurement value columns: exactly one must be present.
VALUE_COLUMNS = ("rssi", "range")
#: Columns of a positions file, in order (``z`` after ``y`` when 3-D).
POSITION_COLUMNS = ("time", "tag", "x", "y", "method", "status", "n_used", "sigma0", "excluded")

_PARQUET_EXT = (".parquet", ".pq")
_DEFAULT_CHUNK_ROWS = 500_000


# --------------------------------------------------------------------------------------
# low-level reading
# --------------------------------------------------------------------------------------


def is_parquet(path: PathLike) -> bool:
    """True if ``path`` names a Parquet file (by extension)."""
    return str(path).lower().endswith(_PARQUET_EXT)


_SPOOLED: dict[str, Path] = {}
#: What standard input was read as in this scope (the reader's noun, ``"truth"``): one
#: input of a command can come from standard input.  Every input named ``-`` read the
#: first one's spooled copy (``evaluate - --truth -`` compared the positions with
#: themselves and exited 0 with every error 0: the input review).
_STDIN_READ_AS: dict[str, str] = {}
_GZIP_MAGIC = b"\x1f\x8b"
_PARQUET_MAGIC = b"PAR1"
#: Compressed CSV by its first bytes (the formats pandas reads): the content decides, not
#: the file's name (a plain CSV named ``.zip`` is read as text; a valid ``.xz`` was
#: refused as "not UTF-8", an invalid ``.zip`` ended in a ``BadZipFile`` traceback: the
#: fuzz review of 2026-12-06).
_COMPRESSED_MAGIC = (("gzip", _GZIP_MAGIC), ("bz2", b"BZh"), ("xz", b"\xfd7zXZ\x00"),
                     ("zip", b"PK\x03\x04"), ("zstd", b"\x28\xb5\x2f\xfd"))


def _display(path: PathLike | pd.DataFrame) -> str:
    """The name of ``path`` in messages (``<stdin>`` for ``-``; an in-memory frame's
    ``attrs["path"]``, else ``<measurements DataFrame>``)."""
    if isinstance(path, pd.DataFrame):
        return str(path.attrs.get("path") or "<measurements DataFrame>")
    return "<stdin>" if str(path) == "-" else str(path)


def in_memory_source(df: pd.DataFrame, what: str = "measurements") -> pd.DataFrame:
    """A frame as a source the readers stream like a file (:func:`iter_measurements`,
    :func:`iter_epochs`): its rows named by their ``line`` index and ``attrs["path"]``
    (kept when it came from a reader, which names the file), else by the line the row
    would have in ``df.to_csv(index=False)`` (row position + 2) of ``<WHAT DataFrame>``.

    Examples
    --------
    >>> src = in_memory_source(pd.DataFrame({"time": [0.0], "tag": ["t"], "anchor": ["a"],
    ...                                      "range": [1.0]}))
    >>> src.attrs["path"], list(src.index)
    ('<measurements DataFrame>', [2])
    """
    if df.index.name == "line" and df.attrs.get("path"):
        return df
    out = df.copy()
    out.index = pd.RangeIndex(2, len(out) + 2, name="line")
    out.attrs = {"path": f"<{what} DataFrame>"}
    return out


def _cleanup_spool() -> None:
    for tmp in list(_SPOOLED.values()):
        try:
            tmp.unlink()
        except OSError:
            pass
    _SPOOLED.clear()
    _STDIN_READ_AS.clear()


_SPOOL_DEPTH = [0]
_SPOOL_LOCK = threading.Lock()


@contextlib.contextmanager
def spool_scope() -> Iterator[None]:
    """The life of spooled inputs (:func:`_spool`): one command, or one call of the Python
    API.  Standard input and FIFOs are copied once per scope (a command reads its input
    twice: the log's scale, then the fixes) and the copies removed when the outermost
    scope ends, so the next call reads its input anew.  (The copies used to live as long
    as the process: a program calling ``robustloc.locate("-")`` twice got the first
    call's data again.)"""
    with _SPOOL_LOCK:
        _SPOOL_DEPTH[0] += 1
    try:
        yield
    finally:
        with _SPOOL_LOCK:
            _SPOOL_DEPTH[0] -= 1
            if _SPOOL_DEPTH[0] == 0:
                _cleanup_spool()


def _claim_stdin(what: str | None) -> None:
    """Note that standard input is read as the ``what`` input (the reader's noun:
    ``"measurements"``, ``"truth"``, ...); another input also named ``-`` is an
    :class:`InputError`.

    Standard input is one stream: it can feed one input of a command.  The same input
    read again (``locate`` reads its measurements twice: the log's scale, then the fixes)
    is the same noun and reads the spooled copy.  ``None`` (a caller that does not say
    what it reads) is not checked.

    Raises
    ------
    InputError
        ``<stdin>: standard input is already read as another input of this command (the
        WHAT1 file), so the WHAT2 file cannot also be - (...)``.
    """
    if what is None:
        return
    first = _STDIN_READ_AS.setdefault("-", what)
    if first != what:
        # (a second input named - got the first one's data: the input review)
        raise InputError(
            f"standard input is already read as another input of this command (the "
            f"{first} file), so the {what} file cannot also be - (one input per command "
            "can come from standard input: give the other one as a file)", _display("-"))


def _spool(path: PathLike, what: str | None = None) -> Path:
    """Copy standard input (``-``) or a FIFO (``<(cat m.csv)``) to a temporary regular
    file once per :func:`spool_scope` (else per process), so that it can be read by name,
    more than once, and seeked (Parquet).  Removed when the scope ends, or at exit.

    Parameters
    ----------
    path : str or PathLike
        ``-`` or the FIFO's name.
    what : str, optional
        The input it is read as (``"measurements"``, ``"truth"``, ...): standard input
        read as a second input is an :class:`InputError` (:func:`_claim_stdin`).
    """
    import atexit
    import shutil
    import sys
    import tempfile

    key = str(path)
    if key == "-":
        _claim_stdin(what)
    if key in _SPOOLED:
        return _SPOOLED[key]
    if not _SPOOLED:
        atexit.register(_cleanup_spool)
    suffix = ".parquet" if is_parquet(key) else ".csv"
    fd, name = tempfile.mkstemp(prefix="robustloc-stdin-", suffix=suffix)
    tmp = Path(name)
    _SPOOLED[key] = tmp
    with os.fdopen(fd, "wb") as out:
        if key == "-":
            shutil.copyfileobj(sys.stdin.buffer, out, 1 << 20)
        else:
            with open(path, "rb") as src:
                shutil.copyfileobj(src, out, 1 << 20)
    return tmp


def _check_file(path: PathLike, engine_hint: bool = True, what: str | None = None) -> Path:
    """The regular file to read for ``path`` (standard input and FIFOs are spooled);
    missing, a directory, or empty is an :class:`InputError`.  ``engine_hint``: a
    directory's error says a partitioned dataset is read with ``--engine dask`` (for a
    command that offers it), else that the command reads one file.  ``what``: the input
    it is read as (:func:`_spool`)."""
    import stat

    name = _display(path)
    if str(path) == "-":
        p = _spool(path, what)
    else:
        p = Path(path)
        if not p.exists():
            raise InputError("file not found", name)
        if p.is_dir():
            # (a `robustloc partition` dataset is read with --engine dask: the new-user
            # review found no word of it)
            # (replay, which has no --engine, gave that hint too: the replay review)
            raise InputError("is a directory, expected a file (" + (
                "a partitioned dataset is read with --engine dask" if engine_hint else
                "this command reads one file, not a partitioned dataset") + ")", name)
        if not stat.S_ISREG(p.stat().st_mode):  # FIFO, character device: read, don't stat
            p = _spool(path)
    if p.stat().st_size == 0:
        # (a file of /proc or /sys has content but reports size 0: `/proc/self/status:1:
        # empty file` -- the input review; such a file is read once, as a FIFO)
        with open(p, "rb") as fh:
            if not fh.read(1):
                raise InputError("empty file (expected a header line)", name, 1)
        p = _spool(path)
    return p


def _magic(p: Path) -> bytes:
    with open(p, "rb") as fh:
        return fh.read(6)


def _format(p: Path, path: PathLike) -> str:
    """``parquet``, a compressed CSV (``gzip``, ``bz2``, ``xz``, ``zip``, ``zstd``) or
    ``csv`` (plain text), by the file's first bytes: a gzip file named ``.csv`` is read
    decompressed, a Parquet file named ``.csv`` as Parquet, a plain CSV named ``.zip`` as
    text.  A Parquet file is also known by its extension (:func:`is_parquet`)."""
    head = _magic(p)
    for kind, magic in _COMPRESSED_MAGIC:
        if head.startswith(magic):
            return kind
    if is_parquet(path) or head[:4] == _PARQUET_MAGIC:
        return "parquet"
    return "csv"


def _open_bytes(p: Path, fmt: str):
    """The file's bytes, decompressed as :func:`_format` found them."""
    if fmt == "gzip":
        import gzip

        return gzip.open(p, "rb")
    if fmt == "bz2":
        import bz2

        return bz2.open(p, "rb")
    if fmt == "xz":
        import lzma

        return lzma.open(p, "rb")
    if fmt == "zip":
        return _zip_member(p)
    if fmt == "zstd":
        try:
            import zstandard
        except ImportError:
            raise InputError("a zstd-compressed file: reading it needs the zstandard "
                             "package (pip install zstandard), or decompress it first",
                             _display(p)) from None
        return zstandard.ZstdDecompressor().stream_reader(open(p, "rb"), closefd=True)
    return open(p, "rb")


@contextlib.contextmanager
def _zip_member(p: Path) -> Iterator[Any]:
    """The one file of a zip archive (pandas reads a zip of exactly one file)."""
    try:
        z = zipfile.ZipFile(p)
    except (zipfile.BadZipFile, OSError, ValueError) as exc:
        raise InputError(f"cannot read the zip file: {_first_line(exc)}",
                         _display(p)) from None
    with z:
        members = [i for i in z.infolist() if not i.is_dir()]
        if len(members) != 1:
            raise InputError(f"a zip file must hold exactly one file (this one holds "
                             f"{len(members)})", _display(p))
        with z.open(members[0]) as fh:
            yield fh


def _compression(fmt: str) -> str | None:
    """pandas' ``compression`` for a file of format ``fmt`` (None: plain text)."""
    return fmt if fmt in ("gzip", "bz2", "xz", "zip", "zstd") else None


_TOKENIZE_RE = re.compile(r"Expected (\d+) fields in line (\d+), saw (\d+)")


def _parser_error(exc: Exception, p: Path, path: PathLike, fmt: str) -> InputError:
    name = _display(path)
    if isinstance(exc, UnicodeDecodeError):
        return _decode_error(p, path, fmt)
    msg = str(exc)
    m = _TOKENIZE_RE.search(msg)
    if m:
        # pandas names the first row with too many fields; an earlier row with too few
        # (which it fills with NaN) is the first one to fix: the same scan as the guard's
        first = _ragged_line(p, path, fmt)
        if first.line is not None and first.line < int(m.group(2)):
            return first
        return InputError(
            f"expected {m.group(1)} fields, found {m.group(3)}", name, int(m.group(2))
        )
    if "EOF inside string" in msg:
        return _unclosed_quote(p, path, fmt)
    return InputError(f"cannot parse: {msg.strip()}", name)


def _unclosed_quote(p: Path, path: PathLike, fmt: str) -> InputError:
    """The line where a quoted field opens and is never closed (slow path, after pandas'
    "EOF inside string starting at row N", whose N counts records, not lines)."""
    start, inside = None, False
    with _open_bytes(p, fmt) as raw:
        for k, line in enumerate(raw, start=1):
            if line.count(b'"') % 2:
                inside = not inside
                start = k if inside else start
    return InputError('a quoted field opens here and is never closed (a " without its '
                      'closing ")', _display(path), start if inside else None)


def _empty_error(p: Path, path: PathLike, fmt: str) -> InputError:
    """pandas' "No columns to parse": the file is empty, or its first line is blank."""
    with _open_bytes(p, fmt) as raw:
        first = raw.readline()
    if first.strip(b"\r\n\t \xef\xbb\xbf"):
        return InputError("no columns in the header line", _display(path), 1)
    if first:
        return InputError("line 1 is blank: the first line must be the header "
                          "(time,tag,anchor,...)", _display(path), 1)
    return InputError("empty file (expected a header line)", _display(path), 1)


def _decode_error(p: Path, path: PathLike, fmt: str) -> InputError:
    """Locate the first line that is not UTF-8 (slow path, only after a failure)."""
    import codecs

    name = _display(path)
    try:
        with _open_bytes(p, fmt) as fh:
            for i, raw in enumerate(fh, 1):
                try:
                    codecs.decode(raw, "utf-8")
                except UnicodeDecodeError as exc:
                    return InputError(
                        f"not UTF-8 text: byte 0x{raw[exc.start]:02x} at column {exc.start + 1}"
                        " (a binary or compressed file? save it as UTF-8 CSV)", name, i)
    except OSError as exc:  # e.g. a truncated gzip stream
        return InputError(f"cannot read: {exc}", name)
    return InputError("not UTF-8 text", name)


def _ragged_line(p: Path, path: PathLike, fmt: str = "csv") -> InputError:
    """Locate the first row whose field count differs from the header's (slow path)."""
    import csv
    import io

    name = _display(path)
    with _open_bytes(p, fmt) as raw:
        fh = io.TextIOWrapper(raw, encoding="utf-8", errors="replace", newline="")
        reader = csv.reader(fh)
        header = next(reader, [])
        for row in reader:
            if row and len(row) != len(header):
                # a comment line read as the header (the no-loss review): say so
                hint = ("; line 1 looks like a comment: robustloc reads no comment lines, "
                        "the first line must be the header"
                        if header and header[0].lstrip().startswith("#") else "")
                return InputError(f"expected {len(header)} fields, found {len(row)}{hint}",
                                  name, reader.line_num)
    return InputError("rows do not match the header's number of fields", name)


class _RaggedGuard:
    """Turn pandas' "Length of header ... does not match" warning into an InputError.

    (With ``index_col=False`` pandas truncates a row with extra fields and only warns;
    without it, an extra field in the first row silently becomes the index.)

    Also refuses a file that changed while it was read (its size or modification time
    differs at the end): a log still being written was read up to a half-written line,
    whose epoch was solved on part of its rows or with a cut value ("-7" of "-79.0"),
    with exit 0 (the no-loss review).
    """

    def __init__(self, p: Path, path: PathLike, fmt: str) -> None:
        self.p, self.path, self.fmt = p, path, fmt

    def _stamp(self) -> tuple[int, int] | None:
        try:
            s = os.stat(self.p)
        except OSError:
            return None
        return (s.st_size, s.st_mtime_ns) if stat.S_ISREG(s.st_mode) else None

    def __enter__(self) -> _RaggedGuard:
        self._before = self._stamp()
        self._cm = warnings.catch_warnings(record=True)
        self._log = self._cm.__enter__()
        warnings.simplefilter("always", pd.errors.ParserWarning)
        return self

    def __exit__(self, *exc: object) -> None:
        self._cm.__exit__(*exc)
        if exc[0] is None:
            self.check()
            if self._before is not None and self._stamp() != self._before:
                raise InputError("the file changed while it was read (is it still being "
                                 "written?): run again on a complete copy",
                                 _display(self.path))

    def check(self) -> None:
        for w in self._log:
            if issubclass(w.category, pd.errors.ParserWarning) and "Length of header" in str(
                w.message
            ):
                raise _ragged_line(self.p, self.path, self.fmt)


_NA_NUMERIC = ["", "nan", "NaN", "NAN", "NA", "null", "None"]


def _check_header(names: Sequence[str], path: PathLike) -> None:
    """A column named twice is an error on line 1 (pandas would rename one ``x.1``)."""
    seen: set[str] = set()
    for c in names:
        c = str(c).strip()
        if c in seen:
            raise InputError(f"duplicate column {c!r} in the header", _display(path), 1)
        seen.add(c)


def _csv_kwargs(p: Path, path: PathLike, fmt: str, str_columns: Sequence[str]) -> dict:
    """read_csv options: ids as strings (only an empty field is missing, so an anchor may
    be called "NA"), the usual missing-value spellings in every other column."""
    import csv
    import io

    with _open_bytes(p, fmt) as raw:
        fh = io.TextIOWrapper(raw, encoding="utf-8", newline="")
        first = next(csv.reader(fh, skipinitialspace=True), [])
    _check_header(first, path)
    header = pd.read_csv(p, nrows=0, skipinitialspace=True, index_col=False,
                         compression=_compression(fmt))
    names = [str(c) for c in header.columns]
    strs = {c for c in str_columns}
    return dict(
        index_col=False,
        dtype={c: str for c in names if c.strip() in strs},
        skip_blank_lines=False,
        skipinitialspace=True,
        keep_default_na=False,
        na_values={c: ([""] if c.strip() in strs else _NA_NUMERIC) for c in names},
        compression=_compression(fmt),
    )


_NEWLINE_RE = r"\r\n|\r|\n"


def _quoted_newlines(df: pd.DataFrame) -> np.ndarray | None:
    """Line breaks inside each row's quoted fields, or None when there are none.

    A CSV record that holds a quoted field with a line break spans several physical lines;
    numbering records as lines would point every later error at the wrong line.  Only
    text columns can hold one, and ids repeat, so the unique values are checked first.
    """
    counts = None
    for col in df.columns:
        s = df[col]
        if s.dtype != object and not pd.api.types.is_string_dtype(s.dtype):
            continue
        uniq = pd.unique(s.dropna())
        if not any(isinstance(v, str) and ("\n" in v or "\r" in v) for v in uniq):
            continue
        n = s.str.count(_NEWLINE_RE).fillna(0).to_numpy(dtype=np.int64)
        counts = n if counts is None else counts + n
    return counts


#: Bytes read at a time by the scan for line breaks in quoted fields.
_SCAN_BLOCK = 1 << 20
#: Record breaks of a file whose records each take one line.
_NO_BREAKS: tuple[NDArray[np.int64], NDArray[np.int64]] = (
    np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64))


def _csv_bytes(p: Path, fmt: str):
    """The file's text as bytes, decompressed as pandas reads it (gzip found by content,
    other compressions by the extension): a handle whose ``.handle`` is a binary stream."""
    from pandas.io.common import get_handle

    return get_handle(p, "rb", compression=_compression(fmt), is_text=False)


def _may_break_in_quotes(p: Path, fmt: str) -> bool:
    """Whether a line break byte may lie inside a quoted field: one after an odd number of
    ``"`` bytes (a doubled ``""`` inside a field counts two).  False for a file without
    any ``"`` after one fast pass; a stray quote inside an unquoted field may answer True
    wrongly, never False wrongly."""
    odd = 0
    with _csv_bytes(p, fmt) as h:
        while True:
            block = h.handle.read(_SCAN_BLOCK)
            if not block:
                return False
            if not odd and b'"' not in block:
                continue
            a = np.frombuffer(block, dtype=np.uint8)
            quotes = np.flatnonzero(a == 34)
            breaks = np.flatnonzero((a == 10) | (a == 13))
            # the quotes before each break: odd (with the blocks before) = inside one
            if np.any((np.searchsorted(quotes, breaks) + odd) & 1):
                return True
            odd = (odd + quotes.size) & 1


def _record_breaks(
    p: Path, fmt: str
) -> tuple[NDArray[np.int64], NDArray[np.int64]] | None:
    """Line breaks inside the quoted fields of each data record, counted on the file's
    text (any column: a number such as ``"5\n"`` is read as 5 and its break was lost).

    Returns ``(records, extra)``: the 0-based data records (the record after the header
    is 0; a blank line is a record, as pandas reads it) that span more than one line, and
    how many lines each spans beyond its first; empty arrays when every record takes one
    line (one fast pass over a file without quotes).  None when the text cannot be
    scanned (the CSV reader then reports the file's fault, or the breaks are counted in
    the text columns).
    """
    import csv
    import io

    try:
        if not _may_break_in_quotes(p, fmt):
            return _NO_BREAKS
        recs: list[int] = []
        extra: list[int] = []
        with _csv_bytes(p, fmt) as h:
            fh = io.TextIOWrapper(h.handle, encoding="utf-8", errors="replace", newline="")
            # (skipinitialspace as the reader's: `, "5` opens a quoted field)
            reader = csv.reader(fh, skipinitialspace=True)
            prev = 0
            for rec, _ in enumerate(reader, start=-1):
                k = reader.line_num - prev - 1
                if k > 0 and rec >= 0:
                    recs.append(rec)
                    extra.append(k)
                prev = reader.line_num
    except (OSError, EOFError, ValueError, csv.Error):
        return None
    return np.asarray(recs, dtype=np.int64), np.asarray(extra, dtype=np.int64)


def _extra_lines(
    breaks: tuple[NDArray[np.int64], NDArray[np.int64]], first_record: int, n: int
) -> NDArray[np.int64] | None:
    """Lines beyond the first of records ``first_record .. first_record + n - 1`` (None
    when each takes one), from :func:`_record_breaks`."""
    recs, extra = breaks
    lo, hi = np.searchsorted(recs, [first_record, first_record + n])
    if lo == hi:
        return None
    out = np.zeros(n, dtype=np.int64)
    out[recs[lo:hi] - first_record] = extra[lo:hi]
    return out


def _finish_frame(
    df: pd.DataFrame, path: PathLike, first_line: int, *, text: bool = False,
    breaks: tuple[NDArray[np.int64], NDArray[np.int64]] | None = None,
    first_record: int = 0,
) -> tuple[pd.DataFrame, int]:
    """Name the index by source line, strip column names, drop blank lines.

    Returns the frame and the line after its last row.  With ``text`` (a CSV file) a record
    whose quoted field holds line breaks takes as many lines as it spans: by ``breaks``
    (:func:`_record_breaks` of the file; ``first_record`` is the frame's first record),
    else by the breaks found in the frame's text columns.
    """
    df.columns = [str(c).strip() for c in df.columns]
    _check_header(df.columns, path)
    extra = None
    if text:
        extra = (_quoted_newlines(df) if breaks is None
                 else _extra_lines(breaks, first_record, len(df)))
    if extra is None:
        df.index = pd.RangeIndex(first_line, first_line + len(df), name="line")
        next_line = first_line + len(df)
    else:
        start = first_line + np.arange(len(df), dtype=np.int64) + np.cumsum(extra) - extra
        df.index = pd.Index(start, name="line")
        next_line = first_line + len(df) + int(extra.sum())
    if len(df) and df.shape[1]:
        na = df.isna()
        blank = na.all(axis=1).to_numpy().copy()
        # a line of only white space other than spaces (a tab: skipinitialspace strips
        # spaces alone) is blank too; it was an "empty id" error (the no-loss review)
        one = np.flatnonzero(na.sum(axis=1).to_numpy() == df.shape[1] - 1)
        if one.size:
            first = df.iloc[one, 0]
            blank[one] = first.map(lambda v: isinstance(v, str) and not v.strip()).to_numpy(
                dtype=bool)
            # a comment line between data lines ('#' first, no other field) is named as
            # one above the header is (it was an "empty id" error: the no-loss review)
            hashed = first.map(lambda v: isinstance(v, str) and v.lstrip().startswith("#"))
            if hashed.any():
                k = int(one[int(np.argmax(hashed.to_numpy(dtype=bool)))])
                raise InputError(f"the line looks like a comment ({str(df.iloc[k, 0])[:40]!r}):"
                                 " robustloc reads no comment lines; remove it",
                                 _display(path), int(df.index[k]))
        if blank.any():
            df = df.loc[~blank]
    df.attrs["path"] = _display(path)
    return df, next_line


#: What pandas' C parser raises on a malformed file (besides ParserError): an undecodable
#: byte, a NUL or other byte it cannot tokenize, a truncated compressed stream.
_CSV_ERRORS: tuple[type[BaseException], ...] = (
    pd.errors.ParserError, UnicodeDecodeError, EOFError, OSError, ValueError,
    zipfile.BadZipFile, lzma.LZMAError)


def _first_line(exc: BaseException) -> str:
    text = str(exc).strip()
    return text.splitlines()[0] if text else type(exc).__name__


def _read_raw(path: PathLike, str_columns: Sequence[str] = (),
              engine_hint: bool = True, what: str | None = None) -> pd.DataFrame:
    """Read a whole CSV or Parquet file; index = source line number (``engine_hint``,
    ``what``: :func:`_check_file`'s)."""
    p = _check_file(path, engine_hint, what)
    fmt = _format(p, path)
    if fmt == "parquet":
        try:
            import pyarrow.parquet as pq

            _check_header(pq.read_schema(p).names, path)
            df = pd.read_parquet(p)
        except InputError:
            raise
        except Exception as exc:  # noqa: BLE001 - any pyarrow failure is a bad file
            raise InputError(f"cannot read Parquet file: {_first_line(exc)}",
                             _display(path)) from None
        return _finish_frame(df.reset_index(drop=True), path, 2)[0]
    try:
        with _RaggedGuard(p, path, fmt):
            df = pd.read_csv(p, **_csv_kwargs(p, path, fmt, str_columns))
    except InputError:
        raise
    except pd.errors.EmptyDataError:
        raise _empty_error(p, path, fmt) from None
    except _CSV_ERRORS as exc:
        raise _parser_error(exc, p, path, fmt) from None
    return _finish_frame(df, path, 2, text=True, breaks=_record_breaks(p, fmt))[0]


def _iter_raw(
    path: PathLike, chunk_rows: int, str_columns: Sequence[str] = (),
    what: str | None = None,
) -> Iterator[pd.DataFrame]:
    """Stream a CSV or Parquet file in chunks of about ``chunk_rows`` rows (an in-memory
    frame of :func:`in_memory_source`: slices of it; ``what``: :func:`_check_file`'s)."""
    if chunk_rows < 1:
        raise ValueError(f"chunk_rows must be >= 1, got {chunk_rows}")
    if isinstance(path, pd.DataFrame):
        if len(path) == 0:
            raise InputError("measurements table has no rows", _display(path))
        for i in range(0, len(path), chunk_rows):
            yield path.iloc[i: i + chunk_rows]
        return
    p = _check_file(path, what=what)
    fmt = _format(p, path)
    if fmt == "parquet":
        import pyarrow.parquet as pq

        try:
            # pre_buffer (pyarrow's default) keeps the pre-read column chunks of every row
            # group iterated so far: the reader's memory grew with the file, ~8 MiB per
            # million rows (a 100 M-row partition pushed a 2 GiB Dask worker over its
            # limit); without it memory stays at one batch (measured flat over 60 M rows)
            pf = pq.ParquetFile(p, pre_buffer=False)
            _check_header(pf.schema_arrow.names, path)
            line = 2
            for batch in pf.iter_batches(batch_size=chunk_rows):
                df, line = _finish_frame(batch.to_pandas(), path, line)
                yield df
        except InputError:
            raise
        except Exception as exc:  # noqa: BLE001
            raise InputError(f"cannot read Parquet file: {_first_line(exc)}",
                             _display(path)) from None
        return
    try:
        line = 2
        record = 0
        with _RaggedGuard(p, path, fmt) as guard:
            reader = pd.read_csv(p, chunksize=chunk_rows,
                                 **_csv_kwargs(p, path, fmt, str_columns))
            breaks = _record_breaks(p, fmt)
            with reader:
                for df in reader:
                    guard.check()
                    n = len(df)
                    df, line = _finish_frame(df, path, line, text=True, breaks=breaks,
                                             first_record=record)
                    record += n
                    yield df
    except InputError:
        raise
    except pd.errors.EmptyDataError:
        raise _empty_error(p, path, fmt) from None
    except _CSV_ERRORS as exc:
        raise _parser_error(exc, p, path, fmt) from None


# --------------------------------------------------------------------------------------
# column validation
# --------------------------------------------------------------------------------------


def _path_of(df: pd.DataFrame, path: PathLike | None) -> str | None:
    if path is not None:
        return str(path)
    return df.attrs.get("path")


def _line_of(df: pd.DataFrame, pos: int) -> int | None:
    idx = df.index
    if idx.name == "line":
        return int(idx[pos])
    return None


def anchor_sigma(anchors: pd.DataFrame) -> NDArray[np.float64] | None:
    """The anchors' ``sigma`` column as the solvers' per-anchor a-priori sigma (m or dB).

    None when there is no such column or every cell is empty (not given).  A column given
    for some anchors and empty for others is refused naming the first anchor without one
    and its line: the solvers need one sigma per anchor, and guessing the missing ones
    would weight that anchor by a number nobody chose.  A value outside
    :data:`robustloc.options.SIGMA_RANGE` is refused the same way (the readers refuse it already; a
    hand-made frame may not have passed them).
    """
    if "sigma" not in anchors.columns:
        return None
    sg = to_number(anchors["sigma"]).to_numpy(dtype=float)
    if np.all(np.isnan(sg)):
        return None
    lo, hi = SIGMA_RANGE
    bad = ~((sg >= lo) & (sg <= hi))
    if bad.any():
        i = int(np.argmax(bad))
        name = anchors["anchor"].iloc[i] if "anchor" in anchors.columns else i
        what = ("has no sigma while other anchors have one: give every anchor a sigma "
                "(robustloc calibrate writes them) or none" if np.isnan(sg[i])
                else f"sigma must lie in [{lo:g}, {hi:g}], got {sg[i]:g}")
        raise InputError(f"anchor {str(name)!r} {what}", _path_of(anchors, None),
                         _line_of(anchors, i))
    return sg


def require_columns(
    df: pd.DataFrame, columns: Sequence[str], what: str, path: PathLike | None = None
) -> None:
    """Raise :class:`InputError` (line 1, the header) if a column is missing."""
    missing = [c for c in columns if c not in df.columns]
    if missing:
        have = ", ".join(map(str, df.columns)) or "none"
        # a column there in other case or with spaces ("Time", " x"): say which to rename
        near = {str(c).strip().lower(): str(c) for c in df.columns}
        wanted = [w for c in missing for w in c.split(" or ")]
        hints = [f"{near[w]!r} -> {w!r}" for w in wanted if w in near and near[w] != w]
        hint = (f"; column names are lower case without spaces: rename {', '.join(hints)}"
                if hints else "")
        # one column whose name holds the others: another separator (the no-loss review)
        if len(df.columns) == 1:
            for sep, name in ((";", "semicolons"), ("\t", "tabs"), ("|", "bars")):
                if sep in str(df.columns[0]):
                    hint += (f"; the header is one column: its fields are separated by "
                             f"{name}, and robustloc reads commas (CSV)")
                    break
        # a measurements log given where a survey goes (`calibrate LOG`): say what reads
        # a log (the new-user review)
        if what == "survey" and "time" in df.columns and "distance" in missing:
            hint += ("; this looks like a measurements log: calibrate it with --self "
                     "(no truth) or --measurements LOG --truth TRUTH")
        raise InputError(
            f"{what} file is missing column(s) {', '.join(missing)} (has: {have}){hint}",
            _path_of(df, path),
            1,
        )


def _numeric(
    df: pd.DataFrame,
    col: str,
    path: PathLike | None = None,
    *,
    allow_nan: bool = False,
    allow_inf: bool = False,
) -> None:
    """Convert ``df[col]`` to float in place; error at the first bad line."""
    s = df[col]
    if isinstance(s.dtype, pd.PeriodDtype):  # its start (its ordinal counted periods)
        s = s.dt.to_timestamp()
    if pd.api.types.is_datetime64_any_dtype(s) or pd.api.types.is_timedelta64_dtype(s):
        s = pd.Series(_seconds(s), index=s.index, name=col)
    if pd.api.types.is_bool_dtype(s):
        raise InputError(f"column '{col}' holds booleans, expected numbers", _path_of(df, path), 1)
    if pd.api.types.is_complex_dtype(s):  # (to float: the imaginary part dropped, a
        # ComplexWarning from pandas' insides the only sign; the review of 2026-12-06)
        raise InputError(f"column '{col}' holds complex numbers, expected real numbers",
                         _path_of(df, path), 1)
    if pd.api.types.is_numeric_dtype(s):
        v = s.to_numpy(dtype=float, na_value=np.nan)
    else:
        num = to_number(s)
        if pd.api.types.is_complex_dtype(num):
            raise InputError(f"column '{col}' holds complex numbers, expected real numbers",
                             _path_of(df, path), 1)
        v = num.to_numpy(dtype=float, na_value=np.nan)
        bad = np.isnan(v) & s.notna().to_numpy()
        if bad.any():
            i = int(np.argmax(bad))
            raise InputError(
                f"column '{col}': {str(s.iloc[i])!r} is not a number",
                _path_of(df, path),
                _line_of(df, i),
            )
    if not allow_nan:
        bad = np.isnan(v)
        if bad.any():
            i = int(np.argmax(bad))
            raise InputError(
                f"column '{col}': missing or NaN value", _path_of(df, path), _line_of(df, i)
            )
    if not allow_inf:
        bad = np.isinf(v)
        if bad.any():
            i = int(np.argmax(bad))
            raise InputError(
                f"column '{col}': infinite value {v[i]}", _path_of(df, path), _line_of(df, i)
            )
    df[col] = v


def _seconds(s: pd.Series) -> NDArray[np.float64]:
    """A timestamp column as float seconds since the Unix epoch (UTC), a duration column as
    float seconds; NaT becomes NaN.  Whatever the stored unit (s, ms, us, ns)."""
    if pd.api.types.is_timedelta64_dtype(s):
        return s.dt.total_seconds().to_numpy(dtype=float, na_value=np.nan)
    if getattr(s.dt, "tz", None) is not None:
        s = s.dt.tz_convert("UTC").dt.tz_localize(None)
    epoch = pd.Timestamp("1970-01-01")
    return (s - epoch).dt.total_seconds().to_numpy(dtype=float, na_value=np.nan)


def _ids(df: pd.DataFrame, col: str, path: PathLike | None = None) -> None:
    """Convert an id column to stripped strings; empty ids are an error.

    Floating-point ids (a DataFrame or Parquet column of numbers) are written value by
    value: a whole number without its ``.0`` (``1.0`` -> ``"1"``), any other as Python
    prints it (``1.5`` -> ``"1.5"``).  The id of a value never depends on the other values
    of its chunk (a whole-column rule named 1.0 ``"1"`` in one chunk and ``"1.0"`` in the
    next, so one tag became two and an epoch across the chunks two epochs).  Text ids (a
    CSV column) are kept as written."""
    s = df[col]
    if isinstance(s.dtype, pd.CategoricalDtype) and _holds_floats(s.cat.categories):
        s = s.astype(object)  # (a categorical of 1.0 named its tag "1.0")
    if pd.api.types.is_float_dtype(s):
        s = _float_ids(s)
    elif s.dtype == object and _holds_floats(s):
        # floats in an object column (after a concat, say): each by the same rule as a
        # float column's (it was "1.0" there and "1" in a float column)
        s = s.map(_float_id, na_action="ignore")
    missing = s.isna().to_numpy()
    out = s if isinstance(s.dtype, pd.StringDtype) else s.astype(str)
    out = out.str.strip()
    empty = missing | (out == "").to_numpy(dtype=bool, na_value=True)
    if empty.any():
        i = int(np.argmax(empty))
        raise InputError(f"column '{col}': empty id", _path_of(df, path), _line_of(df, i))
    df[col] = out


def _holds_floats(values: Any) -> bool:
    """Whether an object (or category) column holds floating-point values (one C pass:
    a column of text answers "string")."""
    if getattr(values, "dtype", None) is not None and values.dtype.kind == "f":
        return True
    # ("mixed-integer": ints beside text, which may hide a float too: [1.0, 7, "x"] kept
    # "1.0" where [1.0, "x"] gave "1", the API review)
    return pd.api.types.infer_dtype(values, skipna=True) in (
        "floating", "mixed-integer-float", "mixed", "mixed-integer")


def _float_id(v: object) -> object:
    """One value of an id column: a float by :func:`_float_ids`' rule, others as they are."""
    if isinstance(v, float | np.floating) and np.isfinite(v):
        f = float(v)
        return str(int(f)) if f == round(f) and abs(f) < 2.0**63 else str(f)
    return v


def _float_ids(s: pd.Series) -> pd.Series:
    """Float ids as text, each by its own value (:func:`_ids`); NaN stays missing."""
    v = s.to_numpy(dtype=float, na_value=np.nan)
    whole = np.isfinite(v) & (v == np.round(v)) & (np.abs(v) < 2.0**63)
    text = s.astype(str).to_numpy(dtype=object)
    text[whole] = v[whole].astype(np.int64).astype(str)
    return pd.Series(np.where(np.isnan(v), None, text), index=s.index, dtype=object)


def _require_rows(df: pd.DataFrame, what: str, path: PathLike | None = None) -> None:
    if len(df) == 0:
        raise InputError(f"{what} file has a header but no data rows", _path_of(df, path), 2)


# --------------------------------------------------------------------------------------
# anchors, survey, truth, positions
# --------------------------------------------------------------------------------------


def validate_anchors(df: pd.DataFrame, path: PathLike | None = None) -> pd.DataFrame:
    """Validate an anchors frame in place-like fashion and return it (see :func:`read_anchors`)."""
    df = df.copy()
    require_columns(df, ("anchor", "x", "y"), "anchors", path)
    _require_rows(df, "anchors", path)
    _ids(df, "anchor", path)
    for c in ("x", "y", "z"):
        if c in df.columns:
            _numeric(df, c, path)
    # (sigma too: text there was read as "no sigma", the anchors silently unweighted)
    for c in (*ANCHOR_PARAM_COLUMNS, "sigma"):
        if c in df.columns:
            _numeric(df, c, path, allow_nan=True)
    # parameters that only make sense positive: a path-loss exponent, a range scale, a
    # noise sigma (an empty cell is "not given" and stays NaN)
    for c, what in (("n", "path-loss exponent n"), ("gamma", "path-loss exponent gamma"),
                    ("scale", "range scale"), ("sigma", "sigma")):
        if c in df.columns:
            v = to_number(df[c]).to_numpy(dtype=float)
            bad = ~np.isnan(v) & ~(v > 0)
            if bad.any():
                i = int(np.argmax(bad))
                raise InputError(f"{what} must be positive, got {v[i]:g} for anchor "
                                 f"{df['anchor'].iloc[i]!r}", _path_of(df, path),
                                 _line_of(df, i))
    # path-loss parameters far outside anything physical (a typo, a unit slip) overflowed
    # the models silently and left every epoch without a fix: refused with their line
    from robustloc.io.limits import PATH_LOSS_EXPONENT_LIMITS, RANGE_SCALE_LIMITS, limits_for

    # (and the range calibration and sigma: a bias of 1e300 m with a scale of 1e-300
    # overflowed into every range and made every epoch invalid_measurement without naming
    # the anchors file; a sigma of 1e-300 made every fix ill_conditioned -- the input
    # review.  A bias as long as the longest plausible range, a scale of 1e-3 to 1e3 and
    # sigma as --sigma, SIGMA_RANGE)
    rssi, rng = limits_for("rssi"), limits_for("range")
    for c, what, lo, hi in (("A", "RSSI at 1 m A", rssi.low, rssi.high),
                            ("p0", "RSSI at d0 p0", rssi.low, rssi.high),
                            ("n", "path-loss exponent n", *PATH_LOSS_EXPONENT_LIMITS),
                            ("gamma", "path-loss exponent gamma", *PATH_LOSS_EXPONENT_LIMITS),
                            ("bias", "range bias", -rng.high, rng.high),
                            ("scale", "range scale", *RANGE_SCALE_LIMITS),
                            ("sigma", "sigma", *SIGMA_RANGE)):
        if c in df.columns:
            v = to_number(df[c]).to_numpy(dtype=float)
            bad = ~np.isnan(v) & ~((v >= lo) & (v <= hi))
            if bad.any():
                i = int(np.argmax(bad))
                raise InputError(f"{what} must lie in [{lo:g}, {hi:g}], got {v[i]:g} for "
                                 f"anchor {df['anchor'].iloc[i]!r}", _path_of(df, path),
                                 _line_of(df, i))
    dup = df["anchor"].duplicated().to_numpy()
    if dup.any():
        i = int(np.argmax(dup))
        raise InputError(
            f"duplicate anchor id {df['anchor'].iloc[i]!r}", _path_of(df, path), _line_of(df, i)
        )
    return df


def read_anchors(path: PathLike) -> pd.DataFrame:
    """Read an anchors file: ``anchor, x, y[, z]`` plus optional parameter columns.

    Parameters
    ----------
    path : str or PathLike
        CSV or Parquet file.

    Returns
    -------
    DataFrame
        ``anchor`` (str), ``x, y[, z]`` (float, metres, finite), and when present the
        path-loss columns ``A, n`` (log-distance, seed 000 eq. (1)), ``p0, gamma, faf, d0``
        (attenuation factor, seed 002 eq. (5)), the range calibration ``bias, scale``
        and the a-priori ``sigma`` (float; an empty value is NaN, meaning "not set for
        this anchor"; text is an error).  Extra columns are kept.  Index: source line.

    Raises
    ------
    InputError
        Missing column, empty file, non-numeric or non-finite coordinate, duplicate or
        empty anchor id -- with file and line.
    """
    return validate_anchors(_read_raw(path, ("anchor",), what="anchors"), _display(path))


def read_survey(
    path: PathLike, anchors: pd.DataFrame | Sequence[str] | None = None
) -> pd.DataFrame:
    """Read a calibration survey: ``anchor, distance`` and one of ``rssi`` or ``range``.

    ``distance`` (m) is the true anchor-receiver distance; ``rssi`` (dBm) or ``range`` (m)
    is what was measured there.  For an RSSI survey ``distance`` must be positive (the
    path-loss models take its logarithm); for a range survey it must be non-negative.
    Returns a frame with ``anchor`` (str), ``distance`` and the value column (float),
    index = source line; ``frame.attrs["value"]`` is ``"rssi"`` or ``"range"``.  With
    ``anchors`` given, an anchor id not among them is an error naming its line.
    """
    df = _read_raw(path, ("anchor",), what="survey")
    return validate_survey(df, _display(path), anchors)


def _check_known(
    df: pd.DataFrame, anchors: pd.DataFrame | Sequence[str], path: PathLike | None
) -> None:
    ok = df["anchor"].isin(_anchor_ids(anchors)).to_numpy()
    if not ok.all():
        i = int(np.argmax(~ok))
        raise InputError(
            f"unknown anchor id {df['anchor'].iloc[i]!r} (not in the anchors file)",
            _path_of(df, path),
            _line_of(df, i),
        )


def validate_survey(
    df: pd.DataFrame,
    path: PathLike | None = None,
    anchors: pd.DataFrame | Sequence[str] | None = None,
) -> pd.DataFrame:
    """Validate a survey frame (see :func:`read_survey`)."""
    df = df.copy()
    value = _value_column(df, "survey", path)
    require_columns(df, ("anchor", "distance"), "survey", path)
    _require_rows(df, "survey", path)
    _ids(df, "anchor", path)
    _numeric(df, "distance", path)
    _numeric(df, value, path)
    d = df["distance"].to_numpy()
    bad = (d <= 0) if value == "rssi" else (d < 0)
    if bad.any():
        i = int(np.argmax(bad))
        need = "positive" if value == "rssi" else "non-negative"
        raise InputError(
            f"column 'distance': {d[i]} must be {need}", _path_of(df, path), _line_of(df, i)
        )
    # a survey value outside the physical limits (robustloc.io.limits) is a typo or a
    # unit mix-up, not a measurement: one such row moved a fitted A by 14 dB (locate sets
    # such rows aside per epoch; a fit has no row to give them, so it refuses them)
    from robustloc.io.limits import limits_for

    for col, lim in ((value, limits_for(value)), ("distance", limits_for("range"))):
        out = ~lim.check(df[col].to_numpy(dtype=float))
        if out.any():
            i = int(np.argmax(out))
            # :g where it is exact, else 15 significant digits (100000.4 read as 100000,
            # inside the limit it broke: the calibration review)
            v = float(df[col].iloc[i])
            shown = f"{v:g}" if float(f"{v:g}") == v else f"{v:.15g}"
            raise InputError(f"column '{col}': {shown} is implausible "
                             f"({lim.describe().replace(lim.name, col, 1)})",
                             _path_of(df, path), _line_of(df, i))
    if anchors is not None:
        _check_known(df, anchors, path)
    df.attrs["value"] = value
    return df


def _value_column(df: pd.DataFrame, what: str, path: PathLike | None,
                  value: str | None = None) -> str:
    if value is not None:  # the reader's caller names the column it uses (fuse: range)
        other = [c for c in VALUE_COLUMNS if c != value and c in df.columns]
        if value not in df.columns and other:
            raise InputError(f"{what} file has no '{value}' column (it has '{other[0]}'; "
                             f"this command takes {value}s)", _path_of(df, path), 1)
        require_columns(df, (value,), what, path)
        return value
    present = [c for c in VALUE_COLUMNS if c in df.columns]
    if len(present) == 0:
        require_columns(df, ("rssi or range",), what, path)
    if len(present) == 2:
        raise InputError(
            f"{what} file has both 'rssi' and 'range' columns; keep exactly one",
            _path_of(df, path),
            1,
        )
    return present[0]


def read_truth(path: PathLike) -> pd.DataFrame:
    """Read a truth file: ``time, tag, x, y[, z]`` (all finite; each ``(time, tag)`` once,
    see :func:`refuse_duplicate_truth`).  Index: source line."""
    df = _read_raw(path, ("tag",), what="truth")
    return validate_truth(df, _display(path))


def validate_truth(df: pd.DataFrame, path: PathLike | None = None) -> pd.DataFrame:
    """Validate a truth frame (see :func:`read_truth`)."""
    df = df.copy()
    require_columns(df, ("time", "tag", "x", "y"), "truth", path)
    _require_rows(df, "truth", path)
    _ids(df, "tag", path)
    for c in ("time", "x", "y", "z"):
        if c in df.columns:
            _numeric(df, c, path)
    refuse_duplicate_truth(df, path)
    return df


def refuse_duplicate_truth(truth: pd.DataFrame, path: PathLike | None = None) -> None:
    """Refuse two truth rows for one ``(time, tag)``.

    The consumers would place the epoch at either position (whichever they met first):
    ``evaluate``, ``calibrate`` and ``stats`` refuse such truth alike.

    Parameters
    ----------
    truth : DataFrame
        Truth frame with ``time`` and ``tag`` columns.
    path : str or PathLike, optional
        The file named in the error; default ``truth.attrs["path"]``.

    Raises
    ------
    InputError
        Naming the second row's line: ``duplicate truth for time T and tag 'X'``.
    """
    key = pd.DataFrame({"time": truth["time"].to_numpy(),
                        "tag": truth["tag"].astype(str).to_numpy()})
    dup = key.duplicated().to_numpy()
    if dup.any():
        i = int(np.argmax(dup))
        raise InputError(
            f"duplicate truth for time {key['time'].iloc[i]} and tag {key['tag'].iloc[i]!r}",
            _path_of(truth, path), _line_of(truth, i))


def read_positions(path: PathLike) -> pd.DataFrame:
    """Read a positions file (``time, tag, x, y[, z], method, status, ...``).

    ``x, y, z`` and ``sigma0`` may be empty/NaN (a failed epoch: its ``status`` says why);
    ``method`` defaults to ``"unknown"`` and ``status`` to ``"ok"`` when the columns are
    absent (a positions file from another tool); an empty ``method`` or ``status`` cell
    is an :class:`InputError` naming its line.  ``n_used`` and ``excluded`` are optional.
    """
    df = _read_raw(path, ("tag", "method", "status", "excluded"), what="positions")
    return validate_positions(df, _display(path))


def validate_positions(df: pd.DataFrame, path: PathLike | None = None) -> pd.DataFrame:
    """Validate a positions frame (see :func:`read_positions`)."""
    df = df.copy()
    require_columns(df, ("time", "tag", "x", "y"), "positions", path)
    _require_rows(df, "positions", path)
    _ids(df, "tag", path)
    _numeric(df, "time", path)
    for c in ("x", "y", "z", "sigma0"):
        if c in df.columns:
            _numeric(df, c, path, allow_nan=True, allow_inf=False)
    if "n_used" in df.columns:
        _numeric(df, "n_used", path, allow_nan=True)
    for c in ("hpl", "vpl"):  # protection levels: metres, >= 0; inf = unbounded, NaN = none
        if c in df.columns:
            _numeric(df, c, path, allow_nan=True, allow_inf=True)
            neg = (df[c].to_numpy(dtype=float) < 0)
            if neg.any():
                i = int(np.argmax(neg))
                raise InputError(f"column '{c}': negative protection level {df[c].iloc[i]}",
                                 _path_of(df, path), _line_of(df, i))
    for c, default in (("method", "unknown"), ("status", "ok")):
        if c not in df.columns:
            df[c] = default
        elif c == "method":
            # an empty cell is a mistake, as an empty tag (it was scored as "unknown",
            # beside the file's named methods)
            df[c] = df[c].fillna("").astype(str).str.strip().astype(object)
            empty = (df[c] == "").to_numpy()
            if empty.any():
                i = int(np.argmax(empty))
                raise InputError("column 'method': empty value (name the method, or drop "
                                 "the column for one unnamed method)", _path_of(df, path),
                                 _line_of(df, i))
        else:  # a status decides whether a fix is scored: an unknown one is refused, never
            # silently counted as failed (or an empty one as usable)
            from robustloc import status as st

            df[c] = df[c].fillna("").astype(str).str.strip().astype(object)
            bad = ~st.among(df[c].to_numpy(object), st.ALL)
            if bad.any():
                i = int(np.argmax(bad))
                v = df[c].iloc[i]
                raise InputError(
                    ("empty status" if v == "" else f"unknown status {v[:40]!r}")
                    + f" (one of: {', '.join(st.ALL)})", _path_of(df, path), _line_of(df, i))
    if "excluded" in df.columns:
        df["excluded"] = df["excluded"].fillna("").astype(str).astype(object)
    return df


# --------------------------------------------------------------------------------------
# measurements
# --------------------------------------------------------------------------------------


def validate_measurements(
    df: pd.DataFrame,
    path: PathLike | None = None,
    anchors: pd.DataFrame | Sequence[str] | None = None,
    value: str | None = None,
) -> pd.DataFrame:
    """Validate a measurements frame (see :func:`read_measurements`).

    A finite value or time outside the physical limits of :mod:`robustloc.io.limits` (a
    range of 1e308 m, an RSSI of -500 dBm) is data, not a file error: the row is kept
    here; :func:`to_epochs` leaves it out of the fix and counts it (``Epochs.n_invalid``).
    """
    df = df.copy()
    value = _value_column(df, "measurements", path, value)
    require_columns(df, ("time", "tag", "anchor"), "measurements", path)
    _ids(df, "tag", path)
    _ids(df, "anchor", path)
    _numeric(df, "time", path)
    _numeric(df, value, path)
    if anchors is not None:
        _check_known(df, anchors, path)
    df.attrs["value"] = value
    return df


def _anchor_ids(anchors: pd.DataFrame | Sequence[str]) -> list[str]:
    if isinstance(anchors, pd.DataFrame):
        return [str(a) for a in anchors["anchor"]]
    return [str(a) for a in anchors]


def read_measurements(
    path: PathLike, anchors: pd.DataFrame | Sequence[str] | None = None,
    value: str | None = None, *, engine_hint: bool = True,
) -> pd.DataFrame:
    """Read a whole measurements file: ``time, tag, anchor`` and one of ``rssi``/``range``.

    Parameters
    ----------
    path : str or PathLike
        CSV or Parquet file, or ``-`` for standard input.  Rows may come in any order.
    anchors : DataFrame or sequence of str, optional
        The anchors (frame from :func:`read_anchors`, or ids).  When given, an anchor id
        not among them is an error naming its line.

    Returns
    -------
    DataFrame
        ``time`` (float s; a Parquet timestamp column becomes seconds since the Unix
        epoch), ``tag`` and ``anchor`` (str), ``rssi`` (dBm) or ``range`` (m) (float),
        extra columns kept;
        index = source line; ``frame.attrs["value"]`` names the value column.  A NaN/inf
        value, time or an empty id is an error naming its line (never a silent drop).
        Negative ranges are accepted.
    value : ``"rssi"`` or ``"range"``, optional
        The value column the caller uses: required, and the other one, if present, is
        kept as an extra column (unchecked).  ``None`` (default): the file must hold
        exactly one of them (which one is meant cannot be told: ``locate``).  ``fuse``
        takes ranges, and the DWM1001 loader writes both columns (the fuse review).
    engine_hint : bool, default True
        A directory's error says a partitioned dataset is read with ``--engine dask``;
        False (a command without ``--engine``): that the command reads one file.
    """
    if isinstance(path, pd.DataFrame):  # an in_memory_source
        _require_rows(path, "measurements", _display(path))
        return validate_measurements(path, _display(path), anchors, value)
    df = _read_raw(path, ("tag", "anchor"), engine_hint, what="measurements")
    _require_rows(df, "measurements", _display(path))
    return validate_measurements(df, _display(path), anchors, value)


class UnsortedInput(InputError):
    """Rows not in streaming order (see :func:`iter_measurements`), found after chunks were
    already yielded; the consumer restarts with ``order="sort"`` (or ``"check"``)."""


def _mem_available_bytes() -> int:
    try:
        with open("/proc/meminfo") as fh:
            for line in fh:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    return 4 << 30


def default_memory_budget() -> int:
    """Memory the in-memory sort may use: half of the available memory (``MemAvailable``
    of /proc/meminfo; 2 GiB when unknown)."""
    return _mem_available_bytes() // 2


#: Bytes of pandas memory per byte of CSV when a measurements file is read whole (object
#: strings for tag and anchor, float columns, the sort's copy), measured on generated
#: files of 10 ranges per epoch: about 6; 8 leaves a margin.
_MEM_PER_CSV_BYTE = 8.0
#: The same per uncompressed Parquet byte.
_MEM_PER_PARQUET_BYTE = 4.0


def _in_memory_estimate(path: PathLike | pd.DataFrame) -> float:
    if isinstance(path, pd.DataFrame):
        return 0.0  # already in memory: sorting it there costs one copy
    p = _check_file(path, what="measurements")
    fmt = _format(p, path)
    if fmt == "parquet":
        try:
            import pyarrow.parquet as pq

            md = pq.ParquetFile(p).metadata
            raw = sum(md.row_group(i).total_byte_size for i in range(md.num_row_groups))
        except Exception:  # noqa: BLE001 - unreadable: the reader will say why
            raw = p.stat().st_size
        return raw * _MEM_PER_PARQUET_BYTE
    size = p.stat().st_size
    if _compression(fmt) is not None:
        size *= 5  # typical compression ratio of numeric CSV
    return size * _MEM_PER_CSV_BYTE


def _epoch_starts(t: NDArray[np.float64], h: NDArray[np.uint64]) -> NDArray[np.bool_]:
    """True where a row starts a new (time, tag) run (the first row always does)."""
    start = np.ones(len(t), dtype=bool)
    start[1:] = (t[1:] != t[:-1]) | (h[1:] != h[:-1])
    return start


def _tag_hash(tags: pd.Series) -> NDArray[np.uint64]:
    """64-bit hash of each tag.  Factorized first (Arrow-native for pandas' string dtype),
    so that Python string objects are made only for the distinct tags, not for every row
    (with one tag per epoch, per-row objects cost more memory than the chunk itself)."""
    codes, uniques = pd.factorize(tags)
    hu = pd.util.hash_array(np.asarray(uniques, dtype=object), categorize=False)
    return hu[codes]


def _finish_chunk(df: pd.DataFrame, path: str, value: str) -> pd.DataFrame:
    df.attrs["path"] = path
    df.attrs["value"] = value
    return df


def _cut_sorted(frames: Iterator[pd.DataFrame], path: str) -> Iterator[pd.DataFrame]:
    """Chunks of rows already in epoch order, cut so that no epoch is split: the rows of
    the last epoch of each chunk are held back for the next (memory: one chunk plus one
    epoch)."""
    carry: pd.DataFrame | None = None
    value = None
    for chunk in frames:
        if len(chunk) == 0:
            continue
        value = chunk.attrs.get("value", value)
        if carry is not None:
            chunk = pd.concat([carry, chunk])
        t = chunk["time"].to_numpy()
        h = _tag_hash(chunk["tag"])
        starts = np.flatnonzero(_epoch_starts(t, h))
        last = int(starts[-1])
        if last == 0:
            carry = chunk
            continue
        carry = chunk.iloc[last:]
        yield _finish_chunk(chunk.iloc[:last], path, value)
    if carry is not None and len(carry):
        yield _finish_chunk(carry, path, value)


def _in_sorted_parts(h: NDArray[np.uint64], parts: list[NDArray[np.uint64]]) -> NDArray:
    """Mask of ``h`` found in any of the sorted arrays ``parts`` (binary search)."""
    hit = np.zeros(len(h), dtype=bool)
    for arr in parts:
        if len(arr):
            i = np.minimum(np.searchsorted(arr, h), len(arr) - 1)
            hit |= arr[i] == h
    return hit


#: A time group (rows of one time value) is held whole up to this many rows (or
#: ``chunk_rows`` if larger); beyond, its epochs must be contiguous to stream.
_MIN_GROUP_ROWS = 100_000


def _iter_streamed(
    path: PathLike, chunk_rows: int, known: list[str] | None
) -> Iterator[pd.DataFrame]:
    """The streaming path: rows in time order, checked as they come.

    ``time`` must be non-decreasing.  The rows of the last time value of each chunk are
    held back (tags of one time may mix in any order), unless that time group grows beyond
    ``max(chunk_rows, 100 000)`` rows: then its epochs must be contiguous (each tag's rows
    together), and all
    but the last are emitted, remembering the 64-bit hashes of their tags (8 bytes per
    epoch) to refuse a later row of an epoch already emitted.  So memory stays bounded by
    about two chunks whatever the grouping (10 M rows that all have ``time = 0``, each
    epoch its own tag, stream like time-sorted rows).  Any other order raises
    :class:`UnsortedInput` naming the first offending line.
    """
    name = _display(path)
    last_t = -np.inf
    carry: pd.DataFrame | None = None
    seen: list[NDArray[np.uint64]] = []  # sorted hashes of tags emitted at time last_t
    n_rows = 0
    value = None
    for raw in _iter_raw(path, chunk_rows, ("tag", "anchor"), "measurements"):
        if len(raw) == 0:
            continue
        chunk = validate_measurements(raw, name, known)
        value = chunk.attrs["value"]
        t = chunk["time"].to_numpy()
        tb = np.concatenate(([last_t], t))
        back = tb[1:] < tb[:-1]
        if back.any():
            i = int(np.argmax(back))
            raise UnsortedInput(
                f"time {t[i]} is earlier than the previous row's (rows not sorted by time)",
                name, _line_of(chunk, i))
        n_carry = 0 if carry is None else len(carry)
        frame = chunk if carry is None else pd.concat([carry, chunk])
        tt = frame["time"].to_numpy()
        t_end = tt[-1]
        first_tail = int(np.searchsorted(tt, t_end, side="left"))
        big = len(frame) - first_tail > max(chunk_rows, _MIN_GROUP_ROWS)
        # tag hashes, once per chunk, only where needed (a time group over several chunks)
        lo = min(first_tail, n_carry) if big else n_carry
        h_from = _tag_hash(frame["tag"].iloc[lo:]) if (big or seen) else None
        if seen:
            hc = h_from[n_carry - lo:]
            hit = (t == last_t) & _in_sorted_parts(hc, seen)
            if hit.any():
                i = int(np.argmax(hit))
                raise UnsortedInput(
                    f"time {t[i]} and tag {chunk['tag'].iloc[i]!r}: a row of an epoch whose "
                    "rows were interrupted by other epochs of the same time over more than "
                    "one chunk (rows not grouped by epoch)", name, _line_of(chunk, i))
        n_rows += len(chunk)
        if t_end != last_t:
            seen = []
        head, tail = frame.iloc[:first_tail], frame.iloc[first_tail:]
        if big:  # a big time group: emit its closed epochs
            h = h_from[first_tail - lo:]
            starts = np.flatnonzero(_epoch_starts(tail["time"].to_numpy(), h))
            run_h = h[starts]
            dup = pd.Series(run_h).duplicated().to_numpy()
            if dup.any():
                i = int(starts[int(np.argmax(dup))])
                raise UnsortedInput(
                    f"time {t_end} and tag {tail['tag'].iloc[i]!r}: {len(tail)} rows of one "
                    "time with the tags' rows mixed (rows not grouped by epoch)",
                    name, _line_of(tail, i))
            last = int(starts[-1])
            seen.append(np.unique(run_h[:-1]))  # no merged copy: 8 bytes per epoch
            out = frame.iloc[: first_tail + last]  # head and the closed epochs: one slice
            carry = tail.iloc[last:]
        else:
            out, carry = head, tail
        last_t = t_end
        if len(out):
            yield _finish_chunk(out, name, value)
    if n_rows == 0:
        raise InputError("measurements file has a header but no data rows", name, 2)
    if carry is not None and len(carry):
        yield _finish_chunk(carry, name, value)


def _sort_frame(df: pd.DataFrame) -> pd.DataFrame:
    """Rows in epoch order: by time, then tag, then source line (stable)."""
    codes, _ = pd.factorize(df["tag"], sort=True)
    line = (df.index.to_numpy(dtype=np.int64) if df.index.name == "line"
            else np.arange(len(df), dtype=np.int64))
    order = np.lexsort((line, codes, df["time"].to_numpy()))
    out = df.iloc[order]
    out.attrs = dict(df.attrs)
    return out


def _iter_sorted_in_memory(
    path: PathLike, chunk_rows: int, known: list[str] | None
) -> Iterator[pd.DataFrame]:
    df = _sort_frame(read_measurements(path, known))
    name = _display(path)

    def frames() -> Iterator[pd.DataFrame]:
        for i in range(0, len(df), chunk_rows):
            yield _finish_chunk(df.iloc[i : i + chunk_rows], name, df.attrs["value"])

    yield from _cut_sorted(frames(), name)


def _iter_sorted_out_of_core(
    path: PathLike, chunk_rows: int, known: list[str] | None
) -> Iterator[pd.DataFrame]:
    """Sort a file larger than memory: validate it in a streaming pass into a Parquet
    spool (time, tag, anchor, value, line), then let DuckDB sort the spool with
    its external (disk-spilling) sort and stream the sorted rows back in record batches.
    Extra columns are not carried on this path."""
    import tempfile

    import duckdb
    import pyarrow as pa
    import pyarrow.parquet as pq

    name = _display(path)
    value = None
    with tempfile.TemporaryDirectory(prefix="robustloc-sort-") as tmp:
        spool = Path(tmp) / "rows.parquet"
        writer = None
        n_rows = 0
        try:
            for raw in _iter_raw(path, chunk_rows, ("tag", "anchor"), "measurements"):
                if len(raw) == 0:
                    continue
                chunk = validate_measurements(raw, name, known)
                value = chunk.attrs["value"]
                part = pd.DataFrame({
                    "time": chunk["time"].to_numpy(dtype=float),
                    "tag": chunk["tag"].astype(str).to_numpy(dtype=object),
                    "anchor": chunk["anchor"].astype(str).to_numpy(dtype=object),
                    value: chunk[value].to_numpy(dtype=float),
                    "line": chunk.index.to_numpy(dtype=np.int64),
                })
                table = pa.Table.from_pandas(part, preserve_index=False)
                if writer is None:
                    writer = pq.ParquetWriter(spool, table.schema)
                writer.write_table(table.cast(writer.schema))
                n_rows += len(part)
        finally:
            if writer is not None:
                writer.close()
        if n_rows == 0:
            raise InputError("measurements file has a header but no data rows", name, 2)
        con = duckdb.connect()
        try:
            # DuckDB's own memory (the rest spills to `tmp`): 256 MB to 1 GB
            limit = min(max(default_memory_budget() // 4, 256 << 20), 1 << 30)
            con.execute(f"SET memory_limit='{limit // (1 << 20)}MB'")
            con.execute(f"SET temp_directory='{tmp}'")
            con.execute("SET threads=1")
            con.execute("SET enable_progress_bar=false")  # never into a data stream
            rel = con.sql(f"SELECT * FROM read_parquet('{spool}') ORDER BY time, tag, line")
            reader = rel.to_arrow_reader(batch_size=chunk_rows)

            def frames() -> Iterator[pd.DataFrame]:
                for batch in reader:
                    df = batch.to_pandas()
                    df.index = pd.Index(df.pop("line").to_numpy(dtype=np.int64), name="line")
                    yield _finish_chunk(df, name, value)

            yield from _cut_sorted(frames(), name)
        finally:
            con.close()


def iter_measurements(
    path: PathLike,
    chunk_rows: int = _DEFAULT_CHUNK_ROWS,
    anchors: pd.DataFrame | Sequence[str] | None = None,
    *,
    order: str = "auto",
    memory_budget_bytes: int | None = None,
) -> Iterator[pd.DataFrame]:
    """Stream a measurements file in validated chunks that never split an epoch.

    An epoch is one ``(time, tag)``.  Rows may come in any order (several tags' logs one
    after another, shuffled rows); every epoch arrives whole in exactly one chunk, and
    the epochs come in time order.

    * **Epoch-ordered input** (``time`` non-decreasing, the rows of each epoch
      contiguous, tags within one time in any order) is streamed: memory is bounded by
      ``chunk_rows`` plus one epoch, whatever the grouping (10 M rows that all have
      ``time = 0``, each epoch its own tag, stream like time-sorted rows).
    * **Any other order** is sorted by ``(time, tag, line)``: in memory when the estimate
      fits ``memory_budget_bytes``, else out of core (a validated Parquet spool sorted by
      DuckDB, which spills to disk; extra columns are dropped on that path).

    Parameters
    ----------
    path : str, PathLike or DataFrame
        CSV or Parquet file, ``-`` (standard input, spooled to a temporary file), or a
        frame of :func:`in_memory_source` (the Python API's input; read like a file).
    chunk_rows : int
        Rows read per chunk (default 500 000).
    anchors : DataFrame or sequence of str, optional
        As in :func:`read_measurements`.
    order : {"auto", "check", "sort"}
        ``auto`` streams and, if disorder appears before the first chunk was yielded,
        switches to sorting transparently; after that it raises :class:`UnsortedInput`
        (the consumer discards what it wrote and restarts with ``order="sort"``).
        ``check`` makes one validating pass first to decide (never raises
        :class:`UnsortedInput`; for consumers that cannot restart, e.g. writing to
        standard output).  ``sort`` always sorts.
    memory_budget_bytes : int, optional
        Largest estimated memory for the in-memory sort (default
        :func:`default_memory_budget`: half the available memory).

    Yields
    ------
    DataFrame
        Validated chunks, as returned by :func:`read_measurements`; ``attrs["resorted"]``
        is True on chunks of a log that had to be sorted.
    """
    if order not in ("auto", "check", "sort"):
        raise ValueError(f"order must be 'auto', 'check' or 'sort', got {order!r}")
    if chunk_rows < 1:
        raise ValueError(f"chunk_rows must be >= 1, got {chunk_rows}")
    known = None if anchors is None else _anchor_ids(anchors)
    budget = default_memory_budget() if memory_budget_bytes is None else memory_budget_bytes

    def resorted() -> Iterator[pd.DataFrame]:
        if _in_memory_estimate(path) <= budget:
            chunks = _iter_sorted_in_memory(path, chunk_rows, known)
        else:
            chunks = _iter_sorted_out_of_core(path, chunk_rows, known)
        for chunk in chunks:  # marked: the run summary says the rows were sorted
            chunk.attrs["resorted"] = True
            yield chunk

    if order == "sort":
        yield from resorted()
        return
    if order == "check":
        try:
            for _ in _iter_streamed(path, chunk_rows, known):
                pass
        except UnsortedInput:
            yield from resorted()
            return
        yield from _iter_streamed(path, chunk_rows, known)
        return
    stream = _iter_streamed(path, chunk_rows, known)
    try:
        first = next(stream)
    except StopIteration:
        return
    except UnsortedInput:
        yield from resorted()
        return
    yield first
    yield from stream


@dataclass(frozen=True)
class Epochs:
    """Measurements pivoted to one row per epoch ``(time, tag)``.

    Attributes
    ----------
    time : ndarray, shape (N,)
        Epoch time (s), sorted ascending (ties broken by tag).
    tag : ndarray of object, shape (N,)
        Receiver id of each epoch.
    values : ndarray, shape (N, m)
        ``rssi`` (dBm) or ``range`` (m) per anchor, columns in ``anchor_ids`` order; NaN
        where the anchor was not heard in that epoch.  Duplicates (an anchor reported more
        than once in one epoch) are averaged (arithmetic mean of the values as given, i.e.
        in dB for RSSI), and counted in ``n_duplicates``.
    anchor_ids : tuple of str
        Column order of ``values``.
    value : str
        ``"rssi"`` or ``"range"``.
    line : ndarray of int, shape (N,)
        Source line of each epoch's first row (0 when the frame had no line index).
    n_duplicates : int
        Rows merged into an earlier row of the same epoch and anchor.
    n_invalid : ndarray of int, shape (N,)
        Rows of each epoch whose value or time lay outside the physical limits
        (:mod:`robustloc.io.limits`): not in ``values`` (NaN, as if not heard), counted here.
        An epoch whose every row is invalid has ``n_invalid > 0`` and no finite value; its
        output row gets status ``invalid_measurement``.
    resorted : bool
        The block comes from a log whose rows were not in epoch order and were sorted
        (:func:`iter_epochs`); the run summaries say so.
    """

    time: NDArray[np.float64]
    tag: NDArray[np.object_]
    values: NDArray[np.float64]
    anchor_ids: tuple[str, ...]
    value: str
    line: NDArray[np.int64]
    n_duplicates: int = 0
    n_invalid: NDArray[np.int64] | None = None
    resorted: bool = False

    def __post_init__(self) -> None:
        n = int(np.asarray(self.values).shape[0])
        if self.n_invalid is None:
            object.__setattr__(self, "n_invalid", np.zeros(n, dtype=np.int64))
        elif np.shape(self.n_invalid) != (n,):
            raise ValueError(f"n_invalid has shape {np.shape(self.n_invalid)}, expected ({n},)")

    @property
    def all_invalid(self) -> NDArray[np.bool_]:
        """Epochs whose every row was invalid (status ``invalid_measurement``)."""
        return (self.n_invalid > 0) & ~np.isfinite(self.values).any(axis=1)

    @property
    def n_epochs(self) -> int:
        return int(self.values.shape[0])

    def __len__(self) -> int:
        return self.n_epochs

    def take(self, rows: slice | NDArray[np.int64]) -> Epochs:
        """The epochs ``rows`` (a slice or an index array), in that order; the other
        attributes (``anchor_ids``, ``n_duplicates``, ...) as they are."""
        from dataclasses import replace

        return replace(self, time=self.time[rows], tag=self.tag[rows],
                       values=self.values[rows], line=self.line[rows],
                       n_invalid=self.n_invalid[rows])

    @staticmethod
    def concat(blocks: list[Epochs]) -> Epochs:
        """Epoch blocks (of one log: the same anchors and value) as one, in the given
        order; ``n_duplicates`` summed, ``resorted`` if any block's is."""
        from dataclasses import replace

        if not blocks:
            raise ValueError("no epoch blocks")
        if len(blocks) == 1:
            return blocks[0]
        return replace(blocks[0], time=np.concatenate([b.time for b in blocks]),
                       tag=np.concatenate([np.asarray(b.tag, dtype=object) for b in blocks]),
                       values=np.concatenate([b.values for b in blocks]),
                       line=np.concatenate([b.line for b in blocks]),
                       n_duplicates=sum(b.n_duplicates for b in blocks),
                       n_invalid=np.concatenate([b.n_invalid for b in blocks]),
                       resorted=any(b.resorted for b in blocks))


def to_epochs(
    frame: pd.DataFrame, anchor_ids: Sequence[str], value: str | None = None
) -> Epochs:
    """Pivot a measurements frame to ``(N epochs, m anchors)``, vectorized.

    Parameters
    ----------
    frame : DataFrame
        From :func:`read_measurements` / :func:`iter_measurements` (or any frame with
        ``time, tag, anchor`` and the value column).
    anchor_ids : sequence of str
        Anchor order of the output columns (e.g. ``anchors["anchor"]``).  A row whose
        anchor is not among them is an :class:`InputError` naming its line.
    value : {"rssi", "range"}, optional
        Value column; default ``frame.attrs["value"]`` or the one present.

    Returns
    -------
    Epochs
        One row per distinct ``(time, tag)`` (times compared exactly), sorted by time then
        tag; NaN where an anchor was not heard; duplicates averaged.
    """
    if value is None:
        value = frame.attrs.get("value") or _value_column(frame, "measurements", None)
    if value not in VALUE_COLUMNS:
        raise ValueError(f"value must be 'rssi' or 'range', got {value!r}")
    require_columns(frame, ("time", "tag", "anchor", value), "measurements")
    ids = tuple(str(a) for a in anchor_ids)
    m = len(ids)
    if len(frame) == 0:
        return Epochs(
            np.empty(0), np.empty(0, dtype=object), np.empty((0, m)), ids, value,
            np.empty(0, dtype=np.int64), 0, np.empty(0, dtype=np.int64),
        )
    anchor_col = frame["anchor"]
    if not isinstance(anchor_col.dtype, pd.StringDtype):
        anchor_col = anchor_col.astype(str)
    col = pd.Index(ids).get_indexer(anchor_col)
    if (col < 0).any():
        i = int(np.argmax(col < 0))
        raise InputError(
            f"unknown anchor id {str(frame['anchor'].iloc[i])!r} (not in the anchors)",
            frame.attrs.get("path"),
            _line_of(frame, i),
        )
    t = frame["time"].to_numpy(dtype=float)
    tag_col = frame["tag"]
    if not isinstance(tag_col.dtype, pd.StringDtype):
        tag_col = tag_col.astype(str)
    tag_codes, tag_uniques = pd.factorize(tag_col, sort=True)
    v = frame[value].to_numpy(dtype=float)
    lines = frame.index.to_numpy(dtype=np.int64) if frame.index.name == "line" else None
    return pivot_epochs(t, tag_codes, np.asarray(tag_uniques, dtype=object), col, v, ids,
                        value, lines)


def pivot_epochs(
    time: NDArray[np.float64], tag_code: NDArray[np.integer],
    tag_names: NDArray[np.object_], anchor_col: NDArray[np.integer],
    values: NDArray[np.float64], anchor_ids: Sequence[str], value: str,
    lines: NDArray[np.int64] | None = None,
) -> Epochs:
    """The pivot of :func:`to_epochs` on rows already coded (its core, shared by the live
    service, whose rows arrive coded).

    Parameters
    ----------
    time, values : ndarray (n,)
        Row times (s) and values (dBm or m).
    tag_code : ndarray (n,) of int
        Index of each row's tag in ``tag_names``; epochs are sorted by time, then by tag
        code, so codes in the sort order of the names give :func:`to_epochs`' order.
    tag_names : ndarray of str objects
    anchor_col : ndarray (n,) of int
        Column of each row's anchor in ``anchor_ids`` (all valid).
    anchor_ids : sequence of str
    value : {"rssi", "range"}
    lines : ndarray (n,) of int, optional
        Source line of each row (the epochs' ``line`` is the first); zeros when None.
    """
    ids = tuple(str(a) for a in anchor_ids)
    m = len(ids)
    t = np.asarray(time, dtype=float)
    v = np.asarray(values, dtype=float)
    n_tags = max(len(tag_names), 1)
    time_codes, time_uniques = pd.factorize(t, sort=True)
    key = time_codes.astype(np.int64) * n_tags + np.asarray(tag_code, dtype=np.int64)
    ukey, epoch = np.unique(key, return_inverse=True)
    n = len(ukey)
    flat = epoch.astype(np.int64) * m + np.asarray(anchor_col, dtype=np.int64)
    ok = plausible(value, v) & plausible("time", t)  # robustloc.io.limits
    n_invalid = np.bincount(epoch[~ok], minlength=n).astype(np.int64)
    flat, v = flat[ok], v[ok]
    sums = np.bincount(flat, weights=v, minlength=n * m)
    counts = np.bincount(flat, minlength=n * m)
    with np.errstate(invalid="ignore", divide="ignore"):
        vals = np.where(counts > 0, sums / np.maximum(counts, 1), np.nan).reshape(n, m)
    n_dup = int(np.sum(np.maximum(counts - 1, 0)))
    times = np.asarray(time_uniques, dtype=float)[ukey // n_tags]
    tags = np.asarray(tag_names, dtype=object)[ukey % n_tags]
    if lines is not None:
        first = np.full(n, np.iinfo(np.int64).max, dtype=np.int64)
        np.minimum.at(first, epoch, np.asarray(lines, dtype=np.int64))
    else:
        first = np.zeros(n, dtype=np.int64)
    return Epochs(times, tags, vals, ids, value, first, n_dup, n_invalid)


def iter_epochs(
    path: PathLike,
    anchors: pd.DataFrame | Sequence[str],
    chunk_rows: int = _DEFAULT_CHUNK_ROWS,
    *,
    order: str = "auto",
    memory_budget_bytes: int | None = None,
) -> Iterator[Epochs]:
    """Stream a measurements file (rows in any order) as :class:`Epochs` blocks.

    Combines :func:`iter_measurements` (see it for ``order`` and the memory bound) and
    :func:`to_epochs`; every epoch is in exactly one block, blocks come in time order.
    """
    ids = _anchor_ids(anchors)
    for chunk in iter_measurements(path, chunk_rows=chunk_rows, anchors=ids, order=order,
                                   memory_budget_bytes=memory_budget_bytes):
        block = to_epochs(chunk, ids)
        yield replace(block, resorted=True) if chunk.attrs.get("resorted") else block


# --------------------------------------------------------------------------------------
# writing
# --------------------------------------------------------------------------------------


def _refuse_parquet_stdout(path: PathLike) -> None:
    from robustloc.io.atomic import is_stdio

    if is_stdio(path) and is_parquet(path):  # pragma: no cover - "-" is never .parquet
        raise InputError("Parquet cannot be written to standard output", path)


def _is_parquet_out(path: PathLike, parquet: bool | None) -> bool:
    return is_parquet(path) if parquet is None else parquet


#: What a table output's name may end in: CSV (also plain text or no extension, and
#: gzip-compressed with .gz) or Parquet.
TABLE_SUFFIXES = (".csv", ".txt", "") + _PARQUET_EXT
_COMPRESSION_SUFFIXES = (".gz",)  # (the others: robustloc.io.atomic refuses them)


def check_table_path(path: PathLike) -> None:
    """Refuse a table output whose extension names another format (``.json``, ``.xlsx``,
    ``.tsv``, ...): it was written as CSV without a word.  ``-`` is CSV on standard
    output.

    Raises
    ------
    InputError
        Naming the extension and the formats written.
    """
    if str(path) == "-":
        return
    if not str(path).strip():
        raise InputError("the output name is empty (give a file name, or - for standard "
                         "output)")
    name = Path(path).name.lower()
    stem, suffix = os.path.splitext(name)
    shown = suffix
    ok = suffix in TABLE_SUFFIXES
    if suffix in _COMPRESSION_SUFFIXES:  # gzip-compressed CSV (robustloc.io.atomic)
        inner = os.path.splitext(stem)[1]
        shown = inner + suffix
        ok = inner in (".csv", ".txt", "")
    elif suffix in (".bz2", ".xz", ".zip", ".zst"):
        # refused now, in robustloc.io.atomic's words (it names the compressions it
        # writes), not after the work that the output was for
        from robustloc.io.atomic import _gzip_wanted

        _gzip_wanted(Path(path))
        return
    if not ok:
        raise InputError(f"cannot write a table as {shown!r}: the output is CSV (.csv, "
                         ".txt or no extension, optionally .gz) or "
                         "Parquet (.parquet, .pq); - writes CSV to standard output",
                         str(path))


def write_table(
    frame: pd.DataFrame, path: PathLike, *, parquet: bool | None = None
) -> Path:
    """Write a frame as CSV or Parquet (by extension), atomically, creating parent folders.

    The data go to a temporary file in the target folder that is renamed onto ``path``
    only when complete (:func:`robustloc.io.atomic.atomic_output`): after an error, an
    interrupt or a full disk nothing is left at ``path`` (or its previous content stays).
    ``-`` writes CSV to standard output (``parquet=True`` with ``-`` is an error).  The
    index is not written (the ``line`` index of read frames is bookkeeping).  Floats are
    written with full precision (``repr``), so a CSV round trip is exact.

    Raises
    ------
    OutputError
        The output cannot be written (no space, read-only, a parent that is a file).
    """
    from robustloc.io.atomic import atomic_output, is_stdio

    if parquet is None:  # a name the user gave (a temporary target comes with `parquet`)
        check_table_path(path)
    pq_out = _is_parquet_out(path, parquet)
    if is_stdio(path) and pq_out:
        raise InputError("Parquet cannot be written to standard output; write a file, or "
                         "CSV to -", "-")
    out = frame.reset_index(drop=True)
    out.attrs = {}
    with atomic_output(path, binary=False) as (target, stream):
        if stream is not None:
            out.to_csv(stream, index=False)
        elif pq_out:
            out.to_parquet(target, index=False)
        else:
            out.to_csv(target, index=False)
    return Path(path)


def positions_frame(
    solution: object,
    time: NDArray[np.float64],
    tag: NDArray[np.object_] | Sequence[str],
    anchor_ids: Sequence[str],
    method: str | None = None,
    columns: Mapping[str, ArrayLike] | None = None,
) -> pd.DataFrame:
    """Build the contract positions frame from a :class:`~robustloc.estimators.Solution`.

    Columns ``time, tag, x, y[, z], method, status, n_used, sigma0, excluded`` (the
    ``excluded`` column is the ``;``-joined ids of the observations rejected in each
    epoch); ``z`` is written when the solution is 3-D.  ``hpl`` (and ``vpl`` in 3-D), the
    protection levels in metres, follow when the solution carries them; ``iterations`` is
    appended as an extra column, then the ``columns`` given, in their order (the frame is
    built once: adding columns afterwards copies it each time).
    """
    pos = np.asarray(solution.position, dtype=float)
    n, dim = pos.shape
    time = np.asarray(time, dtype=float)
    if time.shape != (n,):
        raise ValueError(f"time has shape {time.shape}, solution has {n} epochs")
    data: dict[str, object] = {
        "time": time,
        "tag": np.asarray(tag, dtype=object),
        "x": pos[:, 0],
        "y": pos[:, 1],
    }
    if dim >= 3:
        data["z"] = pos[:, 2]
    data["method"] = method if method is not None else getattr(solution, "method", "unknown")
    data["status"] = np.asarray(solution.status, dtype=object)
    data["n_used"] = np.asarray(solution.n_used, dtype=np.int64)
    data["sigma0"] = np.asarray(solution.sigma0, dtype=float)
    data["excluded"] = solution.excluded_ids(list(anchor_ids))
    extra = getattr(solution, "extra", {}) or {}
    if "hpl" in extra:  # protection levels (robustloc.integrity.fixes.protect), metres
        data["hpl"] = np.asarray(extra["hpl"], dtype=float)
        if dim >= 3:
            data["vpl"] = np.asarray(extra["vpl"], dtype=float)
    data["iterations"] = np.asarray(solution.iterations, dtype=np.int64)
    data.update(columns or {})
    return pd.DataFrame(data)


def write_positions(frame: pd.DataFrame, path: PathLike) -> Path:
    """Write a positions frame with the contract columns first, in contract order.

    Missing contract columns are an error (``ValueError``); extra columns follow.  A
    timestamp ``time`` column is written as seconds since the Unix epoch (a duration as
    seconds), as the readers read one.
    """
    cols = list(POSITION_COLUMNS)
    if "z" in frame.columns:
        cols.insert(4, "z")
    missing = [c for c in cols if c not in frame.columns]
    if missing:
        raise ValueError(f"positions frame is missing column(s): {', '.join(missing)}")
    extra = [c for c in frame.columns if c not in cols]
    out = frame[cols + extra]
    t = out["time"]
    if pd.api.types.is_datetime64_any_dtype(t) or pd.api.types.is_timedelta64_dtype(t):
        # seconds, as the readers turn a timestamp column (a datetime written as text was
        # a file read_positions refuses)
        out = out.assign(time=_seconds(t))
    return write_table(out, path)


class _InMemory:
    """The "open file" of a :class:`PositionsWriter` that keeps its chunks in memory."""


class PositionsWriter:
    """Write a positions file chunk by chunk (bounded memory for streamed logs), atomically.

    CSV chunks are appended under one header; Parquet chunks become row groups of one
    file.  Each chunk is ordered as :func:`write_positions` orders it; every chunk must
    have the same columns as the first.  The chunks go to a temporary file in the target
    folder, renamed onto ``path`` by :meth:`close` (see :func:`write_table`); leaving the
    ``with`` block by an exception (an input error, Ctrl-C, SIGTERM, a full disk) removes
    it, and the final path keeps its previous content or stays absent.  ``-`` writes CSV
    to standard output; ``None`` keeps the chunks in memory (the Python API), ordered the
    same way, for :meth:`frame`.  Use as a context manager::

        with PositionsWriter("positions.csv") as out:
            for epochs in iter_epochs(path, anchors):
                out.write(positions_frame(solver.solve(...), epochs.time, epochs.tag, ids))
    """

    def __init__(self, path: PathLike | None) -> None:
        if path is not None:
            check_table_path(path)
        self.path = None if path is None else Path(path) if str(path) != "-" else path
        self.n_rows = 0
        self._columns: list[str] | None = None
        self._pq_writer = None
        self._cm = None
        self._target: Path | None = None
        self._stream = None
        self._chunks: list[pd.DataFrame] = []

    def frame(self) -> pd.DataFrame:
        """In-memory mode: every chunk written, as one frame (index 0..n-1)."""
        if not self._chunks:
            return pd.DataFrame({c: [] for c in (self._columns or POSITION_COLUMNS)})
        out = pd.concat(self._chunks, ignore_index=True) if len(self._chunks) > 1 \
            else self._chunks[0]
        out.attrs = {}
        return out

    def __enter__(self) -> PositionsWriter:
        from robustloc.io.atomic import atomic_output, is_stdio

        if self.path is None:
            self._cm = _InMemory()
            return self
        if is_stdio(self.path) and is_parquet(self.path):  # pragma: no cover
            raise InputError("Parquet cannot be written to standard output", "-")
        self._cm = atomic_output(self.path, binary=False)
        self._target, self._stream = self._cm.__enter__()
        return self

    def write(self, frame: pd.DataFrame) -> None:
        """Append one chunk of positions."""
        if self._cm is None:
            self.__enter__()
        cols = list(POSITION_COLUMNS)
        if "z" in frame.columns:
            cols.insert(4, "z")
        missing = [c for c in cols if c not in frame.columns]
        if missing:
            raise ValueError(f"positions frame is missing column(s): {', '.join(missing)}")
        ordered = cols + [c for c in frame.columns if c not in cols]
        if self._columns is None:
            self._columns = ordered
        elif ordered != self._columns:
            raise ValueError(
                f"positions chunk has columns {ordered}, the first chunk had {self._columns}"
            )
        out = frame[self._columns].reset_index(drop=True)
        out.attrs = {}
        if self.path is None:
            self._chunks.append(out)
        elif self._stream is not None:
            out.to_csv(self._stream, header=self.n_rows == 0, index=False)
        elif is_parquet(self.path):
            import pyarrow as pa
            import pyarrow.parquet as pq

            table = pa.Table.from_pandas(out, preserve_index=False)
            if self._pq_writer is None:
                self._pq_writer = pq.ParquetWriter(self._target, table.schema)
            self._pq_writer.write_table(table.cast(self._pq_writer.schema))
        else:
            out.to_csv(self._target, mode="w" if self.n_rows == 0 else "a",
                       header=self.n_rows == 0, index=False)
        self.n_rows += len(out)

    def close(self) -> None:
        """Finish the file (Parquet footer) and move it to its final path."""
        self._finish(None)

    def abort(self) -> None:
        """Discard everything written so far (the final path is not touched)."""
        self._finish(_Aborted())

    def _finish(self, exc: BaseException | None) -> None:
        cm, self._cm = self._cm, None
        if self.path is None:
            if exc is not None:
                self._chunks = []
            return
        try:
            if self._pq_writer is not None:
                w, self._pq_writer = self._pq_writer, None
                w.close()
        except BaseException as err:
            if cm is not None and exc is None:
                exc = err
            if cm is None:
                raise
        if cm is None:
            return
        if exc is None:
            if self._stream is None and self.n_rows == 0 and self._target is not None:
                self._write_empty()
            cm.__exit__(None, None, None)
        else:
            try:
                cm.__exit__(type(exc), exc, exc.__traceback__)
            except _Aborted:
                pass

    def _write_empty(self) -> None:
        """No chunk written: still leave a valid file with the header."""
        cols = list(POSITION_COLUMNS)
        empty = pd.DataFrame({c: [] for c in cols})
        if is_parquet(self.path):
            empty.to_parquet(self._target, index=False)
        else:
            empty.to_csv(self._target, index=False)

    def __exit__(self, exc_type: object, exc: BaseException | None, tb: object) -> None:
        self._finish(exc)


class _Aborted(Exception):
    """Internal: PositionsWriter.abort() passes it to the atomic output to discard it."""


def read_table(path: PathLike, what: str = "table") -> pd.DataFrame:
    """Read any CSV/Parquet table without contract validation (index = source line);
    ``what``: the input it is, for standard input (:func:`_spool`)."""
    return _read_raw(path, what=what)
