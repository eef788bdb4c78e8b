"""CPU ray-casting renderer (open3d ``RaycastingScene``) of a :class:`~loopmodel.sim.scene.Scene`.

Rays come from :meth:`CentralCamera.lift` of the pixel centres, so pinhole (xi = 0) and
unified-model omnidirectional (xi > 0) cameras render alike. Shading is Lambertian with a
point light and an ambient term (plus an optional Blinn-Phong specular term, which makes
the appearance depend on the viewing direction); albedo is the scene's tri-planar procedural texture at the
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


def to_tensor(a: NDArray) -> o3d.core.Tensor:
    """Copy of a float32 or uint32 numpy array as an open3d CPU tensor."""
    dtype = o3d.core.float32 if a.dtype == np.float32 else o3d.core.uint32
    return o3d.core.Tensor(np.ascontiguousarray(a), dtype, o3d.core.Device("CPU:0"))


def _dot3(a: F32, b: F32, tmp: F32, out: F32 | None = None) -> F32:
    """a[0] b[0] + a[1] b[1] + a[2] b[2] (rows of N, or 3 scalars against rows), summed in that order, into ``out``.

    ``tmp`` (N) is scratch space; in place so a view's shading makes few temporaries (gen20, issue 32).
    """
    out = np.empty_like(tmp) if out is None else out
    np.multiply(a[0], b[0], out=out)
    np.multiply(a[1], b[1], out=tmp)
    out += tmp
    np.multiply(a[2], b[2], out=tmp)
    out += tmp
    return out


def _inverse_norm(v: F32, tmp: F32) -> F32:
    """1 / max(|v|, 1e-12) of the N columns of ``v`` (3 x N)."""
    out = _dot3(v, v, tmp)
    np.sqrt(out, out=out)
    np.maximum(out, 1e-12, out=out)
    return np.divide(1.0, out, out=out)


def pixel_rays(camera: CentralCamera, width: int, height: int) -> RayBundle:
    """Unit rays (camera frame) through the pixel centres and which pixels have a valid ray.

    Pixel (u, v) has its centre at u, v, row-major; a valid ray lies in the unified model's image
    disc.
    """
    u, v = np.meshgrid(np.arange(width, dtype=float), np.arange(height, dtype=float))
    uv = np.column_stack([u.ravel(), v.ravel()])
    x = (uv[:, 0] - camera.u0) / camera.px
    y = (uv[:, 1] - camera.v0) / camera.py
    valid = 1.0 + (1.0 - camera.xi**2) * (x * x + y * y) >= 0.0
    rays = camera.lift(uv)
    valid &= np.all(np.isfinite(rays), axis=1)
    rays[~valid] = (0.0, 0.0, 1.0)
    return RayBundle(np.ascontiguousarray(rays.T, dtype=np.float32), valid, (int(height), int(width)))


@dataclass
class RayBundle:
    """Unit ray directions of a camera's pixels.

    ``dirs`` 3 x N (camera frame, float32), ``valid`` (N,) and the image ``shape`` (H, W) with N = H
    * W.
    """

    dirs: F32
    valid: NDArray[np.bool_]
    shape: tuple[int, int]

    @property
    def all_valid(self) -> bool:
        """Every pixel has a ray (always so for a pinhole camera)."""
        return bool(self.valid.all())


@dataclass
class Hits:
    """Nearest hits of N rays.

    ``range_m`` (inf for a miss), ``primitive`` (triangle id, -1 miss, -2 occluder) and unit
    ``normal`` (3 x N, world, facing the ray origin).
    """

    range_m: F32
    primitive: NDArray[np.int64]
    normal: F32


@dataclass
class View:
    """One rendered view (H x W arrays).

    ``radiance`` (albedo x shading, about 0..1), ``range_m`` (distance along the ray, inf where
    nothing is hit), ``depth_m`` (camera z), ``primitive`` (triangle id, -1 miss, -2 occluder),
    ``points_world`` (H x W x 3).
    """

    radiance: F32
    range_m: F32
    depth_m: F32
    primitive: NDArray[np.int64]
    points_soa: F32  # 3 x H*W

    @property
    def points_world(self) -> F32:
        """Surface points (H x W x 3, world, metres; meaningless where nothing is hit)."""
        h, w = self.radiance.shape
        return np.ascontiguousarray(self.points_soa.T).reshape(h, w, 3)


class Raycaster:
    """Ray casting and shading of a scene; build once, render many views.

    ``markers`` is a list of (world point, sigma_m, amplitude): each adds a 3-D Gaussian
    spot to the albedo (for checking where the renderer shows a known point). ``patches`` is a
    list of (world centre, radius_m, kind): surface inside the sphere is ``"flat"`` (uniform
    albedo 0.55: textureless) or ``"tiles"`` (a 12 mm checkerboard: repetitive)."""

    def __init__(self, scene: Scene) -> None:
        self.scene = scene
        self._rs = o3d.t.geometry.RaycastingScene()
        self._rs.add_triangles(
            to_tensor(scene.vertices.astype(np.float32)),
            to_tensor(scene.triangles.astype(np.uint32)),
        )
        self._ntri = scene.triangles.shape[0]
        self.markers: list[tuple[F64, float, float]] = []
        self.patches: list[tuple[F64, float, str]] = []
        self.threads = 0  # open3d ray-casting threads (0: all cores)
        cn = scene.corner_normals
        # rows: n0 (xyz), n1 - n0, n2 - n0: barycentric interpolation n0 + u dn1 + v dn2
        tn = np.concatenate([cn[:, 0], cn[:, 1] - cn[:, 0], cn[:, 2] - cn[:, 0]], axis=1)
        self._tn = np.ascontiguousarray(tn.T, dtype=np.float32)  # 9 x T
        self._tri_mat = scene.triangle_material.astype(np.int64)
        size = scene.textures[0].shape[0]
        self._tex_size = float(size)
        pad = [np.pad(t, ((0, 1), (0, 1)), mode="wrap") for t in scene.textures]
        self._atlas = np.ascontiguousarray(np.vstack(pad), dtype=np.float32)
        mats = scene.materials
        self._mat_scale = np.array([1.0 / m.texel_m for m in mats], np.float32)
        self._mat_gain = np.array([m.gain for m in mats], np.float32)
        self._mat_row = np.array([m.texture * (size + 1) for m in mats], np.float32)
        # per axis k and texture coordinate j: M offsets (texels)
        self._mat_off = np.ascontiguousarray(np.transpose(scene.texture_offsets, (1, 2, 0)), np.float32)
        self._patch_key: tuple[tuple[tuple[float, ...], float, str], ...] | None = None
        self._patch_bits_cached = np.zeros(0, np.uint64)
        # the occluder: an ellipsoid in its own frame, cast separately (it moves)
        occ = o3d.geometry.TriangleMesh.create_sphere(1.0, 24)
        ov = np.asarray(occ.vertices) * np.asarray(OCCLUDER_RADII_M)
        self._occ = o3d.t.geometry.RaycastingScene()
        self._occ.add_triangles(
            to_tensor(ov.astype(np.float32)),
            to_tensor(np.asarray(occ.triangles).astype(np.uint32)),
        )

    # -- ray casting
    def cast(self, origins_world: F32 | F64, dirs_world: F32, world_from_occluder: F64 | None = None) -> Hits:
        """Nearest hits of rays with origins ``origins_world`` (3 or 3 x N).

        Unit directions ``dirs_world`` (3 x N), world frame, metres.
        """
        n = dirs_world.shape[1]
        org = np.asarray(origins_world, np.float32)
        rays = np.empty((n, 6), np.float32)
        rays[:, :3] = org.T if org.ndim == 2 else org
        rays[:, 3:] = dirs_world.T
        ans = self._rs.cast_rays(o3d.core.Tensor.from_numpy(rays), nthreads=self.threads)
        t = ans["t_hit"].numpy()
        pid = ans["primitive_ids"].numpy().astype(np.int64)
        uv = ans["primitive_uvs"].numpy()
        u = np.ascontiguousarray(uv[:, 0])
        v = np.ascontiguousarray(uv[:, 1])
        tn = self._tn
        nrm = np.empty((3, n), np.float32)
        for k in range(3):
            nrm[k] = np.take(tn[k], pid, mode="clip")
            nrm[k] += u * np.take(tn[3 + k], pid, mode="clip")
            nrm[k] += v * np.take(tn[6 + k], pid, mode="clip")
        hit = np.isfinite(t)
        pid[~hit] = -1
        if world_from_occluder is not None:
            occ_from_world = invert_pose(world_from_occluder)
            R = occ_from_world[:3, :3].astype(np.float32)
            tr = occ_from_world[:3, 3].astype(np.float32)
            orays = np.empty_like(rays)
            orays[:, :3] = rays[:, :3] @ R.T + tr
            orays[:, 3:] = rays[:, 3:] @ R.T
            oans = self._occ.cast_rays(o3d.core.Tensor.from_numpy(orays), nthreads=self.threads)
            to = oans["t_hit"].numpy()
            closer = to < t
            if np.any(closer):
                t = np.where(closer, to, t)
                pid[closer] = -2
                Rw = world_from_occluder[:3, :3].astype(np.float32)
                nrm[:, closer] = Rw @ oans["primitive_normals"].numpy()[closer].T
        tmp = np.empty(n, np.float32)
        inv = _inverse_norm(nrm, tmp)
        facing = _dot3(nrm, dirs_world, tmp)
        np.negative(inv, out=inv, where=facing > 0)  # two-sided: normals face the ray origin
        nrm *= inv
        return Hits(t.astype(np.float32, copy=False), pid, nrm)

    def cast_points(self, origins_world: F64, dirs_world: F64, world_from_occluder: F64 | None = None) -> Hits:
        """:meth:`cast` for N x 3 arrays (or one 3-vector origin)."""
        o = np.asarray(origins_world, np.float32)
        o = o.T if o.ndim == 2 else o
        d = np.ascontiguousarray(np.asarray(dirs_world, np.float32).T)
        return self.cast(o, d, world_from_occluder)

    # -- appearance
    def albedo(self, points_world: F32, normals_world: F32, primitive: NDArray[np.int64]) -> F32:
        """Albedo (about 0..1) at N surface points.

        Points 3 x N world, unit normals 3 x N; from the tri-planar texture of their triangles'
        materials (occluder: uniform).
        """
        n = points_world.shape[1]
        mat = np.take(self._tri_mat, primitive, mode="clip")
        scale = np.take(self._mat_scale, mat)
        row = np.take(self._mat_row, mat)
        w = normals_world * normals_world
        w *= w
        w /= np.maximum(w[0] + w[1] + w[2], 1e-12)
        # remap wants 2-D maps with sides below 32767: lay the N samples out in rows
        cols = 1024 if n > 1024 else n
        rows_n = -(-n // cols)
        m = rows_n * cols
        out = np.zeros(n, np.float32)
        size = np.float32(self._tex_size)
        inv_size = np.float32(1.0 / self._tex_size)
        mu = np.zeros(m, np.float32)
        mv = np.zeros(m, np.float32)
        cu = np.empty(n, np.float32)
        cv = np.empty(n, np.float32)
        wrap = np.empty(n, np.float32)
        for k, (a, b) in enumerate(_AXES):
            np.multiply(points_world[a], scale, out=cu)
            cu += np.take(self._mat_off[k, 0], mat)
            np.multiply(points_world[b], scale, out=cv)
            cv += np.take(self._mat_off[k, 1], mat)
            np.multiply(cu, inv_size, out=wrap)
            np.floor(wrap, out=wrap)
            wrap *= size
            np.subtract(cu, wrap, out=mu[:n])
            np.multiply(cv, inv_size, out=wrap)
            np.floor(wrap, out=wrap)
            wrap *= size
            np.subtract(cv, wrap, out=wrap)
            np.add(wrap, row, out=mv[:n])
            sample = cv2.remap(
                self._atlas,
                mu.reshape(rows_n, cols),
                mv.reshape(rows_n, cols),
                cv2.INTER_LINEAR,
                borderMode=cv2.BORDER_REPLICATE,
            )
            np.multiply(w[k], sample.reshape(-1)[:n], out=wrap)
            out += wrap
        out *= np.take(self._mat_gain, mat)
        for centre, sigma, amplitude in self.markers:
            c = np.asarray(centre, np.float32)
            r2 = (points_world[0] - c[0]) ** 2 + (points_world[1] - c[1]) ** 2
            r2 += (points_world[2] - c[2]) ** 2
            out += np.float32(amplitude) * np.exp(r2 * np.float32(-0.5 / sigma**2))
        if self.patches:
            self._paint_patches(out, points_world, w, primitive)
        out[primitive == -2] = OCCLUDER_ALBEDO
        out[primitive == -1] = 0.0
        return out

    def _paint_patches(self, out: F32, points_world: F32, w: F32, primitive: NDArray[np.int64]) -> None:
        """Set ``out`` (albedo of N points) inside :attr:`patches`, later patches over earlier ones.

        Only points on triangles whose bounding box comes near a patch (:meth:`_patch_bits`) and inside
        the patch's box in x and y are tested: the values are those of testing all points (the sample's
        albedo 23 -> 17 ms CPU a view; gen20, issue 32).
        """
        bits = np.take(self._patch_bits(), primitive, mode="clip")
        near = np.flatnonzero(bits)
        bits = bits[near]
        pts_near = points_world[:, near]
        for j, (centre, radius, kind) in enumerate(self.patches):
            c = np.asarray(centre, np.float32)
            reach = np.float32(radius + 1e-3)  # the sphere's box in x and y, 1 mm wider
            box = (bits & (1 << j)) != 0
            box &= np.abs(pts_near[0] - c[0]) <= reach
            box &= np.abs(pts_near[1] - c[1]) <= reach
            sel = np.flatnonzero(box)
            idx = near[sel]
            pts = pts_near[:, sel]
            r2 = (pts[0] - c[0]) ** 2 + (pts[1] - c[1]) ** 2
            r2 += (pts[2] - c[2]) ** 2
            inside = r2 < np.float32(radius * radius)
            if not np.any(inside):
                continue
            if kind == "flat":
                out[idx[inside]] = 0.55
            else:  # tiles on the dominant tri-planar axis: period 24 mm, 0.3 / 0.7
                ax = np.argmax(w[:, idx[inside]], axis=0)
                pts = pts[:, inside]
                a = np.choose(ax, [pts[1], pts[0], pts[0]])
                b = np.choose(ax, [pts[2], pts[2], pts[1]])
                par = (np.floor(a / 0.012) + np.floor(b / 0.012)) % 2
                out[idx[inside]] = (0.3 + 0.4 * par).astype(np.float32)

    def _patch_bits(self) -> NDArray[np.uint64]:
        """Per triangle: bit j set when its bounding box, grown by 1 mm, meets patch j's sphere's box."""
        key = tuple((tuple(np.asarray(c, float).tolist()), float(r), kind) for c, r, kind in self.patches)
        if self._patch_key != key:
            corners = self.scene.vertices[self.scene.triangles]  # T x 3 corners x 3
            lo = corners.min(axis=1) - 1e-3
            hi = corners.max(axis=1) + 1e-3
            bits = np.zeros(len(corners), np.uint64)
            for j, (c, r, _kind) in enumerate(key):
                meets = np.all((lo <= np.add(c, r)) & (hi >= np.subtract(c, r)), axis=1)
                bits[meets] |= np.uint64(1 << j)
            self._patch_key, self._patch_bits_cached = key, bits
        return self._patch_bits_cached

    def render(
        self,
        rays: RayBundle,
        world_from_cam: F64,
        light_world_m: F64,
        ambient: float,
        world_from_occluder: F64 | None = None,
        specular: float = 0.0,
        shininess: float = 30.0,
    ) -> View:
        """Render the view of a camera at ``world_from_cam`` with pixel rays ``rays``.

        ``specular`` weights a Blinn-Phong highlight of exponent ``shininess``.
        """
        R = world_from_cam[:3, :3].astype(np.float32)
        o = world_from_cam[:3, 3].astype(np.float32)
        c = rays.dirs
        d = np.empty_like(c)
        tmp = np.empty(c.shape[1], np.float32)
        for k in range(3):
            _dot3(R[k], c, tmp, d[k])  # R c, by rows
        hits = self.cast(o, d, world_from_occluder)
        t, pid, nrm = hits.range_m, hits.primitive, hits.normal
        if not rays.all_valid:
            t[~rays.valid] = np.inf
            pid[~rays.valid] = -1
        hit = np.isfinite(t)
        tt = np.where(hit, t, np.float32(0.0))
        p = np.empty_like(d)
        for k in range(3):
            np.multiply(d[k], tt, out=p[k])
            p[k] += o[k]
        albedo = self.albedo(p, nrm, pid)
        light = np.asarray(light_world_m, np.float32)
        L = light[:, None] - p
        inv = _inverse_norm(L, tmp)
        diffuse = _dot3(nrm, L, tmp)
        diffuse *= inv
        np.maximum(diffuse, 0.0, out=diffuse)
        rad = diffuse * np.float32(1.0 - ambient)
        rad += np.float32(ambient)
        rad *= albedo  # albedo 0 on a miss
        if specular > 0:
            half = L * inv  # light + view directions
            half -= d
            hn = _inverse_norm(half, tmp)
            nh = _dot3(nrm, half, tmp)
            nh *= hn
            np.maximum(nh, 0.0, out=nh)
            np.power(nh, np.float32(shininess), out=nh)
            nh *= np.float32(specular * (1.0 - ambient))
            rad += np.where((diffuse > 0) & hit, nh, np.float32(0.0))
        depth = np.where(hit, t * c[2], np.float32(np.inf))
        h, w = rays.shape
        return View(
            radiance=rad.reshape(h, w),
            range_m=t.reshape(h, w),
            depth_m=depth.reshape(h, w),
            primitive=pid.reshape(h, w),
            points_soa=p,
        )
