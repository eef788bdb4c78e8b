"""The keyframe loop gate's cost and verdicts as loops accumulate (issue 33, gate16).

``python tools/bench_gate.py [ROUNDS] [MAX_LOOPS,...] [SEED]``: a synthetic run of ROUNDS rounds of 20 keyframes
around an object (one keyframe every 18 degrees, each round at its own radius and height; the odometry drifts by
0.3 deg and 1 cm of noise per step), every keyframe after the first round closing a true loop to the keyframe at
its azimuth in a random earlier round, plus false loops (random ones from :func:`add_false_loops` at 10 % and
near misses, a pair's true relative pose off by 0.25 m and 5 deg, as many as a tenth of the loops). The loops are
gated one by one in keyframe order as the loop stage does (:func:`gate_in_order`), with every earlier loop (0) and
with each bound; prints the verdicts, the disagreements with the full gate and the CPU per gate by sixth of the
run. Then one gate of the widest window with a thread spinning beside it: the spinner's longest gap is how long
the gate held the interpreter lock at once.
"""

from __future__ import annotations

import math
import sys
import threading
import time

import numpy as np

from loopmodel.backend.robust_posegraph import GateSigmas, PoseGraph, add_false_loops, gate_keyframe_loop
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


def perturbed(T: F64, rng: np.random.Generator, sigma_deg: float, sigma_m: float) -> F64:
    """``T`` (4x4) times a random pose of ``sigma_deg`` per rotation axis and ``sigma_m`` per axis."""
    D = np.eye(4)
    D[:3, :3] = so3_exp(np.radians(sigma_deg) * rng.normal(size=3))
    D[:3, 3] = sigma_m * rng.normal(size=3)
    return np.asarray(T @ D, dtype=float)


def rounds_run(
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
        world.append(world[-1] @ perturbed(invert_pose(true[k - 1]) @ true[k], rng, 0.3, 0.01))
    loops: list[tuple[int, int, F64, str]] = []
    for q in range(per_round, n):
        r_old = int(rng.integers(0, q // per_round))
        m = r_old * per_round + (q % per_round)  # the same azimuth step (offsets differ by < 18 deg)
        loops.append((q, m, perturbed(invert_pose(true[q]) @ true[m], rng, 0.3, 0.01), "true"))
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


def gate_in_order(
    world: dict[int, F64], loops: list[tuple[int, int, F64, str]], max_loops: int | None
) -> tuple[np.ndarray, list[int], list[float]]:
    """Each loop's verdict (gated in order, the accepted ones joining later gates), its graph's loop count, CPU ms."""
    accepted: list[tuple[int, int, F64]] = []
    verdicts, sizes, cpu_ms = [], [], []
    for q, m, q_from_m, _ in loops:
        chain = list(range(m, q + 1))
        c0 = time.thread_time()
        ok, _, n_loops = gate_keyframe_loop(world, chain, accepted, (q, m, q_from_m), SIGMAS, 0.99, max_loops)
        cpu_ms.append((time.thread_time() - c0) * 1e3)
        verdicts.append(ok)
        sizes.append(n_loops)
        if ok:
            accepted.append((q, m, q_from_m))
    return np.array(verdicts), sizes, cpu_ms


def _spinner_gap_ms(world: dict[int, F64], loops: list[tuple[int, int, F64, str]], max_loops: int | None) -> str:
    """One gate of the widest window with a counting thread beside it: its longest gap, and idle."""
    q, m, q_from_m, _ = max(loops, key=lambda lp: lp[0] - lp[1])
    earlier = [lp[:3] for lp in loops if lp[3] == "true" and lp[1] >= m and lp[0] < q]
    gaps: list[float] = []
    stop = threading.Event()

    def spin() -> None:
        last = time.perf_counter()
        while not stop.is_set():
            now = time.perf_counter()
            gaps.append(now - last)
            last = now

    th = threading.Thread(target=spin)
    th.start()
    time.sleep(0.3)
    idle = max(gaps)
    n0 = len(gaps)
    c0 = time.thread_time()
    _, _, n = gate_keyframe_loop(world, list(range(m, q + 1)), earlier, (q, m, q_from_m), SIGMAS, 0.99, max_loops)
    cpu = time.thread_time() - c0
    stop.set()
    th.join()
    gap_ms = max(gaps[n0:]) * 1e3
    return f"{n} loops: gate {cpu * 1e3:.0f} ms CPU, spinner's longest gap {gap_ms:.0f} ms (idle {idle * 1e3:.0f})"


def main() -> None:
    rounds = int(sys.argv[1]) if len(sys.argv) > 1 else 18
    bounds = [int(x) for x in (sys.argv[2] if len(sys.argv) > 2 else "0,32").split(",")]
    seed = int(sys.argv[3]) if len(sys.argv) > 3 else 1
    world, loops = rounds_run(rounds, 20, 0.1, seed)
    kind = np.array([lp[3] for lp in loops])
    print({x: int(np.sum(kind == x)) for x in ("true", "random", "near")})
    verdicts = {}
    for k in bounds:
        c0 = time.thread_time()
        v, _, ms = gate_in_order(world, loops, k or None)
        verdicts[k] = v
        sixths = [round(float(np.median(b)), 1) for b in np.array_split(np.array(ms), 6)]
        kept = {x: f"{int(np.sum(v[kind == x]))}/{int(np.sum(kind == x))}" for x in ("true", "random", "near")}
        print(f"max_loops {k}: kept {kept}; CPU ms per gate by sixth {sixths}, max {max(ms):.0f}, "
              f"all {time.thread_time() - c0:.1f} s", flush=True)
        if 0 in verdicts and k:
            print(f"  disagreements with every loop: {int(np.sum(v != verdicts[0]))}")
    for k in bounds:
        print(f"max_loops {k}:", _spinner_gap_ms(world, loops, k or None))


if __name__ == "__main__":
    main()
