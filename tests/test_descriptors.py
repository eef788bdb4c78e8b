"""The descriptor registry (issue 32): one module per kind, one place the config, features and map use."""

from __future__ import annotations

from typing import get_args

import cv2
import numpy as np
import pytest

from loopmodel.config import DescriptorKind, LoopConfig
from loopmodel.errors import ConfigError
from loopmodel.loop.descriptors import DESCRIPTORS, descriptor
from loopmodel.loop.features import describe_at, detect_and_describe, empty_features, make_extractor


def _texture() -> np.ndarray:
    """A seeded blob texture, 240 x 320 grey: corners and blobs for every detector."""
    rng = np.random.default_rng(11)
    img = cv2.GaussianBlur(rng.uniform(0, 255, (60, 80)).astype(np.float32), (0, 0), 1.0)
    img = cv2.resize(img, (320, 240), interpolation=cv2.INTER_CUBIC)
    return np.clip((img - img.min()) / (np.ptp(img) + 1e-9) * 255, 0, 255).astype(np.uint8)


def test_the_config_accepts_exactly_the_registered_kinds() -> None:
    assert set(get_args(DescriptorKind)) == set(DESCRIPTORS)
    for kind in DESCRIPTORS:
        assert LoopConfig(descriptor=kind).descriptor == kind
    with pytest.raises(ConfigError, match="unknown descriptor 'brisk'"):
        descriptor("brisk")


@pytest.mark.parametrize("kind", sorted(DESCRIPTORS))
def test_each_kind_gives_the_descriptors_its_entry_declares(kind: str) -> None:
    d = descriptor(kind)
    img = _texture()
    ex = make_extractor(kind, 300, LoopConfig().surf)
    fs = detect_and_describe(img, kind, 300, ex)
    assert fs.kind == kind and 20 <= len(fs) <= 300
    assert fs.descriptors.shape[1] == d.dim and fs.descriptors.dtype == d.dtype and fs.binary == d.binary
    assert np.all(fs.laplacian != 0) == (kind == "surf")  # only SURF carries Laplacian signs
    # described again at its own detected positions: the same number of features (border ones may go)
    again, kept = describe_at(img, fs.keypoints_px, kind, extractor=ex)
    assert again.descriptors.shape[1] == d.dim and np.array_equal(again.keypoints_px, fs.keypoints_px[kept])
    assert kept.size >= 0.5 * len(fs)
    none = empty_features(kind)
    assert len(none) == 0 and none.descriptors.shape == (0, d.dim) and none.descriptors.dtype == d.dtype
