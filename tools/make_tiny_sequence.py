"""Write the bundled tiny KITTI-layout sequence (``datasets/tiny_kitti``).

A textured fronto-parallel plane 2 m away seen by a rectified stereo pair moving sideways, so the
disparity (fx*b/z = 6 px) and the poses are known exactly. Used by `make demo` when ``../shared`` is
absent. Deterministic (seeded).
"""

from __future__ import annotations

import sys
from pathlib import Path

import cv2
import numpy as np

FX, CX, CY, BASELINE_M, DEPTH_M, W, H, FRAMES, STEP_M = 200.0, 80.0, 60.0, 0.06, 2.0, 160, 120, 8, 0.02


def main(out: Path) -> None:
    rng = np.random.default_rng(2026)
    # multi-scale texture on the plane, sampled at 1 px = DEPTH_M / FX metres
    tex = np.zeros((H, W + 200), np.float32)
    for scale in (2, 4, 8, 16):
        noise = rng.normal(size=((H // scale) + 2, (W + 200) // scale + 2)).astype(np.float32)
        tex += cv2.resize(noise, (tex.shape[1], tex.shape[0]), interpolation=cv2.INTER_CUBIC) * scale
    tex = cv2.normalize(tex, None, 20, 235, cv2.NORM_MINMAX)
    for d in ("image_0", "image_1"):
        (out / d).mkdir(parents=True, exist_ok=True)
    disparity_px = FX * BASELINE_M / DEPTH_M
    poses = []
    for i in range(FRAMES):
        shift_px = i * STEP_M * FX / DEPTH_M
        for d, extra in (("image_0", 0.0), ("image_1", disparity_px)):
            M = np.float32([[1, 0, -(100 + shift_px + extra)], [0, 1, 0]])  # dst(x) = tex(x + c)
            img = cv2.warpAffine(tex, M, (W, H), flags=cv2.INTER_CUBIC)
            cv2.imwrite(str(out / d / f"{i:06d}.png"), np.clip(img, 0, 255).astype(np.uint8))
        poses.append(f"1 0 0 {i * STEP_M:.6f} 0 1 0 0 0 0 1 0")
    p0 = f"P0: {FX} 0 {CX} 0 0 {FX} {CY} 0 0 0 1 0"
    p1 = f"P1: {FX} 0 {CX} {-FX * BASELINE_M} 0 {FX} {CY} 0 0 0 1 0"
    (out / "calib.txt").write_text(p0 + "\n" + p1 + "\n")
    (out / "poses.txt").write_text("\n".join(poses) + "\n")
    (out / "times.txt").write_text("\n".join(f"{i * 0.1:.6f}" for i in range(FRAMES)) + "\n")


if __name__ == "__main__":
    main(Path(sys.argv[1] if len(sys.argv) > 1 else "datasets/tiny_kitti"))
