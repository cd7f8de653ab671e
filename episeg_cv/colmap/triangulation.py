"""Triangulation of a database from :func:`~episeg_cv.colmap.match_model` with the known poses."""

from __future__ import annotations

import os
import shutil
from pathlib import Path

from ..interrupts import terminate_as_interrupt
from .database import remove_stale_partials
from .dbfeatures import reconstruction_from_database
from .poses import load_views
from .views import require_pycolmap

__all__ = ["triangulate", "check_triangulation_folder", "known_pose_reconstruction"]


def known_pose_reconstruction(database, views, rec=None):
    """The reconstruction (no points) that ``pycolmap.triangulate_points`` needs for ``database``.

    ``rec`` (the model's own) when the database's image and camera ids are the views' (a database
    written by :func:`match_model` from extracted features); otherwise (views given as a list, such
    as refined poses, or COLMAP's features, ``features="database"``) one with the database's
    cameras, rigs, frames and ids, found by image name, posed by the views.
    """
    pycolmap = require_pycolmap()
    db = pycolmap.Database.open(str(database))
    try:
        ids = {im.name: (int(im.image_id), int(im.camera_id)) for im in db.read_all_images()}
    finally:
        db.close()
    missing = [v.name for v in views if v.name not in ids]
    if missing:
        raise ValueError(f"image {missing[0]!r} of the model is not in database {str(database)!r}")
    if rec is not None and all(ids[v.name] == (v.image_id, v.camera_id) for v in views):
        return rec
    return reconstruction_from_database(database, views)


def triangulate(database, model, image_dir, output_dir, options=None):
    """Run ``pycolmap.triangulate_points`` on a database from :func:`match_model`.

    Parameters
    ----------
    database : str or Path
    model : str, Path or list of View
        The same model given to :func:`match_model` (its 3D points are cleared).
        The images are found in the database by name, so a database of
        COLMAP's features (other image ids) works too.
    image_dir, output_dir : str or Path
        ``output_dir`` is created; the triangulated model is written there (into a temporary
        folder first, then moved file by file, so an interrupted run leaves no half-written model).
        It may not be the input model's folder.
    options : pycolmap.IncrementalPipelineOptions, optional
        COLMAP's defaults otherwise. Note that they ignore two-view tracks
        (``triangulation.ignore_two_view_tracks``): a point needs three views.

    Returns
    -------
    pycolmap.Reconstruction
    """
    pycolmap = require_pycolmap()
    out = check_triangulation_folder(output_dir, model, image_dir)
    remove_stale_partials(out)
    views, rec = load_views(model, image_dir)
    rec = known_pose_reconstruction(database, views, rec)
    if options is None:
        options = pycolmap.IncrementalPipelineOptions()
    tmp = out.with_name(f".{out.name}.{os.getpid()}.partial")
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir(parents=True)
    try:
        with terminate_as_interrupt():
            result = pycolmap.triangulate_points(rec, str(database), str(image_dir), str(tmp), options=options)
            out.mkdir(parents=True, exist_ok=True)
            for f in sorted(tmp.iterdir()):  # the model's files, each replaced at once
                os.replace(f, out / f.name)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return result


def check_triangulation_folder(output_dir, model, image_dir=None) -> Path:
    """The folder a triangulated model goes to: not a file, not the input model's folder, not the image folder."""
    out = Path(output_dir)
    if out.exists() and not out.is_dir():
        raise ValueError(f"triangulation folder {str(out)!r} is a file, expected a folder")
    if not isinstance(model, (list, tuple)) and Path(model).is_dir() and out.is_dir() \
            and os.path.samefile(out, model):
        raise ValueError(f"triangulation folder {str(out)!r} is the input model's folder; its files would be "
                         "replaced: give another folder")
    if image_dir is not None and Path(image_dir).is_dir() and out.is_dir() and os.path.samefile(out, image_dir):
        raise ValueError(f"triangulation folder {str(out)!r} is the image folder: give another folder")
    parent = out.parent if str(out.parent) else Path(".")
    if not parent.is_dir():
        raise ValueError(f"triangulation folder {str(out)!r}: its parent folder does not exist")
    return out
