"""CPU ray-casting renderer (open3d ``RaycastingScene``) of a :class:`~loopmodel.sim.scene.Scene`.

Rays come from :meth:`CentralCamera.lift` of the pixel centres, so pinhole (xi = 0) and
unified-model omnidirectional (xi > 0) cameras render alike. Shading is Lambertian with a
point light and an ambient term; albedo is the scene's tri-planar procedural texture at the
3-D surface point. A rigid moving occluder (a hand-sized ellipsoid) can be added per view.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
import open3d as o3d
from numpy.typing import NDArray

from loopmodel.geometry.camera import CentralCamera
from loopmodel.geometry.se3 import invert_pose
from loopmodel.sim.scene import Scene

F32 = NDArray[np.float32]
F64 = NDArray[np.float64]

_AXES = ((1, 2), (0, 2), (0, 1))  # texture plane of each projection axis x, y, z
OCCLUDER_ALBEDO = 0.32
OCCLUDER_RADII_M = (0.035, 0.05, 0.025)


def pixel_rays(camera: CentralCamera, width: int, height: int) -> tuple[F32, NDArray[np.bool_]]:
    """Unit rays (H*W x 3, camera frame) through the pixel centres (pixel (u, v) has its centre
    at u, v) and which pixels have a valid ray (the unified model's image disc)."""
    u, v = np.meshgrid(np.arange(width, dtype=float), np.arange(height, dtype=float))
    uv = np.column_stack([u.ravel(), v.ravel()])
    x = (uv[:, 0] - camera.u0) / camera.px
    y = (uv[:, 1] - camera.v0) / camera.py
    valid = 1.0 + (1.0 - camera.xi**2) * (x * x + y * y) >= 0.0
    rays = camera.lift(uv)
    valid &= np.all(np.isfinite(rays), axis=1)
    rays[~valid] = (0.0, 0.0, 1.0)
    return rays.astype(np.float32), valid


@dataclass
class View:
    """One rendered view: ``radiance`` (H x W, albedo x shading, about 0..1), ``range_m``
    (distance along the ray, inf where nothing is hit), ``depth_m`` (camera z), ``primitive``
    (triangle id, -1 for a miss, ``-2`` for the occluder) and ``points_world`` (H x W x 3)."""

    radiance: F32
    range_m: F32
    depth_m: F32
    primitive: NDArray[np.int64]
    points_world: F32


class Raycaster:
    """Ray casting and shading of a scene; build once, render many views."""

    def __init__(self, scene: Scene) -> None:
        self.scene = scene
        self._rs = o3d.t.geometry.RaycastingScene()
        self._rs.add_triangles(
            o3d.core.Tensor(scene.vertices.astype(np.float32)),
            o3d.core.Tensor(scene.triangles.astype(np.uint32)),
        )
        cn = scene.corner_normals
        # per triangle: n0, n1 - n0, n2 - n0 (barycentric interpolation n0 + u dn1 + v dn2)
        self._tri_normals = np.concatenate(
            [cn[:, 0], cn[:, 1] - cn[:, 0], cn[:, 2] - cn[:, 0]], axis=1
        )
        self._tri_mat = scene.triangle_material.astype(np.int32)
        size = scene.textures[0].shape[0]
        self._tex_size = float(size)
        pad = [np.pad(t, ((0, 1), (0, 1)), mode="wrap") for t in scene.textures]
        self._atlas = np.ascontiguousarray(np.vstack(pad), dtype=np.float32)
        mats = scene.materials
        self._mat_scale = np.array([1.0 / m.texel_m for m in mats], np.float32)
        self._mat_gain = np.array([m.gain for m in mats], np.float32)
        self._mat_row = np.array([m.texture * (size + 1) for m in mats], np.float32)
        self._mat_off = scene.texture_offsets.astype(np.float32)
        # the occluder: an ellipsoid in its own frame, cast separately (it moves)
        occ = o3d.geometry.TriangleMesh.create_sphere(1.0, 24)
        ov = np.asarray(occ.vertices) * np.asarray(OCCLUDER_RADII_M)
        self._occ = o3d.t.geometry.RaycastingScene()
        self._occ.add_triangles(
            o3d.core.Tensor(ov.astype(np.float32)),
            o3d.core.Tensor(np.asarray(occ.triangles).astype(np.uint32)),
        )

    # -- ray casting
    def cast(
        self, origins_world: F64 | F32, dirs_world: F32, world_from_occluder: F64 | None = None
    ) -> tuple[F32, NDArray[np.int64], F32, F32]:
        """Nearest hits of rays (N x 3 origins or one origin, N x 3 unit directions, world):
        range (inf for a miss), triangle id (-1 miss, -2 occluder), barycentric (u, v) and
        the unit normal in the world frame facing the ray's origin."""
        n = dirs_world.shape[0]
        rays = np.empty((n, 6), np.float32)
        rays[:, :3] = origins_world
        rays[:, 3:] = dirs_world
        ans = self._rs.cast_rays(o3d.core.Tensor.from_numpy(rays))
        t = ans["t_hit"].numpy()
        pid_u = ans["primitive_ids"].numpy()
        uv = ans["primitive_uvs"].numpy()
        hit = np.isfinite(t)
        pid = np.where(hit, pid_u, 0).astype(np.int64)
        w = self._tri_normals[pid]
        nrm = w[:, 0:3] + uv[:, :1] * w[:, 3:6] + uv[:, 1:2] * w[:, 6:9]
        pid[~hit] = -1
        if world_from_occluder is not None:
            occ_from_world = invert_pose(world_from_occluder).astype(np.float32)
            R, tr = occ_from_world[:3, :3], occ_from_world[:3, 3]
            orays = np.empty_like(rays)
            orays[:, :3] = rays[:, :3] @ R.T + tr
            orays[:, 3:] = rays[:, 3:] @ R.T
            oans = self._occ.cast_rays(o3d.core.Tensor.from_numpy(orays))
            to = oans["t_hit"].numpy()
            closer = to < t
            if np.any(closer):
                t = np.where(closer, to, t)
                pid[closer] = -2
                on = oans["primitive_normals"].numpy()[closer] @ world_from_occluder[
                    :3, :3
                ].T.astype(np.float32)
                nrm[closer] = on
        nrm /= np.maximum(np.linalg.norm(nrm, axis=1, keepdims=True), 1e-12)
        flip = np.einsum("ij,ij->i", nrm, dirs_world) > 0
        nrm[flip] *= -1
        return t.astype(np.float32), pid, uv.astype(np.float32), nrm.astype(np.float32)

    # -- appearance
    def albedo(self, points_world: F32, normals_world: F32, primitive: NDArray[np.int64]) -> F32:
        """Surface albedo (about 0..1) at N surface points from the tri-planar texture of
        their triangles' materials (occluder: uniform)."""
        n = points_world.shape[0]
        tri = np.maximum(primitive, 0)
        mat = self._tri_mat[tri]
        scale = self._mat_scale[mat]
        row = self._mat_row[mat]
        w = normals_world.astype(np.float32) ** 2
        w *= w
        w /= np.maximum(w.sum(axis=1, keepdims=True), 1e-12)
        # remap wants 2-D maps with sides below 32767: lay the N samples out in rows
        cols = 1024
        rows_n = -(-n // cols)
        out = np.zeros(n, np.float32)
        size = self._tex_size
        for k, (a, b) in enumerate(_AXES):
            sel = w[:, k] > 1e-3
            if not np.any(sel):
                continue
            cu = np.mod(points_world[:, a] * scale + self._mat_off[mat, k, 0], size)
            cv = np.mod(points_world[:, b] * scale + self._mat_off[mat, k, 1], size) + row
            mu = np.zeros(rows_n * cols, np.float32)
            mv = np.zeros(rows_n * cols, np.float32)
            mu[:n] = cu
            mv[:n] = cv
            s = cv2.remap(
                self._atlas,
                mu.reshape(rows_n, cols),
                mv.reshape(rows_n, cols),
                cv2.INTER_LINEAR,
                borderMode=cv2.BORDER_REPLICATE,
            ).ravel()[:n]
            out += w[:, k] * s
        out *= self._mat_gain[mat]
        out[primitive == -2] = OCCLUDER_ALBEDO
        out[primitive == -1] = 0.0
        return out

    def render(
        self,
        camera_rays: F32,
        world_from_cam: F64,
        light_world_m: F64,
        ambient: float,
        world_from_occluder: F64 | None = None,
        valid: NDArray[np.bool_] | None = None,
        shape: tuple[int, int] | None = None,
    ) -> View:
        """Render the view of a camera at ``world_from_cam`` whose pixel rays (camera frame)
        are ``camera_rays``; ``shape`` = (H, W) of the image."""
        R = world_from_cam[:3, :3].astype(np.float32)
        o = world_from_cam[:3, 3].astype(np.float32)
        d = camera_rays @ R.T
        t, pid, _uv, nrm = self.cast(o, d, world_from_occluder)
        if valid is not None:
            t = np.where(valid, t, np.float32(np.inf))
            pid = np.where(valid, pid, -1)
        hit = np.isfinite(t)
        tt = np.where(hit, t, 0.0).astype(np.float32)
        p = o + d * tt[:, None]
        albedo = self.albedo(p, nrm, pid)
        L = np.asarray(light_world_m, np.float32) - p
        L /= np.maximum(np.linalg.norm(L, axis=1, keepdims=True), 1e-12)
        diffuse = np.maximum(np.einsum("ij,ij->i", nrm, L), 0.0)
        rad = albedo * (ambient + (1.0 - ambient) * diffuse)
        rad[~hit] = 0.0
        depth = np.where(hit, t * camera_rays[:, 2], np.inf).astype(np.float32)
        h, w = shape if shape is not None else (1, t.shape[0])
        return View(
            radiance=rad.reshape(h, w).astype(np.float32),
            range_m=t.reshape(h, w),
            depth_m=depth.reshape(h, w),
            primitive=pid.reshape(h, w),
            points_world=p.reshape(h, w, 3).astype(np.float32),
        )
