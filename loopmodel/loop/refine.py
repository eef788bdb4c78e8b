"""Robust refinement of a camera pose from 2-D/3-D correspondences (after the P3P bank),
by the project's one robust pose solver (``loopmodel.pose``, the front end's as well).

The P3P bank works on unit rays; :func:`project_refiner` maps them back to the pixels of the
query camera for the solver. Without a camera at hand, :data:`refine_pose` uses the unified
model with ``xi = 1`` (unit focal length), which maps every central ray except the backward
axis to a finite image point, so it serves any central camera.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from numpy.typing import NDArray

from loopmodel.errors import LoopmodelError
from loopmodel.geometry.camera import CentralCamera
from loopmodel.pose import CameraRig, PointTerm, PoseOptions
from loopmodel.pose import refine_pose as solve_pose

F64 = NDArray[np.float64]

#: (cam_from_world 4x4, unit rays (N, 3) in the camera frame, points (N, 3) in the world
#: frame [m], angular noise scale [rad]) -> refined cam_from_world.
PoseRefiner = Callable[[F64, F64, F64, float], F64]


def project_refiner(camera: CentralCamera) -> PoseRefiner:
    """A :data:`PoseRefiner` for images of ``camera``.

    LM with a Huber loss at the given noise scale on the pixels of the rays. A refinement that fails
    keeps the hypothesis.
    """
    rig = CameraRig.single(camera)
    f = max(camera.px, camera.py)

    def refine(cam_from_world: F64, rays_in_cam: F64, p_in_world: F64, sigma_rad: float) -> F64:
        if rays_in_cam.shape[0] < 3:
            return cam_from_world
        visible = camera.in_front(rays_in_cam)
        uv = camera.project(rays_in_cam[visible])
        opts = PoseOptions(loss="huber", fixed_scale=max(sigma_rad * f, 1e-6))
        try:
            res = solve_pose(PointTerm(rig, p_in_world[visible], uv), cam_from_world, opts)
        except LoopmodelError:
            return cam_from_world
        return np.asarray(res.rig_from_ref, dtype=float)

    return refine


#: The default refiner: any central camera, through the unit-sphere (xi = 1) model.
refine_pose: PoseRefiner = project_refiner(CentralCamera(1.0, 1.0, 0.0, 0.0, xi=1.0))
