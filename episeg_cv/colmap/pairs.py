"""Which pairs of a collection to match: a pairs file, every pair, or each view's best partners."""

from __future__ import annotations

import numpy as np

from ..io.paths import input_file

__all__ = ["read_pairs", "index_pairs", "exhaustive_pairs", "overlap_scores", "neighbor_pairs", "sample_grid"]


def read_pairs(path, names) -> list[tuple[int, int]]:
    """Read a pairs file: one ``name1 name2`` per line (COLMAP's and hloc's format).

    Blank lines and lines starting with ``#`` are skipped; a pair listed twice
    (in either order) is kept once.

    Parameters
    ----------
    path : str or Path
    names : sequence of str
        The collection's image names; a pair is returned as two indices into it.

    Returns
    -------
    list of (int, int)
        Index pairs ``(i, j)`` with ``i < j``, in file order.

    Raises
    ------
    ValueError
        ``path:line: ...`` for a line without two names, an unknown image, or
        an image paired with itself.
    """
    items = []
    path = input_file(path, "pairs file")
    try:
        text = path.read_text(encoding="utf-8-sig")
    except UnicodeDecodeError as e:
        raise ValueError(f"pairs file {str(path)!r} is not a text file ({e.reason} at byte {e.start})") from None
    for lineno, raw in enumerate(text.splitlines(), 1):
        line = raw.strip()
        if not line or line.startswith("#"):
            continue
        parts = line.split()
        if len(parts) < 2:
            raise ValueError(f"{path}:{lineno}: expected 'name1 name2', got {line!r}")
        items.append((f"{path}:{lineno}", parts[0], parts[1]))
    if not items:
        raise ValueError(f"pairs file {str(path)!r} lists no pairs (only blank lines or comments)")
    return index_pairs(items, names)


def index_pairs(items, names) -> list[tuple[int, int]]:
    """``(where, name1, name2)`` items -> unique index pairs ``(i, j)``, ``i < j``, in order.

    Raises ``ValueError`` prefixed with ``where`` for an unknown image or an image paired with itself.
    """
    index = {n: i for i, n in enumerate(names)}
    out, seen = [], set()
    for where, a, b in items:
        for n in (a, b):
            if n not in index:
                raise ValueError(f"{where}: unknown image {n!r} (not in the model)")
        if a == b:
            raise ValueError(f"{where}: image {a!r} is paired with itself")
        key = (min(index[a], index[b]), max(index[a], index[b]))
        if key not in seen:
            seen.add(key)
            out.append(key)
    return out


def exhaustive_pairs(n: int) -> list[tuple[int, int]]:
    """Every pair ``(i, j)``, ``i < j < n``."""
    return [(i, j) for i in range(n) for j in range(i + 1, n)]


def sample_grid(image_size, n: int = 12) -> np.ndarray:
    w, h = image_size
    xs = (np.arange(n) + 0.5) * w / n - 0.5
    ys = (np.arange(n) + 0.5) * h / n - 0.5
    return np.stack(np.meshgrid(xs, ys), -1).reshape(-1, 2)


def overlap_scores(views, samples: int = 12) -> np.ndarray:
    """View overlap from the segment test: which sampled pixels of one view can be seen by the other.

    For each ordered pair ``(i, j)``, a ``samples x samples`` grid of pixels of
    view ``i`` is tested: a pixel counts when its epipolar segment in view
    ``j``, within view ``i``'s depth range, is non-empty (it meets image
    ``j``). The score of the pair is the smaller of the two directions, in
    ``[0, 1]``. With ``depth_range=(0, inf)`` this is only a cheirality and
    field-of-view test; depth ranges make it a real overlap test.

    Returns
    -------
    (n, n) float64
        Symmetric, zero on the diagonal.
    """
    n = len(views)
    s = np.zeros((n, n))
    grids = [sample_grid(v.image_size, samples) for v in views]
    for i in range(n):
        for j in range(n):
            if i != j:
                seg = views[i].geometry_to(views[j]).segments(grids[i], views[i].depth_range)
                s[i, j] = seg.valid.mean()
    return np.minimum(s, s.T)


def neighbor_pairs(views, k: int, samples: int = 12) -> list[tuple[int, int]]:
    """For each view, its ``k`` best partners by :func:`overlap_scores` (ties: nearer camera first).

    Partners with a zero score are never chosen. Returns the union as sorted
    ``(i, j)``, ``i < j``.
    """
    if isinstance(k, bool) or not isinstance(k, (int, np.integer)) or k < 1:
        raise ValueError(f"neighbors must be a positive integer, got {k!r}")
    scores = overlap_scores(views, samples)
    centers = np.array([v.center for v in views])
    out = set()
    for i in range(len(views)):
        dist = np.linalg.norm(centers - centers[i], axis=1)
        order = np.lexsort((dist, -scores[i]))
        chosen = [j for j in order if j != i and scores[i, j] > 0][:k]
        out.update((min(i, j), max(i, j)) for j in chosen)
    return sorted(out)
