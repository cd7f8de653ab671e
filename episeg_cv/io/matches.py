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
import zipfile
from pathlib import Path

import numpy as np

from .paths import input_file, output_file, read_json, written_atomically

__all__ = ["FORMAT", "FORMAT_VERSION", "write_matches", "read_matches", "json_number"]

FORMAT = "episeg-matches"
FORMAT_VERSION = 1
SUFFIXES = (".json", ".npz", ".csv")


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
    if path.suffix.lower() not in SUFFIXES:
        raise ValueError(f"matches file {str(path)!r} must end in .json, .npz or .csv")
    path = output_file(path, "matches file")
    k1 = np.asarray(keypoints1, np.float64).reshape(-1, 2)
    k2 = np.asarray(keypoints2, np.float64).reshape(-1, 2)
    m = np.asarray(matches, np.int64).reshape(-1, 2)
    d = np.asarray(distances, np.float64).reshape(-1)
    labels = [str(x) for x in labels]
    if not (len(m) == len(d) == len(labels)):
        raise ValueError(f"matches, distances and labels must have the same length, got {len(m)}, {len(d)}, {len(labels)}")
    extra = extra or {}
    suffix = path.suffix.lower()
    try:
        with written_atomically(path) as tmp:
            if suffix == ".json":
                out = {"meta": meta, "keypoints1": np.round(k1, 4).tolist(), "keypoints2": np.round(k2, 4).tolist(),
                       "matches": m.tolist(), "distances": [round(float(x), 5) for x in d], "labels": labels}
                out.update({k: _json_points(v) for k, v in extra.items()})
                tmp.write_text(json.dumps(out, separators=(",", ":")) + "\n")
            elif suffix == ".npz":
                np.savez_compressed(tmp, meta=np.array(json.dumps(meta)), keypoints1=k1, keypoints2=k2, matches=m,
                                    distances=d.astype(np.float32), labels=np.array(labels, dtype="U16"),
                                    **{k: np.asarray(v, np.float64) for k, v in extra.items()})
            else:  # .csv
                with tmp.open("w", newline="") as f:
                    w = csv.writer(f)
                    w.writerow(["x1", "y1", "x2", "y2", "distance", "label"])
                    for (i, j), dist, lab in zip(m, d, labels):
                        w.writerow([f"{k1[i, 0]:.4f}", f"{k1[i, 1]:.4f}", f"{k2[j, 0]:.4f}", f"{k2[j, 1]:.4f}",
                                    f"{dist:.5g}", lab])
    except OSError as exc:
        raise OSError(f"matches file {str(path)!r}: cannot write it ({exc.strerror or exc})") from None
    return path


def _json_points(points) -> list:
    """(N, 2) points as JSON lists, rounded; ``null`` where a coordinate is NaN (no position)."""
    return [[json_number(round(x, 4)), json_number(round(y, 4))] for x, y in np.asarray(points, np.float64).tolist()]


def read_matches(path) -> dict:
    """Read a ``.json`` or ``.npz`` matches file back into arrays (``meta`` as a dict).

    ``.csv`` files are for other tools (one row per match, without the
    keypoints): they are not read back.

    Raises
    ------
    FileNotFoundError, IsADirectoryError
        No such file.
    ValueError
        Another suffix, or a file that is not a matches file (unparseable, or a key missing or
        of the wrong shape), named with the key.
    """
    path = input_file(path, "matches file")
    suffix = path.suffix.lower()
    if suffix == ".csv":
        raise ValueError(f"matches file {str(path)!r}: .csv files are not read back (no keypoints in them); "
                         "write .json or .npz to read the matches again")
    if suffix not in (".json", ".npz"):
        raise ValueError(f"matches file {str(path)!r} must end in .json or .npz")
    if suffix == ".json":
        data = read_json(path, "matches file")
    else:
        try:
            with open(path, "rb") as fh, np.load(fh, allow_pickle=False) as z:  # (our handle: closed on any error)
                data = {k: z[k] for k in z.files}
        except (ValueError, OSError, EOFError, zipfile.BadZipFile) as exc:
            raise ValueError(f"matches file {str(path)!r} cannot be read: {type(exc).__name__}: "
                             f"{' '.join(str(exc).split())[:200]}") from None
    if not isinstance(data, dict):
        raise ValueError(f"matches file {str(path)!r}: the top level must be an object, got {type(data).__name__}")
    missing = [k for k in ("meta", "keypoints1", "keypoints2", "matches", "distances", "labels") if k not in data]
    if missing:
        raise ValueError(f"matches file {str(path)!r} is not an episeg matches file: missing {', '.join(missing)}")
    out = {}
    for k, v in data.items():
        try:
            if k == "meta":
                try:
                    out[k] = json.loads(str(v)) if suffix == ".npz" else v
                except json.JSONDecodeError as exc:
                    raise ValueError(f"expected a JSON object, got text that is not JSON ({exc})") from None
                if not isinstance(out[k], dict):
                    raise ValueError(f"expected an object, got {type(out[k]).__name__}")
            elif k.startswith("keypoints"):
                out[k] = _array(v, np.float64, (-1, 2))
            elif k == "matches":
                out[k] = _array(v, np.intp, (-1, 2))
            elif k == "distances":
                out[k] = _array(v, np.float64, (-1,))
            elif k == "labels":
                out[k] = np.asarray(v, dtype="U16").reshape(-1)
        except (ValueError, TypeError, OverflowError, RecursionError) as exc:
            raise ValueError(f"matches file {str(path)!r}: key '{k}': {' '.join(str(exc).split())[:160]}") from None
    n = len(out["matches"])
    if not len(out["distances"]) == len(out["labels"]) == n:
        raise ValueError(f"matches file {str(path)!r}: matches, distances and labels must have the same length, "
                         f"got {n}, {len(out['distances'])}, {len(out['labels'])}")
    for col, key in ((0, "keypoints1"), (1, "keypoints2")):
        if n and (out["matches"][:, col].min() < 0 or out["matches"][:, col].max() >= len(out[key])):
            raise ValueError(f"matches file {str(path)!r}: key 'matches': an index is out of range for the "
                             f"{len(out[key])} {key}")
    return out


def _array(value, dtype, shape) -> np.ndarray:
    arr = np.asarray(value, dtype=dtype)
    if arr.size == 0:
        return arr.reshape((0,) + shape[1:])
    if arr.ndim != len(shape) or (len(shape) == 2 and arr.shape[1] != shape[1]):
        raise ValueError(f"expected an array of shape {('N',) + shape[1:]}, got shape {arr.shape}")
    return arr
