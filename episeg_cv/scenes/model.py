"""The scene model: textured planar quads, the room with boxes, and camera placement.

A :class:`Scene` is a set of textured planar quads (parallelograms): the
panels of a room seen from inside and the faces of boxes standing in it. The
textures are photographs shipped with scikit-image (``skimage.data``),
converted to grey.

Conventions: world-to-camera poses ``X_cam = R @ X_world + t``; cameras look
along ``+z``, ``x`` to the right and ``y`` down; the world of
:func:`make_room_scene` has ``y`` pointing down too (the floor is at
``y = +height / 2``). Lengths are in metres.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, field

import cv2
import numpy as np

from .._validation import as_array, as_nonnegative, as_vector3

__all__ = ["TEXTURE_NAMES", "TEXTURE_SIZE", "Quad", "Scene", "load_texture", "box_quads", "make_room_scene", "look_at"]

#: Photographs of ``skimage.data`` usable as textures by name.
TEXTURE_NAMES = (
    "astronaut", "coffee", "chelsea", "rocket", "brick", "gravel", "grass", "camera",
    "moon", "text", "coins", "page", "clock", "immunohistochemistry", "hubble_deep_field",
)

#: Side of the square, power-of-two textures kept by a :class:`Scene`.
TEXTURE_SIZE = 512



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
    mips: tuple = field(init=False, repr=False)  #: per texture, its mip-map pyramid (finest first)

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
        object.__setattr__(self, "mips", tuple(_mip_pyramid(t) for t in textures))


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
