"""Stereo rig calibration from chessboard pairs.

Intrinsics and distortion per camera, the extrinsics ``right_from_left``, rectification, and the
errors that judge them.

Steps: corners with sub-pixel refinement in every image; views without a board in both
images are rejected with the reason; each camera is calibrated alone (``cv2.calibrateCamera``),
views whose reprojection RMS is far above the others are rejected and the cameras
re-calibrated; then one joint refinement of both cameras and the extrinsics
(``cv2.stereoCalibrate`` seeded with the per-camera results). The reference the issue asks
for - plain ``cv2.calibrateCamera`` + ``cv2.stereoCalibrate`` with fixed intrinsics on the
same corners - is computed in the same run. Rectification is ``cv2.stereoRectify``
(alpha 0); its epipolar error is the row difference of the rectified corners.
Units: pixels, metres (the board's square size sets the scale).
"""

from __future__ import annotations

import logging
import re
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
from numpy.typing import NDArray

from loopmodel.calibration.chessboard import Corners, detect_in_file
from loopmodel.errors import InputError
from loopmodel.io.images import image_size
from loopmodel.io.mcap_io import camera_info_dicts
from loopmodel.types import StereoCalibration

logger = logging.getLogger(__name__)

F64 = NDArray[np.float64]

#: a view is rejected when its RMS exceeds this many times the median view RMS (and 1 px)
OUTLIER_VIEW_FACTOR = 3.0
MIN_VIEWS = 3


@dataclass
class RejectedView:
    """A view left out of the calibration, and why."""

    path: str
    reason: str


@dataclass
class ViewError:
    """Reprojection RMS (pixels) of one accepted stereo view, per camera."""

    left_path: str
    right_path: str
    rms_left_px: float
    rms_right_px: float


@dataclass
class StereoCalibrationResult:
    """A calibrated stereo rig (unrectified, with distortion) and its rectification.

    ``R_left``/``R_right`` rotate raw camera frames into the rectified ones, ``P_left``/
    ``P_right`` are the rectified 3x4 projections (``P_right[0, 3] = fx * t_x``).
    """

    calibration: StereoCalibration
    rms_left_px: float
    rms_right_px: float
    rms_stereo_px: float
    reference_rms_left_px: float
    reference_rms_right_px: float
    reference_rms_stereo_px: float
    epipolar_err_px_rms: float
    epipolar_err_px_max: float
    R_left: F64
    R_right: F64
    P_left: F64
    P_right: F64
    views: list[ViewError]
    rejected: list[RejectedView]
    corners_left: list[F64] = field(repr=False, default_factory=list)
    corners_right: list[F64] = field(repr=False, default_factory=list)
    square_m: float = 1.0

    def rectified(self) -> StereoCalibration:
        """The calibration of the rectified images (what the KITTI form and the front end use)."""
        K0, K1 = self.P_left[:3, :3].copy(), self.P_right[:3, :3].copy()
        right_from_left = np.eye(4)
        right_from_left[0, 3] = (self.P_right[0, 3] - self.P_left[0, 3]) / K1[0, 0]
        return StereoCalibration(K0, K1, right_from_left, self.calibration.image_size, rectified=True)


def _number(path: Path) -> int | None:
    m = re.findall(r"\d+", path.stem)
    return int(m[-1]) if m else None


def pair_images(left: list[Path], right: list[Path]) -> list[tuple[Path, Path]]:
    """Left/right image pairs, matched by file name number or by sorted order.

    By the last number in the file names when every name has one, else in sorted order (then the
    counts must agree).
    """
    if not left:
        raise InputError("IMAGES_LEFT", "no images")
    if not right:
        raise InputError("IMAGES_RIGHT", "no images")
    nl = {_number(p): p for p in left}
    nr = {_number(p): p for p in right}
    if None not in nl and None not in nr and len(nl) == len(left) and len(nr) == len(right):
        common = sorted(set(nl) & set(nr))  # type: ignore[type-var]
        if not common:
            raise InputError(str(left[0].parent), "no left and right images share a number in their names")
        alone = sorted((nl.keys() | nr.keys()) - set(common))  # type: ignore[type-var]
        if alone:  # said, as the KITTI reader does (issue 34)
            names = [(nl.get(k) or nr[k]).name for k in alone]
            logger.warning(
                "%d images without a partner of the same number skipped: %s", len(names), ", ".join(names[:5])
            )
        return [(nl[k], nr[k]) for k in common]
    if len(left) != len(right):
        raise InputError(str(right[0].parent), f"{len(left)} left but {len(right)} right images")
    return list(zip(sorted(left), sorted(right), strict=True))


def _view_rms(obj: F64, uv: F64, K: F64, d: F64, rvec: F64, tvec: F64) -> float:
    proj, _ = cv2.projectPoints(obj, rvec, tvec, K, d)
    return float(np.sqrt(np.mean(np.sum((proj.reshape(-1, 2) - uv) ** 2, axis=1))))


def _calibrate_one(
    obj: list[F64], uv: list[F64], size: tuple[int, int]
) -> tuple[float, F64, F64, list[F64], list[F64]]:
    o = [x.astype(np.float32) for x in obj]
    p = [x.astype(np.float32).reshape(-1, 1, 2) for x in uv]
    rms, K, d, rv, tv = cv2.calibrateCamera(o, p, size, None, None)
    return float(rms), np.asarray(K), np.asarray(d).ravel(), list(rv), list(tv)


def _stereo(
    obj: list[F64],
    uvl: list[F64],
    uvr: list[F64],
    K0: F64,
    d0: F64,
    K1: F64,
    d1: F64,
    size: tuple[int, int],
    flags: int,
) -> tuple[float, F64, F64, F64, F64, F64, F64]:
    o = [x.astype(np.float32) for x in obj]
    pl = [x.astype(np.float32).reshape(-1, 1, 2) for x in uvl]
    pr = [x.astype(np.float32).reshape(-1, 1, 2) for x in uvr]
    crit = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 100, 1e-6)
    rms, K0, d0, K1, d1, R, T, _E, _F = cv2.stereoCalibrate(
        o, pl, pr, K0.copy(), d0.copy(), K1.copy(), d1.copy(), size, flags=flags, criteria=crit
    )
    return float(rms), np.asarray(K0), np.asarray(d0).ravel(), np.asarray(K1), np.asarray(d1).ravel(), R, T


def epipolar_errors(uvl: list[F64], uvr: list[F64], cal: StereoCalibration, R0: F64, R1: F64, P0: F64, P1: F64) -> F64:
    """Row differences (pixels) of all corners after rectification (zero for a perfect rig)."""
    out = []
    for a, b in zip(uvl, uvr, strict=True):
        ra = cv2.undistortPoints(a.reshape(-1, 1, 2), cal.K_left, cal.dist_left, R=R0, P=P0).reshape(-1, 2)
        rb = cv2.undistortPoints(b.reshape(-1, 1, 2), cal.K_right, cal.dist_right, R=R1, P=P1).reshape(-1, 2)
        out.append(ra[:, 1] - rb[:, 1])
    return np.concatenate(out) if out else np.zeros(0)


def _same_grid(c: Corners, board: tuple[int, int]) -> bool:
    return c.grid == board


def calibrate_stereo(
    pairs: list[tuple[Path, Path]], board: tuple[int, int], square_m: float
) -> StereoCalibrationResult:
    """Calibrate a stereo rig from chessboard image pairs.

    ``board`` inner corners, squares of ``square_m`` metres.
    """
    if not (np.isfinite(square_m) and square_m > 0):
        raise InputError("--square-m", f"square size must be a positive number of metres, got {square_m}")
    rejected: list[RejectedView] = []
    accepted: list[tuple[Path, Path, Corners, Corners]] = []
    first = pairs[0][0]
    size = image_size(first)
    for lp, rp in pairs:  # sizes first: a wrong image fails before any corner search
        for p in (lp, rp):
            s = image_size(p)
            if s != size:
                raise InputError(p, f"image size {s[0]}x{s[1]}, expected {size[0]}x{size[1]} (as {first})")
    for lp, rp in pairs:
        found = []
        for p in (lp, rp):
            c, _ = detect_in_file(p, board, square_m)
            found.append(c)
        cl, cr = found
        if cl is None or cr is None:
            miss = lp if cl is None else rp
            rejected.append(RejectedView(str(miss), f"no {board[0]}x{board[1]} chessboard corners found"))
            continue
        if not (_same_grid(cl, board) and _same_grid(cr, board)):
            rejected.append(RejectedView(str(lp), "board detected with a different orientation in the two images"))
            continue
        accepted.append((lp, rp, cl, cr))
    if len(accepted) < MIN_VIEWS:
        why = "; ".join(f"{r.path}: {r.reason}" for r in rejected[:3])
        raise InputError(
            pairs[0][0] if not rejected else rejected[0].path,
            f"only {len(accepted)} of {len(pairs)} views have a {board[0]}x{board[1]} board in both images "
            f"(need {MIN_VIEWS}; wrong --board?){' - ' + why if why else ''}",
        )

    # per camera, then reject views far worse than the rest and calibrate again
    while True:
        obj = [a[2].board_m for a in accepted]
        uvl = [a[2].uv_px for a in accepted]
        uvr = [a[3].uv_px for a in accepted]
        _, K0, d0, rv0, tv0 = _calibrate_one(obj, uvl, size)
        _, K1, d1, rv1, tv1 = _calibrate_one(obj, uvr, size)
        el = np.array([_view_rms(o, u, K0, d0, r, t) for o, u, r, t in zip(obj, uvl, rv0, tv0, strict=True)])
        er = np.array([_view_rms(o, u, K1, d1, r, t) for o, u, r, t in zip(obj, uvr, rv1, tv1, strict=True)])
        worst = np.maximum(el, er)
        limit = max(OUTLIER_VIEW_FACTOR * float(np.median(worst)), 1.0)
        k = int(np.argmax(worst))
        if worst[k] <= limit or len(accepted) <= MIN_VIEWS:
            break
        rejected.append(
            RejectedView(str(accepted[k][0]), f"reprojection RMS {worst[k]:.2f} px > {limit:.2f} px (outlier view)")
        )
        del accepted[k]

    # reference: plain OpenCV on exactly these corners
    ref_l, rK0, rd0, _, _ = _calibrate_one(obj, uvl, size)
    ref_r, rK1, rd1, _, _ = _calibrate_one(obj, uvr, size)
    ref_s, *_ = _stereo(obj, uvl, uvr, rK0, rd0, rK1, rd1, size, cv2.CALIB_FIX_INTRINSIC)

    # joint refinement of both cameras and the extrinsics
    rms_s, K0, d0, K1, d1, R, T = _stereo(obj, uvl, uvr, K0, d0, K1, d1, size, cv2.CALIB_USE_INTRINSIC_GUESS)
    right_from_left = np.eye(4)
    right_from_left[:3, :3] = R
    right_from_left[:3, 3] = np.asarray(T).ravel()
    cal = StereoCalibration(K0, K1, right_from_left, size, d0, d1, rectified=False).check("stereo calibration")

    # per-view errors of the final cameras (board poses re-fitted per view with the final intrinsics)
    views = []
    sq_l, sq_r, n = 0.0, 0.0, 0
    for lp, rp, cl, cr in accepted:
        errs = []
        for c, K, d in ((cl, K0, d0), (cr, K1, d1)):
            ok, rvec, tvec = cv2.solvePnP(c.board_m, c.uv_px, K, d, flags=cv2.SOLVEPNP_ITERATIVE)
            errs.append(_view_rms(c.board_m, c.uv_px, K, d, rvec, tvec))
        views.append(ViewError(str(lp), str(rp), errs[0], errs[1]))
        sq_l += errs[0] ** 2 * len(cl.uv_px)
        sq_r += errs[1] ** 2 * len(cr.uv_px)
        n += len(cl.uv_px)

    left_info, right_info = camera_info_dicts(cal)
    R0 = np.array(left_info["r"]).reshape(3, 3)
    R1 = np.array(right_info["r"]).reshape(3, 3)
    P0 = np.array(left_info["p"]).reshape(3, 4)
    P1 = np.array(right_info["p"]).reshape(3, 4)
    epi = epipolar_errors(uvl, uvr, cal, R0, R1, P0, P1)
    return StereoCalibrationResult(
        cal,
        float(np.sqrt(sq_l / n)),
        float(np.sqrt(sq_r / n)),
        rms_s,
        ref_l,
        ref_r,
        ref_s,
        float(np.sqrt(np.mean(epi**2))),
        float(np.max(np.abs(epi))),
        R0,
        R1,
        P0,
        P1,
        views,
        rejected,
        uvl,
        uvr,
        square_m,
    )


def stereo_summary(result: StereoCalibrationResult) -> dict[str, object]:
    """The calibration summary written as ``--out``.

    Both cameras as ROS ``camera_info`` dicts, the extrinsics, the rectification and every error
    figure.
    """
    from loopmodel.io.camera_yaml import camera_info_yaml

    left, right = camera_info_dicts(result.calibration)
    cal = result.calibration
    return {
        "left": camera_info_yaml(left, "left"),
        "right": camera_info_yaml(right, "right"),
        "right_from_left": [[float(x) for x in row] for row in cal.right_from_left],
        "baseline_m": float(cal.baseline_m),
        "square_m": float(result.square_m),
        "rms_left_px": result.rms_left_px,
        "rms_right_px": result.rms_right_px,
        "rms_stereo_px": result.rms_stereo_px,
        "reference_opencv": {
            "rms_left_px": result.reference_rms_left_px,
            "rms_right_px": result.reference_rms_right_px,
            "rms_stereo_px": result.reference_rms_stereo_px,
        },
        "epipolar_err_px_rms": result.epipolar_err_px_rms,
        "epipolar_err_px_max": result.epipolar_err_px_max,
        "views": [
            {"left": v.left_path, "right": v.right_path, "rms_left_px": v.rms_left_px, "rms_right_px": v.rms_right_px}
            for v in result.views
        ],
        "rejected": [{"path": r.path, "reason": r.reason} for r in result.rejected],
    }


def write_stereo_outputs(result: StereoCalibrationResult, out: Path) -> list[Path]:
    """Write the summary YAML, the ROS camera_info files, the KITTI calib file and the errors plot.

    ``out`` (summary YAML), ``<stem>_left.yaml`` / ``<stem>_right.yaml`` (ROS ``camera_info``),
    ``<stem>_kitti_calib.txt`` (rectified P0/P1) and ``<stem>_errors.png``.
    """
    from loopmodel.calibration.plots import plot_stereo_calibration
    from loopmodel.io.atomic import write_text_atomic
    from loopmodel.io.camera_yaml import dump_yaml, write_camera_info_yaml, write_kitti_calib

    left, right = camera_info_dicts(result.calibration)
    stem = out.with_suffix("")
    paths = [
        write_text_atomic(out, dump_yaml(stereo_summary(result))),
        write_camera_info_yaml(Path(f"{stem}_left.yaml"), left, "left"),
        write_camera_info_yaml(Path(f"{stem}_right.yaml"), right, "right"),
        write_kitti_calib(Path(f"{stem}_kitti_calib.txt"), result.P_left, result.P_right),
        plot_stereo_calibration(result, Path(f"{stem}_errors.png")),
    ]
    return paths
