"""Partitioned Parquet datasets and the partitioning rules of the distributed engine.

A *dataset* is a directory (searched recursively), a glob, or one file.  Its files are
its *partitions*: every file whose name does not start with ``_`` or ``.`` (those are
ignored, as Spark, dask, pyarrow and DuckDB do; symbolic links are followed, a link to
nothing is refused).  Each must be Parquet -- known by its first bytes, ``PAR1``, or a
``.parquet``, ``.pq`` or ``.parq`` name, so Hive's ``000000_0`` is one -- and any other
file is refused by name, never left out (a CSV beside a Parquet file lost its rows
without a word: the dask review).  Each partition file is the unit of work
and of error reporting: a problem found in it is ``error: PARTITION_FILE:LINE: what``,
where LINE counts the file's rows as in CSV (data row ``i`` from 0 is line ``i + 2``).

Hive trees (``tag=T1/date=2026-01-01/part-0.parquet``) are understood: a key of the path
that is a contract id column (``tag``, ``anchor``) and absent from the file is added to
its rows, at its place in ``time, tag, anchor`` (dask's and DuckDB's partitioned writers
drop it from the file).  Other keys (dates, time bins, buckets) only organize the files.
A folder's name is unescaped as pyarrow and DuckDB escape it (``tag=a%2Fb`` is tag
``a/b``).  dask's ``partition_on`` does not escape, so a tree of files without their id
column is refused where its folders cannot be read back (:func:`_hive_folders`: a folder
that is not ``key=value`` below an id's, ``tag=a/b/``; :func:`_check_id_spellings`:
``tag=A`` beside ``tag=%41``); a tag ``a/b`` was read as ``a``, two walks one track.

Partitioning rules
------------------
* Snapshot methods (``locate``): every epoch ``(time, tag)`` is solved on its own, so any
  partitioning is correct as long as **an epoch's rows are never split** between two
  files.  :func:`plan_snapshot` checks it: the times of a tag in two files must not meet
  (files by time, by tag, or by tag and date all qualify).  Each
  partition must be sorted by time (the single-process streaming reader's contract).
* Filters and trackers (``filter``, ``track``): a tag's history must be processed in time
  order by one task.  :func:`plan_tagwise` groups the files that share a tag (a
  tag-partitioned dataset gives one group per file; ``tag=/date=`` trees give one group
  per tag holding its days in time order).  We chose tag partitions over time chunks with
  the filter state handed from chunk to chunk: tag partitions are independent (no task
  waits for another, no state crosses the network), the result is trivially identical to
  the single-process run, and a site has hundreds of tags to spread over the workers.
  The cost: one tag's history must fit in a worker's memory (a day of a 10 Hz tag with 8
  anchors is 7 M rows, about 0.5 GB); split longer histories by tag and date.
"""

from __future__ import annotations

import glob
import os
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from urllib.parse import unquote

import numpy as np
import pandas as pd

from robustloc._arrays import to_number
from robustloc.errors import InputError

#: Hive keys restored as columns when absent from the partition file.
HIVE_ID_COLUMNS = ("tag", "anchor")
#: Names of Parquet files (a file of another name is Parquet by its first bytes).
_PARQUET_EXT = (".parquet", ".pq", ".parq")
_PARQUET_MAGIC = b"PAR1"


@dataclass(frozen=True)
class Partition:
    """One partition file of a dataset.

    Attributes
    ----------
    path : str
        The file.
    keys : tuple of (str, str)
        Hive ``key=value`` pairs of its directories, outermost first.
    """

    path: str
    keys: tuple[tuple[str, str], ...] = ()

    def key(self, name: str) -> str | None:
        """The value of hive key ``name`` in the path, or None."""
        for k, v in self.keys:
            if k == name:
                return v
        return None


@dataclass(frozen=True)
class PartitionInfo:
    """What the planner knows of a partition (read from its metadata and tag column)."""

    part: Partition
    n_rows: int
    columns: tuple[str, ...]
    time_min: float
    time_max: float
    tags: frozenset[str] = field(default_factory=frozenset)


def _hidden(name: str) -> bool:
    return name.startswith(("_", "."))


def is_parquet_file(path: str | os.PathLike) -> bool:
    """Whether ``path`` is a Parquet file: its name ends in ``.parquet``, ``.pq`` or
    ``.parq`` (any case), or its first four bytes are Parquet's magic ``PAR1``.

    The name alone is not the test: Hive names its files ``000000_0``, and those were
    left out of a dataset without a word (the dask review).  A file with a Parquet name
    is one without its bytes being read, so that a damaged one is reported as an
    unreadable partition, not as a file of another kind.

    Raises
    ------
    InputError
        The file's first bytes cannot be read (``FILE: cannot read (REASON)``).
    """
    if str(path).lower().endswith(_PARQUET_EXT):
        return True
    try:
        with open(path, "rb") as fh:
            return fh.read(len(_PARQUET_MAGIC)) == _PARQUET_MAGIC
    except OSError as exc:
        raise InputError(f"cannot read ({exc.strerror or exc})", path) from None


def _not_parquet(path: Path, what: str, one_file: bool) -> InputError:
    """The error for a file of a Parquet dataset that is not Parquet: refused, never
    skipped (its rows were left out, exit 0: the dask review), saying what to do."""
    # (robustloc partition writes measurements only: positions are written as Parquet
    # by the command that made them, with -o DIR --engine dask)
    how = ("robustloc partition INPUT -o DATASET" if "measurements" in what
           else "the command's --engine dask writes it so")
    if one_file:
        return InputError(f"not a Parquet file: a {what} for --engine dask is Parquet "
                          f"({how}), or read this one file without --engine dask", path)
    return InputError(f"not a Parquet file, and every file of a {what} is read as a "
                      f"partition (its rows are never left out): convert the data to "
                      f"Parquet ({how}), or keep a side file under a name starting with "
                      "'_' or '.', which datasets ignore", path)


def _lacks_column(path: Path, column: str) -> bool:
    """Whether ``path`` is a Parquet file without ``column`` (so that a hive key of its
    path would be restored as that column); False for another file (its hive keys are
    never read) or one whose schema cannot be read (its reader says why)."""
    import pyarrow.parquet as pq

    try:
        if not is_parquet_file(path):
            return False
        return column not in pq.read_schema(path).names
    except Exception:  # noqa: BLE001 - unreadable: the partition's reader reports it
        return False


def _hive_folders(path: Path, base: Path | None) -> list[tuple[Path, str, str]]:
    """The hive folders of ``path`` (below ``base``): ``(folder, key, value)``, key and
    value unescaped as pyarrow and DuckDB escape them (``tag=a%2Fb`` is tag ``a/b``).

    Raises
    ------
    InputError
        A folder that is not ``key=value`` below the folder of an id key
        (:data:`HIVE_ID_COLUMNS`) when the file lacks that column: dask's
        ``to_parquet(partition_on=["tag"])`` does not escape a tag's ``/``, so tag
        ``a/b``'s rows lie in ``tag=a/b/`` and were read as tag ``a``, two walks merged
        into one track with exit 0 (the dask review).
    """
    rel = path.parent.parts if base is None else path.parent.relative_to(base).parts
    out: list[tuple[Path, str, str]] = []
    above: tuple[str, str, str] | None = None  # the innermost id key's folder, key, value
    folder = Path() if base is None else base
    for p in rel:
        folder = folder / p
        k, sep, v = p.partition("=")
        if sep and k:
            key, value = unquote(k), unquote(v)
            out.append((folder, key, value))
            if key in HIVE_ID_COLUMNS:
                above = (p, key, value)
        elif above is not None and _lacks_column(path, above[1]):
            name, key, value = above
            raise InputError(
                f"folder {p!r} below {name!r} is not key=value, and this file has no "
                f"{key} column: it would be read as {key} {value!r}, but its {key} may be "
                f"{value + '/' + p!r} (dask's to_parquet(partition_on=[{key!r}]) writes a "
                f"{key} holding '/' unescaped, as folders in folders); give the data as "
                f"files that hold the {key} column, or write the dataset with robustloc "
                "partition (it escapes the folder names)", path)
    return out


def _hive_keys(path: Path, base: Path | None) -> tuple[tuple[str, str], ...]:
    """The hive ``key=value`` pairs of ``path``'s folders below ``base``, outermost first
    (:func:`_hive_folders`, whose errors it raises)."""
    return tuple((k, v) for _, k, v in _hive_folders(path, base))


def _check_id_spellings(folders: dict[Path, list[tuple[Path, str, str]]]) -> None:
    """Refuse two folders of one id key whose names differ but unescape to one value
    (``tag=A`` and ``tag=%41``) when a file under them lacks the column.

    ``folders``: each file's :func:`_hive_folders`.  pyarrow escapes a ``%`` (tag
    ``%41`` is ``tag=%2541``); dask's ``partition_on`` does not, so ``tag=%41`` may be
    the tag ``%41``, and its rows were merged with tag ``A``'s (the dask review).  One
    spelling of a value is never refused: pyarrow's trees (``tag=a%2Fb``, tag ``a/b``)
    read as before.

    Raises
    ------
    InputError
        ``FOLDER: folders 'tag=A' and 'tag=%41' both read as tag 'A' ...``.
    """
    spellings: dict[tuple[str, str], dict[str, tuple[Path, list[Path]]]] = {}
    for f, hive in folders.items():
        for folder, key, value in hive:
            if key in HIVE_ID_COLUMNS:
                entry = spellings.setdefault((key, value), {}).setdefault(
                    folder.name, (folder, []))
                entry[1].append(f)
    for (key, value), by_name in spellings.items():
        if len(by_name) < 2:
            continue
        if not any(_lacks_column(f, key) for _, fs in by_name.values() for f in fs):
            continue  # every file holds its id: the folders' names are not read
        (a, _), (b, (folder_b, _)) = sorted(by_name.items())[:2]
        raise InputError(
            f"folders {a!r} and {b!r} both read as {key} {value!r} (a folder name is "
            f"unescaped as pyarrow escapes it, but dask's to_parquet(partition_on="
            f"[{key!r}]) does not escape, so one of them may be another {key}): "
            f"ambiguous; give the data as files that hold the {key} column, or write the "
            "dataset with robustloc partition", folder_b)


def _walk(root: Path) -> list[Path]:
    """The files under ``root``, following symbolic links to folders (each real folder
    walked once, so a link loop ends) and keeping links to nothing (for the caller to
    refuse); hidden names (:func:`_hidden`) are left out at any depth.

    ``Path.rglob`` does not follow linked folders (Python 3.11) and ``Path.is_file`` is
    False for a dangling link: both left partitions out without a word.
    """
    out: list[Path] = []
    seen: set[tuple[int, int]] = set()
    for top, dirs, names in os.walk(root, followlinks=True):
        st = os.stat(top)
        if (st.st_dev, st.st_ino) in seen:
            dirs[:] = []
            continue
        seen.add((st.st_dev, st.st_ino))
        dirs[:] = sorted(d for d in dirs if not _hidden(d))
        out += [f for f in (Path(top, n) for n in names if not _hidden(n))
                if f.is_file() or not f.exists()]
    return out


def discover(spec: str | os.PathLike, *, parquet: bool = True, what: str = "dataset",
             absolute: bool = False) -> list[Partition]:
    """The partition files of a dataset: a directory, a glob, or one file.

    Parameters
    ----------
    spec : str or PathLike
        Directory (searched recursively), glob (``**`` allowed) or file.
    parquet : bool
        Every file must be Parquet (default: :func:`is_parquet_file`; any other
        non-hidden file is refused, never left out); False keeps every regular file
        (RINEX inputs, ``partition``'s CSV).
    what : str
        Word for messages.
    absolute : bool
        Give each partition's path as an absolute path (``os.path.abspath``, symbolic
        links kept): what a task on a worker needs, since a worker resolves a relative
        path in its own working directory (a ``--scheduler`` cluster's workers started
        elsewhere read other files, or none).

    Returns
    -------
    list of Partition
        Sorted by path (natural order of zero-padded part numbers).

    Raises
    ------
    InputError
        Nothing matches, no partition file is found, a link leads nowhere, or (with
        ``parquet``) a file is not Parquet -- naming the file.
    """
    s = str(spec)
    p = Path(s)
    base: Path | None = None
    if p.is_dir():
        base = p
        files = _walk(p)
    elif p.is_file():
        files = [p]
    elif p.is_symlink() and not glob.has_magic(s):
        raise InputError("broken link", s)
    elif glob.has_magic(s):
        files = []
        for m in sorted(glob.glob(s, recursive=True)):
            mp = Path(m)
            if mp.is_dir():
                files += _walk(mp)
            elif not _hidden(mp.name):
                files.append(mp)
    else:
        raise InputError(f"{what} not found (expected a directory, a glob or a file)", s)
    for f in files:
        if not f.exists():  # a symbolic link to nothing: refused, never left out
            raise InputError("broken link", f)
    if parquet:
        for f in sorted(files):
            if not is_parquet_file(f):  # refused by name, never skipped (the dask review)
                raise _not_parquet(f, what, base is None and len(files) == 1)
    if not files:
        kind = "Parquet files" if parquet else "files"
        raise InputError(f"no {kind} in this {what}", s)
    folders = {f: _hive_folders(f, base) for f in sorted(set(files))}
    _check_id_spellings(folders)
    return [Partition(os.path.abspath(f) if absolute else str(f),
                      tuple((k, v) for _, k, v in hive)) for f, hive in folders.items()]


def _parquet_file(part: Partition):
    import pyarrow.parquet as pq

    try:
        # no pre-buffering: its read cache grows with every row group read
        # (robustloc.io.tables._iter_raw)
        return pq.ParquetFile(part.path, pre_buffer=False)
    except Exception as exc:  # noqa: BLE001 - any pyarrow failure is a bad partition
        raise InputError(f"cannot read Parquet partition: {exc}", part.path) from None


@contextmanager
def _reading(part: Partition) -> Iterator[None]:
    """Any failure of pyarrow reading ``part``'s data in the block (a corrupt page:
    ``ArrowInvalid: Index not in dictionary bounds``, a ``ValueError`` that a task
    returned as a plain one, or an ``OSError`` it raised) as the partition's
    :class:`InputError`, ``cannot read Parquet partition: ...``; an InputError passes.

    Raises
    ------
    InputError
        Naming the partition file.
    """
    try:
        yield
    except InputError:
        raise
    except Exception as exc:  # noqa: BLE001 - any pyarrow failure is a bad partition
        raise InputError(f"cannot read Parquet partition: {exc}", part.path) from None


#: The measurements contract's leading columns, in order (docs/formats.md).
_CONTRACT_ORDER = ("time", "tag", "anchor")


def _key_position(columns: list[str], key: str) -> int:
    """Where a restored hive key ``key`` goes among ``columns``: after the contract
    columns that precede it (``time, tag, anchor``), so that the rows have the columns
    of the single-process reader's input (appended last, ``filter`` and ``partition
    --method dask`` wrote ``time, anchor, rssi, tag``)."""
    before = _CONTRACT_ORDER[:_CONTRACT_ORDER.index(key)]
    at = [i for i, c in enumerate(columns) if str(c).strip() in before]
    return max(at) + 1 if at else 0


def missing_hive_columns(part: Partition, columns: tuple[str, ...] | list[str]) -> list[str]:
    """Hive id keys of ``part``'s path that its file lacks (to be added to its rows)."""
    return [k for k, _ in part.keys if k in HIVE_ID_COLUMNS and k not in columns]


def inspect(part: Partition, need: tuple[str, ...] = ("time", "tag"),
            tags: bool = True) -> PartitionInfo:
    """Row count, columns, time range (from the Parquet statistics) and tags of ``part``.

    Raises
    ------
    InputError
        Unreadable file (or a corrupt page of a column read), or a column of ``need``
        missing (neither in the file nor a hive key of its path) -- naming the partition
        file.
    """
    pf = _parquet_file(part)
    cols = tuple(pf.schema_arrow.names)
    have = set(cols) | {k for k, _ in part.keys if k in HIVE_ID_COLUMNS}
    missing = [c for c in need if c not in have]
    if missing:
        raise InputError(
            f"partition is missing column(s) {', '.join(missing)} (has: {', '.join(cols)})",
            part.path, 1,
        )
    if "time" in cols:
        _check_time_type(pf.schema_arrow.field("time").type, part.path)
    n = pf.metadata.num_rows
    tmin, tmax = np.inf, -np.inf
    if "time" in cols and n:
        rng = _time_range_from_statistics(pf)
        if rng is None:
            lo, hi = np.inf, -np.inf
            with _reading(part):  # a corrupt page is the partition's error
                for b in pf.iter_batches(batch_size=_PLAN_BATCH_ROWS, columns=["time"]):
                    try:
                        v = _time_seconds(b.column(0))
                    except Exception:  # noqa: BLE001 - no numbers: the reader names the line
                        lo, hi = -np.inf, np.inf
                        break
                    if v.size:
                        lo, hi = min(lo, float(v.min())), max(hi, float(v.max()))
            rng = lo, hi
        tmin, tmax = rng
    tagset: frozenset[str] = frozenset()
    if tags and n:
        hive_tag = part.key("tag")
        if "tag" not in cols and hive_tag is not None:
            tagset = frozenset([hive_tag])
        elif "tag" in cols:
            # batch by batch: the whole column of a 100 M-row partition is ~1.4 GiB of
            # strings, which paused a 2 GiB worker (memory bounded by one batch now)
            seen: set[object] = set()
            with _reading(part):  # (a corrupt page crashed track and filter --engine
                # dask with a traceback: pyarrow's ArrowInvalid is a plain ValueError)
                for b in pf.iter_batches(batch_size=_PLAN_BATCH_ROWS, columns=["tag"]):
                    seen.update(b.column(0).unique().to_pylist())
            tagset = frozenset(_id_text(v) for v in seen if v is not None)
    return PartitionInfo(part, n, cols, tmin, tmax, tagset)


def _check_time_type(t: object, path: str) -> None:
    """Refuse a ``time`` column the readers cannot turn into seconds: dates (an ``inf``
    that DuckDB sniffed as an infinite date, in a dataset written by an older ``robustloc
    partition``), times of day, booleans, nested values.  Numbers, numbers as text,
    timestamps and durations pass (the reader converts them, and names a bad row).

    Raises
    ------
    InputError
        ``PARTITION:1: column 'time' holds TYPE values, expected numbers (seconds)``.
    """
    import pyarrow as pa

    if isinstance(t, pa.DictionaryType):
        t = t.value_type
    ok = (pa.types.is_integer(t) or pa.types.is_floating(t) or pa.types.is_decimal(t)
          or pa.types.is_timestamp(t) or pa.types.is_duration(t) or pa.types.is_string(t)
          or pa.types.is_large_string(t) or pa.types.is_null(t))
    if not ok:
        raise InputError(f"column 'time' holds {t} values, expected numbers (seconds); "
                         "repartition the input", path, 1)


#: Rows per batch when the planner reads a partition's columns (bounded memory).
_PLAN_BATCH_ROWS = 1 << 20


def _time_values(col: object) -> np.ndarray:
    """A ``time`` column batch in seconds, row for row (NaN where there is no number):
    a timestamp as seconds since the Unix epoch, a duration as seconds, text as the
    number it spells."""
    from robustloc.io.tables import _seconds

    s = col.to_pandas()
    if pd.api.types.is_datetime64_any_dtype(s) or pd.api.types.is_timedelta64_dtype(s):
        return np.asarray(_seconds(s), dtype=float)
    if pd.api.types.is_numeric_dtype(s) and not pd.api.types.is_bool_dtype(s):
        return s.to_numpy(dtype=float, na_value=np.nan)
    return to_number(s).to_numpy(dtype=float, na_value=np.nan)


def _time_seconds(col: object) -> np.ndarray:
    """The finite times of a ``time`` column batch in seconds, as the readers convert them
    (:func:`robustloc.io.tables._numeric`: a timestamp as seconds since the Unix epoch, a
    duration as seconds, text as the number it spells; what is no number is left to the
    reader, which names its line)."""
    v = _time_values(col)
    return v[np.isfinite(v)]


def _time_range_from_statistics(pf: object) -> tuple[float, float] | None:
    """(min, max) of a numeric ``time`` column from the row groups' statistics (no data
    read), or None when a row group has none -- or when the column is not numbers: the
    statistics of text order it as text ("10" < "9") and those of a timestamp are dates,
    so a split epoch passed the overlap check (text) or every partition overlapped
    (timestamps); those are read (:func:`_time_seconds`)."""
    import pyarrow as pa

    t = pf.schema_arrow.field("time").type if "time" in pf.schema_arrow.names else None
    if isinstance(t, pa.DictionaryType):
        t = t.value_type
    if t is None or not (pa.types.is_integer(t) or pa.types.is_floating(t)
                         or pa.types.is_decimal(t)):
        return None
    md = pf.metadata
    j = next((k for k in range(md.num_columns) if md.schema.column(k).path == "time"), None)
    if j is None or md.num_row_groups == 0:
        return None
    lo, hi = np.inf, -np.inf
    for i in range(md.num_row_groups):
        st = md.row_group(i).column(j).statistics
        if st is None or not st.has_min_max or md.row_group(i).column(j).statistics.null_count:
            return None
        try:
            lo, hi = min(lo, float(st.min)), max(hi, float(st.max))
        except Exception:  # noqa: BLE001 - not numbers (an infinite date overflows)
            return None
    if not (np.isfinite(lo) and np.isfinite(hi)):
        return None
    return lo, hi


def overlapping(infos: list[PartitionInfo]) -> list[PartitionInfo]:
    """The partitions whose time range meets another's (only those can split an epoch,
    so only their tags need reading)."""
    use = sorted((i for i in infos if i.n_rows), key=lambda i: (i.time_min, i.part.path))
    out = []
    run_max = -np.inf
    for k, info in enumerate(use):
        before = k > 0 and info.time_min <= run_max
        after = k + 1 < len(use) and info.time_max >= use[k + 1].time_min
        if before or after:
            out.append(info)
        run_max = max(run_max, info.time_max)
    return out


def _id_text(v: object) -> str:
    """An id as the readers spell it (an integral float 3.0 is the id "3")."""
    if isinstance(v, float) and v.is_integer():
        return str(int(v))
    return str(v).strip()


def read_partition(part: Partition, columns: list[str] | None = None) -> pd.DataFrame:
    """A partition's rows, hive id keys added, index = CSV-equivalent line numbers.

    ``frame.attrs["path"]`` is the partition file, so the contract validators
    (:func:`robustloc.io.tables.validate_measurements` ...) name it in their errors.
    """
    pf = _parquet_file(part)
    try:
        df = pf.read(columns=columns).to_pandas()
    except Exception as exc:  # noqa: BLE001
        raise InputError(f"cannot read Parquet partition: {exc}", part.path) from None
    return _as_frame(part, df)


def read_first_epochs(part: Partition, n_epochs: int,
                      batch_rows: int = 1 << 16,
                      until: float | None = None) -> pd.DataFrame:
    """The rows of ``part``'s first ``n_epochs`` epochs by time, or more, as
    :func:`read_partition` gives them (a prefix of its rows, same lines).

    A time-sorted partition (as ``robustloc partition`` writes) is streamed in batches
    of ``batch_rows`` and read until the rows before the latest time seen hold
    ``n_epochs`` epochs (``(time, tag)`` pairs): those rows, all epochs earlier than any
    left unread.  With ``until``, it is also read only until a batch passes that time:
    then only its rows at or before ``until`` (every epoch at that time whole: one with a
    smaller tag than the caller's epoch at ``until`` comes before it).  A partition whose
    times go back (or are not comparable numbers) is read whole: its first epochs by
    time cannot be known before.  (``track --link-offsets auto``'s sample read every
    file whole in the client: 680 MB for a tag of 3 M rows, where the workers' streamed
    run took 165 MB.)

    Parameters
    ----------
    part : Partition
        The partition file.
    n_epochs : int
        The epochs wanted from its start.
    batch_rows : int, optional
        Rows read at a time.
    until : float, optional
        A time in seconds, as the readers convert the ``time`` column: the rows after it
        are not wanted (``track --engine dask``'s sample, once it holds its epochs, needs
        from the next files only the epochs before its last; the dask review).

    Returns
    -------
    DataFrame
        A prefix of :func:`read_partition`'s rows holding the first ``n_epochs`` epochs
        (all of them when fewer), or every row at or before ``until``, whichever stops
        first; every row of a partition not sorted by time.
    """
    import pyarrow as pa

    pf = _parquet_file(part)
    batches: list[pa.RecordBatch] = []
    # the rows read so far are a prefix of times ``< last`` (complete: every later row has
    # time >= last), ``done_rows`` of them holding ``done_epochs`` (time, tag) pairs, and
    # the rows at ``last`` (``pending``: their epochs may go on in the next batch).  Each
    # batch adds the pairs of its own complete rows, whose times all lie at or after the
    # earlier ``last``: no pair is counted twice, and no batch looks at the earlier ones
    # again (the whole prefix was concatenated and deduplicated at every batch).
    done_rows = done_epochs = read_rows = 0
    pending = pd.DataFrame({"time": [], "tag": []})
    last = None
    with _reading(part):
        cols = pf.schema_arrow.names
        has_tag = "tag" in cols
        for b in pf.iter_batches(batch_size=batch_rows):
            if b.num_rows == 0:
                continue
            time = b.column(cols.index("time")).to_numpy(zero_copy_only=False)
            if time.dtype.kind not in "iufM" or (
                    (last is not None and time[0] < last) or not np.all(time[1:] >= time[:-1])):
                return read_partition(part)  # not sorted by time (or NaN): read it whole
            last = time[-1]
            batches.append(b)
            read_rows += b.num_rows
            if until is not None:
                # in the readers' seconds (a timestamp column's are dates), still sorted
                sec = _time_values(b.column(cols.index("time")))
                if sec[-1] > until:  # every row at or before ``until`` is read
                    keep = read_rows - b.num_rows + int(np.searchsorted(sec, until, "right"))
                    df = pa.Table.from_batches(batches).slice(0, keep).to_pandas()
                    return _as_frame(part, df)
            rows = pd.DataFrame({
                "time": time, "tag": b.column(cols.index("tag")).to_numpy(
                    zero_copy_only=False) if has_tag else ""})
            new = rows if pending.empty else pd.concat([pending, rows], ignore_index=True)
            complete = (new["time"] < last).to_numpy()
            done_rows += int(complete.sum())
            done_epochs += len(new[complete].drop_duplicates())
            pending = new[~complete]
            if done_epochs >= n_epochs:
                df = pa.Table.from_batches(batches).slice(0, done_rows).to_pandas()
                return _as_frame(part, df)
        df = (pa.Table.from_batches(batches) if batches
              else pf.schema_arrow.empty_table()).to_pandas()
    return _as_frame(part, df)


def _as_frame(part: Partition, df: pd.DataFrame) -> pd.DataFrame:
    """``df`` read from ``part`` as :func:`read_partition` gives it."""
    for k in missing_hive_columns(part, list(df.columns)):
        df.insert(_key_position(list(df.columns), k), k, part.key(k))
    df.columns = [str(c).strip() for c in df.columns]
    df.index = pd.RangeIndex(2, 2 + len(df), name="line")
    df.attrs["path"] = part.path
    return df


def count_epochs(part: Partition) -> int | None:
    """A quick count of the epochs of ``part``: the runs of equal ``(time, tag)`` in its
    row order (no validation, O(rows)); None when the columns cannot be read as such.

    Exact when each epoch's rows are contiguous (``robustloc partition`` sorts by time,
    tag, anchor; logs written epoch by epoch); an overcount otherwise, which the caller
    detects against the validating reader's count.
    """
    import pyarrow as pa
    import pyarrow.compute as pc
    import pyarrow.parquet as pq

    try:
        schema = pq.read_schema(part.path)
        has_tag = "tag" in schema.names
        dict_tag = has_tag and pa.types.is_string(schema.field("tag").type)
        pf = pq.ParquetFile(part.path, pre_buffer=False,
                            read_dictionary=["tag"] if dict_tag else None)
        runs = 0
        last: tuple[float, object] | None = None  # the previous batch's last (time, tag)
        # batch by batch (bounded memory), the run boundary carried across batches
        for b in pf.iter_batches(batch_size=_PLAN_BATCH_ROWS,
                                 columns=["time"] + (["tag"] if has_tag else [])):
            if b.num_rows == 0:
                continue
            time = np.asarray(b.column(0).to_numpy(zero_copy_only=False), dtype=float)
            change = time[1:] != time[:-1]
            first_tag: object = None
            last_tag: object = None
            if has_tag:  # without it: a hive tree's one tag
                tag = b.column(1)
                if not pa.types.is_dictionary(tag.type):
                    tag = pc.dictionary_encode(tag)
                idx = tag.indices.to_numpy(zero_copy_only=False)
                change |= idx[1:] != idx[:-1]
                first_tag, last_tag = tag[0].as_py(), tag[-1].as_py()
            runs += 1 + int(np.count_nonzero(change))
            if last is not None and last == (float(time[0]), first_tag):
                runs -= 1  # the batch continues the previous batch's epoch
            last = (float(time[-1]), last_tag)
        return runs
    except Exception:  # noqa: BLE001 - the reader reports the problem with its line
        return None


def materialize(part: Partition, directory: str | os.PathLike) -> str:
    """The path of a file with ``part``'s rows and its hive id keys as columns.

    ``part.path`` itself when nothing is missing; otherwise a copy under ``directory``
    written row group by row group (bounded memory), for a per-file reader.
    """
    import pyarrow as pa
    import pyarrow.parquet as pq

    pf = _parquet_file(part)
    add = missing_hive_columns(part, pf.schema_arrow.names)
    if not add:
        return part.path
    out = Path(directory) / f"{abs(hash(part.path)):x}-{Path(part.path).name}"
    writer = None
    try:
        for i in range(pf.num_row_groups):
            with _reading(part):
                t = pf.read_row_group(i)
            for k in add:
                t = t.add_column(_key_position(t.column_names, k), k,
                                 pa.array([part.key(k)] * t.num_rows, pa.string()))
            if writer is None:
                writer = pq.ParquetWriter(out, t.schema)
            writer.write_table(t)
        if writer is None:  # no row groups: an empty file with the columns
            schema = pf.schema_arrow
            for k in add:
                schema = schema.insert(_key_position(schema.names, k),
                                       pa.field(k, pa.string()))
            pq.write_table(schema.empty_table(), out)
    finally:
        if writer is not None:
            writer.close()
    return str(out)


def plan_snapshot(infos: list[PartitionInfo]) -> list[PartitionInfo]:
    """Order partitions for snapshot methods and check that no epoch is split.

    Returns the non-empty partitions sorted by (first time, path).  Two partitions that
    hold the same tag must not overlap in that tag's time (its last time in one < its
    first time in the next), or an epoch ``(time, tag)`` could have rows in both.  The
    partitions' time ranges (:class:`PartitionInfo`) decide alone when they do not meet;
    when they do, the tag's own times in each are read (:func:`_tag_time_ranges`), and
    the message quotes those.

    Raises
    ------
    InputError
        Naming the second partition, the first one and the tag.
    """
    use = sorted((i for i in infos if i.n_rows), key=lambda i: (i.time_min, i.part.path))
    by_tag: dict[str, list[PartitionInfo]] = {}
    for info in use:
        for t in info.tags:
            by_tag.setdefault(t, []).append(info)
    ranges: dict[str, dict[str, tuple[float, float]] | None] = {}  # per partition, read once
    for tag, lst in by_tag.items():
        if not any(b.time_min <= a.time_max for a, b in zip(lst, lst[1:])):  # by time_min
            continue
        # the partitions' time ranges meet: compare the tag's own times in each (the
        # message quoted the partitions' ranges, which the tag need not span)
        own = []
        for info in lst:
            if info.part.path not in ranges:
                ranges[info.part.path] = _tag_time_ranges(info.part)
            per = ranges[info.part.path]
            lo, hi = (info.time_min, info.time_max) if per is None else per.get(
                tag, (info.time_min, info.time_max))
            own.append((lo, hi, info))
        own.sort(key=lambda r: (r[0], r[2].part.path))
        a_lo, a_hi, a = own[0]
        for b_lo, b_hi, b in own[1:]:
            if b_lo <= a_hi:
                raise InputError(
                    f"tag {tag!r} has rows in times [{b_lo}, {b_hi}] here and in "
                    f"[{a_lo}, {a_hi}] in {a.part.path}: an epoch's rows could be "
                    "split between partitions (repartition: robustloc partition INPUT -o "
                    "DATASET --by time)",
                    b.part.path, _overlap_line(b.part, tag, a_lo, a_hi),
                )
            if b_hi > a_hi:
                a_lo, a_hi, a = b_lo, b_hi, b
    return use


def _tag_time_batches(part: Partition):  # noqa: ANN202 - a generator of arrays
    """``(first row, times, tags)`` of ``part``, batch by batch (times in seconds as the
    readers convert them, tags as their text, ``ok`` rows only: a finite time and a
    tag); None when the file has no time or no tag."""
    pf = _parquet_file(part)
    names = pf.schema_arrow.names
    if "time" not in names:
        return None
    hive_tag = part.key("tag")
    if "tag" not in names and hive_tag is None:
        return None
    cols = ["time"] + (["tag"] if "tag" in names else [])

    def batches():  # noqa: ANN202
        first = 0
        for b in pf.iter_batches(batch_size=_PLAN_BATCH_ROWS, columns=cols):
            t = _time_values(b.column(0))
            if "tag" in names:
                tags = pd.Series(b.column(1).to_pylist(), dtype=object)
            else:
                tags = pd.Series([hive_tag] * len(t), dtype=object)
            ok = np.isfinite(t) & tags.notna().to_numpy()
            rows = first + np.flatnonzero(ok)
            first += len(t)
            if ok.any():
                yield rows, t[ok], tags[ok].map(_id_text).to_numpy()

    return batches()


def _overlap_line(part: Partition, tag: str, lo: float, hi: float) -> int | None:
    """The line (as the readers number a Parquet file's rows: the first is line 2) of
    the first row of ``tag`` in ``part`` whose time lies in ``[lo, hi]``; None when the
    file cannot be read so."""
    try:
        batches = _tag_time_batches(part)
        for rows, t, tags in batches or ():
            hit = np.flatnonzero((tags == tag) & (t >= lo) & (t <= hi))
            if hit.size:
                return int(rows[hit[0]]) + 2
    except Exception:  # noqa: BLE001 - unreadable here: the message names the file only
        return None
    return None


def _tag_time_ranges(part: Partition) -> dict[str, tuple[float, float]] | None:
    """Each tag's (first, last) time in ``part`` (in seconds, as the readers convert
    them; read batch by batch), or None when the file cannot be read so (the caller then
    uses the partition's range)."""
    try:
        batches = _tag_time_batches(part)
        if batches is None:
            return None
        out: dict[str, tuple[float, float]] = {}
        for _, t, tags in batches:
            g = pd.DataFrame({"t": t, "tag": tags}).groupby("tag")["t"].agg(["min", "max"])
            for tag, lo, hi in zip(g.index, g["min"], g["max"]):
                old = out.get(tag)
                out[tag] = ((float(lo), float(hi)) if old is None
                            else (min(old[0], float(lo)), max(old[1], float(hi))))
        return out
    except Exception:  # noqa: BLE001 - unreadable here: the partition's range is used
        return None


def plan_tagwise(infos: list[PartitionInfo]) -> list[list[PartitionInfo]]:
    """Group partitions so that each tag's whole history is in exactly one group.

    Files sharing a tag are joined (union-find over tags); each group's files are ordered
    by (first time, path), so a tag's rows come in time order when concatenated.  Groups
    are ordered by their smallest tag.  A dataset partitioned by tag gives one group per
    file; a dataset partitioned by time only gives one group (correct, but serial: the
    caller warns and suggests ``robustloc partition --by tag``).
    """
    use = [i for i in infos if i.n_rows]
    parent = list(range(len(use)))

    def find(i: int) -> int:
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i

    first: dict[str, int] = {}
    for i, info in enumerate(use):
        for t in info.tags:
            if t in first:
                ra, rb = find(first[t]), find(i)
                if ra != rb:
                    parent[rb] = ra
            else:
                first[t] = i
    groups: dict[int, list[PartitionInfo]] = {}
    for i, info in enumerate(use):
        groups.setdefault(find(i), []).append(info)
    out = [sorted(g, key=lambda i: (i.time_min, i.part.path)) for g in groups.values()]
    out.sort(key=lambda g: min((t for i in g for t in i.tags), default=""))
    return out
