"""Typed configuration: one nested pydantic model with defaults in code.

A YAML file overrides any part of it; an unknown key is an error that names the key.
Every run writes the effective configuration into its results folder.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any, Literal, TypeVar

import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from loopmodel.errors import ConfigError

BackendKind = Literal["isam2", "givens", "both", "none"]
"""``backend.kind``: iSAM2, the Givens estimator, iSAM2 behind the Givens screen, or none."""
ImageFormat = Literal["raw", "png", "jpeg"]
"""How images are stored in an MCAP file."""
DescriptorKind = Literal["orb", "sift", "surf"]
"""Feature descriptor of loop closing."""
AlignMode = Literal["se3", "sim3", "origin", "none"]
"""Alignment of an estimated trajectory to the ground truth before its errors."""


class _Section(BaseModel):
    model_config = ConfigDict(extra="forbid", validate_assignment=True)


class TopicsConfig(_Section):
    """MCAP topic names (DESIGN.md)."""

    left_image: str = "/cam0/image_raw"
    right_image: str = "/cam1/image_raw"
    left_info: str = "/cam0/camera_info"
    right_info: str = "/cam1/camera_info"
    stripe: str = "/laser/stripe"
    laser_image: str = "/laser/image"
    ground_truth: str = "/ground_truth/pose"


class SequenceConfig(_Section):
    """How sequences are read."""

    topics: TopicsConfig = Field(default_factory=TopicsConfig)
    stereo_pair_tolerance_ns: int = Field(1_000_000, ge=0, description="max left/right stamp gap")
    kitti_rate_hz: float = Field(10.0, gt=0, description="frame rate when times.txt is absent")
    # an image (MCAP message) declaring more pixels than this is refused before decoding: a
    # safety limit (100 Mpx, ~15x the largest shared image), not a tuned value
    max_image_pixels: int = Field(100_000_000, ge=1, le=2**31 - 1, description="max width*height")
    # orb13 (issue 33): the run may read and decode its frames on a thread of its own, this many frames ahead
    # of the tracking (the MCAP chunks, the PNG inflate and the laser images release the interpreter lock),
    # instead of on the tracking thread between frames. Off: the reading then competes with the frames' own
    # threads for the two cores. Realistic orbit (datasets/sample/scan.mcap, 150 frames, under SCHED_FIFO at
    # load 11-12: the cores ours), 2 alternated pairs 0 / 2: wall per frame 14.7, 15.1 / 12.8, 13.2 ms, mean
    # frame 8.9, 9.3 / 9.5, 9.5 ms; KITTI clip (configs/kitti.yaml), 2 pairs: cpu_util 1.55, 1.48 / 1.54, 1.57,
    # frame median 13.3, 12.1 / 14.5, 16.1 ms, the same poses. CHANGELOG (orb13)
    read_ahead_frames: int = Field(0, ge=0, le=64, description="frames read and decoded ahead on a thread")


class OutputConfig(_Section):
    """Where and what a run writes."""

    out_dir: str = "results"
    write_kitti: bool | None = Field(
        None,
        description="also write trajectory_*.kitti (KITTI poses.txt rows); null: when the input is a KITTI folder",
    )
    write_map: bool = Field(True, description="write the session map map/ (issue 20: localize, extend, merge)")


class BackendConfig(_Section):
    """Keyframe/landmark back end (``backend/``); iSAM2 keys map onto ``gtsam.ISAM2Params``."""

    kind: BackendKind = Field(
        "isam2",
        description="isam2, givens, both (Givens screen before iSAM2), or none (front-end poses only)",
    )
    pixel_sigma_px: float = Field(1.0, gt=0, description="std. dev. of an image coordinate")
    huber_k: float = Field(
        3.0, ge=0, description="Huber threshold in sigmas (0: Gaussian); weights kept until relin."
    )
    prior_sigma_rad: float = Field(1e-6, gt=0, description="gauge prior, first keyframe")
    prior_sigma_m: float = Field(1e-6, gt=0, description="gauge prior, first keyframe")
    # the gauge of a new segment (issue 34): 10 m / 1 rad left the island of `simulate scan --preset
    # orbit --realism clean` (2 keyframes, 21 landmarks) indeterminate to GTSAM's Cholesky (stopped
    # at frame 18); 0.1 m / 0.1 rad: no rebuild, final ATE 1.88 mm; KITTI clip and the sweeps
    # preset unchanged (CHANGELOG); a loop (0.01 m / 0.01 rad) still outweighs it 100 times
    segment_prior_sigma_rad: float = Field(
        0.1, gt=0, description="prior on a keyframe not linked to the previous one"
    )
    segment_prior_sigma_m: float = Field(
        0.1, gt=0, description="prior on a keyframe not linked to the previous one"
    )
    loop_sigma_rad: float = Field(0.01, gt=0, description="default loop-constraint sigma")
    loop_sigma_m: float = Field(0.01, gt=0, description="default loop-constraint sigma")
    min_disparity_px: float = Field(2.0, ge=0, description="stereo observations below: dropped")
    min_observations: int = Field(2, ge=1, le=1000, description="a landmark enters once seen this often")
    pending_max_age_kf: int = Field(
        3, ge=1, description="forget a not-yet-added landmark unseen for this many keyframes"
    )
    max_landmark_span_kf: int = Field(
        0, ge=0, description="continue a track in a new landmark after this many keyframes (0: no)"
    )
    init_gate_px: float = Field(
        20.0, ge=0, description="drop observations this far from the initial landmark (0: off)"
    )
    init_iterations: int = Field(
        3, ge=0, description="Gauss-Newton steps refining a new landmark on all its observations"
    )
    blunder_sigma: float = Field(
        0.0, ge=0, description="remove new observations whose whitened residual exceeds (0: off)"
    )
    relinearize_threshold_rad: float = Field(0.005, gt=0, description="pose rotation")
    relinearize_threshold_m: float = Field(0.02, gt=0, description="pose position")
    relinearize_threshold_landmark_m: float = Field(0.2, gt=0, description="landmark position")
    # issue 33 item 5 (be18): 1 -> 2. Under local a loop's prior on the newest keyframe bends the window;
    # checked every update, 3-10 window poses crossed relinearize_threshold_rad at about a third of the
    # later keyframes of rounds_5400 (104 of 309), each re-eliminating every landmark it observes (an
    # update 5-7 -> 12-25 ms): the last block's median fell on those. Every second update: 87 of 309, the
    # call stream's back-end CPU 7.63 -> 7.55 s, online keyframe ATE 10.128 -> 10.122 mm; bench scale, 3
    # alternating pairs each (medians): --quick last block / first 1.87 -> 1.71, full 2.18 -> 1.78, the
    # final ATE as before (with the estimate's frozen-keyframe reads, CHANGELOG be18). The KITTI clip
    # (configs/kitti.yaml) and the 600-frame sample (configs/sim.yaml): bench pipeline's accuracy keys as before.
    # (A looser relinearize_threshold_rad, 0.0075-0.01, cost the synthetic rounds' accuracy, be18.)
    relinearize_skip: int = Field(2, ge=1, le=10000, description="check relinearisation every N updates")
    # issue 33 item 5 (be20): left at 1 (off); be20 measured 0.7. In the rounds scan's later rounds the window's
    # poses all sit near relinearize_threshold_rad and crossed it one at a time, each relinearising update then
    # re-eliminating every landmark of the pose that crossed (the last block's median fell on those updates); with
    # it they relinearise together once one crosses (Isam2Backend._poses_held). Call streams replayed (jemalloc, gc
    # frozen, load 5-8), last block / first: rounds_1800 1.80-1.85 (5 runs) -> 1.65-1.72 (3 runs; 0.5 / 0.6 / 0.8:
    # 1.76-1.85 / 1.72-1.81 / 1.72-1.75), online keyframe ATE 10.085 -> 10.112 mm; rounds_5400 2.26 / 2.29 -> 1.70 /
    # 1.73, CPU 7.4-7.8 -> 6.9-7.6 s, ATE 10.118 -> 10.120 mm. bench scale --quick, 5 alternating pairs (load 6-10):
    # backend_ms_last_over_first median 1.795 -> 1.752, its last block 23.3 -> 21.9 ms, back-end CPU 2.70 -> 2.66 s,
    # ate_rmse_after_m 0.00082-0.00083 -> 0.00082-0.00085; full bench scale, 2 pairs (load 4-7): 1.626 / 1.995 ->
    # 1.689 / 1.692, last block 20.9 / 25.1 -> 21.1 / 21.8 ms. bench pipeline (3 alternating pairs, load 6-9): the
    # KITTI clip (configs/kitti.yaml, real) final ATE 0.0252 -> 0.0251 m in every run, online 0.0758 m and the drift
    # after the segment as before (its kitti_frame_ms_p95 was 7-16 ms higher in all three be20 runs at that load,
    # 62.6-85.9 against 46.9-78.9 ms, median frame 30-33 against 22-35 ms: to be checked quiet); the 600-frame
    # sample (configs/sim.yaml) final 0.77 mm, online 10.68 mm, mesh 0.398833 mm as before in 2 of 3 runs (the third
    # 0.74 mm, 10.64 mm, 0.3838 mm, not explained; base gave 0.398833 mm in every run); the 150-frame orbit's mesh
    # 0.346775 mm (0.346726 once). Left off: the live gain on the scale ratio is within the load's noise, and
    # kitti_frame_ms_p95 was higher in all 4 be20 runs of bench pipeline (62.6-85.9 against 46.9-78.9 ms, load 6-11;
    # a fourth pair 51.5 -> 83.4 ms with the KITTI online ATE 0.0758 -> 0.0769 m; not explained: perhaps a crossing
    # update relinearising more poses at once moves more keyframes, which reach the tracker as a correction)
    # (CHANGELOG be20)
    relinearize_group_fraction: float = Field(
        1.0, gt=0, le=1, description="one pose over its thresholds: all above this fraction relinearise (1: off)"
    )
    # issue 33 item 5 (isam12): the full check visits every variable each update (a cost growing with
    # the map); on, the rounds_1800 call stream replayed cost 3.3-3.4 s of back-end CPU against 3.9-4.4
    # (2 runs each, load 9-10) but the synthetic rounds' final estimates (tests/test_backend_growth.py,
    # without the batch BA) 5-15 % worse: left off (CHANGELOG isam12)
    partial_relinearization_check: bool = Field(
        False, description="check relinearisation only in the cliques an update touches"
    )
    wildfire_threshold: float = Field(0.001, ge=0, description="back-substitution stop")
    factorization: Literal["CHOLESKY", "QR"] = Field("CHOLESKY")
    ordering_window_kf: int = Field(
        10, ge=0, description="eliminate the newest N poses last, oldest first (0: GTSAM default)"
    )
    change_tolerance_m: float = Field(
        1e-4, ge=0, description="estimate(): a keyframe counts as changed above this"
    )
    # issue 33 (scale6): reading every pose each keyframe grew the cost per keyframe with the map
    estimate_window_kf: int = Field(
        20, ge=0, le=100000, description="estimate(): read the newest N poses and N older ones in turn (0: all)"
    )
    # issue 33 item 5: local keeps iSAM2 to the last local_window_kf keyframes' landmarks (an
    # observation of an older landmark enters as one of a proxy fixed at its estimate, the real one
    # and the loop constraints wait outside iSAM2); everything joins one graph for the final estimate.
    # Default since window9 (with local_loop_prior): scale --quick (rounds_1800, 3 alternating pairs)
    # back end per keyframe last block / first 15.8 -> 3.3, last loop 149 -> 9 ms, final ATE equal;
    # the KITTI clip (configs/kitti.yaml) and the 600-frame sample (configs/sim.yaml) identical (CHANGELOG)
    loop_policy: Literal["isam2", "local"] = Field(
        "local",
        description="isam2: loops and revisits in iSAM2; local: a local iSAM2 against a fixed old map, "
        "loops and revisits join for the final estimate",
    )
    local_window_kf: int = Field(
        10, ge=1, description="local: observations of landmarks older than this reach iSAM2 through proxies"
    )
    # issue 33 item 5 (isam10): a loop keyframe of the rounds scan brought three iSAM2 updates (its own,
    # the loop's late observations, the loop's prior), each re-eliminating the top of the window; the
    # late observations now join the next update (the loop prior's right after them). scale --quick
    # (rounds_1800, 4 alternating pairs, load 1-13): back-end CPU 6.2-6.6 -> 5.4-5.9 s (late observations
    # 0.96-0.99 -> 0.25-0.27 s), its last block / first 2.61-3.56 -> 2.53-3.23 (noise), final ATE equal.
    # Inert without loops: the KITTI clip (configs/kitti.yaml) and the 600-frame sample never take this path
    local_defer_late: bool = Field(
        True, description="local: a loop's late observations join the next iSAM2 update (its prior's)"
    )
    # issue 33 item 5 (window9): under local a loop also enters iSAM2 at once as a prior on its newer
    # keyframe at the older one's estimate (the live end corrected by one small update). Measured with
    # local on: scale --quick (rounds_1800, 67 loops) last loop's optimisation 7-12 ms, final ATE equal
    # to isam2's (0.00081-0.00083 m); the KITTI clip (configs/kitti.yaml, real) and the 600-frame sample
    # (configs/sim.yaml) identical with it on or off (no loop closes there) (CHANGELOG window9, integration)
    local_loop_prior: bool = Field(
        True, description="local: a loop corrects its newer keyframe online through a prior (else only at the end)"
    )
    # issue 33 item 5 (isam12): under local a keyframe's own update waits for the calls that follow it
    # in the same batch (a loop's late observations and prior) and runs with them at the next estimate:
    # one iSAM2 update a loop keyframe instead of two, the live end corrected in the same estimate
    # rounds_1800 call stream replayed (load 13-15): back-end CPU 5.4 -> 5.0 s, last block median 63 -> 51 ms;
    # the KITTI clip (configs/kitti.yaml) and the orbit identical or within noise in bench pipeline --quick
    local_defer_keyframe: bool = Field(
        True, description="local: a keyframe's iSAM2 update waits for its loop's (one update, at the next estimate)"
    )
    # issue 33 item 5 (be15): a loop found after its keyframe's estimate (the loop worker's usual case)
    # brought a second iSAM2 update to that keyframe (its prior, with its late observations); on, they
    # wait for the next keyframe's update: one update a keyframe, the live end corrected one keyframe later.
    # rounds_1800 call stream replayed as the worker batches it (interleaved, load ~10): the last block
    # 63 -> 51 ms a keyframe (with the budget 42 -> 36), online keyframe ATE 9.69 -> 9.60 mm, final equal.
    # The KITTI clip (configs/kitti.yaml, no loop) and the 600-frame sample (configs/sim.yaml, one loop)
    # identical in bench pipeline (final ATE 0.0251 m / 0.76 mm) (CHANGELOG be15)
    local_defer_loop: bool = Field(
        True, description="local: a loop's prior and late observations join the next keyframe's iSAM2 update"
    )
    # issue 33 item 5 (isam12): under local every N keyframes iSAM2 is rebuilt on the newest
    # local_rebuild_keep_kf keyframes' factors (older keyframes those factors name held by a gauge-tight
    # prior at their estimate; the rest of the map leaves iSAM2 at its estimate and rejoins for the
    # final estimate): what each update pays for stays bounded by construction (0: off). The
    # rounds_5400 call stream (18 rounds, 348 keyframes) replayed with local_defer_keyframe: back end
    # per keyframe last block / first 3.0 -> 1.6 (23.6 -> 71.5 ms against 24.1 -> 38.3), CPU 20.8 /
    # 22.7 s (the rebuilds 5.8 s), online keyframe ATE 9.56 / 9.59 mm; on rounds_1800 20-30 % more CPU;
    # inert below keep + N keyframes: the KITTI clip (13, identical in bench pipeline --quick) and the
    # 600-frame sample (19) (CHANGELOG isam12)
    local_rebuild_kf: int = Field(
        20, ge=0, le=100000, description="local: rebuild iSAM2 on the newest keyframes every N keyframes (0: off)"
    )
    local_rebuild_keep_kf: int = Field(
        10, ge=1, le=100000, description="local_rebuild_kf: keyframes a rebuild keeps free (at least local_window_kf)"
    )
    # issue 33 (be21): an iSAM2 a window rebuild made (local_rebuild_kf) checks relinearisation every Nth update
    # (0: relinearize_skip's). In the rounds scan's later rounds the window's poses cross relinearize_threshold_rad
    # at nearly every check (the proxies pull the window onto the old map), each relinearising update re-eliminating
    # every landmark of the poses that crossed: at every 2nd update the last block's median fell on those updates.
    # Every 4th: the poses that crossed meanwhile relinearise together, half as many such updates, the same back-end
    # CPU. Call streams replayed (jemalloc, gc frozen, alternating with main, load 5-9): rounds_5400 last block /
    # first 2.45 / 2.36 -> 1.43 / 1.64, CPU 6.9 / 6.8 -> 6.9 / 7.1 s, online keyframe ATE 10.118 -> 10.114 mm;
    # rounds_1800 1.83-1.98 -> 1.72-1.81 (3 runs each), ATE 10.085 -> 10.082 mm. Live (load 6.5-12): bench scale
    # --quick 3 alternating pairs, median 1.789 -> 1.697, ate_rmse_after_m 0.00083 -> 0.00082-0.00083; full scale
    # one pair 1.580 -> 1.689 (the last block 20.7 / 20.8 ms: no gain shown live there). Only a rebuilt iSAM2's:
    # relinearize_skip 4 everywhere moved the KITTI clip's (configs/kitti.yaml, real) final ATE 0.0252 -> 0.0254 /
    # 0.0256 m (2 pairs). The clip (13 keyframes) and the 600-frame sample
    # (configs/sim.yaml, 19) never rebuild (local_rebuild_keep_kf + local_rebuild_kf = 30 keyframes first): bench
    # pipeline's accuracy keys identical to main's (CHANGELOG be21). Rebuilds forced on the real clip (integration,
    # session 21: worker inline, local_window_kf 4, local_rebuild_kf 2, local_rebuild_keep_kf 4, loop detection off;
    # deterministic): 0 -> 4 final ATE 0.02777 -> 0.02785 m, online 0.07067 -> 0.07073 m.
    # be23b: -1, never: the next rebuild (every local_rebuild_kf keyframes) relinearises the window at its
    # estimate anyway, and each relinearising update between rebuilds re-eliminated every landmark of the poses
    # that crossed (2-5 of the last 20 keyframes' updates at 800-2,400 variables against ~500). Call streams
    # replayed (jemalloc, gc frozen; re-eliminated variables deterministic): rounds_1800 last block's
    # 17,366 -> 12,432 (first 9,586 both), per keyframe median 513 -> 490, online keyframe ATE 10.069 -> 10.020 mm;
    # rounds_5400 last block 15,624 -> 10,593 (first 9,543), back-end CPU 7.17 -> 6.02 s, ATE 10.137 -> 10.134 mm.
    # bench scale --quick, 11 alternating pairs (load 1.7-9.6): backend_ms_last_over_first median 1.498 -> 1.425
    # (1.337-1.623 -> 1.344-1.484), last block 17.9 -> 17.2 ms, ate_rmse_after_m 0.00083-0.00086 -> 0.00083-0.00085;
    # full bench scale, 2 pairs (load 3.9-6.8): 1.368 / 1.567 -> 1.348 / 1.417, ate_rmse_after_m 0.0009 both.
    # Inert below local_rebuild_keep_kf + local_rebuild_kf keyframes: the KITTI clip (configs/kitti.yaml, real, 13)
    # and the 600-frame sample (configs/sim.yaml, 20) never rebuild; bench pipeline's keys as main's (CHANGELOG be23b).
    # Rebuilds forced on the real clip (integration, session 23: frontend.min_tracked_fraction 0.5 for 23 keyframes,
    # worker inline, local_window_kf 4, local_rebuild_kf 6, local_rebuild_keep_kf 4, loop detection off;
    # deterministic): skip 0 / 4 / -1 online ATE 0.1685 / 0.1645 / 0.1639 m, final 0.08108 / 0.08109 / 0.08090 m
    local_rebuild_relinearize_skip: int = Field(
        -1,
        ge=-1,
        le=10000,
        description="a rebuilt window iSAM2 checks relinearisation every N updates (0: as before; -1: at rebuilds)",
    )
    # issue 33 item 5 (be16): under local a revisit observation (a landmark older than local_window_kf)
    # reaches iSAM2 as three things (a proxy variable, its prior, the observation of it): 170-260
    # factors a keyframe from the first revisit on in rounds_1800, none in the first round. At most N a
    # keyframe (its updates together, late observations included) get proxies, the first N of the
    # spread order (best-supported old landmarks over the image); the rest wait outside iSAM2 as every
    # revisit's real observation does, for the final estimate (the same graph there). rounds_1800 call
    # stream replayed interleaved with 0 (load 12): blocks 4-6 25.6-35.5 ms a keyframe against 31.1-38.0,
    # CPU 5.01 / 5.10 s, online keyframe ATE 10.11 / 9.67 mm, final 8.13 mm both; live scale --quick (3
    # pairs, load 8-14): factors of the last block 750 -> 665, its ms within the load's noise. The KITTI
    # clip (configs/kitti.yaml) and the 600-frame sample (configs/sim.yaml): every key of bench pipeline
    # identical (CHANGELOG be16)
    local_proxies_per_kf: int = Field(
        40, ge=0, le=100000, description="local: old landmarks a keyframe sees through proxies in iSAM2 (0: all)"
    )
    # issue 33 (scale8): rounds_1800 replay (local): a keyframe's observations of landmarks already in
    # the graph (local map and revisits) grow 92 -> 378 a keyframe from the first round to the sixth,
    # its new landmarks' 342 -> 406; over the budget its monocular ones wait outside iSAM2 for the
    # final estimate. be13: those kept are spread over the image (best-supported landmarks first). Left
    # off: rounds_1800 call stream replayed (load 7-15) with 200, the sixth round's factors 748 -> 622 a
    # keyframe, re-eliminated variables 735 -> 502, online keyframe ATE 9.60 -> 10.02 mm, final 8.13 ->
    # 8.12 mm at the same final CPU; 100 flattens more (521) but the final estimate's iSAM2 iterations
    # 1 -> 3 (live final refinement 16 -> 99 s). In bench scale --quick (3 alternating pairs at 200) the
    # back end's last block / first 2.70-2.93 against 2.87-3.64 and its CPU 1-15 % lower, but
    # frame_ms_last_over_first 1.51-1.75 against 0.34-1.22 (not explained); the KITTI clip
    # (configs/kitti.yaml) final ATE 0.0251 -> 0.0252 m, the orbit identical (CHANGELOG be13).
    # be15: 150 with the rest dropped (keyframe_obs_overflow; a revisit's observations never are): the
    # rounds_1800 call stream replayed with an estimate after each keyframe as the worker does (back ends
    # interleaved call by call, load ~10): the last block's factors 750 -> 570 a keyframe, its CPU 63 -> 42
    # ms, final keyframe ATE 8.13 -> 8.22 mm (joining at the end instead: 8.13 mm, final CPU +40-140 %);
    # with local_defer_loop, scale --quick (2 alternating pairs, load 9-12) backend_ms_last_over_first
    # 3.5-3.9 -> 2.4-2.6, ATE after equal; the KITTI clip and the 600-frame sample identical. Left off: a
    # short loop's resumed old features are landmarks of the local window, and the budget dropped most of
    # their observations (tests/test_loop_pipeline.py: 126 of 545 reached the back end) (CHANGELOG be15)
    # be19 measured 120, the rest joining at the final estimate (final), a resumed keyframe's landmarks
    # and a loop's late observations never held back (Isam2Backend._old_map_seq). The rounds scan's later
    # rounds bring 178 monocular observations of window landmarks a keyframe (96 in the first) and ~76
    # revisit-proxy factors; the first round's keyframes stay under 120. rounds_1800 call stream replayed
    # (jemalloc, gc frozen as the worker): last block / first 1.79 -> 1.46-1.50, re-eliminated variables of
    # the last block 696 -> 450, online keyframe ATE 10.106 -> 10.107 mm, final 8.147 mm both; bench scale
    # --quick live gains less (5 alternating pairs, load 3-7): backend_ms_last_over_first median 1.737 -> 1.614,
    # the last block 20.9 -> 20.1 ms, first 12.1 both, back-end CPU 2.41 s both, ATE after 0.00081-0.00083 ->
    # 0.00082-0.00084 m. bench pipeline (2 alternating pairs, load 8-10): the KITTI clip
    # (configs/kitti.yaml, real) final ATE 0.0252 m, online 0.0758 m, drift after the segment 0.547 % as
    # before (0.0247 m once, with tests beside it); the 600-frame sample (configs/sim.yaml) final ATE 0.77 mm
    # as before, online 10.68 -> 10.77 mm, mesh 0.3988 -> 0.4052 mm; the 150-frame orbit's mesh as before.
    # 80 flattened more (replay 1.38) but moved the KITTI clip (rotation after the segment 0.163 -> 0.176 deg,
    # final ATE 0.0253 m) (CHANGELOG be19). Left off at integration (nineteenth session): the quick scan's ratio
    # still misses 1.5 with it, its back-end CPU is the same, and the 600-frame sample's mesh and online ATE got
    # worse (quiet bench pipeline, 2 alternating pairs at load 0.1-1.9: sim_mesh_err_after_mm 0.3988 -> 0.4052 in
    # both; the KITTI clip, real, 0.0252 m in both); be19's exemptions stay for a budget set by hand.
    # be22: 80 with keyframe_obs_redundant_kf 3 (below: over the budget only observations of landmarks that 3
    # observations fix in iSAM2 wait). Measured with both (bench pipeline's runs, nearly deterministic here:
    # every config gave the same keys in 2-4 repeats at load 9-15; one clip run of 8 with these defaults
    # online 0.0755 m, drift 0.560 %, rotation 0.180 deg): the KITTI clip (configs/kitti.yaml, real) final
    # ATE 0.0252 m as before, online 0.0758 -> 0.0754 m, drift after the segment 0.547 -> 0.544 %, rotation after
    # it 0.163 -> 0.166 deg; the 600-frame sample (configs/sim.yaml) final ATE 0.77 -> 0.76 mm, online 10.68 ->
    # 10.88 mm, mesh 0.398833 -> 0.398398 mm. The band of perturbations that should not matter, same runs:
    # backend.worker inline moves the clip's final ATE to 0.0249 m, online 0.0685 m, rotation 0.167 deg, the
    # sample's final 0.82 mm, online 10.37 mm, mesh 0.3937 mm; relinearize_skip 3 the clip's final to 0.0255 m;
    # the budget alone at 120 / 80 the sample's mesh to 0.4052 / 0.3913 mm, online 10.77 / 10.90 mm, the clip's
    # final 0.0252 / 0.0258 m. rounds_1800 call stream replayed (jemalloc, gc frozen): re-eliminated variables
    # last block / first 1.83 -> 1.51, online keyframe ATE 10.082 -> 10.052 mm; rounds_5400: back-end CPU
    # 7.9 -> 6.7 s. bench scale --quick live (5 alternating pairs, load 10-17): backend_ms_last_over_first
    # median 1.772 -> 1.536 (1.619-1.822 -> 1.507-1.577), last block 23.1 -> 19.8 ms, ATE after 0.00082-0.00083
    # -> 0.00083-0.00084 m; full scale one pair (load 13-16) 1.617 -> 1.464; sim150 mesh 0.346775 -> 0.349210 mm
    # (inline 0.353606), orbit300 mesh 0.334023 -> 0.326601 mm (CHANGELOG be22)
    keyframe_obs_budget: int = Field(
        80, ge=0, le=100000, description="observations of landmarks in the graph a keyframe's update takes (0: all)"
    )
    # be22 (issue 33): ORB-SLAM's redundancy rule for observations rather than keyframes: a keyframe's
    # monocular observation of a window landmark that this many observations already fix in iSAM2 may wait
    # outside it for the final estimate (keyframe_obs_overflow) once the update holds keyframe_obs_budget, the
    # others always entering; without a budget it does nothing. A revisit's and a resumed keyframe's never wait
    # (0: any observation may). Measured alone (every redundant one held back, no budget; not a form the code
    # offers any more) at 3 it cost the KITTI clip (configs/kitti.yaml,
    # real): final ATE 0.0252 -> 0.0265 m, drift after the segment 0.547 -> 0.623 % (4: 0.0256 m, 0.593 %), the
    # 600-frame sample's online ATE 10.68 -> 11.53 mm, though the quick scan's ratio fell less than with the
    # budget (live 1.683 / 1.758 -> 1.624 / 1.603); with the budget (80) it binds mostly on the rounds scan's later
    # rounds (measurements above keyframe_obs_budget; CHANGELOG be22)
    keyframe_obs_redundant_kf: int = Field(
        3, ge=0, le=100000, description="over the budget only mono observations of landmarks so fixed wait (0: any)"
    )
    keyframe_obs_overflow: Literal["final", "drop"] = Field(
        "final", description="keyframe_obs_budget: the observations over it join at the final estimate, or are dropped"
    )
    # issue 33: where the back end runs; process: beside the tracker, which never waits for it
    worker: Literal["process", "thread", "inline"] = Field(
        "process", description="process (beside the tracker), thread, or inline (the tracker waits)"
    )
    # kf12 (issue 33): the worker's keyframe updates on a thread of lowered scheduling priority (what the
    # run waits for - the final estimate, landmarks - keeps the run's), so the tracking thread and its keyframe
    # threads get the 2-core machine first. Off: a lagging back end moves the online corrections, and with
    # them the results: KITTI clip (configs/kitti.yaml, full pipeline, 5 alternated pairs at load 9-10) with
    # 10, final ATE 0.0251 -> 0.0215-0.0228 m, drift after the constant-rate segment 0.547 -> 0.566-0.654 %
    # (frame median 72.8 -> 51.2 ms, p95 139.1 -> 132.4 ms). CHANGELOG (kf12)
    worker_nice: int = Field(0, ge=0, le=19, description="lower the worker's update thread's priority by this")
    # issue 33 item 5 (be17): with glibc's allocator the iSAM2 update's CPU per re-eliminated variable
    # doubles over the long scan (rounds_5400 call stream replayed: 14 -> 38 us at the same Bayes-tree
    # size and density); with jemalloc it stays 13-15 us. Replays (rounds_1800 / rounds_5400, load ~5):
    # back-end CPU 3.18 -> 2.26 s / 13.7 -> 7.8 s, last block / first 1.87 -> 1.65 / 3.62 -> 2.54, estimates
    # bit-identical. Only the worker process; without the library (Debian: libjemalloc2) the system's.
    # bench pipeline with it: the KITTI clip (configs/kitti.yaml) and the 600-frame sample (configs/sim.yaml)
    # identical (final ATE 0.0251 m / 0.76 mm, online 0.0758 m / 10.69 mm) (CHANGELOG be17)
    worker_allocator: Literal["system", "jemalloc"] = Field(
        "jemalloc", description="process worker: its memory allocator (jemalloc when installed, else the system's)"
    )


class FrontendConfig(_Section):
    """Stereo keyframe front end: detection, stereo matching, KLT, robust pose, keyframes."""

    # keyframe features (rectified left image)
    max_features: int = Field(800, ge=10, le=100000, description="corners per keyframe (before stereo)")
    grid_cols: int = Field(8, ge=1, le=256, description="detection grid columns (bucketing)")
    grid_rows: int = Field(4, ge=1, le=256, description="detection grid rows (bucketing)")
    gftt_quality: float = Field(0.005, gt=0, lt=1, description="Shi-Tomasi quality, per cell")
    min_distance_px: float = Field(10.0, gt=0, description="minimum corner spacing")
    border_px: int = Field(12, ge=0, le=1000, description="no corners this close to the image border")
    detect_half_resolution: bool = Field(False, description="find corners in the half-size image")
    # stereo row search (rectified pair)
    patch_px: int = Field(11, ge=3, le=101, description="matching window (odd)")
    min_disparity_px: float = Field(1.0, ge=0, description="reject matches below (far points)")
    max_disparity_px: float = Field(160.0, gt=0, description="search range along the row")
    min_zncc: float = Field(0.7, ge=-1, le=1, description="minimum normalised correlation")
    lr_tolerance_px: float = Field(1.0, gt=0, description="left-right consistency tolerance")
    max_row_error_px: float = Field(1.0, ge=0, description="max vertical offset of the match")
    max_depth_m: float = Field(200.0, gt=0, description="reject triangulated points beyond")
    min_stereo_points: int = Field(30, ge=6, le=100000, description="fewest points for a keyframe")
    max_keyframe_points: int = Field(300, ge=0, le=100000, description="keep at most this many (spread); 0: all")
    # KLT
    klt_window_px: int = Field(13, ge=5, le=101, description="Lucas-Kanade window")
    klt_levels: int = Field(3, ge=0, le=10, description="pyramid levels above the base")
    klt_iterations: int = Field(7, ge=1, le=100)
    fb_threshold_px: float = Field(1.0, gt=0, description="forward-backward tolerance")
    # issue 33 (fe9): points of one frame's KLT at the same place moving alike (a local-map point and a
    # later keyframe's corner on the same feature) are searched once, the others moved with it. At 1 px:
    # 14.5 % of the KITTI clip's points (configs/kitti.yaml), 9 % of the realistic orbit's; front-end
    # accuracy within noise on both and the sample scan, but no CPU gain measured (KITTI -0.18 ms a frame,
    # orbit +0.09 ms, replayed KLT calls): off
    klt_share_px: float = Field(0.0, ge=0, le=2, description="KLT points this close (px) share a search; 0 off")
    klt_share_motion_px: float = Field(
        2.0, gt=0, le=10, description="... when their predicted motions also agree to this (px)"
    )
    # orb13 (issue 33): a frame's KLT (7-13 ms on the tracking thread, half its frame on the orbit) split in two
    # halves, the second on a thread beside (OpenCV releases the interpreter lock; each point is searched on its
    # own: the same tracks, bit for bit). 0: one call on the tracking thread. Measured under SCHED_FIFO (the two
    # cores ours) at load 16-18, 3 alternated pairs with the tree before: realistic orbit (datasets/sample/scan.mcap,
    # `bench peer --quick`, 150 frames) mean frame 10.0 -> 8.0 ms (median), with the MCAP and order changes of
    # orb13; KITTI clip (configs/kitti.yaml, `bench pipeline`'s kitti part) p95 23.9 -> 22.0 ms, but the median
    # 11.1 -> 12.5 ms (split off / on alone: 10.8 / 12.8: the second core is busy there), the same poses on
    # both. CHANGELOG (orb13)
    # orb21: off by default. With `opencv_threads` 2 OpenCV splits the one call's points over its own two threads
    # (the caller's and one worker, taking stripes as each is free) and builds each image's pyramid once, where the
    # halves built both pyramids twice: the same tracks (front-end poses identical on the orbit and KITTI), one
    # 420-point orbit KLT in 3.6 ms wall both ways (SCHED_FIFO) at 5.0-5.5 ms of CPU against the halves' 6.8-7.2 ms.
    # Measured with `opencv_threads` below (CHANGELOG orb21).
    klt_split_min_points: int = Field(
        0, ge=0, le=100000, description="a KLT of this many points or more runs in two halves at once; 0 off"
    )
    # robust pose
    pose_loss: Literal["tukey", "huber"] = Field("tukey")
    pose_min_scale_px: float = Field(0.5, gt=0, description="floor of the MAD scale")
    ransac_threshold_px: float = Field(2.0, gt=0)
    prediction_gate_px: float = Field(
        4.0, gt=0, description="prediction good enough to skip RANSAC"
    )
    pose_step_tolerance: float = Field(5e-5, gt=0, description="LM stops below this step (m, rad)")
    pose_max_iterations: int = Field(10, ge=1, le=1000)
    pose_huber_warmup: int = Field(2, ge=0, le=1000, description="Huber IRLS iterations before Tukey")
    pose_reweight_iterations: int = Field(4, ge=1, le=1000, description="IRLS weight updates, then frozen")
    depth_weighting: bool = Field(True, description="down-weight points of uncertain stereo depth")
    disparity_sigma_px: float = Field(0.3, gt=0, description="stereo disparity noise (weighting)")
    # keyframe policy
    min_tracked_fraction: float = Field(0.5, gt=0, le=1, description="new keyframe below this")
    min_tracked: int = Field(100, ge=6, le=100000, description="new keyframe below this many inliers")
    max_parallax_ratio: float = Field(0.25, gt=0, description="translation / median depth")
    max_rotation_deg: float = Field(20.0, gt=0, description="rotation since the keyframe")
    # issue 36 (tail14): the run's last frame, tracked, becomes a keyframe (the pipeline tells the front
    # end which frame is the last); the frames after the policy's last keyframe are then bridged between
    # two keyframes and the last pose is in the final (calibrating) BA. Default config, trajectory_final
    # against ground truth, off / on: 1200-frame modeler scan (30 frames after the last keyframe) drift
    # 0.0051 / 0.00056 %, last-pose rotation error 0.0166 / 0.0058 deg, SE(3) ATE 0.715 / 0.693 mm; orbit
    # sample (configs/sim.yaml, bench pipeline's sim keys) drift 0.033 / 0.018 %, ATE 0.75 / 0.76 mm. Not
    # on the KITTI clip (configs/kitti.yaml: its 1-3-frame tails, the ATE worse). CHANGELOG.md (tail14)
    last_frame_keyframe: bool = Field(True, description="the run's last tracked frame becomes a keyframe")
    # tracking loss
    min_inliers: int = Field(20, ge=6, le=100000, description="LOST below this many inliers")
    max_jump_m: float = Field(0.6, gt=0, description="LOST when the pose departs from the motion model by more")
    max_jump_deg: float = Field(15.0, gt=0)
    min_image_std: float = Field(4.0, ge=0, description="black/flat image threshold (grey levels)")
    min_sharpness: float = Field(20.0, ge=0, description="variance of the Laplacian (blur) threshold")
    max_retrack_frames: int = Field(5, ge=0, le=1000, description="frames to try resuming on the old keyframe")
    # local hybrid keyframe BA (seed 004 eq. 1)
    local_ba: bool = True
    ba_iterations: int = Field(5, ge=1, le=1000)
    ba_huber_px: float = Field(1.0, gt=0)
    ba_final_stereo: bool = Field(False, description="add the final right projections to eq. 1")
    # depth of features without a stereo match (seed-003 observer with the tracker's poses)
    mono_depth: Literal["none", "observer"] = Field("none", description="depth of unmatched corners")
    mono_max_features: int = Field(300, ge=0, le=100000, description="most tracks without stereo depth")
    mono_max_rel_sigma: float = Field(0.1, gt=0, description="converged below this relative depth std")
    mono_min_parallax_deg: float = Field(1.0, ge=0, description="excitation: recent mean parallax")
    mono_sigma_px: float = Field(3.0, gt=0, description="pixel noise of KLT and tracker poses (depth std)")
    keyframe_remeasure: bool = Field(
        True, description="re-measure tracks against the keyframe patch (affine) at a new keyframe"
    )
    remeasure_half_window_px: int = Field(7, ge=2, le=50, description="half size of the re-measured patch")
    remeasure_min_ncc: float = Field(0.8, ge=-1, le=1, description="keep re-measured tracks above this NCC")
    remeasure_max_shift_px: float = Field(2.0, gt=0, description="keep re-measured tracks moved less")
    remeasure_older_keyframes: int = Field(
        1, ge=0, description="also find the points of this many older keyframes in a new keyframe"
    )
    # far points in the pose solve (issue 26, item 4): "bearing" tracks the stereo matches that
    # the disparity gate drops (disparity below min_disparity_px, down to 0, or depth beyond
    # max_depth_m) and, with far_depth_baselines > 0, every point beyond that many baselines
    # (ORB-SLAM's 40), and solves the pose with them as bearings with an inverse-depth prior
    # (at infinity for zero disparity); they never become keyframe landmarks. Measured (front
    # end alone): KITTI clip, configs/kitti.yaml of 0.5 tracked fraction (200 m gate, ~5 dropped matches a keyframe)
    # final rotation error after the ground truth's constant-rate segment 0.232 -> 0.233 deg,
    # with a 25 m gate 0.335 -> 0.294 deg; simulated orbit sample drift 0.944 -> 0.942 %.
    # far_depth_baselines = 40 (ORB-SLAM's) made the KITTI clip worse (0.232 -> 0.313 deg,
    # drift 0.738 -> 0.856 %, 25 -> 43 keyframes): off by default
    far_points: Literal["drop", "bearing"] = Field("bearing", description="far stereo matches: drop, or bearings")
    far_depth_baselines: float = Field(0.0, ge=0, description="'bearing': also points beyond this many baselines")
    far_max_points: int = Field(100, ge=0, le=100000, description="most far bearings per keyframe (spread)")
    # keyframe policy that adapts to the motion (issue 26, item 3): "angle" compares the median
    # change of the tracked points' viewing angles with atan(max_parallax_ratio) instead of the
    # translation with max_parallax_ratio x the median depth. Measured (front end alone,
    # translation -> angle): KITTI clip unchanged (the tracked fraction triggers every keyframe
    # there: points leave the image; 25 keyframes), simulated orbit drift 0.94 -> 0.87 % (19 -> 20
    # keyframes), simulated modeler scan (400 frames) mean rotation error 2.21 -> 2.08 deg, mean
    # position error 24.8 -> 23.3 mm (34 keyframes). But with the whole pipeline, the seeded
    # 400-frame realistic orbit of tests/test_sim_realism.py closes no loop with "angle" (0 loops,
    # ATE 13.5 -> 13.0 mm) where "translation" closes it (1 loop, ATE 13.8 -> 1.06 mm): the
    # keyframe times move and the revisit keyframe no longer sees the first one. So the
    # default stays "translation" until the loop stage is robust to it.
    keyframe_parallax: Literal["translation", "angle"] = Field(
        "translation", description="parallax test of the keyframe policy"
    )
    # local-map tracking (issue 36, item 2): the points of this many earlier keyframes' sets stay
    # tracked (KLT from frame to frame, started at their projection with the predicted pose) and
    # in each frame's robust pose, carried through the keyframe poses, with the depths the local BA
    # refined and their own depth weights; each new keyframe observes them (the back end's
    # landmarks then span up to that many more keyframes), measured again against their own
    # keyframe's patch with local_map_remeasure (without it the KLT-chained positions bent the
    # rotation: KITTI clip rotation error after the ground truth's constant-rate segment 0.178 ->
    # 0.233 deg). Measured, full pipeline, peer.py eval of trajectory_final, 0 -> 4 with remeasure:
    # KITTI clip (configs/kitti.yaml) rotation error after the segment 0.178 -> 0.144 deg, Sim(3)
    # ATE 20.7 -> 17.5 mm, SE(3) ATE 0.102 -> 0.105 m, drift 1.02 -> 1.05 % (0.754 -> 0.755 % after
    # the segment); realistic modeler scan (first 400 frames) drift 0.27 -> 0.11 %, rotation error
    # 1.20 -> 0.55 deg, SE(3) ATE 3.2 -> 2.7 mm; realistic orbit sample (first 300 frames) rotation
    # error 1.81 -> 1.54 deg, drift 0.85 -> 0.88 %, SE(3) ATE 2.8 -> 3.4 mm. 8 keyframes: about the
    # same (KITTI 0.143 deg, modeler 0.51 deg, orbit identical). The cost: KITTI CPU per frame
    # +20 % in alternated full runs (35.6/40.8/36.3 -> 42.8/50.0 ms), front end alone 16.3 -> 22.6
    # ms; `bench peer` has the ratios to ORB-SLAM3 (issue 36: they miss the 0.5x target). 0: off.
    local_map_keyframes: int = Field(4, ge=0, le=100, description="earlier keyframes whose points the pose keeps using")
    local_map_remeasure: bool = Field(
        True, description="measure the local map's points in a new keyframe against their own keyframe's patch"
    )
    # a wider local BA (issue 36, item 4): the hybrid BA closing a keyframe set also takes the
    # points of this many local-map sets seen in the new keyframe, with their stereo observations
    # in their own (fixed) keyframes. 0: the two-keyframe BA of seed 004. Measured (issue 36, acc4;
    # full pipeline, peer.py eval of trajectory_final, 0 / 2 / 4 / 8 with local_map_keyframes 8):
    # KITTI clip (configs/kitti.yaml) SE(3) ATE 0.045 / 0.047 / 0.068 / 0.081 m, drift after the
    # ground truth's constant-rate segment 0.551 / 0.581 / 0.657 / 0.690 %, rotation error after
    # it 0.151 / 0.159 / 0.161 / 0.150 deg; the street scene of tests/test_street_scale.py
    # exported to KITTI layout (configs/kitti.yaml) Sim(3) ATE 0.022 / 0.026 / 0.036 / 0.038 m,
    # SE(3) 0.116 / 0.047 / 0.148 / 0.221 m, step-scale growth 1.004 / 0.991 / 0.983 / 0.980;
    # realistic orbit sample, first 150 frames (5 keyframes): drift 0.720 / 0.724 / 0.717 / 0.717 %;
    # first 300 frames (11 keyframes), 0 / 2 / 4: drift 0.872 / 0.843 / 0.844 %, rotation error
    # 1.517 / 1.520 / 1.508 deg, SE(3) ATE 3.68 / 3.50 / 3.47 mm.
    # The wider BA does not pay on the KITTI clip (the window's keyframes are held fixed: their
    # pose errors enter the new keyframe's): 0 stays.
    local_ba_keyframes: int = Field(0, ge=0, le=100, description="local-map sets added to the keyframe BA")
    # robust stereo matching (issue 36, items 1 and 3; frontend/stereo.py, frontend/tracker.py).
    # Measured, front end alone, these five defaults against all off (SE(3) / Sim(3) ATE): KITTI
    # clip (configs/kitti.yaml) 0.100 / 0.021 -> 0.036 / 0.023 m, Sim(3) scale 0.9945 -> 0.9984 (a
    # disparity offset of about 0.07 px estimated), rotation error after the ground truth's
    # constant-rate segment 0.166 -> 0.280 deg (worse); simulated street scans of sim/street.py
    # (configs/kitti.yaml): near street 0.034 / 0.017 -> 0.070 / 0.019 m (worse; Sim(3) scale
    # 0.998 -> 0.996, offset estimated -0.015 px where it is 0), open highway 0.167 / 0.154 ->
    # 0.150 / 0.082 m, the view opening 0.083 / 0.083 -> 0.081 / 0.072 m, the same with a 0.5 px
    # right-camera principal-point error
    # 2.72 / 0.58 -> 0.055 / 0.037 m (per-step scale growth 1.061 -> 0.998); realistic orbit sample,
    # 600 frames (configs/sim.yaml): SE(3) ATE 13.0 -> 4.3 mm, drift 0.94 -> 0.34 %, rotation error
    # 3.54 -> 1.24 deg (offset 0.40 px estimated: its recorded calibration is off); a realistic
    # 150-frame scan (onepass's scan150): SE(3) ATE 11.7 -> 6.7 mm, drift 0.88 -> 0.57 %, rotation
    # error 3.37 -> 2.15 deg
    stereo_subpixel: Literal["parabola", "gradient", "gradient_2d"] = Field(
        "gradient",
        description="sub-pixel disparity: parabola through 3 ZNCC scores, 1-D Lucas-Kanade, or 2-D (the row too)",
    )
    stereo_uniqueness: float = Field(
        0.05, ge=0, le=2, description="ZNCC margin of the best over the second-best peak along the row; 0: off"
    )
    disparity_sigma_source: Literal["constant", "match"] = Field(
        "match", description="disparity std in the pose weights and the local BA: disparity_sigma_px, or per match"
    )
    # moving_gate (issue 36, acc3): a static point whose stereo depth is off drifts along its
    # epipolar line as the camera moves; the gate first takes out of the running mean residual what
    # a depth error within moving_gate x the point's depth sigma explains. Measured, depth-explained
    # part kept -> taken out: KITTI clip (configs/kitti.yaml, full pipeline, peer.py eval) rotation
    # error after the ground truth's constant-rate segment 0.211 -> 0.151 deg, drift after it
    # 0.559 -> 0.551 %, SE(3) ATE 0.044 -> 0.045 m (front end alone 0.265 -> 0.201 deg; the gate
    # off: 0.171); realistic orbit sample (first 150 frames, full pipeline) rotation error 0.897 ->
    # 0.865 deg, drift 0.766 -> 0.718 %, SE(3) ATE 1.01 -> 0.98 mm; a 150-frame realistic orbit
    # that closes its loop rotation error 0.113 -> 0.054 deg, drift 0.038 -> 0.020 %, SE(3) ATE
    # 2.79 -> 3.25 mm (Sim(3) 0.87 -> 0.76 mm); simulated street scans (sim/street.py, 50 frames
    # at 2 m, car ahead at 0.97 of our speed, configs/kitti.yaml, front end) seed 7 rotation
    # 0.275 -> 0.255 deg, drift 0.36 -> 0.39 %, SE(3) ATE 0.077 -> 0.086 m; seed 3 0.396 -> 0.382
    # deg, 1.233 -> 1.228 %, 0.385 -> 0.380 m; the slow loop test's scan: mesh after the loop 1.86 mm
    moving_gate: float = Field(
        3.0, ge=0, description="drop a track whose running mean residual exceeds this x the frame's scale; 0: off"
    )
    moving_radius_px: float = Field(12.0, gt=0, description="a new keyframe takes no point this near a moving track")
    # disparity_offset: not a code default (integration, third wave). The offset is corrected as it
    # converges, so keyframes before and after see different depth scales, and a loop closure cannot
    # reconcile them: the realistic 400-frame orbit of tests/test_sim_realism.py (400 x 300, seed 5),
    # estimate -> none: dead reckoning ATE 5.17 -> 14.3 mm, after the closure 1.88 -> 1.71 mm, mesh
    # after closure 3.03 -> 1.78 mm (ground-truth-pose floor 1.95 mm; with the estimate the mesh after
    # closing was worse than before it, 2.79 mm). On the KITTI clip (no loop) the estimate is the
    # preset's (configs/kitti.yaml), where it took SE(3) ATE 0.103 -> 0.045 m.
    disparity_offset: Literal["none", "estimate"] = Field(
        "none", description="estimate a constant disparity offset in the local BA and correct new matches by it"
    )
    # issue 33: at a keyframe the new set's detection and stereo matching and the local map's and
    # older keyframes' re-measurements (GIL-releasing numpy and OpenCV calls) run on threads beside
    # the outgoing set's closing and local BA on the tracking thread. The same poses either way
    # (bit-identical: KITTI clip, orbit sample); the tracking thread's CPU in a keyframe frame, front
    # end alone: KITTI clip (configs/kitti.yaml) 140 -> 40 ms, orbit sample (configs/sim.yaml) 236 ->
    # 80 ms; all threads' CPU about the same (CHANGELOG.md, issue 33)
    keyframe_stereo: Literal["thread", "inline"] = Field(
        "thread", description="a new keyframe's stereo matching: on a thread beside the local BA, or inline"
    )
    # fe8 (issue 33): a frame expected to make a keyframe (the policy run one frame ahead) starts its
    # corner detection and stereo matching beside its own KLT and pose (keyframe_stereo: thread); a
    # false expectation drops them. The same poses and stereo points (bit-identical, front end alone
    # on the KITTI clip). Off: no gain measured. Full pipeline, KITTI clip (configs/kitti.yaml), under
    # SCHED_FIFO at load 12.4-12.9, 3 alternated rounds on / off: kitti_frame_ms_p95 44.7, 45.6, 43.7 /
    # 41.8, 44.1, 43.0 ms (both cores are busy in a keyframe frame already; the thread's start waited
    # up to 28 ms for the interpreter). CHANGELOG.md (fe8)
    keyframe_match_ahead: bool = Field(
        False, description="an expected keyframe's corners and stereo matches made beside its frame's tracking"
    )
    # issue 33: the local BA of a keyframe's interval on a thread beside the pipeline's end of that
    # frame and the next frame's reading; taken between frames with the keyframe's hand-off to the loop
    # stage and back end (fe5: the inline order and results). Full pipeline, on / off: KITTI clip
    # (configs/kitti.yaml) trajectory_final ATE 0.0427 / 0.0427 m, drift and rotation after the ground
    # truth's constant-rate segment 0.531 / 0.531 %, 0.138 / 0.138 deg; orbit sample (configs/sim.yaml)
    # final ATE 2.87 / 2.87 mm; KITTI: the tracking thread's CPU in a keyframe frame 12-14 / 19-22 ms,
    # kitti_frame_ms_p95 37.9 / 42.0 ms (4 alternating pairs, load 2.7-3). CHANGELOG.md (issue 33, fe5)
    local_ba_beside: bool = Field(True, description="run the local BA beside the tracking, taken between frames")
    # fe7 (issues 33, 36): OpenCV's own worker threads (two on the 2-core machine) split each KLT, remap
    # and corner detection, but the keyframe work already keeps both cores busy from Python threads and
    # OpenCV's workers wait actively. One: the same poses, less CPU. Front end alone on the KITTI clip
    # (configs/kitti.yaml), CPU per frame 2 / 1 thread(s), 2 alternated pairs of 2 passes at load 11-13:
    # 31.9, 30.7, 31.0, 28.1 / 28.5, 28.2, 26.9, 26.9 ms; full pipeline, KITTI clip (3 alternated rounds,
    # SCHED_FIFO at load 17) CPU per frame median 47.3 / 41.4 ms, p95 51.4 / 49.2 ms, final ATE 0.0427 m
    # both; realistic orbit sample (configs/sim.yaml, first 200 frames, 2 rounds at load 17-20) CPU per frame
    # 25.7, 24.6 / 29.1, 24.3 ms (noise), final ATE 1.336 mm both. CHANGELOG.md (fe7)
    # orb21 (issue 33): 2, with `klt_split_min_points` 0: the tracking thread's KLT now splits its points in
    # OpenCV's own two threads (above). Realistic orbit (datasets/sample/scan.mcap, bench peer's configuration):
    # `_Run.step` mean under SCHED_FIFO, 6 alternated pairs, lower in each by 0.08-0.33 ms (median -4.0 %), the
    # run's process CPU 13.3 -> 13.05 and 15.1 -> 14.8 ms a frame, identical poses; bench peer's mean frame quiet
    # (load 1-2.6, 3 pairs) 7.59 -> 7.26 ms, ratio to ORB-SLAM3's 0.512 -> 0.490; at load 6-12 19.0 -> 16.3 ms.
    # KITTI clip (configs/kitti.yaml, real): the front end alone identical with 1 and 2 threads, the full
    # pipeline identical with `backend.worker: inline`; with the worker process its final ATE follows which
    # back-end estimate each keyframe finds finished (0.0219-0.0270 m over 7 runs, median 0.0252; main 0.0252),
    # process CPU within noise (23.2, 24.3 / 24.5, 21.6 ms a frame at load 5). CHANGELOG (orb21)
    opencv_threads: int = Field(
        2, ge=0, le=256, description="at most this many OpenCV threads in the process (0: OpenCV's own count)"
    )
    # kf12 (issue 33): in a keyframe frame three threads of the run take turns on the interpreter lock (the
    # tracking thread's compiled and OpenCV calls, the keyframe threads' stereo set and re-measurements); each
    # return from a call that released it waited up to Python's 5 ms interval for a thread running Python.
    # Process-wide, only ever lowered (as opencv_threads). Full pipeline, 5 ms (base) vs 0.5, the same results
    # (ATE, drift, mesh error): KITTI clip (configs/kitti.yaml, real; 4 alternated pairs at load 12-14) frame
    # p95 148.9 -> 145.0 ms, max after the first 182.6 -> 169.8, median 68.3 -> 64.9; orbit sample
    # (configs/sim.yaml, 200 frames; 4 pairs at load 10-12) p95 67.2 -> 52.1 ms (lower in 4 of 4), max
    # after warm-up 157 -> 111, median 19.0 -> 14.8; on a quiet machine (load 2-3) within noise. CHANGELOG (kf12)
    gil_switch_interval_ms: float = Field(
        0.5, ge=0, le=100, description="lower the interpreter's switch interval to this (ms; 0: Python's own)"
    )


class MappingConfig(_Section):
    """Laser-stripe integration and open3d meshing (lengths in metres, world frame)."""

    # sdf16 (issue 32): the final mesh by the signed-distance surface (mapping/meshing._sdf) instead of screened
    # Poisson (the live mesh: live_method). The same
    # captured final clouds (configs/sim.yaml runs), Poisson -> sdf (with normal_radius_m 0.012): mesh error against
    # scene.ply / completeness of the object, 150-frame realistic orbit 0.418 -> 0.350 mm / 0.917 -> 0.933; the
    # 600-frame sample 0.419 -> 0.402 mm / 0.979 -> 0.982; 300-frame orbit 0.387 -> 0.332 mm / 0.972 -> 0.975; the
    # mesh call on the 150-frame orbit's cloud 4.0x faster (wall; CPU 2.07 -> 0.47 s). The KITTI clip has no laser
    # (no mesh). The real turntable scan keeps Poisson (turntable/run.py; no surface truth there): the sdf's mesh
    # lies farther from its points (mean 0.228 -> 0.279 mm) with a few small holes. CHANGELOG (sdf16)
    method: Literal["poisson", "sdf", "ball_pivoting"] = Field(default="sdf", description="surface method")
    write_mesh: bool = Field(True, description="the pipeline writes mesh.ply (its errors: the evaluation after a run)")
    voxel_m: float = Field(default=0.0015, gt=0, description="voxel down-sampling size before meshing")
    # sdf16: 6 -> 12 mm. Where the stripes are sparse (fewer than 10 samples within 6 mm) the 6 mm neighbourhood
    # holds one stripe and its normal is a guess: against scene.ply's normals (150-frame realistic orbit's final
    # cloud) median error 26 / 20 deg there, 5.1 deg overall; with 12 mm 1.5 / 1.8 deg, 1.8 deg overall (the 20
    # nearest within the radius: the same cost). Poisson's mesh error with it: 150-frame orbit 0.418 -> 0.354 mm,
    # sample 0.419 -> 0.399 mm, 300-frame orbit 0.387 -> 0.329 mm, completeness 0.917 -> 0.925, equal, 0.972 ->
    # 0.972. The real turntable scan (Poisson): nearly the same mesh, 17,631 -> 17,627 vertices, the same distances
    # of its points to it (dense stripes: the 20 nearest are within 6 mm)
    normal_radius_m: float = Field(default=0.012, gt=0, description="neighbourhood radius for normals")
    normal_max_nn: int = Field(default=20, ge=3, description="max neighbours for normals")
    line_ratio: float = Field(
        default=0.003, ge=0, lt=1, description="eigenvalue ratio below which a neighbourhood is a line"
    )
    poisson_depth: int = Field(default=0, ge=0, le=12, description="octree depth; 0 = from voxel_m")
    # issue 32: the final mesh was most of the time after the last frame. Octree cells of about 2 x
    # voxel_m instead of 1 x (octree depth 9 -> 8; 150-frame realistic orbits of the bust / of the
    # box, their final trajectories, one Poisson thread): CPU 12.1 -> 5.7 s / 12.4 -> 6.0 s, mesh
    # error against scene.ply 3.36 -> 3.09 mm / 1.783 -> 1.784 mm, completeness 0.156 -> 0.153 /
    # 0.358 -> 0.340 (the KITTI clip has no laser: no mesh). Real laser data: the shared turntable
    # scan (every other frame, its own pipeline) has no surface truth; there 2 x voxel_m cells take its
    # mesh from 18,012 to 4,537 vertices (35,426 -> 8,692 triangles) with the same stripe points, so the
    # turntable keeps 1 (turntable/run.py). Not measured on a real hand-held laser scan (none shared).
    poisson_cell_voxels: float = Field(
        default=2.0, ge=0.5, le=8.0,
        description="Poisson's finest octree cell (its derived depth) and the sdf's grid cell, in voxel_m",
    )
    poisson_max_depth: int = Field(default=10, ge=4, le=12, description="cap on the derived depth")
    poisson_scale: float = Field(default=1.1, gt=1.0, description="bounding cube / samples' box")
    poisson_linear_fit: bool = True
    density_quantile: float = Field(
        default=0.02, ge=0, lt=1, description="trim vertices below this density quantile"
    )
    trim_distance_m: float = Field(
        default=0.0, ge=0, description="drop vertices farther from the samples; 0 = 2.5 x voxel_m"
    )
    # sdf16 (issue 32): the signed-distance surface (method sdf) on the grid of Poisson's finest cell. Reach 3 and
    # sigma 1.5 cells: on the 150-frame orbit completeness 0.931 (reach 2, sigma 1: 0.87-0.91 by the weight floor).
    # The five values below chosen on the 150-frame realistic orbit's final cloud, then measured unchanged on the
    # 600-frame sample and the 300-frame orbit (method's comment above) and on the real turntable scan (its points
    # 0.279 mm from the mesh on average against Poisson's 0.228, a few small holes; CHANGELOG sdf16)
    sdf_reach_cells: float = Field(
        default=3.0, gt=0.5, le=6.0, description="sdf: a sample's plane distance reaches corners this many cells away"
    )
    sdf_sigma_cells: float = Field(default=1.5, gt=0, description="sdf: Gaussian weight's sigma, cells")
    sdf_min_weight: float = Field(
        default=0.5, ge=0, description="sdf: a grid corner has a value from this summed weight on"
    )
    sdf_min_component_cells: float = Field(
        default=50.0, ge=0, description="sdf: drop connected pieces of a smaller area than this many cells' faces"
    )
    sdf_project_steps: int = Field(
        default=1, ge=0, le=5, description="sdf: Newton steps of each vertex onto the field evaluated at it"
    )
    bpa_radii_m: list[float] = Field(
        default_factory=list, description="ball-pivoting radii; empty = 1.5, 3, 6 x voxel_m"
    )
    max_stripe_gap_ns: int = Field(
        default=200_000_000, ge=0, description="widest frame interval a stripe is interpolated in"
    )
    live_mesh_every_kf: int = Field(
        default=0, ge=0, description="during a run, re-mesh the live mesh's changed blocks every N keyframes; 0 = off"
    )
    # issue 33: open3d's reconstruction holds the interpreter lock, so a thread stalls tracking
    live_mesh_worker: Literal["process", "thread"] = Field(
        default="process", description="where live-mesh updates run: process (tracking never stalls) or thread"
    )
    # tail11 (issues 32, 33): a live update takes a core for 0.3-1 s (the 300-frame realistic orbit: 15 ms of
    # CPU a frame); at normal priority it took the core of the tracking thread's keyframe work. Measured
    # in CHANGELOG (tail11). A scheduling priority, not a data-dependent setting; KITTI has no laser data
    live_mesh_nice: int = Field(
        default=10, ge=0, le=19, description="live-mesh updates run this much below the run's priority (0 = same)"
    )
    # sdf16 kept Poisson for the live mesh: at the live settings (3 mm voxels and cells) the sdf of then covered
    # less of the object (150-frame realistic orbit's final cloud meshed whole: completeness 0.975 -> 0.806).
    # live19 (issue 33): the sdf of now (fin18's normals) at the same settings, every block of the run's stripes
    # placed with its final trajectory, against scene.ply / the object: 150-frame realistic orbit error
    # 0.376 -> 0.381 mm, completeness 0.977 -> 0.972; the 600-frame sample 0.516 -> 0.406 mm, 0.988 -> 0.986;
    # the sample's live updates (captured blocks) 2.6 -> 0.6 s CPU: its worker took the tracking thread's core
    # (`bench peer` orbit, 4 pairs: our workers' CPU 20.6 -> 17.6 ms a frame; CHANGELOG live19). Laser meshing
    # only: the KITTI clip (real) has no laser data, and no real laser scan runs through the pipeline
    live_method: Literal["poisson", "sdf", "ball_pivoting"] = Field(
        default="sdf", description="surface method of the live mesh's updates"
    )
    live_voxel_m: float = Field(
        default=0.003, gt=0, description="voxel size of the live mesh (coarser than voxel_m: faster updates)"
    )
    # finish8 (issue 32): the final mesh in the live mesh's worker process when it is idle at the last
    # frame, while the run's process makes the session map. No gain measured on the loaded machine
    # (150-frame orbit, 7 alternating pairs at load 8-18: wall over frames median 1.601 off / 1.689 on,
    # KITTI, whose finish it does not touch, 1.194 / 1.235 in the same pairs: the noise). On by default
    # since finish10: the run's process then imports open3d (0.85 s CPU, holding the interpreter) while
    # the worker meshes, instead of beside the final refinement, whose Python it slows on a quiet machine;
    # the same mesh (tests/test_finish_interrupt.py). Measured in CHANGELOG (finish10); integration (tenth
    # session), 150-frame orbit in fresh processes, 3 pairs off / on: wall over frames 1.844 / 1.913, 1.883 / 1.787,
    # 1.949 / 2.111 (noise). KITTI (real) has no laser mesh: untouched; no real laser scan measured
    final_mesh_in_live_worker: bool = Field(
        default=True, description="make the final mesh in the live mesh's worker process when it is idle"
    )
    # finish11 (issue 32): the final mesh started in the mesh's process as soon as the keyframes and the
    # stripes are refined, while this process re-solves the frames between keyframes; its vertices then
    # moved as the stripe points moved (mapping/final.VertexMover: median 0.31-0.36 mm, at most
    # 2.7-3.5 mm). Mesh against scene.ply, the same captured finish meshed both ways: 150-frame
    # realistic orbit 0.42384 -> 0.42290 mm, completeness 0.9161 -> 0.9165; the 600-frame sample
    # 0.45131 -> 0.45117 mm, 0.97872 -> 0.97896. Measured on simulated laser scans only (no real laser
    # scan is shared). Without laser stripes (the KITTI clip, real) it is a no-op: no mesh process, no
    # early mesh; fin12: KITTI's trajectory_final.tum bit-identical with it on, off, on (configs/kitti.yaml)
    final_mesh_before_resolve: bool = Field(
        default=True, description="start the final mesh before the frames' re-solve and move it after (needs a"
        " mesh process: final_mesh_in_live_worker)"
    )
    # mesh14 (issue 32): the live mesh's update still running at the last frame (niced; 1.8-6 s long on the
    # 150-frame realistic orbit) held the final mesh up until it ended. Measured (`bench pipeline`, 3 alternated
    # pairs, load 3-5) on the 150-frame realistic orbit (mesh step 3.86 -> 2.17 s) and the 300-frame one
    # (wall / frames 1.60 -> 1.51), mesh errors identical; no real laser-line sequence runs through the
    # pipeline (the KITTI clip has no laser: unaffected). CHANGELOG (mesh14)
    final_mesh_in_helper_when_busy: bool = Field(
        default=True, description="the live mesh's worker busy at the last frame: the final mesh in the idle laser"
        " extraction process (open3d imported there beside the refinement), the live update ended"
    )
    # 1 by default: Open3D's multi-threaded Poisson segfaults at random (Open3D issue #6828; here once
    # in the final mesh of tests/test_one_pass.py under load 22), and a crash loses the whole run
    poisson_threads: int = Field(
        default=1, ge=0, description="threads of a Poisson reconstruction; 0 = all cores (may crash: Open3D #6828)"
    )
    chunk_m: float = Field(default=0.05, gt=0, description="block edge of the chunked live mesh")
    min_points: int = Field(default=100, ge=4, description="fewest points a surface is made from")
    laser_plane_point_in_cam_m: list[float] = Field(
        default_factory=lambda: [0.12, 0.0, 0.0],
        min_length=3,
        max_length=3,
        description="a point of the calibrated light plane (left-camera frame)",
    )
    laser_plane_normal_in_cam: list[float] = Field(
        default_factory=lambda: [0.977, 0.0, 0.213],
        min_length=3,
        max_length=3,
        description="normal of the calibrated light plane (left-camera frame)",
    )
    peak_min_contrast: float = Field(
        default=20.0, ge=0, description="laser line: min peak above the background (grey levels)"
    )
    # issue 17: 4 (was 3) with peak_smooth_along_px and peak_local_background below
    peak_window_px: int = Field(default=4, ge=1, description="laser line: half-width of the window")
    peak_method: Literal["cog", "gauss"] = Field(default="cog", description="sub-pixel method")
    peak_axis: Literal["columns", "rows"] = Field(
        default="rows", description="one peak per image row (vertical line) or column"
    )
    # issue 17: a Gaussian along the laser line before the peak search (averages the speckle of
    # neighbouring profiles) and the background under the peak from the samples beside the window
    # (texture under a dim line). Measured with window 4: realistic simulated modeler (every 20th
    # laser image) p95 0.380 -> 0.185 px against the true stripe; the real turntable chessboard
    # images (shared/data/turntable_laser/laser_calibration) laser-plane fit RMS 0.145 -> 0.134 mm
    peak_smooth_along_px: float = Field(
        default=1.5, ge=0, le=10, description="laser line: Gaussian sigma (px) along the line; 0 = off"
    )
    peak_local_background: bool = Field(
        default=True, description="laser line: background under the peak from the samples beside the window"
    )
    # issue 17 (demo engineer): refine each peak across the line (along its local normal, averaged
    # along the line) instead of along the image row; the per-row peak is skewed where the line is
    # oblique. Measured p95 against the true stripe, realistic orbit 0.238 -> 0.175 px, modeler_1200
    # 0.187 -> 0.155 px; real turntable chessboard images (shared/data/turntable_laser/laser_calibration,
    # these peak settings) laser-plane fit RMS 0.1344 -> 0.1326 mm
    peak_across_line: bool = Field(
        default=True, description="laser line: refine each peak across the line (local normal)"
    )


# ----------------------------------------------------------------------------- simulation (issue 3)

    @model_validator(mode="after")
    def _positive_radii(self) -> MappingConfig:
        # a negative or zero ball-pivoting radius makes Open3D fail deep inside the mesher
        if any(not (0 < r < 1e3) for r in self.bpa_radii_m):
            raise ValueError(f"bpa_radii_m: every radius must be in (0, 1000) metres, got {self.bpa_radii_m}")
        return self


class SimCameraConfig(_Section):
    """Rectified stereo pair of the simulator (pixels, metres).

    ``xi > 0`` renders the unified central model (omnidirectional). Principal point defaults to the
    image centre.
    """

    width_px: int = Field(640, gt=0, le=8192)
    height_px: int = Field(480, gt=0, le=8192)
    fx_px: float = Field(500.0, gt=0)
    fy_px: float | None = Field(None, gt=0, description="defaults to fx_px")
    cx_px: float | None = Field(None, description="defaults to (width_px - 1) / 2")
    cy_px: float | None = Field(None, description="defaults to (height_px - 1) / 2")
    xi: float = Field(0.0, ge=0, description="unified-model mirror parameter; 0 is a pinhole")
    baseline_m: float = Field(0.06, gt=0, description="left-to-right camera distance along x")
    # rosbag (issue 25): render raw equidistant (Kannala-Brandt) fisheye images with these
    # k1..k4; the calibration is then unrectified with camera_model "equidistant"
    fisheye_k: list[float] | None = Field(None, min_length=4, max_length=4, description="k1..k4; None: pinhole")


class SimSceneConfig(_Section):
    """The scanned object on a table in a room."""

    kind: Literal["bust", "box", "mix"] = "bust"
    object_height_m: float = Field(0.5, gt=0.05, le=2.0)
    room: bool = Field(True, description="table legs, floor, walls, shelves around the table")
    texture_size_px: int = Field(2048, ge=64, le=8192, description="side of each procedural texture")
    seed: int | None = Field(None, description="seed of the object and room (None: the simulation's seed)")


class SimRenderConfig(_Section):
    """Image formation: Lambertian shading, light, exposure, noise, blur."""

    noise_sigma: float = Field(2.0, ge=0, description="Gaussian image noise (grey levels of 255)")
    ambient: float = Field(0.3, ge=0, le=1, description="ambient share of the lighting")
    brightness: float = Field(1.0, gt=0, description="global gain")
    light: Literal["fixed", "moving", "headlamp"] = "moving"
    light_position_m: list[float] = Field(default_factory=lambda: [0.4, -0.6, 1.4], min_length=3, max_length=3)
    light_motion_radius_m: float = Field(0.3, ge=0, description="'moving': circle radius")
    light_period_s: float = Field(40.0, gt=0, description="'moving': time of one light circle")
    exposure_s: float = Field(0.004, ge=0, description="exposure time for motion blur")
    motion_blur: bool = True
    exposure_variation: float = Field(0.0, ge=0, lt=1, description="relative gain wander")


class SimTrajectoryConfig(_Section):
    """Hand-held path around the object (world z up, object on the table at the origin)."""

    kind: Literal["orbit", "sweeps", "browse", "modeler", "rounds"] = "orbit"
    frames: int = Field(600, gt=0, le=1000000)
    rate_hz: float = Field(25.0, gt=0)
    radius_m: float = Field(0.65, gt=0, description="camera distance from the object axis")
    height_m: float = Field(0.35, description="camera height above the table")
    sweeps: int = Field(3, ge=1, le=1000, description="'sweeps': back-and-forth sweeps; 'rounds': rounds")
    shake_translation_m: float = Field(0.002, ge=0)
    shake_rotation_deg: float = Field(0.3, ge=0)
    start_time_ns: int = Field(1_000_000_000, ge=0)
    start_azimuth_deg: float | None = Field(None, description="azimuth of the path's start (None: drawn from the seed)")


class SimLaserConfig(_Section):
    """Laser-stripe profiler: a light plane fixed in the left-camera frame."""

    enabled: bool = True
    origin_in_cam_m: list[float] = Field(
        default_factory=lambda: [0.12, 0.0, 0.0], min_length=3, max_length=3,
        description="laser 12 cm right of the left camera",
    )
    normal_in_cam: list[float] = Field(
        default_factory=lambda: [0.977, 0.0, 0.213], min_length=3, max_length=3,
        description="vertical plane crossing the optical axis about 0.55 m ahead",
    )
    fan_deg: float = Field(70.0, gt=0, lt=180)
    rays: int = Field(640, ge=2, le=100000)
    range_noise_m: float = Field(0.0002, ge=0)
    max_range_m: float = Field(1.2, gt=0, description="measuring range: farther points are not reported")
    image: bool = Field(False, description="also write /laser/image")


class SimFaultsConfig(_Section):
    """Faults on demand; frame indices count generated frames from 0, ranges are inclusive."""

    dropped: list[int] = Field(default_factory=list)
    blackout: list[tuple[int, int]] = Field(default_factory=list)
    blur: list[tuple[int, int]] = Field(default_factory=list)
    occluder: list[tuple[int, int]] = Field(default_factory=list)
    duplicate_timestamp: list[int] = Field(default_factory=list)
    blur_length_px: float = Field(15.0, gt=0)


class SimRealismConfig(_Section):
    """Realistic sensor, optics, laser and motion (issue 17).

    ``clean`` is the ideal world of issue 3. Magnitudes and their sources:
    ``loopmodel/sim/sensor.py`` (image), ``loopmodel/sim/laser.py`` (laser),
    ``loopmodel/sim/trajectory.py`` (motion).
    """

    level: Literal["clean", "realistic"] = "clean"
    # sensor: Sony IMX250 EMVA 1288 figures (see loopmodel/sim/sensor.py)
    full_well_e: float = Field(10700.0, gt=0, description="saturation capacity (electrons)")
    read_noise_e: float = Field(2.9, ge=0, description="temporal dark noise (electrons)")
    prnu: float = Field(0.006, ge=0, description="photo-response non-uniformity (relative)")
    dsnu_e: float = Field(1.5, ge=0, description="dark-signal non-uniformity (electrons)")
    adc_bits: int = Field(12, ge=8, le=16)
    gamma: float = Field(0.7, gt=0, le=1.5, description="8-bit output = 255 (DN / DN_max)^gamma")
    light_e_per_s: float = Field(1.8e6, gt=0, description="photo-electrons per second at radiance 1")
    ae_target: float = Field(0.22, gt=0, lt=1, description="auto-exposure target (share of full well)")
    ae_max_exposure_s: float = Field(0.008, gt=0)
    ae_max_gain: float = Field(4.0, ge=1)
    right_sensitivity: float = Field(0.97, gt=0, description="right camera responsivity / left")
    # optics
    vignetting_corner: float = Field(0.6, gt=0, le=1, description="relative illumination at the corner")
    lens_sigma_px: float = Field(0.5, ge=0, description="lens PSF (Gaussian sigma, px)")
    f_number: float = Field(2.8, gt=0)
    focus_m: float = Field(0.6, gt=0)
    pixel_um: float = Field(6.0, gt=0)
    specular: float = Field(0.25, ge=0, description="Blinn-Phong specular weight")
    shininess: float = Field(30.0, gt=0)
    patches: bool = Field(True, description="textureless and repetitive patches on table and walls")
    # recorded calibration error (standard deviations)
    calib_focal_err_px: float = Field(0.3, ge=0)
    calib_pp_err_px: float = Field(0.3, ge=0)
    calib_k1_err: float = Field(0.002, ge=0)
    calib_rot_err_deg: float = Field(0.02, ge=0)
    calib_baseline_err_m: float = Field(0.00005, ge=0)
    # laser (see loopmodel/sim/laser.py)
    laser_peak: float = Field(420.0, gt=0, description="line peak (grey) on white at 0.5 m, normal incidence")
    laser_sigma_px: float = Field(1.2, gt=0, description="line cross-section sigma (px)")
    laser_speckle_contrast: float = Field(0.35, ge=0, lt=1)
    laser_spurious_rate: float = Field(0.08, ge=0, le=1, description="frames with a spurious reflection")
    laser_plane_rot_err_deg: float = Field(0.02, ge=0, description="true plane vs calibrated plane")
    laser_plane_offset_err_m: float = Field(0.0001, ge=0)
    laser_time_offset_s: float = Field(0.001, description="laser exposure after the camera's mid-exposure")
    # motion (see loopmodel/sim/trajectory.py)
    pace: Literal["smooth", "handheld"] = Field("handheld", description="handheld: saccades and pauses")
    revisit_offset_m: float = Field(0.03, ge=0, description="the return misses the start view by this much")


class SimulationConfig(_Section):
    """Synthetic scan generator (``loopmodel simulate scan``)."""

    seed: int = Field(0, ge=0)
    camera: SimCameraConfig = Field(default_factory=SimCameraConfig)
    scene: SimSceneConfig = Field(default_factory=SimSceneConfig)
    render: SimRenderConfig = Field(default_factory=SimRenderConfig)
    trajectory: SimTrajectoryConfig = Field(default_factory=SimTrajectoryConfig)
    laser: SimLaserConfig = Field(default_factory=SimLaserConfig)
    faults: SimFaultsConfig = Field(default_factory=SimFaultsConfig)
    realism: SimRealismConfig = Field(default_factory=SimRealismConfig)  # issue 17
    workers: int = Field(2, ge=0, le=256, description="render processes; 0 = one per core, 1 = in-process")
    image_format: ImageFormat = Field("png")
    write_scene_ply: bool = Field(True, description="also write <out>.scene.ply beside the MCAP")

    @model_validator(mode="after")
    def _faults_within_frames(self) -> SimulationConfig:
        n = self.trajectory.frames
        f = self.faults
        ranges = [("dropped", i, i) for i in f.dropped] + [("duplicate_timestamp", i, i) for i in f.duplicate_timestamp]
        ranges += [(k, a, b) for k in ("blackout", "blur", "occluder") for a, b in getattr(f, k)]
        for kind, a, b in ranges:
            if a > b or a < 0 or b >= n:
                raise ValueError(f"faults.{kind}: frames {a}-{b} outside 0-{n - 1} (or first > last)")
        return self


class EvalConfig(_Section):
    """Evaluation against ground truth (``loopmodel eval``, and after ``loopmodel run``)."""

    align: AlignMode = Field(default="se3", description="alignment to ground truth")
    first_n: int | None = Field(default=None, ge=3, description="align on the first N poses only")
    max_dt_ms: float = Field(default=10.0, gt=0, description="max time gap of associated poses")
    rpe_delta_frames: int = Field(default=1, ge=1, description="RPE pose-pair spacing in frames")
    rpe_delta_m: float | None = Field(
        default=None, gt=0, description="RPE path distance; None: about a tenth of the path"
    )
    kitti_segment_lengths_m: list[float] = Field(
        default_factory=lambda: [100.0, 200.0, 300.0, 400.0, 500.0, 600.0, 700.0, 800.0]
    )
    plots: bool = True
    # onepass (issue 32): the evaluation after a run measures the run's final mesh; the two reference
    # meshes (stripes placed with the ground-truth and with the online poses) cost two more Poisson
    # reconstructions, so only when asked
    mesh_references: bool = Field(
        default=False,
        description="also mesh the stripes with the ground-truth and online poses (mesh_err_gt_mm, mesh_err_before_mm)",
    )
    # issue 35: evo's --plot_mode; auto: xz for camera-frame ground truth (KITTI), xy for z-up worlds
    plot_mode: Literal["auto", "xy", "xz", "yz", "xyz"] = Field(
        default="auto", description="plane of the path plots: auto, xy, xz, yz or xyz (3-D)"
    )


class SurfConfig(_Section):
    """The SURF detector/descriptor written here (:class:`loopmodel.loop.surf.Surf`, issue 18).

    Measured with ``tools/bench.py surf`` (fountain-P11 views and RTAB-Map corridor images,
    real, under known homographies), ``reloc`` (fountain) and ``loopdet`` (corridor loop images);
    the measurements behind each value are in the comments of :class:`~loopmodel.loop.surf.Surf`.
    """

    # 1.5e-5 keeps max_features even in low-contrast corridor images (5e-5: 185 in image 50,
    # loop recall 0.77; 1.5e-5: 0.84)
    threshold: float = Field(1.5e-5, gt=0, description="Hessian-determinant threshold (image in [0, 1])")
    n_octaves: int = Field(4, ge=1, le=8, description="octaves of box filters")
    n_layers: int = Field(4, ge=3, le=8, description="filters per octave")
    step0: int = Field(1, ge=1, le=8, description="sampling step of the first octave (px)")
    dense_octaves: int = Field(1, ge=1, le=8, description="octaves keeping step0 (then it doubles)")
    # 1.5 px raised repeatability under rotation and scale on both image sets
    presmooth_sigma_px: float = Field(1.5, ge=0, description="Gaussian smoothing of the first octave (px)")
    edge_ratio: float = Field(0.0, ge=0, description="reject maxima above this curvature ratio (0: off)")
    overlap: bool = Field(True, description="overlapping Gaussian-weighted sub-regions (M-SURF)")
    extended: bool = Field(False, description="128-element descriptors")
    upright: bool = Field(False, description="U-SURF: no orientation")
    # issue 18: rotation 30/45/135 repeatability 0.55/0.57/0.58 -> 0.60/0.62/0.62 on both sets
    smooth_per_octave: bool = Field(True, description="smoothing grows with the octave's filters")
    # issue 18: orientation error under a 90-degree rotation 1.25 -> 0.23 deg (median, both sets)
    subpixel_haar: bool = Field(True, description="orientation: Haar wavelets of real-valued centre and side")
    # issue 18, bench surf/loopdet/reloc in one session: on, loop-detection recall 0.818 (off: 0.795)
    # and fountain view 10 at 0.21 deg (off: 0.38 deg); detect+describe 640x480 1.13x SIFT's (off: 0.82x)
    subpixel_descriptor: bool = Field(True, description="the same for the descriptor's wavelets (2x slower)")
    # issue 18: fountain view 10 relocalized (67 of 253 inliers; 1.5: 52 of 255, 0.5: 62 of 254)
    describe_sigma_px: float = Field(0.8, ge=0, description="smoothing of the image orientation and descriptor use")


class LoopConfig(_Section):
    """Appearance-based relocalization and loop closing (``loopmodel.loop``)."""

    enabled: bool = True
    descriptor: DescriptorKind = Field("orb", description="orb, sift or surf")
    n_features: int = Field(1500, ge=50, le=100000, description="features per keyframe")
    surf: SurfConfig = Field(default_factory=SurfConfig, description="SURF settings (descriptor: surf)")
    ratio: float = Field(0.8, gt=0, le=1, description="Lowe ratio of descriptor matching")
    vocabulary_path: str | None = Field(
        None, description="trained vocabulary .npz; None: the one shipped for the descriptor kind"
    )
    # perf (issue 26): training during the run cost 4.3 s of 11 s on the KITTI clip
    vocabulary_online: bool = Field(
        False, description="train the vocabulary on the fly from the run's keyframes instead"
    )
    vocabulary_branching: int = Field(8, ge=2, le=64)
    vocabulary_levels: int = Field(4, ge=1, le=10)
    vocabulary_train_after: int = Field(6, ge=2, le=100000, description="keyframes before on-the-fly training")
    min_gap_keyframes: int = Field(10, ge=1, le=100000, description="recent keyframes never loop candidates")
    consistency: int = Field(2, ge=1, le=1000, description="consecutive agreeing queries before a loop")
    min_score: float = Field(0.01, ge=0)
    threshold_px: float = Field(2.0, gt=0, description="P3P inlier bound (pixels)")
    min_inliers: int = Field(25, ge=6, le=100000)
    min_inlier_ratio: float = Field(0.25, gt=0, le=1)
    max_samples: int = Field(4096, ge=64, le=1000000, description="P3P bank minimal samples per query")
    min_epipolar_inliers: int = Field(40, ge=8, le=100000, description="monocular verification")
    max_cycle_rot_deg: float = Field(2.0, gt=0, description="forward/reverse pose agreement")
    max_cycle_trans_m: float = Field(0.05, gt=0)
    # onepass (issue 32): the knobs the parameter classes (PlaceParams, RelocParams, LoopParams) had
    # as their own defaults, now read from here; values unchanged
    relative_score: float = Field(0.5, ge=0, le=1, description="place candidates: score share of the best")
    island_gap: int = Field(2, ge=0, le=1000, description="keyframe gap that splits candidate islands")
    consistency_tol: int = Field(3, ge=0, le=1000, description="keyframe tolerance of consistent queries")
    max_islands: int = Field(4, ge=1, le=1000, description="candidate islands verified per query")
    retrain_growth: float = Field(1.5, gt=1, description="on-the-fly vocabulary retrained when keyframes grow so")
    max_train_keyframes: int = Field(400, ge=2, description="keyframes sampled to train a vocabulary on the fly")
    max_train_descriptors: int = Field(60000, ge=100, description="descriptors to train a vocabulary on the fly")
    confidence: float = Field(0.999, gt=0, lt=1, description="RANSAC confidence of relocalization")
    min_inlier_spread_frac: float = Field(
        0.03, ge=0, le=1, description="inliers' smaller principal spread, fraction of the image width"
    )
    epipolar_threshold_px: float = Field(2.0, gt=0, description="monocular verification: epipolar bound")
    min_epipolar_inlier_ratio: float = Field(0.3, gt=0, le=1, description="monocular verification")
    min_epipolar_spread_frac: float = Field(0.05, ge=0, le=1, description="monocular verification: inlier spread")
    max_members_verified: int = Field(3, ge=1, le=1000, description="keyframes of an island verified")
    # robust gate on verified loops (loopmodel.backend.robust_posegraph): a keyframe pose
    # graph of odometry (known inliers) and loops solved by GNC-TLS; a loop it rejects is
    # never applied. Sigmas per keyframe step / per loop constraint: the loop sigmas are of
    # the order of the forward/reverse agreement bounds above; checked on the rendered loop
    # runs of tests/test_loop_pipeline.py and tests/test_loop_closer.py (every true loop
    # kept), not yet on a real sequence with loops.
    robust: Literal["gnc", "none"] = Field("gnc", description="gnc: GNC-TLS loop gate; none: trust loops")
    robust_probability: float = Field(0.99, gt=0.5, lt=1, description="chi-square inlier quantile")
    robust_odometry_sigma_deg: float = Field(1.0, gt=0, le=90, description="rotation per keyframe step")
    robust_odometry_sigma_m: float = Field(0.02, gt=0, le=100, description="translation per keyframe step")
    robust_loop_sigma_deg: float = Field(1.0, gt=0, le=90, description="loop constraint rotation")
    robust_loop_sigma_m: float = Field(0.03, gt=0, le=100, description="loop constraint translation")
    # issue 33: the gate's pose graph took every earlier loop between the new loop's keyframes, so its
    # GNC solve grew with the loops (up to 244 of them on rounds_5400: 182 ms CPU, one gtsam call holding
    # the interpreter lock). It takes those on the shortest bridges between the new loop's keyframes
    # (robust_posegraph.nearest_loops); 0: every loop. tools/bench_gate.py (synthetic rounds, 18 x 20
    # keyframes, 340 true loops, 34 random false ones, 37 near misses 0.25 m / 5 deg off; seeds 0, 1, 2):
    # every true loop kept and every random one rejected at any bound; near misses accepted that every
    # loop rejects: at 32 0, 2, 1, at 48 0, 1, 0; CPU per gate in the last sixth 17-20 ms at 32, 25-27 at
    # 48, flat (every loop: 28-58 ms, growing, max 292-383). rounds_5400's 295 real gates replayed: the
    # same verdicts at 32 and 48 (CPU per gate at most 31 ms at 32, 37 at 48; every loop 174-182). KITTI: no loop
    # closes (unchanged). Not checked on a real sequence with loops.
    robust_max_loops: int = Field(48, ge=0, le=100000, description="earlier loops in a gate's graph (0: all)")
    # perf (issue 26): loop detection off the tracking path
    # KITTI clip, 2 runs each at load 25 on 2 cores (frame-time p95 / track_ms median):
    # thread 472, 466 / 57, 53 ms; process 416, 473 / 61, 69 ms; none 506, 904 / 29, 40 ms.
    # Both workers take CPU from tracking on a loaded machine; the thread starts at once
    # (the process imports the package again, ~2 s) and is the default. Measured on the real
    # KITTI clip only; the loop tests on rendered sequences find the same loops with either.
    detection_worker: Literal["process", "thread", "none"] = Field(
        "thread", description="where retrieval and verification run; applied at the next keyframe"
    )
    # kf12 (issue 33): the detection worker (thread or process) and the late loops' apply thread at a lowered
    # scheduling priority (a keyframe's detection, ~11 ms of CPU on the KITTI clip, runs beside the next
    # frame's tracking). Off: full pipeline, 10 vs 0, the same results; KITTI clip (configs/kitti.yaml, 5
    # alternated pairs at load 11-14) frame median 58.7 -> 39.9 ms, max after the first 226 -> 140 ms, p95
    # 108.0 -> 106.8 ms; but the orbit sample (configs/sim.yaml, 200 frames, 4 pairs at load 7-9) max after
    # warm-up 122 -> 198 ms (higher in 4 of 4): a lowered thread descheduled while it holds the interpreter
    # lock keeps the tracking thread waiting. CHANGELOG (kf12)
    worker_nice: int = Field(0, ge=0, le=19, description="lower the detection and apply workers' priority by this")
    # issue 33 item 1: a loop the detection worker found for an earlier keyframe is moved to the current
    # keyframe (its old features tracked into that image, P3P bank) and gated; ``thread``: both on a
    # thread of their own, the loop applied between frames when done (its constraint with the
    # keyframe's observations of the old landmarks, the old set to the front end while that keyframe is
    # still the active one); ``none``: inline in the keyframe's loop stage, as before (rounds scan,
    # scale6: about 115 ms of tracking and 4-135 ms of gate per applied loop on the tracking thread).
    # Default measured (scale7, CHANGELOG): the rounds scan (rounds_1800, load 9-22) loop time on the tracking
    # thread 41-47 -> 0.6-1.0 s; the real KITTI clip and the quick orbit/sim-loop scans close no loop late:
    # accuracy keys identical (bench pipeline --quick KITTI 0.0427 m, bench sim-loop --quick).
    apply_worker: Literal["thread", "none"] = Field(
        "thread", description="where a late loop is moved to the current keyframe and gated"
    )
    # whether such a loop, applied between frames while its keyframe is the front end's active one, hands
    # the old features to the front end to track on (seed 004 section 5), as inline application does.
    # bench scale --quick (rounds_1800, load 4-21): with it, final ATE 14.99-15.22 mm in 4 runs of 5
    # and 24.48 mm in one (inline application: 14.95-14.96 mm in 3); without it 9.36 and 9.37 mm (2 runs,
    # side by side with two of the former). Only this scan closes loops late (the KITTI clip and the
    # quick sim-loop scans close none): kept on until a second sequence with loops is measured.
    late_resume: bool = Field(True, description="a loop applied between frames resumes its old features")
    # a backlog bound, not a tuned value: 16 keyframes is seconds of scanning at any keyframe rate
    max_queued_keyframes: int = Field(
        16, ge=1, le=100000, description="worker backlog above which new keyframes are stored but not queried"
    )
    # scale (issue 17): at the end of a run the worker's pending detections are waited for, so a loop
    # found at the last keyframes reaches the final refinement as the inline detection would have it.
    # A bound against a hung worker, not a tuned value: a full backlog (16 keyframes) at the
    # detection's median of about 0.1-0.3 s per keyframe (orbit, KITTI clip) drains in a few seconds.
    drain_timeout_s: float = Field(
        60.0, ge=0, le=3600, description="longest wait for the loop worker's pending detections at the end of a run"
    )
    # a loop applied after its query keyframe reached the back end (found after the last keyframe,
    # or late with too few old features tracked into the next keyframe): with the query keyframe's
    # observations of the old landmarks (true: what inline detection, detection_worker none, gives
    # the back end; the final result then equals the inline one) or as its relative pose alone.
    # Measured (scale, issue 17) with the loop found after the last keyframe, final ATE: clean
    # 600-frame orbit 0.111 mm with them (= inline) vs 0.130 mm without; seeded realistic 400-frame
    # orbit of tests/test_sim_realism.py 8.86 mm with them (= inline) vs 1.06 mm without (the
    # recorded calibration's depth bias: landmark factors close the loop through biased structure,
    # the pose constraint alone is spread along the chain). Simulated sequences only: no real
    # sequence with loops and ground truth is at hand.
    late_loop_observations: bool = Field(
        False, description="late loops bring the query keyframe's observations of old landmarks to the back end"
    )


class AccuracyConfig(_Section):
    """Marker-pose Cramér–Rao bound (``loopmodel bound``, seed 001)."""

    distance_m: float = Field(50.0, gt=0, description="camera-to-marker distance R")
    focal_mm: float = Field(18.0, gt=0, description="focal length")
    pixel_um: float = Field(10.0, gt=0, description="pixel pitch: the image length unit")
    noise: float = Field(0.2, gt=0, description="N0/2, contrast^2 px^2 (variance on a 1 px cell)")
    theta_deg: list[float] = Field(default_factory=lambda: [5.0 + 10.0 * k for k in range(7)])
    phi_deg: list[float] = Field(default_factory=lambda: [10.0 * k for k in range(36)])
    edge_subdivisions: int = Field(64, ge=1, le=100000, description="trapezoid sub-intervals per polygon edge")
    circle_points: int = Field(256, ge=8, le=100000, description="trapezoid points per circle")
    pixel_study_px: list[float] = Field(default_factory=lambda: [0.25, 0.5, 1.0, 2.0, 4.0])


class VvsConfig(_Section):
    """Model-based tracking by virtual visual servoing (``loopmodel vvs``, seed 002)."""

    sample_step_px: float = Field(3.0, gt=0, description="spacing of edge samples on each conic")
    search_px: int = Field(10, ge=1, le=1000, description="moving-edge search range along the normal")
    edge_noise_px: float = Field(0.15, ge=0, description="simulated edge noise before pixel rounding")
    loss: Literal["tukey", "huber", "l2"] = Field("tukey", description="M-estimator")
    huber_warmup: int = Field(1, ge=0, le=1000, description="first VVS iterations with Huber")
    max_iterations: int = Field(20, ge=1, le=1000)
    min_features: int = Field(20, ge=6, le=100000, description="fewer matched edge points: tracking failure")
    lost_rot_deg: float = Field(5.0, gt=0, description="frame counted lost above this rotation error")
    lost_pos_mm: float = Field(50.0, gt=0, description="frame counted lost above this position error")


class GivensConfig(_Section):
    """Sequential Givens estimator and Baarda data snooping (``backend/givens*.py``, seed 000)."""

    alpha: float = Field(0.001, gt=0, lt=1, description="significance level of the w-test")
    min_redundancy: float = Field(
        0.3, gt=0, le=1, description="an observation is tested once its r_i reaches this"
    )
    sigma_px: float = Field(1.0, gt=0, description="std. dev. of an image coordinate")
    relin_px: float = Field(
        0.1, gt=0, description="re-linearise rows whose linearisation error exceeds this"
    )
    min_downdate_cos2: float = Field(1e-6, gt=0, lt=1, description="hyperbolic pivot safety")
    point_prior_sigma_m: float = Field(1.0, gt=0, description="weak prior on a new point")
    frame_prior_sigma_rad: float = Field(0.05, gt=0, description="weak prior, frame rotation")
    frame_prior_sigma_m: float = Field(0.1, gt=0, description="weak prior, frame position")


class RefineConfig(_Section):
    """Final refinement after the last loop closure (pipeline, end of a run)."""

    batch_ba: bool = Field(True, description="batch bundle adjustment of all keyframes and landmarks (iSAM2)")
    # iSAM2's extra updates (each relinearising every variable) until none needs relinearising, at most
    # this many. The pipeline sets 0 when the calibrating bundle adjustment follows (calibration.refine
    # final), which re-solves every keyframe and landmark from there (fin17: on the 349-keyframe scale
    # scan one such update took 33.5 s CPU and moved no keyframe by more than 0.06 mm; `bench pipeline`: the
    # simulated scans' keys unchanged, the KITTI clip's final ATE 25.15 -> 25.17 mm, within its run-to-run
    # spread; CHANGELOG fin17)
    extra_iterations: int = Field(
        10, ge=0, le=100, description="iSAM2 updates relinearising everything before the final estimate (at most)"
    )
    # perf (issue 26): the former constant 0.05 px was tuned on the simulator; KITTI's KLT
    # residuals are several times larger
    pixel_sigma_px: float | None = Field(
        None, gt=0, description="batch BA: std. dev. of a feature position; None: the run's residual MAD"
    )
    huber_k: float = Field(1.345, ge=0, description="batch BA: Huber threshold in sigmas (0: Gaussian)")
    max_iterations: int = Field(30, ge=1, le=1000, description="batch BA: Levenberg-Marquardt iterations")
    # perf (issue 26): 3 (a 3-sigma test) measured on the KITTI clip (the drop is 1.3 SD and
    # the refinement raises ATE 0.0998 -> 0.1126 m: not applied) and the simulated orbit
    # (9.2 SD, ATE 0.44 -> 0.20 mm: applied)
    min_gain_sd: float = Field(
        3.0, ge=0, description="batch BA kept only when its robust chi-square drop exceeds this many SD"
    )
    # issue 32 (finish6): Levenberg-Marquardt ran 21 iterations on the KITTI clip (gtsam's 1e-5
    # tolerances), the last 16 lowering gtsam's error by 4.7 in all (chi-square 9.5, 0.07 of its SD
    # 128). At 0.01 SD: 8 iterations, the batch BA's CPU 0.36 -> 0.17 s; its robust chi-square drop
    # 275.9 -> 282.6 (2.2 SD, rejected either way: the KITTI keys unchanged). The bench's simulated
    # scans reject it too (refine_applied false); an accepted one stops where an iteration gains less
    # than 0.01 SD, far below what the acceptance test (min_gain_sd) tells apart from noise. 0: gtsam's
    # own tolerances (1e-5)
    stop_gain_sd: float = Field(
        0.01, ge=0, description="batch BA: stop when an iteration lowers the robust chi-square by less than this SD"
    )
    # how the drift is distributed (mapping/anchored.bridge_interval, issue 31 bridge4): tracked
    # translations scaled to the estimated link, the rest spread by tracked path, not time. Measured by
    # replaying each run's bridging inputs, old -> new: realistic orbits refined (tools/bench_selfcal.py,
    # seeds 1 / 2 / 3) segment drift 0.0786 / 0.0967 / 0.0339 -> 0.0699 / 0.0854 / 0.0331 %; the demo
    # sample (configs/sim.yaml) ATE 2.918 -> 2.866 mm; the real KITTI clip (configs/kitti.yaml) ATE
    # 45.277 -> 45.279 mm. Without any bridge (false) the demo gives 2.454 mm and KITTI 44.39 mm, the
    # refined orbits 1.22 / 1.29 / 0.45 mm (the bridge halves those): true kept, to be re-measured
    bridge_frames: bool = Field(
        True, description="distribute each keyframe interval's tracking drift over its frames"
    )
    # issue 17: the batch BA leaves a loop open where the image measurements are precise but biased
    # (calibration error): spread each verified loop's discrepancy along its keyframe cycle, odometry
    # edges of equal noise per step (backend/loop_distribution.py). Sigmas as the loop stage's robust
    # gate (loop.robust_odometry_sigma_*); the loop edges take backend.loop_sigma_*. Measured on the
    # realistic simulated orbit and modeler (tools/bench_sim_loop.py) and the KITTI clip (no loop:
    # unchanged)
    distribute_loops: bool = Field(True, description="spread loop discrepancies along the keyframe chain")
    loop_odometry_sigma_deg: float = Field(1.0, gt=0, le=90, description="per keyframe step, rotation")
    loop_odometry_sigma_m: float = Field(0.02, gt=0, le=100, description="per keyframe step, translation")


class SessionConfig(_Section):
    """A run in or beside a saved map (``loopmodel run --map MAP --mode ...``, issue 20)."""

    mode: Literal["localize", "extend"] = Field(
        "localize", description="with a map: localize in it (nothing added) or extend it (merged map and mesh)"
    )
    # a relocalization in the map that moves a keyframe already in the map's frame by more than this
    # is taken for a false match and not applied (the tracker's drift between keyframes is mm).
    # Where set: the simulated hand-held sessions of tools/bench_sessions.py and tests/test_sessions.py
    # (close range); on the real KITTI clip a car drifts cm to dm between keyframes and needs 0.5 m
    # (configs/kitti.yaml, with which every frame 20-30 relocalized)
    max_correction_m: float = Field(0.05, gt=0, description="largest correction of a localized keyframe")
    max_correction_deg: float = Field(5.0, gt=0, description="largest correction of a localized keyframe")
    # links between two maps agree when their worldA_from_worldB differ by less than this; the merge
    # test's two simulated runs agree to 0.77 mm / 0.033 deg, the bench's realistic sessions to
    # 5-16 mm (not yet checked on a real pair of sessions)
    merge_agree_m: float = Field(0.02, gt=0, description="agreement of two links between maps (translation)")
    merge_agree_deg: float = Field(2.0, gt=0, description="agreement of two links between maps (rotation)")
    # issue 31 item 4: a map made with calibration.refine carries its refined calibration; a session
    # whose recorded rig differs from it by no more than this many combined sigma per parameter (the
    # recorded calibration's prior and the map's posterior) is the same rig and starts from it (0: never).
    # The realistic simulator draws each session's recorded calibration about 1 prior sigma off the true
    # rig per parameter: the sessions bench's B against A's refined rig 1.60 sigma at most (fy_right_px),
    # tests/test_sessions.py's rendered rig 0.86; another camera of a model differs by pixels in its
    # focal lengths (2 px: 6.3 sigma). No real pair of sessions of one rig is in the shared data: the
    # value rests on the simulated sessions bench and the rendered test rig only.
    same_rig_sigma: float = Field(
        4.0, ge=0, description="a map's refined calibration is used when the rig differs by at most this (sigmas)"
    )


class SelfCalibrationConfig(_Section):
    """Self-calibration of the stereo rig and the light plane from the scan itself (issue 31).

    Priors: the recorded calibration with these standard deviations (a good chessboard calibration;
    the simulator's realistic world draws its recorded-calibration error with the same values).
    """

    # default none (tools/bench_selfcal.py): on the realistic orbits (3 seeds) final cuts ATE 6.3-6.7 ->
    # 0.7-1.0 mm and the mesh error 4.0 -> 0.6-1.0 mm, and the KITTI clip improves (ATE 0.104 -> 0.048 m;
    # re-measured with the front end's disparity offset off: 0.102 -> 0.052 m), but there its stereo
    # rotation moves 2.9 sigma (the largest move: 12 posterior sigmas), and on the real chessboard rig cy_left
    # 3.4 sigma: not "within sigma" on well-calibrated real rigs, so opt-in.
    # calib5 (CHANGELOG): with the right rows measured and weak combinations held, final beats none on
    # accuracy everywhere measured (bench peer --quick, 3 rounds: orbit drift / rotation error 0.720 /
    # 0.866 -> 0.224 / 0.222 against ORB-SLAM3's 0.66-0.69 / 0.65-0.69, modeler 0.555 / 0.694 -> 0.205 /
    # 0.106 against 0.50-0.55 / 0.55-0.59; KITTI kitti.yaml ATE 0.0427 -> 0.031-0.034 m; chessboard largest move
    # 0.53 sigma; KITTI's moves about z and y confirmed by the right rows and the ground truth's motion),
    # but the finish: KITTI wall over frames 1.17-1.24 -> 1.53 with the refinement on one BLAS thread
    # (issue 32's target 1.2; the self-calibration 4.0 s on an 11.5 s frame loop, load 22).
    # calib7: default final. The refinement's solver cut (rough solves until the pixel noise settles,
    # one final solve: KITTI 16 -> 10 iterations, the 150-frame orbit 21 -> 17, values within 0.005
    # prior sigma), its modules imported during the set-up. Measured (CHANGELOG calib7): the KITTI clip
    # (configs/kitti.yaml) wall over frames final 1.236 -> 1.161 (none 1.119) at load 5-10, ATE
    # 0.0347 m (none 0.0427), drift 0.830 % (none 0.907); the 150-frame realistic orbit (configs/sim.yaml)
    # mesh error after closure 0.595 mm (none 3.84); bench peer --quick orbit / modeler drift 0.227 /
    # 0.207 % against ORB-SLAM3's 0.650 / 0.587; the real chessboard rig's largest move 0.527 prior sigma
    refine: Literal["none", "final", "online"] = Field(
        "final",
        description="none: the recorded calibration as given; final: refined in the final bundle adjustment;"
        " online: also in windows of recent keyframes during the run, the rectification following it",
    )
    # issue 31 item 1 (calib8, calibration/online.py): refine online. Every online_every_kf keyframes
    # the last online_window_kf go through the calibrating bundle adjustment beside the tracker; the
    # windows' information is fused, and when the fused calibration has moved online_switch_sigma
    # prior sigmas from the one in force the front end's rectification follows it (the left lens kept).
    # Not the default: measured (CHANGELOG calib8; one run per mode, alternating, load 7-17) it costs
    # accuracy: KITTI clip (default config) ATE 0.0495 -> 0.0541 / 0.0546 m (drift 0.841 -> 0.837 /
    # 0.838 %); realistic orbits (tools/bench_selfcal.py's runs) segment drift seeds 1 / 2 / 3 0.0597 /
    # 0.0283 / 0.0365 -> 0.0676 / 0.0328 / 0.0419 %; the rendered rig of tests/test_online_calib.py
    # 0.41 -> 0.70 mm.
    # Without the switches (windows and warm start only) KITTI, seed 3 and that rig are unchanged
    # (0.0494 m, 0.0363 %, 0.43 mm): the re-rectified images themselves (their resampling) move it
    online_every_kf: int = Field(3, ge=1, description="online: a window refinement every this many keyframes")
    online_window_kf: int = Field(6, ge=3, description="online: keyframes in a window")
    online_switch_sigma: float = Field(
        0.5, gt=0, description="online: a move (prior sigmas) of the fused calibration that re-rectifies"
    )
    online_worker: Literal["process", "thread", "inline"] = Field(
        "process", description="online: where the window refinements run (inline: on the tracking thread)"
    )
    sigma_focal_px: float = Field(0.3, gt=0, description="prior std. dev. of fx, fy of each camera")
    sigma_principal_px: float = Field(0.3, gt=0, description="prior std. dev. of cx, cy of each camera")
    sigma_k1: float = Field(0.002, gt=0, description="prior std. dev. of the first radial term of each camera")
    sigma_k2: float = Field(0.002, gt=0, description="prior std. dev. of the second radial term (when refine_k2)")
    refine_k2: bool = Field(False, description="also refine k2 of each camera")
    # the right camera's fy, cy and the rotation about the baseline (x) move right-image points along
    # the image columns. The front end hands on each right match's row (Keyframe.right_rows_px); with
    # this on, both its rectified coordinates are measured and the three are estimated (off: the
    # right column only, the three held; estimated from the columns alone they went 3.8 / 2.6 / 1.8
    # prior sigmas off the truth on the realistic orbit). Measured (calib5; the runs' own refinement
    # inputs replayed, off -> on): realistic orbits seeds 1 / 2 / 3 (tools/bench_selfcal.py) largest
    # parameter error 0.87 / 0.68 / 1.82 -> 0.60 / 0.73 / 0.57 prior sigmas, rms 0.41 / 0.29 / 0.66 ->
    # 0.30 / 0.37 / 0.24, keyframe ATE 0.55 / 0.19 / 0.25 -> 0.30 / 0.24 / 0.20 mm; the KITTI clip
    # keyframe ATE 54.1 -> 52.7 mm (with observable_direction_ratio 0.7: 48.3 mm)
    refine_right_rows: bool = Field(
        True, description="measure the right matches' rows and refine the right camera's fy, cy and the x rotation"
    )
    sigma_rotation_deg: float = Field(0.02, gt=0, description="prior std. dev. of the stereo rotation, per axis")
    sigma_baseline_m: float = Field(5e-5, gt=0, description="prior std. dev. of the stereo baseline")
    sigma_plane_offset_m: float = Field(1e-4, gt=0, description="prior std. dev. of the light plane's offset")
    sigma_plane_tilt_deg: float = Field(0.02, gt=0, description="prior std. dev. of the light plane's tilt, per axis")
    # a parameter whose posterior std. dev. is above this share of its prior's is hardly constrained
    # by the data: reported as unobservable (one not informed at all, above 0.99, is held at its
    # recorded value). Set on the synthetic scans of tests/test_selfcal.py
    observable_ratio: float = Field(
        0.9, gt=0, lt=1, description="posterior/prior sigma above which a parameter is unobservable"
    )
    # issue 31, calib5: a combination of parameters can be unobservable while each parameter is not
    # (a common vertical principal point of both cameras is nearly a rotation of the rig about x,
    # which the keyframe poses absorb). Combinations whose posterior sigma stays above this share of
    # the prior's are held at the recorded values and reported (1: none held). 0.7 (about 1/sqrt(2)):
    # the scan alone determines such a combination worse than the recorded calibration does. Measured
    # (calib5): the real chessboard rig with the right rows (tools/bench_selfcal.py chess_*_rows) holds
    # the common cy (posterior/prior 0.75), common cx and focal lengths: largest move 4.94 -> 0.53
    # prior sigmas; the realistic orbits (seeds 1-3) hold nothing (results identical); the KITTI clip
    # holds 5 (0.72-1.0), keyframe ATE 52.7 -> 48.3 mm
    observable_direction_ratio: float = Field(
        0.7, gt=0, le=1, description="posterior/prior sigma above which a combination of parameters is held"
    )
    # issue 31/36 (ridge9): a held common principal point (nearly a rotation of every pose) is held
    # through the left camera's, the right camera carrying the left-right difference the data
    # determine: held as the sum of both, the left camera's share of that difference turns the
    # reported camera frame and the trajectory (the KITTI clip: cx_left +0.385 px, 0.54 mrad of yaw).
    # rectified (default): for rectified input only, whose left camera (the rectified one) defines the
    # frame the poses and the ground truth refer to. Measured (CHANGELOG ridge9, alternating pairs):
    # KITTI clip (configs/kitti.yaml) drift after the ground truth's constant-rate segment 0.551 ->
    # 0.512 %, ATE 0.0216 -> 0.0222 m (within its run spread); the street scene of bench peer (KITTI
    # layout, right cx 0.5 px off) ATE 0.0694 -> 0.0684 m. For raw input (always) it costs where the
    # left lens is off too: bench selfcal --quick (seed 1) mesh 0.60 -> 2.29 mm; the chessboard rig's
    # largest move 0.527 -> 0.540 prior sigma
    anchor_principal_point: Literal["rectified", "always", "never"] = Field(
        "rectified", description="hold an unobservable common principal point through the left camera's"
        " (rectified: for rectified input only)"
    )
    huber_k: float = Field(1.345, ge=0, description="Huber threshold in sigmas (0: Gaussian)")
    max_iterations: int = Field(15, ge=1, le=200, description="Levenberg-Marquardt iterations")
    # off: the loops' relative poses were measured with the recorded calibration. On the realistic
    # orbits (tools/bench_selfcal.py, seeds 1 / 2; seed 3 has no loop constraint) spreading them
    # again after the refinement brings end-point drift 0.064 / 0.044 -> 0.032 / 0.018 % and rotation
    # gain 1.0015 / 0.9991 -> 1.0005 / 0.9997, but ATE 0.88 / 1.02 -> 0.68 / 1.21 mm and mesh error
    # 0.58 / 0.97 -> 0.70 / 1.19 mm
    close_loops: bool = Field(False, description="spread loop discrepancies along the keyframe chain after refining")
    laser_match_px: float = Field(
        1.5, gt=0, description="laser-stereo: a landmark this close to the stripe in the image"
    )
    # issue 31, selfcal4: with the recorded rectification a right match lies up to 2.4 px off the
    # left row (realistic orbits); the 1-D sub-pixel step reads its column at the left row, where a
    # patch's shear turns the row offset into a column error that biases the calibration. While
    # refining (refine != none) the front end measures at the match's own row (frontend.stereo_subpixel
    # gradient_2d); with refine none it is untouched. Measured (tools/bench_selfcal.py, refined run,
    # frontend -> gradient_2d; realistic orbits, seeds 1 / 2 / 3): largest parameter error 2.11 /
    # 2.06 / 1.69 -> 0.87 / 0.68 / 1.82 prior sigmas, drift 0.081 / 0.135 / 0.036 -> 0.079 / 0.097 /
    # 0.034 %, mesh 0.59 / 0.88 / 0.70 -> 0.49 / 0.76 / 0.66 mm; the KITTI clip refined drift 0.889 ->
    # 0.899 %, ATE 0.052 -> 0.055 m (off: 1.036 %, 0.102 m)
    stereo_subpixel: Literal["frontend", "gradient_2d"] = Field(
        "gradient_2d",
        description="front end's sub-pixel disparity while refining: frontend.stereo_subpixel as set, or gradient_2d",
    )

    # issue 31, retrack5: the frames between keyframes were tracked with the recorded calibration;
    # after the final refinement each is solved again from the points its pose kept, as the refined
    # calibration sees them, against the refined landmarks, and each interval bridged onto its refined
    # keyframes (calibration/retrack.py). Measured on the refined runs of tools/bench_selfcal.py
    # (realistic orbits, seeds 1 / 2 / 3, same runs): segment drift 0.0699 / 0.0854 / 0.0331 ->
    # 0.0877 / 0.0391 / 0.0346 % (true calibration 0.024 / 0.025 / 0.024; seed 1 is left with its
    # refined map's scale, 0.12 % short: without it 0.025 %), ATE 0.64 / 0.83 / 0.28 -> 0.85 / 0.36 /
    # 0.31 mm; the real KITTI clip (refined, Config()): ATE 0.054933 -> 0.054951 m, drift 0.8985 % both;
    # a rendered 14-frame perfect rig (tests/test_selfcal.py): ATE 0.271 -> 0.270 mm (refine none 0.283)
    retrack_frames: bool = Field(True, description="while refining: re-solve the frames between keyframes")
    # 20: the value of the measured runs above (selfcal seeds 1-3, the KITTI clip); not varied
    retrack_min_points: int = Field(
        20, ge=6, description="fewest points a re-solved frame needs (else it keeps its bridged pose)"
    )
    # issue 32 (finish10): the re-solves are independent and hold the interpreter; the run's stripe-extraction
    # worker process, idle after the last frame, solves this share of them meanwhile (bit-identical poses).
    # The 600-frame sample (2 alternating pairs, load 11-14): the run's own re-solve CPU 1.01 -> 0.58-0.67 s
    # (the helper 272-290 of 581 frames; its imports 0.85 s CPU beside the calibrating BA); the 150-frame
    # orbit 0.26 -> 0.13 s. Only where laser-line images are extracted (KITTI: no such process, unchanged)
    retrack_helper_share: float = Field(
        0.5, ge=0, lt=1, description="share of the frames re-solved in the idle stripe-extraction process; 0 = none"
    )
    # the helper's imports cost 0.85 s CPU: a run of fewer frames re-solves them alone (the 150-frame orbit's
    # half share was 0.13-0.17 s CPU; on a loaded machine the imports cost more than they save)
    retrack_helper_min_frames: int = Field(
        300, ge=0, description="fewest frames of a run whose re-solve is shared with the helper process"
    )

    @property
    def retracks(self) -> bool:
        """Whether the frames between keyframes are re-solved after refining (the front end keeps their points)."""
        return self.refine != "none" and self.retrack_frames

    def frontend_config(self, frontend: FrontendConfig) -> FrontendConfig:
        """The front end's configuration for a run with this self-calibration (``stereo_subpixel`` while refining)."""
        if self.refine == "none" or self.stereo_subpixel == "frontend":
            return frontend
        return frontend.model_copy(update={"stereo_subpixel": self.stereo_subpixel})


class Config(_Section):
    """The whole configuration of loopmodel."""

    sequence: SequenceConfig = Field(default_factory=SequenceConfig)
    output: OutputConfig = Field(default_factory=OutputConfig)
    frontend: FrontendConfig = Field(default_factory=FrontendConfig)
    mapping: MappingConfig = Field(default_factory=MappingConfig)
    eval: EvalConfig = Field(default_factory=EvalConfig)
    loop: LoopConfig = Field(default_factory=LoopConfig)
    accuracy: AccuracyConfig = Field(default_factory=AccuracyConfig)
    simulation: SimulationConfig = Field(default_factory=SimulationConfig)
    vvs: VvsConfig = Field(default_factory=VvsConfig)
    givens: GivensConfig = Field(default_factory=GivensConfig)
    backend: BackendConfig = Field(default_factory=BackendConfig)
    refine: RefineConfig = Field(default_factory=RefineConfig)
    session: SessionConfig = Field(default_factory=SessionConfig)
    calibration: SelfCalibrationConfig = Field(default_factory=SelfCalibrationConfig)


def _deep_merge(base: dict[str, Any], override: dict[str, Any]) -> dict[str, Any]:
    out = dict(base)
    for key, value in override.items():
        if isinstance(value, dict) and isinstance(out.get(key), dict):
            out[key] = _deep_merge(out[key], value)
        else:
            out[key] = value
    return out


def config_from_dict(data: dict[str, Any], source: str | Path | None = None) -> Config:
    """Validate a (partial) nested dict over the defaults; errors name the key."""
    merged = _deep_merge(Config().model_dump(), data)
    try:
        return Config.model_validate(merged)
    except ValidationError as exc:
        err = exc.errors()[0]
        key = ".".join(str(p) for p in err["loc"])
        if err["type"] == "extra_forbidden":
            raise ConfigError(source, f"unknown key '{key}'") from None
        raise ConfigError(source, f"key '{key}': {err['msg']}") from None


SectionT = TypeVar("SectionT", bound=BaseModel)


def apply_overrides(
    section: SectionT, overrides: Mapping[str, Any], names: Mapping[str, str] | None = None
) -> SectionT:
    """A validated copy of ``section`` with the dotted keys of ``overrides`` set.

    ``section`` is the whole :class:`Config` or one of its sections; overrides such as
    ``{"eval.align": "sim3"}``; None values are skipped. The one way command-line flags change a
    configuration: an unknown key or an invalid value raises :class:`ConfigError` naming
    ``names[key]`` (e.g. the flag) or the key.
    """
    names = names or {}
    data = section.model_dump()
    for key, value in overrides.items():
        if value is None:
            continue
        *parents, leaf = key.split(".")
        node: Any = data
        for part in parents:
            node = node.get(part) if isinstance(node, dict) else None
        if not isinstance(node, dict) or leaf not in node:
            raise ConfigError(names.get(key, key), f"unknown configuration key '{key}'")
        node[leaf] = value
    try:
        return type(section).model_validate(data)
    except ValidationError as exc:
        err = exc.errors()[0]
        key = ".".join(str(p) for p in err["loc"])
        value = overrides.get(key, err.get("input"))
        raise ConfigError(names.get(key, key), f"{err['msg']}, got {value!r}") from None


def load_config(path: str | Path | Sequence[str | Path] | None = None) -> Config:
    """Defaults overridden by the YAML file at ``path`` (when given).

    A list of files is layered in order: each overrides the ones before it (``-c a.yaml -c b.yaml``).
    """
    if path is None:
        return Config()
    if not isinstance(path, str | Path):
        files = list(path)
        if not files:
            return Config()
        merged: dict[str, Any] = {}
        for f in files:
            load_config(f)  # each file valid on its own: errors name it
            merged = merge_nested(merged, _read_yaml_mapping(Path(f)))
        return config_from_dict(merged, Path(files[-1]))
    p = Path(path)
    return config_from_dict(_read_yaml_mapping(p), p)


def merge_nested(base: dict[str, Any], over: dict[str, Any]) -> dict[str, Any]:
    """``over`` on top of ``base``, mappings merged key by key (issue 35: layered config files)."""
    out = dict(base)
    for k, v in over.items():
        out[k] = merge_nested(out[k], v) if isinstance(v, dict) and isinstance(out.get(k), dict) else v
    return out


def _read_yaml_mapping(p: Path) -> dict[str, Any]:
    """The top-level mapping of a configuration file (errors name the file)."""
    if not p.is_file():  # an existing FIFO or device was "does not exist" (issue 34)
        there = p.exists() or p.is_symlink()
        raise ConfigError(p, "not a regular file" if there else "configuration file does not exist")
    try:
        data = yaml.safe_load(p.read_text()) or {}
    except yaml.YAMLError as exc:
        raise ConfigError(p, f"not valid YAML ({str(exc).splitlines()[0]})") from None
    except UnicodeDecodeError:  # random bytes
        raise ConfigError(p, "not a UTF-8 YAML text file") from None
    except OSError as exc:  # a FIFO, no permission
        raise ConfigError(p, f"cannot read the configuration: {exc.strerror}") from None
    if not isinstance(data, dict):
        raise ConfigError(p, "expected a mapping of sections at the top level")
    return data


#: Top-level sections that configure other commands than the pipeline (``eval``, ``bound``,
#: ``simulate``, ``vvs``); a run's ``config.yaml`` holds every other section.
TOOL_SECTIONS: tuple[str, ...] = ("eval", "accuracy", "simulation", "vvs")


def pipeline_sections() -> tuple[str, ...]:
    """The sections the pipeline (``loopmodel run``, :func:`loopmodel.run`) reads."""
    return tuple(k for k in Config.model_fields if k not in TOOL_SECTIONS)


def dump_config(config: Config, sections: tuple[str, ...] | None = None) -> str:
    """The configuration as YAML text (every key, defaults included).

    Or only the named top-level ``sections``.
    """
    data = config.model_dump(mode="json")
    if sections is not None:
        data = {k: data[k] for k in sections}
    return yaml.safe_dump(data, sort_keys=False)
