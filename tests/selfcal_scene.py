"""A seeded synthetic stereo scan for the self-calibration tests.

A true distorted rig (EuRoC's lens, as the simulator's realistic world), a recorded calibration off
by drawn errors, points on a bumpy sphere 0.4-0.6 m away seen from an orbit of keyframes; the
measurements are made as the front end makes them: in the images rectified with the recorded
calibration, the right one on the left one's row.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from loopmodel.geometry.se3 import invert_pose, look_at, make_pose, so3_exp
from loopmodel.imaging.rectify import rectification
from loopmodel.types import Keyframe, StereoCalibration

EUROC_DIST_LEFT = np.array([-0.28340811, 0.07395907, 0.00019359, 1.76187114e-05, 0.0])
EUROC_DIST_RIGHT = np.array([-0.28368365, 0.07451284, -0.00010473, -3.55590700e-05, 0.0])


def _project(p: np.ndarray, K: np.ndarray, d: np.ndarray) -> np.ndarray:
    import cv2

    uv, _ = cv2.projectPoints(p.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), K, d)
    return uv.reshape(-1, 2)


def _rectified(uv_raw: np.ndarray, K: np.ndarray, d: np.ndarray, R: np.ndarray, P: np.ndarray) -> np.ndarray:
    import cv2

    return cv2.undistortPoints(
        uv_raw.reshape(-1, 1, 2), K, d, R=R, P=P, criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-12)
    ).reshape(-1, 2)


@dataclass
class Scene:
    """True and recorded rig, true keyframe poses (left camera), world points, keyframes as measured."""

    true: StereoCalibration
    recorded: StereoCalibration
    world_from_kf: np.ndarray
    points_w: np.ndarray
    keyframes: list[Keyframe]
    R1: np.ndarray
    R2: np.ndarray
    P1: np.ndarray
    P2: np.ndarray
    #: keyframe id -> the rectified row of each stereo match in the right image (``stereo_px`` order)
    right_rows: dict[int, np.ndarray] = field(default_factory=dict)


def true_rig(baseline_m: float = 0.06) -> StereoCalibration:
    """The simulator's realistic rig (fx 500 px, 640 x 480, EuRoC lens and stereo rotation)."""
    K = np.array([[500.0, 0, 319.5], [0, 500.0, 239.5], [0, 0, 1]])
    KR = K.copy()
    KR[0, 0] *= 0.9977
    KR[1, 1] *= 0.9975
    KR[0, 2] += 3.0
    KR[1, 2] += 2.0
    c01 = make_pose(so3_exp(np.array([0.00388, 0.00040, 0.00230])), np.array([baseline_m, -0.0004, -0.0004]))
    return StereoCalibration(K, KR, invert_pose(c01), (640, 480), EUROC_DIST_LEFT, EUROC_DIST_RIGHT, rectified=False)


def recorded_rig(true: StereoCalibration, seed: int, scale: float = 1.0) -> StereoCalibration:
    """The true rig off by the realistic world's calibration errors (0.3 px, 0.002 in k1, 0.02 deg, 0.05 mm)."""
    rng = np.random.default_rng(seed)
    KL, KR = true.K_left.copy(), true.K_right.copy()
    for K in (KL, KR):
        K[0, 0] += scale * rng.normal(0, 0.3)
        K[1, 1] += scale * rng.normal(0, 0.3)
        K[0, 2] += scale * rng.normal(0, 0.3)
        K[1, 2] += scale * rng.normal(0, 0.3)
    dl, dr = true.dist_left.copy(), true.dist_right.copy()
    dl[0] += scale * rng.normal(0, 0.002)
    dr[0] += scale * rng.normal(0, 0.002)
    T = true.right_from_left.copy()
    T[:3, :3] = so3_exp(scale * rng.normal(0, np.radians(0.02), 3)) @ T[:3, :3]
    T[:3, 3] *= 1.0 + scale * rng.normal(0, 5e-5) / true.baseline_m
    return StereoCalibration(KL, KR, T, true.image_size, dl, dr, rectified=False)


def make_scene(
    recorded: StereoCalibration | None = None,
    seed: int = 3,
    n_kf: int = 36,
    n_points: int = 1500,
    noise_px: float = 0.1,
    arc_deg: float = 300.0,
    track_kf: int = 3,
) -> Scene:
    """Keyframes on an arc around a bumpy sphere (radius 0.1 m), 0.45 m from its centre."""
    rng = np.random.default_rng(seed)
    true = true_rig()
    rec = recorded if recorded is not None else true
    # points on a bumpy sphere
    d = rng.normal(size=(n_points, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    radius = 0.1 * (1.0 + 0.15 * np.sin(5 * d[:, 0]) * np.cos(4 * d[:, 1]))
    pts = d * radius[:, None]
    poses = []
    for a in np.radians(np.linspace(0.0, arc_deg, n_kf)):
        eye = np.array([0.45 * np.sin(a), 0.08 * np.sin(2 * a), -0.45 * np.cos(a)])
        T = look_at(eye, np.array([0.0, 0.01 * np.cos(3 * a), 0.0]), np.array([0.0, -1.0, 0.0]))
        poses.append(T)
    world_from_kf = np.array(poses)
    # the rig's first keyframe defines the world
    world_from_kf = np.einsum("ij,njk->nik", invert_pose(world_from_kf[0]), world_from_kf)
    pts = (invert_pose(poses[0]) @ np.column_stack([pts, np.ones(n_points)]).T).T[:, :3]
    R1, R2, P1, P2 = rectification(rec)
    w, h = true.image_size
    keyframes: list[Keyframe] = []
    visible: list[np.ndarray] = []
    right_rows: dict[int, np.ndarray] = {}
    for k, T in enumerate(world_from_kf):
        p_l = (invert_pose(T) @ np.column_stack([pts, np.ones(n_points)]).T).T[:, :3]
        p_r = p_l @ true.right_from_left[:3, :3].T + true.right_from_left[:3, 3]
        # visible: in front, facing the camera (on the near side of the sphere)
        normal_w = pts / np.linalg.norm(pts - pts.mean(0), axis=1, keepdims=True)
        view = T[:3, 3][None] - pts
        facing = np.sum((pts - pts.mean(0)) * view, axis=1) > 0.25 * np.linalg.norm(view, axis=1) * np.linalg.norm(
            pts - pts.mean(0), axis=1
        )
        del normal_w
        uvl = _project(p_l, true.K_left, true.dist_left)
        uvr = _project(p_r, true.K_right, true.dist_right)
        inside = (
            (p_l[:, 2] > 0.1) & facing
            & (uvl[:, 0] > 10) & (uvl[:, 0] < w - 10) & (uvl[:, 1] > 10) & (uvl[:, 1] < h - 10)
            & (uvr[:, 0] > 10) & (uvr[:, 0] < w - 10) & (uvr[:, 1] > 10) & (uvr[:, 1] < h - 10)
        )
        idx = np.flatnonzero(inside)
        uvl_n = uvl[idx] + rng.normal(0, noise_px, (idx.size, 2))
        uvr_n = uvr[idx] + rng.normal(0, noise_px, (idx.size, 2))
        rl = _rectified(uvl_n, rec.K_left, rec.dist_left, R1, P1)
        rr = _rectified(uvr_n, rec.K_right, rec.dist_right, R2, P2)
        # the front end: every keyframe defines new landmarks in stereo (id: point + n_points * keyframe),
        # tracked as monocular observations into the next ``track_kf`` keyframes
        stereo_px = np.column_stack([rl[:, 0], rr[:, 0], rl[:, 1]])
        right_rows[k] = rr[:, 1].copy()
        ids = idx + n_points * k
        mono_rows = []
        for j in range(1, track_kf + 1):
            if k - j >= 0:
                was = np.isin(idx, visible[k - j])
                mono_rows.append(np.column_stack([(idx[was] + n_points * (k - j)).astype(float), rl[was]]))
        mono = np.vstack(mono_rows) if mono_rows else np.zeros((0, 3))
        visible.append(idx)
        keyframes.append(
            Keyframe(
                id=k,
                timestamp_ns=k * 10**8,
                world_from_kf=T.copy(),
                landmark_ids=ids.astype(np.int64),
                points_in_kf=p_l[idx],
                stereo_px=stereo_px,
                mono_obs=mono,
                rect_from_cam=make_pose(R1, np.zeros(3)),
            )
        )
    return Scene(true, rec, world_from_kf, pts, keyframes, R1, R2, P1, P2, right_rows)
