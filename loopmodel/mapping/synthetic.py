"""Small synthetic laser scans by ray casting open3d primitives (tests and benchmarks of the
mapping stage; the full simulator lives in ``loopmodel.sim``).

World frame: y down (like the camera); the object sits around the origin. The camera orbits
the object looking at it; the light plane is fixed in the camera frame, its laser source
offset along the camera x axis, so stripes are roughly vertical in the image.
"""

from __future__ import annotations

import numpy as np
import open3d as o3d
from numpy.typing import NDArray

from loopmodel.geometry.se3 import Y_DOWN_UP, invert_pose, look_at
from loopmodel.mapping.extraction import LightPlane
from loopmodel.types import StripeProfile, Trajectory

F64 = NDArray[np.float64]


def orbit_pose(t_s: float, radius_m: float, rate_rad_s: float, height_m: float) -> F64:
    """Pose on a horizontal circle around the origin at angular rate ``rate_rad_s``."""
    a = rate_rad_s * t_s
    eye = np.array([radius_m * np.sin(a), height_m, -radius_m * np.cos(a)])
    return look_at(eye, np.zeros(3), Y_DOWN_UP)


def default_light_plane(baseline_m: float = 0.06, cross_depth_m: float = 0.3) -> LightPlane:
    """Plane through the laser at (baseline, 0, 0) (camera frame) containing the camera y
    direction and crossing the optical axis at ``cross_depth_m``."""
    n = np.array([cross_depth_m, 0.0, baseline_m])
    return LightPlane.from_point_normal([baseline_m, 0.0, 0.0], n)


def laser_origin(plane_baseline_m: float = 0.06) -> F64:
    """Laser source position in the camera frame used by :func:`default_light_plane`."""
    return np.array([plane_baseline_m, 0.0, 0.0])


def raycasting_scene(mesh: o3d.geometry.TriangleMesh) -> o3d.t.geometry.RaycastingScene:
    """open3d ray-casting scene of one legacy triangle mesh."""
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(mesh))
    return scene


def cast_stripe(
    scene: o3d.t.geometry.RaycastingScene,
    world_from_cam: F64,
    timestamp_ns: int,
    rays: int = 400,
    fan_deg: float = 30.0,
    baseline_m: float = 0.06,
    cross_depth_m: float = 0.3,
) -> StripeProfile:
    """One noiseless profile.

    Laser rays fanned in the light plane, kept where they hit the scene and the camera sees the hit
    point. Points in the camera frame (metres).
    """
    o_cam = laser_origin(baseline_m)
    e1 = np.array([0.0, 1.0, 0.0])
    e2 = np.array([-baseline_m, 0.0, cross_depth_m])
    e2 /= np.linalg.norm(e2)
    phi = np.deg2rad(np.linspace(-fan_deg, fan_deg, rays))
    d_cam = np.cos(phi)[:, None] * e2 + np.sin(phi)[:, None] * e1
    R, t = world_from_cam[:3, :3], world_from_cam[:3, 3]
    o_w = R @ o_cam + t
    d_w = d_cam @ R.T
    r = np.hstack([np.repeat(o_w[None], rays, 0), d_w]).astype(np.float32)
    hit = scene.cast_rays(o3d.core.Tensor.from_numpy(r))["t_hit"].numpy().astype(np.float64)
    ok = np.isfinite(hit)
    p_w = o_w + d_w[ok] * hit[ok, None]
    # visibility from the camera centre
    v = p_w - t
    dist = np.linalg.norm(v, axis=1)
    vr = np.hstack([np.repeat(t[None], v.shape[0], 0), v / dist[:, None]]).astype(np.float32)
    seen = scene.cast_rays(o3d.core.Tensor.from_numpy(vr))["t_hit"].numpy() >= dist - 1e-5 * np.maximum(dist, 1)
    p_w = p_w[seen]
    cam_from_world = invert_pose(world_from_cam)
    p_c = p_w @ cam_from_world[:3, :3].T + cam_from_world[:3, 3]
    return StripeProfile(int(timestamp_ns), p_c)


def orbit_scan(
    mesh: o3d.geometry.TriangleMesh,
    frames: int = 120,
    stripes_per_frame: int = 2,
    rate_hz: float = 30.0,
    radius_m: float = 0.3,
    height_m: float = -0.08,
    turns: float = 1.0,
    rays: int = 400,
) -> tuple[Trajectory, list[StripeProfile]]:
    """Ground-truth frame poses of an orbit and noiseless stripes taken at frame times and
    between them (``stripes_per_frame`` per frame interval), posed exactly on the orbit."""
    scene = raycasting_scene(mesh)
    duration = (frames - 1) / rate_hz
    rate = 2 * np.pi * turns / duration
    t_ns = np.round(np.arange(frames) / rate_hz * 1e9).astype(np.int64)
    poses = np.stack([orbit_pose(t * 1e-9, radius_m, rate, height_m) for t in t_ns])
    stripes = []
    for i in range(frames - 1):
        for j in range(stripes_per_frame):
            ts = int(t_ns[i] + (t_ns[i + 1] - t_ns[i]) * j // stripes_per_frame)
            T = orbit_pose(ts * 1e-9, radius_m, rate, height_m)
            st = cast_stripe(scene, T, ts, rays)
            if st.points_in_cam.shape[0]:
                stripes.append(st)
    return Trajectory(t_ns, poses), stripes
