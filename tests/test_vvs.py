"""Virtual visual servoing (seed 002).

Interaction matrices vs finite differences, conics of projected lines, robust N-camera pose, rig
calibration.
"""

from __future__ import annotations

import numpy as np
import pytest

from loopmodel.geometry.camera import CentralCamera
from loopmodel.geometry.se3 import invert_pose, make_pose, se3_exp, so3_exp, so3_log
from loopmodel.pose import CameraRig, PointTerm
from loopmodel.pose.vvs import (
    LineTerm,
    VvsOptions,
    conic_value,
    distance_interaction_matrix,
    line_conics,
    pixel_point_interaction_matrix,
    point_interaction_matrix,
    sample_conic_arc,
    twist_transform,
    vvs_pose,
)

XIS = [0.0, 0.5, 1.0]


def _rot_err_deg(A: np.ndarray, B: np.ndarray) -> float:
    return float(np.degrees(np.linalg.norm(so3_log(A[:3, :3].T @ B[:3, :3]))))


def _rig(n: int, xi: float) -> CameraRig:
    """n cameras on a 10 cm square, optical axes parallel (the 4-mirror layout)."""
    offs = [(-0.05, -0.05), (0.05, 0.05), (0.05, -0.05), (-0.05, 0.05)][:n]
    cams, poses = [], []
    for j, (ox, oy) in enumerate(offs):
        cams.append(CentralCamera(300.0 + 10 * j, 305.0 + 10 * j, 320.0 + j, 240.0 - j, xi))
        R = so3_exp(np.array([0.01 * j, -0.02 * j, 0.03 * j]))
        rig_from_cam = make_pose(R, np.array([ox, oy, 0.0]))
        T = invert_pose(rig_from_cam)
        poses.append(T @ invert_pose(make_pose(np.eye(3), np.array([offs[0][0], offs[0][1], 0]))))
    # camera 1 is the rig frame
    c0 = poses[0]
    poses = [T @ invert_pose(c0) for T in poses]
    return CameraRig(tuple(cams), tuple(poses))


def _box_lines() -> np.ndarray:
    """12 edges (2 x 3 endpoints) of a 30 x 25 x 20 cm box centred at the origin."""
    h = np.array([0.15, 0.125, 0.10])
    corners = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)]) * h
    edges = []
    for i in range(8):
        for k in range(i + 1, 8):
            if np.sum(np.abs(corners[i] - corners[k]) > 1e-9) == 1:
                edges.append([corners[i], corners[k]])
    return np.array(edges)


@pytest.mark.parametrize("xi", XIS)
def test_projection_jacobian_fd(xi: float, rng: np.random.Generator) -> None:
    cam = CentralCamera(400.0, 380.0, 320.0, 240.0, xi)
    P = rng.uniform([-0.4, -0.3, 0.3], [0.4, 0.3, 1.0], (20, 3))
    J = cam.project_jacobian(P)
    h = 1e-6
    for k in range(3):
        e = np.zeros(3)
        e[k] = h
        fd = (cam.project(P + e) - cam.project(P - e)) / (2 * h)
        np.testing.assert_allclose(J[:, :, k], fd, rtol=1e-6, atol=1e-5)
    # lift inverts project
    rays = cam.lift(cam.project(P))
    np.testing.assert_allclose(rays, P / np.linalg.norm(P, axis=1, keepdims=True), atol=1e-9)


@pytest.mark.parametrize("xi", XIS)
def test_point_interaction_matrix_fd(xi: float, rng: np.random.Generator) -> None:
    P = rng.uniform([-0.5, -0.4, 0.2], [0.5, 0.4, 1.2], (25, 3))
    L = point_interaction_matrix(P, xi)
    cam = CentralCamera(1.0, 1.0, 0.0, 0.0, xi)
    h = 1e-6
    for k in range(6):
        e = np.zeros(6)
        e[k] = h
        # the camera moves by exp(v dt): points in the camera frame move by exp(-v dt)
        fwd = (se3_exp(-e)[:3, :3] @ P.T).T + se3_exp(-e)[:3, 3]
        bwd = (se3_exp(e)[:3, :3] @ P.T).T + se3_exp(e)[:3, 3]
        fd = (cam.project(fwd) - cam.project(bwd)) / (2 * h)
        np.testing.assert_allclose(L[:, :, k], fd, rtol=1e-5, atol=1e-7)
    if xi == 0.0:  # the classical perspective interaction matrix
        x, y, Z = P[:, 0] / P[:, 2], P[:, 1] / P[:, 2], P[:, 2]
        Lc = np.stack(
            [
                np.column_stack([-1 / Z, 0 * Z, x / Z, x * y, -(1 + x * x), y]),
                np.column_stack([0 * Z, -1 / Z, y / Z, 1 + y * y, -x * y, -x]),
            ],
            axis=1,
        )
        np.testing.assert_allclose(L, Lc, atol=1e-12)


@pytest.mark.parametrize("xi", XIS)
def test_point_term_matches_stacked_interaction(xi: float, rng: np.random.Generator) -> None:
    """The shared solver's point Jacobian is -L_j jV1 (eq. 12-13) in every camera."""
    rig = _rig(4, xi)
    T = make_pose(so3_exp(np.array([0.1, -0.2, 0.05])), np.array([0.05, -0.02, 0.6]))
    P = rng.uniform(-0.15, 0.15, (40, 3))
    cam_index = np.arange(40) % 4
    term = PointTerm(rig, P, np.zeros((40, 2)), cam_index)
    _, J = term.residuals_and_jacobian(T)
    for j in range(4):
        idx = cam_index == j
        p_cam = (rig.cam_from_rig[j] @ T @ np.c_[P[idx], np.ones(idx.sum())].T).T[:, :3]
        L = pixel_point_interaction_matrix(rig.cameras[j], p_cam) @ twist_transform(
            rig.cam_from_rig[j]
        )
        np.testing.assert_allclose(J[idx], -L, rtol=1e-9, atol=1e-9)


@pytest.mark.parametrize("xi", XIS)
def test_line_conic_interaction_fd(xi: float, rng: np.random.Generator) -> None:
    P0 = rng.uniform([-0.4, -0.3, 0.4], [0.4, 0.3, 0.9], (15, 3))
    P1 = P0 + rng.uniform(-0.2, 0.2, (15, 3))
    lc = line_conics(P0, P1, xi)
    assert lc.valid.all()
    xy = rng.uniform(-0.5, 0.5, (15, 2))
    Ld = distance_interaction_matrix(lc.a, lc.L_a, xy)
    h = 1e-6
    for k in range(6):
        e = np.zeros(6)
        e[k] = h
        Tf, Tb = se3_exp(-e), se3_exp(e)
        lf = line_conics(P0 @ Tf[:3, :3].T + Tf[:3, 3], P1 @ Tf[:3, :3].T + Tf[:3, 3], xi)
        lb = line_conics(P0 @ Tb[:3, :3].T + Tb[:3, 3], P1 @ Tb[:3, :3].T + Tb[:3, 3], xi)
        fd_a = (lf.a - lb.a) / (2 * h)
        np.testing.assert_allclose(lc.L_a[:, :, k], fd_a, rtol=1e-5, atol=1e-6)
        fd_d = (conic_value(lf.a, xy) - conic_value(lb.a, xy)) / (2 * h)
        np.testing.assert_allclose(Ld[:, k], fd_d, rtol=1e-5, atol=1e-6)


@pytest.mark.parametrize("xi", XIS)
def test_conic_contains_projected_line(xi: float, rng: np.random.Generator) -> None:
    cam = CentralCamera(300.0, 300.0, 320.0, 240.0, xi)
    for _ in range(10):
        P0 = rng.uniform([-0.5, -0.4, 0.3], [0.5, 0.4, 0.8], 3)
        P1 = P0 + rng.uniform(-0.3, 0.3, 3)
        lc = line_conics(P0[None], P1[None], xi)
        s = np.linspace(-1.0, 2.0, 50)
        pts = P0 + s[:, None] * (P1 - P0)
        pts = pts[cam.in_front(pts)]
        xy = cam.normalized(pts)
        q = conic_value(np.repeat(lc.a, len(xy), axis=0), xy)
        # relative to the size of the coefficients
        assert np.max(np.abs(q)) < 1e-9 * (1 + np.abs(lc.a).max()), q
        # a point off the line is off the conic
        off = cam.normalized((0.5 * (P0 + P1) + 0.05 * lc.n1[0])[None])
        assert abs(conic_value(lc.a, off)[0]) > 1e-6
        if xi > 0.0:  # conic sampling (eq. 26-28) stays on the conic and on the segment
            mid = cam.normalized((0.5 * (P0 + P1))[None])[0]
            xy0, xy1 = cam.normalized(np.array([P0, P1]))
            samples = sample_conic_arc(lc.a[0], xy0, xy1, mid, 20)
            if samples is None:
                continue
            qa = conic_value(np.repeat(lc.a, 20, axis=0), samples)
            assert np.max(np.abs(qa)) < 1e-8 * (1 + np.abs(lc.a).max())
            rays = CentralCamera(1.0, 1.0, 0.0, 0.0, xi).lift(samples)
            # each sample ray meets the 3-D segment: the ray is in plane P1, and the
            # intersection with the line lies between the endpoints
            d = P1 - P0
            for ray in rays:
                A = np.column_stack([ray, -d])
                (lam, mu), *_ = np.linalg.lstsq(A, P0, rcond=None)
                assert np.linalg.norm(lam * ray - (P0 + mu * d)) < 1e-9
                assert lam > 0 and -1e-9 <= mu <= 1 + 1e-9


@pytest.mark.parametrize("distance", ["algebraic", "normalized"])
@pytest.mark.parametrize("xi", XIS)
def test_line_term_jacobian_fd(xi: float, distance: str, rng: np.random.Generator) -> None:
    rig = _rig(4, xi)
    lines = _box_lines()
    T = make_pose(so3_exp(np.array([0.3, -0.2, 0.1])), np.array([0.05, -0.03, 0.6]))
    k = 48
    term = LineTerm(
        rig,
        lines,
        rng.uniform(200, 400, (k, 2)),
        np.arange(k) % 12,
        (np.arange(k) // 12) % 4,
        distance=distance,  # type: ignore[arg-type]
    )
    r, J = term.residuals_and_jacobian(T)
    h = 1e-6
    for c in range(6):
        e = np.zeros(6)
        e[c] = h
        fd = (term.residuals(se3_exp(e) @ T) - term.residuals(se3_exp(-e) @ T)) / (2 * h)
        np.testing.assert_allclose(J[:, :, c], fd, rtol=1e-5, atol=1e-5 * (1 + np.abs(fd).max()))


def _simulate_points(rig: CameraRig, T: np.ndarray, n: int, rng: np.random.Generator):
    P = rng.uniform([-0.15, -0.125, -0.1], [0.15, 0.125, 0.1], (n, 3))
    cam_index = np.arange(n) % len(rig)
    uv = np.empty((n, 2))
    for j in range(len(rig)):
        idx = cam_index == j
        p_cam = (rig.cam_from_rig[j] @ T @ np.c_[P[idx], np.ones(idx.sum())].T).T[:, :3]
        uv[idx] = rig.cameras[j].project(p_cam)
    return P, uv, cam_index


def test_pose_recovery_with_outliers(rng: np.random.Generator) -> None:
    """Points and point-to-conic features, 4 parabolic cameras, 30 % gross outliers."""
    rig = _rig(4, 1.0)
    T_true = make_pose(so3_exp(np.array([0.4, -0.3, 0.2])), np.array([0.1, -0.05, 0.55]))
    P, uv, ci = _simulate_points(rig, T_true, 200, rng)
    uv += rng.normal(0, 0.3, uv.shape)
    out = rng.random(200) < 0.3
    uv[out] += rng.uniform(-40, 40, (out.sum(), 2))
    T0 = se3_exp(np.array([0.03, -0.02, 0.04, 0.05, -0.04, 0.03])) @ T_true
    opt = VvsOptions(huber_warmup=3)
    res = vvs_pose(PointTerm(rig, P, uv, ci), T0, opt)
    # independent reference: least squares on the true inliers only
    ref = vvs_pose(PointTerm(rig, P[~out], uv[~out], ci[~out]), T0, VvsOptions(loss="l2"))
    assert _rot_err_deg(res.rig_from_ref, ref.rig_from_ref) < 0.02
    assert np.linalg.norm(res.rig_from_ref[:3, 3] - ref.rig_from_ref[:3, 3]) < 2e-4
    assert _rot_err_deg(res.rig_from_ref, T_true) < 0.5
    assert np.linalg.norm(res.rig_from_ref[:3, 3] - T_true[:3, 3]) < 2e-3
    detected = ~res.inliers[0]
    assert np.mean(detected[out]) > 0.9 and np.mean(detected[~out]) < 0.05

    # line features: edge points sampled on the projected box edges, 30 % outliers
    lines = _box_lines()
    uvs, li, cj = [], [], []
    for j in range(4):
        Tj = rig.cam_from_rig[j] @ T_true
        for m, (a, b) in enumerate(lines):
            s = rng.uniform(0.05, 0.95, 8)
            pts = (a + s[:, None] * (b - a)) @ Tj[:3, :3].T + Tj[:3, 3]
            uvs.append(rig.cameras[j].project(pts))
            li += [m] * 8
            cj += [j] * 8
    uvl = np.vstack(uvs) + rng.normal(0, 0.3, (len(li), 2))
    outl = rng.random(len(li)) < 0.3
    uvl[outl] += rng.uniform(-30, 30, (outl.sum(), 2))
    res_l = vvs_pose(LineTerm(rig, lines, uvl, np.array(li), np.array(cj)), T0, opt)
    assert _rot_err_deg(res_l.rig_from_ref, T_true) < 0.5
    assert np.linalg.norm(res_l.rig_from_ref[:3, 3] - T_true[:3, 3]) < 3e-3
    # the start was 3-5 cm / 3 deg off: both terms together converge as well
    res_b = vvs_pose(
        [PointTerm(rig, P, uv, ci), LineTerm(rig, lines, uvl, np.array(li), np.array(cj))], T0, opt
    )
    assert _rot_err_deg(res_b.rig_from_ref, T_true) < 0.5
    assert np.linalg.norm(res_b.rig_from_ref[:3, 3] - T_true[:3, 3]) < 2e-3


def test_n_cameras_consistent_noiseless(rng: np.random.Generator) -> None:
    T_true = make_pose(so3_exp(np.array([-0.2, 0.5, 0.1])), np.array([-0.05, 0.08, 0.5]))
    T0 = se3_exp(np.array([0.02, 0.02, -0.03, -0.04, 0.03, 0.05])) @ T_true
    poses = {}
    for n in (1, 2, 4):
        rig = _rig(n, 1.0)
        P, uv, ci = _simulate_points(rig, T_true, 60 * n, rng)
        res = vvs_pose(PointTerm(rig, P, uv, ci), T0, VvsOptions(loss="l2"))
        assert res.converged
        poses[n] = res.rig_from_ref
    for n in (1, 2, 4):
        assert _rot_err_deg(poses[n], T_true) < 1e-6
        assert np.linalg.norm(poses[n][:3, 3] - T_true[:3, 3]) < 1e-8
    # the control law with a gain < 1 reaches the same pose (exponential decrease of e)
    rig = _rig(2, 0.5)
    P, uv, ci = _simulate_points(rig, T_true, 80, rng)
    opt = VvsOptions(loss="l2", gain=0.5, max_iterations=80, step_tolerance=1e-11)
    res = vvs_pose(PointTerm(rig, P, uv, ci), T0, opt)
    assert np.linalg.norm(res.rig_from_ref - T_true) < 1e-7


@pytest.mark.parametrize("noise_px", [0.0, 0.2])
def test_rig_calibration_recovers_jm1_and_gamma(noise_px: float, rng: np.random.Generator) -> None:
    from loopmodel.pose.calibration import CalibrationView, calibrate_rig

    truth = _rig(4, 0.9)
    # a 3-D calibration object: points on three orthogonal faces (40 cm)
    g = np.linspace(-0.2, 0.2, 6)
    A, B = np.meshgrid(g, g)
    faces = [
        np.column_stack([A.ravel(), B.ravel(), np.full(36, 0.2)]),
        np.column_stack([A.ravel(), np.full(36, 0.2), B.ravel()]),
        np.column_stack([np.full(36, 0.2), A.ravel(), B.ravel()]),
    ]
    obj = np.vstack(faces)
    views, poses_true = [], []
    for _ in range(6):
        T = make_pose(so3_exp(rng.normal(0, 0.35, 3)), np.array([0, 0, 0.7]) + rng.normal(0, 0.1, 3))
        poses_true.append(T)
        P, uv, ci = [], [], []
        for j in range(4):
            p_cam = (truth.cam_from_rig[j] @ T @ np.c_[obj, np.ones(len(obj))].T).T[:, :3]
            ok = truth.cameras[j].in_front(p_cam)
            P.append(obj[ok])
            uv.append(truth.cameras[j].project(p_cam[ok]) + rng.normal(0, noise_px, (ok.sum(), 2)))
            ci.append(np.full(ok.sum(), j))
        views.append(CalibrationView(np.vstack(P), np.vstack(uv), np.concatenate(ci)))
    cams0 = tuple(
        CentralCamera(c.px * 1.05, c.py * 0.96, c.u0 + 6, c.v0 - 5, c.xi - 0.1) for c in truth.cameras
    )
    ext0 = tuple(
        [truth.cam_from_rig[0]]
        + [se3_exp(rng.normal(0, [0.01] * 3 + [0.02] * 3)) @ T for T in truth.cam_from_rig[1:]]
    )
    poses0 = [se3_exp(rng.normal(0, [0.02] * 3 + [0.03] * 3)) @ T for T in poses_true]
    cal = calibrate_rig(views, CameraRig(cams0, ext0), poses0)
    tol_g = 1e-6 if noise_px == 0 else 0.02  # relative (intrinsics)
    tol_t = 1e-8 if noise_px == 0 else 2e-3  # metres
    tol_r = 1e-6 if noise_px == 0 else 0.5  # degrees (tilt vs principal point)
    for c_est, c_true in zip(cal.rig.cameras, truth.cameras, strict=True):
        g_est = np.array([c_est.px, c_est.py, c_est.u0, c_est.v0, c_est.xi])
        g_true = np.array([c_true.px, c_true.py, c_true.u0, c_true.v0, c_true.xi])
        np.testing.assert_allclose(g_est, g_true, rtol=tol_g, atol=tol_g)
    for E_est, E_true in zip(cal.rig.cam_from_rig, truth.cam_from_rig, strict=True):
        assert np.linalg.norm(E_est[:3, 3] - E_true[:3, 3]) < tol_t
        assert _rot_err_deg(E_est, E_true) < tol_r
    assert cal.rms_px < 1e-6 + 2 * noise_px


def test_omni_sensor_masks_the_other_mirrors() -> None:
    from loopmodel.sim.omni import omni_sensor

    sensor = omni_sensor()
    cam = sensor.cameras[0]
    # from mirror 1, the direction of mirror 4 at mirror height is hidden; the opposite is not
    d = sensor.foci_m[3] - sensor.foci_m[0]
    uv = cam.project(np.array([d / np.linalg.norm(d), -d / np.linalg.norm(d)]))
    assert list(sensor.valid(0, uv)) == [False, True]
    # the rim: straight up (towards the camera) is outside every mirror's image
    up = cam.project(np.array([[0.2, 0.0, -1.0]]))
    assert not sensor.valid(0, up)[0]


def test_box_model_edges_and_conic_sampling() -> None:
    from loopmodel.pose.tracking import PolyhedronModel, sample_model_edges
    from loopmodel.sim.omni import omni_sensor

    model = PolyhedronModel.box((0.3, 0.25, 0.2))
    assert model.edges.shape == (12, 2) and model.edge_faces.shape == (12, 2)
    # seen from far along +x, +y, +z: 3 faces visible, 9 edges
    assert model.visible_edges(np.array([5.0, 4.0, 3.0])).sum() == 9
    rig = omni_sensor().rig()
    T = make_pose(so3_exp(np.array([0.0, 0.0, 0.7])) @ so3_exp(np.array([0.0, 0.4, 0.0])), [0.5, 0.2, 0.03])
    s = sample_model_edges(rig, model, T, 3.0)
    term = LineTerm(rig, model.lines, s.uv_px, s.line_index, s.cam_index)
    assert len(term) > 200
    np.testing.assert_allclose(term.residuals(T), 0.0, atol=1e-9)  # samples lie on the conics


def test_tracking_first_frames_of_the_box_sequence() -> None:
    from loopmodel.sim.omni import simulate_tracking

    # the full sequence is the benchmark's; here its first 8 frames with 4 and 2 mirrors
    for mirrors in ((0, 1, 2, 3), (0, 3)):
        short = simulate_tracking(mirrors, 312, stop_frame=8)
        assert len(short.rot_err_deg) == 8 and not short.lost.any()
        assert np.median(short.rot_err_deg) < 0.8 and np.median(short.pos_err_mm) < 4.0


def test_cli_vvs(tmp_path, capsys) -> None:  # type: ignore[no-untyped-def]
    from loopmodel.cli import main

    assert main(["vvs", "simulate", "--frames", "312", "--out", str(tmp_path), "--mirrors", "3"]) == 2
    assert "--mirrors" in capsys.readouterr().err
    bad = tmp_path / "points.npz"
    np.savez(bad, p_in_ref=np.zeros((5, 3)))
    assert main(["vvs", "calibrate", "--points", str(bad), "--out", str(tmp_path)]) == 2
    assert "points.npz" in capsys.readouterr().err


def test_line_term_plugs_into_the_shared_lm_solver(rng: np.random.Generator) -> None:
    """One core.

    The front end's LM solver and the VVS control law reach the same pose with the same point +
    point-to-conic terms.
    """
    from loopmodel.pose import PoseOptions, refine_pose

    rig = _rig(2, 1.0)
    lines = _box_lines()
    T_true = make_pose(so3_exp(np.array([0.3, 0.2, -0.1])), np.array([0.02, 0.03, 0.5]))
    P, uv, ci = _simulate_points(rig, T_true, 60, rng)
    uvs, li, cj = [], [], []
    for j in range(2):
        Tj = rig.cam_from_rig[j] @ T_true
        for m, (a, b) in enumerate(lines):
            s = np.linspace(0.1, 0.9, 6)
            uvs.append(rig.cameras[j].project((a + s[:, None] * (b - a)) @ Tj[:3, :3].T + Tj[:3, 3]))
            li += [m] * 6
            cj += [j] * 6
    uvl = np.vstack(uvs) + rng.normal(0, 0.3, (len(li), 2))
    terms = [
        PointTerm(rig, P, uv + rng.normal(0, 0.3, uv.shape), ci),
        LineTerm(rig, lines, uvl, np.array(li), np.array(cj)),
    ]
    T0 = se3_exp(np.array([0.01, -0.01, 0.02, 0.02, 0.01, -0.02])) @ T_true
    for term in terms:  # (with several terms, VVS weights each by its own robust scale)
        a = vvs_pose(term, T0, VvsOptions(loss="l2", step_tolerance=1e-10))
        b = refine_pose(term, T0, PoseOptions(loss="l2", max_iterations=50, step_tolerance=1e-10))
        assert _rot_err_deg(a.rig_from_ref, b.rig_from_ref) < 1e-5
        assert np.linalg.norm(a.rig_from_ref[:3, 3] - b.rig_from_ref[:3, 3]) < 1e-7
