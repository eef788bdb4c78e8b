"""Image file helpers shared by the folder readers."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
from numpy.typing import NDArray

from loopmodel.errors import InputError


def read_image(path: Path) -> NDArray[np.uint8]:
    """Read an image file unchanged (grey stays HxW); a clear error when unreadable."""
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise InputError(path, "cannot read image (missing or corrupt)")
    return np.asarray(img)


def image_size(path: Path) -> tuple[int, int]:
    """(width, height) of an image file."""
    img = read_image(path)
    return int(img.shape[1]), int(img.shape[0])


def read_image_of_size(path: Path, size: tuple[int, int]) -> NDArray[np.uint8]:
    """Read an image and check it is ``size`` = (width, height) pixels."""
    img = read_image(path)
    if (img.shape[1], img.shape[0]) != size:
        raise InputError(path, f"image size {img.shape[1]}x{img.shape[0]}, expected {size[0]}x{size[1]}")
    return img
