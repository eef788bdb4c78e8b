"""Stereo keyframe front end (seed 004, section 4).

Stereo matching and triangulation at keyframes, KLT tracking, robust pose (via
:mod:`loopmodel.pose`), keyframe policy, local hybrid keyframe BA.

Usage::

    fe = FrontEnd(calibration, config.frontend)
    for frame in sequence.frames():
        res = fe.process(frame)          # FrameResult: world_from_cam, status OK/LOST, ...
        if res.keyframe is not None:     # a new stereo keyframe (feature set), after its local BA
            backend.add_keyframe(res.keyframe)
    for kf in fe.finish_keyframes():     # the last one (frontend.local_ba_beside)
        backend.add_keyframe(kf)
    fe.apply_correction(corrected_world_from_kf)   # e.g. after a loop closure

``world_from_cam == world_from_kf[res.keyframe_id] @ res.kf_from_cam`` holds for every
result; a LOST result's pose is only the motion-model prediction.
"""

from loopmodel.frontend.keyframe import FrameResult, Keyframe, TrackedFeatures
from loopmodel.frontend.tracker import FrontEnd

__all__ = ["FrontEnd", "FrameResult", "Keyframe", "TrackedFeatures"]
