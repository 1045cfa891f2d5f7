"""Array helpers shared by the layers (no robustloc imports)."""

from __future__ import annotations

import math
import sys
from typing import Any

import numpy as np
import pandas as pd
from numpy.typing import NDArray


def true_first(mask: NDArray[np.bool_], width: int | None = None) -> NDArray[np.intp]:
    """Indices of each row's ``True`` entries first, in their order, then the others,
    cut to ``width`` columns (default: the most ``True`` any row holds).

    A large site's epochs hear a few of its anchors: their rows are gathered to the front
    (``np.take_along_axis(values, idx, axis=1)``) and the work is done on ``width``
    columns instead of every anchor's (``sandwich_qvv``, ``lege``, the self-calibration's
    residual blocks and reduced normal matrix).

    >>> true_first(np.array([[False, True, False, True], [True, False, False, False]]))
    array([[1, 3],
           [0, 1]])
    """
    if width is None:
        width = int(mask.sum(axis=1).max()) if mask.shape[0] else 0
    return np.argsort(~mask, axis=1, kind="stable")[:, :width]


def real_array(x: object, name: str) -> NDArray[np.float64]:
    """``x`` as a float array; ``TypeError`` naming ``name`` for ``None``, booleans or complex
    numbers (``np.asarray(..., dtype=float)`` drops an imaginary part with only a
    ``ComplexWarning``: a range of 5+1j was located as 5; the review of 2026-12-06)."""
    if x is None:
        raise TypeError(f"{name} is None; expected an array of numbers")
    a = np.asarray(x)
    if np.iscomplexobj(a) or (a.dtype == object and any(isinstance(v, complex)
                                                         for v in a.ravel().tolist())):
        raise TypeError(f"{name} holds complex numbers; expected real numbers")
    # (booleans: True read as a range of 1 m, and a fix said `ok`; the API review)
    if a.dtype == bool or (a.dtype == object and any(isinstance(v, bool | np.bool_)
                                                      for v in a.ravel().tolist())):
        raise TypeError(f"{name} holds booleans; expected numbers")
    return np.asarray(a, dtype=float)


def _beyond_float(v: Any) -> Any:
    """A whole number beyond float's range as +-inf (the value it stands for in float);
    any other value as it is."""
    if isinstance(v, int) and not isinstance(v, bool) and abs(v) > sys.float_info.max:
        return math.inf if v > 0 else -math.inf
    return v


def to_number(values: pd.Series) -> pd.Series:
    """``pd.to_numeric(values, errors="coerce")``: what is not a number becomes NaN.

    A whole number beyond float's range (a CSV field of 400 nines, which pandas keeps as
    a Python int, or one of more than 4 000 digits, which it read as NaN) becomes +-inf,
    as the same number written ``9.99e399`` does; pandas
    raised ``OverflowError: int too large to convert to float`` on it, and every command
    reading the column ended in a traceback (the fuzz review of 2026-12-06).
    """
    try:
        out = pd.to_numeric(values, errors="coerce")
    except OverflowError:
        out = pd.to_numeric(values.map(_beyond_float), errors="coerce")
    # whole numbers written with more digits than Python converts (4 300) came out NaN,
    # "not a number", where 1 000 nines read +inf: the same +-inf (the serve review)
    if not pd.api.types.is_numeric_dtype(values) and pd.api.types.is_float_dtype(out):
        na = out.isna().to_numpy()
        if na.any():
            cand = values[na].astype(object)
            text = cand[cand.str.len().fillna(0).to_numpy() > 4000].str.strip()
            text = text[text.str.fullmatch(r"[+-]?\d+").fillna(False).to_numpy(bool)]
            if len(text):
                out = out.copy()
                out[text.index] = np.where(text.str.startswith("-"), -np.inf, np.inf)
    return out
