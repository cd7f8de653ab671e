"""The compiled segments and clipped lines against the array formulation (docs/geometry.md) in numpy.

The kernel computes ``a = H [x1; 1]`` itself, in the order ``x H00 + y H01 + H02`` without fused
multiply-adds; numpy's product may round differently, by an ulp or so. So the test is in two parts:
given the kernel's own ``a``, every other output is the numpy formulation's to the last bit; and ``a``
is numpy's within a few ulps. Serial and parallel variants give the same bits.
"""

import cv2
import numba
import numpy as np
import pytest

from episeg_cv import TwoViewGeometry, threads
from episeg_cv.geometry import CHEIRALITY_EPS


def clip(U, V, s0, s1, rect, cheirality_c=None):
    """Homogeneous Liang-Barsky: clip ``U + s (V - U)``, ``s`` in ``[s0, s1]``; ``(lo, hi, valid)``."""
    xmin, xmax, ymin, ymax = rect
    n = U.shape[0]
    D = V - U
    u1, u2, u3 = U.T
    d1, d2, d3 = D.T
    constraints = [(u1 - xmin * u3, d1 - xmin * d3), (xmax * u3 - u1, xmax * d3 - d1),
                   (u2 - ymin * u3, d2 - ymin * d3), (ymax * u3 - u2, ymax * d3 - d2)]
    if cheirality_c is not None:
        constraints.append((u3 - cheirality_c, d3))
    lo, hi = np.full(n, float(s0)), np.full(n, float(s1))
    infeasible = np.zeros(n, dtype=bool)
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        for P, Q in constraints:
            r = -P / Q
            np.maximum(lo, np.where(Q > 0, r, -np.inf), out=lo)
            np.minimum(hi, np.where(Q < 0, r, np.inf), out=hi)
            infeasible |= (Q == 0) & (P < 0)
    return lo, hi, (lo <= hi) & ~infeasible


def reference(g, a, zmin, zmax, rect):
    """The segments of the homogeneous p_inf ``a (N, 3)``, in numpy (the library's formulation before issue 17)."""
    n = len(a)
    b = g.epipole_homogeneous
    zmin = np.broadcast_to(zmin, (n,))[:, None]
    zmax = np.broadcast_to(zmax, (n,))[:, None]
    U = zmin * a + b
    finite_far = np.isfinite(zmax)
    V = np.where(finite_far, np.where(finite_far, zmax, 0.0) * a + b, a)
    c = CHEIRALITY_EPS * (np.linalg.norm(U, axis=1) + np.linalg.norm(V, axis=1))
    lo, hi, valid = clip(U, V, 0.0, 1.0, rect, c)
    D = V - U
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        start = (U + lo[:, None] * D)[:, :2] / (U + lo[:, None] * D)[:, 2:3]
        end = (U + hi[:, None] * D)[:, :2] / (U + hi[:, None] * D)[:, 2:3]
        start[~valid] = np.nan
        end[~valid] = np.nan
        line = np.cross(b, a)
        norm = np.sqrt(line[:, 0] ** 2 + line[:, 1] ** 2)
        line = line / np.where(norm > 0, norm, np.nan)[:, None]
        p_inf = a[:, :2] / a[:, 2:3]
        # the whole line, clipped
        p0 = -line[:, 2:3] * line[:, :2]
        d = np.column_stack([-line[:, 1], line[:, 0]])
        L0, L1 = np.column_stack([p0, np.ones(n)]), np.column_stack([p0 + d, np.ones(n)])
        llo, lhi, ok = clip(np.nan_to_num(L0), np.nan_to_num(L1), -np.inf, np.inf, rect)
        ok &= np.all(np.isfinite(line), axis=1)
        line_start = np.where(ok[:, None], p0 + llo[:, None] * d, np.nan)
        line_end = np.where(ok[:, None], p0 + lhi[:, None] * d, np.nan)
    return dict(start=start, end=end, valid=valid, line=line, infinity_point=p_inf, line_start=line_start,
                line_end=line_end)


def scenes(count=60, seed=1):
    """Random pairs, every fifth kind special: t3 = 0, t = 0, R = I; and depth ranges of every shape."""
    rng = np.random.default_rng(seed)
    for trial in range(count):
        w, h = int(rng.integers(40, 2000)), int(rng.integers(40, 2000))
        f = rng.uniform(0.3, 3) * max(w, h)
        K1 = np.array([[f, rng.uniform(-0.01, 0.01) * f, rng.uniform(0.3, 0.7) * w], [0, f, rng.uniform(0.3, 0.7) * h],
                       [0, 0, 1]])
        K2 = K1.copy()
        K2[0, 0] *= rng.uniform(0.8, 1.2)
        rv = rng.normal(size=3)
        R = cv2.Rodrigues(rv * rng.uniform(0, np.pi) / np.linalg.norm(rv))[0]
        t = rng.normal(size=3) * rng.uniform(0.01, 3)
        kind = trial % 5
        if kind == 1:
            t[2] = 0.0
        elif kind == 2:
            t[:] = 0.0
        elif kind == 3:
            R = np.eye(3)
        g = TwoViewGeometry(K1, K2, R, t, image_size1=(w, h), image_size2=(w, h))
        n = 500
        x1 = np.column_stack([rng.uniform(-0.5, w - 0.5, n), rng.uniform(-0.5, h - 0.5, n)])
        x1[:10] = np.round(x1[:10])
        dr = [(0.0, np.inf), (0.5, 20.0), (rng.uniform(0, 1, n), rng.uniform(1, 50, n)), (0.0, 3.0)][trial % 4]
        yield g, x1, dr, (0.0, 2.0)[trial % 2]


FIELDS = ("start", "end", "valid", "line", "infinity_point", "line_start", "line_end")


def test_kernel_equals_the_numpy_formulation_given_its_a():
    compared = 0
    for g, x1, dr, margin in scenes():
        seg = g.segments(x1, dr, margin=margin)
        ref = reference(g, seg._a, *dr, seg._rect)
        for f in FIELDS:
            got = getattr(seg, f)
            assert got.dtype == ref[f].dtype and got.shape == ref[f].shape, f
            assert got.tobytes() == ref[f].tobytes(), f
        compared += 1
    assert compared == 60


def test_a_is_numpy_within_a_few_ulps():
    for g, x1, dr, margin in scenes(20, seed=2):
        H = g.infinity_homography
        a_np = x1 @ H[:, :2].T + H[:, 2]
        a = g.segments(x1, dr, margin=margin)._a
        scale = np.abs(x1[:, :1]) * np.abs(H[:, 0]) + np.abs(x1[:, 1:]) * np.abs(H[:, 1]) + np.abs(H[:, 2])
        assert np.all(np.abs(a - a_np) <= 4 * np.finfo(float).eps * scale)


@pytest.mark.skipif(numba.config.NUMBA_NUM_THREADS < 2, reason="numba has a single thread here")
def test_serial_and_parallel_give_the_same_bits(monkeypatch):
    threads.set_num_threads(None)  # follow numba's setting, changed below
    before = numba.get_num_threads()
    try:
        for g, x1, dr, margin in scenes(10, seed=3):
            got = []
            for n, min_items in ((1, 10**9), (2, 1)):
                monkeypatch.setattr(threads, "MIN_PARALLEL_ITEMS", min_items)
                numba.set_num_threads(n)
                seg = g.segments(x1, dr, margin=margin)
                got.append([getattr(seg, f).tobytes() for f in FIELDS + ("_a",)])
            assert got[0] == got[1]
    finally:
        numba.set_num_threads(before)
