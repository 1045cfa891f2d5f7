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
non-numeric value, NaN/inf in a numeric field, empty id, duplicate anchor id, unknown anchor
id (when the anchors are given), malformed rows.  Blank lines are skipped.

The frames returned keep the source line numbers as their index (named ``line``), so a
consumer can still point at a line after filtering; ``frame.attrs["path"]`` holds the file.

Ids (``anchor``, ``tag``) are strings.  ``time`` is seconds (float).  A range may be negative
or shorter than the height difference: that is data, not an error.
"""

from __future__ import annotations

import os
import re
import warnings
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd
from numpy.typing import NDArray

from robustloc.errors import InputError

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


def _check_file(path: PathLike) -> Path:
    p = Path(path)
    if not p.exists():
        raise InputError("file not found", p)
    if p.is_dir():
        raise InputError("is a directory, expected a file", p)
    if p.stat().st_size == 0:
        raise InputError("empty file (expected a header line)", p, 1)
    return p


_TOKENIZE_RE = re.compile(r"Expected (\d+) fields in line (\d+), saw (\d+)")


def _parser_error(exc: Exception, path: Path) -> InputError:
    msg = str(exc)
    m = _TOKENIZE_RE.search(msg)
    if m:
        return InputError(
            f"expected {m.group(1)} fields, found {m.group(3)}", path, int(m.group(2))
        )
    return InputError(f"cannot parse: {msg.strip()}", path)


def _ragged_line(path: Path) -> InputError:
    """Locate the first row whose field count differs from the header's (slow path)."""
    import csv

    with open(path, newline="", encoding="utf-8", errors="replace") as fh:
        reader = csv.reader(fh)
        header = next(reader, [])
        for row in reader:
            if row and len(row) != len(header):
                return InputError(
                    f"expected {len(header)} fields, found {len(row)}", path, reader.line_num
                )
    return InputError("rows do not match the header's number of fields", path)


class _RaggedGuard:
    """Turn pandas' "Length of header ... does not match" warning into an InputError.

    (With ``index_col=False`` pandas truncates a row with extra fields and only warns;
    without it, an extra field in the first row silently becomes the index.)
    """

    def __init__(self, path: Path) -> None:
        self.path = path

    def __enter__(self) -> _RaggedGuard:
        self._cm = warnings.catch_warnings(record=True)
        self._log = self._cm.__enter__()
        warnings.simplefilter("always", pd.errors.ParserWarning)
        return self

    def __exit__(self, *exc: object) -> None:
        self._cm.__exit__(*exc)
        if exc[0] is None:
            self.check()

    def check(self) -> None:
        for w in self._log:
            if issubclass(w.category, pd.errors.ParserWarning) and "Length of header" in str(
                w.message
            ):
                raise _ragged_line(self.path)


_NA_NUMERIC = ["", "nan", "NaN", "NAN", "NA", "null", "None"]


def _csv_kwargs(path: Path, str_columns: Sequence[str]) -> dict:
    """read_csv options: ids as strings (only an empty field is missing, so an anchor may
    be called "NA"), the usual missing-value spellings in every other column."""
    header = pd.read_csv(path, nrows=0, skipinitialspace=True, index_col=False)
    names = [str(c) for c in header.columns]
    strs = {c for c in str_columns}
    return dict(
        index_col=False,
        dtype={c: str for c in names if c.strip() in strs},
        skip_blank_lines=False,
        skipinitialspace=True,
        keep_default_na=False,
        na_values={c: ([""] if c.strip() in strs else _NA_NUMERIC) for c in names},
    )


def _finish_frame(df: pd.DataFrame, path: Path, first_line: int) -> pd.DataFrame:
    """Name the index by source line, strip column names, drop blank lines."""
    df.columns = [str(c).strip() for c in df.columns]
    df.index = pd.RangeIndex(first_line, first_line + len(df), name="line")
    if len(df) and df.shape[1]:
        blank = df.isna().all(axis=1).to_numpy()
        if blank.any():
            df = df.loc[~blank]
    df.attrs["path"] = str(path)
    return df


def _read_raw(path: PathLike, str_columns: Sequence[str] = ()) -> pd.DataFrame:
    """Read a whole CSV or Parquet file; index = source line number."""
    p = _check_file(path)
    if is_parquet(p):
        try:
            df = pd.read_parquet(p)
        except Exception as exc:  # noqa: BLE001 - any pyarrow failure is a bad file
            raise InputError(f"cannot read Parquet file: {exc}", p) from None
        return _finish_frame(df.reset_index(drop=True), p, 2)
    try:
        with _RaggedGuard(p):
            df = pd.read_csv(p, **_csv_kwargs(p, str_columns))
    except pd.errors.EmptyDataError:
        raise InputError("empty file (expected a header line)", p, 1) from None
    except (pd.errors.ParserError, UnicodeDecodeError) as exc:
        raise _parser_error(exc, p) from None
    return _finish_frame(df, p, 2)


def _iter_raw(
    path: PathLike, chunk_rows: int, str_columns: Sequence[str] = ()
) -> Iterator[pd.DataFrame]:
    """Stream a CSV or Parquet file in chunks of about ``chunk_rows`` rows."""
    p = _check_file(path)
    if chunk_rows < 1:
        raise ValueError(f"chunk_rows must be >= 1, got {chunk_rows}")
    if is_parquet(p):
        import pyarrow.parquet as pq

        try:
            pf = pq.ParquetFile(p)
            line = 2
            for batch in pf.iter_batches(batch_size=chunk_rows):
                df = batch.to_pandas()
                yield _finish_frame(df, p, line)
                line += len(df)
        except InputError:
            raise
        except Exception as exc:  # noqa: BLE001
            raise InputError(f"cannot read Parquet file: {exc}", p) from None
        return
    try:
        line = 2
        with _RaggedGuard(p) as guard:
            reader = pd.read_csv(p, chunksize=chunk_rows, **_csv_kwargs(p, str_columns))
            with reader:
                for df in reader:
                    guard.check()
                    n = len(df)
                    yield _finish_frame(df, p, line)
                    line += n
    except pd.errors.EmptyDataError:
        raise InputError("empty file (expected a header line)", p, 1) from None
    except (pd.errors.ParserError, UnicodeDecodeError) as exc:
        raise _parser_error(exc, p) from None


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


def require_columns(
    df: pd.DataFrame, columns: Sequence[str], what: str, path: PathLike | None = None
) -> None:
    """Raise :class:`InputError` (line 1, the header) if a column is missing."""
    missing = [c for c in columns if c not in df.columns]
    if missing:
        have = ", ".join(map(str, df.columns)) or "none"
        raise InputError(
            f"{what} file is missing column(s) {', '.join(missing)} (has: {have})",
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
    if pd.api.types.is_bool_dtype(s):
        raise InputError(f"column '{col}' holds booleans, expected numbers", _path_of(df, path), 1)
    if pd.api.types.is_numeric_dtype(s):
        v = s.to_numpy(dtype=float, na_value=np.nan)
    else:
        v = pd.to_numeric(s, errors="coerce").to_numpy(dtype=float, na_value=np.nan)
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


def _ids(df: pd.DataFrame, col: str, path: PathLike | None = None) -> None:
    """Convert an id column to stripped strings; empty ids are an error."""
    s = df[col]
    if pd.api.types.is_float_dtype(s):
        v = s.to_numpy(dtype=float)
        if np.all(np.isnan(v) | (v == np.round(v))):
            s = s.astype("Int64")
    missing = s.isna().to_numpy()
    out = s if isinstance(s.dtype, pd.StringDtype) else s.astype(str)
    out = out.str.strip()
    empty = missing | (out == "").to_numpy(dtype=bool, na_value=True)
    if empty.any():
        i = int(np.argmax(empty))
        raise InputError(f"column '{col}': empty id", _path_of(df, path), _line_of(df, i))
    df[col] = out


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
    for c in ANCHOR_PARAM_COLUMNS:
        if c in df.columns:
            _numeric(df, c, path, allow_nan=True)
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
        (attenuation factor, seed 002 eq. (5)) and the range calibration ``bias, scale``
        (float; an empty value is NaN, meaning "not set for this anchor").  Extra columns
        are kept.  Index: source line.

    Raises
    ------
    InputError
        Missing column, empty file, non-numeric or non-finite coordinate, duplicate or
        empty anchor id -- with file and line.
    """
    return validate_anchors(_read_raw(path, ("anchor",)), path)


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
    df = _read_raw(path, ("anchor",))
    return validate_survey(df, path, anchors)


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
    if anchors is not None:
        _check_known(df, anchors, path)
    df.attrs["value"] = value
    return df


def _value_column(df: pd.DataFrame, what: str, path: PathLike | None) -> str:
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
    """Read a truth file: ``time, tag, x, y[, z]`` (all finite).  Index: source line."""
    df = _read_raw(path, ("tag",))
    return validate_truth(df, path)


def validate_truth(df: pd.DataFrame, path: PathLike | None = None) -> pd.DataFrame:
    """Validate a truth frame (see :func:`read_truth`)."""
    df = df.copy()
    require_columns(df, ("time", "tag", "x", "y"), "truth", path)
    _require_rows(df, "truth", path)
    _ids(df, "tag", path)
    for c in ("time", "x", "y", "z"):
        if c in df.columns:
            _numeric(df, c, path)
    return df


def read_positions(path: PathLike) -> pd.DataFrame:
    """Read a positions file (``time, tag, x, y[, z], method, status, ...``).

    ``x, y, z`` and ``sigma0`` may be empty/NaN (a failed epoch: its ``status`` says why);
    ``method`` defaults to ``"unknown"`` and ``status`` to ``"ok"`` when the columns are
    absent (a positions file from another tool).  ``n_used`` and ``excluded`` are optional.
    """
    df = _read_raw(path, ("tag", "method", "status", "excluded"))
    return validate_positions(df, path)


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
    for c, default in (("method", "unknown"), ("status", "ok")):
        if c not in df.columns:
            df[c] = default
        else:
            df[c] = df[c].fillna(default).astype(str).str.strip().astype(object)
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
) -> pd.DataFrame:
    """Validate a measurements frame (see :func:`read_measurements`)."""
    df = df.copy()
    value = _value_column(df, "measurements", path)
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
    path: PathLike, anchors: pd.DataFrame | Sequence[str] | None = None
) -> pd.DataFrame:
    """Read a whole measurements file: ``time, tag, anchor`` and one of ``rssi``/``range``.

    Parameters
    ----------
    path : str or PathLike
        CSV or Parquet file.  Rows may come in any order.
    anchors : DataFrame or sequence of str, optional
        The anchors (frame from :func:`read_anchors`, or ids).  When given, an anchor id
        not among them is an error naming its line.

    Returns
    -------
    DataFrame
        ``time`` (float s), ``tag`` and ``anchor`` (str), ``rssi`` (dBm) or ``range`` (m)
        (float), extra columns kept; index = source line; ``frame.attrs["value"]`` names
        the value column.  A NaN/inf value, time or an empty id is an error naming its line
        (never a silent drop).  Negative ranges are accepted.
    """
    df = _read_raw(path, ("tag", "anchor"))
    _require_rows(df, "measurements", path)
    return validate_measurements(df, path, anchors)


def iter_measurements(
    path: PathLike,
    chunk_rows: int = _DEFAULT_CHUNK_ROWS,
    anchors: pd.DataFrame | Sequence[str] | None = None,
) -> Iterator[pd.DataFrame]:
    """Stream a measurements file in validated chunks that never split an epoch.

    An epoch is one ``(time, tag)``.  Streaming requires the rows to be sorted by ``time``
    (non-decreasing; rows of equal time may mix tags and anchors in any order).  The rows
    of the last ``time`` value of each raw chunk are held back and prepended to the next
    chunk, so every epoch arrives whole in exactly one yielded chunk, and memory stays
    bounded by ``chunk_rows`` plus one time step.  A ``time`` that goes backwards is an
    :class:`InputError` naming its line (sort the file, or use :func:`read_measurements`,
    which accepts any order).

    Parameters
    ----------
    path : str or PathLike
        CSV or Parquet file.
    chunk_rows : int
        Rows read per chunk (default 500 000).
    anchors : DataFrame or sequence of str, optional
        As in :func:`read_measurements`.

    Yields
    ------
    DataFrame
        Validated chunks, as returned by :func:`read_measurements`.
    """
    known = None if anchors is None else _anchor_ids(anchors)
    carry: pd.DataFrame | None = None
    last_time = -np.inf
    value: str | None = None
    n_rows = 0
    for raw in _iter_raw(path, chunk_rows, ("tag", "anchor")):
        if len(raw) == 0:
            continue
        chunk = validate_measurements(raw, path, known)
        if value is None:
            value = chunk.attrs["value"]
        t = chunk["time"].to_numpy()
        back = np.diff(np.concatenate(([last_time], t))) < 0
        if back.any():
            i = int(np.argmax(back))
            raise InputError(
                f"time {t[i]} is earlier than the previous row's; streaming needs rows "
                "sorted by time (sort the file, or read it whole)",
                path,
                _line_of(chunk, i),
            )
        last_time = t[-1]
        n_rows += len(chunk)
        if carry is not None and len(carry):
            chunk = pd.concat([carry, chunk])
            chunk.attrs["path"] = str(path)
            chunk.attrs["value"] = value
        tt = chunk["time"].to_numpy()
        hold = tt == tt[-1]
        n_hold = int(hold[::-1].argmin()) if not hold.all() else len(hold)
        if n_hold == len(chunk):
            carry = chunk
            continue
        carry = chunk.iloc[len(chunk) - n_hold :]
        out = chunk.iloc[: len(chunk) - n_hold]
        out.attrs["path"] = str(path)
        out.attrs["value"] = value
        yield out
    if n_rows == 0:
        raise InputError("measurements file has a header but no data rows", path, 2)
    if carry is not None and len(carry):
        carry.attrs["path"] = str(path)
        carry.attrs["value"] = value
        yield carry


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
    """

    time: NDArray[np.float64]
    tag: NDArray[np.object_]
    values: NDArray[np.float64]
    anchor_ids: tuple[str, ...]
    value: str
    line: NDArray[np.int64]
    n_duplicates: int = 0

    @property
    def n_epochs(self) -> int:
        return int(self.values.shape[0])

    def __len__(self) -> int:
        return self.n_epochs


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
            np.empty(0, dtype=np.int64), 0,
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
    time_codes, time_uniques = pd.factorize(t, sort=True)
    key = time_codes.astype(np.int64) * len(tag_uniques) + tag_codes
    ukey, epoch = np.unique(key, return_inverse=True)
    n = len(ukey)
    flat = epoch.astype(np.int64) * m + col
    v = frame[value].to_numpy(dtype=float)
    sums = np.bincount(flat, weights=v, minlength=n * m)
    counts = np.bincount(flat, minlength=n * m)
    with np.errstate(invalid="ignore", divide="ignore"):
        values = np.where(counts > 0, sums / np.maximum(counts, 1), np.nan).reshape(n, m)
    n_dup = int(np.sum(np.maximum(counts - 1, 0)))
    times = np.asarray(time_uniques, dtype=float)[ukey // len(tag_uniques)]
    tags = np.asarray(tag_uniques, dtype=object)[ukey % len(tag_uniques)]
    if frame.index.name == "line":
        lines_src = frame.index.to_numpy(dtype=np.int64)
        first = np.full(n, np.iinfo(np.int64).max, dtype=np.int64)
        np.minimum.at(first, epoch, lines_src)
    else:
        first = np.zeros(n, dtype=np.int64)
    return Epochs(times, tags, values, ids, value, first, n_dup)


def iter_epochs(
    path: PathLike,
    anchors: pd.DataFrame | Sequence[str],
    chunk_rows: int = _DEFAULT_CHUNK_ROWS,
) -> Iterator[Epochs]:
    """Stream a (time-sorted) measurements file as :class:`Epochs` blocks.

    Combines :func:`iter_measurements` and :func:`to_epochs`; every epoch is in exactly
    one block, blocks come in time order.  Memory is bounded by ``chunk_rows``.
    """
    ids = _anchor_ids(anchors)
    for chunk in iter_measurements(path, chunk_rows=chunk_rows, anchors=ids):
        yield to_epochs(chunk, ids)


# --------------------------------------------------------------------------------------
# writing
# --------------------------------------------------------------------------------------


def write_table(frame: pd.DataFrame, path: PathLike) -> Path:
    """Write a frame as CSV or Parquet (by extension), creating parent folders.

    The index is not written (the ``line`` index of read frames is bookkeeping).  Floats
    are written with full precision (``repr``), so a CSV round trip is exact.
    """
    p = Path(path)
    if p.parent and not p.parent.exists():
        p.parent.mkdir(parents=True, exist_ok=True)
    out = frame.reset_index(drop=True)
    out.attrs = {}
    if is_parquet(p):
        out.to_parquet(p, index=False)
    else:
        out.to_csv(p, index=False)
    return p


def positions_frame(
    solution: object,
    time: NDArray[np.float64],
    tag: NDArray[np.object_] | Sequence[str],
    anchor_ids: Sequence[str],
    method: str | None = None,
) -> pd.DataFrame:
    """Build the contract positions frame from a :class:`~robustloc.estimators.Solution`.

    Columns ``time, tag, x, y[, z], method, status, n_used, sigma0, excluded`` (the
    ``excluded`` column is the ``;``-joined ids of the observations rejected in each
    epoch); ``z`` is written when the solution is 3-D.  ``hpl`` (and ``vpl`` in 3-D), the
    protection levels in metres, follow when the solution carries them; ``iterations`` is
    appended as an extra column.
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
    return pd.DataFrame(data)


def write_positions(frame: pd.DataFrame, path: PathLike) -> Path:
    """Write a positions frame with the contract columns first, in contract order.

    Missing contract columns are an error (``ValueError``); extra columns follow.
    """
    cols = list(POSITION_COLUMNS)
    if "z" in frame.columns:
        cols.insert(4, "z")
    missing = [c for c in cols if c not in frame.columns]
    if missing:
        raise ValueError(f"positions frame is missing column(s): {', '.join(missing)}")
    extra = [c for c in frame.columns if c not in cols]
    return write_table(frame[cols + extra], path)


class PositionsWriter:
    """Write a positions file chunk by chunk (bounded memory for streamed logs).

    CSV chunks are appended under one header; Parquet chunks become row groups of one
    file.  Each chunk is ordered as :func:`write_positions` orders it; every chunk must
    have the same columns as the first.  Use as a context manager::

        with PositionsWriter("positions.csv") as out:
            for epochs in iter_epochs(path, anchors):
                out.write(positions_frame(solver.solve(...), epochs.time, epochs.tag, ids))
    """

    def __init__(self, path: PathLike) -> None:
        self.path = Path(path)
        self.n_rows = 0
        self._columns: list[str] | None = None
        self._pq_writer = None

    def __enter__(self) -> PositionsWriter:
        if self.path.parent and not self.path.parent.exists():
            self.path.parent.mkdir(parents=True, exist_ok=True)
        return self

    def write(self, frame: pd.DataFrame) -> None:
        """Append one chunk of positions."""
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
        if is_parquet(self.path):
            import pyarrow as pa
            import pyarrow.parquet as pq

            table = pa.Table.from_pandas(out, preserve_index=False)
            if self._pq_writer is None:
                self._pq_writer = pq.ParquetWriter(self.path, table.schema)
            self._pq_writer.write_table(table.cast(self._pq_writer.schema))
        else:
            out.to_csv(self.path, mode="w" if self.n_rows == 0 else "a",
                       header=self.n_rows == 0, index=False)
        self.n_rows += len(out)

    def close(self) -> None:
        """Finish the file (Parquet footer)."""
        if self._pq_writer is not None:
            self._pq_writer.close()
            self._pq_writer = None

    def __exit__(self, *exc: object) -> None:
        self.close()


def read_table(path: PathLike) -> pd.DataFrame:
    """Read any CSV/Parquet table without contract validation (index = source line)."""
    return _read_raw(path)
