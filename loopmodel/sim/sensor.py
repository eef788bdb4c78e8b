"""Realistic image formation of the simulator (issue 17): lens, optics and a CMOS sensor.

One model, applied after ray casting to the radiance of every view when
``simulation.realism.level`` is ``realistic`` (the ``clean`` world skips it):

1. **Lens geometry** (:class:`TrueRig`): radial-tangential (OpenCV plumb-bob) distortion and
   a right camera that is slightly rotated and offset, so the images are *unrectified*; the
   recorded ``camera_info`` is the true rig plus a stated calibration error.
2. **Optics**: per-pixel motion blur from each pixel's own image motion during the exposure
   (:func:`motion_blur`), a Gaussian lens PSF widened by thin-lens defocus (:func:`defocus`),
   vignetting (:func:`vignetting_map`).
3. **Sensor** (:class:`SensorModel`): photo-electrons, PRNU and DSNU fixed patterns, photon
   shot noise plus read noise (EMVA 1288 linear model), full-well clipping, a 12-bit ADC,
   a gamma response curve and 8-bit output; per-camera auto-exposure with a left/right
   sensitivity mismatch (:func:`auto_exposure`).

Magnitudes and where they come from (pixel units are those of the simulated 640 x 480
camera, fx = 500 px):

- Sensor: Sony IMX250 (Pregius global-shutter CMOS) as characterised to EMVA 1288 in
  camera data sheets: full well 10.7 ke- at 12 bit (Teledyne DALSA Genie Nano M2450 manual,
  "Standard design"), dynamic range 71.2 dB (MATRIX VISION mvBlueFOX3-2051 data,
  EMVA 1288) -> temporal dark (read) noise 10.7 ke- / 10^(71.2/20) = 2.9 e-. PRNU 0.6 % and
  DSNU 1.5 e- are typical EMVA 1288 summary values of such sensors (the sheets above do not
  list them; stated as an assumption).
- Lens distortion: the calibrated lens of the EuRoC MAV dataset's cam0/cam1 (MT9V034
  global-shutter WVGA, 6 um pixels, fx 458 px): k1 = -0.2834, k2 = 0.0740,
  p1 = 1.94e-4, p2 = 1.76e-5 (cam1: -0.2837, 0.0745, -1.05e-4, -3.56e-5); its stereo
  rotation of about 0.25 deg and a 0.4 mm off-axis baseline offset.
- Calibration error of the recorded camera_info (a good checkerboard calibration, RMS
  0.1-0.3 px): 0.3 px in focal length and principal point, 0.002 in k1, 0.02 deg in the
  stereo rotation, 0.05 mm in the baseline (each drawn with that standard deviation).
- Optics: 6 um pixels -> f = 500 px * 6 um = 3.0 mm, f/2.8, focused at 0.6 m; lens PSF
  sigma 0.5 px (an M12 machine-vision lens at MTF50 near half Nyquist); relative
  illumination 0.6 at the image corner (typical of short-focal M12 lenses' data sheets).
- Auto-exposure: per camera, a damped controller on the previous frame's mean (one frame
  late, as camera AE loops are); the two cameras' responsivity differs by 3 % (unit-to-unit
  QE/gain spread of one sensor model), so their images differ in brightness.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from loopmodel.geometry.se3 import make_pose, so3_exp
from loopmodel.types import StereoCalibration

F32 = NDArray[np.float32]
F64 = NDArray[np.float64]

# EuRoC cam0 / cam1 lens (k1, k2, p1, p2, k3): a real calibrated machine-vision stereo lens
EUROC_DIST_LEFT = (-0.28340811, 0.07395907, 0.00019359, 1.76187114e-05, 0.0)
EUROC_DIST_RIGHT = (-0.28368365, 0.07451284, -0.00010473, -3.55590700e-05, 0.0)
# EuRoC cam0-from-cam1 rotation angles (rad, about x, y, z): about 0.22, 0.02, 0.13 deg
EUROC_ROT_RIGHT_RAD = (0.00388, 0.00040, 0.00230)


# ----------------------------------------------------------------------------- lens geometry


def distort_normalized(xy: F64, dist: F64) -> F64:
    """Plumb-bob distortion (OpenCV k1, k2, p1, p2, k3) of N x 2 normalised coordinates."""
    k1, k2, p1, p2, k3 = (list(np.asarray(dist, float).ravel()) + [0.0] * 5)[:5]
    x, y = xy[:, 0], xy[:, 1]
    r2 = x * x + y * y
    radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    return np.column_stack([xd, yd])


def project_distorted(p_in_cam: F64, K: F64, dist: F64) -> F64:
    """N x 2 pixels of N x 3 camera-frame points through a pinhole with plumb-bob distortion."""
    p = np.asarray(p_in_cam, float).reshape(-1, 3)
    z = np.where(np.abs(p[:, 2]) > 1e-12, p[:, 2], 1e-12)
    xy = distort_normalized(p[:, :2] / z[:, None], dist)
    return np.column_stack([K[0, 0] * xy[:, 0] + K[0, 1] * xy[:, 1] + K[0, 2], K[1, 1] * xy[:, 1] + K[1, 2]])


def undistort_pixels(uv_px: F64, K: F64, dist: F64, iterations: int = 60) -> F64:
    """N x 2 undistorted normalised coordinates of N x 2 distorted pixels (inverse of :func:`project_distorted`).

    Fixed-point iteration x = (x_d - tangential(x)) / radial(x), as OpenCV's undistortPoints but run
    to convergence (residual below 1e-9 px for the EuRoC lens over a 640 x 480 image).
    """
    uv = np.asarray(uv_px, float).reshape(-1, 2)
    k1, k2, p1, p2, k3 = (list(np.asarray(dist, float).ravel()) + [0.0] * 5)[:5]
    yd = (uv[:, 1] - K[1, 2]) / K[1, 1]
    xd = (uv[:, 0] - K[0, 2] - K[0, 1] * yd) / K[0, 0]
    x, y = xd.copy(), yd.copy()
    for _ in range(iterations):
        r2 = x * x + y * y
        radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
        dx = 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
        dy = p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
        x = (xd - dx) / radial
        y = (yd - dy) / radial
    return np.column_stack([x, y])


@dataclass
class TrueRig:
    """The simulated stereo rig as it really is.

    Left/right intrinsics and distortion and ``cam0_from_cam1`` (4x4, metres); ``recorded`` is what
    its camera_info says.
    """

    K_left: F64
    K_right: F64
    dist_left: F64
    dist_right: F64
    cam0_from_cam1: F64
    size: tuple[int, int]  # (width, height)
    recorded: StereoCalibration

    @classmethod
    def create(
        cls,
        K: F64,
        baseline_m: float,
        size: tuple[int, int],
        seed: int,
        focal_err_px: float,
        pp_err_px: float,
        k1_err: float,
        rot_err_deg: float,
        baseline_err_m: float,
    ) -> TrueRig:
        """The rig of a nominal camera ``K`` (both cameras), EuRoC's lens and stereo rotation,
        and a recorded calibration off by the stated errors (seeded)."""
        rng = np.random.default_rng(np.random.SeedSequence([int(seed), 23]))
        KL = np.array(K, float)
        KR = np.array(K, float)
        KR[0, 0] *= 0.9977  # EuRoC: right focal length 0.23 % shorter, principal point offset
        KR[1, 1] *= 0.9975
        KR[0, 2] += 3.0
        KR[1, 2] += 2.0
        dl, dr = np.array(EUROC_DIST_LEFT), np.array(EUROC_DIST_RIGHT)
        c01 = make_pose(so3_exp(np.array(EUROC_ROT_RIGHT_RAD)), np.array([baseline_m, -0.0004, -0.0004]))

        def perturb_K(K0: F64) -> F64:
            Kp = K0.copy()
            Kp[0, 0] += rng.normal(0, focal_err_px)
            Kp[1, 1] += rng.normal(0, focal_err_px)
            Kp[0, 2] += rng.normal(0, pp_err_px)
            Kp[1, 2] += rng.normal(0, pp_err_px)
            return Kp

        KL_rec, KR_rec = perturb_K(KL), perturb_K(KR)
        dl_rec, dr_rec = dl.copy(), dr.copy()
        dl_rec[0] += rng.normal(0, k1_err)
        dr_rec[0] += rng.normal(0, k1_err)
        c01_rec = c01.copy()
        c01_rec[:3, :3] = c01[:3, :3] @ so3_exp(rng.normal(0, np.radians(rot_err_deg), 3))
        c01_rec[:3, 3] *= 1.0 + rng.normal(0, baseline_err_m) / baseline_m
        right_from_left: F64 = np.asarray(np.linalg.inv(c01_rec), dtype=np.float64)
        rec = StereoCalibration(KL_rec, KR_rec, right_from_left, size, dl_rec, dr_rec, rectified=False)
        return cls(KL, KR, dl, dr, c01, size, rec.check("simulation.realism"))

    def rays(self, right: bool) -> F32:
        """3 x (H*W) unit rays (camera frame) through the pixel centres of one camera."""
        w, h = self.size
        u, v = np.meshgrid(np.arange(w, dtype=float), np.arange(h, dtype=float))
        K, d = (self.K_right, self.dist_right) if right else (self.K_left, self.dist_left)
        xy = undistort_pixels(np.column_stack([u.ravel(), v.ravel()]), K, d)
        r = np.column_stack([xy, np.ones(xy.shape[0])])
        r /= np.linalg.norm(r, axis=1, keepdims=True)
        return np.ascontiguousarray(r.T, dtype=np.float32)

    def project(self, p_in_cam: F64, right: bool = False) -> F64:
        """True (distorted) pixels of N x 3 points in the left (or right) camera frame."""
        if right:
            return project_distorted(p_in_cam, self.K_right, self.dist_right)
        return project_distorted(p_in_cam, self.K_left, self.dist_left)


# ----------------------------------------------------------------------------- optics


def vignetting_map(rays: F32, shape: tuple[int, int], corner_relative: float) -> F32:
    """Relative illumination (H x W) as cos^n of each pixel's field angle, n chosen so that
    the darkest image corner receives ``corner_relative`` of the on-axis illumination."""
    cos_t = np.clip(rays[2], 1e-3, 1.0).reshape(shape)
    cmin = float(cos_t.min())
    if corner_relative >= 1.0 or cmin >= 1.0 - 1e-9:
        return np.ones(shape, np.float32)
    n = np.log(corner_relative) / np.log(cmin)
    return np.power(cos_t, n).astype(np.float32)


def motion_blur(img: F32, flow_px: F32, max_taps: int = 12) -> F32:
    """Per-pixel motion blur.

    Pixel x averages the sharp image along its own image motion during the exposure, ``mean_s img(x
    + s * flow(x))`` for s uniform in [-1/2, 1/2] (``flow_px`` H x W x 2: each pixel's displacement
    from exposure start to end).
    """
    length = float(np.max(np.hypot(flow_px[..., 0], flow_px[..., 1]))) if flow_px.size else 0.0
    if length < 0.25:
        return img
    taps = int(min(max(np.ceil(length) + 1, 2), max_taps))
    h, w = img.shape
    gx, gy = np.meshgrid(np.arange(w, dtype=np.float32), np.arange(h, dtype=np.float32))
    acc = np.zeros_like(img)
    for s in (np.arange(taps, dtype=np.float32) + 0.5) / taps - 0.5:
        acc += cv2.remap(
            img, gx + s * flow_px[..., 0], gy + s * flow_px[..., 1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT
        )
    return acc / np.float32(taps)


def defocus_sigma_px(
    depth_m: F32, focal_mm: float, f_number: float, focus_m: float, pixel_um: float, lens_sigma_px: float
) -> F32:
    """Gaussian PSF sigma (px) per pixel.

    The lens PSF combined with the thin-lens circle of confusion c = f^2 |z - z_f| / (N z (z_f -
    f)), sigma_c = c / 2.4 (px).
    """
    f = focal_mm * 1e-3
    z = np.where(np.isfinite(depth_m), depth_m, 10.0).astype(np.float32)
    c_m = (f * f / f_number) * np.abs(z - focus_m) / np.maximum(z * (focus_m - f), 1e-9)
    sc = c_m / (pixel_um * 1e-6) / 2.4
    return np.sqrt(lens_sigma_px**2 + sc * sc).astype(np.float32)


def defocus(img: F32, sigma_px: F32, levels: tuple[float, ...] = (0.5, 1.0, 2.0, 4.0)) -> F32:
    """Spatially varying Gaussian blur.

    Per pixel, linear interpolation between the image blurred at the bracketing ``levels`` of its
    sigma (clamped to the range of levels).
    """
    s = np.clip(sigma_px, levels[0], levels[-1])
    need = [lv for i, lv in enumerate(levels) if i == 0 or float(s.max()) > levels[i - 1]]
    blurred = [cv2.GaussianBlur(img, (0, 0), lv, borderType=cv2.BORDER_REFLECT) for lv in need]
    out = blurred[0].copy()
    for i in range(1, len(need)):
        lo, hi = need[i - 1], need[i]
        t = np.clip((s - lo) / (hi - lo), 0.0, 1.0)
        sel = s > lo
        out[sel] = ((1 - t) * blurred[i - 1] + t * blurred[i])[sel]
    return out


# ----------------------------------------------------------------------------- sensor


@dataclass
class SensorModel:
    """EMVA 1288 linear camera model of one camera: electrons -> 12-bit DN -> 8-bit grey.

    ``full_well_e``, ``read_noise_e`` (temporal dark noise), ``prnu`` (relative gain spread,
    fixed per pixel), ``dsnu_e`` (offset spread, fixed per pixel), ``adc_bits``, ``gamma``
    (8-bit output = 255 (DN / DN_max)^gamma); ``sensitivity`` scales the collected
    electrons (the left/right mismatch)."""

    full_well_e: float
    read_noise_e: float
    prnu: float
    dsnu_e: float
    adc_bits: int
    gamma: float
    sensitivity: float
    prnu_map: F32
    dsnu_map: F32

    @classmethod
    def create(
        cls,
        shape: tuple[int, int],
        seed: int,
        camera: int,
        full_well_e: float,
        read_noise_e: float,
        prnu: float,
        dsnu_e: float,
        adc_bits: int,
        gamma: float,
        sensitivity: float,
    ) -> SensorModel:
        """Sensor with its seeded fixed-pattern maps (``camera`` 0 left, 1 right)."""
        rng = np.random.default_rng(np.random.SeedSequence([int(seed), 29, int(camera)]))
        prnu_map = (1.0 + prnu * rng.standard_normal(shape)).astype(np.float32)
        dsnu_map = (dsnu_e * rng.standard_normal(shape)).astype(np.float32)
        return cls(full_well_e, read_noise_e, prnu, dsnu_e, adc_bits, gamma, sensitivity, prnu_map, dsnu_map)

    @property
    def dn_max(self) -> float:
        """Largest ADC value."""
        return float(2**self.adc_bits - 1)

    @property
    def dn_per_e(self) -> float:
        """System gain K (DN per electron) at analog gain 1: full well maps to full scale."""
        return self.dn_max / self.full_well_e

    def expose_dn(self, electrons: F32, analog_gain: float, noise_seed: int, fixed_pattern: bool = True) -> F32:
        """12-bit DN of a mean photo-electron image.

        PRNU/DSNU, shot + read noise (Gaussian approximations of Poisson and of the dark noise),
        full-well clipping, analog gain, ADC clipping and quantisation.
        """
        e = electrons * np.float32(self.sensitivity)
        if fixed_pattern:
            e = e * self.prnu_map + self.dsnu_map
        np.maximum(e, 0.0, out=e)
        n1 = np.empty_like(e)
        n2 = np.empty_like(e)
        cv2.setRNGSeed(int(noise_seed) & 0x7FFFFFFF)  # OpenCV's per-thread RNG: deterministic
        cv2.randn(n1, 0.0, 1.0)
        cv2.randn(n2, 0.0, float(self.read_noise_e))
        e = e + np.sqrt(e) * n1 + n2
        np.clip(e, 0.0, self.full_well_e, out=e)
        dn = e * np.float32(self.dn_per_e * analog_gain)
        np.clip(dn, 0.0, self.dn_max, out=dn)
        return np.floor(dn + np.float32(0.5))

    def to_8bit(self, dn: F32) -> NDArray[np.uint8]:
        """Gamma response: 255 (DN / DN_max)^gamma, rounded to 8 bits."""
        x = np.power(dn * np.float32(1.0 / self.dn_max), np.float32(self.gamma))
        return np.clip(x * 255.0 + 0.5, 0, 255).astype(np.uint8)


def auto_exposure(
    mean_radiance: F64,
    light_e_per_s: float,
    full_well_e: float,
    target_fraction: float,
    min_exposure_s: float,
    max_exposure_s: float,
    max_gain: float,
    damping: float = 0.6,
) -> tuple[F64, F64]:
    """Exposure time (s) and analog gain of each frame from an AE loop that sees the previous
    frame's mean signal (``mean_radiance`` times the exposure, in electrons) and moves
    towards ``target_fraction`` of the full well by the power ``damping`` of the ratio;
    exposure first (up to ``max_exposure_s``), then gain. Frame 0 starts converged."""
    n = mean_radiance.shape[0]
    exp_s = np.zeros(n)
    gain = np.ones(n)
    target_e = target_fraction * full_well_e

    def settle(m: float) -> tuple[float, float]:
        need = target_e / max(m * light_e_per_s, 1e-9)  # exposure * gain that hits the target
        e = float(np.clip(need, min_exposure_s, max_exposure_s))
        return e, float(np.clip(need / e, 1.0, max_gain))

    exp_s[0], gain[0] = settle(float(mean_radiance[0]))
    for i in range(1, n):
        seen = max(float(mean_radiance[i - 1]) * light_e_per_s * exp_s[i - 1] * gain[i - 1], 1e-9)
        eg = exp_s[i - 1] * gain[i - 1] * (target_e / seen) ** damping
        exp_s[i] = float(np.clip(eg, min_exposure_s, max_exposure_s))
        gain[i] = float(np.clip(eg / exp_s[i], 1.0, max_gain))
    return exp_s, gain
