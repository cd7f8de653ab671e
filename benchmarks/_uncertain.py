"""Two sections of ``benchmarks/compare.py`` (issue 16): poses that are off, and no pose at all.

1. **Pose noise.** The pose handed to the matcher is the true one turned by
   ``a_r`` degrees about a random axis, with ``t`` turned by ``a_t`` degrees
   towards a random perpendicular direction (same length); levels (0, 0),
   (0.25, 1), (0.5, 2.5), (1, 5). Rows: fixed ``tol`` 1, 2, 4, 8, 16 px,
   ``tol="auto"``, and the covariance band with the true covariance of that
   noise (:func:`episeg_cv.pose_covariance`; matched in the bands of its
   posterior). Correct matches at 99 % / 95 %
   precision along the ratio sweep, precision at the default rule.
2. **No pose.** OpenCV as users run it (``BFMatcher`` + ratio 0.8 +
   ``findFundamentalMat(USAC_MAGSAC)`` inliers, and ``findEssentialMat`` +
   ``recoverPose`` with ``K``) against :func:`episeg_cv.match_without_pose`
   (the oriented half-line from ``F``; with ``K``, the refined ``E`` pose),
   also with ``reject_repeats=True`` (matches whose keypoints have a twin in
   their own image inside the same band left out).

Pairs: synthetic renders of the pose suite, Motorcycle, a synthetic room whose
walls are tiled with periodic textures (repetitive texture), and real pairs of
Middlebury's dinoSparseRing (``../shared/data/dinoSparseRing`` from the
repository root, or ``--dino``; skipped with a note when absent). Only the
public API of ``episeg_cv`` is used.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from episeg_cv import (AcceptRule, TwoViewGeometry, consistent_pairs, datasets, guided_matches, match_without_pose,
                       pose_covariance, scenes)

RATIOS = np.round(np.linspace(0.30, 1.00, 71), 2)
DEFAULT_RATIO = AcceptRule().ratio
LEVELS = [(0.0, 0.0), (0.25, 1.0), (0.5, 2.5), (1.0, 5.0)]
FIXED = (1.0, 2.0, 4.0, 8.0, 16.0)
SIFT = dict(nfeatures=4000, contrastThreshold=0.02)
SIFT_DINO = dict(nfeatures=4000, contrastThreshold=0.005)  # the dinosaur is untextured: 0.02 finds ~220


@dataclass
class Pair:
    """One image pair with SIFT features and ground truth (``is_correct(pairs)``, ``known (N1,)``)."""

    name: str
    geometry: TwoViewGeometry
    p1: np.ndarray
    p2: np.ndarray
    d1: np.ndarray
    d2: np.ndarray
    gt: object


def _sift(img, params):
    k, d = cv2.SIFT_create(**params).detectAndCompute(img, None)
    return np.array([x.pt for x in k], dtype=np.float64).reshape(-1, 2), d


class _DepthGT:
    def __init__(self, gt):
        self.gt = gt
        self.known = np.all(np.isfinite(gt.projected), axis=1)

    def is_correct(self, pairs):
        return self.gt.is_correct(pairs) if len(pairs) else np.zeros(0, bool)


def _from_image_pair(name, ip) -> Pair:
    p1, d1 = _sift(ip.image1, SIFT)
    p2, d2 = _sift(ip.image2, SIFT)
    return Pair(name, ip.geometry_true, p1, p2, d1, d2, _DepthGT(ip.ground_truth(p1, p2)))


def synthetic(pose: str, size) -> Pair:
    return _from_image_pair(f"synthetic {pose}", scenes.make_pair(pose, image_size=size))


def motorcycle() -> Pair:
    return _from_image_pair("Motorcycle", datasets.load_motorcycle())


# -- repetitive texture ---------------------------------------------------------------------------------
def _periodic(kind: str, size: int = 512) -> np.ndarray:
    """Seamless periodic textures (their periods divide 512)."""
    y, x = np.mgrid[0:size, 0:size].astype(np.float32)
    if kind == "checker":  # 32-px squares, a blob in each (SIFT finds corners and blobs)
        c = ((x // 32 + y // 32) % 2).astype(np.float32)
        blob = np.exp(-(((x % 32) - 16) ** 2 + ((y % 32) - 16) ** 2) / 18.0)
        img = 40 + 150 * c + 60 * blob * (1 - 2 * c)
    else:  # 64-px tiles with grout lines and a four-petal motif
        gx, gy = x % 64, y % 64
        grout = (np.minimum(gx, 64 - gx) < 3) | (np.minimum(gy, 64 - gy) < 3)
        r, ang = np.hypot(gx - 32, gy - 32), np.arctan2(gy - 32, gx - 32)
        img = np.where(grout, 40.0, 180.0 - 90 * (r < 18 + 6 * np.cos(4 * ang)))
    return np.clip(img, 20, 235).astype(np.float32)


def repetitive_scene(seed: int = 0) -> scenes.Scene:
    """A room (8 x 3 x 10 m) whose four walls are tiled with periodic textures (a checkerboard, tiles, a
    brick photograph mirrored into a 512-px period), with a photographed floor, ceiling and boxes."""
    rng = np.random.default_rng(seed)
    brick = scenes.load_texture("brick")[:256, :256]
    textures = [_periodic("checker"), _periodic("tiles"),
                np.block([[brick, brick[:, ::-1]], [brick[::-1], brick[::-1, ::-1]]]).astype(np.float32),
                scenes.load_texture("gravel"), scenes.load_texture("moon"), scenes.load_texture("astronaut"),
                scenes.load_texture("coffee"), scenes.load_texture("chelsea")]
    W, H, D = 8.0, 3.0, 10.0
    x0, x1, y0, y1, z0, z1 = -W / 2, W / 2, -H / 2, H / 2, -D / 2, D / 2
    ex, ey, ez = np.array([W, 0, 0.0]), np.array([0, H, 0.0]), np.array([0, 0, D])
    quads = []
    for origin, tex in ((np.array([x0, y1, z0]), 3), (np.array([x0, y0, z0]), 4)):  # floor, ceiling: photos
        for i in range(4):
            for j in range(5):
                A = np.array([[W / 4 / 0.006, 0, rng.uniform(0, 512)], [0, D / 5 / 0.006, rng.uniform(0, 512)]])
                quads.append(scenes.Quad(origin + ex * i / 4 + ez * j / 5, ex / 4, ez / 5, tex, A,
                                         float(rng.uniform(0.7, 1))))
    for origin, eu, ev, tex in ((np.array([x0, y0, z0]), ex, ey, 2), (np.array([x0, y0, z1]), ex, ey, 2),
                                (np.array([x0, y0, z0]), ez, ey, 0), (np.array([x1, y0, z0]), ez, ey, 1)):
        lu, lv = np.linalg.norm(eu), np.linalg.norm(ev)  # the walls: pure repetition, no offset or rotation
        A = np.array([[lu / 0.004, 0.0, 0.0], [0.0, lv / 0.004, 0.0]])
        quads.append(scenes.Quad(origin, eu, ev, tex, A, float(rng.uniform(0.75, 1.0))))
    for k in range(5):
        size = rng.uniform([0.5, 0.5, 0.5], [1.2, 1.4, 1.2])
        c = [rng.uniform(-2.5, 2.5), y1 - size[1] / 2, rng.uniform(0.5, 4.0)]
        quads += scenes.box_quads(c, size, float(rng.uniform(0, np.pi / 2)), 5 + k % 3, rng=rng, texel_size=0.003)
    return scenes.Scene(quads, textures)


def repetitive(pose: str, size, seed: int = 0) -> Pair:
    """The repetitive room (scene ``seed``) seen by the cameras of the pose suite's case ``pose``."""
    case = scenes.pose_suite()[pose]
    K1, K2 = case.intrinsics(size)
    scene = repetitive_scene(seed)
    im1, z1 = scenes.render(scene, K1, case.R1, case.t1, size)
    im2, z2 = scenes.render(scene, K2, case.R2, case.t2, size)
    g = case.geometry(size)
    p1, d1 = _sift(im1, SIFT)
    p2, d2 = _sift(im2, SIFT)
    name = f"repetitive {pose}" + (f", scene seed {seed}" if seed else "")
    return Pair(name, g, p1, p2, d1, d2, _DepthGT(scenes.ground_truth_matches(p1, p2, z1, z2, g)))


# -- dinoSparseRing: calibrated, no depth maps --------------------------------------------------------------
#: The object's bounding box (the data set's README), metres.
DINO_BOX = (np.array([-0.061897, -0.018874, -0.057845]), np.array([0.010897, 0.068227, 0.015495]))


class _DinoGT:
    """A match of views (i, j) is correct iff x2 is within 2 px of the true epipolar line of x1 and x1 of that of
    x2, and its triangulation with the true cameras is in front of both, inside the object's bounding box
    ``box`` (dinoSparseRing's by default; templeSparseRing's is in its README) grown by 5 mm, and inside the
    silhouette of every view it projects into (the README's recipe: threshold 0.19,
    dilate 10, erode 7; holes filled, grown 6 px). A wrong match displaced along the true line by less
    than the line's chord through this hull passes: precision here is an upper bound."""

    def __init__(self, cams, masks, i, j, p1, p2, box=DINO_BOX):
        self.box = box
        self.P = [K @ np.column_stack([R, t]) for _, K, R, t in cams]
        self.cams, self.masks, self.i, self.j, self.p1, self.p2 = cams, masks, i, j, p1, p2
        (_, K1, R1, t1), (_, K2, R2, t2) = cams[i], cams[j]
        self.F = TwoViewGeometry.from_world_poses(K1, R1, t1, K2, R2, t2, image_size1=(640, 480),
                                                  image_size2=(640, 480)).fundamental_matrix
        self.known = np.ones(len(p1), bool)

    def is_correct(self, pairs):
        pairs = np.asarray(pairs, np.intp).reshape(-1, 2)
        if len(pairs) == 0:
            return np.zeros(0, bool)
        h1 = np.column_stack([self.p1[pairs[:, 0]], np.ones(len(pairs))])
        h2 = np.column_stack([self.p2[pairs[:, 1]], np.ones(len(pairs))])
        l2, l1 = h1 @ self.F.T, h2 @ self.F
        ok = (np.abs((l2 * h2).sum(1)) / np.hypot(l2[:, 0], l2[:, 1]) <= 2) & \
             (np.abs((l1 * h1).sum(1)) / np.hypot(l1[:, 0], l1[:, 1]) <= 2)
        P1, P2 = self.P[self.i], self.P[self.j]
        x1, x2 = h1[:, :2], h2[:, :2]
        A = np.stack([x1[:, :1] * P1[2] - P1[0], x1[:, 1:2] * P1[2] - P1[1],
                      x2[:, :1] * P2[2] - P2[0], x2[:, 1:2] * P2[2] - P2[1]], axis=1)
        X = np.linalg.svd(A)[2][:, -1]
        with np.errstate(divide="ignore", invalid="ignore"):
            X = X[:, :3] / X[:, 3:4]
        lo, hi = self.box
        ok &= np.all((X >= lo - 0.005) & (X <= hi + 0.005), axis=1)
        for k, (_, K, R, t) in enumerate(self.cams):
            Xc = X @ R.T + t
            if k in (self.i, self.j):
                ok &= Xc[:, 2] > 0
            with np.errstate(divide="ignore", invalid="ignore"):
                u = np.round(Xc[:, 0] / Xc[:, 2] * K[0, 0] + K[0, 2])
                v = np.round(Xc[:, 1] / Xc[:, 2] * K[1, 1] + K[1, 2])
            inside = (Xc[:, 2] > 0) & (u >= 0) & (u < 640) & (v >= 0) & (v < 480)
            m = np.ones(len(X), bool)
            m[inside] = self.masks[k][v[inside].astype(int), u[inside].astype(int)]
            ok &= m
        return ok


def _dino_masks(folder: Path, cams) -> list:
    out = []
    for name, *_ in cams:
        img = cv2.imread(str(folder / name)).astype(np.float32) / 255
        m = (img.max(axis=2) > 0.19).astype(np.uint8)
        m = cv2.erode(cv2.dilate(m, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (21, 21))),
                      cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (15, 15)))
        flood = m.copy()
        h, w = m.shape
        for x, y in ((0, 0), (w - 1, 0), (0, h - 1), (w - 1, h - 1)):
            if flood[y, x] == 0:
                cv2.floodFill(flood, np.zeros((h + 2, w + 2), np.uint8), (x, y), 2)
        m = cv2.dilate((flood != 2).astype(np.uint8), cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (13, 13)))
        out.append(m.astype(bool))
    return out


_DINO = {}


def dino(folder: Path, i: int, j: int) -> Pair | None:
    """Views ``i, j`` (0-based) of dinoSparseRing, or None when the folder is absent."""
    par = folder / "dinoSR_par.txt"
    if not par.is_file():
        return None
    if folder not in _DINO:
        cams = []
        for line in par.read_text().split("\n")[1:]:
            v = line.split()
            if len(v) == 22:
                a = np.array(v[1:], float)
                U, _, Vt = np.linalg.svd(a[9:18].reshape(3, 3))
                cams.append((v[0], a[:9].reshape(3, 3), U @ np.diag([1, 1, np.linalg.det(U @ Vt)]) @ Vt, a[18:]))
        _DINO[folder] = (cams, _dino_masks(folder, cams))
    cams, masks = _DINO[folder]
    im1, im2 = (cv2.imread(str(folder / cams[k][0]), cv2.IMREAD_GRAYSCALE) for k in (i, j))
    p1, d1 = _sift(im1, SIFT_DINO)
    p2, d2 = _sift(im2, SIFT_DINO)
    (_, K1, R1, t1), (_, K2, R2, t2) = cams[i], cams[j]
    g = TwoViewGeometry.from_world_poses(K1, R1, t1, K2, R2, t2, image_size1=(640, 480), image_size2=(640, 480))
    return Pair(f"dinoSparseRing {i}-{j}", g, p1, p2, d1, d2, _DinoGT(cams, masks, i, j, p1, p2))


# -- metrics ----------------------------------------------------------------------------------------------
def summary(pair: Pair, pairs, ratio=None, mutual=None) -> dict:
    """``p99``, ``p95`` (most correct along the ratio sweep at that precision; for a fixed output, its count
    if its precision reaches it), ``correct`` and ``precision`` at the default rule, over queries with truth."""
    pairs = np.asarray(pairs, np.intp).reshape(-1, 2)
    known = pair.gt.known[pairs[:, 0]] if len(pairs) else np.zeros(0, bool)
    pairs = pairs[known]
    good = pair.gt.is_correct(pairs)
    if ratio is None:
        n, k = len(pairs), int(good.sum())
        p = k / n if n else float("nan")
        return dict(p99=k if p >= 0.99 else 0, p95=k if p >= 0.95 else 0, correct=k, returned=n, precision=p)
    ratio, mutual = ratio[known], mutual[known]
    ret, cor = [], []
    for t in RATIOS:
        s = mutual & ((ratio < t) if t < 1 else True)
        ret.append(int(s.sum()))
        cor.append(int((s & good).sum()))
    ret, cor = np.array(ret), np.array(cor)

    def at(p):
        ok = (ret > 0) & (cor >= p * ret)
        return int(cor[ok].max()) if ok.any() else 0

    k = int(np.argmin(np.abs(RATIOS - DEFAULT_RATIO)))
    return dict(p99=at(0.99), p95=at(0.95), correct=int(cor[k]), returned=int(ret[k]),
                precision=cor[k] / ret[k] if ret[k] else float("nan"))


def perturb(g: TwoViewGeometry, rot_deg: float, tdir_deg: float, seed: int) -> TwoViewGeometry:
    """``R' = Rot(random axis, rot_deg) R``; ``t`` turned by ``tdir_deg`` towards a random perpendicular."""
    rng = np.random.default_rng(seed)
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    S = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    a = np.deg2rad(rot_deg)
    R = (np.eye(3) + np.sin(a) * S + (1 - np.cos(a)) * S @ S) @ g.R
    u = g.t / np.linalg.norm(g.t)
    d = rng.normal(size=3)
    d -= (d @ u) * u
    d /= np.linalg.norm(d)
    b = np.deg2rad(tdir_deg)
    t = np.linalg.norm(g.t) * (np.cos(b) * u + np.sin(b) * d)
    return TwoViewGeometry(g.K1, g.K2, R, t, image_size1=g.image_size1, image_size2=g.image_size2)


# -- section 1: pose noise --------------------------------------------------------------------------------------
def noise_rows(pair: Pair, seeds: int, first_seed: int = 0) -> list:
    """Rows of the noise section: every level with ``seeds`` random errors (seeds ``first_seed, ...``)."""
    rows = []
    for li, (a_r, a_t) in enumerate(LEVELS):
        for seed in range(first_seed, first_seed + seeds) if li else [first_seed]:
            g = perturb(pair.geometry, a_r, a_t, 1000 * li + seed) if li else pair.geometry
            methods = [(f"tol {t:g}", dict(tol=t), g) for t in FIXED] + [("auto", dict(tol="auto"), g)]
            if li:
                methods.append(("covariance band", {}, g.with_covariance(pose_covariance(g, a_r, a_t))))
            for label, kw, geom in methods:
                t0 = time.perf_counter()
                gm = guided_matches(pair.d1, pair.d2, pair.p1, pair.p2, geom, **kw)
                s = summary(pair, gm.pairs, gm.ratio, gm.mutual)
                s.update(pair=pair.name, level=li, seed=seed, method=label, seconds=time.perf_counter() - t0)
                if gm.estimate is not None:
                    s["tol_used"], s["pose_kept"] = gm.estimate.tol, gm.estimate.pose_kept
                rows.append(s)
    return rows


def noise_report(rows: list) -> tuple[list, dict]:
    """Markdown lines of the noise section and its goals, evaluated."""
    pairs = list(dict.fromkeys(r["pair"] for r in rows))
    methods = list(dict.fromkeys(r["method"] for r in rows))
    cell = {(r["pair"], r["level"], r["seed"], r["method"]): r for r in rows}
    L = ["## Pose noise: fixed tol, tol=\"auto\" and the covariance band", "",
         "The pose given to the matcher is off by the rotation and translation-direction errors of each level "
         "(a random axis and direction per seed). Cells: correct matches @P99 / @P95 / precision at the default "
         "rule, mean over the seeds. `covariance band`: `geometry.with_covariance(pose_covariance(geometry, a_r, "
         "a_t))`, the true covariance of the injected error (matched in the bands of its posterior: the pose "
         "refined on the confident matches of the covariance's bands, with the covariance as its prior).", ""]
    L += ["| pair | error (deg) | " + " | ".join(methods) + " |", "|---|---|" + "---|" * len(methods)]
    for p in pairs:
        for li, lev in enumerate(LEVELS):
            cells = []
            for m in methods:
                rs = [r for (pp, l_, s, mm), r in cell.items() if pp == p and l_ == li and mm == m]
                if not rs:
                    cells.append("")
                    continue
                cells.append(f"{np.mean([r['p99'] for r in rs]):.0f} / {np.mean([r['p95'] for r in rs]):.0f} / "
                             f"{np.nanmean([r['precision'] for r in rs]):.3f}")
            L.append(f"| {p} | {lev[0]:g}, {lev[1]:g} | " + " | ".join(cells) + " |")
    # the goals, per seed
    worst_auto, worst_cov, min_prec, exact, exact_prec = np.inf, np.inf, np.inf, np.inf, np.inf
    for (p, li, s, m), r in cell.items():
        if m != "auto":
            continue
        best = max(cell[(p, li, s, f"tol {t:g}")]["p95"] for t in FIXED)
        if li == 0:
            ref = cell[(p, li, s, "tol 2")]
            exact = min(exact, r["p95"] / ref["p95"] if ref["p95"] else 1.0)
            exact_prec = min(exact_prec, ref["precision"])
            continue
        worst_auto = min(worst_auto, r["p95"] / best if best else (np.inf if r["p95"] else 1.0))
        min_prec = min(min_prec, r["precision"])
        cov = cell.get((p, li, s, "covariance band"))
        if cov is not None:
            worst_cov = min(worst_cov, cov["p95"] / best if best else (np.inf if cov["p95"] else 1.0))
    goals = {"auto_precision_min": min_prec, "exact_pose_tol2_precision_min": exact_prec,
             "auto_vs_best_fixed_min": worst_auto, "auto_vs_tol2_exact_min": exact, "cov_vs_best_fixed_min": worst_cov}
    sec = {m: float(np.median([r["seconds"] for r in rows if r["method"] == m])) for m in methods}
    L += ["", "Goals (issue 16), per pair and seed, errors up to (1, 5) deg:", "",
          f"- `tol=\"auto\"` precision >= 0.95: lowest {min_prec:.3f} -> "
          f"**{'met' if min_prec >= 0.95 else 'not met'}** "
          f"(the default rule on the exact pose, tol 2: lowest {exact_prec:.3f})",
          f"- `tol=\"auto\"` >= 0.9x the best fixed tol in hindsight (@P95): lowest ratio {worst_auto:.2f} -> "
          f"**{'met' if worst_auto >= 0.9 else 'not met'}**",
          f"- exact pose: `tol=\"auto\"` within 1 % of tol 2 (@P95): lowest ratio {exact:.3f} -> "
          f"**{'met' if exact >= 0.99 else 'not met'}**",
          f"- covariance band >= the best fixed tol (@P95): lowest ratio {worst_cov:.2f} -> "
          f"**{'met' if worst_cov >= 1.0 else 'not met'}**", "",
          "Median seconds per call (this machine, all pairs): " +
          ", ".join(f"{m} {s:.3f}" for m, s in sec.items()) + "."]
    return L, goals


# -- section 2: no pose -------------------------------------------------------------------------------------------
def _opencv(pair: Pair, essential: bool, threshold: float = 1.0) -> np.ndarray:
    knn = cv2.BFMatcher(cv2.NORM_L2).knnMatch(pair.d1, pair.d2, k=2)
    first = np.array([[m[0].queryIdx, m[0].trainIdx] for m in knn
                      if len(m) == 2 and m[0].distance < 0.8 * m[1].distance], np.intp).reshape(-1, 2)
    if len(first) < 8:
        return np.zeros((0, 2), np.intp)
    x1, x2 = pair.p1[first[:, 0]], pair.p2[first[:, 1]]
    cv2.setRNGSeed(0)
    if not essential:
        F, mask = cv2.findFundamentalMat(x1, x2, cv2.USAC_MAGSAC, threshold, 0.999, 10000)
        return first[mask.ravel() > 0] if F is not None else first[:0]
    K1, K2 = pair.geometry.K1, pair.geometry.K2
    n1 = cv2.undistortPoints(x1.reshape(-1, 1, 2), K1, None).reshape(-1, 2)
    n2 = cv2.undistortPoints(x2.reshape(-1, 1, 2), K2, None).reshape(-1, 2)
    E, mask = cv2.findEssentialMat(n1, n2, np.eye(3), cv2.USAC_MAGSAC, 0.999, threshold / K1[0, 0])
    if E is None:
        return first[:0]
    _, _, _, mask = cv2.recoverPose(E[:3], n1, n2, np.eye(3), mask=mask)
    return first[mask.ravel() > 0]


def nopose_rows(pair: Pair) -> list:
    g = pair.geometry
    size = dict(image_size1=g.image_size1, image_size2=g.image_size2)
    runs = [("OpenCV F (ratio 0.8 + MAGSAC inliers)", lambda: _opencv(pair, False)),
            ("OpenCV E + recoverPose (with K)", lambda: _opencv(pair, True)),
            ("ours, F (oriented half-line)", lambda: match_without_pose(pair.d1, pair.d2, pair.p1, pair.p2,
                                                                        **size)[0]),
            ("ours, E (with K)", lambda: match_without_pose(pair.d1, pair.d2, pair.p1, pair.p2, K1=g.K1, K2=g.K2,
                                                            **size)[0]),
            ("ours, F, repeats rejected", lambda: match_without_pose(pair.d1, pair.d2, pair.p1, pair.p2,
                                                                     reject_repeats=True, **size)[0]),
            ("ours, E, repeats rejected", lambda: match_without_pose(pair.d1, pair.d2, pair.p1, pair.p2, K1=g.K1,
                                                                     K2=g.K2, reject_repeats=True, **size)[0]),
            ("ours, F, repeats + consistency", lambda: match_without_pose(
                pair.d1, pair.d2, pair.p1, pair.p2, reject_repeats=True, consistency=True, **size)[0]),
            ("ours, E, repeats + consistency", lambda: match_without_pose(
                pair.d1, pair.d2, pair.p1, pair.p2, K1=g.K1, K2=g.K2, reject_repeats=True, consistency=True,
                **size)[0])]
    rows = []
    for label, fn in runs:
        t0 = time.perf_counter()
        try:
            pairs = fn()
        except ValueError:  # the geometry could not be estimated
            pairs = np.zeros((0, 2), np.intp)
        s = summary(pair, pairs)
        s.update(pair=pair.name, method=label, seconds=time.perf_counter() - t0)
        rows.append(s)
    gm = guided_matches(pair.d1, pair.d2, pair.p1, pair.p2, g)
    exact = gm.accept()[0]
    s = summary(pair, exact)
    s.update(pair=pair.name, method="reference: exact pose, tol 2", seconds=float("nan"))
    rows.append(s)
    s = summary(pair, exact[consistent_pairs(pair.p1, pair.p2, exact)])
    s.update(pair=pair.name, method="reference: exact pose, tol 2, + consistency", seconds=float("nan"))
    rows.append(s)
    return rows


def nopose_report(rows: list, repetitive_names=()) -> tuple[list, dict]:
    pairs = list(dict.fromkeys(r["pair"] for r in rows))
    methods = list(dict.fromkeys(r["method"] for r in rows))
    cell = {(r["pair"], r["method"]): r for r in rows}
    L = ["## No pose: estimated geometry, then guided matching", "",
         "Cells: correct matches @ precision (one operating point each). OpenCV: BFMatcher + ratio 0.8, then the "
         "inliers of findFundamentalMat(USAC_MAGSAC, 1 px), or of findEssentialMat(USAC_MAGSAC) + recoverPose "
         "with K. Ours: `match_without_pose` (F: the oriented half-line from the epipole; with K: the E pose "
         "refined by `tol=\"auto\"`, full segments), the guided matches plus the first-pass matches on their "
         "final segment; `repeats rejected`: `reject_repeats=True`, without the matches whose keypoints have a "
         "twin in their own image inside the same band (`episeg_cv.matching.repeats`); `+ consistency`: also "
         "`consistency=True`, without the matches that disagree with the affine map of their 10 nearest "
         "first-pass matches (`episeg_cv.consistent_pairs`; with the exact pose, every match is an anchor). "
         "Held out: repetitive backward and the repetitive rooms of scene seeds 1 and 2 (other wall "
         "intensities, floor offsets and boxes) were added after every constant of the twin test and the "
         "consistency check was chosen.", "",
         "| pair | " + " | ".join(methods) + " |", "|---|" + "---|" * len(methods)]
    for p in pairs:
        L.append(f"| {p} | " + " | ".join(
            f"{cell[(p, m)]['correct']} @ {cell[(p, m)]['precision']:.3f}" for m in methods) + " |")
    ours = [m for m in methods if m.startswith("ours")]
    per = {m: {"precision": True, "more": True, "repetitive": True, "misses": []} for m in ours}
    rep_gain = {}
    for p in pairs:
        cv_best = max(cell[(p, m)]["correct"] for m in methods if m.startswith("OpenCV"))
        for m in ours:
            r, g = cell[(p, m)], per[m]
            if p in repetitive_names:
                gain = r["correct"] / cv_best - 1 if cv_best else np.inf
                rep_gain[f"{p}: {m}"] = (gain, r["precision"])
                if not (gain >= 0.2 and r["precision"] >= 0.95):
                    g["repetitive"] = False
                    g["misses"].append(f"{p}: {100 * gain:+.0f} % at {r['precision']:.3f}")
                continue
            if not r["precision"] >= 0.95:
                g["precision"] = False
                g["misses"].append(f"{p}: precision {r['precision']:.3f}")
            if not r["correct"] > cv_best:
                g["more"] = False
                g["misses"].append(f"{p}: {r['correct']} correct vs OpenCV's {cv_best}")
    yes = {True: "yes", False: "**no**"}
    L += ["", "Goals (issue 16), per configuration: precision >= 0.95 on every pair (repetitive texture apart); "
          "more correct matches than OpenCV's better pipeline (the larger count) on every pair; on repetitive "
          "texture >= +20 % correct matches at precision >= 0.95.", "",
          "| configuration | precision | more than OpenCV | repetitive | misses |", "|---|---|---|---|---|"]
    for m in ours:
        g = per[m]
        L.append(f"| {m} | {yes[g['precision']]} | {yes[g['more']]} | {yes[g['repetitive']]} | "
                 f"{'; '.join(g['misses']) or '-'} |")
    met = [m for m in ours if per[m]["precision"] and per[m]["more"] and per[m]["repetitive"]]
    L += ["", f"Every goal met by one configuration: **{', '.join(met) if met else 'none'}**."]
    return L, {"per_configuration": per, "repetitive": rep_gain, "met_by": met}
