"""Figures with ``cv2`` only: epipolar segments as in the paper, and matches.

Every function takes grey or colour images (``(H, W)``, ``(H, W, 1)``,
``(H, W, 3)`` BGR or ``(H, W, 4)`` BGRA; uint8, uint16 or float in ``[0, 1]``)
and returns a new ``(H, W, 3)`` uint8 BGR image; :func:`save_image` writes it
with ``cv2.imwrite``. Line widths, markers and text scale with the image size.

Colours (BGR) are in :data:`COLORS`: the correct visible segment is green,
the excluded pieces of the epipolar line red, the epipole a magenta cross and
the virtual infinity points orange diamonds.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from ._validation import as_points
from .geometry import EpipolarSegments
from .io.paths import output_file, written_atomically

__all__ = ["COLORS", "draw_segments", "draw_points", "draw_segment_figure", "draw_matches", "save_image"]

#: BGR colours used by the figures.
COLORS = {
    "segment": (0, 200, 0),
    "excluded": (40, 40, 230),
    "epipole": (255, 0, 255),
    "infinity": (0, 165, 255),
    "point": (0, 255, 255),
    "correct": (0, 200, 0),
    "wrong": (40, 40, 230),
    "unknown": (255, 160, 0),
    "text": (255, 255, 255),
    "outline": (0, 0, 0),
}

_SHIFT = 4  # sub-pixel bits for cv2 drawing
_ONE = 1 << _SHIFT


def _to_bgr(image, name: str) -> np.ndarray:
    img = np.asarray(image)
    if img.ndim == 3 and img.shape[2] == 1:
        img = img[:, :, 0]
    if img.ndim not in (2, 3) or (img.ndim == 3 and img.shape[2] not in (3, 4)) or 0 in img.shape[:2]:
        raise ValueError(f"{name} must be an (H, W), (H, W, 1), (H, W, 3) or (H, W, 4) image, got shape {img.shape}")
    if img.dtype == np.uint16:
        img = (img // 257).astype(np.uint8)
    elif np.issubdtype(img.dtype, np.floating) or img.dtype == bool:
        img = np.clip(np.nan_to_num(img.astype(np.float64)) * 255.0 + 0.5, 0, 255).astype(np.uint8)
    elif img.dtype != np.uint8:
        raise TypeError(f"{name} must be uint8, uint16 or float in [0, 1], got dtype {img.dtype}")
    if img.ndim == 2:
        return cv2.cvtColor(img, cv2.COLOR_GRAY2BGR)
    if img.shape[2] == 4:
        return cv2.cvtColor(img, cv2.COLOR_BGRA2BGR)
    return np.ascontiguousarray(img).copy()


class _Style:
    """Sizes that scale with the image: 1 at 640 px on the long side."""

    def __init__(self, shape):
        s = max(shape[0], shape[1]) / 640.0
        self.thick = max(1, int(round(2 * s)))
        self.thin = max(1, int(round(1 * s)))
        self.marker = max(8, int(round(16 * s)))
        self.radius = max(2, int(round(4 * s)))
        self.font = 0.5 * max(s, 0.6)
        self.font_thick = max(1, int(round(1.2 * s)))


def _fix(p) -> tuple[int, int]:
    return int(round(p[0] * _ONE)), int(round(p[1] * _ONE))


def _finite(p) -> bool:
    return bool(np.all(np.isfinite(p))) and bool(np.all(np.abs(p) < 1e6))


def _inside(p, shape) -> bool:
    return _finite(p) and -0.5 <= p[0] <= shape[1] - 0.5 and -0.5 <= p[1] <= shape[0] - 0.5


def _line(img, a, b, color, thickness):
    if _finite(a) and _finite(b):
        cv2.line(img, _fix(a), _fix(b), color, thickness, cv2.LINE_AA, _SHIFT)


def _dot(img, p, color, radius, filled=True, thickness=1):
    if _finite(p):
        cv2.circle(img, _fix(p), radius * _ONE, color, -1 if filled else thickness, cv2.LINE_AA, _SHIFT)


def _text(img, text, org, st: _Style, color=None):
    """Text with a dark outline so that it reads on any background; clamped into the image."""
    (w, h), base = cv2.getTextSize(text, cv2.FONT_HERSHEY_SIMPLEX, st.font, st.font_thick)
    x = int(np.clip(org[0], 2, max(2, img.shape[1] - w - 2)))
    y = int(np.clip(org[1], h + 2, max(h + 2, img.shape[0] - base - 2)))
    cv2.putText(img, text, (x, y), cv2.FONT_HERSHEY_SIMPLEX, st.font, COLORS["outline"], st.font_thick + 2, cv2.LINE_AA)
    cv2.putText(img, text, (x, y), cv2.FONT_HERSHEY_SIMPLEX, st.font, color or COLORS["text"], st.font_thick,
                cv2.LINE_AA)


def _legend(img, entries, st: _Style, corner="top-left", ink=None):
    """A box of ``(kind, colour, text)`` rows; kind in {'line', 'cross', 'diamond', 'dot', 'none'}.

    With ``ink`` (an (H, W) bool mask of what the figure drew) the corner is
    chosen to cover the least of it.
    """
    if not entries:
        return img
    (_, th), base = cv2.getTextSize("Ag", cv2.FONT_HERSHEY_SIMPLEX, st.font, st.font_thick)
    row = th + base + 2 * st.thin + 4
    sym = max(st.marker, 3 * row // 2)
    widths = [cv2.getTextSize(t, cv2.FONT_HERSHEY_SIMPLEX, st.font, st.font_thick)[0][0] for _, _, t in entries]
    pad = max(4, row // 3)
    bw = pad * 3 + sym + max(widths)
    bh = pad * 2 + row * len(entries)

    def origin(c):
        return (pad if c.endswith("left") else max(0, img.shape[1] - bw - pad),
                pad if c.startswith("top") else max(0, img.shape[0] - bh - pad))

    if ink is not None:  # the corner that hides the least of what was drawn
        corners = ("top-left", "top-right", "bottom-left", "bottom-right")
        cost = [np.count_nonzero(ink[y:y + bh, x:x + bw]) for x, y in map(origin, corners)]
        corner = corners[int(np.argmin(cost))]
    x0, y0 = origin(corner)
    x1, y1 = min(img.shape[1], x0 + bw), min(img.shape[0], y0 + bh)
    roi = img[y0:y1, x0:x1]
    roi[:] = (roi.astype(np.float32) * 0.35).astype(np.uint8)
    cv2.rectangle(img, (x0, y0), (x1 - 1, y1 - 1), (200, 200, 200), 1)
    for k, (kind, color, text) in enumerate(entries):
        cy = y0 + pad + row * k + row // 2
        sx = x0 + pad
        if kind == "line":
            cv2.line(img, (sx, cy), (sx + sym, cy), color, st.thick + 1, cv2.LINE_AA)
        elif kind == "cross":
            cv2.drawMarker(img, (sx + sym // 2, cy), color, cv2.MARKER_TILTED_CROSS, min(sym, row), st.thick)
        elif kind == "diamond":
            cv2.drawMarker(img, (sx + sym // 2, cy), color, cv2.MARKER_DIAMOND, min(sym, row), st.thick)
        elif kind == "dot":
            cv2.circle(img, (sx + sym // 2, cy), st.radius, color, -1, cv2.LINE_AA)
        cv2.putText(img, text, (sx + sym + pad, cy + th // 2), cv2.FONT_HERSHEY_SIMPLEX, st.font, COLORS["text"],
                    st.font_thick, cv2.LINE_AA)
    return img


def _labels(labels, n):
    if labels is True:
        return [str(i + 1) for i in range(n)]
    if labels is False or labels is None:
        return [None] * n
    labels = [str(x) for x in labels]
    if len(labels) != n:
        raise ValueError(f"labels must be a bool or hold one label per point ({n}), got {len(labels)}")
    return labels


def _as_correct(correct, n, name="correct"):
    if correct is None:
        return None
    c = np.asarray(correct)
    if c.shape != (n,) or c.dtype != bool:
        raise ValueError(f"{name} must be a ({n},) bool array, got shape {c.shape} and dtype {c.dtype}")
    return c


def draw_segments(image2, segments: EpipolarSegments, points=None, correct=None, labels=True,
                  legend: bool = True) -> np.ndarray:
    """The paper's figure in image 2: each epipolar line split into its correct and excluded parts.

    For each query point of image 1: the whole epipolar line clipped to the
    image (``segments.line_start`` to ``line_end``) in red, the correct
    visible segment (``start`` to ``end``) in green over it, and the point's
    number next to the segment. The epipole and the virtual infinity points
    are marked where they fall inside the image. An empty segment (the ray is
    behind camera 2) leaves only the red line; pure rotation gives a green dot.

    Parameters
    ----------
    image2 : (H, W) or (H, W, 3) array
        Image 2, grey or BGR.
    segments : EpipolarSegments
        From :meth:`TwoViewGeometry.segments` for the query points.
    points : (N, 2) array_like, optional
        A point of image 2 per segment to mark (a match, or the true
        projection); rows with NaN are skipped.
    correct : (N,) bool, optional
        Colours ``points`` green (True) or red (False); blue when omitted.
    labels : bool or sequence of str, optional
        Number the segments ``1..N`` (True), not at all, or with these labels.
    legend : bool, optional
        Draw the legend box.

    Returns
    -------
    (H, W, 3) uint8
        A new BGR image.

    Examples
    --------
    >>> import numpy as np
    >>> from episeg_cv import TwoViewGeometry
    >>> K = [[50, 0, 49.5], [0, 50, 49.5], [0, 0, 1]]
    >>> g = TwoViewGeometry(K, K, np.eye(3), [0, 0, -1], image_size1=(100, 100), image_size2=(100, 100))
    >>> img = draw_segments(np.zeros((100, 100), np.uint8), g.segments([[80.0, 49.5]]), legend=False)
    >>> img.shape, img.dtype.name
    ((100, 100, 3), 'uint8')
    >>> int(img[49, 90].argmax()), int(img[49, 20].argmax())    # green beyond p_inf = x1, red towards the epipole
    (1, 2)
    """
    if not isinstance(segments, EpipolarSegments):
        raise TypeError(f"segments must be an EpipolarSegments, got {type(segments).__name__}")
    img = _to_bgr(image2, "image2")
    base = img.copy()
    st = _Style(img.shape)
    n = len(segments)
    names = _labels(labels, n)
    pts = None
    if points is not None:
        pts = np.asarray(points, dtype=np.float64)
        if pts.shape != (n, 2):
            raise ValueError(f"points must have shape ({n}, 2), one per segment, got shape {pts.shape}")
    ok = _as_correct(correct, n)
    for i in range(n):
        _line(img, segments.line_start[i], segments.line_end[i], COLORS["excluded"], st.thick)
    for i in range(n):
        if segments.valid[i]:
            a, b = segments.start[i], segments.end[i]
            if np.hypot(*(b - a)) < 0.5:
                _dot(img, (a + b) / 2, COLORS["segment"], st.radius)
            else:
                _line(img, a, b, COLORS["segment"], st.thick)
    has_inf = False
    for i in range(n):
        p = segments.infinity_point[i]
        if _inside(p, img.shape):
            has_inf = True
            cv2.drawMarker(img, (int(round(p[0])), int(round(p[1]))), COLORS["infinity"], cv2.MARKER_DIAMOND,
                           st.marker, st.thick, cv2.LINE_AA)
    e = segments.epipole
    has_epi = _inside(e, img.shape)
    if has_epi:
        cv2.drawMarker(img, (int(round(e[0])), int(round(e[1]))), COLORS["epipole"], cv2.MARKER_TILTED_CROSS,
                       int(st.marker * 1.5), st.thick + 1, cv2.LINE_AA)
    if pts is not None:
        for i in range(n):
            color = COLORS["unknown"] if ok is None else COLORS["correct" if ok[i] else "wrong"]
            _dot(img, pts[i], COLORS["outline"], st.radius + 2)
            _dot(img, pts[i], color, st.radius + 1)
    for i, name in enumerate(names):
        if name is None:
            continue
        if segments.valid[i]:
            anchor = segments.end[i]
        elif _finite(segments.line_start[i]):
            anchor = (segments.line_start[i] + segments.line_end[i]) / 2
        else:
            continue
        _text(img, name, (anchor[0] + st.radius + 2, anchor[1] - st.radius - 2), st)
    if legend:
        entries = [("line", COLORS["segment"], "correct segment"), ("line", COLORS["excluded"], "excluded part of line")]
        if has_epi:
            entries.append(("cross", COLORS["epipole"], "epipole"))
        if has_inf:
            entries.append(("diamond", COLORS["infinity"], "virtual infinity point"))
        if pts is not None:
            if ok is None:
                entries.append(("dot", COLORS["unknown"], "point in image 2"))
            else:
                entries.append(("dot", COLORS["correct"], f"correct match ({int(ok.sum())})"))
                entries.append(("dot", COLORS["wrong"], f"wrong match ({int((~ok).sum())})"))
        _legend(img, entries, st, ink=np.any(img != base, axis=2))
    return img


def draw_points(image1, points, numbers=True, color=None) -> np.ndarray:
    """Image 1 with the query points circled and numbered ``1..N``.

    Parameters
    ----------
    image1 : (H, W) or (H, W, 3) array
    points : (N, 2) array_like
        Pixels of image 1.
    numbers : bool or sequence of str, optional
        As ``labels`` of :func:`draw_segments`.
    color : (B, G, R), optional
        Default ``COLORS["point"]`` (yellow).

    Returns
    -------
    (H, W, 3) uint8

    Examples
    --------
    >>> img = draw_points(np.zeros((60, 80), np.uint8), [[40.0, 30.0]])
    >>> img.shape, img[30, 40].tolist() == list(COLORS["point"])
    ((60, 80, 3), True)
    """
    img = _to_bgr(image1, "image1")
    p = as_points(points, "points")
    st = _Style(img.shape)
    names = _labels(numbers, len(p))
    color = COLORS["point"] if color is None else tuple(int(c) for c in color)
    for q, name in zip(p, names):
        _dot(img, q, COLORS["outline"], st.radius + 2)
        _dot(img, q, color, st.radius + 1)
        cv2.circle(img, _fix(q), (st.marker // 2 + st.radius) * _ONE, color, st.thin, cv2.LINE_AA, _SHIFT)
        if name is not None:
            _text(img, name, (q[0] + st.marker // 2 + st.radius, q[1] - st.radius), st)
    return img


def _side_by_side(a: np.ndarray, b: np.ndarray, gap: int) -> np.ndarray:
    h = max(a.shape[0], b.shape[0])
    out = np.zeros((h, a.shape[1] + gap + b.shape[1], 3), np.uint8)
    out[:a.shape[0], :a.shape[1]] = a
    out[:b.shape[0], a.shape[1] + gap:] = b
    return out


def draw_segment_figure(image1, image2, points1, segments: EpipolarSegments, points2=None, correct=None,
                        gap: int = 8) -> np.ndarray:
    """The two-panel figure: image 1 with the numbered points | image 2 with their segments.

    Parameters
    ----------
    image1, image2 : arrays
        Grey or BGR images.
    points1 : (N, 2) array_like
        The query points of image 1, from which ``segments`` were computed.
    segments : EpipolarSegments
    points2, correct : optional
        As ``points`` and ``correct`` of :func:`draw_segments`.
    gap : int, optional
        Black columns between the panels.

    Returns
    -------
    (T + max(H1, H2), W1 + gap + W2, 3) uint8
        With a title bar of height ``T`` on top.

    Examples
    --------
    >>> import numpy as np
    >>> from episeg_cv import TwoViewGeometry
    >>> K = [[50, 0, 49.5], [0, 50, 39.5], [0, 0, 1]]
    >>> g = TwoViewGeometry(K, K, np.eye(3), [-1, 0, 0], image_size1=(100, 80), image_size2=(100, 80))
    >>> fig = draw_segment_figure(np.zeros((80, 100)), np.zeros((80, 100)), [[60.0, 20.0]], g.segments([[60.0, 20.0]]))
    >>> fig.shape[1:]
    (208, 3)
    """
    p1 = as_points(points1, "points1")
    if not isinstance(segments, EpipolarSegments):
        raise TypeError(f"segments must be an EpipolarSegments, got {type(segments).__name__}")
    if len(p1) != len(segments):
        raise ValueError(f"points1 has {len(p1)} points but segments has {len(segments)}")
    left = draw_points(image1, p1)
    right = draw_segments(image2, segments, points2, correct)
    panels = _side_by_side(left, right, int(gap))
    st = _Style(left.shape)
    (_, th), base = cv2.getTextSize("Ag", cv2.FONT_HERSHEY_SIMPLEX, st.font, st.font_thick)
    bar = np.zeros((th + base + 4 * st.thin + 4, panels.shape[1], 3), np.uint8)
    for x, title in ((0, "image 1: query points"), (left.shape[1] + int(gap), "image 2: epipolar segments")):
        cv2.putText(bar, title, (x + 4, th + 2 * st.thin + 2), cv2.FONT_HERSHEY_SIMPLEX, st.font, COLORS["text"],
                    st.font_thick, cv2.LINE_AA)
    return np.vstack([bar, panels])


def draw_matches(image1, image2, points1, points2, pairs, correct=None, gap: int = 8,
                 max_lines: int | None = None, rng=None) -> np.ndarray:
    """Both images side by side with a line per match: green correct, red wrong, blue unknown.

    Parameters
    ----------
    image1, image2 : arrays
        Grey or BGR images.
    points1, points2 : (N1, 2), (N2, 2) array_like
        Keypoint positions in pixels.
    pairs : (K, 2) integer array_like
        ``(i1, i2)`` indices into ``points1`` and ``points2``.
    correct : (K,) bool, optional
        Which matches are right; without it every line is drawn in blue.
    gap : int, optional
        Black columns between the images.
    max_lines : int, optional
        Draw at most this many lines (a random subset, the counts in the legend
        stay those of all matches).
    rng : int or numpy.random.Generator, optional
        For the subset.

    Returns
    -------
    (max(H1, H2), W1 + gap + W2, 3) uint8

    Examples
    --------
    >>> img = draw_matches(np.zeros((200, 300)), np.zeros((150, 320)), [[250.0, 150.0]], [[20.0, 100.0]], [[0, 0]], [False])
    >>> img.shape, int(img[150, 250].argmax())          # a red dot on the keypoint of image 1
    ((200, 628, 3), 2)
    """
    a, b = _to_bgr(image1, "image1"), _to_bgr(image2, "image2")
    p1, p2 = as_points(points1, "points1"), as_points(points2, "points2")
    m = np.asarray(pairs)
    if m.size == 0:
        m = np.zeros((0, 2), np.intp)
    if m.ndim != 2 or m.shape[1] != 2 or not np.issubdtype(m.dtype, np.integer):
        raise ValueError(f"pairs must be a (K, 2) integer array, got shape {m.shape} and dtype {m.dtype}")
    if len(m) and (m.min() < 0 or m[:, 0].max() >= len(p1) or m[:, 1].max() >= len(p2)):
        raise ValueError(f"pairs index out of range for {len(p1)} and {len(p2)} keypoints")
    ok = _as_correct(correct, len(m))
    out = _side_by_side(a, b, int(gap))
    st = _Style(a.shape)
    off = np.array([a.shape[1] + int(gap), 0.0])
    order = np.arange(len(m))
    if max_lines is not None and len(m) > max_lines:
        order = np.sort(np.random.default_rng(rng).choice(len(m), int(max_lines), replace=False))
    if ok is not None:  # wrong ones last, on top
        order = order[np.argsort(~ok[order], kind="stable")]
    width = st.thin
    for k in order:
        color = COLORS["unknown"] if ok is None else COLORS["correct" if ok[k] else "wrong"]
        q1, q2 = p1[m[k, 0]], p2[m[k, 1]] + off
        _line(out, q1, q2, color, width)
        _dot(out, q1, color, max(1, st.radius - 1))
        _dot(out, q2, color, max(1, st.radius - 1))
    if ok is None:
        entries = [("line", COLORS["unknown"], f"matches: {len(m)} (correctness unknown)")]
    else:
        prec = f", precision {ok.mean():.1%}" if len(m) else ""
        entries = [("line", COLORS["correct"], f"correct: {int(ok.sum())}"),
                   ("line", COLORS["wrong"], f"wrong: {int((~ok).sum())}{prec}")]
    if len(order) < len(m):
        entries.append(("none", COLORS["text"], f"{len(order)} of {len(m)} lines drawn"))
    _legend(out, entries, st)
    return out


def save_image(path, image) -> Path:
    """Write ``image`` with ``cv2.imwrite``, creating the folder; raise ``OSError`` if it fails.

    Returns
    -------
    pathlib.Path
    """
    path = Path(path)
    if not cv2.haveImageWriter(str(path)):
        raise ValueError(f"image {str(path)!r}: OpenCV cannot write the extension {path.suffix!r} "
                         "(use .png, .jpg, .tif, ...)")
    path = output_file(path, "image")
    try:
        ok, data = cv2.imencode(path.suffix, np.asarray(image))
    except cv2.error as exc:
        raise ValueError(f"cannot encode image {str(path)!r}: {str(exc).strip().splitlines()[-1]}") from None
    if not ok:
        raise ValueError(f"cannot encode image {str(path)!r} as {path.suffix}")
    try:
        with written_atomically(path) as tmp:
            tmp.write_bytes(data.tobytes())
    except OSError as exc:
        raise OSError(f"cannot write image {str(path)!r}: {exc.strerror}") from None
    return path
