"""frontend.mono_depth.

The seed-003 adaptive depth update with known camera motion, on synthetic views against ground truth
and in the front end on real KITTI frames whose right image is half blanked, against stereo depths
from the unblanked right image.
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np

from loopmodel.geometry.se3 import invert_pose, se3_exp
from loopmodel.observers.known_motion import KnownMotionDepthObserver


def _views(pts: np.ndarray, twists: list[np.ndarray], sigma: float, rng: np.random.Generator):
    for tw in twists:
        cur_from_ref = invert_pose(se3_exp(tw))
        P = pts @ cur_from_ref[:3, :3].T + cur_from_ref[:3, 3]
        yield cur_from_ref, P[:, :2] / P[:, 2:3] + rng.normal(0, sigma, (len(pts), 2))


def test_known_motion_observer_recovers_depths(rng: np.random.Generator) -> None:
    pts = np.column_stack([rng.uniform(-8, 8, 60), rng.uniform(-2, 2, 60), rng.uniform(5, 40, 60)])
    sigma = 0.3 / 700.0  # 0.3 px at f = 700 px
    obs = KnownMotionDepthObserver()
    obs.add(pts[:, :2] / pts[:, 2:3], 1.0 / 15.0)
    twists = [np.array([0.05 * k, 0.0, 1.2 * k, 0.0, 0.01 * k, 0.0]) for k in range(1, 8)]
    for cur_from_ref, m in _views(pts, twists, sigma, rng):
        obs.update(cur_from_ref[:3, :3], cur_from_ref[:3, 3], m, 0.1)
    rel = np.abs(obs.depth_m() - pts[:, 2]) / pts[:, 2]
    pred = obs.rel_sigma(sigma)
    well = pred < 0.05
    assert well.sum() > 40
    assert np.median(rel[well]) < 0.01
    assert np.mean(rel[well] < 3 * pred[well] + 1e-3) > 0.9  # the predicted uncertainty is honest
    assert obs.excited(np.radians(1.0)).sum() > 30


def test_known_motion_observer_without_translation_is_not_excited(rng: np.random.Generator) -> None:
    pts = np.column_stack([rng.uniform(-3, 3, 20), rng.uniform(-2, 2, 20), rng.uniform(5, 20, 20)])
    obs = KnownMotionDepthObserver()
    obs.add(pts[:, :2] / pts[:, 2:3], 0.1)
    twists = [np.array([0, 0, 0, 0.01 * k, 0.02 * k, 0.0]) for k in range(1, 10)]
    for cur_from_ref, m in _views(pts, twists, 1e-4, rng):
        obs.update(cur_from_ref[:3, :3], cur_from_ref[:3, 3], m, 0.1)
    assert not obs.excited(np.radians(0.1)).any()
    assert np.allclose(obs.theta, 0.1)  # nothing learnt, nothing diverged
    assert np.all(obs.rel_sigma(1e-3) == np.inf)


def test_frontend_mono_depth_matches_stereo_on_kitti(shared_data: Path) -> None:
    """Right image blanked left of its middle.

    Corners there find no stereo match and get observer depths from the tracker's poses; compare
    with stereo on the full right image.
    """
    from loopmodel.config import load_config
    from loopmodel.frontend import FrontEnd
    from loopmodel.frontend.stereo import match_stereo
    from loopmodel.io.sequence import open_sequence

    seq = open_sequence(shared_data / "kitti_clip")
    root = Path(__file__).resolve().parents[1]
    cfg = load_config(root / "configs" / "kitti.yaml").frontend.model_copy(update={"mono_depth": "observer"})
    fe = FrontEnd(seq.calibration, cfg)
    frames = [f for f, _ in zip(seq.frames(), range(12), strict=False)]
    kf_frame = {}
    used = 0
    for f in frames:
        right = f.right.copy()
        right[:, : right.shape[1] // 2] = 0
        r = fe.process(replace(f, right=right))
        assert r.ok
        used += r.mono_points
        if r.keyframe is not None:
            kf_frame[r.keyframe.id] = f
    assert used > 0
    est = fe.mono_depth_estimates()
    assert est is not None
    rel = []
    for k in np.unique(est["ref_kf"]):
        sel = np.flatnonzero((est["ref_kf"] == k) & est["converged"])
        f = kf_frame[int(k)]
        m = match_stereo(fe.rectifier.left(f.left), fe.rectifier.right(f.right), est["uv_ref"][sel], cfg)
        z = fe.calibration.fx_px * fe.calibration.baseline_m / m.disparity
        rel += list(np.abs(est["depth_m"][sel][m.index] - z) / z)
    assert len(rel) >= 10
    assert np.median(rel) < 0.06
    off = FrontEnd(seq.calibration, cfg.model_copy(update={"mono_depth": "none"}))
    assert off.mono_depth_estimates() is None
