"""The DataFrame-level Python API: ``robustloc.locate``, ``track``, ``calibrate``,
``evaluate``, ``spp`` and the contract readers and writer.

Each function builds the typed settings of its workflow (:mod:`robustloc.pipelines`) and
runs it; the command of the same name is a thin layer over the same workflow (it parses
its options into the same settings and prints the same summary).  So a frame from the API
equals, row for row, the file the command writes for the same input, and a mistake
raises :class:`robustloc.InputError` with the message the command prints after
``error:`` (a refused option reads ``argument --NAME: ...`` as argparse words it).
Inputs are DataFrames or paths (CSV or Parquet; ``pathlib.Path``, str, or the
``importlib.resources.files(...)`` of the data shipped with the package), outputs are
DataFrames in the contract formats of ``docs/formats`` (the design's file contract).  The
run summary (what ``--json`` prints) is in ``frame.attrs["summary"]``; notes and warnings
become :class:`RobustlocWarning`.

A DataFrame input is read like a file (:func:`robustloc.io.tables.in_memory_source`; no
temporary file): an error names it ``<measurements DataFrame>`` (or ``<anchors ...>``,
...) and the line that row would have in ``frame.to_csv(index=False)`` (row position +
2), unless the frame came from :func:`read_measurements` & co., whose errors name the
source file and line.  The functions keep no global state (no redirected streams, no
temporary files), so they can be called from several threads.
"""

from __future__ import annotations

import contextlib
import json
import os
import sys
import warnings
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from pathlib import Path
from typing import Any, Literal, Union

import pandas as pd

from robustloc.errors import InputError

if sys.version_info >= (3, 11):
    from importlib.resources.abc import Traversable
else:  # (the same protocol, under its older name)
    from importlib.abc import Traversable

__all__ = [
    "RobustlocWarning",
    "calibrate",
    "evaluate",
    "locate",
    "read_anchors",
    "read_measurements",
    "read_positions",
    "read_truth",
    "spp",
    "track",
    "write_positions",
]

#: A file path as a str or :class:`os.PathLike` (a file written).
PathLike = Union[str, "os.PathLike[str]"]
#: A file read: a str, an :class:`os.PathLike`, or an :mod:`importlib.resources`
#: ``Traversable`` such as ``files("robustloc") / "data" / ...`` (a :class:`pathlib.Path`
#: for a package installed as files; one inside an archive is refused with a hint:
#: :func:`importlib.resources.as_file` gives a file to read).
InputPath = Union[str, "os.PathLike[str]", Traversable]
#: A contract table held in memory, or a file holding one (CSV / Parquet; as
#: :data:`InputPath`).
FrameOrPath = Union[pd.DataFrame, str, "os.PathLike[str]", Traversable]


class RobustlocWarning(UserWarning):
    """A note or warning the command line prints on stderr (``note: ...``,
    ``warning: ...``), raised through :mod:`warnings` by the API."""


# --------------------------------------------------------------------------------------
# inputs and errors
# --------------------------------------------------------------------------------------


class _InputTypeError(InputError, TypeError):
    """An argument of the wrong type (``None`` or a number for a path, a Series for a
    frame): an :class:`InputError`, as every mistake in a call is, and the
    :class:`TypeError` Python raises for a wrong type."""


def _path(src: object, what: str, expected: str = "a path") -> str:
    """``src`` (str or PathLike, which includes the ``Traversable`` that
    ``importlib.resources.files`` gives for a package installed as files) as a str;
    anything else is an :class:`InputError` (and :class:`TypeError`) naming ``what``:
    ``WHAT: expected a path, got NoneType``, or for a resource that is no file (inside a
    zip archive) the way to one."""
    if isinstance(src, (str, os.PathLike)):
        path = os.fspath(src)
        if isinstance(path, str):
            return path
    if isinstance(src, Traversable):
        raise _InputTypeError(
            f"{what}: {src} ({type(src).__name__}) is a resource, not a file on the file "
            "system: read it through `with importlib.resources.as_file(resource) as path:`")
    raise _InputTypeError(f"{what}: expected {expected}, got {type(src).__name__}")


def _source(src: object, what: str) -> pd.DataFrame | str:
    """``src`` as a table input: a DataFrame as given, a path as a str; anything else is
    an :class:`InputError` (and :class:`TypeError`) naming ``what``."""
    if isinstance(src, pd.DataFrame):
        return src
    return _path(src, what, "a DataFrame or a path")


@contextlib.contextmanager
def _labelled() -> Iterator[None]:
    """An :class:`OSError` about a user's path becomes the :class:`InputError` the command
    line prints (``error: PATH: what``); inputs spooled from standard input or a FIFO
    live as long as the call (:func:`robustloc.io.tables.spool_scope`)."""
    from robustloc.io.atomic import describe_oserror
    from robustloc.io.tables import spool_scope

    try:
        with spool_scope():  # standard input / a FIFO: read anew by each call
            yield
    except OSError as exc:
        name = exc.filename if exc.filename is not None else exc.filename2
        if name is None:
            raise
        raise InputError(describe_oserror(exc), str(name)) from None


def _check_option(flag: str, value: Any, check: Callable[[str], object]) -> Any:
    """Refuse ``value`` as the command line refuses ``flag VALUE`` (a converter of
    :mod:`robustloc.options`): :class:`InputError` ``argument FLAG: ...``, the words
    :func:`robustloc.options.check_settings` gives a settings field.  Returns the value
    to use: text as the converter reads it, anything else as given."""
    import argparse

    arg = (str(value) if isinstance(value, (int, float)) and not isinstance(value, bool)
           else value)
    try:
        converted = check(arg)
    except (argparse.ArgumentTypeError, ValueError, TypeError) as exc:
        raise InputError(f"argument {flag}: {exc}") from None
    # a value given as text is used as the command line reads it (evaluate's
    # time_tolerance="1" reached the matching code as text: the API review)
    return converted if isinstance(value, str) else value


def _labelled_frame(df: pd.DataFrame, what: str) -> pd.DataFrame:
    """A frame whose rows the validators can name: its own ``line`` index and ``path``
    (read from a file) or the line of ``df.to_csv(index=False)`` in ``<what DataFrame>``."""
    if not (df.index.name == "line" and df.attrs.get("path")):
        df = df.copy()
        df.index = pd.RangeIndex(2, len(df) + 2, name="line")
        df.attrs["path"] = f"<{what} DataFrame>"
        df = _stripped_names(df)
    _refuse_duplicate_columns(df)
    return df


def _stripped_names(df: pd.DataFrame) -> pd.DataFrame:
    """The frame with its column names stripped of surrounding spaces, as a CSV header's
    are (``" time"`` is ``time``); the caller's frame is not changed."""
    names = [c.strip() if isinstance(c, str) else c for c in df.columns]
    return df if names == list(df.columns) else df.set_axis(names, axis=1)


def _robust_choice(robust: object) -> str | None:
    """``calibrate``'s ``robust``: ``True`` (Huber), ``False`` or ``None`` (plain), or a
    weight's name; anything else is an :class:`InputError` (``robust=0`` and ``""`` were
    taken as plain, ``1`` refused as a weight's name: the API review)."""
    import numpy as np

    if isinstance(robust, (bool, np.bool_)):
        return "huber" if robust else None
    if robust is None or (isinstance(robust, str) and robust):
        return robust
    raise _InputTypeError(f"robust: expected True, False or a weight's name, got {robust!r}")


def _flag(name: str, value: object) -> bool:
    """A yes/no argument: ``True`` or ``False`` (NumPy's too); anything else (``"no"``,
    ``0``, a list) is an :class:`InputError` (and :class:`TypeError`): Python would take a
    non-empty string such as ``"no"`` as true."""
    import numpy as np

    if isinstance(value, (bool, np.bool_)):
        return bool(value)
    raise _InputTypeError(f"{name}: expected True or False, got {value!r}")


def _link_offsets(value: object) -> bool | str:
    """``link_offsets`` as :class:`~robustloc.pipelines.track.TrackSettings` takes it:
    ``True`` / ``False`` (NumPy's too), or the words of ``--link-offsets on|off|auto``
    (``"on"`` is ``True``, ``"off"`` ``False``); anything else is an :class:`InputError`
    (and :class:`TypeError` for a value that is neither a flag nor a word)."""
    import numpy as np

    words: dict[str, bool | str] = {"on": True, "off": False, "auto": "auto"}
    if isinstance(value, str) and value in words:
        return words[value]
    if isinstance(value, (bool, np.bool_)):
        return bool(value)
    text = f"link_offsets: expected True, False, 'on', 'off' or 'auto', got {value!r}"
    raise InputError(text) if isinstance(value, str) else _InputTypeError(text)


def _refuse_duplicate_columns(df: pd.DataFrame, what: str | None = None) -> None:
    """A column named twice is an error naming the frame (its ``attrs["path"]``, else
    ``<what DataFrame>``), as a file's header naming a column twice is (pandas would raise
    a raw error on ``df[name]``, or use either)."""
    dup = df.columns.duplicated()
    if dup.any():
        name = str(df.columns[int(dup.argmax())])
        where = df.attrs.get("path") or (None if what is None else f"<{what} DataFrame>")
        raise InputError(f"duplicate column {name!r}", where)


# --------------------------------------------------------------------------------------
# contract files
# --------------------------------------------------------------------------------------


def _as_anchor_frame(anchors: FrameOrPath | None) -> pd.DataFrame | None:
    return None if anchors is None else read_anchors(anchors)


def read_anchors(source: FrameOrPath) -> pd.DataFrame:
    """Read (or check) an anchors table: ``anchor, x, y[, z]`` + optional parameters.

    Parameters
    ----------
    source : DataFrame, str, PathLike or Traversable
        A CSV or Parquet file, or a frame with the same columns.

    Returns
    -------
    DataFrame
        ``anchor`` (str), ``x, y[, z]`` (float, m), and when present the path-loss
        columns ``A, n`` or ``p0, gamma, faf, d0``, the range calibration ``bias, scale``
        and ``sigma`` (float; empty = NaN).  Index: source line.

    Raises
    ------
    InputError
        A missing column, a non-numeric or non-finite coordinate, a duplicate or empty
        anchor id, with file and line.

    Examples
    --------
    >>> import pandas as pd
    >>> import robustloc
    >>> robustloc.read_anchors(  # doctest: +NORMALIZE_WHITESPACE
    ...     pd.DataFrame({"anchor": ["a", "b"], "x": [0, 10], "y": [0, 0]}))
         anchor     x    y
    line
    2         a   0.0  0.0
    3         b  10.0  0.0
    >>> robustloc.read_anchors(pd.DataFrame({"anchor": ["a", "a"], "x": [0, 1], "y": [0, 0]}))
    Traceback (most recent call last):
    ...
    robustloc.errors.InputError: <anchors DataFrame>:3: duplicate anchor id 'a'
    """
    from robustloc import io

    src = _source(source, "anchors")
    if isinstance(src, pd.DataFrame):
        df = _labelled_frame(src, "anchors")
        return io.validate_anchors(df, df.attrs.get("path"))
    with _labelled():
        return io.read_anchors(src)


def read_measurements(
    source: FrameOrPath, anchors: FrameOrPath | Sequence[str] | None = None
) -> pd.DataFrame:
    """Read (or check) a measurements log: ``time, tag, anchor`` + ``rssi`` or ``range``.

    Parameters
    ----------
    source : DataFrame, str, PathLike or Traversable
        A CSV or Parquet file (rows in any order), or a frame with the same columns.
    anchors : DataFrame, path or sequence of str, optional
        When given, an anchor id not among them is an error naming its line.

    Returns
    -------
    DataFrame
        ``time`` (float s), ``tag``, ``anchor`` (str), ``rssi`` (dBm) or ``range`` (m);
        extra columns kept; index = source line; ``attrs["value"]`` names the value
        column.

    Raises
    ------
    InputError
        A missing column, a NaN or non-numeric value or time, an empty id, an unknown
        anchor, both or neither of ``rssi``/``range``, with file and line.

    Examples
    --------
    >>> import pandas as pd
    >>> import robustloc
    >>> log = pd.DataFrame({"time": [0.0, 0.0], "tag": "t", "anchor": ["a", "b"],
    ...                     "range": [1.5, None]})
    >>> robustloc.read_measurements(log)
    Traceback (most recent call last):
    ...
    robustloc.errors.InputError: <measurements DataFrame>:3: column 'range': missing or NaN value
    """
    from robustloc import io

    src = _source(source, "measurements")
    known: pd.DataFrame | Sequence[str] | None
    if anchors is None or isinstance(anchors, (pd.DataFrame, str, os.PathLike, Traversable)):
        known = _as_anchor_frame(anchors)
    elif isinstance(anchors, Iterable):
        known = [str(a) for a in anchors]
    else:
        raise _InputTypeError(f"anchors: expected a DataFrame, a path or a sequence of "
                              f"anchor ids, got {type(anchors).__name__}")
    if isinstance(src, pd.DataFrame):
        df = _labelled_frame(src, "measurements")
        if len(df) == 0:  # as an empty file is, and as read_truth refuses an empty frame
            raise InputError("measurements file has a header but no data rows",
                             df.attrs.get("path"), 2)
        return io.validate_measurements(df, df.attrs.get("path"), known)
    with _labelled():
        return io.read_measurements(src, known)


def read_truth(source: FrameOrPath) -> pd.DataFrame:
    """Read (or check) a truth table: ``time, tag, x, y[, z]``, all finite.

    Parameters
    ----------
    source : DataFrame, str, PathLike or Traversable
        A CSV or Parquet file, or a frame with the same columns.

    Examples
    --------
    >>> import pandas as pd
    >>> import robustloc
    >>> robustloc.read_truth(  # doctest: +NORMALIZE_WHITESPACE
    ...     pd.DataFrame({"time": [0.0], "tag": [7], "x": [1], "y": [2]}))
          time tag    x    y
    line
    2      0.0   7  1.0  2.0
    """
    from robustloc import io

    src = _source(source, "truth")
    if isinstance(src, pd.DataFrame):
        df = _labelled_frame(src, "truth")
        return io.validate_truth(df, df.attrs.get("path"))
    with _labelled():
        return io.read_truth(src)


def read_positions(source: FrameOrPath) -> pd.DataFrame:
    """Read (or check) a positions table (``time, tag, x, y[, z], method, status, ...``).

    Empty coordinates are allowed (a failed epoch; its ``status`` says why); ``method``
    and ``status`` default to ``unknown`` and ``ok`` when absent.

    Parameters
    ----------
    source : DataFrame, str, PathLike or Traversable
        A CSV or Parquet file, or a frame with the same columns.

    Examples
    --------
    >>> import pandas as pd
    >>> import robustloc
    >>> robustloc.read_positions(  # doctest: +NORMALIZE_WHITESPACE
    ...     pd.DataFrame({"time": [0.0], "tag": ["t"], "x": [1.0], "y": [2.0]})
    ... )[["method", "status"]]
           method status
    line
    2     unknown     ok
    """
    from robustloc import io

    src = _source(source, "positions")
    if isinstance(src, pd.DataFrame):
        df = _labelled_frame(src, "positions")
        return io.validate_positions(df, df.attrs.get("path"))
    with _labelled():
        return io.read_positions(src)


def write_positions(positions: pd.DataFrame, path: PathLike) -> Path:
    """Write a positions frame (contract columns first), CSV or Parquet by extension.

    Written atomically: after an error nothing is left at ``path``.  Floats keep full
    precision, so reading the file back gives the same numbers.

    Parameters
    ----------
    positions : DataFrame
        Positions with at least the contract columns (``time, tag, x, y[, z], method,
        status, n_used, sigma0, excluded``); extra columns are written after them.
    path : str or PathLike
        Output file: ``.parquet`` for Parquet, anything else CSV (``.gz`` compressed).

    Returns
    -------
    Path
        ``path``.

    Raises
    ------
    InputError
        A contract column is missing, or the file cannot be written; ``positions`` not a
        DataFrame or ``path`` not a path (also a :class:`TypeError`).

    Examples
    --------
    >>> import tempfile, pathlib
    >>> import pandas as pd
    >>> import robustloc
    >>> pos = pd.DataFrame({"time": [0.0], "tag": ["t"], "x": [1.0], "y": [2.0],
    ...                     "method": ["nls"], "status": ["ok"], "n_used": [4],
    ...                     "sigma0": [0.1], "excluded": [""]})
    >>> with tempfile.TemporaryDirectory() as d:
    ...     out = robustloc.write_positions(pos, pathlib.Path(d) / "positions.csv")
    ...     print(out.read_text().splitlines()[0])
    time,tag,x,y,method,status,n_used,sigma0,excluded
    """
    from robustloc import io

    if not isinstance(positions, pd.DataFrame):
        raise _InputTypeError(f"positions: expected a DataFrame, got "
                              f"{type(positions).__name__}")
    path = _path(path, "path")
    _refuse_duplicate_columns(positions, "positions")  # a file read_positions refuses
    try:
        return io.write_positions(positions, path)
    except InputError:
        raise
    except ValueError as exc:  # the missing-column check of io.write_positions
        raise InputError(str(exc), path) from None


# --------------------------------------------------------------------------------------
# the commands
# --------------------------------------------------------------------------------------

Method = Literal["auto", "ls", "wls", "nls", "huber", "hampel", "igg", "igg3", "asym",
                 "lege", "snooping"]


def locate(
    measurements: FrameOrPath,
    anchors: FrameOrPath,
    method: str | Sequence[str] = "auto",
    *,
    dim: Literal[2, 3] = 2,
    solver: Literal["nonlinear", "linearized"] = "nonlinear",
    reference: Literal["first", "nearest"] = "first",
    domain: Literal["range", "rssi"] = "range",
    sigma: float | None = None,
    robust_scale: Literal["log", "mad", "apriori"] = "log",
    alert_limit: float | None = None,
    k_noise: float | None = None,
    min_scale: float = 0.0,
    params: Mapping[str, float] | None = None,
    model: Literal["log-distance", "attenuation-factor", "friis"] | None = None,
    tag_height: float | None = None,
    range_calibration: bool = True,
    alpha0: float = 0.001,
    beta0: float = 0.10,
    chunk_rows: int = 500_000,
    side_prior: Literal["log", "none"] = "log",
) -> pd.DataFrame:
    r"""Position fixes for every epoch of a measurements log (``robustloc locate``).

    Every epoch (one ``time`` and ``tag``) gets one row per method with a ``status``;
    each fix is tested and carries a protection level (:mod:`robustloc.integrity.fixes`).
    RSSI is turned into ranges by the anchors' path-loss model, each with
    :math:`\sigma_d = d \ln 10\, \sigma_{dB} / (10 n)` (seed 000 eq. 1); ranges are
    corrected by the anchors' ``bias``/``scale``: :math:`r_c = (r - b) / s`.

    Parameters
    ----------
    measurements : DataFrame, str, PathLike or Traversable
        ``time, tag, anchor`` and ``rssi`` (dBm) or ``range`` (m); rows in any order.
    anchors : DataFrame, str, PathLike or Traversable
        ``anchor, x, y[, z]`` (m) and optional ``A, n`` / ``p0, gamma, faf, d0`` /
        ``bias, scale`` / ``sigma`` columns (see :func:`calibrate`).
    method : str or sequence of str
        ``auto`` (default), ``ls``, ``wls``, ``nls``, ``huber``, ``hampel``, ``igg``,
        ``igg3``, ``asym``, ``lege``, ``snooping``; several give several rows per epoch
        (``docs/choosing-a-method.md``).  ``auto`` is "test, then robustify": Gauss-Newton
        on every epoch, each fix tested; a fix that passes is kept, and so is one whose
        test fails only by the ranges the w-test names (``fault_detected``, its ``hpl``
        widened); the epochs whose test fails without naming the ranges at fault (or
        that are ``unavailable``) are solved again by ``huber`` with the log's noise
        scale and tested again.  A log whose first pass (``robust_scale="log"``, the
        default) finds more than 3.3 % gross residuals (beyond 4 sigma;
        :data:`robustloc.integrity.fixes.AUTO_GROSS_SHARE`) is solved by ``igg`` on every
        epoch instead.
    dim, solver, reference, domain, robust_scale, model
        As the ``robustloc locate`` options of the same name (``--robust-scale`` is
        ``robust_scale``); see ``robustloc locate --help``.
    sigma, alert_limit, k_noise, min_scale, tag_height, alpha0, beta0, chunk_rows
        As the options of the same name: ``sigma`` in m or dB, ``alert_limit`` and
        ``tag_height`` in m.
    params : mapping of str to float, optional
        Weight-function thresholds (``--param NAME=VALUE``), e.g. ``{"c": 1.5}``.
    range_calibration : bool
        Apply the anchors' ``bias``/``scale`` columns (``False`` is
        ``--no-range-calibration``).
    side_prior : {"log", "none"}
        Nearly collinear anchors: place a fix that fits either side of their line on the
        side where the log's unambiguous fixes lie (``--side-prior``).

    Returns
    -------
    DataFrame
        The positions contract: ``time, tag, x, y[, z], method, status, n_used,
        sigma0, excluded`` and the integrity columns (``hpl``, ...), one row per epoch and
        method, in time order; ``attrs["summary"]`` is the run summary (status counts,
        duplicate and invalid rows, timings, ``anchors_not_used``, ``anchors_suspect``).

    Warns
    -----
    RobustlocWarning
        An anchor lies far outside the others (more than 20 times their median spread:
        a typo?) and is not used by any fix, or its measurements disagree with the fixes
        far more than the median anchor's (its noise scale over the log above
        :data:`robustloc.pipelines.locate.SUSPECT_SCALE_RATIO` times the median's), as
        the command warns.

    Raises
    ------
    InputError
        A malformed input (file and line, or ``<measurements DataFrame>`` and the row's
        CSV line) or a refused option, with the command line's message.

    See Also
    --------
    robustloc.estimators.ranging.Locator : the array-level solver.

    Examples
    --------
    Four anchors at the corners of a 10 m square and one tag at (3, 4) m, two epochs:

    >>> import numpy as np
    >>> import pandas as pd
    >>> import robustloc
    >>> anchors = pd.DataFrame({"anchor": ["a", "b", "c", "d"],
    ...                         "x": [0.0, 10.0, 10.0, 0.0], "y": [0.0, 0.0, 10.0, 10.0]})
    >>> d = np.hypot(anchors.x - 3.0, anchors.y - 4.0)
    >>> log = pd.DataFrame({"time": np.repeat([0.0, 1.0], 4), "tag": "t1",
    ...                     "anchor": np.tile(anchors.anchor, 2),
    ...                     "range": np.tile(d, 2) + [0.02, -0.01, 0.03, 0.0,
    ...                                               -0.02, 0.01, 0.0, 0.02]})
    >>> pos = robustloc.locate(log, anchors)
    >>> pos[["time", "tag", "x", "y", "method", "status"]].round(1)
       time tag    x    y method status
    0   0.0  t1  3.0  4.0   auto     ok
    1   1.0  t1  3.0  4.0   auto     ok

    A mistake is an :class:`InputError` naming the row:

    >>> robustloc.locate(log.assign(anchor=log.anchor.replace("d", "e")), anchors)
    Traceback (most recent call last):
    ...
    robustloc.errors.InputError: <measurements DataFrame>:5: unknown anchor id 'e' (not in ...)
    """
    from robustloc.pipelines.locate import LocateSettings, run_locate

    with _labelled():
        settings = LocateSettings(
            method=_method_names(method), dim=dim,
            solver=solver, reference=reference, domain=domain, sigma=sigma,
            robust_scale=robust_scale, alert_limit=alert_limit, k_noise=k_noise,
            min_scale=min_scale, param=_param_items(params), model=model,
            tag_height=tag_height,
            range_calibration=_flag("range_calibration", range_calibration), alpha0=alpha0,
            beta0=beta0, chunk_rows=chunk_rows, side_prior=side_prior)
        anchor_frame, source = _log_inputs(measurements, anchors)
        frame, summary = run_locate(source, anchor_frame, settings)
    from robustloc.pipelines.locate import anchor_warnings

    for line in anchor_warnings(summary, anchor_frame.attrs.get("path")):  # the command's
        warnings.warn(line, RobustlocWarning, stacklevel=2)
    return _with_summary(frame, summary)


def _method_names(method: object) -> tuple[str, ...]:
    """``"huber"`` -> ``("huber",)``, a sequence of names as a tuple (checked by the
    settings as ``--method``); no name at all is the command's refusal of an empty one."""
    if isinstance(method, str):
        return (method,)
    if isinstance(method, Iterable) and not isinstance(method, (bytes, Mapping)):
        return tuple(method)
    from robustloc.pipelines.locate import methods_known

    raise InputError(f"argument --method: expected one or more of "
                     f"{', '.join(methods_known())}, got {method!r}")


def _param_items(params: Mapping[str, float] | None) -> tuple[str, ...]:
    """``{"c": 1.5}`` -> ``("c=1.5",)``, the ``--param`` items (floats exact; a value that
    is not a number is passed as text, for the settings to refuse as the command does)."""
    if params is None:
        return ()
    if not isinstance(params, Mapping):
        raise InputError(f"argument --param: expected a mapping of NAME to NUMBER, got "
                         f"{type(params).__name__}")

    def item(name: object, value: object) -> str:
        try:
            return f"{name}={float(value)!r}"  # type: ignore[arg-type]
        except (TypeError, ValueError):
            return f"{name}={value}"

    return tuple(item(k, v) for k, v in params.items())


def _log_inputs(measurements: FrameOrPath, anchors: FrameOrPath
                ) -> tuple[pd.DataFrame, str | pd.DataFrame]:
    """A log and its anchors as the pipelines take them: the anchors validated (a frame
    named ``<anchors DataFrame>`` in errors), the log a path or an in-memory source
    (validated as it streams, like a file)."""
    from robustloc.io.tables import in_memory_source

    anchor_src = _source(anchors, "anchors")
    source = _source(measurements, "measurements")
    if isinstance(source, pd.DataFrame):
        source = in_memory_source(_stripped_names(source))
        _refuse_duplicate_columns(source)
    return read_anchors(anchor_src), source


def _with_summary(frame: pd.DataFrame | None, summary: dict[str, object]) -> pd.DataFrame:
    """The pipeline's in-memory output with its run summary in ``attrs["summary"]`` (the
    command's ``--json`` text, as plain JSON types)."""
    out = pd.DataFrame() if frame is None else frame.reset_index(drop=True)
    out.attrs = {"summary": json.loads(json.dumps(summary))}
    return out


def track(
    measurements: FrameOrPath,
    anchors: FrameOrPath,
    *,
    model: Literal["cv", "ca", "static"] = "cv",
    filter: Literal["ekf", "ukf"] = "ekf",  # noqa: A002 - the command line's name
    q: float = 1.0,
    weight: str | None = None,
    domain: Literal["range", "rssi"] = "range",
    sigma: float | None = None,
    smooth: bool = False,
    fixed_lag: int | None = None,
    engine: Literal["compiled", "numpy"] = "compiled",
    cusum_h: float | None = None,
    tag_height: float | None = None,
    alpha0: float = 0.001,
    beta0: float = 0.10,
    integrity_risk: float = 0.001,
    chunk_rows: int = 500_000,
    range_offset: bool = False,
    range_offset_sd: float = 0.5,
    range_offset_q: float = 1e-4,
    link_offsets: bool | Literal["on", "off", "auto"] = "auto",
    link_offset_sd: float | None = None,
    link_offset_q: float = 0.0,
    noise_scale_min: float = 1.0,
    noise_scale_max: float = 4.0,
) -> pd.DataFrame:
    r"""Tracks for every tag of a measurements log (``robustloc track``).

    A tight robust filter per tag (:class:`robustloc.tracking.Tracker`): every epoch's anchor
    observations update it directly, one row per input epoch with a ``status`` and
    ``hpl``.

    Parameters
    ----------
    measurements : DataFrame, str, PathLike or Traversable
        ``time, tag, anchor`` and ``rssi`` (dBm) or ``range`` (m); rows in any order.
    anchors : DataFrame, str, PathLike or Traversable
        ``anchor, x, y[, z]`` and optional path-loss / ``bias, scale, sigma`` columns.
    model, filter, q, weight, domain, sigma, smooth, fixed_lag, cusum_h
        As the ``robustloc track`` options of the same name (see its ``--help``);
        ``smooth`` and ``fixed_lag`` are exclusive (one smoother or the other).
    engine : {"compiled", "numpy"}
        The tracker's kernels (``robustloc track --kernel``; ``Tracker(engine=...)``).
    tag_height, alpha0, beta0, integrity_risk, chunk_rows, noise_scale_min, noise_scale_max
        As the options of the same name (the last two bound the adaptive measurement
        noise scale, ``--noise-scale-min`` and ``--noise-scale-max``).
    range_offset, range_offset_sd, range_offset_q
        Ranges: estimate each tag's common range offset (m) as one more state, its
        a-priori standard deviation (m) and random-walk growth (m^2/s)
        (``--range-offset``; columns ``range_offset, var_range_offset``).
    link_offsets, link_offset_sd, link_offset_q
        Estimate an offset of each link of each tag (dB of RSSI, m of ranges) as one more
        state per anchor, its a-priori standard deviation (None: 1 dB or 0.1 m) and
        random-walk growth (``--link-offsets``; the summary's ``link_offset_db`` or
        ``link_offset_m`` gives each tag's final offsets).  Not with ``range_offset``.
        ``link_offsets`` takes ``True`` / ``False`` or the command's words ``"on"`` /
        ``"off"``; ``"auto"`` (the default): the log's first epochs choose
        (``--link-offsets auto``; the summary's ``link_offsets_auto`` says what and why;
        with ``range_offset`` they are left out).

    Returns
    -------
    DataFrame
        The track format: ``time, tag, x, y, vx, vy[, ax, ay], method, status, var_x,
        var_y, cov_xy, ..., hpl``; ``attrs["summary"]`` is the run summary.

    Raises
    ------
    InputError
        A malformed input or a refused option, with the command line's message.

    Examples
    --------
    >>> import numpy as np
    >>> import pandas as pd
    >>> import robustloc
    >>> anchors = pd.DataFrame({"anchor": ["a", "b", "c", "d"],
    ...                         "x": [0.0, 10.0, 10.0, 0.0], "y": [0.0, 0.0, 10.0, 10.0]})
    >>> t = np.arange(20) * 0.5
    >>> xy = np.c_[2.0 + 0.3 * t, np.full(t.size, 5.0)]
    >>> d = np.hypot(anchors.x.to_numpy() - xy[:, :1], anchors.y.to_numpy() - xy[:, 1:])
    >>> log = pd.DataFrame({"time": np.repeat(t, 4), "tag": "t1",
    ...                     "anchor": np.tile(anchors.anchor, t.size), "range": d.ravel()})
    >>> trk = robustloc.track(log, anchors)
    >>> len(trk), bool(np.all(np.hypot(trk.x - xy[:, 0], trk.y - xy[:, 1]) < 0.1))
    (20, True)
    """
    from robustloc.pipelines.track import TrackSettings, run_track

    smooth = _flag("smooth", smooth)
    if smooth and fixed_lag is not None:  # the command's mutually exclusive options
        raise InputError("argument --fixed-lag: not allowed with argument --smooth")
    with _labelled():
        settings = TrackSettings(
            model=model, filter=filter, q=q, weight=weight, domain=domain, sigma=sigma,
            smooth=smooth, fixed_lag=fixed_lag, kernel=engine, cusum_h=cusum_h,
            tag_height=tag_height, alpha0=alpha0, beta0=beta0,
            integrity_risk=integrity_risk, chunk_rows=chunk_rows,
            range_offset=_flag("range_offset", range_offset), range_offset_sd=range_offset_sd,
            range_offset_q=range_offset_q, link_offsets=_link_offsets(link_offsets),
            link_offset_sd=link_offset_sd, link_offset_q=link_offset_q,
            noise_scale_min=noise_scale_min, noise_scale_max=noise_scale_max)
        anchor_frame, source = _log_inputs(measurements, anchors)
        frame, summary = run_track(source, anchor_frame, settings)
    return _with_summary(frame, summary)


def _validated_measurements(
    df: pd.DataFrame, path: str | None, anchors: pd.DataFrame | None
) -> pd.DataFrame:
    from robustloc import io

    return io.validate_measurements(df, path, anchors)


def _validated_survey(
    df: pd.DataFrame, path: str | None, anchors: pd.DataFrame | None
) -> pd.DataFrame:
    from robustloc import io

    return io.validate_survey(df, path, anchors)


def _validated_truth(df: pd.DataFrame, path: str | None) -> pd.DataFrame:
    from robustloc import io

    return io.validate_truth(df, path)


def calibrate(
    survey: FrameOrPath | None = None,
    anchors: FrameOrPath | None = None,
    *,
    model: Literal["log-distance", "attenuation-factor", "friis"] = "log-distance",
    robust: bool | str | None = None,
    scale: bool | None = None,
    pooled: bool = False,
    d0: float = 1.0,
    p0: float | None = None,
    measurements: FrameOrPath | None = None,
    truth: FrameOrPath | None = None,
    time_tolerance: float = 1e-6,
    self_log: FrameOrPath | None = None,
    dim: Literal[2, 3] = 2,
    tag_height: float | None = None,
    se_ratio: float = 3.0,
) -> pd.DataFrame:
    r"""Fit path-loss parameters (RSSI) or range bias/scale per anchor (``robustloc calibrate``).

    Three ways, as on the command line:

    * a **survey** (``anchor, distance, rssi|range``): per anchor and pooled, the
      log-distance model :math:`RSSI = A - 10 n \lg d` (seed 000 eq. 1), the
      attenuation-factor or Friis model (seed 002 eqs. 4-5), or for ranges
      :math:`r = s\,d + b`;
    * ``measurements`` + ``truth`` (+ ``anchors``): the survey built from positioned data;
    * ``self_log`` + ``anchors``: **self-calibration** without truth, the parameters and
      every epoch's position adjusted jointly (:mod:`robustloc.models.selfcal`).

    Parameters
    ----------
    survey : DataFrame, str, PathLike or Traversable, optional
        The survey.
    anchors : DataFrame, str, PathLike or Traversable, optional
        Anchors to add the fitted columns to (required by ``measurements`` and
        ``self_log``).
    model : {"log-distance", "attenuation-factor", "friis"}
        Path-loss model for RSSI data.
    robust : bool or str, optional
        Robust IRLS fit: ``True`` (huber) or a weight name (``hampel``, ``igg``, ``igg3``).
    scale : bool, optional
        Range data: fit a scale factor too (default no for a survey, yes for ``self_log``).
    pooled, d0, p0, time_tolerance, dim, tag_height, se_ratio
        As the ``robustloc calibrate`` options of the same name.
    measurements, truth : DataFrame, str, PathLike or Traversable, optional
        Positioned data to build the survey from.
    self_log : DataFrame, str, PathLike or Traversable, optional
        A measurements log for self-calibration (``--self``).

    Returns
    -------
    DataFrame
        The anchors with the fitted columns (``A, n`` or ``bias, scale``, ``sigma``, their
        standard errors, ``calib_source``), or without ``anchors`` the parameter table;
        ``attrs["summary"]`` holds the fit table and notes (``--json``).

    Raises
    ------
    InputError
        A malformed input, or a survey that cannot determine a parameter (the anchor and
        parameter named), with the command line's message.

    Examples
    --------
    A range survey of two anchors, each reading 5 % long and 0.3 m late:

    >>> import numpy as np
    >>> import pandas as pd
    >>> import robustloc
    >>> d = np.array([1.0, 2.0, 4.0, 6.0, 8.0])
    >>> noise = [0.01, -0.02, 0.0, 0.02, -0.01]
    >>> survey = pd.DataFrame({"anchor": np.repeat(["a", "b"], 5), "distance": np.tile(d, 2),
    ...                        "range": np.tile(1.05 * d + 0.3 + noise, 2)})
    >>> anchors = pd.DataFrame({"anchor": ["a", "b"], "x": [0.0, 5.0], "y": [0.0, 0.0]})
    >>> cal = robustloc.calibrate(survey, anchors, scale=True)
    >>> cal[["anchor", "bias", "scale"]].round(2)
      anchor  bias  scale
    0      a   0.3   1.05
    1      b   0.3   1.05
    """
    from robustloc.pipelines.calibrate import CalibrateSettings, run_calibrate

    with _labelled():
        settings = CalibrateSettings(
            model=model, robust=_robust_choice(robust),
            scale=None if scale is None else _flag("scale", scale),
            pooled=_flag("pooled", pooled), d0=d0, p0=p0, time_tolerance=time_tolerance,
            dim=dim, tag_height=tag_height, se_ratio=se_ratio)
        anchor_frame = _as_anchor_frame(anchors)
        cal = run_calibrate(
            settings,
            survey=_checked(survey, "survey",
                            lambda df, p: _validated_survey(df, p, anchor_frame)),
            anchors=anchor_frame,
            measurements=_checked(measurements, "measurements",
                                  lambda df, p: _validated_measurements(df, p, anchor_frame)),
            truth=_checked(truth, "truth", _validated_truth),
            self_log=_checked(self_log, "measurements",
                              lambda df, p: _validated_measurements(df, p, anchor_frame)))
    for text in cal.notes + cal.warnings:
        warnings.warn(text, RobustlocWarning, stacklevel=2)
    return _with_summary(cal.output, cal.summary)


def _checked(src: FrameOrPath | None, what: str,
             validate: Callable[[pd.DataFrame, str | None], pd.DataFrame]
             ) -> str | pd.DataFrame | None:
    """An optional input as a pipeline takes it: a path as given, a frame validated (its
    errors name ``<what DataFrame>`` and the row's CSV line)."""
    if src is None:
        return None
    checked = _source(src, what)
    if isinstance(checked, pd.DataFrame):
        df = _labelled_frame(checked, what)
        return validate(df, df.attrs.get("path"))
    return checked


def evaluate(
    positions: FrameOrPath,
    truth: FrameOrPath,
    *,
    baseline: str = "ls",
    time_tolerance: float = 1e-6,
    plot: PathLike | None = None,
) -> pd.DataFrame:
    """Error statistics of positions against truth, per tag and method (``robustloc evaluate``).

    Each position is matched to the truth of its tag at the same time (within
    ``time_tolerance`` s); over the epochs with a usable fix: max, min, mean, RMS (the
    paper's sigma0), spread sigma1, median and 95th percentile of the horizontal error
    (3-D too when both have ``z``), failed and missing epochs, and the improvement of mean
    and RMS over ``baseline`` in %.  Tag ``all`` pools every epoch, tag ``mean`` averages
    the per-tag rows (the paper's Table 1 average rows).

    Parameters
    ----------
    positions : DataFrame, str, PathLike or Traversable
        Positions (from :func:`locate`, or a file).
    truth : DataFrame, str, PathLike or Traversable
        ``time, tag, x, y[, z]``.
    baseline : str
        Method the improvements refer to: ``ls`` (its improvements are NaN when the
        positions have no ``ls`` rows) or one of the positions' methods.
    time_tolerance : float
        Largest absolute time difference between a position and its truth (s), finite
        and >= 0.
    plot : str or PathLike, optional
        Also draw the figure of ``evaluate --plot`` into this ``.png``, ``.svg`` or ``.pdf``
        file (:func:`robustloc.eval.plots.evaluation_figure`: the error CDF, a map of the
        fixes over the truth, each method's Stanford diagram).

    Returns
    -------
    DataFrame
        One row per tag and method (plus ``all`` and ``mean``), the command's ``-o`` table;
        ``attrs["summary"]["n_unmatched"]`` counts positions without truth.

    Examples
    --------
    >>> import pandas as pd
    >>> import robustloc
    >>> truth = pd.DataFrame({"time": [0.0, 1.0], "tag": "t", "x": [0.0, 1.0], "y": 0.0})
    >>> pos = truth.assign(x=[0.3, 1.4], method="nls", status="ok")
    >>> robustloc.evaluate(pos, truth)[["tag", "method", "n", "max", "rms"]].round(3)
        tag method    n  max    rms
    0     t    nls  2.0  0.4  0.354
    1   all    nls  2.0  0.4  0.354
    2  mean    nls  2.0  0.4  0.354
    """
    from robustloc.eval.metrics import error_table
    from robustloc.options import figure_path, nonnegative_float

    time_tolerance = _check_option("--time-tolerance", time_tolerance, nonnegative_float)
    if plot is not None:
        from robustloc.io.atomic import check_not_input

        _check_option("--plot", os.fspath(plot) if isinstance(plot, os.PathLike) else plot,
                      figure_path)
        check_not_input(plot, [p for p in (positions, truth)
                               if isinstance(p, (str, os.PathLike))])
    with _labelled():
        pos = read_positions(positions)
        if baseline != "ls" and baseline not in set(pos["method"]):  # as the command
            methods = ", ".join(sorted(set(pos["method"])))
            raise InputError(f"--baseline {baseline!r} is not a method of this file "
                             f"(methods: {methods})", pos.attrs.get("path"))
        tru = read_truth(truth)
        table = error_table(pos, tru, time_tolerance_s=time_tolerance, baseline=baseline)
        if plot is not None:
            from robustloc.eval.metrics import epoch_errors
            from robustloc.eval.plots import evaluation_figure

            evaluation_figure(epoch_errors(pos, tru, time_tolerance), plot,
                              baseline=baseline)
    return _with_summary(table, {"n_unmatched": int(table.attrs.get("n_unmatched", 0))})


def spp(
    obs: InputPath,
    nav: InputPath | Sequence[InputPath] | None = (),
    *,
    sp3: InputPath | None = None,
    clk: InputPath | None = None,
    systems: str = "GREC",
    elevation_mask: float = 15.0,
    iono: Literal["klobuchar", "iflc", "none"] | None = None,
    tropo: Literal["saastamoinen", "none"] = "saastamoinen",
    smooth: int = 0,
    raim: bool = False,
    alpha0: float = 0.001,
    beta0: float = 0.10,
    max_exclusions: int | None = None,
    reference: tuple[float, float, float] | str | None = None,
    inject: Mapping[str, float] | str | None = None,
    inject_from: str | None = None,
    inject_until: str | None = None,
) -> pd.DataFrame:
    """GNSS single-point positioning from RINEX files, with optional RAIM (``robustloc spp``).

    Parameters
    ----------
    obs : str, PathLike or Traversable
        RINEX observation file (2.xx or 3.xx).
    nav : path or sequence of paths
        RINEX navigation file(s) (broadcast ephemerides); may be empty (or ``None``) with
        ``sp3``.
    sp3, clk : str, PathLike or Traversable, optional
        Precise orbit (SP3) and clock (RINEX CLK) products.
    systems : str
        Constellations, e.g. ``"G"`` or ``"GREC"``.
    elevation_mask : float
        Degrees.
    iono : {"klobuchar", "iflc", "none"}, optional
        Default ``iflc`` with ``sp3``, else ``klobuchar``.
    tropo, smooth, alpha0, beta0, max_exclusions, inject_from, inject_until
        As the ``robustloc spp`` options of the same name.
    raim : bool
        Fault detection and exclusion (B-method global test + w-test) and protection
        levels.
    reference : (float, float, float) or str, optional
        ECEF reference position (m) for the summary's errors (default: the RINEX header's
        approximate position); also the command's ``"X,Y,Z"`` text.
    inject : mapping of str to float, or str, optional
        Biases to add (m) per satellite, e.g. ``{"G11": 20.0}`` or the command's
        ``"G11:20"`` text (fault injection).

    Returns
    -------
    DataFrame
        One row per epoch: time, ECEF and geodetic position, clock, status, satellites
        used and excluded, DOP and (with ``raim``) protection levels;
        ``attrs["summary"]`` the run summary (errors against the reference, RAIM counts).

    Examples
    --------
    The GEONET excerpt shipped with the package (GPS, 30 s epochs):

    >>> from importlib.resources import files
    >>> import robustloc
    >>> data = files("robustloc") / "data" / "gnss-geonet"
    >>> sol = robustloc.spp(data / "07590920.05o", data / "07590920_0000-0400.05n",
    ...                     systems="G", raim=True)
    >>> len(sol) > 100, bool((sol["status"] == "ok").mean() > 0.9)
    (True, True)
    """
    from robustloc.pipelines.spp import SppSettings, run_spp

    obs_path = _path(obs, "obs")
    if nav is None:
        nav = ()
    if isinstance(nav, (str, os.PathLike, Traversable)) or not isinstance(nav, Iterable):
        nav = [nav]
    nav_paths = [_path(n, "nav") for n in nav]
    sp3_path = None if sp3 is None else _path(sp3, "sp3")
    clk_path = None if clk is None else _path(clk, "clk")
    with _labelled():
        settings = SppSettings(
            systems=systems, elevation_mask=elevation_mask, iono=iono, tropo=tropo,
            smooth=smooth, raim=_flag("raim", raim), alpha0=alpha0, beta0=beta0,
            max_exclusions=max_exclusions, reference=_spp_reference(reference),
            inject=_spp_inject(inject), inject_from=inject_from, inject_until=inject_until)
        frame, summary = run_spp(obs_path, nav_paths, settings, sp3=sp3_path, clk=clk_path)
    return _with_summary(frame, summary)


def _spp_reference(reference: object) -> tuple[float, float, float] | None:
    """``reference`` as ``SppSettings`` takes it: three numbers, or the command's
    ``"X,Y,Z"`` text; anything else is the command's refusal of ``--reference``."""
    from robustloc.pipelines.spp import check_reference, parse_reference

    if reference is None:
        return None
    if isinstance(reference, str):
        return parse_reference(reference)
    try:
        return check_reference(tuple(reference))  # type: ignore[arg-type]
    except InputError:
        raise
    except (TypeError, ValueError):  # not three numbers: the same refusal, naming them
        return check_reference((), reference)


def _spp_inject(inject: object) -> dict[str, float] | None:
    """``inject`` as ``SppSettings`` takes it: a mapping of satellite to bias (m), or the
    command's ``"PRN:BIAS_M[,...]"`` text; a bias that is not a number is the command's
    refusal of ``--inject``."""
    from robustloc.pipelines.spp import check_inject, parse_inject

    if not inject:
        return None
    if isinstance(inject, str):
        return parse_inject(inject)
    if not isinstance(inject, Mapping):
        raise InputError(f"--inject: expected a mapping of PRN to BIAS_M, got "
                         f"{type(inject).__name__}")
    for sat, bias in inject.items():
        try:
            float(bias)
        except (TypeError, ValueError):
            raise InputError(f"--inject: expected PRN:BIAS_M, got {f'{sat}:{bias}'!r}"
                             ) from None
    return check_inject(inject)
