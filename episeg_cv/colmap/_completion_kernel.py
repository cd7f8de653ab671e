"""The compiled loops of track completion (:mod:`.completion`): a grid of each view's keypoints, the
keypoints near each group's projections (:func:`nearby`, and its parallel twin with the same result), and the
tracks completed (:func:`additions`, serial: it applies the proposals in order).

Every array is checked and laid out by :func:`.completion.complete_groups`; these functions trust them.
Views are ``0 .. n_views - 1``; keypoints are numbered per view, and ``kp_ptr[k]:kp_ptr[k + 1]`` are view
``k``'s rows of the concatenated keypoint arrays.
"""

from __future__ import annotations

import numba as nb
import numpy as np
from numba import prange

from ._consensus_kernel import distinct_views, find_root, reprojection_error, triangulate_point

#: Norm codes of :func:`_distance` (those of the matching kernels' ``NORM_CODES`` by name).
L2, L1, HAMMING = 0, 1, 2


@nb.njit(cache=True, nogil=True)
def build_grid(kp_xy, kp_ptr, sizes, tau):
    """Each view's keypoints bucketed in square cells: ``(cell, cell_ptr, cell_off, cell_nx, cell_items)``.

    View ``k``'s cells have side ``cell[k]`` = ``max(tau, sqrt(w h / n))`` pixels (about one keypoint per
    cell, never smaller than the search radius), ``cell_nx[k]`` per row; cell ``c`` of view ``k`` holds the
    local keypoint indices ``cell_items[cell_ptr[cell_off[k] + c]:cell_ptr[cell_off[k] + c + 1]]``, in
    index order. Keypoints outside the image or without a position (NaN) are in no cell.
    """
    n_views = sizes.shape[0]
    cell = np.empty(n_views)
    cell_nx = np.empty(n_views, np.int64)
    cell_off = np.zeros(n_views + 1, np.int64)
    for k in range(n_views):
        w, h = sizes[k, 0], sizes[k, 1]
        n = max(kp_ptr[k + 1] - kp_ptr[k], 1)
        cell[k] = max(tau, np.sqrt(w * h / n))
        cell_nx[k] = np.int64(w / cell[k]) + 1
        cell_off[k + 1] = cell_off[k] + cell_nx[k] * (np.int64(h / cell[k]) + 1)
    total = kp_ptr[n_views]
    where = np.full(total, -1, np.int64)
    cell_ptr = np.zeros(cell_off[n_views] + 1, np.int64)
    for k in range(n_views):
        w, h = sizes[k, 0], sizes[k, 1]
        for q in range(kp_ptr[k], kp_ptr[k + 1]):
            x = kp_xy[q, 0] + 0.5  # (pixel centres at integers: the image is [-0.5, w - 0.5))
            y = kp_xy[q, 1] + 0.5
            if not (0.0 <= x < w and 0.0 <= y < h):
                continue
            c = cell_off[k] + np.int64(y / cell[k]) * cell_nx[k] + np.int64(x / cell[k])
            where[q] = c
            cell_ptr[c + 1] += 1
    for c in range(cell_off[n_views]):
        cell_ptr[c + 1] += cell_ptr[c]
    fill = cell_ptr[:-1].copy()
    cell_items = np.empty(cell_ptr[cell_off[n_views]], np.int64)
    for k in range(n_views):
        for q in range(kp_ptr[k], kp_ptr[k + 1]):
            c = where[q]
            if c >= 0:
                cell_items[fill[c]] = q - kp_ptr[k]
                fill[c] += 1
    return cell, cell_ptr, cell_off, cell_nx, cell_items


@nb.njit(cache=True, nogil=True)
def _distance(a, b, norm):
    """The descriptor distance of rows ``a`` and ``b`` in ``norm`` (a code of this module)."""
    s = 0.0
    if norm == HAMMING:
        for i in range(a.shape[0]):
            x = np.uint8(a[i]) ^ np.uint8(b[i])
            while x:
                s += 1.0
                x &= x - np.uint8(1)
        return s
    if norm == L1:
        for i in range(a.shape[0]):
            s += abs(np.float64(a[i]) - np.float64(b[i]))
        return s
    for i in range(a.shape[0]):
        d = np.float64(a[i]) - np.float64(b[i])
        s += d * d
    return np.sqrt(s)


@nb.njit(cache=True, nogil=True)
def _group(g, P, grp_ptr, grp_nodes, node_image, node_kp, node_xy, kp_xy, kp_ptr, descriptors, norm, sizes, tau,
           cell, cell_ptr, cell_off, cell_nx, cell_items, has, X, best_kp, best_d):
    """Row ``g`` of :func:`nearby`'s outputs (``X``: row ``g`` of its points)."""
    a, b = grp_ptr[g], grp_ptr[g + 1]
    if not triangulate_point(P, node_image, node_xy, grp_nodes[a:b], b - a, X):
        return
    has[:] = False
    for q in range(a, b):
        has[node_image[grp_nodes[q]]] = True
    for k in range(P.shape[0]):
        if has[k]:
            continue
        h0 = P[k, 0, 0] * X[0] + P[k, 0, 1] * X[1] + P[k, 0, 2] * X[2] + P[k, 0, 3]
        h1 = P[k, 1, 0] * X[0] + P[k, 1, 1] * X[1] + P[k, 1, 2] * X[2] + P[k, 1, 3]
        h2 = P[k, 2, 0] * X[0] + P[k, 2, 1] * X[1] + P[k, 2, 2] * X[2] + P[k, 2, 3]
        if not (h2 > 0.0):
            continue
        u = h0 / h2
        v = h1 / h2
        w, h = sizes[k, 0], sizes[k, 1]
        if not (-0.5 <= u < w - 0.5 and -0.5 <= v < h - 0.5):
            continue
        cs = cell[k]
        nx = cell_nx[k]
        ny = (cell_off[k + 1] - cell_off[k]) // nx
        x0 = max(np.int64((u + 0.5 - tau) / cs), 0)
        x1 = min(np.int64((u + 0.5 + tau) / cs), nx - 1)
        y0 = max(np.int64((v + 0.5 - tau) / cs), 0)
        y1 = min(np.int64((v + 0.5 + tau) / cs), ny - 1)
        d1 = np.inf
        y_best = -1
        dk = descriptors[k]
        for cy in range(y0, y1 + 1):
            for cx in range(x0, x1 + 1):
                c = cell_off[k] + cy * nx + cx
                for p in range(cell_ptr[c], cell_ptr[c + 1]):
                    y = cell_items[p]
                    dx = kp_xy[kp_ptr[k] + y, 0] - u
                    dy = kp_xy[kp_ptr[k] + y, 1] - v
                    if not (dx * dx + dy * dy <= tau * tau):
                        continue
                    d = np.inf
                    for q in range(a, b):
                        o = grp_nodes[q]
                        d = min(d, _distance(descriptors[node_image[o]][node_kp[o]], dk[y], norm))
                    if d < d1 or (d == d1 and y < y_best):
                        d1 = d
                        y_best = y
        best_kp[g, k] = y_best
        best_d[g, k] = d1


@nb.njit(cache=True, nogil=True)
def _outputs(n_groups, n_views):
    return (np.full((n_groups, n_views), -1, np.int64), np.full((n_groups, n_views), np.inf),
            np.full((n_groups, 3), np.nan))


@nb.njit(cache=True, nogil=True)
def nearby(P, grp_ptr, grp_nodes, node_image, node_kp, node_xy, kp_xy, kp_ptr, descriptors, norm, sizes, tau, cell,
           cell_ptr, cell_off, cell_nx, cell_items):
    """Each group's nearest keypoint, by descriptor, near its projection in each view it is not in:
    ``(best_kp (G, n_views) int64, best_d (G, n_views), points (G, 3))``.

    Group ``g``'s point is triangulated from its observations ``grp_nodes[grp_ptr[g]:grp_ptr[g + 1]]``;
    in each view ``k`` that holds none of them, where the point lies in front of the camera and inside the
    image, the keypoints within ``tau`` pixels of its projection are compared with the group's
    descriptors (a keypoint's distance to the group: the smallest to any of its observations).
    ``best_kp[g, k]`` is the nearest (ties: the lower index; -1: none, or the view holds the group),
    ``best_d`` its distance (inf: none), ``points`` the triangulated points (NaN where triangulation
    failed: no keypoint was then looked for).
    """
    n_groups = grp_ptr.shape[0] - 1
    n_views = P.shape[0]
    best_kp, best_d, points = _outputs(n_groups, n_views)
    has = np.zeros(n_views, np.bool_)
    for g in range(n_groups):
        _group(g, P, grp_ptr, grp_nodes, node_image, node_kp, node_xy, kp_xy, kp_ptr, descriptors, norm, sizes, tau,
               cell, cell_ptr, cell_off, cell_nx, cell_items, has, points[g], best_kp, best_d)
    return best_kp, best_d, points


@nb.njit(cache=True, nogil=True, parallel=True)
def nearby_parallel(P, grp_ptr, grp_nodes, node_image, node_kp, node_xy, kp_xy, kp_ptr, descriptors, norm, sizes, tau,
                    cell, cell_ptr, cell_off, cell_nx, cell_items, blocks):
    """:func:`nearby` on threads, in ``blocks`` blocks of groups (each group writes its own row only)."""
    n_groups = grp_ptr.shape[0] - 1
    n_views = P.shape[0]
    best_kp, best_d, points = _outputs(n_groups, n_views)
    for blk in prange(blocks):
        has = np.zeros(n_views, np.bool_)
        for g in range(blk * n_groups // blocks, (blk + 1) * n_groups // blocks):
            _group(g, P, grp_ptr, grp_nodes, node_image, node_kp, node_xy, kp_xy, kp_ptr, descriptors, norm, sizes,
                   tau, cell, cell_ptr, cell_off, cell_nx, cell_items, has, points[g], best_kp, best_d)
    return best_kp, best_d, points


@nb.njit(cache=True, nogil=True)
def _holds(head, nxt, rec_image, k):
    """Whether the track starting at record ``head`` has an observation in view ``k``."""
    r = head
    while r >= 0:
        if rec_image[r] == k:
            return True
        r = nxt[r]
    return False


@nb.njit(cache=True, nogil=True)
def _gather(head, nxt, rec_image, rec_xy, obs_image, obs_xy, n):
    """The track's observations appended to ``obs_*[n:]``; the new count."""
    r = head
    while r >= 0:
        obs_image[n] = rec_image[r]
        obs_xy[n, 0] = rec_xy[r, 0]
        obs_xy[n, 1] = rec_xy[r, 1]
        n += 1
        r = nxt[r]
    return n


@nb.njit(cache=True, nogil=True)
def additions(P, centers, grp_ptr, grp_nodes, node_image, node_kp, node_xy, group, kp_node, kp_xy, kp_ptr, sel, best_kp,
              order, tau, cos_min_angle, min_views, confident):
    """The tracks completed: ``(edge_a (E, 2), edge_b (E, 2), views (G,), n_added, n_merged)``.

    The proposals ``order`` (flat indices ``s * n_views + k`` of ``best_kp``: group ``sel[s]``, view ``k``;
    the descriptor test passed), in that order (nearest first), each on the tracks as they are by then: a
    track starts as a group. A proposal whose keypoint is an observation of another group's track proposes
    to merge the two; otherwise to add the keypoint, once (the first proposal takes it). It is applied when
    the track does not see view ``k`` yet (a merge: the two tracks share no view) and the point
    triangulated from all the observations reprojects within ``tau`` pixels in each, in front of its
    camera.

    A track that changed and spans at least ``min_views`` distinct views
    (:func:`~._consensus_kernel.distinct_views`), one more unless one of its groups is ``confident``, gives
    ``views[g]`` for each of its groups (-1 elsewhere) and new edges: every two of its observations that
    came from different groups or were added, as ``(image, keypoint)`` rows of ``edge_a`` and ``edge_b``.
    """
    n_groups = grp_ptr.shape[0] - 1
    n_views = P.shape[0]
    n_rec0 = grp_ptr[n_groups]
    cap = n_rec0 + order.shape[0]
    rec_image = np.empty(cap, np.int64)
    rec_kp = np.empty(cap, np.int64)
    rec_xy = np.empty((cap, 2))
    rec_unit = np.empty(cap, np.int64)
    nxt = np.full(cap, -1, np.int64)
    head = np.empty(n_groups, np.int64)
    tail = np.empty(n_groups, np.int64)
    for g in range(n_groups):
        head[g] = grp_ptr[g] if grp_ptr[g + 1] > grp_ptr[g] else -1
        tail[g] = grp_ptr[g + 1] - 1
        for q in range(grp_ptr[g], grp_ptr[g + 1]):
            v = grp_nodes[q]
            rec_image[q] = node_image[v]
            rec_kp[q] = node_kp[v]
            rec_xy[q, 0] = node_xy[v, 0]
            rec_xy[q, 1] = node_xy[v, 1]
            rec_unit[q] = g
            if q + 1 < grp_ptr[g + 1]:
                nxt[q] = q + 1
    parent = np.arange(n_groups)
    changed = np.zeros(n_groups, np.bool_)
    claimed = np.zeros(kp_ptr[n_views], np.bool_)
    obs_image = np.empty(2 * n_views, np.int64)
    obs_xy = np.empty((2 * n_views, 2))
    idx = np.arange(2 * n_views)
    X = np.empty(3)
    n_rec = n_rec0
    n_added = 0
    n_merged = 0
    for p in range(order.shape[0]):
        s = order[p] // n_views
        k = order[p] % n_views
        r = find_root(parent, sel[s])
        if _holds(head[r], nxt, rec_image, k):
            continue
        q = kp_ptr[k] + best_kp[s, k]
        v = kp_node[q]
        h = find_root(parent, group[v]) if v >= 0 and group[v] >= 0 else -1
        if h == r:
            continue
        if h < 0 and claimed[q]:
            continue
        n = _gather(head[r], nxt, rec_image, rec_xy, obs_image, obs_xy, 0)
        n0 = n
        if h >= 0:
            n = _gather(head[h], nxt, rec_image, rec_xy, obs_image, obs_xy, n)
            disjoint = True
            for a in range(n0):
                for b in range(n0, n):
                    if obs_image[a] == obs_image[b]:
                        disjoint = False
            if not disjoint:
                continue
        else:
            obs_image[n] = k
            obs_xy[n, 0] = kp_xy[q, 0]
            obs_xy[n, 1] = kp_xy[q, 1]
            n += 1
        if not triangulate_point(P, obs_image, obs_xy, idx, n, X):
            continue
        ok = True
        for a in range(n):
            if not (reprojection_error(P, obs_image[a], obs_xy[a, 0], obs_xy[a, 1], X) <= tau):
                ok = False
                break
        if not ok:
            continue
        if h >= 0:  # merge h into r
            parent[h] = r
            nxt[tail[r]] = head[h]
            tail[r] = tail[h]
            n_merged += 1
        else:
            rec_image[n_rec] = k
            rec_kp[n_rec] = best_kp[s, k]
            rec_xy[n_rec, 0] = kp_xy[q, 0]
            rec_xy[n_rec, 1] = kp_xy[q, 1]
            rec_unit[n_rec] = n_groups + n_rec
            nxt[tail[r]] = n_rec
            tail[r] = n_rec
            n_rec += 1
            claimed[q] = True
            n_added += 1
        changed[r] = True
    views = np.full(n_groups, -1, np.int64)
    root_views = np.full(n_groups, -1, np.int64)
    dirs = np.empty((2 * n_views, 3))
    n_edges = 0
    sure = np.zeros(n_groups, np.bool_)
    for g in range(n_groups):
        if confident[g]:
            sure[find_root(parent, g)] = True
    for g in range(n_groups):
        if parent[g] != g or not changed[g]:
            continue
        n = _gather(head[g], nxt, rec_image, rec_xy, obs_image, obs_xy, 0)
        triangulate_point(P, obs_image, obs_xy, idx, n, X)
        root_views[g] = distinct_views(obs_image, centers, X, idx, n, cos_min_angle, dirs)
        if root_views[g] < min_views + (0 if sure[g] else 1):
            root_views[g] = -1
        if root_views[g] >= min_views:
            n_edges += n * (n - 1) // 2
    edge_a = np.empty((n_edges, 2), np.int64)
    edge_b = np.empty((n_edges, 2), np.int64)
    e = 0
    for g in range(n_groups):
        r = find_root(parent, g)
        if root_views[r] < min_views:
            continue
        views[g] = root_views[r]
        if r != g:
            continue
        a = head[g]
        while a >= 0:
            b = nxt[a]
            while b >= 0:
                if rec_unit[a] != rec_unit[b]:
                    edge_a[e, 0] = rec_image[a]
                    edge_a[e, 1] = rec_kp[a]
                    edge_b[e, 0] = rec_image[b]
                    edge_b[e, 1] = rec_kp[b]
                    e += 1
                b = nxt[b]
            a = nxt[a]
    return edge_a[:e], edge_b[:e], views, n_added, n_merged


@nb.njit(cache=True, nogil=True)
def _lerp(a, p, q):
    """``p + a (q - p)`` in float32 with one rounding of the product and sum, as OpenCV's ``remap`` computes
    it (a fused multiply-add)."""
    return np.float32(np.float64(a) * np.float64(q - p) + np.float64(p))


@nb.njit(cache=True, nogil=True)
def sample(pixels, off, w, h, x, y):
    """Bilinear sample of the float32 image ``pixels[off:off + w h]`` (row-major, ``w`` by ``h``) at pixel
    ``(x, y)`` (pixel centres at integers), as ``cv2.remap(..., INTER_LINEAR, BORDER_CONSTANT, NaN)`` on
    float32 maps gives it: the position rounded to float32, NaN unless its four neighbours are in the image."""
    xf = np.float32(x)
    yf = np.float32(y)
    if not (xf >= 0 and xf < w - 1 and yf >= 0 and yf < h - 1):  # (False for NaN)
        return np.nan
    x0 = np.floor(xf)
    y0 = np.floor(yf)
    a = np.float32(xf - x0)
    b = np.float32(yf - y0)
    i = off + np.int64(y0) * w + np.int64(x0)
    top = _lerp(a, pixels[i], pixels[i + 1])
    bottom = _lerp(a, pixels[i + w], pixels[i + w + 1])
    return np.float64(_lerp(b, top, bottom))


@nb.njit(cache=True, nogil=True, error_model="numpy")
def _photo(t, Kinv, P, centers, X, k, y, obs_image, pixels, im_off, im_w, im_h, half, cos_max, ref, plane, other):
    """The least NCC of proposal ``t`` over its group's views (:func:`photo`); ``ref``, ``plane``, ``other``
    are scratch arrays of ``S`` samples."""
    v = k[t]
    C = centers[v]
    n = C - X[t]
    n = n / np.sqrt(n[0] * n[0] + n[1] * n[1] + n[2] * n[2])
    seen = False
    for a in range(obs_image.shape[1]):  # the angle test first: any view beyond it gives NaN
        u = obs_image[t, a]
        if u < 0:
            continue
        seen = True
        d = centers[u] - X[t]
        d = d / np.sqrt(d[0] * d[0] + d[1] * d[1] + d[2] * d[2])
        if not (d[0] * n[0] + d[1] * n[1] + d[2] * n[2] >= cos_max):
            return np.nan
    if not seen:
        return np.inf
    side = 2 * half + 1
    S = side * side
    num = n[0] * (X[t, 0] - C[0]) + n[1] * (X[t, 1] - C[1]) + n[2] * (X[t, 2] - C[2])
    mean = 0.0
    for s in range(S):
        px = y[t, 0] + (s % side - half)
        py = y[t, 1] + (s // side - half)
        ref[s] = sample(pixels, im_off[v], im_w[v], im_h[v], px, py)
        if np.isnan(ref[s]):
            return np.nan
        mean += ref[s]
        rx = Kinv[v, 0, 0] * px + Kinv[v, 0, 1] * py + Kinv[v, 0, 2]
        ry = Kinv[v, 1, 0] * px + Kinv[v, 1, 1] * py + Kinv[v, 1, 2]
        rz = Kinv[v, 2, 0] * px + Kinv[v, 2, 1] * py + Kinv[v, 2, 2]
        depth = num / (n[0] * rx + n[1] * ry + n[2] * rz)
        plane[s, 0] = C[0] + depth * rx
        plane[s, 1] = C[1] + depth * ry
        plane[s, 2] = C[2] + depth * rz
    mean /= S
    ref_ss = 0.0
    for s in range(S):
        ref[s] -= mean
        ref_ss += ref[s] * ref[s]
    least = np.inf
    for a in range(obs_image.shape[1]):
        u = obs_image[t, a]
        if u < 0:
            continue
        Pu = P[u]
        mean = 0.0
        for s in range(S):
            hx = Pu[0, 0] * plane[s, 0] + Pu[0, 1] * plane[s, 1] + Pu[0, 2] * plane[s, 2] + Pu[0, 3]
            hy = Pu[1, 0] * plane[s, 0] + Pu[1, 1] * plane[s, 1] + Pu[1, 2] * plane[s, 2] + Pu[1, 3]
            hz = Pu[2, 0] * plane[s, 0] + Pu[2, 1] * plane[s, 1] + Pu[2, 2] * plane[s, 2] + Pu[2, 3]
            other[s] = sample(pixels, im_off[u], im_w[u], im_h[u], hx / hz, hy / hz)
            if np.isnan(other[s]):
                return np.nan
            mean += other[s]
        mean /= S
        ss = 0.0
        cross = 0.0
        for s in range(S):
            o = other[s] - mean
            ss += o * o
            cross += ref[s] * o
        den = np.sqrt(ref_ss * ss)
        if not den > 1e-6:
            return np.nan
        least = min(least, cross / den)
    return least


@nb.njit(cache=True, nogil=True)
def photo(Kinv, P, centers, X, k, y, obs_image, pixels, im_off, im_w, im_h, half, cos_max):
    """The photometric check of every proposal (:func:`.completion.photo_consistency`): ``(T,)`` float64.

    Proposal ``t``'s ``(2 half + 1)^2`` pixels round ``y[t]`` in view ``k[t]`` (row by row) are cast onto
    the plane through ``X[t]`` facing the camera (``Kinv``: the inverses of ``P[:, :, :3]``) and projected
    into each view ``obs_image[t, a]`` (-1: none); the least NCC (inf: no view; NaN: a view at an angle
    cosine below ``cos_max``, a sample beyond an image, a flat patch). Images: view ``v``'s float32 pixels
    are ``pixels[im_off[v]:]``, ``im_w[v]`` by ``im_h[v]``.
    """
    T = k.shape[0]
    out = np.empty(T)
    S = (2 * half + 1) ** 2
    ref, plane, other = np.empty(S), np.empty((S, 3)), np.empty(S)
    for t in range(T):
        out[t] = _photo(t, Kinv, P, centers, X, k, y, obs_image, pixels, im_off, im_w, im_h, half, cos_max, ref,
                        plane, other)
    return out


@nb.njit(cache=True, nogil=True, parallel=True)
def photo_parallel(Kinv, P, centers, X, k, y, obs_image, pixels, im_off, im_w, im_h, half, cos_max, blocks):
    """:func:`photo` on threads, in ``blocks`` blocks of proposals."""
    T = k.shape[0]
    out = np.empty(T)
    S = (2 * half + 1) ** 2
    for blk in prange(blocks):
        ref, plane, other = np.empty(S), np.empty((S, 3)), np.empty(S)
        for t in range(blk * T // blocks, (blk + 1) * T // blocks):
            out[t] = _photo(t, Kinv, P, centers, X, k, y, obs_image, pixels, im_off, im_w, im_h, half, cos_max,
                            ref, plane, other)
    return out
