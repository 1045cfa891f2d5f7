"""Out-of-core repartitioning of measurements into a dataset for ``--engine dask``.

``by="tag"``: one hive directory per tag (``tag=T1/part-0.parquet``), or per bucket of tags
(``tag_bucket=0007/``, the tags hashed into ``buckets``), each file sorted by time: what
filters and trackers need (a tag's whole history in one file, in time order).

``by="time"``: contiguous time bins (``time_bin=000003/part-0.parquet``) of ``span_s``
seconds (default: the span giving about ``rows_per_partition`` rows per file at the log's
mean rate), each sorted by ``time, tag, anchor``.  Bins are ``floor((time - t0) / span)``,
so all rows of one time -- hence of one epoch -- land in one file: what snapshot methods
need.

Two engines, measured by ``benchmarks/bench_dask.py`` (the default is the faster):

* ``duckdb``: one partitioned ``COPY`` (DuckDB spills to disk beyond ``memory_limit``), then
  each file sorted by a second ``COPY`` -- DuckDB's partitioned writer does not keep the
  order of the query's ``ORDER BY`` within a file, and a file is bounded, so its sort is
  cheap;
* ``dask``: ``read_csv/read_parquet -> shuffle(key) -> sort within partitions ->
  to_parquet(partition_on=key)`` on a dask cluster.

Ids (``tag``, ``anchor``) are read as text, so ``007`` stays ``007``; so is every other
CSV column but ``time``, ``rssi`` and ``range`` (numbers), value for value.

The input is checked before anything is written, as the commands' readers check a file
(``time``, ``tag`` and ``anchor`` columns; no empty id; ``time``, ``rssi`` and ``range``
numbers, not missing, NaN or infinite): a bad row is ``error: FILE:LINE: what``, found by
one DuckDB scan and located by the project's reader.  The output directory must not be an
input, hold one or lie inside one (it is replaced whole).
"""

from __future__ import annotations

import os
import shutil
import sys
import threading
import time as _time
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING
from urllib.parse import quote

from robustloc.engines.dataset import (
    Partition,
    _hive_keys,
    discover,
    is_parquet_file,
    missing_hive_columns,
)
from robustloc.errors import InputError, OutputError

BY = ("tag", "time")
METHODS = ("duckdb", "dask")
#: Columns every input must have: the sort within a file is by time, tag, anchor.
REQUIRED = ("time", "tag", "anchor")
#: Columns read as numbers (and checked finite), and as ids (checked non-empty).
NUMERIC = ("time", "rssi", "range")
IDS = ("tag", "anchor")

if TYPE_CHECKING:
    import pandas as pd
    import pyarrow as pa


@dataclass(frozen=True)
class PartitionSummary:
    """What :func:`partition_dataset` wrote."""

    rows: int
    files: int
    by: str
    key: str
    span_s: float | None
    seconds: float
    method: str


#: Names of files in an input folder that are notes or metadata, never tables.
_NOT_TABLES = (".json", ".md")


def _inputs(spec: str) -> tuple[list[str], str, dict[str, dict[str, str]]]:
    """Input files, their format (``csv`` or ``parquet``; one format per input) and, per
    Parquet file that lacks an id column its path names (``tag=T1/part-0.parquet``
    without ``tag``), those ids' values: the hive keys the commands' readers restore
    (:func:`robustloc.engines.dataset.missing_hive_columns`); no other key is read."""
    p = Path(spec)
    if p.is_file():
        parts = [Partition(str(p), _hive_keys(p, None))]
    else:
        found = discover(spec, parquet=False, what="input")
        # notes and metadata (.json, .md) are no tables: left out, and said so; any other
        # file is read as a table (a log named .txt was left out without a word: the
        # dask fixer; a text that is no table is refused at its line)
        parts = [x for x in found if not x.path.lower().endswith(_NOT_TABLES)]
        left = [x.path for x in found if x.path.lower().endswith(_NOT_TABLES)]
        if not parts:  # (an IndexError before)
            raise InputError(f"no table in this input, only notes ({', '.join(left[:3])})",
                             spec)
        if left:
            print(f"note: {spec}: left out {len(left)} file(s) that are notes, not tables "
                  f"({', '.join(_NOT_TABLES)}): {', '.join(left[:3])}"
                  + (" ..." if len(left) > 3 else ""), file=sys.stderr)
    files = [x.path for x in parts]
    # Parquet by the datasets' test (its first bytes or name): by the name alone, a folder
    # of Hive's Parquet files (000000_0) "mixed CSV and Parquet" (the dask review)
    kind = {f: "parquet" if is_parquet_file(f) else "csv" for f in files}
    if len(set(kind.values())) != 1:
        one = next(f for f in files if kind[f] == "parquet")
        other = next(f for f in files if kind[f] == "csv")
        raise InputError(f"input mixes Parquet files and others ({other} is not Parquet, "
                         f"{one} is); give one format, or keep a side file under a name "
                         "starting with '_' or '.', which inputs ignore", spec)
    fmt = kind[files[0]]
    return files, fmt, (_hive_ids(parts) if fmt == "parquet" else {})


def _hive_ids(parts: list[Partition]) -> dict[str, dict[str, str]]:
    """Per file, the id columns (:data:`IDS`) it lacks and its path names, with their
    values (the outermost, unescaped as the readers unescape them)."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    out = {}
    for part in parts:
        if not any(k in IDS for k, _ in part.keys):
            continue
        try:
            have = pq.read_schema(part.path).names
        except (OSError, pa.ArrowException):
            continue  # (unreadable: DuckDB's scan says so)
        lack = {k: str(part.key(k)) for k in missing_hive_columns(part, have)}
        if lack:
            out[part.path] = lack
    return out


def _sql_str(s: str) -> str:
    return "'" + s.replace("'", "''") + "'"


def _q(name: str) -> str:
    """A quoted SQL identifier."""
    return '"' + name.replace('"', '""') + '"'


def _fresh_name(base: str, names: list[str]) -> str:
    """``base``, or ``base_1``, ``base_2`` ...: a column name none of ``names`` is (DuckDB
    compares names without case)."""
    taken = {n.lower() for n in names}
    name, i = base, 0
    while name.lower() in taken:
        i += 1
        name = f"{base}_{i}"
    return name


#: What :meth:`str.strip` strips (the readers' ids, :func:`robustloc.io.tables._ids`).
_WHITESPACE = "".join(c for c in map(chr, range(0x110000)) if c.isspace())


def _csv_headers(files: list[str]) -> list[list[str]]:
    """Each CSV file's column names as the commands' reader takes them (stripped), after
    the reader's checks of the header: a column named twice, a missing ``time``, ``tag``
    or ``anchor`` (with the reader's hints: a name in other case, another separator), an
    empty file or blank first line -- each ``FILE:1``."""
    import pandas as pd

    from robustloc.io.tables import (
        _CSV_ERRORS,
        _check_file,
        _compression,
        _csv_kwargs,
        _empty_error,
        _format,
        _parser_error,
        require_columns,
    )

    headers = []
    for f in files:
        p = _check_file(f)
        fmt = _format(p, f)
        if fmt == "parquet":  # (a Parquet file named .csv: DuckDB's scan says so)
            continue
        try:
            _csv_kwargs(p, f, fmt, IDS)  # (refuses a duplicate column name)
            names = [str(c).strip() for c in pd.read_csv(
                p, nrows=0, skipinitialspace=True, index_col=False,
                skip_blank_lines=False, compression=_compression(fmt)).columns]
        except InputError:
            raise
        except pd.errors.EmptyDataError:
            raise _empty_error(p, f, fmt) from None
        except _CSV_ERRORS as exc:
            raise _parser_error(exc, p, f, fmt) from None
        if not names:  # a blank first line
            raise _empty_error(p, f, fmt)
        missing = [c for c in REQUIRED if c not in names]
        if missing:  # partition's words, with the reader's hints (a rename, a separator)
            try:
                require_columns(pd.DataFrame(columns=names), REQUIRED, "measurements", f)
            except InputError as exc:
                said = (f"measurements file is missing column(s) {', '.join(missing)} "
                        f"(has: {', '.join(names) or 'none'})")
                hint = exc.message[len(said):] if exc.message.startswith(said) else ""
                raise InputError(f"input is missing column(s) {', '.join(missing)} "
                                 f"(has: {', '.join(names)}){hint}", f, 1) from None
        headers.append(names)
    return headers


def _check_one_kind(files: list[str], headers: list[list[str]]) -> None:
    """Every file with the value column (:data:`robustloc.io.tables.VALUE_COLUMNS`:
    ``rssi`` or ``range``) of the first: a dataset holds one kind of measurement.

    ``headers``: each file's column names, in ``files``' order.  Checked per file before
    the files are read as one: their union gave a file of ranges the RSSI column of the
    others, all missing, and the error named the folder, not the file (``gl3: column
    'rssi': 153 missing ...``: the commands review).

    Raises
    ------
    InputError
        ``FILE:1``: the first file whose value column is not the first file's.
    """
    from robustloc.io.tables import VALUE_COLUMNS

    kinds = [[c for c in VALUE_COLUMNS if c in names] for names in headers]
    for f, kind in zip(files[1:], kinds[1:]):
        if kind == kinds[0]:
            continue
        def said(k: list[str]) -> str:
            return (" and ".join(repr(c) for c in k) if k
                    else "no " + " or ".join(repr(c) for c in VALUE_COLUMNS))

        raise InputError(f"has {said(kind)}, not {said(kinds[0])} as {files[0]}: a dataset "
                         "holds one kind of measurement (partition the RSSI and the range "
                         "files apart)", f, 1)


def _parquet_headers(files: list[str]) -> list[list[str]] | None:
    """Each Parquet file's column names, or None when one cannot be read (DuckDB's scan
    then says why), after the checks of :func:`_check_parquet_columns`."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    try:
        schemas = [pq.read_schema(f) for f in files]
    except (OSError, pa.ArrowException):
        return None
    for f, schema in zip(files, schemas):
        _check_parquet_columns(f, schema)
    return [schema.names for schema in schemas]


def _check_parquet_columns(path: str, schema: pa.Schema) -> None:
    """A Parquet file's columns checked as the commands' reader checks them, with its
    words: a column named twice (DuckDB renamed the second ``rssi_1`` and wrote it, exit
    0, where the same CSV header and ``locate`` were refused) and a column of
    :data:`NUMERIC` holding booleans (DuckDB read them as 1.0 and 0.0; only ``locate
    --engine dask`` refused the dataset, later: the input review).

    Raises
    ------
    InputError
        ``FILE:1: duplicate column 'rssi' in the header``
        (:func:`robustloc.io.tables._check_header`) or ``FILE:1: column 'rssi' holds
        booleans, expected numbers`` (:func:`robustloc.io.tables._numeric`'s words).
    """
    import pyarrow as pa

    from robustloc.io.tables import _check_header

    _check_header(schema.names, path)
    for c in NUMERIC:
        if c not in schema.names:
            continue
        t = schema.field(c).type
        if isinstance(t, pa.DictionaryType):
            t = t.value_type
        if pa.types.is_boolean(t):
            raise InputError(f"column '{c}' holds booleans, expected numbers", path, 1)


def _source(con, files: list[str], fmt: str, spec: str,
            hive: dict[str, dict[str, str]] | None = None) -> tuple[str, list[str]]:
    """DuckDB's table function over the input and its column names; ids read as text.

    The rows are the files' own, as the commands' readers take them: no hive key of a
    path is read (DuckDB added each as a column, a stale ``time_bin`` of a dataset
    partitioned before, and its folder's value hid a column of that name: the partition
    review), but the ids ``hive`` gives (:func:`_inputs`) for the files that lack them.

    A CSV is read in the commands' dialect, told, not sniffed: comma, double quote
    (doubled inside a field), no comment lines, a header (its names stripped, checked by
    :func:`_csv_headers`).  A row DuckDB cannot read (a ragged or garbage line) is
    located by the commands' reader (:func:`_first_bad_row`).  Text ids are stripped as
    the readers strip them, so ``T1`` and ``T1 `` are one tag.  A CSV column of
    :data:`NUMERIC` is read as DOUBLE whatever DuckDB's sniffer made of it (``inf`` is
    sniffed as an infinite DATE, a stray word as VARCHAR), so that the check of
    :func:`_stats` sees numbers (or fails on the row that is not one); every other CSV
    column is read as text, as written (DuckDB types a column from a sample of the file:
    a later value of another type was changed or refused).
    """
    import duckdb

    lst = "[" + ", ".join(_sql_str(f) for f in files) + "]"
    if fmt == "csv":
        src = (f"read_csv({lst}, header=true, union_by_name=true, hive_partitioning=false, "
               "delim=',', quote='\"', escape='\"', comment='', skip=0")
        headers = _csv_headers(files)
        if len(headers) == len(files):  # (else a Parquet file named .csv: DuckDB says so)
            _check_one_kind(files, headers)
        if headers and all(h == headers[0] for h in headers):  # (" tag" is "tag")
            src += ", names=[" + ", ".join(_sql_str(c) for c in headers[0]) + "]"
    else:
        src = f"read_parquet({lst}, union_by_name=true, hive_partitioning=false"
        schemas = _parquet_headers(files)
        if schemas is not None:
            _check_one_kind(files, schemas)
    try:
        described = con.execute(f"DESCRIBE SELECT * FROM {src})").fetchall()
    except duckdb.Error as exc:
        if fmt != "csv":
            raise InputError(f"cannot read: {str(exc).splitlines()[0]}", spec) from None
        # DuckDB's sniffer refuses what the commands read (lines ending in CRLF and LF
        # in one file, say): the commands' own reader decides.  A row it refuses is that
        # row's FILE:LINE error; a file it accepts is read again without DuckDB's strict
        # mode (which would otherwise stop the partitioning of a readable log)
        bad = _first_bad_row(files, list(NUMERIC) + list(IDS))
        if bad is not None:
            raise bad from None
        src += ", strict_mode=false"
        try:
            described = con.execute(f"DESCRIBE SELECT * FROM {src})").fetchall()
        except duckdb.Error as exc2:
            raise InputError(f"cannot read: {str(exc2).splitlines()[0]}", spec) from None
    names = [r[0] for r in described]
    replace = []
    if fmt != "csv" and "time" in names:
        seconds = _parquet_time_seconds(files, spec)
        if seconds is not None:
            replace.append(f"{seconds} AS time")
    if fmt == "csv":
        # numbers as DOUBLE, as the readers read them: a column sniffed as BIGINT took
        # hexadecimal text ("0x10" became 16, which the readers refuse; the review).
        # Every other column as text, value for value: typed from DuckDB's sample of
        # the file, 1.5 on line 55 002 of an integer column became 2, two 20-digit ids
        # one double, TRUE a boolean and 1e3 1000.0 (exit 0), and a word there stopped
        # the run with DuckDB's "Conversion Error" (the partition review)
        types = {c: "DOUBLE" if c in NUMERIC else "VARCHAR" for c in names}
        if types:
            src += ", types={" + ", ".join(f"{_sql_str(c)}: {_sql_str(t)}"
                                           for c, t in types.items()) + "}"
    rel = src + ")"
    if hive:
        rel, described = _with_hive_ids(con, src, described, hive)
        names = [r[0] for r in described]
    text_ids = [r[0] for r in described if r[0] in IDS
                and (fmt == "csv" or str(r[1]).upper() == "VARCHAR")]
    replace += [f"trim({_q(c)}, {_sql_str(_WHITESPACE)}) AS {_q(c)}" for c in text_ids]
    # a Parquet id of floating point named as the readers name it (1.0 -> "1", 1.5 ->
    # "1.5": robustloc.io.tables._ids); DuckDB wrote tag=1.0 where Dask and the readers
    # said 1 (the partition review, 2026-12-07)
    float_ids = [r[0] for r in described if r[0] in IDS and fmt != "csv"
                 and str(r[1]).upper() in ("DOUBLE", "FLOAT", "REAL")]
    replace += [f"{_float_id(_q(c))} AS {_q(c)}" for c in float_ids]
    if replace:
        return f"(SELECT * REPLACE ({', '.join(replace)}) FROM {rel})", names
    return rel, names


def _float_id(ref: str) -> str:
    """The SQL of a floating-point id as text, as the readers name it."""
    return (f"(CASE WHEN {ref} = round({ref}) AND abs({ref}) < 9.2e18 THEN "
            f"CAST(CAST({ref} AS BIGINT) AS VARCHAR) ELSE CAST({ref} AS VARCHAR) END)")


def _with_hive_ids(con, src: str, described: list, hive: dict[str, dict[str, str]]
                   ) -> tuple[str, list]:
    """The relation of ``src`` (an unclosed ``read_parquet(``) with the ids of ``hive``
    (per file, the id columns it lacks and their values from its path) as text, and its
    DESCRIBE.  Joined on each row's file name (a column of a name the input does not
    use); an id a file has is its own, as text."""
    names = [str(r[0]) for r in described]
    types = {str(r[0]): str(r[1]).upper() for r in described}
    fcol = _fresh_name("__file", names)
    ids = [k for k in IDS if any(k in v for v in hive.values())]
    table = "__robustloc_hive_ids"
    con.execute(f"CREATE OR REPLACE TEMP TABLE {table} (f VARCHAR, "
                + ", ".join(f"{_q(k)} VARCHAR" for k in ids) + ")")
    con.executemany(f"INSERT INTO {table} VALUES ({', '.join('?' * (1 + len(ids)))})",
                    [(f, *(v.get(k) for k in ids)) for f, v in hive.items()])
    replace, add = [], []
    for k in ids:
        if k not in types:
            add.append(f"h.{_q(k)} AS {_q(k)}")
            continue
        own = f"s.{_q(k)}"
        own = (own if types[k] == "VARCHAR" else _float_id(own)
               if types[k] in ("DOUBLE", "FLOAT", "REAL") else f"CAST({own} AS VARCHAR)")
        replace.append(f"(CASE WHEN h.{_q(k)} IS NOT NULL THEN h.{_q(k)} ELSE {own} END) "
                       f"AS {_q(k)}")
    sel = f"s.* EXCLUDE ({_q(fcol)})"
    if replace:
        sel += f" REPLACE ({', '.join(replace)})"
    sel += "".join(", " + a for a in add)
    rel = (f"(SELECT {sel} FROM {src}, filename={_sql_str(fcol)}) AS s "
           f"LEFT JOIN {table} AS h ON s.{_q(fcol)} = h.f)")
    return rel, con.execute(f"DESCRIBE SELECT * FROM {rel}").fetchall()


def _parquet_time_seconds(files: list[str], spec: str) -> str | None:
    """The SQL of a Parquet ``time`` column in seconds, as the commands' reader turns it
    (:func:`robustloc.io.tables._seconds`), or None for numbers.  Text is read as the
    number it spells.  A timestamp is seconds
    since the Unix epoch (``CAST(time AS DOUBLE)`` refused it); a duration, which DuckDB
    reads as a BIGINT of its unit, is divided by the unit (it was taken as seconds: a
    duration of 9 s in microseconds became 9e6 s).

    Raises
    ------
    InputError
        Files whose ``time`` columns are timestamps or durations of different kinds.
    """
    import pyarrow as pa
    import pyarrow.parquet as pq

    kinds = set()
    for f in files:
        try:
            t = pq.read_schema(f).field("time").type
        except (KeyError, OSError, pa.ArrowException):
            continue  # (a file without the column or unreadable: DuckDB's scan says so)
        if isinstance(t, pa.DictionaryType):
            t = t.value_type
        kinds.add(("timestamp", None) if pa.types.is_timestamp(t)
                  else ("duration", t.unit) if pa.types.is_duration(t)
                  else ("text", None) if pa.types.is_string(t) or pa.types.is_large_string(t)
                  else ("number", None))
    if len(kinds) > 1 and any(k not in ("number", "text") for k, _ in kinds):
        raise InputError("the files' time columns differ in kind ("
                         + ", ".join(sorted(f"{k} {u}" if u else k for k, u in kinds))
                         + "): write them with one", spec)
    if kinds == {("timestamp", None)}:
        return "epoch(time)"
    if ("text", None) in kinds:
        # numbers written as text, which the readers take (they were binned by text
        # arithmetic, an error, and sorted as text: "10" < "9"; the Dask review)
        return "CAST(trim(CAST(time AS VARCHAR)) AS DOUBLE)"
    if len(kinds) == 1 and next(iter(kinds))[0] == "duration":
        per_s = {"s": 1, "ms": 1_000, "us": 1_000_000, "ns": 1_000_000_000}
        return f"CAST(time AS DOUBLE) / {per_s[next(iter(kinds))[1]]}"
    return None


def _first_bad_row(files: list[str], names: list[str]) -> InputError | None:
    """The first row, in file order, that the commands' reader refuses (a missing,
    non-numeric, NaN or infinite number, an empty id), as its ``FILE:LINE`` error; None
    if the reader accepts every row.  Streamed (bounded memory); only run once the DuckDB
    scan found a bad value."""
    from robustloc.io.tables import _ids, _iter_raw, _numeric

    numeric = [c for c in NUMERIC if c in names]
    ids = [c for c in IDS if c in names]
    for f in files:
        try:
            for chunk in _iter_raw(f, 200_000, IDS):
                chunk = chunk.copy()
                for c in ids:
                    if c in chunk.columns:
                        _ids(chunk, c, f)
                for c in numeric:
                    if c in chunk.columns:
                        _numeric(chunk, c, f)
        except InputError as exc:
            return exc
    return None


def partition_dataset(
    source: str, out: str | os.PathLike, by: str, *, span_s: float | None = None,
    rows_per_partition: int = 2_000_000, buckets: int = 0, method: str = "duckdb",
    memory_limit: str = "2GB", threads: int | None = None, scheduler: str | None = None,
    workers: int | None = None, progress: bool = False,
) -> PartitionSummary:
    """Repartition measurements ``source`` (CSV or Parquet: file, directory or glob).

    Parameters
    ----------
    source : str
        Input file, directory or glob; rows in any order.
    out : str or PathLike
        Dataset directory to write (staged, then renamed into place).
    by : {"tag", "time"}
        Partition key (see the module docstring).
    span_s : float, optional
        ``by="time"``: bin width (s).  Default: ``(t_max - t_min) rows_per_partition / n``.
    rows_per_partition : int
        ``by="time"`` without ``span_s``: target rows per file.
    buckets : int
        ``by="tag"``: 0 = one directory per tag; N > 0 = tags hashed into N buckets.
    method : {"duckdb", "dask"}
        Engine (see the module docstring).
    memory_limit : str
        DuckDB's memory limit (it spills beyond it); dask workers use 2 GiB each.
    threads : int, optional
        DuckDB threads (default: the cores available).
    scheduler, workers
        ``method="dask"``: as ``--scheduler``, ``--workers``.
    progress : bool
        Show a progress bar on a terminal (stderr; dask's own on stdout for the dask
        method's shuffle, as the engine's other commands).
    """
    from robustloc.engines.dask import DatasetOutput

    if by not in BY:
        raise ValueError(f"--by must be one of {', '.join(BY)}, got {by!r}")
    if method not in METHODS:
        raise ValueError(f"--method must be one of {', '.join(METHODS)}, got {method!r}")
    if span_s is not None and not (span_s > 0 and span_s < float("inf")):
        raise ValueError(f"--span must be a positive number of seconds, got {span_s}")
    if rows_per_partition < 1 or buckets < 0:
        raise ValueError("--rows-per-partition must be >= 1 and --buckets >= 0")
    from robustloc.engines.dask import input_paths

    if not str(out).strip():  # Path("") is ".": the working folder would be replaced
        raise InputError("--out: empty output name (give a dataset directory name)")
    t0 = _time.perf_counter()
    files, fmt, hive = _inputs(source)
    # the output replaces a whole directory: never one that is, holds or lies in an input
    dest = DatasetOutput(out, input_paths(source, (), *files), writer="partition")
    try:
        if method == "duckdb":
            rows, span, key = _duckdb(files, fmt, dest.stage, by, span_s, rows_per_partition,
                                      buckets, memory_limit, threads, source, str(out), hive,
                                      progress)
        else:
            dtypes = _check_with_duckdb(files, fmt, dest.stage, memory_limit, threads,
                                        source, hive, by == "tag" and not buckets, progress)
            rows, span, key = _dask(files, fmt, dest.stage, by, span_s, rows_per_partition,
                                    buckets, scheduler, workers, source, dtypes, hive,
                                    progress)
        written = list(dest.stage.rglob("*.parquet"))
        n_files = len(written)
        _check_rows_written(written, rows, out)
        summary = PartitionSummary(rows, n_files, by, key, span, 0.0, method)
        dest.commit({"command": "partition", "input": str(source), "by": by, "key": key,
                     "span_s": span, "rows": rows, "files": n_files, "method": method})
    except BaseException:
        dest.abort()
        raise
    return PartitionSummary(summary.rows, summary.files, by, key, span,
                            round(_time.perf_counter() - t0, 3), method)


def _key_expr(by: str, buckets: int, t0: float, span: float | None,
              t1: float | None = None) -> tuple[str, str]:
    """The partition key's name and SQL.  Keys are zero-padded to one width, so that the
    folders sort in time (bucket) order; the width holds the largest key: DuckDB's
    ``lpad`` cuts a longer text to the width (bin 1000005 became 100000, and bins 12 days
    apart were one partition, which ``locate --engine dask`` then refused; the review)."""
    if by == "tag":
        if buckets:
            width = max(4, len(str(buckets - 1)))
            return "tag_bucket", f"lpad(CAST(hash(tag) % {buckets} AS VARCHAR), {width}, '0')"
        return "tag", "tag"
    last = 0 if t1 is None or span is None else int((t1 - t0) // span)
    width = max(6, len(str(last)) + 1)  # (+1: a bin's floor rounding one past the last)
    return "time_bin", f"lpad(CAST(CAST(floor((time - {t0!r}) / {span!r}) AS BIGINT) AS " \
                       f"VARCHAR), {width}, '0')"


def _check_time_limits(tmin: float, tmax: float, files: list[str], spec: str) -> None:
    """``--by time`` bins need times within the documented limits (|t| <= 1e12 s,
    :mod:`robustloc.io.limits`): a time of 1e20, which ``locate`` counts as an
    ``invalid_measurement``, stopped the partitioning with DuckDB's "can't be cast ...
    INT64" and no line, and 1e13 made a bin of its own number far beyond the others (the
    review).  The first such row is named by its line."""
    from robustloc.io.limits import LIMITS

    lo, hi = LIMITS["time"].low, LIMITS["time"].high
    if lo <= tmin and tmax <= hi:
        return
    from robustloc.io.tables import _iter_raw, _line_of, _numeric

    for f in files:
        for chunk in _iter_raw(f, 200_000, IDS):
            chunk = chunk.copy()
            _numeric(chunk, "time", f)
            t = chunk["time"].to_numpy(dtype=float)
            bad = (t < lo) | (t > hi)
            if bad.any():
                i = int(bad.argmax())
                raise InputError(
                    f"time {t[i]:g} s is beyond the limits of {lo:g} to {hi:g} s: --by time "
                    "cannot bin it (locate counts such a row invalid_measurement); remove "
                    "it, or partition --by tag", f, _line_of(chunk, i))
    raise InputError(f"column 'time' holds values beyond {lo:g} to {hi:g} s (--by time "
                     "cannot bin them; partition --by tag)", spec)


class _Progress:
    """The DuckDB work's progress bar on stderr, only on a terminal and when ``show``
    (``-q`` hides it), as the other commands draw theirs: each pass over the rows (the
    check, the partitioned ``COPY``) in per cent of DuckDB's own estimate
    (``query_progress``, polled by a thread while the query runs), then the sort of the
    partitions, file by file.  A 3 M-row partitioning printed nothing for half a minute
    (the partition review).  Off, :meth:`query` is a plain ``execute``."""

    _QUERY = "partition, {desc}: {percentage:3.0f}%|{bar}| [{elapsed}<{remaining}]"
    _FILES = "partition, {desc}: {n_fmt}/{total_fmt} files|{bar}| [{elapsed}<{remaining}]"

    def __init__(self, show: bool) -> None:
        self.bar = None
        if show and sys.stderr.isatty():
            from tqdm import tqdm

            self.bar = tqdm(total=100, desc="reading", file=sys.stderr, leave=False,
                            bar_format=self._QUERY)

    def _stage(self, desc: str, total: int, fmt: str) -> None:
        assert self.bar is not None
        self.bar.bar_format = fmt
        self.bar.set_description_str(desc, refresh=False)
        self.bar.reset(total=total)

    def query(self, con, sql: str, desc: str) -> list:
        """``con.execute(sql).fetchall()``, the bar following DuckDB's progress, polled
        by a thread.  The query runs in the calling (main) thread, so that an interrupt
        stops it as before (run in a thread, Ctrl-C aborted the process: "FATAL:
        exception not rethrown")."""
        if self.bar is None:
            return con.execute(sql).fetchall()
        self._stage(desc, 100, self._QUERY)
        bar, stop = self.bar, threading.Event()

        def watch() -> None:
            while not stop.wait(0.2):
                try:
                    done = float(con.query_progress())
                except Exception:  # noqa: BLE001 - the bar only stops following
                    return
                if done > bar.n:
                    bar.update(min(done, 100.0) - bar.n)

        watcher = threading.Thread(target=watch, name="partition-progress", daemon=True)
        watcher.start()
        try:
            rows = con.execute(sql).fetchall()
        finally:
            stop.set()
            watcher.join()
        bar.update(100 - bar.n)
        return rows

    def files(self, desc: str, total: int) -> None:
        """A stage of ``total`` steps (:meth:`step`)."""
        if self.bar is not None:
            self._stage(desc, total, self._FILES)

    def step(self) -> None:
        if self.bar is not None:
            self.bar.update(1)

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()


def _stats(con, src: str, names: list[str], spec: str, files: list[str],
           progress: _Progress | None = None) -> tuple[int, float, float, int]:
    """Rows, time range and longest tag (bytes) of the input, after checking it as the
    commands' reader does.

    One scan counts, per column, the values the reader refuses (:data:`NUMERIC`: missing,
    NaN or infinite; :data:`IDS`: missing or empty); if any, :func:`_first_bad_row`
    names the first such row with its line.

    Raises
    ------
    InputError
        A missing column (line 1), a bad value (``FILE:LINE``), no data rows.
    """
    import duckdb

    missing = [c for c in REQUIRED if c not in names]
    if missing:
        raise InputError(f"input is missing column(s) {', '.join(missing)} "
                         f"(has: {', '.join(names)})", spec, 1)
    checks = [(c, f"{_q(c)} IS NULL OR NOT isfinite(CAST({_q(c)} AS DOUBLE))",
               "missing, NaN or infinite value(s)") for c in NUMERIC if c in names]
    checks += [(c, f"{_q(c)} IS NULL OR trim(CAST({_q(c)} AS VARCHAR)) = ''",
                "empty id(s)") for c in IDS if c in names]
    counts = ", ".join(f"count(*) FILTER (WHERE {cond})" for _, cond, _ in checks)
    try:
        n, tmin, tmax, longest, *bad = (progress or _Progress(False)).query(
            con, f"SELECT count(*), min(CAST(time AS DOUBLE)), max(CAST(time AS DOUBLE)), "
            f"max(strlen(CAST(tag AS VARCHAR))), {counts} FROM {src}", "checking")[0]
    except duckdb.Error as exc:  # a value that is not a number: the reader names its line
        found = _first_bad_row(files, names)
        if found is not None:
            raise found from None
        raise InputError(f"column 'time': {str(exc).splitlines()[0]}", spec) from None
    for (col, _, what), k in zip(checks, bad):
        if k:
            found = _first_bad_row(files, names)
            if found is not None:
                raise found from None
            raise InputError(f"column '{col}': {k} {what}", spec)
    if not n:
        raise InputError("input has no data rows", spec, 2)
    return int(n), float(tmin), float(tmax), int(longest or 0)


def _name_max(folder: Path) -> int:
    """The longest file name (bytes) the file system of ``folder`` takes (255 if not
    known)."""
    try:
        return int(os.pathconf(folder, "PC_NAME_MAX"))
    except (OSError, ValueError, AttributeError):
        return 255


def _check_tag_folders(con, src: str, longest: int, stage: Path, files: list[str],
                       spec: str) -> None:
    """``--by tag`` without ``--buckets``: each tag's folder (``tag=`` and the tag escaped,
    as both methods name it) must be a file name the output's file system takes; a tag
    of 300 bytes stopped the run with an IO error naming the hidden staging folder ("File
    name too long": the partition review).  ``longest`` (bytes, from :func:`_stats`)
    rules out most logs without a look at the tags (escaping at most triples a byte).

    Raises
    ------
    InputError
        At the first row of such a tag (``FILE:LINE`` when the readers find it), with the
        way out: ``--buckets``.
    """
    limit = _name_max(stage)
    room = limit - len("tag=")
    if 3 * longest <= room:
        return
    tag = "CAST(tag AS VARCHAR)"
    cur = con.execute(f"SELECT DISTINCT {tag} FROM {src} WHERE strlen({tag}) > {room // 3}")
    too_long = None
    while too_long is None and (rows := cur.fetchmany(10_000)):
        too_long = next((t for (t,) in rows if len(quote(t, safe="")) > room), None)
    if too_long is None:
        return
    where: tuple = (spec,)
    found = _first_long_tag(files, room)
    if found is not None:
        too_long, where = found[0], found[1:]
    n = len(too_long.encode())
    raise InputError(
        f"tag {too_long[:24]!r}... ({n} bytes) is too long for a folder name: tag= and "
        f"the tag escaped take {4 + len(quote(too_long, safe=''))} bytes, this file "
        f"system allows {limit}; give --buckets N to hash the tags into N folders "
        "(tag_bucket=NNNN/, each file keeps its rows' tags)", *where)


def _first_long_tag(files: list[str], room: int) -> tuple[str, str, int | None] | None:
    """The first tag, in file order, whose escaped text is longer than ``room`` bytes,
    with its file and line (as the readers read the ids); None if the readers find none
    (a tag from a hive path)."""
    from robustloc.io.tables import _ids, _iter_raw, _line_of

    for f in files:
        for chunk in _iter_raw(f, 200_000, IDS):
            if "tag" not in chunk.columns:
                break
            chunk = chunk.copy()
            _ids(chunk, "tag", f)
            tags = chunk["tag"].astype(str)
            long = (tags.str.len() > room // 3).to_numpy()
            for i in long.nonzero()[0]:
                t = tags.iloc[i]
                if len(quote(t, safe="")) > room:
                    return t, f, _line_of(chunk, int(i))
    return None


def _connect(memory_limit: str, threads: int | None, tmp: Path):
    """A DuckDB connection with the memory limit, threads and spill directory."""
    import duckdb

    from robustloc.engines.cluster import machine_cores

    con = duckdb.connect()
    try:
        try:
            con.execute(f"SET memory_limit={_sql_str(memory_limit)}")
        except duckdb.Error:
            raise InputError(f"--memory-limit: expected a size such as 2GB or 500MB, got "
                             f"{memory_limit!r}") from None
        con.execute(f"SET threads={int(threads or machine_cores())}")
        # DuckDB's own bar never printed (stdout holds --json); its progress is kept for
        # the command's bar (_Progress)
        con.execute("SET enable_progress_bar=true")
        con.execute("SET enable_progress_bar_print=false")
        con.execute(f"SET temp_directory={_sql_str(str(tmp))}")
    except BaseException:
        con.close()
        raise
    return con


def _check_rows_written(files: list[Path], rows: int, out: str | os.PathLike) -> None:
    """Refuse a dataset whose files hold other than the ``rows`` read (from their
    metadata): rows written elsewhere were lost, silently (the Dask review: 529 of 2 158
    rows went outside the output, and the summary said 2 158)."""
    import pyarrow.parquet as pq

    have = sum(pq.ParquetFile(f).metadata.num_rows for f in files)
    if have != rows:
        raise OutputError(f"the partitioned dataset holds {have} rows of the {rows} read: "
                          "not written (a bug in robustloc; please report it)", out)


#: The dtype of a text column in the dask method (Arrow strings, as dask's own).
_TEXT = "string[pyarrow]"
#: DuckDB column types that the dask method reads as float64 in a column of
#: :data:`NUMERIC` (any other column keeps its type: :func:`_check_with_duckdb`).
_NUMBER_TYPES = ("DOUBLE", "FLOAT", "REAL", "BIGINT", "INTEGER", "SMALLINT", "TINYINT",
                 "HUGEINT", "UBIGINT", "UINTEGER", "USMALLINT", "UTINYINT", "DECIMAL")


def _check_with_duckdb(files: list[str], fmt: str, stage: Path, memory_limit: str,
                       threads: int | None, spec: str, hive: dict[str, dict[str, str]],
                       tag_folders: bool, progress: bool = False) -> dict[str, object]:
    """``method="dask"``: the input checked by :func:`_stats` first (one DuckDB scan),
    and its tags' folder names (:func:`_check_tag_folders`) when ``tag_folders``.

    Returns each column of all the files together (their union, in DuckDB's order) with
    the dtype the dask method reads it as: ids as text (:data:`_TEXT`), a number of
    :data:`NUMERIC` as ``float64`` (as the readers read them), every other column in the
    type DuckDB reads it as (a ``pandas.ArrowDtype`` of its Arrow type; text for a CSV's
    columns, :func:`_source`), so that both methods write the same values: an int64
    column was made float64 here, which changed ids and nanosecond stamps beyond 2**53
    (1910 of the 1917 ``field.stamp`` of the uwb-dwm1001 log ``A3.csv``: the partition
    review).  Dask takes the columns and their types from the first file (or its first
    block): a later file with an integer ``time`` where the first had a float, or with
    one more column, stopped the run with an internal error, and a Parquet file's extra
    column was dropped without a word (the Dask review)."""
    import pandas as pd
    import pyarrow as pa

    tmp = stage / ".duckdb-tmp"
    con = _connect(memory_limit, threads, tmp)
    bar = _Progress(progress)
    try:
        src, names = _source(con, files, fmt, spec, hive)
        *_, longest = _stats(con, src, names, spec, files, bar)
        if tag_folders:
            _check_tag_folders(con, src, longest, stage, files, spec)
        described = con.execute(f"DESCRIBE SELECT * FROM {src}").fetchall()
        empty = con.sql(f"SELECT * FROM {src} LIMIT 0")
        # (DuckDB 1.2 names it arrow(); 2.0 warns there and names it to_arrow_table())
        schema = (empty.to_arrow_table() if hasattr(empty, "to_arrow_table")
                  else empty.arrow()).schema
    finally:
        bar.close()
        con.close()
        shutil.rmtree(tmp, ignore_errors=True)
    arrow = {f.name: f.type for f in schema}
    dtypes: dict[str, object] = {}
    for c, t, *_ in described:
        c = str(c)
        a = arrow.get(c)
        if c in IDS:
            dtypes[c] = _TEXT
        elif c in NUMERIC and str(t).upper().startswith(_NUMBER_TYPES):
            dtypes[c] = "float64"
        elif a is None or pa.types.is_string(a) or pa.types.is_large_string(a) \
                or getattr(pa.types, "is_string_view", lambda _: False)(a):
            dtypes[c] = _TEXT
        else:
            dtypes[c] = pd.ArrowDtype(a)
    return dtypes


def _arrow_backed(s: pd.Series, kind: pd.ArrowDtype) -> pd.Series:
    """``s`` in the Arrow type of ``kind`` (a ``pandas.ArrowDtype``), value for value (a
    safe cast: an int64 column of one file in another's double, as DuckDB promotes
    them)."""
    import pandas as pd
    import pyarrow as pa

    arr = pa.array(s, from_pandas=True)
    return pd.Series(pd.arrays.ArrowExtensionArray(arr.cast(kind.pyarrow_dtype)),
                     index=s.index, name=s.name)


def _numpy_backed(s: pd.Series) -> pd.Series:
    """An Arrow-backed column as pandas' default conversion of it (what the readers see:
    datetime64 for a timestamp, float64 or int64 for numbers, object text)."""
    import pandas as pd
    import pyarrow as pa

    if not isinstance(s.dtype, pd.ArrowDtype):
        return s
    return pd.Series(pa.array(s, from_pandas=True).to_pandas(), index=s.index, name=s.name)


def _dask_columns(df: pd.DataFrame, dtypes: dict[str, object], path: str,
                  ids: dict[str, str]) -> pd.DataFrame:
    """One block of one input file in the dataset's columns and types (``dtypes``, from
    :func:`_check_with_duckdb`): an id the file lacks is its value in ``ids`` (from the
    file's path, :func:`_inputs`), another column it lacks is missing values, a Parquet
    ``time`` in seconds as the readers take it, numbers of :data:`NUMERIC` as float64,
    ids as the readers name them (:func:`robustloc.io.tables._ids`: stripped text,
    ``1.0`` as ``"1"``), every other column in its own type (Arrow-backed)."""
    import numpy as np
    import pandas as pd

    from robustloc.io.tables import _ids, _seconds

    # a name as DuckDB has it: a CSV header stripped (its reader's), a Parquet name as
    # written (stripped here, a Parquet column " x" was left empty: exit 0)
    df = df.rename(columns={c: str(c).strip() for c in df.columns
                            if str(c) not in dtypes and str(c).strip() in dtypes})
    for c, v in ids.items():
        if c not in df.columns:
            df[c] = pd.Series(v, index=df.index, dtype=object)
    cols = {}
    for c, k in dtypes.items():
        if c not in df.columns:
            cols[c] = pd.Series(np.nan if k == "float64" else None, index=df.index, dtype=k)
            continue
        s = df[c]
        if c in IDS:
            one = pd.DataFrame({c: _numpy_backed(s)})
            _ids(one, c, path)
            cols[c] = one[c].astype(k)
        elif k == "float64":
            s = _numpy_backed(s)
            if pd.api.types.is_datetime64_any_dtype(s) or pd.api.types.is_timedelta64_dtype(s):
                cols[c] = pd.Series(_seconds(s), index=df.index)
            elif pd.api.types.is_numeric_dtype(s):
                cols[c] = s.astype("float64")
            else:  # (numbers written as text)
                cols[c] = pd.to_numeric(s.astype(str).str.strip()).astype("float64")
        elif isinstance(k, pd.ArrowDtype):
            cols[c] = _arrow_backed(s, k)
        else:
            cols[c] = s.astype(k)
    return pd.DataFrame(cols, index=df.index)


def _auto_span(n: int, tmin: float, tmax: float, span_s: float | None, rows: int) -> float:
    if span_s is not None:
        return float(span_s)
    if tmax <= tmin:
        return 1.0
    return (tmax - tmin) * rows / n * (1 + 1e-9) or 1.0


def _output_error(exc: BaseException, out: str) -> OutputError:
    """An error of writing the partitions, against the output folder as the user named it
    (a full disk was reported against the input, or as an internal error: the no-loss
    review)."""
    text = str(exc)
    for words in ("No space left on device", "Read-only file system"):
        if words in text:
            return OutputError(f"cannot write the partitions: {words.lower()}", out,
                               errno_=28 if words.startswith("No space") else 30)
    return OutputError(f"cannot write the partitions: {text.splitlines()[0]}", out)


def _output_failed(exc: BaseException, stage: Path) -> bool:
    """A DuckDB error that is about writing the output (no space, a read-only or missing
    folder at the staging path), not about reading the input."""
    text = str(exc)
    return ("No space left" in text or "Read-only file system" in text
            or str(stage) in text)


def _out_of_memory(exc: BaseException) -> bool:
    """A DuckDB error that is its memory limit, not the input."""
    return "Out of Memory" in str(exc)


def _memory_error(exc: BaseException, memory_limit: str) -> InputError:
    """``--memory-limit`` too small for DuckDB's sort (it spills most of the work, not all
    of it): said against the option, not the input (the partition review, 2026-12-07:
    100MB on a 98 MB log of 4 million rows said "big.csv: cannot partition")."""
    return InputError(f"{memory_limit} is too small for this log (DuckDB: "
                      f"{str(exc).splitlines()[0]}); give more (e.g. --memory-limit 1GB) "
                      "or fewer --threads", "--memory-limit")


def _duckdb(files, fmt, stage: Path, by, span_s, rows_per_partition, buckets, memory_limit,
            threads, spec, out: str, hive: dict[str, dict[str, str]], progress: bool
            ) -> tuple[int, float | None, str]:
    import duckdb

    tmp = stage / ".duckdb-tmp"
    con = _connect(memory_limit, threads, tmp)
    bar = _Progress(progress)
    try:
        src, names = _source(con, files, fmt, spec, hive)
        n, tmin, tmax, longest = _stats(con, src, names, spec, files, bar)
        if by == "tag" and not buckets:
            _check_tag_folders(con, src, longest, stage, files, spec)
        if by == "time":
            _check_time_limits(tmin, tmax, files, spec)
        span = _auto_span(n, tmin, tmax, span_s, rows_per_partition) if by == "time" else None
        key, expr = _key_expr(by, buckets, tmin, span, tmax)
        raw = stage / ".unsorted"
        # Stage 1: one partitioned COPY (out of core).  The key column is written into the
        # files only when it is a contract column (tag); bins and buckets live in the path,
        # staged in a column of a name the input does not use (an input column "__key"
        # was replaced by the key: the partition review)
        kcol = _fresh_name("__key", names)
        sel = (f"SELECT *, {expr} AS {_q(kcol)} FROM {src}" if key != "tag"
               else f"SELECT * FROM {src}")
        pby = _q(kcol) if key != "tag" else "tag"
        try:
            bar.query(con, f"COPY ({sel}) TO {_sql_str(str(raw))} (FORMAT parquet, "
                      f"PARTITION_BY ({pby}), WRITE_PARTITION_COLUMNS true)", "writing")
        except duckdb.Error as exc:
            if _output_failed(exc, stage):  # the output's disk, not the input, failed
                raise _output_error(exc, out) from None
            if _out_of_memory(exc):
                raise _memory_error(exc, memory_limit) from None
            raise InputError(f"cannot partition: {str(exc).splitlines()[0]}", spec) from None
        # Stage 2: each key's files sorted into one file.
        folders = sorted(p for p in raw.iterdir() if p.is_dir())
        bar.files("sorting", len(folders))
        for d in folders:
            value = d.name.split("=", 1)[1]
            target = stage / f"{key}={value}"
            target.mkdir()
            parts = sorted(str(f) for f in d.glob("*.parquet"))
            lst = "[" + ", ".join(_sql_str(f) for f in parts) + "]"
            drop = f" EXCLUDE ({_q(kcol)})" if key != "tag" else ""
            try:  # (reads and writes the staged files only: a failure is the output's)
                con.execute(
                    f"COPY (SELECT *{drop} FROM read_parquet({lst}, hive_partitioning=false) "
                    "ORDER BY time, tag, "
                    f"anchor) TO {_sql_str(str(target / 'part-0.parquet'))} (FORMAT parquet)"
                )
            except duckdb.IOException as exc:
                raise _output_error(exc, out) from None
            except duckdb.Error as exc:
                if _out_of_memory(exc):
                    raise _memory_error(exc, memory_limit) from None
                raise
            shutil.rmtree(d)
            bar.step()
        shutil.rmtree(raw, ignore_errors=True)
        shutil.rmtree(tmp, ignore_errors=True)
    finally:
        bar.close()
        con.close()
    return n, span, key


def _pad_folders(stage: Path, staged: str, key: str, width: int) -> None:
    """Dask's ``staged=3/part.0.parquet`` renamed as the DuckDB method names them,
    ``key=000003/part-0.parquet`` (:func:`_key_expr`'s width): ``time_bin=10`` sorted
    before ``time_bin=2`` in a listing (the partition review, 2026-12-07).  ``staged``
    is the key's column while dask writes, a name the input does not use."""
    for folder in sorted(stage.glob(f"{staged}=*")):
        value = folder.name.split("=", 1)[1]
        for f in folder.glob("part.*.parquet"):
            f.rename(f.with_name("part-" + f.name[len("part."):]))
        if value.lstrip("-").isdigit():
            folder.rename(folder.with_name(f"{key}={int(value):0{width}d}"))


def _dask(files, fmt, stage: Path, by, span_s, rows_per_partition, buckets, scheduler, workers,
          spec, dtypes: dict[str, object], hive: dict[str, dict[str, str]],
          progress: bool = False) -> tuple[int, float | None, str]:
    import dask.dataframe as dd
    import numpy as np
    import pandas as pd

    from robustloc.engines.cluster import dask_client, gather_with_progress

    meta = pd.DataFrame({c: pd.Series(dtype=k) for c, k in dtypes.items()})
    with dask_client(scheduler, workers) as client:
        # each file read alone and brought to the dataset's columns and types (dask
        # takes both from the first file: _check_with_duckdb)
        parts = []
        for f in files:
            if fmt == "csv":  # every column as text, typed by _dask_columns
                # (a compressed file cannot be split into blocks: dask said so in a
                # UserWarning on stderr for every .csv.gz)
                packed = f.lower().endswith((".gz", ".bz2", ".xz", ".zst", ".zip"))
                one = dd.read_csv(f, dtype=str, keep_default_na=False, na_values=[""],
                                  blocksize=None if packed else "64MB",
                                  skipinitialspace=True)
            else:  # a task per row group, in Arrow types (pandas' default made an int64
                # column with a missing value float64); no hive key of the path (the ids
                # of a file that lacks them from hive, as the readers take them)
                one = dd.read_parquet(f, split_row_groups=True, dtype_backend="pyarrow",
                                      dataset={"partitioning": None})
            parts.append(one.map_partitions(_dask_columns, dtypes, f, hive.get(f, {}),
                                            meta=meta))
        ddf = parts[0] if len(parts) == 1 else dd.concat(parts)
        missing = [c for c in REQUIRED if c not in ddf.columns]
        if missing:
            raise InputError(f"input is missing column(s) {', '.join(missing)}", spec, 1)
        # the counts too through the engine's gathering (dask's compute, interrupted,
        # printed "Task exception was never retrieved ... AllExit": the dask review)
        n = int(gather_with_progress(client, [client.compute(ddf.shape[0])], False)[0])
        span = None
        # the key's column (or the raw tag's, by="tag") under a name the input does not
        # use: an input column "time_bin" (or "__robustloc_tag") was replaced by it
        kcol = _fresh_name("__key", list(ddf.columns))
        if by == "time":
            tmin, tmax = (float(v) for v in gather_with_progress(
                client, client.compute([ddf["time"].min(), ddf["time"].max()]), False))
            _check_time_limits(tmin, tmax, files, spec)
            span = _auto_span(n, tmin, tmax, span_s, rows_per_partition)
            key = "time_bin"
            ddf = ddf.assign(**{kcol: ((ddf["time"] - tmin) // span).astype("int64")})
        elif buckets:
            key = "tag_bucket"
            ddf = ddf.map_partitions(
                lambda df: df.assign(**{kcol: (pd.util.hash_array(
                    df["tag"].to_numpy(dtype=object)) % np.uint64(buckets)).astype("int64")}))
        else:
            key = "tag"
            # dask names each folder by the raw value: a tag holding "/" made folders in
            # folders (a traceback, a tag renamed, rows written outside -o: the Dask
            # review).  The folders get the id escaped as DuckDB's (tag=a%2Fb, which the
            # readers unescape), the files the id itself (put back below)
            kcol = "tag"
            order = list(ddf.columns)  # the input's (DuckDB's method keeps it)
            raw_tag = _fresh_name("__robustloc_tag", list(ddf.columns))
            ddf = ddf.map_partitions(lambda df: df.assign(**{
                raw_tag: df["tag"].astype(str),
                "tag": [quote(str(t), safe="") for t in df["tag"].tolist()]}))
        n_parts = max(1, min(ddf.npartitions, 1 + n // max(rows_per_partition, 1)))
        ddf = ddf.shuffle(on=kcol, npartitions=n_parts)
        ddf = ddf.map_partitions(lambda df: df.sort_values([kcol, "time", "tag", "anchor"],
                                                          kind="stable"))
        # through the engine's gathering: an interrupt cancels the tasks quietly (dask's
        # own compute printed "Task exception was never retrieved": the Dask review)
        write = ddf.to_parquet(str(stage), partition_on=[kcol], write_index=False,
                               write_metadata_file=False, compute=False)
        gather_with_progress(client, [client.compute(write)], progress)
    if key != "tag":  # the folders as DuckDB names them (zero-padded: ls sorts them)
        last = (buckets - 1) if key == "tag_bucket" else int((tmax - tmin) // span)
        _pad_folders(stage, kcol, key, max(4, len(str(last))) if key == "tag_bucket"
                     else max(6, len(str(last)) + 1))
    if key == "tag":  # the files' tag: the id itself (dask dropped the escaped one)
        import pyarrow.parquet as pq

        for f in stage.rglob("*.parquet"):
            t = pq.read_table(f)
            if raw_tag in t.column_names:
                if "tag" in t.column_names:
                    t = t.drop_columns(["tag"])
                t = t.rename_columns(["tag" if c == raw_tag else c for c in t.column_names])
                # the tag at its input place (appended, it came last: time, anchor,
                # rssi, tag where the input and DuckDB's method have time, tag, ...)
                t = t.select([c for c in order if c in t.column_names]
                             + [c for c in t.column_names if c not in order])
                pq.write_table(t, f)
    return n, span, key
