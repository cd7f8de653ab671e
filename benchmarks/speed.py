"""Speed of guided matching against ``cv2.BFMatcher``, FLANN, plain epipolar-line filtering and a segment-tree peer.

Usage::

    python benchmarks/speed.py [--quick] [--repeats N] [--threads 1,2] [--out DIR]

On synthetic renders of the pose suite (``episeg_cv.scenes.make_pair``) at 1600 x 1200, real SIFT
keypoints (the ``n`` strongest by response in each image, n = 2k, 5k, 10k, 20k) are matched by every
method below, all on the same keypoints and descriptors. Each method is timed end to end (geometry,
candidate gathering, distances, acceptance and the conversion to ``cv2.DMatch``), after a warm-up, as the
median of ``--repeats`` rounds; within each round every method runs once at every thread count
(``cv2.setNumThreads(n)`` and ``episeg_cv.set_num_threads(n)`` together), so that methods and thread
counts share the machine's load. Every time is reported as ``t_BF / t_method`` ("x faster than
BFMatcher"), with ``t_BF = cv2.BFMatcher(cv2.NORM_L2).knnMatch(k=2)`` at the same thread count. At
n = 10k there are at least 30 rounds, and ratios of two methods (line / segment, 1 / 2 threads) are
medians of per-round ratios with a paired bootstrap 95 % interval.

Then, on the first pose:

- the time of each stage of ``match`` at 10k (checks, segments, index, scan, acceptance, DMatch),
  against the arithmetic floor, at every thread count, and Amdahl's law for 16 cores (``_stages.py``);
- a race against the segment-tree matcher of "Pixel-Accurate Epipolar Guided Matching" (3DV 2026) at 5k,
  10k, 20k, 50k (a 2400 x 1800 render where 1600 x 1200 has too few keypoints): same keypoints, descriptors,
  pose, tol and threads; time, candidates per query and correct matches (``_peer.py``). The peer is
  imported from ``EPISEG_PEER_PATH``; where it is not available the benchmark says why, prints how to
  build it, and runs the rest;
- ORB (binary descriptors, ``NORM_HAMMING``) and ``filter`` on 100k matches.

``--quick`` runs one pose, n = 2k and 5k, the stage profile at 5k and the race at 2k and 5k.

Writes ``speed.md`` (tables and the issue's goals, evaluated from the numbers) and ``speed.json`` (every raw
timing and the machine metadata) into ``--out`` (default ``benchmarks/results``).
"""

from __future__ import annotations

import argparse
import functools
import gc
import json
import os
import shlex
import sys
import time
from pathlib import Path

import cv2
import numpy as np
from threadpoolctl import threadpool_info

sys.path.insert(0, str(Path(__file__).resolve().parent))
import _peer  # noqa: E402
import _stages  # noqa: E402
from _common import machine_metadata, package_dirty  # noqa: E402
from _speed_common import (BOOTSTRAP, FILTER_MATCHES, FLANN_INDEX, FLANN_SEARCH, GOAL_FLOOR,  # noqa: E402
                           GOAL_SCALING, GOAL_VS_LINE, GOAL_X, IMAGE_SIZE, METHODS, POSES, QUICK_POSES, QUICK_SIZES,
                           RACE_IMAGE_SIZE, RACE_SIZES, RATIO, REPEATS, RESULTS, SCRIPT, SIZES, TARGET_N,
                           TARGET_REPEATS, TOL)
from _speed_report import write_markdown  # noqa: E402
from _stages import set_threads  # noqa: E402

from episeg_cv import CandidateIndex, SegmentMatcher, filter_pairs, ground_truth_matches  # noqa: E402
from episeg_cv import knn_descriptors, match_descriptors, scenes  # noqa: E402

def progress(msg: str) -> None:
    print(f"[speed {time.strftime('%H:%M:%S')}] {msg}", file=sys.stderr, flush=True)


# ---------------------------------------------------------------------------------
# setup (never timed)
# ---------------------------------------------------------------------------------
def detect_sorted(image: np.ndarray):
    """All SIFT keypoints of ``image`` (contrastThreshold 0), strongest response first, with descriptors."""
    sift = cv2.SIFT_create(nfeatures=0, contrastThreshold=0.0)
    kp, des = sift.detectAndCompute(image, None)
    if des is None:
        return [], np.zeros((0, 128), np.float32)
    order = np.argsort([-k.response for k in kp], kind="stable")
    return [kp[i] for i in order], des[order]


def strongest(kp, des, n: int):
    """The ``n`` strongest keypoints: cv2.KeyPoint list, (n, 128) float32 descriptors, (n, 2) positions."""
    kp = list(kp[:n])
    des = np.ascontiguousarray(des[:n])
    pts = np.array([k.pt for k in kp], dtype=np.float64).reshape(-1, 2)
    return kp, des, pts


def _ratio(knn):
    return [m[0] for m in knn if len(m) == 2 and m[0].distance < RATIO * m[1].distance]


def make_methods(geometry, kp1, kp2, d1, d2, p1, p2) -> dict:
    """Zero-argument callables, one per method, over the same keypoints and descriptors."""
    bf = cv2.BFMatcher(cv2.NORM_L2)
    flann = cv2.FlannBasedMatcher(dict(FLANN_INDEX), dict(FLANN_SEARCH))
    seg = SegmentMatcher(geometry, cv2.NORM_L2, constraint="segment", tol=TOL)
    line = SegmentMatcher(geometry, cv2.NORM_L2, constraint="line", tol=TOL)

    return {
        "bf_knn": lambda: bf.knnMatch(d1, d2, k=2),
        "bf_ratio_line": lambda: line.filter(_ratio(bf.knnMatch(d1, d2, k=2)), kp1, kp2),
        "flann_ratio": lambda: _ratio(flann.knnMatch(d1, d2, k=2)),
        "segment_match": lambda: seg.match(d1, d2, kp1, kp2),
        "segment_knn": lambda: seg.knnMatch(d1, d2, kp1, kp2, k=2),
        "line_match": lambda: line.match(d1, d2, kp1, kp2),
        "line_knn": lambda: line.knnMatch(d1, d2, kp1, kp2, k=2),
        "segment_arrays": lambda: match_descriptors(d1, d2, p1, p2, geometry, norm="l2", tol=TOL,
                                                    constraint="segment")[0],
        "line_arrays": lambda: match_descriptors(d1, d2, p1, p2, geometry, norm="l2", tol=TOL,
                                                 constraint="line")[0],
    }


def _output_size(result) -> int:
    """Matches returned: pairs for match-like output, neighbours for knn lists."""
    if isinstance(result, np.ndarray):
        return int(len(result))
    return int(sum(len(r) if isinstance(r, (list, tuple)) else 1 for r in result))


def time_interleaved(methods: dict, repeats: int, thread_counts=(None,)) -> tuple[dict, dict]:
    """One warm-up call of each method at each thread count, then ``repeats`` rounds, each timing every method
    once at every thread count (so that the counts share the machine's load, round by round).

    Returns ``(times, outputs)``: ``times[n][name]`` seconds per round at ``n`` threads (``None``: as set).
    """
    outputs = {}
    for n in thread_counts:
        if n is not None:
            set_threads(n)
        outputs.update({name: _output_size(f()) for name, f in methods.items()})
    times = {n: {name: [] for name in methods} for n in thread_counts}
    for _ in range(repeats):
        for n in thread_counts:
            if n is not None:
                set_threads(n)
            for name, f in methods.items():
                gc.collect()
                t0 = time.perf_counter()
                f()
                times[n][name].append(time.perf_counter() - t0)
    return times, outputs


def ratio_interval(numerator, denominator, level: float = 0.95, seed: int = 0):
    """Median of the per-round ratios ``numerator[r] / denominator[r]`` and a paired bootstrap interval.

    The methods are interleaved in every round, so the two times of a round share the machine's load
    at that moment; resampling rounds (not single times) keeps that pairing. Returns
    ``(median, low, high)``, the interval being the percentile interval of the resampled medians.
    """
    r = np.asarray(numerator, float) / np.asarray(denominator, float)
    boot = np.median(r[np.random.default_rng(seed).integers(0, len(r), (BOOTSTRAP, len(r)))], axis=1)
    a = (1 - level) / 2
    return float(np.median(r)), float(np.quantile(boot, a)), float(np.quantile(boot, 1 - a))


def exponent(ns, ts):
    """Least-squares slope of log t against log n, or None with fewer than two sizes."""
    ns, ts = np.asarray(ns, float), np.asarray(ts, float)
    if len(ns) < 2 or len(np.unique(ns)) < 2:
        return None
    return float(np.polyfit(np.log(ns), np.log(ts), 1)[0])


# ---------------------------------------------------------------------------------
# runs
# ---------------------------------------------------------------------------------
@functools.lru_cache(maxsize=None)
def setup(name: str, image_size):
    """The rendered pair and its sorted SIFT keypoints and descriptors (cached per pose)."""
    t0 = time.perf_counter()
    pair = scenes.make_pair(name, image_size)
    progress(f"{name}: rendered {image_size[0]}x{image_size[1]} in {time.perf_counter() - t0:.1f} s")
    t0 = time.perf_counter()
    kp1_all, des1_all = detect_sorted(pair.image1)
    kp2_all, des2_all = detect_sorted(pair.image2)
    progress(f"{name}: SIFT found {len(kp1_all)} / {len(kp2_all)} keypoints in {time.perf_counter() - t0:.1f} s")
    return pair, kp1_all, des1_all, kp2_all, des2_all


def _medians(times: dict) -> dict:
    return {k: float(np.median(v)) for k, v in times.items()}


def run_pose(name: str, sizes, repeats: int, image_size, thread_counts) -> dict:
    pair, kp1_all, des1_all, kp2_all, des2_all = setup(name, image_size)
    geometry = pair.geometry
    e = geometry.epipole_homogeneous
    out = {
        "description": scenes.pose_suite()[name].description,
        "epipole_homogeneous": np.asarray(e, float).tolist(),
        "keypoints_detected": [len(kp1_all), len(kp2_all)],
        "sizes": {},
    }
    for n in sizes:
        kp1, d1, p1 = strongest(kp1_all, des1_all, n)
        kp2, d2, p2 = strongest(kp2_all, des2_all, n)
        if len(kp1) < n or len(kp2) < n:
            progress(f"{name}: only {len(kp1)} / {len(kp2)} keypoints for n = {n}")
        cands = {c: float(CandidateIndex(geometry, p1, p2, tol=TOL, constraint=c).candidate_counts().mean())
                 if len(p1) and len(p2) else 0.0 for c in ("segment", "line")}
        methods = make_methods(geometry, kp1, kp2, d1, d2, p1, p2)
        t0 = time.perf_counter()
        times, outputs = time_interleaved(methods, max(repeats, TARGET_REPEATS) if n == TARGET_N else repeats,
                                          thread_counts)
        by = {}
        for nt in thread_counts:
            med = _medians(times[nt])
            by[str(nt)] = {"times_s": times[nt], "median_s": med,
                           "x_faster_than_bf": {k: med["bf_knn"] / v for k, v in med.items()}}
        out["sizes"][str(n)] = {"n_requested": n, "n1": len(kp1), "n2": len(kp2),
                                "candidates_per_query": {**cands, "none": float(len(kp2))},
                                "threads": by, "output_size": outputs}
        top = by[str(thread_counts[-1])]
        progress(f"{name} n={n}: {time.perf_counter() - t0:.1f} s; at {thread_counts[-1]} threads BF "
                 f"{1e3 * top['median_s']['bf_knn']:.0f} ms; segment match {top['x_faster_than_bf']['segment_match']:.1f}x, "
                 f"knn {top['x_faster_than_bf']['segment_knn']:.1f}x; line match "
                 f"{top['x_faster_than_bf']['line_match']:.1f}x; candidates/query segment {cands['segment']:.1f}, "
                 f"line {cands['line']:.1f}")
    ns = [0.5 * (s["n1"] + s["n2"]) for s in out["sizes"].values()]
    top = str(thread_counts[-1])
    out["exponent"] = {k: exponent(ns, [s["threads"][top]["median_s"][k] for s in out["sizes"].values()]) for k in METHODS}
    return out


def run_stages(pose: str, n: int, repeats: int, image_size, thread_counts) -> dict:
    """The stage profile of ``match`` at ``n`` (segment and line), the floor and the Amdahl estimate."""
    pair, kp1_all, des1_all, kp2_all, des2_all = setup(pose, image_size)
    kp1, d1, p1 = strongest(kp1_all, des1_all, n)
    kp2, d2, p2 = strongest(kp2_all, des2_all, n)
    out = {"pose": pose, "n1": len(p1), "n2": len(p2), "constraints": {}}
    for c in ("segment", "line"):
        t0 = time.perf_counter()
        r = _stages.profile(pair.geometry, kp1, kp2, d1, d2, p1, p2, c, TOL, thread_counts, repeats)
        out["constraints"][c] = r
        one = r["by_threads"][str(thread_counts[0])]
        progress(f"stages {pose} n={n} {c}: core {1e3 * one['core_cpu_s']:.1f} ms CPU at {thread_counts[0]} thread(s), "
                 f"floor {1e3 * r['floor']['time_s']:.2f} ms ({r['floor']['rate_mac_per_s'] / 1e9:.1f} G MAC/s); "
                 f"{time.perf_counter() - t0:.0f} s")
    return out


def _race_data(pose: str, n: int, image_size):
    """Keypoints for the race: the run's render, or the larger one where it has fewer than n keypoints."""
    data = setup(pose, image_size)
    if min(len(data[1]), len(data[3])) < n and tuple(image_size) == IMAGE_SIZE:
        data = setup(pose, RACE_IMAGE_SIZE)
    return data


def run_race(pose: str, sizes, repeats: int, image_size, thread_counts) -> dict:
    """Ours (knn_descriptors k=2 + ratio) against the peer (tree / hash candidates + the same nearest-two and ratio)."""
    module = _peer.load()
    out = {"pose": pose, "available": module is not None, "why_unavailable": _peer.why_unavailable(),
           "ratio": RATIO, "tol": TOL, "sizes": {}}
    if module is None:
        progress(f"race: the segment-tree peer is not available ({out['why_unavailable']}); racing ours alone.\n"
                 + _peer.RECIPE)
    for n in sizes:
        pair, kp1_all, des1_all, kp2_all, des2_all = _race_data(pose, n, image_size)
        _, d1, p1 = strongest(kp1_all, des1_all, n)
        _, d2, p2 = strongest(kp2_all, des2_all, n)
        g = pair.geometry
        F = g.fundamental_matrix
        gt = ground_truth_matches(p1, p2, pair.depth1, pair.depth2, pair.geometry_true)
        stats = {}

        def ours(c):
            def f():
                nb = knn_descriptors(d1, d2, p1, p2, g, k=2, tol=TOL, constraint=c)
                return _peer.ratio_test(nb.indices, nb.distances * nb.distances, RATIO)  # the same rule as the peer's
            return f

        def theirs(method):
            def f():
                st = {}
                res = _peer.match(d1, d2, p1, p2, F, TOL, RATIO, method, parallel=_peer_threads[0] > 1, timings=st)
                stats.setdefault(method, []).append(st)
                return res
            return f

        methods = {"ours segment": ours("segment"), "ours line": ours("line")}
        if module is not None:
            methods.update({"peer tree": theirs("tree"), "peer hash": theirs("hash")})
        cand = {"ours segment": float(CandidateIndex(g, p1, p2, tol=TOL).candidate_counts().mean()),
                "ours line": float(CandidateIndex(g, p1, p2, tol=TOL, constraint="line").candidate_counts().mean())}
        by = {}
        for nt in thread_counts:  # thread counts in turn: the peer's OpenMP limit is a context
            _peer_threads[0] = nt
            stats.clear()
            set_threads(nt)
            with _peer.openmp_limit(nt):
                results = {k: f() for k, f in methods.items()}  # warm-up
                stats.clear()
                times, cpu = {k: [] for k in methods}, {k: [] for k in methods}
                for _ in range(repeats):
                    for k, f in methods.items():
                        gc.collect()
                        t0, c0 = time.perf_counter(), time.thread_time()
                        f()
                        times[k].append(time.perf_counter() - t0)
                        cpu[k].append(time.thread_time() - c0)
            row = {}
            for k in methods:
                pairs = results[k][0]
                row[k] = {"median_s": float(np.median(times[k])), "median_cpu_s": float(np.median(cpu[k])),
                          "times_s": times[k], "matches": int(len(pairs)),
                          "correct": int(gt.is_correct(pairs).sum()) if len(pairs) else 0}
            for method, st in stats.items():
                cand[f"peer {method}"] = st[0]["candidates"] / max(len(p1), 1)
                row[f"peer {method}"]["stages_s"] = {x: float(np.median([s[x] for s in st]))
                                                     for x in ("peer", "peer_cpp", "csr", "knn", "ratio")}
            by[str(nt)] = row
        out["sizes"][str(n)] = {"n1": len(p1), "n2": len(p2), "image_size": list(pair.geometry.image_size1),
                                "candidates_per_query": cand, "threads": by}
        top = by[str(thread_counts[-1])]
        progress(f"race {pose} n={n}: " + ", ".join(f"{k} {1e3 * v['median_s']:.1f} ms ({v['correct']} correct)"
                                                     for k, v in top.items()))
    return out


_peer_threads = [1]


def run_filter(repeats: int, image_size, pose: str, n: int = TARGET_N, n_matches: int = FILTER_MATCHES) -> dict:
    """``SegmentMatcher.filter`` and ``filter_pairs`` on ``n_matches`` random index pairs."""
    pair, kp1_all, des1_all, kp2_all, des2_all = setup(pose, image_size)
    kp1, _, p1 = strongest(kp1_all, des1_all, n)
    kp2, _, p2 = strongest(kp2_all, des2_all, n)
    rng = np.random.default_rng(0)
    pairs = np.column_stack([rng.integers(0, len(p1), n_matches), rng.integers(0, len(p2), n_matches)])
    dmatches = [cv2.DMatch(int(i), int(j), 0, 1.0) for i, j in pairs]
    g = pair.geometry
    methods = {}
    for c in ("segment", "line"):
        m = SegmentMatcher(g, cv2.NORM_L2, constraint=c, tol=TOL)
        methods[f"SegmentMatcher.filter {c}"] = (lambda m=m: m.filter(dmatches, kp1, kp2))
        methods[f"filter_pairs {c}"] = (lambda c=c: filter_pairs(pairs, p1, p2, g, tol=TOL, constraint=c))
    times, _ = time_interleaved(methods, repeats)
    times = times[None]
    kept = {c: int(filter_pairs(pairs, p1, p2, g, tol=TOL, constraint=c).sum()) for c in ("segment", "line")}
    med = {k: float(np.median(v)) for k, v in times.items()}
    progress("filter on {} matches: ".format(n_matches) + ", ".join(f"{k} {1e3 * v:.1f} ms" for k, v in med.items()))
    return {"pose": pose, "n1": len(p1), "n2": len(p2), "matches": n_matches, "kept": kept,
            "times_s": times, "median_s": med}


def run_binary(repeats: int, image_size, pose: str, n: int = TARGET_N) -> dict:
    """ORB (binary descriptors, NORM_HAMMING): BFMatcher against the segment and the line, at ``n`` keypoints."""
    pair = setup(pose, image_size)[0]
    orb = cv2.ORB_create(nfeatures=n)
    (kp1, d1), (kp2, d2) = (orb.detectAndCompute(im, None) for im in (pair.image1, pair.image2))
    bf = cv2.BFMatcher(cv2.NORM_HAMMING)
    methods = {"BFMatcher knnMatch(k=2) (reference)": lambda: bf.knnMatch(d1, d2, k=2)}
    for c in ("segment", "line"):
        m = SegmentMatcher(pair.geometry, cv2.NORM_HAMMING, constraint=c, tol=TOL)
        methods[f"SegmentMatcher {c}: match"] = lambda m=m: m.match(d1, d2, kp1, kp2)
        methods[f"SegmentMatcher {c}: knnMatch(k=2)"] = lambda m=m: m.knnMatch(d1, d2, kp1, kp2, k=2)
    times, outputs = time_interleaved(methods, max(repeats, TARGET_REPEATS) if n == TARGET_N else repeats)
    times = times[None]
    med = {k: float(np.median(v)) for k, v in times.items()}
    bf_t = med["BFMatcher knnMatch(k=2) (reference)"]
    line_vs_segment = {what: ratio_interval(times[f"SegmentMatcher line: {what}"], times[f"SegmentMatcher segment: {what}"])
                       for what in ("match", "knnMatch(k=2)")}
    progress(f"ORB n={n}: " + ", ".join(f"{k} {bf_t / v:.1f}x" for k, v in med.items()))
    return {"pose": pose, "n1": len(kp1), "n2": len(kp2), "times_s": times, "median_s": med,
            "x_faster_than_bf": {k: bf_t / v for k, v in med.items()}, "output_size": outputs,
            "line_vs_segment": line_vs_segment}


# ---------------------------------------------------------------------------------
# the goals
# ---------------------------------------------------------------------------------
def pose_goals(poses: dict) -> dict:
    """Per pose, at n = TARGET_N: x faster than BFMatcher and line / segment at each thread count, and the
    scaling from 1 to 2 threads (medians of per-round ratios with paired bootstrap intervals). None without
    that size."""
    out = {}
    for name, r in poses.items():
        s = r["sizes"].get(str(TARGET_N))
        if s is None:
            out[name] = None
            continue
        g = {"by_threads": {}, "scaling": None}
        for nt, t in s["threads"].items():
            x, times = t["x_faster_than_bf"], t["times_s"]
            row = {"segment_match_x": x["segment_match"], "segment_knn_x": x["segment_knn"],
                   "rounds": len(times["segment_match"]),
                   "segment_match_vs_line": ratio_interval(times["line_match"], times["segment_match"]),
                   "segment_knn_vs_line": ratio_interval(times["line_knn"], times["segment_knn"])}
            row["met_x"] = bool(x["segment_match"] >= GOAL_X and x["segment_knn"] >= GOAL_X)
            row["met_vs_line"] = bool(row["segment_match_vs_line"][0] >= GOAL_VS_LINE
                                      and row["segment_knn_vs_line"][0] >= GOAL_VS_LINE)
            g["by_threads"][nt] = row
        if "1" in s["threads"] and "2" in s["threads"]:
            one, two = s["threads"]["1"]["times_s"], s["threads"]["2"]["times_s"]
            sc = {k: ratio_interval(one[k], two[k]) for k in METHODS}
            g["scaling"] = {"per_method": sc,
                            "met": bool(sc["segment_match"][0] >= GOAL_SCALING and sc["segment_knn"][0] >= GOAL_SCALING)}
        out[name] = g
    return out


def floor_goal(stages: dict | None) -> dict | None:
    """Core work of match (everything but the cv2 objects) over the floor, at one thread (CPU-time medians)."""
    if not stages:
        return None
    out = {"n": stages["n1"]}
    for c, r in stages["constraints"].items():
        one = r["by_threads"].get("1")
        if one is None:
            return None
        x = one["core_cpu_s"] / r["floor"]["time_s"]
        out[c] = {"core_s": one["core_cpu_s"], "floor_s": r["floor"]["time_s"], "x": x, "met": bool(x <= GOAL_FLOOR)}
    out["met"] = all(v["met"] for k, v in out.items() if isinstance(v, dict))
    return out


def race_goal(race: dict | None) -> dict | None:
    """Per size, thread count and peer method: is ours faster, with at least as many correct matches?"""
    if not race or not race["available"]:
        return None
    out = {"by_size": {}}
    for n, s in race["sizes"].items():
        for nt, row in s["threads"].items():
            for m in ("peer tree", "peer hash"):
                if m not in row:
                    continue
                p = row[m]
                cmp = {}
                for ours in ("ours segment", "ours line"):
                    o = row[ours]
                    cmp[ours] = {"x_faster": p["median_s"] / o["median_s"], "correct_diff": o["correct"] - p["correct"],
                                 "met": bool(o["median_s"] < p["median_s"] and o["correct"] >= p["correct"])}
                cmp["met"] = cmp["ours segment"]["met"] or cmp["ours line"]["met"]
                out["by_size"].setdefault(n, {}).setdefault(nt, {})[m] = cmp
    out["met"] = all(c["met"] for by_nt in out["by_size"].values() for by_m in by_nt.values() for c in by_m.values())
    return out


def amdahl_methods(poses: dict, n: int) -> dict:
    """Per pose and method, at size ``n``: Amdahl's parallel fraction from the 1- and 2-thread medians, and the
    time and x-faster-than-BFMatcher extrapolated to 16 cores."""
    out = {}
    for name, r in poses.items():
        s = r["sizes"].get(str(n))
        if s is None or "1" not in s["threads"] or "2" not in s["threads"]:
            continue
        one, two = s["threads"]["1"]["median_s"], s["threads"]["2"]["median_s"]
        rows = {}
        for k in METHODS:
            p = _stages.parallel_fraction(one[k], two[k])
            rows[k] = {"p": p, "t1_s": one[k], "t2_s": two[k], "t16_s": _stages.on_cores(one[k], p)}
        for k in METHODS:
            rows[k]["x_faster_than_bf_16"] = rows["bf_knn"]["t16_s"] / rows[k]["t16_s"]
        out[name] = rows
    return out


# ---------------------------------------------------------------------------------
# output
# ---------------------------------------------------------------------------------
def _image_size(text: str):
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected WIDTHxHEIGHT, got {text!r}") from None
    return w, h


def _sizes(text: str):
    try:
        out = tuple(int(v) for v in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected comma-separated integers, got {text!r}") from None
    if not out or min(out) < 1:
        raise argparse.ArgumentTypeError(f"sizes must be positive, got {text!r}")
    return out


def _threads(text: str):
    try:
        out = tuple(int(v) for v in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected comma-separated thread counts, got {text!r}") from None
    if not out or min(out) < 1:
        raise argparse.ArgumentTypeError(f"thread counts must be >= 1, got {text!r}")
    return tuple(sorted(set(out)))


def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--quick", action="store_true", help="one pose (forward), n = 2k and 5k")
    p.add_argument("--repeats", type=int, default=REPEATS, help=f"timed rounds per method (default {REPEATS})")
    p.add_argument("--threads", type=_threads, default=None,
                   help="thread counts to compare (default 1,2; 1 on a one-core machine)")
    p.add_argument("--out", type=Path, default=None,
                   help="output directory (default benchmarks/results; benchmarks/results/quick with --quick)")
    # for the smoke test and experiments
    p.add_argument("--sizes", type=_sizes, default=None, help=argparse.SUPPRESS)
    p.add_argument("--race-sizes", type=_sizes, default=None, help=argparse.SUPPRESS)
    p.add_argument("--poses", type=lambda s: tuple(s.split(",")), default=None, help=argparse.SUPPRESS)
    p.add_argument("--image-size", type=_image_size, default=IMAGE_SIZE, help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.repeats < 1:
        p.error(f"--repeats must be >= 1, got {args.repeats}")
    return args


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    args = parse_args(argv)
    sizes = args.sizes or (QUICK_SIZES if args.quick else SIZES)
    poses = args.poses or (QUICK_POSES if args.quick else POSES)
    race_sizes = args.race_sizes or (sizes if args.quick or args.sizes else RACE_SIZES)
    thread_counts = args.threads or ((1, 2) if (os.cpu_count() or 1) >= 2 else (1,))
    stage_n = min(TARGET_N, max(sizes))
    command = " ".join(["python", SCRIPT] + [shlex.quote(a) for a in argv])
    load0 = os.getloadavg()[0]
    meta = machine_metadata()  # at the start: the commit of the code that runs
    meta["episeg_cv_uncommitted_changes"] = package_dirty()
    t_start = time.perf_counter()
    progress(f"{command}: poses {', '.join(poses)}; sizes {', '.join(map(str, sizes))}; threads "
             f"{', '.join(map(str, thread_counts))}; repeats {args.repeats}")
    results = {name: run_pose(name, sizes, args.repeats, args.image_size, thread_counts) for name in poses}
    stages = run_stages(poses[0], stage_n, max(args.repeats, 21 if stage_n == TARGET_N else args.repeats),
                        args.image_size, thread_counts)
    race = run_race(poses[0], race_sizes, args.repeats, args.image_size, thread_counts)
    set_threads(thread_counts[-1])
    filt = run_filter(args.repeats, args.image_size, poses[0], n=min(TARGET_N, max(sizes)))
    binary = run_binary(args.repeats, args.image_size, poses[0], n=min(TARGET_N, max(sizes)))
    blas = [{k: i.get(k) for k in ("internal_api", "num_threads", "version")} for i in threadpool_info()
            if i.get("user_api") == "blas"]
    res = {
        "command": command,
        "machine": meta,
        "load_average": [load0, os.getloadavg()[0]],
        "threads": {"counts": list(thread_counts), "blas": ", ".join(sorted({f"{b['internal_api']} {b['num_threads']}"
                                                                              for b in blas})) or "none",
                    "blas_info": blas},
        "config": {"image_size": list(args.image_size), "sizes": list(sizes), "poses": list(poses),
                   "threads": list(thread_counts), "repeats": args.repeats, "warmup": 1, "statistic": "median",
                   "ratio": RATIO, "tol": TOL, "race_sizes": list(race_sizes), "stage_n": stage_n,
                   "sift": {"nfeatures": 0, "contrastThreshold": 0.0, "keep": "n strongest by response"},
                   "flann": {"index": FLANN_INDEX, "search": FLANN_SEARCH},
                   "methods": {k: v[1] for k, v in METHODS.items()}},
        "poses": results,
        "stages": stages,
        "race": race,
        "filter": filt,
        "binary": binary,
    }
    amdahl_n = TARGET_N if any(str(TARGET_N) in r["sizes"] for r in results.values()) else max(sizes)
    res["amdahl_n"] = amdahl_n
    res["amdahl"] = amdahl_methods(results, amdahl_n)
    res["goals"] = {"poses": pose_goals(results), "floor": floor_goal(stages), "race": race_goal(race)}
    res["wall_time_s"] = time.perf_counter() - t_start
    args.out = args.out or (RESULTS / "quick" if args.quick else RESULTS)  # --quick never overwrites the full run
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "speed.json").write_text(json.dumps(res, indent=2) + "\n")
    write_markdown(args.out / "speed.md", res)
    progress(f"wrote {args.out / 'speed.md'} and speed.json in {res['wall_time_s']:.0f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
