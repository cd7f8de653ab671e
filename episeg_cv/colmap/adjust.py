"""Poses that are off: refine a collection's poses before its matches are written (``refine_poses=True``).

Poses from odometry, GPS/IMU or a rig that drifted are off by fractions of a
degree. The segments, the collection's band and the track consensus all use
the poses, so errors the size of a few pixels cost correct matches and let
wrong ones through; COLMAP's pose-free matching does not suffer this.
:func:`adjust_poses` refines the poses from the collection's own matches, in
rounds:

1. match the collection with the current poses, with the run's own settings,
   into a temporary database (``run_round``, :func:`~.pipeline.match_model`);
2. triangulate it with those poses (:func:`~.triangulation.triangulate`,
   COLMAP's defaults);
3. bundle-adjust poses and points with pycolmap (intrinsics fixed, the gauge
   fixed by two cameras, a Cauchy loss of 1 px);
4. keep the scene where it was: the adjusted poses are mapped by the
   similarity that brings the adjusted points back onto the points
   triangulated with the current poses (:func:`similarity`,
   :func:`in_frame`), so that the given world frame, its scale and the depth
   ranges still hold, and only the cameras move. A view that sees fewer than
   :data:`MIN_POINTS` of the round's 3D points keeps its pose.

It stops when a round moves no view's image points by more than
:data:`MIN_CHANGE_PX` (:func:`change_px`). When that does not happen within
:data:`MAX_ROUNDS` rounds, the matches do not determine the poses better than
they are given, and the given poses are kept (with a warning). Measured in
scratch runs (COLMAP's features, matches triangulated with the true poses):
on the synthetic 12-view room (a 65-degree lens, thousands of points) poses
off by 0.25 and 0.5 degrees and 1.25 and 2.5 cm converge in 2 and 3 rounds to
0.006 degrees of relative rotation error, and the accurate 3D points are those
of the exact poses (4447 and 4449 against 4452; with the poses as given 3855
and 3704). On the real dinoSparseRing (an 11-degree lens on a small object,
about 350 points on COLMAP's features) rotation and translation trade off:
from the exact poses it converges in 2 rounds to poses 0.2 degrees away in
relative rotation (324 accurate points against 325); from poses off by 0.02
and 0.05 degrees and 0.2 and 0.5 mm (1-3 px) it restores the accurate
fraction (93.5 and 93.2 % against 89.7 and 89.2 % as given, with 319 and 328
points against 400 and 397), and from 0.1 degrees (6 px) it does not
converge and keeps them. ``benchmarks/noisy_poses.py`` measures it
at every level.
"""

from __future__ import annotations

import dataclasses
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .triangulation import triangulate
from .views import View, require_pycolmap

__all__ = ["PoseAdjustment", "adjust_poses", "similarity", "in_frame", "change_px", "MAX_ROUNDS", "MIN_CHANGE_PX",
           "MIN_POINTS", "CHANGE_PERCENTILE", "FUNCTION_TOLERANCE"]

#: Most rounds of match, triangulate, adjust.
MAX_ROUNDS = 8
#: A round that moves no view's image points by more than this (pixels) ends the refinement.
MIN_CHANGE_PX = 0.25
#: 3D points a view must see for its pose to be adjusted.
MIN_POINTS = 20
#: The percentile of the moves of a view's points that :func:`change_px` reports (high, but robust to a few).
CHANGE_PERCENTILE = 90.0
#: The bundle adjustment stops when an iteration lowers the cost by less than this fraction (Ceres's own
#: default; COLMAP's options set 0, so every solve ran its 100 iterations without converging). Measured
#: (scratch, noisy poses): on the 12-view room (0.5 px) 101 -> 33 iterations, 1.80 -> 0.69 s a solve; on
#: dinoSparseRing (2 px) 101 -> 69, 0.12 -> 0.08 s; the poses differ from the 100 iterations' by at most
#: 0.0067 px (95th percentile of a view's points' moves), 1/37 of :data:`MIN_CHANGE_PX`.
FUNCTION_TOLERANCE = 1e-6


@dataclass(frozen=True)
class PoseAdjustment:
    """The result of :func:`adjust_poses` (``MatchReport.poses``).

    Attributes
    ----------
    views : list of View
        The refined views, in the given world frame (``X_cam = R @ X_world + t``), the given
        intrinsics, depth ranges and ids; the given views when the refinement did not converge.
    rounds : int
        Rounds run (the last one adjusted nothing when too few images saw enough points).
    changes_px : list of float
        Per round that adjusted the poses, the largest effect of its pose change on any view's
        image points, pixels (:func:`change_px`).
    points : list of int
        3D points triangulated per round.
    converged : bool
        The last round moved no view by more than :data:`MIN_CHANGE_PX` (otherwise ``views`` are the
        given ones).
    seconds : float
        Wall time of the refinement.
    """

    views: list
    rounds: int
    changes_px: list
    points: list
    converged: bool
    seconds: float

    def summary(self) -> str:
        if not self.changes_px:
            return (f"poses kept as given: fewer than 3 images see {MIN_POINTS} or more of the "
                    f"{self.points[-1]} triangulated points")
        steps = ", ".join(f"{c:.2f}" for c in self.changes_px)
        head = (f"poses refined in {self.rounds} round(s)" if self.converged else
                f"poses kept as given: the refinement did not converge in {self.rounds} round(s)")
        return f"{head}; largest change per round: {steps} px"


def _project(view: View, X: np.ndarray) -> np.ndarray:
    x = (X @ view.R.T + view.t) @ view.K.T
    return x[:, :2] / x[:, 2:]


def change_px(before: View, after: View, points: np.ndarray) -> float:
    """How far a pose change moves the view's image points, pixels.

    The :data:`CHANGE_PERCENTILE` th percentile of the moves of ``points`` ``(N, 3)`` (world, in front of
    both poses) from their projection under ``before`` to that under ``after``. A rotation that a move of
    the centre compensates at the scene's depth (nearly so with a narrow lens) moves them little.

    >>> K = [[500, 0, 320], [0, 500, 240], [0, 0, 1]]
    >>> a = View("a.png", 1, 1, K, np.eye(3), [0, 0, 0], (640, 480))
    >>> b = dataclasses.replace(a, t=np.array([0.01, 0.0, 0.0]))   # 1 cm to the side
    >>> round(change_px(a, b, np.array([[0.0, 0.0, 5.0], [1.0, 0.0, 5.0]])), 3)   # 500 * 0.01 / 5
    1.0
    """
    moves = np.linalg.norm(_project(after, points) - _project(before, points), axis=1)
    return float(np.percentile(moves, CHANGE_PERCENTILE)) if len(moves) else 0.0


def similarity(source: np.ndarray, target: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """``(s, R, t)`` with ``target ~ s R source + t`` in least squares (Umeyama): points ``(N, 3)``, N >= 3.

    >>> X = np.array([[0, 0, 0], [1, 0, 0], [0, 2, 0], [0, 0, 3.0]])
    >>> s, R, t = similarity(X, 2 * X + [1, 2, 3])
    >>> round(s, 9), np.allclose(R, np.eye(3)), np.round(t, 9).tolist()
    (2.0, True, [1.0, 2.0, 3.0])
    """
    source, target = np.asarray(source, dtype=np.float64), np.asarray(target, dtype=np.float64)
    if source.shape != target.shape or source.ndim != 2 or source.shape[1] != 3 or len(source) < 3:
        raise ValueError(f"source and target must be two (N, 3) arrays of the same N >= 3, got shapes "
                         f"{source.shape} and {target.shape}")
    ms, mt = source.mean(axis=0), target.mean(axis=0)
    A, B = source - ms, target - mt
    U, d, Vt = np.linalg.svd(B.T @ A)
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
    R = U @ D @ Vt
    s = float(np.trace(np.diag(d) @ D) / (A**2).sum())
    return s, R, mt - s * R @ ms


def in_frame(views: list, s: float, R: np.ndarray, t: np.ndarray) -> list:
    """The cameras of ``views`` in the frame ``X' = s R X + t`` (their camera frames scaled by ``s``).

    >>> K = [[500, 0, 320], [0, 500, 240], [0, 0, 1]]
    >>> v = View("a.png", 1, 1, K, np.eye(3), [0, 0, 1.0], (640, 480))
    >>> w = in_frame([v], 2.0, np.eye(3), np.array([0, 0, 4.0]))[0]
    >>> w.center.tolist(), w.t.tolist()                   # the centre moved with the world; depths doubled
    ([0.0, 0.0, 2.0], [0.0, 0.0, -2.0])
    """
    out = []
    for v in views:  # X_cam = Rv X + tv, X = R^T (X' - t) / s; metric camera frames scale with the world: times s
        Rv = v.R @ R.T
        out.append(dataclasses.replace(v, R=Rv, t=s * v.t - Rv @ t))
    return out


def _adjusted(rec, views: list) -> tuple[list, dict]:
    """The views with the reconstruction's poses (those seeing at least :data:`MIN_POINTS` points), and the
    points each of those sees (``{name: (N, 3)}``, in the reconstruction's frame)."""
    by_name = {im.name: im for im in rec.images.values()}
    out, seen = [], {}
    for v in views:
        im = by_name.get(v.name)
        ids = [p.point3D_id for p in im.points2D if p.has_point3D()] if im is not None and im.has_pose else []
        if len(ids) < MIN_POINTS:
            out.append(v)
            continue
        P = np.asarray(im.cam_from_world().matrix(), dtype=np.float64)
        seen[v.name] = np.array([rec.points3D[i].xyz for i in ids])
        out.append(dataclasses.replace(v, R=P[:, :3], t=P[:, 3]))
    return out, seen


def _bundle_adjust(rec) -> None:
    """Poses and points of ``rec`` adjusted in place: intrinsics fixed, the gauge fixed by two cameras (COLMAP's
    ``TWO_CAMS_FROM_WORLD``; without it the normal equations are singular), a Cauchy loss of 1 px, stopped at
    :data:`FUNCTION_TOLERANCE`. Only the images that see :data:`MIN_POINTS` or more points take part: with
    images of 11-18 points the problem of dinoSparseRing on COLMAP's features was rank deficient, and Ceres
    failed its steps."""
    pycolmap = require_pycolmap()
    options = pycolmap.BundleAdjustmentOptions()
    options.refine_focal_length = options.refine_principal_point = options.refine_extra_params = False
    options.print_summary = False
    options.ceres.loss_function_type = pycolmap.LossFunctionType.CAUCHY
    options.ceres.loss_function_scale = 1.0
    options.ceres.solver_options.function_tolerance = FUNCTION_TOLERANCE
    config = pycolmap.BundleAdjustmentConfig()
    for image_id in rec.reg_image_ids():
        if rec.images[image_id].num_points3D >= MIN_POINTS:
            config.add_image(image_id)
    for camera_id in rec.cameras:
        config.set_constant_cam_intrinsics(camera_id)
    config.fix_gauge(pycolmap.BundleAdjustmentGauge.TWO_CAMS_FROM_WORLD)
    pycolmap.create_default_bundle_adjuster(options, config, rec).solve()


def adjust_poses(views: list, image_dir, run_round, max_rounds: int | None = None,
                 min_change_px: float | None = None, warn=None, progress=None) -> PoseAdjustment:
    """Refine the poses of ``views`` (module docstring).

    Parameters
    ----------
    views : list of View
        The given poses, with their depth ranges.
    image_dir : str or Path
    run_round : callable
        ``run_round(views, database)`` matches the collection with ``views`` into the (temporary) database
        path ``database``, replacing what it holds.
    max_rounds : int, optional
        Default :data:`MAX_ROUNDS`.
    min_change_px : float, optional
        Default :data:`MIN_CHANGE_PX`.
    warn : callable, optional
        Receives a warning when the matches are too few to adjust anything (the given poses are kept).
    progress : callable, optional
        Called as ``progress("poses", round, max_rounds)`` after each round.

    Returns
    -------
    PoseAdjustment
    """
    t0 = time.perf_counter()
    max_rounds = MAX_ROUNDS if max_rounds is None else max_rounds
    min_change_px = MIN_CHANGE_PX if min_change_px is None else min_change_px
    current, changes, points, converged = list(views), [], [], False
    with tempfile.TemporaryDirectory(prefix="episeg_poses_") as tmp:
        database = Path(tmp) / "round.db"
        for k in range(max_rounds):
            run_round(current, database)
            rec = triangulate(database, current, image_dir, Path(tmp) / f"round{k}")
            points.append(int(rec.num_points3D()))
            _, seen = _adjusted(rec, current)  # each view's points, triangulated with the current poses
            if len(seen) < 3:
                if warn is not None:
                    warn(f"warning: pose refinement: only {len(seen)} image(s) see {MIN_POINTS} or more "
                         "triangulated points; the poses are kept as they are")
                break
            before = {i: p.xyz.copy() for i, p in rec.points3D.items()}
            _bundle_adjust(rec)
            moved, _ = _adjusted(rec, current)
            # the scene stays where it was (the given frame), the cameras move: the similarity that brings the
            # adjusted points back onto the points triangulated with the current poses
            ids = sorted(before)
            moved = in_frame(moved, *similarity(np.array([rec.points3D[i].xyz for i in ids]),
                                                np.array([before[i] for i in ids])))
            adjusted = [m if c.name in seen else c for m, c in zip(moved, current)]
            changes.append(max(change_px(c, a, seen[c.name]) for c, a in zip(current, adjusted) if c.name in seen))
            current = adjusted
            converged = changes[-1] < min_change_px
            if progress is not None:
                progress("poses", k + 1, max_rounds)
            if converged:
                break
    if not converged and changes and warn is not None:
        warn(f"warning: pose refinement did not converge in {len(changes)} rounds (largest change per round: "
             + ", ".join(f"{c:.1f}" for c in changes) + " px): the matches do not determine the poses better than "
             "given (a narrow lens or few points); the given poses are used")
    return PoseAdjustment(current if converged else list(views), len(points), changes, points, converged,
                          time.perf_counter() - t0)
