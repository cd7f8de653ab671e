"""Constants, the method table and number formats shared by ``benchmarks/speed.py`` and its report."""

from __future__ import annotations

from pathlib import Path

from episeg_cv import AcceptRule

DEFAULT_RATIO, DEFAULT_PAD = AcceptRule().ratio, AcceptRule().pad  # the library's defaults

RESULTS = Path(__file__).resolve().parent / "results"
SCRIPT = "benchmarks/speed.py"
IMAGE_SIZE = (1600, 1200)  # 1280 x 960 gives fewer than 20k SIFT keypoints on some poses
RACE_IMAGE_SIZE = (2400, 1800)  # for the race sizes that 1600 x 1200 cannot give (about 28k keypoints)
SIZES = (2000, 5000, 10000, 20000)
QUICK_SIZES = (2000, 5000)
RACE_SIZES = (5000, 10000, 20000, 50000)
POSES = ("forward", "lateral")
QUICK_POSES = ("forward",)
REPEATS = 5
RATIO = 0.8  # Lowe's ratio for the cv2 pipelines and the race
TOL = 2.0  # SegmentMatcher's default pixel tolerance
FLANN_INDEX = {"algorithm": 1, "trees": 4}  # FLANN_INDEX_KDTREE
FLANN_SEARCH = {"checks": 64}
FILTER_MATCHES = 100_000
TARGET_N = 10000
#: Repeats at TARGET_N (at least), for the bootstrap intervals of the paired ratios.
TARGET_REPEATS = 30
#: Bootstrap resamples for those intervals.
BOOTSTRAP = 2000
#: The goals of issue 17 (at TARGET_N): x faster than BFMatcher for match and knnMatch, 2 threads over 1,
#: line over segment time, core work over the floor.
GOAL_X = 60.0
GOAL_SCALING = 1.7
GOAL_VS_LINE = 1.5
GOAL_FLOOR = 3.0

#: key -> (label in the tables, short description)
METHODS = {
    "bf_knn": ("BFMatcher knnMatch(k=2) (reference)", "`cv2.BFMatcher(cv2.NORM_L2).knnMatch(d1, d2, k=2)`"),
    "bf_ratio_line": ("BFMatcher knnMatch + ratio + line filter",
                      f"the same, then Lowe's ratio {RATIO}, then "
                      "`SegmentMatcher(geometry, constraint=\"line\").filter(good, kp1, kp2)`"),
    "flann_ratio": ("FLANN knnMatch(k=2) + ratio",
                    f"`cv2.FlannBasedMatcher` (KD-tree, {FLANN_INDEX['trees']} trees, {FLANN_SEARCH['checks']} "
                    f"checks; the index is built in each call) `knnMatch(k=2)`, then ratio {RATIO}: the fast peer"),
    "segment_match": ("SegmentMatcher segment: match", "`SegmentMatcher(geometry, cv2.NORM_L2, "
                      "constraint=\"segment\").match(d1, d2, kp1, kp2)` "
                      f"(the default rule: mutual + ratio {DEFAULT_RATIO}, pad {DEFAULT_PAD})"),
    "segment_knn": ("SegmentMatcher segment: knnMatch(k=2)", "`SegmentMatcher(..., constraint=\"segment\")"
                    ".knnMatch(d1, d2, kp1, kp2, k=2)` (raw neighbours, like BFMatcher's)"),
    "line_match": ("SegmentMatcher line: match", "the same with `constraint=\"line\"`"),
    "line_knn": ("SegmentMatcher line: knnMatch(k=2)", "the same with `constraint=\"line\"`"),
    "segment_arrays": ("match_descriptors segment (arrays)", "`match_descriptors(d1, d2, p1, p2, geometry, "
                       "constraint=\"segment\")` on arrays, no cv2 objects"),
    "line_arrays": ("match_descriptors line (arrays)", "the same with `constraint=\"line\"`"),
}


def kilo(n: int) -> str:
    return f"{n // 1000}k" if n % 1000 == 0 and n >= 1000 else str(n)


def fmt_x(v: float) -> str:
    return f"{v:.0f}" if v >= 100 else f"{v:.1f}" if v >= 1 else f"{v:.2f}"


def fmt_ms(v: float) -> str:
    ms = 1e3 * v
    return f"{ms:.0f}" if ms >= 100 else f"{ms:.1f}" if ms >= 1 else f"{ms:.2f}"


def fmt_ci(v) -> str:
    return f"{v[0]:.2f} [{v[1]:.2f}, {v[2]:.2f}]"


def yes(b) -> str:
    return "**yes**" if b else "**no**"


def dirty_note(meta) -> str:
    return ", with uncommitted changes in episeg_cv/" if meta.get("episeg_cv_uncommitted_changes") else ""


def fmt_signed_ms(v: float) -> str:
    return fmt_ms(v) if v >= 0 else f"-{fmt_ms(-v)}"
