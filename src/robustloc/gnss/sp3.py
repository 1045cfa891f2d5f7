"""Precise orbits (SP3-c/d) and clocks (RINEX CLK), interpolated at any time.

* Orbits: Lagrange interpolation of degree 10 (11 samples around the query time, the usual
  choice for 15-min and 5-min products; e.g. Schenewerk 2003, RTKLIB ``interppol``) in the
  ECEF frame of the product, vectorized over all (epoch, satellite) queries.
* Clocks: linear interpolation of the 30-s ``AS`` records of the CLK file; where the CLK
  file has no record around the query time, the 5-min SP3 clock (linearly interpolated).

The products refer to the satellite centre of mass and to the ionosphere-free combination of
the clock reference signals (GPS P1/P2, Galileo E1/E5a for CODE MGEX): use them with the
ionosphere-free pseudorange combination (``SppSolver(iono="iflc")``).  Satellite antenna
offsets (ANTEX) are not applied.
"""

from __future__ import annotations

from dataclasses import dataclass
from os import PathLike

import numpy as np
from numpy.typing import NDArray

from robustloc.errors import InputError
from robustloc.gnss.ephemeris import C_LIGHT, SatState
from robustloc.gnss.rinex import _calendar, _read_lines, datetime64_to_gps_s

#: Orbit + clock error of precise products used in the weights (m).
PRECISE_SIGMA_M = 0.05
#: Interpolation window (samples) of the orbit.
N_LAGRANGE = 11


def _epoch_s(parts: list[str], path: str, line: int) -> float:
    try:
        y, mo, d, h, mi = (int(v) for v in parts[:5])
        s = float(parts[5])
    except (ValueError, IndexError) as exc:
        raise InputError(f"malformed epoch {' '.join(parts[:6])!r}", path, line) from exc
    _calendar(y, mo, d, h, mi, s, "epoch", path, line)  # month 13, NaN seconds, ...
    t = np.datetime64(f"{y:04d}-{mo:02d}-{d:02d}T{h:02d}:{mi:02d}", "ns") + np.timedelta64(
        int(round(s * 1e9)), "ns"
    )
    return float(datetime64_to_gps_s(np.array([t]))[0])


def _sat_id(text: str, path: str, line: int) -> str:
    """``G07`` from ``G07``, ``G 7`` or ``G7 `` (left-aligned: once read as G70); a blank
    system letter is GPS (SP3-a)."""
    system = text[:1] if text[:1].strip() else "G"
    try:
        prn = int(text[1:3])
    except ValueError:
        prn = -1
    if not system.isalpha() or prn < 0:
        raise InputError(f"malformed satellite id {text!r}", path, line)
    return f"{system}{prn:02d}"


@dataclass(frozen=True)
class Sp3:
    """Precise orbit samples: ``pos_m (S, T, 3)`` and ``clock_s (S, T)`` (NaN = missing)."""

    sats: list[str]
    t_gps_s: NDArray[np.float64]
    pos_m: NDArray[np.float64]
    clock_s: NDArray[np.float64]
    path: str


def read_sp3(path: str | PathLike[str]) -> Sp3:
    """Read an SP3-c or SP3-d file (position records ``P``; velocities ignored)."""
    path = str(path)
    lines = _read_lines(path)
    if not lines or not lines[0].startswith("#") or lines[0][1:2] not in "abcd":
        raise InputError("not an SP3 file (first line must start with #a/#b/#c/#d)", path, 1)
    times: list[float] = []
    recs: list[tuple[int, str, float, float, float, float]] = []
    for i, ln in enumerate(lines):
        if ln.startswith("* "):
            t = _epoch_s(ln[1:].split(), path, i + 1)
            if times and not t > times[-1]:
                # (a repeated or swapped epoch put two epochs' samples in one
                # interpolation window, without a word)
                raise InputError(f"epoch {ln[1:].strip()!r} is not later than the previous "
                                 "one: SP3 epochs must increase", path, i + 1)
            times.append(t)
        elif ln.startswith("P") and times:
            try:
                x, y, z = float(ln[4:18]), float(ln[18:32]), float(ln[32:46])
                c = float(ln[46:60]) if ln[46:60].strip() else 999999.999999
            except ValueError as exc:
                raise InputError(f"malformed SP3 position record {ln[:60]!r}", path,
                                 i + 1) from exc
            recs.append((len(times) - 1, _sat_id(ln[1:4], path, i + 1), x, y, z, c))
        elif ln.startswith("EOF"):
            break
    if not times or not recs:
        raise InputError("no epochs / position records in the SP3 file", path, len(lines))
    sats = sorted({r[1] for r in recs}, key=lambda s: ("GRECJS".find(s[0]), s))
    col = {s: k for k, s in enumerate(sats)}
    T = len(times)
    pos = np.full((len(sats), T, 3), np.nan)
    clk = np.full((len(sats), T), np.nan)
    ti = np.array([r[0] for r in recs])
    si = np.array([col[r[1]] for r in recs])
    xyz = np.array([r[2:5] for r in recs]) * 1e3
    cc = np.array([r[5] for r in recs])
    bad = np.all(xyz == 0.0, axis=1)
    xyz[bad] = np.nan
    pos[si, ti] = xyz
    clk[si, ti] = np.where(np.abs(cc) >= 999999.0, np.nan, cc * 1e-6)
    return Sp3(sats, np.asarray(times), pos, clk, path)


@dataclass(frozen=True)
class Clk:
    """Satellite clock records ``clock_s (S, T)`` on the time grid ``t_gps_s`` (NaN = none)."""

    sats: list[str]
    t_gps_s: NDArray[np.float64]
    clock_s: NDArray[np.float64]
    path: str


def read_clk(path: str | PathLike[str]) -> Clk:
    """Read the satellite (``AS``) records of a RINEX clock file."""
    path = str(path)
    lines = _read_lines(path)
    head = lines[0][:60].split() if lines else []
    # file type "C": column 21 in RINEX clock 2.xx, where it is written "CLOCK DATA"
    # (e.g. CODE's COD0OPSRAP files), column 22 in 3.0x: the first letter of the 2nd field
    if not lines or "RINEX VERSION" not in lines[0] or len(head) < 2 or head[1][0] != "C":
        raise InputError("not a RINEX clock file (type C)", path, 1)
    tt: list[float] = []
    ss: list[str] = []
    vv: list[float] = []
    in_body = False
    for i, ln in enumerate(lines):
        if not in_body:
            in_body = "END OF HEADER" in ln[60:]
            continue
        if not ln.startswith("AS "):
            continue
        parts = ln.split()
        if len(parts) < 10:
            raise InputError(f"truncated clock record {ln.rstrip()!r}", path, i + 1)
        try:
            v = float(parts[9].replace("D", "E"))
        except ValueError as exc:
            raise InputError(f"malformed clock value {parts[9]!r}", path, i + 1) from exc
        tt.append(_epoch_s(parts[2:8], path, i + 1))
        ss.append(parts[1])
        vv.append(v)
    if not in_body:
        raise InputError("no END OF HEADER in the clock file", path, len(lines))
    if not tt:
        raise InputError("no satellite clock (AS) records", path, len(lines))
    t_all = np.asarray(tt)
    grid, ti = np.unique(t_all, return_inverse=True)
    sats = sorted(set(ss), key=lambda s: ("GRECJS".find(s[0]), s))
    col = {s: k for k, s in enumerate(sats)}
    clk = np.full((len(sats), grid.size), np.nan)
    clk[np.array([col[s] for s in ss]), ti] = vv
    return Clk(sats, grid, clk, path)


def _lagrange(t_grid: NDArray, table: NDArray, rows: NDArray, t: NDArray,
              order: int = N_LAGRANGE) -> NDArray:
    """Interpolate ``table[rows] (Q, T, d)`` at ``t (Q,)`` on ``t_grid (T,)`` (Lagrange)."""
    T = t_grid.size
    n = min(order, T)
    k = np.searchsorted(t_grid, t)
    i0 = np.clip(k - n // 2, 0, T - n)
    idx = i0[:, None] + np.arange(n)[None, :]  # (Q, n)
    tg = t_grid[idx]
    scale = 900.0
    x = (t[:, None] - tg) / scale  # (Q, n)
    tg_s = tg / scale
    # Lagrange basis l_j(t) = prod_{m != j} (t - t_m) / (t_j - t_m)
    diff = tg_s[:, :, None] - tg_s[:, None, :]  # (Q, n, n) t_j - t_m
    eye = np.eye(n, dtype=bool)[None]
    num = np.where(eye, 1.0, x[:, None, :])
    den = np.where(eye, 1.0, diff)
    basis = np.prod(num / den, axis=2)  # (Q, n)
    v = table[rows[:, None], idx]  # (Q, n, d)
    inside = (t >= t_grid[0]) & (t <= t_grid[-1])
    out = np.einsum("qn,qnd->qd", basis, v)
    return np.where(inside[:, None], out, np.nan)


@dataclass(frozen=True)
class PreciseProducts:
    """Precise orbits plus (optional) clocks, evaluated by :meth:`state`."""

    sp3: Sp3
    clk: Clk | None = None

    @property
    def sats(self) -> list[str]:
        return list(self.sp3.sats)

    def state(self, sats: list[str], t_gps_s: NDArray[np.float64]) -> SatState:
        """Positions (ECEF at ``t``) and clocks for satellites ``sats (S,)`` at ``t (N, S)``.

        Invalid (NaN) where the satellite is not in the product, the time is outside it, or
        a sample in the interpolation window is missing.
        """
        t = np.asarray(t_gps_s, dtype=float)
        N, S = t.shape
        col = {s: k for k, s in enumerate(self.sp3.sats)}
        si = np.array([col.get(s, -1) for s in sats])
        pos = np.full((N, S, 3), np.nan)
        clk = np.full((N, S), np.nan)
        have = si >= 0
        js_pos = np.nonzero(have)[0]
        if have.any():
            js = js_pos
            tq = t[:, js].T.reshape(-1)  # (len(js)*N,)
            finite = np.isfinite(tq)
            tq0 = np.where(finite, tq, self.sp3.t_gps_s[0])
            rows = np.repeat(si[js], N)
            p = _lagrange(self.sp3.t_gps_s, self.sp3.pos_m, rows, tq0)
            p[~finite] = np.nan
            # velocity by a 1-s central difference, for the relativistic clock term
            vel = (_lagrange(self.sp3.t_gps_s, self.sp3.pos_m, rows, tq0 + 0.5)
                   - _lagrange(self.sp3.t_gps_s, self.sp3.pos_m, rows, tq0 - 0.5))
            rel = -2.0 * np.einsum("qd,qd->q", p, vel) / C_LIGHT**2
            rel = rel.reshape(len(js), N).T
            pos[:, js] = p.reshape(len(js), N, 3).transpose(1, 0, 2)
            c = _linear(self.sp3.t_gps_s, self.sp3.clock_s, rows, tq0)
            c[~finite] = np.nan
            clk[:, js] = c.reshape(len(js), N).T
        if self.clk is not None:
            ccol = {s: k for k, s in enumerate(self.clk.sats)}
            ci = np.array([ccol.get(s, -1) for s in sats])
            js = np.nonzero(ci >= 0)[0]
            if js.size:
                tq = t[:, js].T.reshape(-1)
                finite = np.isfinite(tq)
                tq0 = np.where(finite, tq, self.clk.t_gps_s[0])
                c = _linear(self.clk.t_gps_s, self.clk.clock_s, np.repeat(ci[js], N), tq0,
                            max_gap_s=300.0)
                c = c.reshape(len(js), N).T
                clk[:, js] = np.where(np.isfinite(c), c, clk[:, js])
        if have.any():
            # precise clocks exclude the periodic relativistic term: -2 r.v / c^2
            # (IERS conventions 2010 eq. 10.17; RTKLIB peph2pos)
            clk[:, js_pos] = clk[:, js_pos] + rel
        valid = np.all(np.isfinite(pos), axis=-1) & np.isfinite(clk)
        return SatState(pos, clk, np.where(valid, PRECISE_SIGMA_M**2, np.nan), valid)

    def state_at_transmit(
        self, sats: list[str], t_rx_gps_s: NDArray[np.float64], pr_m: NDArray[np.float64]
    ) -> SatState:
        """States at transmit time ``t_rx - P/c - dt_sat`` (see ``ephemeris.nav_state``)."""
        t_tx = t_rx_gps_s[:, None] - np.nan_to_num(pr_m) / C_LIGHT
        st0 = self.state(sats, t_tx)
        t_tx = t_tx - np.nan_to_num(st0.clock_s)
        st = self.state(sats, t_tx)
        ok = st.valid & np.isfinite(pr_m)
        return SatState(np.where(ok[..., None], st.pos_m, np.nan),
                        np.where(ok, st.clock_s, np.nan), np.where(ok, st.var_m2, np.nan), ok)


def _linear(t_grid: NDArray, table: NDArray, rows: NDArray, t: NDArray,
            max_gap_s: float = 1e9) -> NDArray:
    """Linear interpolation of ``table[rows] (Q, T)`` at ``t (Q,)``; NaN across big gaps."""
    T = t_grid.size
    k = np.clip(np.searchsorted(t_grid, t) - 1, 0, max(T - 2, 0))
    k1 = np.minimum(k + 1, T - 1)
    t0, t1 = t_grid[k], t_grid[k1]
    v0, v1 = table[rows, k], table[rows, k1]
    with np.errstate(invalid="ignore", divide="ignore"):
        f = np.where(t1 > t0, (t - t0) / (t1 - t0), 0.0)
    out = v0 + f * (v1 - v0)
    bad = (t < t_grid[0]) | (t > t_grid[-1]) | ((t1 - t0) > max_gap_s)
    return np.where(bad, np.nan, out)
