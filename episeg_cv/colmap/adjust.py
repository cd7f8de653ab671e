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
3. bundle-adjust poses and points (``pycolmap.bundle_adjustment``; the
   intrinsics stay fixed);
4. map the adjusted poses back to the given world frame (:func:`align`: the
   rotation, scale and translation that best bring their orientations and
   camera centres onto the given poses, the same target every round), so that
   depth ranges and the user's frame still hold. A view that sees fewer than :data:`MIN_POINTS` of the
   round's 3D points keeps its pose (nothing determines it).

It stops when a round moves no view's image points by more than
:data:`MIN_CHANGE_PX` (:func:`change_px`). When that does not happen within
:data:`MAX_ROUNDS` rounds, the matches do not determine the poses better than
they are given, and the given poses are kept (with a warning). On the
synthetic 12-view room (a 90-degree lens, thousands of points; COLMAP's
features) poses off by 0.25 and 0.5 degrees and 1.25 and 2.5 cm converge in 2
and 3 rounds to 0.005 degrees of relative rotation error, and the matches
then equal those of the exact poses. On the real dinoSparseRing (an 11-degree
lens on a small object, about 350 points) it never converges, even from the
exact poses: rotation and translation trade off there, and the adjustment
wanders by tenths of a degree; those poses are kept as given. What it buys and costs at each level of pose noise is measured in
``benchmarks/noisy_poses.py``.
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

__all__ = ["PoseAdjustment", "adjust_poses", "align", "change_px", "MAX_ROUNDS", "MIN_CHANGE_PX", "MIN_POINTS"]

#: Most rounds of match, triangulate, adjust.
MAX_ROUNDS = 8
#: A round that moves no view's image points by more than this (pixels) ends the refinement.
MIN_CHANGE_PX = 0.25
#: 3D points a view must see for its pose to be adjusted.
MIN_POINTS = 20


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
        Per round that adjusted the poses, the largest effect of its pose change on any view's image points, pixels
        (:func:`change_px`).
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
        steps = ", ".join(f"{c:.2f}" for c in self.changes_px) or "none"
        head = (f"poses refined in {self.rounds} round(s)" if self.converged else
                f"poses kept as given: the refinement did not converge in {self.rounds} round(s)")
        return f"{head}; largest change per round: {steps} px"


def _rotation_angle(R: np.ndarray) -> float:
    return float(np.arccos(np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0)))


def change_px(before: View, after: View, depth: float) -> float:
    """How far a pose change moves the view's image points, pixels: ``f (theta + |dC| / depth)``.

    ``theta`` is the angle of the rotation change (radians), ``dC`` the move of the camera centre and
    ``depth`` a typical depth of the scene in the view (world units), ``f`` the mean focal length.

    >>> K = [[500, 0, 320], [0, 500, 240], [0, 0, 1]]
    >>> a = View("a.png", 1, 1, K, np.eye(3), [0, 0, 0], (640, 480))
    >>> b = dataclasses.replace(a, t=np.array([0.01, 0.0, 0.0]))   # 1 cm to the side
    >>> round(change_px(a, b, depth=5.0), 3)                        # 500 * 0.01 / 5
    1.0
    """
    theta = _rotation_angle(after.R @ before.R.T)
    shift = float(np.linalg.norm(after.center - before.center))
    f = 0.5 * (before.K[0, 0] + before.K[1, 1])
    return float(f * (theta + (shift / depth if depth > 0 else 0.0)))


def align(given: list, adjusted: list) -> list:
    """``adjusted`` mapped into the frame of ``given`` (the same views, in the same order).

    A bundle adjustment fixes its gauge (frame and scale) its own way. The similarity
    ``X_given = s Ra X_adjusted + ta`` is chosen with ``Ra`` the rotation nearest to the mean of
    ``R_given_i^T R_adjusted_i``, ``s`` and ``ta`` by least squares on the camera centres (``s = 1`` when
    the centres coincide, as on a rotating rig).

    >>> K = [[500, 0, 320], [0, 500, 240], [0, 0, 1]]
    >>> g = [View(f"{k}.png", k + 1, 1, K, np.eye(3), [-k, 0, 0], (640, 480)) for k in range(3)]
    >>> moved = [dataclasses.replace(v, t=2 * v.t + np.array([0, 0, 1.0])) for v in g]   # scaled, shifted
    >>> [np.allclose(a.t, v.t) for a, v in zip(align(g, moved), g)]
    [True, True, True]
    """
    M = sum(v.R.T @ a.R for v, a in zip(given, adjusted))
    U, _, Vt = np.linalg.svd(M)
    Ra = U @ np.diag([1.0, 1.0, np.linalg.det(U @ Vt)]) @ Vt
    Cg = np.array([v.center for v in given])
    Ca = np.array([a.center for a in adjusted]) @ Ra.T
    A, B = Cg - Cg.mean(axis=0), Ca - Ca.mean(axis=0)
    spread = float((B**2).sum())
    s = float((A * B).sum()) / spread if spread > 1e-12 * max(1.0, float((A**2).sum())) else 1.0
    s = s if s > 0 else 1.0
    ta = Cg.mean(axis=0) - s * Ca.mean(axis=0)
    out = []
    for a in adjusted:  # X_cam = R X_adj + t, X_adj = Ra^T (X_given - ta) / s; cameras keep metric depth: times s
        R = a.R @ Ra.T
        out.append(dataclasses.replace(a, R=R, t=s * a.t - R @ ta))
    return out


def _adjusted(rec, views: list) -> tuple[list, dict]:
    """The views with the reconstruction's poses (those seeing at least :data:`MIN_POINTS` points), and each
    view's median depth of the points it sees (``{name: depth}``, views with too few points left out)."""
    by_name = {im.name: im for im in rec.images.values()}
    out, depths = [], {}
    for v in views:
        im = by_name.get(v.name)
        ids = [p.point3D_id for p in im.points2D if p.has_point3D()] if im is not None and im.has_pose else []
        if len(ids) < MIN_POINTS:
            out.append(v)
            continue
        P = np.asarray(im.cam_from_world().matrix(), dtype=np.float64)
        X = np.array([rec.points3D[i].xyz for i in ids])
        depths[v.name] = float(np.median(X @ P[:, :3][2] + P[2, 3]))
        out.append(dataclasses.replace(v, R=P[:, :3], t=P[:, 3]))
    return out, depths


def _bundle_adjust(rec) -> None:
    """Poses and points of ``rec`` adjusted in place: intrinsics fixed, the gauge fixed by two cameras (COLMAP's
    ``TWO_CAMS_FROM_WORLD``; without it the normal equations are singular), a Cauchy loss of 1 px."""
    pycolmap = require_pycolmap()
    options = pycolmap.BundleAdjustmentOptions()
    options.refine_focal_length = options.refine_principal_point = options.refine_extra_params = False
    options.print_summary = False
    options.ceres.loss_function_type = pycolmap.LossFunctionType.CAUCHY
    options.ceres.loss_function_scale = 1.0
    config = pycolmap.BundleAdjustmentConfig()
    for image_id in rec.reg_image_ids():
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
            _, depths = _adjusted(rec, current)
            if len(depths) < 3:
                if warn is not None:
                    warn(f"warning: pose refinement: only {len(depths)} image(s) see {MIN_POINTS} or more "
                         "triangulated points; the poses are kept as they are")
                break
            _bundle_adjust(rec)
            moved, _ = _adjusted(rec, current)
            keep = [v.name in depths for v in current]
            aligned = iter(align([v for v, k in zip(views, keep) if k], [m for m, k in zip(moved, keep) if k]))
            adjusted = [next(aligned) if k else c for c, k in zip(current, keep)]
            changes.append(max(change_px(c, a, depths[c.name]) for c, a, k in zip(current, adjusted, keep) if k))
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
