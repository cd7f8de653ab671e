"""Descriptor distances: the scores that rank candidates, and the distances reported to users.

Scores are computed pair by pair in compiled code (:mod:`._kernels`): the
squared distance for L2, the distance itself for L1 and Hamming, in float32.
They rank candidates, and the distances reported to users are made from them
(:meth:`Distances.to_distance`, :meth:`Distances.exact`): on integer-valued
descriptors (SIFT, uint8) they equal ``cv2.BFMatcher``'s, on others they agree
within float32 rounding.
"""

from __future__ import annotations

import numpy as np

from .. import threads
from . import _kernels

__all__ = ["Distances"]


_scratch = threads.Scratch()  # per Python thread: the padding's row and product buffers
#: Rows per BLAS product of :meth:`Distances.nearest_excluding` (256 KiB of product for 128 keypoints).
PAD_CHUNK = 512
#: The last, shorter chunk is multiplied with its rows padded to a multiple of this.
PAD_ROUND = 64


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
        """``(K,)`` float32 scores of the pairs ``(i[k], j[k])``."""
        i, j = np.asarray(i, np.int64), np.asarray(j, np.int64)
        return threads.run(_kernels.paired_scores, _kernels.paired_scores_parallel, len(i), self.a, self.b, i, j,
                           self.code)

    def nearest_excluding(self, qi: np.ndarray, tj: np.ndarray, exclude: np.ndarray) -> np.ndarray:
        """``(len(qi),)`` smallest score of each query ``qi[r]`` over the keypoints ``tj``, leaving out
        ``exclude[r]``; inf when nothing is left.

        Every query against the same keypoints is a dense product: for L2 it is done with BLAS
        (:func:`._kernels.padding_l2`), in chunks of :data:`PAD_CHUNK` rows (the last one rounded up to
        :data:`PAD_ROUND`) whose product stays in
        cache, each fused with its minimum. The chunks are cut at fixed row numbers and run on the
        compiled kernels' threads with BLAS on one thread each, so a row's arithmetic does not depend on
        the thread count.
        """
        qi, tj, exclude = (np.asarray(v, dtype=np.int64) for v in (qi, tj, exclude))
        if self.norm not in ("l2", "l2sqr"):
            return threads.run(_kernels.nearest_excluding, _kernels.nearest_excluding_parallel, len(qi), self.a,
                               self.b, qi, tj, exclude, self.code)
        out = np.empty(len(qi), dtype=np.float32)
        if len(qi) == 0 or len(tj) == 0:
            out.fill(np.inf)
            return out
        bt2, bb = _kernels.padding_operands(self.b, tj)
        chunks = -(-len(qi) // PAD_CHUNK)
        n = min(threads.get_num_threads(), chunks)
        D = self.a.shape[1]
        # BLAS on one thread: a multi-threaded BLAS on these small products, next to the compiled kernels'
        # idle threads, was slower with two threads than with one
        with threads.blas_limit(1):
            if n == 1:
                rows = _scratch.get("rows", (PAD_CHUNK, D), np.float32)
                prod = _scratch.get("prod", (PAD_CHUNK, len(tj)), np.float32)
                _kernels.padding_l2(self.a, qi, bt2, bb, tj, exclude, 0, len(qi), rows, prod, out, PAD_ROUND)
            else:  # whole chunks per block
                cuts = np.array([PAD_CHUNK * (chunks * h // n) for h in range(n)] + [len(qi)], dtype=np.int64)
                rows = _scratch.get("rows", (n, PAD_CHUNK, D), np.float32)
                prod = _scratch.get("prod", (n, PAD_CHUNK, len(tj)), np.float32)
                threads.call_parallel(_kernels.padding_l2_parallel, self.a, qi, bt2, bb, tj, exclude, cuts, rows,
                                      prod, out, PAD_ROUND)
        return out

    def to_distance(self, scores: np.ndarray) -> np.ndarray:
        """Scores -> distances in the units of the norm (the square root for L2)."""
        return np.sqrt(scores, dtype=scores.dtype) if self.norm == "l2" else scores

    def exact(self, i: np.ndarray, j: np.ndarray) -> np.ndarray:
        """Paired distances ``d(i[k], j[k])`` as float32, in the units ``cv2.BFMatcher`` reports.

        The same compiled float32 sums that rank the candidates (:meth:`paired`), so a reported
        distance is the one the matcher ranked by. On integer-valued descriptors (SIFT, uint8) they
        are exact, hence equal to cv2's; on others, within float32 rounding of cv2's (the order of
        the sums differs, as it does between ``cv2.norm`` and ``cv2.BFMatcher`` themselves).
        """
        return self.to_distance(self.paired(i, j))
