"""Track completion: consensus groups of too few views extended by projection with the known poses.

COLMAP's triangulation (``tri_ignore_two_view_tracks``, its default) makes no
point of a track seen in two views. After the track consensus
(:mod:`.consensus`) many groups span only two (distinct) views: the feature
was detected in other views too, but the pairs' matching did not find it
(not the nearest on its segment, or not mutual). :func:`complete_groups` looks
for it where the group's point must be:

1. **Proposals.** Each group of fewer than ``min_views`` distinct views is
   triangulated from its observations and projected into every view it is not
   in, where the point is in front of the camera and inside the image. Among
   the keypoints within ``tau`` pixels of the projection (the consensus's
   reprojection tolerance), the nearest by descriptor to the group (its
   smallest distance to any of the group's observations) is proposed.
2. **Tracks, nearest first.** The proposals are applied in order of their
   descriptor distance: a keypoint free of any group joins the group's track
   (the first proposal takes it: each keypoint goes to the track it resembles
   most); a keypoint of another group's track merges the two tracks when they
   share no view (the same 3D point, split by the pairs into two groups). A
   proposal is applied only if the point triangulated from all the
   observations reprojects within ``tau`` in each.
3. **Decision.** A completed track counts when it spans ``min_views`` distinct
   views (views within ``min_angle`` of one another count once), one more when
   none of its groups holds a match below the pair rule's ratio (``strict``):
   a view found by projection backs up a match the pair rule accepted, and it
   takes two to back up looser ones. Its groups' edges are then kept, and every
   two of its observations that came from different groups or were added
   become new matches (when their two images are a pair of the run).

Measured on COLMAP's SIFT features (``features="database"``; issue 14: accurate
3D points against pycolmap's extract + match_exhaustive + triangulate_points,
which COLMAP's ``tri_ignore_two_view_tracks`` makes three-view points), with
the consensus alone -> with completion: dinoSparseRing +19 % -> +29 %, rooms of 12
and 10 views +21 % -> +26 % and +19 % -> +23 %, held out: a 14-view room +17 % ->
+20 %, an 8-view room +32 % -> +39 % (accurate fraction 1.5 -> 2.1 points below
pycolmap's), templeSparseRing +33 % -> +63 %. With our own features (end to
end) it also adds points, but lowers the accurate fraction on
templeSparseRing (98.3 % -> 95.5 %) and the 8-view room (95.9 % -> 95.0 %):
dense features put a keypoint near almost any projection. Hence it is an
option (``TrackConsensus(complete=True)``), off by default.

What does not make it precise enough (measured, issue 14; accurate fraction
end to end, completion off -> on -> variant). A Lowe test on each proposal,
at the consensus's loose ratio 1 (``d1`` to the group below ``d2``, the
second keypoint within ``tau`` or the nearest of the pair rule's 128 random
keypoints of the view), keeps the fraction (templeSparseRing 98.3 % -> 95.5 %
-> 98.2 %, 8-view room 95.9 -> 95.0 -> 95.9) but removes most proposals (84 %
on the 12-view room), and the gain with them (same features: +0.3 to +1.1 %
accurate points over completion off, against +2.7 to +23 % for completion); at the
pair rule's ratio 0.68 almost nothing is left (0 to 11 observations added per
collection). The descriptor does not tell the proposals apart: on the
12-view room, the proposals taken by groups whose point is true have a
median ratio of 1.22 to that reference, those of false groups 1.28 (16 % and
9 % below 1): the true keypoint of a third view, which the pairs did not
match either, is rarely closer to the group than a random keypoint. The
position tells them apart only in part: the hits of true groups lie a median
0.51 ``tau`` from the projection, those of false groups 0.78 (uniform in the
disc: 0.71). Also tried, each more than a point below completion off on
templeSparseRing end to end (97.3 % at best): the second keypoint within
``tau`` alone (ratio 0.68), a search radius of ``tau / 2``, completing only
the groups that hold a strict match, and taking a hit only when a keypoint
that close to the projection was improbable (below 5 %) at the local
keypoint density.
"""

from __future__ import annotations

import numba as nb
import numpy as np

from .. import threads
from . import _completion_kernel as _kernel

__all__ = ["complete_groups", "NORM_CODES"]

#: The descriptor norms of :class:`~episeg_cv.colmap.FeatureStore` and their kernel codes.
NORM_CODES = {"l2": _kernel.L2, "l2sqr": _kernel.L2, "l1": _kernel.L1, "hamming": _kernel.HAMMING}


def complete_groups(P, centers, sizes, node_image, node_kp, node_xy, group, group_views, eligible, confident,
                    keypoints, descriptors, norm, tau, cos_min_angle, min_views):
    """The groups of the track consensus completed by projection (module docstring).

    Parameters
    ----------
    P, centers : (n, 3, 4), (n, 3) float64
        The views' projection matrices and camera centres, in one world frame.
    sizes : (n, 2) float64
        The views' image sizes ``(w, h)``, pixels.
    node_image, node_kp : (N,) int64
        Each observation's view and keypoint index.
    node_xy : (N, 2) float64
        Each observation's position, pixels of the pinhole image.
    group : (N,) int64
        Each observation's group (-1: none).
    group_views : (G,) int64
        Each group's distinct views.
    eligible, confident : (G,) bool
        The groups to complete; those holding a match below the pair rule's ratio.
    keypoints, descriptors : callable
        ``keypoints(k)`` -> ``(N_k, 2)`` float64 pinhole positions (NaN: none) and ``descriptors(k)`` ->
        ``(N_k, D)`` of every keypoint of view ``k``.
    norm : str
        A key of :data:`NORM_CODES`.
    tau : float
        Pixels.
    cos_min_angle : float
        The cosine of the minimum angle between two distinct views (2: every view counts).
    min_views : int

    Returns
    -------
    edge_a, edge_b : (E, 2) int64
        New matches, ``(view, keypoint)`` of each end.
    views : (G,) int64
        Each group's distinct views afterwards.
    stats : dict
        ``added`` (observations), ``merged`` (tracks merged into others), ``new_edges``.

    Raises
    ------
    ValueError
        An unknown ``norm``; descriptors not one row per keypoint.

    Examples
    --------
    Two cameras see the point (0, 0, 5); a third camera's keypoint lies where it projects:

    >>> K = np.array([[100.0, 0, 50], [0, 100.0, 50], [0, 0, 1]])
    >>> P = np.array([K @ np.column_stack([np.eye(3), [-k, 0, 0]]) for k in range(3)])
    >>> kp = [np.array([[50.0 - 20 * k, 50.0]]) for k in range(3)]
    >>> des = [np.array([[1.0, 0.0]], np.float32)] * 3
    >>> ea, eb, views, stats = complete_groups(
    ...     P, np.array([[k, 0.0, 0] for k in range(3)]), np.full((3, 2), 100.0), np.array([0, 1]),
    ...     np.array([0, 0]), np.array([[50.0, 50.0], [30.0, 50.0]]), np.array([0, 0]), np.array([2]),
    ...     np.array([True]), np.array([True]), lambda k: kp[k], lambda k: des[k], "l2", 1.0, 2.0, 3)
    >>> ea.tolist(), eb.tolist(), views.tolist(), stats["added"]
    ([[0, 0], [1, 0]], [[2, 0], [2, 0]], [3], 1)
    """
    if norm not in NORM_CODES:
        raise ValueError(f"norm must be one of {tuple(NORM_CODES)}, got {norm!r}")
    n_views = P.shape[0]
    xy = [np.asarray(keypoints(k), np.float64).reshape(-1, 2) for k in range(n_views)]
    des = []
    for k in range(n_views):
        d = np.ascontiguousarray(descriptors(k))
        if d.ndim != 2 or len(d) != len(xy[k]) or (len(des) and d.shape[1] != des[0].shape[1]):
            raise ValueError(f"descriptors of view {k} must be one row of {des[0].shape[1] if des else 'D'} per "
                             f"keypoint ({len(xy[k])}), got shape {d.shape}")
        des.append(d.astype(des[0].dtype if des else d.dtype, copy=False))
    kp_ptr = np.concatenate([[0], np.cumsum([len(x) for x in xy])]).astype(np.int64)
    kp_xy = np.concatenate(xy)
    kp_node = np.full(kp_ptr[-1], -1, np.int64)
    kp_node[kp_ptr[node_image] + node_kp] = np.arange(len(node_image))
    # the groups' observations, group by group
    n_groups = len(group_views)
    order = np.argsort(group, kind="stable")
    order = order[group[order] >= 0].astype(np.int64)
    grp_ptr = np.searchsorted(group[order], np.arange(n_groups + 1)).astype(np.int64)
    sel = np.flatnonzero(eligible).astype(np.int64)
    counts = grp_ptr[sel + 1] - grp_ptr[sel]
    sub_ptr = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
    sub_nodes = order[np.repeat(grp_ptr[sel] - sub_ptr[:-1], counts) + np.arange(sub_ptr[-1])]
    grid = _kernel.build_grid(kp_xy, kp_ptr, sizes, tau)
    best_kp, best_d = threads.run(
        _kernel.nearby, _kernel.nearby_parallel, len(sel), P, sub_ptr, sub_nodes, node_image, node_kp, node_xy,
        kp_xy, kp_ptr, nb.typed.List(des), NORM_CODES[norm], sizes, tau, *grid)
    flat = np.flatnonzero(best_kp.ravel() >= 0)
    proposals = flat[np.argsort(best_d.ravel()[flat], kind="stable")]  # nearest first, ties in (group, view) order
    ea, eb, views, n_added, n_merged = _kernel.additions(
        P, centers, grp_ptr, order, node_image, node_kp, node_xy, group, kp_node, kp_xy, kp_ptr, sel, best_kp,
        proposals, tau, cos_min_angle, min_views, confident)
    out = group_views.copy()
    out[views >= 0] = views[views >= 0]
    return ea, eb, out, {"added": int(n_added), "merged": int(n_merged), "new_edges": len(ea)}
