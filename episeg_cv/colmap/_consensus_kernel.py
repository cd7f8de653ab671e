"""The compiled loop of the track consensus (:mod:`.consensus`): union-find, then RANSAC-style groups.

Components share no observation and no edge, so they are processed independently: one after the
other (:func:`consensus`) or in blocks on threads (:func:`consensus_parallel`), with the same result.

Every array is checked and laid out by :func:`.consensus.verify_tracks`; these
functions trust them. Nodes are (image, keypoint) observations, ``0 .. n-1``;
edges are candidate matches between two nodes of different images with their ratio values.
"""

from __future__ import annotations

import numba as nb
import numpy as np
from numba import prange


@nb.njit(cache=True, nogil=True)
def _find(parent, x):
    while parent[x] != x:
        parent[x] = parent[parent[x]]  # path halving
        x = parent[x]
    return x


@nb.njit(cache=True, nogil=True)
def _triangulate(P, node_image, node_xy, nodes, count, out):
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
def _support(P, node_image, node_xy, X, a, b, adj_ptr, adj, eu, ev, alive, tau, stamp, mark, queue, best_err,
             best_node, touched, out):
    """The support of the point ``X`` grown from the observations ``a`` and ``b`` through the match graph:
    ``(count, score)``.

    Breadth first from ``a`` and ``b`` along the edges, through alive observations only, and only through
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
        h0 = P[k, 0, 0] * X[0] + P[k, 0, 1] * X[1] + P[k, 0, 2] * X[2] + P[k, 0, 3]
        h1 = P[k, 1, 0] * X[0] + P[k, 1, 1] * X[1] + P[k, 1, 2] * X[2] + P[k, 1, 3]
        h2 = P[k, 2, 0] * X[0] + P[k, 2, 1] * X[1] + P[k, 2, 2] * X[2] + P[k, 2, 3]
        if not (h2 > 0.0):
            continue
        dx = h0 / h2 - node_xy[v, 0]
        dy = h1 / h2 - node_xy[v, 1]
        err = np.sqrt(dx * dx + dy * dy)
        if not (err <= tau):
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
            if mark[w] != stamp and alive[w]:
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
    return n_touched, score


@nb.njit(cache=True, nogil=True)
def _window(e0, adj_ptr, adj, eu, ev, rank, alive, dead, hops, limit, max_seeds, stamp, mark, queue, depth, estamp,
            seeds):
    """The seeds of a round: ``e0`` first, then the live edges of lowest ``rank`` (ratio, then input order)
    among the alive observations within ``hops`` edges of its ends (breadth first, at most ``limit``
    observations); at most ``max_seeds``, in ``seeds``. Returns their number."""
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
            if mark[w] != stamp and alive[w]:
                mark[w] = stamp
                queue[tail] = w
                depth[tail] = d + 1
                tail += 1
                if tail >= limit:
                    break
    seeds[0] = e0
    n = 1
    estamp[e0] = stamp
    for q in range(tail):
        v = queue[q]
        for p in range(adj_ptr[v], adj_ptr[v + 1]):
            k = adj[p]
            if estamp[k] == stamp or dead[k] or mark[eu[k] + ev[k] - v] != stamp:
                continue
            estamp[k] = stamp
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
    return n


@nb.njit(cache=True, nogil=True)
def _distinct_views(node_image, centers, X, nodes, count, cos_min_angle, dirs):
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


@nb.njit(cache=True, nogil=True)
def _sort_by_ratio(edge_order, p, q, er):
    """Sort ``edge_order[p:q]`` by ``er``, stably (ties keep their order): an insertion sort for the
    few edges of most components, numba's mergesort for the others."""
    if q - p <= 32:
        for i in range(p + 1, q):
            k = edge_order[i]
            r = er[k]
            j = i - 1
            while j >= p and er[edge_order[j]] > r:
                edge_order[j + 1] = edge_order[j]
                j -= 1
            edge_order[j + 1] = k
        return
    seg = edge_order[p:q].copy()
    o = np.argsort(er[seg], kind="mergesort")
    for i in range(q - p):
        edge_order[p + i] = seg[o[i]]


@nb.njit(cache=True, nogil=True)
def _prepare(node_image, eu, ev, er):
    """Union-find, adjacency and the orders: ``(adj_ptr, adj, node_order, edge_order, comp_node, comp_edge)``.

    ``adj[adj_ptr[v]:adj_ptr[v + 1]]`` are the edges of node ``v``. Components in the order of their
    root; ``comp_node[c]:comp_node[c + 1]`` are the positions in ``node_order`` of component ``c``'s
    nodes, ``comp_edge`` the same in ``edge_order`` (in input order: :func:`_sort_by_ratio` sorts them)."""
    n = node_image.shape[0]
    m = eu.shape[0]
    parent = np.arange(n)
    for e in range(m):
        ra = _find(parent, eu[e])
        rb = _find(parent, ev[e])
        if ra != rb:
            parent[ra] = rb
    root = np.empty(n, np.int64)
    for v in range(n):
        root[v] = _find(parent, v)
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
    # nodes and edges by component, in input order (each component's edges are then sorted by ratio,
    # by _sort_by_ratio, where the component is processed)
    node_order = _stable_by_key(np.arange(n), root, n)
    edge_root = np.empty(m, np.int64)
    for e in range(m):
        edge_root[e] = root[eu[e]]
    edge_order = _stable_by_key(np.arange(m), edge_root, n)
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
def _components(c0, c1, P, centers, node_image, node_xy, eu, ev, er, n_images, tau, cos_min_angle, max_seeds,
                neighbourhood, hops, adj_ptr, adj, edge_order, comp_node, comp_edge, alive, dead, mark, estamp, group,
                slot_views, comp_groups, comp_unsupported, bound, rank):
    """Components ``c0:c1`` (disjoint node and edge sets: the shared arrays are written in their rows only).

    Each round takes the component's lowest-ratio live edge (both ends alive, not found unsupported) and
    the seeds around it (:func:`_window`); the seed with the best support (:func:`_support`) wins, its
    observations are triangulated together, checked again and form a group. ``bound[k]`` is an upper
    bound of seed edge ``k``'s score, kept from the round that last scored it: observations only leave the
    graph (into groups), so a support can only shrink, and a seed whose bound does not beat the best score
    of the round so far is not scored again (the first seed with the best score still wins).

    A group of component ``c`` is numbered ``comp_node[c] + local`` (a component has fewer groups than
    nodes); :func:`_number_groups` renumbers them in component order. ``slot_views`` holds each group's
    distinct views (:func:`_distinct_views`), ``comp_groups[c]`` the number of groups,
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
    stamp = 0  # (mark and estamp are read only for nodes and edges of the component being processed)
    for c in range(c0, c1):
        p_node = comp_node[c]
        p_edge, q_edge = comp_edge[c], comp_edge[c + 1]
        _sort_by_ratio(edge_order, p_edge, q_edge, er)  # lowest ratio first; ties in input order
        for q in range(p_edge, q_edge):
            rank[edge_order[q]] = q
        n_groups = 0
        n_unsupported = 0
        first = p_edge  # edges before it have a removed end or found no support: they stay so
        while True:
            while first < q_edge:
                k = edge_order[first]
                if alive[eu[k]] and alive[ev[k]] and not dead[k]:
                    break
                first += 1
            if first == q_edge:
                break
            stamp += 1
            n_seeds = _window(edge_order[first], adj_ptr, adj, eu, ev, rank, alive, dead, hops, neighbourhood,
                              max_seeds, stamp, mark, queue, depth, estamp, seeds)
            best_count = 0
            best_score = 0.0
            best_seed = -1
            for s in range(n_seeds):
                k = seeds[s]
                if bound[k] <= best_score:  # cannot win this round
                    continue
                pair[0] = eu[k]
                pair[1] = ev[k]
                if not _triangulate(P, node_image, node_xy, pair, 2, X):
                    bound[k] = 0.0  # (the same two rays every round)
                    continue
                stamp += 1
                cnt, score = _support(P, node_image, node_xy, X, eu[k], ev[k], adj_ptr, adj, eu, ev, alive, tau,
                                      stamp, mark, queue, best_err, best_node, touched, inl)
                bound[k] = score
                if cnt >= 2 and score > best_score:
                    best_count = cnt
                    best_score = score
                    best_seed = k
                    best_inl[:cnt] = inl[:cnt]
            if best_seed < 0:
                for s in range(n_seeds):
                    dead[seeds[s]] = True
                n_unsupported += n_seeds
                continue
            count = best_count
            if _triangulate(P, node_image, node_xy, best_inl, best_count, X):
                stamp += 1
                cnt, _ = _support(P, node_image, node_xy, X, eu[best_seed], ev[best_seed], adj_ptr, adj, eu, ev,
                                  alive, tau, stamp, mark, queue, best_err, best_node, touched, again)
                if cnt >= 2:
                    best_inl[:cnt] = again[:cnt]
                    count = cnt
                    _triangulate(P, node_image, node_xy, best_inl, count, X)
            else:
                pair[0] = eu[best_seed]
                pair[1] = ev[best_seed]
                _triangulate(P, node_image, node_xy, pair, 2, X)
            slot = p_node + n_groups
            for q in range(count):
                v = best_inl[q]
                group[v] = slot
                alive[v] = False
            slot_views[slot] = _distinct_views(node_image, centers, X, best_inl, count, cos_min_angle, dirs)
            n_groups += 1
        comp_groups[c] = n_groups
        comp_unsupported[c] = n_unsupported


@nb.njit(cache=True, nogil=True)
def _setup(n, m, n_comp):
    return (np.ones(n, np.bool_), np.zeros(m, np.bool_), np.zeros(n, np.int64), np.zeros(m, np.int64),
            np.full(n, -1, np.int64), np.zeros(n, np.int64), np.zeros(n_comp, np.int64), np.zeros(n_comp, np.int64),
            np.full(m, np.inf), np.empty(m, np.int64))


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
    alive, dead, mark, estamp, group, slot_views, comp_groups, comp_unsupported, bound, rank = _setup(
        node_image.shape[0], eu.shape[0], n_comp)
    _components(0, n_comp, P, centers, node_image, node_xy, eu, ev, er, n_images, tau, cos_min_angle, max_seeds,
                neighbourhood, hops, adj_ptr, adj, edge_order, comp_node, comp_edge, alive, dead, mark, estamp, group,
                slot_views, comp_groups, comp_unsupported, bound, rank)
    return _number_groups(group, slot_views, comp_node, comp_groups, comp_unsupported)


@nb.njit(cache=True, nogil=True, parallel=True)
def consensus_parallel(P, centers, node_image, node_xy, eu, ev, er, n_images, tau, cos_min_angle, max_seeds,
                       neighbourhood, hops, blocks):
    """:func:`consensus` on threads: blocks of components with about equal numbers of edges (components
    share no node or edge, and the groups are numbered in component order afterwards: the same result)."""
    adj_ptr, adj, node_order, edge_order, comp_node, comp_edge = _prepare(node_image, eu, ev, er)
    n_comp = comp_node.shape[0] - 1
    alive, dead, mark, estamp, group, slot_views, comp_groups, comp_unsupported, bound, rank = _setup(
        node_image.shape[0], eu.shape[0], n_comp)
    m = eu.shape[0]
    nblk = blocks
    cuts = np.searchsorted(comp_edge, np.arange(nblk + 1) * m // nblk)  # component index at each edge quantile
    cuts[0] = 0
    cuts[nblk] = n_comp
    for b in prange(nblk):
        c0, c1 = cuts[b], cuts[b + 1]
        if c1 > c0:
            _components(c0, c1, P, centers, node_image, node_xy, eu, ev, er, n_images, tau, cos_min_angle,
                        max_seeds, neighbourhood, hops, adj_ptr, adj, edge_order, comp_node, comp_edge, alive, dead,
                        mark, estamp, group, slot_views, comp_groups, comp_unsupported, bound, rank)
    return _number_groups(group, slot_views, comp_node, comp_groups, comp_unsupported)
