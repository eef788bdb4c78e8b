"""Laser-stripe profiler: a fan of rays in a light plane fixed in the left-camera frame.

The rays are intersected with the scene by ray casting. A profile keeps the points the left camera
sees (in front, inside the image, not occluded), in the left-camera frame (metres).

The realistic world (issue 17) only *images* the stripe (:func:`realistic_laser_image`): the
line's brightness follows the surface (albedo x cos(incidence) x (0.5 m / range)^2, so dark
or grazing surfaces drop out below the extractor's contrast), it saturates on bright
surfaces (``laser_peak`` 420 grey levels on white at 0.5 m: clipped at 255, with blooming
into the neighbours), it carries laser speckle (multiplicative, gamma-distributed, contrast
0.35 per pixel: a red laser imaged at f/2.8 has speckle grains of about lambda / NA =
0.65 um / 0.18 = 3.6 um, finer than a 6 um pixel, so a pixel averages a few grains and the
fully developed contrast of 1 drops to about 1 / sqrt(8); assumed, not measured), photon
shot noise, and spurious reflections (inter-reflections: in 8 % of the frames a copy of part
of the line, 6-40 px aside, at 30-90 % of its brightness). The light plane the scene sees is
the configured one rotated by ``laser_plane_rot_err_deg`` (0.02 deg) and shifted by
``laser_plane_offset_err_m`` (0.1 mm): a light-plane calibration of a few hundredths of a
degree, as a good plane fit on a calibration target gives (with the 12 cm laser-camera
baseline at 0.6 m, 0.02 deg moves the triangulated surface by about 1 mm). The laser is exposed
``laser_time_offset_s`` (1 ms) after the camera's mid-exposure (trigger latency): the stripe
is cast from the pose at that time but stamped with the frame's time.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from loopmodel.geometry.camera import CentralCamera
from loopmodel.sim.render import Raycaster

F64 = NDArray[np.float64]


@dataclass(frozen=True)
class LaserPlane:
    """Light plane through ``origin_in_cam_m`` with unit ``normal_in_cam`` (left-camera frame).

    The fan spans ``fan_deg`` around the plane direction closest to the optical axis.
    """

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
        """Validated plane; raises ValueError for a zero normal.

        Points farther than ``max_range_m`` from the camera are outside the profiler's measuring
        range.
        """
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
    """Noiseless stripe of one frame, keeping points visible in the left image.

    Returns (N x 3 points in the left-camera frame, N x 3 unit laser ray directions in that frame).
    """
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
    """Segment end points (a, b) of a polyline cut so that no segment is longer than ``step_px``.

    The cut points lie on the original straight segments.
    """
    a, b = uv_px[:-1], uv_px[1:]
    pieces = np.maximum(np.ceil(np.linalg.norm(b - a, axis=1) / step_px), 1).astype(int)
    seg = np.repeat(np.arange(a.shape[0]), pieces)
    k = np.arange(seg.size) - np.repeat(np.cumsum(pieces) - pieces, pieces)
    f0 = (k / pieces[seg])[:, None]
    f1 = ((k + 1) / pieces[seg])[:, None]
    d = b[seg] - a[seg]
    return a[seg] + f0 * d, a[seg] + f1 * d


def stripe_reflectance(
    caster: Raycaster,
    plane: LaserPlane,
    world_from_cam: F64,
    points_in_cam: F64,
    world_from_occluder: F64 | None = None,
) -> F64:
    """Relative line brightness at N stripe points.

    Albedo x |cos(incidence)| x (0.5 m / distance from the laser)^2 (1 for a white surface at 0.5 m,
    normal incidence).
    """
    if points_in_cam.shape[0] == 0:
        return np.zeros(0)
    R, t = world_from_cam[:3, :3], world_from_cam[:3, 3]
    d = points_in_cam - plane.origin_in_cam_m
    dist = np.linalg.norm(d, axis=1)
    d = d / np.maximum(dist, 1e-12)[:, None]
    origin_w = R @ plane.origin_in_cam_m + t
    hits = caster.cast_points(origin_w, d @ R.T, world_from_occluder)
    pts_w = (origin_w[:, None] + (d @ R.T).T * hits.range_m.astype(float)).astype(np.float32)
    albedo = caster.albedo(pts_w, hits.normal, hits.primitive).astype(float)
    cos_i = np.abs(np.sum(hits.normal.T.astype(float) * (d @ R.T), axis=1))
    return albedo * cos_i * (0.5 / np.maximum(dist, 1e-3)) ** 2


def _line_intensity(shape: tuple[int, int], uv: F64, points_in_cam: F64, peaks: F64, sigma_px: float) -> F64:
    """H x W intensity of a polyline through pixels ``uv``.

    Broken where neighbouring 3-D points are more than 5 mm apart: ``peak · exp(-d² / 2σ²)`` for the
    distance ``d`` (px) of each pixel centre to the nearest segment, ``peak`` that of the segment's
    start point.
    """
    h, w = shape
    line = np.zeros(h * w)
    if uv.shape[0] < 2:
        return line.reshape(h, w)
    gaps = np.linalg.norm(np.diff(points_in_cam, axis=0), axis=1) > 0.005
    keep = ~gaps & np.all(np.isfinite(uv[:-1]) & np.isfinite(uv[1:]), axis=1)
    starts, ends, pk = [], [], []
    for seg in np.split(np.arange(uv.shape[0]), np.flatnonzero(~keep) + 1):
        if seg.size >= 2:
            a, b = _densify_px(uv[seg], 0.5)
            starts.append(a)
            ends.append(b)
            # the peak of each piece: interpolated along its original segment
            idx = np.interp(np.linspace(0, seg.size - 1, a.shape[0]), np.arange(seg.size), peaks[seg])
            pk.append(idx)
    if not starts:
        return line.reshape(h, w)
    a, b, p = np.concatenate(starts), np.concatenate(ends), np.concatenate(pk)
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
    val = p[:, None, None] * np.exp(-0.5 * dist2 / sigma_px**2)
    inside = (x >= 0) & (x < w) & (y >= 0) & (y < h)
    np.maximum.at(line, (y[inside] * w + x[inside]), val[inside])
    return line.reshape(h, w)


def realistic_laser_image(
    background: NDArray[np.uint8],
    uv_px: F64,
    points_in_cam: F64,
    reflectance: F64,
    rng: np.random.Generator,
    peak: float = 420.0,
    sigma_px: float = 1.2,
    speckle_contrast: float = 0.35,
    spurious_rate: float = 0.08,
    e_per_grey: float = 42.0,
) -> NDArray[np.uint8]:
    """Laser-line image of the realistic world over a dimmed ``background``.

    See the module docstring: the line through the true (distorted) pixels ``uv_px`` of the stripe
    points, peak ``peak x reflectance``, a spurious reflection in ``spurious_rate`` of the frames,
    speckle, shot noise (``e_per_grey`` electrons per grey level), saturation and blooming.
    """
    h, w = background.shape[:2]
    bg = background.astype(np.float64)
    if bg.ndim == 3:
        bg = bg.mean(axis=2)
    line = _line_intensity((h, w), uv_px, points_in_cam, peak * reflectance, sigma_px)
    n = uv_px.shape[0]
    if n >= 8 and rng.random() < spurious_rate:
        m = int(rng.integers(max(n // 10, 2), max(n // 3, 3)))
        i0 = int(rng.integers(0, n - m))
        seg = slice(i0, i0 + m)
        along = uv_px[min(i0 + m, n - 1)] - uv_px[i0]
        perp = np.array([-along[1], along[0]]) / max(float(np.linalg.norm(along)), 1e-9)
        shift = perp * rng.uniform(6.0, 40.0) * rng.choice([-1.0, 1.0])
        ghost = _line_intensity(
            (h, w), uv_px[seg] + shift, points_in_cam[seg], peak * reflectance[seg] * rng.uniform(0.3, 0.9), sigma_px
        )
        np.maximum(line, ghost, out=line)
    lit = np.flatnonzero(line > 0.5)  # (the same values as with the mask; in place: gen20, issue 32)
    if speckle_contrast > 0 and lit.size:
        k = 1.0 / speckle_contrast**2
        line.ravel()[lit] *= rng.gamma(k, 1.0 / k, size=lit.size)
    if lit.size:
        on = line.ravel()[lit]
        line.ravel()[lit] += np.sqrt(on / e_per_grey) * rng.standard_normal(lit.size)
    img = bg  # a copy of the background
    img *= 0.15
    img += np.maximum(line, 0.0, out=line)
    if img.max() > 255.0:  # blooming: charge above full well spills into the neighbours
        excess = np.maximum(img - 255.0, 0.0)
        img += 0.5 * cv2.GaussianBlur(excess, (0, 0), 1.5)
    img += 0.5
    return np.clip(img, 0, 255, out=img).astype(np.uint8)


def draw_laser_image(
    background: NDArray[np.uint8],
    points_in_cam: F64,
    camera: CentralCamera,
    peak: float = 230.0,
    sigma_px: float = 1.0,
) -> NDArray[np.uint8]:
    """Image of the laser line over a dimmed ``background``.

    The stripe points are projected into the left image and joined into a polyline (broken where
    neighbours are more than 5 mm apart); every pixel centre gets ``peak · exp(-d² / 2σ²)`` for its
    distance ``d`` (px) to the polyline, the Gaussian cross-section of a focused laser line of
    standard deviation ``sigma_px``. The intensity ridge therefore runs exactly along the projected
    profile.
    """
    img = background.astype(np.float32) * 0.15
    h, w = background.shape[:2]
    if points_in_cam.shape[0] < 2:
        return np.clip(img, 0, 255).astype(np.uint8)
    uv = camera.project(points_in_cam)
    line = _line_intensity((h, w), uv, points_in_cam, np.full(uv.shape[0], peak), sigma_px).astype(np.float32)
    if img.ndim == 3:
        line = line[:, :, None]
    return np.clip(img + line, 0, 255).astype(np.uint8)
