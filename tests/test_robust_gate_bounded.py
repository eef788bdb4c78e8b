"""The keyframe loop gate with a bounded number of earlier loops decides as the gate with all of them (issue 33).

A synthetic run of rounds around an object (one keyframe every 18 degrees, each round at its own
radius and height): the odometry drifts (0.3 deg and 1 cm of noise per step), every keyframe after
the first round closes a true loop to the keyframe at its azimuth in a random earlier round, and
false loops are injected (random ones from :func:`add_false_loops` and near misses: a pair's true
relative pose off by 0.25 m and 5 deg). The loops are gated one by one in keyframe order, as the
loop stage does; the accepted ones join the later gates.
"""

from __future__ import annotations

import math

import numpy as np

from loopmodel.backend.robust_posegraph import (
    GateSigmas,
    PoseGraph,
    add_false_loops,
    chain_information,
    gate_keyframe_loop,
    nearest_loops,
    pose_information,
)
from loopmodel.config import LoopConfig
from loopmodel.geometry.se3 import invert_pose, so3_exp

F64 = np.ndarray
SIGMAS = GateSigmas(1.0, 0.02, 1.0, 0.03)  # the loop stage's defaults (LoopConfig.robust_*)


def _look_at_origin(p: F64) -> F64:
    """``world_from_cam`` (4x4) of a camera at ``p`` (m) whose optical axis (z) points at the origin."""
    z = -p / np.linalg.norm(p)
    x = np.cross([0.0, 0.0, 1.0], z)
    x /= np.linalg.norm(x)
    T = np.eye(4)
    T[:3, :3] = np.c_[x, np.cross(z, x), z]
    T[:3, 3] = p
    return T


def _perturbed(T: F64, rng: np.random.Generator, sigma_deg: float, sigma_m: float) -> F64:
    D = np.eye(4)
    D[:3, :3] = so3_exp(np.radians(sigma_deg) * rng.normal(size=3))
    D[:3, 3] = sigma_m * rng.normal(size=3)
    return np.asarray(T @ D, dtype=float)


def _rounds_run(
    rounds: int, per_round: int, false_rate: float, seed: int
) -> tuple[dict[int, F64], list[tuple[int, int, F64, str]]]:
    """Drifting keyframe poses ``world_from_kf`` and loops ``(kf_q, kf_m, q_from_m, kind)`` in gate order.

    ``kind``: "true", "random" (false) or "near" (false: a near miss).
    """
    rng = np.random.default_rng(seed)
    true: list[F64] = []
    for r in range(rounds):
        radius_m, height_m = 2.0 + 0.3 * (r % 3), 0.2 * (r % 5)
        offset = rng.uniform(0.0, 2.0 * math.pi / per_round)
        for k in range(per_round):
            th = 2.0 * math.pi * k / per_round + offset
            true.append(_look_at_origin(np.array([radius_m * math.cos(th), radius_m * math.sin(th), height_m])))
    n = len(true)
    world = [true[0]]
    for k in range(1, n):
        world.append(world[-1] @ _perturbed(invert_pose(true[k - 1]) @ true[k], rng, 0.3, 0.01))
    loops: list[tuple[int, int, F64, str]] = []
    for q in range(per_round, n):
        r_old = int(rng.integers(0, q // per_round))
        m = r_old * per_round + (q % per_round)  # the same azimuth step (offsets differ by < 18 deg)
        loops.append((q, m, _perturbed(invert_pose(true[q]) @ true[m], rng, 0.3, 0.01), "true"))
    edges = [(k - 1, k) for k in range(1, n)] + [(m, q) for q, m, _, _ in loops]
    graph = PoseGraph(
        3,
        dict(enumerate(true)),
        np.asarray(edges, dtype=np.int64),
        [invert_pose(true[a]) @ true[b] for a, b in edges],
        [np.eye(6)] * len(edges),
        np.r_[np.ones(n - 1, bool), np.zeros(len(loops), bool)],
    )
    bad = add_false_loops(graph, false_rate, seed + 1)
    for e in range(graph.n_edges, bad.n_edges):
        a, b = (int(v) for v in bad.edges_ij[e])
        loops.append((b, a, invert_pose(bad.i_from_j[e]), "random"))
    for q in rng.choice(np.arange(per_round, n), len(loops) // 10, replace=False):
        m = int(rng.integers(0, (int(q) // per_round) * per_round))
        off = np.eye(4)
        off[:3, :3] = so3_exp(np.radians(5.0) * rng.normal(size=3) / math.sqrt(3.0))
        d = rng.normal(size=3)
        off[:3, 3] = 0.25 * d / np.linalg.norm(d)
        loops.append((int(q), m, invert_pose(true[int(q)]) @ true[m] @ off, "near"))
    loops.sort(key=lambda lp: lp[0])
    return dict(enumerate(world)), loops


def _gate_in_order(
    world: dict[int, F64], loops: list[tuple[int, int, F64, str]], max_loops: int | None
) -> tuple[np.ndarray, list[int]]:
    """Each loop's verdict (gated in order, the accepted ones joining later gates) and its graph's loop count."""
    accepted: list[tuple[int, int, F64]] = []
    verdicts, sizes = [], []
    for q, m, q_from_m, _ in loops:
        chain = list(range(m, q + 1))
        ok, _, n_loops = gate_keyframe_loop(world, chain, accepted, (q, m, q_from_m), SIGMAS, 0.99, max_loops)
        verdicts.append(ok)
        sizes.append(n_loops)
        if ok:
            accepted.append((q, m, q_from_m))
    return np.array(verdicts), sizes


def test_bounded_gate_decides_as_the_full_gate() -> None:
    world, loops = _rounds_run(rounds=7, per_round=20, false_rate=0.1, seed=4)
    kind = np.array([lp[3] for lp in loops])
    assert [int(np.sum(kind == x)) for x in ("true", "random", "near")] == [120, 12, 13]
    k = LoopConfig().robust_max_loops
    full, full_sizes = _gate_in_order(world, loops, None)
    bounded, sizes = _gate_in_order(world, loops, k)
    assert max(full_sizes) > 3 * k  # the full gate's graph grows with the loops
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
        world[k] = world[k - 1] @ _perturbed(np.eye(4), rng, 20.0, 0.3)
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
