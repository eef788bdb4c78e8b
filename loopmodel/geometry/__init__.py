"""Geometry: SE(3)/SO(3) helpers, interpolation, alignment and camera models."""

from loopmodel.geometry.align import umeyama_alignment
from loopmodel.geometry.se3 import (
    hat,
    interpolate_pose,
    interpolate_poses,
    invert_pose,
    make_pose,
    quat_wxyz_from_rotation,
    rotation_from_quat_wxyz,
    se3_exp,
    se3_log,
    so3_exp,
    so3_log,
)

__all__ = [
    "hat",
    "interpolate_pose",
    "interpolate_poses",
    "invert_pose",
    "make_pose",
    "quat_wxyz_from_rotation",
    "rotation_from_quat_wxyz",
    "se3_exp",
    "se3_log",
    "so3_exp",
    "so3_log",
    "umeyama_alignment",
]
