"""Stages of one ``match`` at n keypoints, the arithmetic floor, and Amdahl's law (for ``benchmarks/speed.py``).

Every stage is timed by calling the library's own pieces, in the order ``match`` calls them, through
public (non-underscore) names; a stage that has no call of its own is the difference of two calls:

- checks: ``MatchInputs.check`` (validation of the four arrays, once per call);
- segments: ``geometry.segments(points1, margin=tol)`` (and the clipped lines for ``"line"``);
- index: ``CandidateIndex(...)`` minus the segments;
- scan: ``CandidateIndex.scan`` on a built index (the exact test, the scores, top-2 and the best query of
  each keypoint);
- acceptance: ``guided.match`` on a built index minus the scan (padding references, ratio, mutual check,
  the exact distances of the kept pairs);
- DMatch: ``SegmentMatcher.match`` minus ``match_descriptors`` on the same built index minus the keypoint
  conversion (``keypoints_to_array``): the ``cv2.DMatch`` objects; the same for ``knnMatch`` (one list per
  query).

The floor is the time to score exactly the candidate pairs once, each keypoint's descriptor already laid out
next to the previous one (the scan's best case: contiguous rows), by a compiled float32 squared-L2 loop on
one thread. Its rate, candidates x dimensions / time, is reported with it.
"""

from __future__ import annotations

import gc
import time

import cv2
import numba as nb
import numpy as np

import episeg_cv
from episeg_cv import CandidateIndex, SearchConfig, SegmentMatcher, keypoints_to_array, knn_descriptors
from episeg_cv import match_descriptors
from episeg_cv.matching import guided

from _peer import l2sqr  # the same compiled score as the peer race's (benchmarks/ is on sys.path)

#: The method, for the report.
DESCRIPTION = """\
Each stage is timed by calling the library's own pieces in the order `match` calls them (public names only);
a stage without a call of its own is the difference of two calls:

- **checks**: `MatchInputs.check` (validation of the four arrays);
- **segments**: `geometry.segments(points1, margin=tol)` (and the clipped lines for `"line"`);
- **index**: `CandidateIndex(...)` minus the segments;
- **scan**: `CandidateIndex.scan` on a built index (exact test, scores, top-2, best query per keypoint);
- **acceptance**: `guided.match` on a built index minus the scan (padding references, ratio, mutual check, exact
  distances of the kept pairs);
- **DMatch**: `SegmentMatcher.match` minus `match_descriptors` (both on the built index) minus the keypoint
  conversion `keypoints_to_array`: the `cv2.DMatch` objects, the only cv2 cost; the same for `knnMatch` (one
  list per query).

**The floor** is the time to score exactly the candidate pairs once, each pair's keypoint descriptor already laid
out after the previous one (the scan's best case: contiguous rows), by a compiled float32 squared-L2 loop on one
thread (CPU-time median). Its rate, candidates x dimensions / time, is the machine's rate for this arithmetic
from memory; the core work of `match` is compared with it."""

STAGES = ("checks", "segments", "index", "scan", "acceptance", "DMatch (match)", "DMatch (knnMatch)")
#: The stages of the "core work" of match (everything but the cv2 objects).
CORE = ("checks", "segments", "index", "scan", "acceptance")
CORES = 16


def set_threads(n: int) -> None:
    """The same thread count for every library of the benchmark: OpenCV and episeg_cv."""
    cv2.setNumThreads(int(n))
    episeg_cv.set_num_threads(int(n))


@nb.njit(cache=True)
def _score_pairs(A, qi, Bc):
    """Sum of the scores of query ``qi[m]`` against row ``m`` of ``Bc`` (the pairs' keypoint rows in order)."""
    acc = np.float32(0.0)
    for m in range(qi.shape[0]):
        acc += l2sqr(A, qi[m], Bc, m)
    return acc


def floor(geometry, p1, p2, d1, d2, search: SearchConfig, repeats: int) -> dict:
    """Time (median of the calling thread's CPU time) to score each candidate pair once from contiguous rows."""
    pairs = CandidateIndex(geometry, p1, p2, search=search).pairs()
    A = np.ascontiguousarray(d1, dtype=np.float32)
    qi = np.ascontiguousarray(pairs[:, 0], dtype=np.int64)
    Bc = np.ascontiguousarray(np.asarray(d2, dtype=np.float32)[pairs[:, 1]])
    _score_pairs(A, qi, Bc)
    ts = []
    for _ in range(max(repeats, 5)):
        t0 = time.thread_time()
        _score_pairs(A, qi, Bc)
        ts.append(time.thread_time() - t0)
    t = float(np.median(ts))
    macs = len(pairs) * A.shape[1]
    return {"candidates": int(len(pairs)), "dimensions": int(A.shape[1]), "time_s": t,
            "rate_mac_per_s": macs / t if t > 0 else float("inf")}


def calls(geometry, kp1, kp2, d1, d2, p1, p2, search: SearchConfig) -> dict:
    """The zero-argument calls the stages are computed from (the built index is shared by the '_on_index' ones)."""
    rule = episeg_cv.AcceptRule()
    inputs = guided.MatchInputs.check(d1, d2, p1, p2, "l2")
    dist = inputs.distances
    index = CandidateIndex(geometry, p1, p2, search=search)
    n1, n2 = len(p1), len(p2)
    m = SegmentMatcher(geometry, cv2.NORM_L2, search=search)
    line = search.constraint == "line"

    def segments():
        s = geometry.segments(p1, search.depth_range, margin=search.tol)
        return s.line_start if line else s

    def scan():
        idx = np.full((n1, 2), -1, dtype=np.intp)
        sc = np.full((n1, 2), np.inf, dtype=np.float32)
        counts = np.zeros(n1, dtype=np.intp)
        col_s = np.full(n2, np.inf, dtype=np.float32)
        col_i = np.full(n2, -1, dtype=np.intp)
        index.scan(dist.a, dist.b, dist.code, idx, sc, counts, col_s, col_i)

    return {
        "checks": lambda: guided.MatchInputs.check(d1, d2, p1, p2, "l2"),
        "segments": segments,
        "index_with_segments": lambda: CandidateIndex(geometry, p1, p2, search=search),
        "scan": scan,
        "match_on_index": lambda: guided.match(inputs, geometry, search, rule, index=index),
        "match_descriptors": lambda: match_descriptors(d1, d2, p1, p2, geometry, search=search),
        "match_descriptors_on_index": lambda: match_descriptors(d1, d2, p1, p2, geometry, search=search, index=index),
        "SegmentMatcher.match_on_index": lambda: m.match(d1, d2, kp1, kp2, index=index),
        "keypoints_to_array": lambda: (keypoints_to_array(kp1), keypoints_to_array(kp2)),
        "knn_descriptors_on_index": lambda: knn_descriptors(d1, d2, p1, p2, geometry, k=2, search=search, index=index),
        "SegmentMatcher.knnMatch_on_index": lambda: m.knnMatch(d1, d2, kp1, kp2, k=2, index=index),
        "SegmentMatcher.match": lambda: m.match(d1, d2, kp1, kp2),
    }


def stages_of(med: dict) -> dict:
    """Stage times from the medians of :func:`calls` (differences may dip below 0 by noise: kept as measured)."""
    return {
        "checks": med["checks"],
        "segments": med["segments"],
        "index": med["index_with_segments"] - med["segments"],
        "scan": med["scan"],
        "acceptance": med["match_on_index"] - med["scan"],
        "DMatch (match)": med["SegmentMatcher.match_on_index"] - med["match_descriptors_on_index"]
        - med["keypoints_to_array"],
        "DMatch (knnMatch)": med["SegmentMatcher.knnMatch_on_index"] - med["knn_descriptors_on_index"]
        - med["keypoints_to_array"],
    }


def profile(geometry, kp1, kp2, d1, d2, p1, p2, constraint: str, tol: float, thread_counts, repeats: int) -> dict:
    """Medians (wall, and the calling thread's CPU) of every call at every thread count, interleaved per round;
    the stages, the floor (one thread) and the Amdahl estimate for :data:`CORES` cores."""
    search = SearchConfig(tol=tol, constraint=constraint)
    fns = calls(geometry, kp1, kp2, d1, d2, p1, p2, search)
    wall = {n: {k: [] for k in fns} for n in thread_counts}
    cpu = {n: {k: [] for k in fns} for n in thread_counts}
    for n in thread_counts:  # warm-up at every count
        set_threads(n)
        for f in fns.values():
            f()
    for _ in range(repeats):
        for n in thread_counts:
            set_threads(n)
            for k, f in fns.items():
                gc.collect()
                t0, c0 = time.perf_counter(), time.thread_time()
                f()
                wall[n][k].append(time.perf_counter() - t0)
                cpu[n][k].append(time.thread_time() - c0)
    out = {"constraint": constraint, "repeats": repeats, "by_threads": {}}
    for n in thread_counts:
        mw = {k: float(np.median(v)) for k, v in wall[n].items()}
        mc = {k: float(np.median(v)) for k, v in cpu[n].items()}
        out["by_threads"][str(n)] = {"median_wall_s": mw, "median_cpu_s": mc, "stages_wall_s": stages_of(mw),
                                     "stages_cpu_s": stages_of(mc), "core_wall_s": mw["match_descriptors"],
                                     "core_cpu_s": mc["match_descriptors"]}
    out["floor"] = floor(geometry, p1, p2, d1, d2, search, repeats)
    if 1 in thread_counts and 2 in thread_counts:
        out["amdahl"] = amdahl_stages(out["by_threads"]["1"]["stages_wall_s"], out["by_threads"]["2"]["stages_wall_s"])
    return out


def parallel_fraction(t1: float, t2: float) -> float:
    """Amdahl's parallel fraction ``p`` from the times on one and two threads: ``t2 = t1 (1 - p + p / 2)``,
    clipped to [0, 1]."""
    if not t1 > 0:
        return 0.0
    return float(min(max(2.0 * (1.0 - t2 / t1), 0.0), 1.0))


def on_cores(t1: float, p: float, cores: int = CORES) -> float:
    """Amdahl's time on ``cores`` cores."""
    return t1 * ((1.0 - p) + p / cores)


def amdahl_stages(one: dict, two: dict, cores: int = CORES) -> dict:
    """Per stage: ``p`` from the measured 1- and 2-thread times, and the time extrapolated to ``cores``."""
    out = {}
    for s in STAGES:
        t1 = max(one[s], 0.0)
        p = 0.0 if s.startswith("DMatch") else parallel_fraction(t1, max(two[s], 0.0))  # Python objects: serial
        out[s] = {"p": p, "t1_s": t1, "t2_s": max(two[s], 0.0), f"t{cores}_s": on_cores(t1, p, cores)}
    return out
