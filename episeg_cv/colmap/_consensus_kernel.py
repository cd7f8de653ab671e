"""The compiled loop of the track consensus (:mod:`.consensus`): union-find, then RANSAC-style groups.

Components share no observation and no edge, so they are processed independently: one after the
other (:func:`consensus`) or in blocks on threads (:func:`consensus_parallel`), with the same result.

Every array is checked and laid out by :func:`.consensus.verify_tracks`; these
functions trust them. Nodes are (image, keypoint) observations, ``0 .. n-1``;
edges are candidate matches between two nodes with their ratio values.
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
def _inliers(P, node_image, node_xy, X, cand, n_cand, tau, best_err, best_node, touched, out):
    """The observations among ``cand`` that reproject within ``tau`` px of ``X`` (in front of the
    camera), one per image: the closest. Written to ``out``; returns their number."""
    n_touched = 0
    for q in range(n_cand):
        v = cand[q]
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
    for q in range(n_touched):
        k = touched[q]
        out[q] = best_node[k]
        best_node[k] = -1
        best_err[k] = np.inf
    return n_touched


@nb.njit(cache=True, nogil=True)
def _ball(a, b, adj_ptr, adj, alive, hops, limit, stamp, mark, queue, depth):
    """Alive nodes within ``hops`` edges of ``a`` or ``b`` (breadth first, at most ``limit``), in ``queue``."""
    head = 0
    tail = 0
    for s in (a, b):
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
            w = adj[p]
            if mark[w] != stamp and alive[w]:
                mark[w] = stamp
                queue[tail] = w
                depth[tail] = d + 1
                tail += 1
                if tail >= limit:
                    break
    return tail


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

    Components in the order of their root; ``comp_node[c]:comp_node[c + 1]`` are the positions in
    ``node_order`` of component ``c``'s nodes, ``comp_edge`` the same in ``edge_order`` (in input
    order: :func:`_sort_by_ratio` sorts them)."""
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
    # adjacency (CSR), for the neighbourhoods of big components
    deg = np.zeros(n + 1, np.int64)
    for e in range(m):
        deg[eu[e] + 1] += 1
        deg[ev[e] + 1] += 1
    adj_ptr = np.cumsum(deg)
    fill = adj_ptr[:-1].copy()
    adj = np.empty(2 * m, np.int64)
    for e in range(m):
        adj[fill[eu[e]]] = ev[e]
        fill[eu[e]] += 1
        adj[fill[ev[e]]] = eu[e]
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
def _components(c0, c1, P, node_image, node_xy, eu, ev, er, n_images, tau, max_seeds, max_component, hops, adj_ptr, adj,
                node_order, edge_order, comp_node, comp_edge, alive, dead, mark, group, slot_views, comp_groups,
                comp_stats, bound):
    """Components ``c0:c1`` (disjoint node and edge sets: the shared arrays are written in their rows only).

    ``bound[k]`` is an upper bound of seed edge ``k``'s support, kept from the round that last counted it:
    observations only leave the candidates (into groups), so a support can only shrink, and a seed whose
    bound does not beat the best support of the round so far is not counted again. The first seed with
    the largest support still wins, so the groups are those of counting every seed every round (a big
    component's neighbourhood cut at ``max_component`` could gain observations: its count is no bound).

    A group of component ``c`` is numbered ``comp_node[c] + local`` (a component has fewer groups than
    nodes); :func:`_number_groups` renumbers them in component order. ``comp_groups[c]`` is the
    number of groups, ``comp_stats[c]`` = (big, unsupported seeds)."""
    best_err = np.full(n_images, np.inf)
    best_node = np.full(n_images, -1, np.int64)
    touched = np.empty(n_images, np.int64)
    inl = np.empty(n_images, np.int64)
    best_inl = np.empty(n_images, np.int64)
    again = np.empty(n_images, np.int64)
    seeds = np.empty(max_seeds, np.int64)
    cand = np.empty(max_component + 2, np.int64)
    depth = np.empty(max_component + 2, np.int64)
    X = np.empty(3)
    pair = np.empty(2, np.int64)
    stamp = 0  # (mark is read only for nodes of the component being processed)
    for c in range(c0, c1):
        p_node, q_node = comp_node[c], comp_node[c + 1]
        p_edge, q_edge = comp_edge[c], comp_edge[c + 1]
        _sort_by_ratio(edge_order, p_edge, q_edge, er)  # lowest ratio first; ties in input order
        nc = q_node - p_node
        big = nc > max_component
        n_groups = 0
        n_unsupported = 0
        first = p_edge  # edges before it have a removed or dead end
        while True:
            n_seeds = 0
            e = first
            while e < q_edge and n_seeds < max_seeds:
                k = edge_order[e]
                if alive[eu[k]] and alive[ev[k]] and not dead[k]:
                    seeds[n_seeds] = k
                    n_seeds += 1
                e += 1
            if n_seeds == 0:
                break
            # an edge with a removed or dead end stays so: the scanned ones are dropped, the seeds moved up to
            # the unscanned rest (same order), so that no round scans them again
            first = e - n_seeds
            for s in range(n_seeds):
                edge_order[first + s] = seeds[s]
            n_cand = 0
            if not big:  # every alive node of the component
                for q in range(p_node, q_node):
                    v = node_order[q]
                    if alive[v]:
                        cand[n_cand] = v
                        n_cand += 1
            best_count = 0
            best_seed = -1
            for s in range(n_seeds):
                k = seeds[s]
                if bound[k] <= best_count:  # cannot win this round
                    continue
                if big:
                    stamp += 1
                    n_cand = _ball(eu[k], ev[k], adj_ptr, adj, alive, hops, max_component, stamp, mark, cand, depth)
                pair[0] = eu[k]
                pair[1] = ev[k]
                if not _triangulate(P, node_image, node_xy, pair, 2, X):
                    bound[k] = 0  # (the same two rays every round)
                    continue
                cnt = _inliers(P, node_image, node_xy, X, cand, n_cand, tau, best_err, best_node, touched, inl)
                bound[k] = cnt if not (big and n_cand >= max_component) else n_images
                if cnt > best_count:
                    best_count = cnt
                    best_seed = k
                    best_inl[:cnt] = inl[:cnt]
            if best_count < 2:
                for s in range(n_seeds):
                    dead[seeds[s]] = True
                n_unsupported += n_seeds
                continue
            count = best_count
            if _triangulate(P, node_image, node_xy, best_inl, best_count, X):
                if big:
                    stamp += 1
                    n_cand = _ball(eu[best_seed], ev[best_seed], adj_ptr, adj, alive, hops, max_component, stamp,
                                   mark, cand, depth)
                cnt = _inliers(P, node_image, node_xy, X, cand, n_cand, tau, best_err, best_node, touched, again)
                if cnt >= 2:
                    best_inl[:cnt] = again[:cnt]
                    count = cnt
            slot = p_node + n_groups
            for q in range(count):
                v = best_inl[q]
                group[v] = slot
                alive[v] = False
            slot_views[slot] = count  # one observation per image
            n_groups += 1
        comp_groups[c] = n_groups
        comp_stats[c, 0] = 1 if big else 0
        comp_stats[c, 1] = n_unsupported


@nb.njit(cache=True, nogil=True)
def _setup(n, m, n_comp, n_images):
    return (np.ones(n, np.bool_), np.zeros(m, np.bool_), np.zeros(n, np.int64), np.full(n, -1, np.int64),
            np.zeros(n, np.int64), np.zeros(n_comp, np.int64), np.zeros((n_comp, 2), np.int64),
            np.full(m, n_images, np.int64))  # a group holds at most one observation per image


@nb.njit(cache=True, nogil=True)
def _number_groups(group, slot_views, comp_node, comp_groups, comp_stats):
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
    stats = np.array([n_comp, total, comp_stats[:, 0].sum(), comp_stats[:, 1].sum()], np.int64)
    return group, group_views, stats


@nb.njit(cache=True, nogil=True)
def consensus(P, node_image, node_xy, eu, ev, er, n_images, tau, max_seeds, max_component, hops):
    """Consensus groups of the observations: ``(group (n,) int64, group_views (G,) int64, stats (4,) int64)``.

    ``group[v]`` is -1 for an observation in no group. ``stats``: components,
    groups, components above ``max_component`` nodes, seeds that found no
    support. See :func:`.consensus.verify_tracks` for the algorithm.
    """
    adj_ptr, adj, node_order, edge_order, comp_node, comp_edge = _prepare(node_image, eu, ev, er)
    n_comp = comp_node.shape[0] - 1
    alive, dead, mark, group, slot_views, comp_groups, comp_stats, bound = _setup(node_image.shape[0], eu.shape[0],
                                                                                 n_comp, n_images)
    _components(0, n_comp, P, node_image, node_xy, eu, ev, er, n_images, tau, max_seeds, max_component, hops, adj_ptr,
                adj, node_order, edge_order, comp_node, comp_edge, alive, dead, mark, group, slot_views, comp_groups,
                comp_stats, bound)
    return _number_groups(group, slot_views, comp_node, comp_groups, comp_stats)


@nb.njit(cache=True, nogil=True, parallel=True)
def consensus_parallel(P, node_image, node_xy, eu, ev, er, n_images, tau, max_seeds, max_component, hops, blocks):
    """:func:`consensus` on threads: blocks of components with about equal numbers of edges (components
    share no node or edge, and the groups are numbered in component order afterwards: the same result)."""
    adj_ptr, adj, node_order, edge_order, comp_node, comp_edge = _prepare(node_image, eu, ev, er)
    n_comp = comp_node.shape[0] - 1
    alive, dead, mark, group, slot_views, comp_groups, comp_stats, bound = _setup(node_image.shape[0], eu.shape[0],
                                                                                 n_comp, n_images)
    m = eu.shape[0]
    nblk = blocks
    cuts = np.searchsorted(comp_edge, np.arange(nblk + 1) * m // nblk)  # component index at each edge quantile
    cuts[0] = 0
    cuts[nblk] = n_comp
    for b in prange(nblk):
        c0, c1 = cuts[b], cuts[b + 1]
        if c1 > c0:
            _components(c0, c1, P, node_image, node_xy, eu, ev, er, n_images, tau, max_seeds, max_component, hops,
                        adj_ptr, adj, node_order, edge_order, comp_node, comp_edge, alive, dead, mark, group,
                        slot_views, comp_groups, comp_stats, bound)
    return _number_groups(group, slot_views, comp_node, comp_groups, comp_stats)
