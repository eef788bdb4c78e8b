"""Global hybrid BA on a synthetic orbit: the loop residuals remove the accumulated drift."""

from __future__ import annotations

import numpy as np
import pytest

from loopmodel.errors import InputError
from loopmodel.geometry.se3 import invert_pose, so3_log
from loopmodel.loop.global_ba import global_hybrid_ba
from loopmodel.sim.loop_problem import orbit_problem


def _errors(T_est: dict[int, np.ndarray], T_true: list[np.ndarray]) -> tuple[float, float]:
    last = len(T_true) - 1
    d = invert_pose(T_true[last]) @ T_est[last]
    return float(np.linalg.norm(d[:3, 3])), float(np.degrees(np.linalg.norm(so3_log(d[:3, :3]))))


def test_loop_closure_ba_reduces_endpoint_error() -> None:
    pr = orbit_problem(n_keyframes=16, features_per_kf=30, drift_trans_m=0.006, seed=3)
    before = _errors({k.id: k.world_from_kf for k in pr.keyframes}, pr.true_world_from_kf)
    args = (pr.fx_px, pr.fx_px, pr.cx_px, pr.cy_px, pr.baseline_m)
    with_loop = global_hybrid_ba(pr.keyframes, pr.loops, *args)
    without = global_hybrid_ba(pr.keyframes, [], *args)
    after = _errors(with_loop.world_from_kf, pr.true_world_from_kf)
    odo = _errors(without.world_from_kf, pr.true_world_from_kf)
    assert before[0] > 0.01  # the drift is there
    assert after[0] < 0.2 * before[0]
    assert after[0] < 0.5 * odo[0]  # the loop residuals, not just the BA, do it
    assert after[1] < 0.5 * before[1]
    # every keyframe close to the truth; the first one is held fixed
    assert np.array_equal(with_loop.world_from_kf[0], pr.keyframes[0].world_from_kf)
    pos = [np.linalg.norm(with_loop.world_from_kf[i][:3, 3] - T[:3, 3]) for i, T in enumerate(pr.true_world_from_kf)]
    assert max(pos) < 0.01
    assert with_loop.final_error < with_loop.initial_error
    assert with_loop.n_parameters == 6 * 15 + 3 * 16 * 30


def test_global_ba_input_errors() -> None:
    pr = orbit_problem(n_keyframes=4, features_per_kf=10)
    args = (pr.fx_px, pr.fx_px, pr.cx_px, pr.cy_px, pr.baseline_m)
    with pytest.raises(InputError, match="no keyframes"):
        global_hybrid_ba([], [], *args)
    with pytest.raises(InputError, match="fixed keyframe"):
        global_hybrid_ba(pr.keyframes, [], *args, fixed_kf_id=99)
