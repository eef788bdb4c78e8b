"""Stereo keyframe front end: stereo matching and triangulation at keyframes, KLT tracking,
robust pose (via :mod:`loopmodel.pose`), keyframe policy, local hybrid keyframe BA."""

from loopmodel.frontend.keyframe import FrameResult, Keyframe
from loopmodel.frontend.tracker import FrontEnd

__all__ = ["FrontEnd", "FrameResult", "Keyframe"]
