"""Self-calibration at the end of a run (``calibration.refine: final``, issue 31).

:func:`refine_final` takes the keyframes as the front end measured them (rectified with the
recorded calibration), the back end's final poses and landmarks, and runs the calibrating bundle
adjustment of :mod:`loopmodel.calibration.refine_rig`; :func:`apply_laser_scale` then brings in
the laser-stereo consistency of :mod:`loopmodel.calibration.refine_laser` (the baseline and the
light plane's offset). :class:`SelfCalibration` holds the refined poses, landmarks, calibration
and light plane, and the report for ``metrics.json`` and ``calibration_refined.yaml``.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from loopmodel.calibration.refine_laser import LaserStereoScale, laser_stereo_scale
from loopmodel.calibration.refine_rig import (
    PARAM_NAMES,
    RigObservations,
    RigRefinement,
    observations_from_keyframes,
    prior_sigmas,
    refine_rig,
)
from loopmodel.config import SelfCalibrationConfig
from loopmodel.errors import LoopmodelError
from loopmodel.geometry.se3 import invert_pose
from loopmodel.imaging.rectify import rectification
from loopmodel.types import Keyframe, StereoCalibration, StripeProfile

logger = logging.getLogger(__name__)

#: Parameters that move right-image points along the columns only (not measured by the front end).
RIGHT_ROW_PARAMS = ("fy_right_px", "cy_right_px", "rot_x_deg")

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]


@dataclass
class SelfCalibration:
    """What the final self-calibration produced.

    ``world_from_kf`` (keyframe id -> 4x4, metres), landmarks (ids, world points), the refined raw
    ``calibration`` (same camera model as the input, unrectified), the light plane
    (``plane_normal_in_cam``, ``plane_d_m``: ``n . p + d = 0`` in the left camera) before and after,
    the rig report and the laser-stereo estimate (None without stripes on seen surfaces).
    """

    world_from_kf: dict[int, F64]
    landmark_ids: I64
    landmarks_in_world: F64
    calibration: StereoCalibration
    recorded: StereoCalibration
    rig: RigRefinement
    plane_normal_in_cam: F64
    plane_d_m: float
    plane_d_recorded_m: float
    sigma_plane_offset_m: float
    laser: LaserStereoScale | None = None
    sigma_plane_tilt_rad: float = 0.0
    seconds: float = 0.0
    extra: dict[str, Any] = field(default_factory=dict)

    def parameters(self) -> dict[str, dict[str, Any]]:
        """Per parameter: recorded and refined value, prior and posterior sigma, move in sigmas, observable.

        Rotation in degrees (the correction of the recorded stereo rotation), lengths in metres,
        pixels in pixels; the light plane's offset last.
        """
        r = self.rig
        rec = r.values_named(r.recorded_values)
        val = r.values_named()
        post = r.sigma_named()
        prior = r.values_named(r.prior_sigma)
        moved = r.moved_sigma()
        out: dict[str, dict[str, Any]] = {}
        for name in PARAM_NAMES:
            out[name] = {
                "recorded": rec[name],
                "refined": val[name],
                "sigma_prior": prior[name],
                "sigma": post[name],
                "moved_sigma": moved[name],
                "estimated": bool(r.estimated[PARAM_NAMES.index(name)]),
                "observable": name not in r.unobservable and bool(r.estimated[PARAM_NAMES.index(name)]),
            }
        if self.laser is not None:
            b0 = r.values[-1]
            b = self.calibration.baseline_m
            sb = self.laser.sigma_log_baseline * b
            out["baseline_m"].update(
                refined=b, sigma=sb, moved_sigma=(b - b0) / r.prior_sigma[-1] + moved["baseline_m"],
                estimated=True, observable=sb < 0.9 * r.prior_sigma[-1],
            )
        d0, d = self.plane_d_recorded_m, self.plane_d_m
        sd = self.laser.sigma_log_plane_offset * abs(d) if self.laser is not None else self.sigma_plane_offset_m
        out["plane_offset_m"] = {
            "recorded": d0,
            "refined": d,
            "sigma_prior": self.sigma_plane_offset_m,
            "sigma": sd,
            "moved_sigma": (d - d0) / self.sigma_plane_offset_m,
            "estimated": self.laser is not None,
            "observable": self.laser is not None and sd < 0.9 * self.sigma_plane_offset_m,
        }
        if self.laser is not None:
            prior_tilt = float(np.degrees(self.sigma_plane_tilt_rad))
            for i in (0, 1):
                t, st = float(np.degrees(self.laser.tilt_rad[i])), float(np.degrees(self.laser.sigma_tilt_rad[i]))
                out[f"plane_tilt_{i + 1}_deg"] = {
                    "recorded": 0.0,
                    "refined": t,
                    "sigma_prior": prior_tilt,
                    "sigma": st,
                    "moved_sigma": t / prior_tilt,
                    "estimated": True,
                    "observable": st < 0.9 * prior_tilt,
                }
        return out

    def report(self) -> dict[str, Any]:
        """The parameters (:meth:`parameters`) and the refined light plane, for ``calibration_refined.yaml``."""
        n = self.plane_normal_in_cam
        return {
            "parameters": self.parameters(),
            "light_plane": {
                "normal_in_cam": [float(v) for v in n],
                "d_m": float(self.plane_d_m),
                "point_in_cam_m": [float(v) for v in -self.plane_d_m * n],
                "sigma_offset_m": float(self.parameters()["plane_offset_m"]["sigma"]),
            },
        }

    def metrics(self) -> dict[str, Any]:
        """``metrics.json`` keys (``calibration_*``)."""
        params = self.parameters()
        moved = {k: round(float(v["moved_sigma"]), 3) for k, v in params.items()}
        m: dict[str, Any] = {
            "calibration_refine": "final",
            "calibration_moved_sigma": moved,
            "calibration_moved_max_sigma": max(abs(v) for v in moved.values()),
            # the move in units of the refined value's own (honest) posterior sigma
            "calibration_moved_max_post_sigma": max(
                abs(v["refined"] - v["recorded"]) / v["sigma"] for v in params.values() if v["sigma"] > 0
            ),
            "calibration_unobservable": [k for k, v in params.items() if not v["observable"]],
            "calibration_parameters": params,
            "calibration_pixel_sigma_px": self.rig.pixel_sigma_px,
            "calibration_observations": self.rig.observations,
            "calibration_iterations": self.rig.iterations,
            "calibration_rms_px_before": self.rig.rms_px_before,
            "calibration_rms_px_after": self.rig.rms_px_after,
            "calibration_refine_s": self.seconds,
            "calibration_unobservable_directions": self.rig.unobservable_directions,
            "calibration_anchored": list(self.rig.anchored),
        }
        if self.laser is not None:
            m["calibration_laser_pairs"] = self.laser.pairs
            m["calibration_laser_keyframes"] = self.laser.keyframes
            m["calibration_laser_discrepancy_pct"] = 100.0 * self.laser.discrepancy_log
            m["calibration_laser_discrepancy_sigma_pct"] = 100.0 * self.laser.discrepancy_sigma
            m["calibration_plane_tilt_deg"] = [float(v) for v in np.degrees(self.laser.tilt_rad)]
            m["calibration_plane_tilt_sigma_deg"] = [float(v) for v in np.degrees(self.laser.sigma_tilt_rad)]
        m.update(self.extra)
        return m


def estimated_parameters(config: SelfCalibrationConfig) -> NDArray[np.bool_]:
    """Which of :data:`PARAM_NAMES` the configuration makes unknowns (k2 and the right rows optional)."""
    estimate = np.ones(len(PARAM_NAMES), bool)
    if not config.refine_k2:
        estimate[[PARAM_NAMES.index("k2_left"), PARAM_NAMES.index("k2_right")]] = False
    if not config.refine_right_rows:
        estimate[[PARAM_NAMES.index(n) for n in RIGHT_ROW_PARAMS]] = False
    return estimate


def anchors_principal_point(config: SelfCalibrationConfig, calibration: StereoCalibration) -> bool:
    """Whether a held common principal point is held through the left camera's (``anchor_principal_point``).

    ``rectified``: for rectified input, whose (rectified) left camera defines the frame the poses refer to.
    """
    mode = config.anchor_principal_point
    return mode == "always" or (mode == "rectified" and bool(calibration.rectified))


def right_rows(keyframes: list[Keyframe], config: SelfCalibrationConfig) -> dict[int, F64] | None:
    """The right matches' measured rows (keyframe id -> rectified rows) when ``refine_right_rows``, else None.

    Keyframes without them (not measured by the front end) give only their right columns.
    """
    if not config.refine_right_rows:
        return None
    return {
        int(k.id): np.asarray(k.right_rows_px, float)
        for k in keyframes
        if np.asarray(k.right_rows_px).size == np.asarray(k.landmark_ids).size
    }


def rectifying_rotations(cal: StereoCalibration) -> tuple[F64, F64, F64, F64]:
    """``R1, R2, K1, K2``: rectifying rotations and rectified camera matrices (identity/K for rectified input)."""
    if cal.rectified:
        return np.eye(3), np.eye(3), cal.K_left.copy(), cal.K_right.copy()
    R1, R2, P1, P2 = rectification(cal)
    return R1, R2, P1[:3, :3].copy(), P2[:3, :3].copy()


def _triangulated(kf: Keyframe, ids: I64) -> F64:
    """World points of a keyframe's own stereo landmarks ``ids`` (its ``points_in_kf``)."""
    pos = {int(i): k for k, i in enumerate(np.asarray(kf.landmark_ids).tolist())}
    p = np.asarray(kf.points_in_kf, float).reshape(-1, 3)[[pos[int(i)] for i in ids]]
    T = np.asarray(kf.world_from_kf, float)
    return p @ T[:3, :3].T + T[:3, 3]


@dataclass
class FinalObservations:
    """:func:`refine_final`'s measurements of its keyframes, made before the back end's estimate is there (fin19)."""

    ids: list[int]  # the keyframes' ids, in order
    obs: RigObservations | None  # of the landmarks kept (refine_final adds the loops)
    kf_ids: list[int]
    lm_ids: I64
    rows: dict[int, F64] | None
    unusable: LoopmodelError | None = None  # why nothing can be refined


def final_observations(
    keyframes: list[Keyframe], calibration: StereoCalibration, config: SelfCalibrationConfig
) -> FinalObservations:
    """The keyframes' observations of landmarks seen in stereo by 2 keyframes, as :func:`refine_final` refines them.

    Needs no estimate: made while the back end's final estimate is made (issue 32, fin19). ``calibration``:
    the recorded one.
    """
    ids = [int(k.id) for k in keyframes]
    if len(keyframes) < 3:
        err = LoopmodelError(f"self-calibration needs 3 keyframes, got {len(keyframes)}")
        return FinalObservations(ids, None, [], np.zeros(0, np.int64), None, err)
    R1, R2, K1, K2 = rectifying_rotations(calibration)
    rows = right_rows(keyframes, config)
    obs, kf_ids, lm_ids = observations_from_keyframes(keyframes, calibration, K1, K2, R1, R2, rows)
    # a landmark needs a stereo observation and a second keyframe (else it only adds unknowns)
    n_pt = lm_ids.size
    stereo = np.zeros(n_pt, bool)
    stereo[obs.point_idx[obs.cam == 1]] = True
    kf_count = np.zeros(n_pt, np.int64)
    pairs = np.unique(obs.point_idx * (len(kf_ids) + 1) + obs.pose_idx)
    np.add.at(kf_count, pairs // (len(kf_ids) + 1), 1)
    keep_pt = stereo & (kf_count >= 2)
    if int(keep_pt.sum()) < 20:
        err = LoopmodelError(f"self-calibration: {int(keep_pt.sum())} landmarks seen in stereo by 2 keyframes")
        return FinalObservations(ids, None, [], np.zeros(0, np.int64), None, err)
    new_index = np.cumsum(keep_pt) - 1
    sel = keep_pt[obs.point_idx]
    obs.pose_idx, obs.cam, obs.uv_px, obs.measure = obs.pose_idx[sel], obs.cam[sel], obs.uv_px[sel], obs.measure[sel]
    obs.point_idx = new_index[obs.point_idx[sel]]
    return FinalObservations(ids, obs, list(kf_ids), lm_ids[keep_pt], rows)


def refine_final(
    keyframes: list[Keyframe],
    world_from_kf: dict[int, F64],
    landmark_ids: I64,
    landmarks_in_world: F64,
    calibration: StereoCalibration,
    config: SelfCalibrationConfig,
    plane_normal_in_cam: F64,
    plane_d_m: float,
    loops: list[tuple[int, int, F64]] | None = None,
    loop_sigmas: F64 | None = None,
    start_values: F64 | None = None,
    observed: FinalObservations | None = None,
) -> SelfCalibration:
    """The calibrating bundle adjustment over the run's keyframes; see the module docstring.

    ``loops``: the run's loop constraints ``(kf_a, kf_b, kf_a_from_kf_b)`` with ``loop_sigmas``
    (rad x3, m x3), as the back end holds them (without them a loop held only by its landmark
    observations opens: on the realistic orbit, seed 1, end-point drift 0.03 -> 1.3 % with the
    calibration held).

    ``calibration`` is the recorded (input) calibration; ``world_from_kf`` and the landmarks the back
    end's final estimate (landmarks it does not hold start from their keyframe's triangulation).
    ``start_values``: the calibration the adjustment starts from (:data:`PARAM_NAMES` order; the
    online estimate), the priors staying at ``calibration``. ``observed``: :func:`final_observations` of
    these keyframes made beforehand (used when the estimate holds the same keyframes).
    Raises :class:`LoopmodelError` when there is nothing to refine.
    """
    t0 = time.perf_counter()
    kfs = [k for k in keyframes if int(k.id) in world_from_kf]
    seen = observed if observed is not None and observed.ids == [int(k.id) for k in kfs] else None
    seen = seen or final_observations(kfs, calibration, config)
    if seen.unusable is not None or seen.obs is None:
        raise seen.unusable or LoopmodelError("self-calibration: no observations")
    obs, kf_ids, lm_ids, rows = seen.obs, seen.kf_ids, seen.lm_ids, seen.rows
    index = {k: i for i, k in enumerate(kf_ids)}
    obs.loops = [(index[a], index[b], np.asarray(T, float)) for a, b, T in (loops or []) if a in index and b in index]
    if loop_sigmas is not None:
        obs.loop_sigmas = np.asarray(loop_sigmas, float)
    # start values: the back end's landmarks, else the first keyframe's stereo triangulation
    start = {int(i): p for i, p in zip(np.asarray(landmark_ids).tolist(), np.asarray(landmarks_in_world), strict=True)}
    pts = np.zeros((lm_ids.size, 3))
    missing = [k for k, i in enumerate(lm_ids.tolist()) if i not in start]
    for k, i in enumerate(lm_ids.tolist()):
        if i in start:
            pts[k] = start[i]
    if missing:
        by_kf: dict[int, list[int]] = {}
        owner = {int(i): int(kf.id) for kf in kfs for i in np.asarray(kf.landmark_ids).tolist()}
        for k in missing:
            by_kf.setdefault(owner[int(lm_ids[k])], []).append(k)
        kf_by_id = {int(k.id): k for k in kfs}
        for kid, ks in by_kf.items():
            kf = kf_by_id[kid]
            T = world_from_kf[kid] @ invert_pose(np.asarray(kf.world_from_kf, float))  # the keyframe's move
            p = _triangulated(kf, lm_ids[ks])
            pts[ks] = p @ T[:3, :3].T + T[:3, 3]
    poses = np.array([world_from_kf[k] for k in kf_ids])
    sig = prior_sigmas(
        config.sigma_focal_px,
        config.sigma_principal_px,
        config.sigma_k1,
        config.sigma_k2,
        config.sigma_rotation_deg,
        config.sigma_baseline_m,
    )
    estimate = estimated_parameters(config)
    if not rows:  # no keyframe measured its right rows: the right columns alone do not inform them
        estimate[[PARAM_NAMES.index(n) for n in RIGHT_ROW_PARAMS]] = False
    poses_out, pts_out, rep = refine_rig(
        obs, poses, pts, calibration, sig, estimate, config.observable_ratio, config.huber_k, config.max_iterations,
        observable_direction_ratio=config.observable_direction_ratio, start_values=start_values,
        anchor_principal_point=anchors_principal_point(config, calibration),
    )
    rep.world_from_kf = {k: poses_out[i] for i, k in enumerate(kf_ids)}
    rep.landmark_ids = lm_ids
    out = SelfCalibration(
        world_from_kf=dict(rep.world_from_kf),
        landmark_ids=lm_ids,
        landmarks_in_world=pts_out,
        calibration=rep.calibration,
        recorded=calibration,
        rig=rep,
        plane_normal_in_cam=np.asarray(plane_normal_in_cam, float),
        plane_d_m=float(plane_d_m),
        plane_d_recorded_m=float(plane_d_m),
        sigma_plane_offset_m=config.sigma_plane_offset_m,
    )
    out.seconds = time.perf_counter() - t0
    logger.info(
        "self-calibration: %d observations, %.3f -> %.3f px rms, unobservable %s (%.1f s)",
        rep.observations, rep.rms_px_before, rep.rms_px_after, rep.unobservable, out.seconds,
    )
    return out


def keyframe_landmarks(keyframes: list[Keyframe]) -> dict[int, I64]:
    """The landmark ids each keyframe observed (stereo and monocular)."""
    out = {}
    for kf in keyframes:
        mono = np.asarray(kf.mono_obs, float).reshape(-1, 3)[:, 0].astype(np.int64)
        out[int(kf.id)] = np.unique(np.concatenate([np.asarray(kf.landmark_ids, np.int64), mono]))
    return out


def apply_laser_scale(
    sc: SelfCalibration,
    keyframes: list[Keyframe],
    stripes: list[StripeProfile],
    sigma_plane_tilt_deg: float,
) -> list[StripeProfile]:
    """The laser-stereo estimate applied to ``sc`` and the stripes.

    Baseline, poses and landmarks scaled about the world origin (the first keyframe's camera), the
    plane offset and the stripes scaled about the camera.

    Returns the stripes as the refined plane places them (unchanged when the estimate is not possible).
    """
    cal = sc.calibration
    b = cal.baseline_m
    laser = laser_stereo_scale(
        stripes,
        {int(k.id): int(k.timestamp_ns) for k in keyframes},
        sc.world_from_kf,
        keyframe_landmarks(keyframes),
        sc.landmark_ids,
        sc.landmarks_in_world,
        cal,
        sc.rig.prior_sigma[-1] / b,
        sc.sigma_plane_offset_m / max(abs(sc.plane_d_m), 1e-9),
        sc.plane_normal_in_cam,
        sc.plane_d_m,
        np.radians(sigma_plane_tilt_deg),
        # the refined left camera's remaining uncertainty moves the stripes' depth too (laser6: on the
        # realistic orbits, seeds 1 / 2, the baseline's share of the discrepancy -0.040 / -0.052 ->
        # -0.034 / -0.046 %; the plane's tilt about the vertical -0.024 / -0.027 -> -0.021 / -0.024 deg,
        # truth -0.018 / -0.020)
        sigma_left_camera=np.where(sc.rig.estimated, sc.rig.posterior_sigma, sc.rig.prior_sigma)[:5],
    )
    if laser is None:
        logger.info("laser-stereo consistency: no stripe on surfaces the landmarks see")
        return stripes
    sc.laser = laser
    sc.sigma_plane_tilt_rad = float(np.radians(sigma_plane_tilt_deg))
    s_b, s_d = laser.baseline_factor, laser.plane_offset_factor
    T = cal.right_from_left.copy()
    T[:3, 3] *= s_b
    sc.calibration = StereoCalibration(
        cal.K_left, cal.K_right, T, cal.image_size, cal.dist_left, cal.dist_right, cal.rectified, cal.camera_model
    )
    for k, P in sc.world_from_kf.items():
        Q = P.copy()
        Q[:3, 3] *= s_b
        sc.world_from_kf[k] = Q
    sc.landmarks_in_world = sc.landmarks_in_world * s_b
    n_new, d_new = laser.refined_plane(sc.plane_normal_in_cam, sc.plane_d_m)
    sc.plane_normal_in_cam, sc.plane_d_m = n_new, d_new
    logger.info(
        "laser-stereo consistency: stripe/stereo depth %+.3f %% (%d keyframes); baseline x%.5f, plane offset x%.5f,"
        " tilt %s deg",
        100 * laser.discrepancy_log, laser.keyframes, s_b, s_d, np.round(np.degrees(laser.tilt_rad), 4),
    )
    out = []
    for s in stripes:  # each stripe point's ray met with the refined plane
        p = s.points_in_cam
        out.append(StripeProfile(s.timestamp_ns, p * (-d_new / (p @ n_new))[:, None]))
    return out


def close_loops(
    sc: SelfCalibration,
    keyframes: list[Keyframe],
    loops: list[tuple[int, int, F64]],
    odometry_sigma_deg: float,
    odometry_sigma_m: float,
    loop_sigma_deg: float,
    loop_sigma_m: float,
) -> None:
    """Each loop's remaining discrepancy spread along its keyframe cycle, as the back end's final estimate does.

    :func:`loopmodel.backend.loop_distribution.distribute_loop_errors` on the refined poses (links:
    consecutive connected keyframes); each landmark moves with the first keyframe that observed it.
    """
    from loopmodel.backend.loop_distribution import distribute_loop_errors

    if not loops:
        return
    links = [(int(k.prev_keyframe_id), int(k.id)) for k in keyframes if k.connected and k.prev_keyframe_id is not None]
    moved = distribute_loop_errors(
        sc.world_from_kf, links, loops, odometry_sigma_deg, odometry_sigma_m, loop_sigma_deg, loop_sigma_m
    )
    fix = {k: moved[k] @ invert_pose(sc.world_from_kf[k]) for k in moved}
    first: dict[int, int] = {}
    for kf in keyframes:
        for i in np.asarray(kf.landmark_ids, np.int64).tolist():
            first.setdefault(int(i), int(kf.id))
    pts = sc.landmarks_in_world.copy()
    for j, lid in enumerate(sc.landmark_ids.tolist()):
        F = fix.get(first.get(int(lid), -1))
        if F is not None:
            pts[j] = F[:3, :3] @ pts[j] + F[:3, 3]
    sc.world_from_kf = dict(moved)
    sc.landmarks_in_world = pts


def restripe(
    stripes: list[StripeProfile],
    recorded: StereoCalibration,
    refined: StereoCalibration,
    plane_normal_in_cam: F64,
    plane_d_m: float,
) -> list[StripeProfile]:
    """Stripes triangulated with the recorded left camera, moved to the refined one.

    Each point goes back to its raw laser-image pixel through the recorded model (exactly the pixel
    it was triangulated from), then out along the refined camera's ray to the light plane
    (``n . p + d = 0``, left camera, metres).
    """
    import cv2

    n = np.asarray(plane_normal_in_cam, float)
    d_rec = np.zeros(5) if recorded.rectified else recorded.dist_left
    out = []
    for s in stripes:
        p = np.asarray(s.points_in_cam, float).reshape(-1, 3)
        if p.shape[0] == 0:
            out.append(s)
            continue
        uv, _ = cv2.projectPoints(p.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), recorded.K_left, d_rec)
        ray = rays_from_raw_px(uv.reshape(-1, 2), refined.K_left, refined.dist_left)
        out.append(StripeProfile(s.timestamp_ns, ray * (-plane_d_m / (ray @ n))[:, None]))
    return out


def rays_from_raw_px(uv_raw_px: F64, K: F64, dist: F64) -> F64:
    """Rays ``(x, y, 1)`` (N x 3, camera frame) of raw (distorted) pixels through ``K`` and ``dist`` (OpenCV).

    The distortion inverted iteratively (up to 50 iterations, to 1e-12).
    """
    import cv2

    uv = np.ascontiguousarray(np.asarray(uv_raw_px, float).reshape(-1, 1, 2))
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-12)
    if hasattr(cv2, "undistortPointsIter"):
        xy = cv2.undistortPointsIter(uv, K, dist, None, None, crit).reshape(-1, 2)
    else:
        xy = cv2.undistortPoints(uv, K, dist, criteria=crit).reshape(-1, 2)
    return np.column_stack([xy, np.ones(xy.shape[0])])
