"""A street scene for stereo odometry (issue 36): repetitive texture, far field, moving cars.

A KITTI-like forward-driving rectified stereo camera (1.65 m above the road, 0.54 m baseline,
about 1 m per frame at 10 Hz) on a straight road with a gentle weave. Over much of the view
the texture repeats: hedges and trees of dense ``foliage`` (stochastic, self-similar leaves),
a ``fence`` of vertical bars beside the road (periodic along the image row: the row search
of a stereo matcher finds a bar one period off), dashed lane markings, building facades
(a ``facade`` grid of windows) 60-160 m away and hills beyond 300 m (far field: a disparity
of a few pixels or less). Two cars move independently: one ahead in our lane at
``lead_speed_ratio`` of our speed, one oncoming in the other lane.

Frames: the world is the first left camera (x right, y down, z forward, metres); poses are
``world_from_cam`` of the rectified left camera. Every surface is a textured rectangle; a view is
ray cast (open3d) at ``supersample`` x the resolution with a trilinear texture pyramid, shaded
by a sun and sky, blurred by a 0.5 px lens, and goes through a simple sensor (shot and read
noise, 3 % left/right gain mismatch, 8 bit). :func:`street_frame` also returns the true
disparity (px) and which pixels see a moving car, at the pixel centres of the left image.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass, field

import cv2
import numpy as np
import open3d as o3d
from numpy.typing import NDArray

from loopmodel.geometry.se3 import make_pose, so3_exp
from loopmodel.sim.render import to_tensor
from loopmodel.sim.texture import make_texture
from loopmodel.types import StereoCalibration, StereoFrame, Trajectory

F32 = NDArray[np.float32]
F64 = NDArray[np.float64]

CAMERA_HEIGHT_M = 1.65
SUN_DIR = np.array([0.4, -0.8, 0.45]) / np.linalg.norm([0.4, -0.8, 0.45])  # towards the sun (world)
# material: (texture style, metres per texel, albedo gain)
MATERIALS: tuple[tuple[str, float, float], ...] = (
    ("stone", 0.004, 0.55),  # 0 asphalt
    ("poster", 0.004, 1.15),  # 1 lane marking (bright)
    ("foliage", 0.02, 0.8),  # 2 hedges and trees: leaves 4-20 cm
    ("fence", 0.008, 0.9),  # 3 fence: 16 texels = 12.8 cm bars
    ("facade", 0.03, 0.85),  # 4 buildings: 1.9 x 3.8 m windows grid
    ("stone", 0.15, 0.7),  # 5 hills
    ("poster", 0.004, 0.9),  # 6 car body
    ("wood", 0.02, 1.0),  # 7 sky (faint clouds, almost flat)
)
SKY = 7


@dataclass(frozen=True)
class StreetConfig:
    """Camera, path and scene options of the street scene (pixels, metres, frames at ``rate_hz``)."""

    width_px: int = 832
    height_px: int = 256
    fx_px: float = 480.0
    baseline_m: float = 0.54
    frames: int = 60
    rate_hz: float = 10.0
    speed_m_per_frame: float = 1.0
    seed: int = 0
    supersample: int = 2
    lead_car: bool = True
    lead_speed_ratio: float = 0.85  # the car ahead drives at this fraction of our speed
    lead_start_m: float = 14.0
    oncoming_car: bool = True
    fence: bool = True
    hedge_m: float = 5.5  # lateral distance of the hedges (0: none)
    trees_m: tuple[float, float] = (6.5, 11.0)  # lateral distance range of the trees
    open_from_m: float = 0.0  # > 0: beyond this distance no hedges, trees at ``trees_open_m`` (the view opens)
    trees_open_m: tuple[float, float] = (14.0, 45.0)
    right_cx_error_px: float = 0.0  # the right image rendered with its principal point off (calibration error)
    texture_size_px: int = 1024
    noise_dn: float = 1.5  # read noise (grey levels)


@dataclass
class StreetFrame:
    """One stereo frame with its truth.

    Images, ``world_from_cam`` (4x4), true disparity (H x W, px; 0 for the sky), moving-car mask.
    """

    frame: StereoFrame
    world_from_cam: F64
    disparity_px: F32
    moving: NDArray[np.bool_]


@dataclass
class _Rect:
    """Rectangle ``origin + s * axis_s + t * axis_t``, 0 <= s <= size_s, 0 <= t <= size_t (object frame, metres)."""

    origin: F64
    axis_s: F64
    axis_t: F64
    size_s: float
    size_t: float
    material: int
    body: int = 0  # 0 static, 1 lead car, 2 oncoming car


def _rect(o: tuple[float, float, float], a: tuple[float, float, float], b: tuple[float, float, float],
          ls: float, lt: float, mat: int, body: int = 0) -> _Rect:
    return _Rect(np.asarray(o, float), np.asarray(a, float), np.asarray(b, float), ls, lt, mat, body)


def _box(centre: tuple[float, float, float], size: tuple[float, float, float], mat: int, body: int) -> list[_Rect]:
    """The five faces of a box other than its bottom (x right, y down, z forward; ``size`` = w, h, l)."""
    cx, cy, cz = centre
    w, h, l = size
    x0, x1, y0, z0, z1 = cx - w / 2, cx + w / 2, cy - h / 2, cz - l / 2, cz + l / 2
    return [
        _rect((x0, y0, z0), (1, 0, 0), (0, 1, 0), w, h, mat, body),  # back
        _rect((x0, y0, z1), (1, 0, 0), (0, 1, 0), w, h, mat, body),  # front
        _rect((x0, y0, z0), (0, 0, 1), (0, 1, 0), l, h, mat, body),  # left side
        _rect((x1, y0, z0), (0, 0, 1), (0, 1, 0), l, h, mat, body),  # right side
        _rect((x0, y0, z0), (1, 0, 0), (0, 0, 1), w, l, mat, body),  # roof
    ]


@dataclass
class StreetScene:
    """The rectangles, the bodies' motion and the materials' texture pyramids."""

    config: StreetConfig
    rects: list[_Rect]
    pyramids: list[list[F32]] = field(default_factory=list)

    @classmethod
    def build(cls, cfg: StreetConfig) -> StreetScene:
        """The scene of ``cfg`` (deterministic in ``cfg.seed``)."""
        rng = np.random.default_rng([cfg.seed, 36])
        g = CAMERA_HEIGHT_M
        length = cfg.frames * cfg.speed_m_per_frame + 200.0
        half_w = max(cfg.hedge_m, cfg.trees_m[1], cfg.trees_open_m[1] if cfg.open_from_m > 0 else 0.0) + 2.0
        r: list[_Rect] = [_rect((-half_w, g, -20.0), (1, 0, 0), (0, 0, 1), 2 * half_w, length + 20, 0)]
        for z in np.arange(-10.0, length, 9.0):  # dashed centre line, 3 m dashes every 9 m
            r.append(_rect((-1.95, g - 0.002, z), (1, 0, 0), (0, 0, 1), 0.15, 3.0, 1))
        for side in (-1.0, 1.0):  # continuous hedges, then trees of irregular width behind them
            hedge_end = cfg.open_from_m if cfg.open_from_m > 0 else length
            if cfg.hedge_m > 0:
                r.append(_rect((side * cfg.hedge_m, g - 2.4, -20.0), (0, 0, 1), (0, 1, 0), hedge_end + 20, 2.4, 2))
            z = -15.0
            while z < length:
                w = float(rng.uniform(3.0, 9.0))
                h = float(rng.uniform(5.0, 11.0))
                lateral = cfg.trees_open_m if 0 < cfg.open_from_m < z else cfg.trees_m
                xt = side * float(rng.uniform(*lateral))
                r.append(_rect((xt, g - h, z), (0, 0, 1), (0, 1, 0), w, h, 2))
                # a clump facing the road: its face is oblique to the rows
                r.append(_rect((xt, g - h * 0.8, z + w / 2), (-side * 0.7, 0, 0.7), (0, 1, 0), 2.5, h * 0.8, 2))
                z += w + float(rng.uniform(-1.0, 2.0))
        if cfg.fence:
            r.append(_rect((3.8, g - 1.1, -20.0), (0, 0, 1), (0, 1, 0), length + 20, 1.1, 3))
        for z in np.arange(60.0, length + 100.0, 25.0):  # facades at 60-160 m beyond the trees
            x = float(rng.uniform(-40.0, 25.0))
            w, h = float(rng.uniform(12.0, 30.0)), float(rng.uniform(10.0, 30.0))
            r.append(_rect((x, g - h, z + 60.0), (1, 0, 0), (0, 1, 0), w, h, 4))
        zf = length + 300.0
        r.append(_rect((-600.0, g - 60.0, zf), (1, 0, 0), (0, 1, 0), 1200.0, 60.0, 5))  # hills
        r.append(_rect((-3000.0, -2000.0, 3000.0), (1, 0, 0), (0, 1, 0), 6000.0, 2000.0 + g - 50.0, SKY))
        if cfg.lead_car:
            r += _box((0.0, g - 0.75, 0.0), (1.8, 1.5, 4.2), 6, 1)
        if cfg.oncoming_car:
            r += _box((0.0, g - 0.8, 0.0), (1.9, 1.6, 4.5), 6, 2)
        ss = np.random.SeedSequence([cfg.seed, 36, 1]).spawn(len(MATERIALS))
        pyramids = []
        for (style, _texel, _gain), s in zip(MATERIALS, ss, strict=True):
            tex = make_texture(s, cfg.texture_size_px, style)
            if style == "wood":  # the sky: faint
                tex = (0.85 + 0.08 * (tex - tex.mean())).astype(np.float32)
            levels = [tex]
            while levels[-1].shape[0] > 8:
                levels.append(cv2.pyrDown(levels[-1], borderType=cv2.BORDER_WRAP))
            pyramids.append(levels)
        return cls(cfg, r, pyramids)

    # --------------------------------------------------------------- motion
    def world_from_cam(self, i: int) -> F64:
        """True pose of the rectified left camera at frame ``i`` (world = frame 0)."""
        c = self.config
        s = c.speed_m_per_frame
        tt = np.arange(i + 1, dtype=float)
        yaw = 0.035 * np.sin(2 * np.pi * tt / 45.0) + 0.02 * np.sin(2 * np.pi * tt / 17.0 + 1.0)
        yaw -= yaw[0]
        steps = np.column_stack([np.sin(yaw), np.zeros_like(yaw), np.cos(yaw)]) * s
        p = steps[:-1].sum(axis=0) if i > 0 else np.zeros(3)
        p[1] = 0.015 * np.sin(2 * np.pi * i / 7.0)  # suspension
        pitch = 0.004 * np.sin(2 * np.pi * i / 7.0 + 0.8)
        R = so3_exp(np.array([0.0, yaw[-1], 0.0])) @ so3_exp(np.array([pitch, 0.0, 0.0]))
        return make_pose(R, p)

    def world_from_body(self, body: int, i: int) -> F64:
        """Pose of a moving car at frame ``i`` (its box is modelled about the origin)."""
        c = self.config
        cam_z = self.world_from_cam(i)[2, 3]
        if body == 1:
            z = c.lead_start_m + c.lead_speed_ratio * c.speed_m_per_frame * i
            x = 0.25 * np.sin(2 * np.pi * i / 30.0)
            return make_pose(np.eye(3), np.array([x, 0.0, z]))
        # oncoming: passes the camera a third of the way through the scan
        z = cam_z + 2.0 * c.speed_m_per_frame * (c.frames / 3.0 - i) + 2.0
        return make_pose(np.eye(3), np.array([-3.6, 0.0, z]))

    def _rects_at(self, i: int) -> tuple[F64, F64, F64, F64, NDArray[np.int64], NDArray[np.int64]]:
        """Per rectangle at frame ``i``: origins, axes s and t (world), sizes (s, t), material, body."""
        o, a, b, size, mat, body = [], [], [], [], [], []
        poses = {k: self.world_from_body(k, i) for k in (1, 2)}
        for rc in self.rects:
            T = poses.get(rc.body)
            if T is None:
                o.append(rc.origin)
                a.append(rc.axis_s)
                b.append(rc.axis_t)
            else:
                o.append(T[:3, :3] @ rc.origin + T[:3, 3])
                a.append(T[:3, :3] @ rc.axis_s)
                b.append(T[:3, :3] @ rc.axis_t)
            size.append((rc.size_s, rc.size_t))
            mat.append(rc.material)
            body.append(rc.body)
        return (np.array(o), np.array(a) / np.linalg.norm(a, axis=1, keepdims=True),
                np.array(b) / np.linalg.norm(b, axis=1, keepdims=True), np.array(size, float),
                np.array(mat, np.int64), np.array(body, np.int64))

    # --------------------------------------------------------------- rendering
    def _cast(self, i: int, world_from_view: F64, K: F64, w: int, h: int, full: bool = True) -> dict[str, NDArray]:
        """Ray cast a w x h pinhole view: depth (camera z, m) and rectangle id.

        With ``full`` also (s, t) on the rectangle, the footprint (m per pixel) and the shading.
        """
        o, a, b, size, mat, _body = self._rects_at(i)
        corners = np.stack([o, o + a * size[:, :1], o + a * size[:, :1] + b * size[:, 1:], o + b * size[:, 1:]], 1)
        verts = corners.reshape(-1, 3).astype(np.float32)
        base = 4 * np.arange(len(o), dtype=np.uint32)[:, None]
        tris = np.concatenate([base + np.array([0, 1, 2], np.uint32), base + np.array([0, 2, 3], np.uint32)], 1)
        rs = o3d.t.geometry.RaycastingScene()
        rs.add_triangles(to_tensor(verts), to_tensor(tris.reshape(-1, 3).astype(np.uint32)))
        R, c = world_from_view[:3, :3], world_from_view[:3, 3]
        xs = ((np.arange(w) - K[0, 2]) / K[0, 0]).astype(np.float32)
        ys = ((np.arange(h) - K[1, 2]) / K[1, 1]).astype(np.float32)
        d_w = (xs[None, :, None] * R[:, 0].astype(np.float32) + ys[:, None, None] * R[:, 1].astype(np.float32)
               + R[:, 2].astype(np.float32)).reshape(-1, 3)
        rays = np.empty((d_w.shape[0], 6), np.float32)
        rays[:, :3] = c
        rays[:, 3:] = d_w
        out = rs.cast_rays(to_tensor(rays))
        depth = out["t_hit"].numpy()  # along d_w, whose camera z is 1: camera z
        hit = np.isfinite(depth)
        sky = int(np.flatnonzero(mat == SKY)[0])
        rid = np.where(hit, out["primitive_ids"].numpy().astype(np.int64) // 2, sky)  # a miss sees the sky
        res: dict[str, NDArray] = {"depth": depth.reshape(h, w), "rect": rid.reshape(h, w), "rid": rid}
        if not full:
            return res
        dep = np.where(hit, depth, 0.0).astype(np.float32)
        rel = (c.astype(np.float32) - o[rid].astype(np.float32)) + d_w * dep[:, None]
        res["s"] = np.einsum("ij,ij->i", rel, a[rid].astype(np.float32))
        res["t"] = np.einsum("ij,ij->i", rel, b[rid].astype(np.float32))
        n_rect = np.cross(a, b)
        n = n_rect[rid].astype(np.float32)
        dn = np.linalg.norm(d_w, axis=1)
        cos = np.abs(np.einsum("ij,ij->i", n, d_w)) / dn
        res["foot"] = np.where(hit, dep * dn / K[0, 0] / np.maximum(cos, 0.05), 1e3)
        res["shade"] = (0.45 + 0.55 * np.abs(n_rect @ SUN_DIR))[rid].astype(np.float32)
        return res

    def _radiance(self, i: int, cast: dict[str, NDArray], shape: tuple[int, int]) -> F32:
        """Albedo x shading of a cast view (trilinear texture pyramid)."""
        _o, _a, _b, _size, mat, _body = self._rects_at(i)
        m = mat[cast["rid"]]
        out = np.zeros(m.shape, np.float32)
        for k, (_style, texel, gain) in enumerate(MATERIALS):
            sel = np.flatnonzero(m == k)
            if sel.size == 0:
                continue
            pyr = self.pyramids[k]
            su = cast["s"][sel] / texel
            sv = cast["t"][sel] / texel
            lev = np.clip(np.log2(np.maximum(cast["foot"][sel] / texel, 1e-6)), 0, len(pyr) - 1)
            lo = np.floor(lev).astype(int)
            frac = (lev - lo).astype(np.float32)
            val = np.zeros(sel.size, np.float32)
            for L in np.unique(lo):
                for LL, wgt in ((L, 1.0 - frac), (min(L + 1, len(pyr) - 1), frac)):
                    j = np.flatnonzero(lo == L)
                    img = pyr[LL]
                    n = img.shape[0]
                    val[j] += wgt[j] * _sample_wrap(img, np.mod(su[j] / 2**LL, n), np.mod(sv[j] / 2**LL, n))
            shade = 1.0 if k == SKY else cast["shade"][sel]
            out[sel] = gain * val * shade
        return out.reshape(shape)

    def render(self, i: int) -> StreetFrame:
        """Frame ``i``: the stereo pair (8 bit), its true pose, disparity and moving-car mask."""
        c = self.config
        K = self.K
        ss = c.supersample
        Ks = K.copy()
        Ks[:2, :] *= ss
        Ks[0, 2] = (K[0, 2] + 0.5) * ss - 0.5
        Ks[1, 2] = (K[1, 2] + 0.5) * ss - 0.5
        world_from_cam = self.world_from_cam(i)
        rng = np.random.default_rng([c.seed, 36, 2, i])
        imgs = []
        for side, gain in ((0, 1.0), (1, 1.03)):
            world_from_view = world_from_cam.copy()
            world_from_view[:3, 3] += world_from_cam[:3, 0] * c.baseline_m * side
            Kv = Ks.copy()
            Kv[0, 2] += side * c.right_cx_error_px * ss
            cast = self._cast(i, world_from_view, Kv, c.width_px * ss, c.height_px * ss)
            rad = self._radiance(i, cast, (c.height_px * ss, c.width_px * ss))
            rad = cv2.resize(rad, (c.width_px, c.height_px), interpolation=cv2.INTER_AREA)
            rad = cv2.GaussianBlur(rad, (0, 0), 0.5)
            e = 210.0 * gain * rad  # grey levels before noise
            e = e + rng.standard_normal(e.shape).astype(np.float32) * np.sqrt(c.noise_dn**2 + 0.05 * np.maximum(e, 0))
            imgs.append(np.clip(np.rint(e), 0, 255).astype(np.uint8))
        truth = self._cast(i, world_from_cam, K, c.width_px, c.height_px, full=False)
        depth = truth["depth"]
        finite = np.isfinite(depth)
        disp = np.where(finite, c.fx_px * c.baseline_m / np.where(finite, depth, 1.0), 0.0)
        _o, _a, _b, _size, _mat, body = self._rects_at(i)
        moving = body[truth["rect"]] > 0
        t_ns = round(i * 1e9 / c.rate_hz)
        return StreetFrame(StereoFrame(t_ns, imgs[0], imgs[1], i), world_from_cam, disp.astype(np.float32), moving)

    @property
    def K(self) -> F64:
        """Intrinsics of both rectified cameras (pixels)."""
        c = self.config
        return np.array([[c.fx_px, 0.0, (c.width_px - 1) / 2.0], [0.0, c.fx_px, (c.height_px - 1) / 2.0],
                         [0.0, 0.0, 1.0]])

    @property
    def calibration(self) -> StereoCalibration:
        """The rectified pair's calibration (right camera ``baseline_m`` along +x)."""
        right_from_left = np.eye(4)
        right_from_left[0, 3] = -self.config.baseline_m
        size = (self.config.width_px, self.config.height_px)
        return StereoCalibration(self.K, self.K, right_from_left, size).check("street scene")

    def frames(self) -> Iterator[StreetFrame]:
        """All frames in order."""
        for i in range(self.config.frames):
            yield self.render(i)

    def ground_truth(self) -> Trajectory:
        """True poses of every frame."""
        c = self.config
        return Trajectory(np.array([round(i * 1e9 / c.rate_hz) for i in range(c.frames)], np.int64),
                          np.stack([self.world_from_cam(i) for i in range(c.frames)]))


def _sample_wrap(img: F32, x: F64, y: F64) -> F32:
    """Bilinear samples of a periodic texture at texel coordinates (x, y)."""
    n = x.size
    cols = 1024
    rows = -(-n // cols)
    mx = np.zeros(rows * cols, np.float32)
    my = np.zeros(rows * cols, np.float32)
    mx[:n], my[:n] = x, y
    out = cv2.remap(img, mx.reshape(rows, cols), my.reshape(rows, cols), cv2.INTER_LINEAR,
                    borderMode=cv2.BORDER_WRAP)
    return out.ravel()[:n]


def street_frame(cfg: StreetConfig, i: int) -> StreetFrame:
    """Frame ``i`` of the street scene of ``cfg`` (builds the scene; use :class:`StreetScene` for many)."""
    return StreetScene.build(cfg).render(i)
