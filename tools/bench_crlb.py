"""Benchmark ``crlb``: the marker-pose Cramér–Rao bound (seed 001) and its Monte-Carlo check.

* ``grid_ms``: wall time of the whole 7 x 36 grid for both markers (triangle with spot, T),
  median of repeated runs after a warm-up (``grid_ms_p95`` too).
* Monte-Carlo: at several grid points, noisy renderings (Gaussian PSF of 0.282 px, 0.25 px
  samples, noise N0/2 = 0.2 contrast^2 px^2, i.e. variance 3.2 per sample) fitted by
  Gauss-Newton; ``mc_over_crlb_ratio_median`` is the median over points and parameters of
  (RMS error / contour bound). ``mc_trials`` counts all trials.
"""

from __future__ import annotations

import time

import numpy as np

from loopmodel.accuracy import bound_grid, t_marker, triangle_marker
from loopmodel.accuracy.montecarlo import run_trials

PARAMS = ("r", "v", "u", "gamma")


def run(quick: bool) -> dict:
    markers = {"triangle": triangle_marker(), "t": t_marker()}
    for m in markers.values():          # warm-up
        bound_grid(m)
    times = []
    for _ in range(5 if quick else 20):
        t0 = time.perf_counter()
        for m in markers.values():
            bound_grid(m)
        times.append((time.perf_counter() - t0) * 1e3)

    if quick:
        points = [("triangle", 35.0, 70.0), ("t", 15.0, 120.0)]
        trials = 30
    else:
        points = [("triangle", 5.0, 0.0), ("triangle", 45.0, 250.0),
                  ("t", 25.0, 120.0), ("t", 65.0, 40.0)]
        trials = 200
    rng = np.random.default_rng(20101014)
    ratios, sampled, per_point = [], [], []
    t0 = time.perf_counter()
    for name, th, ph in points:
        res = run_trials(markers[name], th, ph, trials, rng)
        ratios.append(res.ratio)
        sampled.append(res.sigma_sampled / res.sigma_crlb)
        per_point.append({
            "marker": name, "theta_deg": th, "phi_deg": ph,
            "ratio": {p: round(float(x), 3) for p, x in zip(PARAMS, res.ratio, strict=True)},
            "sigma_crlb": [float(f"{x:.4g}") for x in res.sigma_crlb],
            "sigma_mc": [float(f"{x:.4g}") for x in res.sigma_mc],
            "rho_abs_diff_max": round(float(np.max(np.abs(res.rho_mc - res.rho_crlb))), 3),
            "gn_iterations_median": float(np.median(res.iterations)),
            "samples": res.n_samples,
        })
        print(per_point[-1], flush=True)
    mc_s = time.perf_counter() - t0
    r = np.concatenate(ratios)
    s = np.concatenate(sampled)
    half_width = 1.96 / np.sqrt(2 * trials)    # 95 % interval of an RMS estimate / true sigma
    return {
        "dataset": "triangle (base 2 m, height 3 m, spot r = 0.3 m) and T of equal area; "
                   "R = 50 m, f = 18 mm, 10 um px, N0/2 = 0.2 px^2",
        "grid_points": 7 * 36 * 2,
        "grid_ms": round(float(np.median(times)), 2),
        "grid_ms_p95": round(float(np.percentile(times, 95)), 2),
        "mc_trials": trials * len(points),
        "mc_points": len(points),
        "mc_over_crlb_ratio_median": round(float(np.median(r)), 4),
        "mc_over_crlb_ratio_min": round(float(r.min()), 4),
        "mc_over_crlb_ratio_max": round(float(r.max()), 4),
        "mc_ratio_sampling_halfwidth_95": round(float(half_width), 4),
        "sampled_over_contour_crlb_median": round(float(np.median(s)), 4),
        "mc_s": round(mc_s, 1),
        "mc_per_point": per_point,
    }
