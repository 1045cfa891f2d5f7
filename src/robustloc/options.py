"""Checked option values, shared by the command line and the Python API.

``type=float`` accepts ``nan``, ``inf`` and any sign, so a typo such as
``--elevation-mask nan`` would silently disable a check.  These converters refuse such
values with a message naming the accepted range.  The command line uses them as
``argparse`` ``type=`` (argparse prints ``robustloc CMD: error: argument --x: ...`` and
exits with code 2); the settings dataclasses of :mod:`robustloc.pipelines` declare them
on their fields (``option(...)``) and :func:`check_settings` applies them to values given
from Python, raising :class:`~robustloc.errors.InputError` with the same
``argument --x: ...`` text.  One definition of every check, two front ends.

Examples
--------
>>> finite_float("1.5")
1.5
>>> float_in(0, 90)("45")
45.0
"""

from __future__ import annotations

import argparse
import math
import numbers
import os
from collections.abc import Callable, Mapping, Sequence
from dataclasses import field, fields
from typing import Any

__all__ = [
    "check_settings",
    "choice",
    "option",
    "finite_float",
    "positive_float",
    "nonnegative_float",
    "float_in",
    "positive_int",
    "nonnegative_int",
    "int_in",
]


def _float(text: str | float) -> float:
    # (a complex number: NumPy's converted to its real part with only a warning, so
    # locate(sigma=np.complex128(1+1j)) ran as sigma 1; the API review)
    if isinstance(text, bool) or (isinstance(text, numbers.Complex)
                                  and not isinstance(text, numbers.Real)):
        # (numbers.Complex: Python's and every NumPy complex type, np.complex64 too)
        raise argparse.ArgumentTypeError(f"expected a real number, got {text!r}")
    try:
        value = float(text)
    except (ValueError, TypeError):
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"expected a finite number, got {text!r}")
    return value


def finite_float(text: str) -> float:
    """A finite float (no NaN, no infinity)."""
    return _float(text)


def positive_float(text: str) -> float:
    """A finite float > 0."""
    value = _float(text)
    if value <= 0:
        raise argparse.ArgumentTypeError(f"expected a number > 0, got {text!r}")
    return value


def nonnegative_float(text: str) -> float:
    """A finite float >= 0."""
    value = _float(text)
    if value < 0:
        raise argparse.ArgumentTypeError(f"expected a number >= 0, got {text!r}")
    return value


#: Figure formats a ``--plot FILE`` may name, by its suffix (matplotlib writes each).
FIGURE_FORMATS = ("png", "svg", "pdf")


def figure_path(text: str) -> str:
    """A figure's file name whose suffix is one of :data:`FIGURE_FORMATS` (checked before
    any work is done)."""
    if not isinstance(text, str) or text.rsplit(".", 1)[-1].lower() not in FIGURE_FORMATS:
        raise argparse.ArgumentTypeError(
            f"{text!r}: the figure's name must end in "
            f"{', '.join('.' + f for f in FIGURE_FORMATS)}")
    return text


def choice(synonyms: Mapping[str, str]) -> Callable[[str], str]:
    """Converter of a choice option: a synonym becomes the name it stands for, anything
    else stays as given (for ``argparse``'s ``choices`` to accept or refuse with its own
    message).

    Examples
    --------
    >>> choice({"asym": "asymmetric-igg"})("asym")
    'asymmetric-igg'
    >>> choice({"asym": "asymmetric-igg"})("huber")
    'huber'
    """

    def convert(text: str) -> str:
        return synonyms.get(text, text) if isinstance(text, str) else text

    convert.__name__ = "choice"
    return convert


def float_in(low: float, high: float, *, open_high: bool = False) -> Callable[[str], float]:
    """Converter for a finite float in the closed interval ``[low, high]``, or in
    ``[low, high)`` with ``open_high``.

    An open bound is said as open: ``--gate`` bounded by ``1 - 1e-12`` printed
    "expected a number in [0.5, 1], got '1'" (``:g`` rounds it to 1; the fuse review).

    >>> float_in(0.5, 1.0, open_high=True)("0.999")
    0.999
    """

    def convert(text: str) -> float:
        value = _float(text)
        if not (low <= value < high if open_high else low <= value <= high):
            raise argparse.ArgumentTypeError(
                f"expected a number in [{low:g}, {high:g}{')' if open_high else ']'}, "
                f"got {text!r}")
        return value

    convert.__name__ = f"float_in_{low:g}_{high:g}{'_open' if open_high else ''}"
    return convert


#: An observation's a-priori standard deviation (``--sigma``, an anchors file's ``sigma``,
#: ``RobustRssiFilter``'s ``sigma_rssi_db``; metres or dB): 1 um to 1000 km.
#: 1e-300 passed as positive and made every fix ``ill_conditioned`` with numpy warnings on
#: stderr (the tracker review); ``montecarlo --sigma`` had this range already.
SIGMA_RANGE = (1e-6, 1e6)
sigma_value = float_in(*SIGMA_RANGE)

#: The largest process-noise intensity of the tracker (``track --q``, ``--range-offset-q``,
#: ``--link-offset-q``; ``serve --track-q``), as ``fuse --q``'s: 1e6.  A random walk of
#: 1e6 unit^2/s lets an offset wander by 1000 units (m or dB) in one second; a white
#: acceleration of 1e6 (m/s^2)^2 is 1000 m/s^2 (100 g) per second of one-sigma
#: acceleration: far beyond any tag or link, and far from float64's overflow.  1e308 was
#: accepted: ``track --link-offset-q 1e308`` wrote 73 of 180 rows ``ok`` without an
#: ``hpl`` (the covariance overflowed), ``--range-offset-q 1e308`` leaked NumPy overflow
#: warnings (the input review).
PROCESS_NOISE_MAX = 1e6
#: A random walk's variance growth (``--range-offset-q``, ``--link-offset-q``): 0 (a
#: constant offset) to :data:`PROCESS_NOISE_MAX`.
process_noise = float_in(0.0, PROCESS_NOISE_MAX)


def positive_process_noise(text: str) -> float:
    """A process-noise intensity ``q`` in ``(0, PROCESS_NOISE_MAX]`` (``track --q``,
    ``serve --track-q``).

    >>> positive_process_noise("2")
    2.0
    """
    value = _float(text)
    if not 0 < value <= PROCESS_NOISE_MAX:
        raise argparse.ArgumentTypeError(
            f"expected a number in (0, {PROCESS_NOISE_MAX:g}], got {text!r}")
    return value


#: The floor of an estimated robust scale (``--min-scale``, units of sigma): 0 to 1e6.
#: 1e300 passed and made every bound infinite on fixes still called ``ok`` (the input
#: review).
scale_floor = float_in(0.0, 1e6)


def _int(text: str | int) -> int:
    if isinstance(text, bool) or (isinstance(text, float) and not text.is_integer()):
        raise argparse.ArgumentTypeError(f"expected a whole number, got {text!r}")
    try:
        return int(text)
    except (ValueError, TypeError, OverflowError):
        raise argparse.ArgumentTypeError(f"expected a whole number, got {text!r}") from None


#: Largest autocorrelation lag (samples) that
#: :class:`~robustloc.eval.rssi_stats.RssiStatistics` computes: a day of 1 Hz samples.  Its
#: table holds ``max_lag + 1`` rows per link whatever the log's length (NaN beyond its
#: samples): ``stats --max-lag 1000000000000`` asked for 7.3 TiB (a MemoryError traceback,
#: the fuzz review of 2026-12-06).
MAX_LAG = 86_400


def positive_int(text: str) -> int:
    """A whole number >= 1."""
    value = _int(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"expected a whole number >= 1, got {text!r}")
    return value


def local_workers(text: str) -> int:
    """``--workers``: a whole number from 1 to :func:`max_local_workers` (a million
    LocalCluster worker processes took 2.8 GB and 10 minutes without starting one, and
    held the SIGTERM of ``timeout`` meanwhile: the Dask review)."""
    value = positive_int(text)
    limit, cores = max_local_workers()
    if value > limit:
        raise argparse.ArgumentTypeError(
            f"expected at most {limit} (4 per core, at least 8; this machine has {cores}; "
            f"for a bigger cluster start one and give --scheduler), got {text!r}")
    return value


def max_local_workers() -> tuple[int, int]:
    """The most LocalCluster workers ``--workers`` takes, and the cores available: 4 per
    core, at least 8 (one worker process per core is what a machine can run at once)."""
    try:
        cores = len(os.sched_getaffinity(0))
    except AttributeError:  # pragma: no cover - not Linux
        cores = os.cpu_count() or 1
    return max(8, 4 * cores), cores


def nonnegative_int(text: str) -> int:
    """A whole number >= 0."""
    value = _int(text)
    if value < 0:
        raise argparse.ArgumentTypeError(f"expected a whole number >= 0, got {text!r}")
    return value


def int_in(low: int, high: int) -> Callable[[str], int]:
    """Converter for a whole number in ``[low, high]``."""

    def convert(text: str) -> int:
        value = _int(text)
        if not low <= value <= high:
            raise argparse.ArgumentTypeError(
                f"expected a whole number in [{low}, {high}], got {text!r}")
        return value

    convert.__name__ = f"int_in_{low}_{high}"
    return convert


# --------------------------------------------------------------------------------------
# settings dataclasses
# --------------------------------------------------------------------------------------


#: A tag height in m (``--tag-height``): within +-10 km of the datum.  A tag 10 km or more
#: above or below the anchors is no indoor or terrestrial ranging problem (a range of
#: 1e5 m is the plausibility limit, :mod:`robustloc.io.limits`); 1e200 squared overflowed
#: to every epoch ``ill_conditioned`` and exit code 0.
tag_height_m = float_in(-1e4, 1e4)


def option(
    default: Any, *, check: Callable[[Any], Any] | None = None,
    choices: Sequence[Any] | None = None, flag: str | None = None,
    synonyms: Mapping[str, str] | None = None,
) -> Any:
    """A settings-dataclass field that is a command-line option.

    Parameters
    ----------
    default : object
        The default (the command line's).
    check : callable, optional
        A converter of this module (``positive_float``, ``float_in(0, 1)``, ...) or any
        callable raising :class:`argparse.ArgumentTypeError` / :class:`ValueError` on a
        refused value.
    choices : sequence, optional
        The allowed values.
    flag : str, optional
        The option's name on the command line (default ``--`` + the field name with
        dashes), used in messages.
    synonyms : mapping, optional
        Other names of ``choices``' values (``{"asym": "asymmetric-igg"}``): a synonym
        given is stored as the value it names (:func:`check_settings`).
    """
    return field(default=default, metadata={"check": check, "choices": choices, "flag": flag,
                                            "synonyms": synonyms or {}})


def check_settings(settings: object) -> None:
    """Apply the checks declared with :func:`option` to a settings dataclass.

    ``None`` is "not given" and is not checked where the field's default is ``None``;
    elsewhere it is refused (the numerical code met it: ``TypeError: '<' not supported
    between 'NoneType' and 'int'`` -- the API review, 2026-12-06).  A value given as text
    is stored as its checker converts it (``q="1"`` is ``1.0``, ``fixed_lag="3"`` is
    ``3``, as the command line reads them; the text reached the numerical code).  A
    synonym declared with ``option(synonyms=...)`` is replaced by the value it names.  A
    refused value raises
    :class:`~robustloc.errors.InputError` with argparse's wording, ``argument --NAME:
    ...``, so the API and the command line say the same.

    Examples
    --------
    >>> from dataclasses import dataclass
    >>> @dataclass(frozen=True)
    ... class S:
    ...     sigma: float | None = option(None, check=positive_float)
    ...     dim: int = option(2, choices=(2, 3))
    ...     def __post_init__(self): check_settings(self)
    >>> S(sigma=-1.0)
    Traceback (most recent call last):
    ...
    robustloc.errors.InputError: argument --sigma: expected a number > 0, got '-1.0'
    >>> S(dim=4)
    Traceback (most recent call last):
    ...
    robustloc.errors.InputError: argument --dim: invalid choice: 4 (choose from 2, 3)
    """
    from robustloc.errors import InputError

    for f in fields(settings):  # type: ignore[arg-type]
        meta = f.metadata
        if not meta or "check" not in meta:
            continue
        value = getattr(settings, f.name)
        flag = meta["flag"] or "--" + f.name.replace("_", "-")
        if value is None:
            if f.default is None:
                continue
            raise InputError(f"argument {flag}: expected a value, got None (leave it out "
                             f"for the default {f.default!r})")
        synonyms = meta.get("synonyms") or {}
        if isinstance(value, str) and value in synonyms:
            value = synonyms[value]
            object.__setattr__(settings, f.name, value)  # frozen dataclasses too
        choices = meta["choices"]
        if choices is not None and value not in choices:
            raise InputError(f"argument {flag}: invalid choice: {value!r} (choose from "
                             f"{', '.join(repr(c) for c in choices)})")
        if meta["check"] is not None:
            # a number is checked as the text the command line would get, so the
            # message is the command line's word for word (``got '-1.0'``)
            arg = (str(value) if isinstance(value, (int, float)) and not isinstance(value, bool)
                   else value)
            try:
                converted = meta["check"](arg)
            except (argparse.ArgumentTypeError, ValueError, TypeError) as exc:
                raise InputError(f"argument {flag}: {exc}") from None
            if isinstance(value, str) and converted is not None:
                object.__setattr__(settings, f.name, converted)  # frozen dataclasses too


def check_systems(text: str, allowed: str) -> str:
    """``--systems``: letters of ``allowed`` (GNSS constellations: G, R, E, C), each at most
    once, as upper case.  (A repeated letter put each satellite in twice: every epoch of
    ``montecarlo --gnss --systems GG`` was unavailable.)

    Raises
    ------
    InputError
        No letter, a letter outside ``allowed``, or a letter given twice.
    """
    from robustloc.errors import InputError

    if not isinstance(text, str):  # (None read as 'NONE': "unknown constellation 'NO'")
        raise InputError(f"--systems: expected letters of {allowed} as text, got {text!r}")
    up = text.upper()
    bad = sorted(set(up) - set(allowed))
    if not up or bad:
        raise InputError(f"--systems: unknown constellation(s) {''.join(bad)!r}; use "
                         f"letters of {allowed}, got {text!r}")
    twice = sorted({c for c in up if up.count(c) > 1})
    if twice:
        raise InputError(f"--systems: {''.join(twice)!r} listed twice in {text!r}; give "
                         "each constellation once")
    return up
