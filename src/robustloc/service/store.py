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
  truncated (those rows were never acknowledged: the sync had not returned).

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
import io
import os
import struct
import sys
import threading
import zlib
from pathlib import Path

import pyarrow as pa
import pyarrow.dataset as ds
import pyarrow.parquet as pq

_MAGIC = b"RLW1"
_HEADER = struct.Struct("<4sII")  # magic, payload length, crc32


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


def _read_log(path: Path) -> tuple[list[pa.Table], int]:
    """Frames of a log file, and the byte length of its valid prefix."""
    data = path.read_bytes()
    out: list[pa.Table] = []
    pos = 0
    while pos + _HEADER.size <= len(data):
        magic, length, crc = _HEADER.unpack_from(data, pos)
        end = pos + _HEADER.size + length
        if magic != _MAGIC or end > len(data):
            break
        payload = data[pos + _HEADER.size : end]
        if zlib.crc32(payload) != crc:
            break
        try:
            out.append(pa.ipc.open_stream(payload).read_all())
        except pa.ArrowInvalid:
            break
        pos = end
    return out, pos


class SegmentLog:
    """One durable append-only table (a folder of ``*.parquet`` segments and ``*.wal`` logs).

    Parameters
    ----------
    directory : path
        Created if missing.
    seal_rows : int
        Rows per log before it is sealed into a Parquet segment.
    fsync : bool
        Sync every append (default True; False only for throw-away stores in tests).
    """

    def __init__(self, directory: str | os.PathLike, seal_rows: int = 1_000_000,
                 fsync: bool = True) -> None:
        self.dir = Path(directory)
        self.dir.mkdir(parents=True, exist_ok=True)
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
            self._segments.append(p)
            seqs.add(int(p.name[4:12]))
        for p in sorted(self.dir.glob("seg-*.wal")):
            seq = int(p.name[4:12])
            if seq in seqs:  # sealed, the log's deletion did not happen before a crash
                p.unlink()
                continue
            tables, valid = _read_log(p)
            size = p.stat().st_size
            if valid < size:
                self.truncated_bytes += size - valid
                with open(p, "r+b") as f:
                    f.truncate(valid)
                    os.fsync(f.fileno())
            self._memory[seq] = tables
            self.recovered_rows += sum(t.num_rows for t in tables)
            seqs.add(seq)
        self._seq = max(seqs, default=-1) + 1
        self._rows = 0
        self._file = open(self._path(self._seq, "wal"), "ab")  # noqa: SIM115 - long-lived
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

    def append(self, table: pa.Table | pa.RecordBatch) -> None:
        """Append rows durably (synced to disk when this returns)."""
        if table.num_rows == 0:
            return
        if isinstance(table, pa.RecordBatch):
            table = pa.Table.from_batches([table])
        frame = _encode(table)
        with self._lock:
            self._file.write(frame)
            self._file.flush()
            if self.fsync:
                os.fdatasync(self._file.fileno())
            self._memory[self._seq].append(table)
            self._rows += table.num_rows
            if self._rows >= self.seal_rows:
                self._rotate()

    def _rotate(self) -> None:
        old = self._seq
        self._file.close()
        self._seq += 1
        self._rows = 0
        self._file = open(self._path(self._seq, "wal"), "ab")  # noqa: SIM115
        self._memory[self._seq] = []
        if self.fsync:
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
        pq.write_table(table, tmp, compression="zstd")
        with open(tmp, "rb") as f:
            os.fsync(f.fileno())
        os.replace(tmp, final)
        _fsync_dir(self.dir)
        with self._lock:
            self._segments.append(final)
            del self._memory[seq]
        self._path(seq, "wal").unlink(missing_ok=True)

    def wait_sealed(self) -> None:
        """Block until background sealing is done (tests, shutdown)."""
        for t in list(self._sealers):
            t.join()

    def scan(
        self, columns: list[str] | None = None, expression: ds.Expression | None = None,
    ) -> pa.Table:
        """All rows (optionally only ``columns``, filtered by a dataset ``expression``)."""
        with self._lock:
            segments = list(self._segments)
            memory = [t for seq in sorted(self._memory) for t in self._memory[seq]]
        parts: list[pa.Table] = []
        if segments:
            # the union of the segments' columns: a dataset of several files takes the
            # first file's schema, and the columns only later segments have (a segment
            # of fallback rows of six columns sealed first: every later row lost its
            # hpl and covariance terms after a restart) were dropped
            schema = pa.unify_schemas([self._schema(p) for p in segments],
                                      promote_options="permissive")
            cols = None if columns is None else [c for c in columns if c in schema.names]
            parts.append(ds.dataset([str(p) for p in segments], schema=schema,
                                    format="parquet").to_table(columns=cols,
                                                               filter=expression))
        if memory:
            mem = pa.concat_tables(memory, promote_options="default")
            if expression is not None:
                mem = mem.filter(expression)
            if columns is not None:
                mem = mem.select([c for c in columns if c in mem.column_names])
            parts.append(mem)
        if not parts:
            return pa.table({})
        return pa.concat_tables(parts, promote_options="default")

    def _schema(self, path: Path) -> pa.Schema:
        """The schema of a sealed segment (read once: segments never change)."""
        sch = self._schemas.get(path)
        if sch is None:
            sch = self._schemas[path] = pq.read_schema(path)
        return sch

    def close(self) -> None:
        with self._lock:
            self._file.close()
        self.wait_sealed()


def max_by(table: pa.Table, key: str, value: str) -> dict[str, float]:
    """``{key: max(value)}`` over a table (e.g. the latest time per tag)."""
    if table.num_rows == 0:
        return {}
    g = table.group_by(key).aggregate([(value, "max")])
    return dict(zip(g[key].to_pylist(), g[f"{value}_max"].to_pylist()))


__all__ = ["SegmentLog", "max_by"]
