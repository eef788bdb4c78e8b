"""Ray-cast renderings for the calibration and turntable tests: chessboards seen by a
distorted pinhole camera, a laser line on them, and a turntable with ArUco markers and a
cylinder lit by a laser plane. Every pixel is traced exactly (OpenCV's distortion model
inverted per pixel), then lightly blurred and noised (seeded)."""

from __future__ import annotations

import cv2
import numpy as np

from loopmodel.geometry.se3 import make_pose, so3_exp

_RAYS: dict[bytes, np.ndarray] = {}


def pixel_rays(K: np.ndarray, dist: np.ndarray, size: tuple[int, int], supersample: int = 2) -> np.ndarray:
    """(H*s, W*s, 3) camera-frame rays (z = 1) of a supersampled pixel grid of the distorted image."""
    key = np.concatenate([np.ravel(K), np.ravel(dist), size, [supersample]]).tobytes()
    if key not in _RAYS:
        _RAYS[key] = _pixel_rays(K, dist, size, supersample)
    return _RAYS[key]


def _pixel_rays(K: np.ndarray, dist: np.ndarray, size: tuple[int, int], supersample: int) -> np.ndarray:
    w, h = size
    s = supersample
    u, v = np.meshgrid((np.arange(w * s) + 0.5) / s - 0.5, (np.arange(h * s) + 0.5) / s - 0.5)
    uv = np.column_stack([u.ravel(), v.ravel()]).astype(np.float64)
    xy = cv2.undistortPoints(
        uv.reshape(-1, 1, 2), K, dist, criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 30, 1e-9)
    ).reshape(-1, 2)
    rays = np.column_stack([xy, np.ones(len(xy))])
    return rays.reshape(h * s, w * s, 3)


def _finish(img: np.ndarray, s: int, rng: np.random.Generator, noise: float = 1.5) -> np.ndarray:
    h, w = img.shape[0] // s, img.shape[1] // s
    small = img.reshape(h, s, w, s, *img.shape[2:]).mean(axis=(1, 3))
    small = cv2.GaussianBlur(small, (0, 0), 0.6)
    small = small + rng.normal(0.0, noise, small.shape)
    return np.clip(small, 0, 255).astype(np.uint8)


def board_pose(rng: np.random.Generator, board_size_m: tuple[float, float], distance_m: float = 0.5) -> np.ndarray:
    """A random ``cam_from_board`` facing the camera, the board centred near the optical axis."""
    w, h = board_size_m
    R = so3_exp(np.array([np.pi, 0.0, 0.0]) + rng.uniform(-0.45, 0.45, 3) * [1, 1, 0.3])
    centre = np.array([rng.uniform(-0.06, 0.06), rng.uniform(-0.04, 0.04), distance_m + rng.uniform(-0.1, 0.1)])
    t = centre - R @ np.array([w / 2, h / 2, 0.0])
    return make_pose(R, t)


def render_board(
    K: np.ndarray,
    dist: np.ndarray,
    size: tuple[int, int],
    cam_from_board: np.ndarray,
    board: tuple[int, int],
    square_m: float,
    rng: np.random.Generator,
    laser: tuple[np.ndarray, float] | None = None,
    laser_sigma_m: float = 4e-4,
    margin_squares: float = 1.0,
) -> np.ndarray:
    """BGR image of a chessboard (``board`` inner corners; corner (0, 0) at the board origin,
    squares of ``square_m``) on a white sheet, optionally crossed by the laser plane
    ``(normal, d)`` (camera frame) drawn as a green line of ``laser_sigma_m`` width."""
    s = 2
    rays = pixel_rays(K, dist, size, s)
    R, t = cam_from_board[:3, :3], cam_from_board[:3, 3]
    n = R[:, 2]
    lam = (n @ t) / (rays @ n)  # ray parameter to the board plane
    P = rays * lam[..., None]
    B = (P - t) @ R  # board-frame points
    x, y = B[..., 0] / square_m, B[..., 1] / square_m
    nx, ny = board
    on_sheet = (
        (x > -1 - margin_squares) & (x < nx + margin_squares) & (y > -1 - margin_squares) & (y < ny + margin_squares)
    )
    on_squares = (x > -1) & (x < nx) & (y > -1) & (y < ny)
    dark = ((np.floor(x + 1) + np.floor(y + 1)) % 2 == 0) & on_squares
    grey = np.where(on_sheet, np.where(dark, 30.0, 200.0), 90.0)
    grey = np.where(lam > 0, grey, 90.0)
    img = np.repeat(grey[..., None], 3, axis=2)
    if laser is not None:
        ln, ld = laser
        dd = P @ ln + ld
        g = 255.0 * np.exp(-0.5 * (dd / laser_sigma_m) ** 2) * on_sheet
        img[..., 1] = np.maximum(img[..., 1], np.minimum(255.0, img[..., 1] + g))
        img[..., 0] = np.minimum(255.0, img[..., 0] + 0.25 * g)
        img[..., 2] = np.minimum(255.0, img[..., 2] + 0.25 * g)
    return _finish(img, s, rng)


def render_turntable_frame(
    K: np.ndarray,
    size: tuple[int, int],
    cam_from_table: np.ndarray,
    table_texture: np.ndarray,
    table_radius_m: float,
    cylinder_radius_m: float,
    cylinder_height_m: float,
    laser: tuple[np.ndarray, float],
    rng: np.random.Generator,
    laser_sigma_m: float = 4e-4,
) -> np.ndarray:
    """BGR frame of a table disc (z = 0, texture over [-R, R]^2) carrying an upright cylinder
    at its centre, a dark wall behind, and the laser plane (camera frame) lighting the table
    and the cylinder in green. No distortion."""
    s = 2
    rays = pixel_rays(K, np.zeros(5), size, s).reshape(-1, 3)
    Ti = np.linalg.inv(cam_from_table)
    o = Ti[:3, 3]
    d = rays @ Ti[:3, :3].T  # ray directions in the table frame
    hit = np.full(len(d), np.inf)
    colour = np.zeros((len(d), 3))
    # table top
    lt = -o[2] / d[:, 2]
    pt = o + d * lt[:, None]
    on_table = (lt > 0) & (np.hypot(pt[:, 0], pt[:, 1]) <= table_radius_m)
    n_tex = table_texture.shape[0]
    iu = np.clip(((pt[:, 0] + table_radius_m) / (2 * table_radius_m) * n_tex).astype(int), 0, n_tex - 1)
    iv = np.clip(((table_radius_m - pt[:, 1]) / (2 * table_radius_m) * n_tex).astype(int), 0, n_tex - 1)
    tex = table_texture[iv, iu].astype(float)
    hit = np.where(on_table, lt, hit)
    colour[on_table] = np.repeat(tex[on_table, None], 3, axis=1)
    # cylinder side: |(o + l d)_xy| = r
    a = d[:, 0] ** 2 + d[:, 1] ** 2
    b = 2 * (o[0] * d[:, 0] + o[1] * d[:, 1])
    c = o[0] ** 2 + o[1] ** 2 - cylinder_radius_m**2
    disc = b * b - 4 * a * c
    lc = np.where(disc > 0, (-b - np.sqrt(np.maximum(disc, 0))) / (2 * a), np.inf)
    zc = o[2] + lc * d[:, 2]
    on_cyl = (disc > 0) & (lc > 0) & (zc >= 0) & (zc <= cylinder_height_m) & (lc < hit)
    hit = np.where(on_cyl, lc, hit)
    colour[on_cyl] = [60.0, 120.0, 200.0]  # orange-ish (BGR)
    # cylinder top cap
    lcap = (cylinder_height_m - o[2]) / d[:, 2]
    pcap = o + d * lcap[:, None]
    on_cap = (lcap > 0) & (np.hypot(pcap[:, 0], pcap[:, 1]) <= cylinder_radius_m) & (lcap < hit)
    hit = np.where(on_cap, lcap, hit)
    colour[on_cap] = [70.0, 130.0, 210.0]
    wall = ~np.isfinite(hit)
    colour[wall] = [50.0, 45.0, 55.0]
    # laser on table and cylinder (camera-frame distance of the hit point to the plane)
    Pc = rays * np.where(np.isfinite(hit), hit, 0.0)[:, None]  # table-frame ray length = camera length
    ln, ld = laser
    dd = Pc @ ln + ld
    g = np.where(np.isfinite(hit), 255.0 * np.exp(-0.5 * (dd / laser_sigma_m) ** 2), 0.0)
    colour[:, 1] = np.minimum(255.0, colour[:, 1] + g)
    colour[:, 0] = np.minimum(255.0, colour[:, 0] + 0.1 * g)
    colour[:, 2] = np.minimum(255.0, colour[:, 2] + 0.1 * g)
    w, h = size
    return _finish(colour.reshape(h * s, w * s, 3), s, rng)


def table_texture(
    marker_ids: list[int], side_m: float, centres_m: list[tuple[float, float]], radius_m: float, n: int = 2000
) -> np.ndarray:
    """White table-top texture (n x n over [-R, R]^2, x right, y up) with ArUco 4x4_50
    markers of side ``side_m`` centred at ``centres_m`` (table frame), axes along the table's."""
    tex = np.full((n, n), 235, np.uint8)
    dic = cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_4X4_50)
    px = int(round(side_m / (2 * radius_m) * n))
    border = px // 6
    for i, (cx, cy) in zip(marker_ids, centres_m, strict=True):
        m = cv2.aruco.generateImageMarker(dic, i, px)
        u0 = int(round((cx + radius_m) / (2 * radius_m) * n - px / 2))
        v0 = int(round((radius_m - cy) / (2 * radius_m) * n - px / 2))
        tex[v0 - border : v0 + px + border, u0 - border : u0 + px + border] = 255
        tex[v0 : v0 + px, u0 : u0 + px] = m
    return tex
