"""The keyframe loop gate with a bounded number of earlier loops decides as the gate with all of them (issue 33).

A synthetic run of rounds around an object (one keyframe every 18 degrees, each round at its own
radius and height): the odometry drifts (0.3 deg and 1 cm of noise per step), every keyframe after
the first round closes a true loop to the keyframe at its azimuth in a random earlier round, and
false loops are injected (random ones from :func:`add_false_loops` and near misses: a pair's true
relative pose off by 0.25 m and 5 deg). The loops are gated one by one in keyframe order, as the
loop stage does; the accepted ones join the later gates.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

from loopmodel.backend.robust_posegraph import chain_information, nearest_loops, pose_information
from loopmodel.config import LoopConfig
from loopmodel.geometry.se3 import invert_pose

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tools"))
from bench_gate import gate_in_order, perturbed, rounds_run  # noqa: E402 - tools/ is not a package


def test_bounded_gate_decides_as_the_full_gate() -> None:
    world, loops = rounds_run(rounds=7, per_round=20, false_rate=0.1, seed=4)
    kind = np.array([lp[3] for lp in loops])
    assert [int(np.sum(kind == x)) for x in ("true", "random", "near")] == [120, 12, 13]
    k = LoopConfig().robust_max_loops
    full, full_sizes, _ = gate_in_order(world, loops, None)
    bounded, sizes, _ = gate_in_order(world, loops, k)
    assert max(full_sizes) > 2 * k  # the full gate's graph grows with the loops (to 106)
    assert max(sizes) == k
    assert np.array_equal(bounded, full)  # no disagreement
    assert full[kind == "true"].all()  # every true loop kept
    assert not full[kind == "random"].any()  # every random false loop rejected
    # near misses: 7 of 13 pass the full gate too (0.25 m and 5 deg are within what 14-68 keyframe steps
    # of 1 deg and 2 cm and the loops allow); the bounded gate decides the same
    assert int(np.sum(~full[kind == "near"])) == 6


def test_nearest_loops_keep_the_shortest_bridges() -> None:
    eye = np.eye(4)
    # between keyframes 0 and 100: (50, 0) and (100, 50) bridge them in two loop steps together; (99, 2)
    # alone leaves 3 keyframe steps; (70, 30) at least 20 + 20 (over the other loops)
    loops = [(50, 0, eye), (99, 2, eye), (70, 30, eye), (100, 50, eye)]
    assert [lp[:2] for lp in nearest_loops(loops, 0, 100, 2)] == [(50, 0), (100, 50)]
    assert [lp[:2] for lp in nearest_loops(loops, 0, 100, 3)] == [(50, 0), (99, 2), (100, 50)]
    assert nearest_loops(loops, 0, 100, None) == loops
    assert nearest_loops(loops, 0, 100, 4) == loops


def test_chain_information_is_the_sum_of_the_steps_covariances() -> None:
    rng = np.random.default_rng(0)
    world = {0: np.eye(4)}
    for k in range(1, 6):
        world[k] = world[k - 1] @ perturbed(np.eye(4), rng, 20.0, 0.3)
    step = pose_information(1.0, 0.02)
    cov = np.zeros((6, 6))
    for k in range(1, 6):  # independently: the adjoint of last^-1 k, written out
        T = invert_pose(world[5]) @ world[k]
        R, t = T[:3, :3], T[:3, 3]
        tx = np.array([[0.0, -t[2], t[1]], [t[2], 0.0, -t[0]], [-t[1], t[0], 0.0]])
        A = np.block([[R, np.zeros((3, 3))], [tx @ R, R]])
        cov += A @ np.linalg.inv(step) @ A.T
    got = np.linalg.inv(chain_information(world, list(range(6)), step))
    np.testing.assert_allclose(got, cov, rtol=1e-9, atol=1e-12 * np.abs(cov).max())
