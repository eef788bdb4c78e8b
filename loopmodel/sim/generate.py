"""Generate a synthetic hand-held scan and write it as MCAP (topics of DESIGN.md).

Per frame: a rectified stereo pair rendered by ray casting, one laser-stripe profile (left
camera frame), the ground-truth ``world_from_cam0``, optionally the laser-line image. In the
realistic world (``realism.level``, issue 17) the pair is unrectified and distorted and goes
through the sensor model of :mod:`loopmodel.sim.sensor`, the recorded calibration is off by
a stated error, and the stripe is only imaged (``/laser/image``; the true stripe is written
to ``/ground_truth/laser_stripe`` for evaluation). The
scene mesh rides along as attachments ``scene.ply`` (everything) and ``object.ply``; the
generator's parameters and the injected faults (with frame and time ranges) are MCAP
metadata records ``simulation`` and ``faults``. All randomness derives from the seed, per
frame, so the content does not depend on the number of worker processes.
"""

from __future__ import annotations

import contextlib
import json
import logging
import multiprocessing as mp
import os
import pickle
import shlex
import shutil
import signal
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Generator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from loopmodel import __version__
from loopmodel.config import SimulationConfig, TopicsConfig
from loopmodel.errors import ConfigError, InputError
from loopmodel.geometry.camera import CentralCamera
from loopmodel.geometry.se3 import invert_pose, so3_exp
from loopmodel.io.atomic import check_output_file, write_bytes_atomic
from loopmodel.io.mcap_io import McapSequenceWriter
from loopmodel.open3d_import import start_without_plotly_viewer
from loopmodel.sim.faults import FaultPlan, cam_from_occluder
from loopmodel.sim.laser import (
    LaserPlane,
    draw_laser_image,
    realistic_laser_image,
    stripe_profile,
    stripe_reflectance,
)
from loopmodel.sim.render import RayBundle, Raycaster, View, pixel_rays, to_tensor
from loopmodel.sim.scene import Scene, build_scene
from loopmodel.sim.sensor import (
    SensorModel,
    TrueRig,
    auto_exposure,
    defocus,
    defocus_sigma_px,
    motion_blur,
    vignetting_map,
)
from loopmodel.sim.trajectory import HandheldPath
from loopmodel.types import StereoCalibration, StereoFrame, StripeProfile

logger = logging.getLogger(__name__)

F64 = NDArray[np.float64]

_REAL: dict[str, object] = {"level": "realistic"}
PRESETS: dict[str, dict[str, dict[str, object]]] = {
    "orbit": {"trajectory": {"kind": "orbit", "frames": 600}, "realism": _REAL},
    "sweeps": {"trajectory": {"kind": "sweeps", "frames": 750}, "realism": _REAL},
    "browse": {"trajectory": {"kind": "browse", "frames": 450}, "realism": _REAL},
    # seed 004's scan: 4 sweeps over 90 deg, a loop closure, a second orbit (120 s at 25 Hz)
    "modeler": {"trajectory": {"kind": "modeler", "frames": 3000}, "realism": _REAL},
    # the scale bench's long scan (issue 33): 16 rounds at other heights and distances, 400 s at 25 Hz
    "rounds": {"trajectory": {"kind": "rounds", "frames": 10000, "sweeps": 16}, "realism": _REAL},
}
REALISM_LEVELS = ("clean", "realistic")

_NOISE_STREAM, _STRIPE_STREAM, _LASER_STREAM = 11, 13, 31
GT_STRIPE_TOPIC = "/ground_truth/laser_stripe"  # realistic world: the true stripe (not used by the pipeline)
MAX_BLUR_PX = 60.0


# ----------------------------------------------------------------------------- set-up


def camera_of(cfg: SimulationConfig) -> CentralCamera:
    """Left (and right) camera model of the configuration (pixels; unified model with xi)."""
    c = cfg.camera
    fy = c.fy_px if c.fy_px is not None else c.fx_px
    cx = c.cx_px if c.cx_px is not None else (c.width_px - 1) / 2.0
    cy = c.cy_px if c.cy_px is not None else (c.height_px - 1) / 2.0
    return CentralCamera(c.fx_px, fy, cx, cy, c.xi)


def realistic(cfg: SimulationConfig) -> bool:
    """True for the realistic world (issue 17), False for the clean one."""
    return cfg.realism.level == "realistic"


def rig_of(cfg: SimulationConfig) -> TrueRig:
    """The true (distorted, unrectified) rig of a realistic configuration and its recorded calibration.

    The recorded calibration is off by the configured calibration errors.
    """
    if cfg.camera.xi != 0:
        raise ConfigError("simulation.realism.level", "the realistic world needs a pinhole camera (xi = 0)")
    r = cfg.realism
    return TrueRig.create(
        camera_of(cfg).K,
        cfg.camera.baseline_m,
        (cfg.camera.width_px, cfg.camera.height_px),
        cfg.seed,
        r.calib_focal_err_px,
        r.calib_pp_err_px,
        r.calib_k1_err,
        r.calib_rot_err_deg,
        r.calib_baseline_err_m,
    )


_RIG_RAYS: dict[str, tuple[NDArray[np.float32], NDArray[np.float32]]] = {}


def _rig_key(cfg: SimulationConfig) -> str:
    """What the realistic rig's pixel rays depend on: the seed, the camera and the realism section."""
    return f"{cfg.seed}|{cfg.camera.model_dump_json()}|{cfg.realism.model_dump_json()}"


def rig_rays(cfg: SimulationConfig) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
    """The realistic rig's left and right pixel rays (3 x H*W, camera frames; :meth:`TrueRig.rays`).

    Computed once per process and configuration (the last one kept): planning and every render
    worker need them, and undistorting every pixel costs about 0.2 s of CPU per camera.
    """
    key = _rig_key(cfg)
    if key not in _RIG_RAYS:
        rig = rig_of(cfg)
        rays = (rig.rays(False), rig.rays(True))
        _RIG_RAYS.clear()
        _RIG_RAYS[key] = rays
    return _RIG_RAYS[key]


def calibration_of(cfg: SimulationConfig) -> StereoCalibration:
    """The calibration a recording carries.

    Rectified (identical K, right camera ``baseline_m`` along +x) in the clean world; the realistic
    rig's recorded (erroneous, unrectified, distorted) calibration otherwise.
    """
    if realistic(cfg):
        if cfg.camera.fisheye_k is not None:  # the realistic rig renders through its own lens model
            raise ConfigError(
                "simulation.camera.fisheye_k", "a fisheye rig is simulated in the clean world only (--realism clean)"
            )
        return rig_of(cfg).recorded
    K = camera_of(cfg).K
    right_from_left = np.eye(4)
    right_from_left[0, 3] = -cfg.camera.baseline_m
    size = (cfg.camera.width_px, cfg.camera.height_px)
    if cfg.camera.fisheye_k is not None:  # raw fisheye images, rectified by the front end
        if cfg.laser.image:
            raise ConfigError("simulation.camera.fisheye_k", "laser-line images are drawn pinhole; set laser.image off")
        k = np.asarray(cfg.camera.fisheye_k, dtype=float)
        return StereoCalibration(K, K, right_from_left, size, k, k, False, "equidistant").check("simulation.camera")
    return StereoCalibration(K, K, right_from_left, size).check("simulation.camera")


def scene_of(cfg: SimulationConfig) -> Scene:
    """The scene of the configuration (deterministic in the seed)."""
    s = cfg.scene
    seed = cfg.seed if s.seed is None else s.seed  # two sessions of one object share it (issue 20)
    return build_scene(s.kind, seed, s.object_height_m, s.room, s.texture_size_px)


def path_of(cfg: SimulationConfig) -> HandheldPath:
    """The hand-held path of the configuration: the last frame is the end of the path."""
    tr = cfg.trajectory
    return HandheldPath(
        tr.kind,
        max(tr.frames - 1, 1) / tr.rate_hz,
        cfg.seed,
        tr.radius_m,
        tr.height_m,
        cfg.scene.object_height_m,
        tr.sweeps,
        tr.shake_translation_m,
        tr.shake_rotation_deg,
        cfg.realism.pace if realistic(cfg) else "smooth",
        cfg.realism.revisit_offset_m if realistic(cfg) else 0.0,
        tr.start_azimuth_deg,
    )


def frame_time_ns(cfg: SimulationConfig, index: int) -> int:
    """Timestamp of generated frame ``index`` (ns)."""
    return cfg.trajectory.start_time_ns + round(index * 1e9 / cfg.trajectory.rate_hz)


def light_position(cfg: SimulationConfig, t_s: float, world_from_cam: F64) -> F64:
    """Light position (world, metres) at time ``t_s``."""
    r = cfg.render
    p = np.asarray(r.light_position_m, float)
    if r.light == "moving":
        a = 2 * np.pi * t_s / r.light_period_s
        return p + r.light_motion_radius_m * np.array([np.cos(a), np.sin(a), 0.0])
    if r.light == "headlamp":
        return world_from_cam[:3, :3] @ np.array([0.0, -0.05, 0.0]) + world_from_cam[:3, 3]
    return p


def exposure_gain(cfg: SimulationConfig, t_s: float) -> float:
    """Slow relative exposure wander (1 +- exposure_variation)."""
    ev = cfg.render.exposure_variation
    if ev == 0:
        return 1.0
    rng = np.random.default_rng(np.random.SeedSequence([cfg.seed, 17]))
    f = rng.uniform(0.05, 0.5, 4)
    ph = rng.uniform(0, 2 * np.pi, 4)
    return float(1.0 + ev * np.mean(np.sin(2 * np.pi * f * t_s + ph)) * np.sqrt(2))


def parse_fault(spec: str) -> tuple[str, int, int]:
    """``KIND:FIRST[-LAST]`` (e.g. ``blackout:100-110``, ``dropped:57``) -> (kind, first, last)."""
    kinds = ("dropped", "blackout", "blur", "occluder", "duplicate_timestamp")
    kind, sep, rng = spec.partition(":")
    kind = kind.strip().replace("-", "_")
    if not sep or kind not in kinds:
        raise ConfigError("--fault", f"'{spec}': expected KIND:FIRST[-LAST] with KIND one of {', '.join(kinds)}")
    a, _, b = rng.partition("-")
    try:
        first = int(a)
        last = int(b) if b else first
    except ValueError:
        raise ConfigError("--fault", f"'{spec}': frame numbers must be integers") from None
    return kind, first, last


def resolve_config(
    base: SimulationConfig,
    preset: str | None = None,
    overrides: dict[str, dict[str, object]] | None = None,
    faults: list[str] | None = None,
    realism: str | None = None,
) -> SimulationConfig:
    """``base`` with a preset, section overrides, fault specs and a realism level applied.

    The preset: trajectory kind, its frame count, realism level ``realistic``; then section
    overrides (``{"trajectory": {"frames": 50}}``), fault specs and a realism level (``clean`` or
    ``realistic``); errors name the key.
    """
    from loopmodel.config import config_from_dict

    data = base.model_dump()
    if preset is not None:
        if preset not in PRESETS:
            raise ConfigError("--preset", f"unknown preset '{preset}'; expected one of {', '.join(PRESETS)}")
        for sec, vals in PRESETS[preset].items():
            data[sec].update(vals)
    for sec, vals in (overrides or {}).items():
        data[sec].update({k: v for k, v in vals.items() if v is not None})
    if realism is not None:
        if realism not in REALISM_LEVELS:
            raise ConfigError("--realism", f"unknown level '{realism}'; expected one of {', '.join(REALISM_LEVELS)}")
        data["realism"]["level"] = realism
    for spec in faults or []:
        kind, first, last = parse_fault(spec)
        if kind in ("dropped", "duplicate_timestamp"):
            data["faults"][kind].extend(range(first, last + 1))
        else:
            data["faults"][kind].append((first, last))
    return config_from_dict({"simulation": data}, "simulation").simulation


# ----------------------------------------------------------------------------- per frame


@dataclass
class FrameTask:
    """Everything a worker needs to render generated frame ``index``."""

    index: int
    world_from_cam: F64
    exposure_poses: tuple[F64, F64] | None
    light_world_m: F64
    gain: float
    blackout: bool
    blur_min_px: float
    world_from_occluder: F64 | None
    stripe_in_cam: F64 | None
    # realistic world: per camera (left, right) exposure time (s), analog gain and the poses
    # at the start and end of each camera's exposure; the laser line's true pixels, stripe
    # points (camera frame at the laser's time) and relative brightness
    exposure_s: tuple[float, float] = (0.0, 0.0)
    analog_gain: tuple[float, float] = (1.0, 1.0)
    exposure_poses_right: tuple[F64, F64] | None = None
    laser_uv: F64 | None = None
    laser_reflectance: F64 | None = None


@dataclass
class FrameImages:
    """A worker's result: 8-bit left, right and (optionally) laser images."""

    index: int
    left: NDArray[np.uint8]
    right: NDArray[np.uint8]
    laser: NDArray[np.uint8] | None = None
    render_s: float = 0.0


@dataclass
class _WorkerState:
    cfg: SimulationConfig
    caster: Raycaster
    camera: CentralCamera
    rays: RayBundle
    cam0_from_cam1: F64
    shape: tuple[int, int]
    real: _RealState | None = None


@dataclass
class _RealState:
    """The realistic world's rig, per-camera rays, vignetting and sensors."""

    rig: TrueRig
    rays: tuple[RayBundle, RayBundle]
    vignette: tuple[NDArray[np.float32], NDArray[np.float32]]
    sensors: tuple[SensorModel, SensorModel]


_STATE: _WorkerState | None = None


def _init_worker_from_file(setup: str) -> None:
    """A render worker's set-up from the file the parent wrote (see :func:`_iter_rendered`)."""
    with open(setup, "rb") as f:
        cfg, scene, rays = pickle.load(f)  # written by this package's parent process just before
    if rays is not None:  # the parent's rig rays (:func:`rig_rays`): not computed again here
        _RIG_RAYS.clear()
        _RIG_RAYS[_rig_key(cfg)] = rays
    _init_worker(cfg, scene)


def _init_worker(cfg: SimulationConfig, scene: Scene) -> None:
    global _STATE
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # (already ignored from the start; see _iter_rendered)
    cv2.setNumThreads(1)
    _STATE = _make_state(cfg, scene)
    _STATE.caster.threads = 1  # one process per core already


def _make_state(cfg: SimulationConfig, scene: Scene) -> _WorkerState:
    cam = camera_of(cfg)
    rays = pixel_rays(cam, cfg.camera.width_px, cfg.camera.height_px)
    if cfg.camera.fisheye_k is not None:
        rays = fisheye_pixel_rays(cam.K, np.asarray(cfg.camera.fisheye_k, float), rays.shape)
    c01 = np.eye(4)
    c01[0, 3] = cfg.camera.baseline_m
    shape = (cfg.camera.height_px, cfg.camera.width_px)
    caster = Raycaster(scene)
    real = None
    if realistic(cfg):
        r = cfg.realism
        rig = rig_of(cfg)
        c01 = rig.cam0_from_cam1
        bundles = []
        for dirs in rig_rays(cfg):
            bundles.append(RayBundle(dirs, np.ones(dirs.shape[1], bool), shape))
        vig = tuple(vignetting_map(b.dirs, shape, r.vignetting_corner) for b in bundles)
        sensors = tuple(
            SensorModel.create(
                shape, cfg.seed, k, r.full_well_e, r.read_noise_e, r.prnu, r.dsnu_e, r.adc_bits, r.gamma,
                1.0 if k == 0 else r.right_sensitivity,
            )
            for k in (0, 1)
        )
        real = _RealState(rig, (bundles[0], bundles[1]), (vig[0], vig[1]), (sensors[0], sensors[1]))
        if r.patches:
            caster.patches = scene_patches(cfg)
    return _WorkerState(cfg, caster, cam, rays, c01, shape, real)


def scene_patches(cfg: SimulationConfig) -> list[tuple[F64, float, str]]:
    """Textureless (``flat``) and repetitive (``tiles``) regions of the realistic world.

    Two of each on the table top around the object, one of each on the object's lower part.
    """
    hgt = cfg.scene.object_height_m
    return [
        (np.array([0.26, 0.10, 0.0]), 0.09, "flat"),
        (np.array([-0.22, -0.20, 0.0]), 0.08, "flat"),
        (np.array([0.05, -0.30, 0.0]), 0.10, "tiles"),
        (np.array([-0.25, 0.22, 0.0]), 0.08, "tiles"),
        (np.array([0.16, 0.0, 0.3 * hgt]), 0.06, "flat"),
        (np.array([-0.16, 0.0, 0.25 * hgt]), 0.06, "tiles"),
    ]


def fisheye_pixel_rays(K: F64, k: F64, shape: tuple[int, int]) -> RayBundle:
    """Unit rays through the pixel centres of an equidistant (Kannala-Brandt) camera.

    The distorted angle r_d = |K^-1 uv| is inverted for theta (Newton on theta (1 + k1 theta^2 + ...
    + k4 theta^8) = r_d); rays beyond 90 degrees are invalid.
    """
    h, w = shape
    u, v = np.meshgrid(np.arange(w, dtype=float), np.arange(h, dtype=float))
    x = (u.ravel() - K[0, 2]) / K[0, 0]
    y = (v.ravel() - K[1, 2]) / K[1, 1]
    rd = np.hypot(x, y)
    th = rd.copy()
    for _ in range(20):
        t2 = th * th
        f = th * (1 + t2 * (k[0] + t2 * (k[1] + t2 * (k[2] + t2 * k[3])))) - rd
        df = 1 + t2 * (3 * k[0] + t2 * (5 * k[1] + t2 * (7 * k[2] + t2 * 9 * k[3])))
        th -= f / df
    valid = (th < np.pi / 2 - 1e-3) & np.isfinite(th)
    s = np.where(rd > 1e-12, np.sin(th) / np.maximum(rd, 1e-12), 1.0)
    dirs = np.stack([x * s, y * s, np.cos(th)])
    dirs[:, ~valid] = np.array([[0.0], [0.0], [1.0]])
    return RayBundle(np.ascontiguousarray(dirs, dtype=np.float32), valid, (int(h), int(w)))


def _blur_kernel(dx: float, dy: float) -> NDArray[np.float32] | None:
    """Normalised linear motion-blur kernel for an image motion of (dx, dy) pixels."""
    length = float(np.hypot(dx, dy))
    if length < 0.5:
        return None
    if length > MAX_BLUR_PX:  # beyond this the image is a smear anyway; keep filtering cheap
        dx, dy, length = dx * MAX_BLUR_PX / length, dy * MAX_BLUR_PX / length, MAX_BLUR_PX
    half = int(np.ceil(length / 2)) + 1
    k = np.zeros((2 * half + 1, 2 * half + 1), np.float32)
    n = max(int(np.ceil(length * 4)), 2)
    s = np.linspace(-0.5, 0.5, n)
    xs, ys = half + s * dx, half + s * dy
    x0, y0 = np.floor(xs).astype(int), np.floor(ys).astype(int)
    fx, fy = xs - x0, ys - y0
    for ox, oy, w in (
        (0, 0, (1 - fx) * (1 - fy)),
        (1, 0, fx * (1 - fy)),
        (0, 1, (1 - fx) * fy),
        (1, 1, fx * fy),
    ):
        np.add.at(k, (y0 + oy, x0 + ox), w)
    return k / k.sum()


def _image_motion(st: _WorkerState, view: View, task: FrameTask) -> tuple[float, float]:
    """Image motion (pixels) of the scene at the image centre over the exposure."""
    h, w = st.shape
    if task.exposure_poses is None:
        return 0.0, 0.0
    pts = view.points_soa.reshape(3, h, w)[:, h // 4 : 3 * h // 4 : 8, w // 4 : 3 * w // 4 : 8]
    pts = pts.reshape(3, -1).T.astype(float)
    ok = np.isfinite(view.range_m[h // 4 : 3 * h // 4 : 8, w // 4 : 3 * w // 4 : 8].ravel())
    if not np.any(ok):
        return 0.0, 0.0
    pts = pts[ok]
    uv = []
    for T in task.exposure_poses:
        Tc = invert_pose(T)
        uv.append(st.camera.project(pts @ Tc[:3, :3].T + Tc[:3, 3]))
    d = np.median(uv[1] - uv[0], axis=0)
    return float(d[0]), float(d[1])


def pixel_flow(rig: TrueRig, view: View, poses: tuple[F64, F64], right: bool, step: int = 4) -> NDArray[np.float32]:
    """H x W x 2 image motion (true distorted pixels) of each pixel's scene point during the exposure.

    From the start to the end of the exposure (``poses``: world_from_cam at both instants); computed
    on every ``step``-th pixel and interpolated; zero where nothing is hit.
    """
    h, w = view.radiance.shape
    pts = view.points_soa.reshape(3, h, w)[:, ::step, ::step]
    hs, ws = pts.shape[1:]
    p = pts.reshape(3, -1).T.astype(float)
    ok = np.isfinite(view.range_m[::step, ::step].ravel())
    uv = []
    for T in poses:
        Tc = invert_pose(T)
        pc = p @ Tc[:3, :3].T + Tc[:3, 3]
        ok &= pc[:, 2] > 1e-3
        uv.append(rig.project(np.where(ok[:, None], pc, [0.0, 0.0, 1.0]), right))
    flow = np.where(ok[:, None], uv[1] - uv[0], 0.0).astype(np.float32).reshape(hs, ws, 2)
    return cv2.resize(flow, (w, h), interpolation=cv2.INTER_LINEAR)


def _render_realistic(st: _WorkerState, task: FrameTask, t0: float) -> FrameImages:
    """The realistic world's stereo pair.

    Distorted unrectified views, specular shading, per-pixel motion blur, defocus, vignetting,
    sensor noise and response, auto-exposure.
    """
    cfg, real = st.cfg, st.real
    assert real is not None
    r = cfg.realism
    seeds = np.random.SeedSequence([cfg.seed, _NOISE_STREAM, task.index]).generate_state(3)
    out = []
    scale = cfg.render.brightness * task.gain * (0.0 if task.blackout else 1.0) * r.light_e_per_s
    for k in (0, 1):
        T = task.world_from_cam if k == 0 else task.world_from_cam @ st.cam0_from_cam1
        view = st.caster.render(
            real.rays[k], T, task.light_world_m, cfg.render.ambient, task.world_from_occluder, r.specular, r.shininess
        )
        rad = view.radiance
        poses = task.exposure_poses if k == 0 else task.exposure_poses_right
        if cfg.render.motion_blur and poses is not None:
            rad = motion_blur(rad, pixel_flow(real.rig, view, poses, k == 1))
        if task.blur_min_px > 0:
            kernel = _blur_kernel(task.blur_min_px, 0.0)
            if kernel is not None:
                rad = cv2.filter2D(rad, -1, kernel, borderType=cv2.BORDER_REFLECT)
        focal_mm = real.rig.K_left[0, 0] * r.pixel_um * 1e-3
        sigma = defocus_sigma_px(view.depth_m, focal_mm, r.f_number, r.focus_m, r.pixel_um, r.lens_sigma_px)
        rad = defocus(rad, sigma)
        electrons = rad * real.vignette[k] * np.float32(scale * task.exposure_s[k])
        dn = real.sensors[k].expose_dn(electrons, task.analog_gain[k], int(seeds[k]))
        out.append(real.sensors[k].to_8bit(dn))
    laser = None
    if task.laser_uv is not None and task.stripe_in_cam is not None and task.laser_reflectance is not None:
        rng = np.random.default_rng(np.random.SeedSequence([cfg.seed, _LASER_STREAM, task.index]))
        laser = realistic_laser_image(
            out[0],
            task.laser_uv,
            task.stripe_in_cam,
            task.laser_reflectance,
            rng,
            r.laser_peak,
            r.laser_sigma_px,
            r.laser_speckle_contrast,
            r.laser_spurious_rate,
            r.full_well_e / 255.0,
        )
    return FrameImages(task.index, out[0], out[1], laser, time.perf_counter() - t0)


def render_frame(st: _WorkerState, task: FrameTask) -> FrameImages:
    """Render, blur, expose, add noise and quantise the stereo pair of one frame."""
    t0 = time.perf_counter()
    if st.real is not None:
        return _render_realistic(st, task, t0)
    cfg = st.cfg
    amb = cfg.render.ambient
    left = st.caster.render(
        st.rays,
        task.world_from_cam,
        task.light_world_m,
        amb,
        task.world_from_occluder,
    )
    right = st.caster.render(
        st.rays,
        task.world_from_cam @ st.cam0_from_cam1,
        task.light_world_m,
        amb,
        task.world_from_occluder,
    )
    dx, dy = _image_motion(st, left, task) if cfg.render.motion_blur or task.blur_min_px > 0 else (0.0, 0.0)
    if not cfg.render.motion_blur:
        dx = dy = 0.0
    if task.blur_min_px > 0:
        length = float(np.hypot(dx, dy))
        if length < 1e-3:
            dx, dy = task.blur_min_px, 0.0
        elif length < task.blur_min_px:
            dx, dy = dx * task.blur_min_px / length, dy * task.blur_min_px / length
    kernel = _blur_kernel(dx, dy)
    seeds = np.random.SeedSequence([cfg.seed, _NOISE_STREAM, task.index]).generate_state(2)
    scale = 255.0 * cfg.render.brightness * task.gain * (0.0 if task.blackout else 1.0)
    out = []
    noise = np.empty(st.shape, np.float32)
    for view, seed in zip((left, right), seeds, strict=True):
        img = view.radiance * np.float32(scale)
        if kernel is not None:
            img = cv2.filter2D(img, -1, kernel, borderType=cv2.BORDER_REFLECT)
        if cfg.render.noise_sigma > 0:
            cv2.setRNGSeed(int(seed) & 0x7FFFFFFF)  # OpenCV's per-thread RNG: deterministic
            cv2.randn(noise, 0.0, float(cfg.render.noise_sigma))
            img += noise
        out.append(np.clip(img + 0.5, 0, 255).astype(np.uint8))
    laser = None
    if cfg.laser.image and task.stripe_in_cam is not None:
        laser = draw_laser_image(out[0], task.stripe_in_cam, st.camera)
    return FrameImages(task.index, out[0], out[1], laser, time.perf_counter() - t0)


def _worker_render(task: FrameTask) -> FrameImages:
    assert _STATE is not None, "worker not initialised"
    return render_frame(_STATE, task)


# ----------------------------------------------------------------------------- the run


@dataclass
class SimulationResult:
    """What a run wrote and how long it took."""

    path: Path
    frames: int
    frames_written: int
    stripes_written: int
    seconds: float
    setup_seconds: float
    ms_per_frame: float
    render_ms_median: float
    size_bytes: int
    faults: list[dict[str, int | str]] = field(default_factory=list)
    scene_ply: Path | None = None
    laser_images_written: int = 0


def plan_frames(
    cfg: SimulationConfig, caster: Raycaster, plan: FaultPlan, path: HandheldPath
) -> tuple[list[FrameTask], list[F64 | None], F64]:
    """Poses, lights, faults and noiseless stripes of every frame.

    Validates that the path stays clear of the scene and that the light plane hits it.
    """
    tr = cfg.trajectory
    n = tr.frames
    cam = camera_of(cfg)
    size = (cfg.camera.width_px, cfg.camera.height_px)
    real = realistic(cfg)
    laser = None
    if cfg.laser.enabled:
        try:
            laser = LaserPlane.create(
                cfg.laser.origin_in_cam_m,
                cfg.laser.normal_in_cam,
                cfg.laser.fan_deg,
                cfg.laser.rays,
                cfg.laser.max_range_m,
            )
        except ValueError as exc:
            raise ConfigError("simulation.laser.normal_in_cam", str(exc)) from None
    tasks: list[FrameTask] = []
    stripes: list[F64 | None] = []
    poses = np.zeros((n, 4, 4))
    exp_s = cfg.render.exposure_s
    for i in range(n):
        t_s = i / tr.rate_hz
        T = path.pose(t_s)
        poses[i] = T
        kinds = plan.kinds_at(i)
        frac = plan.occluder_fraction(i)
        w_occ = T @ cam_from_occluder(frac) if frac is not None else None
        stripe = None
        if laser is not None and not real:
            stripe, _dirs = stripe_profile(caster, laser, cam, size, T, w_occ)
        stripes.append(stripe)
        # (the realistic world's per-camera exposure intervals replace them: _plan_realistic)
        exposure = (path.pose(t_s - exp_s / 2), path.pose(t_s + exp_s / 2)) if exp_s > 0 and not real else None
        tasks.append(
            FrameTask(
                index=i,
                world_from_cam=T,
                exposure_poses=exposure,
                light_world_m=light_position(cfg, t_s, T),
                gain=exposure_gain(cfg, t_s),
                blackout="blackout" in kinds,
                blur_min_px=cfg.faults.blur_length_px if "blur" in kinds else 0.0,
                world_from_occluder=w_occ,
                stripe_in_cam=stripe if cfg.laser.image else None,
            )
        )
    if real:
        _plan_realistic(cfg, caster, path, laser, tasks, stripes)
    # the camera must stay in free space, clear of the scene surface
    import open3d as o3d

    rs = o3d.t.geometry.RaycastingScene()
    rs.add_triangles(
        to_tensor(caster.scene.vertices.astype(np.float32)),
        to_tensor(caster.scene.triangles.astype(np.uint32)),
    )
    centres = np.vstack([poses[:, :3, 3], (poses @ np.array([cfg.camera.baseline_m, 0, 0, 1.0]))[:, :3]])
    dist = rs.compute_distance(to_tensor(centres.astype(np.float32))).numpy()
    if float(dist.min()) < 0.05:
        i = int(np.argmin(dist)) % n
        raise ConfigError(
            "simulation.trajectory",
            f"the camera passes {dist.min():.3f} m from the scene surface at frame {i} "
            "(radius_m/height_m put it inside or against the object or table)",
        )
    if laser is not None and not any(s is not None and s.shape[0] > 0 for s in stripes):
        raise ConfigError(
            "simulation.laser",
            "the light plane never hits the scene where the left camera sees it "
            "(check origin_in_cam_m, normal_in_cam and fan_deg)",
        )
    return tasks, stripes, poses


def true_light_plane(cfg: SimulationConfig, nominal: LaserPlane) -> LaserPlane:
    """The light plane the realistic world really casts.

    The configured (calibrated) plane rotated by ``laser_plane_rot_err_deg`` about a seeded axis in
    the plane and shifted by ``laser_plane_offset_err_m`` along its normal.
    """
    r = cfg.realism
    rng = np.random.default_rng(np.random.SeedSequence([cfg.seed, 37]))
    n = nominal.normal_in_cam
    a = np.cross(n, rng.standard_normal(3))
    a /= np.linalg.norm(a)
    n_true = so3_exp(np.radians(r.laser_plane_rot_err_deg) * a) @ n
    o_true = nominal.origin_in_cam_m + r.laser_plane_offset_err_m * n_true
    return LaserPlane.create(o_true, n_true, nominal.fan_deg, nominal.rays, nominal.max_range_m)


def _plan_realistic(
    cfg: SimulationConfig,
    caster: Raycaster,
    path: HandheldPath,
    laser: LaserPlane | None,
    tasks: list[FrameTask],
    stripes: list[F64 | None],
) -> None:
    """The realistic world's additions to :func:`plan_frames`, in place.

    Per-camera auto-exposure (from a 1/8-resolution render of every frame) and each camera's
    exposure interval; the laser stripe of the true light plane at the laser's exposure time, its
    true pixels and brightness.
    """
    r = cfg.realism
    rig = rig_of(cfg)
    w, h = cfg.camera.width_px, cfg.camera.height_px
    sub_shape = (len(range(0, h, 8)), len(range(0, w, 8)))
    means = np.zeros((len(tasks), 2))
    for k in (0, 1):
        dirs = rig_rays(cfg)[k]
        vig = vignetting_map(dirs, (h, w), r.vignetting_corner)[::8, ::8].ravel()
        sub = dirs.reshape(3, h, w)[:, ::8, ::8].reshape(3, -1)
        bundle = RayBundle(np.ascontiguousarray(sub), np.ones(sub.shape[1], bool), sub_shape)
        for i, task in enumerate(tasks):
            T = task.world_from_cam if k == 0 else task.world_from_cam @ rig.cam0_from_cam1
            v = caster.render(bundle, T, task.light_world_m, cfg.render.ambient, task.world_from_occluder,
                              r.specular, r.shininess)
            sens = 1.0 if k == 0 else r.right_sensitivity
            means[i, k] = float(np.mean(v.radiance.ravel() * vig)) * sens * task.gain * cfg.render.brightness
    ae = [auto_exposure(means[:, k], r.light_e_per_s, r.full_well_e, r.ae_target, 2e-5, r.ae_max_exposure_s,
                        r.ae_max_gain) for k in (0, 1)]
    rate = cfg.trajectory.rate_hz
    plane = true_light_plane(cfg, laser) if laser is not None else None
    cam = camera_of(cfg)
    size = (w, h)
    for i, task in enumerate(tasks):
        t_s = i / rate
        e0, e1 = float(ae[0][0][i]), float(ae[1][0][i])
        task.exposure_s = (e0, e1)
        task.analog_gain = (float(ae[0][1][i]), float(ae[1][1][i]))
        c01 = rig.cam0_from_cam1
        task.exposure_poses = (path.pose(t_s - e0 / 2), path.pose(t_s + e0 / 2))
        task.exposure_poses_right = (path.pose(t_s - e1 / 2) @ c01, path.pose(t_s + e1 / 2) @ c01)
        if plane is None:
            continue
        T_l = path.pose(t_s + r.laser_time_offset_s)
        w_occ = task.world_from_occluder
        pts, _dirs = stripe_profile(caster, plane, cam, size, T_l, w_occ)
        if pts.shape[0]:
            uv = rig.project(pts)
            inside = (uv[:, 0] >= -0.5) & (uv[:, 0] <= w - 0.5) & (uv[:, 1] >= -0.5) & (uv[:, 1] <= h - 0.5)
            pts, uv = pts[inside], uv[inside]
        else:
            uv = np.zeros((0, 2))
        stripes[i] = pts
        task.stripe_in_cam = pts
        task.laser_uv = uv
        task.laser_reflectance = stripe_reflectance(caster, plane, T_l, pts, w_occ)


def _runs(executable: str) -> bool:
    """Whether ``executable`` starts Python here (``-S -c ''``)."""
    import subprocess

    try:
        return subprocess.run([executable, "-S", "-c", ""], capture_output=True, timeout=60).returncode == 0
    except (OSError, subprocess.SubprocessError):
        return False


def _iter_rendered(
    cfg: SimulationConfig, scene: Scene, tasks: list[FrameTask], state: _WorkerState | None
) -> Generator[FrameImages, None, None]:
    workers = cfg.workers if cfg.workers > 0 else (mp.cpu_count() or 1)
    workers = min(workers, max(len(tasks), 1))
    if workers <= 1:
        st = state if state is not None else _make_state(cfg, scene)
        for task in tasks:
            yield render_frame(st, task)
        return
    ctx = mp.get_context("spawn")
    # The workers start through a launcher that ignores SIGINT before it runs Python (an ignored
    # signal stays ignored across exec, and Python then installs no KeyboardInterrupt handler):
    # Ctrl-C, which reaches the whole process group, stops only the parent, which terminates the
    # pool; no worker tracebacks. Their set-up (configuration and scene, megabytes) goes through a
    # file, not the pipe that starts each worker (starting the pool waited seconds for the workers
    # to read it). While the pool starts, Ctrl-C and SIGTERM are noted and raised once it exists
    # (issue 34: the parent used to ignore SIGINT then, and a Ctrl-C in the first seconds was lost).
    tmp = tempfile.mkdtemp(prefix="loopmodel-sim-")
    try:  # the set-up files removed however it ends
        yield from _render_in_pool(ctx, workers, cfg, scene, tasks, tmp)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def _render_in_pool(
    ctx: Any, workers: int, cfg: SimulationConfig, scene: Scene, tasks: list[FrameTask], tmp: str
) -> Generator[FrameImages, None, None]:
    """The frames rendered by a pool of ``workers`` processes whose set-up files go in ``tmp``."""
    setup, launcher = os.path.join(tmp, "setup.pickle"), os.path.join(tmp, "python")
    with open(setup, "wb") as f:
        pickle.dump((cfg, scene, rig_rays(cfg) if realistic(cfg) else None), f, protocol=pickle.HIGHEST_PROTOCOL)
    with open(launcher, "w") as f:
        f.write(f"#!/bin/sh\ntrap '' INT\nexec {shlex.quote(sys.executable)} \"$@\"\n")
    os.chmod(launcher, 0o700)
    if not _runs(launcher):  # a temporary folder mounted noexec: Python itself, SIGINT ignored in the parent
        launcher = sys.executable
    main_thread = threading.current_thread() is threading.main_thread()
    caught: list[int] = []
    previous: dict[int, Any] = {}
    if main_thread:
        for signum in (signal.SIGINT, signal.SIGTERM):
            previous[signum] = signal.signal(signum, lambda sig, frame: caught.append(sig))
        if launcher == sys.executable:
            signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        ctx.set_executable(launcher)
        # the workers load open3d without its plotly viewer: 0.7 s CPU each (loopmodel.open3d_import)
        start = (f"{__name__}:{_init_worker_from_file.__name__}", setup)
        pool = ctx.Pool(workers, initializer=start_without_plotly_viewer, initargs=start)
    finally:
        ctx.set_executable(sys.executable)
        for sig_restored, handler in previous.items():
            signal.signal(sig_restored, handler)
    if caught:
        pool.terminate()
        raise KeyboardInterrupt(f"signal {caught[0]}")
    with pool:
        yield from pool.imap(_worker_render, tasks, chunksize=1)


def simulate_scan(
    cfg: SimulationConfig,
    out: str | Path,
    topics: TopicsConfig | None = None,
    progress: Callable[[int, int], None] | None = None,
    preset: str | None = None,
) -> SimulationResult:
    """Generate the scan described by ``cfg`` into the MCAP file ``out`` (written atomically).

    ``progress(done, total)`` is called after each frame. Raises :class:`ConfigError` for impossible
    parameters (before any rendering).
    """
    out = Path(out)
    if out.suffix.lower() != ".mcap":
        raise InputError(out, "output must end in .mcap")
    check_output_file(out)
    t_start = time.perf_counter()
    tr = cfg.trajectory
    n = tr.frames
    plan = FaultPlan.from_config(cfg.faults, n)
    calib = calibration_of(cfg)
    scene = scene_of(cfg)
    caster = Raycaster(scene)
    path = path_of(cfg)
    tasks, stripes, poses = plan_frames(cfg, caster, plan, path)
    setup_s = time.perf_counter() - t_start
    period_ns = 1e9 / tr.rate_hz
    dup = {f.first for f in plan.faults if f.kind == "duplicate_timestamp"}
    dropped = {f.first for f in plan.faults if f.kind == "dropped"}
    black = {i for f in plan.faults if f.kind == "blackout" for i in f.frames()}
    frames_written = stripes_written = laser_images_written = 0
    render_s: list[float] = []
    state = _make_state(cfg, scene) if cfg.workers == 1 else None
    rendered = _iter_rendered(cfg, scene, tasks, state)
    # closed on any exit (Ctrl-C while writing too): the pool ends, its set-up files are removed
    with McapSequenceWriter(out, calib, topics, cfg.image_format) as writer, contextlib.closing(rendered):
        for k, img in enumerate(rendered):
            i = img.index
            render_s.append(img.render_s)
            t_ns = frame_time_ns(cfg, i)
            if i in dup:
                t_ns = frame_time_ns(cfg, i - 1)
            else:
                writer.write_pose(t_ns, poses[i])
            if i not in dropped:
                writer.write_frame(StereoFrame(t_ns, img.left, img.right, i))
                frames_written += 1
                s = stripes[i]
                if realistic(cfg):  # only measured: the laser image; the true stripe as ground truth
                    if s is not None and i not in dup:
                        writer.write_stripe(StripeProfile(t_ns, s), GT_STRIPE_TOPIC)
                elif s is not None and i not in dup and i not in black:
                    noise_rng = np.random.default_rng(np.random.SeedSequence([cfg.seed, _STRIPE_STREAM, i]))
                    pts = _noisy_stripe(s, cfg, noise_rng)
                    writer.write_stripe(StripeProfile(t_ns, pts))
                    stripes_written += 1
                if img.laser is not None:
                    writer.write_image((topics or TopicsConfig()).laser_image, t_ns, img.laser, "cam0")
                    laser_images_written += 1
            if progress is not None:
                progress(k + 1, n)
        scene_ply = scene.ply_bytes()
        writer.add_attachment("scene.ply", scene_ply, "application/x-ply")
        writer.add_attachment("object.ply", scene.ply_bytes(object_only=True), "application/x-ply")
        records = plan.records(tr.start_time_ns, period_ns)
        writer.add_metadata(
            "simulation",
            {
                "generator": "loopmodel.sim",
                "version": __version__,
                "preset": preset or tr.kind,
                "seed": str(cfg.seed),
                "frames": str(n),
                "rate_hz": repr(tr.rate_hz),
                "start_time_ns": str(tr.start_time_ns),
                "period_ns": repr(period_ns),
                "world_frame": "z up, origin at the centre of the table top, metres",
                "xi": repr(cfg.camera.xi),
                "config_json": cfg.model_dump_json(),
            },
        )
        meta = {"count": str(len(records)), "json": json.dumps(records)}
        for j, r in enumerate(records):
            meta[f"{j:03d}_{r['kind']}"] = f"frames {r['first_frame']}-{r['last_frame']}"
        writer.add_metadata("faults", meta)
    ply_path = None
    if cfg.write_scene_ply:
        ply_path = out.with_suffix(".scene.ply")
        write_bytes_atomic(ply_path, scene_ply)
    seconds = time.perf_counter() - t_start
    return SimulationResult(
        path=out,
        frames=n,
        frames_written=frames_written,
        stripes_written=stripes_written,
        laser_images_written=laser_images_written,
        seconds=seconds,
        setup_seconds=setup_s,
        ms_per_frame=1000.0 * seconds / n,
        render_ms_median=1000.0 * float(np.median(render_s)) if render_s else 0.0,
        size_bytes=out.stat().st_size,
        faults=records,
        scene_ply=ply_path,
    )


def _noisy_stripe(points_in_cam: F64, cfg: SimulationConfig, rng: np.random.Generator) -> F64:
    """Stripe points with range noise along the laser rays (they stay in the light plane)."""
    sigma = cfg.laser.range_noise_m
    if sigma == 0 or points_in_cam.shape[0] == 0:
        return points_in_cam
    d = points_in_cam - np.asarray(cfg.laser.origin_in_cam_m, float)
    d /= np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-12)
    return points_in_cam + d * rng.normal(0.0, sigma, size=(points_in_cam.shape[0], 1))
