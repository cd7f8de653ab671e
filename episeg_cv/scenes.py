"""Synthetic two-view scenes with exact ground truth.

A :class:`Scene` is a set of textured planar quads (parallelograms): the
panels of a room seen from inside and the faces of boxes standing in it. The
textures are photographs shipped with scikit-image (``skimage.data``),
converted to grey. :func:`render` ray-casts the quads exactly for any pinhole
camera and returns a grey image and a depth map; :func:`make_pair` renders the
two views of a named case of :func:`pose_suite`; :func:`ground_truth_matches`
turns two depth maps and the true pose into the true match of every keypoint.

Conventions (as in :mod:`episeg_cv.geometry`)
---------------------------------------------
- World-to-camera poses: ``X_cam = R @ X_world + t``. The relative pose of a
  pair is ``X2 = R @ X1 + t``.
- Cameras look along their ``+z`` axis, ``x`` to the right and ``y`` down.
  The world of :func:`make_room_scene` has ``y`` pointing down too: the floor
  is at ``y = +height / 2`` and the ceiling at ``y = -height / 2``.
- Pixel centres are at integer coordinates; an image of size
  ``(width, height)`` covers ``[-0.5, width - 0.5] x [-0.5, height - 0.5]``.
- Depth is the ``z`` coordinate in the camera (not the distance along the
  ray), in the scene's length unit (metres for :func:`make_room_scene`),
  ``inf`` where a pixel sees nothing.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, field

import cv2
import numpy as np

from ._validation import as_array, as_camera_matrix, as_image_size, as_nonnegative, as_points, as_rotation, as_vector3
from .geometry import TwoViewGeometry

__all__ = [
    "Quad",
    "Scene",
    "load_texture",
    "box_quads",
    "make_room_scene",
    "look_at",
    "render",
    "PoseCase",
    "pose_suite",
    "ImagePair",
    "make_pair",
    "GroundTruth",
    "ground_truth_matches",
    "disparity_ground_truth",
    "PosedCollection",
    "collection_poses",
    "make_collection",
    "TEXTURE_NAMES",
]

#: Photographs of ``skimage.data`` usable as textures by name.
TEXTURE_NAMES = (
    "astronaut", "coffee", "chelsea", "rocket", "brick", "gravel", "grass", "camera",
    "moon", "text", "coins", "page", "clock", "immunohistochemistry", "hubble_deep_field",
)

#: Side of the square, power-of-two textures kept by a :class:`Scene`.
TEXTURE_SIZE = 512

_EDGE_EPS = 1e-9  # inclusive inside test, so that adjacent quads leave no cracks


# --------------------------------------------------------------------------------------
# Scene model
# --------------------------------------------------------------------------------------
@dataclass(frozen=True, eq=False)
class Quad:
    """A textured planar parallelogram ``corner + u * edge_u + v * edge_v``, ``u, v`` in ``[0, 1]``.

    Parameters
    ----------
    corner, edge_u, edge_v : (3,) array_like
        World coordinates of one corner and the two edges from it, in the
        scene's length unit. The edges must not be parallel.
    texture : int
        Index into :attr:`Scene.textures`.
    uv_to_texel : (2, 3) array_like, optional
        Affine map from ``(u, v, 1)`` to texel coordinates ``(column, row)`` of
        the texture (texel centres at integers). Texels outside the texture wrap
        around (tiling). Default: the whole texture once, ``u`` along columns.
    gain : float, optional
        Brightness factor of this quad (flat shading), default 1.
    """

    corner: np.ndarray
    edge_u: np.ndarray
    edge_v: np.ndarray
    texture: int = 0
    uv_to_texel: np.ndarray | None = None
    gain: float = 1.0

    def __post_init__(self):
        object.__setattr__(self, "corner", as_vector3(self.corner, "corner"))
        object.__setattr__(self, "edge_u", as_vector3(self.edge_u, "edge_u"))
        object.__setattr__(self, "edge_v", as_vector3(self.edge_v, "edge_v"))
        n = np.cross(self.edge_u, self.edge_v)
        if np.linalg.norm(n) <= 1e-12 * (np.linalg.norm(self.edge_u) * np.linalg.norm(self.edge_v) + 1e-300):
            raise ValueError("edge_u and edge_v must be non-zero and not parallel")
        if isinstance(self.texture, (bool, np.bool_)) or not isinstance(self.texture, (int, np.integer)) or self.texture < 0:
            raise TypeError(f"texture must be a non-negative int index, got {self.texture!r}")
        A = self.uv_to_texel
        if A is None:
            S = TEXTURE_SIZE
            A = np.array([[S, 0.0, -0.5], [0.0, S, -0.5]])
        object.__setattr__(self, "uv_to_texel", as_array(A, "uv_to_texel", (2, 3)))
        object.__setattr__(self, "gain", as_nonnegative(self.gain, "gain"))
        for f in ("corner", "edge_u", "edge_v", "uv_to_texel"):
            getattr(self, f).flags.writeable = False

    @property
    def corners(self) -> np.ndarray:
        """(4, 3) the four corners, in order ``(0, 0), (1, 0), (1, 1), (0, 1)`` of ``(u, v)``."""
        c, a, b = self.corner, self.edge_u, self.edge_v
        return np.array([c, c + a, c + a + b, c + b])

    def point(self, u, v) -> np.ndarray:
        """World point(s) at ``(u, v)``; ``u, v`` scalars or equal-shape arrays, result ``(..., 3)``."""
        u = np.asarray(u, dtype=np.float64)[..., None]
        v = np.asarray(v, dtype=np.float64)[..., None]
        return self.corner + u * self.edge_u + v * self.edge_v


def _mip_pyramid(tex: np.ndarray) -> tuple[np.ndarray, ...]:
    levels = [tex]
    while levels[-1].shape[0] > 4:
        a = levels[-1]
        levels.append(0.25 * (a[0::2, 0::2] + a[1::2, 0::2] + a[0::2, 1::2] + a[1::2, 1::2]))
    for a in levels:
        a.flags.writeable = False
    return tuple(levels)


def _as_texture(img, name: str) -> np.ndarray:
    a = np.asarray(img)
    if a.ndim == 3 and a.shape[2] in (3, 4):
        a = cv2.cvtColor(np.ascontiguousarray(a[..., :3]).astype(np.uint8) if a.dtype != np.uint8 else np.ascontiguousarray(a[..., :3]),
                         cv2.COLOR_RGB2GRAY)
    if a.ndim != 2 or min(a.shape) < 2:
        raise ValueError(f"{name} must be a grey (H, W) or RGB (H, W, 3) image, got shape {a.shape}")
    a = a.astype(np.float32)
    if a.shape != (TEXTURE_SIZE, TEXTURE_SIZE):
        a = cv2.resize(a, (TEXTURE_SIZE, TEXTURE_SIZE), interpolation=cv2.INTER_AREA if min(a.shape) > TEXTURE_SIZE else cv2.INTER_LINEAR)
    return a


@dataclass(frozen=True, eq=False)
class Scene:
    """Textured quads and their textures.

    Parameters
    ----------
    quads : sequence of Quad
        The surfaces. Quads are two-sided; where several are hit by a ray the
        nearest wins.
    textures : sequence of (H, W) or (H, W, 3) array_like
        Grey (or RGB, converted to grey) images with values in ``[0, 255]``.
        Each is resized to ``TEXTURE_SIZE x TEXTURE_SIZE`` (512) and
        mip-mapped, for anti-aliased sampling.

    Examples
    --------
    >>> wall = Quad([-1, -1, 3], [2, 0, 0], [0, 2, 0], texture=0)
    >>> scene = Scene([wall], [load_texture("brick")])
    >>> len(scene.quads), scene.textures[0].shape
    (1, (512, 512))
    """

    quads: tuple
    textures: tuple
    _mips: tuple = field(init=False, repr=False)

    def __post_init__(self):
        quads = tuple(self.quads)
        for i, q in enumerate(quads):
            if not isinstance(q, Quad):
                raise TypeError(f"quads[{i}] must be a Quad, got {type(q).__name__}")
        textures = tuple(_as_texture(t, f"textures[{i}]") for i, t in enumerate(self.textures))
        if not textures:
            raise ValueError("textures must hold at least one image")
        for i, q in enumerate(quads):
            if q.texture >= len(textures):
                raise ValueError(f"quads[{i}].texture is {q.texture}, but there are only {len(textures)} textures")
        object.__setattr__(self, "quads", quads)
        object.__setattr__(self, "textures", textures)
        object.__setattr__(self, "_mips", tuple(_mip_pyramid(t) for t in textures))


@functools.lru_cache(maxsize=None)
def _load_texture_cached(name: str) -> np.ndarray:
    import skimage.data

    img = np.asarray(getattr(skimage.data, name)())
    if img.dtype == bool:
        img = img.astype(np.uint8) * 255
    if img.ndim == 3:
        img = cv2.cvtColor(np.ascontiguousarray(img[..., :3]), cv2.COLOR_RGB2GRAY)
    img = img.astype(np.float32)
    h, w = img.shape
    s = min(h, w)
    img = img[(h - s) // 2:(h - s) // 2 + s, (w - s) // 2:(w - s) // 2 + s]
    img = cv2.resize(img, (TEXTURE_SIZE, TEXTURE_SIZE), interpolation=cv2.INTER_AREA if s > TEXTURE_SIZE else cv2.INTER_CUBIC)
    lo, hi = np.percentile(img, [1, 99])
    img = (np.clip((img - lo) / max(hi - lo, 1.0), 0.0, 1.0) * 215.0 + 20.0).astype(np.float32)
    img.flags.writeable = False
    return img


def load_texture(name: str) -> np.ndarray:
    """A grey ``(512, 512)`` float32 texture made from a ``skimage.data`` photograph.

    The centre square of the image is cropped, resized to 512 x 512 and its
    contrast stretched (1st and 99th percentiles to 20 and 235). No network
    is needed: these images ship with scikit-image.

    Parameters
    ----------
    name : str
        One of :data:`TEXTURE_NAMES`.

    Returns
    -------
    (512, 512) float32, read-only, values in ``[20, 235]``.

    Examples
    --------
    >>> tex = load_texture("gravel")
    >>> tex.shape, tex.dtype.name
    ((512, 512), 'float32')
    """
    if name not in TEXTURE_NAMES:
        raise ValueError(f"name must be one of {TEXTURE_NAMES}, got {name!r}")
    return _load_texture_cached(name)


def _texel_map(rng, width: float, height: float, texel_size: float) -> np.ndarray:
    """A random rotation/flip and offset of a texture over a ``width x height`` panel."""
    S = TEXTURE_SIZE
    # one texture copy spans `S * texel_size` scene units
    su, sv = width / (S * texel_size), height / (S * texel_size)
    k = int(rng.integers(8))
    A = np.array([[su * S, 0.0], [0.0, sv * S]])
    if k & 1:
        A = A[::-1].copy()  # transpose: u along rows
    if k & 2:
        A[0] = -A[0]
    if k & 4:
        A[1] = -A[1]
    off = rng.uniform(0, S, size=2)
    return np.column_stack([A, off])


def box_quads(center, size, yaw: float, texture: int, *, rng=None, texel_size: float = 0.004,
              gains=(0.95, 0.8, 0.7, 0.85, 1.0, 0.6), bottom: bool = False) -> list:
    """The faces of a box, as quads.

    Parameters
    ----------
    center : (3,) array_like
        Centre of the box, world coordinates.
    size : (3,) array_like
        Extent along the box's own ``x, y, z`` axes (``y`` vertical).
    yaw : float
        Rotation about the vertical (world ``y``) axis, radians.
    texture : int
        Texture index for all faces.
    rng : None, int or numpy.random.Generator
        Draws each face's texture placement; ``np.random.default_rng(rng)``.
    texel_size : float
        Scene units per texel.
    gains : sequence of 6 floats
        Flat shading of the faces ``-x, +x, -y (top), +y (bottom), -z, +z``.
    bottom : bool
        Include the bottom face (``+y``), which is hidden when the box rests on the floor.

    Returns
    -------
    list of Quad
    """
    rng = np.random.default_rng(rng)
    c = as_vector3(center, "center")
    s = as_vector3(size, "size")
    if np.any(s <= 0):
        raise ValueError(f"size must be positive, got {s.tolist()}")
    cy, sy = np.cos(yaw), np.sin(yaw)
    ax = np.array([cy, 0.0, -sy]) * s[0]
    ay = np.array([0.0, 1.0, 0.0]) * s[1]
    az = np.array([sy, 0.0, cy]) * s[2]
    o = c - (ax + ay + az) / 2  # the (-,-,-) corner
    faces = [  # (corner, edge_u, edge_v, gain index, extents)
        (o, az, ay, 0, (s[2], s[1])),
        (o + ax, az, ay, 1, (s[2], s[1])),
        (o, ax, az, 2, (s[0], s[2])),
        (o + ay, ax, az, 3, (s[0], s[2])),
        (o, ax, ay, 4, (s[0], s[1])),
        (o + az, ax, ay, 5, (s[0], s[1])),
    ]
    quads = []
    for corner, eu, ev, gi, (w, h) in faces:
        if gi == 3 and not bottom:
            continue
        quads.append(Quad(corner, eu, ev, texture, _texel_map(rng, w, h, texel_size), gains[gi]))
    return quads


def make_room_scene(rng=None, *, room=(8.0, 3.0, 10.0), n_boxes: int = 8, keep_clear=(), clearance: float = 1.2,
                    panel: float = 2.0) -> Scene:
    """A room seen from inside, with boxes at several depths (so there is occlusion).

    The room is centred at the origin, ``x`` in ``[-W/2, W/2]``, ``y`` in
    ``[-H/2, H/2]`` (``y`` down: the floor is at ``+H/2``), ``z`` in
    ``[-D/2, D/2]``, in metres. Floor, ceiling and walls are split into panels
    of about ``panel`` metres, each with a randomly chosen, placed and oriented
    photograph. Boxes rest on the floor, except a few that float (shelves,
    lamps), with random sizes, positions, yaw and textures.

    Parameters
    ----------
    rng : None, int or numpy.random.Generator
        Seed or generator, ``np.random.default_rng(rng)``. The same seed gives
        the same scene.
    room : (W, H, D)
        Room size in metres.
    n_boxes : int
        Number of boxes.
    keep_clear : sequence of (3,) array_like
        Points (camera centres) that no box may come within ``clearance`` of
        (horizontally).
    clearance : float
        Metres.
    panel : float
        Approximate panel size in metres.

    Returns
    -------
    Scene

    Examples
    --------
    >>> scene = make_room_scene(rng=0, n_boxes=3)
    >>> len(scene.quads) > 6
    True
    """
    rng = np.random.default_rng(rng)
    W, H, D = (float(v) for v in room)
    if min(W, H, D) <= 0:
        raise ValueError(f"room must be three positive sizes, got {room!r}")
    keep = [as_vector3(p, "keep_clear point") for p in keep_clear]
    names = TEXTURE_NAMES
    textures = [load_texture(n) for n in names]
    floor_tex = [names.index(n) for n in ("gravel", "brick", "grass", "coins", "moon")]
    wall_tex = [i for i, n in enumerate(names) if n not in ("gravel",)]
    ceil_tex = [names.index(n) for n in ("moon", "gravel", "hubble_deep_field", "text", "page")]

    quads = []

    def plane(origin, eu, ev, choices, texel_size):
        lu, lv = np.linalg.norm(eu), np.linalg.norm(ev)
        nu, nv = max(1, round(lu / panel)), max(1, round(lv / panel))
        for i in range(nu):
            for j in range(nv):
                corner = origin + eu * (i / nu) + ev * (j / nv)
                tex = int(rng.choice(choices))
                A = _texel_map(rng, lu / nu, lv / nv, texel_size * rng.uniform(0.8, 1.25))
                quads.append(Quad(corner, eu / nu, ev / nv, tex, A, float(rng.uniform(0.65, 1.0))))

    x0, x1, y0, y1, z0, z1 = -W / 2, W / 2, -H / 2, H / 2, -D / 2, D / 2
    ex, ey, ez = np.array([W, 0, 0.0]), np.array([0, H, 0.0]), np.array([0, 0, D])
    plane(np.array([x0, y1, z0]), ex, ez, floor_tex, 0.006)  # floor
    plane(np.array([x0, y0, z0]), ex, ez, ceil_tex, 0.008)  # ceiling
    plane(np.array([x0, y0, z0]), ex, ey, wall_tex, 0.005)  # back wall (z = z0)
    plane(np.array([x0, y0, z1]), ex, ey, wall_tex, 0.005)  # front wall (z = z1)
    plane(np.array([x0, y0, z0]), ez, ey, wall_tex, 0.005)  # left wall (x = x0)
    plane(np.array([x1, y0, z0]), ez, ey, wall_tex, 0.005)  # right wall (x = x1)

    placed = []
    for k in range(n_boxes):
        for _ in range(200):
            size = rng.uniform([0.4, 0.4, 0.4], [1.3, 1.5, 1.3])
            floating = k % 4 == 3
            half = np.hypot(size[0], size[2]) / 2
            x = rng.uniform(x0 + half + 0.05, x1 - half - 0.05)
            z = rng.uniform(z0 + half + 0.05, z1 - half - 0.05)
            y = rng.uniform(y0 + size[1] / 2 + 0.2, 0.3) if floating else y1 - size[1] / 2
            ok = all(np.hypot(x - p[0], z - p[2]) > clearance + half for p in keep)
            ok &= all(np.hypot(x - q[0], z - q[1]) > half + q[2] + 0.1 for q in placed)
            if ok:
                break
        else:
            continue
        placed.append((x, z, half))
        tex = int(rng.choice(wall_tex))
        quads.extend(box_quads([x, y, z], size, float(rng.uniform(0, np.pi / 2)), tex, rng=rng,
                               bottom=floating))
    return Scene(quads, textures)


# --------------------------------------------------------------------------------------
# Rendering
# --------------------------------------------------------------------------------------
def look_at(position, target, roll: float = 0.0):
    """World-to-camera pose of a camera at ``position`` looking at ``target``.

    The camera's ``y`` axis (image down) is as close as possible to world
    ``+y`` (down, in :func:`make_room_scene`'s world), then rolled by
    ``roll`` radians about the optical axis.

    Returns
    -------
    R : (3, 3) float64
        Rotation, ``X_cam = R @ X_world + t``.
    t : (3,) float64
        Translation, ``-R @ position``.

    Examples
    --------
    >>> R, t = look_at([0, 0, -2], [0, 0, 5])
    >>> R.round(6).tolist(), t.round(6).tolist()
    ([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]], [0.0, 0.0, 2.0])
    """
    c = as_vector3(position, "position")
    z = as_vector3(target, "target") - c
    if np.linalg.norm(z) == 0:
        raise ValueError("target must differ from position")
    z /= np.linalg.norm(z)
    x = np.cross([0.0, 1.0, 0.0], z)
    if np.linalg.norm(x) < 1e-9:
        raise ValueError("the viewing direction must not be vertical")
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    R = np.array([x, y, z])
    cr, sr = np.cos(roll), np.sin(roll)
    R = np.array([[cr, -sr, 0.0], [sr, cr, 0.0], [0.0, 0.0, 1.0]]) @ R
    return R, -R @ c


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
               & (u >= -_EDGE_EPS) & (u <= 1 + _EDGE_EPS) & (v >= -_EDGE_EPS) & (v <= 1 + _EDGE_EPS))
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
        mips = scene._mips[q.texture]
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


# --------------------------------------------------------------------------------------
# Ground truth
# --------------------------------------------------------------------------------------
@dataclass(frozen=True, eq=False)
class GroundTruth:
    """The true match in view 2 of every keypoint of view 1.

    Attributes
    ----------
    match : (N1,) intp
        Index into ``points2`` of the true match, ``-1`` where there is none
        (not visible in view 2, or no view-2 keypoint within ``max_px``).
    projected : (N1,) x 2 float64
        Where the keypoint's surface point projects in image 2, in pixels;
        NaN where its depth (or disparity) is unknown or it is behind camera 2.
    visible : (N1,) bool
        The surface point is in front of camera 2, inside image 2 and not
        occluded there.
    distance : (N1,) float64
        Pixel distance from ``projected`` to the true match; ``inf`` where
        there is none.
    points2 : (N2, 2) float64
        The view-2 keypoints searched.
    max_px : float
        The matching radius, pixels.

    Notes
    -----
    A returned match ``(i1, i2)`` is *correct* (:meth:`is_correct`) when
    keypoint ``i1`` is visible and ``points2[i2]`` lies within ``max_px`` of
    its projection. This is not ``match[i1] == i2``: detectors such as SIFT
    return several keypoints at one position (one per orientation), and any
    of them is a right answer. ``match`` is the nearest one.
    """

    match: np.ndarray
    projected: np.ndarray
    visible: np.ndarray
    distance: np.ndarray
    points2: np.ndarray
    max_px: float

    def __post_init__(self):
        for f in ("match", "projected", "visible", "distance", "points2"):
            getattr(self, f).flags.writeable = False

    def __len__(self) -> int:
        return self.match.shape[0]

    @property
    def matchable(self) -> np.ndarray:
        """(N1,) bool: the keypoint has a true match."""
        return self.match >= 0

    @property
    def num_matchable(self) -> int:
        """Number of view-1 keypoints with a true match (the denominator of recall)."""
        return int(np.count_nonzero(self.match >= 0))

    def is_correct(self, matches) -> np.ndarray:
        """Which of the ``(K, 2)`` index pairs ``(i1, i2)`` are correct.

        ``(i1, i2)`` is correct iff keypoint ``i1`` is visible in view 2 and
        ``points2[i2]`` lies within ``max_px`` of its projection (see Notes of
        :class:`GroundTruth`).

        Returns
        -------
        (K,) bool
        """
        m = np.asarray(matches)
        if m.size == 0:
            return np.zeros(0, dtype=bool)
        if m.ndim != 2 or m.shape[1] != 2 or not np.issubdtype(m.dtype, np.integer):
            raise ValueError(f"matches must be a (K, 2) integer array, got shape {m.shape} and dtype {m.dtype}")
        if m.min() < 0 or m[:, 0].max() >= len(self) or m[:, 1].max() >= len(self.points2):
            raise ValueError(f"matches must index the {len(self)} view-1 and {len(self.points2)} view-2 keypoints")
        with np.errstate(invalid="ignore"):
            return self.visible[m[:, 0]] & (self.error(m) <= self.max_px)

    def error(self, matches) -> np.ndarray:
        """(K,) pixel distance from ``points2[i2]`` to the projection of keypoint ``i1``; NaN if unknown."""
        m = np.asarray(matches, dtype=np.intp).reshape(-1, 2)
        return np.hypot(*(self.points2[m[:, 1]] - self.projected[m[:, 0]]).T)


def _as_map(a, name: str) -> np.ndarray:
    a = np.asarray(a)
    if a.ndim != 2 or a.shape[0] < 1 or a.shape[1] < 1 or not np.issubdtype(a.dtype, np.floating):
        raise ValueError(f"{name} must be a floating (H, W) array, got shape {a.shape} and dtype {a.dtype}")
    return a.astype(np.float64, copy=False)


def _inside(p: np.ndarray, shape) -> np.ndarray:
    h, w = shape
    with np.errstate(invalid="ignore"):
        return (p[:, 0] >= -0.5) & (p[:, 0] <= w - 0.5) & (p[:, 1] >= -0.5) & (p[:, 1] <= h - 0.5)


def _sample_map(m: np.ndarray, p: np.ndarray, rtol: float | None, atol: float | None, inverse: bool) -> np.ndarray:
    """Values of ``m`` (depth or disparity) at points ``p``; NaN outside or unknown.

    Bilinear when the four neighbours are finite, positive and agree within
    ``rtol`` (relative) or ``atol`` (absolute), otherwise the nearest pixel.
    With ``inverse`` the interpolation is done on ``1 / m``: the inverse depth of a
    plane is affine in the pixel, so this is exact on a plane.
    """
    n = p.shape[0]
    out = np.full(n, np.nan)
    ok = _inside(p, m.shape) & np.all(np.isfinite(p), axis=1)
    if not ok.any():
        return out
    h, w = m.shape
    q = p[ok]
    ix = np.clip(np.floor(q[:, 0] + 0.5).astype(np.intp), 0, w - 1)
    iy = np.clip(np.floor(q[:, 1] + 0.5).astype(np.intp), 0, h - 1)
    nearest = m[iy, ix]
    x0 = np.clip(np.floor(q[:, 0]).astype(np.intp), 0, max(w - 2, 0))
    y0 = np.clip(np.floor(q[:, 1]).astype(np.intp), 0, max(h - 2, 0))
    x1, y1 = np.minimum(x0 + 1, w - 1), np.minimum(y0 + 1, h - 1)
    fx = np.clip(q[:, 0] - x0, 0.0, 1.0)
    fy = np.clip(q[:, 1] - y0, 0.0, 1.0)
    v = np.stack([m[y0, x0], m[y0, x1], m[y1, x0], m[y1, x1]])
    with np.errstate(invalid="ignore", divide="ignore"):
        good = np.all(np.isfinite(v) & (v > 0), axis=0)
        lo, hi = v.min(axis=0), v.max(axis=0)
        agree = (hi - lo <= rtol * lo) if rtol is not None else (hi - lo <= atol)
        f = 1.0 / v if inverse else v
        wts = np.stack([(1 - fx) * (1 - fy), fx * (1 - fy), (1 - fx) * fy, fx * fy])
        bil = (f * wts).sum(axis=0)
        if inverse:
            bil = 1.0 / bil
    val = np.where(good & agree, bil, nearest)
    val = np.where(np.isfinite(val) & (val > 0), val, np.nan)
    out[ok] = val
    return out


def _nearest_within(query: np.ndarray, points: np.ndarray, radius: float) -> tuple[np.ndarray, np.ndarray]:
    """Index of the nearest ``points`` row to each ``query`` row if within ``radius``, else -1.

    Buckets ``points`` in a grid of ``radius``-sized cells and looks in the
    3 x 3 cells around each query: ``O((N + M) log M)``, no ``N x M`` array.
    Ties go to the lowest index. NaN queries get -1.
    """
    n = query.shape[0]
    best = np.full(n, -1, dtype=np.intp)
    dist = np.full(n, np.inf)
    valid = np.all(np.isfinite(query), axis=1)
    if n == 0 or points.shape[0] == 0 or not valid.any():
        return best, dist
    cell = max(float(radius), 1e-6)
    qv = query[valid]
    origin = np.minimum(points.min(axis=0), qv.min(axis=0)) - 2 * cell
    pc = np.floor((points - origin) / cell).astype(np.int64)
    qc = np.floor((qv - origin) / cell).astype(np.int64)
    stride = int(max(pc[:, 1].max(), qc[:, 1].max())) + 3
    keys = pc[:, 0] * stride + pc[:, 1]
    order = np.argsort(keys, kind="stable")
    sk = keys[order]
    vb = np.full(qv.shape[0], -1, dtype=np.intp)
    vd = np.full(qv.shape[0], np.inf)
    for dx in (-1, 0, 1):
        for dy in (-1, 0, 1):
            k = (qc[:, 0] + dx) * stride + (qc[:, 1] + dy)
            lo = np.searchsorted(sk, k, side="left")
            cnt = np.searchsorted(sk, k, side="right") - lo
            j = 0
            while True:
                act = np.flatnonzero(cnt > j)
                if act.size == 0:
                    break
                cand = order[lo[act] + j]
                d = np.hypot(*(qv[act] - points[cand]).T)
                better = (d < vd[act]) | ((d == vd[act]) & (cand < vb[act]))
                vd[act[better]] = d[better]
                vb[act[better]] = cand[better]
                j += 1
    far = vd > radius
    vb[far] = -1
    vd[far] = np.inf
    best[valid] = vb
    dist[valid] = vd
    return best, dist


def ground_truth_matches(points1, points2, depth1, depth2, geometry: TwoViewGeometry, max_px: float = 3.0,
                         depth_rtol: float = 0.01) -> GroundTruth:
    """The true match of every view-1 keypoint, from two depth maps and the true pose.

    For keypoint ``x1``:

    1. its depth ``z1`` is read from ``depth1``: bilinearly (on inverse
       depth, exact on a plane) when the four surrounding pixels are finite and
       agree within ``depth_rtol``, otherwise from the nearest pixel (so no
       depth is invented across an occluding edge);
    2. it is back-projected and projected into view 2 with the true geometry
       (:meth:`TwoViewGeometry.transfer`), giving ``x2`` and ``z2``;
    3. it is *visible* iff ``z2 > 0``, ``x2`` is inside image 2 and it is not
       occluded: ``depth2`` read at ``x2`` the same way agrees with ``z2``
       within ``depth_rtol`` (relative);
    4. its true match is the view-2 keypoint nearest to ``x2``, if one lies
       within ``max_px`` pixels (ties to the lowest index).

    Parameters
    ----------
    points1 : (N1, 2) array_like
        Keypoints of image 1, pixels (centres at integer coordinates).
    points2 : (N2, 2) array_like
        Keypoints of image 2.
    depth1 : (H1, W1) float array
        ``z`` in camera 1 per pixel, in the unit of ``geometry.t``; ``inf``,
        NaN or ``<= 0`` where unknown.
    depth2 : (H2, W2) float array
        The same for camera 2.
    geometry : TwoViewGeometry
        The *true* geometry (``X2 = R X1 + t``).
    max_px : float, optional
        Matching radius in pixels, default 3.
    depth_rtol : float, optional
        Relative depth agreement for the occlusion test and interpolation, default 0.01.

    Returns
    -------
    GroundTruth
        ``match`` (N1,) intp (``-1``: none), ``projected`` (N1, 2),
        ``visible`` (N1,) bool, ``distance`` (N1,).

    Examples
    --------
    >>> import numpy as np
    >>> from episeg_cv import TwoViewGeometry
    >>> K = [[100, 0, 49.5], [0, 100, 39.5], [0, 0, 1]]
    >>> g = TwoViewGeometry(K, K, np.eye(3), [-0.5, 0, 0], image_size1=(100, 80), image_size2=(100, 80))
    >>> depth = np.full((80, 100), 5.0)                   # a fronto-parallel wall at z = 5
    >>> gt = ground_truth_matches([[50, 40], [5, 40]], [[40.5, 40], [70, 10]], depth, depth, g)
    >>> gt.match.tolist(), gt.projected.round(2).tolist()  # the wall moves by 100 * 0.5 / 5 = 10 px
    ([0, -1], [[40.0, 40.0], [-5.0, 40.0]])
    """
    if not isinstance(geometry, TwoViewGeometry):
        raise TypeError(f"geometry must be a TwoViewGeometry, got {type(geometry).__name__}")
    p1 = as_points(points1, "points1")
    p2 = as_points(points2, "points2")
    d1 = _as_map(depth1, "depth1")
    d2 = _as_map(depth2, "depth2")
    for name, d, size in (("depth1", d1, geometry.image_size1), ("depth2", d2, geometry.image_size2)):
        if d.shape != (size[1], size[0]):
            raise ValueError(f"{name} must have shape {(size[1], size[0])} (the geometry's image size), got {d.shape}")
    max_px = as_nonnegative(max_px, "max_px")
    depth_rtol = as_nonnegative(depth_rtol, "depth_rtol")
    n = p1.shape[0]
    z1 = _sample_map(d1, p1, depth_rtol, None, inverse=True)
    known = np.isfinite(z1)
    proj = np.full((n, 2), np.nan)
    z2 = np.full(n, np.nan)
    if known.any():
        proj[known], z2[known] = geometry.transfer(p1[known], z1[known])
    with np.errstate(invalid="ignore"):
        front = z2 > 0
    proj[~front] = np.nan
    d2_at = _sample_map(d2, proj, depth_rtol, None, inverse=True)
    with np.errstate(invalid="ignore"):
        visible = front & _inside(proj, d2.shape) & (np.abs(d2_at - z2) <= depth_rtol * z2)
    match, dist = _nearest_within(np.where(visible[:, None], proj, np.nan), p2, max_px)
    return GroundTruth(match, proj, visible, dist, p2, max_px)


def disparity_ground_truth(points1, points2, disparity, image_size2, max_px: float = 2.0) -> GroundTruth:
    """True matches of a rectified pair from the left view's disparity map.

    The disparity is indexed by the **left** (view-1) pixel:
    ``x2 = x1 - disparity[y1, x1]``, ``y2 = y1``. It is read bilinearly when the
    four neighbours are finite and within 1 px of each other, else from the
    nearest pixel. A keypoint is visible iff its disparity is finite and
    positive and ``x2`` is inside image 2 (occlusion is already encoded in
    the disparity map as inf/NaN). Its true match is the nearest view-2
    keypoint within ``max_px``.

    Parameters
    ----------
    points1, points2 : (N1, 2), (N2, 2) array_like
        Keypoints, pixels.
    disparity : (H1, W1) float array
        Left disparity in pixels; inf or NaN where unknown.
    image_size2 : (int, int)
        ``(width, height)`` of image 2.
    max_px : float, optional
        Matching radius, default 2.

    Returns
    -------
    GroundTruth

    Examples
    --------
    >>> import numpy as np
    >>> disp = np.full((10, 20), 4.0)
    >>> gt = disparity_ground_truth([[10, 5], [2, 5]], [[6.5, 5]], disp, (20, 10))
    >>> gt.match.tolist(), gt.visible.tolist()
    ([0, -1], [True, False])
    """
    p1 = as_points(points1, "points1")
    p2 = as_points(points2, "points2")
    disp = _as_map(disparity, "disparity")
    w2, h2 = as_image_size(image_size2, "image_size2")
    max_px = as_nonnegative(max_px, "max_px")
    d = _sample_map(disp, p1, None, 1.0, inverse=False)
    proj = np.column_stack([p1[:, 0] - d, p1[:, 1]])
    visible = np.isfinite(d) & _inside(proj, (h2, w2))
    proj[~np.isfinite(d)] = np.nan
    match, dist = _nearest_within(np.where(visible[:, None], proj, np.nan), p2, max_px)
    return GroundTruth(match, proj, visible, dist, p2, max_px)


# --------------------------------------------------------------------------------------
# Pose suite and pairs
# --------------------------------------------------------------------------------------
#: Image size ``(width, height)`` of the pose suite's intrinsics.
SUITE_IMAGE_SIZE = (640, 480)


def _K(f: float, size=SUITE_IMAGE_SIZE) -> np.ndarray:
    w, h = size
    return np.array([[f, 0.0, (w - 1) / 2], [0.0, f, (h - 1) / 2], [0.0, 0.0, 1.0]])


def _scale_K(K: np.ndarray, old_size, new_size) -> np.ndarray:
    """Intrinsics for the same camera at another resolution (pixel centres at integers)."""
    sx, sy = new_size[0] / old_size[0], new_size[1] / old_size[1]
    return np.array([[K[0, 0] * sx, K[0, 1] * sx, (K[0, 2] + 0.5) * sx - 0.5],
                     [0.0, K[1, 1] * sy, (K[1, 2] + 0.5) * sy - 0.5], [0.0, 0.0, 1.0]])


def _rotation(axis, angle: float) -> np.ndarray:
    """Rodrigues' rotation about ``axis`` by ``angle`` radians."""
    a = np.asarray(axis, dtype=np.float64)
    a = a / np.linalg.norm(a)
    S = np.array([[0.0, -a[2], a[1]], [a[2], 0.0, -a[0]], [-a[1], a[0], 0.0]])
    return np.eye(3) + np.sin(angle) * S + (1 - np.cos(angle)) * (S @ S)


@dataclass(frozen=True, eq=False)
class PoseCase:
    """One named two-view configuration of the pose suite.

    Attributes
    ----------
    name, description : str
    seed : int
        Seed of the room (:func:`make_room_scene`) and of the pose noise.
    image_size : (int, int)
        ``(width, height)`` for which ``K1``, ``K2`` are given (640 x 480).
    K1, K2 : (3, 3) float64
        Intrinsics at ``image_size``.
    R1, t1, R2, t2 : (3, 3), (3,) float64
        World-to-camera poses of the two cameras, ``X_cam = R X_world + t``, metres.
    R, t : (3, 3), (3,) float64
        True relative pose, ``X2 = R @ X1 + t`` (exact: e.g. ``t[2] == 0`` for lateral).
    R_given, t_given : (3, 3), (3,) float64
        The relative pose handed to the matcher: equal to ``R, t`` except for
        ``noisy_pose``, where it is off by about 0.5 degrees and 2 % in direction.
    clear_between : bool
        No box stands between the two cameras (so that each sees the other's
        position and the wall behind it).
    """

    name: str
    description: str
    seed: int
    image_size: tuple
    K1: np.ndarray
    K2: np.ndarray
    R1: np.ndarray
    t1: np.ndarray
    R2: np.ndarray
    t2: np.ndarray
    R: np.ndarray
    t: np.ndarray
    R_given: np.ndarray
    t_given: np.ndarray
    clear_between: bool = False

    def __post_init__(self):
        for f in ("K1", "K2", "R1", "t1", "R2", "t2", "R", "t", "R_given", "t_given"):
            getattr(self, f).flags.writeable = False

    def intrinsics(self, image_size=None) -> tuple[np.ndarray, np.ndarray]:
        """``(K1, K2)`` for the same cameras rendered at ``image_size`` (default: ``self.image_size``)."""
        size = self.image_size if image_size is None else as_image_size(image_size, "image_size")
        return _scale_K(self.K1, self.image_size, size), _scale_K(self.K2, self.image_size, size)

    def geometry(self, image_size=None, given: bool = False) -> TwoViewGeometry:
        """The true (or, with ``given``, the matcher's) :class:`TwoViewGeometry` at ``image_size``."""
        size = self.image_size if image_size is None else as_image_size(image_size, "image_size")
        K1, K2 = self.intrinsics(size)
        R, t = (self.R_given, self.t_given) if given else (self.R, self.t)
        return TwoViewGeometry(K1, K2, R, t, image_size1=size, image_size2=size)

    @property
    def centers(self) -> tuple[np.ndarray, np.ndarray]:
        """World positions of the two camera centres, ``-R_i^T t_i``."""
        return -self.R1.T @ self.t1, -self.R2.T @ self.t2

    def keep_clear(self) -> list:
        """World points that boxes keep clear of: the camera centres (and the line between them)."""
        C1, C2 = self.centers
        if not self.clear_between:
            return [C1, C2]
        return [C1 + s * (C2 - C1) for s in np.linspace(0.0, 1.0, 9)]


def _case(name, description, seed, K1, K2, cam1, cam2=None, relative=None, noise=None, clear_between=False) -> PoseCase:
    R1, t1 = look_at(*cam1[:2], *cam1[2:])
    if relative is not None:
        R, t = (np.asarray(a, dtype=np.float64) for a in relative)
        R2, t2 = R @ R1, R @ t1 + t
    else:
        R2, t2 = look_at(*cam2[:2], *cam2[2:])
        R = R2 @ R1.T
        t = t2 - R @ t1
    R_given, t_given = R, t
    if noise is not None:
        rng = np.random.default_rng(seed)
        rot_deg, dir_frac = noise
        R_given = _rotation(rng.normal(size=3), np.deg2rad(rot_deg)) @ R
        u = t / np.linalg.norm(t)
        d = rng.normal(size=3)
        d -= (d @ u) * u
        u2 = u + dir_frac * d / np.linalg.norm(d)
        t_given = u2 / np.linalg.norm(u2) * np.linalg.norm(t)
    return PoseCase(name, description, seed, SUITE_IMAGE_SIZE, K1, K2, R1, t1, R2, t2, R, t, R_given, t_given, clear_between)


def _converging_cameras():
    # camera 2 far back in a corner, camera 1 further in, 25 degrees off camera 2's
    # axis (so camera 1's centre, the epipole, is in image 2); both look at T.
    T = np.array([-2.2, 0.2, 3.6])
    C2 = np.array([3.0, -0.2, -4.3])
    d = T - C2
    d[1] = 0.0
    d /= np.linalg.norm(d)
    C1 = C2 + 5.5 * (_rotation([0, 1, 0], np.deg2rad(-25.0)) @ d) + np.array([0.0, 0.25, 0.0])
    return (C1, T), (C2, T + np.array([0.3, 0.0, 0.0]))


@functools.lru_cache(maxsize=None)
def _suite() -> dict:
    K = _K(500.0)
    Kb = _K(560.0)
    cases = [
        _case("forward", "camera 2 moves 1 m forward (t3 < 0); the epipole is in image 2", 101, K, K,
              ((0.0, 0.0, -3.6), (0.2, 0.1, 5.0)), ((0.25, 0.05, -2.6), (0.45, 0.15, 5.0), 0.03)),
        _case("backward", "camera 2 moves 1 m backward (t3 > 0); the epipole is in image 2", 102, K, K,
              ((0.1, -0.05, -2.4), (-0.2, 0.1, 5.0)), ((-0.15, 0.0, -3.4), (-0.1, 0.15, 5.0), -0.02)),
        _case("lateral", "sideways motion, t3 = 0 exactly: the epipole is at infinity", 103, K, K,
              ((-0.5, -0.1, -3.5), (-0.3, 0.1, 5.0)),
              relative=(_rotation([0, 1, 0], np.deg2rad(4.0)), [-0.6, 0.05, 0.0])),
        _case("converging", "wide baseline (5.5 m), views converging by about 35 degrees; the epipole is in image 2",
              104, K, Kb, *[(c, tg) for c, tg in _converging_cameras()]),
        _case("face_to_face", "the cameras face each other from opposite ends of the room (8 m apart)", 105, K, K,
              ((0.3, 0.0, -4.0), (-0.5, -0.05, 4.0)), ((-0.4, -0.1, 4.0), (0.2, 0.05, -4.0)), clear_between=True),
        _case("near_pure_rotation", "|t| = 2 cm for a scene 2 to 9 m away, rotation about 9 degrees", 106, K, K,
              ((0.5, 0.0, -2.0), (1.5, 0.2, 5.0)), ((0.515, -0.01, -1.992), (2.6, -0.3, 5.0))),
        _case("partial_behind", "crossing views, camera 2 turned 67 degrees: (R K1^-1 x)_3 < 0 for the left part of image 1", 107, K, K,
              ((1.5, 0.0, -3.0), (1.5 - 5 * np.sin(0.35), 0.25, -3.0 + 5 * np.cos(0.35))),
              ((-2.0, 0.1, -2.0), (-2.0 + 5 * np.sin(0.82), 0.35, -2.0 + 5 * np.cos(0.82)))),
        _case("noisy_pose", "general oblique motion; the matcher is given a pose off by 0.5 degrees and 2 % in direction",
              108, K, K, ((-1.0, 0.0, -3.0), (0.0, 0.3, 5.0)), ((0.2, -0.2, -2.2), (-0.5, 0.1, 5.0), 0.05),
              noise=(0.5, 0.02)),
    ]
    return {c.name: c for c in cases}


def pose_suite() -> dict:
    """The named two-view cases, each with a fixed seed, covering every geometric case.

    ========================  ==============================================================
    ``forward``               ``t3 < 0``, epipole in image 2
    ``backward``              ``t3 > 0``, epipole in image 2
    ``lateral``               ``t3 = 0`` exactly: epipole at infinity
    ``converging``            wide baseline, converging views, epipole in image 2
    ``face_to_face``          cameras facing each other, each seeing the wall behind the other
    ``near_pure_rotation``    ``|t|`` = 2 cm, scene 2 to 9 m away
    ``partial_behind``        ``(R K1^-1 x)_3 < 0`` for part of image 1
    ``noisy_pose``            the matcher's pose is off by 0.5 degrees and 2 % in direction
    ========================  ==============================================================

    Returns
    -------
    dict of str to PoseCase
        A new dict each call (the cases themselves are immutable).

    Examples
    --------
    >>> suite = pose_suite()
    >>> list(suite)[:3]
    ['forward', 'backward', 'lateral']
    >>> float(suite["lateral"].t[2])
    0.0
    """
    return dict(_suite())


@functools.lru_cache(maxsize=16)
def _case_scene(seed: int, keep_clear: tuple) -> Scene:
    return make_room_scene(rng=seed, keep_clear=[np.array(c) for c in keep_clear])


@dataclass(frozen=True, eq=False)
class ImagePair:
    """Two grey images with their calibration and ground truth.

    Made by :func:`make_pair` and by the loaders of :mod:`episeg_cv.datasets`.

    Attributes
    ----------
    name : str
    image1, image2 : (H1, W1), (H2, W2) uint8
        Grey images.
    geometry : TwoViewGeometry
        The geometry to hand to a matcher (perturbed for ``noisy_pose``).
    geometry_true : TwoViewGeometry
        The true geometry, ``X2 = R X1 + t``.
    depth1, depth2 : (H, W) float64 or None
        ``z`` per pixel in each camera (unit of ``t``), ``inf`` where unknown.
    disparity : (H1, W1) float or None
        Left disparity of a rectified pair, ``x2 = x1 - disparity[y1, x1]``.
    max_px : float
        Default matching radius of :meth:`ground_truth`.
    """

    name: str
    image1: np.ndarray
    image2: np.ndarray
    geometry: TwoViewGeometry
    geometry_true: TwoViewGeometry
    depth1: np.ndarray | None = None
    depth2: np.ndarray | None = None
    disparity: np.ndarray | None = None
    max_px: float = 3.0

    def __post_init__(self):
        for f in ("image1", "image2", "depth1", "depth2", "disparity"):
            a = getattr(self, f)
            if a is not None:
                a.flags.writeable = False

    @property
    def K1(self) -> np.ndarray:
        """(3, 3) true intrinsics of camera 1."""
        return self.geometry_true.K1

    @property
    def K2(self) -> np.ndarray:
        """(3, 3) true intrinsics of camera 2."""
        return self.geometry_true.K2

    @property
    def R(self) -> np.ndarray:
        """(3, 3) true relative rotation, ``X2 = R X1 + t``."""
        return self.geometry_true.R

    @property
    def t(self) -> np.ndarray:
        """(3,) true relative translation."""
        return self.geometry_true.t

    def ground_truth(self, points1, points2, max_px: float | None = None) -> GroundTruth:
        """True matches of keypoints ``points1`` among ``points2``.

        Uses :func:`ground_truth_matches` on the depth maps, or
        :func:`disparity_ground_truth` when the pair has a disparity map.
        ``max_px`` defaults to :attr:`max_px`.
        """
        r = self.max_px if max_px is None else max_px
        if self.disparity is not None:
            return disparity_ground_truth(points1, points2, self.disparity, self.geometry_true.image_size2, r)
        if self.depth1 is None or self.depth2 is None:
            raise ValueError(f"pair {self.name!r} has neither depth maps nor a disparity map")
        return ground_truth_matches(points1, points2, self.depth1, self.depth2, self.geometry_true, r)


def make_pair(name: str, image_size=SUITE_IMAGE_SIZE, seed: int | None = None, supersample: int = 2) -> ImagePair:
    """Render both views of a case of :func:`pose_suite`.

    Parameters
    ----------
    name : str
        A key of :func:`pose_suite`.
    image_size : (int, int), optional
        ``(width, height)``; the intrinsics are scaled from 640 x 480 (same field of view).
    seed : int, optional
        Seed of the room; default (None) the case's own fixed seed. Boxes are
        kept clear of both cameras (:meth:`PoseCase.keep_clear`) whatever the seed.
    supersample : int, optional
        Passed to :func:`render`.

    Returns
    -------
    ImagePair
        ``image1, image2`` (uint8), ``depth1, depth2`` (metres), ``K1, K2, R, t``
        (true, ``X2 = R X1 + t``), ``geometry_true`` and ``geometry`` (what a
        matcher is given; perturbed for ``noisy_pose``).

    Examples
    --------
    >>> pair = make_pair("forward", image_size=(80, 60))
    >>> pair.image1.shape, pair.depth2.shape, bool(pair.t[2] < 0)
    ((60, 80), (60, 80), True)
    """
    suite = _suite()
    if name not in suite:
        raise ValueError(f"name must be one of {list(suite)}, got {name!r}")
    case = suite[name]
    size = as_image_size(image_size, "image_size")
    s = case.seed if seed is None else int(seed)
    scene = _case_scene(s, tuple(tuple(c.tolist()) for c in case.keep_clear()))
    K1, K2 = case.intrinsics(size)
    image1, depth1 = render(scene, K1, case.R1, case.t1, size, supersample)
    image2, depth2 = render(scene, K2, case.R2, case.t2, size, supersample)
    return ImagePair(name, image1, image2, case.geometry(size, given=True), case.geometry(size), depth1, depth2, None, 3.0)


# --------------------------------------------------------------------------------------
# Posed collections (many views of one room)
# --------------------------------------------------------------------------------------
@dataclass(frozen=True, eq=False)
class PosedCollection:
    """Several rendered views of one room, with exact poses and depth.

    Made by :func:`make_collection`.

    Attributes
    ----------
    names : tuple of str
        File names, ``view_000.png``, ...
    images : tuple of (H, W) uint8
    depths : tuple of (H, W) float64
        ``z`` per pixel, metres, ``inf`` where the view sees nothing.
    K : (3, 3) float64
        Shared intrinsics (pixel centres at integer coordinates).
    R : (n, 3, 3) float64
    t : (n, 3) float64
        World-to-camera poses, ``X_cam = R[i] @ X_world + t[i]``.
    image_size : (int, int)
        ``(width, height)``.
    """

    names: tuple
    images: tuple
    depths: tuple
    K: np.ndarray
    R: np.ndarray
    t: np.ndarray
    image_size: tuple

    def __len__(self) -> int:
        return len(self.names)

    def geometry(self, i: int, j: int) -> TwoViewGeometry:
        """True :class:`TwoViewGeometry` from view ``i`` to view ``j``."""
        return TwoViewGeometry.from_world_poses(self.K, self.R[i], self.t[i], self.K, self.R[j], self.t[j],
                                                image_size1=self.image_size, image_size2=self.image_size)


def collection_poses(n_views: int = 12) -> tuple[np.ndarray, np.ndarray]:
    """World-to-camera poses of :func:`make_collection`: a walk on an arc with several baselines.

    The cameras stand on an arc of radius 3.2 m around the room's centre at
    about 1.5 m from the back wall, turning from -45 to +45 degrees, and look
    at points near the front wall; every third camera steps 0.9 m towards
    its target (forward motion, so epipoles fall inside the images). Neighbours
    are about 0.5 m apart, the ends of the arc about 4.5 m.

    Returns
    -------
    R : (n, 3, 3) float64
    t : (n, 3) float64
    """
    n = int(n_views)
    if n < 2:
        raise ValueError(f"n_views must be at least 2, got {n_views!r}")
    Rs, ts = [], []
    for i, a in enumerate(np.deg2rad(np.linspace(-45.0, 45.0, n))):
        c = np.array([3.2 * np.sin(a), -0.15 + 0.1 * np.sin(2.7 * i), 0.3 - 3.2 * np.cos(a)])
        target = np.array([1.6 * np.sin(1.3 * a) + 0.4 * np.sin(1.9 * i), 0.2, 4.0])
        if i % 3 == 2:
            d = target - c
            c = c + 0.9 * d / np.linalg.norm(d)
        R, t = look_at(c, target, roll=0.03 * np.sin(3.1 * i))
        Rs.append(R)
        ts.append(t)
    return np.array(Rs), np.array(ts)


def make_collection(n_views: int = 12, image_size=SUITE_IMAGE_SIZE, seed: int = 7, focal: float = 500.0,
                    supersample: int = 2) -> PosedCollection:
    """Render ``n_views`` posed views of one room with boxes (see :func:`collection_poses`).

    Parameters
    ----------
    n_views : int, optional
        At least 2.
    image_size : (int, int), optional
        ``(width, height)``.
    seed : int, optional
        Seed of the room (:func:`make_room_scene`); boxes keep clear of every camera.
    focal : float, optional
        Focal length in pixels at 640 x 480, scaled with ``image_size``.
    supersample : int, optional
        Passed to :func:`render`.

    Returns
    -------
    PosedCollection

    Examples
    --------
    >>> c = make_collection(3, image_size=(64, 48))
    >>> len(c), c.images[0].shape, c.R.shape
    (3, (48, 64), (3, 3, 3))
    """
    size = as_image_size(image_size, "image_size")
    R, t = collection_poses(n_views)
    centers = [-Ri.T @ ti for Ri, ti in zip(R, t)]
    scene = make_room_scene(rng=seed, keep_clear=centers, clearance=0.9)
    K = _scale_K(_K(float(focal)), SUITE_IMAGE_SIZE, size)
    images, depths = [], []
    for Ri, ti in zip(R, t):
        img, depth = render(scene, K, Ri, ti, size, supersample)
        img.flags.writeable = False
        depth.flags.writeable = False
        images.append(img)
        depths.append(depth)
    for a in (K, R, t):
        a.flags.writeable = False
    names = tuple(f"view_{i:03d}.png" for i in range(len(R)))
    return PosedCollection(names, tuple(images), tuple(depths), K, R, t, size)
