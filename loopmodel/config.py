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


class BackendConfig(_Section):
    """Keyframe/landmark back end (``backend/``); iSAM2 keys map onto ``gtsam.ISAM2Params``."""

    kind: str = Field("isam2", pattern="^(isam2|givens)$", description="which back end runs")
    pixel_sigma_px: float = Field(1.0, gt=0, description="std. dev. of an image coordinate")
    huber_k: float = Field(
        3.0, ge=0, description="Huber threshold in sigmas (0: Gaussian); weights kept until relin."
    )
    prior_sigma_rad: float = Field(1e-6, gt=0, description="gauge prior, first keyframe")
    prior_sigma_m: float = Field(1e-6, gt=0, description="gauge prior, first keyframe")
    segment_prior_sigma_rad: float = Field(
        1.0, gt=0, description="prior on a keyframe not linked to the previous one"
    )
    segment_prior_sigma_m: float = Field(
        10.0, gt=0, description="prior on a keyframe not linked to the previous one"
    )
    loop_sigma_rad: float = Field(0.01, gt=0, description="default loop-constraint sigma")
    loop_sigma_m: float = Field(0.01, gt=0, description="default loop-constraint sigma")
    min_disparity_px: float = Field(2.0, ge=0, description="stereo observations below: dropped")
    min_observations: int = Field(2, ge=1, description="a landmark enters once seen this often")
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
    relinearize_threshold_rad: float = Field(0.002, gt=0, description="pose rotation")
    relinearize_threshold_m: float = Field(0.01, gt=0, description="pose position")
    relinearize_threshold_landmark_m: float = Field(0.05, gt=0, description="landmark position")
    relinearize_skip: int = Field(1, ge=1, description="check relinearisation every N updates")
    partial_relinearization_check: bool = Field(
        False, description="check relinearisation only in the cliques an update touches"
    )
    wildfire_threshold: float = Field(0.001, ge=0, description="back-substitution stop")
    factorization: str = Field("CHOLESKY", pattern="^(CHOLESKY|QR)$")
    order_poses_chronologically: bool = Field(
        True, description="eliminate landmarks first, then poses oldest to newest"
    )
    change_tolerance_m: float = Field(
        1e-4, ge=0, description="estimate(): a keyframe counts as changed above this"
    )


class Config(_Section):
    """The whole configuration of loopmodel."""

    sequence: SequenceConfig = Field(default_factory=SequenceConfig)
    output: OutputConfig = Field(default_factory=OutputConfig)
    backend: BackendConfig = Field(default_factory=BackendConfig)


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
