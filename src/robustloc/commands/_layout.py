"""What a layout's anchors file says about its observations, for the planning commands
(``reliability``, ``montecarlo``): the model (ranges or RSSI) and the a-priori sigma that
``--model`` and ``--sigma`` leave out."""

from __future__ import annotations

import argparse
from typing import TYPE_CHECKING

import numpy as np

from robustloc.errors import InputError

if TYPE_CHECKING:
    import pandas as pd

    from robustloc.models.pathloss import PathLossModel

#: The unit of an observation's sigma, by ``--model``.
UNITS = {"range": "m", "rssi": "dB"}


def file_defaults(df: pd.DataFrame,
                  args: argparse.Namespace) -> tuple[PathLossModel | None, str | None]:
    """Fill in ``args.model`` and ``args.sigma`` left out from what the anchors file says.

    The model is ``rssi`` when the file has a path-loss model
    (:func:`robustloc.models.pathloss.model_from_anchors`, the columns ``locate`` uses) and
    no range calibration (``bias``, ``scale``:
    :data:`robustloc.models.calibration.FIT_COLUMNS`), else ``range``.  The sigma is the
    file's per-anchor ``sigma`` column (:func:`robustloc.io.tables.anchor_sigma`) when it
    is in the model's unit (a path-loss fit's is dB, a range calibration's m; a file with
    both says neither), else 1.

    Parameters
    ----------
    df : pandas.DataFrame
        The anchors (:func:`robustloc.io.read_anchors`).
    args : argparse.Namespace
        The command line; ``model`` and ``sigma`` are set in place when None.

    Raises
    ------
    InputError
        The file has path-loss columns with an anchor's value missing, and ``--model`` is
        not ``range`` (the error names the anchor and its line).

    Returns
    -------
    path_loss : PathLossModel or None
        The file's path-loss model (its exponents for ``rssi``), None without one.
    note : str or None
        What was taken from the file, or why its sigma was not (None: nothing to say).
    """
    from robustloc.io.tables import anchor_sigma
    from robustloc.models.calibration import FIT_COLUMNS
    from robustloc.models.pathloss import MODEL_COLUMNS, model_from_anchors

    try:
        path_loss = model_from_anchors(df)
    except InputError:
        # no path-loss columns; or an anchor without a value, which is a mistake unless
        # --model range says the columns do not matter (it planned RSSI layouts as 1 m
        # ranges without a word)
        has_columns = {"A", "n"} <= set(df.columns) or "p0" in df.columns
        if has_columns and args.model != "range":
            raise
        path_loss = None
    fitted = [c for c in MODEL_COLUMNS[path_loss.name] if c in df.columns] if path_loss else []
    ranging = [c for c in FIT_COLUMNS["range"] if c in df.columns]
    # what the file's sigma is the residual of (None: the file does not say)
    kind = None if bool(fitted) == bool(ranging) else ("rssi" if fitted else "range")
    said = []
    if args.model is None:
        args.model = "rssi" if kind == "rssi" else "range"
        if kind is not None:
            said.append(f"model {args.model} from its {', '.join(fitted or ranging)} columns")
        elif fitted:
            said.append(f"model range: it has path-loss columns ({', '.join(fitted)}) and a "
                        f"range calibration ({', '.join(ranging)}), give --model rssi for RSSI")
    sigma = anchor_sigma(df)
    if args.sigma is None:
        args.sigma = 1.0
        if sigma is not None and kind in (None, args.model) and not (fitted and ranging):
            args.sigma = float(sigma[0]) if np.all(sigma == sigma[0]) else sigma
            said.append(f"sigma {sigma_text(args.sigma, args.model)} from its sigma column")
        elif sigma is not None:
            of = {"rssi": "a path-loss fit's (dB)", "range": "a range calibration's (m)",
                  None: "a path-loss fit's (dB) or a range calibration's (m)"}[kind]
            said.append(f"sigma 1 {UNITS[args.model]}, not its sigma column, which is {of}")
    if not said:
        return path_loss, None
    return path_loss, (f"{args.anchors}: " + "; ".join(said)
                       + " (--model and --sigma override what the file says)")


def sigma_text(sigma: object, model: str) -> str:
    """``sigma`` for the summary: one number, or the per-anchor range and median."""
    s = np.asarray(sigma, dtype=float)
    unit = UNITS[model]
    if s.ndim == 0:
        return f"{float(s):g} {unit}"
    return (f"per anchor {s.min():.3g} .. {s.max():.3g} {unit} (median "
            f"{float(np.median(s)):.3g})")
