"""Re-measurement of tracked features against the keyframe patch (affine warp).

Checked against images related by an exact plane homography and against finite differences.
"""

from __future__ import annotations

import cv2
import numpy as np

from loopmodel.frontend.affine_klt import predicted_affine, refine_affine
from loopmodel.geometry.camera import CentralCamera
from loopmodel.geometry.se3 import make_pose, so3_exp

CAM = CentralCamera(500.0, 500.0, 319.5, 239.5)


def _texture(rng: np.random.Generator, shape: tuple[int, int] = (480, 640)) -> np.ndarray:
    img = rng.random(shape).astype(np.float32)
    img = cv2.GaussianBlur(img, (0, 0), 2.0)
    img = (img - img.min()) / (img.max() - img.min())
    return np.clip(20 + 215 * img, 0, 255).astype(np.uint8)


def _plane_homography(cur_from_ref: np.ndarray, normal: np.ndarray, d: float) -> np.ndarray:
    """Pixel homography cur <- ref of the plane normal . X = d (reference frame)."""
    K = CAM.K
    H = K @ (cur_from_ref[:3, :3] + np.outer(cur_from_ref[:3, 3], normal) / d) @ np.linalg.inv(K)
    return H / H[2, 2]


def _apply(H: np.ndarray, uv: np.ndarray) -> np.ndarray:
    p = np.column_stack([uv, np.ones(len(uv))]) @ H.T
    return p[:, :2] / p[:, 2:]


def test_refine_affine_recovers_the_true_position_under_a_plane_homography(rng: np.random.Generator) -> None:
    ref = _texture(rng)
    # a slanted plane 0.8 m away; the camera moved 8 cm sideways and turned 12 degrees
    normal = np.array([0.3, 0.0, -1.0])
    normal /= np.linalg.norm(normal)
    d = -0.8 * normal[2]
    cur_from_ref = make_pose(so3_exp([0.0, np.radians(12.0), 0.02]), [-0.08, 0.01, 0.01])
    H = _plane_homography(cur_from_ref, normal, d)
    # cur(x) = ref(H^-1 x): the exact image of the textured plane in the moved camera
    cur = cv2.warpPerspective(ref, np.linalg.inv(H), (640, 480), flags=cv2.INTER_CUBIC | cv2.WARP_INVERSE_MAP)
    uv_ref = np.stack(np.meshgrid(np.linspace(150, 490, 8), np.linspace(120, 360, 6)), -1).reshape(-1, 2)
    truth = _apply(H, uv_ref)
    inside = (truth[:, 0] > 20) & (truth[:, 0] < 620) & (truth[:, 1] > 20) & (truth[:, 1] < 460)
    uv_ref, truth = uv_ref[inside], truth[inside]
    guess = truth + rng.uniform(-0.7, 0.7, truth.shape)  # a drifted track
    # points on the plane (reference frame) for the predicted warp
    rays = np.column_stack([(uv_ref - [319.5, 239.5]) / 500.0, np.ones(len(uv_ref))])
    pts = rays * (d / (rays @ normal))[:, None]
    m = refine_affine(ref, cur, uv_ref, guess, predicted_affine(CAM, pts, cur_from_ref))
    err = np.linalg.norm(m.uv_px - truth, axis=1)
    assert m.ok.mean() > 0.95
    assert np.median(err[m.ok]) < 0.03 and err[m.ok].max() < 0.1, (np.median(err), err.max())
    assert np.median(np.linalg.norm(guess - truth, axis=1)) > 0.3  # it did move the guesses
    # the patch correlates after warping
    assert np.all(m.ncc[m.ok] > 0.95)


def test_refine_affine_rejects_a_patch_that_is_not_there(rng: np.random.Generator) -> None:
    ref = _texture(rng)
    other = _texture(np.random.default_rng(123))
    uv = rng.uniform(60, 400, (40, 2))
    m = refine_affine(ref, other, uv, uv)
    assert m.ok.mean() < 0.1
    assert refine_affine(ref, ref, np.zeros((0, 2)), np.zeros((0, 2))).uv_px.shape == (0, 2)


def test_predicted_affine_matches_finite_differences(rng: np.random.Generator) -> None:
    pts = np.column_stack([rng.uniform(-0.3, 0.3, 10), rng.uniform(-0.2, 0.2, 10), rng.uniform(0.5, 2.0, 10)])
    cur_from_ref = make_pose(so3_exp([0.05, -0.25, 0.03]), [-0.1, 0.02, 0.05])
    M = predicted_affine(CAM, pts, cur_from_ref)
    h = 1e-3
    for X, Mi in zip(pts, M, strict=True):
        n = X / np.linalg.norm(X)  # plane through X, perpendicular to the viewing ray
        uv0 = CAM.project(X[None])[0]

        def cur_of(uv: np.ndarray, X: np.ndarray = X, n: np.ndarray = n) -> np.ndarray:
            ray = CAM.lift(uv[None])[0]
            P = ray * (n @ X) / (n @ ray)
            return CAM.project((cur_from_ref[:3, :3] @ P + cur_from_ref[:3, 3])[None])[0]

        steps = (np.array([h, 0.0]), np.array([0.0, h]))
        J = np.column_stack([(cur_of(uv0 + e) - cur_of(uv0 - e)) / (2 * h) for e in steps])
        np.testing.assert_allclose(Mi, J, atol=1e-5)
    # behind the camera: identity
    assert np.allclose(predicted_affine(CAM, np.array([[0.0, 0.0, -1.0]]), cur_from_ref)[0], np.eye(2))
