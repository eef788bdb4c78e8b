"""Feature-level simulation of the 4-mirror catadioptric stereo sensor of seed 002 tracking
a hand-held box in a cluttered scene.

Sensor: one orthographic camera above four parabolic mirrors (xi = 1) on a square, mirror
axes parallel to the optical axis; modelled as four central cameras ``CentralCamera`` with
their frames at the mirror foci (all axes parallel; z = optical axis, pointing from the
camera down to the mirrors; the sensor frame is mirror 1's frame). Each mirror's image is a
disc of normalised radius ``rim`` (the mirror rim). The mirrors are solids (cylinders of the
mirror radius from the vertex to the rim): a mirror sees its neighbours, which hide the
scene behind them (the self-occlusion / inter-reflection zones); those image zones are
masked as in the paper.

Rendering is feature level, not images: the moving-edge search along each sample's normal
is emulated exactly — every edge of the scene (box edges at the true pose, edges of clutter
objects, background line segments) whose projected conic crosses the search segment is a
candidate; candidates are kept when the 3-D point is visible from the mirror focus (open3d
``RaycastingScene`` against the clutter and the other mirrors, an exact ray/box test for
the moving box incl. its own hidden faces), inside the rim, and oriented like the searched
edge; the strongest (contrast x orientation) wins, and its position gets Gaussian noise.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import open3d as o3d
from numpy.typing import NDArray

from loopmodel.geometry.camera import CentralCamera
from loopmodel.geometry.se3 import invert_pose, make_pose, so3_exp
from loopmodel.pose.rig import F64, CameraRig
from loopmodel.pose.tracking import PolyhedronModel, TrackerOptions
from loopmodel.pose.vvs import conic_gradient, line_conics

BOX_SIZE_M = (0.30, 0.25, 0.20)
_SIDE_M = 0.08  # distance between neighbouring mirror foci


@dataclass
class OmniSensor:
    """The 4-mirror sensor: mirror cameras, foci in the sensor frame (metres), mirror radius
    and the extent of the mirror solid along z (vertex below the focus, rim above)."""

    cameras: tuple[CentralCamera, ...]
    foci_m: F64  # (4, 3) in the sensor frame (= mirror 1 frame)
    mirror_radius_m: float
    z_vertex_m: float  # > 0: below the focus (z points down)
    z_rim_m: float  # < 0: above the focus
    rim: float  # normalised image radius of the mirror rim
    image_size: tuple[int, int]
    _scenes: list[o3d.t.geometry.RaycastingScene] = field(default_factory=list, repr=False)

    def rig(self, mirrors: tuple[int, ...] = (0, 1, 2, 3)) -> CameraRig:
        """Rig of the listed mirrors; its frame is the sensor frame (mirror 1)."""
        cams = tuple(self.cameras[m] for m in mirrors)
        poses = tuple(make_pose(np.eye(3), -self.foci_m[m]) for m in mirrors)
        return CameraRig(cams, poses)

    def _mirror_scene(self, m: int) -> o3d.t.geometry.RaycastingScene:
        while len(self._scenes) <= m:
            k = len(self._scenes)
            scene = o3d.t.geometry.RaycastingScene()
            height = self.z_vertex_m - self.z_rim_m
            for other in range(len(self.cameras)):
                if other == k:
                    continue
                cyl = o3d.geometry.TriangleMesh.create_cylinder(
                    radius=self.mirror_radius_m, height=height, resolution=48
                )
                centre = self.foci_m[other] + [0, 0, 0.5 * (self.z_vertex_m + self.z_rim_m)]
                cyl.translate(centre)
                scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(cyl))
            self._scenes.append(scene)
        return self._scenes[m]

    def valid(self, m: int, uv_px: F64) -> NDArray[np.bool_]:
        """Pixels of mirror ``m`` inside its rim and outside the mask of the other mirrors."""
        cam = self.cameras[m]
        xy = (uv_px - [cam.u0, cam.v0]) / [cam.px, cam.py]
        inside = np.hypot(xy[:, 0], xy[:, 1]) <= self.rim
        out = np.zeros(len(uv_px), dtype=bool)
        if inside.any():
            rays = cam.lift(uv_px[inside])
            hit = _cast(self._mirror_scene(m), self.foci_m[m], rays)
            out[np.flatnonzero(inside)] = ~np.isfinite(hit)
        return out


def _cast(scene: o3d.t.geometry.RaycastingScene, origin: F64, dirs: F64) -> F64:
    """Distance to the first hit along unit rays (inf: none)."""
    r = np.empty((len(dirs), 6), dtype=np.float32)
    r[:, :3] = origin
    r[:, 3:] = dirs
    return scene.cast_rays(o3d.core.Tensor(r))["t_hit"].numpy().astype(float)  # type: ignore[call-overload]


def omni_sensor(
    side_m: float = _SIDE_M,
    mirror_radius_m: float = 0.035,
    semi_latus_m: float = 0.02,
    image_size: tuple[int, int] = (1024, 1024),
) -> OmniSensor:
    """The sensor: 4 parabolic mirrors (xi = 1) on a square of side ``side_m``, mirror 1
    top-left, 2 top-right, 3 bottom-left, 4 bottom-right (1 and 4: widest baseline). The
    paraboloid ``z = (h^2 - r^2) / (2h)`` (z down, focus at 0) ends at the mirror radius."""
    h = semi_latus_m
    z_rim = (h * h - mirror_radius_m**2) / (2 * h)  # negative: above the focus
    theta_max = np.pi / 2 + np.arctan2(-z_rim, mirror_radius_m)  # from +z (down)
    rim = float(np.tan(theta_max / 2))
    w, hgt = image_size
    disc_px = 0.23 * min(w, hgt)  # image radius of a mirror disc
    f = disc_px / rim
    offs = [(-1, -1), (1, -1), (-1, 1), (1, 1)]
    cams = tuple(
        CentralCamera(f, f, w / 2 + sx * w / 4, hgt / 2 + sy * hgt / 4, 1.0) for sx, sy in offs
    )
    foci = np.array([[sx * side_m / 2, sy * side_m / 2, 0.0] for sx, sy in offs])
    foci -= foci[0]
    return OmniSensor(cams, foci, mirror_radius_m, h / 2, z_rim, rim, image_size)


# --------------------------------------------------------------------------- scene


@dataclass
class ClutterScene:
    """Static clutter: boxes (occluders with edges) and background line segments, each line
    with an edge contrast; per-mirror ray-casting scenes with the clutter and the other
    mirrors."""

    lines: F64  # (K, 2, 3) sensor frame
    contrast: F64  # (K,)
    polarity: F64  # (K,) +-1
    boxes: list[tuple[F64, F64]]  # (sensor_from_box, size)
    sensor: OmniSensor
    _scenes: list[o3d.t.geometry.RaycastingScene] = field(default_factory=list, repr=False)

    def scene(self, m: int) -> o3d.t.geometry.RaycastingScene:
        while len(self._scenes) <= m:
            k = len(self._scenes)
            sc = o3d.t.geometry.RaycastingScene()
            s = self.sensor
            for other in range(len(s.cameras)):
                if other == k:
                    continue
                cyl = o3d.geometry.TriangleMesh.create_cylinder(
                    radius=s.mirror_radius_m, height=s.z_vertex_m - s.z_rim_m, resolution=48
                )
                cyl.translate(s.foci_m[other] + [0, 0, 0.5 * (s.z_vertex_m + s.z_rim_m)])
                sc.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(cyl))
            for T, size in self.boxes:
                mesh = o3d.geometry.TriangleMesh.create_box(*size)
                mesh.translate(-0.5 * np.asarray(size))
                mesh.transform(T)
                sc.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(mesh))
            self._scenes.append(sc)
        return self._scenes[m]


def clutter_scene(sensor: OmniSensor, seed: int = 7, n_boxes: int = 16, n_posters: int = 40) -> ClutterScene:
    """Boxes 0.95-1.6 m around the sensor and rectangular 'posters' (edges only) on a
    cylinder of radius 2.2 m, all in the mirrors' field of view."""
    rng = np.random.default_rng(seed)
    lines, contrast, boxes = [], [], []
    for _ in range(n_boxes):
        az = rng.uniform(0, 2 * np.pi)
        dist = rng.uniform(0.95, 1.6)
        size = rng.uniform([0.1, 0.1, 0.1], [0.45, 0.45, 0.6])
        z = rng.uniform(-0.2, 0.35)
        T = make_pose(so3_exp([0, 0, rng.uniform(0, np.pi)]), [dist * np.cos(az), dist * np.sin(az), z])
        boxes.append((T, size))
        model = PolyhedronModel.box(tuple(size))
        L = model.lines @ T[:3, :3].T + T[:3, 3]
        lines.append(L)
        contrast.append(rng.uniform(0.2, 1.3, len(L)))
    for _ in range(n_posters):
        az = rng.uniform(0, 2 * np.pi)
        w, hgt = rng.uniform(0.2, 0.8), rng.uniform(0.2, 0.8)
        zc = rng.uniform(-0.6, 0.9)
        R = 2.2
        c, t = np.array([np.cos(az), np.sin(az), 0.0]), np.array([-np.sin(az), np.cos(az), 0.0])
        base = R * c + [0, 0, zc]
        up = np.array([0, 0, 1.0])
        corners = [base + a * w / 2 * t + b * hgt / 2 * up for a, b in ((-1, -1), (1, -1), (1, 1), (-1, 1))]
        L = np.array([[corners[i], corners[(i + 1) % 4]] for i in range(4)])
        lines.append(L)
        contrast.append(rng.uniform(0.2, 1.3, 4))
    # a bookshelf behind the inter-reflection zone of mirrors 1 and 4: shelf boards and
    # the front rectangles of many books (dense edges parallel to the box edges)
    centre = np.array([0.5, 0.5, 0.0]) * _SIDE_M
    for az_deg in np.arange(20.0, 72.0, 1.6):
        az = np.deg2rad(az_deg + rng.uniform(-0.4, 0.4))
        c, t = np.array([np.cos(az), np.sin(az), 0.0]), np.array([-np.sin(az), np.cos(az), 0.0])
        for shelf_z in (-0.45, -0.12, 0.21):  # z down: shelf bottoms
            if rng.random() < 0.15:
                continue  # a gap
            height = rng.uniform(0.15, 0.3)
            width = rng.uniform(0.015, 0.035)
            base = centre + 1.25 * c + [0, 0, shelf_z]
            top = base - [0, 0, height]
            corners = [base - width / 2 * t, base + width / 2 * t, top + width / 2 * t, top - width / 2 * t]
            lines.append(np.array([[corners[i], corners[(i + 1) % 4]] for i in range(4)]))
            contrast.append(rng.uniform(0.3, 1.0, 4))
    for shelf_z in (-0.45, -0.12, 0.21, 0.5):
        a0, a1 = np.deg2rad(18.0), np.deg2rad(74.0)
        pts = [centre + 1.25 * np.array([np.cos(a), np.sin(a), 0.0]) + [0, 0, shelf_z] for a in np.linspace(a0, a1, 7)]
        lines.append(np.array([[pts[i], pts[i + 1]] for i in range(6)]))
        contrast.append(rng.uniform(0.4, 1.0, 6))
    con = np.concatenate(contrast)
    pol = rng.choice([-1.0, 1.0], len(con))
    return ClutterScene(np.vstack(lines), con, pol, boxes, sensor)


def box_trajectory(n_frames: int = 312, seed: int = 3) -> list[F64]:
    """``sensor_from_box`` of a hand-held box (10 frames/s): centre 40-70 cm from the
    sensor, sweeping about 200 degrees of azimuth around it, turned and tilted by the hand;
    in the last fifth it moves, shaken faster, into the inter-reflection zone of the
    diagonal mirrors 1 and 4 (behind mirror 4 as seen from mirror 1, at mirror height)."""
    from scipy.interpolate import PchipInterpolator

    rng = np.random.default_rng(seed)
    u = np.linspace(0.0, 1.0, n_frames)
    keys = np.array([0.0, 0.2, 0.4, 0.6, 0.77, 0.87, 1.0])

    def curve(values: list[float]) -> F64:
        return np.asarray(PchipInterpolator(keys, values)(u))

    az = np.deg2rad(curve([-150, -100, -45, -5, 30, 45, 47]) + 6 * np.sin(2 * np.pi * 2.3 * u))
    dist = curve([0.55, 0.42, 0.65, 0.45, 0.60, 0.70, 0.70])
    z = curve([0.05, 0.08, 0.0, 0.06, 0.01, -0.025, -0.025])
    shake = np.clip((u - 0.77) / 0.1, 0.0, 1.0)  # faster hand motion at the end
    t_s = np.arange(n_frames) / 10.0
    # radial frame (x out, y tangential, z down); the box shows a corner (two side faces)
    # and, tilted towards the sensor, its top face; the hand turns and tilts it
    spin = np.deg2rad(45 + 20 * np.sin(2 * np.pi * 1.7 * u) + 15 * shake * np.sin(2 * np.pi * 0.8 * t_s))
    tilt = np.deg2rad(24 + 8 * np.sin(2 * np.pi * 1.3 * u + 2.0) + 8 * shake * np.sin(2 * np.pi * 0.6 * t_s))
    roll = np.deg2rad(8 * np.sin(2 * np.pi * 0.9 * u + 1.0))
    z = z + 0.015 * shake * np.sin(2 * np.pi * 0.7 * t_s + 1.0)
    tremor = rng.normal(0, 0.0015, (n_frames, 3)) * (1.0 + shake)[:, None]
    centre = np.array([0.5, 0.5, 0.0])  # the sensor centre between the mirrors, metres/side
    out = []
    for k in range(n_frames):
        R = so3_exp([0, 0, az[k]]) @ so3_exp([0, tilt[k], 0]) @ so3_exp([roll[k], 0, 0])
        R = R @ so3_exp([0, 0, spin[k]])
        p = np.array([dist[k] * np.cos(az[k]), dist[k] * np.sin(az[k]), z[k]]) + tremor[k]
        out.append(make_pose(R, p + centre * _SIDE_M))
    return out


def _ray_box_entry(origin: F64, dirs: F64, box_from_sensor: F64, half: F64) -> F64:
    """Entry distance of unit rays into an oriented box (inf: miss)."""
    o = box_from_sensor[:3, :3] @ origin + box_from_sensor[:3, 3]
    d = dirs @ box_from_sensor[:3, :3].T
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / d
        t1 = (-half - o) * inv
        t2 = (half - o) * inv
    tmin = np.nanmax(np.minimum(t1, t2), axis=1)
    tmax = np.nanmin(np.maximum(t1, t2), axis=1)
    hit = (tmax >= tmin) & (tmax > 0)
    return np.where(hit, np.maximum(tmin, 0.0), np.inf)


@dataclass
class MovingEdgeSimulator:
    """Moving-edge search emulation for one frame (true box pose ``sensor_from_box``).

    Like ViSP's moving edges, a site accepts a candidate only with the polarity of its edge
    and a contrast within ``[contrast_low, contrast_high]`` times the contrast it measured
    in the previous frame (``expected_contrast``, per rig camera and model edge: the sites'
    memory, which follows whatever they matched, clutter included); among those, the most
    similar contrast wins. ``matched`` records, per camera, what the sites matched.
    Positions are found on the integer pixel grid along the normal (quantisation)
    after Gaussian image noise ``noise_px``.
    """

    sensor: OmniSensor
    clutter: ClutterScene
    model: PolyhedronModel
    sensor_from_box: F64
    box_contrast: F64  # (E,) this frame
    expected_contrast: F64  # (N, E) what each camera's edge sites matched in the last frame
    box_polarity: F64  # (E,) +-1 (true edges)
    site_polarity: F64  # (N, E) +-1 the polarity each camera's edge sites look for
    mirrors: tuple[int, ...]
    search_px: int = 10
    noise_px: float = 0.15
    max_angle_deg: float = 30.0
    contrast_low: float = 0.5
    contrast_high: float = 1.5
    min_contrast: float = 0.3  # the gradient threshold: weaker edges are not detected
    spurious_rate: float = 0.15  # texture edges per search (Poisson mean)
    rng: np.random.Generator = field(default_factory=lambda: np.random.default_rng(0))
    matched: dict[int, tuple[NDArray[np.int64], F64, F64]] = field(default_factory=dict)

    def measure(
        self, j: int, uv: F64, normals: F64, line_index: NDArray[np.int64]
    ) -> tuple[NDArray[np.bool_], F64]:
        m = self.mirrors[j]
        cam = self.sensor.cameras[m]
        focus = self.sensor.foci_m[m]
        box_lines = self.model.lines @ self.sensor_from_box[:3, :3].T + self.sensor_from_box[:3, 3]
        L = np.concatenate([box_lines, self.clutter.lines])
        contrast = np.concatenate([self.box_contrast, self.clutter.contrast])
        polarity = np.concatenate([self.box_polarity, self.clutter.polarity])
        Lc = L - focus  # mirror frame (axes parallel to the sensor frame)
        lc = line_conics(Lc[:, 0], Lc[:, 1], cam.xi)
        p = (uv - [cam.u0, cam.v0]) / [cam.px, cam.py]  # (n, 2) normalised
        nn = normals / [cam.px, cam.py]  # normalised units per pixel of search
        a = lc.a
        # Q(p + s n) = q0 + q1 s + q2 s^2 for every (sample, line)
        x, y = p[:, 0:1], p[:, 1:2]
        nx, ny = nn[:, 0:1], nn[:, 1:2]
        a0, a1, a2, a3, a4 = (a[:, i][None, :] for i in range(5))
        q0 = a0 * x * x + a1 * y * y + 2 * a2 * x * y + 2 * a3 * x + 2 * a4 * y + 1
        q1 = 2 * (a0 * x * nx + a1 * y * ny + a2 * (x * ny + y * nx) + a3 * nx + a4 * ny)
        q2 = a0 * nx * nx + a1 * ny * ny + 2 * a2 * nx * ny
        disc = q1 * q1 - 4 * q2 * q0
        ok = (disc >= 0) & lc.valid[None, :]
        sq = np.sqrt(np.where(ok, disc, 0.0))
        with np.errstate(divide="ignore", invalid="ignore"):
            lin = np.abs(q2) < 1e-12 * (np.abs(q1) + 1e-300)
            r1 = np.where(lin, -q0 / q1, (-q1 - sq) / (2 * q2))
            r2 = np.where(lin, np.inf, (-q1 + sq) / (2 * q2))
        roots = np.stack([r1, r2], axis=2)  # (n, K, 2) in pixels along the normal
        cand = ok[:, :, None] & np.isfinite(roots) & (np.abs(roots) <= self.search_px)
        si, ki, ri = np.nonzero(cand)
        s = roots[si, ki, ri]
        found = np.zeros(len(uv), dtype=bool)
        pos = np.zeros(len(uv))
        best = np.full(len(uv), np.inf)  # contrast dissimilarity of the chosen candidate
        expected = self.expected_contrast[j, line_index]
        site_pol = self.site_polarity[j, line_index]
        got_c = np.zeros(len(uv))
        got_p = np.zeros(len(uv))
        if si.size:
            q = p[si] + s[:, None] * nn[si]
            rays = cam.lift(q * [cam.px, cam.py] + [cam.u0, cam.v0])
            P0, D = Lc[ki, 0], Lc[ki, 1] - Lc[ki, 0]
            # ray (lam r) and line (P0 + mu D): closest points
            rd = np.einsum("ij,ij->i", rays, D)
            dd = np.einsum("ij,ij->i", D, D)
            rp = np.einsum("ij,ij->i", rays, P0)
            dp = np.einsum("ij,ij->i", D, P0)
            den = dd - rd * rd
            lam = (rp * dd - rd * dp) / np.where(den > 1e-12, den, 1.0)
            mu = (lam * rd - dp) / dd
            keep = (lam > 0) & (mu >= 0) & (mu <= 1) & (den > 1e-12)
            keep &= np.hypot(q[:, 0], q[:, 1]) <= self.sensor.rim
            # orientation and polarity of the candidate edge vs the searched one
            g = conic_gradient(a[ki], q) / [cam.px, cam.py]
            g /= np.maximum(np.linalg.norm(g, axis=1, keepdims=True), 1e-300)
            cosang = np.abs(np.einsum("ij,ij->i", g, normals[si]))
            keep &= cosang >= np.cos(np.deg2rad(self.max_angle_deg))
            keep &= polarity[ki] == site_pol[si]
            ratio = contrast[ki] * cosang / expected[si]
            keep &= (ratio >= self.contrast_low) & (ratio <= self.contrast_high)
            keep &= contrast[ki] * cosang >= self.min_contrast
            if keep.any():
                idx = np.flatnonzero(keep)
                vis = self._visible(m, rays[idx], lam[idx], ki[idx])
                idx = idx[vis]
                dis = np.abs(np.log(ratio[idx]))
                order = np.argsort(-dis)  # later (more similar) writes win
                sel = idx[order]
                best[si[sel]] = dis[order]
                found[si[sel]] = True
                pos[si[sel]] = s[sel]
                got_c[si[sel]] = contrast[ki[sel]] * cosang[sel]
                got_p[si[sel]] = polarity[ki[sel]]
        # background texture: spurious edges of random polarity and contrast
        n_sp = self.rng.poisson(self.spurious_rate, len(uv))
        for i in np.flatnonzero(n_sp):
            for _ in range(n_sp[i]):
                if self.rng.random() < 0.5:
                    continue  # the other polarity
                c_i = self.rng.uniform(0.1, 1.3)
                ratio_i = c_i / expected[i]
                dis_i = abs(np.log(ratio_i))
                ok_i = self.contrast_low <= ratio_i <= self.contrast_high and c_i >= self.min_contrast
                if ok_i and dis_i < best[i]:
                    best[i] = dis_i
                    found[i] = True
                    pos[i] = self.rng.uniform(-self.search_px, self.search_px)
                    got_c[i], got_p[i] = c_i, site_pol[i]
        pos = np.clip(np.round(pos + self.rng.normal(0, self.noise_px, len(uv))), -self.search_px, self.search_px)
        self.matched[j] = (line_index[found], got_c[found], got_p[found])
        return found, uv + pos[:, None] * normals

    def _visible(self, m: int, rays: F64, lam: F64, line_k: NDArray[np.int64]) -> NDArray[np.bool_]:
        focus = self.sensor.foci_m[m]
        hit = _cast(self.clutter.scene(m), focus, rays)
        box_from_sensor = invert_pose(self.sensor_from_box)
        half = np.abs(self.model.vertices).max(axis=0)
        t_box = _ray_box_entry(focus, rays, box_from_sensor, half)
        tol = 0.004 + 0.004 * lam
        is_box = line_k < len(self.model.edges)
        # box edges lie on the box surface: compare with the entry distance; clutter edges
        # behind the box are hidden when the ray enters the box first
        vis = hit >= lam - tol
        vis &= np.where(is_box, t_box >= lam - tol, t_box > lam)
        return vis


# --------------------------------------------------------------------------- sequence


@dataclass
class TrackingRun:
    """Per-frame results of a simulated tracking run (``sensor_from_box`` estimates)."""

    mirrors: tuple[int, ...]
    rot_err_deg: F64
    pos_err_mm: F64
    num_matched: NDArray[np.int64]
    num_inliers: NDArray[np.int64]
    tracker_ok: NDArray[np.bool_]
    iter_ms: F64  # one VVS iteration (all cameras), per frame
    frame_ms: F64  # sampling + edge search + VVS, per frame
    lost: NDArray[np.bool_]
    search_ms: F64 | None = None  # the moving-edge search alone, per frame (image tracking)


def simulate_tracking(
    mirrors: tuple[int, ...] = (0, 1, 2, 3),
    n_frames: int = 312,
    seed: int = 0,
    lost_rot_deg: float = 5.0,
    lost_pos_mm: float = 50.0,
    options: TrackerOptions | None = None,
    search_px: int = 10,
    edge_noise_px: float = 0.15,
    progress: Callable[[int], None] | None = None,
    start_frame: int = 0,
    stop_frame: int | None = None,
) -> TrackingRun:
    """Track the box through the simulated sequence with the listed mirrors, starting from
    the true pose of ``start_frame`` (frames before it, and from ``stop_frame`` on, are
    skipped). A frame is lost when the tracker fails or the pose error exceeds
    ``lost_rot_deg`` / ``lost_pos_mm``; tracking continues from the estimate (no reset)."""
    import time

    from loopmodel.geometry.se3 import so3_log
    from loopmodel.pose.tracking import track_frame

    opt = options or TrackerOptions()
    sensor = omni_sensor()
    clutter = clutter_scene(sensor)
    model = PolyhedronModel.box(BOX_SIZE_M)
    rig = sensor.rig(mirrors)
    truth = box_trajectory(n_frames)[start_frame:stop_frame]
    rng = np.random.default_rng(seed)
    phase = rng.uniform(0, 2 * np.pi, len(model.edges))
    polarity = rng.choice([-1.0, 1.0], len(model.edges))
    T = truth[0].copy()
    n = len(truth)
    rot, pos = np.zeros(n), np.zeros(n)
    matched, inl = np.zeros(n, np.int64), np.zeros(n, np.int64)
    ok, it_ms, fr_ms = np.zeros(n, bool), np.zeros(n), np.zeros(n)

    def valid(j: int, uv: F64) -> NDArray[np.bool_]:
        return sensor.valid(mirrors[j], uv)

    # the edge sites' memory (per camera and model edge), initialised on the first image
    site_c = np.tile(0.6 + 0.35 * np.sin(2 * np.pi * start_frame / 90.0 + phase), (len(mirrors), 1))
    site_p = np.tile(polarity, (len(mirrors), 1))
    for k in range(n):
        # illumination changes: each edge's contrast drifts between 0.25 and 0.95
        kk = k + start_frame
        contrast = 0.6 + 0.35 * np.sin(2 * np.pi * kk / 90.0 + phase)
        me = MovingEdgeSimulator(
            sensor, clutter, model, truth[k], contrast, site_c, polarity, site_p, mirrors,
            search_px=search_px, noise_px=edge_noise_px, rng=rng,
        )
        t0 = time.perf_counter()
        res = track_frame(rig, model, T, me.measure, opt, valid)
        fr_ms[k] = 1e3 * (time.perf_counter() - t0)
        # the sites remember what they matched, except those the M-estimator rejected
        # (ViSP suppresses such sites); the term lists the matches camera by camera
        w_all = res.vvs.weights[0] if res.vvs is not None else None
        start_w = 0
        for j in sorted(me.matched):
            li, cj, pj = me.matched[j]
            w = w_all[start_w : start_w + len(li)] if w_all is not None else np.ones(len(li))
            start_w += len(li)
            good = w > 0.5
            for m in np.unique(li[good]):
                sel = good & (li == m)
                site_c[j, m] = float(np.median(cj[sel]))
                site_p[j, m] = 1.0 if pj[sel].sum() >= 0 else -1.0
        T = res.rig_from_ref
        rot[k] = float(np.degrees(np.linalg.norm(so3_log(T[:3, :3].T @ truth[k][:3, :3]))))
        pos[k] = 1e3 * float(np.linalg.norm(T[:3, 3] - truth[k][:3, 3]))
        matched[k], inl[k], ok[k] = res.num_matched, res.num_inliers, res.ok
        it_ms[k] = res.vvs.info.get("iter_ms", np.nan) if res.vvs is not None else np.nan
        if progress is not None:
            progress(k)
    lost = (~ok) | (rot > lost_rot_deg) | (pos > lost_pos_mm)
    return TrackingRun(mirrors, rot, pos, matched, inl, ok, it_ms, fr_ms, lost)


def tracking_csv(runs: list[TrackingRun]) -> str:
    """Per-frame errors of one or more runs as CSV text (one block of columns per run)."""
    cols = ["frame"]
    for r in runs:
        tag = f"m{len(r.mirrors)}"
        names = ("rot_err_deg", "pos_err_mm", "matched", "inliers", "ok", "lost", "iter_ms", "frame_ms")
        cols += [f"{tag}_{c}" for c in names]
    lines = [",".join(cols)]
    n = len(runs[0].rot_err_deg)
    for k in range(n):
        row = [str(k)]
        for r in runs:
            row += [
                repr(float(r.rot_err_deg[k])), repr(float(r.pos_err_mm[k])), str(int(r.num_matched[k])),
                str(int(r.num_inliers[k])), str(int(r.tracker_ok[k])), str(int(r.lost[k])),
                repr(float(r.iter_ms[k])), repr(float(r.frame_ms[k])),
            ]
        lines.append(",".join(row))
    return "\n".join(lines) + "\n"


def tracking_figure(runs: list[TrackingRun]) -> object:
    """Rotation and position errors per frame (log scale), lost frames shaded."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(3, 1, figsize=(9, 8), sharex=True)
    for r in runs:
        label = f"{len(r.mirrors)} mirrors ({int(r.lost.sum())} lost)"
        frames = np.arange(len(r.rot_err_deg))
        axes[0].semilogy(frames, np.maximum(r.rot_err_deg, 1e-4), label=label)
        axes[1].semilogy(frames, np.maximum(r.pos_err_mm, 1e-3), label=label)
        axes[2].plot(frames, r.num_inliers, label=label)
    axes[0].set_ylabel("rotation error (deg)")
    axes[1].set_ylabel("position error (mm)")
    axes[2].set_ylabel("inlier edge points")
    axes[2].set_xlabel("frame")
    for ax in axes:
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(loc="upper left", fontsize=8)
    fig.suptitle("VVS tracking of the box, simulated omnidirectional stereo sensor")
    fig.tight_layout()
    return fig


def manufactured_rig(sensor: OmniSensor, seed: int = 0) -> CameraRig:
    """A sensor as built, not as designed: each mirror camera's focal lengths off by up to
    3 %, principal point by a few pixels, ``xi`` between 0.95 and 1 (a lens that is not
    exactly telecentric makes the parabolic mirror's effective ``xi`` smaller than 1), each
    mirror tilted by about 0.5 deg and displaced by about 2 mm (assembly tolerances). Mirror 1
    keeps the rig frame."""
    rng = np.random.default_rng(seed + 1)
    design = sensor.rig()
    cams = tuple(
        CentralCamera(
            c.px * rng.uniform(0.97, 1.03),
            c.py * rng.uniform(0.97, 1.03),
            c.u0 + rng.normal(0, 4),
            c.v0 + rng.normal(0, 4),
            float(rng.uniform(0.95, 1.0)),
        )
        for c in design.cameras
    )
    poses = [design.cam_from_rig[0].copy()]
    for T in design.cam_from_rig[1:]:
        D = make_pose(so3_exp(rng.normal(0, np.deg2rad(0.5), 3)), rng.normal(0, 0.002, 3))
        poses.append(D @ T)
    return CameraRig(cams, tuple(poses))


def calibration_views(
    sensor: OmniSensor, n_views: int = 8, noise_px: float = 0.3, seed: int = 0, rig: CameraRig | None = None
) -> tuple[list[tuple[F64, F64, NDArray[np.int64]]], list[F64]]:
    """Views of a 3-D calibration object (points on three faces of a 40 cm corner) around
    the sensor: per view ``(p_in_ref, uv_px, cam_index)`` and the true ``sensor_from_ref``.
    Points hidden by the other mirrors or outside a rim are not observed. ``rig``: the
    cameras that see them (default: the sensor as designed)."""
    rng = np.random.default_rng(seed)
    g = np.linspace(-0.15, 0.15, 6)
    A, B = np.meshgrid(g, g)
    obj = np.vstack(
        [
            np.column_stack([A.ravel(), B.ravel(), np.full(A.size, -0.15)]),
            np.column_stack([A.ravel(), np.full(A.size, -0.15), B.ravel()]),
            np.column_stack([np.full(A.size, -0.15), A.ravel(), B.ravel()]),
        ]
    )
    rig = rig if rig is not None else sensor.rig()
    views, poses = [], []
    for v in range(n_views):
        az = 2 * np.pi * v / n_views + rng.uniform(-0.3, 0.3)
        d = rng.uniform(0.45, 0.7)
        R = so3_exp([0, 0, az + np.pi + np.pi / 4]) @ so3_exp(rng.normal(0, 0.2, 3))
        T = make_pose(R, [d * np.cos(az), d * np.sin(az), rng.uniform(-0.05, 0.1)])
        P, uv, ci = [], [], []
        for j, cam in enumerate(rig.cameras):
            p_cam = obj @ (rig.cam_from_rig[j] @ T)[:3, :3].T + (rig.cam_from_rig[j] @ T)[:3, 3]
            ok = cam.in_front(p_cam)
            pix = cam.project(p_cam[ok])
            keep = sensor.valid(j, pix)
            P.append(obj[ok][keep])
            uv.append(pix[keep] + rng.normal(0, noise_px, (int(keep.sum()), 2)))
            ci.append(np.full(int(keep.sum()), j))
        views.append((np.vstack(P), np.vstack(uv), np.concatenate(ci)))
        poses.append(T)
    return views, poses
