"""Self-calibration (issue 31).

The calibrating bundle adjustment, its Jacobians, the laser-stereo scale, the refined calibration file.

The scans are synthetic (``selfcal_scene``): a true distorted rig, a recorded calibration off by the
realistic world's errors, measurements made in images rectified with the recorded calibration.
"""

from __future__ import annotations

import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).parent))

from selfcal_scene import make_scene, recorded_rig, true_rig  # noqa: E402

from loopmodel.calibration.refine_laser import keyframe_discrepancies, laser_stereo_scale  # noqa: E402
from loopmodel.calibration.refine_rig import (  # noqa: E402
    PARAM_NAMES,
    RigParameters,
    anchored_held_directions,
    observations_from_keyframes,
    prior_sigmas,
    project_with_jacobians,
    raw_from_rectified_px,
    refine_rig,
    residuals_and_jacobians,
)
from loopmodel.calibration.selfcal import (  # noqa: E402
    anchors_principal_point,
    estimated_parameters,
    final_observations,
    refine_final,
)
from loopmodel.config import SelfCalibrationConfig  # noqa: E402
from loopmodel.errors import LoopmodelError  # noqa: E402
from loopmodel.geometry.align import umeyama_alignment  # noqa: E402
from loopmodel.geometry.se3 import so3_exp, so3_log  # noqa: E402
from loopmodel.types import StereoCalibration, StripeProfile  # noqa: E402

PRIOR = prior_sigmas(0.3, 0.3, 0.002, 0.002, 0.02, 5e-5)
# the pipeline's unknowns with the right columns only (the observations of ``_problem``)
EST = estimated_parameters(SelfCalibrationConfig(refine_right_rows=False))
N_KF, N_PT = 30, 1200


def _problem(recorded, seed: int, n_kf: int = N_KF, n_pt: int = N_PT):
    sc = make_scene(recorded, n_kf=n_kf, n_points=n_pt, noise_px=0.1, seed=seed)
    obs, kf_ids, lm_ids = observations_from_keyframes(
        sc.keyframes, sc.recorded, sc.P1[:3, :3], sc.P2[:3, :3], sc.R1, sc.R2
    )
    pts0 = sc.points_w[lm_ids % n_pt] + np.random.default_rng(0).normal(0, 1e-3, (lm_ids.size, 3))
    return sc, obs, pts0


def _true_values(sc) -> np.ndarray:
    """The true rig in the recorded rig's parameters (rotation: correction of the recorded one)."""
    tr = RigParameters.of(sc.true).values
    tr[12:15] = so3_log(sc.true.right_from_left[:3, :3] @ sc.recorded.right_from_left[:3, :3].T)
    return tr


def _pose_error_mm(poses: np.ndarray, truth: np.ndarray) -> float:
    """Position RMS after a similarity alignment (mm): the shape of the trajectory, not its scale."""
    R, t, s = umeyama_alignment(poses[:, :3, 3], truth[:, :3, 3], with_scale=True)
    p = s * poses[:, :3, 3] @ np.asarray(R).T + t
    return 1e3 * float(np.sqrt(np.mean(np.sum((p - truth[:, :3, 3]) ** 2, axis=1))))


# ----------------------------------------------------------------------------- (c) Jacobians


def test_projection_matches_opencv_and_rectification_round_trip() -> None:
    rig = true_rig()
    rng = np.random.default_rng(1)
    p = np.column_stack([rng.uniform(-0.2, 0.2, (50, 2)), rng.uniform(0.3, 0.8, 50)])
    K, d = rig.K_right, rig.dist_right
    uv, _, _ = project_with_jacobians(p, np.array([K[0, 0], K[1, 1], K[0, 2], K[1, 2]]), d)
    ref, _ = cv2.projectPoints(p.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), K, d)
    assert np.abs(uv - ref.reshape(-1, 2)).max() < 1e-9
    # rectified -> raw (ours) -> rectified (OpenCV's undistortPoints with R and P)
    from loopmodel.imaging.rectify import rectification

    R1, R2, P1, P2 = rectification(rig)
    rect = np.column_stack([rng.uniform(50, 590, 50), rng.uniform(50, 430, 50)])
    raw = raw_from_rectified_px(rect, P2[:3, :3], R2, K, d)
    back = cv2.undistortPoints(
        raw.reshape(-1, 1, 2), K, d, R=R2, P=P2, criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-14)
    ).reshape(-1, 2)
    assert np.abs(back - rect).max() < 1e-6


@pytest.mark.parametrize("right_rows", [False, True])
def test_jacobians_match_finite_differences(right_rows: bool) -> None:
    sc, obs, _ = _problem(recorded_rig(true_rig(), 4), 4, 12, 400)
    R, t = sc.world_from_kf[:, :3, :3], sc.world_from_kf[:, :3, 3]
    obs_r, _, lm_ids = observations_from_keyframes(
        sc.keyframes, sc.recorded, sc.P1[:3, :3], sc.P2[:3, :3], sc.R1, sc.R2, sc.right_rows
    )
    if right_rows:
        obs = obs_r
    pts = sc.points_w[lm_ids % 400]
    rig = RigParameters.of(sc.recorded)
    theta = rig.values.copy()
    theta[:12] += np.random.default_rng(2).normal(0, 1e-3, 12)  # away from the recorded values
    r, Jp, Jl, Jt = residuals_and_jacobians(obs, R, t, pts, rig, theta)
    if right_rows:  # every row measured
        assert np.all(obs.row_measured) and np.all(r[:, 1] != 0) and obs.residual_count == 2 * len(obs)
    else:  # right points: only the rectified u is measured
        assert np.any(r[:, 1] == 0) and np.any(r[:, 1] != 0) and not np.all(obs.row_measured)

    def check(num: np.ndarray, ana: np.ndarray) -> None:
        scale = max(float(np.abs(ana).max()), 1e-12)
        assert np.abs(num - ana).max() < 2e-5 * scale + 1e-7

    for k in range(len(PARAM_NAMES)):
        h = 1e-6 if k not in (12, 13, 14) else 1e-8
        tp, tm = theta.copy(), theta.copy()
        tp[k] += h
        tm[k] -= h
        num = residuals_and_jacobians(obs, R, t, pts, rig, tp)[0]
        num = num - residuals_and_jacobians(obs, R, t, pts, rig, tm)[0]
        check(num / (2 * h), Jt[:, :, k])
    for k in range(6):
        d = np.zeros(6)
        d[k] = 1e-7
        Rp, Rm = R @ so3_exp(d[:3]), R @ so3_exp(-d[:3])
        tp, tm = t + np.einsum("nij,j->ni", R, d[3:]), t - np.einsum("nij,j->ni", R, d[3:])
        num = residuals_and_jacobians(obs, Rp, tp, pts, rig, theta)[0] - residuals_and_jacobians(
            obs, Rm, tm, pts, rig, theta
        )[0]
        check(num / 2e-7, Jp[:, :, k])
    for k in range(3):
        pp, pm = pts.copy(), pts.copy()
        pp[:, k] += 1e-7
        pm[:, k] -= 1e-7
        num = residuals_and_jacobians(obs, R, t, pp, rig, theta)[0]
        num = num - residuals_and_jacobians(obs, R, t, pm, rig, theta)[0]
        check(num / 2e-7, Jl[:, :, k])


# ----------------------------------------------------------------------------- (a) recovery


def test_injected_calibration_error_is_recovered() -> None:
    """A seeded injected error (the realistic world's sigmas) is recovered.

    The estimate is consistent with its posterior sigma and nearer the truth than the recorded values;
    the keyframe poses are as good as with the true calibration (within 2x), the recorded ones not.
    """
    seed = 2
    sc, obs, pts0 = _problem(recorded_rig(true_rig(), seed), seed)
    poses, _pts, rep = refine_rig(obs, sc.world_from_kf.copy(), pts0, sc.recorded, PRIOR, EST)
    truth = _true_values(sc)
    est = rep.estimated
    z_after = (rep.values - truth)[est] / rep.posterior_sigma[est]
    before = (rep.recorded_values - truth)[est] / PRIOR[est]
    after = (rep.values - truth)[est] / PRIOR[est]
    # the baseline (scale) is not observable from images alone
    assert "baseline_m" in rep.unobservable and rep.values[-1] == rep.recorded_values[-1]
    # within 1 sigma on the whole (rms of the normalised errors; measured 0.99), none beyond 3 sigma
    assert float(np.sqrt(np.mean(z_after**2))) < 1.5
    assert np.abs(z_after).max() < 3.0
    # rms error in prior sigmas: measured 1.01 -> 0.74
    assert np.sqrt(np.mean(after**2)) < 0.85 * np.sqrt(np.mean(before**2))
    # the disparity parameters the issue names dominate the depth error: recovered within a prior sigma
    for name in ("cx_right_px", "k1_right", "k1_left", "cx_left_px"):
        i = PARAM_NAMES.index(name)
        assert abs(rep.values[i] - truth[i]) < PRIOR[i]
    # poses: refined vs the same scan measured and adjusted with the true calibration
    sct, obst, pts0t = _problem(None, seed)
    none = np.zeros(len(PARAM_NAMES), bool)
    p_true, _, _ = refine_rig(obst, sct.world_from_kf.copy(), pts0t, sct.true, PRIOR, estimate=none)
    p_rec, _, _ = refine_rig(obs, sc.world_from_kf.copy(), pts0, sc.recorded, PRIOR, estimate=none)
    e_ref, e_true, e_rec = (_pose_error_mm(p, sc.world_from_kf) for p in (poses, p_true, p_rec))
    assert e_ref < 2.0 * e_true  # measured 0.213 vs 0.203 mm
    assert e_rec > 2.0 * e_true  # the recorded calibration bends the trajectory (measured 1.13 mm)


def test_posterior_sigmas_cover_the_errors() -> None:
    """The reported posterior sigmas (track-robust, with the held parameters considered) match the errors.

    Normalised errors against the truth over three seeded scans, the parameters the data constrain:
    their rms near 1, neither over-confident (the pixel-noise model alone: rms 1.36) nor inflated.
    """
    z_honest, z_model = [], []
    for seed in (2, 3, 4):
        sc, obs, pts0 = _problem(recorded_rig(true_rig(), seed), seed, n_kf=20, n_pt=800)
        _poses, _pts, rep = refine_rig(obs, sc.world_from_kf.copy(), pts0, sc.recorded, PRIOR, EST)
        constrained = rep.estimated & np.array([n not in rep.unobservable for n in PARAM_NAMES])
        err = (rep.values - _true_values(sc))[constrained]
        z_honest.append(err / rep.posterior_sigma[constrained])
        z_model.append(err / rep.posterior_sigma_model[constrained])
        # the held right-row parameters (wrong in the recorded rig) widen cy_left the most
        i = PARAM_NAMES.index("cy_left_px")
        assert rep.posterior_sigma_consider[i] > 0.3 * rep.posterior_sigma_model[i]
    zh, zm = np.concatenate(z_honest), np.concatenate(z_model)
    rms_h, rms_m = float(np.sqrt(np.mean(zh**2))), float(np.sqrt(np.mean(zm**2)))
    assert 0.7 < rms_h < 1.25  # measured 1.02 (30 errors)
    assert np.abs(zh).max() < 2.6  # measured 2.17
    assert rms_m > rms_h  # measured 1.36: the pixel-noise model alone is over-confident


# ----------------------------------------------------------------------------- (b) no error


def test_well_calibrated_rig_moves_nothing_beyond_its_sigma() -> None:
    sc, obs, pts0 = _problem(None, seed=6)  # recorded == true
    _poses, _pts, rep = refine_rig(obs, sc.world_from_kf.copy(), pts0, sc.recorded, PRIOR, EST)
    moved = rep.moved_sigma()
    assert max(abs(v) for v in moved.values()) < 1.0, moved


# ----------------------------------------------------------------------------- laser-stereo


def test_laser_stereo_scale_finds_a_plane_offset_error() -> None:
    """Stripes triangulated with a plane offset 0.3 % too large, on a wall the landmarks see.

    The discrepancy is measured, and the baseline and plane offset share it by their priors (no tilt
    is found where there is none).
    """
    rng = np.random.default_rng(3)
    n = np.array([0.977, 0.0, 0.213])
    n /= np.linalg.norm(n)
    d_plane = -float(n @ np.array([0.12, 0.0, 0.0]))
    kfs, lms, stripes, poses = {}, {}, [], {}
    pts_w = []
    for k in range(8):
        T = np.eye(4)
        T[:3, 3] = [0.01 * k, 0.0, 0.0]
        poses[k] = T
        z = 0.45 + 0.02 * k  # a wall facing the camera at depth z; landmarks on it
        xy = rng.uniform(-0.15, 0.15, (300, 2))
        p = np.column_stack([xy, np.full(300, z)])
        pts_w.append(p + T[:3, 3])
        lms[k] = np.arange(300) + 1000 * k
        # the stripe: the light plane on the wall, triangulated with an offset 0.3 % too large
        y = np.linspace(-0.1, 0.1, 80)
        x = (-d_plane - n[2] * z) / n[0]
        stripes.append(StripeProfile(k * 100, np.column_stack([np.full(80, x), y, np.full(80, z)]) * 1.003))
        kfs[k] = k * 100
    ids_all = np.concatenate([lms[k] for k in range(8)])
    P = np.concatenate(pts_w)
    d, used = keyframe_discrepancies(stripes[0].points_in_cam, P[:300], 500.0)
    assert d.size > 5 and used.shape == (d.size, 3) and abs(float(np.median(d)) - np.log(1.003)) < 2e-4
    est = laser_stereo_scale(
        stripes, kfs, poses, lms, ids_all, P, true_rig(), 8.3e-4, 8.5e-4, n, d_plane * 1.003, np.radians(0.02)
    )
    assert est is not None and est.keyframes == 8
    assert abs(est.discrepancy_log - np.log(1.003)) < 2e-4
    # the constant part of the model takes the discrepancy; the priors (near equal) share it out
    assert abs((est.log_baseline - est.log_plane_offset) - est.discrepancy_log) < 0.2 * est.discrepancy_log
    assert est.log_baseline > 0 > est.log_plane_offset
    assert np.all(np.abs(est.tilt_rad) < 3 * est.sigma_tilt_rad)
    n_new, d_new = est.refined_plane(n, d_plane * 1.003)
    assert abs(float(n_new @ n) - 1.0) < 1e-6 and abs(d_new / (d_plane * 1.003) - est.plane_offset_factor) < 1e-12


# ----------------------------------------------------------------------------- (d) the file


def test_refined_calibration_file_is_read_by_calib(tmp_path: Path) -> None:
    from loopmodel.io.calib_files import read_stereo_calibration, refined_calibration_yaml

    sc, obs, pts0 = _problem(recorded_rig(true_rig(), 2), 2, 12, 400)
    _poses, _pts, rep = refine_rig(obs, sc.world_from_kf.copy(), pts0, sc.recorded, PRIOR, EST)
    cal = rep.calibration
    params = {
        n: {"sigma": s, "refined": v}
        for (n, s), v in zip(rep.sigma_named().items(), rep.values_named().values(), strict=True)
    }
    path = tmp_path / "calibration_refined.yaml"
    path.write_text(refined_calibration_yaml(cal, {"parameters": params}))
    back = read_stereo_calibration(path)
    assert not back.rectified and back.camera_model == "pinhole"
    assert np.allclose(back.K_left, cal.K_left) and np.allclose(back.K_right, cal.K_right)
    assert np.allclose(back.dist_left, cal.dist_left) and np.allclose(back.dist_right, cal.dist_right)
    assert np.allclose(back.right_from_left, cal.right_from_left)
    import yaml

    data = yaml.safe_load(path.read_text())
    assert data["cam1"]["sigma"]["cx_px"] == pytest.approx(rep.sigma_named()["cx_right_px"])


# ----------------------------------------------------------------------------- the run


def test_run_writes_the_refined_calibration(tmp_path: Path) -> None:
    """``calibration.refine: final`` in a run: the file, the metrics, and a trajectory no worse."""
    from frontend_scene import write_kitti_folder

    from loopmodel.config import Config
    from loopmodel.io.calib_files import read_stereo_calibration
    from loopmodel.io.sequence import open_sequence
    from loopmodel.pipeline import run_pipeline

    folder = tmp_path / "seq"
    write_kitti_folder(folder, 14, np.random.default_rng(7))
    out = {}
    for refine in ("none", "final"):
        cfg = Config()
        cfg.frontend.max_disparity_px = 64
        cfg.frontend.max_features = 400
        cfg.frontend.min_tracked_fraction = 0.95
        cfg.calibration.refine = refine  # type: ignore[assignment]
        out[refine] = run_pipeline(open_sequence(folder), cfg, tmp_path, refine)
    res = out["final"]
    m = res.metrics
    assert m["calibration_refine"] == "final" and "baseline_m" in m["calibration_unobservable"]
    # a perfectly calibrated (rendered) rig: nothing moves beyond its sigma
    assert m["calibration_moved_max_sigma"] < 1.0, m["calibration_moved_sigma"]
    assert m["ate_rmse_m"] <= 1.1 * out["none"].metrics["ate_rmse_m"] + 5e-5
    assert res.folder is not None
    cal = read_stereo_calibration(res.folder / "calibration_refined.yaml")
    seq_cal = open_sequence(folder).calibration
    assert abs(cal.baseline_m - seq_cal.baseline_m) < 1e-9
    assert np.allclose(cal.K_left, res.calibration_refined.K_left)
    assert not (out["none"].folder / "calibration_refined.yaml").exists()


def test_refining_reads_right_columns_at_their_rows() -> None:
    """While refining, the front end measures the right column at the match's own row (gradient_2d).

    With refine none the front end's own setting stands; ``calibration.stereo_subpixel: frontend`` keeps it too.
    """
    from loopmodel.config import Config

    cfg = Config()
    own = cfg.frontend.stereo_subpixel
    assert own != "gradient_2d"  # the front end's default (else the test checks nothing)
    cfg.calibration.refine = "none"  # type: ignore[assignment]
    assert cfg.calibration.frontend_config(cfg.frontend).stereo_subpixel == own
    cfg.calibration.refine = "final"  # type: ignore[assignment]
    assert cfg.calibration.frontend_config(cfg.frontend).stereo_subpixel == "gradient_2d"
    assert cfg.frontend.stereo_subpixel == own  # the run's configuration is not changed
    cfg.calibration.stereo_subpixel = "frontend"  # type: ignore[assignment]
    assert cfg.calibration.frontend_config(cfg.frontend).stereo_subpixel == own


def test_measured_right_rows_make_the_row_parameters_observable() -> None:
    """With the right image's rows measured, its fy, cy and the rotation about the baseline are estimated.

    From the right columns alone those three are hardly informed (``refine_right_rows`` off); with
    the rows they are observable, the errors stay consistent with the posterior sigmas, and the rotation
    about the optical axis (which moves right points along the rows too) is better determined.
    """
    seed = 1
    sc, obs_u, pts0 = _problem(recorded_rig(true_rig(), seed), seed)
    obs, _, _ = observations_from_keyframes(
        sc.keyframes, sc.recorded, sc.P1[:3, :3], sc.P2[:3, :3], sc.R1, sc.R2, sc.right_rows
    )
    rows = [PARAM_NAMES.index(n) for n in ("fy_right_px", "cy_right_px", "rot_x_deg")]
    est = EST.copy()
    est[rows] = True
    _poses, _pts, rep = refine_rig(obs, sc.world_from_kf.copy(), pts0, sc.recorded, PRIOR, est)
    _poses, _pts, rep_u = refine_rig(obs_u, sc.world_from_kf.copy(), pts0, sc.recorded, PRIOR, est)
    truth = _true_values(sc)
    for i in rows:
        # posterior / prior, u only -> rows measured: 1.25 -> 0.71, 1.08 -> 0.86, 1.10 -> 0.81 (measured)
        assert rep.estimated[i] and PARAM_NAMES[i] not in rep.unobservable
        assert rep.posterior_sigma[i] < 0.9 * rep_u.posterior_sigma[i]
    z = ((rep.values - truth) / rep.posterior_sigma)[rep.estimated]
    # measured on seeds 1 / 2 / 3: rms 0.63 / 0.88 / 0.59, max 1.15 / 2.12 / 1.12 (u only, seed 1: 0.82, 2.15)
    assert float(np.sqrt(np.mean(z**2))) < 1.2 and float(np.abs(z).max()) < 2.5
    rz = PARAM_NAMES.index("rot_z_deg")
    # posterior / prior of the rotation about z: 0.20 -> 0.13 (measured); error -0.40 -> -0.15 prior sigmas
    assert rep.posterior_sigma[rz] < 0.8 * rep_u.posterior_sigma[rz]


# ----------------------------------------------------------------------------- unobservable combinations


def _rows_problem(recorded, seed: int, n_kf: int, arc_deg: float, n_pt: int = 800):
    sc = make_scene(recorded, n_kf=n_kf, n_points=n_pt, noise_px=0.1, seed=seed, arc_deg=arc_deg)
    obs, _kf, lm_ids = observations_from_keyframes(
        sc.keyframes, sc.recorded, sc.P1[:3, :3], sc.P2[:3, :3], sc.R1, sc.R2, sc.right_rows
    )
    pts0 = sc.points_w[lm_ids % n_pt] + np.random.default_rng(0).normal(0, 1e-3, (lm_ids.size, 3))
    return sc, obs, pts0


def test_an_unobservable_combination_is_held_and_reported() -> None:
    """A common vertical principal point of both cameras is nearly a rotation of the rig about x.

    On a short arc (60 deg, 10 keyframes) each cy is informed by the right rows, but their common
    move hardly is (posterior/prior 0.98, measured): the per-parameter check cannot see it. Held
    (``observable_direction_ratio``), the refinement does not move along it, reports it, and its
    prior variance stays in the parameters' sigmas; the rest is estimated as well as before.
    """
    est = estimated_parameters(SelfCalibrationConfig(refine_right_rows=True))
    seed = 1
    sc, obs, pts0 = _rows_problem(recorded_rig(true_rig(), seed), seed, n_kf=10, arc_deg=60.0)
    _p, _q, free = refine_rig(obs, sc.world_from_kf.copy(), pts0, sc.recorded, PRIOR, est)
    _p, _q, held = refine_rig(
        obs, sc.world_from_kf.copy(), pts0, sc.recorded, PRIOR, est, observable_direction_ratio=0.9
    )
    common = {"cy_left_px": 1.0, "cy_right_px": 1.0}
    assert free.direction_ratio(common) > 0.95  # measured 0.981
    assert "cy_left_px" not in free.unobservable and "cy_right_px" not in free.unobservable
    assert not free.unobservable_directions
    # reported: a held direction made mostly of the two cy
    cy_dirs = [d for d in held.unobservable_directions if abs(d.get("cy_left_px", 0.0)) > 0.4
               and abs(d.get("cy_right_px", 0.0)) > 0.4]
    assert cy_dirs and all(d["ratio"] > 0.9 for d in held.unobservable_directions)
    # not moved along any held direction (prior-whitened), while the free solution moves along them
    act = held.estimated
    along_held = held.held_directions.T @ ((held.values - held.recorded_values) / PRIOR)
    along_free = held.held_directions.T @ ((free.values - free.recorded_values) / PRIOR)
    assert held.held_directions.shape[1] == len(held.unobservable_directions)
    assert np.abs(along_held).max() < 1e-3  # measured 1e-6 (the stiff prior's sigma 1e-3)
    assert np.abs(along_free).max() > 0.02  # the free solution does move along them
    # its prior variance is in the sigmas (consider): cy's model sigma as the free solution's, where
    # the data hardly moved it from the prior (measured 0.227 / 0.223 px held, 0.223 / 0.219 free)
    for n in ("cy_left_px", "cy_right_px"):
        i = PARAM_NAMES.index(n)
        s_held = np.hypot(held.posterior_sigma_model[i], held.posterior_sigma_consider[i])
        assert s_held >= 0.97 * free.posterior_sigma_model[i]
        assert held.posterior_sigma_consider[i] > 2.0 * held.posterior_sigma_model[i]  # measured 0.225 vs 0.027
    truth = _true_values(sc)
    z = ((held.values - truth) / held.posterior_sigma)[act]
    assert np.abs(z).max() < 2.5  # measured 1.79 (free 1.64)
    # the rest about as good against the truth (rms in prior sigmas; measured 0.49 free, 0.55 held)
    e_free = np.sqrt(np.mean((((free.values - truth) / PRIOR)[act]) ** 2))
    e_held = np.sqrt(np.mean((((held.values - truth) / PRIOR)[act]) ** 2))
    assert e_held < 1.1 * e_free + 0.05


def test_well_calibrated_rig_with_rows_and_held_combinations_moves_nothing() -> None:
    """The configuration's refinement (right rows measured, weak combinations held): a correct rig stays."""
    cfg = SelfCalibrationConfig(refine_right_rows=True, observable_direction_ratio=0.7)
    sc, obs, pts0 = _rows_problem(None, seed=6, n_kf=30, arc_deg=300.0)
    _p, _q, rep = refine_rig(obs, sc.world_from_kf.copy(), pts0, sc.recorded, PRIOR, estimated_parameters(cfg),
                             observable_direction_ratio=cfg.observable_direction_ratio)
    moved = rep.moved_sigma()
    assert max(abs(v) for v in moved.values()) < 1.0, moved  # measured max 0.13
    assert rep.unobservable_directions  # the scan's weak combinations are held (measured: 6, 0.73-0.96)


def test_a_held_common_principal_point_is_held_through_the_left_camera() -> None:
    """A right-camera principal-point error on a short arc, where the common principal point is held.

    Recorded rig: the true one with the right camera's cx 0.6 px and cy 0.4 px off (a right-image
    rectification error; KITTI's refinement finds one, ridge9). The data determine the left-right
    difference, not the common shift (nearly a rotation of every pose), which is held. Held as the
    sum of both, the difference is split between the cameras by their priors and the left camera's
    share turns the reported frame; held through the left camera (``anchor_principal_point``) the
    left principal point stays and the right camera carries the error.
    """
    tr = true_rig()
    KR = tr.K_right.copy()
    KR[0, 2] -= 0.6
    KR[1, 2] += 0.4
    rec = StereoCalibration(tr.K_left.copy(), KR, tr.right_from_left.copy(), tr.image_size, tr.dist_left.copy(),
                            tr.dist_right.copy(), rectified=False)
    est = estimated_parameters(SelfCalibrationConfig(refine_right_rows=True))
    sc, obs, pts0 = _rows_problem(rec, 1, n_kf=10, arc_deg=60.0)
    truth = _true_values(sc)
    i = {n: PARAM_NAMES.index(n) for n in ("cx_left_px", "cy_left_px", "cx_right_px", "cy_right_px")}
    runs = {}
    for anchor in (False, True):
        _p, _q, runs[anchor] = refine_rig(obs, sc.world_from_kf.copy(), pts0, sc.recorded, PRIOR, est,
                                          observable_direction_ratio=0.9, anchor_principal_point=anchor)
    split, held = runs[False], runs[True]
    assert split.anchored == [] and held.anchored == ["cx_left_px", "cy_left_px"]
    moved = held.values - held.recorded_values
    assert abs(moved[i["cx_left_px"]]) < 0.01 and abs(moved[i["cy_left_px"]]) < 0.01  # measured 0.000
    # the right camera carries the error (measured off the truth by 0.073 / 0.005 px; split: 0.32 / 0.16)
    assert abs(held.values[i["cx_right_px"]] - truth[i["cx_right_px"]]) < 0.15
    assert abs(held.values[i["cy_right_px"]] - truth[i["cy_right_px"]]) < 0.1
    assert abs(split.values[i["cx_left_px"]] - split.recorded_values[i["cx_left_px"]]) > 0.15  # measured 0.27
    # the same left-right difference either way (what the data determine)
    for a, b in (("cx_left_px", "cx_right_px"), ("cy_left_px", "cy_right_px")):
        assert abs((held.values[i[a]] - held.values[i[b]]) - (split.values[i[a]] - split.values[i[b]])) < 0.06
    z = ((held.values - truth) / held.posterior_sigma)[held.estimated]
    assert np.abs(z).max() < 2.0  # measured 1.33 (split 1.44)
    # the held directions: orthonormal, with their complement a basis; the left cx among them
    names = [n for n, a in zip(PARAM_NAMES, held.estimated, strict=True) if a]
    U = held.held_directions[held.estimated]
    H, O, pinned = anchored_held_directions(U, names)
    assert pinned == [] and np.allclose(H, U)  # already anchored: unchanged
    B = np.column_stack([O, H])
    assert np.allclose(B.T @ B, np.eye(len(names)), atol=1e-9)
    e = np.zeros(len(names))
    e[names.index("cx_left_px")] = 1.0
    assert np.linalg.norm(U @ (U.T @ e) - e) < 1e-9


def test_the_principal_point_is_anchored_for_rectified_input_by_default() -> None:
    """``anchor_principal_point: rectified``: the rectified left camera defines the frame; a raw rig's is a lens."""
    raw = true_rig()
    rect = StereoCalibration(raw.K_left, raw.K_left, raw.right_from_left, raw.image_size, np.zeros(5), np.zeros(5),
                             rectified=True)
    cfg = SelfCalibrationConfig()
    assert anchors_principal_point(cfg, rect) and not anchors_principal_point(cfg, raw)
    always = cfg.model_copy(update={"anchor_principal_point": "always"})
    never = cfg.model_copy(update={"anchor_principal_point": "never"})
    assert anchors_principal_point(always, raw) and not anchors_principal_point(never, rect)


# ----------------------------------------------------------------------------- the solver (calib7)


def test_reduced_system_matches_a_dense_schur_complement() -> None:
    """The reduced system summed per pose pair and landmark equals ``H_zz - H_zl H_ll^-1 H_lz`` of the dense problem."""
    from loopmodel.calibration import refine_rig as rr

    sc, obs, pts0 = _problem(recorded_rig(true_rig(), 2), 2, n_kf=6, n_pt=150)
    rig = rr.RigParameters.of(sc.recorded)
    st = rr._State(sc.world_from_kf[:, :3, :3].copy(), sc.world_from_kf[:, :3, 3].copy(), pts0, rig.values.copy())
    sigma, k = 0.1, 1.345
    S = rr._reduced_system(obs, st, rig, rig.values, PRIOR, EST, sigma, k)
    # the dense whitened Jacobian: free poses (6 each, the first fixed), active parameters, landmarks
    r, Jp, Jl, Jt = rr.residuals_and_jacobians(obs, st.R, st.t, st.pts, rig, st.theta)
    w = np.sqrt(np.where(np.linalg.norm(r, axis=1) / sigma <= k, 1.0, k * sigma / np.linalg.norm(r, axis=1))) / sigma
    n_pose, n_pt, nc = st.R.shape[0], st.pts.shape[0], int(EST.sum())
    npz = 6 * (n_pose - 1)
    J = np.zeros((2 * len(obs), npz + nc + 3 * n_pt))
    for i in range(len(obs)):
        rows = slice(2 * i, 2 * i + 2)
        p = int(obs.pose_idx[i])
        if p > 0:
            J[rows, 6 * (p - 1) : 6 * p] = w[i] * Jp[i]
        J[rows, npz : npz + nc] = w[i] * Jt[i][:, EST]
        q = npz + nc + 3 * int(obs.point_idx[i])
        J[rows, q : q + 3] = w[i] * Jl[i]
    H = J.T @ J
    H[npz : npz + nc, npz : npz + nc] += np.diag(1.0 / PRIOR[EST] ** 2)
    z, lm = slice(0, npz + nc), slice(npz + nc, None)
    dense = H[z, z] - H[z, lm] @ np.linalg.solve(H[lm, lm] + 1e-12 * np.eye(3 * n_pt), H[lm, z])
    assert np.allclose(S, dense, rtol=1e-7, atol=1e-6 * np.abs(dense).max())


def test_early_stops_land_within_noise_of_the_converged_solution(monkeypatch: pytest.MonkeyPatch) -> None:
    """The rough solves and the final stopping rule leave the calibration within hundredths of a prior sigma.

    Against the same problem solved to convergence (tolerances near zero, the noise re-estimated until it
    stops moving): values, pixel noise, posterior sigmas and what is reported unobservable.
    """
    from loopmodel.calibration import refine_rig as rr

    sc, obs, pts0 = _problem(recorded_rig(true_rig(), 3), 3, n_kf=12, n_pt=400)
    _p, _q, rep = refine_rig(obs, sc.world_from_kf.copy(), pts0, sc.recorded, PRIOR, EST)
    for name, value in (("MIN_REL", 1e-10), ("STEP_TOL_REL", 1e-10), ("STEP_TOL_SIGMA", 1e-4),
                        ("ROUGH_STEP_SIGMA", 0.0), ("SIGMA_REL_TOL", 1e-5), ("SIGMA_ROUNDS", 10)):
        monkeypatch.setattr(rr, name, value)
    _p, _q, conv = refine_rig(obs, sc.world_from_kf.copy(), pts0, sc.recorded, PRIOR, EST, max_iterations=60)
    assert rep.iterations < conv.iterations  # measured 13 vs 311 (to zero tolerances)
    # measured 0.029 prior sigma (seed 3; 0.014 on seed 2), the posterior sigmas 0.03 %, the noise 0.1 %
    assert np.max(np.abs(rep.values - conv.values) / PRIOR) < 0.06
    assert np.max(np.abs(rep.posterior_sigma - conv.posterior_sigma) / conv.posterior_sigma) < 0.01
    assert abs(rep.pixel_sigma_px / conv.pixel_sigma_px - 1.0) < 0.01
    assert rep.unobservable == conv.unobservable


# ----------------------------------------------------------------------------- the compiled kernels (fin12)


@pytest.mark.parametrize("right_rows", [False, True])
def test_compiled_residuals_and_jacobians_give_the_numpy_ones(right_rows: bool) -> None:
    """The kernel's residuals and Jacobians equal the numpy form's (distortion, rotation correction, right rows)."""
    from loopmodel.calibration.refine_rig import residuals_and_jacobians_compiled

    sc, obs, pts = _rows_problem(recorded_rig(true_rig(), 5), 5, 8, 90.0, 300) if right_rows else _problem(
        recorded_rig(true_rig(), 5), 5, 8, 300
    )
    rig = RigParameters.of(sc.recorded)
    theta = rig.values.copy()
    theta[:12] += np.random.default_rng(5).normal(0, 1e-3, 12)
    theta[12:15] = [1e-3, -2e-3, 5e-4]
    R, t = sc.world_from_kf[:, :3, :3], sc.world_from_kf[:, :3, 3]
    ref = residuals_and_jacobians(obs, R, t, pts, rig, theta)
    got = residuals_and_jacobians_compiled(obs, R, t, pts, rig, theta)
    for a, b in zip(ref, got, strict=True):
        assert a.shape == b.shape
        assert np.abs(a - b).max() <= 1e-12 * max(float(np.abs(a).max()), 1.0)  # measured <= 1.2e-14 relative
    assert np.array_equal(residuals_and_jacobians_compiled(obs, R, t, pts, rig, theta, jacobians=False)[0], got[0])


def test_compiled_reduced_system_and_steps_give_the_numpy_ones() -> None:
    """Normal equations, the landmarks' elimination and the products with the coupling: kernel against numpy."""
    from loopmodel.calibration import refine_rig as rr

    sc, obs, pts0 = _rows_problem(recorded_rig(true_rig(), 6), 6, 7, 90.0, 200)
    rig = rr.RigParameters.of(sc.recorded)
    est = estimated_parameters(SelfCalibrationConfig())
    out = []
    for compiled in (False, True):
        st = rr._State(sc.world_from_kf[:, :3, :3].copy(), sc.world_from_kf[:, :3, 3].copy(), pts0, rig.values.copy(),
                       compiled)
        # a small sigma puts some observations in the Huber tail
        H, b, Hzl, V, bl, _r, cost, rn = rr._normal_equations(obs, st, rig, rig.values, PRIOR, est, 0.05, 1.345)
        S, Vinv = rr._schur(H, Hzl, V, 1e-3)
        x = np.random.default_rng(1).normal(size=bl.size)
        y = np.random.default_rng(2).normal(size=b.size)
        out.append((H, b, V, bl, np.array([cost]), rn, S, Vinv, rr._hzl_dot(Hzl, x), rr._hlz_dot(Hzl, y), Hzl.W, Hzl.Y))
    assert np.any(out[0][5] > 1.345) and np.any(out[0][5] <= 1.345)
    for a, b in zip(*out, strict=True):
        assert np.allclose(a, b, rtol=1e-10, atol=1e-10 * float(np.abs(a).max()))


def test_compiled_adjustment_gives_the_numpy_adjustment() -> None:
    """``refine_rig`` with the kernels and with numpy: the same solution, noise, posterior and iterations.

    After a warm-up no kernel compiles again (the run loads them before its frames).
    """
    from loopmodel.calibration import _rig_kernels

    _rig_kernels.warm_up()
    kernels = [_rig_kernels.evaluate, _rig_kernels.normal_equations, _rig_kernels.schur, _rig_kernels.hzl_dot,
               _rig_kernels.hlz_dot]
    signatures = [len(k.signatures) for k in kernels]
    sc, obs, pts0 = _problem(recorded_rig(true_rig(), 3), 3, n_kf=10, n_pt=300)
    p0, q0, a = refine_rig(obs, sc.world_from_kf.copy(), pts0, sc.recorded, PRIOR, EST, compiled=False)
    p1, q1, b = refine_rig(obs, sc.world_from_kf.copy(), pts0, sc.recorded, PRIOR, EST)
    assert [len(k.signatures) for k in kernels] == signatures
    assert a.iterations == b.iterations and a.unobservable == b.unobservable
    # measured: poses 3e-14 m, values 3e-12 prior sigma, posterior 2.4e-10 relative, noise 2e-15 px
    assert np.abs(p0 - p1).max() < 1e-10 and np.abs(q0 - q1).max() < 1e-10
    assert np.max(np.abs(a.values - b.values) / PRIOR) < 1e-8
    assert np.max(np.abs(a.posterior_sigma / b.posterior_sigma - 1.0)) < 1e-7
    assert abs(a.pixel_sigma_px - b.pixel_sigma_px) < 1e-12


def test_restriped_points_keep_their_pixels_and_lie_on_the_plane() -> None:
    """``restripe`` (all stripes in one call, fin15): each point keeps its raw pixel and stays on the light plane.

    Stripes of a few points triangulated with the recorded rig (distorted lens); restriped to the
    true rig, each point projects through the true left camera to the pixel it had through the
    recorded one, on the plane ``n . p + d = 0``; an empty stripe stays empty, the order and times kept.
    """
    from loopmodel.calibration.selfcal import restripe

    true = true_rig()
    rec = recorded_rig(true, 4)
    n = np.array([0.977, 0.0, 0.213]) / np.linalg.norm([0.977, 0.0, 0.213])
    d = -float(n @ np.array([0.12, 0.0, 0.0]))
    rng = np.random.default_rng(5)
    stripes = []
    for k, count in enumerate((40, 0, 7, 120)):
        ray = np.column_stack([rng.uniform(-0.4, 0.4, count), rng.uniform(-0.3, 0.3, count), np.ones(count)])
        stripes.append(StripeProfile(1000 * k, ray * (-d / (ray @ n))[:, None]))
    out = restripe(stripes, rec, true, n, d)
    assert [s.timestamp_ns for s in out] == [s.timestamp_ns for s in stripes]
    for before, after in zip(stripes, out, strict=True):
        assert after.points_in_cam.shape == before.points_in_cam.shape
        if before.points_in_cam.shape[0] == 0:
            continue
        px = [
            cv2.projectPoints(p.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), c.K_left, c.dist_left)[0].reshape(-1, 2)
            for p, c in ((before.points_in_cam, rec), (after.points_in_cam, true))
        ]
        np.testing.assert_allclose(px[1], px[0], atol=1e-6)
        np.testing.assert_allclose(after.points_in_cam @ n + d, 0.0, atol=1e-12)
        assert np.max(np.abs(after.points_in_cam - before.points_in_cam)) > 1e-6  # the rigs differ: moved


def _loop_terms_one_by_one(R: np.ndarray, t: np.ndarray, loops: list, sigmas: np.ndarray) -> tuple:
    """The loop block, gradient and cost a loop at a time, by central differences (fin17's reference)."""
    n = R.shape[0]
    H, g, cost, w, h = np.zeros((6 * n, 6 * n)), np.zeros(6 * n), 0.0, 1.0 / sigmas, 1e-7

    def residual(Ra, ta, Rb, tb, T):  # type: ignore[no-untyped-def]
        Rr = T[:3, :3].T @ Ra.T @ Rb
        return np.concatenate([so3_log(Rr), T[:3, :3].T @ (Ra.T @ (tb - ta) - T[:3, 3])]) * w

    for a, b, T in loops:
        e = residual(R[a], t[a], R[b], t[b], T)
        J = np.zeros((6, 12))
        for k in range(12):
            which, j = divmod(k, 6)
            res = []
            for sgn in (1.0, -1.0):
                Rs, ts = [R[a].copy(), R[b].copy()], [t[a].copy(), t[b].copy()]
                ts[which] = ts[which] + Rs[which] @ (sgn * h * np.eye(3)[j - 3]) if j >= 3 else ts[which]
                Rs[which] = Rs[which] @ so3_exp(sgn * h * np.eye(3)[j]) if j < 3 else Rs[which]
                res.append(residual(Rs[0], ts[0], Rs[1], ts[1], T))
            J[:, k] = (res[0] - res[1]) / (2 * h)
        idx = np.r_[6 * a : 6 * a + 6, 6 * b : 6 * b + 6]
        H[np.ix_(idx, idx)] += J.T @ J
        g[idx] += J.T @ e
        cost += float(e @ e)
    return H, g, cost


def test_loop_terms_at_once_give_them_one_by_one() -> None:
    """fin17: every loop's residual and numerical Jacobian in one batch, as one loop at a time (poses sharing loops)."""
    from loopmodel.calibration.refine_rig import RigObservations, loop_terms

    rng = np.random.default_rng(3)
    n = 12
    R = np.stack([so3_exp(rng.normal(size=3)) for _ in range(n)])
    t = rng.normal(size=(n, 3))
    loops = []
    for _ in range(30):
        a, b = (int(i) for i in rng.choice(n, 2, replace=False))
        T = np.eye(4)
        T[:3, :3] = R[a].T @ R[b] @ so3_exp(rng.normal(size=3) * 0.02)
        T[:3, 3] = R[a].T @ (t[b] - t[a]) + rng.normal(size=3) * 0.01
        loops.append((a, b, T))
    loops.append((2, 5, np.eye(4)))  # far from agreeing with the poses
    obs = RigObservations(*[np.zeros(0, np.int64)] * 3, np.zeros((0, 2)), np.zeros((0, 2)))
    obs.loops, obs.loop_sigmas = loops, np.array([0.01] * 3 + [0.02] * 3)
    H, g, cost = loop_terms(R, t, obs)
    H1, g1, cost1 = _loop_terms_one_by_one(R, t, loops, obs.loop_sigmas)
    np.testing.assert_allclose(H, H1, rtol=0, atol=1e-9 * np.abs(H1).max())
    np.testing.assert_allclose(g, g1, rtol=0, atol=1e-9 * np.abs(g1).max())
    assert cost == pytest.approx(cost1, rel=1e-12)
    assert np.allclose(H, H.T)


def test_calibration_covariance_is_the_inverse_s_last_block() -> None:
    from loopmodel.calibration.refine_rig import calibration_covariance

    rng = np.random.default_rng(4)
    A = rng.normal(size=(40, 40))
    S = A @ A.T + 40 * np.eye(40)
    np.testing.assert_allclose(calibration_covariance(S, 7), np.linalg.inv(S)[-7:, -7:], rtol=1e-10, atol=1e-14)
    singular = np.diag([1.0, 1.0, -1.0])  # not positive definite: by the inverse
    np.testing.assert_allclose(calibration_covariance(singular, 2), np.linalg.inv(singular)[-2:, -2:])


def test_observations_made_before_the_estimate_refine_the_same() -> None:
    """fin19 (issue 32): observations made before the back end's final estimate refine bit-identically.

    refine_final with final_observations made beforehand gives the same poses, landmarks and calibration;
    observations of other keyframes than the estimate holds are not used; too few keyframes fail as before.
    """
    seed = 2
    sc = make_scene(recorded_rig(true_rig(), seed), seed=seed, n_kf=8, n_points=600, noise_px=0.1)
    kfs = list(sc.keyframes)
    world_from_kf = {k.id: sc.world_from_kf[i].copy() for i, k in enumerate(kfs)}
    cfg = SelfCalibrationConfig()
    plane = (np.array([0.0, 0.0, 1.0]), -0.5)
    none = (np.zeros(0, np.int64), np.zeros((0, 3)))
    for poses in (world_from_kf, {k: T for k, T in world_from_kf.items() if k != kfs[-1].id}):
        plain = refine_final(kfs, poses, *none, sc.recorded, cfg, *plane)
        early = refine_final(kfs, poses, *none, sc.recorded, cfg, *plane,
                             observed=final_observations(kfs, sc.recorded, cfg))
        assert sorted(early.world_from_kf) == sorted(poses)
        for k in poses:
            assert np.array_equal(early.world_from_kf[k], plain.world_from_kf[k])
        assert np.array_equal(early.landmark_ids, plain.landmark_ids)
        assert np.array_equal(early.landmarks_in_world, plain.landmarks_in_world)
        for name in ("K_left", "K_right", "right_from_left", "dist_left", "dist_right"):
            assert np.array_equal(getattr(early.calibration, name), getattr(plain.calibration, name))
    with pytest.raises(LoopmodelError, match="needs 3 keyframes"):
        refine_final(kfs[:2], world_from_kf, *none, sc.recorded, cfg, *plane,
                     observed=final_observations(kfs[:2], sc.recorded, cfg))
