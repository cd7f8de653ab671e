"""The track consensus (issue 14): candidate matches of a collection verified with the known poses.

Needs no pycolmap: views, candidates and keypoints are built here.
"""

import numpy as np
import pytest
from hypothesis import given, settings, strategies as st

from episeg_cv import scenes
from episeg_cv.colmap import TrackConsensus, View, verify_tracks
from episeg_cv.colmap.consensus import projection_matrices

K = np.array([[500.0, 0, 319.5], [0, 500.0, 239.5], [0, 0, 1]])
SIZE = (640, 480)


def _ring(n, radius=4.0):
    """n cameras on a circle around the origin, all looking at it."""
    views = []
    for k in range(n):
        a = 2 * np.pi * k / n * 0.25  # a quarter circle: every camera sees the centre
        R, t = scenes.look_at([radius * np.sin(a), 0.3 * k, -radius * np.cos(a)], [0, 0, 0])
        views.append(View(f"v{k}.png", k + 1, 1, K, R, t, SIZE))
    return views


def _project(views, X):
    """(n_views, n_points, 2) pixels."""
    return np.stack([(X @ v.R.T + v.t) @ K.T for v in views])[..., :2] / \
        np.stack([(X @ v.R.T + v.t)[:, 2:] for v in views])


def _scene(n_views=4, n_points=30, seed=0):
    rng = np.random.default_rng(seed)
    views = _ring(n_views)
    X = rng.uniform(-0.5, 0.5, (n_points, 3))
    kp = _project(views, X)  # keypoint p of view k is the projection of point p
    return views, X, kp


def _all_pairs(n_views, n_points, ratio=0.5, drop=()):
    """Every true match of every pair, ratio ``ratio``."""
    out = []
    for i in range(n_views):
        for j in range(i + 1, n_views):
            idx = np.array([p for p in range(n_points) if (i, j, p) not in drop], dtype=np.int64)
            out.append((i, j, np.column_stack([idx, idx]), np.full(len(idx), ratio)))
    return out


# --------------------------------------------------------------------------------------
# Hand-made cases
# --------------------------------------------------------------------------------------
def test_true_tracks_are_kept_at_any_ratio_with_three_views():
    views, _, kp = _scene()
    cands = _all_pairs(4, 30, ratio=0.85)  # loose, but every track spans 4 views
    keep, stats = verify_tracks(views, cands, lambda k: kp[k], strict=0.68, tau=2.0)
    assert all(k.all() for k in keep)
    assert stats["groups"] == 30 and stats["components"] == 30 and stats["kept"] == stats["edges"] == 6 * 30


def test_loose_edges_of_two_views_need_a_third():
    views, _, kp = _scene(n_views=2)
    strict = (0, 1, np.array([[0, 0], [1, 1]]), np.array([0.5, 0.6]))
    keep, _ = verify_tracks(views, [strict], lambda k: kp[k], strict=0.68, tau=2.0)
    assert keep[0].tolist() == [True, True]
    loose = (0, 1, np.array([[0, 0], [1, 1]]), np.array([0.7, 0.89]))
    keep, _ = verify_tracks(views, [loose], lambda k: kp[k], strict=0.68, tau=2.0)
    assert keep[0].tolist() == [False, False]
    keep, _ = verify_tracks(views, [loose], lambda k: kp[k], strict=0.68, tau=2.0,
                            config=TrackConsensus(min_views=2))
    assert keep[0].tolist() == [True, True]


def test_a_false_edge_between_two_tracks_is_dropped_and_the_tracks_survive():
    views, _, kp = _scene(n_views=4, n_points=2)
    cands = _all_pairs(4, 2, ratio=0.5)
    # one false, even strict, match: point 0 in view 0 with point 1 in view 3
    i, j, p, r = cands[2]  # the pair (0, 3)
    assert (i, j) == (0, 3)
    cands[2] = (i, j, np.vstack([p, [[0, 1]]]), np.append(r, 0.3))
    keep, stats = verify_tracks(views, cands, lambda k: kp[k], strict=0.68, tau=2.0)
    assert keep[2].tolist() == [True, True, False]  # the lowest ratio of all, still contradicted by the tracks
    assert all(k.all() for q, k in enumerate(keep) if q != 2)
    assert stats["components"] == 1 and stats["groups"] == 2


def test_a_keypoint_off_its_track_is_left_out():
    views, _, kp = _scene(n_views=4, n_points=1)
    kp = kp.copy()
    kp[3, 0] += [6.0, -4.0]  # view 3 observes the point 7 px off: beyond tau
    keep, _ = verify_tracks(views, _all_pairs(4, 1, ratio=0.8), lambda k: kp[k], strict=0.68, tau=2.0)
    pairs = [(i, j) for i in range(4) for j in range(i + 1, 4)]
    assert {pq: bool(k[0]) for pq, k in zip(pairs, keep)} == {
        (0, 1): True, (0, 2): True, (1, 2): True, (0, 3): False, (1, 3): False, (2, 3): False}
    keep, _ = verify_tracks(views, _all_pairs(4, 1, ratio=0.8), lambda k: kp[k], strict=0.68, tau=8.0)
    assert all(k.all() for k in keep)


def test_points_behind_a_camera_do_not_count():
    views, _, kp = _scene(n_views=3, n_points=1)
    behind = views[2].R.T @ (np.array([0, 0, -2.0]) - views[2].t)  # 2 m behind camera 2, on its axis
    kp = kp.copy()
    for k in range(2):
        Xc = views[k].R @ behind + views[k].t
        kp[k, 0] = (K @ Xc)[:2] / Xc[2]
    kp[2, 0] = K[:2, 2]  # where the point's mirror image would project
    keep, _ = verify_tracks(views, _all_pairs(3, 1, ratio=0.8), lambda k: kp[k], strict=0.68, tau=2.0)
    assert keep[0].tolist() == [False] and not keep[1].any() and not keep[2].any()


def test_empty_candidates_and_empty_pairs():
    views, _, kp = _scene(n_views=3)
    keep, stats = verify_tracks(views, [], lambda k: kp[k], strict=0.68, tau=2.0)
    assert keep == [] and stats["edges"] == 0
    empty = (0, 1, np.zeros((0, 2), np.int64), np.zeros(0))
    keep, stats = verify_tracks(views, [empty, _all_pairs(3, 30)[2]], lambda k: kp[k], strict=0.68, tau=2.0)
    assert keep[0].shape == (0,) and keep[1].all() and stats["edges"] == 30


def test_big_components_are_verified_locally():
    """A component above max_component is checked around each seed, not left unverified."""
    views, _, kp = _scene(n_views=5, n_points=40, seed=3)
    cands = _all_pairs(5, 40, ratio=0.5)
    # chain every track to the next one with a false loose edge: one component of 200 observations
    i, j, p, r = cands[0]
    chain = np.column_stack([np.arange(39), np.arange(1, 40)])
    cands[0] = (i, j, np.vstack([p, chain]), np.append(r, np.full(39, 0.85)))
    full, s_full = verify_tracks(views, cands, lambda k: kp[k], strict=0.68, tau=2.0)
    local, s_local = verify_tracks(views, cands, lambda k: kp[k], strict=0.68, tau=2.0,
                                   config=TrackConsensus(max_component=20))
    assert s_full["components"] == 1 and s_full["big_components"] == 0 and s_local["big_components"] == 1
    for keep in (full, local):
        assert keep[0][:40].all() and not keep[0][40:].any()  # the true matches, not the chain
        assert all(k.all() for k in keep[1:])


def test_projection_matrices_are_normalised():
    views = _ring(4, radius=1000.0)
    P = projection_matrices(views)
    X = np.array([[0.3, -0.2, 0.1]])
    centers = np.array([v.center for v in views])
    c0, s = centers.mean(0), np.median(np.linalg.norm(centers - centers.mean(0), axis=1))
    Y = (X - c0) / s
    for v, Pk in zip(views, P):
        h = Pk @ np.append(Y[0], 1.0)
        Xc = v.R @ X[0] + v.t
        np.testing.assert_allclose(h[:2] / h[2], (K @ Xc)[:2] / Xc[2], rtol=1e-9)


@pytest.mark.parametrize("kwargs, match", [
    ({"loose": 1.5}, "loose"), ({"loose": 0}, "loose"), ({"min_views": 1}, "min_views"),
    ({"tau": -1.0}, "tau"), ({"tau": float("nan")}, "tau"), ({"max_seeds": 0}, "max_seeds"),
    ({"max_component": 1}, "max_component"), ({"hops": 0}, "hops"), ({"min_views": 2.5}, "min_views"),
])
def test_config_is_checked(kwargs, match):
    with pytest.raises(ValueError, match=match):
        TrackConsensus(**kwargs)


# --------------------------------------------------------------------------------------
# Properties
# --------------------------------------------------------------------------------------
@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 10_000), n_views=st.integers(3, 6), noise=st.floats(0.0, 0.8))
def test_consistent_tracks_are_kept_and_the_order_of_pairs_does_not_matter(seed, n_views, noise):
    views, _, kp = _scene(n_views=n_views, n_points=12, seed=seed)
    rng = np.random.default_rng(seed)
    kp = kp + rng.uniform(-noise, noise, kp.shape)  # within tau / 2 of the projections
    cands = _all_pairs(n_views, 12, ratio=0.85)
    cands = [(i, j, p, r + rng.uniform(-0.1, 0.04, len(r))) for i, j, p, r in cands]  # distinct ratios
    keep, _ = verify_tracks(views, cands, lambda k: kp[k], strict=0.68, tau=2.0)
    assert all(k.all() for k in keep)
    order = rng.permutation(len(cands))
    shuffled, _ = verify_tracks(views, [cands[q] for q in order], lambda k: kp[k], strict=0.68, tau=2.0)
    for q, k in zip(order, shuffled):
        np.testing.assert_array_equal(k, keep[q])


@pytest.mark.parametrize("wrong, max_component", [(0.002, 1000), (0.15, 3)])  # 3: "big" components, split locally
def test_components_on_threads_give_the_serial_result(wrong, max_component):
    """Thousands of edges: the kernel runs its parallel twin (blocks of components); the kept matches,
    the groups (numbered in component order) and the counts must be those of one thread, with false
    edges, tied ratios and components of every size among them."""
    import episeg_cv
    from episeg_cv.colmap import _consensus_kernel

    views, _, kp = _scene(n_views=6, n_points=400, seed=3)
    rng = np.random.default_rng(8)
    kp = kp + rng.uniform(-0.5, 0.5, kp.shape)
    cands = []
    for i, j, p, r in _all_pairs(6, 400, ratio=0.5):
        false = rng.random(len(p)) < wrong  # false edges: to a random keypoint, merging tracks
        p = p.copy()
        p[false, 1] = rng.integers(0, 400, int(false.sum()))
        cands.append((i, j, p, np.round(rng.uniform(0.3, 0.89, len(p)), 2)))  # rounded: many ties
    assert sum(len(p) for _, _, p, _ in cands) >= episeg_cv.threads.MIN_PARALLEL_ITEMS
    config = TrackConsensus(max_component=max_component)
    calls = []
    real = _consensus_kernel.consensus_parallel

    def spy(*args):
        calls.append(args[-1])
        return real(*args)

    runs = {}
    for n in (1, 2):
        episeg_cv.set_num_threads(n)
        try:
            _consensus_kernel.consensus_parallel = spy
            runs[n] = verify_tracks(views, cands, lambda k: kp[k], strict=0.68, tau=2.0, config=config)
        finally:
            _consensus_kernel.consensus_parallel = real
            episeg_cv.set_num_threads(None)
    if episeg_cv.threads.get_num_threads() > 1:
        assert calls, "the parallel twin did not run"
    (k1, s1), (k2, s2) = runs[1], runs[2]
    assert s1 == s2 and s1["groups"] > 100
    assert s1["big_components"] > 0 if max_component == 3 else s1["components"] > 100
    for a, b in zip(k1, k2):
        np.testing.assert_array_equal(a, b)
    # and the kernel's own outputs, group by group
    P = projection_matrices(views)
    node_image = np.repeat(np.arange(6), 400)
    node_xy = kp.reshape(-1, 2)
    eu = np.concatenate([i * 400 + p[:, 0] for i, _, p, _ in cands])
    ev = np.concatenate([j * 400 + p[:, 1] for _, j, p, _ in cands])
    er = np.concatenate([r for _, _, _, r in cands])
    args = (P, node_image, node_xy, eu, ev, er, 6, 2.0, 24, max_component, 2)
    serial = _consensus_kernel.consensus(*args)
    for blocks in (1, 3, 16, 64):
        par = _consensus_kernel.consensus_parallel(*args, blocks)
        for a, b in zip(serial, par):
            np.testing.assert_array_equal(a, b)


def _reference_groups(P, node_image, node_xy, eu, ev, er, n_images, tau, max_seeds, max_component, hops):
    """The consensus of the module docstring, plainly: every seed counted in every round, every edge
    scanned (no support bounds, no compaction). ``group`` per node, -1 where none; local numbering."""
    n, m = len(node_image), len(eu)
    parent = list(range(n))

    def find(x):
        while parent[x] != x:
            x = parent[x]
        return x

    for a, b in zip(eu, ev):
        ra, rb = find(a), find(b)
        if ra != rb:
            parent[ra] = rb
    adj = [[] for _ in range(n)]
    for a, b in zip(eu, ev):
        adj[a].append(b)
        adj[b].append(a)
    comps = {}
    for v in range(n):
        comps.setdefault(find(v), []).append(v)
    alive, dead, group, gid = np.ones(n, bool), np.zeros(m, bool), np.full(n, -1), 0

    def triangulate(nodes):
        A = []
        for v in nodes:
            Pk = P[node_image[v]]
            for r in range(2):
                a = node_xy[v, r] * Pk[2] - Pk[r]
                if np.linalg.norm(a) > 0:
                    A.append(a / np.linalg.norm(a))
        A = np.array(A)
        N = A[:, :3].T @ A[:, :3]
        return None if abs(np.linalg.det(N)) < 1e-300 else np.linalg.solve(N, -A[:, :3].T @ A[:, 3])

    def inliers(X, cand):
        best = {}
        for v in cand:
            h = P[node_image[v]] @ np.append(X, 1.0)
            if h[2] > 0:
                err = np.hypot(h[0] / h[2] - node_xy[v, 0], h[1] / h[2] - node_xy[v, 1])
                if err <= tau and (node_image[v] not in best or err < best[node_image[v]][0]):
                    best[node_image[v]] = (err, v)
        return [v for _, v in best.values()]

    def ball(a, b):  # breadth first from both ends, alive nodes within hops, at most max_component
        queue, depth = list(dict.fromkeys([a, b])), [0, 0]
        head = 0
        while head < len(queue) < max_component:
            v, d = queue[head], depth[head]
            head += 1
            for w in adj[v] if d < hops else ():
                if alive[w] and w not in queue:
                    queue.append(w)
                    depth.append(d + 1)
                    if len(queue) >= max_component:
                        break
        return queue

    for root in sorted(comps, key=lambda r: comps[r][0]):
        nodes = comps[root]
        big = len(nodes) > max_component
        edges = sorted((k for k in range(m) if find(eu[k]) == root), key=lambda k: er[k])
        while True:
            seeds = [k for k in edges if alive[eu[k]] and alive[ev[k]] and not dead[k]][:max_seeds]
            if not seeds:
                break
            best, best_seed = [], None
            for k in seeds:
                X = triangulate([eu[k], ev[k]])
                if X is None:
                    continue
                cand = ball(eu[k], ev[k]) if big else [v for v in nodes if alive[v]]
                got = inliers(X, cand)
                if len(got) > len(best):
                    best, best_seed = got, k
            if len(best) < 2:
                dead[seeds] = True
                continue
            X = triangulate(best)
            if X is not None:
                again = inliers(X, ball(eu[best_seed], ev[best_seed]) if big else [v for v in nodes if alive[v]])
                best = again if len(again) >= 2 else best
            group[best] = gid
            alive[best] = False
            gid += 1
    return group


@pytest.mark.parametrize("wrong, max_component", [(0.3, 1000), (0.3, 4)])
def test_the_kernel_is_the_plain_algorithm(wrong, max_component):
    """The kernel's shortcuts (support bounds kept across rounds, scanned edges dropped) change no group:
    the same partition of the observations as counting every seed in every round."""
    from episeg_cv.colmap import _consensus_kernel

    views, _, kp = _scene(n_views=5, n_points=25, seed=5)
    rng = np.random.default_rng(2)
    node_image, node_xy, eu, ev = [], [], [], []
    nid = {}
    for k in range(5):
        for p in range(25):
            nid[k, p] = len(node_image)
            node_image.append(k)
            node_xy.append(kp[k, p] + rng.uniform(-0.6, 0.6, 2))
    for i in range(5):
        for j in range(i + 1, 5):
            for p in range(25):
                q = int(rng.integers(0, 25)) if rng.random() < wrong else p
                eu.append(nid[i, p])
                ev.append(nid[j, q])
    args = (projection_matrices(views), np.array(node_image), np.array(node_xy), np.array(eu), np.array(ev),
            np.round(rng.uniform(0.3, 0.9, len(eu)), 1), 5, 2.0, 6, max_component, 2)
    got = _consensus_kernel.consensus(*args)[0]
    want = _reference_groups(*args)
    assert (got >= 0).sum() > 40
    # the same partition (the kernel numbers its groups by component; compare the node sets)
    assert {tuple(np.flatnonzero(got == g)) for g in set(got[got >= 0])} == \
        {tuple(np.flatnonzero(want == g)) for g in set(want[want >= 0])}
