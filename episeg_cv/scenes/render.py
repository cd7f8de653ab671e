"""Exact ray casting of a :class:`~episeg_cv.scenes.model.Scene`: a grey image and a depth map.

Pixel centres are at integer coordinates; an image of size ``(width, height)``
covers ``[-0.5, width - 0.5] x [-0.5, height - 0.5]``. Depth is the ``z``
coordinate in the camera (not the distance along the ray), in the scene's
length unit, ``inf`` where a pixel sees nothing.
"""

from __future__ import annotations


import cv2
import numpy as np

from .._validation import as_camera_matrix, as_image_size, as_rotation, as_vector3
from .model import Quad, Scene

__all__ = ["render"]

EDGE_EPS = 1e-9  # inclusive inside test, so that adjacent quads leave no cracks

#: Most samples (pixels x supersample^2) one render takes; a bound on its memory (about 150 bytes each).
MAX_SAMPLES = 2**26


def _clip_bbox(P_cam: np.ndarray, K: np.ndarray, xs: np.ndarray, ys: np.ndarray, near: float):
    """Index ranges of the sample grid that the polygon ``P_cam`` (camera coords) can cover."""
    # clip the polygon against z >= near (Sutherland-Hodgman, one plane)
    out = []
    n = len(P_cam)
    for i in range(n):
        a, b = P_cam[i], P_cam[(i + 1) % n]
        ina, inb = a[2] >= near, b[2] >= near
        if ina:
            out.append(a)
        if ina != inb:
            s = (near - a[2]) / (b[2] - a[2])
            out.append(a + s * (b - a))
    if not out:
        return None
    p = np.array(out) @ K.T
    p = p[:, :2] / p[:, 2:3]
    lo, hi = p.min(axis=0) - 1.0, p.max(axis=0) + 1.0
    i0, i1 = np.searchsorted(xs, lo[0]), np.searchsorted(xs, hi[0], side="right")
    j0, j1 = np.searchsorted(ys, lo[1]), np.searchsorted(ys, hi[1], side="right")
    if i0 >= i1 or j0 >= j1:
        return None
    return i0, i1, j0, j1


def _quad_coefficients(q: Quad, R, t, Kinv):
    """Affine functions of the pixel ``(x, y, 1)``: inverse depth, and ``u * iz``, ``v * iz`` offsets.

    With ``d = Kinv @ (x, y, 1)`` (so ``d_3 = 1``) the ray ``X = z d`` meets the
    plane ``n . (X - P) = 0`` at ``1 / z = (n^T Kinv / (n . P)) (x, y, 1)``.
    The quad coordinates are ``u = U* . (X - P) = (U*^T Kinv (x, y, 1)) / iz - U* . P``
    with ``U*, V*`` the dual basis of the edges.
    """
    P = R @ q.corner + t
    U = R @ q.edge_u
    V = R @ q.edge_v
    n = np.cross(U, V)
    nP = n @ P
    if abs(nP) <= 1e-12 * np.linalg.norm(n) * (np.linalg.norm(P) + 1e-300):
        return None  # the plane passes through the camera centre: seen edge-on
    nn = n @ n
    Ud = np.cross(V, n) / nn
    Vd = np.cross(n, U) / nn
    ciz = (n @ Kinv) / nP
    cu = Ud @ Kinv
    cv = Vd @ Kinv
    return P, U, V, ciz, cu, Ud @ P, cv, Vd @ P


def _raycast(scene: Scene, K, R, t, xs, ys, near=1e-6):
    """Nearest quad for every ray through the grid ``xs x ys``: (inverse depth, quad id, u, v)."""
    H, W = len(ys), len(xs)
    iz = np.zeros((H, W))  # 1 / depth; 0 = nothing (inf depth)
    qid = np.full((H, W), -1, dtype=np.int32)
    ub = np.zeros((H, W))
    vb = np.zeros((H, W))
    Kinv = np.linalg.inv(K)
    for k, q in enumerate(scene.quads):
        co = _quad_coefficients(q, R, t, Kinv)
        if co is None:
            continue
        P, U, V, ciz, cu, u0, cv, v0 = co
        box = _clip_bbox(np.array([P, P + U, P + U + V, P + V]), K, xs, ys, near)
        if box is None:
            continue
        i0, i1, j0, j1 = box
        x = xs[i0:i1][None, :]
        y = ys[j0:j1][:, None]
        z_inv = ciz[0] * x + ciz[1] * y + ciz[2]
        with np.errstate(divide="ignore", invalid="ignore"):
            u = (cu[0] * x + cu[1] * y + cu[2]) / z_inv - u0
            v = (cv[0] * x + cv[1] * y + cv[2]) / z_inv - v0
        cur = iz[j0:j1, i0:i1]
        hit = ((z_inv > 0) & (z_inv < 1.0 / near) & (z_inv > cur)
               & (u >= -EDGE_EPS) & (u <= 1 + EDGE_EPS) & (v >= -EDGE_EPS) & (v <= 1 + EDGE_EPS))
        if not hit.any():
            continue
        cur[hit] = z_inv[hit]
        qid[j0:j1, i0:i1][hit] = k
        ub[j0:j1, i0:i1][hit] = u[hit]
        vb[j0:j1, i0:i1][hit] = v[hit]
    return iz, qid, ub, vb


def _remap_flat(img: np.ndarray, mx: np.ndarray, my: np.ndarray) -> np.ndarray:
    """Bilinear, wrapping samples of ``img`` at the flat coordinate arrays ``mx, my``."""
    n = mx.size
    cols = 1024
    rows = -(-n // cols)
    pad = rows * cols - n
    mxp = np.concatenate([mx.astype(np.float32), np.zeros(pad, np.float32)]).reshape(rows, cols)
    myp = np.concatenate([my.astype(np.float32), np.zeros(pad, np.float32)]).reshape(rows, cols)
    out = cv2.remap(img, mxp, myp, interpolation=cv2.INTER_LINEAR, borderMode=cv2.BORDER_WRAP)
    return out.reshape(-1)[:n]


def _shade(scene: Scene, K, R, t, xs, ys, iz, qid, ub, vb) -> np.ndarray:
    """Texture every hit sample, mip-mapped (trilinear) by its texel footprint."""
    out = np.zeros(qid.shape, np.float32)
    flat = qid.reshape(-1)
    order = np.argsort(flat, kind="stable")
    sorted_ids = flat[order]
    starts = np.searchsorted(sorted_ids, np.arange(len(scene.quads) + 1))
    Kinv = np.linalg.inv(K)
    step = float(xs[1] - xs[0]) if len(xs) > 1 else 1.0
    izf, uf, vf = iz.reshape(-1), ub.reshape(-1), vb.reshape(-1)
    of = out.reshape(-1)
    for k, q in enumerate(scene.quads):
        idx = order[starts[k]:starts[k + 1]]
        if idx.size == 0:
            continue
        _, _, _, ciz, cu, u0, cv, v0 = _quad_coefficients(q, R, t, Kinv)
        z_inv, u, v = izf[idx], uf[idx], vf[idx]
        # derivatives of u, v per sample step: d(A / iz)/dx = (a - (u + u0) * ciz_x) / iz
        dudx = (cu[0] - (u + u0) * ciz[0]) / z_inv * step
        dudy = (cu[1] - (u + u0) * ciz[1]) / z_inv * step
        dvdx = (cv[0] - (v + v0) * ciz[0]) / z_inv * step
        dvdy = (cv[1] - (v + v0) * ciz[1]) / z_inv * step
        A = q.uv_to_texel
        tx = A[0, 0] * u + A[0, 1] * v + A[0, 2]
        ty = A[1, 0] * u + A[1, 1] * v + A[1, 2]
        fx = np.hypot(A[0, 0] * dudx + A[0, 1] * dvdx, A[1, 0] * dudx + A[1, 1] * dvdx)
        fy = np.hypot(A[0, 0] * dudy + A[0, 1] * dvdy, A[1, 0] * dudy + A[1, 1] * dvdy)
        mips = scene.mips[q.texture]
        level = np.clip(np.log2(np.maximum(np.maximum(fx, fy), 1e-6)), 0.0, len(mips) - 1.0)
        l0 = np.floor(level).astype(np.intp)
        frac = (level - l0).astype(np.float32)
        val = np.zeros(idx.size, np.float32)
        for lev in np.unique(l0):
            sel = np.flatnonzero(l0 == lev)
            s = 2.0 ** -lev
            a = _remap_flat(mips[lev], (tx[sel] + 0.5) * s - 0.5, (ty[sel] + 0.5) * s - 0.5)
            f = frac[sel]
            if lev + 1 < len(mips):
                b = _remap_flat(mips[lev + 1], (tx[sel] + 0.5) * s / 2 - 0.5, (ty[sel] + 0.5) * s / 2 - 0.5)
                a = a * (1 - f) + b * f
            val[sel] = a
        of[idx] = val * q.gain
    return out


def render(scene: Scene, K, R, t, image_size, supersample: int = 2) -> tuple[np.ndarray, np.ndarray]:
    """Render a grey image and a depth map of ``scene`` by exact ray casting.

    Every pixel ray is intersected with every quad's plane (in closed form:
    the inverse depth of a plane is an affine function of the pixel), kept if
    it falls inside the quad, and the nearest hit wins. Textures are sampled
    bilinearly from a mip-map chosen by each sample's texel footprint
    (trilinear), and the image is supersampled ``supersample x supersample``
    and box-filtered, so that edges and textures are anti-aliased. Only the
    quads whose projected bounding box covers a pixel are tested there.

    Parameters
    ----------
    scene : Scene
    K : (3, 3) array_like
        Intrinsics, in pixels (pixel centres at integer coordinates).
    R : (3, 3) array_like
        World-to-camera rotation: ``X_cam = R @ X_world + t``.
    t : (3,) array_like
        World-to-camera translation, in the scene's length unit.
    image_size : (int, int)
        ``(width, height)`` in pixels.
    supersample : int, optional
        Samples per pixel along each axis (``>= 1``), default 2 (4 per pixel).

    Returns
    -------
    image : (height, width) uint8
        Grey image.
    depth : (height, width) float64
        ``z`` in the camera of the surface seen through each pixel centre (one
        ray through the centre, not the supersamples), in the scene's unit;
        ``inf`` where the ray meets nothing.

    Examples
    --------
    >>> import numpy as np
    >>> from episeg_cv.scenes import Quad, Scene, load_texture
    >>> wall = Quad([-2, -2, 4], [4, 0, 0], [0, 4, 0])
    >>> scene = Scene([wall], [load_texture("brick")])
    >>> K = np.array([[40.0, 0, 31.5], [0, 40.0, 23.5], [0, 0, 1]])
    >>> image, depth = render(scene, K, np.eye(3), np.zeros(3), (64, 48))
    >>> image.shape, image.dtype.name, float(depth[20, 30])
    ((48, 64), 'uint8', 4.0)
    """
    if not isinstance(scene, Scene):
        raise TypeError(f"scene must be a Scene, got {type(scene).__name__}")
    K = as_camera_matrix(K, "K")
    R = as_rotation(R, "R")
    t = as_vector3(t, "t")
    w, h = as_image_size(image_size, "image_size")
    if isinstance(supersample, (bool, np.bool_)) or not isinstance(supersample, (int, np.integer)) or supersample < 1:
        raise ValueError(f"supersample must be an int >= 1, got {supersample!r}")
    s = int(supersample)
    if w * h * s * s > MAX_SAMPLES:
        raise ValueError(f"image_size {w}x{h} with supersample {s} is {w * h * s * s:,} samples per image; at most "
                         f"{MAX_SAMPLES:,} are rendered (about {MAX_SAMPLES * 150 // 2**30} GiB of work memory)")
    xs = (np.arange(w * s) + 0.5) / s - 0.5
    ys = (np.arange(h * s) + 0.5) / s - 0.5
    iz, qid, ub, vb = _raycast(scene, K, R, t, xs, ys)
    hi = _shade(scene, K, R, t, xs, ys, iz, qid, ub, vb)
    if s > 1:
        hi = hi.reshape(h, s, w, s).mean(axis=(1, 3))
    image = np.clip(np.rint(hi), 0, 255).astype(np.uint8)
    if s == 1:
        iz_c = iz
    else:
        iz_c = _raycast(scene, K, R, t, np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))[0]
    with np.errstate(divide="ignore"):
        depth = np.where(iz_c > 0, 1.0 / iz_c, np.inf)
    return image, depth

