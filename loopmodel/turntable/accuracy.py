"""Scatter of single-marker poses on the real turntable against the Cramér–Rao bound.

The bound of the project's ``bound`` tool (:mod:`loopmodel.accuracy`) for the same marker, distance,
viewing angle and the measured corner noise.

Parameters as in seed 001 (:mod:`loopmodel.accuracy.view`): ``r`` the camera's range along the
line of sight, ``v``/``u`` its position along the image x/y axes, ``gamma`` the roll about the
optical axis. The measured scatter is each single-marker pose (its four corners, robust
solver) about the marker pose the loop-closed graph predicts; the bound is the inverse Fisher
information of the four corners (their image flows from the tool's ``flows``) with the
measured corner noise. The solver also estimates the marker's two tilts, which the
seed's four-parameter bound holds fixed: the measured scatter can exceed that bound for this
reason alone.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from loopmodel.accuracy import crlb, flows, stabilised_views
from loopmodel.geometry.se3 import so3_log
from loopmodel.turntable.markers import marker_corners_in_marker

F64 = NDArray[np.float64]


@dataclass
class MarkerScatter:
    """Measured RMS scatter and the bound (r, v, u in mm; gamma in deg) and their ratio."""

    measured: dict[str, float]
    bound: dict[str, float]
    corner_noise_px: float
    distance_m: float
    theta_deg: float
    samples: int

    def as_dict(self) -> dict[str, object]:
        """Benchmark form."""
        ratio = {k: self.measured[k] / self.bound[k] for k in self.measured}
        return {
            "measured": self.measured,
            "bound": self.bound,
            "ratio": ratio,
            "corner_noise_px": self.corner_noise_px,
            "distance_m": self.distance_m,
            "theta_deg": self.theta_deg,
            "samples": self.samples,
        }


def marker_scatter(
    detections: list[dict[int, F64]],
    cam_from_table: list[F64],
    table_from_marker: dict[int, F64],
    side_m: float,
    K: F64,
    dist: F64,
) -> MarkerScatter:
    """Single-marker pose scatter about the graph's prediction, and the corner-noise bound."""
    from loopmodel.calibration.pose import target_pose

    dev, res2, dists, thetas = [], [], [], []
    local = marker_corners_in_marker(side_m)
    for det, G in zip(detections, cam_from_table, strict=True):
        for i, c in det.items():
            if i not in table_from_marker:
                continue
            pred = G @ table_from_marker[i]  # cam_from_marker
            r = target_pose(local, c, K, dist, pred)
            T = r.rig_from_ref
            res2.append(float(np.sum(r.residual_norms[0] ** 2)))
            # the marker's position in the camera frame: with the camera's orientation held
            # (the seed's space-stabilised camera) a camera move is minus this
            d_cam = T[:3, 3] - pred[:3, 3]
            roll = so3_log(T[:3, :3] @ pred[:3, :3].T)[2]
            dev.append([d_cam[2], d_cam[0], d_cam[1], roll])
            los = pred[:3, 3] / np.linalg.norm(pred[:3, 3])
            dists.append(float(np.linalg.norm(pred[:3, 3])))
            thetas.append(float(np.degrees(np.arccos(abs(float(pred[:3, 2] @ los))))))
    D = np.array(dev)
    # 8 residual components and 6 pose parameters per marker fit
    sigma_c = float(np.sqrt(np.sum(res2) / (len(res2) * (8 - 6)) / 2.0))
    meas = np.sqrt(np.mean((D - np.median(D, axis=0)) ** 2, axis=0))
    R, th = float(np.median(dists)), float(np.median(thetas))
    views = stabilised_views(R, th, np.arange(0.0, 360.0, 15.0), float(K[0, 0]))
    Q = flows(views, local[:, :2])  # (n, 4 corners, 4 params, 2)
    J = np.einsum("nmia,nmja->nij", Q, Q) / sigma_c**2
    b = crlb(J).sigma  # (n, 4): r, v, u in m; gamma in deg
    bm = np.median(b, axis=0)
    names = ("r_mm", "v_mm", "u_mm", "gamma_deg")
    measured = {
        names[0]: 1e3 * meas[0],
        names[1]: 1e3 * meas[1],
        names[2]: 1e3 * meas[2],
        names[3]: float(np.degrees(meas[3])),
    }
    bound = {names[0]: 1e3 * bm[0], names[1]: 1e3 * bm[1], names[2]: 1e3 * bm[2], names[3]: float(bm[3])}
    return MarkerScatter(measured, bound, sigma_c, R, th, len(D))
