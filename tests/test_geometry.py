"""SE(3) helpers, alignment and the central camera model, checked against independent computations."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.linalg import expm, logm
from scipy.spatial.transform import Rotation

from loopmodel.geometry.align import umeyama_alignment
from loopmodel.geometry.camera import CentralCamera
from loopmodel.geometry.se3 import (
    hat,
    interpolate_pose,
    invert_pose,
    quat_wxyz_from_rotation,
    rotation_from_quat_wxyz,
    se3_exp,
    se3_log,
    so3_exp,
    so3_log,
)


def _twist_matrix(xi: np.ndarray) -> np.ndarray:
    M = np.zeros((4, 4))
    M[:3, :3] = hat(xi[3:])
    M[:3, 3] = xi[:3]
    return M


def test_exp_log_against_matrix_exponential(rng: np.random.Generator) -> None:
    for scale in (1e-9, 1e-3, 0.5, 2.0, 3.1):
        xi = rng.normal(size=6)
        xi[3:] *= scale / np.linalg.norm(xi[3:])
        T = se3_exp(xi)
        assert np.allclose(T, expm(_twist_matrix(xi)), atol=1e-12)
        assert np.allclose(se3_log(T), xi, atol=1e-9)
    w = np.array([0.0, 0.0, np.pi - 1e-6])
    assert np.allclose(so3_log(so3_exp(w)), w, atol=1e-6)
    R = so3_exp(rng.normal(size=3))
    assert np.allclose(hat(so3_log(R)), np.real(logm(R)), atol=1e-9)


def test_quaternions_match_scipy(rng: np.random.Generator) -> None:
    q_xyzw = Rotation.random(20, random_state=3).as_quat()
    q_wxyz = q_xyzw[:, [3, 0, 1, 2]]
    R = rotation_from_quat_wxyz(q_wxyz)
    assert np.allclose(R, Rotation.from_quat(q_xyzw).as_matrix(), atol=1e-12)
    back = quat_wxyz_from_rotation(R)
    sign = np.sign(np.sum(back * q_wxyz, axis=1))[:, None]
    assert np.allclose(back * sign, q_wxyz, atol=1e-12)


def test_invert_and_interpolate(rng: np.random.Generator) -> None:
    T0, T1 = se3_exp(rng.normal(size=6)), se3_exp(rng.normal(size=6))
    assert np.allclose(invert_pose(T0) @ T0, np.eye(4), atol=1e-12)
    assert np.allclose(interpolate_pose(T0, T1, 0.0), T0, atol=1e-12)
    assert np.allclose(interpolate_pose(T0, T1, 1.0), T1, atol=1e-12)
    Tm = interpolate_pose(T0, T1, 0.3)
    assert np.allclose(Tm[:3, :3].T @ Tm[:3, :3], np.eye(3), atol=1e-12)
    # rotation angle splits 30/70 along the geodesic
    a01 = np.linalg.norm(so3_log(T0[:3, :3].T @ T1[:3, :3]))
    a0m = np.linalg.norm(so3_log(T0[:3, :3].T @ Tm[:3, :3]))
    assert a0m == pytest.approx(0.3 * a01, rel=1e-9)


@pytest.mark.parametrize("with_scale", [False, True])
def test_umeyama_recovers_transform(rng: np.random.Generator, with_scale: bool) -> None:
    src = rng.normal(size=(100, 3)) * 10
    T = se3_exp(rng.normal(size=6))
    s = 2.7 if with_scale else 1.0
    dst = s * src @ T[:3, :3].T + T[:3, 3]
    R, t, s_est = umeyama_alignment(src, dst, with_scale)
    assert np.allclose(R, T[:3, :3], atol=1e-10) and np.allclose(t, T[:3, 3], atol=1e-9)
    assert s_est == pytest.approx(s, rel=1e-10)


@pytest.mark.parametrize("xi", [0.0, 0.5, 1.0])
def test_central_camera_jacobian_and_lift(rng: np.random.Generator, xi: float) -> None:
    cam = CentralCamera(400.0, 410.0, 320.0, 240.0, xi)
    P = rng.normal(size=(30, 3)) + [0, 0, 2.0]
    J = cam.project_jacobian(P)
    eps = 1e-6
    for k in range(3):
        d = np.zeros(3)
        d[k] = eps
        fd = (cam.project(P + d) - cam.project(P - d)) / (2 * eps)
        assert np.allclose(J[:, :, k], fd, atol=1e-5)
    rays = cam.lift(cam.project(P))
    assert np.allclose(rays, P / np.linalg.norm(P, axis=1, keepdims=True), atol=1e-9)


def test_look_at_points_the_optical_axis_and_keeps_image_y_against_up(rng: np.random.Generator) -> None:
    from loopmodel.geometry.se3 import Y_DOWN_UP, look_at

    for up in (np.array([0.0, 0.0, 1.0]), Y_DOWN_UP):
        eye, target = rng.normal(size=3), rng.normal(size=3)
        T = look_at(eye, target, up)
        R = T[:3, :3]
        assert np.allclose(R.T @ R, np.eye(3), atol=1e-12) and np.linalg.det(R) == pytest.approx(1.0)
        assert np.allclose(R[:, 2], (target - eye) / np.linalg.norm(target - eye), atol=1e-12)
        assert abs(R[:, 0] @ up) < 1e-12 and R[:, 1] @ up < 0  # x level, image y against up
        assert np.allclose(T[:3, 3], eye)


def _orbit_world_z_up(rng: np.random.Generator, n: int = 36, elevation_deg: float = 30.0) -> np.ndarray:
    """Cameras around an object at the origin, 0.5 m away, ``elevation_deg`` above it (world z up)."""
    from loopmodel.geometry.se3 import look_at

    el = np.radians(elevation_deg)
    out = []
    for a in np.linspace(0, 2 * np.pi, n, endpoint=False):
        eye = 0.5 * np.array([np.cos(el) * np.cos(a), np.cos(el) * np.sin(a), np.sin(el)]) + rng.normal(0, 0.005, 3)
        out.append(look_at(eye, rng.normal(0, 0.01, 3), [0.0, 0.0, 1.0]))
    return np.array(out)


def test_up_from_poses_finds_gravity_in_a_runs_world(rng: np.random.Generator) -> None:
    """Up in a run's world (its first camera's, y down) from the path's principal axes (issue 35 item 7)."""
    from loopmodel.geometry.se3 import invert_pose, look_at, up_from_poses, world_up

    def angle_deg(a: np.ndarray, b: np.ndarray) -> float:
        return float(np.degrees(np.arccos(np.clip(a @ b / np.linalg.norm(a) / np.linalg.norm(b), -1, 1))))

    z = np.array([0.0, 0.0, 1.0])
    # a hand-held orbit looking down at the object: the first camera's -y is 30 degrees off
    truth = _orbit_world_z_up(rng)
    run = invert_pose(truth[0])[None] @ truth  # the run's world: its first camera
    true_up = truth[0][:3, :3].T @ z
    assert angle_deg(-run[0][:3, 1], true_up) > 25  # what the pictures used before
    assert angle_deg(up_from_poses(run), true_up) < 1.0  # measured 0.25-0.36 (seeds 0-2; 5 mm noise, 0.5 m orbit)
    assert angle_deg(world_up(run), true_up) < 1.0  # first pose the identity: no gravity known
    assert np.array_equal(world_up(truth), z)  # a simulator's or motion capture's world: z up
    # a car: forward along a gentle curve, the camera pitched down 3 degrees; a flat path
    car = []
    for s in np.linspace(0, 60, 50):
        eye = np.array([s, 0.002 * s**2, 1.65])
        ahead = eye + [1.0, 0.004 * s, -np.tan(np.radians(3.0))]
        car.append(look_at(eye, ahead, z))
    car_run = invert_pose(car[0])[None] @ np.array(car)
    assert angle_deg(up_from_poses(car_run), car[0][:3, :3].T @ z) < 0.5
    # a vertical sweep over a wall: the path's plane is vertical, its normal is rejected for the
    # cameras' mean up (held level)
    wall = [look_at([x, -1.0, h], [x, 0.0, h], z) for x in np.linspace(0, 1, 6) for h in (0.2, 0.6, 1.0)]
    assert angle_deg(up_from_poses(np.array(wall)), z) < 1e-6
