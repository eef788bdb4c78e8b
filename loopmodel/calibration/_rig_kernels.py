"""Compiled inner loops of the calibrating bundle adjustment (:mod:`~loopmodel.calibration.refine_rig`; numba, nogil).

The numpy form builds each Levenberg-Marquardt step from some eighty array calls over the
observations (stacked 2x6, 2x3, 2x16 blocks, batched products, sparse sums per pose, pair and
landmark): 9 ms a KITTI clip step of 4,400 observations, most of it call overhead and temporaries.
Here one pass per observation, the same model and the same sums:

- :data:`evaluate`: residuals (predicted minus measured pixels through ``measure``) and the
  Jacobians by the pose increment ``(w, v)``, the world point and the 16 calibration parameters,
  as :func:`~loopmodel.calibration.refine_rig.residuals_and_jacobians` returns them;
- :data:`normal_equations`: the Huber-weighted, whitened normal equations: pose and calibration
  blocks, the pose-landmark blocks ``W`` of each (pose, landmark) pair, the calibration-landmark
  blocks ``Y`` and the landmark blocks ``V`` with their right-hand sides;
- :data:`schur`: the landmarks eliminated (``V`` damped and inverted per landmark, the 3x3
  adjugate of the local BA's kernels), the reduced system summed over every two pairs of a landmark;
- :data:`hzl_dot` / :data:`hlz_dot`: products with the pose/calibration-landmark coupling.

Only the order of the floating-point sums differs from the numpy form (``tests/test_selfcal.py``
compares both). Frames and units as in :mod:`~loopmodel.calibration.refine_rig`: ``R``/``t`` the
keyframes' ``world_from_cam`` (metres), points in the world, pixels raw (distorted).
"""

from __future__ import annotations

import math

import numba
import numpy as np

from loopmodel.frontend._ba_kernels import _inv3


def _project_py(X, Y, Z, intr, dist, uv, Jq, Ji):  # type: ignore[no-untyped-def]
    """Plumb-bob pixel ``uv``, ``Jq`` = d uv / d point, ``Ji`` = d uv / d (fx, fy, cx, cy, k1, k2)."""
    fx, fy, cx, cy = intr[0], intr[1], intr[2], intr[3]
    k1, k2, p1, p2, k3 = dist[0], dist[1], dist[2], dist[3], dist[4]
    iz = 1.0 / (Z if abs(Z) > 1e-9 else 1e-9)
    x = X * iz
    y = Y * iz
    r2 = x * x + y * y
    rad = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    drad = k1 + r2 * (2.0 * k2 + 3.0 * k3 * r2)
    xd = x * rad + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
    yd = y * rad + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
    uv[0] = fx * xd + cx
    uv[1] = fy * yd + cy
    a00 = fx * (rad + 2.0 * x * x * drad + 2.0 * p1 * y + 6.0 * p2 * x)
    a01 = fx * (2.0 * x * y * drad + 2.0 * p1 * x + 2.0 * p2 * y)
    a10 = fy * (2.0 * x * y * drad + 2.0 * p1 * x + 2.0 * p2 * y)
    a11 = fy * (rad + 2.0 * y * y * drad + 6.0 * p1 * y + 2.0 * p2 * x)
    Jq[0, 0] = a00 * iz
    Jq[0, 1] = a01 * iz
    Jq[0, 2] = a00 * (-x * iz) + a01 * (-y * iz)
    Jq[1, 0] = a10 * iz
    Jq[1, 1] = a11 * iz
    Jq[1, 2] = a10 * (-x * iz) + a11 * (-y * iz)
    Ji[0, 0] = xd
    Ji[0, 1] = 0.0
    Ji[0, 2] = 1.0
    Ji[0, 3] = 0.0
    Ji[0, 4] = fx * x * r2
    Ji[0, 5] = fx * x * r2 * r2
    Ji[1, 0] = 0.0
    Ji[1, 1] = yd
    Ji[1, 2] = 0.0
    Ji[1, 3] = 1.0
    Ji[1, 4] = fy * y * r2
    Ji[1, 5] = fy * y * r2 * r2


def _evaluate_py(pose_idx, point_idx, cam, uv_px, measure, R, t, pts, intr, dist, R_rl, t_rl, bdir, jac, r, Jp, Jl, Jt):  # type: ignore[no-untyped-def]
    """Residuals ``r`` (N, 2) and with ``jac`` the Jacobians ``Jp`` (N, 2, 6), ``Jl`` (N, 2, 3), ``Jt`` (N, 2, 16).

    ``intr`` (2, 4) fx, fy, cx, cy and ``dist`` (2, 5) of the left and right camera; ``R_rl``,
    ``t_rl`` the right camera's rotation and offset from the left, ``bdir`` the unit baseline.
    """
    n = pose_idx.shape[0]
    uv = np.empty(2)
    Jq = np.empty((2, 3))
    Ji = np.empty((2, 6))
    pc = np.empty(3)
    q = np.empty(3)
    jq = np.empty(3)
    jl = np.empty(3)
    if jac:
        Jp[:] = 0.0
        Jl[:] = 0.0
        Jt[:] = 0.0
    for i in range(n):
        p = pose_idx[i]
        lm = point_idx[i]
        dx = pts[lm, 0] - t[p, 0]
        dy = pts[lm, 1] - t[p, 1]
        dz = pts[lm, 2] - t[p, 2]
        for k in range(3):  # p_l = R^T (p_w - t)
            pc[k] = R[p, 0, k] * dx + R[p, 1, k] * dy + R[p, 2, k] * dz
        side = cam[i]
        if side == 1:
            for k in range(3):
                q[k] = R_rl[k, 0] * pc[0] + R_rl[k, 1] * pc[1] + R_rl[k, 2] * pc[2] + t_rl[k]
        else:
            q[0], q[1], q[2] = pc[0], pc[1], pc[2]
        _project(q[0], q[1], q[2], intr[side], dist[side], uv, Jq, Ji)
        du = uv[0] - uv_px[i, 0]
        dv = uv[1] - uv_px[i, 1]
        for row in range(2):
            if side == 1:  # the rows of m: the rectified pixel's gradient by the raw pixel
                m0 = measure[i, row, 0]
                m1 = measure[i, row, 1]
                r[i, row] = m0 * du + m1 * dv
                if not jac:
                    continue
                for k in range(3):
                    jq[k] = m0 * Jq[0, k] + m1 * Jq[1, k]
                for k in range(6):
                    Jt[i, row, 6 + k] = m0 * Ji[0, k] + m1 * Ji[1, k]
                a0, a1, a2 = q[0] - t_rl[0], q[1] - t_rl[1], q[2] - t_rl[2]
                Jt[i, row, 12] = a1 * jq[2] - a2 * jq[1]
                Jt[i, row, 13] = a2 * jq[0] - a0 * jq[2]
                Jt[i, row, 14] = a0 * jq[1] - a1 * jq[0]
                Jt[i, row, 15] = jq[0] * bdir[0] + jq[1] * bdir[1] + jq[2] * bdir[2]
                for k in range(3):  # by p_l
                    jl[k] = jq[0] * R_rl[0, k] + jq[1] * R_rl[1, k] + jq[2] * R_rl[2, k]
            else:
                r[i, row] = du if row == 0 else dv
                if not jac:
                    continue
                for k in range(6):
                    Jt[i, row, k] = Ji[row, k]
                jl[0], jl[1], jl[2] = Jq[row, 0], Jq[row, 1], Jq[row, 2]
            # d p_l / d w = [p_l]x, d p_l / d v = -I, d p_l / d p_w = R^T
            Jp[i, row, 0] = jl[1] * pc[2] - jl[2] * pc[1]
            Jp[i, row, 1] = jl[2] * pc[0] - jl[0] * pc[2]
            Jp[i, row, 2] = jl[0] * pc[1] - jl[1] * pc[0]
            Jp[i, row, 3] = -jl[0]
            Jp[i, row, 4] = -jl[1]
            Jp[i, row, 5] = -jl[2]
            for k in range(3):
                Jl[i, row, k] = R[p, k, 0] * jl[0] + R[p, k, 1] * jl[1] + R[p, k, 2] * jl[2]


def _normal_equations_py(r, Jp, Jl, Jt, pose_idx, point_idx, pair_idx, cols, sigma, huber_k, H, b, W, Y, V, bl, rn):  # type: ignore[no-untyped-def]
    """The whitened Huber-weighted normal equations; returns the robust cost of the residuals.

    ``cols`` the active calibration columns of ``Jt``; ``H`` (6 (P - 1) + nc square) and ``b``
    get the free poses' blocks (the first pose fixed) and the calibration's (no prior), ``W``
    (pairs, 6, 3) each (pose, landmark) pair's block (also of the first pose), ``Y`` (L, nc, 3),
    ``V`` (L, 3, 3), ``bl`` (L, 3) each landmark's; ``rn`` (N) the residual norms over ``sigma``.
    """
    n = pose_idx.shape[0]
    nc = cols.shape[0]
    npz = H.shape[0] - nc
    H[:] = 0.0
    b[:] = 0.0
    W[:] = 0.0
    Y[:] = 0.0
    V[:] = 0.0
    bl[:] = 0.0
    jp = np.empty((2, 6))
    jl = np.empty((2, 3))
    jt = np.empty((2, nc))
    nz = np.empty(nc, np.int64)
    rw = np.empty(2)
    cost = 0.0
    for i in range(n):
        nrm = math.sqrt(r[i, 0] * r[i, 0] + r[i, 1] * r[i, 1]) / sigma
        rn[i] = nrm
        if huber_k <= 0.0 or nrm <= huber_k:
            cost += nrm * nrm
            w = 1.0 / sigma
        else:
            cost += 2.0 * huber_k * nrm - huber_k * huber_k
            w = math.sqrt(huber_k / max(nrm, 1e-12)) / sigma
        for a in range(2):
            rw[a] = r[i, a] * w
            for k in range(6):
                jp[a, k] = Jp[i, a, k] * w
            for k in range(3):
                jl[a, k] = Jl[i, a, k] * w
        m = 0  # the calibration columns this observation moves (one camera's and the rig's)
        for k in range(nc):
            c = cols[k]
            if Jt[i, 0, c] != 0.0 or Jt[i, 1, c] != 0.0:
                jt[0, m] = Jt[i, 0, c] * w
                jt[1, m] = Jt[i, 1, c] * w
                nz[m] = k
                m += 1
        p = pose_idx[i]
        lm = point_idx[i]
        pr = pair_idx[i]
        if p > 0:
            o = 6 * (p - 1)
            for k in range(6):
                for j in range(k, 6):
                    H[o + k, o + j] += jp[0, k] * jp[0, j] + jp[1, k] * jp[1, j]
                for u in range(m):
                    H[o + k, npz + nz[u]] += jp[0, k] * jt[0, u] + jp[1, k] * jt[1, u]
                b[o + k] -= jp[0, k] * rw[0] + jp[1, k] * rw[1]
        for u in range(m):
            k = nz[u]
            for v in range(u, m):
                H[npz + k, npz + nz[v]] += jt[0, u] * jt[0, v] + jt[1, u] * jt[1, v]
            b[npz + k] -= jt[0, u] * rw[0] + jt[1, u] * rw[1]
            for j in range(3):
                Y[lm, k, j] += jt[0, u] * jl[0, j] + jt[1, u] * jl[1, j]
        for k in range(6):
            for j in range(3):
                W[pr, k, j] += jp[0, k] * jl[0, j] + jp[1, k] * jl[1, j]
        for k in range(3):
            for j in range(3):
                V[lm, k, j] += jl[0, k] * jl[0, j] + jl[1, k] * jl[1, j]
            bl[lm, k] -= jl[0, k] * rw[0] + jl[1, k] * rw[1]
    for k in range(npz):  # the symmetric blocks
        o = k - k % 6
        for j in range(o, k):
            H[k, j] = H[j, k]
    for k in range(nc):
        for j in range(k):
            H[npz + k, npz + j] = H[npz + j, npz + k]
    for k in range(npz):
        for j in range(nc):
            H[npz + j, k] = H[k, npz + j]
    return cost


def _schur_py(H, W, Y, V, damping, pair_pose, lm_start, lm_pairs, S, Vinv):  # type: ignore[no-untyped-def]
    """``S`` = the reduced system ``H - Hzl V^-1 Hlz``, ``Vinv`` = ``V^-1``, both with LM damping.

    The pose blocks summed over every two (pose, landmark) pairs of a landmark (``lm_pairs``
    ``[lm_start[l]:lm_start[l + 1]]``). Returns False when a landmark block is singular.
    """
    nc = Y.shape[1]
    npz = H.shape[0] - nc
    N = H.shape[0]
    for k in range(N):
        for j in range(N):
            S[k, j] = H[k, j]
        S[k, k] *= 1.0 + damping
    A = np.empty((3, 3))
    WV = np.empty((lm_pairs.shape[0], 6, 3))
    YV = np.empty((nc, 3))
    for lm in range(V.shape[0]):
        for k in range(3):
            for j in range(3):
                A[k, j] = V[lm, k, j]
            A[k, k] = A[k, k] * (1.0 + damping) + 1e-12
        if not _inv3(A, Vinv[lm]):
            return False
        Vi = Vinv[lm]
        for k in range(nc):
            for j in range(3):
                YV[k, j] = Y[lm, k, 0] * Vi[0, j] + Y[lm, k, 1] * Vi[1, j] + Y[lm, k, 2] * Vi[2, j]
        for k in range(nc):
            for j in range(nc):
                S[npz + k, npz + j] -= YV[k, 0] * Y[lm, j, 0] + YV[k, 1] * Y[lm, j, 1] + YV[k, 2] * Y[lm, j, 2]
        s0, s1 = lm_start[lm], lm_start[lm + 1]
        for u in range(s0, s1):
            pa = lm_pairs[u]
            a = pair_pose[pa]
            if a == 0:
                continue
            oa = 6 * (a - 1)
            for k in range(6):
                for j in range(3):
                    WV[u, k, j] = W[pa, k, 0] * Vi[0, j] + W[pa, k, 1] * Vi[1, j] + W[pa, k, 2] * Vi[2, j]
            for k in range(6):
                for j in range(nc):
                    S[oa + k, npz + j] -= (WV[u, k, 0] * Y[lm, j, 0] + WV[u, k, 1] * Y[lm, j, 1]
                                           + WV[u, k, 2] * Y[lm, j, 2])
            for v in range(s0, s1):
                pb = lm_pairs[v]
                c = pair_pose[pb]
                if c < a or c == 0:  # each two pairs once: pose a <= pose c, mirrored below
                    continue
                ob = 6 * (c - 1)
                for k in range(6):
                    for j in range(6):
                        S[oa + k, ob + j] -= (WV[u, k, 0] * W[pb, j, 0] + WV[u, k, 1] * W[pb, j, 1]
                                              + WV[u, k, 2] * W[pb, j, 2])
    for k in range(npz):  # the blocks below the diagonal blocks, and the calibration rows
        for j in range(k - k % 6):
            S[k, j] = S[j, k]
        for j in range(nc):
            S[npz + j, k] = S[k, npz + j]
    return True


def _hzl_dot_py(W, Y, pair_pose, pair_point, x, out):  # type: ignore[no-untyped-def]
    """``out`` = ``Hzl x`` of a landmark vector ``x`` (L, 3): the free poses' rows, then the calibration's."""
    nc = Y.shape[1]
    npz = out.shape[0] - nc
    out[:] = 0.0
    for u in range(pair_pose.shape[0]):
        a = pair_pose[u]
        if a == 0:
            continue
        lm = pair_point[u]
        o = 6 * (a - 1)
        for k in range(6):
            out[o + k] += W[u, k, 0] * x[lm, 0] + W[u, k, 1] * x[lm, 1] + W[u, k, 2] * x[lm, 2]
    for lm in range(Y.shape[0]):
        for k in range(nc):
            out[npz + k] += Y[lm, k, 0] * x[lm, 0] + Y[lm, k, 1] * x[lm, 1] + Y[lm, k, 2] * x[lm, 2]


def _hlz_dot_py(W, Y, pair_pose, pair_point, y, out):  # type: ignore[no-untyped-def]
    """``out`` (L, 3) = ``Hlz y`` of a vector ``y`` of the free poses and the calibration."""
    nc = Y.shape[1]
    npz = y.shape[0] - nc
    for lm in range(Y.shape[0]):
        for j in range(3):
            acc = 0.0
            for k in range(nc):
                acc += Y[lm, k, j] * y[npz + k]
            out[lm, j] = acc
    for u in range(pair_pose.shape[0]):
        a = pair_pose[u]
        if a == 0:
            continue
        lm = pair_point[u]
        o = 6 * (a - 1)
        for j in range(3):
            acc = 0.0
            for k in range(6):
                acc += W[u, k, j] * y[o + k]
            out[lm, j] += acc


_project = numba.njit(cache=True, nogil=True, inline="always")(_project_py)
evaluate = numba.njit(cache=True, nogil=True)(_evaluate_py)
normal_equations = numba.njit(cache=True, nogil=True)(_normal_equations_py)
schur = numba.njit(cache=True, nogil=True)(_schur_py)
hzl_dot = numba.njit(cache=True, nogil=True)(_hzl_dot_py)
hlz_dot = numba.njit(cache=True, nogil=True)(_hlz_dot_py)


def warm_up() -> None:
    """Load (or compile) the kernels for the float64 / int64 arrays the adjustment passes."""
    n, n_pose, n_pt = 4, 2, 2
    pose_idx = np.array([0, 0, 1, 1], np.int64)
    point_idx = np.array([0, 1, 0, 1], np.int64)
    cam = np.array([0, 1, 0, 1], np.int64)
    uv = np.full((n, 2), 300.0)
    measure = np.tile(np.eye(2), (n, 1, 1))
    R = np.tile(np.eye(3), (n_pose, 1, 1))
    t = np.zeros((n_pose, 3))
    pts = np.array([[0.1, 0.2, 5.0], [-0.3, 0.1, 7.0]])
    intr = np.array([[500.0, 500.0, 320.0, 240.0]] * 2)
    dist = np.zeros((2, 5))
    r = np.zeros((n, 2))
    Jp, Jl, Jt = np.zeros((n, 2, 6)), np.zeros((n, 2, 3)), np.zeros((n, 2, 16))
    evaluate(pose_idx, point_idx, cam, uv, measure, R, t, pts, intr, dist, np.eye(3), np.array([-0.1, 0.0, 0.0]),
             np.array([-1.0, 0.0, 0.0]), True, r, Jp, Jl, Jt)
    for a in (r, Jp, Jl, Jt):  # as the adjustment's state keeps them (read-only: numba types them apart)
        a.setflags(write=False)
    cols = np.arange(3, dtype=np.int64)
    N = 6 * (n_pose - 1) + cols.size
    H, b = np.zeros((N, N)), np.zeros(N)
    W, Y, V, bl = np.zeros((n, 6, 3)), np.zeros((n_pt, cols.size, 3)), np.zeros((n_pt, 3, 3)), np.zeros((n_pt, 3))
    normal_equations(r, Jp, Jl, Jt, pose_idx, point_idx, np.arange(n, dtype=np.int64), cols, 1.0, 1.345, H, b, W, Y,
                     V, bl, np.zeros(n))
    S, Vinv = np.zeros((N, N)), np.zeros((n_pt, 3, 3))
    schur(H, W, Y, V, 1e-4, pose_idx, np.array([0, 2, 4], np.int64), np.array([0, 2, 1, 3], np.int64), S, Vinv)
    x = np.zeros((n_pt, 3))
    hzl_dot(W, Y, pose_idx, point_idx, x, np.zeros(N))
    hlz_dot(W, Y, pose_idx, point_idx, np.zeros(N), x)
