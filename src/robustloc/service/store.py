"""Durable store of the service: accepted measurement rows and computed positions.

Design: an append-only **write-ahead log of Arrow IPC frames**, sealed into **Parquet
segments**.

* ``append`` writes one frame (magic, length, CRC-32, an Arrow IPC stream of the batch) to
  the active log file and ``fdatasync``s it before returning, so the caller (the HTTP
  handler) answers ``202`` only for rows that are on disk.  One sync per request (group
  commit): at 8 000 rows per request the sync cost is shared by all its rows.
* When the active log holds ``seal_rows`` rows it is closed and a new one started; a
  background thread writes the closed log's rows as a Parquet segment (``.tmp``, fsync,
  atomic rename, directory fsync) and only then deletes the log file.
* The positions log is written the same way without the per-append sync (positions are
  recomputed from the measurements after a crash; see :mod:`robustloc.service.engine`).
  Its sealed Parquet segments are synced like the measurements'.
* On open, Parquet segments are read as they are, and every log file without a segment is
  replayed frame by frame; a torn or corrupt tail (a crash mid-write) ends the replay and is
  truncated, with a warning on stderr (those rows were never acknowledged: the sync had not
  returned).  A bad frame followed by an intact one (found by the frame magic) is damage,
  not a torn tail: the open is refused naming the file and the offsets
  (:class:`StoreError`), as for a damaged Parquet segment, rather than the acknowledged
  frames after it being cut off.
* One writer per folder: a :class:`SegmentLog` holds an exclusive ``flock`` on its folder's
  ``.lock`` file while it is open (opening seals every log file it finds, which would take
  the active log of another writer); a second opener gets :class:`StoreInUse`.
  ``robustloc serve`` also locks the whole store (:class:`StoreLock` on ``DIR/.lock``).
* A failed append (disk full, I/O error) leaves the log file as it was: the log is written
  unbuffered, and on any ``OSError`` it is truncated back to its length before the append
  and :class:`StoreWriteError` is raised; nothing of the refused rows is kept (in memory
  or on disk), so a caller that answers an error has stored nothing.

Why not DuckDB or SQLite: both were considered.  The write path here is the hot path
(80 000 rows/s target) and needs exactly one primitive - "append a batch and make it
durable" - which a framed log does with one ``write`` + ``fdatasync`` and no row-by-row
conversion; queries (positions by tag and time) are served from Parquet with predicate
push-down by pyarrow, and the files are readable by any Arrow/Parquet tool
(``robustloc locate`` reads a sealed segment directly).  See benchmarks/bench_serve.py for
the measured ingest rate.
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import io
import os
import struct
import sys
import threading
import zlib
from pathlib import Path

import pyarrow as pa
import pyarrow.acero as acero
import pyarrow.compute as pc
import pyarrow.dataset as ds
import pyarrow.parquet as pq

_MAGIC = b"RLW1"
_HEADER = struct.Struct("<4sII")  # magic, payload length, crc32


class StoreError(OSError):
    """A store that cannot be used: in use by another writer, damaged, or not writable.

    Parameters
    ----------
    message : str
        What is wrong, in words a user understands.
    path : path, optional
        The store file or folder concerned.
    """

    def __init__(self, message: str, path: str | os.PathLike | None = None) -> None:
        super().__init__(message)
        self.message = message
        self.path = None if path is None else str(path)

    def __str__(self) -> str:
        return self.message if self.path is None else f"{self.path}: {self.message}"


class StoreInUse(StoreError):
    """The store (folder) is locked by another open :class:`SegmentLog` or server."""


class StoreWriteError(StoreError):
    """An append failed (disk full, I/O error); the log file is as it was before it.

    ``insufficient_space`` is True for ``ENOSPC``, ``EDQUOT`` and ``EFBIG`` (a file size
    limit): the storage is full rather than broken.
    """

    def __init__(self, message: str, path: str | os.PathLike | None = None,
                 errno_: int | None = None) -> None:
        super().__init__(message, path)
        self.errno = errno_
        self.insufficient_space = errno_ in (errno.ENOSPC, errno.EDQUOT, errno.EFBIG)


class StoreLock:
    """An exclusive, non-blocking ``flock`` on ``DIRECTORY/.lock`` (held until released).

    The lock file holds the holder's pid (for the message of a refused opener).  The
    operating system releases the lock when the holder exits, even after ``kill -9``: a
    stale lock file never blocks a restart.

    Parameters
    ----------
    directory : path
        The folder to lock (created if missing).
    what : str
        How the holder is named in the refusal ("store in use by another WHAT").

    Raises
    ------
    StoreInUse
        The lock is held by another process (or another open lock in this process).
    """

    def __init__(self, directory: str | os.PathLike, what: str = "writer") -> None:
        self._fd: int | None = None
        self.dir = Path(directory)
        self.dir.mkdir(parents=True, exist_ok=True)
        self.path = self.dir / ".lock"
        fd = os.open(self.path, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            try:
                holder = os.pread(fd, 32, 0).decode(errors="replace").strip()
            except OSError:
                holder = ""
            os.close(fd)
            pid = f"pid {holder}" if holder.isdigit() else "pid unknown"
            raise StoreInUse(f"store in use by another {what} ({pid}); stop it first, or "
                             "give another folder", self.dir) from None
        except BaseException:
            os.close(fd)
            raise
        with contextlib.suppress(OSError):  # the pid is informative only
            os.ftruncate(fd, 0)
            os.pwrite(fd, f"{os.getpid()}\n".encode(), 0)
        self._fd = fd

    @property
    def held(self) -> bool:
        """True until :meth:`release`."""
        return self._fd is not None

    def release(self) -> None:
        """Release the lock (idempotent).  The lock file stays: deleting it would let a
        second opener lock a new file while a third still waits on the old one."""
        fd, self._fd = self._fd, None
        if fd is not None:
            os.close(fd)  # closing the only descriptor releases the flock

    def __enter__(self) -> StoreLock:
        return self

    def __exit__(self, *exc: object) -> None:
        self.release()

    def __del__(self) -> None:
        self.release()


def _write_all(fd: int, data: bytes) -> None:
    """``os.write`` until all of ``data`` is written (a short write is not an error)."""
    view = memoryview(data)
    while view:
        n = os.write(fd, view)
        view = view[n:]


def _fsync_dir(path: Path) -> None:
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def _background_priority() -> None:
    """Lower the calling thread's CPU priority (Linux, where nice is per thread): sealing
    a segment is background work, and on a busy machine it must not take the CPU from the
    threads that acknowledge rows and publish positions (it spread a ~0.5 s burst over the
    latency tail).  Elsewhere a no-op."""
    if sys.platform.startswith("linux"):
        with contextlib.suppress(OSError, AttributeError):
            os.setpriority(os.PRIO_PROCESS, threading.get_native_id(), 10)


def _encode(batch: pa.RecordBatch | pa.Table) -> bytes:
    sink = io.BytesIO()
    with pa.ipc.new_stream(sink, batch.schema) as w:
        w.write(batch)
    payload = sink.getvalue()
    return _HEADER.pack(_MAGIC, len(payload), zlib.crc32(payload)) + payload


def _frame_at(data: bytes, pos: int) -> tuple[pa.Table, int] | None:
    """The table of the frame starting at byte ``pos`` of ``data`` and the frame's end, or
    None when no whole, intact frame starts there."""
    if pos + _HEADER.size > len(data):
        return None
    magic, length, crc = _HEADER.unpack_from(data, pos)
    end = pos + _HEADER.size + length
    if magic != _MAGIC or end > len(data):
        return None
    payload = data[pos + _HEADER.size : end]
    if zlib.crc32(payload) != crc:
        return None
    try:
        return pa.ipc.open_stream(payload).read_all(), end
    except pa.ArrowException:
        return None


def _read_log(path: Path) -> tuple[list[pa.Table], int, int | None]:
    """The frames of a log file before its first bad one, the byte length of that valid
    prefix, and the offset of the first intact frame after the bad one (None: nothing
    intact follows, the bad bytes are a torn tail).

    The bytes after a bad frame are searched for the frame magic: an append crashed
    mid-write leaves only a prefix of its own frame, so an intact frame after a bad one
    means the file was damaged in the middle, and the frames after it were acknowledged
    (cutting the file at the first bad frame silently deleted them: the serve review).
    """
    data = path.read_bytes()
    out: list[pa.Table] = []
    pos = 0
    while (frame := _frame_at(data, pos)) is not None:
        out.append(frame[0])
        pos = frame[1]
    # the bad frame's own bytes are not searched when its header is whole and its payload
    # ends inside the file (a wrong checksum: the damage is in it), and a frame found
    # after the bad one counts only when the frames from it run to the end of the file
    # (the last one may be torn).  A payload holds the rows' text: a tag id shaped as a
    # frame, inside a frame torn by a crash mid-append, was taken for acknowledged frames
    # after damage, and the store refused to start (the review of the fix); a real
    # damage's later frames run to the end, whatever the bad frame's header says
    at = pos
    if pos + _HEADER.size <= len(data):
        magic, length, _ = _HEADER.unpack_from(data, pos)
        if magic == _MAGIC and pos + _HEADER.size + length <= len(data):
            at = pos + _HEADER.size + length - 1
    while (at := data.find(_MAGIC, at + 1)) >= 0:
        if _frames_to_end(data, at):
            return out, pos, at
    return out, pos, None


def _frames_to_end(data: bytes, pos: int) -> bool:
    """Whether whole frames run from byte ``pos`` to the end of ``data``, but for a torn
    last one (a prefix of a frame: its header cut, or its payload ending past the end) or
    a zero-filled tail (space allocated, never written)."""
    if _frame_at(data, pos) is None:
        return False
    while (frame := _frame_at(data, pos)) is not None:
        pos = frame[1]
    rest = len(data) - pos
    if rest == 0 or rest < _HEADER.size or not data[pos:].strip(b"\0"):
        return True
    magic, length, _ = _HEADER.unpack_from(data, pos)
    return magic == _MAGIC and pos + _HEADER.size + length > len(data)


class SegmentLog:
    """One durable append-only table (a folder of ``*.parquet`` segments and ``*.wal`` logs).

    Parameters
    ----------
    directory : path
        Created if missing.
    seal_rows : int
        Rows per log before it is sealed into a Parquet segment.
    fsync : bool
        Sync every append (default True; False only for throw-away stores in tests, and
        the positions log).
    refuse_damage : bool
        A log damaged before intact frames is refused at open (default True: its rows
        were acknowledged).  False for a log whose rows are recomputed after a crash (the
        positions): it is cut at the damage, with a warning, as a torn tail is -- a power
        cut can lose any unsynced page of it, and that must not stop the service.
    """

    def __init__(self, directory: str | os.PathLike, seal_rows: int = 1_000_000,
                 fsync: bool = True, refuse_damage: bool = True) -> None:
        self.refuse_damage = refuse_damage
        self.dir = Path(directory)
        self.dir.mkdir(parents=True, exist_ok=True)
        # one writer per folder, taken before anything is read, sealed or deleted
        self._dir_lock = StoreLock(self.dir)
        try:
            self._open(seal_rows, fsync)
        except BaseException:
            self._dir_lock.release()
            raise

    def _open(self, seal_rows: int, fsync: bool) -> None:
        self.seal_rows = int(seal_rows)
        self.fsync = fsync
        self._lock = threading.Lock()
        self._segments: list[Path] = []
        self._schemas: dict[Path, pa.Schema] = {}  # a sealed segment's (immutable) schema
        self._memory: dict[int, list[pa.Table]] = {}  # log seq -> tables not yet in Parquet
        self._sealers: list[threading.Thread] = []
        self.recovered_rows = 0
        self.truncated_bytes = 0
        seqs: set[int] = set()
        for p in sorted(self.dir.glob("seg-*.parquet.tmp")):
            p.unlink()
        for p in sorted(self.dir.glob("seg-*.parquet")):
            # a damaged segment is named now, not by a later query's Arrow message
            self._schema(p)
            self._segments.append(p)
            seqs.add(int(p.name[4:12]))
        for p in sorted(self.dir.glob("seg-*.wal")):
            seq = int(p.name[4:12])
            if seq in seqs:  # sealed, the log's deletion did not happen before a crash
                p.unlink()
                continue
            tables, valid, intact = _read_log(p)
            if intact is not None and self.refuse_damage:
                # acknowledged frames after a damaged one: refused, as a damaged segment
                # (never cut off: those rows were synced and answered 202)
                raise StoreError(f"damaged write-ahead log of the store (a bad frame at "
                                 f"byte {valid}, intact frames from byte {intact}); move "
                                 "it aside to start without its rows", p)
            size = p.stat().st_size
            if valid < size:
                self.truncated_bytes += size - valid
                with open(p, "r+b") as f:
                    f.truncate(valid)
                    os.fsync(f.fileno())
                # (said, not silent: these bytes were never acknowledged, the sync of
                # their append had not returned)
                if intact is None:
                    msg = (f"{size - valid} bytes of an incomplete last frame cut off at "
                           f"byte {valid} (an append interrupted by a crash, never "
                           "acknowledged)")
                else:
                    msg = (f"{size - valid} bytes cut off at byte {valid}, from a damaged "
                           "frame on (this log's rows are recomputed after a crash)")
                print(f"warning: {p}: {msg}", file=sys.stderr, flush=True)
            self._memory[seq] = tables
            self.recovered_rows += sum(t.num_rows for t in tables)
            seqs.add(seq)
        self._seq = max(seqs, default=-1) + 1
        self._rows = 0
        self._file = self._open_log(self._seq)
        self._size = 0  # the log's length: every frame before it was written completely
        self._memory[self._seq] = []
        # seal logs recovered from a crash (they are complete: their frames were synced)
        for seq in sorted(self._memory):
            if seq != self._seq and self._memory[seq]:
                self._seal_async(seq)
            elif seq != self._seq:
                self._path(seq, "wal").unlink(missing_ok=True)
                del self._memory[seq]

    def _path(self, seq: int, ext: str) -> Path:
        return self.dir / f"seg-{seq:08d}.{ext}"

    def _open_log(self, seq: int) -> io.FileIO:
        """A new, empty log file, unbuffered: a failed write leaves nothing in a buffer
        that a later write would flush (a refused body's rows appeared on disk)."""
        return open(self._path(seq, "wal"), "ab", buffering=0)  # noqa: SIM115 - long-lived

    def append(self, table: pa.Table | pa.RecordBatch) -> None:
        """Append rows durably (synced to disk when this returns).

        Raises
        ------
        StoreWriteError
            The write or the sync failed (disk full, I/O error).  The log file is then as
            it was before the call and the rows are not kept: the caller must report the
            rows as not stored.
        """
        if table.num_rows == 0:
            return
        if isinstance(table, pa.RecordBatch):
            table = pa.Table.from_batches([table])
        frame = _encode(table)
        with self._lock:
            fd = self._file.fileno()
            try:
                if os.fstat(fd).st_size != self._size:  # an earlier cut-back had failed
                    os.ftruncate(fd, self._size)
                _write_all(fd, frame)
                if self.fsync:
                    os.fdatasync(fd)
            except OSError as exc:
                self._cut_back(fd)
                raise StoreWriteError(f"store write failed: {exc.strerror or exc}",
                                      self._path(self._seq, "wal"), exc.errno) from None
            self._size += len(frame)
            self._memory[self._seq].append(table)
            self._rows += table.num_rows
            if self._rows >= self.seal_rows:
                self._rotate()

    def _cut_back(self, fd: int) -> None:
        """Truncate the log to its length before a failed append (best effort: when this
        fails too, the next append retries it before writing)."""
        with contextlib.suppress(OSError):
            os.ftruncate(fd, self._size)
            if self.fsync:
                os.fdatasync(fd)

    def _rotate(self) -> None:
        """Start a new log and seal the full one.  The rows are already durable: a new log
        that cannot be created (disk full) keeps the current one open, retried at the
        next append, rather than failing an append whose rows are on disk."""
        try:
            new = self._open_log(self._seq + 1)
        except OSError:
            return
        old = self._seq
        self._file.close()
        self._seq += 1
        self._rows = 0
        self._size = 0
        self._file = new
        self._memory[self._seq] = []
        if self.fsync:
            with contextlib.suppress(OSError):  # the new log's entry; retried by the seal
                _fsync_dir(self.dir)
        self._seal_async(old)

    def _seal_async(self, seq: int) -> None:
        th = threading.Thread(target=self._seal, args=(seq,), name=f"seal-{seq}", daemon=True)
        self._sealers = [t for t in self._sealers if t.is_alive()] + [th]
        th.start()

    def _seal(self, seq: int) -> None:
        _background_priority()
        tables = self._memory[seq]
        table = pa.concat_tables(tables, promote_options="default")
        final = self._path(seq, "parquet")
        tmp = final.with_name(final.name + ".tmp")
        try:
            pq.write_table(table, tmp, compression="zstd")
            with open(tmp, "rb") as f:
                os.fsync(f.fileno())
            os.replace(tmp, final)
            _fsync_dir(self.dir)
        except OSError as exc:  # disk full: the log stays (its rows stay readable from
            # memory and are sealed at the next start); one line, no traceback
            with contextlib.suppress(OSError):
                tmp.unlink(missing_ok=True)
            print(f"warning: {final}: sealing the log into Parquet failed ({exc}); the log "
                  "is kept and sealed at the next start", file=sys.stderr, flush=True)
            return
        with self._lock:
            self._segments.append(final)
            del self._memory[seq]
        self._path(seq, "wal").unlink(missing_ok=True)

    def wait_sealed(self) -> None:
        """Block until background sealing is done (tests, shutdown)."""
        for t in list(self._sealers):
            t.join()

    def snapshot(self) -> LogSnapshot:
        """The rows held now, to be read later as they are now (:class:`LogSnapshot`):
        rows appended or sealed meanwhile are not in it."""
        with self._lock:
            segments = list(self._segments)
            memory = [t for seq in sorted(self._memory) for t in self._memory[seq]]
        return LogSnapshot(self, segments, memory)

    def scan(
        self, columns: list[str] | None = None, expression: ds.Expression | None = None,
    ) -> pa.Table:
        """All rows (optionally only ``columns``, filtered by a dataset ``expression``)."""
        return self.snapshot().scan(columns, expression)

    @staticmethod
    def _damaged(segments: list[Path], schema: pa.Schema, columns: list[str] | None,
                 exc: BaseException) -> StoreError:
        """The error naming the segment whose read failed with ``exc`` (each segment read
        alone to find it; the folder when none fails alone)."""
        for p in segments:
            try:
                ds.dataset([str(p)], schema=schema, format="parquet").to_table(
                    columns=columns)
            except (pa.ArrowException, OSError) as one:
                why = " ".join(str(one).split())  # (Arrow's messages span lines)
                return StoreError(f"damaged Parquet segment of the store ({why}); move it "
                                  "aside to start without its rows", p)
        why = " ".join(str(exc).split())
        return StoreError(f"damaged Parquet segments of the store ({why})", segments[0].parent)

    def _schema(self, path: Path) -> pa.Schema:
        """The schema of a sealed segment (read once: segments never change).

        Raises
        ------
        StoreError
            Its footer cannot be read (a damaged file): named, at open as at a query (a
            segment sealed after the start and damaged before any query read it gave a
            query Arrow's message, a generic 500).
        """
        sch = self._schemas.get(path)
        if sch is None:
            try:
                sch = self._schemas[path] = pq.read_schema(path)
            except (pa.ArrowException, OSError) as exc:
                raise StoreError(f"damaged Parquet segment of the store ({exc}); move it "
                                 "aside to start without its rows", path) from None
        return sch

    def close(self) -> None:
        """Close the active log, wait for the sealing threads, release the folder."""
        with self._lock:
            self._file.close()
        self.wait_sealed()
        self._dir_lock.release()


class LogSnapshot:
    """The rows of a :class:`SegmentLog` at one moment: its sealed segments (immutable
    files, never deleted while the log is open) and the tables of its logs not yet
    sealed.  Two scans of one snapshot read the same rows in the same order, whatever
    was appended or sealed between them (a query reads the key columns of every
    matching row first, then every column of the rows it keeps only).

    Parameters
    ----------
    log : SegmentLog
        The log (its cached segment schemas, and the naming of a damaged segment).
    segments : list of Path
        The sealed segments, in the log's order.
    memory : list of Table
        The rows not yet sealed, in order.
    """

    def __init__(self, log: SegmentLog, segments: list[Path], memory: list[pa.Table]) -> None:
        self.log = log
        self.segments = segments
        self.memory = memory

    def schemas(self) -> list[pa.Schema]:
        """The schema of each segment and each unsealed table (not unified)."""
        return [self.log._schema(p) for p in self.segments] + [t.schema for t in self.memory]

    def scan(
        self, columns: list[str] | None = None, expression: ds.Expression | None = None,
    ) -> pa.Table:
        """All rows (optionally only ``columns``, filtered by a dataset ``expression``)."""
        segments, memory = self.segments, self.memory
        parts: list[pa.Table] = []
        if segments:
            # the union of the segments' columns: a dataset of several files takes the
            # first file's schema, and the columns only later segments have (a segment
            # of fallback rows of six columns sealed first: every later row lost its
            # hpl and covariance terms after a restart) were dropped
            schema = pa.unify_schemas([self.log._schema(p) for p in segments],
                                      promote_options="permissive")
            cols = None if columns is None else [c for c in columns if c in schema.names]
            try:
                parts.append(ds.dataset([str(p) for p in segments], schema=schema,
                                        format="parquet").to_table(columns=cols,
                                                                   filter=expression))
            except (pa.ArrowException, OSError) as exc:
                # a segment damaged in its data (its footer reads): named, as at open; the
                # Arrow message alone named no file, and at start it was a traceback
                raise self.log._damaged(segments, schema, cols, exc) from None
        if memory:
            parts.append(scan_table(pa.concat_tables(memory, promote_options="default"),
                                    columns, expression))
        if not parts:
            return pa.table({})
        return pa.concat_tables(parts, promote_options="default")


def scan_table(table: pa.Table, columns: list[str] | None = None,
               expression: ds.Expression | None = None) -> pa.Table:
    """The rows of an in-memory ``table`` that ``expression`` keeps, ``columns`` only
    (those of them it has), in the table's order: as a scan of a segment reads them.

    The expression is evaluated over the columns it names only, and the columns wanted
    are selected (no copy) before the rows are filtered: ``Table.filter`` copied every
    column of the rows it kept, most then dropped (a query with ``since`` over 1 000 000
    unsealed positions: 134 MiB of Arrow memory for a first pass of a few columns, 23 MiB
    without a filter).  When every row is kept nothing is copied.

    Parameters
    ----------
    table : Table
        The rows.
    columns : list of str, optional
        The columns wanted, in this order (default: all).
    expression : Expression, optional
        A dataset filter (default: every row); a row where it is null is left out, as a
        filter leaves it.

    Returns
    -------
    Table
        The rows kept, the columns wanted.
    """
    kept = table if columns is None else table.select(
        [c for c in columns if c in table.column_names])
    if expression is None:
        return kept
    # (one boolean per row, in the table's order, as ``Table.filter`` evaluates it)
    mask = acero.Declaration.from_sequence([
        acero.Declaration("table_source", acero.TableSourceNodeOptions(table)),
        acero.Declaration("project", acero.ProjectNodeOptions([expression], ["keep"])),
    ]).to_table()["keep"]
    if mask.null_count == 0 and pc.all(mask).as_py() is not False:  # every row kept
        return kept
    return kept.filter(mask)


def max_by(table: pa.Table, key: str, value: str) -> dict[str, float]:
    """``{key: max(value)}`` over a table (e.g. the latest time per tag)."""
    if table.num_rows == 0:
        return {}
    g = table.group_by(key).aggregate([(value, "max")])
    return dict(zip(g[key].to_pylist(), g[f"{value}_max"].to_pylist()))


__all__ = ["LogSnapshot", "SegmentLog", "StoreError", "StoreInUse", "StoreLock",
           "StoreWriteError", "max_by", "scan_table"]
