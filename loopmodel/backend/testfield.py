"""An OLTRIS-size synthetic test (seed 000): a 3-D test field seen by a camera along two strips.

World frame: x right along the field, y down, z away from the camera path (metres). The test
field is a wall (z = 0) about 4 m x 2.4 m with points on it and on structures up to 0.8 m in
front of it; the camera moves along an upper and a lower horizontal strip about 4.5 m in front,
looking at the field. Defaults give 166 points, 88 frames and 79–146 visible points per image.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from loopmodel.geometry.camera import CentralCamera
from loopmodel.geometry.se3 import Y_DOWN_UP, look_at, so3_exp

if TYPE_CHECKING:
    from loopmodel.backend.givens_bundle import GivensScreen

F64 = NDArray[np.float64]


@dataclass
class TestField:
    """Ground truth and measurements of the synthetic sequence."""

    camera: CentralCamera
    width_px: int
    height_px: int
    points_world: F64  # P x 3
    control: NDArray[np.int64]  # indices of the control points
    world_from_cam: list[F64]  # true poses, 4x4
    observations: list[tuple[NDArray[np.int64], F64]]  # per frame: point ids, N x 2 pixels
    blunder: list[NDArray[np.bool_]]  # per frame: which observations carry a blunder
    sigma_px: float


def make_testfield(
    n_frames: int = 88,
    n_points: int = 166,
    sigma_px: float = 0.5,
    blunder_fraction: float = 0.0,
    blunder_sigmas: tuple[float, float] = (6.0, 12.0),
    seed: int = 0,
) -> TestField:
    """Generate the two-strip test-field sequence (noise σ in pixels, blunders in σ units)."""
    rng = np.random.default_rng(seed)
    cam = CentralCamera(px=950.0, py=950.0, u0=360.0, v0=288.0)
    W, H = 720, 576
    pts = np.column_stack([rng.uniform(0.0, 4.0, n_points), rng.uniform(0.0, 2.4, n_points), np.zeros(n_points)])
    front = rng.random(n_points) < 0.3
    pts[front, 2] = -rng.uniform(0.1, 0.8, int(front.sum()))
    # control points: four near the corners and one near the centre, on the wall
    targets = np.array([[0.3, 0.3], [3.7, 0.3], [0.3, 2.1], [3.7, 2.1], [2.0, 1.2]])
    control: list[int] = []
    for t in targets:
        d = np.linalg.norm(pts[:, :2] - t, axis=1) + 10.0 * front
        i = int(np.argmin(d + 1e3 * np.isin(np.arange(n_points), control)))
        pts[i, 2] = 0.0
        control.append(i)
    n_upper = n_frames // 2
    poses: list[F64] = []
    for f in range(n_frames):
        upper = f < n_upper
        k = f if upper else f - n_upper
        n_strip = n_upper if upper else n_frames - n_upper
        s = k / max(n_strip - 1, 1)
        x = 0.2 + 3.6 * s if upper else 3.8 - 3.6 * s  # the lower strip runs back
        y = 0.6 if upper else 1.8
        C = np.array([x, y, -4.3]) + rng.normal(0.0, 0.03, 3)
        target = np.array([2.0 + 0.7 * (x - 2.0), 1.2, 0.0])
        T = look_at(C, target, Y_DOWN_UP)
        T[:3, :3] = T[:3, :3] @ so3_exp(rng.normal(0.0, 0.01, 3))
        poses.append(T)
    obs: list[tuple[NDArray[np.int64], F64]] = []
    blunders: list[NDArray[np.bool_]] = []
    lo, hi = blunder_sigmas
    for T in poses:
        p_cam = (pts - T[:3, 3]) @ T[:3, :3]
        uv = cam.project(p_cam)
        vis = (p_cam[:, 2] > 0.1) & (uv[:, 0] >= 0) & (uv[:, 0] < W) & (uv[:, 1] >= 0) & (uv[:, 1] < H)
        ids = np.flatnonzero(vis)
        meas = uv[ids] + rng.normal(0.0, sigma_px, (ids.size, 2))
        bl = rng.random(ids.size) < blunder_fraction
        for kb in np.flatnonzero(bl).tolist():
            coord = int(rng.integers(2))
            meas[kb, coord] += rng.choice([-1.0, 1.0]) * rng.uniform(lo, hi) * sigma_px
        obs.append((ids, meas))
        blunders.append(bl)
    return TestField(cam, W, H, pts, np.array(control), poses, obs, blunders, sigma_px)


@dataclass
class ScreeningOutcome:
    """What the Givens screen did over a test field.

    The image points (frame, point id) that carried an injected blunder, and those the screen
    rejected (at once or later).
    """

    blunders: set[tuple[int, int]]
    flagged: set[tuple[int, int]]

    @property
    def caught(self) -> int:
        """Injected blunders the screen rejected."""
        return len(self.blunders & self.flagged)

    @property
    def false_alarms(self) -> int:
        """Good image points the screen rejected."""
        return len(self.flagged - self.blunders)


def screen_testfield(
    tf: TestField, screen: GivensScreen, progress: Callable[[int], None] | None = None
) -> ScreeningOutcome:
    """Feed the test field frame by frame to ``screen`` and score its rejections.

    Control points get a 0.1 mm prior; rejections are scored against the injected blunders.
    """
    ctrl = set(tf.control.tolist())
    flagged: set[tuple[int, int]] = set()
    truth: set[tuple[int, int]] = set()
    for f, (ids, uv) in enumerate(tf.observations):
        for i in ids.tolist():
            if i not in screen.bundle.points:
                screen.add_point(i, tf.points_world[i], 1e-4 if i in ctrl else None)
        mask = screen.screen(f, tf.world_from_cam[f], ids.tolist(), uv, first_frame=(f == 0))
        truth |= {(f, i) for i, b in zip(ids.tolist(), tf.blunder[f], strict=True) if b}
        flagged |= {(f, i) for i, ok in zip(ids.tolist(), mask, strict=True) if not ok}
        flagged |= {(int(a), int(b)) for a, b in screen.late_rejections()}  # type: ignore[call-overload]
        if progress is not None:
            progress(f + 1)
    return ScreeningOutcome(truth, flagged)
