"""The compiled loop of the track consensus (:mod:`.consensus`): union-find, then RANSAC-style groups.

Components share no observation and no edge, so they are processed independently: one after the
other (:func:`consensus`) or in blocks on threads (:func:`consensus_parallel`), with the same result.
A component too big for one thread (false edges chain tracks into one: 82 % of the edges of the
24-view room) runs its own rounds on every thread, in speculative batches of chains applied in order;
a chain that read what an earlier one took runs again (:func:`_big_component`), again with the serial
result.

Every array is checked and laid out by :func:`.consensus.verify_tracks`; these
functions trust them. Nodes are (image, keypoint) observations, ``0 .. n-1``;
edges are candidate matches between two nodes of different images with their ratio values.
"""

from __future__ import annotations

import numba as nb
import numpy as np
from numba import prange


@nb.njit(cache=True, nogil=True)
def find_root(parent, x):
    """The root of ``x`` in the union-find forest ``parent`` (path halving)."""
    while parent[x] != x:
        parent[x] = parent[parent[x]]
        x = parent[x]
    return x


@nb.njit(cache=True, nogil=True)
def reprojection_error(P, k, x, y, X):
    """Reprojection error of ``X`` at ``(x, y)`` in view ``k``, pixels (inf behind the camera)."""
    h0 = P[k, 0, 0] * X[0] + P[k, 0, 1] * X[1] + P[k, 0, 2] * X[2] + P[k, 0, 3]
    h1 = P[k, 1, 0] * X[0] + P[k, 1, 1] * X[1] + P[k, 1, 2] * X[2] + P[k, 1, 3]
    h2 = P[k, 2, 0] * X[0] + P[k, 2, 1] * X[1] + P[k, 2, 2] * X[2] + P[k, 2, 3]
    if not (h2 > 0.0):
        return np.inf
    dx = h0 / h2 - x
    dy = h1 / h2 - y
    return np.sqrt(dx * dx + dy * dy)


@nb.njit(cache=True, nogil=True)
def triangulate_point(P, node_image, node_xy, nodes, count, out):
    """Least-squares point of ``count`` observations (linear, inhomogeneous, rows normalised).

    Each observation gives two rows ``x P3 - P1`` and ``y P3 - P2`` of ``A [X; 1] = 0``,
    scaled to unit norm; ``X`` solves the 3x3 normal equations. False when they are
    singular (parallel rays).
    """
    n00 = n01 = n02 = n11 = n12 = n22 = 0.0
    b0 = b1 = b2 = 0.0
    for q in range(count):
        v = nodes[q]
        k = node_image[v]
        for r in range(2):
            c = node_xy[v, r]
            a0 = c * P[k, 2, 0] - P[k, r, 0]
            a1 = c * P[k, 2, 1] - P[k, r, 1]
            a2 = c * P[k, 2, 2] - P[k, r, 2]
            a3 = c * P[k, 2, 3] - P[k, r, 3]
            nrm = np.sqrt(a0 * a0 + a1 * a1 + a2 * a2 + a3 * a3)
            if nrm == 0.0:
                continue
            a0 /= nrm
            a1 /= nrm
            a2 /= nrm
            a3 /= nrm
            n00 += a0 * a0
            n01 += a0 * a1
            n02 += a0 * a2
            n11 += a1 * a1
            n12 += a1 * a2
            n22 += a2 * a2
            b0 -= a0 * a3
            b1 -= a1 * a3
            b2 -= a2 * a3
    c00 = n11 * n22 - n12 * n12
    c01 = n02 * n12 - n01 * n22
    c02 = n01 * n12 - n02 * n11
    det = n00 * c00 + n01 * c01 + n02 * c02
    scale = (n00 + n11 + n22) / 3.0
    if not (abs(det) > 1e-12 * scale * scale * scale):
        return False
    c11 = n00 * n22 - n02 * n02
    c12 = n01 * n02 - n00 * n12
    c22 = n00 * n11 - n01 * n01
    out[0] = (c00 * b0 + c01 * b1 + c02 * b2) / det
    out[1] = (c01 * b0 + c11 * b1 + c12 * b2) / det
    out[2] = (c02 * b0 + c12 * b1 + c22 * b2) / det
    return True


@nb.njit(cache=True, nogil=True)
def _support(P, node_image, node_xy, X, a, b, adj_ptr, adj, eu, ev, alive, taken, chain, tau, stamp, mark, queue,
             best_err, best_node, touched, out):
    """The support of the point ``X`` grown from the observations ``a`` and ``b`` through the match graph:
    ``(count, score, visited)``; ``queue[:visited]`` are the alive observations it looked at.

    Breadth first from ``a`` and ``b`` along the edges, through alive observations only (``alive``, and not
    ``chain`` in ``taken``: a thread's own overlay of the groups its chain took), and only through
    those that reproject within ``tau`` pixels of ``X`` in front of their camera: the support is connected
    by candidate matches. Per image only the closest counts; they are written to ``out``. ``score`` is
    MSAC's (Torr and Zisserman 2000): the sum over them of ``1 - (error / tau)^2``, so that of two points
    explaining as many observations the one that explains them more tightly wins.
    """
    head = 0
    tail = 0
    for s in (a, b):
        if mark[s] != stamp:
            mark[s] = stamp
            queue[tail] = s
            tail += 1
    n_touched = 0
    while head < tail:
        v = queue[head]
        head += 1
        k = node_image[v]
        err = reprojection_error(P, k, node_xy[v, 0], node_xy[v, 1], X)
        if not (err <= tau):  # (inf behind the camera)
            continue
        if best_node[k] < 0:
            touched[n_touched] = k
            n_touched += 1
            best_err[k] = err
            best_node[k] = v
        elif err < best_err[k]:
            best_err[k] = err
            best_node[k] = v
        for p in range(adj_ptr[v], adj_ptr[v + 1]):
            w = eu[adj[p]] + ev[adj[p]] - v
            if mark[w] != stamp and alive[w] and taken[w] != chain:
                mark[w] = stamp
                queue[tail] = w
                tail += 1
    score = 0.0
    for q in range(n_touched):
        k = touched[q]
        out[q] = best_node[k]
        e = best_err[k] / tau
        score += 1.0 - e * e
        best_node[k] = -1
        best_err[k] = np.inf
    return n_touched, score, tail


@nb.njit(cache=True, nogil=True)
def _window(e0, adj_ptr, adj, eu, ev, rank, alive, taken, chain, dead, hops, limit, max_seeds, stamp, mark, queue,
            depth, seeds):
    """The seeds of a round: ``e0`` first, then the live edges of lowest ``rank`` (ratio, then input order)
    among the alive observations within ``hops`` edges of its ends (breadth first, at most ``limit``
    observations); at most ``max_seeds``, in ``seeds``. Returns their number and the number of
    observations in the window (``queue[:window]``)."""
    head = 0
    tail = 0
    for s in (eu[e0], ev[e0]):
        if mark[s] != stamp:
            mark[s] = stamp
            queue[tail] = s
            depth[tail] = 0
            tail += 1
    while head < tail and tail < limit:
        v = queue[head]
        d = depth[head]
        head += 1
        if d >= hops:
            continue
        for p in range(adj_ptr[v], adj_ptr[v + 1]):
            w = eu[adj[p]] + ev[adj[p]] - v
            if mark[w] != stamp and alive[w] and taken[w] != chain:
                mark[w] = stamp
                queue[tail] = w
                depth[tail] = d + 1
                tail += 1
                if tail >= limit:
                    break
    seeds[0] = e0
    n = 1
    for q in range(tail):
        v = queue[q]
        for p in range(adj_ptr[v], adj_ptr[v + 1]):
            k = adj[p]
            w = eu[k] + ev[k] - v
            # an edge with both ends in the window, once (from its lower end); ranks are distinct
            if k == e0 or w < v or dead[k] or mark[w] != stamp:
                continue
            # into seeds[1:n], ordered by rank, keeping the max_seeds - 1 lowest (e0 has the lowest of all)
            r = rank[k]
            if n < max_seeds:
                j = n
                n += 1
            elif rank[seeds[n - 1]] > r:
                j = n - 1
            else:
                continue
            while j > 1 and rank[seeds[j - 1]] > r:
                seeds[j] = seeds[j - 1]
                j -= 1
            seeds[j] = k
    return n, tail


@nb.njit(cache=True, nogil=True)
def distinct_views(node_image, centers, X, nodes, count, cos_min_angle, dirs):
    """How many of the observations ``nodes[:count]`` see the point ``X`` from directions at least the
    minimum angle apart (greedy, in order): views whose rays meet at a smaller angle count once."""
    n = 0
    for q in range(count):
        k = node_image[nodes[q]]
        d0 = centers[k, 0] - X[0]
        d1 = centers[k, 1] - X[1]
        d2 = centers[k, 2] - X[2]
        nrm = np.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
        if nrm > 0.0:
            d0 /= nrm
            d1 /= nrm
            d2 /= nrm
        new = True
        for r in range(n):
            if d0 * dirs[r, 0] + d1 * dirs[r, 1] + d2 * dirs[r, 2] > cos_min_angle:
                new = False
                break
        if new:
            dirs[n, 0] = d0
            dirs[n, 1] = d1
            dirs[n, 2] = d2
            n += 1
    return n


@nb.njit(cache=True, nogil=True)
def number_observations(img_a, img_b, pairs, start):
    """The candidates' ends numbered densely in (image, keypoint) order: ``(eu, ev, node_image, node_kp)``.

    Candidate ``e`` joins keypoint ``pairs[e, 0]`` of image ``img_a[e]`` to ``pairs[e, 1]`` of ``img_b[e]``;
    image ``k``'s keypoints are the ids ``start[k]:start[k + 1]`` (checked in range by the caller); the used
    ids are renumbered ``0 .. n-1`` in order."""
    m = img_a.shape[0]
    used = np.zeros(start[-1] + 1, np.int64)  # then: each id's new number plus one
    for e in range(m):
        used[start[img_a[e]] + pairs[e, 0]] = 1
        used[start[img_b[e]] + pairs[e, 1]] = 1
    n = 0
    for k in range(start.shape[0] - 1):
        for f in range(start[k], start[k + 1]):
            if used[f]:
                n += 1
                used[f] = n
    node_image, node_kp = np.empty(n, np.int64), np.empty(n, np.int64)
    for k in range(start.shape[0] - 1):
        for f in range(start[k], start[k + 1]):
            if used[f]:
                node_image[used[f] - 1], node_kp[used[f] - 1] = k, f - start[k]
    eu, ev = np.empty(m, np.int64), np.empty(m, np.int64)
    for e in range(m):
        eu[e] = used[start[img_a[e]] + pairs[e, 0]] - 1
        ev[e] = used[start[img_b[e]] + pairs[e, 1]] - 1
    return eu, ev, node_image, node_kp


@nb.njit(cache=True, nogil=True)
def _stable_by_key(items, keys, n_keys):
    """``items`` reordered by ``keys`` (ints in ``[0, n_keys)``, one per item), ties in their order: a
    counting sort, the order a stable sort by key gives, in linear time."""
    start = np.zeros(n_keys + 1, np.int64)
    for q in range(keys.shape[0]):
        start[keys[q] + 1] += 1
    for k in range(n_keys):
        start[k + 1] += start[k]
    out = np.empty_like(items)
    for q in range(keys.shape[0]):
        k = keys[q]
        out[start[k]] = items[q]
        start[k] += 1
    return out


#: Bits per digit of :func:`_by_ratio`'s radix sort: 11 (2048 counters, in the first-level cache) took 10 ms
#: on 330k edges, 8 bits 11 ms, 13 bits 12 ms, 16 bits 14 ms (one thread).
RADIX_BITS = 11


@nb.njit(cache=True, nogil=True)
def _by_ratio(er):
    """Edge indices sorted by ratio, ties in input order: a least-significant-digit radix sort (stable) of
    the ratios' bits, mapped so that their order as unsigned integers is the order of the numbers (the
    sign bit set for positive ones and zeros, every bit flipped for negative ones). Digits of
    :data:`RADIX_BITS` bits, the keys carried along with the indices (each pass reads both in order); a
    digit that is the same for every edge (most of the exponent) is skipped. 10 ms for 330k edges, where
    numba's stable sort of each component took about 25 ms, NumPy's stable argsort 31 ms, and 16-bit
    digits read through the permutation 16 ms."""
    m = er.shape[0]
    keys = (er + 0.0).view(np.uint64)  # a new array (+ 0.0: -0.0 becomes 0.0, equal as numbers)
    top = np.uint64(1) << np.uint64(63)
    for i in range(m):
        keys[i] = ~keys[i] if keys[i] & top else keys[i] | top
    spare = np.empty_like(keys)
    order = np.arange(m)
    out = np.empty(m, np.int64)
    n_digits = 1 << RADIX_BITS
    mask = np.uint64(n_digits - 1)
    count = np.empty(n_digits, np.int64)
    for shift in range(0, 64, RADIX_BITS):
        sh = np.uint64(shift)
        count[:] = 0
        for i in range(m):
            count[np.int64((keys[i] >> sh) & mask)] += 1
        if count.max() == m:  # one digit for every edge: this pass would change nothing
            continue
        total = 0
        for d in range(n_digits):
            c = count[d]
            count[d] = total
            total += c
        for i in range(m):
            k = keys[i]
            d = np.int64((k >> sh) & mask)
            p = count[d]
            count[d] = p + 1
            out[p] = order[i]
            spare[p] = k
        order, out = out, order
        keys, spare = spare, keys
    return order


@nb.njit(cache=True, nogil=True)
def _prepare(node_image, eu, ev, er):
    """Union-find, adjacency and the orders: ``(adj_ptr, adj, node_order, edge_order, comp_node, comp_edge)``.

    ``adj[adj_ptr[v]:adj_ptr[v + 1]]`` are the edges of node ``v``. Components in the order of their
    root; ``comp_node[c]:comp_node[c + 1]`` are the positions in ``node_order`` of component ``c``'s
    nodes, ``comp_edge`` the same in ``edge_order`` (each component's edges by ratio, ties in input order)."""
    n = node_image.shape[0]
    m = eu.shape[0]
    parent = np.arange(n)
    for e in range(m):
        ra = find_root(parent, eu[e])
        rb = find_root(parent, ev[e])
        if ra != rb:
            parent[ra] = rb
    root = np.empty(n, np.int64)
    for v in range(n):
        root[v] = find_root(parent, v)
    # adjacency (CSR): the edges of each node
    deg = np.zeros(n + 1, np.int64)
    for e in range(m):
        deg[eu[e] + 1] += 1
        deg[ev[e] + 1] += 1
    adj_ptr = np.cumsum(deg)
    fill = adj_ptr[:-1].copy()
    adj = np.empty(2 * m, np.int64)
    for e in range(m):
        adj[fill[eu[e]]] = e
        fill[eu[e]] += 1
        adj[fill[ev[e]]] = e
        fill[ev[e]] += 1
    # nodes by component in input order; edges by component, each component's by ratio (ties in input order)
    node_order = _stable_by_key(np.arange(n), root, n)
    by_ratio = _by_ratio(er)
    edge_root = np.empty(m, np.int64)
    for q in range(m):
        edge_root[q] = root[eu[by_ratio[q]]]
    edge_order = _stable_by_key(by_ratio, edge_root, n)
    n_comp = 0
    for q in range(n):
        if q == 0 or root[node_order[q]] != root[node_order[q - 1]]:
            n_comp += 1
    comp_node = np.empty(n_comp + 1, np.int64)
    comp_edge = np.empty(n_comp + 1, np.int64)
    c = 0
    p_edge = 0
    for q in range(n):
        if q == 0 or root[node_order[q]] != root[node_order[q - 1]]:
            comp_node[c] = q
            comp_edge[c] = p_edge
            r = root[node_order[q]]
            while p_edge < m and root[eu[edge_order[p_edge]]] == r:
                p_edge += 1
            c += 1
    comp_node[n_comp] = n
    comp_edge[n_comp] = m
    return adj_ptr, adj, node_order, edge_order, comp_node, comp_edge


@nb.njit(cache=True, nogil=True)
def _copy(dst, at, src, n):
    """``dst[at:at + n] = src[:n]`` as a loop: numba compiles a slice assignment with its shape-error
    formatting into each kernel that has one (about 3 s of compile time for ``_round``, timed with
    numba's compile events)."""
    for k in range(n):
        dst[at + k] = src[k]


@nb.njit(cache=True, nogil=True)
def _note(reads, n, cap, queue, tail):
    """``reads[:n]`` with ``queue[:tail]`` appended: the new length, or -1 once they do not fit in ``cap``
    (``cap = 0``: nothing is recorded)."""
    if cap == 0 or n < 0:
        return n
    if n + tail > cap:
        return -1
    _copy(reads, n, queue, tail)
    return n + tail


@nb.njit(cache=True, nogil=True)
def _round(e0, P, centers, node_image, node_xy, eu, ev, tau, cos_min_angle, max_seeds, neighbourhood, hops, adj_ptr,
           adj, rank, alive, taken, chain, dead, bound, write_bound, mark, stamp, best_err, best_node, touched, inl,
           best_inl, again, dirs, seeds, queue, depth, X, pair, reads, cap):
    """One round from the live edge ``e0`` (:func:`_components`) on the current graph: it reads ``alive``,
    ``taken`` and ``dead`` and writes only ``bound`` (if ``write_bound``), ``mark`` and its own buffers. An
    observation is alive when ``alive`` says so and ``taken`` does not hold ``chain`` (-1: no overlay).

    Returns ``(count, views, n_seeds, n_reads, stamp)``: a group of ``count`` >= 2 observations,
    ``best_inl[:count]``, with ``views`` distinct views; or ``count = 0``, no seed found support, and
    ``seeds[:n_seeds]`` are to be set aside. ``reads[:n_reads]`` are the observations the round found alive,
    with repeats (at most ``cap``; -1 when they did not fit; ``cap = 0``: not recorded): the round's result
    holds as long as none of them leaves the graph. ``stamp`` is the last mark used.
    """
    stamp += 1
    n_seeds, tail = _window(e0, adj_ptr, adj, eu, ev, rank, alive, taken, chain, dead, hops, neighbourhood, max_seeds,
                            stamp, mark, queue, depth, seeds)
    zero, two = np.int64(0), np.int64(2)  # not literals: numba compiles a callee once per literal typing
    n_reads = _note(reads, zero, cap, queue, tail)
    best_count = zero
    best_score = 0.0
    best_seed = -1
    for s in range(n_seeds):
        k = seeds[s]
        if bound[k] <= best_score:  # cannot win this round
            continue
        pair[0] = eu[k]
        pair[1] = ev[k]
        if not triangulate_point(P, node_image, node_xy, pair, two, X):
            bound[k] = 0.0  # (the same two rays every round)
            continue
        stamp += 1
        cnt, score, tail = _support(P, node_image, node_xy, X, eu[k], ev[k], adj_ptr, adj, eu, ev, alive, taken, chain,
                                    tau, stamp, mark, queue, best_err, best_node, touched, inl)
        n_reads = _note(reads, n_reads, cap, queue, tail)
        if write_bound:
            bound[k] = score
        if cnt >= 2 and score > best_score:
            best_count = cnt
            best_score = score
            best_seed = k
            _copy(best_inl, zero, inl, cnt)
    if best_seed < 0:
        return 0, 0, n_seeds, n_reads, stamp
    count = best_count
    if triangulate_point(P, node_image, node_xy, best_inl, best_count, X):
        stamp += 1
        cnt, _, tail = _support(P, node_image, node_xy, X, eu[best_seed], ev[best_seed], adj_ptr, adj, eu, ev, alive,
                                taken, chain, tau, stamp, mark, queue, best_err, best_node, touched, again)
        n_reads = _note(reads, n_reads, cap, queue, tail)
        if cnt >= 2:
            _copy(best_inl, zero, again, cnt)
            count = cnt
            triangulate_point(P, node_image, node_xy, best_inl, count, X)
    else:
        pair[0] = eu[best_seed]
        pair[1] = ev[best_seed]
        triangulate_point(P, node_image, node_xy, pair, two, X)
    views = distinct_views(node_image, centers, X, best_inl, count, cos_min_angle, dirs)
    return count, views, n_seeds, n_reads, stamp


@nb.njit(cache=True, nogil=True)
def _order(c, edge_order, comp_edge, rank):
    """The ranks of component ``c``'s edges (their positions in ``edge_order``: by ratio, ties in input order)."""
    for q in range(comp_edge[c], comp_edge[c + 1]):
        rank[edge_order[q]] = q


@nb.njit(cache=True, nogil=True)
def _live(k, eu, ev, alive, dead):
    return alive[eu[k]] and alive[ev[k]] and not dead[k]


@nb.njit(cache=True, nogil=True)
def _components(c0, c1, skip, P, centers, node_image, node_xy, eu, ev, er, n_images, tau, cos_min_angle, max_seeds,
                neighbourhood, hops, adj_ptr, adj, edge_order, comp_node, comp_edge, alive, dead, mark, group,
                slot_views, comp_groups, comp_unsupported, bound, rank):
    """Components ``c0:c1`` but those flagged in ``skip``, one round after the other (disjoint node and edge
    sets: the shared arrays are written in their rows only).

    Each round takes the component's lowest-ratio live edge (both ends alive, not found unsupported) and
    the seeds around it (:func:`_window`); the seed with the best support (:func:`_support`) wins, its
    observations are triangulated together, checked again and form a group (:func:`_round`). ``bound[k]``
    is an upper bound of seed edge ``k``'s score, kept from the round that last scored it: observations
    only leave the graph (into groups), so a support can only shrink, and a seed whose bound does not beat
    the best score of the round so far is not scored again (the first seed with the best score still wins).

    A group of component ``c`` is numbered ``comp_node[c] + local`` (a component has fewer groups than
    nodes); :func:`_number_groups` renumbers them in component order. ``slot_views`` holds each group's
    distinct views (:func:`distinct_views`), ``comp_groups[c]`` the number of groups,
    ``comp_unsupported[c]`` the seeds that found no support."""
    max_nodes = 1
    for c in range(c0, c1):
        max_nodes = max(max_nodes, comp_node[c + 1] - comp_node[c])
    best_err = np.full(n_images, np.inf)
    best_node = np.full(n_images, -1, np.int64)
    touched = np.empty(n_images, np.int64)
    inl = np.empty(n_images, np.int64)
    best_inl = np.empty(n_images, np.int64)
    again = np.empty(n_images, np.int64)
    dirs = np.empty((n_images, 3))
    seeds = np.empty(max_seeds, np.int64)
    queue = np.empty(max_nodes, np.int64)  # (a search never leaves its component)
    depth = np.empty(max_nodes, np.int64)
    X = np.empty(3)
    pair = np.empty(2, np.int64)
    reads = np.empty(0, np.int64)
    taken = np.zeros(node_image.shape[0], np.int64)  # (no overlay: chain -1 never matches)
    stamp = np.int64(0)  # (mark is read only for the nodes of the component being processed)
    # (not literals: numba compiles _round once per literal typing; these share the speculative calls' compile)
    no_chain, yes, zero = np.int64(-1), np.bool_(True), np.int64(0)
    for c in range(c0, c1):
        if skip[c]:
            continue
        p_node = comp_node[c]
        _order(c, edge_order, comp_edge, rank)
        q_edge = comp_edge[c + 1]
        n_groups = 0
        n_unsupported = 0
        first = comp_edge[c]  # edges before it have a removed end or found no support: they stay so
        while True:
            while first < q_edge and not _live(edge_order[first], eu, ev, alive, dead):
                first += 1
            if first == q_edge:
                break
            count, views, n_seeds, _, stamp = _round(
                edge_order[first], P, centers, node_image, node_xy, eu, ev, tau, cos_min_angle, max_seeds,
                neighbourhood, hops, adj_ptr, adj, rank, alive, taken, no_chain, dead, bound, yes, mark, stamp,
                best_err, best_node, touched, inl, best_inl, again, dirs, seeds, queue, depth, X, pair, reads, zero)
            if count == 0:
                for s in range(n_seeds):
                    dead[seeds[s]] = True
                n_unsupported += n_seeds
                continue
            slot = p_node + n_groups
            for q in range(count):
                v = best_inl[q]
                group[v] = slot
                alive[v] = False
            slot_views[slot] = views
            n_groups += 1
        comp_groups[c] = n_groups
        comp_unsupported[c] = n_unsupported


#: Observations a speculative chain may record as read (:func:`_big_component`); a chain that reads more is
#: run again in the apply phase (none did on the measured sets: a window holds at most ``neighbourhood``).
READ_CAP = 8192
#: Speculative chains per slot and batch (:func:`_big_component`). Since a clash costs only the chain that
#: clashed (run again), larger batches waste little; on the 24-view room's big component (270k of 330k
#: edges, 2 threads) 4, 8, 16 and 32 took the same time within this machine's noise (scratch sweep).
ROUNDS_PER_SLOT = 16
#: Most slots (buffers of a speculative round, one per thread; a node mark each) of :func:`_big_component`.
MAX_SLOTS = 16
#: Most groups of one speculative chain (:func:`_big_component`): on the 24-view room, 2905 of 14.7k rounds
#: follow a round of the same edge (a neighbouring seed's group won and left the edge live); chains of 1,
#: 2, 4 and 8 took the same time within noise, and a longer chain than this goes on in the apply phase.
MAX_CHAIN = 4


@nb.njit(cache=True, nogil=True, parallel=True)
def _big_component(c, slots, rounds_per_slot, read_cap, max_chain, P, centers, node_image, node_xy, eu, ev, er,
                   n_images, tau, cos_min_angle, max_seeds, neighbourhood, hops, adj_ptr, adj, edge_order, comp_node,
                   comp_edge, alive, dead, group, slot_views, comp_groups, comp_unsupported, bound, rank):
    """Component ``c``'s rounds on ``slots`` threads, with the result of :func:`_components` (deterministic
    reservations, Blelloch et al. 2012).

    A batch takes the component's next ``slots * rounds_per_slot`` live edges, lowest ratio first. Each
    thread runs their rounds on the graph as it is, and, for an edge that a round's group leaves live, the
    edge's next rounds (at most ``max_chain`` in all), on the graph less the groups this chain took (a
    thread's own overlay, ``taken``): what the serial loop would run next if nothing else changed. Each
    chain records the observations it found alive (at most ``read_cap``). Then, in ratio order, a chain's
    groups are applied if none of the observations it read was taken into a group (or was the end of a
    seed set aside) by a chain applied before it in this batch; otherwise its edge's rounds run again
    here, on the graph as it is now, as do the rounds of an edge a full chain leaves live. The result is
    the serial loop's. Rounds far apart in the graph, the usual case in a big component, do not touch each
    other, so nearly every chain is applied as it is.

    ``bound`` (each seed's upper bound of score) is written only by rounds on the graph as it is at the
    start of the batch or later: a chain's later rounds run on a graph that may never exist, where a score
    could be lower than on the real one.
    """
    p_node = comp_node[c]
    n_nodes = comp_node[c + 1] - p_node
    q_edge = comp_edge[c + 1]
    _order(c, edge_order, comp_edge, rank)
    batch = slots * rounds_per_slot
    n = node_image.shape[0]
    mark = np.zeros((slots, n), np.int64)
    taken = np.zeros((slots, n), np.int64)
    stamps = np.zeros(slots, np.int64)
    chains = np.zeros(slots, np.int64)
    best_err = np.full((slots, n_images), np.inf)
    best_node = np.full((slots, n_images), -1, np.int64)
    touched = np.empty((slots, n_images), np.int64)
    inl = np.empty((slots, n_images), np.int64)
    again = np.empty((slots, n_images), np.int64)
    dirs = np.empty((slots, n_images, 3))
    queue = np.empty((slots, n_nodes), np.int64)
    depth = np.empty((slots, n_nodes), np.int64)
    X = np.empty((slots, 3))
    pair = np.empty((slots, 2), np.int64)
    cand = np.empty(batch, np.int64)
    n_chain = np.empty(batch, np.int64)  # groups in the chain
    set_aside = np.empty(batch, np.bool_)  # the chain ended in a round whose seeds found no support
    n_seeds = np.empty(batch, np.int64)
    n_reads = np.empty(batch, np.int64)
    counts = np.empty((batch, max_chain), np.int64)
    views = np.empty((batch, max_chain), np.int64)
    nodes = np.empty((batch, max_chain, n_images), np.int64)
    seeds = np.empty((batch, max_seeds), np.int64)
    reads = np.empty((batch, read_cap), np.int64)
    written = np.zeros(n, np.int64)  # the batch that took an observation (or set aside an edge at it)
    no_chain, yes, zero = np.int64(-1), np.bool_(True), np.int64(0)  # (as in _components)
    first = comp_edge[c]
    n_groups = 0
    n_unsupported = 0
    bid = 0
    while True:
        nc = 0
        while first < q_edge and nc < batch:  # (every edge before first is no longer live, and stays so)
            if _live(edge_order[first], eu, ev, alive, dead):
                cand[nc] = edge_order[first]
                nc += 1
            first += 1
        if nc == 0:
            break
        for sl in prange(slots):
            for b in range(sl, nc, slots):
                e0 = cand[b]
                chains[sl] += 1
                ch = chains[sl]
                nr = 0
                ng = 0
                set_aside[b] = False
                while True:
                    count, n_view, n_seed, got, stamps[sl] = _round(
                        e0, P, centers, node_image, node_xy, eu, ev, tau, cos_min_angle, max_seeds, neighbourhood,
                        hops, adj_ptr, adj, rank, alive, taken[sl], ch, dead, bound, ng == 0, mark[sl], stamps[sl],
                        best_err[sl], best_node[sl], touched[sl], inl[sl], nodes[b, ng], again[sl], dirs[sl],
                        seeds[b], queue[sl], depth[sl], X[sl], pair[sl], reads[b, nr:], read_cap - nr)
                    if got < 0 or nr == read_cap:
                        nr = -1
                        break
                    nr += got
                    if count == 0:
                        set_aside[b] = True
                        n_seeds[b] = n_seed
                        break
                    counts[b, ng] = count
                    views[b, ng] = n_view
                    for q2 in range(count):
                        taken[sl, nodes[b, ng, q2]] = ch
                    ng += 1
                    if ng == max_chain or not _live(e0, eu, ev, alive, dead) or taken[sl, eu[e0]] == ch \
                            or taken[sl, ev[e0]] == ch:
                        break
                n_chain[b] = ng
                n_reads[b] = nr
        bid += 1
        for b in range(nc):
            e0 = cand[b]
            if not _live(e0, eu, ev, alive, dead):  # taken by a chain before it: the serial loop skips it
                continue
            clash = n_reads[b] < 0
            for r in range(n_reads[b]):
                if written[reads[b, r]] == bid:
                    clash = True
                    break
            if not clash:
                for g in range(n_chain[b]):
                    slot = p_node + n_groups
                    for q2 in range(counts[b, g]):
                        v = nodes[b, g, q2]
                        group[v] = slot
                        alive[v] = False
                        written[v] = bid
                    slot_views[slot] = views[b, g]
                    n_groups += 1
                if set_aside[b]:
                    for s in range(n_seeds[b]):
                        k = seeds[b, s]
                        dead[k] = True
                        written[eu[k]] = bid
                        written[ev[k]] = bid
                    n_unsupported += n_seeds[b]
            # a chain that clashed, or one cut short with e0 still live: e0's rounds on the graph as it is now
            # (the chains after it in this batch are then checked against what these take too)
            while _live(e0, eu, ev, alive, dead):
                count, n_view, n_seed, _, stamps[0] = _round(
                    e0, P, centers, node_image, node_xy, eu, ev, tau, cos_min_angle, max_seeds, neighbourhood, hops,
                    adj_ptr, adj, rank, alive, taken[0], no_chain, dead, bound, yes, mark[0], stamps[0],
                    best_err[0], best_node[0], touched[0], inl[0], nodes[b, 0], again[0], dirs[0], seeds[b], queue[0],
                    depth[0], X[0], pair[0], reads[b], zero)
                if count == 0:
                    for s in range(n_seed):
                        k = seeds[b, s]
                        dead[k] = True
                        written[eu[k]] = bid
                        written[ev[k]] = bid
                    n_unsupported += n_seed
                else:
                    slot = p_node + n_groups
                    for q2 in range(count):
                        v = nodes[b, 0, q2]
                        group[v] = slot
                        alive[v] = False
                        written[v] = bid
                    slot_views[slot] = n_view
                    n_groups += 1
    comp_groups[c] = n_groups
    comp_unsupported[c] = n_unsupported


@nb.njit(cache=True, nogil=True)
def _setup(n, m, n_comp):
    return (np.ones(n, np.bool_), np.zeros(m, np.bool_), np.zeros(n, np.int64), np.full(n, -1, np.int64),
            np.zeros(n, np.int64), np.zeros(n_comp, np.int64), np.zeros(n_comp, np.int64), np.full(m, np.inf),
            np.empty(m, np.int64), np.zeros(n_comp, np.bool_))


@nb.njit(cache=True, nogil=True)
def _number_groups(group, slot_views, comp_node, comp_groups, comp_unsupported):
    """Groups numbered 0, 1, ... in component order (as one pass over the components would):
    ``(group, group_views, stats)``."""
    n_comp = comp_groups.shape[0]
    new_id = np.full(group.shape[0] + 1, -1, np.int64)
    total = 0
    for c in range(n_comp):
        total += comp_groups[c]
    group_views = np.empty(total, np.int64)
    g = 0
    for c in range(n_comp):
        for local in range(comp_groups[c]):
            slot = comp_node[c] + local
            new_id[slot] = g
            group_views[g] = slot_views[slot]
            g += 1
    for v in range(group.shape[0]):
        if group[v] >= 0:
            group[v] = new_id[group[v]]
    stats = np.array([n_comp, total, comp_unsupported.sum()], np.int64)
    return group, group_views, stats


@nb.njit(cache=True, nogil=True)
def consensus(P, centers, node_image, node_xy, eu, ev, er, n_images, tau, cos_min_angle, max_seeds, neighbourhood,
              hops):
    """Consensus groups of the observations: ``(group (n,) int64, group_views (G,) int64, stats (3,) int64)``.

    ``P (n_images, 3, 4)`` and ``centers (n_images, 3)`` in the same world frame; ``group[v]`` is -1 for
    an observation in no group; ``group_views`` counts each group's views whose rays at its point are at
    least the minimum angle apart (``cos_min_angle`` its cosine). ``stats``: components, groups, seeds
    that found no support. See :func:`.consensus.verify_tracks` for the algorithm.
    """
    adj_ptr, adj, node_order, edge_order, comp_node, comp_edge = _prepare(node_image, eu, ev, er)
    n_comp = comp_node.shape[0] - 1
    alive, dead, mark, group, slot_views, comp_groups, comp_unsupported, bound, rank, skip = _setup(
        node_image.shape[0], eu.shape[0], n_comp)
    _components(np.int64(0), n_comp, skip, P, centers, node_image, node_xy, eu, ev, er, n_images, tau, cos_min_angle,
                max_seeds, neighbourhood, hops, adj_ptr, adj, edge_order, comp_node, comp_edge, alive, dead, mark,
                group, slot_views, comp_groups, comp_unsupported, bound, rank)
    return _number_groups(group, slot_views, comp_node, comp_groups, comp_unsupported)


#: A component with at least this many edges, and more than a thread's share of them, runs its rounds on
#: every thread (:func:`_big_component`) rather than on one.
BIG_COMPONENT = 4096


def consensus_parallel(P, centers, node_image, node_xy, eu, ev, er, n_images, tau, cos_min_angle, max_seeds,
                       neighbourhood, hops, blocks):
    """:func:`consensus` on numba's threads (of the calling Python thread), with the same result: the big
    components one after the other, each on every thread (:func:`_big_component`), then the others in
    ``blocks`` blocks of components with about equal numbers of edges (:func:`_blocks`; components share no
    node or edge, and the groups are numbered in component order afterwards).

    Plain Python around compiled calls: a compiled function that calls parallel ones cannot be cached.
    """
    adj_ptr, adj, node_order, edge_order, comp_node, comp_edge = _prepare(node_image, eu, ev, er)
    n_comp = comp_node.shape[0] - 1
    alive, dead, mark, group, slot_views, comp_groups, comp_unsupported, bound, rank, skip = _setup(
        node_image.shape[0], eu.shape[0], n_comp)
    threads = nb.get_num_threads()
    slots = min(threads, MAX_SLOTS)
    sizes = np.diff(comp_edge)
    skip[:] = (slots > 1) & (sizes >= BIG_COMPONENT) & (sizes * threads > eu.shape[0])
    for c in np.flatnonzero(skip):
        _big_component(c, slots, ROUNDS_PER_SLOT, READ_CAP, MAX_CHAIN, P, centers, node_image, node_xy, eu, ev, er,
                       n_images, tau, cos_min_angle, max_seeds, neighbourhood, hops, adj_ptr, adj, edge_order,
                       comp_node, comp_edge, alive, dead, group, slot_views, comp_groups, comp_unsupported, bound, rank)
    left = np.concatenate(([0], np.cumsum(np.where(skip, 0, sizes))))  # edges of the other components, cumulated
    cuts = np.searchsorted(left, np.arange(blocks + 1) * left[-1] // blocks)  # blocks of about equal edges
    cuts[0], cuts[blocks] = 0, n_comp
    _blocks(cuts, skip, P, centers, node_image, node_xy, eu, ev, er, n_images, tau, cos_min_angle, max_seeds,
            neighbourhood, hops, adj_ptr, adj, edge_order, comp_node, comp_edge, alive, dead, mark, group, slot_views,
            comp_groups, comp_unsupported, bound, rank)
    return _number_groups(group, slot_views, comp_node, comp_groups, comp_unsupported)


@nb.njit(cache=True, nogil=True, parallel=True)
def _blocks(cuts, skip, P, centers, node_image, node_xy, eu, ev, er, n_images, tau, cos_min_angle, max_seeds,
            neighbourhood, hops, adj_ptr, adj, edge_order, comp_node, comp_edge, alive, dead, mark, group, slot_views,
            comp_groups, comp_unsupported, bound, rank):
    """:func:`_components` on the blocks ``cuts[b]:cuts[b + 1]`` of components, on threads."""
    for b in prange(cuts.shape[0] - 1):
        c0, c1 = cuts[b], cuts[b + 1]
        if c1 > c0:
            _components(c0, c1, skip, P, centers, node_image, node_xy, eu, ev, er, n_images, tau, cos_min_angle,
                        max_seeds, neighbourhood, hops, adj_ptr, adj, edge_order, comp_node, comp_edge, alive, dead,
                        mark, group, slot_views, comp_groups, comp_unsupported, bound, rank)
