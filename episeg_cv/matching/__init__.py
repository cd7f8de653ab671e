"""Matching on arrays: candidates on the segment, descriptor distances, the acceptance rule, filtering.

The data flows one way: :mod:`.config` (the settings) -> :mod:`.candidates`
(which keypoints lie on each query's segment) -> :mod:`.distances` and
:mod:`.guided` (score only those, accept by the rule) ; :mod:`.filtering`
tests pairs from any matcher against the geometry, :mod:`.consistency` against
their neighbours. :mod:`._kernels` holds the compiled loops.
:mod:`.auto` resolves ``tol="auto"`` (:func:`estimate_band`) and a pose
covariance (per-query bands, :mod:`.banded`) before calling them.
"""

from .auto import BandEstimate, estimate_band
from .candidates import CandidateIndex
from .config import CONSTRAINTS, AcceptRule, AutoTol, SearchConfig
from .consistency import consistent_pairs
from .filtering import explain_pairs, filter_pairs
from .guided import (GuidedMatches, MatchInputs, Neighbors, guided_matches, knn_descriptors, match_descriptors,
                     radius_descriptors)

__all__ = ["SearchConfig", "AcceptRule", "AutoTol", "BandEstimate", "estimate_band", "CONSTRAINTS", "CandidateIndex", "MatchInputs", "Neighbors",
           "GuidedMatches", "knn_descriptors", "radius_descriptors", "guided_matches", "match_descriptors",
           "filter_pairs", "explain_pairs", "consistent_pairs"]
