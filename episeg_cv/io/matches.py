"""The matches file: what ``episeg match`` and ``episeg demo`` write (format ``episeg-matches``).

Version 1, in three encodings chosen by the file suffix.

JSON::

    {"meta": {"format": "episeg-matches", "format_version": 1, "command", "episeg_cv", "opencv",
              "numpy", "image1", "image2", "calib", "convention", "undistorted",
              "settings": {...}, "counts": {"keypoints1", "keypoints2", "matches", <label>: n, ...}},
     "keypoints1": [[x, y], ...],          # as detected, pixels of the input image 1
     "keypoints2": [[x, y], ...],
     "matches": [[i1, i2], ...],           # indices into keypoints1 / keypoints2
     "distances": [d, ...],                # descriptor distances, as cv2.BFMatcher reports
     "labels": ["on_segment", ...]}        # Rejection.NAMES of each match (episeg_cv.explain_pairs)

With lens distortion, ``keypoints1_undistorted`` and ``keypoints2_undistorted``
(the positions the constraint used) are added. ``.npz`` holds the same names as
arrays (``meta`` as a JSON string); ``.csv`` has one row per match with the
header ``x1,y1,x2,y2,distance,label``.
"""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np

__all__ = ["FORMAT", "FORMAT_VERSION", "write_matches", "read_matches", "json_number"]

FORMAT = "episeg-matches"
FORMAT_VERSION = 1


def json_number(x):
    """A finite float, or None (JSON has no NaN or inf)."""
    x = float(x)
    return x if np.isfinite(x) else None


def write_matches(path, meta: dict, keypoints1, keypoints2, matches, distances, labels, extra=None) -> Path:
    """Write a matches file in the documented format; the suffix picks JSON, NPZ or CSV.

    Parameters
    ----------
    path : str or os.PathLike
        ``*.json``, ``*.npz`` or ``*.csv``.
    meta : dict
        Settings, versions and counts (JSON-serialisable).
    keypoints1, keypoints2 : (N1, 2), (N2, 2) float
    matches : (K, 2) int
    distances : (K,) float
    labels : sequence of str, length K
    extra : dict of str to (N, 2) arrays, optional
        More keypoint arrays (e.g. ``keypoints1_undistorted``); JSON and NPZ only.

    Returns
    -------
    pathlib.Path
    """
    path = Path(path)
    k1 = np.asarray(keypoints1, np.float64).reshape(-1, 2)
    k2 = np.asarray(keypoints2, np.float64).reshape(-1, 2)
    m = np.asarray(matches, np.int64).reshape(-1, 2)
    d = np.asarray(distances, np.float64).reshape(-1)
    labels = [str(x) for x in labels]
    if not (len(m) == len(d) == len(labels)):
        raise ValueError(f"matches, distances and labels must have the same length, got {len(m)}, {len(d)}, {len(labels)}")
    extra = extra or {}
    suffix = path.suffix.lower()
    if path.parent != Path(""):
        path.parent.mkdir(parents=True, exist_ok=True)
    if suffix == ".json":
        out = {"meta": meta, "keypoints1": np.round(k1, 4).tolist(), "keypoints2": np.round(k2, 4).tolist(),
               "matches": m.tolist(), "distances": [round(float(x), 5) for x in d], "labels": labels}
        out.update({k: np.round(np.asarray(v, np.float64), 4).tolist() for k, v in extra.items()})
        path.write_text(json.dumps(out, separators=(",", ":")) + "\n")
    elif suffix == ".npz":
        np.savez_compressed(path, meta=np.array(json.dumps(meta)), keypoints1=k1, keypoints2=k2, matches=m,
                            distances=d.astype(np.float32), labels=np.array(labels, dtype="U16"),
                            **{k: np.asarray(v, np.float64) for k, v in extra.items()})
    elif suffix == ".csv":
        with path.open("w", newline="") as f:
            w = csv.writer(f)
            w.writerow(["x1", "y1", "x2", "y2", "distance", "label"])
            for (i, j), dist, lab in zip(m, d, labels):
                w.writerow([f"{k1[i, 0]:.4f}", f"{k1[i, 1]:.4f}", f"{k2[j, 0]:.4f}", f"{k2[j, 1]:.4f}",
                            f"{dist:.5g}", lab])
    else:
        raise ValueError(f"path must end in .json, .npz or .csv, got {path.name!r}")
    return path


def read_matches(path) -> dict:
    """Read a ``.json`` or ``.npz`` matches file back into arrays (``meta`` as a dict)."""
    path = Path(path)
    if path.suffix.lower() == ".npz":
        with np.load(path) as z:
            out = {k: z[k] for k in z.files}
        out["meta"] = json.loads(str(out["meta"]))
        return out
    data = json.loads(path.read_text())
    out = {"meta": data["meta"], "labels": np.array(data["labels"], dtype="U16"),
           "matches": np.array(data["matches"], np.intp).reshape(-1, 2),
           "distances": np.array(data["distances"], np.float64)}
    for k, v in data.items():
        if k.startswith("keypoints"):
            out[k] = np.array(v, np.float64).reshape(-1, 2)
    return out
