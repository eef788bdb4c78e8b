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


class LoopConfig(_Section):
    """Appearance-based relocalization and loop closing (``loopmodel.loop``)."""

    enabled: bool = True
    descriptor: str = Field("orb", pattern="^(orb|sift|surf)$", description="orb, sift or surf")
    n_features: int = Field(1500, ge=50, description="features per keyframe")
    ratio: float = Field(0.8, gt=0, le=1, description="Lowe ratio of descriptor matching")
    vocabulary_path: str | None = Field(None, description="trained vocabulary .npz; None: on the fly")
    vocabulary_branching: int = Field(8, ge=2)
    vocabulary_levels: int = Field(4, ge=1)
    min_gap_keyframes: int = Field(10, ge=1, description="recent keyframes never loop candidates")
    consistency: int = Field(2, ge=1, description="consecutive agreeing queries before a loop")
    min_score: float = Field(0.01, ge=0)
    threshold_px: float = Field(2.0, gt=0, description="P3P inlier bound (pixels)")
    min_inliers: int = Field(25, ge=6)
    min_inlier_ratio: float = Field(0.25, gt=0, le=1)
    max_samples: int = Field(4096, ge=64, description="P3P bank minimal samples per query")
    min_epipolar_inliers: int = Field(40, ge=8, description="monocular verification")
    max_cycle_rot_deg: float = Field(2.0, gt=0, description="forward/reverse pose agreement")
    max_cycle_trans_m: float = Field(0.05, gt=0)
    background_ba: bool = Field(True, description="global BA in a worker process")


class Config(_Section):
    """The whole configuration of loopmodel."""

    sequence: SequenceConfig = Field(default_factory=SequenceConfig)
    output: OutputConfig = Field(default_factory=OutputConfig)
    eval: EvalConfig = Field(default_factory=EvalConfig)
    loop: LoopConfig = Field(default_factory=LoopConfig)


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
