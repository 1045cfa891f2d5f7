"""Parsing and validation of measurement rows sent to the service (HTTP, WebSocket, MQTT).

A body is a JSON array of rows, or NDJSON (one JSON row per line), or one JSON row.  A row
is an object with the measurements file's columns (design.md, contract)::

    {"time": 12.5, "tag": "T1", "anchor": "A3", "rssi": -71.0}
    {"time": 12.5, "tag": "T1", "anchor": "A3", "range": 4.62}

Validation is vectorized over the batch and returns, for every rejected row, its 0-based
index in the body and the reason (the first problem found, in the order time, tag, anchor,
value).  The checks are those of :func:`robustloc.io.tables.validate_measurements` (ids are
non-empty stripped strings or integers, numbers finite, anchors known) plus the physical
plausibility limits of :mod:`robustloc.io.limits` and an id length limit.

The common body - a JSON array of regular, valid rows - takes a fast path
(:class:`RowDecoder`): msgspec decodes it against the row schema (the service's anchor ids
as a ``Literal``, so a known anchor costs no string allocation) straight into structs the
garbage collector does not track, and the columns are checked in a few vectorized passes.
Any body the fast path does not accept as a whole goes through :func:`parse_body` and
:func:`validate_rows`, which give the same verdict on every valid row and the reason for
every invalid one.
"""

from __future__ import annotations

import json
import math
import sys
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np
import pandas as pd
from numpy.typing import NDArray

from robustloc.io.limits import limits_for

try:  # msgspec decodes a body against the row schema 2x faster than orjson; optional
    import msgspec as _msgspec
except ImportError:  # pragma: no cover - depends on the environment
    _msgspec = None

if _msgspec is not None:  # generic JSON: msgspec parses 3-5x faster than the standard library
    _loads: Any = _msgspec.json.decode
    _JSONError: tuple[type[Exception], ...] = (_msgspec.DecodeError, ValueError)
else:  # pragma: no cover - depends on the environment
    _loads = json.loads
    _JSONError = (ValueError,)


def _loads_any(text: bytes) -> Any:
    """:data:`_loads`, and for a number beyond the parser's range (``1e400``, an integer
    of thousands of digits: valid JSON) the standard library's reading (``inf``, a
    Python int), so that only the rows holding one are refused, each with its reason (the
    service review: the whole body was refused as "not valid JSON" with its good rows)."""
    try:
        return _loads(text)
    except _JSONError as exc:
        if "out of range" not in str(exc):
            raise
        return json.loads(text, parse_int=_int_or_digits)


def _int_or_digits(digits: str) -> int | str:
    """An integer literal as an int, or as its digits beyond Python's conversion limit
    (4 300 digits): a value then reads as an infinite float, an id as a too-long id."""
    limit = getattr(sys, "get_int_max_str_digits", lambda: 0)()
    return digits if limit and len(digits.lstrip("-")) > limit else int(digits)


# JSON nested deeper than the parser's limit (a valid row nests two levels) raises
# RecursionError in msgspec and the standard library; orjson 3.8 segfaulted on 60 000 levels
# of objects, which killed the service (the reason it is no longer used here)
_TOO_DEEP = "body is nested too deeply to be rows"


#: Longest accepted tag or anchor id (characters).
MAX_ID_CHARS = 128


class BodyError(ValueError):
    """The body as a whole is not rows.  ``status`` is the HTTP code to answer (400, 422)."""

    def __init__(self, message: str, status: int = 400) -> None:
        super().__init__(message)
        self.status = status


@dataclass(frozen=True)
class RowBatch:
    """Accepted rows of one body, as columns.

    Attributes
    ----------
    time : ndarray (n,), float seconds
    tag, anchor : ndarray (n,) of str objects
    value : ndarray (n,), dBm or m
    anchor_col : ndarray (n,) of int, column of the anchor in the service's anchor order
    """

    time: NDArray[np.float64]
    tag: NDArray[np.object_]
    anchor: NDArray[np.object_]
    value: NDArray[np.float64]
    anchor_col: NDArray[np.int64]

    def __len__(self) -> int:
        return int(self.time.shape[0])


def parse_body(body: bytes | str) -> tuple[list[Any], list[tuple[int, str]]]:
    """Decode a body to a list of (not yet validated) rows.

    Returns the rows and the NDJSON lines that are not JSON, as ``(index, error)``
    (a row index counts the non-blank lines).  A JSON array or NDJSON is accepted; a body
    that starts like an array but is not JSON is a :class:`BodyError` (400); JSON that is
    neither an array nor an object is a :class:`BodyError` (422).
    """
    if isinstance(body, str):
        body = body.encode("utf-8", "surrogatepass")
    text = body.strip()
    if not text:
        raise BodyError("empty body: send a JSON array or NDJSON of rows", 400)
    if text[:1] == b"[":
        try:
            doc = _loads_any(text)
        except _JSONError as exc:
            raise BodyError(f"body is not valid JSON: {exc}", 400) from None
        except RecursionError:
            raise BodyError(_TOO_DEEP, 400) from None
        if not isinstance(doc, list):  # pragma: no cover - '[' always decodes to a list
            raise BodyError("body is not a JSON array of rows", 422)
        return doc, []
    rows: list[Any] = []
    bad: list[tuple[int, str]] = []
    lines = [ln for ln in text.split(b"\n") if ln.strip()]
    for i, ln in enumerate(lines):
        try:
            rows.append(_loads_any(ln))
        except _JSONError as exc:
            rows.append(_NotJSON(str(exc)))
            bad.append((i, f"line is not JSON: {exc}"))
        except RecursionError:
            rows.append(_NotJSON(_TOO_DEEP))
            bad.append((i, f"line is not JSON: {_TOO_DEEP}"))
    if len(lines) == 1 and not isinstance(rows[0], dict | _NotJSON):
        raise BodyError("body is not rows: send a JSON array or NDJSON of objects", 422)
    if bad and len(bad) == len(lines) and len(lines) == 1:
        why = rows[0].error if isinstance(rows[0], _NotJSON) else bad[0][1]
        raise BodyError(why if why == _TOO_DEEP else f"body is not valid JSON: {why}", 400)
    return rows, bad


#: ASCII whitespace as ``bytes.strip`` takes it (a blank NDJSON line is only these).
_WS = np.zeros(256, dtype=bool)
_WS[list(b" \t\n\r\x0b\x0c")] = True
#: Bytes per vectorized pass of the row count (bounds its temporary arrays to ~10 MB).
_COUNT_CHUNK = 1 << 20


def rows_beyond(body: bytes | str, limit: int) -> int | None:
    """The number of rows :func:`parse_body` would return, when it is more than ``limit``;
    None when it is at most ``limit``.  Counted without decoding anything.

    Decoding first cost 1.5 GB for a 32 MiB NDJSON body of ``{}`` lines (11 million
    dicts) before it was refused for its rows (the serve review).  Counting is a few
    vectorized passes over the bytes: NDJSON rows are the non-blank lines; a JSON array's
    rows are its elements, the commas at depth 1 outside strings, plus one.  The
    count is exact for any body :func:`parse_body` decodes; for a malformed array it is
    the count of what looks like its elements.

    Parameters
    ----------
    body : bytes or str
        The body as received.
    limit : int
        Most rows accepted.

    Returns
    -------
    int or None
        The rows, if more than ``limit``.
    """
    if isinstance(body, str):
        body = body.encode("utf-8", "surrogatepass")
    text = body.strip()
    if text[:1] == b"[":
        if text.count(b",") < limit:  # (every element after the first follows a comma)
            return None
        n = _array_elements(text)
    else:
        if text.count(b"\n") < limit:  # (every row after the first follows a newline)
            return None
        n = _nonblank_lines(text)
    return n if n > limit else None


def _nonblank_lines(text: bytes) -> int:
    """Lines of ``text`` (split at ``\\n``) holding a byte other than ASCII whitespace."""
    n, after_newline = 0, True
    for off in range(0, len(text), _COUNT_CHUNK):
        b = np.frombuffer(text, np.uint8, min(_COUNT_CHUNK, len(text) - off), off)
        newline = b == 10
        # the newlines and the other non-blank bytes, in order: a line is non-blank where
        # a non-blank byte follows a newline (or the start)
        is_nl = newline[newline | ~_WS[b]]
        if not len(is_nl):
            continue
        prev = np.empty(len(is_nl), dtype=bool)
        prev[0] = after_newline
        prev[1:] = is_nl[:-1]
        n += int(np.count_nonzero(~is_nl & prev))
        after_newline = bool(is_nl[-1])
    return n


def _array_elements(text: bytes) -> int:
    """Elements of the JSON array ``text``: its commas at depth 1 outside strings, plus
    one unless it is empty.

    NumPy passes over chunks of the bytes, the state carried from one chunk to the next:
    the depth, whether a string is open, and the run of backslashes at the chunk's end (a
    quote after an odd run is escaped).  A regular expression blanking the strings took
    9 s and 970 MB for a 39 MiB body of 700 000 rows (a list of its pieces)."""
    commas, depth, seen = 0, 0, False
    in_string, backslashes = False, 0
    for off in range(0, len(text), _COUNT_CHUNK):
        b = np.frombuffer(text, np.uint8, min(_COUNT_CHUNK, len(text) - off), off)
        quotes = np.flatnonzero(b == 34)
        before = np.zeros(len(quotes), dtype=np.int64)  # backslashes before each quote
        is_bs = b == 92
        if is_bs.any():
            idx = np.arange(len(b), dtype=np.int32)
            # the run of backslashes ending at each byte: i - (index of the last other)
            last_other = np.where(is_bs, np.int32(-1), idx)
            np.maximum.accumulate(last_other, out=last_other)
            run = idx - last_other
            run[last_other < 0] += backslashes  # (a run going on from the last chunk)
            before[quotes > 0] = run[quotes[quotes > 0] - 1]
            end_run = int(run[-1])
        else:
            end_run = 0
        if len(quotes) and quotes[0] == 0:
            before[0] = backslashes
        backslashes = end_run
        opening = quotes[before % 2 == 0]  # the quotes that open or close a string
        outside = None
        if len(opening) or in_string:
            toggle = np.zeros(len(b), dtype=bool)
            toggle[opening] = True
            inside = (np.cumsum(toggle, dtype=np.int32) + in_string) % 2 == 1
            inside[opening] = True  # (a string's quotes are in it)
            outside = ~inside
            in_string = bool((len(opening) + in_string) % 2)
        opens = (b == 91) | (b == 123)
        closes = (b == 93) | (b == 125)
        if outside is not None:
            opens &= outside
            closes &= outside
        step = opens.astype(np.int32) - closes
        level = np.cumsum(step, dtype=np.int64)
        level += depth
        level -= step  # the depth at each byte
        at1 = level == 1
        comma = b == 44
        if outside is not None:
            comma &= outside
        commas += int(np.count_nonzero(at1 & comma))
        # an element: a byte at depth 1 other than whitespace and the closing bracket
        seen = seen or bool(np.any(at1 & ~_WS[b] & ~closes))
        depth = int(level[-1] + step[-1])
    return commas + 1 if seen else 0


class _NotJSON:
    """Placeholder for an NDJSON line that did not decode (already rejected)."""

    __slots__ = ("error",)

    def __init__(self, error: str) -> None:
        self.error = error


def _floats(col: list[Any], name: str, err: list[str | None]) -> NDArray[np.float64]:
    """Column to float; sets ``err[i]`` for a missing, boolean or non-numeric value."""
    kinds = set(map(type, col))
    if kinds <= {float, int}:
        try:
            return np.array(col, dtype=float)
        except OverflowError:  # an integer beyond float range: say which row below
            pass
    out = np.full(len(col), np.nan)
    # numbers written as text: as the batch readers take them (robustloc._arrays.
    # to_number; Python's float() also took "1_000" and other scripts' digits, which
    # `locate` refuses: the same log gave positions here and an error there, the serve
    # review of 2026-12-06)
    texts = [i for i, x in enumerate(col) if type(x) is str and err[i] is None]
    if texts:
        from robustloc._arrays import to_number

        parsed = to_number(pd.Series([col[i] for i in texts], dtype=object)).to_numpy(
            dtype=float, na_value=np.nan)
        as_text = dict(zip(texts, parsed.tolist()))
    for i, x in enumerate(col):
        t = type(x)
        if t is float:
            out[i] = x
        elif t is int:
            try:
                out[i] = x
            except OverflowError:
                if err[i] is None:
                    err[i] = f"'{name}' is beyond the range of a float"
        elif err[i] is not None:
            continue
        elif x is None:
            err[i] = f"missing '{name}'"
        elif t is bool:
            err[i] = f"'{name}' is a boolean, expected a number"
        elif t is str:
            v = as_text[i]
            if v == v or x.strip().lower() == "nan":  # (NaN: as a missing value)
                out[i] = v
            else:
                err[i] = f"'{name}': {x[:40]!r} is not a number"
        else:
            err[i] = f"'{name}' is a {_json_type(x)}, expected a number"
    return out


def _json_type(x: Any) -> str:
    if isinstance(x, dict):
        return "object"
    if isinstance(x, list):
        return "array"
    if isinstance(x, str):
        return "string"
    if x is None:
        return "null"
    if isinstance(x, bool):
        return "boolean"
    return "number" if isinstance(x, int | float) else type(x).__name__


def _ids(col: list[Any], name: str, err: list[str | None]) -> NDArray[np.object_]:
    """Column to stripped string ids; sets ``err[i]`` for a missing, empty or long id."""
    kinds = set(map(type, col))
    if kinds <= {str}:
        arr = np.array(col, dtype=object)
    else:
        arr = np.empty(len(col), dtype=object)
        for i, x in enumerate(col):
            t = type(x)
            if t is str:
                arr[i] = x
            else:
                arr[i] = ""
                if err[i] is not None:
                    continue
                if x is None:
                    err[i] = f"missing '{name}'"
                elif t is int:
                    if -(10**MAX_ID_CHARS) < x < 10**MAX_ID_CHARS:
                        arr[i] = str(x)
                    else:  # (str() of a huge integer is slow, or refused past 4 300 digits)
                        err[i] = f"'{name}' longer than {MAX_ID_CHARS} characters"
                elif t is float and math.isfinite(x) and x == int(x):  # (1e400 is inf)
                    arr[i] = str(int(x))
                else:
                    err[i] = f"'{name}' is a {_json_type(x)}, expected a string id"
    uniq = set(arr.tolist())
    fix: dict[str, str] = {}
    badu: dict[str, str] = {}
    for u in uniq:
        s = u.strip()
        if not s:
            badu[u] = f"empty '{name}'"
        elif len(s) > MAX_ID_CHARS:
            badu[u] = f"'{name}' longer than {MAX_ID_CHARS} characters"
        elif s != u:
            fix[u] = s
    if badu:
        for i, x in enumerate(arr.tolist()):
            if x in badu and err[i] is None:
                err[i] = badu[x]
    if fix:
        arr = np.array([fix.get(x, x) for x in arr.tolist()], dtype=object)
    return arr


def _regular_batch(t: list, tag: list, anc: list, val: list, kind: str,
                   amap: dict[str, int], ids: NDArray[np.object_]) -> RowBatch | None:
    """Columns of regular rows (numbers are numbers, ids strings) to a batch, or None when
    a tag id is empty, too long or not stripped, an anchor unknown or a number outside its
    limits (the row-by-row path then says which row and why)."""
    for u in set(tag):
        if not u or len(u) > MAX_ID_CHARS or u.strip() != u:
            return None
    n = len(t)
    try:
        col = np.fromiter(map(amap.__getitem__, anc), np.int64, n)
    except KeyError:
        return None
    try:
        tv = np.fromiter(t, float, n)
        vv = np.fromiter(val, float, n)
    except OverflowError:  # an integer beyond float range: the row path says which
        return None
    if not (limits_for("time").check(tv).all() and limits_for(kind).check(vv).all()):
        return None
    return RowBatch(tv, np.array(tag, dtype=object), ids[col], vv, col)


def _fast_path(rows: list[Any], anchor_index: pd.Index, kind: str) -> RowBatch | None:
    """The batch when every decoded row is regular and valid (the common case), else None.

    Regular: every row an object with exactly the keys time, tag, anchor and ``kind``;
    numbers are JSON numbers, ids strings.  A few C-level passes extract the columns; any
    irregularity returns None and :func:`validate_rows` takes the row-by-row path, whose
    verdicts on valid rows are the same.
    """
    n = len(rows)
    if set(map(type, rows)) != {dict} or sum(map(len, rows)) != 4 * n:
        return None
    try:  # one list per column (zip(*rows) of 8 000 tuples is 10x slower)
        t = [r["time"] for r in rows]
        tag = [r["tag"] for r in rows]
        anc = [r["anchor"] for r in rows]
        val = [r[kind] for r in rows]
    except KeyError:
        return None
    num = {float, int}
    if not (set(map(type, t)) <= num and set(map(type, val)) <= num
            and set(map(type, tag)) == {str} and set(map(type, anc)) == {str}):
        return None
    names = anchor_index.tolist()
    amap = {a: i for i, a in enumerate(names)}
    return _regular_batch(t, tag, anc, val, kind, amap, np.array(names, dtype=object))


class RowDecoder:
    """Fast path of the common body: a JSON array of regular, valid rows, decoded by msgspec
    straight into columns.

    The row schema is ``{"time": number, "tag": string, "anchor": one of the anchor ids,
    KIND: number}`` with no other key; msgspec checks it while it parses, into structs the
    garbage collector does not track.  :meth:`decode` returns None for any body that is not
    such an array or has a row that is not regular and valid; the caller then takes
    :func:`parse_body` and :func:`validate_rows`, whose verdict on every valid row is the
    same (tests/test_service.py checks both paths on the same bodies).

    Parameters
    ----------
    anchor_ids : sequence of str
        The service's anchors, in column order.
    """

    def __init__(self, anchor_ids: Sequence[str]) -> None:
        names = [str(a) for a in anchor_ids]
        self._amap = {a: i for i, a in enumerate(names)}
        self._ids = np.array(names, dtype=object)
        self._decoders: dict[str, Any] = {}
        if _msgspec is None or not names:
            return
        anchor_type = Literal[tuple(names)]  # type: ignore[valid-type]
        for kind in ("rssi", "range"):
            row = _msgspec.defstruct(
                f"_{kind.capitalize()}Row",
                [("time", float), ("tag", str), ("anchor", anchor_type), (kind, float)],
                forbid_unknown_fields=True, gc=False)
            self._decoders[kind] = _msgspec.json.Decoder(list[row])  # type: ignore[valid-type]

    @property
    def available(self) -> bool:
        """Whether msgspec is installed (else :meth:`decode` always returns None)."""
        return bool(self._decoders)

    def decode(self, body: bytes | str, kind: str | None) -> RowBatch | None:
        """The accepted rows of ``body``, when all of them are regular and valid; else None.

        ``kind`` is the service's value (None until fixed: then always None).
        """
        dec = self._decoders.get(kind) if kind is not None else None
        if dec is None:
            return None
        try:
            rows = dec.decode(body)
        except (_msgspec.DecodeError, _msgspec.ValidationError, RecursionError):
            return None
        t = [r.time for r in rows]
        tag = [r.tag for r in rows]
        anc = [r.anchor for r in rows]
        val = [r.range for r in rows] if kind == "range" else [r.rssi for r in rows]
        return _regular_batch(t, tag, anc, val, kind, self._amap, self._ids)


def _first_accepted_kind(
    t: NDArray[np.float64], rs: list[Any], rg: list[Any], has_rs: NDArray[np.bool_],
    has_rg: NDArray[np.bool_], err: list[str | None], allowed: tuple[str, ...],
) -> str | None:
    """The value of the first row that passes every check with it (one value, a number
    within that value's limits, a time within its limits, no other error so far), or None.

    The kind was that of the first row without an error *before* the value checks: a
    first row ``{"range": "abc"}``, rejected, fixed the service (and its store's
    meta.json) to ranges for good (the serve review)."""
    clean = np.array([e is None for e in err], dtype=bool)
    clean &= (has_rs ^ has_rg) & limits_for("time").check(t)
    first, found = len(t), None
    for name, has, col in (("rssi", has_rs, rs), ("range", has_rg, rg)):
        idx = np.flatnonzero(clean & has)
        if name not in allowed or not len(idx):
            continue
        scratch: list[str | None] = [None] * len(idx)  # (the row's errors are set later)
        v = _floats([col[i] for i in idx.tolist()], name, scratch)
        good = idx[np.array([e is None for e in scratch], dtype=bool)
                   & limits_for(name).check(v)]
        if len(good) and good[0] < first:
            first, found = int(good[0]), name
    return found


def validate_rows(
    rows: list[Any], anchor_index: pd.Index, kind: str | None,
    allowed: tuple[str, ...] = ("rssi", "range"),
) -> tuple[RowBatch, str | None, list[tuple[int, str]]]:
    """Validate decoded rows against the service's anchors and value kind.

    Parameters
    ----------
    rows : list
        Decoded JSON rows (any JSON values; non-objects are rejected).
    anchor_index : pandas.Index
        The anchor ids, in the service's anchor (column) order.
    kind : {"rssi", "range"} or None
        The value the service locates; ``None`` until the first accepted row fixes it.
    allowed : tuple of str
        The values the service can locate at all (``("range",)`` when the anchors have no
        path-loss parameters): a row with another value is rejected with the reason, and
        never fixes ``kind``.

    Returns
    -------
    batch : RowBatch
        The accepted rows, in body order.
    kind : str or None
        The value kind (when ``kind`` was None: that of the first row accepted, None if
        none is).
    rejected : list of (index, error)
        Sorted by index.
    """
    n = len(rows)
    if kind is not None and n:
        fast = _fast_path(rows, anchor_index, kind)
        if fast is not None:
            return fast, kind, []
    err: list[str | None] = [None] * n
    if set(map(type, rows)) <= {dict}:
        objs: list[dict] = rows
    else:
        objs = []
        for i, r in enumerate(rows):
            if type(r) is dict:
                objs.append(r)
            else:
                objs.append({})
                err[i] = f"line is not JSON: {r.error}" if isinstance(r, _NotJSON) else (
                    f"row is a JSON {_json_type(r)}, expected an object")
    t = _floats([r.get("time") for r in objs], "time", err)
    tag = _ids([r.get("tag") for r in objs], "tag", err)
    anc = _ids([r.get("anchor") for r in objs], "anchor", err)
    col = anchor_index.get_indexer(pd.Index(anc.tolist(), dtype=object))
    unknown = np.flatnonzero(col < 0)
    for i in unknown.tolist():
        if err[i] is None:
            err[i] = f"unknown anchor id {str(anc[i])[:40]!r} (not in the anchors)"
    rs = [r.get("rssi") for r in objs]
    rg = [r.get("range") for r in objs]
    has_rs = np.fromiter((x is not None for x in rs), bool, n)
    has_rg = np.fromiter((x is not None for x in rg), bool, n)
    for name, has in (("rssi", has_rs), ("range", has_rg)):
        if name not in allowed:
            why = (f"this service cannot locate from {name}: the anchors have no path-loss "
                   "parameters (columns A, n; run `robustloc calibrate`)" if name == "rssi"
                   else f"this service cannot locate from {name}")
            for i in np.flatnonzero(has & ~(has_rs & has_rg)).tolist():
                if err[i] is None:
                    err[i] = why
    if kind is None:
        kind = _first_accepted_kind(t, rs, rg, has_rs, has_rg, err, allowed)
    for i in np.flatnonzero(has_rs & has_rg).tolist():
        if err[i] is None:
            err[i] = "row has both 'rssi' and 'range'; send one value per row"
    for i in np.flatnonzero(~has_rs & ~has_rg).tolist():
        if err[i] is None:
            err[i] = "row has no value: expected 'rssi' (dBm) or 'range' (m)"
    if kind is not None:
        other = has_rg if kind == "rssi" else has_rs
        for i in np.flatnonzero(other & ~(has_rs & has_rg)).tolist():
            if err[i] is None:
                err[i] = (f"this service locates from {kind}; row has "
                          f"{'range' if kind == 'rssi' else 'rssi'}")
        val = _floats(rs if kind == "rssi" else rg, kind, err)
        checks = [("time", t, None), (kind, val, None)]
    else:
        # no row is accepted: each row's reason by its own value (unchecked, a row with
        # a range that is not a number was accepted with a NaN value)
        val = np.full(n, np.nan)
        checks = [("time", t, None)]
        for name, has, given in (("rssi", has_rs, rs), ("range", has_rg, rg)):
            idx = np.flatnonzero(has & ~(has_rs & has_rg))
            if len(idx):
                sub = [err[i] for i in idx.tolist()]
                val[idx] = _floats([given[i] for i in idx.tolist()], name, sub)
                for i, e in zip(idx.tolist(), sub):
                    err[i] = e
                checks.append((name, val, has))
    for name, v, rows_of in checks:
        lim = limits_for(name)
        bad = ~lim.check(v) if rows_of is None else ~lim.check(v) & rows_of
        for i in np.flatnonzero(bad).tolist():
            if err[i] is None:
                err[i] = (f"'{name}' is not finite" if not np.isfinite(v[i])
                          else f"{lim.describe()}, got {v[i]:g}")
    ok = np.fromiter((e is None for e in err), bool, n)
    rejected = [(i, e) for i, e in enumerate(err) if e is not None]
    batch = RowBatch(t[ok], tag[ok], anc[ok], val[ok], col[ok].astype(np.int64))
    return batch, kind, rejected

