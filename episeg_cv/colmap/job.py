"""The per-pair job: what a worker runs, and what it sends back to the one writer."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .. import threads
from ..matching import fused, guided, small
from ..matching.config import AcceptRule, SearchConfig
from ..matching.distances import Distances
from ..matching.filtering import keep_mask
from .store import FeatureStore
from .views import View, is_bounded

__all__ = ["PairJob", "PairResult", "image_rows", "match_pair", "match_pairs", "pair_inputs", "pinhole_count"]


@dataclass(frozen=True)
class PairJob:
    """Everything a worker needs to match one pair; small and picklable.

    ``search`` (its constraint and tol) and ``rule`` are as in
    :func:`~episeg_cv.match_descriptors`; each view's ``depth_range`` bounds its own segments.
    ``loose``: for the track consensus, the candidates with a ratio below it come back with
    their ratio values (None: the matches of ``rule``). ``samples``: queries whose search lengths
    are measured (0: none; a statistic, not used to match).
    """

    index: int
    view1: View
    view2: View
    store: FeatureStore
    search: SearchConfig = SearchConfig()
    rule: AcceptRule = AcceptRule()
    samples: int = 256
    loose: float | None = None


@dataclass(frozen=True)
class PairResult:
    """What a worker sends back to the writer.

    ``matches`` and ``inliers`` are ``(M, 2)`` uint32 keypoint indices
    ``(i1, i2)`` into the two images' stored keypoints. ``lengths`` holds the
    summed search lengths in image 2, in pixels, of up to ``PairJob.samples``
    queries: the epipolar line, the segment, and the segment within view 1's
    depth range (all clipped to the image); ``samples`` is their number.
    ``ratios`` (with ``PairJob.loose``): ``(K,)`` float64 ratio values of the inliers.
    """

    index: int
    matches: np.ndarray
    inliers: np.ndarray
    lengths: tuple
    samples: int
    ratios: np.ndarray | None = None


def pair_inputs(view1: View, view2: View, store: FeatureStore):
    """``(inputs, geometry, idx1, idx2)``: the checked :class:`~episeg_cv.matching.guided.MatchInputs`
    of a pair's keypoints that have a pinhole position, the geometry from ``view1`` to ``view2``, and the
    stored indices of the rows kept in each image (None: all of them)."""
    q1, d1, idx1 = _pinhole_rows(view1, store)
    q2, d2, idx2 = _pinhole_rows(view2, store)
    # the store's arrays were checked when they were read (finite, one row per keypoint, one dtype)
    return guided.MatchInputs(Distances(d1, d2, store.norm), q1, q2), view1.geometry_to(view2), idx1, idx2


def pinhole_count(view: View, store: FeatureStore) -> int:
    """How many keypoints of ``view`` have a pinhole position (the rows :func:`pair_inputs` keeps)."""
    q = store.load(view)[1]
    return len(q) if np.isfinite(q).all() else int((np.isfinite(q[:, 0]) & np.isfinite(q[:, 1])).sum())


def _pinhole_rows(view: View, store: FeatureStore):
    """``(points, descriptors, stored indices or None)`` of the keypoints of ``view`` that have a pinhole
    position (None: all of them)."""
    _, q, d = store.load(view)
    if np.isfinite(q).all():  # a flat test first: the row test costs 0.1 ms on 8k keypoints
        return q, d, None
    idx = np.flatnonzero(np.isfinite(q[:, 0]) & np.isfinite(q[:, 1]))
    return q[idx], d[idx], idx


def match_pair(job: PairJob) -> PairResult:
    """Match one pair on the segment (or line) and keep the inliers of both directions.

    The raw matches are :func:`~episeg_cv.match_descriptors` from view 1 to view 2 with
    view 1's depth range. The inliers are the raw matches that also satisfy
    the constraint from view 2 to view 1 (with view 2's depth range): a
    match must be consistent with both cameras' depth ranges. With
    ``job.loose``, the raw matches are those of ratio ``job.loose`` (same rule
    otherwise), and the inliers come back with their ratio values.
    Keypoints without a pinhole position (NaN) are not matched.

    On one kernel thread (:func:`episeg_cv.threads.get_num_threads`, as in the runner's workers), a
    pair that the small-pair path does not take is matched in one compiled call that holds no GIL
    (:func:`_fused`), so that a pool of threads is not held back by the Python between the stages:
    on the 24-view room the Python share of a pair's CPU time went from 20 % to 5 %
    (``benchmarks/_gil.py``). The results are the same bits (``tests/colmap/test_pair_kernel.py``).
    """
    inputs, g, idx1, idx2 = pair_inputs(job.view1, job.view2, job.store)
    q1, q2, dist = inputs.points1, inputs.points2, inputs.distances
    if _fusable(job, len(q1), len(q2)):
        return _fused(job, g, (q1, dist.a, idx1), (q2, dist.b, idx2))
    pairs, ratios, keep = _stages(job, inputs, g)
    return _result(job, g, q1, pairs, keep, ratios, idx1, idx2)


def _fusable(job: PairJob, n1: int, n2: int) -> bool:
    """Whether :func:`_fused` serves a pair of ``n1`` and ``n2`` keypoints: one kernel thread in this Python
    thread (a worker of the pool, or of Dask), a numeric band, and a pair too large for the small-pair
    path, which :func:`~episeg_cv.matching.guided.nearest` takes otherwise."""
    return (threads.get_num_threads() == 1 and job.search.constraint != "none" and job.search.auto is None
            and not small.fits(n1, n2, job.search, job.rule))


def _stages(job: PairJob, inputs, g):
    """``(pairs, ratios or None, keep)`` of :func:`match_pair`, stage by stage (each stage's kernels on
    the kernel threads): the raw matches, their ratios (with ``job.loose``), and which pass the
    reverse test."""
    q1, q2 = inputs.points1, inputs.points2
    search = job.search.replace(depth_range=job.view1.depth_range)
    ratios = None
    if job.loose is None:
        pairs, _ = guided.match(inputs, g, search, job.rule)
    else:
        rule = job.rule.replace(ratio=job.loose)
        i, j, r, mutual, _ = guided.nearest(inputs, g, search, rule, prefilter=True)
        keep = (r < job.loose) & (mutual if (rule.mutual or rule.cross_check) else True)
        pairs, ratios = np.column_stack([i[keep], j[keep]]).astype(np.intp), r[keep]
    keep = keep_mask(pairs[:, ::-1], q2, q1, g.inverse(), job.search.replace(depth_range=job.view2.depth_range))
    return pairs, ratios, keep


def _fused(job: PairJob, g, image1: tuple, image2: tuple) -> PairResult:
    """:func:`match_pair` in one compiled call on this thread, without the GIL
    (:func:`episeg_cv.matching.fused.match_pair`): the same result as :func:`_stages` gives.
    ``image1`` / ``image2``: ``(points, scoring rows, stored indices or None)`` (:func:`image_rows`)."""
    (q1, a1, idx1), (q2, a2, idx2) = image1, image2
    pairs, ratios, keep = fused.match_pair(q1, a1, q2, a2, job.store.norm, g, job.view1.depth_range,
                                           job.view2.depth_range, job.search, job.rule, job.loose)
    return _result(job, g, q1, pairs, keep, ratios if job.loose is not None else None, idx1, idx2)


def _result(job: PairJob, g, q1, pairs, keep, ratios, idx1, idx2) -> PairResult:
    """The pair's result: ``pairs`` (rows of the kept keypoints) as stored indices, and the search lengths."""
    sample = q1[:: max(1, len(q1) // max(job.samples, 1))][: job.samples]
    lengths = (0.0, 0.0, 0.0)
    if len(sample):
        full = g.segments(sample)
        ranged = g.segments(sample, job.view1.depth_range) if is_bounded(job.view1.depth_range) else full
        lengths = tuple(float(np.sum(x)) for x in (full.line_length, full.length, ranged.length))
    if idx1 is not None and len(pairs):
        pairs[:, 0] = idx1[pairs[:, 0]]
    if idx2 is not None and len(pairs):
        pairs[:, 1] = idx2[pairs[:, 1]]
    return PairResult(job.index, pairs.astype(np.uint32), pairs[keep].astype(np.uint32), lengths, len(sample),
                      None if ratios is None else ratios[keep].astype(np.float64))


def match_pairs(jobs: list) -> list:
    """:func:`match_pair` of every job, the same results in the same order. The small pairs
    (:func:`~episeg_cv.matching.small.fits`) are matched in one compiled call
    (:func:`~episeg_cv.matching.small.many`), on the kernels' threads (a pair per thread);
    the others one by one. The jobs share one store and one setting (as :func:`~.pipeline.match_model`
    makes them); otherwise all go one by one.

    A pair's Python (its inputs, its geometry, its result) took as long as its arithmetic on
    dinoSparseRing (about 0.2 ms each) and held the GIL: two threads matched pairs 1.07x as fast as one.
    Here the inputs are prepared once per image, and only the geometry and the result once per pair;
    the large pairs use them too when they are matched in one compiled call (:func:`match_pair`).
    """
    if not jobs:
        return []
    first = jobs[0]
    if not all(j.store is first.store and j.search == first.search and j.rule == first.rule
               and j.loose == first.loose for j in jobs):
        return [match_pair(j) for j in jobs]
    images = {}
    for job in jobs:
        for v in (job.view1, job.view2):
            if v.name not in images:
                images[v.name] = image_rows(v, first.store)
    small_ones = [small.fits(len(images[j.view1.name][0]), len(images[j.view2.name][0]), j.search, j.rule)
                  for j in jobs]
    batch = _match_batch([j for j, s in zip(jobs, small_ones) if s], images)
    out = {r.index: r for r in batch}
    out.update((j.index, _match_one(j, images)) for j, s in zip(jobs, small_ones) if not s)
    return [out[j.index] for j in jobs]


def _match_one(job: PairJob, images: dict) -> PairResult:
    """:func:`match_pair` of a large pair whose images' rows are loaded (:func:`image_rows`)."""
    image1, image2 = images[job.view1.name], images[job.view2.name]
    if _fusable(job, len(image1[0]), len(image2[0])):
        return _fused(job, job.view1.geometry_to(job.view2), image1, image2)
    return match_pair(job)


def image_rows(view: View, store: FeatureStore):
    """``(points, scoring rows, stored indices or None)`` of an image's keypoints with a pinhole position,
    as :func:`pair_inputs` keeps them."""
    q, d, idx = _pinhole_rows(view, store)
    return np.ascontiguousarray(q, dtype=np.float64), Distances(d, d[:0], store.norm).a, idx


def _match_batch(jobs: list, images: dict) -> list:
    if not jobs:
        return []
    job0 = jobs[0]
    geoms = [j.view1.geometry_to(j.view2) for j in jobs]
    items = [small.SmallPair(*images[j.view1.name][:2], *images[j.view2.name][:2], g, job0.search.tol,
                             j.view1.depth_range, j.view2.depth_range) for j, g in zip(jobs, geoms)]
    loose = job0.rule.ratio if job0.loose is None else job0.loose  # (the pair rule: its own ratio)
    found = small.many(items, job0.rule, loose, job0.store.norm,
                       lambda n2, n_pad: guided.padding_references(0, n2, n_pad))
    results = []
    for job, g, (i, j, r, inlier) in zip(jobs, geoms, found):
        pairs = np.column_stack([i, j]).astype(np.intp)
        results.append(_result(job, g, images[job.view1.name][0], pairs, inlier, r if job.loose is not None else None,
                               images[job.view1.name][2], images[job.view2.name][2]))
    return results
