"""Tiny piecewise-planar textured scene rendered by homographies (test support).

Planes are textured rectangles; a camera image is the painter's composition of the
planes' homography warps (far to near). Ground-truth depth comes from ray casting.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from loopmodel.geometry.se3 import invert_pose, make_pose, so3_exp
from loopmodel.types import StereoCalibration, StereoFrame


def random_texture(rng: np.random.Generator, h: int, w: int) -> np.ndarray:
    """Smooth random texture (uint8) with corners at several scales."""
    acc = np.zeros((h, w), np.float32)
    for cell, amp in ((32, 1.0), (8, 0.8), (3, 0.5)):
        small = rng.random((max(2, h // cell), max(2, w // cell))).astype(np.float32)
        acc += amp * cv2.resize(small, (w, h), interpolation=cv2.INTER_CUBIC)
    acc = cv2.GaussianBlur(acc, (0, 0), 0.8)
    acc -= acc.min()
    return np.clip(255 * acc / max(float(acc.max()), 1e-6), 0, 255).astype(np.uint8)


@dataclass
class Plane:
    """Rectangle ``origin + s*axis_s + t*axis_t`` in the world frame, carrying ``texture``.

    s, t in texels, metres per texel in the axes.
    """

    origin: np.ndarray
    axis_s: np.ndarray
    axis_t: np.ndarray
    texture: np.ndarray

    def homography(self, K: np.ndarray, cam_from_world: np.ndarray) -> np.ndarray:
        R, t = cam_from_world[:3, :3], cam_from_world[:3, 3]
        return K @ np.column_stack([R @ self.axis_s, R @ self.axis_t, R @ self.origin + t])


def default_scene(rng: np.random.Generator) -> list[Plane]:
    """A wall 9 m away and a panel 4.5 m away, both textured, facing the camera at z=0."""
    wall = Plane(
        np.array([-12.0, -5.0, 9.0]),
        np.array([0.02, 0, 0]),
        np.array([0, 0.02, 0]),
        random_texture(rng, 500, 1200),
    )
    panel = Plane(
        np.array([-1.5, -1.2, 4.5]),
        np.array([0.01, 0, 0.003]),
        np.array([0, 0.01, 0]),
        random_texture(rng, 240, 300),
    )
    return [wall, panel]


def render(
    planes: list[Plane], K: np.ndarray, cam_from_world: np.ndarray, size: tuple[int, int]
) -> np.ndarray:
    """Grey image (uint8) of the planes; farther planes first."""
    w, h = size
    img = np.full((h, w), 0, np.uint8)
    depth = [float((cam_from_world @ np.append(p.origin, 1.0))[2]) for p in planes]
    for i in np.argsort(depth)[::-1]:
        p = planes[i]
        H = p.homography(K, cam_from_world)
        warped = cv2.warpPerspective(p.texture, H, (w, h), flags=cv2.INTER_LINEAR)
        mask = cv2.warpPerspective(
            np.full(p.texture.shape, 255, np.uint8), H, (w, h), flags=cv2.INTER_NEAREST
        )
        img[mask > 0] = warped[mask > 0]
    return img


def depth_at(
    planes: list[Plane], K: np.ndarray, cam_from_world: np.ndarray, uv: np.ndarray
) -> np.ndarray:
    """Ground-truth Z (camera frame, metres) of the nearest plane hit at each pixel (nan: none)."""
    world_from_cam = invert_pose(cam_from_world)
    rays_cam = np.column_stack([uv, np.ones(len(uv))]) @ np.linalg.inv(K).T  # z = 1
    rays = rays_cam @ world_from_cam[:3, :3].T
    c = world_from_cam[:3, 3]
    best = np.full(len(uv), np.inf)
    for p in planes:
        n = np.cross(p.axis_s, p.axis_t)
        denom = rays @ n
        lam = ((p.origin - c) @ n) / np.where(np.abs(denom) > 1e-12, denom, np.nan)
        X = c + lam[:, None] * rays
        # texel coordinates of the hit
        A = np.column_stack([p.axis_s, p.axis_t])
        st, *_ = np.linalg.lstsq(A, (X - p.origin).T, rcond=None)
        hh, ww = p.texture.shape
        inside = (st[0] >= 0) & (st[0] <= ww - 1) & (st[1] >= 0) & (st[1] <= hh - 1) & (lam > 0)
        best = np.where(inside & (lam < best), lam, best)
    return np.where(np.isfinite(best), best, np.nan)


def stereo_rig(
    f: float = 450.0, size: tuple[int, int] = (640, 360), baseline_m: float = 0.3
) -> StereoCalibration:
    """Rectified pinhole stereo calibration."""
    K = np.array([[f, 0, size[0] / 2 - 0.5], [0, f, size[1] / 2 - 0.5], [0, 0, 1.0]])
    right_from_left = make_pose(np.eye(3), [-baseline_m, 0, 0])
    return StereoCalibration(K, K, right_from_left, size)


def stereo_frames(planes: list[Plane], cal: StereoCalibration, poses: np.ndarray) -> list[StereoFrame]:
    """The rectified stereo pair rendered at each (N, 4, 4) world_from_cam pose, 0.1 s apart."""
    frames = []
    for i, world_from_cam in enumerate(poses):
        cam_from_world = invert_pose(world_from_cam)
        left = render(planes, cal.K_left, cam_from_world, cal.image_size)
        right = render(planes, cal.K_right, cal.right_from_left @ cam_from_world, cal.image_size)
        frames.append(StereoFrame(i * 100_000_000, left, right, i))
    return frames


def trajectory(n: int, step_m: float = 0.06) -> np.ndarray:
    """(n, 4, 4) world_from_cam poses: sideways and forward drift with a slow yaw."""
    out = []
    for i in range(n):
        R = so3_exp([0.0, np.radians(0.4) * i, np.radians(0.1) * i])
        out.append(make_pose(R, [step_m * i, 0.01 * np.sin(i / 3), 0.5 * step_m * i]))
    return np.array(out)


def write_kitti_folder(folder: Path, n: int, rng: np.random.Generator, cx_right_error_px: float = 0.0) -> np.ndarray:
    """A rendered rectified stereo sequence in KITTI layout with ground truth poses.

    ``cx_right_error_px``: the right images rendered with the right camera's cx this far off what
    ``calib.txt`` says (a recorded calibration with an error, issue 31).
    """
    planes = default_scene(rng)
    cal = stereo_rig()
    poses = trajectory(n)
    poses = invert_pose(poses[0]) @ poses
    K_right = cal.K_right.copy()
    K_right[0, 2] += cx_right_error_px
    (folder / "image_0").mkdir(parents=True)
    (folder / "image_1").mkdir()
    for i, world_from_cam in enumerate(poses):
        cam_from_world = invert_pose(world_from_cam)
        cv2.imwrite(
            str(folder / "image_0" / f"{i:06d}.png"),
            render(planes, cal.K_left, cam_from_world, cal.image_size),
        )
        cv2.imwrite(
            str(folder / "image_1" / f"{i:06d}.png"),
            render(planes, K_right, cal.right_from_left @ cam_from_world, cal.image_size),
        )
    P0 = np.hstack([cal.K_left, np.zeros((3, 1))])
    P1 = P0.copy()
    P1[0, 3] = -cal.K_left[0, 0] * cal.baseline_m
    row = [" ".join(repr(float(x)) for x in P.ravel()) for P in (P0, P1)]
    (folder / "calib.txt").write_text(f"P0: {row[0]}\nP1: {row[1]}\n")
    (folder / "poses.txt").write_text(
        "".join(" ".join(repr(float(x)) for x in T[:3, :].ravel()) + "\n" for T in poses)
    )
    return poses
