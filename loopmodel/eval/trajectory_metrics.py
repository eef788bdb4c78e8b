"""Trajectory error metrics: association by time, alignment, ATE, RPE, KITTI segment errors.

Poses are 4x4 ``world_from_cam`` matrices (metres), times ``int`` nanoseconds. The
definitions follow the usual conventions (TUM RGB-D benchmark, KITTI odometry devkit) and
the choices of the ``evo`` package, so numbers computed with the same options agree:
association keeps, for every pose of the shorter trajectory, the nearest pose of the
longer one within ``max_dt``; RPE pairs are chosen on the estimate; an aligned estimate is
``s * R * p + t`` for positions and ``R * R_i`` for orientations.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import get_args

import numpy as np
from numpy.typing import NDArray

from loopmodel.config import AlignMode
from loopmodel.errors import InputError
from loopmodel.geometry.align import umeyama_alignment
from loopmodel.geometry.se3 import invert_pose
from loopmodel.io.trajectory_io import ns_to_seconds_text

ALIGN_MODES: tuple[str, ...] = get_args(AlignMode)
KITTI_SEGMENT_LENGTHS_M: tuple[float, ...] = (100, 200, 300, 400, 500, 600, 700, 800)

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]


class EvalInputError(InputError):
    """The data cannot be evaluated (callers re-raise it naming the files)."""

    def __init__(self, problem: str) -> None:
        super().__init__(None, problem)


def seconds_of_ns(times_ns: I64) -> F64:
    """Float seconds of integer nanosecond times, correctly rounded.

    The same double a reader gets from the decimal seconds text of a TUM file.
    """
    t = np.asarray(times_ns, dtype=np.int64)
    return np.array([ns_to_seconds_text(int(x)) for x in t], dtype=np.float64)


def associate(ref_times_ns: I64, est_times_ns: I64, max_dt_ns: int) -> tuple[NDArray[np.intp], NDArray[np.intp]]:
    """Indices ``(i_ref, i_est)`` of associated poses.

    Every pose of the shorter trajectory (the estimate when both are equally long) is paired
    with the nearest pose in time of the longer one when they are at most ``max_dt_ns``
    apart; on a tie the earlier pose wins. The comparison is made on float seconds, exactly
    as evo does it, so that exact ties resolve the same way. Times must not decrease.
    """
    ref_t = seconds_of_ns(ref_times_ns)
    est_t = seconds_of_ns(est_times_ns)
    max_dt = max_dt_ns / 1e9
    est_is_short = not (len(est_t) > len(ref_t))
    short, long_ = (est_t, ref_t) if est_is_short else (ref_t, est_t)
    if len(short) == 0 or len(long_) == 0:
        return np.zeros(0, np.intp), np.zeros(0, np.intp)
    inside = (short >= long_[0] - max_dt) & (short <= long_[-1] + max_dt)
    i_short = np.flatnonzero(inside)
    s = short[i_short]
    up = np.minimum(np.searchsorted(long_, s, side="right"), len(long_) - 1)
    diff_ub = long_[up] - s
    has_lb = up > 0
    lo = np.where(has_lb, up - 1, 0)
    diff_lb = np.where(has_lb, s - long_[lo], np.inf)
    take_ub = (diff_ub <= max_dt) & (diff_ub < diff_lb)
    take_lb = ~take_ub & (diff_lb <= max_dt) & (diff_lb <= diff_ub)
    keep = take_ub | take_lb
    i_long = np.where(take_ub, up, lo)[keep]
    i_short = i_short[keep]
    if est_is_short:
        return i_long.astype(np.intp), i_short.astype(np.intp)
    return i_short.astype(np.intp), i_long.astype(np.intp)


@dataclass
class Alignment:
    """``ref_from_est`` similarity: p_ref = scale * R @ p_est + t (metres)."""

    mode: str
    rotation: F64 = field(default_factory=lambda: np.eye(3))
    translation_m: F64 = field(default_factory=lambda: np.zeros(3))
    scale: float = 1.0
    poses_used: int = 0

    def apply(self, world_from_cam: F64) -> F64:
        """Aligned copies of N x 4 x 4 estimated poses (translations scaled, then moved)."""
        T = np.array(world_from_cam, dtype=float, copy=True)
        T[:, :3, :3] = np.einsum("ij,njk->nik", self.rotation, T[:, :3, :3])
        T[:, :3, 3] = self.scale * T[:, :3, 3] @ self.rotation.T + self.translation_m
        return T

    def summary(self) -> dict[str, object]:
        """Plain numbers for JSON."""
        return {
            "mode": self.mode,
            "scale": float(self.scale),
            "rotation": self.rotation.tolist(),
            "translation_m": self.translation_m.tolist(),
            "poses_used": int(self.poses_used),
        }


def align(ref_poses: F64, est_poses: F64, mode: str = "se3", first_n: int | None = None) -> Alignment:
    """Alignment of associated estimated poses onto reference poses (both N x 4 x 4).

    ``se3``/``sim3``: Umeyama on positions (of the first ``first_n`` pairs when given);
    ``origin``: the first estimated pose is moved onto the first reference pose;
    ``none``: identity.
    """
    n = len(ref_poses)
    if mode not in ALIGN_MODES:
        raise EvalInputError(f"unknown alignment '{mode}' (expected one of {', '.join(ALIGN_MODES)})")
    if mode == "none":
        return Alignment("none", poses_used=0)
    if mode == "origin":
        T = ref_poses[0] @ invert_pose(est_poses[0])
        return Alignment("origin", T[:3, :3].copy(), T[:3, 3].copy(), 1.0, 1)
    use = n if first_n is None or first_n <= 0 else min(int(first_n), n)
    if use < 3:
        raise EvalInputError(f"{mode} alignment needs at least 3 associated poses, got {use}")
    src = est_poses[:use, :3, 3]
    dst = ref_poses[:use, :3, 3]
    if np.linalg.matrix_rank(src - src.mean(axis=0), tol=1e-9) < 2:
        raise EvalInputError(f"{mode} alignment is degenerate: the estimated positions are collinear")
    R, t, s = umeyama_alignment(src, dst, with_scale=(mode == "sim3"))
    return Alignment(mode, R, t, float(s), use)


def statistics(errors: F64) -> dict[str, float]:
    """rmse, mean, median, std, min, max and count of an error array."""
    e = np.asarray(errors, dtype=float)
    if e.size == 0:
        return {"count": 0}
    return {
        "rmse": float(np.sqrt(np.mean(e * e))),
        "mean": float(np.mean(e)),
        "median": float(np.median(e)),
        "std": float(np.std(e)),
        "min": float(np.min(e)),
        "max": float(np.max(e)),
        "count": int(e.size),
    }


def ate_errors(ref_poses: F64, aligned_est_poses: F64) -> F64:
    """Translational absolute error per associated pose (metres)."""
    return np.linalg.norm(ref_poses[:, :3, 3] - aligned_est_poses[:, :3, 3], axis=1)


def inv_mul(A: F64, B: F64) -> F64:
    """``inv(A_k) @ B_k`` for batches of 4x4 poses (rigid inverse, as for SE(3))."""
    out = np.zeros((len(A), 4, 4))
    out[:, 3, 3] = 1.0
    AT = np.transpose(A[:, :3, :3], (0, 2, 1))
    out[:, :3, :3] = AT @ B[:, :3, :3]
    out[:, :3, 3] = np.einsum("nij,nj->ni", AT, B[:, :3, 3] - A[:, :3, 3])
    return out


def relative_poses(poses: F64, i: NDArray[np.intp], j: NDArray[np.intp]) -> F64:
    """``inv(T_i) @ T_j`` for index arrays i, j."""
    return inv_mul(poses[i], poses[j])


def rotation_angles_rad(R: F64) -> F64:
    """Rotation angle of each 3x3 matrix of a batch (radians)."""
    c = (np.trace(R, axis1=-2, axis2=-1) - 1.0) / 2.0
    return np.arccos(np.clip(c, -1.0, 1.0))


def pairs_by_frames(n: int, delta: int, all_pairs: bool = False) -> tuple[NDArray[np.intp], NDArray[np.intp]]:
    """Index pairs ``delta`` poses apart: consecutive (0, d), (d, 2d), ... or all (i, i + d)."""
    if delta < 1:
        raise EvalInputError(f"RPE frame delta must be >= 1, got {delta}")
    if all_pairs:
        i = np.arange(max(n - delta, 0))
        return i, i + delta
    ids = np.arange(0, n, delta)
    return ids[:-1], ids[1:]


def pairs_by_distance(poses: F64, delta_m: float) -> tuple[NDArray[np.intp], NDArray[np.intp]]:
    """Consecutive index pairs whose travelled path (along ``poses``) first reaches ``delta_m``."""
    steps = np.linalg.norm(np.diff(poses[:, :3, 3], axis=0), axis=1).tolist()
    ids = [0]
    acc = 0.0
    for k, d in enumerate(steps, start=1):
        acc += d
        if acc >= delta_m:
            ids.append(k)
            acc = 0.0
    a = np.asarray(ids, dtype=np.intp)
    return a[:-1], a[1:]


def rpe(ref_poses: F64, est_poses: F64, i: NDArray[np.intp], j: NDArray[np.intp]) -> tuple[F64, F64]:
    """Relative pose error of pairs (i, j).

    Translation norm (metres) and angle (degrees) of ``inv(inv(Q_i) Q_j) @ inv(P_i) P_j`` (Q
    reference, P estimate).
    """
    Q = relative_poses(ref_poses, i, j)
    P = relative_poses(est_poses, i, j)
    E = inv_mul(Q, P)
    return np.linalg.norm(E[:, :3, 3], axis=1), np.degrees(rotation_angles_rad(E[:, :3, :3]))


def path_lengths_m(poses: F64) -> F64:
    """Accumulated path length at each pose (metres), starting at 0."""
    steps = np.linalg.norm(np.diff(poses[:, :3, 3], axis=0), axis=1)
    return np.concatenate([[0.0], np.cumsum(steps)])


def kitti_segment_errors(
    ref_poses: F64,
    est_poses: F64,
    lengths_m: tuple[float, ...] = KITTI_SEGMENT_LENGTHS_M,
    step_frames: int = 10,
) -> dict[str, object] | None:
    """KITTI odometry errors.

    For start frames every ``step_frames`` and each segment length, the relative error between the
    start and the first frame ``length`` further along the reference path. Returns translational
    error (%) and rotational error (deg/100 m), overall and per length; None when the path is
    shorter than the shortest length.
    """
    dist = path_lengths_m(ref_poses)
    firsts = np.arange(0, len(ref_poses), step_frames)
    per_length: dict[str, dict[str, float]] = {}
    all_t: list[F64] = []
    all_r: list[F64] = []
    for length in lengths_m:
        last = np.searchsorted(dist, dist[firsts] + length, side="right")
        ok = last < len(dist)
        if not np.any(ok):
            continue
        i, j = firsts[ok], last[ok]
        t_err, r_err_deg = rpe(ref_poses, est_poses, i, j)
        t_pct = t_err / length * 100.0
        r_100 = r_err_deg / length * 100.0
        all_t.append(t_pct)
        all_r.append(r_100)
        per_length[f"{int(length)}"] = {
            "t_err_pct": float(np.mean(t_pct)),
            "r_err_deg_per_100m": float(np.mean(r_100)),
            "segments": int(len(i)),
        }
    if not all_t:
        return None
    return {
        "t_err_pct": float(np.mean(np.concatenate(all_t))),
        "r_err_deg_per_100m": float(np.mean(np.concatenate(all_r))),
        "segments": int(sum(len(a) for a in all_t)),
        "per_length_m": per_length,
    }


def auto_rpe_distance_m(path_length_m: float) -> float:
    """A round RPE distance about a tenth of the path (0.01 m .. 100 m)."""
    for d in (100.0, 50.0, 20.0, 10.0, 5.0, 2.0, 1.0, 0.5, 0.2, 0.1, 0.05, 0.02):
        if d <= path_length_m / 10.0:
            return d
    return 0.01


@dataclass
class PairEvaluation:
    """Everything computed for one (reference, estimate) pair."""

    i_ref: NDArray[np.intp]
    i_est: NDArray[np.intp]
    ref_poses: F64
    est_aligned: F64
    times_ns: I64
    alignment: Alignment
    ate_m: F64
    metrics: dict[str, object]


def evaluate_pair(
    ref_times_ns: I64,
    ref_poses: F64,
    est_times_ns: I64,
    est_poses: F64,
    *,
    max_dt_ns: int,
    align_mode: str = "se3",
    first_n: int | None = None,
    rpe_delta_frames: int = 1,
    rpe_delta_m: float | None = None,
    kitti_lengths_m: tuple[float, ...] = KITTI_SEGMENT_LENGTHS_M,
) -> PairEvaluation:
    """Compare an estimate against a reference.

    Associate, align and compute ATE, RPE (per frames and per distance), KITTI segment errors and
    end-point errors of an estimate against a reference.
    """
    if len(ref_poses) < 2 or len(est_poses) < 2:
        which = "reference" if len(ref_poses) < 2 else "estimate"
        n = min(len(ref_poses), len(est_poses))
        raise EvalInputError(f"the {which} has {n} pose(s); at least 2 are needed")
    i_ref, i_est = associate(ref_times_ns, est_times_ns, max_dt_ns)
    if len(i_ref) == 0:
        raise EvalInputError(
            f"no poses overlap in time within max dt {max_dt_ns / 1e6:g} ms (reference "
            f"{ref_times_ns[0] / 1e9:.3f}..{ref_times_ns[-1] / 1e9:.3f} s, estimate "
            f"{est_times_ns[0] / 1e9:.3f}..{est_times_ns[-1] / 1e9:.3f} s)"
        )
    if len(i_ref) < 2:
        raise EvalInputError(f"only {len(i_ref)} pose pair associated in time; at least 2 are needed")
    Q = ref_poses[i_ref]
    P = est_poses[i_est]
    al = align(Q, P, align_mode, first_n)
    Pa = al.apply(P)
    ate = ate_errors(Q, Pa)
    rot_err = np.degrees(rotation_angles_rad(np.einsum("nji,njk->nik", Q[:, :3, :3], Pa[:, :3, :3])))
    metrics: dict[str, object] = {
        "poses_reference": int(len(ref_poses)),
        "poses_estimate": int(len(est_poses)),
        "matched": int(len(i_ref)),
        "max_dt_ms": max_dt_ns / 1e6,
        "duration_s": float((est_times_ns[i_est[-1]] - est_times_ns[i_est[0]]) * 1e-9),
        "alignment": al.summary(),
        "ate_m": statistics(ate),
        "are_deg": statistics(rot_err),
    }
    path_ref = path_lengths_m(Q)
    length = float(path_ref[-1])
    metrics["path_length_m"] = length
    # RPE per frame delta
    i, j = pairs_by_frames(len(Q), rpe_delta_frames)
    if len(i):
        t_e, r_e = rpe(Q, Pa, i, j)
        metrics["rpe_frames"] = {
            "delta_frames": int(rpe_delta_frames),
            "trans_m": statistics(t_e),
            "rot_deg": statistics(r_e),
        }
    # RPE per distance (pairs chosen on the aligned estimate, as evo does)
    d_m = float(rpe_delta_m) if rpe_delta_m else auto_rpe_distance_m(length)
    i, j = pairs_by_distance(Pa, d_m)
    if len(i):
        t_e, r_e = rpe(Q, Pa, i, j)
        metrics["rpe_distance"] = {
            "delta_m": d_m,
            "trans_m": statistics(t_e),
            "trans_pct": statistics(t_e / d_m * 100.0),
            "rot_deg": statistics(r_e),
        }
    else:
        metrics["rpe_distance"] = {"delta_m": d_m, "note": "path shorter than the RPE distance"}
    metrics["kitti_segments"] = kitti_segment_errors(Q, Pa, kitti_lengths_m)
    end = float(np.linalg.norm(Q[-1, :3, 3] - Pa[-1, :3, 3]))
    origin = align(Q, P, "origin")
    Po = origin.apply(P[-1:])
    end_origin = float(np.linalg.norm(Q[-1, :3, 3] - Po[0, :3, 3]))
    metrics["end_point"] = {
        "error_m": end,
        "error_origin_aligned_m": end_origin,
        "error_origin_aligned_pct": end_origin / length * 100.0 if length > 0 else None,
    }
    return PairEvaluation(i_ref, i_est, Q, Pa, est_times_ns[i_est], al, ate, metrics)


def se3_ate_rmse_m(ref_times_ns: I64, ref_poses: F64, est_times_ns: I64, est_poses: F64, max_dt_ns: int) -> float:
    """Translational ATE RMSE (metres) after SE(3) Umeyama alignment on all associated poses."""
    i_ref, i_est = associate(ref_times_ns, est_times_ns, max_dt_ns)
    Q, P = ref_poses[i_ref], est_poses[i_est]
    al = align(Q, P, "se3")
    return float(np.sqrt(np.mean(ate_errors(Q, al.apply(P)) ** 2)))


def pose_difference(a: F64, b: F64) -> tuple[F64, F64]:
    """Translation distance (metres) and rotation angle (degrees) between pose batches."""
    dt = np.linalg.norm(a[:, :3, 3] - b[:, :3, 3], axis=1)
    dR = np.einsum("nji,njk->nik", a[:, :3, :3], b[:, :3, :3])
    return dt, np.degrees(rotation_angles_rad(dR))


__all__ = [
    "ALIGN_MODES",
    "KITTI_SEGMENT_LENGTHS_M",
    "Alignment",
    "EvalInputError",
    "PairEvaluation",
    "align",
    "associate",
    "ate_errors",
    "evaluate_pair",
    "kitti_segment_errors",
    "inv_mul",
    "pairs_by_distance",
    "pairs_by_frames",
    "path_lengths_m",
    "pose_difference",
    "rpe",
    "se3_ate_rmse_m",
    "statistics",
]


def false_loop_mask(
    final_world_from_cam: F64,
    gt_world_from_cam: F64,
    pairs: list[tuple[int, int]],
    ate_rmse_m: float,
    factor: float = 3.0,
    floor_m: float = 0.005,
) -> NDArray[np.bool_]:
    """Which loop closures (index pairs into the two N x 4 x 4 trajectories) are false.

    The final relative pose of the two frames is off the ground-truth relative pose by more than
    ``factor`` x the run's final ATE or ``floor_m``, whichever is larger (issue 17's gate;
    translation of the relative-pose error, metres).
    """
    gate = max(factor * float(ate_rmse_m), floor_m)
    if not pairs:
        return np.zeros(0, bool)
    i = np.array([p[0] for p in pairs], np.intp)
    j = np.array([p[1] for p in pairs], np.intp)
    est = relative_poses(final_world_from_cam, j, i)
    ref = relative_poses(gt_world_from_cam, j, i)
    return np.linalg.norm(inv_mul(ref, est)[:, :3, 3], axis=1) > gate


def step_scales(ref_poses: F64, est_poses: F64) -> F64:
    """Per-step scale of associated pose stacks (N x 4 x 4): estimated step length / true step length.

    Step ``k`` goes from pose ``k`` to pose ``k + 1`` (positions, metres); NaN where the true step is
    shorter than 1 mm. Alignment-free: a rigid or similarity transform of either trajectory changes
    a step's length only by the similarity's scale.
    """
    ref = np.linalg.norm(np.diff(np.asarray(ref_poses)[:, :3, 3], axis=0), axis=1)
    est = np.linalg.norm(np.diff(np.asarray(est_poses)[:, :3, 3], axis=0), axis=1)
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(ref >= 1e-3, est / ref, np.nan)


def step_scale_last_over_first(ref_poses: F64, est_poses: F64, fraction: float = 0.25) -> float:
    """How the per-step scale grows along a run: scale of the last ``fraction`` of the steps / of the first.

    Each part's scale is its summed estimated step length over its summed true step length
    (steps as in :func:`step_scales`); 1 when the scale holds, 1.2 when the last quarter's steps are
    20 % longer (relative to the truth) than the first quarter's. NaN with fewer than 2 steps.
    """
    ref = np.linalg.norm(np.diff(np.asarray(ref_poses)[:, :3, 3], axis=0), axis=1)
    est = np.linalg.norm(np.diff(np.asarray(est_poses)[:, :3, 3], axis=0), axis=1)
    n = ref.size
    if n < 2:
        return float("nan")
    k = min(max(1, int(round(fraction * n))), n // 2)
    first = est[:k].sum() / max(ref[:k].sum(), 1e-12)
    last = est[-k:].sum() / max(ref[-k:].sum(), 1e-12)
    return float(last / first) if first > 0 else float("nan")


def scale_figures(
    ref_times_ns: I64, ref_poses: F64, est_times_ns: I64, est_poses: F64, max_dt_ns: int = 10_000_000
) -> dict[str, float]:
    """``sim3_scale`` (ground truth / estimate, Umeyama) and ``step_scale_last_over_first`` of associated poses.

    Empty when fewer than 3 poses associate or the estimate is degenerate (collinear positions).
    """
    i_ref, i_est = associate(ref_times_ns, est_times_ns, max_dt_ns)
    if i_ref.size < 3:
        return {}
    ref, est = np.asarray(ref_poses)[i_ref], np.asarray(est_poses)[i_est]
    try:
        a = align(ref, est, "sim3")
    except EvalInputError:
        return {}
    return {"sim3_scale": float(a.scale), "step_scale_last_over_first": step_scale_last_over_first(ref, est)}
