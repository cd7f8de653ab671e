"""The ``episeg`` command: a thin layer over the public API.

Subcommands (one module each, :mod:`.main` assembles the parser)
----------------------------------------------------------------
``episeg demo [--out DIR]``
    Segment- vs line-guided matching on the bundled default pair, scored
    against its ground truth; writes ``matches.png``, ``segments.png`` and
    ``matches.json``.
``episeg match IMG1 IMG2 --calib FILE [...]``
    Detect, match under the segment (or line, or no) constraint, and write the
    matches as JSON, NPZ or CSV (:mod:`episeg_cv.io.matches`), and a figure.
``episeg segments IMG1 IMG2 --calib FILE [--points x,y ...] [--random N]``
    The paper's figure for chosen points.
``episeg bench [--quick]``
    Run the scripts of ``benchmarks/`` (source checkout only).
``episeg colmap MODEL IMAGE_DIR --database DB [...]``
    Match every pair of a posed collection (a COLMAP model or a poses JSON)
    on its epipolar segments and write a COLMAP database
    (:func:`episeg_cv.colmap.match_model`); optionally triangulate it.
``episeg synthetic DIR [--views N]``
    Render a posed synthetic collection (images, COLMAP model, poses JSON)
    to try ``episeg colmap`` on.
``episeg compile [--processes N]``
    Compile every kernel of the commands into numba's cache now, in several
    processes at once (:func:`episeg_cv.kernel_cache.compile_kernels`).

Exit codes: 0 success, 1 bad data (missing or unreadable file, bad
calibration), 2 usage errors. Errors print one line on stderr, no traceback.
"""

from .main import build_parser, main

__all__ = ["main", "build_parser"]
