"""The matcher's settings: two frozen objects, with every default in one place.

:class:`SearchConfig` says *where* a query's candidates are (the constraint,
its pixel tolerance and the depth range); :class:`AcceptRule` says *which*
nearest candidate is kept as a match (the ratio test, the mutual check, the
random padding and the cross-check). Every layer (the array API,
:class:`~episeg_cv.SegmentMatcher`, the COLMAP pipeline and the CLI) passes them
whole, as pycolmap passes its option objects. Both are checked once, when they
are made; the code that receives one trusts it.

Functions of the array API also take the fields as keyword arguments
(``tol=4``, ``ratio=0.8``), merged into the objects by :func:`resolve`; an
unknown keyword is a ``TypeError``, never silently ignored.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from .._validation import as_choice, as_count, as_depth_range, as_nonnegative, as_ratio

__all__ = ["SearchConfig", "AcceptRule", "CONSTRAINTS", "resolve"]

#: The constraints. ``"none"`` (no geometry) is plain ``cv2.BFMatcher`` and has no candidate index.
CONSTRAINTS = ("segment", "line", "none")


@dataclass(frozen=True, eq=False)
class SearchConfig:
    """Where the candidates of a query are.

    Attributes
    ----------
    tol : float
        Pixel distance from a keypoint of image 2 to the query's segment (or
        line) within which it is a candidate. Default 2.
    depth_range : (zmin, zmax)
        Bounds on the depth ``z1`` in camera 1, in the unit of ``t``: two
        scalars, or two ``(N,)`` arrays for per-query bounds.
        ``0 <= zmin < zmax <= inf``. Default ``(0, inf)``: cheirality only.
    constraint : {"segment", "line", "none"}
        ``"segment"`` (the correct epipolar segment), ``"line"`` (plain
        epipolar filtering, by the same code path) or ``"none"``.

    Examples
    --------
    >>> SearchConfig(tol=4).replace(constraint="line")
    SearchConfig(tol=4.0, depth_range=(0.0, inf), constraint='line')
    >>> SearchConfig(tol=-1)
    Traceback (most recent call last):
    ...
    ValueError: tol must be a finite number >= 0, got -1
    """

    tol: float = 2.0
    depth_range: tuple = (0.0, np.inf)
    constraint: str = "segment"

    def __post_init__(self):
        object.__setattr__(self, "tol", as_nonnegative(self.tol, "tol"))
        zmin, zmax = as_depth_range(self.depth_range, None)
        bounds = tuple(float(z) if z.ndim == 0 else z for z in (zmin, zmax))
        for z in bounds:
            if isinstance(z, np.ndarray):
                z.flags.writeable = False
        object.__setattr__(self, "depth_range", bounds)
        object.__setattr__(self, "constraint", as_choice(self.constraint, "constraint", CONSTRAINTS))

    @property
    def bounded(self) -> bool:
        """Whether the depth range says more than ``(0, inf)``."""
        zmin, zmax = self.depth_range
        return bool(np.any(np.asarray(zmin) > 0) or np.any(np.isfinite(zmax)))

    def replace(self, **changes) -> "SearchConfig":
        """A copy with some fields changed (and checked)."""
        return dataclasses.replace(self, **changes)

    def _key(self):
        return (self.tol, self.constraint) + tuple(
            z if isinstance(z, float) else ("array", z.tobytes()) for z in self.depth_range)

    def __eq__(self, other):
        return isinstance(other, SearchConfig) and self._key() == other._key()

    def __hash__(self):
        return hash(self._key())

    def __repr__(self):
        dr = tuple(z if isinstance(z, float) else f"<array of {len(z)}>" for z in self.depth_range)
        return f"SearchConfig(tol={self.tol}, depth_range={dr}, constraint={self.constraint!r})"


@dataclass(frozen=True)
class AcceptRule:
    """Which nearest candidate becomes a match (:func:`~episeg_cv.match_descriptors`).

    A query ``i`` is matched to its nearest candidate ``j`` (distance ``d1``) when

    1. ``mutual``: ``i`` is also the nearest, among the queries that have
       ``j`` as a candidate, to ``j``; and
    2. ``ratio``: ``d1 < ratio * d2``, where ``d2`` is the distance to the
       second-nearest *reference* descriptor: the second candidate, or the
       nearest of ``pad`` keypoints of image 2 drawn at random (the same for
       all queries, ``j`` itself excluded), whichever is nearer.

    A ratio test inside a restricted candidate set alone lets every query
    with a single candidate through; the random padding gives every query a
    reference that does not depend on how many candidates it has. The
    defaults were chosen on the precision-recall benchmark
    (``benchmarks/compare.py``, ``docs/benchmarks.md``): the largest ratio
    that keeps precision at or above 0.95 on every scene and on Motorcycle is
    0.69, and the default is one step (0.01) below it.

    Attributes
    ----------
    ratio : float in (0, 1]
        1.0 disables the ratio test. Default 0.68.
    mutual : bool
        Default True.
    pad : int >= 0
        Random reference keypoints of image 2 (0 for none). Default 128.
    cross_check : bool
        Check mutuality in both directions, the reverse one with
        ``geometry.inverse()`` and its own segments in image 1 (implies
        ``mutual``). Default False.
    """

    ratio: float = 0.68
    mutual: bool = True
    pad: int = 128
    cross_check: bool = False

    def __post_init__(self):
        object.__setattr__(self, "ratio", as_ratio(self.ratio, "ratio"))
        object.__setattr__(self, "mutual", bool(self.mutual))
        object.__setattr__(self, "pad", as_count(self.pad, "pad"))
        object.__setattr__(self, "cross_check", bool(self.cross_check))

    def replace(self, **changes) -> "AcceptRule":
        """A copy with some fields changed (and checked)."""
        return dataclasses.replace(self, **changes)


_SEARCH_FIELDS = tuple(f.name for f in dataclasses.fields(SearchConfig))
_RULE_FIELDS = tuple(f.name for f in dataclasses.fields(AcceptRule))


def resolve(search=None, rule=None, options=None, *, takes_rule: bool = True):
    """Merge keyword ``options`` into the two objects: ``(SearchConfig, AcceptRule)``.

    ``search`` and ``rule`` default to the defaults. ``options`` holds field
    names of either object (of :class:`SearchConfig` only, with
    ``takes_rule=False``); anything else is a ``TypeError`` that lists the
    accepted names.
    """
    options = dict(options or {})
    allowed = _SEARCH_FIELDS + (_RULE_FIELDS if takes_rule else ())
    unknown = [k for k in options if k not in allowed]
    if unknown:
        raise TypeError(f"unknown option {unknown[0]!r}; the options are {', '.join(allowed)}")
    for value, kind, name in ((search, SearchConfig, "search"), (rule, AcceptRule, "rule")):
        if value is not None and not isinstance(value, kind):
            raise TypeError(f"{name} must be a {kind.__name__} or None, got {type(value).__name__}")
    s = search or SearchConfig()
    r = rule or AcceptRule()
    s_opts = {k: v for k, v in options.items() if k in _SEARCH_FIELDS}
    r_opts = {k: v for k, v in options.items() if k in _RULE_FIELDS}
    return (s.replace(**s_opts) if s_opts else s), (r.replace(**r_opts) if r_opts else r)
