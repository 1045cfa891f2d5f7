"""RINEX observation and navigation files.

* RINEX 2.xx observation files are read by a vectorized reader of our own
  (:func:`read_obs`): the epoch headers are parsed line by line, the observation records of
  the whole file are then cut into fixed-width fields and converted by NumPy in one go.  It is
  about ten times faster than georinex 1.16 on the shared GEONET file and prints no
  warnings; ``tests/test_gnss_rinex.py`` checks it value by value against georinex.
* RINEX 2 GPS and RINEX 3 navigation files are read by fixed-width record readers of our
  own (:func:`read_nav`): georinex 1.16 turns a RINEX 3 record with a blank field (a spare
  written as blanks, e.g. Galileo BROADCAST ORBIT 5 or BeiDou's) into NaN and the record
  was lost, and it files a second record of the same epoch (Galileo I/NAV + F/NAV) under a
  made-up satellite ``E01_1``.  ``tests/test_gnss_orbits_reference.py`` checks the records
  against RTKLIB.
* RINEX 3 observation files are read by a fixed-width reader of our own
  (:func:`_read_obs_v3`): georinex 1.16 silently dropped an epoch with an impossible date
  and every epoch after it, a value that is not a number, and epochs listing 0 satellites.
  RINEX 4 observation files have the records of RINEX 3 and are read by it too.
* RINEX 2 navigation files of other systems than GPS are read through georinex, with its
  xarray ``FutureWarning``/``DeprecationWarning`` flood silenced.
* RINEX 4 navigation files (records framed by ``> EPH``/``> ION``/... lines, the
  ionosphere coefficients in the body) are refused, naming line 1: georinex 1.16 does not
  read them either ("unknown RINEX").

An epoch that lists 0 satellites is an epoch without observations (a row of NaN), so that
every epoch of the file reaches the solver and gets an output row.

Times are GPS time in seconds since 1980-01-06 00:00:00 (``t_gps_s``), a float64.

Every problem of a file (truncated, wrong counts, impossible dates such as month 13, garbage
numbers, a satellite with two records in one epoch) raises
:class:`~robustloc.errors.InputError` naming the file and the line.  A
pseudorange outside the ``pseudorange`` limits of :mod:`robustloc.io.limits`
(1.5e7 .. 5e7 m) is an *invalid measurement*: it is set to NaN (never reaches a solver) and
counted per epoch in :attr:`ObsData.invalid`.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, field
from os import PathLike
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from robustloc.errors import InputError

#: Seconds per GPS week.
WEEK_S = 604800.0
_GPS_EPOCH = np.datetime64("1980-01-06T00:00:00", "ns")
#: BeiDou time (BDT) = GPS time - 14 s; BDT week 0 starts at GPS week 1356.
BDT_OFFSET_S = 14.0
BDT_WEEK0 = 1356


def datetime64_to_gps_s(t: NDArray) -> NDArray[np.float64]:
    """Convert ``datetime64`` values (GPS time scale) to seconds since the GPS epoch."""
    t = np.asarray(t, dtype="datetime64[ns]")
    return (t - _GPS_EPOCH).astype(np.int64) / 1e9


def gps_s_to_datetime64(t_gps_s: NDArray) -> NDArray:
    """Inverse of :func:`datetime64_to_gps_s` (rounded to the microsecond)."""
    us = np.round(np.asarray(t_gps_s, dtype=np.float64) * 1e6).astype(np.int64)
    return _GPS_EPOCH + us.astype("timedelta64[us]")


#: Offset (s) to add to an epoch of each RINEX observation time system to get GPS time
#: (RINEX 2.11 / 3.04 ``TIME OF FIRST OBS``): GPS, Galileo (GST), QZSS and NavIC system
#: times are aligned with GPS time (to nanoseconds), BDT = GPST - 14 s; ``GLO`` is UTC
#: (RINEX: "GLO (=UTC time system)") and gets GPS - UTC (:func:`_utc_to_gps_s`).
_OBS_TIME_SYSTEM_S = {"GPS": 0.0, "GAL": 0.0, "QZS": 0.0, "IRN": 0.0, "BDT": BDT_OFFSET_S}
#: Time system of a file without one in ``TIME OF FIRST OBS`` (RINEX 3.04 table A2: the
#: field is compulsory in mixed files; default GPS for pure GPS files, GLO for GLONASS,
#: GAL for Galileo, QZS for QZSS, BDT for BeiDou, IRN for NavIC).
_DEFAULT_TIME_SYSTEM = {"G": "GPS", "R": "GLO", "E": "GAL", "J": "QZS", "C": "BDT",
                        "I": "IRN", "M": "GPS", "S": "GPS"}


def _utc_to_gps_s(t_utc_s: NDArray[np.float64]) -> NDArray[np.float64]:
    """Epochs on the UTC scale (seconds since 1980-01-06 UTC) as GPS seconds."""
    from robustloc.gnss.spp import leap_seconds

    t = np.asarray(t_utc_s, dtype=np.float64)
    return t + leap_seconds(t + leap_seconds(t))


def _obs_time_system(hdr: dict[str, str], lines: list[str], path: str) -> str:
    """Time system of an observation file's epochs (``TIME OF FIRST OBS``, columns 49-51,
    else the default of the file's satellite system); an unknown one is an error."""
    rec = hdr.get("TIME OF FIRST OBS", "")
    code = rec.split("\n")[0][48:51].strip().upper()
    if not code:
        letter = hdr.get("RINEX VERSION / TYPE", " " * 41)[40:41].strip().upper() or "G"
        return _DEFAULT_TIME_SYSTEM.get(letter, "GPS")
    if code not in _OBS_TIME_SYSTEM_S and code != "GLO":
        line = next((i + 1 for i, ln in enumerate(lines)
                     if ln[60:80].strip() == "TIME OF FIRST OBS"), None)
        raise InputError(f"unknown time system {code!r} in TIME OF FIRST OBS (expected GPS, "
                         "GLO, GAL, QZS, BDT or IRN)", path, line)
    return code


def _epochs_to_gps_s(t: NDArray, system: str) -> NDArray[np.float64]:
    """``datetime64`` epochs of an observation file on ``system``'s scale, as GPS seconds."""
    s = datetime64_to_gps_s(t)
    if system == "GLO":
        return _utc_to_gps_s(s)
    return s + _OBS_TIME_SYSTEM_S[system]


@dataclass(frozen=True)
class ObsData:
    """Observations of one receiver file, as epoch x satellite arrays.

    Attributes
    ----------
    path : str
    version : float
    t_gps_s : ndarray (N,)
        Receiver time of each epoch (GPS seconds since 1980-01-06).
    sats : list of str
        Satellite ids (``G05``, ``E11``, ...), the columns of every array in ``obs``.
    obs : dict of str -> ndarray (N, S)
        Every observation type (``C1``, ``P2``, ``L1`` ... or RINEX 3 ``C1C`` ...), NaN where
        absent.  Pseudoranges in metres.
    approx_xyz_m : ndarray (3,)
        Header APPROX POSITION XYZ (zeros when absent).
    epoch_flag : ndarray of int (N,)
        RINEX epoch flag (0 ok, 1 power failure); flags 2-5 (events) and 6 (cycle-slip
        records of an epoch already given: slips in the observations' places) carry no
        observations and are not epochs.
    line : ndarray of int (N,)
        1-based line number of each epoch header (for messages).
    header : dict
        Header records.
    invalid : ndarray of int (N,), optional
        Pseudoranges of each epoch outside the physical limits, set to NaN
        (``invalid_measurement``); ``None`` is read as zeros.
    invalid_cells : dict of str -> ndarray of bool (N, S)
        Where those values were, per observation type (only the types that had one): the
        solver's status tells from them whether an epoch lost its fix to them.
    """

    path: str
    version: float
    t_gps_s: NDArray[np.float64]
    sats: list[str]
    obs: dict[str, NDArray[np.float64]]
    approx_xyz_m: NDArray[np.float64]
    epoch_flag: NDArray[np.int64]
    line: NDArray[np.int64]
    header: dict[str, str] = field(default_factory=dict)
    invalid: NDArray[np.int64] | None = None
    invalid_cells: dict[str, NDArray[np.bool_]] = field(default_factory=dict)

    @property
    def n_epochs(self) -> int:
        return int(self.t_gps_s.shape[0])

    @property
    def invalid_per_epoch(self) -> NDArray[np.int64]:
        """Implausible pseudoranges of each epoch (zeros when none were found)."""
        if self.invalid is None:
            return np.zeros(self.n_epochs, dtype=np.int64)
        return np.asarray(self.invalid, dtype=np.int64)

    def system_of(self) -> NDArray[np.str_]:
        """One-letter constellation of every column (``G``, ``R``, ``E``, ``C``, ``J``, ``S``)."""
        return np.array([s[0] for s in self.sats])

    def select(self, rows: slice | NDArray) -> ObsData:
        """A copy restricted to some epochs (a slice or boolean/int index)."""
        return ObsData(
            self.path, self.version, self.t_gps_s[rows], list(self.sats),
            {k: v[rows] for k, v in self.obs.items()}, self.approx_xyz_m,
            self.epoch_flag[rows], self.line[rows], dict(self.header),
            self.invalid_per_epoch[rows], {k: v[rows] for k, v in self.invalid_cells.items()},
        )


def is_pseudorange(obs_type: str) -> bool:
    """RINEX 2 ``C1, P1, P2, C2, C5, ...`` or RINEX 3 ``C1C, C2W, ...`` code observations."""
    return len(obs_type) >= 2 and obs_type[0] in "CP" and obs_type[1].isdigit()


def _implausible_pseudoranges(
    obs: dict[str, NDArray[np.float64]],
) -> tuple[NDArray[np.int64], dict[str, NDArray[np.bool_]]]:
    """Set pseudoranges outside the physical limits to NaN (in place); count per epoch,
    and where they were per type (:attr:`ObsData.invalid_cells`)."""
    from robustloc.io.limits import LIMITS

    lim = LIMITS["pseudorange"]
    count = None
    cells: dict[str, NDArray[np.bool_]] = {}
    for name, a in obs.items():
        if not is_pseudorange(name):
            continue
        bad = ~np.isnan(a) & ~lim.check(a)
        if bad.any():
            cells[name] = bad
        a[bad] = np.nan
        count = bad.sum(axis=1) if count is None else count + bad.sum(axis=1)
    n = next(iter(obs.values())).shape[0] if obs else 0
    return (np.zeros(n, dtype=np.int64) if count is None else count.astype(np.int64)), cells


def _calendar(y: int, mo: int, d: int, h: int, mi: int, sec: float, what: str, path: str,
              line: int) -> None:
    """Raise :class:`InputError` unless the fields are a calendar date and time of day."""
    import datetime

    try:
        datetime.date(y, mo, d)
        ok = 0 <= h <= 23 and 0 <= mi <= 59 and 0.0 <= sec < 61.0
    except ValueError:
        ok = False
    if not ok:
        raise InputError(
            f"impossible {what} {y:04d}-{mo:02d}-{d:02d} {h:02d}:{mi:02d}:{sec:06.3f} (month "
            "1-12, day of that month, hour 0-23, minute 0-59, second 0-60)", path, line)


class _Lines(list):  # type: ignore[type-arg]
    """The lines of a file; ``complete`` is False when the last one has no line end (the
    file may have been cut inside it)."""

    complete: bool = True


def _cut_field(lines: _Lines | list[str], first_col: int, path: str) -> None:
    """Raise when the file ends without a line end inside a fixed-width number field.

    Observation records are ``first_col`` characters and then fields of 16: an ``F14.3``
    value, right-aligned, and two one-digit flags; a record line therefore ends (blanks
    stripped) at character 14, 15 or 16 of a field.  A last line that ends elsewhere and has
    no line end was cut inside a value: ``23619216.594`` read as ``236192`` (exit 0, once).
    """
    if getattr(lines, "complete", True) or not lines:
        return
    text = lines[-1].rstrip()
    if len(text) > first_col and (len(text) - first_col) % 16 not in (0, 14, 15):
        start = first_col + 16 * ((len(text) - first_col) // 16)
        raise InputError(f"the file ends inside a value ({text[start:].strip()!r}, no line "
                         "end): the file was cut; the last record cannot be read",
                         path, len(lines))


def _read_lines(path: str | PathLike[str]) -> _Lines:
    p = Path(path)
    raw = p.read_bytes()
    if raw[:2] == b"\x1f\x8b":
        import gzip

        try:
            raw = gzip.decompress(raw)
        except (OSError, EOFError) as exc:  # (truncated: a traceback)
            raise InputError(f"not a readable gzip file ({exc})", str(path)) from None
    text = raw.decode("ascii", errors="replace")
    out = _Lines(text.splitlines())
    out.complete = not text or text.endswith(("\n", "\r"))
    return out


def _header(lines: list[str], path: str) -> tuple[dict[str, str], int]:
    """Header records as ``label -> concatenated contents`` and the index after it."""
    hdr: dict[str, str] = {}
    for i, ln in enumerate(lines):
        label = ln[60:80].strip()
        if label == "END OF HEADER":
            return hdr, i + 1
        if label in hdr:
            hdr[label] += "\n" + ln[:60]
        else:
            hdr[label] = ln[:60]
        if i > 2000:
            break
    raise InputError("no END OF HEADER: not a RINEX file or truncated header", path,
                     min(len(lines), 2001) or 1)


#: Satellite system letters of RINEX 2.11/2.12 observation files (GPS, GLONASS, SBAS,
#: Galileo, Transit; BeiDou and QZSS in 2.12).
RINEX2_SYSTEMS = ("G", "R", "S", "E", "T", "C", "J")
#: Magic bytes of compressions robustloc does not read (gzip it does), with their tools.
_COMPRESSED = {b"\x1f\x9d": "Unix compress (.Z): uncompress it (gunzip reads .Z too)",
               b"BZ": "bzip2: bunzip2 it", b"PK": "a zip archive: unzip it",
               b"\xfd7": "xz: unxz it", b"\x28\xb5": "zstandard: unzstd it"}


def _not_rinex(first: str, head: bytes) -> str:
    """Why a file's first line is no RINEX VERSION / TYPE record, with what to do: a
    Compact RINEX (Hatanaka) file or a compressed one was "not a RINEX VERSION / TYPE
    record" alone (the GNSS review, 2026-12-07)."""
    if "COMPACT RINEX" in first.upper() or "CRINEX" in first:
        return ("a Compact RINEX (Hatanaka) file: decompress it with crx2rnx (RNXCMP), then "
                "give the RINEX file")
    for magic, what in _COMPRESSED.items():
        if head.startswith(magic):
            return f"a compressed file ({what}, then give the RINEX file)"
    return "first line is not a RINEX VERSION / TYPE record"


def rinex_version(path: str | PathLike[str]) -> tuple[float, str]:
    """Version and file type letter (``O``, ``N``, ``G``, ...) of a RINEX file."""
    try:
        with open(path, "rb") as fh:
            head = fh.read(2)
            fh.seek(0)
            if head == b"\x1f\x8b":  # gzip, as _read_lines reads it (the spp review:
                import gzip  # a .gz file was refused as "not a RINEX VERSION record")

                try:
                    with gzip.open(fh) as gz:
                        first = gz.readline().decode("ascii", errors="replace")
                except (OSError, EOFError) as exc:
                    raise InputError(f"not a readable gzip file ({exc})", path) from None
            else:
                first = fh.readline().decode("ascii", errors="replace")
    except IsADirectoryError as exc:
        raise InputError("is a directory, expected a RINEX file", path) from exc
    if "RINEX VERSION" not in first:
        raise InputError(_not_rinex(first, head), path, 1)
    try:
        version = float(first[:9])
    except ValueError as exc:
        raise InputError(f"unreadable RINEX version {first[:9]!r}", path, 1) from exc
    if not 2.0 <= version < 5.0:  # (1.00 was read as 2, 9.99 as 3: the GNSS review)
        raise InputError(f"RINEX version {first[:9].strip()} is not supported (2.xx and "
                         "3.xx are, and 4.xx observation files)", path, 1)
    return version, first[20:21].upper()


def _obs_types_v2(hdr: dict[str, str], path: str, end_line: int | None = None) -> list[str]:
    rec = hdr.get("# / TYPES OF OBSERV")
    if rec is None:
        raise InputError("missing '# / TYPES OF OBSERV' header record (a RINEX 2 observation "
                         "header needs it)", path, end_line)
    parts = rec.split("\n")
    try:
        n = int(parts[0][:6])
    except ValueError as exc:
        raise InputError("unreadable number of observation types", path) from exc
    types: list[str] = []
    for p in parts:
        types += p[6:60].split()
    if len(types) < n:
        raise InputError(f"header lists {len(types)} observation types, expected {n}", path)
    return types[:n]


def _approx(hdr: dict[str, str]) -> NDArray[np.float64]:
    """The header's APPROX POSITION XYZ, or zeros when absent, unreadable or no position
    near the Earth's surface (within 100 km of the ellipsoid's radii, 6.25e6-6.48e6 m
    from the centre): ``inf`` was taken as the reference and printed as ``Infinity`` in
    ``--json``, 1e308 as the start (the spp review)."""
    try:
        xyz = np.array([float(v) for v in hdr["APPROX POSITION XYZ"].split()[:3]])
    except (KeyError, ValueError):
        return np.zeros(3)
    with np.errstate(over="ignore", invalid="ignore"):
        r = float(np.linalg.norm(xyz)) if xyz.size == 3 else np.nan
    return xyz if 6.25e6 < r < 6.48e6 else np.zeros(3)


def read_obs(path: str | PathLike[str]) -> ObsData:
    """Read a RINEX 2, 3 or 4 observation file.

    The versions are read by the fixed-width readers of this module
    (:func:`_read_obs_v2`, :func:`_read_obs_v3`; RINEX 4 observation records are those of
    RINEX 3).

    Parameters
    ----------
    path : str or path-like
        Observation file, optionally gzip-compressed.

    Returns
    -------
    ObsData
        One row per epoch of the file (flags 0 and 1), including epochs that list no
        satellites (all NaN).  A flag-6 record (cycle slips, in the format of
        observations) is skipped: its values were read as pseudoranges, and its time,
        an epoch's already, gave a second row.

    Raises
    ------
    InputError
        With file and line, for a truncated or malformed file (impossible epoch time,
        satellite count that does not match the records, a value that is not a number, a
        satellite with two records in one epoch: which one is right cannot be told).
    """
    path = str(path)
    version, ftype = rinex_version(path)
    if ftype != "O":
        raise InputError(f"not an observation file (RINEX type {ftype!r})", path, 1)
    if version < 3:
        return _read_obs_v2(path, version)
    return _read_obs_v3(path, version)


def _read_obs_v2(path: str, version: float) -> ObsData:
    lines = _read_lines(path)
    hdr, i0 = _header(lines, path)
    types = _obs_types_v2(hdr, path, i0)
    ntypes = len(types)
    nlines_sat = (ntypes + 4) // 5
    default_sys = hdr.get("RINEX VERSION / TYPE", " " * 41)[40:41].strip() or "G"
    if default_sys == "M":
        default_sys = "G"
    times: list[tuple[int, int, int, int, int, float]] = []
    flags: list[int] = []
    ep_lines: list[int] = []
    sat_ids: list[str] = []  # one per record
    rec_epoch: list[int] = []
    rec_start: list[int] = []  # index in lines of the first line of each record
    i = i0
    n = len(lines)
    block = i0  # first line of the last epoch's records
    while i < n:
        ln = lines[i]
        if not ln.strip():
            i += 1
            continue
        try:
            flag = int(ln[26:29] or 0)
            nsat = int(ln[29:32])
        except ValueError as exc:
            _stray_record(lines, block, i, path)
            raise InputError(f"malformed epoch header {ln.rstrip()!r}", path, i + 1) from exc
        if not 0 <= flag <= 6 or nsat < 0:
            _stray_record(lines, block, i, path)
            raise InputError(f"malformed epoch header {ln.rstrip()!r}: epoch flag must be "
                             f"0-6 and the satellite count >= 0", path, i + 1)
        if flag >= 2 and flag <= 5:
            i += 1 + nsat  # event: nsat special records follow
            continue
        try:
            yy = int(ln[1:3])
            ep = (
                yy + (2000 if yy < 80 else 1900), int(ln[4:6]), int(ln[7:9]), int(ln[10:12]),
                int(ln[13:15]), float(ln[15:26]),
            )
            sec = ep[5]
        except ValueError as exc:
            _stray_record(lines, block, i, path)
            raise InputError(f"malformed epoch time {ln[:26]!r}", path, i + 1) from exc
        _calendar(*ep[:5], sec, "epoch time", path, i + 1)
        svtxt = ln[32:68]
        # the epoch header takes one line per 12 satellites, and one line with none: an
        # epoch that lists 0 satellites is an epoch without observations, not an endless loop
        nhead = max(1, (nsat + 11) // 12)
        for k in range(1, nhead):
            if i + k >= n:
                raise InputError("file ends inside an epoch header", path, i + k)
            svtxt += lines[i + k][32:68]
        sats = []
        for k in range(nsat):
            s = svtxt[3 * k : 3 * k + 3]
            if len(s) < 3 or not s.strip():
                raise InputError(
                    f"the epoch announces {nsat} satellites but lists {k}", path, i + 1)
            sysch = s[0] if s[0] != " " else default_sys
            if sysch not in RINEX2_SYSTEMS:  # (X24 was dropped without a word and its
                # epoch said ill_conditioned: the GNSS review, 2026-12-07)
                raise InputError(f"unknown satellite system {sysch!r} in {s!r} (RINEX 2 "
                                 f"knows {', '.join(RINEX2_SYSTEMS)})", path, i + 1)
            try:
                prn = int(s[1:3])
            except ValueError as exc:
                raise InputError(f"malformed satellite id {s!r}", path, i + 1) from exc
            sats.append(f"{sysch}{prn:02d}")
        if flag == 6:  # cycle slips in the observations' places: not an epoch
            if i + nhead + nsat * nlines_sat > n:
                raise InputError(f"file ends inside the cycle-slip records starting here "
                                 f"({nsat} satellites announced)", path, i + 1)
            i += nhead + nsat * nlines_sat
            continue
        epoch_idx = len(times)
        times.append(ep)  # type: ignore[arg-type]
        flags.append(flag)
        ep_lines.append(i + 1)
        i += nhead
        block = i
        if i + nsat * nlines_sat > n:
            raise InputError(
                f"file ends inside the epoch starting here ({nsat} satellites announced)",
                path, ep_lines[-1],
            )
        first_rec: dict[str, int] = {}
        for s in sats:
            if s in first_rec:
                _listed_twice(s, ep_lines[-1], first_rec[s], i + 1, path)
            first_rec[s] = i + 1
            sat_ids.append(s)
            rec_epoch.append(epoch_idx)
            rec_start.append(i)
            i += nlines_sat
    if not times:
        raise InputError("no observation epochs after the header", path, i0 + 1)
    if rec_start and rec_start[-1] <= n - 1 < rec_start[-1] + nlines_sat:
        _cut_field(lines, 0, path)  # (the last line is an observation record)

    # vectorized field extraction: each record -> nlines_sat padded 80-char lines
    nrec = len(rec_start)
    starts = np.asarray(rec_start, dtype=np.int64)
    idx = (starts[:, None] + np.arange(nlines_sat)[None, :]).ravel()
    block = "".join(lines[j][:80].ljust(80) for j in idx.tolist())
    buf = np.frombuffer(block.encode("ascii", errors="replace"), dtype="S1").reshape(
        nrec, nlines_sat, 80
    )
    values = np.full((nrec, ntypes), np.nan)
    for t in range(ntypes):
        li, col = divmod(t, 5)
        fld = buf[:, li, col * 16 : col * 16 + 14].copy().view("S14").ravel()
        blank = np.char.strip(fld) == b""
        vals, bad = _numbers(fld, blank)
        if bad >= 0:
            raise InputError(
                f"malformed {types[t]} value {fld[bad].decode(errors='replace')!r}",
                path, int(starts[bad]) + li + 1,
            ) from None
        values[:, t] = vals
    # 0.0 means "not observed" in some writers
    values[values == 0.0] = np.nan

    all_sats = sorted(set(sat_ids), key=lambda s: ("GRECJS".find(s[0]), s))
    col_of = {s: k for k, s in enumerate(all_sats)}
    cols = np.array([col_of[s] for s in sat_ids], dtype=np.int64)
    rows = np.asarray(rec_epoch, dtype=np.int64)
    nep = len(times)
    obs = {}
    for t, name in enumerate(types):
        a = np.full((nep, len(all_sats)), np.nan)
        a[rows, cols] = values[:, t]
        obs[name] = a
    tt = np.array(
        [
            np.datetime64(f"{y:04d}-{mo:02d}-{d:02d}T{h:02d}:{mi:02d}", "ns")
            + np.int64(round(s * 1e9)).astype("timedelta64[ns]")
            for (y, mo, d, h, mi, s) in times
        ]
    )
    invalid, cells = _implausible_pseudoranges(obs)
    return ObsData(
        path, version, _epochs_to_gps_s(tt, _obs_time_system(hdr, lines, path)), all_sats,
        obs, _approx(hdr),
        np.asarray(flags, dtype=np.int64), np.asarray(ep_lines, dtype=np.int64), hdr,
        invalid, cells,
    )


def _listed_twice(sat: str, epoch_line: int, first: int, second: int, path: str) -> None:
    """Raise for a satellite with two observation records in one epoch (1-based lines).

    A receiver writes one record per satellite and epoch: two are a malformed file (an
    edit or a splice gone wrong), and which of them is right cannot be told.  The later
    one silently replaced the earlier (a record 1000 m off gave an ``ok`` fix 315 m off
    without RAIM: the spp review); averaging them, as ``locate`` merges the duplicate
    rows of a measurements table (repeated measurements of one quantity), would put
    the fix halfway.
    """
    raise InputError(f"satellite {sat} listed twice in the epoch of line {epoch_line} "
                     f"(its first record is line {first}): one record per satellite and "
                     "epoch; remove the wrong one", path, second)


def _stray_record(lines: list[str], start: int, stop: int, path: str) -> None:
    """Raise for the first line of ``lines[start:stop]`` (the last epoch's observation
    records) that is not an observation record: a field of columns ``16 c .. 16 c + 14``
    that is neither blank nor a number, or a loss-of-lock / strength flag that is not a
    digit.  Records are counted, not recognized, so a stray line inside an epoch shifts
    the records after it and the reader stumbles only at the line taken for the next
    epoch's header, up to a whole epoch later: the stray line itself is the place to
    name.  Returns when every line is a record.
    """
    for j in range(max(start, 0), stop):
        text = lines[j].rstrip("\r\n")
        for c in range(5):
            fld = text[16 * c : 16 * c + 14]
            flags = text[16 * c + 14 : 16 * c + 16]
            if (fld.strip() and not _isfloat(fld.encode(errors="replace"))) or any(
                    ch not in " 0123456789" for ch in flags):
                raise InputError(f"not an observation record {text!r} (a stray line, or "
                                 "a line missing, in the epoch's records)", path, j + 1)


def _isfloat(b: bytes, finite: bool = True) -> bool:
    """A number as a fixed-width RINEX field writes it: Python's ``float`` also takes
    ``1_000``, ``nan`` and ``inf``, which no RINEX writer produces (a hand edit, or another
    program's text: once read as values)."""
    if b"_" in b:
        return False
    try:
        value = float(b)
    except ValueError:
        return False
    return bool(np.isfinite(value)) or not finite


def _numbers(fld: NDArray, blank: NDArray[np.bool_],
             finite: bool = True) -> tuple[NDArray[np.float64], int]:
    """Values of fixed-width fields ``fld`` (bytes), NaN where ``blank``, and the index of
    the first field that is not a number (:func:`_isfloat`), or -1."""
    try:
        vals = np.where(blank, b"nan", fld).astype(np.float64)
    except ValueError:
        vals = np.full(fld.shape, np.nan)
        return vals, next(k for k in range(fld.size) if not blank[k] and not _isfloat(fld[k]))
    odd = ~blank & (np.char.find(fld, b"_") >= 0)
    if finite:
        odd |= ~blank & ~np.isfinite(vals)
    return vals, int(np.argmax(odd)) if odd.any() else -1


def _georinex_load(path: str, **kw):  # noqa: ANN202
    import georinex as gr

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        try:
            return gr.load(path, **kw)
        except InputError:
            raise
        except Exception as exc:  # georinex raises many types on malformed input
            raise InputError(f"georinex could not read the file: {exc}", path) from exc


def _obs_types_v3(hdr: dict[str, str], path: str,
                  end_line: int | None = None) -> dict[str, list[str]]:
    """Observation types of each system from the ``SYS / # / OBS TYPES`` records.

    A record starts with the system letter and the number of types (``A1,2X,I3``), followed
    by up to 13 types (``13(1X,A3)``); continuation lines have a blank system and count.
    """
    rec = hdr.get("SYS / # / OBS TYPES")
    if rec is None:
        raise InputError("missing 'SYS / # / OBS TYPES' header record (a RINEX 3/4 "
                         "observation header needs it; is the version on line 1 right?)",
                         path, end_line)
    types: dict[str, list[str]] = {}
    want: dict[str, int] = {}
    sysch = ""
    for part in rec.split("\n"):
        if part[:1].strip():
            sysch = part[0]
            try:
                want[sysch] = int(part[3:6])
            except ValueError as exc:
                raise InputError(f"unreadable number of {sysch} observation types in "
                                 f"{part.rstrip()!r}", path) from exc
            types[sysch] = []
        elif not sysch:
            raise InputError("'SYS / # / OBS TYPES' continuation line without a system",
                             path)
        types[sysch] += part[7:60].split()
    for sysch, n in want.items():
        if len(types[sysch]) < n:
            raise InputError(f"header lists {len(types[sysch])} {sysch} observation types, "
                             f"expected {n}", path)
        types[sysch] = types[sysch][:n]
    return types


def _read_obs_v3(path: str, version: float) -> ObsData:
    """Fixed-width reader of RINEX 3 observation files (RINEX 3.04 section 6.6, table A3).

    An epoch is a line ``> YYYY MM DD HH MM SS.SSSSSSS  F NNN`` (columns 3-6 year, 8-9
    month, 11-12 day, 14-15 hour, 17-18 minute, 19-29 second, 32 epoch flag, 33-35 number
    of satellites) followed by one line per satellite: ``SNN`` and 16 characters per
    observation type of that system (``F14.3`` value, loss-of-lock and signal-strength
    indicators).  Epoch flags 2-5 are events followed by as many special records as the
    count says, and flag 6 reports cycle slips in the records of an epoch already given;
    they carry no observations and are skipped.  An epoch that lists 0
    satellites is an epoch without observations (all NaN).  Blank fields and ``0.000``
    (not observed) are NaN; an impossible epoch time, a count that does not match the
    records, a truncated file or a value that is not a number raises :class:`InputError`
    naming the file and the line (georinex, used before, dropped such epochs or values
    silently, and with them every later epoch).
    """
    lines = _read_lines(path)
    hdr, i0 = _header(lines, path)
    types = _obs_types_v3(hdr, path, i0)
    times: list[tuple[int, int, int, int, int, float]] = []
    flags: list[int] = []
    ep_lines: list[int] = []
    rec_sat: list[str] = []  # one per satellite record
    rec_epoch: list[int] = []
    rec_line: list[int] = []  # index in lines of each record
    i = i0
    n = len(lines)
    while i < n:
        ln = lines[i]
        if not ln.strip():
            i += 1
            continue
        if ln[:1] != ">":
            raise InputError(f"expected an epoch line '> YYYY MM DD HH MM SS.SSSSSSS  F NNN', "
                             f"got {ln.rstrip()[:40]!r}", path, i + 1)
        try:
            flag = int(ln[29:32] or 0)
            nsat = int(ln[32:35])
        except ValueError as exc:
            raise InputError(f"malformed epoch line {ln.rstrip()!r}", path, i + 1) from exc
        if not 0 <= flag <= 6 or nsat < 0:
            raise InputError(f"malformed epoch line {ln.rstrip()!r}: epoch flag must be 0-6 "
                             "and the satellite count >= 0", path, i + 1)
        if 2 <= flag <= 5:
            i += 1 + nsat  # event: nsat special records follow
            continue
        try:
            ep = (int(ln[2:6]), int(ln[7:9]), int(ln[10:12]), int(ln[13:15]),
                  int(ln[16:18]), float(ln[18:29]))
        except ValueError as exc:
            raise InputError(f"malformed epoch time {ln[:29]!r}", path, i + 1) from exc
        _calendar(*ep, "epoch time", path, i + 1)
        if i + 1 + nsat > n:
            raise InputError(
                f"file ends inside the epoch starting here ({nsat} satellites announced)",
                path, i + 1)
        if flag == 6:  # cycle slips in the observations' places: not an epoch
            i += 1 + nsat
            continue
        epoch_idx = len(times)
        times.append(ep)
        flags.append(flag)
        ep_lines.append(i + 1)
        first_rec: dict[str, int] = {}
        for k in range(1, nsat + 1):
            rec = lines[i + k]
            if rec[:1] == ">" or not rec.strip():
                raise InputError(f"the epoch announces {nsat} satellites but lists {k - 1}",
                                 path, i + 1)
            sysch = rec[0]
            try:
                prn = int(rec[1:3])  # "G07", "G 7", "G7 " (not G70)
            except ValueError as exc:
                raise InputError(f"malformed satellite id {rec[:3]!r}", path,
                                 i + k + 1) from exc
            if sysch not in types:
                raise InputError(f"satellite {rec[:3]!r} of a system without "
                                 "'SYS / # / OBS TYPES' in the header", path, i + k + 1)
            sat = f"{sysch}{prn:02d}"
            if sat in first_rec:
                _listed_twice(sat, i + 1, first_rec[sat], i + k + 1, path)
            first_rec[sat] = i + k + 1
            rec_sat.append(sat)
            rec_epoch.append(epoch_idx)
            rec_line.append(i + k)
        i += 1 + nsat
    if not times:
        raise InputError("no observation epochs after the header", path, i0 + 1)
    if rec_line and rec_line[-1] == n - 1:
        _cut_field(lines, 3, path)  # (the last line is an observation record)

    names = list(dict.fromkeys(t for ts in types.values() for t in ts))
    all_sats = sorted(set(rec_sat), key=lambda s: ("GRECJS".find(s[0]), s))
    col_of = {s: k for k, s in enumerate(all_sats)}
    nep = len(times)
    obs = {name: np.full((nep, len(all_sats)), np.nan) for name in names}
    rec_sys = np.array([s[0] for s in rec_sat], dtype="U1")
    rows_all = np.asarray(rec_epoch, dtype=np.int64)
    cols_all = np.array([col_of[s] for s in rec_sat], dtype=np.int64)
    lines_all = np.asarray(rec_line, dtype=np.int64)
    for sysch, sys_types in types.items():
        sel = np.flatnonzero(rec_sys == sysch)
        if sel.size == 0 or not sys_types:
            continue
        width = 3 + 16 * len(sys_types)
        block = "".join(lines[j][:width].ljust(width) for j in lines_all[sel].tolist())
        buf = np.frombuffer(block.encode("ascii", errors="replace"), dtype="S1").reshape(
            sel.size, width)
        for t, name in enumerate(sys_types):
            fld = buf[:, 3 + 16 * t : 17 + 16 * t].copy().view("S14").ravel()
            blank = np.char.strip(fld) == b""
            vals, bad = _numbers(fld, blank)
            if bad >= 0:
                raise InputError(
                    f"malformed {name} value {fld[bad].decode(errors='replace')!r} of "
                    f"{rec_sat[sel[bad]]}", path, int(lines_all[sel[bad]]) + 1,
                ) from None
            vals[vals == 0.0] = np.nan  # 0.000: not observed
            obs[name][rows_all[sel], cols_all[sel]] = vals
    tt = np.array(
        [
            np.datetime64(f"{y:04d}-{mo:02d}-{d:02d}T{h:02d}:{mi:02d}", "ns")
            + np.int64(round(sec * 1e9)).astype("timedelta64[ns]")
            for (y, mo, d, h, mi, sec) in times
        ],
        dtype="datetime64[ns]",
    )
    invalid, cells = _implausible_pseudoranges(obs)
    return ObsData(
        path, version, _epochs_to_gps_s(tt, _obs_time_system(hdr, lines, path)), all_sats,
        obs, _approx(hdr),
        np.asarray(flags, dtype=np.int64), np.asarray(ep_lines, dtype=np.int64), hdr,
        invalid, cells,
    )


# --------------------------------------------------------------------------- navigation


#: Broadcast ephemeris fields kept (georinex names); system-specific group delays are
#: mapped to ``tgd`` (GPS TGD, Galileo BGD E1/E5a, BeiDou TGD1) and, for BeiDou, ``tgd2``
#: (TGD2, B2I against the B3I clock; 0 for the other systems).
_KEPLER = (
    "SVclockBias", "SVclockDrift", "SVclockDriftRate", "Crs", "DeltaN", "M0", "Cuc",
    "Eccentricity", "Cus", "sqrtA", "Toe", "Cic", "Omega0", "Cis", "Io", "Crc", "omega",
    "OmegaDot", "IDOT", "health",
)

#: Largest magnitude of a broadcast parameter that can belong to a real orbit or clock: at
#: least 100 times the largest value the GPS (IS-GPS-200 table 20-III), Galileo (OS SIS ICD
#: tables 60 and 63) and BeiDou (B1I ICD section 5.2.4) messages can encode, rounded up to
#: a power of ten.  RINEX units: s, s/s, s/s^2, m, rad, rad/s.
NAV_MAX_ABS = {
    "SVclockBias": 10.0,  # encodable: 2^-4 s (Galileo af0)
    "SVclockDrift": 1e-5,  # 2^-26 s/s (Galileo af1)
    "SVclockDriftRate": 1e-12,  # 2^-48 s/s^2 (GPS af2)
    "Crs": 1e6, "Crc": 1e6,  # 2048 m (BeiDou)
    "Cuc": 1e-2, "Cus": 1e-2, "Cic": 1e-2, "Cis": 1e-2,  # 2^-14 rad
    "DeltaN": 1e-5,  # 2^-28 semicircles/s = 1.2e-8 rad/s
    "M0": 1e3, "Omega0": 1e3, "omega": 1e3, "Io": 1e3,  # one semicircle = pi rad
    "OmegaDot": 1e-3,  # 2^-20 semicircles/s = 3.0e-6 rad/s
    "IDOT": 1e-6,  # 2^-30 semicircles/s = 2.9e-9 rad/s
    "tgd": 1e-4,  # 2^-23 s (Galileo BGD)
    "tgd2": 1e-4,  # 51.2 ns (BeiDou TGD2: 10 bits of 0.1 ns)
}
#: sqrt(A) of an Earth orbit (sqrt(m); GNSS 5153 .. 6493): A = 1e6 m is inside the Earth
#: (the perigee test below is the sharper one), 1e10 m far beyond the Earth's sphere of
#: influence (about 1e9 m).
NAV_SQRT_A_RANGE = (1e3, 1e5)
#: Polar radius of the Earth (m): an orbit whose perigee A (1 - e) is below it crosses the
#: Earth.
EARTH_POLAR_RADIUS_M = 6356752.0


class NavRecordWarning(UserWarning):
    """A navigation record that cannot describe a satellite was set aside (not used); the
    message names the file and line (``FILE:LINE: ...``)."""


def nav_record_problems(
    params: dict[str, NDArray[np.float64]],
) -> list[tuple[str, NDArray[np.bool_], str]]:
    """Broadcast records that cannot describe an orbit and a clock, check by check.

    A record must have every parameter finite, ``0 <= e < 1`` (a closed orbit),
    ``sqrt(A)`` in :data:`NAV_SQRT_A_RANGE`, a perigee ``A (1 - e)`` above the Earth's
    surface, ``0 <= Toe <= 604800`` s (a second of the week) and every parameter of
    :data:`NAV_MAX_ABS` within its limit.  Only comparisons: no arithmetic on values out
    of range (nothing can overflow).

    Parameters
    ----------
    params : dict of str -> ndarray (R,)
        :attr:`NavData.params` (or the same keys for records being read).

    Returns
    -------
    list of (str, ndarray of bool (R,), str)
        For each check, in the order above: the parameter it is about, the records that
        fail it, and what the parameter must be (for messages).
    """
    out: list[tuple[str, NDArray[np.bool_], str]] = [
        (k, ~np.isfinite(v), "must be a finite number") for k, v in params.items()
    ]
    e = params["Eccentricity"]
    sqrt_a = params["sqrtA"]
    lo, hi = NAV_SQRT_A_RANGE
    e_ok = (e >= 0.0) & (e < 1.0)
    a_ok = (sqrt_a >= lo) & (sqrt_a <= hi)
    out.append(("Eccentricity", ~e_ok, "must lie in [0, 1) (a closed orbit)"))
    out.append(("sqrtA", ~a_ok, f"must lie in [{lo:g}, {hi:g}] sqrt(m) (an Earth orbit)"))
    both = e_ok & a_ok  # the perigee of values in range: no overflow
    perigee = np.where(both, sqrt_a, 0.0) ** 2 * (1.0 - np.where(both, e, 0.0))
    out.append(("sqrtA", both & ~(perigee >= EARTH_POLAR_RADIUS_M),
                "gives a perigee sqrtA^2 (1 - Eccentricity) below the Earth's surface "
                f"({EARTH_POLAR_RADIUS_M:.0f} m)"))
    toe = params["Toe"]
    out.append(("Toe", ~((toe >= 0.0) & (toe <= WEEK_S)),
                f"must lie in [0, {WEEK_S:.0f}] s (a second of the week)"))
    for k, lim in NAV_MAX_ABS.items():
        if k in params:  # (tgd2: BeiDou's, absent from NavData built by hand)
            out.append((k, ~(np.abs(params[k]) <= lim), f"must lie within +-{lim:g}"))
    return out


def plausible_records(params: dict[str, NDArray[np.float64]]) -> NDArray[np.bool_]:
    """Records that pass every check of :func:`nav_record_problems`."""
    bad = np.zeros(np.shape(params["sqrtA"]), dtype=bool)
    for _, fails, _ in nav_record_problems(params):
        bad |= fails
    return ~bad


def _without_impossible(
    rec: dict[str, NDArray], lines: dict[str, NDArray[np.int64]] | None, path: str,
) -> tuple[dict[str, NDArray], list[str]]:
    """The records of ``rec`` that pass :func:`nav_record_problems`, and one message
    ``FILE:LINE: ...`` per record set aside (its first problem; ``lines`` are the 0-based
    file lines of each parameter, ``None`` when unknown).  ``rec`` holds the parameters,
    ``sat`` and ``toc``."""
    checks = nav_record_problems({k: rec[k] for k in (*_KEPLER, "tgd", "tgd2") if k in rec})
    fails = np.stack([f for _, f, _ in checks])  # (checks, R)
    bad = fails.any(axis=0)
    messages = []
    for r in np.flatnonzero(bad).tolist():
        name, _, what = checks[int(np.argmax(fails[:, r]))]
        line = None if lines is None else int(lines[name][r]) + 1
        which = str(rec["sat"][r])
        if line is None:  # no line to point at: the record's clock epoch (GPS time)
            toc = gps_s_to_datetime64(rec["toc"][r : r + 1])[0]
            which += " record of " + np.datetime_as_string(toc, unit="s").replace("T", " ")
        else:
            which += " record"
        messages.append(str(InputError(
            f"{which} set aside: {name} = {rec[name][r]:.12g} {what}; it is not used",
            path, line)))
    return {k: v[~bad] for k, v in rec.items()}, messages


@dataclass(frozen=True)
class NavData:
    """Broadcast ephemerides of GPS, Galileo and BeiDou, one row per record.

    Attributes
    ----------
    sat : ndarray of str (R,)
    toc_gps_s : ndarray (R,)
        Clock reference time, GPS seconds (BeiDou converted from BDT).
    toe_gps_s : ndarray (R,)
        Ephemeris reference time, GPS seconds, week resolved from ``toc`` (so week-number
        rollover in the file does not matter).
    params : dict of str -> ndarray (R,)
        Keplerian and clock parameters (georinex names) plus the group delays ``tgd``
        (s; GPS TGD, Galileo BGD E1/E5a, BeiDou TGD1) and ``tgd2`` (s; BeiDou TGD2, else
        0).
    ion_alpha, ion_beta : ndarray (4,) or None
        GPS Klobuchar coefficients from the header.
    paths : list of str
    rejected : tuple of str
        One message ``FILE:LINE: ...`` per record of the files set aside because it cannot
        describe a satellite (:func:`nav_record_problems`); those records are not here.
    """

    sat: NDArray[np.str_]
    toc_gps_s: NDArray[np.float64]
    toe_gps_s: NDArray[np.float64]
    params: dict[str, NDArray[np.float64]]
    ion_alpha: NDArray[np.float64] | None
    ion_beta: NDArray[np.float64] | None
    paths: list[str]
    rejected: tuple[str, ...] = ()

    @property
    def n_records(self) -> int:
        return int(self.sat.shape[0])


def _parse_d(s: str) -> float:
    return float(s.replace("D", "E").replace("d", "e"))


def _klobuchar_from_header(hdr_lines: list[str]) -> tuple[NDArray | None, NDArray | None]:
    alpha = beta = None
    for ln in hdr_lines:
        label = ln[60:80].strip()
        body = ln[:60]
        try:
            if label == "ION ALPHA":
                alpha = np.array([_parse_d(body[2 + 12 * k : 14 + 12 * k]) for k in range(4)])
            elif label == "ION BETA":
                beta = np.array([_parse_d(body[2 + 12 * k : 14 + 12 * k]) for k in range(4)])
            elif label == "IONOSPHERIC CORR" and body[:4] == "GPSA":
                alpha = np.array([_parse_d(body[5 + 12 * k : 17 + 12 * k]) for k in range(4)])
            elif label == "IONOSPHERIC CORR" and body[:4] == "GPSB":
                beta = np.array([_parse_d(body[5 + 12 * k : 17 + 12 * k]) for k in range(4)])
        except ValueError:
            continue
    return alpha, beta


def read_nav(paths: str | PathLike[str] | list) -> NavData:
    """Read one or several RINEX 2/3 navigation files (GPS, Galileo, BeiDou records).

    RINEX 2 GPS files and RINEX 3 files are read by the fixed-width record readers of this
    module (:func:`_read_nav_v2`, :func:`_read_nav_v3`): every GPS, Galileo and BeiDou
    record of the file becomes one row, including Galileo I/NAV and F/NAV records of the
    same epoch.  Other RINEX 2 navigation types go through georinex.  GLONASS, SBAS, QZSS
    and NavIC records are skipped (use SP3 for GLONASS).  Raises :class:`InputError` with
    the file and line for a truncated or malformed record, or a blank orbit or clock
    parameter, instead of dropping the record, and on line 1 of a RINEX 4 navigation file
    (not supported: its records are framed by ``> EPH`` lines, which neither this module
    nor georinex 1.16 reads).

    A record whose values cannot describe a satellite (:func:`nav_record_problems`: an
    eccentricity of 1.5, sqrt(A) of 0, an infinite value, ...) is set aside with a
    :class:`NavRecordWarning` ``FILE:LINE: ...`` (also in :attr:`NavData.rejected`): the
    other records are used as if it were not in the file.  An error when no record is
    left.
    """
    if isinstance(paths, (str, PathLike)):
        paths = [paths]
    recs: list[dict[str, NDArray]] = []
    rejected: list[str] = []
    alpha = beta = None
    for p in paths:
        p = str(p)
        version, ftype = rinex_version(p)
        if ftype not in ("N", "G", "L", "E", "C") and not (version >= 3 and ftype == "N"):
            raise InputError(f"not a navigation file (RINEX type {ftype!r})", p, 1)
        if version >= 4:  # (was handed to georinex, which refuses it: "unknown RINEX")
            raise InputError(f"RINEX {version:.2f} navigation files are not supported (their "
                             "records are framed by '> EPH' lines): give RINEX 3 or 2 "
                             "navigation files (e.g. the IGS merged BRDC00..._MN.rnx of "
                             "RINEX 3), or --sp3 and --clk", p, 1)
        lines = _read_lines(p)
        hdr, i0 = _header(lines, p)
        a, b = _klobuchar_from_header(lines[:i0])
        alpha = a if alpha is None else alpha
        beta = b if beta is None else beta
        if not any(ln.strip() for ln in lines[i0:]):
            raise InputError("no ephemeris records after the header", p, i0 + 1)
        if version < 3 and ftype == "N":
            rec, bad = _read_nav_v2(lines, i0, p)
        elif 3 <= version < 4:
            rec, bad = _read_nav_v3(lines, i0, p)
        else:
            rec, bad = _nav_from_georinex(p)
        for text in bad:
            warnings.warn(text, NavRecordWarning, stacklevel=2)
        rejected += bad
        if rec is not None:
            recs.append(rec)
    if not recs:
        raise InputError("no GPS, Galileo or BeiDou ephemeris in the navigation file(s)",
                         str(paths[0]))
    sat = np.concatenate([r["sat"] for r in recs])
    if sat.size == 0:
        raise InputError(f"no usable GPS, Galileo or BeiDou ephemeris: all {len(rejected)} "
                         "records set aside (impossible orbit or clock values)",
                         str(paths[0]))
    return NavData(
        sat,
        np.concatenate([r["toc"] for r in recs]),
        np.concatenate([r["toe"] for r in recs]),
        {k: np.concatenate([r[k] for r in recs]) for k in (*_KEPLER, "tgd", "tgd2")},
        alpha, beta, [str(p) for p in paths], tuple(rejected),
    )


def _nav_from_georinex(path: str) -> tuple[dict[str, NDArray] | None, list[str]]:
    """GPS, Galileo and BeiDou records of a navigation file georinex reads (RINEX 2 types
    other than GPS).  georinex names the second record of a satellite at the same
    epoch ``E01_1``: the suffix is removed so that the record stays with its satellite.
    Returns the records and the messages of those set aside (without line numbers)."""
    ds = _georinex_load(path)
    if ds is None or "sv" not in ds.coords:
        raise InputError("no ephemeris records could be read", path)
    svs = np.asarray([str(s) for s in ds.sv.values])
    sat_l, toc_l, shift_l = [], [], []
    par_l: dict[str, list] = {k: [] for k in (*_KEPLER, "tgd", "tgd2")}
    for sysch, tgd_name in (("G", "TGD"), ("E", "BGDe5a"), ("C", "TGD1")):
        sel = np.char.startswith(svs, sysch)
        if not sel.any() or "sqrtA" not in ds:
            continue
        sub = ds.isel(sv=np.nonzero(sel)[0])
        sq = np.asarray(sub["sqrtA"].values)
        ti, si = np.nonzero(np.isfinite(sq))
        if ti.size == 0:
            continue
        toc = datetime64_to_gps_s(sub.time.values[ti])
        if sysch == "C":
            toc = toc + BDT_OFFSET_S  # georinex gives BDT epochs; convert to GPS time
        sat_l.append(np.asarray([str(s).split("_")[0] for s in sub.sv.values])[si])
        toc_l.append(toc)
        shift_l.append(np.full(ti.size, BDT_OFFSET_S if sysch == "C" else 0.0))
        for k in _KEPLER:
            name = "SatH1" if (k == "health" and sysch == "C") else k
            par_l[k].append(np.asarray(sub[name].values, dtype=np.float64)[ti, si]
                            if name in sub else np.zeros(ti.size))
        for key, name in (("tgd", tgd_name), ("tgd2", "TGD2" if sysch == "C" else "")):
            tg = sub[name] if name and name in sub else None
            par_l[key].append(np.zeros(ti.size) if tg is None
                              else np.asarray(tg.values, dtype=np.float64)[ti, si])
    if not sat_l:
        return None, []
    out = {k: np.concatenate(v) for k, v in par_l.items()}
    for k in ("health", "tgd", "tgd2"):
        out[k] = np.where(np.isnan(out[k]), 0.0, out[k])
    if np.isnan(np.stack([out[k] for k in _REQUIRED])).any():
        raise InputError("georinex left orbit or clock parameters of a record unreadable",
                         path)
    out["sat"] = np.concatenate(sat_l)
    out["toc"] = np.concatenate(toc_l)
    out["shift"] = np.concatenate(shift_l)
    out, rejected = _without_impossible(out, None, path)
    out["toe"] = _resolve_toe(out["toc"], out["Toe"] + out.pop("shift"))
    return out, rejected


#: Parameters without which a record cannot place the satellite: a blank one is an error.
_REQUIRED = tuple(k for k in _KEPLER if k != "health")

#: Field names line by line of a GPS record (RINEX 2.11 table A4 = RINEX 3.04 table A6).
_NAV2_FIELDS = (
    ("SVclockBias", "SVclockDrift", "SVclockDriftRate"),
    ("IODE", "Crs", "DeltaN", "M0"),
    ("Cuc", "Eccentricity", "Cus", "sqrtA"),
    ("Toe", "Cic", "Omega0", "Cis"),
    ("Io", "Crc", "omega", "OmegaDot"),
    ("IDOT", "CodesL2", "GPSWeek", "L2Pflag"),
    ("SVacc", "health", "TGD", "IODC"),
    ("TransTime", "FitIntvl"),
)

#: RINEX 3.04 broadcast records of the systems NavData holds, field names line by line
#: (tables A6 GPS, A8 Galileo, A14 BeiDou; ``""`` = spare).  Each record is 8 lines.
_NAV3_FIELDS = {
    "G": _NAV2_FIELDS,
    "E": (
        _NAV2_FIELDS[0], ("IODnav", "Crs", "DeltaN", "M0"), *_NAV2_FIELDS[2:5],
        ("IDOT", "DataSrc", "GALWeek", ""), ("SISA", "health", "BGDe5a", "BGDe5b"),
        ("TransTime",),
    ),
    "C": (
        _NAV2_FIELDS[0], ("AODE", "Crs", "DeltaN", "M0"), *_NAV2_FIELDS[2:5],
        ("IDOT", "", "BDTWeek", ""), ("SVacc", "SatH1", "TGD1", "TGD2"),
        ("TransTime", "AODC"),
    ),
}
#: Group delay used as ``tgd`` (GPS TGD; Galileo BGD E1/E5a; BeiDou TGD1 B1I/B3I) and the
#: health word used as ``health`` (BeiDou: SatH1, the autonomous health flag).
_TGD_FIELD = {"G": "TGD", "E": "BGDe5a", "C": "TGD1"}
_HEALTH_FIELD = {"G": "health", "E": "health", "C": "SatH1"}
#: Orbit lines after the record's first line, per system (RINEX 3.04 tables A6-A16;
#: GLONASS has a fourth orbit line from RINEX 3.05 on).
_NAV3_ORBIT_LINES = {"G": (7,), "E": (7,), "C": (7,), "J": (7,), "I": (7,), "R": (3, 4),
                     "S": (3,)}


def _nav_field_grid(lines: list[str], rec_lines: NDArray[np.int64], col_first: int,
                    col_other: int, path: str) -> tuple[NDArray[np.float64], NDArray[np.bool_]]:
    """Numbers of fixed-width navigation records as an ``(R, L, 4)`` array, NaN if blank,
    and which fields are blank (a field reading ``NaN`` is NaN but not blank).

    ``rec_lines[r]`` are the ``L`` line indices of record ``r``.  The first line holds three
    19-character fields from column ``col_first`` (after satellite and epoch), the others
    four from ``col_other`` (RINEX 2.11 table A4: ``22``/``3``, ``3X,4D19.12``; RINEX 3.04
    tables A6-A14: ``23``/``4``, ``4X,4D19.12``), with ``D`` or ``E`` exponents.  Blank
    fields (spares, and the trailing fields of right-trimmed lines) are NaN; anything else
    that is not a number raises :class:`InputError` naming its line.
    """
    nrec, nlin = rec_lines.shape
    block = "".join(
        lines[j][:80].replace("D", "E").replace("d", "e").ljust(80)
        for j in rec_lines.ravel().tolist()
    )
    buf = np.frombuffer(block.encode("ascii", errors="replace"), dtype="S1")
    buf = buf.reshape(nrec, nlin, 80)
    out = np.full((nrec, nlin, 4), np.nan)
    blanks = np.ones((nrec, nlin, 4), dtype=bool)
    for li in range(nlin):
        c0, nf = (col_first, 3) if li == 0 else (col_other, 4)
        for fi in range(nf):
            c = c0 + 19 * fi
            fld = buf[:, li, c : c + 19].copy().view("S19").ravel()
            blank = np.char.strip(fld) == b""
            blanks[:, li, fi] = blank
            # (non-finite values: records set aside by nav_record_problems, with a warning)
            out[:, li, fi], bad = _numbers(fld, blank, finite=False)
            if bad >= 0:
                raise InputError(
                    f"malformed number {fld[bad].decode(errors='replace').strip()!r}",
                    path, int(rec_lines[bad, li]) + 1,
                ) from None
    return out, blanks


def _resolve_toe(toc_gps_s: NDArray[np.float64], toe_sow: NDArray[np.float64]) -> NDArray:
    """Ephemeris reference time in GPS seconds: the ``toe`` second of week nearest ``toc``
    (so the week number written in the file, and its rollover, do not matter)."""
    d = toe_sow - np.mod(toc_gps_s, WEEK_S)
    return toc_gps_s + (d - WEEK_S * np.round(d / WEEK_S))


def _field_at(layout: tuple[tuple[str, ...], ...], tgd: str,
              health: str) -> dict[str, tuple[int, int]]:
    """``(line, field)`` of each NavData parameter in a record of ``layout`` (0-based)."""
    where = {name: (li, fi) for li, names in enumerate(layout)
             for fi, name in enumerate(names) if name}
    return {k: where[{"tgd": tgd, "health": health}.get(k, k)] for k in (*_KEPLER, "tgd")}


def _param_lines(layout: tuple[tuple[str, ...], ...], tgd: str, health: str,
                 rec_lines: NDArray[np.int64]) -> dict[str, NDArray[np.int64]]:
    """0-based file line of each NavData parameter of every record (for messages)."""
    return {k: rec_lines[:, li] for k, (li, _) in _field_at(layout, tgd, health).items()}


def _named_params(grid: tuple[NDArray[np.float64], NDArray[np.bool_]],
                  layout: tuple[tuple[str, ...], ...], tgd: str, health: str,
                  sat: NDArray[np.str_], rec_lines: NDArray[np.int64],
                  path: str) -> dict[str, NDArray[np.float64]]:
    """NavData parameters of records of one layout (``grid``: :func:`_nav_field_grid`'s
    values and blanks); a blank required field is an error (values that cannot be an orbit,
    ``NaN`` written out included, are :func:`_without_impossible`'s)."""
    values, blanks = grid
    out: dict[str, NDArray[np.float64]] = {}
    for k, (li, fi) in _field_at(layout, tgd, health).items():
        v, blank = values[:, li, fi], blanks[:, li, fi]
        if k in _REQUIRED and blank.any():
            r = int(np.flatnonzero(blank)[0])
            raise InputError(f"{sat[r]} record without {k} (blank field {fi + 1} of its "
                             f"line {li + 1})", path, int(rec_lines[r, li]) + 1)
        out[k] = np.where(blank, 0.0, v)  # blank health / group delay: not given, 0
    return out


def _read_nav_v2(lines: list[str], i0: int,
                 path: str) -> tuple[dict[str, NDArray] | None, list[str]]:
    """Fast reader of RINEX 2 GPS navigation records (8 lines each, 19-character fields).

    georinex 1.16 needs about 0.5 s for the GEONET file and turns malformed numbers into
    NaN silently; this reader takes a few milliseconds and reports file and line.  Returns
    the records and the messages of those set aside (:func:`_without_impossible`).
    """
    idx = [j for j in range(i0, len(lines)) if lines[j].strip()]
    if len(idx) % 8 != 0:
        raise InputError(
            f"truncated navigation file: {len(idx)} record lines is not a multiple of 8",
            path, len(lines),
        )
    nrec = len(idx) // 8
    if nrec == 0:
        return None, []
    rec_lines = np.asarray(idx, dtype=np.int64).reshape(nrec, 8)
    grid = _nav_field_grid(lines, rec_lines, 22, 3, path)
    sats, tocs = [], []
    for k in range(nrec):
        ln = lines[idx[8 * k]]
        try:
            prn = int(ln[:2])
            yy, mo, dd, hh, mi = (int(ln[c : c + 3]) for c in (2, 5, 8, 11, 14))
            ss = float(ln[17:22])
        except ValueError as exc:
            raise InputError(f"malformed ephemeris record header {ln[:22]!r}", path,
                             idx[8 * k] + 1) from exc
        if not 1 <= prn <= 32:
            raise InputError(f"GPS PRN must be 1-32, got {prn}", path, idx[8 * k] + 1)
        _calendar(yy + (2000 if yy < 80 else 1900), mo, dd, hh, mi, ss, "clock epoch (toc)",
                  path, idx[8 * k] + 1)
        sats.append(f"G{prn:02d}")
        tocs.append(
            np.datetime64(f"{yy + (2000 if yy < 80 else 1900):04d}-{mo:02d}-{dd:02d}T"
                          f"{hh:02d}:{mi:02d}", "ns") + np.int64(round(ss * 1e9))
        )
    out = _named_params(grid, _NAV2_FIELDS, "TGD", "health", np.array(sats), rec_lines, path)
    out["tgd2"] = np.zeros(len(sats))  # GPS: the clock refers to the L1/L2 pair
    out["sat"] = np.array(sats)
    out["toc"] = datetime64_to_gps_s(np.array(tocs, dtype="datetime64[ns]"))
    out, rejected = _without_impossible(
        out, _param_lines(_NAV2_FIELDS, "TGD", "health", rec_lines), path)
    out["toe"] = _resolve_toe(out["toc"], out["Toe"])
    return out, rejected


def _read_nav_v3(lines: list[str], i0: int,
                 path: str) -> tuple[dict[str, NDArray] | None, list[str]]:
    """Reader of the GPS, Galileo and BeiDou records of a RINEX 3 navigation file.

    A record starts with a line whose first column holds the system letter
    (``SNN YYYY MM DD HH MM SS`` + 3 fields), followed by orbit lines indented by four
    blanks (RINEX 3.04 section 6.11, tables A6-A16).  Records of the other systems are
    skipped by counting their orbit lines.  Fields are cut by column, never by
    concatenating lines, so right-trimmed lines and blank spare fields read correctly
    (georinex 1.16 turns a record with a blank field into NaN and drops it).  Epochs of
    BeiDou records are BDT and converted to GPS time (+14 s); Galileo system time is
    aligned with GPS time.  Returns the records and the messages of those set aside
    (:func:`_without_impossible`).
    """
    idx = [j for j in range(i0, len(lines)) if lines[j].strip()]
    heads = [p for p, j in enumerate(idx) if lines[j][:1] != " "]
    if not heads or heads[0] != 0:
        raise InputError("orbit line without a record header line (SNN YYYY MM DD ...)",
                         path, idx[0] + 1)
    keep: list[int] = []  # positions in idx of the kept records' first lines
    for h, p in enumerate(heads):
        ln = lines[idx[p]]
        n_orbit = (heads[h + 1] if h + 1 < len(heads) else len(idx)) - p - 1
        sysch = ln[0]
        if sysch not in _NAV3_ORBIT_LINES:
            raise InputError(f"unknown satellite system {sysch!r} in record header "
                             f"{ln[:23]!r} (expected one of GRECJSI)", path, idx[p] + 1)
        if n_orbit not in _NAV3_ORBIT_LINES[sysch]:
            want = " or ".join(str(n) for n in _NAV3_ORBIT_LINES[sysch])
            raise InputError(f"{ln[:3]} record has {n_orbit} orbit lines, expected {want} "
                             "(truncated record or a line missing)", path, idx[p] + 1)
        if sysch in _NAV3_FIELDS:
            keep.append(p)
    if not keep:
        return None, []
    rec_lines = np.asarray([idx[p : p + 8] for p in keep], dtype=np.int64)
    sats, tocs = [], []
    for j in rec_lines[:, 0].tolist():
        ln = lines[j]
        try:
            prn = int(ln[1:3])  # "G07", "G 7", "G7 " (not G70)
            y, mo, d, hh, mi, ss = (int(ln[c : c + w]) for c, w in
                                    ((4, 4), (9, 2), (12, 2), (15, 2), (18, 2), (21, 2)))
        except ValueError as exc:
            raise InputError(f"malformed record header {ln[:23]!r} (expected "
                             "'SNN YYYY MM DD HH MM SS')", path, j + 1) from exc
        if prn < 1:
            raise InputError(f"satellite number must be >= 1, got {ln[:3]!r}", path, j + 1)
        _calendar(y, mo, d, hh, mi, ss, "clock epoch (toc)", path, j + 1)
        sats.append(f"{ln[0]}{prn:02d}")
        tocs.append(np.datetime64(f"{y:04d}-{mo:02d}-{d:02d}T{hh:02d}:{mi:02d}:{ss:02d}",
                                  "ns"))
    sat = np.array(sats)
    toc = datetime64_to_gps_s(np.array(tocs, dtype="datetime64[ns]"))
    system = np.array([s[0] for s in sats])
    grid = _nav_field_grid(lines, rec_lines, 23, 4, path)
    out: dict[str, NDArray] = {k: np.zeros(len(sats)) for k in (*_KEPLER, "tgd")}
    at: dict[str, NDArray[np.int64]] = {k: np.zeros(len(sats), dtype=np.int64)
                                        for k in (*_KEPLER, "tgd")}
    for sysch, layout in _NAV3_FIELDS.items():
        m = system == sysch
        if not m.any():
            continue
        par = _named_params((grid[0][m], grid[1][m]), layout, _TGD_FIELD[sysch],
                            _HEALTH_FIELD[sysch], sat[m], rec_lines[m], path)
        for k, v in par.items():
            out[k][m] = v
        for k, where in _param_lines(layout, _TGD_FIELD[sysch], _HEALTH_FIELD[sysch],
                                     rec_lines[m]).items():
            at[k][m] = where
    out["tgd2"] = np.zeros(len(sats))
    m = system == "C"
    if m.any():  # BeiDou TGD2 (blank: not given, 0)
        li, fi = next((li, fi) for li, names in enumerate(_NAV3_FIELDS["C"])
                      for fi, name in enumerate(names) if name == "TGD2")
        out["tgd2"][m] = np.where(grid[1][m, li, fi], 0.0, grid[0][m, li, fi])
        at["tgd2"] = np.where(m, rec_lines[:, li], rec_lines[:, 0])
    out["sat"] = sat
    out["toc"] = toc + np.where(system == "C", BDT_OFFSET_S, 0.0)  # BDT = GPST - 14 s
    out, rejected = _without_impossible(out, at, path)
    shift = np.where(np.char.startswith(out["sat"].astype(str), "C"), BDT_OFFSET_S, 0.0)
    out["toe"] = _resolve_toe(out["toc"], out["Toe"] + shift)
    return out, rejected
