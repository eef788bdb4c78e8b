"""Mapping: laser-stripe extraction, stripe-to-world integration, open3d meshing, accuracy."""

from loopmodel.mapping.extraction import (
    LightPlane,
    extract_laser_peaks,
    stripe_from_image,
    triangulate_with_plane,
)
from loopmodel.mapping.stripe_map import StripeMap

__all__ = [
    "LightPlane",
    "StripeMap",
    "extract_laser_peaks",
    "stripe_from_image",
    "triangulate_with_plane",
]
