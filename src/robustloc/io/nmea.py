"""NMEA 0183 reading (RMC, VTG, GGA, GST) through pynmea2, and sentence writing.

What comes out (:func:`read_nmea` / :func:`parse_nmea`, an :class:`NmeaLog`):

* ``motion`` -- one row per RMC or VTG sentence: ``time_s``, ``speed_mps`` (knots x
  1852/3600, or km/h / 3.6), ``course_rad`` (course over ground, true, clockwise from north,
  wrapped to ``[-pi, pi)``; NaN when the receiver leaves it empty, e.g. standing still) and
  ``sentence``.  This is the GPS speed ``v`` and heading ``theta`` of seed 001.
* ``fixes`` -- one row per valid GGA: ``time_s, lat_deg, lon_deg, h_m`` (ellipsoidal:
  altitude + geoid separation), ``quality, n_sats, hdop`` and local ``east_m, north_m,
  up_m`` from pymap3d's ``geodetic2enu`` about ``origin`` (default: the first valid fix).
* ``accuracy`` -- GST: ``time_s, rms_m, sigma_lat_m, sigma_lon_m, sigma_alt_m``.
* ``summary`` -- counts of lines, parsed sentences per type and every skip by reason.

Time: ``time_s`` is seconds since 00:00 UTC of the day of the first sentence kept.  A
sentence carries only the time of day, so each is placed at the time nearest to the
previous one kept (within +-12 h): the step from 23:59:59 to 00:00:00 is one second, into
the next day, and a sentence arriving late across midnight (23:59:59 after 00:00:20) stays
on its own day.  A step of more than an hour (:data:`TIME_JUMP_S`) between successive time
stamps is a *jump* -- a pause of the receiver, or a corrupt time -- and is believed only
when the log continues from the new time: at least two successive time stamps (sentences
of one fix share one) within an hour of each other, which the log does not leave to come
back to the time before the jump.  Such a jump goes forward (a pause of 11 h across
midnight is a new day).  Sentences whose time fails this -- one fix whose time disagrees
with both its neighbours by hours (a GGA at 00:00:00 inside a log at 13:00), a run the
log returns from, a single fix before the log's first run or after its last jump -- are
skipped and counted as ``time_jump`` (with the VTG sentences that would take their
time); the rest of the log keeps its times.  A log made only of single fixes hours apart
has nothing to judge by: every jump is believed.  With a dated RMC,
``time_s + day0_posix_s`` is POSIX time.  Add an offset to align it with another stream
(see :mod:`robustloc.fusion.align`).

VTG carries no time: it belongs to the fix whose timed sentences (RMC, GGA, GST) precede
it in the log, and takes their time.  A VTG without such a fix of its own -- before any
timed sentence, a second VTG after one fix, or one after a timed sentence of another time
that was skipped (its RMC and GGA lost to a bad checksum, an invalid fix) -- is an
*orphan*: it would lend its speed and course to the previous fix, so it is skipped and
counted as ``orphan_vtg``.

Robustness: lines may carry a prefix or suffix (Android GnssLogger ``NMEA,$GP...*hh,ms``):
the sentence is the text from ``$`` to the two hex digits after ``*``.  A bad checksum, a
missing checksum, a truncated sentence (required fields empty), a malformed one (a field
that must be a number is not: ``30XY.0021`` for a latitude, or ``1_0``, which Python's
``float`` and ``int`` read as 10; no field of these types holds a ``_``), an invalid fix
(GGA quality 0, RMC status ``V``, RMC or VTG FAA mode indicator ``N``: data not valid,
NMEA 2.3 on) or an unsupported type is counted in ``summary.skipped`` and skipped --
never an exception.  Only an unreadable *file* raises :class:`InputError`.

Plausibility (:mod:`robustloc.io.limits`): a sentence with a valid checksum can still carry
absurd values (a bit flip before the checksum was computed, a firmware bug).  A speed
outside the ``speed`` limits (0 .. 515 m/s) or a course outside ``course`` (0 .. 360 deg)
is an ``invalid_measurement``: the motion row is *kept* with that value set to NaN (a bad
speed also blanks the course, whose Jacobian ``1/v`` depends on it), and counted in
``summary.invalid``.  A sentence whose time or date is not a calendar value (hour 25, day
32), or a GGA latitude/longitude beyond +-90/+-180 deg, is skipped and counted as
``invalid_measurement`` in ``summary.skipped`` (it has no time, so no row can carry it).
So is a GGA whose hemisphere is not N/S or E/W, whose minutes reach 60, or whose altitude
is not a number, outside the ``height`` limits or not in metres (unit ``M``).  A GGA
without its geoid separation keeps its row with ``h_m`` and ``up_m`` NaN (the altitude is
above the geoid: no ellipsoidal height), counted in ``summary.invalid`` as
``geoid_separation``.
"""

from __future__ import annotations

import datetime
import re
from collections import Counter
from collections.abc import Iterable
from dataclasses import dataclass, field
from os import PathLike
from pathlib import Path

import numpy as np
import pandas as pd
import pymap3d
import pynmea2

from robustloc.errors import InputError
from robustloc.io.limits import LIMITS

KNOT_MPS = 1852.0 / 3600.0

_SENTENCE = re.compile(r"\$([A-Z]{2}[A-Z0-9]{3}),([^*$]*)(\*([0-9A-Fa-f]{2}))?")

#: Reasons a line is skipped (keys of :attr:`NmeaSummary.skipped`).
SKIP_REASONS = (
    "no_sentence",
    "bad_checksum",
    "missing_checksum",
    "truncated",
    "malformed",
    "invalid_fix",
    "unsupported",
    "invalid_measurement",
    "time_jump",
    "orphan_vtg",
)

#: A step between successive time stamps of a log beyond this (s, after the midnight
#: roll-over) is a jump: believed only when the log continues from the new time (module
#: docstring, Time).  An hour: a receiver logs at 1 Hz or faster and a fix lost in a tunnel
#: or a garage comes back within minutes, while a corrupt time (a GGA at 00:00:00 in a log
#: at 13:00, the filter/fuse review) is off by hours.
TIME_JUMP_S = 3600.0


def nmea_checksum(body: str) -> str:
    """XOR checksum of the text between ``$`` and ``*``, two upper-case hex digits."""
    c = 0
    for ch in body:
        c ^= ord(ch)
    return f"{c:02X}"


@dataclass(frozen=True)
class NmeaSummary:
    """What :func:`parse_nmea` read and skipped.

    Attributes
    ----------
    lines : int
        Non-empty input lines.
    parsed : dict[str, int]
        Sentences used, by type (``RMC``, ``VTG``, ``GGA``, ``GST``).
    skipped : dict[str, int]
        Skipped lines by reason (see :data:`SKIP_REASONS`).
    examples : list[tuple[int, str]]
        Up to 20 ``(line number, reason)`` of skipped lines or invalid values, for the user.
    invalid : dict[str, int]
        Values outside their physical limits (``speed``, ``course``) in sentences that
        were kept (the value is NaN in ``motion``).
    """

    lines: int
    parsed: dict[str, int]
    skipped: dict[str, int]
    examples: list[tuple[int, str]] = field(default_factory=list)
    invalid: dict[str, int] = field(default_factory=dict)

    @property
    def n_invalid(self) -> int:
        """Invalid measurements: implausible values kept as NaN plus sentences skipped for an
        impossible time, date or position."""
        return int(sum(self.invalid.values())) + int(self.skipped.get("invalid_measurement", 0))

    @property
    def n_skipped(self) -> int:
        return int(sum(self.skipped.values()))

    def text(self) -> str:
        """One line for a command's stderr."""
        used = ", ".join(f"{k} {v}" for k, v in sorted(self.parsed.items())) or "none"
        skip = ", ".join(f"{k} {v}" for k, v in sorted(self.skipped.items()) if v) or "none"
        bad = ", ".join(f"{k} {v}" for k, v in sorted(self.invalid.items()) if v)
        tail = f"; invalid values {bad} (set to NaN)" if bad else ""
        return f"NMEA: {self.lines} lines; used {used}; skipped {skip}{tail}"


@dataclass(frozen=True)
class NmeaLog:
    """Parsed NMEA stream (see the module docstring for the columns)."""

    motion: pd.DataFrame
    fixes: pd.DataFrame
    accuracy: pd.DataFrame
    origin: tuple[float, float, float] | None
    summary: NmeaSummary
    #: POSIX time (s) of 00:00 UTC of day 0 of ``time_s``, from the first RMC date; None
    #: without any dated RMC.  ``time_s + day0_posix_s`` is POSIX time.
    day0_posix_s: float | None = None


def _is_time(ts: object) -> bool:
    """pynmea2 returns the raw text (a ``str``) when a time or date is not a calendar value."""
    return isinstance(ts, (datetime.time, datetime.datetime))


def _tod(ts) -> float:
    return ts.hour * 3600.0 + ts.minute * 60.0 + ts.second + ts.microsecond * 1e-6


#: Sentence types that carry the time of their fix (a VTG takes theirs).
_TIMED = ("RMC", "GGA", "GST")


def _raw_tod(text: str) -> float | None:
    """The time of day (s) of an ``hhmmss[.ss]`` field, read as pynmea2 reads a kept
    sentence's (so that equal times compare equal), as a skipped sentence (bad checksum,
    invalid fix) still shows it; ``None`` if it is not one."""
    if len(text) < 6 or not text[:6].isdigit():
        return None
    try:
        return _tod(pynmea2.nmea_utils.timestamp(text))
    except (ValueError, TypeError, ArithmeticError):  # minute 61, a fraction that is
        # no number, an hour of 13 digits (OverflowError: a traceback, the fuzz review)
        return None


def _minutes(field: str, degree_digits: int) -> float:
    """The minutes of an NMEA ``ddmm.mmmm`` latitude (``degree_digits`` 2) or
    ``dddmm.mmmm`` longitude (3); NaN when not a number (a malformed field: reading the
    coordinate then raises, as before)."""
    return _num(str(field)[degree_digits:])


def _num(v) -> float:
    """A field's number, NaN when it is none (``1_0`` included: Python's ``float`` reads
    it as 10, no NMEA writer writes it)."""
    if isinstance(v, str) and "_" in v:
        return float("nan")
    try:
        return float(v)
    except (TypeError, ValueError):
        return float("nan")


def _wrap_day(d: np.ndarray) -> np.ndarray:
    """Time-of-day differences (s) wrapped to ``[-12 h, 12 h)``: the nearest step."""
    return (d + 43200.0) % 86400.0 - 43200.0


def _unwrap_days(tod: np.ndarray) -> np.ndarray:
    """Times since 00:00 of the first day kept of a log's time stamps ``tod`` (times of
    day, s, in the order of the log); NaN where a stamp is set aside.

    The rule of the module docstring (Time): runs of successive stamps at most
    :data:`TIME_JUMP_S` apart (the nearest step, across midnight too) are continuous log;
    a run after a jump is placed forward of the time before the jump when it holds two
    stamps or more and the log does not return to that time after it, else it is set
    aside (so are single stamps before the first longer run).  Without any run of two
    stamps every jump is believed.
    """
    N = tod.size
    out = np.full(N, np.nan)
    if N == 0:
        return out
    d = _wrap_day(np.diff(tod))
    brk = np.abs(d) > TIME_JUMP_S
    starts = np.r_[0, np.flatnonzero(brk) + 1]
    ends = np.r_[starts[1:], N]
    cum = np.r_[0.0, np.cumsum(np.where(brk, 0.0, d))]  # steps within the runs
    judge = bool(np.any(ends - starts >= 2))
    ref: float | None = None  # the time of the last stamp kept
    for s, e in zip(starts.tolist(), ends.tolist()):
        if ref is None:
            if judge and e - s < 2:  # a lone fix before the log's first run
                continue
            base = float(tod[s])
        else:
            step = float(_wrap_day(np.asarray(tod[s] - ref)))
            if abs(step) <= TIME_JUMP_S:  # back where the log was before a set-aside run
                base = ref + step
            else:
                back = e < N and abs(float(_wrap_day(np.asarray(tod[e] - ref)))) <= TIME_JUMP_S
                if judge and (e - s < 2 or back):
                    continue
                base = ref + float((tod[s] - ref) % 86400.0)  # a pause: forward
        out[s:e] = base + (cum[s:e] - cum[s])
        ref = float(out[e - 1])
    return out


def parse_nmea(
    lines: Iterable[str] | str | bytes,
    origin: tuple[float, float, float] | None = None,
    source: str = "<nmea>",
) -> NmeaLog:
    """Parse NMEA text lines; see the module docstring.

    Parameters
    ----------
    lines : iterable of str, or str or bytes
        Raw lines (prefixes/suffixes around the sentence are tolerated); a string is NMEA
        text, split into its lines (it was iterated character by character: every
        character a ``no_sentence`` line, no error).  For a file, :func:`read_nmea`.
    origin : (lat_deg, lon_deg, h_m), optional
        ENU origin for GGA positions; default the first valid GGA fix.
    source : str
        Name used in messages.
    """
    if isinstance(lines, bytes):
        lines = lines.decode("ascii", errors="replace")
    if isinstance(lines, str):
        if "$" not in lines and "\n" not in lines.strip() and Path(lines).is_file():
            raise TypeError(f"parse_nmea takes NMEA text or its lines, not a file name "
                            f"({lines!r}): use read_nmea(path)")
        lines = lines.splitlines()
    skipped: Counter[str] = Counter({r: 0 for r in SKIP_REASONS})
    invalid: Counter[str] = Counter()
    speed_lim, course_lim, height_lim = LIMITS["speed"], LIMITS["course"], LIMITS["height"]
    parsed: Counter[str] = Counter()
    examples: list[tuple[int, str]] = []
    motion: list[tuple[float, float, float, str, int]] = []
    fixes: list[tuple] = []
    acc: list[tuple] = []
    n_lines = 0
    dates: list[tuple[int, datetime.date]] = []  # (order, date) of the dated RMC sentences
    where: list[tuple[int, str]] = []  # (line number, type) of each sentence used, by order
    # the fix a VTG may join (module docstring): the time of day of the latest timed
    # sentence kept, whether that fix has its VTG already, and whether a timed sentence of
    # another time was skipped since (the VTG that follows is that lost fix's)
    fix_tod: float | None = None
    fix_has_vtg = False
    fix_passed = False
    kind, body = "", ""  # the sentence being read

    def skip(lineno: int, reason: str) -> None:
        nonlocal fix_passed
        skipped[reason] += 1
        if len(examples) < 20:
            examples.append((lineno, reason))
        if kind in _TIMED:  # a timed sentence lost: is it another fix's?
            tod = _raw_tod(body.split(",", 1)[0])
            fix_passed |= tod is not None and tod != fix_tod

    def checked(lineno: int, speed: float, course_deg: float) -> tuple[float, float]:
        """Speed (m/s) and course (deg) with implausible values set to NaN and counted."""
        if not speed_lim.check(speed):
            invalid["speed"] += 1
            if len(examples) < 20:
                examples.append((lineno, f"invalid_measurement: {speed_lim.describe()}"))
            return float("nan"), float("nan")
        if np.isfinite(course_deg) and not course_lim.check(course_deg):
            invalid["course"] += 1
            if len(examples) < 20:
                examples.append((lineno, f"invalid_measurement: {course_lim.describe()}"))
            course_deg = float("nan")
        return speed, course_deg

    order = 0
    for lineno, raw in enumerate(lines, start=1):
        line = raw.strip()
        if not line:
            continue
        n_lines += 1
        kind = ""
        m = _SENTENCE.search(line)
        if m is None:
            skip(lineno, "no_sentence")
            continue
        talker_type, body, cs = m.group(1), m.group(2), m.group(4)
        kind = talker_type[2:]
        if cs is None:
            skip(lineno, "missing_checksum")
            continue
        if nmea_checksum(f"{talker_type},{body}") != cs.upper():
            skip(lineno, "bad_checksum")
            continue
        if kind not in ("RMC", "VTG", "GGA", "GST"):
            skip(lineno, "unsupported")
            continue
        if "_" in body:  # every number (float, int, pynmea2's latitude and time) would
            # read 1_0 as 10: no field of these sentences holds a '_' (the spp review)
            skip(lineno, "malformed")
            continue
        try:
            msg = pynmea2.parse(m.group(0), check=True)
        except (pynmea2.ParseError, ValueError, TypeError):
            skip(lineno, "truncated")
            continue
        try:
            ts = getattr(msg, "timestamp", None)
            if ts is not None and not _is_time(ts):  # hour 25, minute 61, ...
                skip(lineno, "invalid_measurement")
                continue
            if kind == "RMC":
                if ts is None or not msg.status:
                    skip(lineno, "truncated")
                    continue
                if msg.status != "A" or getattr(msg, "mode_indicator", None) == "N":
                    # (mode N, NMEA 2.3 on: data not valid, as a VTG's; it was a motion row)
                    skip(lineno, "invalid_fix")
                    continue
                if msg.spd_over_grnd in (None, ""):
                    skip(lineno, "truncated")
                    continue
                date = getattr(msg, "datestamp", None)
                if date is not None and not isinstance(date, datetime.date):  # day 32, ...
                    skip(lineno, "invalid_measurement")
                    continue
                speed = float(msg.spd_over_grnd) * KNOT_MPS
                if np.isnan(speed):
                    skip(lineno, "truncated")
                    continue
                speed, course = checked(lineno, speed, _num(msg.true_course))
                if date is not None:
                    dates.append((order, date))
                motion.append((_tod(ts), speed, np.deg2rad(course), "RMC", order))
            elif kind == "VTG":
                if getattr(msg, "faa_mode", None) == "N":
                    skip(lineno, "invalid_fix")
                    continue
                kmh = _num(msg.spd_over_grnd_kmph)
                kts = _num(msg.spd_over_grnd_kts)
                speed = kmh / 3.6 if not np.isnan(kmh) else kts * KNOT_MPS
                if np.isnan(speed):
                    skip(lineno, "truncated")
                    continue
                if fix_tod is None or fix_has_vtg or fix_passed:
                    skip(lineno, "orphan_vtg")  # no fix of its own (module docstring)
                    continue
                speed, course = checked(lineno, speed, _num(msg.true_track))
                # VTG has no time: it takes its fix's, the last timed sentence's
                fix_has_vtg = True
                motion.append((np.nan, speed, np.deg2rad(course), "VTG", order))
            elif kind == "GGA":
                if ts is None or msg.gps_qual is None or not msg.lat or not msg.lon:
                    if msg.gps_qual == 0:
                        skip(lineno, "invalid_fix")
                    else:
                        skip(lineno, "truncated")
                    continue
                if int(msg.gps_qual) == 0:
                    skip(lineno, "invalid_fix")
                    continue
                # a hemisphere other than N/S, E/W (pynmea2 reads it as 0 deg), minutes
                # of 60 or more, an altitude not finite, outside the height limits or
                # not in metres: no position (the GNSS review, 2026-12-07)
                if (msg.lat_dir not in ("N", "S") or msg.lon_dir not in ("E", "W")
                        or _minutes(msg.lat, 2) >= 60.0 or _minutes(msg.lon, 3) >= 60.0
                        or (msg.altitude_units or "M") != "M"
                        or (msg.geo_sep_units or "M") != "M"):
                    skip(lineno, "invalid_measurement")
                    continue
                lat, lon = float(msg.latitude), float(msg.longitude)
                alt = _num(msg.altitude)
                if not (abs(lat) <= 90.0 and abs(lon) <= 180.0) or not height_lim.check(alt):
                    skip(lineno, "invalid_measurement")
                    continue
                sep = _num(msg.geo_sep)
                # the ellipsoidal height needs the geoid separation: without it the
                # altitude (above the geoid) is no ellipsoidal height, tens of metres off
                h = alt + sep
                if not np.isfinite(sep):
                    invalid["geoid_separation"] += 1
                    if len(examples) < 20:
                        examples.append((lineno, "GGA without geoid separation: h_m "
                                                 "(ellipsoidal) unknown"))
                fixes.append(
                    (
                        _tod(ts),
                        lat,
                        lon,
                        h,
                        int(msg.gps_qual),
                        _num(msg.num_sats),
                        _num(msg.horizontal_dil),
                        order,
                    )
                )
            else:  # GST
                vals = (_num(msg.rms), _num(msg.std_dev_latitude),
                        _num(msg.std_dev_longitude), _num(msg.std_dev_altitude))
                if ts is None or not np.isfinite(vals).any():
                    skip(lineno, "truncated")
                    continue
                acc.append((_tod(ts), *vals, order))
        except ValueError:  # a field that must be a number is not (the GNSS review)
            skip(lineno, "malformed")
            continue
        except (TypeError, AttributeError, IndexError, ArithmeticError):
            skip(lineno, "truncated")
            continue
        parsed[kind] += 1
        where.append((lineno, kind))
        order += 1
        if kind in _TIMED:  # the fix a following VTG joins
            if _tod(ts) != fix_tod:
                fix_tod, fix_has_vtg = _tod(ts), False
            fix_passed = False
    kind = ""

    # ---- one time axis: seconds since 00:00 UTC of the first day, with roll-overs and
    # sentences whose time jumps by hours set aside (module docstring, Time)
    events = [(o, t) for (t, *_rest, o) in motion if np.isfinite(t)]
    events += [(r[-1], r[0]) for r in fixes] + [(r[-1], r[0]) for r in acc]
    events.sort()
    ev_tod = np.array([t for _, t in events], dtype=float)
    # time stamps: successive sentences with one time of day (the GGA, RMC, GST of a fix)
    new_stamp = np.r_[True, ev_tod[1:] != ev_tod[:-1]] if len(events) else np.zeros(0, bool)
    stamp_of = np.cumsum(new_stamp) - 1
    stamp_t = _unwrap_days(ev_tod[new_stamp])[stamp_of] if len(events) else ev_tod
    order_to_time = {o: float(t) for (o, _), t in zip(events, stamp_t) if np.isfinite(t)}
    jumped = {o for (o, _), t in zip(events, stamp_t) if not np.isfinite(t)}
    if jumped:
        # a VTG (no time of its own) after a set-aside sentence belongs to its fix
        last_timed = None
        for o, (_, kind) in enumerate(where):
            if kind != "VTG":
                last_timed = o
            elif last_timed in jumped:
                jumped.add(o)
        for o in sorted(jumped):
            lineno, kind = where[o]
            parsed[kind] -= 1
            skip(lineno, "time_jump")
        motion = [r for r in motion if r[-1] not in jumped]
        fixes = [r for r in fixes if r[-1] not in jumped]
        acc = [r for r in acc if r[-1] not in jumped]

    def timeline(rows_order: list[int], tod: list[float]) -> np.ndarray:
        return np.array([order_to_time.get(o, t) for o, t in zip(rows_order, tod)], dtype=float)

    mot = pd.DataFrame(motion, columns=["time_s", "speed_mps", "course_rad", "sentence", "o"])
    if len(mot):
        t = mot["time_s"].to_numpy(copy=True)
        t = timeline(mot["o"].tolist(), t.tolist())
        # VTG inherits the time of the latest earlier timed sentence
        known = sorted(order_to_time.items())
        if known:
            ko = np.array([k for k, _ in known])
            kt = np.array([v for _, v in known])
            idx = np.searchsorted(ko, mot["o"].to_numpy(), side="right") - 1
            fill = np.where(idx >= 0, kt[np.clip(idx, 0, None)], np.nan)
            t = np.where(np.isfinite(t), t, fill)
        mot["time_s"] = t
        mot["course_rad"] = (mot["course_rad"] + np.pi) % (2 * np.pi) - np.pi
    n_vtg_untimed = int(np.isnan(mot["time_s"]).sum()) if len(mot) else 0
    if n_vtg_untimed:
        skipped["truncated"] += n_vtg_untimed
        parsed["VTG"] -= n_vtg_untimed
        mot = mot[np.isfinite(mot["time_s"])]
    mot = mot.drop(columns="o").reset_index(drop=True)

    fx = pd.DataFrame(
        fixes, columns=["time_s", "lat_deg", "lon_deg", "h_m", "quality", "n_sats", "hdop", "o"]
    )
    if len(fx):
        fx["time_s"] = timeline(fx["o"].tolist(), fx["time_s"].tolist())
        if origin is None:
            origin = (float(fx["lat_deg"].iloc[0]), float(fx["lon_deg"].iloc[0]), 0.0)
            h0 = fx["h_m"].iloc[0]
            origin = (origin[0], origin[1], float(h0) if np.isfinite(h0) else 0.0)
        e, n, u = pymap3d.geodetic2enu(
            fx["lat_deg"].to_numpy(),
            fx["lon_deg"].to_numpy(),
            np.nan_to_num(fx["h_m"].to_numpy(), nan=origin[2]),
            *origin,
        )
        fx["east_m"], fx["north_m"] = np.asarray(e), np.asarray(n)
        # (a fix without its ellipsoidal height has no up either)
        fx["up_m"] = np.where(np.isfinite(fx["h_m"].to_numpy()), np.asarray(u), np.nan)
    else:
        for c in ("east_m", "north_m", "up_m"):
            fx[c] = pd.Series(dtype=float)
    fx = fx.drop(columns="o")

    ac = pd.DataFrame(
        acc, columns=["time_s", "rms_m", "sigma_lat_m", "sigma_lon_m", "sigma_alt_m", "o"]
    )
    if len(ac):
        ac["time_s"] = timeline(ac["o"].tolist(), ac["time_s"].tolist())
    ac = ac.drop(columns="o")

    summary = NmeaSummary(
        lines=n_lines, parsed=dict(parsed), skipped=dict(skipped), examples=examples,
        invalid=dict(invalid),
    )
    day0 = None
    first_date = next(((o, d) for o, d in dates if o in order_to_time), None)
    if first_date is not None:
        import calendar

        o, date = first_date
        day_index = int(order_to_time[o] // 86400.0)
        midnight = calendar.timegm((date.year, date.month, date.day, 0, 0, 0))
        day0 = float(midnight - 86400.0 * day_index)
    return NmeaLog(motion=mot, fixes=fx, accuracy=ac, origin=origin, summary=summary,
                   day0_posix_s=day0)


def read_nmea(
    path: str | PathLike[str], origin: tuple[float, float, float] | None = None
) -> NmeaLog:
    """Read an NMEA file (see :func:`parse_nmea`); raises :class:`InputError` if unreadable."""
    p = Path(path)
    try:
        text = p.read_bytes().decode("ascii", errors="replace")
    except OSError as exc:
        raise InputError(f"cannot read NMEA file: {exc.strerror or exc}", p) from None
    log = parse_nmea(text.splitlines(), origin=origin, source=str(p))
    if not len(log.motion) and not len(log.fixes):
        raise InputError(
            f"no usable RMC/VTG/GGA sentence ({log.summary.text()})", p
        )
    return log


# ------------------------------------------------------------------------ writing
def _hhmmss(t_s: float) -> str:
    t = t_s % 86400.0
    h = int(t // 3600)
    mi = int((t - 3600 * h) // 60)
    s = t - 3600 * h - 60 * mi
    return f"{h:02d}{mi:02d}{s:05.2f}"


def _ddmm(value_deg: float, lat: bool) -> tuple[str, str]:
    hemi = ("N" if value_deg >= 0 else "S") if lat else ("E" if value_deg >= 0 else "W")
    a = abs(value_deg)
    d = int(a)
    mins = (a - d) * 60.0
    return (f"{d:02d}{mins:09.6f}" if lat else f"{d:03d}{mins:09.6f}"), hemi


def make_rmc(
    t_s: float,
    speed_mps: float,
    course_deg: float,
    lat_deg: float = 0.0,
    lon_deg: float = 0.0,
    date: str = "010124",
    talker: str = "GP",
) -> str:
    """An RMC sentence with checksum (speed written in knots, course true from north)."""
    la, lah = _ddmm(lat_deg, True)
    lo, loh = _ddmm(lon_deg, False)
    course = "" if not np.isfinite(course_deg) else f"{course_deg % 360.0:.2f}"
    fields = (_hhmmss(t_s), "A", la, lah, lo, loh, f"{speed_mps / KNOT_MPS:.4f}", course, date,
              "", "", "A")
    return str(pynmea2.RMC(talker, "RMC", fields))


def make_vtg(speed_mps: float, course_deg: float, talker: str = "GP") -> str:
    """A VTG sentence with checksum (speed in knots and km/h)."""
    course = "" if not np.isfinite(course_deg) else f"{course_deg % 360.0:.2f}"
    fields = (course, "T", "", "M", f"{speed_mps / KNOT_MPS:.4f}", "N",
              f"{speed_mps * 3.6:.3f}", "K", "A")
    return str(pynmea2.VTG(talker, "VTG", fields))


def make_gga(
    t_s: float, lat_deg: float, lon_deg: float, h_m: float, quality: int = 1,
    n_sats: int = 8, hdop: float = 1.0, talker: str = "GP",
) -> str:
    """A GGA sentence with checksum (altitude written as ``h_m`` with zero geoid height)."""
    la, lah = _ddmm(lat_deg, True)
    lo, loh = _ddmm(lon_deg, False)
    fields = (_hhmmss(t_s), la, lah, lo, loh, str(quality), f"{n_sats:02d}", f"{hdop:.1f}",
              f"{h_m:.2f}", "M", "0.0", "M", "", "")
    return str(pynmea2.GGA(talker, "GGA", fields))
