"""The one robust pose solver of the project.

Pose of an N-camera central rig from feature correspondences (points now; lines/conics plug in as
further terms).
"""

from loopmodel.pose.ransac import ransac_pose
from loopmodel.pose.rig import CameraRig, PointTerm, PoseTerm
from loopmodel.pose.solver import PoseOptions, PoseResult, estimate_pose, refine_pose

__all__ = [
    "CameraRig",
    "PointTerm",
    "PoseTerm",
    "PoseOptions",
    "PoseResult",
    "estimate_pose",
    "refine_pose",
    "ransac_pose",
]
