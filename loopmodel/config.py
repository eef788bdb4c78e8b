"""Typed configuration: one nested pydantic model with defaults in code.

A YAML file overrides any part of it; an unknown key is an error that names the key.
Every run writes the effective configuration into its results folder.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError

from loopmodel.errors import ConfigError


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


class OutputConfig(_Section):
    """Where and what a run writes."""

    out_dir: str = "results"
    write_kitti: bool = False
    image_format: str = Field("png", pattern="^(raw|png|jpeg)$", description="MCAP image encoding")


class FrontendConfig(_Section):
    """Stereo keyframe front end: detection, stereo matching, KLT, robust pose, keyframes."""

    # keyframe features (rectified left image)
    max_features: int = Field(800, ge=10, description="corners per keyframe (before stereo)")
    grid_cols: int = Field(8, ge=1, description="detection grid columns (bucketing)")
    grid_rows: int = Field(4, ge=1, description="detection grid rows (bucketing)")
    gftt_quality: float = Field(0.005, gt=0, lt=1, description="Shi-Tomasi quality, per cell")
    min_distance_px: float = Field(10.0, gt=0, description="minimum corner spacing")
    border_px: int = Field(12, ge=0, description="no corners this close to the image border")
    # stereo row search (rectified pair)
    patch_px: int = Field(11, ge=3, description="matching window (odd)")
    min_disparity_px: float = Field(1.0, ge=0, description="reject matches below (far points)")
    max_disparity_px: float = Field(160.0, gt=0, description="search range along the row")
    min_zncc: float = Field(0.7, ge=-1, le=1, description="minimum normalised correlation")
    lr_tolerance_px: float = Field(1.0, gt=0, description="left-right consistency tolerance")
    max_row_error_px: float = Field(1.0, ge=0, description="max vertical offset of the match")
    max_depth_m: float = Field(200.0, gt=0, description="reject triangulated points beyond")
    min_stereo_points: int = Field(30, ge=6, description="fewest points for a keyframe")
    # KLT
    klt_window_px: int = Field(15, ge=5, description="Lucas-Kanade window")
    klt_levels: int = Field(3, ge=0, description="pyramid levels above the base")
    klt_iterations: int = Field(10, ge=1)
    fb_threshold_px: float = Field(1.0, gt=0, description="forward-backward tolerance")
    # robust pose
    pose_loss: str = Field("tukey", pattern="^(tukey|huber)$")
    pose_min_scale_px: float = Field(0.5, gt=0, description="floor of the MAD scale")
    ransac_threshold_px: float = Field(2.0, gt=0)
    prediction_gate_px: float = Field(
        4.0, gt=0, description="prediction good enough to skip RANSAC"
    )
    pose_step_tolerance: float = Field(5e-5, gt=0, description="LM stops below this step (m, rad)")
    pose_max_iterations: int = Field(10, ge=1)
    pose_huber_warmup: int = Field(2, ge=0, description="Huber IRLS iterations before Tukey")
    pose_reweight_iterations: int = Field(4, ge=1, description="IRLS weight updates, then frozen")
    depth_weighting: bool = Field(True, description="down-weight points of uncertain stereo depth")
    disparity_sigma_px: float = Field(0.3, gt=0, description="stereo disparity noise (weighting)")
    # keyframe policy
    min_tracked_fraction: float = Field(0.5, gt=0, le=1, description="new keyframe below this")
    min_tracked: int = Field(100, ge=6, description="new keyframe below this many inliers")
    max_parallax_ratio: float = Field(0.25, gt=0, description="translation / median depth")
    max_rotation_deg: float = Field(20.0, gt=0, description="rotation since the keyframe")
    # tracking loss
    min_inliers: int = Field(20, ge=6, description="LOST below this many inliers")
    max_jump_m: float = Field(0.6, gt=0, description="LOST when the pose departs from the motion model by more")
    max_jump_deg: float = Field(15.0, gt=0)
    min_image_std: float = Field(4.0, ge=0, description="black/flat image threshold (grey levels)")
    min_sharpness: float = Field(2.0, ge=0, description="variance of the Laplacian (blur) threshold")
    max_retrack_frames: int = Field(5, ge=0, description="frames to try resuming on the old keyframe")
    # local hybrid keyframe BA (seed 004 eq. 1)
    local_ba: bool = True
    ba_iterations: int = Field(5, ge=1)
    ba_huber_px: float = Field(1.0, gt=0)
    ba_final_stereo: bool = Field(False, description="add the final right projections to eq. 1")


class EvalConfig(_Section):
    """Trajectory evaluation (``loopmodel eval``)."""

    align: str = Field(
        default="se3", pattern="^(se3|sim3|origin|none)$", description="alignment to ground truth"
    )
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


class VvsConfig(_Section):
    """Model-based tracking by virtual visual servoing (``loopmodel vvs``, seed 002)."""

    sample_step_px: float = Field(3.0, gt=0, description="spacing of edge samples on each conic")
    search_px: int = Field(10, ge=1, description="moving-edge search range along the normal")
    edge_noise_px: float = Field(0.15, ge=0, description="simulated edge noise before pixel rounding")
    loss: str = Field("tukey", pattern="^(tukey|huber|l2)$", description="M-estimator")
    huber_warmup: int = Field(1, ge=0, description="first VVS iterations with Huber")
    max_iterations: int = Field(20, ge=1)
    min_features: int = Field(20, ge=6, description="fewer matched edge points: tracking failure")
    lost_rot_deg: float = Field(5.0, gt=0, description="frame counted lost above this rotation error")
    lost_pos_mm: float = Field(50.0, gt=0, description="frame counted lost above this position error")


class Config(_Section):
    """The whole configuration of loopmodel."""

    sequence: SequenceConfig = Field(default_factory=SequenceConfig)
    output: OutputConfig = Field(default_factory=OutputConfig)
    frontend: FrontendConfig = Field(default_factory=FrontendConfig)
    eval: EvalConfig = Field(default_factory=EvalConfig)
    vvs: VvsConfig = Field(default_factory=VvsConfig)


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


def load_config(path: str | Path | None = None) -> Config:
    """Defaults overridden by the YAML file at ``path`` (when given)."""
    if path is None:
        return Config()
    p = Path(path)
    if not p.is_file():
        raise ConfigError(p, "configuration file does not exist")
    try:
        data = yaml.safe_load(p.read_text()) or {}
    except yaml.YAMLError as exc:
        raise ConfigError(p, f"not valid YAML ({str(exc).splitlines()[0]})") from None
    if not isinstance(data, dict):
        raise ConfigError(p, "expected a mapping of sections at the top level")
    return config_from_dict(data, p)


def dump_config(config: Config) -> str:
    """The configuration as YAML text (every key, defaults included)."""
    return yaml.safe_dump(config.model_dump(mode="json"), sort_keys=False)
