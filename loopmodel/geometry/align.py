"""Least-squares similarity alignment of point sets (Umeyama 1991)."""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray


def umeyama_alignment(
    src: ArrayLike, dst: ArrayLike, with_scale: bool = False
) -> tuple[NDArray[np.float64], NDArray[np.float64], float]:
    """Rotation R, translation t and scale s minimising sum ||dst - (s R src + t)||^2.

    ``src`` and ``dst`` are N x 3 arrays of corresponding points (same units); without
    ``with_scale`` s is 1 (SE(3) alignment), otherwise Sim(3).
    """
    x = np.asarray(src, dtype=float)
    y = np.asarray(dst, dtype=float)
    if x.shape != y.shape or x.ndim != 2 or x.shape[1] != 3:
        raise ValueError(f"umeyama_alignment needs two N x 3 arrays, got {x.shape} and {y.shape}")
    if x.shape[0] < 3:
        raise ValueError("umeyama_alignment needs at least 3 point pairs")
    mx, my = x.mean(axis=0), y.mean(axis=0)
    xc, yc = x - mx, y - my
    n = x.shape[0]
    cov = yc.T @ xc / n
    U, d, Vt = np.linalg.svd(cov)
    S = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        S[2, 2] = -1.0
    R = U @ S @ Vt
    s = 1.0
    if with_scale:
        var_x = float((xc**2).sum() / n)
        s = float(np.trace(np.diag(d) @ S) / var_x)
    t = my - s * R @ mx
    return R, t, s
