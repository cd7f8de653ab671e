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
   With the images (``images``), a proposal must also look like the group
   (:func:`photo_consistency`): the NCC of a 15 x 15 patch round the keypoint
   against the group's images, each warped by the plane through the group's
   point that faces view ``k``, at least :data:`MIN_NCC` with each, and view
   ``k`` within :data:`MAX_ANGLE` of each of the group's views.
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
option (``TrackConsensus(complete=True)``), off by default; with the images the
proposals are also checked photometrically (below).

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

What the images tell (the photometric check, :func:`photo_consistency`, which
:func:`~episeg_cv.colmap.match_model` applies). Proposals labelled by ground
truth (the point of the group and the keypoint accurate in every view: the
rendered depth for the rooms, box and silhouettes for the real sets): the NCC
separates them on the rooms (AUC 0.79-0.86; at 0.3 it keeps 78-84 % of the
true ones and 26-38 % of the false), hardly on dinoSparseRing and
templeSparseRing (AUC 0.56-0.61), where the median proposal's view is 65
degrees from the group's and a planar patch no longer matches (below 60
degrees on templeSparseRing: AUC 0.71-0.85). Choosing among the keypoints
within ``tau`` by NCC instead of the descriptor changes nothing (both pick
the true one wherever the disc holds one). Hence the check refuses a proposal
unless each of the group's views is within :data:`MAX_ANGLE` (60 degrees;
beyond it the AUC on dinoSparseRing is 0.54) and each NCC is at least
:data:`MIN_NCC` (0.3: on the development sets, dinoSparseRing and rooms of 12
and 10 views, 0.2 / 0.3 / 0.5 / 0.7 all keep the end-to-end fraction within
0.5 points of completion off; 0.3 with a margin). Accurate points and fraction
(gain over pycolmap) with completion off / without the check / with it, the
held-out sets checked with these constants unchanged:

============ ===================== ===================== =====================
same feat.   completion off        without the check     with the check
============ ===================== ===================== =====================
dino         325, 93.1 % (+19 %)   353, 91.7 % (+29 %)   333, 92.5 % (+22 %)
room 12      4456, 93.4 % (+21 %)  4624, 92.8 % (+26 %)  4572, 93.3 % (+24 %)
room 10      3682, 95.6 % (+19 %)  3809, 95.0 % (+23 %)  3758, 95.3 % (+22 %)
room 14      5095, 91.7 % (+17 %)  5235, 90.9 % (+20 %)  5187, 91.4 % (+19 %)
room 8       2608, 94.5 % (+32 %)  2744, 94.0 % (+39 %)  2694, 94.3 % (+36 %)
temple       1863, 98.9 % (+33 %)  2286, 98.1 % (+63 %)  1936, 98.9 % (+38 %)
============ ===================== ===================== =====================

End to end, accurate fraction (off / no check / check): dino 94.5 / 93.7 /
94.5 %, room 12 94.7 / 93.8 / 94.4, room 10 96.2 / 95.5 / 95.9, room 14 93.3 /
92.6 / 93.1, room 8 95.9 / 95.0 / 95.7, templeSparseRing 98.3 / 95.5 / 98.3,
with 3-7 % more accurate points than off: with the check, completion keeps
every end-to-end fraction within 0.5 points of completion off and of pycolmap,
but its same-features gain is 2-5 points, not the 25 % the goal needs on
dino and the 10- and 14-view rooms.

The check's cost (issue 14; :func:`photo_consistency` is one compiled call,
its decisions those of the NumPy / ``cv2.remap`` version it replaced on every
proposal of 8 sets). The verification's CPU seconds with one worker,
completion off / with the check: a 24-view room (end to end) 0.25 / 0.54
(1.32 before), dinoSparseRing (COLMAP's features) 0.005 / 0.10 (0.14),
templeSparseRing 0.03 / 0.14 (0.39). On dinoSparseRing most of it is reading
the 16 images (6 ms each), so matching there takes 0.145 s with completion
against 0.05 s without.
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import cv2
import numba as nb
import numpy as np

from .. import threads
from . import _completion_kernel as _kernel
from .images import read_grey
from .views import PINHOLE_MODELS

__all__ = ["complete_groups", "photo_consistency", "pinhole_image", "pinhole_images", "NORM_CODES", "MIN_NCC",
           "MAX_ANGLE", "PATCH"]

#: The least NCC of a proposal's patch with each of the group's (:func:`photo_consistency`). Chosen on
#: dinoSparseRing and rooms of 12 and 10 views: the lowest of 0.2 / 0.3 / 0.5 / 0.7 with which each one's
#: accurate fraction end to end stays within 0.5 points of completion off, with a margin (module docstring).
MIN_NCC = 0.3
#: Degrees: the largest angle at the group's point between view ``k`` and a group's view that is checked (the
#: NCC of a fronto-parallel plane does not tell true from false proposals beyond it: AUC 0.54 on dinoSparseRing).
MAX_ANGLE = 60.0
#: The half side of the patches, pixels (15 x 15).
PATCH = 7

#: The descriptor norms of :class:`~episeg_cv.colmap.FeatureStore` and their kernel codes.
NORM_CODES = {"l2": _kernel.L2, "l2sqr": _kernel.L2, "l1": _kernel.L1, "hamming": _kernel.HAMMING}


def complete_groups(P, centers, sizes, node_image, node_kp, node_xy, group, group_views, eligible, confident,
                    keypoints, descriptors, norm, tau, cos_min_angle, min_views, images=None):
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
    images : callable or None, optional
        ``images(k)`` -> the pinhole image of view ``k`` (2-D, grayscale; :func:`pinhole_image`): each
        proposal must then pass :func:`photo_consistency`. Default None: no photometric check.

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
    best_kp, best_d, X = threads.run(
        _kernel.nearby, _kernel.nearby_parallel, len(sel), P, sub_ptr, sub_nodes, node_image, node_kp, node_xy,
        kp_xy, kp_ptr, nb.typed.List(des), NORM_CODES[norm], sizes, tau, *grid)
    if images is not None:
        s, k = np.nonzero(best_kp >= 0)
        width = int(counts.max()) if len(counts) else 1
        obs_image = np.full((len(s), width), -1, np.int64)
        for t in range(width):
            has = counts[s] > t
            obs_image[has, t] = node_image[sub_nodes[sub_ptr[s[has]] + t]]
        ncc = photo_consistency(P, centers, X[s], k, kp_xy[kp_ptr[k] + best_kp[s, k]], obs_image, images)
        refused = ~(ncc >= MIN_NCC)
        best_kp[s[refused], k[refused]] = -1
    flat = np.flatnonzero(best_kp.ravel() >= 0)
    proposals = flat[np.argsort(best_d.ravel()[flat], kind="stable")]  # nearest first, ties in (group, view) order
    ea, eb, views, n_added, n_merged = _kernel.additions(
        P, centers, grp_ptr, order, node_image, node_kp, node_xy, group, kp_node, kp_xy, kp_ptr, sel, best_kp,
        proposals, tau, cos_min_angle, min_views, confident)
    out = group_views.copy()
    out[views >= 0] = views[views >= 0]
    return ea, eb, out, {"added": int(n_added), "merged": int(n_merged), "new_edges": len(ea)}


def photo_consistency(P, centers, X, k, y, obs_image, images, half=PATCH, max_angle=MAX_ANGLE):
    """The NCC of a patch round each proposal's keypoint with the group's images: the least over the group.

    The ``(2 half + 1)^2`` pixels round ``y[t]`` in view ``k[t]`` are cast onto the plane through ``X[t]``
    that faces camera ``k[t]`` (normal towards its centre), and the plane points are looked up in the
    image of each observation ``obs_image[t, a]`` (bilinear); the normalised cross-correlation of the two
    patches. Bilinear as ``cv2.remap`` (``INTER_LINEAR``, float32 positions) gives it, NaN unless a
    position's four neighbouring pixels are in the image.

    Each image used is read once (``images`` is called once per view, from several threads when the
    kernels have more than one) and every proposal is checked in one compiled call
    (:func:`._completion_kernel.photo`), on threads for large inputs. Cost (issue 14, CPU seconds, the
    images given in memory; the Python version this replaced in brackets): 0.12 s (0.43) for the 9968
    proposals of a 24-view room, 0.03 s (0.43) for the 10606 of templeSparseRing, 0.003 s (0.03) for the
    374 of dinoSparseRing, with the same decisions and NCC within 3e-15. Reading the images, 6 ms per
    640 x 480 PNG, is then most of the cost on dinoSparseRing.

    Parameters
    ----------
    P, centers : (n, 3, 4), (n, 3) float64
        Projection matrices and camera centres.
    X : (T, 3) float64
        Each proposal's group point.
    k : (T,) int64
        Its view.
    y : (T, 2) float64
        Its keypoint, pixels of the pinhole image.
    obs_image : (T, m) int64
        The views of the group's observations (-1: none).
    images : callable
        ``images(v)`` -> 2-D grayscale pinhole image of view ``v``.
    half : int, optional
    max_angle : float, optional
        Degrees: an observation whose view is further from view ``k`` (at ``X``) gives NaN.

    Returns
    -------
    (T,) float64
        The least NCC over the group's observations; NaN where one is not measured (a patch beyond an
        image, a flat patch, a view beyond ``max_angle``) -- NaN fails any threshold.

    Examples
    --------
    Two cameras see a textured plane z = 5; the patch of the true point correlates, a shifted one does not:

    >>> rng = np.random.default_rng(0)
    >>> tex = cv2.GaussianBlur(rng.uniform(0, 255, (100, 100)).astype(np.float32), (0, 0), 1.5)
    >>> K = np.array([[100.0, 0, 50], [0, 100.0, 50], [0, 0, 1]])
    >>> P = np.array([K @ np.column_stack([np.eye(3), [-c, 0, 0]]) for c in (0.0, 0.5)])
    >>> H = K @ np.array([[1.0, 0, -0.5 / 5], [0, 1, 0], [0, 0, 1]]) @ np.linalg.inv(K)  # view 0 -> view 1
    >>> ims = [tex, cv2.warpPerspective(tex, H, (100, 100), flags=cv2.INTER_LINEAR)]
    >>> X = np.array([[0.0, 0.0, 5.0]])
    >>> at = lambda x: photo_consistency(P, np.array([[0.0, 0, 0], [0.5, 0, 0]]), X, np.array([1]),
    ...                                  np.array([x]), np.array([[0]]), ims.__getitem__)
    >>> bool(at([40.0, 50.0])[0] > 0.95), bool(at([40.0, 60.0])[0] < 0.5)
    (True, False)
    """
    T = len(k)
    if T == 0:
        return np.zeros(0)
    k = np.asarray(k, np.int64)
    obs_image = np.ascontiguousarray(obs_image, np.int64)
    used = np.unique(np.concatenate([k, obs_image[obs_image >= 0]]))
    n_threads = threads.get_num_threads()
    if n_threads > 1:  # (OpenCV's decoding releases the GIL)
        with ThreadPoolExecutor(min(n_threads, len(used))) as pool:
            loaded = list(pool.map(lambda v: np.asarray(images(int(v)), np.float32), used))
    else:
        loaded = [np.asarray(images(int(v)), np.float32) for v in used]
    n_views = P.shape[0]
    size = np.zeros((2, n_views), np.int64)
    size[:, used] = np.array([im.shape[::-1] for im in loaded]).T
    im_off = np.zeros(n_views, np.int64)
    im_off[used] = np.cumsum([0] + [im.size for im in loaded[:-1]])
    pixels = np.concatenate([im.ravel() for im in loaded])
    P = np.ascontiguousarray(P, np.float64)
    Kinv = np.zeros((n_views, 3, 3))
    views = np.unique(k)
    Kinv[views] = np.linalg.inv(P[views, :, :3])
    return threads.run(_kernel.photo, _kernel.photo_parallel, T, Kinv, P, np.ascontiguousarray(centers, np.float64),
                       np.ascontiguousarray(X, np.float64), k, np.ascontiguousarray(y, np.float64), obs_image, pixels,
                       im_off, size[0], size[1], int(half), float(np.cos(np.radians(max_angle))))


def _sample(image, xy):
    """Bilinear samples of ``image`` at the ``(T, S, 2)`` pixel positions: ``(T, S)``, NaN beyond it."""
    xy = np.where(np.isfinite(xy), xy, -1e6).astype(np.float32)
    return cv2.remap(np.asarray(image, np.float32), xy[..., 0], xy[..., 1], cv2.INTER_LINEAR,
                     borderMode=cv2.BORDER_CONSTANT, borderValue=np.nan).astype(np.float64)


def pinhole_image(view, image):
    """``image`` (the raw grayscale image of ``view``) resampled to the pinhole image of its ``K``.

    The identity for ``SIMPLE_PINHOLE`` and ``PINHOLE``; otherwise each pinhole pixel is mapped through
    COLMAP's camera model (``img_from_cam``) to the raw image (bilinear).

    Examples
    --------
    >>> from episeg_cv.colmap import View
    >>> v = View("a.png", 1, 1, [[100, 0, 49.5], [0, 100, 49.5], [0, 0, 1]], np.eye(3), [0, 0, 0], (100, 100))
    >>> im = np.arange(10000, dtype=np.float32).reshape(100, 100)
    >>> pinhole_image(v, im) is im
    True
    """
    if view.camera_model in PINHOLE_MODELS:
        return image
    w, h = view.image_size
    u, v = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    rays = np.column_stack([u.ravel(), v.ravel(), np.ones(u.size)]) @ np.linalg.inv(view.K).T
    raw = np.asarray(view._camera().img_from_cam(rays, check_cheirality=False), np.float64).reshape(-1, 2) - 0.5
    return _sample(image, raw.reshape(1, -1, 2)).reshape(h, w)


def pinhole_images(views, image_dir):
    """``images(k)`` -> the grayscale pinhole image (float32, :func:`pinhole_image`) of ``views[k]``, read
    from ``image_dir`` on first use and kept.

    Raises
    ------
    ValueError
        (on use) An image that OpenCV cannot read.
    """
    cache = {}

    def images(k):
        if k not in cache:
            path = Path(image_dir) / views[k].name
            image = read_grey(path)
            if image is None:
                raise ValueError(f"image {views[k].name!r} cannot be read: {path}")
            cache[k] = pinhole_image(views[k], image.astype(np.float32))
        return cache[k]

    return images
