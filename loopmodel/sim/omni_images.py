"""Rendered images of the multi-mirror omnidirectional sensor of seed 002.

Every pixel of every mirror disc is lifted through its mirror camera's unified central model
(ξ, K) to a ray from the mirror's focus and ray-cast into the scene (open3d
``RaycastingScene`` for the static room, clutter and the other mirrors; an exact ray/box test
for the moving box). The grey level is albedo × Lambertian shading (a light above the
sensor plus ambient light), with procedural texture on every surface, then optical blur and
sensor noise; the discs of all mirrors form one image per frame, as on the seed's sensor
(one camera looking at the mirrors). Pixels outside the discs are black.

Scenarios are drawn by seed from a family (:func:`omni_scenario`): the room, a random number
of clutter boxes and posters placed at random — some behind the self-occlusion zones of
random mirror pairs — and a random hand-held motion of the box around the sensor. Nothing is
placed to reproduce a figure of the paper.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import open3d as o3d
from numpy.typing import NDArray

from loopmodel.geometry.se3 import invert_pose, make_pose, so3_exp
from loopmodel.pose.rig import F64
from loopmodel.pose.tracking import PolyhedronModel
from loopmodel.sim.omni import BOX_SIZE_M, OmniSensor, TrackingRun, _ray_box_entry, omni_sensor

U8 = NDArray[np.uint8]

#: Optical blur (Gaussian sigma, pixels): a small lens focused on the mirrors' virtual images.
BLUR_SIGMA_PX = 0.8
#: Read noise (grey levels) and shot-noise gain (grey levels² per grey level): a typical
#: 8-bit machine-vision CMOS camera at moderate gain (EMVA 1288 order of magnitude).
READ_NOISE_GL = 1.5
SHOT_GAIN_GL = 0.08


def _hash_texture(p: F64, scale_m: float, seed: int) -> F64:
    """Procedural texture in [-1, 1] at 3-D points (sum of random plane waves)."""
    rng = np.random.default_rng(seed)
    k = rng.normal(size=(6, 3))
    k *= (2 * np.pi / scale_m) * rng.uniform(0.5, 2.0, (6, 1)) / np.linalg.norm(k, axis=1, keepdims=True)
    ph = rng.uniform(0, 2 * np.pi, 6)
    return np.sin(p @ k.T + ph).mean(axis=1) * 1.6


@dataclass
class OmniScenario:
    """A seeded scene and box motion: static meshes with one albedo per triangle, the box's
    face albedos and its ``sensor_from_box`` poses (10 frames per second)."""

    seed: int
    sensor: OmniSensor
    static_meshes: list[tuple[o3d.geometry.TriangleMesh, F64]]  # mesh, albedo per triangle
    box_size_m: tuple[float, float, float]
    box_face_albedo: F64  # (6,) faces -x, +x, -y, +y, -z, +z
    sensor_from_box: list[F64]
    clutter_mirrors: tuple[int, ...] = ()  # mirror pairs whose occlusion zone got clutter

    @property
    def model(self) -> PolyhedronModel:
        """The box as the tracker's line model."""
        return PolyhedronModel.box(self.box_size_m)


def _box_mesh(size: F64, T: F64) -> o3d.geometry.TriangleMesh:
    m = o3d.geometry.TriangleMesh.create_box(*size)
    m.translate(-0.5 * np.asarray(size))
    m.transform(T)
    return m


def omni_scenario(seed: int, n_frames: int = 60, clutter: bool = True) -> OmniScenario:
    """Draw a scenario by seed: room, clutter (boxes and posters, some behind the occlusion
    zone of two random mirrors), box albedos and a random smooth motion of the box."""
    from scipy.interpolate import PchipInterpolator

    rng = np.random.default_rng(seed)
    sensor = omni_sensor()
    centre = sensor.foci_m.mean(axis=0)
    meshes: list[tuple[o3d.geometry.TriangleMesh, F64]] = []
    # the room: a 6-sided cylinder wall of radius ~2.5 m, floor and ceiling (z points down)
    room = o3d.geometry.TriangleMesh.create_cylinder(radius=2.5, height=3.0, resolution=24, split=4)
    room.translate(centre)
    meshes.append((room, np.full(len(room.triangles), rng.uniform(0.35, 0.55))))
    pairs: tuple[int, ...] = ()
    if clutter:
        for _ in range(int(rng.integers(6, 14))):
            az, dist = rng.uniform(0, 2 * np.pi), rng.uniform(0.95, 1.8)
            size = rng.uniform([0.1, 0.1, 0.1], [0.5, 0.5, 0.7])
            T = make_pose(
                so3_exp([0, 0, rng.uniform(0, np.pi)]),
                centre + [dist * np.cos(az), dist * np.sin(az), rng.uniform(-0.3, 0.4)],
            )
            m = _box_mesh(size, T)
            meshes.append((m, np.repeat(rng.uniform(0.1, 0.95, 6), 2)))
        # clutter behind the self-occlusion zone of two random neighbouring or diagonal mirrors
        a, b = (int(x) for x in rng.choice(4, 2, replace=False))
        pairs = (a, b)
        d = sensor.foci_m[b] - sensor.foci_m[a]
        az0 = float(np.arctan2(d[1], d[0]))
        for _ in range(int(rng.integers(8, 20))):
            az = az0 + rng.normal(0, 0.25)
            dist = rng.uniform(1.0, 1.6)
            size = rng.uniform([0.02, 0.1, 0.15], [0.05, 0.3, 0.35])
            T = make_pose(so3_exp([0, 0, az]), centre + [dist * np.cos(az), dist * np.sin(az), rng.uniform(-0.4, 0.3)])
            meshes.append((_box_mesh(size, T), np.repeat(rng.uniform(0.05, 0.95, 6), 2)))
        for _ in range(int(rng.integers(10, 30))):  # posters: thin slabs near the wall
            az, w, h = rng.uniform(0, 2 * np.pi), rng.uniform(0.2, 0.8), rng.uniform(0.2, 0.8)
            T = make_pose(so3_exp([0, 0, az]), centre + [2.4 * np.cos(az), 2.4 * np.sin(az), rng.uniform(-0.8, 0.8)])
            meshes.append((_box_mesh(np.array([0.01, w, h]), T), np.repeat(rng.uniform(0.05, 0.95, 6), 2)))
    # the box: distinct face albedos so that every edge has contrast on at least one side
    face = rng.permutation(np.linspace(0.2, 0.9, 6)) + rng.uniform(-0.05, 0.05, 6)
    # motion at 10 frames/s, hand-held speeds whatever the length: the azimuth sweeps at a
    # random rate (4-9 deg/s, either way); distance, height and the hand's turns follow
    # smooth random curves with a key every 3 s
    t_s = np.arange(n_frames) / 10.0
    keys = np.arange(0.0, t_s[-1] + 3.0, 3.0) if n_frames > 1 else np.array([0.0, 3.0])

    def wander(lo: float, hi: float) -> F64:
        return np.asarray(PchipInterpolator(keys, rng.uniform(lo, hi, len(keys)))(t_s))

    rate = np.deg2rad(rng.uniform(4.0, 9.0)) * rng.choice([-1.0, 1.0])
    box_az = np.asarray(rng.uniform(0, 2 * np.pi) + rate * t_s + np.deg2rad(3) * np.sin(2 * np.pi * 0.3 * t_s))
    box_dist, box_z = wander(0.42, 0.7), wander(-0.04, 0.08)
    spin, tilt, roll = np.deg2rad(wander(20, 70)), np.deg2rad(wander(10, 35)), np.deg2rad(wander(-12, 12))
    tremor = rng.normal(0, 0.0015, (n_frames, 3))
    poses = []
    for k in range(n_frames):
        R = so3_exp([0, 0, box_az[k]]) @ so3_exp([0, tilt[k], 0]) @ so3_exp([roll[k], 0, 0]) @ so3_exp([0, 0, spin[k]])
        p = centre + [box_dist[k] * np.cos(box_az[k]), box_dist[k] * np.sin(box_az[k]), box_z[k]] + tremor[k]
        poses.append(make_pose(R, p))
    return OmniScenario(seed, sensor, meshes, BOX_SIZE_M, face, poses, pairs)


@dataclass
class OmniRenderer:
    """Renders the frames of a scenario. The static part (room, clutter, mirrors) is cast once
    per mirror; each frame only intersects the mirror rays with the moving box."""

    scenario: OmniScenario
    light_dir: F64 = field(default_factory=lambda: np.array([0.3, -0.2, -1.0]))  # towards the light (z down)
    _pix: list[tuple[NDArray[np.int64], F64, F64]] = field(
        default_factory=list, repr=False
    )  # flat index, ray, t_static

    def __post_init__(self) -> None:
        s = self.scenario.sensor
        w, h = s.image_size
        self.light_dir = self.light_dir / np.linalg.norm(self.light_dir)
        self._static_img = np.zeros(h * w, np.float32)
        for m, cam in enumerate(s.cameras):
            r_px = s.rim * cam.px
            u0, v0 = cam.u0, cam.v0
            us = np.arange(max(0, int(u0 - r_px) - 1), min(w, int(u0 + r_px) + 2))
            vs = np.arange(max(0, int(v0 - r_px) - 1), min(h, int(v0 + r_px) + 2))
            U, V = np.meshgrid(us, vs)
            inside = np.hypot(U - u0, V - v0) <= r_px
            U, V = U[inside], V[inside]
            rays = cam.lift(np.column_stack([U, V]).astype(float))
            t_static, grey = self._cast_static(m, rays)
            flat = (V * w + U).astype(np.int64)
            self._static_img[flat] = grey
            self._pix.append((flat, rays, t_static))

    def _cast_static(self, m: int, rays: F64) -> tuple[F64, F64]:
        s = self.scenario.sensor
        scene = o3d.t.geometry.RaycastingScene()
        albedo: list[F64] = []
        for mesh, alb in self.scenario.static_meshes:
            scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(mesh))
            albedo.append(alb)
        n_static = sum(len(a) for a in albedo)
        for other in range(len(s.cameras)):  # the other mirrors: dark metal solids
            if other == m:
                continue
            cyl = o3d.geometry.TriangleMesh.create_cylinder(
                radius=s.mirror_radius_m, height=s.z_vertex_m - s.z_rim_m, resolution=48
            )
            cyl.translate(s.foci_m[other] + [0, 0, 0.5 * (s.z_vertex_m + s.z_rim_m)])
            scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(cyl))
            albedo.append(np.full(len(cyl.triangles), 0.08))
        alb_all = np.concatenate(albedo)
        r = np.empty((len(rays), 6), np.float32)
        r[:, :3] = s.foci_m[m]
        r[:, 3:] = rays
        ans = scene.cast_rays(o3d.core.Tensor(r))  # type: ignore[call-overload]
        t = ans["t_hit"].numpy().astype(float)
        prim = ans["primitive_ids"].numpy().astype(np.int64)
        normal = ans["primitive_normals"].numpy().astype(float)
        # triangle ids count across geometries in the order they were added
        geo = ans["geometry_ids"].numpy().astype(np.int64)
        offsets = np.cumsum([0] + [len(a) for a in albedo])
        hit = np.isfinite(t)
        tri = np.where(hit, offsets[np.minimum(geo, len(albedo) - 1)] + prim, 0)
        a = np.where(hit, alb_all[np.minimum(tri, len(alb_all) - 1)], 0.0)
        p = s.foci_m[m] + rays * np.where(hit, t, 0.0)[:, None]
        a = np.clip(a * (1 + 0.12 * _hash_texture(p, 0.05, self.scenario.seed)), 0, 1)
        shade = 0.55 + 0.45 * np.abs(normal @ self.light_dir)
        del n_static
        return np.where(hit, t, np.inf), np.where(hit, a * shade, 0.0)

    def render(self, k: int, rng: np.random.Generator | None = None) -> U8:
        """Frame ``k`` as an 8-bit grey image (all mirror discs in one image)."""
        import cv2

        sc = self.scenario
        s = sc.sensor
        w, h = s.image_size
        T = sc.sensor_from_box[k]
        box_from_sensor = invert_pose(T)
        half = np.asarray(sc.box_size_m) / 2
        flat_img = self._static_img.copy()
        for m in range(len(s.cameras)):
            flat, rays, t_static = self._pix[m]
            focus = s.foci_m[m]
            # only rays inside the cone of the box's bounding sphere can hit it
            to_box = T[:3, 3] - focus
            dist = float(np.linalg.norm(to_box))
            cos_cone = np.cos(min(np.arcsin(min(1.0, float(np.linalg.norm(half)) / dist)) + 0.01, np.pi))
            near = np.flatnonzero(rays @ (to_box / dist) >= cos_cone)
            if near.size == 0:
                continue
            t_box = _ray_box_entry(focus, rays[near], box_from_sensor, half)
            front = t_box < t_static[near]
            if not front.any():
                continue
            sel = near[front]
            p_s = focus + rays[sel] * t_box[front][:, None]
            p_b = p_s @ box_from_sensor[:3, :3].T + box_from_sensor[:3, 3]
            q = p_b / half
            axis = np.argmax(np.abs(q), axis=1)
            sign = np.sign(q[np.arange(len(q)), axis])
            face = 2 * axis + (sign > 0)
            n_b = np.zeros((len(q), 3))
            n_b[np.arange(len(q)), axis] = sign
            n_s = n_b @ T[:3, :3].T
            alb = sc.box_face_albedo[face] * (1 + 0.1 * _hash_texture(p_b, 0.03, sc.seed + 1))
            flat_img[flat[sel]] = np.clip(alb, 0, 1) * (0.55 + 0.45 * np.abs(n_s @ self.light_dir))
        img = flat_img.reshape(h, w)
        img = cv2.GaussianBlur(img * np.float32(250.0), (0, 0), BLUR_SIGMA_PX)
        rng = rng if rng is not None else np.random.default_rng(sc.seed * 1000 + k)
        noise = rng.standard_normal(img.shape, dtype=np.float32)
        noise *= np.sqrt(np.float32(READ_NOISE_GL**2) + np.float32(SHOT_GAIN_GL) * img)
        img += noise
        return np.clip(np.rint(img), 0, 255).astype(np.uint8)


def perturbed_pose(T: F64, rot_deg: float, pos_m: float, rng: np.random.Generator) -> F64:
    """``T`` moved by a rotation of ``rot_deg`` about a random axis (about the box centre) and
    a translation of ``pos_m`` in a random direction."""
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    d = rng.normal(size=3)
    d /= np.linalg.norm(d)
    out = T.copy()
    out[:3, :3] = T[:3, :3] @ so3_exp(np.deg2rad(rot_deg) * axis)
    out[:3, 3] = T[:3, 3] + pos_m * d
    return out


def track_scenario(
    scenario: OmniScenario,
    mirror_sets: tuple[tuple[int, ...], ...] = ((0, 1, 2, 3), (0, 3)),
    init_rot_deg: float = 6.0,
    init_pos_m: float = 0.025,
    lost_rot_deg: float = 5.0,
    lost_pos_mm: float = 50.0,
    options: object | None = None,
    progress: object | None = None,
) -> tuple[list[TrackingRun], float, float]:
    """Render the scenario's frames once and track them from images with each mirror set,
    every set from the same perturbed start. Returns the runs and the start's rotation (deg)
    and position (m) error."""
    import time

    from loopmodel.geometry.se3 import so3_log
    from loopmodel.pose.image_tracking import ImageTracker, ImageTrackingOptions, mask_valid

    renderer = OmniRenderer(scenario)
    rng = np.random.default_rng(10_000 + scenario.seed)
    truth = scenario.sensor_from_box
    start = perturbed_pose(truth[0], init_rot_deg, init_pos_m, rng)
    init_rot = float(np.degrees(np.linalg.norm(so3_log(start[:3, :3].T @ truth[0][:3, :3]))))
    init_pos = float(np.linalg.norm(start[:3, 3] - truth[0][:3, 3]))
    sensor = scenario.sensor
    labels = sensor_mask(sensor)  # the rim and self-occlusion zones, cast once
    trackers = []
    for mirrors in mirror_sets:
        # the label mask of the chosen mirrors, renumbered 1..len(mirrors) in rig order
        sub = np.zeros_like(labels)
        for j, m in enumerate(mirrors):
            sub[labels == m + 1] = j + 1
        opt = options if isinstance(options, ImageTrackingOptions) else ImageTrackingOptions()
        margin = opt.edges.range_px + opt.edges.half_depth_px
        trackers.append(
            ImageTracker(sensor.rig(mirrors), scenario.model, start, mask_valid(sub, labels.shape, margin), opt)
        )
    n = len(truth)
    per = [
        {k: np.zeros(n) for k in ("rot", "pos", "matched", "inl", "ok", "iter", "frame", "search")} for _ in mirror_sets
    ]
    render_ms = []
    for k in range(n):
        t0 = time.perf_counter()
        img = renderer.render(k)
        render_ms.append((time.perf_counter() - t0) * 1e3)
        for r, tr in zip(per, trackers, strict=True):
            ft = tr.track(img)
            T = ft.rig_from_ref
            r["rot"][k] = float(np.degrees(np.linalg.norm(so3_log(T[:3, :3].T @ truth[k][:3, :3]))))
            r["pos"][k] = 1e3 * float(np.linalg.norm(T[:3, 3] - truth[k][:3, 3]))
            r["matched"][k], r["inl"][k], r["ok"][k] = ft.num_matched, ft.num_inliers, ft.ok
            r["iter"][k], r["frame"][k], r["search"][k] = ft.iter_ms, ft.frame_ms, ft.search_ms
        if callable(progress):
            progress(k)
    runs = []
    for mirrors, r in zip(mirror_sets, per, strict=True):
        ok = r["ok"].astype(bool)
        lost = (~ok) | (r["rot"] > lost_rot_deg) | (r["pos"] > lost_pos_mm)
        runs.append(
            TrackingRun(
                mirrors,
                r["rot"],
                r["pos"],
                r["matched"].astype(np.int64),
                r["inl"].astype(np.int64),
                ok,
                r["iter"],
                r["frame"],
                lost,
                r["search"],
            )
        )
    return runs, init_rot, init_pos


def sensor_mask(sensor: OmniSensor) -> U8:
    """Label image of the sensor: value ``m + 1`` where mirror ``m`` sees the scene (inside its
    rim, outside the zones its neighbours hide), 0 elsewhere."""
    w, h = sensor.image_size
    mask = np.zeros((h, w), np.uint8)
    for m, cam in enumerate(sensor.cameras):
        r_px = sensor.rim * cam.px
        us = np.arange(max(0, int(cam.u0 - r_px) - 1), min(w, int(cam.u0 + r_px) + 2))
        vs = np.arange(max(0, int(cam.v0 - r_px) - 1), min(h, int(cam.v0 + r_px) + 2))
        U, V = np.meshgrid(us, vs)
        uv = np.column_stack([U.ravel(), V.ravel()]).astype(float)
        ok = sensor.valid(m, uv)
        mask[V.ravel()[ok], U.ravel()[ok]] = m + 1
    return mask
