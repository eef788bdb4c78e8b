"""Laser-stripe profiler: a fan of rays in a light plane fixed in the left-camera frame,
intersected with the scene by ray casting. A profile keeps the points the left camera sees
(in front, inside the image, not occluded), in the left-camera frame (metres)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from loopmodel.geometry.camera import CentralCamera
from loopmodel.sim.render import Raycaster

F64 = NDArray[np.float64]


@dataclass(frozen=True)
class LaserPlane:
    """Light plane through ``origin_in_cam_m`` with unit ``normal_in_cam`` (left-camera
    frame); the fan spans ``fan_deg`` around the plane direction closest to the optical axis."""

    origin_in_cam_m: F64
    normal_in_cam: F64
    fan_deg: float = 70.0
    rays: int = 640
    max_range_m: float = np.inf

    @classmethod
    def create(
        cls,
        origin: list[float] | F64,
        normal: list[float] | F64,
        fan_deg: float,
        rays: int,
        max_range_m: float = np.inf,
    ) -> LaserPlane:
        """Validated plane; raises ValueError for a zero normal. Points farther than
        ``max_range_m`` from the camera are outside the profiler's measuring range."""
        n = np.asarray(normal, float).reshape(3)
        norm = np.linalg.norm(n)
        if not np.isfinite(norm) or norm < 1e-9:
            raise ValueError("laser plane normal must be a non-zero vector")
        return cls(np.asarray(origin, float).reshape(3), n / norm, float(fan_deg), int(rays), float(max_range_m))

    def directions_in_cam(self) -> F64:
        """N x 3 unit ray directions of the fan (left-camera frame)."""
        n = self.normal_in_cam
        fwd = np.array([0.0, 0.0, 1.0]) - n[2] * n  # optical axis projected into the plane
        if np.linalg.norm(fwd) < 1e-6:  # plane perpendicular to the optical axis
            fwd = np.array([1.0, 0.0, 0.0]) - n[0] * n
        fwd /= np.linalg.norm(fwd)
        side = np.cross(n, fwd)
        a = np.radians(np.linspace(-self.fan_deg / 2, self.fan_deg / 2, self.rays))
        return np.cos(a)[:, None] * fwd + np.sin(a)[:, None] * side


def stripe_profile(
    caster: Raycaster,
    plane: LaserPlane,
    camera: CentralCamera,
    image_size: tuple[int, int],
    world_from_cam: F64,
    world_from_occluder: F64 | None = None,
) -> tuple[F64, F64]:
    """Noiseless stripe of one frame: (N x 3 points in the left-camera frame, N x 3 unit laser
    ray directions in that frame), keeping points visible in the left image."""
    R, t = world_from_cam[:3, :3], world_from_cam[:3, 3]
    dirs_c = plane.directions_in_cam()
    origin_w = R @ plane.origin_in_cam_m + t
    rng_t = caster.cast_points(origin_w, dirs_c @ R.T, world_from_occluder).range_m
    hit = np.isfinite(rng_t)
    # float64 intersection on the ray (open3d works in float32)
    p_cam = plane.origin_in_cam_m + dirs_c * rng_t.astype(float)[:, None]
    p_cam, dirs_c = p_cam[hit], dirs_c[hit]
    if p_cam.shape[0] == 0:
        return p_cam, dirs_c
    # visible from the left camera: in front, in the image, nothing closer along the sight line
    ok = camera.in_front(p_cam)
    uv = camera.project(np.where(ok[:, None], p_cam, [0.0, 0.0, 1.0]))
    w, h = image_size
    ok &= (uv[:, 0] >= -0.5) & (uv[:, 0] <= w - 0.5) & (uv[:, 1] >= -0.5) & (uv[:, 1] <= h - 0.5)
    dist = np.linalg.norm(p_cam, axis=1)
    ok &= dist <= plane.max_range_m
    sight = p_cam / np.maximum(dist, 1e-12)[:, None]
    cam_t = caster.cast_points(t, sight @ R.T, world_from_occluder).range_m
    ok &= cam_t.astype(float) > dist - np.maximum(1e-4, 1e-3 * dist)
    return p_cam[ok], dirs_c[ok]


def _densify_px(uv_px: F64, step_px: float) -> tuple[F64, F64]:
    """Segment end points (a, b) of a polyline cut so that no segment is longer than
    ``step_px``; the cut points lie on the original straight segments."""
    a, b = uv_px[:-1], uv_px[1:]
    pieces = np.maximum(np.ceil(np.linalg.norm(b - a, axis=1) / step_px), 1).astype(int)
    seg = np.repeat(np.arange(a.shape[0]), pieces)
    k = np.arange(seg.size) - np.repeat(np.cumsum(pieces) - pieces, pieces)
    f0 = (k / pieces[seg])[:, None]
    f1 = ((k + 1) / pieces[seg])[:, None]
    d = b[seg] - a[seg]
    return a[seg] + f0 * d, a[seg] + f1 * d


def draw_laser_image(
    background: NDArray[np.uint8],
    points_in_cam: F64,
    camera: CentralCamera,
    peak: float = 230.0,
    sigma_px: float = 1.0,
) -> NDArray[np.uint8]:
    """Image of the laser line over a dimmed ``background``: the stripe points projected into
    the left image and joined into a polyline (broken where neighbours are more than 5 mm
    apart); every pixel centre gets ``peak · exp(-d² / 2σ²)`` for its distance ``d`` (px) to
    the polyline, the Gaussian cross-section of a focused laser line of standard deviation
    ``sigma_px``. The intensity ridge therefore runs exactly along the projected profile."""
    img = background.astype(np.float32) * 0.15
    h, w = background.shape[:2]
    if points_in_cam.shape[0] < 2:
        return np.clip(img, 0, 255).astype(np.uint8)
    uv = camera.project(points_in_cam)
    gaps = np.linalg.norm(np.diff(points_in_cam, axis=0), axis=1) > 0.005
    keep = ~gaps & np.all(np.isfinite(uv[:-1]) & np.isfinite(uv[1:]), axis=1)
    starts, ends = [], []
    for seg in np.split(np.arange(uv.shape[0]), np.flatnonzero(~keep) + 1):
        if seg.size >= 2:
            a, b = _densify_px(uv[seg], 0.5)
            starts.append(a)
            ends.append(b)
    if not starts:
        return np.clip(img, 0, 255).astype(np.uint8)
    a, b = np.concatenate(starts), np.concatenate(ends)
    # every segment is at most 0.5 px long: a fixed window around its start covers every pixel
    # within 4 sigma of it
    reach = int(np.ceil(4.0 * sigma_px)) + 1
    offs = np.arange(-reach, reach + 1)
    x = np.floor(a[:, 0]).astype(int)[:, None, None] + offs[None, None, :]
    y = np.floor(a[:, 1]).astype(int)[:, None, None] + offs[None, :, None]
    x, y = np.broadcast_arrays(x, y)
    d = b - a
    ax, ay = a[:, 0, None, None], a[:, 1, None, None]
    dx, dy = d[:, 0, None, None], d[:, 1, None, None]
    s = np.clip(((x - ax) * dx + (y - ay) * dy) / np.maximum(dx * dx + dy * dy, 1e-12), 0.0, 1.0)
    dist2 = (x - ax - s * dx) ** 2 + (y - ay - s * dy) ** 2
    inside = (x >= 0) & (x < w) & (y >= 0) & (y < h)
    best = np.full(h * w, np.inf)
    np.minimum.at(best, (y[inside] * w + x[inside]), dist2[inside])
    line = (peak * np.exp(-0.5 * best / sigma_px**2)).reshape(h, w).astype(np.float32)
    if img.ndim == 3:
        line = line[:, :, None]
    return np.clip(img + line, 0, 255).astype(np.uint8)
