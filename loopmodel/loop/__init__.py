"""Appearance-based relocalization and loop closing (seed 004, sections 4.2-4.3).

Descriptors on stereo keyframes (:mod:`.features`), a vocabulary tree and keyframe
database for place recognition (:mod:`.vocabulary`, :mod:`.database`), a vectorised P3P
solver and P3P bank (:mod:`.p3p`, :mod:`.pnp`), relocalization (:mod:`.reloc`) and
verified loop detection (:mod:`.closure`).
"""

from loopmodel.loop.closure import (
    LoopDetector,
    LoopEvent,
    LoopParams,
    detector_from_config,
    params_from_config,
    relocalize_in_database,
)
from loopmodel.loop.database import KeyframeDatabase, PlaceCandidate, PlaceParams
from loopmodel.loop.features import (
    FeatureSet,
    describe_at,
    detect_and_describe,
    make_extractor,
    stereo_keyframe_features,
)
from loopmodel.loop.p3p import p3p_grunert
from loopmodel.loop.pnp import PnPResult, solve_pnp_bank
from loopmodel.loop.reloc import RelocParams, RelocResult, localize
from loopmodel.loop.vocabulary import Vocabulary

__all__ = [
    "FeatureSet",
    "KeyframeDatabase",
    "LoopDetector",
    "LoopEvent",
    "LoopParams",
    "PlaceCandidate",
    "PlaceParams",
    "PnPResult",
    "RelocParams",
    "RelocResult",
    "Vocabulary",
    "describe_at",
    "detect_and_describe",
    "detector_from_config",
    "localize",
    "make_extractor",
    "p3p_grunert",
    "params_from_config",
    "relocalize_in_database",
    "solve_pnp_bank",
    "stereo_keyframe_features",
]
