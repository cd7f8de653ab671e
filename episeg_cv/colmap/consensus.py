"""Track consensus: the candidate matches of a whole collection verified with the known poses.

A pair's acceptance rule (:class:`~episeg_cv.AcceptRule`, ratio 0.68) was
chosen for a precision of 0.95 on single pairs. In a collection a match can be
checked again: its 3D point, triangulated with the known poses, must be seen
by the other images of its track. :func:`verify_tracks` does this before
anything is written:

1. **Edges.** Every mutual candidate with ratio below ``loose`` (default 1:
   every mutual candidate; the tracks decide) that also lies on its segment
   in the reverse direction (as :func:`~episeg_cv.colmap.match_pair` checks).
2. **Components.** The edges join (image, keypoint) observations; union-find
   gives the connected components, processed independently.
3. **Consensus groups, RANSAC-style.** Each round takes the component's
   lowest-ratio edge whose two ends are still free and, as seeds, the
   ``max_seeds`` (24) lowest-ratio edges among the free observations within
   ``hops`` (2) edges of it. Each seed is triangulated from its two
   observations; its support grows from them along the edges, through the
   observations that reproject within ``tau`` pixels (the band's consensus
   tolerance) in front of their camera, per image only the closest. The seed
   with the best MSAC score wins (the sum over its support of
   ``1 - (error / tau)^2``: as many observations, explained more tightly). Its
   observations are re-triangulated together, re-checked, and form a group,
   which leaves the graph. A round whose seeds find no support sets them
   aside. Until no free edge remains.
4. **Decision.** An edge is kept when both ends are in the same group and
   either its ratio is below the pair rule's (``strict``, 0.68), or the group
   spans at least ``min_views`` (3) distinct views: views whose
   rays meet at the group's point at less than ``min_angle`` (1.5 degrees,
   COLMAP's minimum triangulation angle) count once, since a view from (nearly)
   the same place adds no check of the depth. A strict edge whose ends fall in
   different groups is dropped: a track contradicts it.
5. **Completion** (optional, ``TrackConsensus(complete=True)``,
   :func:`verify_and_complete`): the groups of too few views are projected
   into the other views and take the keypoints found there
   (:mod:`~episeg_cv.colmap.completion`), before the decision.
6. **Views whose pose looks off** (:func:`suspect_views`): a view whose pose
   is off by more than the band keeps its candidates (its segments still
   cross keypoints) but loses their verification, since the tracks disagree
   with it; its matches then drop out silently. A view is named when the
   share of its candidates kept is below :data:`SUSPECT_FRACTION` of the
   median view's.

Why RANSAC seeds and not a least-squares fit of each whole track: one false
edge that merges two true tracks makes the fit land between them, and the
true observations get dropped. Why the seeds around one edge, not the
component's lowest-ratio ones: false edges chain tracks into components of
thousands of observations (a third of them on the 12-view room, four fifths
on templeSparseRing), and there a seed must compete with the seeds that
explain the same observations, not with unrelated ones. Why the support along
the edges: an observation that merely lands near the point, with no candidate
match to the track, is not evidence for it. Why MSAC's score rather than the
count: the count prefers the seed that sweeps in the most borderline
observations (two nearby features, a T-junction), and those groups were
the least accurate. Why distinct views: templeSparseRing has two images taken
from the same place, whose matches made any third image look like a check.
Measured (``benchmarks/colmap.py`` and held-out rooms and templeSparseRing,
issue 14): see the README.

Why only mutual candidates as edges (measured, rejected): adding each
query's nearest candidate and each keypoint's nearest query when they are
not mutual (kept only in groups of ``min_views`` distinct views) gave 1-2 %
more accurate 3D points with COLMAP's features (dinoSparseRing 325 -> 330,
rooms 12/7 4460 -> 4506 and 10/3 3686 -> 3733), about nothing on top of
the completion, and cost accurate fraction: 1.8 points end to end on the
held-out templeSparseRing (98.3 -> 96.5 %), 1 point on a held-out 8-view
room. Adding the second-nearest candidates cost 3.7-7.4 points of it. On the
12-view room, the views a true track misses are mostly not among any of
the descriptor candidates (a quarter of the true matches: not the nearest
on the segment, or farther than a padding reference), so more
nearest-neighbour edges cannot reach them; only the projection of a group
into the other views can (the completion). (Scratch runs, issue 14.)

Why one ``tau`` for the collection (measured, rejected; ``benchmarks/colmap.py``'s sets, issue 14):
on dinoSparseRing with COLMAP's features, what adds accurate points is ``tau``, not the band: with
``tau`` held at the band's 2.35 px, a band of 3, 3.5 or 4 px gave 326-327 accurate points against 325;
``tau`` = 4 px gave 352 (4 px band and ``tau``: 371, 91.2 % accurate), but on the rooms (exact poses)
``tau`` = 2 px or a 4 px band cost 6-8 points of accurate fraction. Sampling more pairs for the band
(16, 40, 120) moved its sigma only between 0.62 and 0.78 px. The leave-one-out reprojection errors of
dinoSparseRing's groups do differ by view (medians 0.52-1.40 px, the same views on both features;
rooms 0.14-0.25 px), but a tolerance per view from them (3 Rayleigh scales, at least ``tau``; rooms
unchanged) gave only 325 -> 330 and 515 -> 520 accurate points, at 0.7 points less accurate fraction.
They grow with the keypoint's scale (COLMAP's affine shape; smallest to largest fifth: dinoSparseRing
0.65 -> 1.34 px, the 12-view room 0.13 -> 0.33 px), but a tolerance per scale fifth from them (same
rule) gave 325 -> 336 (92.3 %), the rooms again unchanged.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from .. import threads
from .._validation import as_array, as_ratio
from . import _consensus_kernel, completion

__all__ = ["TrackConsensus", "verify_tracks", "verify_and_complete", "projection_matrices", "suspect_views",
           "SUSPECT_FRACTION", "MIN_VIEW_CANDIDATES"]

#: A view is suspect when the share of its candidate matches kept is below this fraction of the median
#: view's. Measured (scratch, one view's pose turned by 4 px or 16 px, every other exact; both features):
#: exact poses gave per-view shares of 0.36-1.0 times the median (the lowest: dinoSparseRing's image 6,
#: which has few features), a view off by 4 px 0.03-0.23, off by 16 px 0.01-0.12, on dinoSparseRing,
#: the held-out templeSparseRing and two rooms.
SUSPECT_FRACTION = 0.25
#: Candidate matches a view needs for its share to be judged.
MIN_VIEW_CANDIDATES = 20


@dataclass(frozen=True)
class TrackConsensus:
    """Settings of the track consensus (:func:`verify_tracks`).

    Attributes
    ----------
    loose : float in (0, 1]
        Candidates with a ratio below it are edges of the match graph. Default 1:
        every mutual candidate, whatever its ratio (ratios at or above 1 mean a
        padding reference is nearer; those stay out). Against 0.9, with the
        collection's ``tol="auto"``, it gave 2-13 % more accurate 3D points on
        the real dinoSparseRing and two synthetic rooms, with COLMAP's features
        and with ours (``benchmarks/colmap.py``).
    min_views : int >= 2
        Distinct views a group must span for its edges with a ratio between the
        pair rule's and ``loose`` to be kept. Default 3.
    tau : float or None
        Reprojection tolerance in pixels (of the pinhole image); None: the
        matching ``tol``. Default None.
    min_angle : float in [0, 90)
        Degrees: views whose rays meet at a group's point at a smaller angle
        count as one view towards ``min_views``. Default 1.5, COLMAP's
        minimum triangulation angle (0: every image counts).
    max_seeds : int >= 1
        Seeds tried per round. Default 24.
    neighbourhood : int >= 2
        A round's seeds come from at most this many observations around its
        lowest-ratio edge. Default 1000.
    hops : int >= 1
        The radius of that neighbourhood, in edges. Default 2.
    complete : bool
        Complete the groups of too few views by projection into the other
        views (:mod:`~episeg_cv.colmap.completion`, :func:`verify_and_complete`),
        for :func:`~episeg_cv.colmap.match_model`, each proposal checked against
        the images (:func:`~episeg_cv.colmap.completion.photo_consistency`).
        Default False: it adds 3-7 % accurate 3D points end to end at the same
        accurate fraction (within 0.5 points on six collections), but it makes
        the verification slower: on a 24-view room 0.25 -> 0.54 s of CPU, and on
        dinoSparseRing matching 0.05 -> 0.12-0.15 s, mostly reading the images
        (the matching-time goal there is 0.055 s).

    Examples
    --------
    >>> TrackConsensus().loose, TrackConsensus(loose=0.8).replace(min_views=4).min_views
    (1.0, 4)
    >>> TrackConsensus(min_views=1)
    Traceback (most recent call last):
    ...
    ValueError: min_views must be an integer >= 2, got 1
    """

    loose: float = 1.0
    min_views: int = 3
    tau: float | None = None
    min_angle: float = 1.5
    max_seeds: int = 24
    neighbourhood: int = 1000
    hops: int = 2
    complete: bool = False

    def __post_init__(self):
        object.__setattr__(self, "loose", as_ratio(self.loose, "loose"))
        for name, low in (("min_views", 2), ("max_seeds", 1), ("neighbourhood", 2), ("hops", 1)):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < low:
                raise ValueError(f"{name} must be an integer >= {low}, got {v!r}")
            object.__setattr__(self, name, int(v))
        if self.tau is not None:
            if not (_is_number(self.tau) and np.isfinite(self.tau) and self.tau > 0):
                raise ValueError(f"tau must be a finite number > 0 or None, got {self.tau!r}")
            object.__setattr__(self, "tau", float(self.tau))
        if not (_is_number(self.min_angle) and 0 <= self.min_angle < 90):
            raise ValueError(f"min_angle must be a number of degrees in [0, 90), got {self.min_angle!r}")
        object.__setattr__(self, "min_angle", float(self.min_angle))
        if not isinstance(self.complete, (bool, np.bool_)):
            raise TypeError(f"complete must be a bool, got {type(self.complete).__name__}")
        object.__setattr__(self, "complete", bool(self.complete))

    def replace(self, **changes) -> "TrackConsensus":
        """A copy with some fields changed (and checked)."""
        return dataclasses.replace(self, **changes)


def _is_number(x) -> bool:
    return isinstance(x, (int, float, np.integer, np.floating)) and not isinstance(x, bool)


def _normalised(views) -> tuple[np.ndarray, np.ndarray]:
    """``(P (n, 3, 4), centers (n, 3))`` in world coordinates moved and scaled so that the camera centres are
    centred at the origin with a median distance of 1 to it (better conditioned)."""
    centers = np.array([v.center for v in views], dtype=np.float64).reshape(-1, 3)
    c0 = centers.mean(axis=0) if len(views) else np.zeros(3)
    s = float(np.median(np.linalg.norm(centers - c0, axis=1))) if len(views) else 1.0
    if not (np.isfinite(s) and s > 0):
        s = 1.0
    M = np.eye(4)
    M[:3, :3] *= s
    M[:3, 3] = c0
    P = np.array([v.K @ np.column_stack([v.R, v.t]) @ M for v in views]).reshape(-1, 3, 4)
    return P, (centers - c0) / s


def projection_matrices(views) -> np.ndarray:
    """``(n, 3, 4)`` float64 ``K [R | t]`` of the views, in world coordinates moved and scaled so that the
    camera centres are centred at the origin with a median distance of 1 to it (better conditioned)."""
    return _normalised(views)[0]


def _candidates(candidates, n_views: int):
    """The checked, flattened candidates: ``(img_a, img_b, pairs, ratio, sizes)``.

    Integer ``(K, 2)`` pairs and float ``(K,)`` ratios are taken as they are and checked for negative
    indices and NaN once, concatenated (a collection's pipeline passes arrays: on dinoSparseRing's 120
    pairs the checks one pair at a time took 1.6 ms, 3 % of the matching); other inputs go through
    :func:`~episeg_cv._validation.as_array` one by one.
    """
    sizes, ends, pairs, ratio = [], [], [], []
    for q, c in enumerate(candidates):
        if not isinstance(c, (tuple, list)) or len(c) != 4:
            raise TypeError(f"candidates[{q}] must be a tuple (i, j, pairs, ratio)")
        i, j, p, r = c
        for name, v in (("i", i), ("j", j)):
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or not 0 <= v < n_views:
                raise ValueError(f"candidates[{q}]: view index {name} must be an integer in [0, {n_views}), "
                                 f"got {v!r}")
        if i == j:
            raise ValueError(f"candidates[{q}]: a pair of two different views is needed, got i = j = {i}")
        if not (isinstance(p, np.ndarray) and p.dtype.kind in "iu" and p.ndim == 2 and p.shape[1] == 2):
            p = as_array(p, f"candidates[{q}] pairs", (None, 2), dtype=np.int64)
        if not (isinstance(r, np.ndarray) and r.dtype.kind == "f" and r.shape == (len(p),)):
            r = as_array(r, f"candidates[{q}] ratio", (len(p),), finite=False)
        sizes.append(len(p))
        ends.append((int(i), int(j)))
        pairs.append(p)
        ratio.append(r)
    if not pairs:
        return np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros((0, 2), np.int64), np.zeros(0), sizes
    pairs = np.concatenate(pairs).astype(np.int64, copy=False)
    ratio = np.concatenate(ratio).astype(np.float64, copy=False)
    last = np.cumsum(sizes)
    bad = np.isnan(ratio)
    if bad.any():
        raise ValueError(f"candidates[{int(np.searchsorted(last, np.argmax(bad), 'right'))}] ratio must not be NaN")
    bad = pairs.min(axis=1) < 0
    if bad.any():
        k = int(np.argmax(bad))
        raise ValueError(f"candidates[{int(np.searchsorted(last, k, 'right'))}] pairs must be keypoint indices >= 0, "
                         f"got {int(pairs[k].min())}")
    ij = np.array(ends, dtype=np.int64).reshape(-1, 2)
    counts = np.array(sizes, dtype=np.int64)
    return np.repeat(ij[:, 0], counts), np.repeat(ij[:, 1], counts), pairs, ratio, sizes


def _observations(img_a, img_b, pairs, keypoints, n_views: int):
    """The observations (image, keypoint) of the candidates, numbered ``0 .. n-1`` in (image, keypoint)
    order: ``(eu, ev, node_image, node_kp, node_xy)``, the two ends of each candidate and each observation's
    image, keypoint index and pinhole position.

    A dense numbering: each view's keypoints get a block of ids (its number of keypoints, from
    ``keypoints``, called once per view with candidates), and the used ids are renumbered in order (the
    numbering of ``np.unique`` of the (image, keypoint) keys), compiled
    (:func:`._consensus_kernel.number_observations`: 8.5 ms for this function on the 24-view room's
    660k ends, 14.6 ms in NumPy, the same arrays).
    """
    xy_of, counts = {}, np.zeros(n_views, np.int64)
    for k in np.flatnonzero(np.bincount(img_a, minlength=n_views) + np.bincount(img_b, minlength=n_views)):
        xy_of[k] = np.asarray(keypoints(int(k)), dtype=np.float64).reshape(-1, 2)
        counts[k] = len(xy_of[k])
    for img, kp in ((img_a, pairs[:, 0]), (img_b, pairs[:, 1])):
        beyond = kp >= counts[img]
        if beyond.any():
            k = int(img[np.argmax(beyond)])
            top = max(int(kp[img == k].max()), int(pairs[img_a == k, 0].max(initial=0)),
                      int(pairs[img_b == k, 1].max(initial=0)))
            raise ValueError(f"candidates: keypoint {top} of view {k} is beyond its {counts[k]} keypoints")
    start = np.concatenate([[0], np.cumsum(counts)])
    eu, ev, node_image, node_kp = _consensus_kernel.number_observations(img_a, img_b, pairs, start)
    node_xy = np.empty((len(node_kp), 2), dtype=np.float64)
    bounds = np.searchsorted(node_image, np.arange(n_views + 1))
    for k, xy in xy_of.items():
        a, b = bounds[k], bounds[k + 1]
        node_xy[a:b] = xy[node_kp[a:b]]
    return eu, ev, node_image, node_kp, node_xy


def verify_tracks(views, candidates, keypoints, strict: float, tau: float,
                  config: TrackConsensus = TrackConsensus()) -> tuple[list, dict]:
    """Which candidate matches of a collection the track consensus keeps (module docstring).

    Parameters
    ----------
    views : sequence of View
        The posed images (``K``, ``R``, ``t``: world-to-camera, ``X_cam = R X + t``).
    candidates : sequence of (int, int, (K, 2) array, (K,) array)
        Per pair ``(i, j, pairs, ratio)``: view indices, keypoint index pairs
        ``(index in view i, index in view j)`` and their ratio values, every one
        below ``config.loose``. The order fixes the result (ties in ratio keep it).
    keypoints : callable
        ``keypoints(i)`` -> ``(N_i, 2)`` float64 keypoints of view ``i`` in its
        pinhole image (episeg_cv's pixel convention). Called once per view with
        candidates.
    strict : float
        The pair rule's ratio: edges below it need no third view.
    tau : float
        Reprojection tolerance in pixels (``config.tau`` overrides it when set).
    config : TrackConsensus, optional

    Returns
    -------
    keep : list of (K,) bool
        One mask per item of ``candidates``.
    stats : dict
        ``components``, ``groups``, ``unsupported_seeds``, ``edges``, ``kept``.

    Raises
    ------
    ValueError, TypeError
        A malformed candidate (view index out of range or ``i = j``, pairs not
        ``(K, 2)`` non-negative integers, a ratio per pair, NaN), a keypoint
        index beyond its view's keypoints, a non-positive ``tau``.

    Examples
    --------
    Three cameras on a line see the point (0, 0, 5); the candidate between
    images 0 and 1 has a loose ratio (0.8), and the third view backs it up:

    >>> from episeg_cv.colmap import View
    >>> K = [[100.0, 0, 50], [0, 100.0, 50], [0, 0, 1]]
    >>> vs = [View(f"{k}", k + 1, 1, K, np.eye(3), [-k, 0, 0], (100, 100)) for k in range(3)]
    >>> kp = [np.array([[50.0 - 100 * k / 5, 50.0], [10.0, 90.0]]) for k in range(3)]
    >>> cands = [(0, 1, np.array([[0, 0]]), np.array([0.8])), (1, 2, np.array([[0, 0]]), np.array([0.5]))]
    >>> keep, stats = verify_tracks(vs, cands, lambda k: kp[k], strict=0.68, tau=2.0)
    >>> [k.tolist() for k in keep], stats["groups"]
    ([[True], [True]], 1)
    >>> keep, _ = verify_tracks(vs, cands[:1], lambda k: kp[k], strict=0.68, tau=2.0)   # two views only
    >>> keep[0].tolist()
    [False]
    """
    keep, _, stats = _verify(views, candidates, keypoints, strict, tau, config, None, "l2")
    return keep, stats


def verify_and_complete(views, candidates, keypoints, descriptors, strict: float, tau: float,
                        config: TrackConsensus = TrackConsensus(), norm: str = "l2",
                        images=None) -> tuple[list, list, dict]:
    """:func:`verify_tracks`, then its groups of too few views completed by projection (:mod:`.completion`).

    Parameters
    ----------
    views, candidates, keypoints, strict, tau, config
        As :func:`verify_tracks`, but ``keypoints(i)`` is called for every view.
    descriptors : callable
        ``descriptors(i)`` -> ``(N_i, D)`` descriptors of view ``i``, a row per keypoint.
    norm : {"l2", "l2sqr", "l1", "hamming"}, optional
        Their norm. Default ``"l2"``.
    images : callable or None, optional
        ``images(i)`` -> the grayscale pinhole image of view ``i``: the proposals must then look like their
        group (:func:`.completion.photo_consistency`). Default None: no photometric check.

    Returns
    -------
    keep : list of (K,) bool
        One mask per item of ``candidates``.
    added : list of (A, 2) int64
        Per item of ``candidates``, its new matches (keypoint index pairs, in the item's order of views).
    stats : dict
        Those of :func:`verify_tracks` and ``added`` (observations added to groups), ``merged`` (tracks
        merged into others), ``new_edges``.

    Examples
    --------
    Three cameras on a line see the point (0, 0, 5); only images 0 and 1 were matched, and image 2's
    keypoint lies where the point projects:

    >>> from episeg_cv.colmap import View
    >>> K = [[100.0, 0, 50], [0, 100.0, 50], [0, 0, 1]]
    >>> vs = [View(f"{k}", k + 1, 1, K, np.eye(3), [-k, 0, 0], (100, 100)) for k in range(3)]
    >>> kp = [np.array([[50.0 - 100 * k / 5, 50.0], [10.0, 90.0]]) for k in range(3)]
    >>> des = [np.array([[1.0, 0.0], [0.0, 1.0]], np.float32)] * 3
    >>> cands = [(0, 1, np.array([[0, 0]]), np.array([0.5])), (0, 2, np.zeros((0, 2), int), np.zeros(0)),
    ...          (1, 2, np.zeros((0, 2), int), np.zeros(0))]
    >>> keep, added, stats = verify_and_complete(vs, cands, lambda k: kp[k], lambda k: des[k], 0.68, 2.0)
    >>> [k.tolist() for k in keep], [a.tolist() for a in added], stats["added"]
    ([[True], [], []], [[], [[0, 0]], [[0, 0]]], 1)
    """
    return _verify(views, candidates, keypoints, strict, tau, config, descriptors, norm, images)


def _verify(views, candidates, keypoints, strict, tau, config, descriptors, norm, images=None):
    """:func:`verify_and_complete`, without the completion when ``descriptors`` is None."""
    tau = config.tau if config.tau is not None else tau
    if not (_is_number(tau) and np.isfinite(tau) and tau > 0):
        raise ValueError(f"tau must be a finite number > 0, got {tau!r}")
    tau = float(tau)
    img_a, img_b, pairs, ratio, sizes = _candidates(candidates, len(views))
    keep = [np.zeros(n, dtype=bool) for n in sizes]
    stats = {"components": 0, "groups": 0, "unsupported_seeds": 0, "edges": int(sum(sizes)), "kept": 0}
    if not sum(sizes):
        return keep, [np.zeros((0, 2), np.int64) for _ in sizes], stats
    m = len(ratio)
    eu, ev, node_image, node_kp, node_xy = _observations(img_a, img_b, pairs, keypoints, len(views))
    P, centers = _normalised(views)
    cos_min_angle = float(np.cos(np.radians(config.min_angle))) if config.min_angle > 0 else 2.0  # (2: none merge)
    group, group_views, st = threads.run(
        _consensus_kernel.consensus, _consensus_kernel.consensus_parallel, m,
        P, centers, node_image, node_xy, eu, ev, ratio, len(views), tau, cos_min_angle,
        config.max_seeds, config.neighbourhood, config.hops)
    added = [np.zeros((0, 2), np.int64) for _ in sizes]
    if descriptors is not None:
        gu, gv = group[eu], group[ev]
        same = (gu >= 0) & (gu == gv)
        lowest = np.full(len(group_views), np.inf)
        np.minimum.at(lowest, gu[same], ratio[same])
        sizes_px = np.array([v.image_size for v in views], np.float64).reshape(-1, 2)
        ea, eb, group_views, more = completion.complete_groups(
            P, centers, sizes_px, node_image, node_kp, node_xy, group, group_views, group_views < config.min_views,
            lowest < strict, keypoints, descriptors, norm, tau, cos_min_angle, config.min_views, images)
        added = _added_matches(candidates, len(views), ea, eb)
        stats.update(more)
    gu, gv = group[eu], group[ev]
    same = (gu >= 0) & (gu == gv)
    spans = np.zeros(m, dtype=np.int64)
    spans[same] = group_views[gu[same]]
    ok = same & ((ratio < strict) | (spans >= config.min_views))
    start = 0
    for q, n in enumerate(sizes):
        keep[q] = ok[start:start + n]
        start += n
    stats.update(components=int(st[0]), groups=int(st[1]), unsupported_seeds=int(st[2]), kept=int(ok.sum()))
    return keep, added, stats


def _added_matches(candidates, n_views: int, ea, eb) -> list:
    """Per item of ``candidates``, the ``(K, 2)`` keypoint pairs of the new matches ``ea``-``eb`` (``(view,
    keypoint)`` rows) whose two views are that item's pair (oriented as the item; the first item of a pair)."""
    which = np.full((n_views, n_views), -1, np.int64)
    for q in range(len(candidates) - 1, -1, -1):
        which[candidates[q][0], candidates[q][1]] = q
    fwd = which[ea[:, 0], eb[:, 0]]
    bwd = np.where(fwd < 0, which[eb[:, 0], ea[:, 0]], -1)
    q = np.concatenate([fwd, bwd])
    rows = np.concatenate([np.column_stack([ea[:, 1], eb[:, 1]]), np.column_stack([eb[:, 1], ea[:, 1]])])
    keep = q >= 0
    q, rows = q[keep], rows[keep]
    o = np.argsort(q, kind="stable")
    bounds = np.searchsorted(q[o], np.arange(len(candidates) + 1))
    return [rows[o[bounds[t]:bounds[t + 1]]] for t in range(len(candidates))]


def suspect_views(n_views: int, candidates, keep) -> list:
    """The views whose pose looks off: ``[(view index, share kept, median share)]`` (module docstring, step 6).

    ``candidates`` and ``keep`` as :func:`verify_tracks` takes and returns them. Views with fewer than
    :data:`MIN_VIEW_CANDIDATES` candidates are not judged.

    >>> c = [(0, 1, np.zeros((100, 2), int), None), (1, 2, np.zeros((100, 2), int), None),
    ...      (0, 2, np.zeros((100, 2), int), None)]
    >>> keep = [np.arange(100) < 90, np.arange(100) < 5, np.arange(100) < 5]  # view 2 keeps 5 of 200
    >>> [(k, round(s, 3), round(m, 3)) for k, s, m in suspect_views(3, c, keep)]
    [(2, 0.05, 0.475)]
    """
    seen, kept = np.zeros(n_views), np.zeros(n_views)
    for (i, j, pairs, _), k in zip(candidates, keep):
        for v in (i, j):
            seen[v] += len(pairs)
            kept[v] += np.count_nonzero(k)
    judged = np.flatnonzero(seen >= MIN_VIEW_CANDIDATES)
    if len(judged) < 3:
        return []
    share = kept[judged] / seen[judged]
    median = float(np.median(share))
    return [(int(v), float(s), median) for v, s in zip(judged, share) if s < SUSPECT_FRACTION * median]
