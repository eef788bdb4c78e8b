"""Benchmark ``posegraph``: robust loop closing on real pose graphs with false loop edges.

Graphs: ``../shared/data/posegraphs/*.g2o`` (intel, MIT, CSAIL, kitti_00: 2-D;
parking-garage, cubicle, sphere2500: 3-D). Each gets 0/5/10/25 % extra random false loop
edges (count relative to the graph's true loop edges; seeded per graph and rate; see
:func:`loopmodel.backend.robust_posegraph.add_false_loops`). ``ours`` is
:func:`robust_optimize` (graduated Cauchy LM + chi-square gate, odometry known inliers) on the corrupted graph,
``gtsam_lm`` plain LM on it, at most 100 iterations and stopped after the iteration that ends
past ``BASELINE_LM_BUDGET_S`` (``gtsam_lm_iterations`` says how many it ran): its result is bent
either way, and on the dense graphs every iteration is expensive (cubicle at 10 %: 33 s per
iteration at load 8, against 0.3 s on the clean graph). The reference is the clean
graph's optimum: the lower-error one of plain LM from the file's poses and ours on the
clean graph (``clean_reference``). ``final_error_ratio``: the clean graph's error at our
poses over its error at the reference. ``ate_vs_clean_m``: RMS position difference to the
reference (same fixed first pose, no alignment); the goal holds when it is at most 1 % of
the trajectory's bounding-box diagonal. Times: one run per case (wall clock, seconds).
"""

from __future__ import annotations

import sys
import zlib

import numpy as np
from shared_data import SHARED_DATA

from loopmodel.backend.robust_posegraph import (
    PoseGraph,
    add_false_loops,
    graph_error,
    optimize_lm,
    robust_optimize,
)
from loopmodel.io.g2o import read_g2o

DATA = SHARED_DATA / "posegraphs"
ALL = ["intel", "MIT", "CSAIL", "kitti_00", "parking-garage", "cubicle", "sphere2500"]
RATES = [0.0, 0.05, 0.10, 0.25]
#: the plain-LM baseline's time budget on the corrupted graphs (the clean reference runs to
#: convergence, at most 100 iterations)
BASELINE_LM_BUDGET_S = 30.0


def _positions(graph: PoseGraph, world_from_pose: dict[int, np.ndarray], ids: list[int]) -> np.ndarray:
    return np.array([world_from_pose[k][: graph.dim, graph.dim] for k in ids])


def run(quick: bool = False) -> dict:
    names = ["MIT", "CSAIL"] if quick else ALL
    rates = [0.0, 0.10] if quick else RATES
    rows = []
    for name in names:
        g = read_g2o(DATA / f"{name}.g2o")
        # the clean graph's optimum: the lower-error one of plain LM from the file's poses
        # and ours on the clean graph (on MIT plain LM stops in a local minimum of 20x the
        # error; the goal is then measured against the better one)
        clean_lm = optimize_lm(g)
        clean_ours = robust_optimize(g)
        lm_err, ours_err = graph_error(g, clean_lm.world_from_pose), graph_error(g, clean_ours.world_from_pose)
        clean, ref_kind = (clean_lm, "lm") if lm_err <= ours_err else (clean_ours, "ours")
        ids = sorted(clean.world_from_pose)
        ref = _positions(g, clean.world_from_pose, ids)
        diag = float(np.linalg.norm(np.ptp(ref, axis=0)))
        clean_err = min(lm_err, ours_err)
        print(f"posegraph {name}: clean LM error {lm_err:.2f}, ours {ours_err:.2f}", file=sys.stderr, flush=True)
        for rate in rates:
            seed = zlib.crc32(f"{name}:{rate}".encode())
            bad = add_false_loops(g, rate, seed)
            n_false = bad.n_edges - g.n_edges
            ours = robust_optimize(bad)
            lm = optimize_lm(bad, time_budget_s=BASELINE_LM_BUDGET_S)
            ate = float(np.sqrt(np.mean(np.sum((_positions(g, ours.world_from_pose, ids) - ref) ** 2, axis=1))))
            ate_lm = float(np.sqrt(np.mean(np.sum((_positions(g, lm.world_from_pose, ids) - ref) ** 2, axis=1))))
            true_loops = ~g.odometry
            print(f"  rate {rate}: ours {ours.solve_s:.1f} s, ATE {ate:.4f} m", file=sys.stderr, flush=True)
            rows.append(
                {
                    "name": name,
                    "dim": g.dim,
                    "poses": len(ids),
                    "loop_edges": int(true_loops.sum()),
                    "outlier_rate": rate,
                    "false_edges": n_false,
                    "ours_s": round(ours.solve_s, 3),
                    "gtsam_lm_s": round(lm.solve_s, 3),
                    "gtsam_lm_iterations": int(lm.info.get("iterations", -1)),
                    "final_error_ratio": round(graph_error(g, ours.world_from_pose) / clean_err, 5),
                    "gtsam_lm_error_ratio": round(graph_error(g, lm.world_from_pose) / clean_err, 3),
                    "clean_reference": ref_kind,
                    "ate_vs_clean_m": round(ate, 5),
                    "gtsam_lm_ate_vs_clean_m": round(ate_lm, 4),
                    "ate_vs_clean_frac_of_extent": round(ate / diag, 6),
                    "within_1pct": bool(ate <= 0.01 * diag),
                    "false_edges_rejected": int(np.sum(~ours.inlier[g.n_edges :])),
                    "true_edges_rejected": int(np.sum(~ours.inlier[: g.n_edges] & true_loops)),
                    "odometry_edges": int(g.odometry.sum()),
                    "information_repaired": g.repaired_information,
                    "loops_readmitted_in_groups": int(ours.info.get("loops_readmitted_in_groups", 0)),
                }
            )
    at10 = [r for r in rows if r["outlier_rate"] == 0.10]
    return {
        "dataset": "SE-Sync pose graphs: " + ", ".join(names),
        "method": "graduated Cauchy LM then GNC-TLS (gtsam), odometry known inliers, chi2 0.99 gate tightened by the"
        " residual scale, consistent groups of rejected loops re-admitted",
        "gtsam_lm_budget_s": BASELINE_LM_BUDGET_S,
        "graphs": rows,
        "goal": "10 % false loops: ATE vs clean <= 1 % of the trajectory extent on every graph",
        "goal_met_10pct": all(r["within_1pct"] for r in at10),
        "misses_10pct": [r["name"] for r in at10 if not r["within_1pct"]],
    }
