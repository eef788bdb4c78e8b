"""Image file helpers shared by the folder readers."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
from numpy.typing import NDArray

from loopmodel.errors import InputError


def read_image(path: Path) -> NDArray[np.uint8]:
    """Read an image file unchanged (grey stays HxW).

    A clear error when unreadable or when its header declares more than ``MAX_IMAGE_PIXELS``.
    """
    check_image_file_header(path)
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


#: Default limit of an image's declared pixel count (width * height) before it is decoded:
#: 10^8 px (e.g. 12000 x 8000), about 300 MB decoded in colour. ``sequence.max_image_pixels``.
MAX_IMAGE_PIXELS = 100_000_000


def declared_image_size(header: bytes) -> tuple[int, int] | None:
    """(width, height) a PNG or JPEG stream declares in its header (None: another format,
    or no size found in ``header``). Reads only the bytes given (PNG: 24; JPEG: up to the
    first start-of-frame marker)."""
    if header[:8] == b"\x89PNG\r\n\x1a\n" and len(header) >= 24 and header[12:16] == b"IHDR":
        return int.from_bytes(header[16:20], "big"), int.from_bytes(header[20:24], "big")
    if header[:2] == b"\xff\xd8":
        i = 2
        while i + 9 <= len(header):
            if header[i] != 0xFF:
                return None
            marker = header[i + 1]
            if marker in (0xD8, 0x01) or 0xD0 <= marker <= 0xD7:  # no length field
                i += 2
                continue
            seg_len = int.from_bytes(header[i + 2 : i + 4], "big")
            if 0xC0 <= marker <= 0xCF and marker not in (0xC4, 0xC8, 0xCC):  # SOFn
                h = int.from_bytes(header[i + 5 : i + 7], "big")
                w = int.from_bytes(header[i + 7 : i + 9], "big")
                return w, h
            i += 2 + seg_len
    return None


def check_declared_size(width: int, height: int, limit_px: int, source: str | Path) -> None:
    """Raise :class:`InputError` when ``width * height`` is zero or above ``limit_px``."""
    if width <= 0 or height <= 0:
        raise InputError(source, f"image declares {width}x{height} pixels")
    if width * height > limit_px:
        raise InputError(
            source,
            f"image declares {width}x{height} = {width * height} pixels, above the limit of {limit_px} "
            "(sequence.max_image_pixels)",
        )


def check_image_file_header(path: Path, limit_px: int = MAX_IMAGE_PIXELS) -> None:
    """Check the size a PNG/JPEG file declares before it is decoded."""
    try:
        with open(path, "rb") as f:
            head = f.read(1 << 16)
    except OSError as exc:
        raise InputError(path, f"cannot read image: {exc.strerror}") from None
    size = declared_image_size(head)
    if size is not None:
        check_declared_size(size[0], size[1], limit_px, path)
