"""The markdown of ``benchmarks/speed.py`` (``speed.md``), from its results dictionary."""

from __future__ import annotations

from pathlib import Path

import _peer
import _stages
from _speed_common import (GOAL_FLOOR, GOAL_SCALING, GOAL_VS_LINE, GOAL_X, METHODS, RATIO, TARGET_N, TARGET_REPEATS, TOL,
                           dirty_note, fmt_ci, fmt_ms, fmt_signed_ms, fmt_x, kilo, yes)


def write_markdown(path: Path, res: dict) -> None:
    meta, cfg = res["machine"], res["config"]
    tcs = [str(n) for n in cfg["threads"]]
    L = ["# Speed: guided matching against cv2.BFMatcher, FLANN, the line and a segment-tree peer\n"]
    L.append(f"Made by `{res['command']}` on {meta['date']} ({meta['cpu']}, {meta['cpu_count']} cores, "
             f"python {meta['python']}, numpy {meta['numpy']}, cv2 {meta['cv2']}, episeg_cv {meta['episeg_cv']}, "
             f"git HEAD {meta['git_commit']} at the start{dirty_note(meta)}). Load average (1 min) "
             f"{res['load_average'][0]:.2f} at the start, {res['load_average'][1]:.2f} at the end"
             + (" **(above the core count: the multi-thread times of this run are not trustworthy)**"
                if max(res["load_average"]) > (meta["cpu_count"] or 1) else "")
             + ". Raw timings and machine metadata in `speed.json`.\n")
    L.append("**Absolute times are unstable on a shared machine; the claim is the ratios**, each method's time "
             "against `cv2.BFMatcher.knnMatch(k=2)` at the same thread count, measured in the same rounds, with "
             "methods and thread counts interleaved in every round.\n")

    # -- goals
    L.append(f"## The goals of issue 17 (n = {kilo(TARGET_N)} keypoints per image)\n")
    pg, fg, rg = res["goals"]["poses"], res["goals"]["floor"], res["goals"]["race"]
    rows = []
    if all(v is None for v in pg.values()):
        rows.append(("`match` and `knnMatch` >= 60x BFMatcher; 2 threads >= 1.7x one; segment >= 1.5x line",
                     f"not evaluated: no n = {kilo(TARGET_N)} in this run (run without `--quick`)", None))
    else:
        for pose, g in pg.items():
            if g is None:
                continue
            for nt, t in g["by_threads"].items():
                rows.append((f"`{pose}`, {nt} thread(s): segment `match` and `knnMatch` >= {GOAL_X:.0f}x BFMatcher",
                             f"match {fmt_x(t['segment_match_x'])}x, knnMatch {fmt_x(t['segment_knn_x'])}x", t["met_x"]))
                rows.append((f"`{pose}`, {nt} thread(s): segment >= {GOAL_VS_LINE}x faster than line (median)",
                             f"match {fmt_ci(t['segment_match_vs_line'])}, knnMatch {fmt_ci(t['segment_knn_vs_line'])}",
                             t["met_vs_line"]))
            if g["scaling"] is not None:
                sc = g["scaling"]["per_method"]
                rows.append((f"`{pose}`: 2 threads >= {GOAL_SCALING}x one (segment match and knnMatch, median)",
                             f"match {fmt_ci(sc['segment_match'])}, knnMatch {fmt_ci(sc['segment_knn'])}",
                             g["scaling"]["met"]))
    if fg is None:
        rows.append((f"core work within {GOAL_FLOOR:g}x the arithmetic floor", "not evaluated (no 1-thread stage profile)",
                     None))
    else:
        for c in ("segment", "line"):
            rows.append((f"core work of `match` within {GOAL_FLOOR:g}x the floor, {c}, n = {kilo(fg['n'])}, 1 thread",
                         f"{fmt_ms(fg[c]['core_s'])} ms / {fmt_ms(fg[c]['floor_s'])} ms = {fg[c]['x']:.1f}x",
                         fg[c]["met"]))
    if rg is None:
        why = res["race"]["why_unavailable"] if res.get("race") else "no race in this run"
        rows.append(("faster than the segment-tree peer at equal or better correct matches",
                     f"not evaluated: the peer is not available here ({why})", None))
    else:
        for n, by_nt in rg["by_size"].items():
            for nt, by_m in by_nt.items():
                for m, c in by_m.items():
                    rows.append((f"faster than {m} at >= its correct matches, n = {kilo(int(n))}, {nt} thread(s)",
                                 f"segment {c['ours segment']['x_faster']:.2f}x faster, {c['ours segment']['correct_diff']:+d} "
                                 f"correct; line {c['ours line']['x_faster']:.2f}x, {c['ours line']['correct_diff']:+d}",
                                 c["met"]))
    L.append("| goal | measured | met |")
    L.append("|---|---|---|")
    for goal, measured, met in rows:
        L.append(f"| {goal} | {measured} | {'n/a' if met is None else yes(met)} |")
    L.append("")
    L.append("Ratios of two methods (line / segment, 1 / 2 threads) are the median of per-round ratios with a 95 % "
             "paired bootstrap interval in brackets; the goal is judged on the median. The peer goal counts as met "
             "at a size when our segment or our line is faster with at least the peer's correct matches (our line "
             "has the peer tree's candidates, hence its matches).\n")
    L += _bounds(res)

    # -- setup
    L.append("## Setup\n")
    L.append(f"- Scenes: `episeg_cv.scenes.make_pair(pose, image_size={tuple(cfg['image_size'])})`, the room "
             "scenes of the pose suite rendered with texture; the matcher gets `pair.geometry`.")
    L.append("- Keypoints: `cv2.SIFT_create(nfeatures=0, contrastThreshold=0.0)` run once per image; for each n "
             "the n strongest by `response` are kept in each image. Keypoints go to `SegmentMatcher` as lists of "
             "`cv2.KeyPoint` and to `match_descriptors` as `(n, 2)` arrays. Rendering, detection and the lists are "
             "outside the timed part.")
    L.append(f"- Timing: one warm-up call per method and thread count, then {cfg['repeats']} rounds "
             f"({TARGET_REPEATS} at n = {kilo(TARGET_N)}); in every round each method runs once at each thread count "
             f"({', '.join(tcs)}). Thread count n means `cv2.setNumThreads(n)` (BFMatcher, FLANN) and "
             "`episeg_cv.set_num_threads(n)` (the compiled kernels and the BLAS product of the padding) together. "
             f"BLAS as loaded: {res['threads']['blas']}.")
    L.append(f"- Candidates per query: `CandidateIndex(geometry, p1, p2, tol={TOL:g}, constraint=...)"
             ".candidate_counts().mean()`; BFMatcher compares each query with all n keypoints of image 2.")
    L.append("- Methods:")
    for k, (label, desc) in METHODS.items():
        L.append(f"  - **{label}**: {desc}.")
    L.append("")

    # -- threads and the 16-core estimate
    am = res["amdahl"]
    if am:
        L.append(f"## Threads: 1 against 2, and an estimate for {_stages.CORES} cores (n = {kilo(res['amdahl_n'])})\n")
        L.append(f"How the estimate is made: Amdahl's law. From the medians at one and two threads, the parallel "
                 f"fraction is `p = 2 (1 - t2 / t1)` (clipped to [0, 1]) and the time on {_stages.CORES} cores "
                 f"`t16 = t1 (1 - p + p / {_stages.CORES})`. It assumes the parallel part keeps scaling linearly and "
                 "that memory bandwidth, frequency and scheduling do not change with the core count; `p` from two "
                 "threads is very uncertain when the speed-up is small or the machine is loaded. It is an estimate, "
                 "not a measurement; the stage-by-stage version is below.\n")
        for pose, rows_ in am.items():
            L.append(f"### Pose `{pose}`\n")
            L.append(f"| method | 1 thread (ms) | 2 threads (ms) | speed-up (per-round median [95 %]) | p | "
                     f"est. {_stages.CORES} cores (ms) | est. x faster than BF at {_stages.CORES} |")
            L.append("|---|---|---|---|---|---|---|")
            sc = (res["goals"]["poses"].get(pose) or {}).get("scaling") or {}
            for k, (label, _) in METHODS.items():
                r = rows_[k]
                ci = fmt_ci(sc["per_method"][k]) if sc else f"{r['t1_s'] / r['t2_s']:.2f}"
                L.append(f"| {label} | {fmt_ms(r['t1_s'])} | {fmt_ms(r['t2_s'])} | {ci} | {r['p']:.2f} | "
                         f"{fmt_ms(r['t16_s'])} | {fmt_x(r['x_faster_than_bf_16'])} |")
            L.append("")

    # -- stages
    st = res.get("stages")
    if st:
        L.append(f"## Stages of `match` at n = {kilo(st['n1'])} (pose `{st['pose']}`), against the floor\n")
        L.append(_stages.DESCRIPTION + "\n")
        for c, r in st["constraints"].items():
            fl = r["floor"]
            L.append(f"### {c}\n")
            L.append(f"Floor: {fl['candidates']:,} candidate pairs x {fl['dimensions']} dimensions scored once = "
                     f"**{fmt_ms(fl['time_s'])} ms** ({fl['rate_mac_per_s'] / 1e9:.2f} G multiply-adds/s, CPU-time "
                     f"median of {r['repeats']}, one thread).\n")
            head = "| stage | " + " | ".join(f"{nt} thr. wall (ms) | {nt} thr. CPU (ms)" for nt in r["by_threads"])
            am_s = r.get("amdahl")
            head += (f" | p | est. {_stages.CORES} cores (ms) |" if am_s else " |")
            L.append(head)
            L.append("|---|" + "---|---|" * len(r["by_threads"]) + ("---|---|" if am_s else ""))
            for s_ in _stages.STAGES:
                cells = " | ".join(f"{fmt_signed_ms(b['stages_wall_s'][s_])} | {fmt_signed_ms(b['stages_cpu_s'][s_])}"
                                   for b in r["by_threads"].values())
                extra = (f" | {am_s[s_]['p']:.2f} | {fmt_ms(am_s[s_]['t16_s'])}" if am_s else "")
                L.append(f"| {s_} | {cells}{extra} |")
            core = " | ".join(f"{fmt_ms(b['core_wall_s'])} | {fmt_ms(b['core_cpu_s'])}" for b in r["by_threads"].values())
            sums = " | ".join(f"{fmt_ms(sum(b['stages_wall_s'][s] for s in _stages.CORE))} | "
                              f"{fmt_ms(sum(b['stages_cpu_s'][s] for s in _stages.CORE))}" for b in r["by_threads"].values())
            extra = (f" | | {fmt_ms(sum(am_s[s]['t16_s'] for s in _stages.CORE))}" if am_s else "")
            L.append(f"| **core work: `match_descriptors` end to end** | {core}{' | |' if am_s else ''} |")
            L.append(f"| sum of the core stages (check) | {sums}{extra} |")
            L.append("")
        L.append("CPU is the calling thread's CPU time (robust to other processes for one thread; with two threads "
                 "the second thread's work is not in it). Differences of two medians can dip below zero by noise.\n")

    # -- race
    race = res.get("race")
    if race:
        L.append(f"## Race against the segment-tree peer (pose `{race['pose']}`)\n")
        if not race["available"]:
            L.append(f"**The peer is not available here**: {race['why_unavailable']}. Only our rows are timed. "
                     "How to build it:\n")
            L.append("```\n" + _peer.RECIPE + "\n```\n")
        else:
            L.append("\"Pixel-Accurate Epipolar Guided Matching\" (3DV 2026), its authors' C++ (pybind11, OpenMP) "
                     f"imported from `{_peer.ENV}`. Both sides get the same keypoints, descriptors, pose (its F from "
                     f"our geometry), tol = {TOL:g} px and thread count (its OpenMP pool limited with threadpoolctl). "
                     f"Its candidate lists go through a compiled nearest-two (numba, float32 squared L2, on threads "
                     f"when n > 1) and Lowe's ratio {RATIO}; ours is `knn_descriptors(k=2)` and the same ratio rule. "
                     "Times are end to end from arrays, median of the rounds (CPU: the calling thread's). Correct: "
                     "`ground_truth_matches` (3 px, the true pose, rendered depth).\n")
        for n, s in race["sizes"].items():
            L.append(f"### n = {kilo(int(n))} ({s['n1']} / {s['n2']} keypoints, render {s['image_size'][0]}x{s['image_size'][1]})\n")
            L.append("| method | " + " | ".join(f"{nt} thr. ms (CPU)" for nt in s["threads"]) +
                     " | candidates / query | matches | correct |")
            L.append("|---|" + "---|" * len(s["threads"]) + "---|---|---|")
            first = next(iter(s["threads"].values()))
            for m in first:
                cells = " | ".join(f"{fmt_ms(b[m]['median_s'])} ({fmt_ms(b[m]['median_cpu_s'])})" for b in s["threads"].values())
                L.append(f"| {m} | {cells} | {s['candidates_per_query'].get(m, float('nan')):.1f} | {first[m]['matches']} | "
                         f"{first[m]['correct']} |")
            for nt, b in s["threads"].items():
                for m, v in b.items():
                    if "stages_s" in v:
                        x = v["stages_s"]
                        L.append(f"\n{m}, {nt} thread(s): the call {fmt_ms(x['peer'])} ms (its C++ clock "
                                 f"{fmt_ms(x['peer_cpp'])}; the rest builds Python lists), lists to CSR "
                                 f"{fmt_ms(x['csr'])}, nearest two {fmt_ms(x['knn'])}, ratio {fmt_ms(x['ratio'])}.")
            L.append("")

    # -- per pose
    for pose, r in res["poses"].items():
        sizes = list(r["sizes"].values())
        cols = [kilo(s["n_requested"]) for s in sizes]
        L.append(f"## Pose `{pose}`: {r['description']}\n")
        L.append(f"SIFT keypoints detected: {r['keypoints_detected'][0]} in image 1, {r['keypoints_detected'][1]} in "
                 "image 2. Keypoints used per size (image 1 / image 2): "
                 + ", ".join(f"{kilo(s['n_requested'])}: {s['n1']} / {s['n2']}" for s in sizes) + ".\n")
        for nt in tcs:
            L.append(f"### x faster than `cv2.BFMatcher.knnMatch(k=2)`, {nt} thread(s) (t_BF / t_method)\n")
            L.append("| method | " + " | ".join(f"n = {c}" for c in cols) + " |")
            L.append("|---|" + "---|" * len(cols))
            for k, (label, _) in METHODS.items():
                cells = [("1 (" + fmt_ms(s["threads"][nt]["median_s"][k]) + " ms)") if k == "bf_knn"
                         else fmt_x(s["threads"][nt]["x_faster_than_bf"][k]) for s in sizes]
                L.append(f"| {label} | " + " | ".join(cells) + " |")
            L.append("")
        L.append(f"Exponent of time against n ({tcs[-1]} threads): " + ", ".join(
            f"{METHODS[k][0]} {'n/a' if v is None else f'{v:.2f}'}" for k, v in r["exponent"].items()) + ".\n")
        L.append("### Candidates per query\n")
        L.append("| constraint | " + " | ".join(f"n = {c}" for c in cols) + " |")
        L.append("|---|" + "---|" * len(cols))
        for c in ("segment", "line"):
            L.append(f"| {c} | " + " | ".join(f"{s['candidates_per_query'][c]:.1f} "
                                               f"({100 * s['candidates_per_query'][c] / max(s['n2'], 1):.2f} %)"
                                               for s in sizes) + " |")
        L.append("| none (BFMatcher) | " + " | ".join(f"{s['n2']}" for s in sizes) + " |")
        L.append("")
        L.append(f"### Median time (ms), {tcs[-1]} threads\n")
        L.append("| method | " + " | ".join(f"n = {c}" for c in cols) + " |")
        L.append("|---|" + "---|" * len(cols))
        for k, (label, _) in METHODS.items():
            L.append(f"| {label} | " + " | ".join(fmt_ms(s["threads"][tcs[-1]]["median_s"][k]) for s in sizes) + " |")
        L.append("")
        L.append("### Output size (matches returned; neighbours for knnMatch)\n")
        L.append("| method | " + " | ".join(f"n = {c}" for c in cols) + " |")
        L.append("|---|" + "---|" * len(cols))
        for k, (label, _) in METHODS.items():
            L.append(f"| {label} | " + " | ".join(str(s["output_size"][k]) for s in sizes) + " |")
        L.append("")

    b = res["binary"]
    L.append(f"## Binary descriptors: ORB, pose `{b['pose']}` ({tcs[-1]} threads)\n")
    L.append(f"`cv2.ORB_create(nfeatures=n)` on the same renders: {b['n1']} / {b['n2']} keypoints; "
             "`cv2.NORM_HAMMING` everywhere. Median of the interleaved rounds; the line / segment figure is the "
             "median per-round ratio with a 95 % paired bootstrap interval, as above.\n")
    L.append("| method | x faster than BFMatcher | median (ms) | output size |")
    L.append("|---|---|---|---|")
    for k, v in b["median_s"].items():
        L.append(f"| {k} | {fmt_x(b['x_faster_than_bf'][k])} | {fmt_ms(v)} | {b['output_size'][k]} |")
    L.append("")
    L.append("Line / segment time: " + ", ".join(f"{what} {fmt_ci(v)}" for what, v in b["line_vs_segment"].items())
             + ".\n")

    f = res["filter"]
    L.append(f"## `filter` on {f['matches']:,} matches ({tcs[-1]} threads)\n")
    L.append(f"{f['matches']:,} random index pairs between the {f['n1']} / {f['n2']} strongest keypoints of the "
             f"`{f['pose']}` pair (kept: segment {f['kept']['segment']}, line {f['kept']['line']}); median of "
             f"{cfg['repeats']} after a warm-up. `SegmentMatcher.filter` takes `cv2.DMatch` and `cv2.KeyPoint` lists "
             "(and converts them); `filter_pairs` takes arrays.\n")
    L.append("| call | median (ms) |")
    L.append("|---|---|")
    for k, v in f["median_s"].items():
        L.append(f"| {k} | {fmt_ms(v)} |")
    L.append("")
    path.write_text("\n".join(L))


def _bounds(res: dict) -> list:
    """What the cv2 objects alone leave of the unmet goals, from this run's own stage times (pose of the stage
    profile, segment, n = 10k): the ``cv2.DMatch`` lists are made in Python and hold the GIL, so no thread
    count shortens them."""
    st, am = res.get("stages"), res.get("amdahl") or {}
    if not st or st["pose"] not in am or "segment" not in st["constraints"]:
        return []
    pose, r = st["pose"], st["constraints"]["segment"]["by_threads"]
    rows = am[pose]
    L = [f"**What bounds the unmet goals** (pose `{pose}`, segment, n = {kilo(st['n1'])}, this run's medians). "
         "The `cv2.DMatch` objects are made in Python under the GIL, so no thread count shortens them:", ""]
    for nt, key in ((1, "t1_s"), (2, "t2_s")):
        if str(nt) not in r:
            continue
        budget = rows["bf_knn"][key] / GOAL_X
        for what, method in (("knnMatch", "segment_knn"), ("match", "segment_match")):
            dm = r[str(nt)]["stages_wall_s"][f"DMatch ({what})"]
            left = budget - dm
            L.append(f"- {nt} thread(s), `{what}`: {GOAL_X:.0f}x BFMatcher leaves {fmt_ms(budget)} ms; its DMatch "
                     f"lists take {fmt_ms(dm)} ms of it, "
                     + (f"so everything else must fit in {fmt_ms(left)} ms (measured: "
                        f"{fmt_ms(rows[method][key] - dm)} ms)." if left > 0 else "**more than the whole budget**."))
    for what, method in (("knnMatch", "segment_knn"), ("match", "segment_match")):
        t1, dm = rows[method]["t1_s"], r["1"]["stages_wall_s"][f"DMatch ({what})"]
        best = t1 / (dm + (t1 - dm) / 2)
        L.append(f"- 2 threads against one, `{what}`: even if all but the DMatch lists ({fmt_ms(dm)} of "
                 f"{fmt_ms(t1)} ms) halved, the speed-up would be {best:.2f}x (goal {GOAL_SCALING}x).")
    return L + [""]
