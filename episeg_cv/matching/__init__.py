"""Matching on arrays: candidates on the segment, descriptor distances, the acceptance rule, filtering.

The data flows one way: :mod:`.config` (the settings) -> :mod:`.candidates`
(which keypoints lie on each query's segment) -> :mod:`.distances` and
:mod:`.guided` (score only those, accept by the rule) ; :mod:`.filtering`
tests pairs from any matcher. :mod:`._kernels` holds the compiled loops.
"""

from .candidates import CandidateIndex
from .config import CONSTRAINTS, AcceptRule, SearchConfig
from .filtering import explain_pairs, filter_pairs
from .guided import (GuidedMatches, MatchInputs, Neighbors, guided_matches, knn_descriptors, match_descriptors,
                     radius_descriptors)

__all__ = ["SearchConfig", "AcceptRule", "CONSTRAINTS", "CandidateIndex", "MatchInputs", "Neighbors",
           "GuidedMatches", "knn_descriptors", "radius_descriptors", "guided_matches", "match_descriptors",
           "filter_pairs", "explain_pairs"]
