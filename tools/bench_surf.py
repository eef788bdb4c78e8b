"""Benchmark ``surf``: SURF (written here) against OpenCV's SIFT and ORB under known homographies.

Base images: real views of Strecha fountain-P11 (downscaled to 640 px wide) and of the
RTAB-Map corridor (512x384). Each is transformed with a known homography H (rotation
about the image centre 30-180 degrees on an enlarged canvas, scale 0.5-2 by area/linear
resampling) or photometrically (Gaussian blur, seeded Gaussian noise, brightness gain
and offset; H = identity). Like with like: only keypoints in the common region of the
two images count (mapped into the other image at least ``MARGIN_PX`` inside it; this
also drops responses to the black canvas borders of rotated images), and in each image
all three detectors keep the same number of them, their strongest: at most
``N_FEATURES`` and no more than the detector with fewest there offers (SIFT's contrast
threshold leaves fewer in small images).

- Repeatability (Mikolajczyk & Schmid's point form): a keypoint of image 1 is repeated
  when a keypoint of image 2 lies within ``EPS_PX`` of its mapped position (measured in
  image 1's pixels) with a scale ratio within ``SCALE_TOL`` of the homography's; ``repeated / min(n1, n2)``.
- Matching score: the pipeline's matcher (:func:`loopmodel.loop.features.match_descriptors`,
  ratio 0.8, mutual) between the two images; correct matches (same geometric test) over
  ``min(n1, n2)``.
- Time: detect + describe on a 640x480 crop of a fountain view and a 1226x370 KITTI image,
  median of repeated runs, SURF and SIFT (both keeping at most ``N_FEATURES``) in the
  same run, alternating.
"""

from __future__ import annotations

import statistics
import time
from collections.abc import Callable

import cv2
import numpy as np
from shared_data import SHARED_DATA

from loopmodel.loop.features import FeatureSet, make_extractor, match_descriptors
from loopmodel.loop.surf import Surf

DATA = SHARED_DATA
N_FEATURES = 1000
EPS_PX = 2.5
SCALE_TOL = 2.0**0.5
MARGIN_PX = 16.0

ROTATIONS_DEG = (30, 45, 90, 135, 180)
SCALES = (0.5, 0.7, 1.4, 2.0)

#: keypoints (N, 2) px, scales (N,) (any unit proportional to the feature size), features
Detection = tuple[np.ndarray, np.ndarray, FeatureSet]


def base_images(quick: bool) -> list[tuple[str, np.ndarray]]:
    """Real grey images: fountain views (640 px wide) and corridor images (512x384)."""
    out = []
    views = (0, 5) if quick else (0, 5, 10)
    for v in views:
        p = DATA / "fountain" / "images" / f"{v:04d}.jpg"
        img = cv2.imread(str(p), cv2.IMREAD_GRAYSCALE)
        if img is None:
            raise FileNotFoundError(p)
        f = 640.0 / img.shape[1]
        out.append((f"fountain{v}", cv2.resize(img, None, fx=f, fy=f, interpolation=cv2.INTER_AREA)))
    for v in (1, 60) if quick else (1, 30, 60):
        p = DATA / "loop_images" / "samples" / f"{v}.jpg"
        img = cv2.imread(str(p), cv2.IMREAD_GRAYSCALE)
        if img is None:
            raise FileNotFoundError(p)
        out.append((f"corridor{v}", img))
    return out


def rotated(img: np.ndarray, deg: float) -> tuple[np.ndarray, np.ndarray]:
    """The image rotated by ``deg`` about its centre on a canvas holding all of it, and H."""
    h, w = img.shape
    c = np.array([(w - 1) / 2.0, (h - 1) / 2.0])
    a = np.radians(deg)
    R = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
    corners = np.array([[0, 0], [w - 1, 0], [0, h - 1], [w - 1, h - 1]], float) - c
    ext = np.abs(corners @ R.T).max(axis=0)
    W, Hh = int(np.ceil(2 * ext[0] + 1)), int(np.ceil(2 * ext[1] + 1))
    c2 = np.array([(W - 1) / 2.0, (Hh - 1) / 2.0])
    H = np.eye(3)
    H[:2, :2] = R
    H[:2, 2] = c2 - R @ c
    return cv2.warpAffine(img, H[:2], (W, Hh), flags=cv2.INTER_LINEAR), H


def scaled(img: np.ndarray, z: float) -> tuple[np.ndarray, np.ndarray]:
    """The image resized by ``z`` (area averaging down, bilinear up) and H (pixel centres)."""
    h, w = img.shape
    W, Hh = int(round(w * z)), int(round(h * z))
    zx, zy = W / w, Hh / h
    interp = cv2.INTER_AREA if z < 1 else cv2.INTER_LINEAR
    H = np.array([[zx, 0, 0.5 * zx - 0.5], [0, zy, 0.5 * zy - 0.5], [0, 0, 1.0]])
    return cv2.resize(img, (W, Hh), interpolation=interp), H


def conditions(quick: bool) -> list[tuple[str, Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]]]]:
    """(name, transform) pairs; a transform returns the new image and H (image 1 -> 2)."""
    out: list[tuple[str, Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]]]] = []
    for d in (45, 90, 180) if quick else ROTATIONS_DEG:
        out.append((f"rot{d}", lambda im, d=d: rotated(im, d)))
    for z in (0.5, 2.0) if quick else SCALES:
        out.append((f"scale{z:g}", lambda im, z=z: scaled(im, z)))
    eye = np.eye(3)
    for s in (1.5,) if quick else (1.5, 3.0):
        out.append((f"blur{s:g}", lambda im, s=s: (cv2.GaussianBlur(im, (0, 0), s), eye)))
    for s in (8.0,) if quick else (8.0, 16.0):

        def noisy(im: np.ndarray, s: float = s) -> tuple[np.ndarray, np.ndarray]:
            rng = np.random.default_rng(7)
            return np.clip(im + rng.normal(0, s, im.shape), 0, 255).astype(np.uint8), eye

        out.append((f"noise{s:g}", noisy))
    out.append(("bright0.6", lambda im: (np.clip(im * 0.6, 0, 255).astype(np.uint8), eye)))
    if not quick:
        out.append(("bright+40", lambda im: (np.clip(im.astype(int) + 40, 0, 255).astype(np.uint8), eye)))
    return out


def keep(det: Detection, n: int) -> Detection:
    """The ``n`` strongest keypoints of a detection (sorted strongest first)."""
    xy, sc, f = det
    return xy[:n], sc[:n], f.subset(np.arange(min(n, len(f))))


class Detector:
    """One detector/descriptor; keypoints sorted strongest first, at most ``n``."""

    def __init__(self, kind: str, n: int) -> None:
        self.kind = kind
        self.n = n
        self.ex = make_extractor(kind, n)

    def __call__(self, img: np.ndarray) -> Detection:
        if isinstance(self.ex, Surf):
            kp, d = self.ex.detect_and_describe(img)
            o = np.argsort(-kp.response, kind="stable")
            return kp.xy[o], kp.scale[o], FeatureSet(kp.xy[o], d[o], "surf", laplacian=kp.sign[o])
        kps, desc = self.ex.detectAndCompute(img, None)
        kps = list(kps)
        order = np.argsort([-k.response for k in kps], kind="stable")[: self.n]
        xy = np.array([kps[i].pt for i in order], float).reshape(-1, 2)
        size = np.array([kps[i].size for i in order], float)
        return xy, size, FeatureSet(xy, desc[order], self.kind)


def _apply(H: np.ndarray, xy: np.ndarray) -> np.ndarray:
    p = np.column_stack([xy, np.ones(len(xy))]) @ H.T
    return p[:, :2] / p[:, 2:]


def _inside(xy: np.ndarray, shape: tuple[int, ...]) -> np.ndarray:
    h, w = shape[:2]
    m = MARGIN_PX
    return (xy[:, 0] >= m) & (xy[:, 0] <= w - 1 - m) & (xy[:, 1] >= m) & (xy[:, 1] <= h - 1 - m)


def common(
    det1: Detection, det2: Detection, H: np.ndarray, shape1: tuple[int, ...], shape2: tuple[int, ...]
) -> tuple[Detection, Detection]:
    """The keypoints of both detections that lie in the common region (order kept)."""
    c1 = _inside(det1[0], shape1) & _inside(_apply(H, det1[0]), shape2)
    c2 = _inside(det2[0], shape2) & _inside(_apply(np.linalg.inv(H), det2[0]), shape1)
    i1, i2 = np.flatnonzero(c1), np.flatnonzero(c2)
    return (det1[0][i1], det1[1][i1], det1[2].subset(i1)), (det2[0][i2], det2[1][i2], det2[2].subset(i2))


def evaluate_pair(det1: Detection, det2: Detection, H: np.ndarray) -> tuple[float, float]:
    """Repeatability and matching score of two detections in the common region.

    The images are related by H (image 1 -> 2).
    """
    xy1, s1, f1 = det1
    xy2, s2, f2 = det2
    zoom = float(np.sqrt(abs(np.linalg.det(H[:2, :2]))))
    n = min(len(xy1), len(xy2))
    if n == 0:
        return 0.0, 0.0
    p2in1 = _apply(np.linalg.inv(H), xy2)
    d = np.linalg.norm(xy1[:, None, :] - p2in1[None, :, :], axis=2)
    ratio = s2[None, :] / (s1[:, None] * zoom)
    ok = (d < EPS_PX) & (ratio < SCALE_TOL) & (ratio > 1.0 / SCALE_TOL)
    repeat = min(int(np.any(ok, axis=1).sum()), n) / n
    pairs = match_descriptors(f1, f2, ratio=0.8)
    if pairs.shape[0] == 0:
        return repeat, 0.0
    dist = np.linalg.norm(xy1[pairs[:, 0]] - p2in1[pairs[:, 1]], axis=1)
    return repeat, int(np.sum(dist < EPS_PX)) / n


def _timing(dets: dict[str, Detector], img: np.ndarray, runs: int) -> dict[str, float]:
    """Median detect+describe milliseconds per detector, runs interleaved (same load)."""
    ts: dict[str, list[float]] = {k: [] for k in dets}
    for d in dets.values():
        d(img)  # warm-up (JIT compilation, caches)
    for _ in range(runs):
        for k, d in dets.items():
            t0 = time.perf_counter()
            d(img)
            ts[k].append((time.perf_counter() - t0) * 1e3)
    return {k: statistics.median(v) for k, v in ts.items()}


def run(quick: bool = False) -> dict:
    kinds = ("surf", "sift", "orb")
    # detect more than kept: the strongest in the common region are selected afterwards
    dets = {k: Detector(k, 3 * N_FEATURES) for k in kinds}
    images = base_images(quick)
    conds = conditions(quick)
    rep: dict[str, dict[str, list[float]]] = {k: {c: [] for c, _ in conds} for k in kinds}
    msc: dict[str, dict[str, list[float]]] = {k: {c: [] for c, _ in conds} for k in kinds}
    for name, img in images:
        base = {k: dets[k](img) for k in kinds}
        for cname, tf in conds:
            img2, H = tf(img)
            both = {k: common(base[k], dets[k](img2), H, img.shape, img2.shape) for k in kinds}
            n1 = min(N_FEATURES, *(len(b[0][0]) for b in both.values()))
            n2 = min(N_FEATURES, *(len(b[1][0]) for b in both.values()))
            for k in kinds:
                r, m = evaluate_pair(keep(both[k][0], n1), keep(both[k][1], n2), H)
                rep[k][cname].append(r)
                msc[k][cname].append(m)
            print(
                f"{name} {cname}: repeatability "
                + ", ".join(f"{k} {rep[k][cname][-1]:.3f}" for k in kinds)
                + "; matching score "
                + ", ".join(f"{k} {msc[k][cname][-1]:.3f}" for k in kinds)
            )
    out: dict = {
        "images": [n for n, _ in images],
        "n_features": N_FEATURES,
        "eps_px": EPS_PX,
    }
    for k in kinds:
        out[f"repeatability_{k}"] = {c: round(float(np.mean(v)), 4) for c, v in rep[k].items()}
        out[f"match_score_{k}"] = {c: round(float(np.mean(v)), 4) for c, v in msc[k].items()}
        out[f"repeatability_{k}_mean"] = round(float(np.mean([np.mean(v) for v in rep[k].values()])), 4)
        out[f"match_score_{k}_mean"] = round(float(np.mean([np.mean(v) for v in msc[k].values()])), 4)
    geo = [c for c, _ in conds if c.startswith(("rot", "scale"))]
    out["surf_ge_sift_conditions"] = [c for c in geo if out["repeatability_surf"][c] >= out["repeatability_sift"][c]]
    out["surf_lt_sift_conditions"] = [c for c in geo if out["repeatability_surf"][c] < out["repeatability_sift"][c]]
    # timing: a 640x480 crop of a fountain view and a 1226x370 KITTI image
    f = cv2.imread(str(DATA / "fountain" / "images" / "0005.jpg"), cv2.IMREAD_GRAYSCALE)
    f = cv2.resize(f, None, fx=0.25, fy=0.25, interpolation=cv2.INTER_AREA)
    y0, x0 = (f.shape[0] - 480) // 2, (f.shape[1] - 640) // 2
    vga = np.ascontiguousarray(f[y0 : y0 + 480, x0 : x0 + 640])
    kitti = cv2.imread(str(DATA / "kitti_clip" / "image_l" / "000000.png"), cv2.IMREAD_GRAYSCALE)
    if kitti is None:
        kitti = cv2.imread(str(sorted((DATA / "kitti_clip" / "image_l").glob("*.png"))[0]), cv2.IMREAD_GRAYSCALE)
    runs = 5 if quick else 11
    timed = {k: Detector(k, N_FEATURES) for k in ("surf", "sift")}  # both keep N_FEATURES
    for label, im in (("640x480", vga), ("1226x370", kitti)):
        for k, ms in _timing(timed, im, runs).items():
            out[f"detect_describe_ms_{k}" + ("" if label == "640x480" else f"_{label}")] = round(ms, 2)
    out["surf_over_sift_time_640x480"] = round(out["detect_describe_ms_surf"] / out["detect_describe_ms_sift"], 3)
    return out
