"""Descriptor distances: the scores that rank candidates, and the distances reported to users.

Scores are computed pair by pair in compiled code (:mod:`._kernels`): the
squared distance for L2, the distance itself for L1 and Hamming, in float32.
They rank candidates. The distances reported to users are recomputed the way
``cv2`` computes them (:meth:`Distances.exact`), so that they agree with
``cv2.BFMatcher`` to the last bit.
"""

from __future__ import annotations

import numpy as np

from .. import threads
from . import _kernels

__all__ = ["Distances"]


_scratch = threads.Scratch()  # per Python thread: the padding's row and product buffers


class Distances:
    """Scores and exact distances between two checked descriptor arrays.

    Parameters
    ----------
    d1, d2 : (N1, D), (N2, D) ndarray
        Checked descriptors (``episeg_cv._validation.as_descriptor_pair``): float32/float64, or uint8
        packed bits for Hamming.
    norm : {"l1", "l2", "l2sqr", "hamming"}
    """

    def __init__(self, d1: np.ndarray, d2: np.ndarray, norm: str):
        self.norm = norm
        self.code = _kernels.NORM_CODES[norm]
        self.raw1, self.raw2 = d1, d2
        if norm == "hamming":
            self.a, self.b = _kernels.as_words(d1), _kernels.as_words(d2)
        else:
            self.a = np.ascontiguousarray(d1, dtype=np.float32)
            self.b = np.ascontiguousarray(d2, dtype=np.float32)

    def reversed(self) -> "Distances":
        """The same descriptors with the two sides swapped (for a reverse pass)."""
        return Distances(self.raw2, self.raw1, self.norm)

    def paired(self, i: np.ndarray, j: np.ndarray) -> np.ndarray:
        """``(K,)`` scores of the pairs ``(i[k], j[k])``."""
        return _kernels.paired_scores(self.a, self.b, np.asarray(i, np.int64), np.asarray(j, np.int64), self.code)

    def nearest_excluding(self, qi: np.ndarray, tj: np.ndarray, exclude: np.ndarray, chunk: int = 4096) -> np.ndarray:
        """``(len(qi),)`` smallest score of each query ``qi[r]`` over the keypoints ``tj`` (sorted), leaving out
        ``exclude[r]``; inf when nothing is left.

        Every query against the same keypoints is a dense product: for L2 it is done with BLAS, in
        row chunks of at most ``chunk`` rows with reused buffers (fresh ``len(qi) x len(tj)`` arrays
        cost more in page faults than the product on a VM), and the exclusion found by ``searchsorted``.
        """
        qi, tj, exclude = (np.asarray(v, dtype=np.int64) for v in (qi, tj, exclude))
        if self.norm not in ("l2", "l2sqr"):
            return threads.run(_kernels.nearest_excluding, _kernels.nearest_excluding_parallel, len(qi), self.a,
                               self.b, qi, tj, exclude, self.code)
        out = np.empty(len(qi), dtype=np.float32)
        if len(qi) == 0 or len(tj) == 0:
            out.fill(np.inf)
            return out
        pos = np.minimum(np.searchsorted(tj, exclude), len(tj) - 1)
        hit = tj[pos] == exclude
        b = self.b[tj]
        bt2 = np.ascontiguousarray(b.T) * np.float32(-2.0)  # exact: a power of two
        bb = np.einsum("ij,ij->i", b, b)[None, :]
        # min_j |a|^2 + |b_j|^2 - 2 a.b_j = |a|^2 + min_j (|b_j|^2 - 2 a.b_j): the row's |a|^2 is added
        # after the minimum, which saves a pass over the product; clamped at 0 (rounding).
        n_threads = threads.get_num_threads()
        n_chunks = n_threads * -(-len(qi) // (n_threads * chunk))  # balanced over the threads
        size = -(-len(qi) // n_chunks)

        def block(a):  # one chunk of rows; single-threaded BLAS, so each row's sums do not depend on the threads
            z = min(a + size, len(qi))
            r = _scratch.get("rows", (size, self.a.shape[1]), np.float32)[:z - a]
            np.take(self.a, qi[a:z], axis=0, out=r, mode="clip")
            p = np.matmul(r, bt2, out=_scratch.get("prod", (size, len(tj)), np.float32)[:z - a])
            p += bb
            h = np.flatnonzero(hit[a:z])
            p[h, pos[a:z][h]] = np.inf
            m = np.min(p, axis=1, out=out[a:z])
            m += np.einsum("ij,ij->i", r, r)
            np.maximum(m, 0.0, out=m)

        # The chunks run on Python threads (numpy and BLAS release the GIL) with BLAS on one thread: a
        # multi-threaded BLAS on these small products, next to the compiled kernels' idle threads,
        # was slower with two threads than with one.
        with threads.blas_limit(1):
            threads.map_blocks(block, list(range(0, len(qi), size)))
        return out

    def to_distance(self, scores: np.ndarray) -> np.ndarray:
        """Scores -> distances in the units of the norm (the square root for L2)."""
        return np.sqrt(scores) if self.norm == "l2" else scores

    def exact(self, i: np.ndarray, j: np.ndarray, chunk: int = 4096) -> np.ndarray:
        """Paired distances ``d(i[k], j[k])`` as float32, computed directly (as ``cv2`` reports them).

        In chunks, with the gathered rows in buffers reused from chunk to chunk.
        """
        raw1, raw2, norm = self.raw1, self.raw2, self.norm
        i, j = np.asarray(i, dtype=np.intp), np.asarray(j, dtype=np.intp)
        out = np.empty(len(i), dtype=np.float32)
        if len(i) == 0:
            return out
        n = min(chunk, len(i))
        if norm == "hamming":
            buf = np.empty((n, raw1.shape[1]), dtype=np.uint8)
            for a in range(0, len(i), chunk):
                z = min(a + chunk, len(i))
                np.bitwise_xor(raw1[i[a:z]], raw2[j[a:z]], out=buf[:z - a])
                out[a:z] = np.unpackbits(buf[:z - a], axis=1).sum(1)
            return out
        # float32 arithmetic, as cv2 does (uint8 descriptors are widened first)
        x = np.empty((n, raw1.shape[1]), dtype=np.float32)
        y = np.empty_like(x)
        for a in range(0, len(i), chunk):
            z = min(a + chunk, len(i))
            xa, ya = x[:z - a], y[:z - a]
            for raw, rows, buf in ((raw1, i[a:z], xa), (raw2, j[a:z], ya)):
                if raw.dtype == np.float32:
                    np.take(raw, rows, axis=0, out=buf, mode="clip")  # (the default 'raise' buffers)
                else:
                    np.copyto(buf, raw[rows], casting="unsafe")
            np.subtract(xa, ya, out=xa)
            if norm == "l1":
                np.abs(xa, out=xa)
                out[a:z] = xa.sum(1, dtype=np.float32)
            else:
                out[a:z] = np.einsum("ij,ij->i", xa, xa)
        return np.sqrt(out, out=out) if norm == "l2" else out
