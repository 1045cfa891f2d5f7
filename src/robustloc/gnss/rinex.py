"""RINEX observation and navigation files.

* RINEX 2.xx observation files are read by a vectorized reader of our own
  (:func:`read_obs`): the epoch headers are parsed line by line, the observation records of
  the whole file are then cut into fixed-width fields and converted by NumPy in one go.  It is
  about ten times faster than georinex 1.16 on the shared GEONET file and prints no
  warnings; ``tests/test_gnss_rinex.py`` checks it value by value against georinex.
* RINEX 3 observation files and all navigation files are read through georinex, with its
  xarray ``FutureWarning``/``DeprecationWarning`` flood silenced.

Times are GPS time in seconds since 1980-01-06 00:00:00 (``t_gps_s``), a float64.

Every problem of a file (truncated, wrong counts, impossible dates such as month 13, garbage
numbers) raises :class:`~robustloc.errors.InputError` naming the file and the line.  A
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
        RINEX epoch flag (0 ok, 1 power failure, 6 cycle slips); flags 2-5 carry no
        observations and are not epochs.
    line : ndarray of int (N,)
        1-based line number of each epoch header (for messages).
    header : dict
        Header records.
    invalid : ndarray of int (N,), optional
        Pseudoranges of each epoch outside the physical limits, set to NaN
        (``invalid_measurement``); ``None`` is read as zeros.
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
            self.invalid_per_epoch[rows],
        )


def is_pseudorange(obs_type: str) -> bool:
    """RINEX 2 ``C1, P1, P2, C2, C5, ...`` or RINEX 3 ``C1C, C2W, ...`` code observations."""
    return len(obs_type) >= 2 and obs_type[0] in "CP" and obs_type[1].isdigit()


def _implausible_pseudoranges(obs: dict[str, NDArray[np.float64]]) -> NDArray[np.int64]:
    """Set pseudoranges outside the physical limits to NaN (in place); count per epoch."""
    from robustloc.io.limits import LIMITS

    lim = LIMITS["pseudorange"]
    count = None
    for name, a in obs.items():
        if not is_pseudorange(name):
            continue
        bad = ~np.isnan(a) & ~lim.check(a)
        a[bad] = np.nan
        count = bad.sum(axis=1) if count is None else count + bad.sum(axis=1)
    n = next(iter(obs.values())).shape[0] if obs else 0
    return np.zeros(n, dtype=np.int64) if count is None else count.astype(np.int64)


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


def _read_lines(path: str | PathLike[str]) -> list[str]:
    p = Path(path)
    raw = p.read_bytes()
    if raw[:2] == b"\x1f\x8b":
        import gzip

        raw = gzip.decompress(raw)
    text = raw.decode("ascii", errors="replace")
    return text.splitlines()


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


def rinex_version(path: str | PathLike[str]) -> tuple[float, str]:
    """Version and file type letter (``O``, ``N``, ``G``, ...) of a RINEX file."""
    try:
        with open(path, "rb") as fh:
            first = fh.readline().decode("ascii", errors="replace")
    except IsADirectoryError as exc:
        raise InputError("is a directory, expected a RINEX file", path) from exc
    if "RINEX VERSION" not in first:
        raise InputError("first line is not a RINEX VERSION / TYPE record", path, 1)
    try:
        version = float(first[:9])
    except ValueError as exc:
        raise InputError(f"unreadable RINEX version {first[:9]!r}", path, 1) from exc
    return version, first[20:21].upper()


def _obs_types_v2(hdr: dict[str, str], path: str) -> list[str]:
    rec = hdr.get("# / TYPES OF OBSERV")
    if rec is None:
        raise InputError("missing '# / TYPES OF OBSERV' header record", path)
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
    try:
        return np.array([float(v) for v in hdr["APPROX POSITION XYZ"].split()[:3]])
    except (KeyError, ValueError):
        return np.zeros(3)


def read_obs(path: str | PathLike[str]) -> ObsData:
    """Read a RINEX 2 or 3 observation file.

    RINEX 2 is read by the fast reader of this module; RINEX 3 through georinex.  Raises
    :class:`InputError` (with file and line) for a truncated or malformed file.
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
    types = _obs_types_v2(hdr, path)
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
    while i < n:
        ln = lines[i]
        if not ln.strip():
            i += 1
            continue
        try:
            flag = int(ln[26:29] or 0)
            nsat = int(ln[29:32])
        except ValueError as exc:
            raise InputError(f"malformed epoch header {ln.rstrip()!r}", path, i + 1) from exc
        if not 0 <= flag <= 6 or nsat < 0:
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
            raise InputError(f"malformed epoch time {ln[:26]!r}", path, i + 1) from exc
        _calendar(*ep[:5], sec, "epoch time", path, i + 1)
        svtxt = ln[32:68]
        nhead = (nsat + 11) // 12
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
            try:
                prn = int(s[1:3])
            except ValueError as exc:
                raise InputError(f"malformed satellite id {s!r}", path, i + 1) from exc
            sats.append(f"{sysch}{prn:02d}")
        epoch_idx = len(times)
        times.append(ep)  # type: ignore[arg-type]
        flags.append(flag)
        ep_lines.append(i + 1)
        i += nhead
        if i + nsat * nlines_sat > n:
            raise InputError(
                f"file ends inside the epoch starting here ({nsat} satellites announced)",
                path, ep_lines[-1],
            )
        for s in sats:
            sat_ids.append(s)
            rec_epoch.append(epoch_idx)
            rec_start.append(i)
            i += nlines_sat
    if not times:
        raise InputError("no observation epochs after the header", path, i0 + 1)

    # vectorized field extraction: each record -> nlines_sat padded 80-char lines
    nrec = len(rec_start)
    starts = np.asarray(rec_start)
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
        try:
            vals = np.where(blank, b"nan", fld).astype(np.float64)
        except ValueError:
            bad = next(
                k for k in range(nrec) if not blank[k] and not _isfloat(fld[k])
            )
            raise InputError(
                f"malformed {types[t]} value {fld[bad].decode(errors='replace')!r}",
                path, int(starts[bad]) + li + 1,
            ) from None
        values[:, t] = vals
    # 0.0 means "not observed" in some writers
    values[values == 0.0] = np.nan

    all_sats = sorted(set(sat_ids), key=lambda s: ("GRECJS".find(s[0]), s))
    col_of = {s: k for k, s in enumerate(all_sats)}
    cols = np.array([col_of[s] for s in sat_ids])
    rows = np.asarray(rec_epoch)
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
    invalid = _implausible_pseudoranges(obs)
    return ObsData(
        path, version, datetime64_to_gps_s(tt), all_sats, obs, _approx(hdr),
        np.asarray(flags, dtype=np.int64), np.asarray(ep_lines, dtype=np.int64), hdr,
        invalid,
    )


def _isfloat(b: bytes) -> bool:
    try:
        float(b)
    except ValueError:
        return False
    return True


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


def _read_obs_v3(path: str, version: float) -> ObsData:
    lines = _read_lines(path)
    hdr, i0 = _header(lines, path)
    ds = _georinex_load(path, fast=False)
    if ds is None or "time" not in ds.coords or ds.sizes.get("time", 0) == 0:
        raise InputError("no observation epochs after the header", path, i0 + 1)
    sats = [str(s) for s in ds.sv.values]
    order = sorted(range(len(sats)), key=lambda k: ("GRECJS".find(sats[k][0]), sats[k]))
    sats = [sats[k] for k in order]
    obs = {
        str(name): np.asarray(ds[name].values, dtype=np.float64)[:, order]
        for name in ds.data_vars
        if ds[name].dims == ("time", "sv")
    }
    t = datetime64_to_gps_s(ds.time.values)
    # epoch lines: find them for messages
    ep_lines = [k + 1 for k in range(i0, len(lines)) if lines[k].startswith(">")]
    ep_lines = (ep_lines + [0] * len(t))[: len(t)]
    invalid = _implausible_pseudoranges(obs)
    return ObsData(
        path, version, t, sats, obs, _approx(hdr), np.zeros(len(t), dtype=np.int64),
        np.asarray(ep_lines, dtype=np.int64), hdr, invalid,
    )


# --------------------------------------------------------------------------- navigation


#: Broadcast ephemeris fields kept (georinex names); system-specific group delays are
#: mapped to ``tgd`` (GPS TGD, Galileo BGD E1/E5a, BeiDou TGD1).
_KEPLER = (
    "SVclockBias", "SVclockDrift", "SVclockDriftRate", "Crs", "DeltaN", "M0", "Cuc",
    "Eccentricity", "Cus", "sqrtA", "Toe", "Cic", "Omega0", "Cis", "Io", "Crc", "omega",
    "OmegaDot", "IDOT", "health",
)


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
        Keplerian and clock parameters (georinex names) plus ``tgd`` (s).
    ion_alpha, ion_beta : ndarray (4,) or None
        GPS Klobuchar coefficients from the header.
    paths : list of str
    """

    sat: NDArray[np.str_]
    toc_gps_s: NDArray[np.float64]
    toe_gps_s: NDArray[np.float64]
    params: dict[str, NDArray[np.float64]]
    ion_alpha: NDArray[np.float64] | None
    ion_beta: NDArray[np.float64] | None
    paths: list[str]

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

    GLONASS, SBAS and QZSS records are ignored (use SP3 for GLONASS).  Raises
    :class:`InputError` for a truncated or malformed file.
    """
    if isinstance(paths, (str, PathLike)):
        paths = [paths]
    sat_l, toc_l, toe_l = [], [], []
    par_l: dict[str, list] = {k: [] for k in (*_KEPLER, "tgd")}
    alpha = beta = None
    for p in paths:
        p = str(p)
        version, ftype = rinex_version(p)
        if ftype not in ("N", "G", "L", "E", "C") and not (version >= 3 and ftype == "N"):
            raise InputError(f"not a navigation file (RINEX type {ftype!r})", p, 1)
        lines = _read_lines(p)
        hdr, i0 = _header(lines, p)
        a, b = _klobuchar_from_header(lines[:i0])
        alpha = a if alpha is None else alpha
        beta = b if beta is None else beta
        if not any(ln.strip() for ln in lines[i0:]):
            raise InputError("no ephemeris records after the header", p, i0 + 1)
        if version < 3 and ftype == "N":
            rec = _read_nav_v2(lines, i0, p)
            if rec is not None:
                for k in _KEPLER:
                    par_l[k].append(rec[k])
                par_l["tgd"].append(np.nan_to_num(rec["TGD"]))
                sat_l.append(rec["sat"])
                toc_l.append(rec["toc"])
                toe_l.append(rec["toe"])
            continue
        ds = _georinex_load(p)
        if ds is None or "sv" not in ds.coords:
            raise InputError("no ephemeris records could be read", p)
        svs = np.asarray([str(s) for s in ds.sv.values])
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
            toe_sow = np.asarray(sub["Toe"].values)[ti, si]
            toe_sow = toe_sow + (BDT_OFFSET_S if sysch == "C" else 0.0)
            toc_sow = np.mod(toc, WEEK_S)
            d = toe_sow - toc_sow
            d = d - WEEK_S * np.round(d / WEEK_S)  # week rollover-safe
            sat_l.append(np.asarray([str(s) for s in sub.sv.values])[si])
            toc_l.append(toc)
            toe_l.append(toc + d)
            for k in _KEPLER:
                if k in sub:
                    par_l[k].append(np.asarray(sub[k].values, dtype=np.float64)[ti, si])
                else:
                    par_l[k].append(np.zeros(ti.size))
            tg = sub[tgd_name] if tgd_name in sub else None
            if tg is None and sysch == "E" and "BGDe5b" in sub:
                tg = sub["BGDe5b"]
            par_l["tgd"].append(
                np.zeros(ti.size) if tg is None
                else np.nan_to_num(np.asarray(tg.values, dtype=np.float64)[ti, si])
            )
    if not sat_l:
        raise InputError("no GPS, Galileo or BeiDou ephemeris in the navigation file(s)",
                         str(paths[0]))
    sat = np.concatenate(sat_l)
    params = {k: np.concatenate(v) for k, v in par_l.items()}
    params["health"] = np.nan_to_num(params["health"])
    good = np.all(np.isfinite(np.stack([params[k] for k in _KEPLER if k != "health"])), axis=0)
    return NavData(
        sat[good], np.concatenate(toc_l)[good], np.concatenate(toe_l)[good],
        {k: v[good] for k, v in params.items()}, alpha, beta, [str(p) for p in paths],
    )


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


def _read_nav_v2(lines: list[str], i0: int, path: str) -> dict[str, NDArray] | None:
    """Fast reader of RINEX 2 GPS navigation records (8 lines each, 19-character fields).

    georinex 1.16 needs about 0.5 s for the GEONET file and turns malformed numbers into
    NaN silently; this reader takes a few milliseconds and reports file and line.
    """
    idx = [j for j in range(i0, len(lines)) if lines[j].strip()]
    if len(idx) % 8 != 0:
        raise InputError(
            f"truncated navigation file: {len(idx)} record lines is not a multiple of 8",
            path, len(lines),
        )
    nrec = len(idx) // 8
    if nrec == 0:
        return None
    block = "".join(
        lines[j][:79].replace("D", "E").replace("d", "e").ljust(79) for j in idx
    )
    buf = np.frombuffer(block.encode("ascii", errors="replace"), dtype="S1").reshape(nrec, 8, 79)
    out: dict[str, NDArray] = {}
    for li, names in enumerate(_NAV2_FIELDS):
        for fi, name in enumerate(names):
            c0 = 22 + 19 * fi if li == 0 else 3 + 19 * fi
            fld = buf[:, li, c0 : c0 + 19].copy().view("S19").ravel()
            blank = np.char.strip(fld) == b""
            try:
                vals = np.where(blank, b"nan", fld).astype(np.float64)
            except ValueError:
                bad = next(k for k in range(nrec) if not blank[k] and not _isfloat(fld[k]))
                raise InputError(
                    f"malformed number {fld[bad].decode(errors='replace').strip()!r}",
                    path, idx[8 * bad + li] + 1,
                ) from None
            out[name] = vals
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
    toc = datetime64_to_gps_s(np.array(tocs, dtype="datetime64[ns]"))
    d = out["Toe"] - np.mod(toc, WEEK_S)
    out["sat"] = np.array(sats)
    out["toc"] = toc
    out["toe"] = toc + (d - WEEK_S * np.round(d / WEEK_S))
    return out
