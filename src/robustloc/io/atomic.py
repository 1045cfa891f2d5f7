"""Atomic output files, standard output as ``-``, and the output-over-input guard.

Every file a command writes goes through :func:`atomic_output`: the data are written to a
temporary file in the target folder (``.NAME.XXXXXX.tmp``), flushed and ``fsync``-ed, and
renamed onto the final path with :func:`os.replace` only when the whole file is complete.
So, whatever happens (an error in the input half way, Ctrl-C, ``kill``, a full disk):

* the final path holds either the previous file, intact, or nothing;
* the temporary file is removed (except after ``kill -9`` or a power cut, when a hidden
  ``.NAME.*.tmp`` may stay behind: it never shadows the real file);
* two runs writing the same path at once never interleave: each rename is atomic, the last
  complete file wins.

Targets that are not regular files cannot be replaced atomically and are written directly:
``-`` (standard output; CSV only), character devices (``/dev/stdout``, ``/dev/null``,
``/dev/full``) and FIFOs.  :func:`writes_to_stdout` tells a command that its data go to
standard output, so that it prints its summary on stderr instead.

A final name ending in ``.gz`` is written gzip-compressed, whatever wrote the temporary
file (the writers write plain CSV; the readers decompress gzip): the complete temporary
file is compressed into a second temporary file, which is renamed into place.  Names of
compressions the readers cannot read back (``.bz2``, ``.xz``, ``.zip``, ``.zst``) are
refused before anything is written.

An OS error while writing (``ENOSPC``, ``EROFS``, a parent that is a file) is raised as
:class:`~robustloc.errors.OutputError` naming the final path, never as a bare ``OSError``.

:func:`check_not_input` refuses an output file that is an input;
:func:`check_not_input_tree` refuses an output directory (a dataset) that is an input,
holds one, or lies inside one -- replacing the directory would delete the input.
"""

from __future__ import annotations

import contextlib
import contextvars
import errno
import os
import re
import socket
import stat
import sys
import tempfile
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import IO

from robustloc.errors import InputError, OutputError

PathLike = str | os.PathLike

__all__ = [
    "STDIO",
    "atomic_output",
    "check_not_input",
    "check_not_input_tree",
    "describe_oserror",
    "is_stdio",
    "parents_not_created",
    "writes_to_stdout",
]

#: The name that means standard input (for readers) or standard output (for writers).
STDIO = "-"


def is_stdio(path: PathLike | None) -> bool:
    """True if ``path`` is ``-`` (standard input or output)."""
    return path is not None and str(path) == STDIO


def _stdout_stat() -> os.stat_result | None:
    try:
        return os.fstat(sys.stdout.fileno())
    except (OSError, ValueError, AttributeError):  # no real fd (pytest capture, closed)
        return None


def writes_to_stdout(path: PathLike | None) -> bool:
    """True if writing ``path`` puts the data on this process's standard output.

    ``-``, ``/dev/stdout``, ``/dev/fd/1``, or any path that is the same file as fd 1 (a
    FIFO or terminal it is connected to).  A command then prints its run summary on
    stderr, so that a summary never mixes into a data stream.
    """
    if path is None:
        return False
    if is_stdio(path):
        return True
    s = str(path)
    if s in ("/dev/stdout", "/dev/fd/1", "/proc/self/fd/1"):
        return True
    out = _stdout_stat()
    if out is None:
        return False
    try:
        st = os.stat(s)
    except OSError:
        return False
    # a regular file that stdout is redirected to (`> file`) is not "the data stream"
    # unless it is the output itself: then the summary would land in the data, too.
    return (st.st_dev, st.st_ino) == (out.st_dev, out.st_ino)


def describe_oserror(exc: OSError) -> str:
    """Short, user-facing words for an OS error on a path (no errno number, no class)."""
    words = {
        errno.ENOENT: "file not found",
        errno.EISDIR: "is a directory, expected a file",
        errno.EACCES: "permission denied",
        errno.EPERM: "permission denied",
        errno.EEXIST: "already exists and is not a folder (a folder was expected)",
        errno.ENOTDIR: "a parent of this path is a file, not a folder",
        errno.ENOSPC: "no space left on device",
        errno.EDQUOT: "disk quota exceeded",
        errno.EROFS: "read-only file system",
        errno.ENAMETOOLONG: "file name too long",
        errno.EFBIG: "file too large",
        errno.EIO: "input/output error",
        errno.EPIPE: "broken pipe",
    }
    if exc.errno in words:
        return words[exc.errno]
    return (exc.strerror or str(exc)).lower()


def _samefile(a: Path, b: Path) -> bool:
    try:
        return os.path.samefile(a, b)
    except OSError:
        return a.resolve() == b.resolve()


def check_not_input(out: PathLike | None, inputs: Iterable[PathLike | None]) -> None:
    """Refuse an output that is one of the inputs (same file, or same resolved path).

    Raises
    ------
    InputError
        ``PATH: output would overwrite an input``, before anything is written.
    """
    if out is None or is_stdio(out):
        return
    _refuse_folder_name(out)  # before any work, as the rest of this check
    o = Path(out)
    for i in inputs:
        if i is None or is_stdio(i):
            continue
        p = Path(i)
        if str(o) in ("/dev/null",):
            return
        if _samefile(o, p):
            raise InputError("output would overwrite an input", out)


def _refuse_folder_name(path: PathLike) -> None:
    """An output file named with a trailing separator (``-o new/``) is a folder's name:
    ``Path`` drops the separator, and a file named ``new`` was written where the user
    expected a folder.  Refused (an existing folder is refused by its kind)."""
    name = os.fspath(path)
    if isinstance(name, str) and name.endswith(tuple(filter(None, (os.sep, os.altsep)))):
        raise OutputError("names a folder (ends with a separator), expected a file", name,
                          errno_=errno.EISDIR)


def _stat_id(p: Path) -> tuple[int, int] | None:
    try:
        st = os.stat(p)
    except (OSError, ValueError):
        return None
    return st.st_dev, st.st_ino


def _resolved(p: Path) -> Path:
    try:
        return p.resolve()
    except (OSError, RuntimeError):  # a symlink loop
        return Path(os.path.abspath(p))


def check_not_input_tree(out: PathLike | None, inputs: Iterable[PathLike | None]) -> None:
    """Refuse an output directory that is an input, holds an input, or lies inside one.

    For outputs written as a whole directory (``--engine dask`` datasets, ``partition``),
    which replace ``out`` on success: an input at ``out`` or below it would be deleted, and
    an ``out`` inside an input dataset would add its files to that dataset.  Paths are
    compared resolved (symbolic links, ``..``) and by device and inode (hard links, bind
    mounts).  Inputs that do not exist (a glob pattern) are skipped; give the paths they
    match.

    Raises
    ------
    InputError
        ``OUT: output would overwrite an input`` (``out`` is an input, or holds one, named
        in the message), or ``OUT: output would be written inside an input (INPUT)``;
        before anything is written.
    """
    if out is None or is_stdio(out):
        return
    o = Path(out)
    o_path, o_id = _resolved(o), _stat_id(o)
    o_up = set(o_path.parents)
    o_up_ids = {i for a in o_up if (i := _stat_id(a)) is not None}
    dir_ids: dict[Path, tuple[int, int] | None] = {}  # partition files share folders

    def holds(p_path: Path) -> bool:
        if o_path in p_path.parents:
            return True
        if o_id is None:
            return False
        for a in p_path.parents:
            if a not in dir_ids:
                dir_ids[a] = _stat_id(a)
            if dir_ids[a] == o_id:
                return True
        return False

    for i in inputs:
        if i is None or is_stdio(i):
            continue
        p = Path(i)
        p_id = _stat_id(p)
        if p_id is None:
            continue
        p_path = _resolved(p)
        if p_path == o_path or p_id == o_id:
            raise InputError("output would overwrite an input", out)
        if holds(p_path):
            raise InputError(f"output would overwrite an input (it holds {p})", out)
        if p_path in o_up or p_id in o_up_ids:
            raise InputError(f"output would be written inside an input ({p})", out)


#: The compression written for a final name ending in ``.gz`` (the readers decompress
#: gzip, whatever the name), and the magic bytes of a file a writer compressed already.
_GZIP_SUFFIX = ".gz"
_GZIP_MAGIC = b"\x1f\x8b"
#: Compressed names the readers cannot read back, refused before writing.
_REFUSED_COMPRESSION = (".bz2", ".xz", ".zip", ".zst", ".zstd", ".tar", ".tgz")


def _gzip_wanted(p: Path) -> bool:
    """True if ``p`` ends in ``.gz`` (the file is written gzip-compressed).

    Raises
    ------
    InputError
        Another compression's name (``.bz2``, ``.xz``, ``.zip``, ``.zst``).
    """
    suffix = p.suffix.lower()
    if suffix in _REFUSED_COMPRESSION:
        raise InputError(f"cannot write {suffix} compressed output; name it .csv.gz for a "
                         "compressed CSV, or .csv or .parquet", p)
    return suffix == _GZIP_SUFFIX


def _host_token() -> str:
    """This host's name, and on Linux its process-id namespace (``HOST~NS``): containers
    that share a folder and a host name but not their process ids (``docker run -v``
    with ``--hostname``) cannot see each other's processes, and one's sweep would take
    the other's live writer for dead."""
    host = re.sub(r"[^A-Za-z0-9_-]", "_", socket.gethostname())[:40] or "host"
    try:
        return f"{host}~{os.stat('/proc/self/ns/pid').st_ino:x}"
    except OSError:  # (no /proc: not Linux)
        return host


#: This host's name as it appears in a temporary file's name (:func:`temp_prefix`).
_HOST = _host_token()


def temp_prefix(final_name: str) -> str:
    """``.NAME.HOST-PID.``, the start of a temporary file's (or folder's) name: it names
    the process that writes it, so that a later write of ``NAME`` can remove what a
    killed process left (:func:`sweep_orphans`)."""
    return f".{final_name}.{_HOST}-{os.getpid()}."


def staging_name(final_name: str) -> str:
    """``.NAME.partial-HOST-PID-XXXXXXXX``: a staging folder's name (a dataset of
    ``--engine dask``, a report of ``reproduce``), its process named as in
    :func:`temp_prefix`."""
    import uuid

    return f".{final_name}.partial-{_HOST}-{os.getpid()}-{uuid.uuid4().hex[:8]}"


def aside_name(final_name: str) -> str:
    """``.NAME.old-HOST-PID-XXXXXXXX``: where a folder output's previous version waits
    while the new one is renamed into place, then is deleted (``reproduce``).  A run
    killed before the deletion leaves it: :func:`sweep_orphans` removes it once ``NAME``
    exists again (while ``NAME`` is missing it may be the only copy, and is kept)."""
    import uuid

    return f".{final_name}.old-{_HOST}-{os.getpid()}-{uuid.uuid4().hex[:8]}"


def _alive(pid: int) -> bool:
    """Whether a process ``pid`` runs on this host (one of another user counts)."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except OSError:  # (PermissionError: it exists)
        return True
    return True


def sweep_orphans(parent: Path, final_name: str) -> int:
    """Remove what a process of this host, now dead, left while writing ``final_name`` in
    ``parent``: temporary files and folders (:func:`temp_prefix`), staging folders
    (:func:`staging_name`) and, once ``final_name`` exists, previous versions set aside
    (:func:`aside_name`).  SIGKILL and the OOM killer run no clean-up: a killed run of
    a 10 GB output left 10 GB beside it, one more per attempt.  What a running process
    or another host (a shared filesystem) writes is kept; so is a name that says no
    process (an older robustloc's).  Returns how many were removed."""
    if os.name != "posix":  # pragma: no cover - os.kill(pid, 0) probes only there
        return 0
    import shutil

    temp, stage = f".{final_name}.{_HOST}-", f".{final_name}.partial-{_HOST}-"
    aside = f".{final_name}.old-{_HOST}-"
    n = 0
    try:  # (one scandir pass: 5 ms in a folder of 10 000 files, two globs took 12 ms)
        entries = [e for e in os.scandir(parent)
                   if e.name.startswith((temp, stage, aside))]
    except OSError:
        return 0
    for e in entries:
        if e.name.startswith(temp) and e.name.endswith(".tmp"):
            pid = e.name[len(temp):].split(".", 1)[0]
        elif e.name.startswith(stage):
            pid = e.name[len(stage):].split("-", 1)[0]
        elif e.name.startswith(aside) and os.path.lexists(os.path.join(parent, final_name)):
            pid = e.name[len(aside):].split("-", 1)[0]
        else:
            continue
        if not pid.isdigit() or int(pid) == os.getpid() or _alive(int(pid)):
            continue
        with contextlib.suppress(OSError):
            if e.is_dir(follow_symlinks=False):
                shutil.rmtree(e.path)
            else:
                os.unlink(e.path)
            n += 1
    return n


def _gzip(tmp: Path, final: Path, temps: list[Path]) -> Path:
    """``tmp`` gzip-compressed into a new temporary file beside it (appended to
    ``temps``, so that the caller removes it on failure); ``tmp`` itself if a writer
    compressed it already."""
    import gzip
    import shutil

    with open(tmp, "rb") as fh:
        if fh.read(len(_GZIP_MAGIC)) == _GZIP_MAGIC:
            return tmp
    fd, name = tempfile.mkstemp(prefix=temp_prefix(final.name), suffix=".tmp",
                                dir=tmp.parent)
    z = Path(name)
    temps.append(z)
    with os.fdopen(fd, "wb") as raw, open(tmp, "rb") as src:
        # the header names the final file (without .gz), not the temporary one
        with gzip.GzipFile(filename=final.name, mode="wb", fileobj=raw,
                           compresslevel=6) as dst:
            shutil.copyfileobj(src, dst, 1 << 20)
    return z


def written_in_place(path: PathLike) -> bool:
    """True when :func:`atomic_output` would write ``path`` in place rather than replace a
    regular file: a device, a FIFO, a name under /dev or /proc, or standard output's file.
    Nothing can be read back from such an output."""
    return is_stdio(path) or _is_special(Path(path))


def _is_special(p: Path) -> bool:
    """A target written in place, not replaced: an existing device or FIFO, or any name
    under /dev or /proc (``/dev/stdout`` redirected to a regular file must not have its
    symlink replaced by a file), or the file standard output is connected to."""
    if str(p).startswith(("/dev/", "/proc/")) or str(p.resolve()).startswith(("/dev/", "/proc/")):
        return True
    try:
        mode = os.stat(p).st_mode
    except OSError:
        return False
    if not stat.S_ISREG(mode) and not stat.S_ISDIR(mode):
        return True
    return writes_to_stdout(p)


def _fsync_dir(folder: Path) -> None:
    try:
        fd = os.open(folder, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def _output_words(exc: OSError, parent: Path) -> str:
    """:func:`describe_oserror` for an output: one that cannot be created is not a
    "file not found" (the words of a missing input) but a file the folder cannot hold
    (``/proc``, a vanished mount)."""
    if exc.errno == errno.ENOENT:
        return f"cannot create a file in {parent or '.'} (no such file or directory)"
    return describe_oserror(exc)


#: False within :func:`parents_not_created` (in this thread or task): a missing parent
#: folder of an output is an error, not created.
_MAKE_PARENTS: contextvars.ContextVar[bool] = contextvars.ContextVar(
    "robustloc_make_parents", default=True)


@contextlib.contextmanager
def parents_not_created() -> Iterator[None]:
    """Within the block (this thread's or task's context only), :func:`atomic_output`
    does not create a missing parent folder: the write fails with :class:`OutputError`.

    For the Dask engine's tasks, which write their part into a staging folder that only
    the client creates: a task still running when a failed run removed that folder
    re-created it, and its part was left behind as a hidden ``.OUT.partial-XXXX``
    folder (the Dask review).
    """
    token = _MAKE_PARENTS.set(False)
    try:
        yield
    finally:
        _MAKE_PARENTS.reset(token)


def _prepare_parent(p: Path) -> Path:
    parent = p.parent if str(p.parent) else Path(".")
    try:
        if _MAKE_PARENTS.get():
            parent.mkdir(parents=True, exist_ok=True)
        elif not parent.exists():
            raise OutputError(f"cannot create a file in {parent} (the folder is gone)", p,
                              errno_=errno.ENOENT)
    except (FileExistsError, NotADirectoryError):
        raise OutputError("a parent of this path is a file, not a folder", p,
                          errno_=errno.ENOTDIR) from None
    except OSError as exc:
        raise OutputError(describe_oserror(exc), p, errno_=exc.errno) from None
    if not parent.is_dir():
        raise OutputError("a parent of this path is a file, not a folder", p,
                          errno_=errno.ENOTDIR)
    if p.is_dir():
        raise OutputError("is a directory, expected a file", p, errno_=errno.EISDIR)
    return parent


@contextlib.contextmanager
def atomic_output(path: PathLike, *, binary: bool = True) -> Iterator[tuple[Path, IO | None]]:
    """Context manager that makes writing ``path`` all-or-nothing.

    Yields ``(target, stream)``:

    * for a regular file, ``target`` is the temporary file to write (by name; ``stream``
      is None); on a clean exit it is gzip-compressed if ``path`` ends in ``.gz``,
      fsync-ed and renamed onto ``path``; on any exception (``KeyboardInterrupt`` and
      SIGTERM included) it is removed and the exception propagates;
    * for ``-``, ``target`` is None and ``stream`` is standard output (binary or text by
      ``binary``);
    * for a device or FIFO, ``target`` is ``path`` itself, written in place.

    Raises
    ------
    OutputError
        An OS error on the output (no space, read-only, parent is a file), naming ``path``.
    InputError
        A ``.bz2``, ``.xz``, ``.zip`` or ``.zst`` name (before anything is written).
    """
    if is_stdio(path):
        stream = sys.stdout.buffer if binary else sys.stdout
        try:
            yield None, stream
            stream.flush()
        except BrokenPipeError:
            raise
        except OSError as exc:
            if exc.errno == errno.EPIPE:
                raise
            raise OutputError(describe_oserror(exc), "<stdout>", errno_=exc.errno) from None
        return
    _refuse_folder_name(path)
    p = Path(path)
    if _is_special(p):
        try:
            yield p, None
        except OSError as exc:
            if isinstance(exc, (BrokenPipeError, OutputError)):
                raise
            raise OutputError(_output_words(exc, p.parent), p, errno_=exc.errno) from None
        return
    compress = _gzip_wanted(p)
    if p.is_symlink():
        # write the file the link names, as a shell's ">" does: the link was replaced by a
        # regular file and its target kept the old content (the no-loss review)
        p = Path(os.path.realpath(p))
    try:  # an existing file keeps its permissions (0640 became 0644)
        mode = stat.S_IMODE(os.stat(p).st_mode)
    except OSError:
        mode = 0o666 & ~_umask()
    parent = _prepare_parent(p)
    sweep_orphans(parent, p.name)  # (before: the space is free for this write)
    try:
        fd, tmp_name = tempfile.mkstemp(prefix=temp_prefix(p.name), suffix=".tmp",
                                        dir=parent)
    except OSError as exc:
        raise OutputError(_output_words(exc, parent), p, errno_=exc.errno) from None
    os.close(fd)
    tmp = Path(tmp_name)
    temps = [tmp]
    done = False
    try:
        yield temps[0], None
        if compress:
            tmp = _gzip(temps[0], p, temps)
        with open(tmp, "rb+") as fh:
            os.fsync(fh.fileno())
        with contextlib.suppress(OSError):  # the old file's or the usual (mkstemp: 0600)
            os.chmod(tmp, mode)
        os.replace(tmp, p)
        done = True
        _fsync_dir(parent)
    except OutputError:
        raise
    except OSError as exc:
        if isinstance(exc, BrokenPipeError) or exc.filename not in (
                None, *(str(t) for t in temps)):
            raise
        raise OutputError(describe_oserror(exc), p, errno_=exc.errno) from None
    finally:
        for t in temps:
            if not done or t != tmp:
                with contextlib.suppress(OSError):
                    t.unlink()


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask
