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

from .._validation import as_choice, as_count, as_depth_range, as_nonnegative, as_positive_int, as_ratio

__all__ = ["SearchConfig", "AcceptRule", "AutoTol", "CONSTRAINTS", "resolve", "as_tol"]

#: The constraints. ``"none"`` (no geometry) is plain ``cv2.BFMatcher`` and has no candidate index.
CONSTRAINTS = ("segment", "line", "none")


@dataclass(frozen=True, eq=False)
class SearchConfig:
    """Where the candidates of a query are.

    Attributes
    ----------
    tol : float or AutoTol
        Pixel distance from a keypoint of image 2 to the query's segment (or
        line) within which it is a candidate. Default 2. ``"auto"`` (stored as
        ``AutoTol()``) or an :class:`AutoTol` asks the matcher to estimate the
        band, and to correct the pose if that matters, from the data
        (:func:`~episeg_cv.estimate_band`).
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
    >>> SearchConfig(tol="auto").auto
    AutoTol()
    >>> SearchConfig(tol=-1)
    Traceback (most recent call last):
    ...
    ValueError: tol must be a finite number >= 0, 'auto' or an AutoTol, got -1
    """

    tol: float = 2.0
    depth_range: tuple = (0.0, np.inf)
    constraint: str = "segment"

    def __post_init__(self):
        object.__setattr__(self, "tol", as_tol(self.tol, "tol"))
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

    @property
    def auto(self) -> "AutoTol | None":
        """The :class:`AutoTol` options when ``tol`` is to be estimated, else None."""
        return self.tol if isinstance(self.tol, AutoTol) else None

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
        tol = "'auto'" if self.tol == AutoTol() else self.tol
        return f"SearchConfig(tol={tol}, depth_range={dr}, constraint={self.constraint!r})"


def _optional(x, name, check):
    return None if x is None else check(x, name)


def _positive(x, name):
    v = as_nonnegative(x, name)
    if v <= 0:
        raise ValueError(f"{name} must be a finite number > 0, got {x!r}")
    return v


@dataclass(frozen=True)
class AutoTol:
    """How ``tol="auto"`` finds the band (:func:`~episeg_cv.estimate_band`).

    The defaults are ``tol="auto"``; the constants and why they were chosen are
    in ``docs/geometry.md`` ("Poses that are off"). In short: confident
    matches (mutual, ratio below ``strict_ratio``) from a wide band around the
    given pose, and from plain nearest neighbours when needed; a robust
    refinement of ``R`` and the direction of ``t`` on their distances to the
    segment; the given pose is kept unless the correction matters; the band is
    ``k`` robust standard deviations of those distances, clamped to
    ``[tol_min, tol_max]``.

    Attributes
    ----------
    band : float or None
        Half-width of the first, wide pass in pixels; None: ``max(16, 0.08 *
        diagonal of image 2)`` (64 px at 640 x 480).
    strict_ratio : float in (0, 1]
        Ratio of the strict rule that selects the confident matches. Default 0.6.
    k : float > 0
        The band is ``k`` sigma. Default 3.
    tol_min : float >= 0
        Smallest band, pixels. Default 2 (keypoint noise; the fixed default).
    tol_max : float or None
        Largest band, pixels; None: ``band``.
    refine : bool
        Correct ``R`` and the direction of ``t`` (needs a calibrated geometry).
        Default True.
    unguided_pass : {"auto", True, False}
        Also take confident matches from plain mutual nearest neighbours over
        all keypoints (covers pose errors larger than ``band``): always, never,
        or ``"auto"`` (default), when the wide pass finds fewer than
        ``min_support`` matches that agree with the refined pose.
    keep_test : float
        Chi-square threshold (5 degrees of freedom, 99 %: 15.09) below which the
        correction is not significant and the given pose is kept.
    keep_px : float or None
        The given pose is also kept when the correction moves the lines by less
        than this at 95 % of the confident matches; None: ``tol_min / 2``.
    prior_deg : float > 0
        Prior standard deviation of the correction (rotation, and direction of
        ``t``), degrees, when the geometry has no covariance. Default 10.
    max_refine_matches : int
        Confident matches used by the refinement, spread over image 1. Default 300.
    min_matches : int
        Fewer confident matches than this: no estimate; the given pose with
        ``tol = 2 tol_min``. Default 12.
    min_support : int
        See ``unguided_pass``. Default 50.

    Examples
    --------
    >>> AutoTol(k=4).replace(tol_min=1.5).tol_min
    1.5
    >>> AutoTol(k=0)
    Traceback (most recent call last):
    ...
    ValueError: k must be a finite number > 0, got 0
    """

    band: float | None = None
    strict_ratio: float = 0.6
    k: float = 3.0
    tol_min: float = 2.0
    tol_max: float | None = None
    refine: bool = True
    unguided_pass: object = "auto"
    keep_test: float = 15.09
    keep_px: float | None = None
    prior_deg: float = 10.0
    max_refine_matches: int = 300
    min_matches: int = 12
    min_support: int = 50

    def __post_init__(self):
        for name, check in (("band", _positive), ("tol_max", _positive), ("keep_px", as_nonnegative)):
            object.__setattr__(self, name, _optional(getattr(self, name), name, check))
        object.__setattr__(self, "strict_ratio", as_ratio(self.strict_ratio, "strict_ratio"))
        for name in ("k", "prior_deg"):
            object.__setattr__(self, name, _positive(getattr(self, name), name))
        for name in ("tol_min", "keep_test"):
            object.__setattr__(self, name, as_nonnegative(getattr(self, name), name))
        object.__setattr__(self, "refine", bool(self.refine))
        u = self.unguided_pass
        if not (u == "auto" if isinstance(u, str) else isinstance(u, (bool, np.bool_))):
            raise ValueError(f"unguided_pass must be 'auto', True or False, got {u!r}")
        object.__setattr__(self, "unguided_pass", u if isinstance(u, str) else bool(u))
        for name in ("max_refine_matches", "min_matches", "min_support"):
            object.__setattr__(self, name, as_positive_int(getattr(self, name), name))
        if self.min_matches < 8:
            raise ValueError(f"min_matches must be at least 8 (the pose has 5 degrees of freedom), "
                             f"got {self.min_matches}")
        if self.tol_max is not None and self.tol_max < self.tol_min:
            raise ValueError(f"tol_max must be >= tol_min, got {self.tol_max} < {self.tol_min}")

    def replace(self, **changes) -> "AutoTol":
        """A copy with some fields changed (and checked)."""
        return dataclasses.replace(self, **changes)

    def __repr__(self) -> str:  # only what differs from the defaults
        changed = [f"{f.name}={getattr(self, f.name)!r}" for f in dataclasses.fields(self)
                   if getattr(self, f.name) != f.default]
        return f"AutoTol({', '.join(changed)})"

    def first_band(self, image_size2) -> float:
        """Half-width of the wide first pass for an image 2 of ``(width, height)`` pixels."""
        return self.band if self.band is not None else max(16.0, 0.08 * float(np.hypot(*image_size2)))

    def bounds(self, image_size2) -> tuple[float, float]:
        """``(tol_min, tol_max)`` for an image 2 of ``(width, height)`` pixels."""
        hi = self.tol_max if self.tol_max is not None else self.first_band(image_size2)
        return self.tol_min, max(hi, self.tol_min)


def as_tol(x, name: str = "tol"):
    """A tolerance: a finite number >= 0 (as float), ``"auto"`` (as ``AutoTol()``) or an :class:`AutoTol`."""
    if isinstance(x, AutoTol):
        return x
    if isinstance(x, str):
        if x.strip().lower() == "auto":
            return AutoTol()
        raise TypeError(f"{name} must be a finite number >= 0, 'auto' or an AutoTol, got {x!r}")
    try:
        return as_nonnegative(x, name)
    except (ValueError, TypeError) as exc:
        raise type(exc)(f"{name} must be a finite number >= 0, 'auto' or an AutoTol, got {x!r}") from None


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
