"""Numbers in the report's tables: three significant digits, counts as integers.

One rule for every table of ``robustloc reproduce`` (report.md, report.html and the tables
printed on stdout), :func:`fmt_num` for a value and :func:`format_frame` for a table:

* a float shows 3 significant digits, trailing zeros kept (``1.196`` -> ``1.20``,
  ``1.997`` -> ``2.00``, ``-3.31`` -> ``-3.31``, ``0.00292`` -> ``0.00292``); a number
  that reaches 1000 after rounding is written without an exponent, rounded to 3 significant
  digits (``2329.4`` -> ``2330``, ``671 234.5`` -> ``671000``), so a bare ``2330`` is
  a rounded float, never a count; below ``1e-4`` Python's exponent form stays
  (``1.23e-05``);
* an integer (a count) prints whole, whatever its size (``2329``), and so does a float
  column whose values are all whole numbers: a count column that a NaN-padded row made
  float (``n`` of a table with a reference row) prints ``2329``, not ``2.33e+03``; a
  float that is a whole number of 1000 or more prints whole too (``6500.0`` -> ``6500``);
* NaN / None / ``pd.NA`` print as an empty cell, infinities as ``inf`` / ``-inf``;
* a table's index prints only when it means something (a name, or not the default
  ``0..n-1`` range): it becomes the first column, never a column of row numbers.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import pandas as pd

#: Significant digits of every float in the report's tables.
SIG = 3


def fmt_num(value: Any, sig: int = SIG) -> str:
    """``value`` as the report prints it in a table cell (module docstring)."""
    if value is None or value is pd.NA or value is pd.NaT:
        return ""
    if isinstance(value, (bool, np.bool_)):
        return str(bool(value))
    if isinstance(value, (int, np.integer)):
        return str(int(value))
    if isinstance(value, (float, np.floating)):
        x = float(value)
        if math.isnan(x):
            return ""
        if math.isinf(x):
            return "inf" if x > 0 else "-inf"
        if abs(x) >= 1000 and x.is_integer():
            return str(int(x))
        s = f"{x:#.{sig}g}"
        if "e" in s:
            if int(s.split("e")[1]) >= sig:  # (>= 1000 once rounded): no exponent
                return f"{float(s):.0f}"
            return s
        return s[:-1] if s.endswith(".") else s
    return str(value)


def _whole(col: pd.Series) -> bool:
    """A float column whose finite values are all whole numbers (a count made float)."""
    if not pd.api.types.is_float_dtype(col.dtype):
        return False
    v = col.to_numpy(dtype=float)
    v = v[np.isfinite(v)]
    return bool(v.size) and bool(np.all(v == np.round(v)))


def format_frame(frame: pd.DataFrame, sig: int = SIG) -> pd.DataFrame:
    """``frame`` as a table of strings, as the report shows it (module docstring): the
    index a first column when it means something, else dropped; every cell through
    :func:`fmt_num`; whole-number float columns as integers."""
    named = frame.index.name is not None or not isinstance(frame.index, pd.RangeIndex)
    df = frame.reset_index() if named else frame.reset_index(drop=True)
    out = {}
    for k in range(df.shape[1]):
        col = df.iloc[:, k]
        if _whole(col):
            out[k] = ["" if not np.isfinite(v) else str(int(v))
                      for v in col.to_numpy(dtype=float)]
        else:
            out[k] = [fmt_num(v, sig) for v in col.tolist()]
    res = pd.DataFrame(out)
    res.columns = [str(c) for c in df.columns]
    return res


def text_table(frame: pd.DataFrame, sig: int = SIG) -> str:
    """``frame`` as plain text for the terminal: :func:`format_frame`, no row numbers."""
    return format_frame(frame, sig).to_string(index=False)
