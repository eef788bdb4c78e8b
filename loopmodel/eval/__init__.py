"""Evaluation.

ATE/RPE/drift against ground truth, loop-closure effect, mesh error, plots, report (``loopmodel
eval``).
"""

from loopmodel.eval.trajectory_metrics import (
    ALIGN_MODES,
    Alignment,
    PairEvaluation,
    align,
    associate,
    evaluate_pair,
    kitti_segment_errors,
    rpe,
    statistics,
)

__all__ = [
    "ALIGN_MODES",
    "Alignment",
    "PairEvaluation",
    "align",
    "associate",
    "evaluate_pair",
    "kitti_segment_errors",
    "rpe",
    "statistics",
]
