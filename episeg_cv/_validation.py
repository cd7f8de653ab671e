"""Input checks shared by the public API.

Every check raises ``TypeError`` (wrong kind of object or dtype) or
``ValueError`` (wrong shape or value) with a message that names the argument,
what was expected, and what was given. None of them uses ``assert``.
"""

from __future__ import annotations

import logging
import math
import numbers

import cv2
import numpy as np

from ._finite_kernels import largest_magnitude

#: Orthonormality error ``|R^T R - I|`` (and ``|det R - 1|``) below which ``R`` is used as given.
ROTATION_ATOL = 1e-9


def _shape_str(shape) -> str:
    return "(" + ", ".join("N" if s is None else str(s) for s in shape) + ")"


def as_array(x, name: str, shape: tuple, *, dtype=np.float64, finite: bool = True) -> np.ndarray:
    """Return ``x`` as a contiguous array of ``dtype`` with the given shape.

    ``None`` in ``shape`` matches any length. Raises ``TypeError`` when ``x``
    is not numeric and ``ValueError`` for a wrong shape or a non-finite value.
    """
    if isinstance(x, (str, bytes)) or x is None:
        raise TypeError(f"{name} must be a numeric array of shape {_shape_str(shape)}, got {type(x).__name__}")
    try:
        arr = np.asarray(x)
    except (ValueError, TypeError) as exc:  # ragged input
        raise ValueError(f"{name} must be a numeric array of shape {_shape_str(shape)}: {exc}") from None
    if arr.dtype == object or not (np.issubdtype(arr.dtype, np.number) or arr.dtype == bool):
        raise TypeError(f"{name} must be a numeric array of shape {_shape_str(shape)}, got dtype {arr.dtype}")
    if np.iscomplexobj(arr):
        raise TypeError(f"{name} must be real, got dtype {arr.dtype}")
    if arr.ndim != len(shape) or any(s is not None and s != a for s, a in zip(shape, arr.shape)):
        raise ValueError(f"{name} must have shape {_shape_str(shape)}, got shape {arr.shape}")
    arr = np.ascontiguousarray(arr, dtype=dtype)
    if finite and arr.size and not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} must be finite, got NaN or inf")
    return arr


def as_points(x, name: str) -> np.ndarray:
    """``(N, 2)`` finite float64 pixel coordinates. An empty list gives ``(0, 2)``."""
    if isinstance(x, (list, tuple)) and len(x) == 0:
        return np.zeros((0, 2))
    return as_array(x, name, (None, 2))


def as_camera_matrix(K, name: str) -> np.ndarray:
    """Check an intrinsic matrix: finite ``(3, 3)``, upper triangular, last row ``[0, 0, 1]``, positive
    focal lengths, and well conditioned (condition number at most 1e12)."""
    K = as_array(K, name, (3, 3))
    if K[1, 0] != 0 or K[2, 0] != 0 or K[2, 1] != 0 or K[2, 2] != 1:
        raise ValueError(f"{name} must be upper triangular with last row [0, 0, 1], got {_inline(K)}")
    if not (K[0, 0] > 0 and K[1, 1] > 0):
        raise ValueError(f"{name} must have positive focal lengths K[0, 0] and K[1, 1] (pixels), "
                         f"got {K[0, 0]:g} and {K[1, 1]:g}")
    cond = np.linalg.cond(K)
    if not np.isfinite(cond) or cond > 1e12:
        raise ValueError(f"{name} is numerically singular (condition number {cond:.2g} > 1e12): focal lengths "
                         f"{K[0, 0]:g}, {K[1, 1]:g}, skew {K[0, 1]:g} and principal point ({K[0, 2]:g}, {K[1, 2]:g}) "
                         "differ by too many orders of magnitude")
    return K


def _inline(a: np.ndarray) -> str:
    return np.array2string(np.asarray(a), separator=", ", max_line_width=10**6).replace("\n", "")


#: Largest orthonormality error ``max |R^T R - I|`` that is treated as rounding and repaired.
ROTATION_REPAIR_ATOL = 1e-3

_log = logging.getLogger("episeg_cv")


def as_rotation(R, name: str) -> np.ndarray:
    """Check a rotation matrix, repairing the rounding of real calibration files.

    ``R`` must be orthonormal with determinant +1. Files written with a few
    decimals (or float32) are not exactly orthonormal: up to an error
    ``max |R^T R - I|`` of :data:`ROTATION_REPAIR_ATOL` (1e-3) ``R`` is replaced
    by the nearest rotation (the polar factor of its SVD), and the repair is
    logged at INFO level on the ``episeg_cv`` logger (``episeg -v`` shows it).
    A larger error, or a reflection, is refused.
    """
    R = as_array(R, name, (3, 3))
    err = float(np.abs(R.T @ R - np.eye(3)).max())
    if err > ROTATION_REPAIR_ATOL:
        raise ValueError(f"{name} must be a rotation matrix (R.T @ R = I within {ROTATION_REPAIR_ATOL:g}), "
                         f"got error {err:.3g}")
    det = np.linalg.det(R)
    if not det > 0:
        raise ValueError(f"{name} must be a rotation matrix with det +1, got det {det:.6g} (a reflection)")
    if err > ROTATION_ATOL or abs(det - 1.0) > ROTATION_ATOL:
        U, _, Vt = np.linalg.svd(R)
        fixed = np.ascontiguousarray(U @ Vt)
        _log.info("%s was not orthonormal (error %.2g, det %.9g): replaced by the nearest rotation (it moved by %.2g)",
                  name, err, det, float(np.abs(fixed - R).max()))
        R = fixed
    return R


def as_vector3(t, name: str) -> np.ndarray:
    """A finite 3-vector; ``(3,)``, ``(3, 1)`` and ``(1, 3)`` are accepted."""
    arr = t
    if not isinstance(t, (str, bytes)) and t is not None:
        try:
            arr = np.asarray(t)
        except (ValueError, TypeError) as exc:  # ragged input
            raise ValueError(f"{name} must be a numeric array of shape (3,): {exc}") from None
    if isinstance(arr, np.ndarray) and arr.size == 3 and arr.ndim <= 2:
        arr = arr.reshape(3)
    return as_array(arr, name, (3,))


def as_covariance(cov, name: str, n: int = 6) -> np.ndarray:
    """A finite, symmetric, positive semi-definite ``(n, n)`` covariance (symmetrised; float64).

    Symmetry and the smallest eigenvalue are checked relative to the largest
    entry (``1e-9``), so that rounding in a file does not make it fail.
    """
    C = as_array(cov, name, (n, n))
    scale = float(np.abs(C).max())
    if float(np.abs(C - C.T).max()) > 1e-9 * scale:
        raise ValueError(f"{name} must be symmetric, got max |C - C^T| = {float(np.abs(C - C.T).max()):.3g}")
    C = 0.5 * (C + C.T)
    low = float(np.linalg.eigvalsh(C).min()) if scale > 0 else 0.0
    if low < -1e-9 * scale:
        raise ValueError(f"{name} must be positive semi-definite, got an eigenvalue {low:.3g}")
    return C


def as_image_size(size, name: str) -> tuple[int, int]:
    """``(width, height)`` as two positive integers."""
    shown = short_repr(size)
    if isinstance(size, (str, bytes)) or size is None or not hasattr(size, "__len__") or len(size) != 2:
        raise ValueError(f"{name} must be (width, height) in pixels, got {shown}")
    out = []
    for v in size:
        if isinstance(v, (bool, np.bool_)) or not isinstance(v, numbers.Real):
            raise TypeError(f"{name} must hold two numbers (width, height), got {shown}")
        if not np.isfinite(v) or v != int(v) or v <= 0 or v > MAX_IMAGE_SIDE:
            raise ValueError(f"{name} must be two positive integers (width, height), at most {MAX_IMAGE_SIDE}, "
                             f"got {shown}")
        out.append(int(v))
    return out[0], out[1]


#: The largest image side accepted (pixels).
MAX_IMAGE_SIDE = 1 << 20


def short_repr(x, limit: int = 80) -> str:
    """A one-line repr of ``x``, cut at ``limit`` characters."""
    text = " ".join(repr(x).split())
    return text if len(text) <= limit else text[:limit - 3] + "..."


def as_nonnegative(x, name: str) -> float:
    """A finite scalar ``>= 0``."""
    if isinstance(x, (bool, np.bool_)) or not isinstance(x, numbers.Real):
        raise TypeError(f"{name} must be a real number, got {type(x).__name__}")
    if not np.isfinite(x) or x < 0:
        raise ValueError(f"{name} must be a finite number >= 0, got {x!r}")
    return float(x)


#: Scalar types that :func:`as_depth_range` checks without numpy (bool is not one).
_REAL_SCALARS = (float, int, np.float64, np.float32, np.int64, np.int32)


def as_depth_range(depth_range, n: int | None, name: str = "depth_range") -> tuple[np.ndarray, np.ndarray]:
    """``(zmin, zmax)`` as two float arrays broadcastable to ``(n,)``.

    Each bound is a scalar or an ``(n,)`` array (any common length when ``n``
    is None). Requires ``0 <= zmin < zmax``; ``zmax`` may be ``inf``; NaN is refused.
    """
    if isinstance(depth_range, (str, bytes)) or not hasattr(depth_range, "__len__") or len(depth_range) != 2:
        raise ValueError(f"{name} must be a pair (zmin, zmax), got {depth_range!r}")
    if all(type(v) in _REAL_SCALARS for v in depth_range):  # the common case, without numpy's overhead
        bounds = [float(v) for v in depth_range]
        for label, v in zip(("zmin", "zmax"), bounds):
            if math.isnan(v):
                raise ValueError(f"{name} {label} must not be NaN")
        zmin, zmax = bounds
        if zmin < 0 or math.isinf(zmin):
            raise ValueError(f"{name} zmin must be finite and >= 0, got {depth_range[0]!r}")
        if zmin >= zmax:
            raise ValueError(f"{name} must have zmin < zmax, got {depth_range!r}")
        return np.array(zmin), np.array(zmax)
    bounds = []
    for label, v in zip(("zmin", "zmax"), depth_range):
        arr = np.asarray(v)
        if arr.dtype == object or not (np.issubdtype(arr.dtype, np.integer) or np.issubdtype(arr.dtype, np.floating)):
            raise TypeError(f"{name} {label} must be a number or an (N,) array, got {type(v).__name__}")
        if arr.ndim == 1 and n is None:
            n = arr.shape[0]
        if arr.ndim > 1 or (arr.ndim == 1 and arr.shape[0] != n):
            raise ValueError(f"{name} {label} must be a scalar or have shape ({n},), got shape {arr.shape}")
        arr = arr.astype(np.float64)
        if np.isnan(arr).any():
            raise ValueError(f"{name} {label} must not be NaN")
        bounds.append(arr)
    zmin, zmax = bounds
    if np.any(zmin < 0) or np.any(np.isinf(zmin)):
        raise ValueError(f"{name} zmin must be finite and >= 0, got {depth_range[0]!r}")
    if np.any(zmin >= zmax):
        raise ValueError(f"{name} must have zmin < zmax, got {depth_range!r}")
    return zmin, zmax


def as_positive_int(x, name: str) -> int:
    """An integer ``>= 1`` (a bool is refused; so is a float, even a whole one)."""
    if isinstance(x, (bool, np.bool_)) or not isinstance(x, (int, np.integer)):
        raise TypeError(f"{name} must be a positive integer (>= 1), got {type(x).__name__}")
    if x < 1:
        raise ValueError(f"{name} must be a positive integer (>= 1), got {x}")
    return int(x)


def as_count(x, name: str) -> int:
    """An integer ``>= 0``."""
    if isinstance(x, (bool, np.bool_)) or not isinstance(x, (int, np.integer)) or x < 0:
        raise ValueError(f"{name} must be an integer >= 0, got {x!r}")
    return int(x)


def as_ratio(x, name: str) -> float:
    """A number in ``(0, 1]``."""
    if isinstance(x, (bool, np.bool_)) or not isinstance(x, (int, float, np.integer, np.floating)) or not 0 < x <= 1:
        raise ValueError(f"{name} must be in (0, 1], got {x!r}")
    return float(x)


def as_choice(x, name: str, choices: tuple) -> str:
    """One of the strings ``choices``."""
    if not isinstance(x, str) or x not in choices:
        raise ValueError(f"{name} must be one of {choices}, got {x!r}")
    return x


# -- descriptors and keypoints --------------------------------------------------------------
_NORMS = {cv2.NORM_L1: "l1", cv2.NORM_L2: "l2", cv2.NORM_L2SQR: "l2sqr", cv2.NORM_HAMMING: "hamming",
          "l1": "l1", "l2": "l2", "l2sqr": "l2sqr", "hamming": "hamming"}


def as_norm(norm, name: str = "normType") -> str:
    """``cv2.NORM_L1/L2/L2SQR/HAMMING`` or their names -> ``"l1"``, ``"l2"``, ``"l2sqr"`` or ``"hamming"``."""
    key = norm.lower() if isinstance(norm, str) else norm
    if isinstance(key, (bool, np.bool_)) or key not in _NORMS:
        raise ValueError(f"{name} must be cv2.NORM_L1, cv2.NORM_L2, cv2.NORM_L2SQR or cv2.NORM_HAMMING "
                         f"(or 'l1', 'l2', 'l2sqr', 'hamming'), got {norm!r}")
    return _NORMS[key]


def as_descriptor_pair(descriptors1, descriptors2, norm: str, names=("descriptors1", "descriptors2")):
    """Validate two descriptor arrays against each other and the norm; returns them as arrays.

    ``None`` (what cv2 detectors return for no keypoints) is an empty array of the other's width.
    float32, float64 (for L1/L2) and uint8 are accepted; both must have the same dtype and width.
    """
    out = []
    for name, d in zip(names, (descriptors1, descriptors2)):
        if d is None:
            other = descriptors2 if name == names[0] else descriptors1
            other = np.asarray(other) if other is not None else np.zeros((0, 0), np.float32)
            d = np.zeros((0, other.shape[1] if other.ndim == 2 else 0), dtype=other.dtype)
        d = np.asarray(d)
        if d.dtype not in (np.float32, np.float64, np.uint8):
            raise TypeError(f"{name} must be float32 or uint8 (as OpenCV's detectors give), got dtype {d.dtype}")
        if d.size == 0:
            d = d.reshape(0, d.shape[1] if d.ndim == 2 else 0)
            if norm == "hamming":
                d = d.astype(np.uint8)
        if d.ndim != 2:
            raise ValueError(f"{name} must have shape (N, D), got shape {d.shape}")
        if d.dtype != np.uint8 and d.size:
            big = largest_magnitude(d)  # NaN if any is NaN, inf if any is infinite (one pass)
            if not np.isfinite(big):
                raise ValueError(f"{name} must be finite, got NaN or inf")
            if d.dtype == np.float64 and big > _FLOAT32_SAFE:
                raise ValueError(f"{name} must fit in float32 (distances are computed in float32, as cv2 does), "
                                 f"got a value of magnitude {big:.3g}")
        out.append(d)
    d1, d2 = out
    if d1.shape[0] and d2.shape[0]:
        if d1.dtype != d2.dtype:
            raise TypeError(f"{names[0]} and {names[1]} must have the same dtype, got {d1.dtype} and {d2.dtype}")
        if d1.shape[1] != d2.shape[1]:
            raise ValueError(f"{names[0]} and {names[1]} must have the same width, got {d1.shape[1]} and {d2.shape[1]}")
    for name, d in zip(names, (d1, d2)):
        if d.shape[0] and norm == "hamming" and d.dtype != np.uint8:
            raise TypeError(f"{name}: NORM_HAMMING needs uint8 (binary) descriptors, got {d.dtype}")
    return d1, d2


#: Largest descriptor magnitude accepted in float64: squared distances of 128-dimensional float32
#: descriptors stay finite below it.
_FLOAT32_SAFE = 1e17


def as_points_of(points, descriptors: np.ndarray, name: str, descriptors_name: str) -> np.ndarray:
    """``(N, 2)`` points, one per row of ``descriptors``."""
    p = as_points(points, name)
    if p.shape[0] != descriptors.shape[0]:
        raise ValueError(f"{name} has {p.shape[0]} keypoints but {descriptors_name} has {descriptors.shape[0]} rows")
    return p


def as_index_pairs(pairs, n1: int, n2: int, names=("points1", "points2")) -> np.ndarray:
    """``(K, 2)`` intp index pairs ``(i1, i2)``, each within its side's ``n`` keypoints."""
    arr = np.asarray(pairs)
    if arr.size == 0:
        arr = np.zeros((0, 2), dtype=np.intp)
    if arr.ndim != 2 or arr.shape[1] != 2 or not (np.issubdtype(arr.dtype, np.integer)):
        raise ValueError(f"pairs must be a (K, 2) integer array, got shape {arr.shape} and dtype {arr.dtype}")
    for col, n, name in ((0, n1, names[0]), (1, n2, names[1])):
        if len(arr) and (arr[:, col].min() < 0 or arr[:, col].max() >= n):  # then find the first offender
            bad = (arr[:, col] < 0) | (arr[:, col] >= n)
            raise ValueError(f"match index {int(arr[bad, col][0])} out of range for {name} with {n} keypoints")
    return arr.astype(np.intp)
