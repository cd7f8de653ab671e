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
   gives the connected components (median 3 observations on the measured sets).
3. **Consensus groups, RANSAC-style.** In each component, up to ``max_seeds``
   (24) remaining edges, lowest ratio first, are triangulated from their two
   observations; the seed whose point reprojects within ``tau`` pixels (the
   matching ``tol``) of the most remaining observations (in front of the
   camera; per image only the closest) wins. Its observations are
   re-triangulated together, re-checked, and form a group, which leaves the
   component. Repeat until fewer than two observations remain. A seed set
   with no support is set aside and the next seeds are tried.
4. **Decision.** An edge is kept when both ends are in the same group and
   either its ratio is below the pair rule's (``strict``, 0.68) or the group
   spans at least ``min_views`` (3) images. A strict edge whose ends fall in
   different groups is dropped: a track contradicts it.

Components above ``max_component`` observations (repeated texture can chain
thousands) are split rather than left unverified: each seed is then tested
against the observations within ``hops`` edges of it, not the whole component.

Why RANSAC seeds and not a least-squares fit of each whole track: one false
edge that merges two true tracks makes the fit land between them, and the
true observations get dropped. Measured on the real dinoSparseRing collection
and two synthetic rooms (issue 14, ``benchmarks/colmap.py``), with the
collection defaults (``tol="auto"``, every mutual candidate an edge) it gives
15-38 % more accurate 3D points than the pair rule alone at 2 px with the same
features, at a higher accurate fraction (by 0.4-0.5 points).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from .. import threads
from .._validation import as_ratio
from . import _consensus_kernel

__all__ = ["TrackConsensus", "verify_tracks", "projection_matrices"]


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
        Images a group must span for its edges with a ratio between the pair
        rule's and ``loose`` to be kept. Default 3.
    tau : float or None
        Reprojection tolerance in pixels (of the pinhole image); None: the
        matching ``tol``. Default None.
    max_seeds : int >= 1
        Seeds tried per group. Default 24.
    max_component : int >= 2
        Above this many observations a component is verified locally
        (``hops``). Default 1000.
    hops : int >= 1
        Neighbourhood of a seed in a big component, in edges. Default 2.

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
    max_seeds: int = 24
    max_component: int = 1000
    hops: int = 2

    def __post_init__(self):
        object.__setattr__(self, "loose", as_ratio(self.loose, "loose"))
        for name, low in (("min_views", 2), ("max_seeds", 1), ("max_component", 2), ("hops", 1)):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < low:
                raise ValueError(f"{name} must be an integer >= {low}, got {v!r}")
            object.__setattr__(self, name, int(v))
        if self.tau is not None:
            ok = isinstance(self.tau, (int, float, np.integer, np.floating)) and not isinstance(self.tau, bool) \
                and np.isfinite(self.tau) and self.tau > 0
            if not ok:
                raise ValueError(f"tau must be a finite number > 0 or None, got {self.tau!r}")
            object.__setattr__(self, "tau", float(self.tau))

    def replace(self, **changes) -> "TrackConsensus":
        """A copy with some fields changed (and checked)."""
        return dataclasses.replace(self, **changes)


def projection_matrices(views) -> np.ndarray:
    """``(n, 3, 4)`` float64 ``K [R | t]`` of the views, in world coordinates moved and scaled so that the
    camera centres are centred at the origin with a median distance of 1 to it (better conditioned)."""
    centers = np.array([v.center for v in views], dtype=np.float64).reshape(-1, 3)
    c0 = centers.mean(axis=0)
    s = float(np.median(np.linalg.norm(centers - c0, axis=1))) if len(views) else 1.0
    if not (np.isfinite(s) and s > 0):
        s = 1.0
    M = np.eye(4)
    M[:3, :3] *= s
    M[:3, 3] = c0
    return np.array([v.K @ np.column_stack([v.R, v.t]) @ M for v in views]).reshape(-1, 3, 4)


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
        ``components``, ``groups``, ``big_components``, ``unsupported_seeds``,
        ``edges``, ``kept``.

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
    tau = float(config.tau if config.tau is not None else tau)
    sizes = [len(p) for _, _, p, _ in candidates]
    keep = [np.zeros(n, dtype=bool) for n in sizes]
    stats = {"components": 0, "groups": 0, "big_components": 0, "unsupported_seeds": 0, "edges": int(sum(sizes)),
             "kept": 0}
    if not sum(sizes):
        return keep, stats
    img_a = np.concatenate([np.full(n, i, np.int64) for (i, _, _, _), n in zip(candidates, sizes)])
    img_b = np.concatenate([np.full(n, j, np.int64) for (_, j, _, _), n in zip(candidates, sizes)])
    pairs = np.concatenate([np.asarray(p, dtype=np.int64).reshape(-1, 2) for _, _, p, _ in candidates])
    ratio = np.concatenate([np.asarray(r, dtype=np.float64).reshape(-1) for _, _, _, r in candidates])
    # observations: unique (image, keypoint), numbered 0 .. n-1
    keys = np.concatenate([(img_a << 32) | pairs[:, 0], (img_b << 32) | pairs[:, 1]])
    uniq, inverse = np.unique(keys, return_inverse=True)
    m = len(ratio)
    eu, ev = inverse[:m].astype(np.int64), inverse[m:].astype(np.int64)
    node_image = (uniq >> 32).astype(np.int64)
    node_kp = (uniq & 0xFFFFFFFF).astype(np.int64)
    node_xy = np.empty((len(uniq), 2), dtype=np.float64)
    for k in np.unique(node_image):
        sel = node_image == k
        node_xy[sel] = np.asarray(keypoints(int(k)), dtype=np.float64)[node_kp[sel]]
    P = projection_matrices(views)
    group, group_views, st = threads.run(
        _consensus_kernel.consensus, _consensus_kernel.consensus_parallel, m,
        P, node_image, node_xy, eu, ev, ratio, len(views), tau, config.max_seeds, config.max_component, config.hops)
    gu, gv = group[eu], group[ev]
    same = (gu >= 0) & (gu == gv)
    spans = np.zeros(m, dtype=np.int64)
    spans[same] = group_views[gu[same]]
    ok = same & ((ratio < strict) | (spans >= config.min_views))
    start = 0
    for q, n in enumerate(sizes):
        keep[q] = ok[start:start + n]
        start += n
    stats.update(components=int(st[0]), groups=int(st[1]), big_components=int(st[2]), unsupported_seeds=int(st[3]),
                 kept=int(ok.sum()))
    return keep, stats
