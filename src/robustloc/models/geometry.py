"""The anchors' geometry as the estimators, the integrity checks, the tracker and the
self-calibration see it: how elongated the anchors an epoch uses are.

One kernel, :func:`anchor_elongation`, serves every caller: ``locate``'s
``ill_conditioned`` status (anchors on a line fix a position only up to its mirror image,
:func:`collinear`), the planner's "unique fix" test, the ambiguity check of
:mod:`robustloc.integrity.fixes` and of the tracker, and the observability check of
``calibrate --self``.  (Three copies of it had grown apart: one in raw moments with a
closed-form eigenvalue, two with ``eigvalsh``.)
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

Array = NDArray[np.float64]

__all__ = ["anchor_elongation", "collinear", "elongation_rows", "mirror_flatness",
           "principal_lines", "unique_rows"]


def unique_rows(mask: NDArray[np.bool_]) -> tuple[NDArray[np.bool_], NDArray[np.intp]]:
    """The distinct rows of a boolean matrix (in the order of their ``np.packbits`` keys)
    and each row's index among them.

    Up to 64 columns a row is one integer, its packed bytes read as a little-endian
    ``uint64``, and pandas' hash factorization finds the distinct ones (4 ms at 100 000
    rows of 10, against 17 ms by ``np.unique``'s sort, the same result: tested)."""
    N, n = mask.shape
    if 0 < n <= 64 and N >= 4096:
        import pandas as pd

        j = np.arange(n)
        shift = (8 * (j // 8) + 7 - j % 8).astype(np.uint64)  # packbits' bit of column j
        keys = mask.astype(np.uint64) @ np.left_shift(np.uint64(1), shift)
        inverse, uniq = pd.factorize(keys, sort=True)
        patterns = ((uniq[:, None] >> shift) & np.uint64(1)).astype(bool)
        return patterns, np.asarray(inverse, dtype=np.intp)
    packed = np.packbits(mask, axis=1)
    width = -(-packed.shape[1] // 8) * 8
    packed = np.pad(packed, ((0, 0), (0, width - packed.shape[1])))
    keys = np.ascontiguousarray(packed).view(np.uint64)
    if keys.shape[1] == 1:
        _, first, inverse = np.unique(keys[:, 0], return_index=True, return_inverse=True)
    else:
        _, first, inverse = np.unique(keys, axis=0, return_index=True, return_inverse=True)
    return mask[first], np.asarray(inverse).reshape(-1)


def anchor_elongation(anchors: ArrayLike, keep: ArrayLike) -> Array:
    """Per epoch, the smallest over the largest eigenvalue of the scatter matrix
    ``sum_i (a_i - c)(a_i - c)^T`` of its kept anchors (all ``p`` coordinates: in 3-D,
    anchors in one plane give 0): 0 for anchors on a line (plane), 1 for a round spread;
    NaN with fewer than two kept anchors or all of them at one point.

    A function of the row's pattern alone: solved once per distinct pattern (a log has
    a handful; the scatter's eigenvalues cost ~1.5 us an epoch).

    Parameters
    ----------
    anchors : (m, p) array
        Anchor coordinates; an anchor no row keeps may be non-finite.
    keep : (N, m) bool array
        The anchors each epoch uses.

    Examples
    --------
    >>> a = np.array([[0.0, 0.0], [10.0, 0.0], [20.0, 0.1], [0.0, 10.0]])
    >>> np.round(anchor_elongation(a, np.array([[1, 1, 1, 0], [1, 1, 1, 1]], bool)), 4)
    array([0.    , 0.1681])
    """
    a = np.asarray(anchors, dtype=float)
    k = np.asarray(keep, dtype=bool)
    if k.ndim != 2 or k.shape[0] == 0:
        return np.full(k.shape[:1], np.nan)
    patterns, inverse = unique_rows(k)
    return elongation_rows(a, patterns)[inverse]


def elongation_rows(anchors: ArrayLike, keep: ArrayLike) -> Array:
    """:func:`anchor_elongation` row by row (no deduplication: for a few rows).

    Each row's scatter is taken about its own kept anchors' centroid (anchors 1e12 m
    from the origin keep their digits), and anchors a row does not keep never enter
    its sums (a non-finite one included)."""
    ev, cnt = _scatter_eigenvalues(anchors, keep)
    with np.errstate(invalid="ignore", divide="ignore"):
        ratio = np.maximum(ev[:, 0], 0.0) / ev[:, -1]
    return np.where((cnt >= 2) & (ev[:, -1] > 0), ratio, np.nan)


def _scatter_eigenvalues(anchors: ArrayLike, keep: ArrayLike) -> tuple[Array, NDArray[np.int64]]:
    """Per row, the ascending eigenvalues of its kept anchors' scatter matrix about their
    centroid (NaN where not finite) and the number of kept anchors."""
    a = np.asarray(anchors, dtype=float)
    k = np.asarray(keep, dtype=bool)
    cnt = k.sum(axis=1)
    with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
        kept = np.where(k[..., None], a[None, :, :], 0.0)  # (K, m, p)
        c = kept.sum(axis=1) / np.maximum(cnt, 1)[:, None]
        da = np.where(k[..., None], kept - c[:, None, :], 0.0)
        S = np.einsum("kmi,kmj->kij", da, da)
        good = np.all(np.isfinite(S), axis=(1, 2))
        ev = np.full(S.shape[:2], np.nan)
        if good.any():
            ev[good] = np.linalg.eigvalsh(S[good])
    return ev, cnt


def principal_lines(anchors: ArrayLike, keep: ArrayLike) -> tuple[Array, Array]:
    """Per row, the centroid ``c`` and unit normal ``u`` of the least-squares line (2-D;
    plane in 3-D) of its kept anchors: ``u`` the eigenvector of the smallest eigenvalue
    of their scatter matrix ``sum_i (a_i - c)(a_i - c)^T``.  A position's mirror image
    across it is ``x - 2 ((x - c) . u) u`` (:func:`robustloc.integrity.fixes.
    mirror_solution` starts there; the tracker carries the line of an ambiguous epoch).

    Parameters
    ----------
    anchors : (m, p) array
    keep : (N, m) bool array

    Returns
    -------
    c, u : (N, p) arrays

    Examples
    --------
    >>> a = np.array([[0.0, 0.0], [10.0, 0.0], [20.0, 0.0], [0.0, 9.0]])
    >>> c, u = principal_lines(a, np.array([[1, 1, 1, 0]], bool))
    >>> c[0].tolist(), np.abs(u[0]).tolist()
    ([10.0, 0.0], [0.0, 1.0])
    """
    a = np.asarray(anchors, dtype=float)
    keep = np.asarray(keep, dtype=bool)
    k = keep.astype(float)
    cnt = np.maximum(k.sum(axis=1), 1.0)
    c = (k @ a) / cnt[:, None]
    da = np.where(keep[..., None], a[None, :, :] - c[:, None, :], 0.0)  # (N, m, p)
    _, vec = np.linalg.eigh(np.einsum("kmi,kmj->kij", da, da))
    return c, vec[:, :, 0]


def mirror_flatness(anchors: ArrayLike, keep: ArrayLike, position: ArrayLike) -> Array:
    """Per epoch, how close its kept anchors lie to a line (2-D; a plane in 3-D) *as seen
    from the tag*: their mean squared distance from their least-squares line,
    ``lambda_min / n`` (the smallest eigenvalue of their scatter matrix over their
    number), over the median squared distance from the position to them.

    0 when the anchors are collinear (the fix has an exact mirror image across their
    line); about :func:`anchor_elongation` for a tag amid the anchors (a round spread
    with the tag at its centre: 1/2).  Unlike the elongation, one anchor far from the
    others does not make a well-spread layout look flat: four anchors on a 20 m square
    and a fifth 190 m away have elongation 0.014 but flatness 0.36 for a tag inside the
    square, whose ranges to the square tell a position from its mirror image across any
    line (the self-calibration review, 2026-12-06).  NaN with fewer than two kept
    anchors or a position that is not finite.

    Parameters
    ----------
    anchors : (m, p) array
    keep : (N, m) bool array
        The anchors each epoch uses.
    position : (N, p) array
        Each epoch's position (a start fix).

    Examples
    --------
    >>> a = np.array([[0.0, 0.0], [20.0, 0.0], [20.0, 20.0], [0.0, 20.0], [200.0, 10.0]])
    >>> keep = np.ones((1, 5), bool)
    >>> round(float(anchor_elongation(a, keep)[0]), 3)
    0.014
    >>> round(float(mirror_flatness(a, keep, np.array([[8.0, 9.0]]))[0]), 2)
    0.36
    """
    a = np.asarray(anchors, dtype=float)
    k = np.asarray(keep, dtype=bool)
    x = np.asarray(position, dtype=float)
    if k.ndim != 2 or k.shape[0] == 0:
        return np.full(k.shape[:1], np.nan)
    patterns, inverse = unique_rows(k)
    ev, cnt = _scatter_eigenvalues(a, patterns)
    width2 = (np.maximum(ev[:, 0], 0.0) / np.maximum(cnt, 1))[inverse]
    with np.errstate(invalid="ignore", over="ignore"):
        d2 = np.where(k, np.sum((x[:, None, :] - a[None, :, :]) ** 2, axis=-1), np.nan)
    has = k.sum(axis=1) >= 2
    med = np.full(k.shape[0], np.nan)
    if has.any():
        med[has] = np.nanmedian(d2[has], axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        out = width2 / med
    return np.where(has & np.isfinite(out), out, np.nan)


def collinear(anchors: ArrayLike, heard: ArrayLike, rel: float = 1e-3) -> NDArray[np.bool_]:
    """Epochs whose heard anchors lie on one line (2-D: the fix is ambiguous by mirror).

    :func:`anchor_elongation` at most ``rel**2`` (anchors within 0.1 % of their spread
    from a line), or undefined (fewer than two anchors, all at one point).

    Examples
    --------
    >>> a = np.array([[0.0, 0.0], [10.0, 0.0], [20.0, 0.0], [0.0, 8.0]])
    >>> collinear(a, np.array([[1, 1, 1, 0], [1, 1, 1, 1], [1, 0, 0, 0]], bool))
    array([ True, False,  True])
    """
    return ~(anchor_elongation(anchors, heard) > rel**2)
