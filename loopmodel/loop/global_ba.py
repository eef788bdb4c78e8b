"""Global hybrid bundle adjustment on loop closure (seed 004, section 4.3, eq. 6).

The residuals are those of the local hybrid BA of every feature set in the loop — stereo
projections (left and right) at the keyframe that triangulated the set, and the final
monocular projections in the next keyframe's left image — plus the loop residuals: the
current keyframe's monocular observations of the re-found old features. All keyframe poses
and all feature positions are optimised together (GTSAM Levenberg–Marquardt with a Huber
loss), with the oldest keyframe of the loop held fixed (gauge). The seed parametrises
features in their keyframe and poses relatively; optimising absolute poses and world
points has the same minimum and lets GTSAM's sparse solver do the work.

Inputs are keyframes (:class:`loopmodel.types.Keyframe`; the image is not read): ``id``,
``world_from_kf`` (4x4, the keyframe's left camera), ``landmark_ids`` (M,), ``points_in_kf``
(M, 3, metres in that camera frame), ``stereo_px`` (M, 3: u_left, u_right, v) and
``mono_obs`` (K, 3: landmark id, u, v) in rectified pixels; ``rect_from_cam`` maps the camera
frame to the rectified one. Keyframes with ``connected = False`` (a new segment after
tracking loss) get a weak prior on their pose so that a segment without a loop link cannot
make the problem singular.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import gtsam
import numpy as np
from numpy.typing import NDArray

from loopmodel.errors import EstimationError, InputError
from loopmodel.types import Keyframe

F64 = NDArray[np.float64]


@dataclass
class LoopObservations:
    """Monocular observations of old landmarks at the loop-closing keyframe ``kf_id``.

    ``landmark_ids`` (N,) and rectified left pixels ``uv_px`` (N, 2).
    """

    kf_id: int
    landmark_ids: NDArray[np.int64]
    uv_px: F64


@dataclass
class GlobalBAResult:
    """Optimised ``world_from_kf`` per keyframe id (camera frame, metres), landmark
    positions in the world frame, problem size and timing."""

    world_from_kf: dict[int, F64]
    p_in_world: dict[int, F64]
    n_parameters: int
    n_residuals: int
    initial_error: float
    final_error: float
    iterations: int
    solve_s: float
    build_s: float
    info: dict[str, Any] = field(default_factory=dict)


def _pose3(T: F64) -> gtsam.Pose3:
    return gtsam.Pose3(gtsam.Rot3(np.asarray(T[:3, :3])), gtsam.Point3(*np.asarray(T[:3, 3])))


def global_hybrid_ba(
    keyframes: Sequence[Keyframe],
    loops: Sequence[LoopObservations],
    fx_px: float,
    fy_px: float,
    cx_px: float,
    cy_px: float,
    baseline_m: float,
    sigma_px: float = 1.0,
    huber_k: float = 1.345,
    max_iterations: int = 20,
    fixed_kf_id: int | None = None,
) -> GlobalBAResult:
    """Jointly optimise keyframe poses and feature positions (rectified pinhole stereo
    with focal lengths/centre in pixels and the baseline in metres). ``fixed_kf_id``
    (default: the first keyframe) is held at its current pose."""
    if not keyframes:
        raise InputError("global_hybrid_ba", "no keyframes")
    t0 = time.perf_counter()
    X = gtsam.symbol_shorthand.X
    L = gtsam.symbol_shorthand.L
    K_mono = gtsam.Cal3_S2(fx_px, fy_px, 0.0, cx_px, cy_px)
    K_st = gtsam.Cal3_S2Stereo(fx_px, fy_px, 0.0, cx_px, cy_px, baseline_m)
    huber = gtsam.noiseModel.mEstimator.Huber.Create(huber_k)
    n2 = gtsam.noiseModel.Robust.Create(huber, gtsam.noiseModel.Isotropic.Sigma(2, sigma_px))
    n3 = gtsam.noiseModel.Robust.Create(huber, gtsam.noiseModel.Isotropic.Sigma(3, sigma_px))
    graph = gtsam.NonlinearFactorGraph()
    values = gtsam.Values()
    world_from_rect: dict[int, F64] = {}
    for kf in keyframes:
        Tw = kf.world_from_rect
        world_from_rect[int(kf.id)] = Tw
        values.insert(X(int(kf.id)), _pose3(Tw))
    owner: dict[int, int] = {}
    n_res = 0
    weak = gtsam.noiseModel.Diagonal.Sigmas(np.array([1.0, 1.0, 1.0, 10.0, 10.0, 10.0]))
    for kf in keyframes:
        if not kf.connected:
            graph.add(gtsam.PriorFactorPose3(X(int(kf.id)), _pose3(world_from_rect[int(kf.id)]), weak))
    for kf in keyframes:
        Tw = np.asarray(kf.world_from_kf, dtype=float)
        ids = np.asarray(kf.landmark_ids, dtype=np.int64)
        pts = np.asarray(kf.points_in_kf, dtype=float).reshape(-1, 3)
        spx = np.asarray(kf.stereo_px, dtype=float).reshape(-1, 3)
        for lid, p, s in zip(ids, pts, spx, strict=True):
            lid = int(lid)
            if lid in owner:
                raise InputError("global_hybrid_ba", f"landmark {lid} appears in two keyframes")
            owner[lid] = int(kf.id)
            values.insert(L(lid), gtsam.Point3(*(Tw[:3, :3] @ p + Tw[:3, 3])))
            graph.add(
                gtsam.GenericStereoFactor3D(gtsam.StereoPoint2(s[0], s[1], s[2]), n3, X(int(kf.id)), L(lid), K_st)
            )
            n_res += 3
    mono_sets: list[tuple[int, F64]] = [
        (int(kf.id), np.asarray(kf.mono_obs, dtype=float).reshape(-1, 3)) for kf in keyframes
    ]
    mono_sets += [
        (
            lo.kf_id,
            np.column_stack([np.asarray(lo.landmark_ids, float), np.asarray(lo.uv_px, float)]),
        )
        for lo in loops
    ]
    n_loop = 0
    for kf_id, obs in mono_sets:
        if kf_id not in world_from_rect:
            raise InputError("global_hybrid_ba", f"observations at unknown keyframe {kf_id}")
        for lid_f, u, v in obs:
            lid = int(lid_f)
            if lid not in owner or owner[lid] == kf_id:
                continue
            graph.add(gtsam.GenericProjectionFactorCal3_S2(gtsam.Point2(u, v), n2, X(kf_id), L(lid), K_mono))
            n_res += 2
    n_loop = sum(len(lo.landmark_ids) for lo in loops)
    fixed = int(keyframes[0].id) if fixed_kf_id is None else int(fixed_kf_id)
    if fixed not in world_from_rect:
        raise InputError("global_hybrid_ba", f"fixed keyframe {fixed} is not in the problem")
    graph.add(gtsam.NonlinearEqualityPose3(X(fixed), _pose3(world_from_rect[fixed])))
    build_s = time.perf_counter() - t0
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(max_iterations)
    params.setRelativeErrorTol(1e-5)
    params.setAbsoluteErrorTol(1e-9)
    t1 = time.perf_counter()
    initial_error = float(graph.error(values))
    try:
        opt = gtsam.LevenbergMarquardtOptimizer(graph, values, params)
        result = opt.optimize()
    except RuntimeError as exc:
        raise EstimationError(f"global hybrid BA failed: {exc}") from None
    solve_s = time.perf_counter() - t1
    out_T: dict[int, F64] = {}
    for kf in keyframes:
        out_T[int(kf.id)] = result.atPose3(X(int(kf.id))).matrix() @ np.asarray(kf.rect_from_cam)
    pts_out = {lid: np.asarray(result.atPoint3(L(lid))) for lid in owner}
    return GlobalBAResult(
        world_from_kf=out_T,
        p_in_world=pts_out,
        n_parameters=6 * (len(keyframes) - 1) + 3 * len(owner),
        n_residuals=n_res,
        initial_error=initial_error,
        final_error=float(graph.error(result)),
        iterations=int(opt.iterations()),
        solve_s=solve_s,
        build_s=build_s,
        info={"loop_observations": n_loop, "landmarks": len(owner)},
    )
