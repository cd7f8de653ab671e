"""Local consistency: a match must agree with the affine map of its nearest confident neighbours.

Near a keypoint, the map from image 1 to image 2 is smooth: to first order an
affine map (a plane seen by two cameras is a homography; a smooth surface is
locally one). A match ``(i, j)`` is *consistent* when keypoint ``j`` lies
within ``tol + slack * spacing`` pixels of where the affine map fitted (least
squares) to its ``k`` nearest *anchors* in image 1 sends keypoint ``i``. The
match itself is left out of the fit, and so is the anchor that the others
predict worst, if it is beyond that allowance (one wrong anchor must not
condemn its neighbours). ``spacing`` is the median distance from ``i`` to
those anchors, so the allowance grows where the neighbours are far and the
affine map is a coarser model; ``tol`` is the keypoint noise (the band's).

The anchors are matches that are unambiguous in the whole image, for example
those that also passed Lowe's ratio test over all keypoints (the first pass of
:func:`~episeg_cv.match_without_pose`). That is what makes the check work on
repeated structure: a wall matched one period off is consistent *with itself*
(a check against all neighbours keeps it, measured), but not with the
unambiguous matches around it. The check runs twice: the second time the
anchors are the matches that passed the first, denser than the given ones
(on the repetitive pairs of ``benchmarks/compare.py``: 5-7 % more correct
matches, precision within 0.01). With fewer than four anchors in all nothing
can be checked, and every match is kept.

It is outlier rejection after matching, for any matcher; it does not need the
pose. It costs correct matches where the surface is not smooth at the scale of
the anchors (depth edges, thin structures, sparse anchors): numbers in
``benchmarks/results/compare.md``.

Tried to keep more of the correct matches at depth edges, and rejected
(``match_without_pose`` with ``K`` and both checks; development pairs and the
held-out repetitive rooms of scene seeds 1 and 2):

- the second pass only adding back what the first refused (never refusing
  what it kept): Motorcycle 1163 -> 1172 correct at 0.950, but held-out
  repetitive lateral precision 0.963 -> 0.948 and 0.959 -> 0.937;
- an allowance that also grows with the anchors' own scatter about their fit
  (``+ c`` robust sigmas, a studentized test): at ``c = 1`` Motorcycle 1174 at
  0.949 and repetitive lateral 0.964 -> 0.946;
- matching the unmatched queries to the keypoint nearest by descriptor within
  the allowance of the anchors' affine prediction (a local Lowe test within
  three allowances): the added matches were 63 % (dinoSparseRing 15-0) to
  92 % (synthetic forward) correct, which lowers every pair's precision.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from .._validation import as_array, as_index_pairs, as_nonnegative, as_points, as_positive_int

__all__ = ["affine_residuals", "consistent_pairs"]

#: Anchors each fit needs at the least, besides the match itself (3 points fix an affine map).
MIN_ANCHORS = 3


def affine_residuals(x1: np.ndarray, x2: np.ndarray, anchors: np.ndarray, k: int, tol: float,
                     slack: float) -> tuple[np.ndarray, np.ndarray]:
    """Residuals of the leave-one-out affine prediction (checked inputs).

    The map is fitted to the ``k`` nearest anchors, without the one that lies farthest from the fit of the
    others if that is beyond ``tol + slack * spacing`` (one wrong anchor must not condemn its neighbours).

    Parameters
    ----------
    x1, x2 : (K, 2) float64
        The matches' keypoints in images 1 and 2, pixels.
    anchors : (K,) bool
        The matches the affine maps are fitted to.
    k : int
        Anchors per fit (fewer when fewer exist).
    tol, slack : float
        As in :func:`consistent_pairs`.

    Returns
    -------
    residual : (K,) float64
        Distance in pixels from ``x2`` to the prediction; all NaN when fewer than four are anchors.
    spacing : (K,) float64
        Median distance in pixels from ``x1`` to its anchors; NaN likewise.
    """
    n = len(x1)
    residual, spacing = np.full(n, np.nan), np.full(n, np.nan)
    idx = np.flatnonzero(anchors)
    k = min(k, len(idx) - 1)  # k + 1 are fetched: the match itself may be one
    if k < MIN_ANCHORS or n == 0:
        return residual, spacing
    dist, nb = cKDTree(x1[idx]).query(x1, k + 1)
    nb = idx[nb]
    self_ = nb == np.arange(n)[:, None]
    # drop the match itself where it is an anchor, else the farthest of the k + 1
    drop = np.where(self_.any(axis=1), self_.argmax(axis=1), k)
    keep = np.ones(nb.shape, dtype=bool)
    keep[np.arange(n), drop] = False
    nb, dist = nb[keep].reshape(n, k), dist[keep].reshape(n, k)
    spacing = np.median(dist, axis=1)
    # coordinates relative to the query: the prediction is the fit's constant term
    A = np.concatenate([x1[nb] - x1[:, None], np.ones((n, k, 1))], axis=2)   # (K, k, 3)
    B = x2[nb]                                                               # (K, k, 2)
    P = np.linalg.pinv(A)                                                    # (K, 3, k)
    # each anchor's distance from the fit of the others (deleted residual: residual / (1 - leverage))
    leverage = np.einsum("nkj,njk->nk", A, P)
    with np.errstate(divide="ignore", invalid="ignore"):
        off = np.linalg.norm(A @ (P @ B) - B, axis=2) / (1.0 - leverage)
    off = np.where(np.isfinite(off), off, np.inf)
    worst = off.argmax(axis=1)
    w = np.ones((n, k))
    w[np.arange(n), worst] = off[np.arange(n), worst] <= tol + slack * spacing
    M = np.linalg.pinv(A * w[..., None]) @ (B * w[..., None])                  # (K, 3, 2)
    return np.hypot(*(M[:, 2] - x2).T), spacing


def consistent_pairs(points1, points2, pairs, *, anchors=None, k: int = 10, tol: float = 2.0,
                     slack: float = 0.1) -> np.ndarray:
    """Which matches agree with the affine map of their nearest anchors (module docstring).

    Parameters
    ----------
    points1 : (N1, 2) array_like
        Keypoints of image 1, pixels.
    points2 : (N2, 2) array_like
        Keypoints of image 2, pixels.
    pairs : (K, 2) array_like of int
        Matches ``(index in points1, index in points2)``, from any matcher.
    anchors : (K,) array_like of bool, optional
        The matches to fit the affine maps to: unambiguous ones (for example those that also pass Lowe's
        ratio test over all keypoints). Default: all matches.
    k : int, optional
        Anchors per fit, at least 3. Default 10 (20 equations for the affine map's 6 unknowns, so that one
        wrong anchor stands out).
    tol : float, optional
        Keypoint noise, pixels (the band's ``tol``). Default 2.
    slack : float, optional
        The allowance per pixel of anchor spacing for a surface that is not a plane. Default 0.1.

    Returns
    -------
    (K,) bool
        True for the consistent matches (for all of them when fewer than four are anchors: nothing can
        be checked).

    Raises
    ------
    ValueError, TypeError
        A wrong shape, NaN or inf, an index out of range, ``anchors`` of another length, ``k < 3``, a negative
        ``tol`` or ``slack``.

    Examples
    --------
    A grid of matches under a translation by (5, 2) pixels, and one match sent 30 pixels off:

    >>> import numpy as np
    >>> g = np.stack(np.meshgrid(np.arange(0, 200, 20.0), np.arange(0, 200, 20.0)), -1).reshape(-1, 2)
    >>> p2 = g + [5.0, 2.0]
    >>> p2[55] += [30.0, 0.0]
    >>> pairs = np.column_stack([np.arange(100), np.arange(100)])
    >>> ok = consistent_pairs(g, p2, pairs)
    >>> int(ok.sum()), bool(ok[55])
    (99, False)
    """
    p1, p2 = as_points(points1, "points1"), as_points(points2, "points2")
    pairs = as_index_pairs(pairs, len(p1), len(p2))
    if anchors is None:
        anchors = np.ones(len(pairs), dtype=bool)
    else:
        if np.asarray(anchors).dtype != bool:
            raise TypeError(f"anchors must be a boolean array, got dtype {np.asarray(anchors).dtype}")
        anchors = as_array(anchors, "anchors", (len(pairs),), dtype=bool)
    k = as_positive_int(k, "k")
    if k < MIN_ANCHORS:
        raise ValueError(f"k must be at least {MIN_ANCHORS} (an affine map needs 3 points), got {k}")
    tol, slack = as_nonnegative(tol, "tol"), as_nonnegative(slack, "slack")
    x1, x2 = p1[pairs[:, 0]], p2[pairs[:, 1]]
    residual, spacing = affine_residuals(x1, x2, anchors, k, tol, slack)
    with np.errstate(invalid="ignore"):
        passed = residual <= tol + slack * spacing
        # again, anchored on the matches that passed (denser and cleaner than the anchors given)
        again, spacing2 = affine_residuals(x1, x2, passed, k, tol, slack)
        second = again <= tol + slack * spacing2
    first = passed | np.isnan(residual)  # a match that cannot be checked is kept
    return np.where(np.isnan(again), first, second)
