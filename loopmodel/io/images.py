"""Image file helpers shared by the folder readers."""

from __future__ import annotations

import os
import threading
from collections.abc import Callable
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from loopmodel.errors import InputError
from loopmodel.imaging.codec import SIZED_FORMATS, declared_image_size, decode_quietly, is_sized_format
from loopmodel.io.text import require_regular_file
from loopmodel.types import StereoFrame

__all__ = ["declared_image_size", "decode_quietly"]  # re-exported: the readers' callers use them from here


def read_image(path: Path, limit_px: int | None = None) -> NDArray[np.uint8]:
    """Read an image file as 8 bits (grey stays HxW, colour BGR HxWx3; 16-bit scaled by 1/256).

    A clear error when it is not a regular file (a FIFO would block), unreadable, or when its
    header declares more than ``limit_px`` (default ``MAX_IMAGE_PIXELS``) pixels; nothing is
    decoded before that check.
    """
    data = read_image_bytes(path)
    check_image_bytes(data, MAX_IMAGE_PIXELS if limit_px is None else limit_px, path)
    return decode_image(data, path)


def decode_image(data: bytes, source: str | Path) -> NDArray[np.uint8]:
    """:func:`read_image`'s decoding of an image file's bytes (checked by :func:`check_image_bytes`)."""
    img = decode_quietly(data) if data else None
    if img is None:
        raise InputError(source, "cannot read image (corrupt or of an unknown format)")
    return image_to_uint8(np.asarray(img), source)


def read_grey_image(path: Path, limit_px: int | None = None) -> NDArray[np.uint8]:
    """:func:`read_image` as 8-bit grey (HxW); the same checks before decoding."""
    img = read_image(path, limit_px)
    return np.asarray(cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)) if img.ndim == 3 else img


def image_to_uint8(img: NDArray[Any], source: str | Path) -> NDArray[np.uint8]:
    """8-bit grey (HxW) or BGR (HxWx3) from a decoded image.

    16-bit: the high byte (the ROS readers' convention); BGRA: alpha dropped; anything else
    (floating point, 2 channels) refused with a line naming ``source``.
    """
    if img.dtype == np.uint16:
        img = (img >> 8).astype(np.uint8)
    if img.dtype != np.uint8:
        raise InputError(source, f"image of {img.dtype} pixels; expected 8 or 16 bits")
    if img.ndim == 3 and img.shape[2] == 1:
        img = img[:, :, 0]
    if img.ndim == 3 and img.shape[2] == 4:
        img = cv2.cvtColor(img, cv2.COLOR_BGRA2BGR)
    if not (img.ndim == 2 or (img.ndim == 3 and img.shape[2] == 3)):
        raise InputError(source, f"image of shape {img.shape}; expected grey or 3-channel colour")
    return np.asarray(img)


#: Image files larger than this are refused before reading (a 10^8 px BGR PNG is ~300 MB at most).
MAX_IMAGE_FILE_BYTES = 1 << 30


def read_image_bytes(path: Path) -> bytes:
    """The bytes of an image file: a regular file only, at most ``MAX_IMAGE_FILE_BYTES``."""
    st = require_regular_file(path, "image file")
    if st.st_size > MAX_IMAGE_FILE_BYTES:
        raise InputError(path, f"image file of {st.st_size} bytes is larger than {MAX_IMAGE_FILE_BYTES}")
    try:
        # O_NONBLOCK: were it replaced by a FIFO since the check, open() must not block
        fd = os.open(path, os.O_RDONLY | getattr(os, "O_NONBLOCK", 0))
        with os.fdopen(fd, "rb") as f:
            return f.read(MAX_IMAGE_FILE_BYTES + 1)
    except OSError as exc:
        raise InputError(path, f"cannot read image: {exc.strerror or type(exc).__name__}") from None


def image_size(path: Path, limit_px: int | None = None) -> tuple[int, int]:
    """(width, height) of an image file."""
    img = read_image(path, limit_px)
    return int(img.shape[1]), int(img.shape[0])


def read_image_of_size(path: Path, size: tuple[int, int], limit_px: int | None = None) -> NDArray[np.uint8]:
    """Read an image and check it is ``size`` = (width, height) pixels."""
    return _of_size(read_image(path, limit_px), size, path)


def _of_size(img: NDArray[np.uint8], size: tuple[int, int], source: str | Path) -> NDArray[np.uint8]:
    if (img.shape[1], img.shape[0]) != size:
        raise InputError(source, f"image size {img.shape[1]}x{img.shape[0]}, expected {size[0]}x{size[1]}")
    return img


def decode_of_size(data: bytes, path: Path, size: tuple[int, int]) -> NDArray[np.uint8]:
    """The image file ``path``'s bytes ``data`` decoded, of ``size`` (width, height) (else :class:`InputError`)."""
    return _of_size(decode_image(data, path), size, path)


class DeferredRightFrame(StereoFrame):
    """A :class:`StereoFrame` whose right image is decoded when first used.

    The front end uses a right image only at a keyframe (its stereo matching, on the keyframe's
    stereo thread), so the other frames' right images are read and their declared size checked
    (:func:`check_image_bytes`) with the frame, but never decoded: a PNG decode costs 3.8 ms of CPU
    per KITTI clip image. A corrupt right image raises :class:`InputError` naming its file (or topic)
    where it is first used. Pickles as a plain :class:`StereoFrame` (decoded).
    """

    def __init__(
        self, timestamp_ns: int, left: NDArray[np.uint8], right: NDArray[np.uint8] | None = None, index: int = 0,
        *, right_decode: Callable[[], NDArray[np.uint8]] | None = None,
    ) -> None:
        """The right image, or a function that decodes it (a file's: :func:`decode_of_size`; an MCAP message's).

        ``right_decode`` raises :class:`InputError` for a bad image.
        """
        if right is None and right_decode is None:
            raise ValueError("DeferredRightFrame needs the right image or its decoder")
        self.timestamp_ns, self.left, self.index = timestamp_ns, left, index
        self._right, self._decode, self._lock = right, right_decode, threading.Lock()

    @property  # type: ignore[override]
    def right(self) -> NDArray[np.uint8]:
        """The right image (8-bit grey or BGR), decoded at the first use."""
        with self._lock:
            if self._right is None:
                assert self._decode is not None
                self._right, self._decode = self._decode(), None
            return self._right

    @right.setter
    def right(self, value: NDArray[np.uint8]) -> None:
        with self._lock:
            self._right, self._decode = value, None

    @property
    def right_decoded(self) -> bool:
        """Whether the right image has been decoded (or was given)."""
        return self._right is not None

    def __reduce__(self) -> tuple[Any, ...]:
        return (StereoFrame, (self.timestamp_ns, self.left, self.right, self.index))


#: Default limit of an image's declared pixel count (width * height) before it is decoded:
#: 10^8 px (e.g. 12000 x 8000), about 300 MB decoded in colour. ``sequence.max_image_pixels``.
MAX_IMAGE_PIXELS = 100_000_000


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


def check_image_bytes(data: bytes | NDArray[np.uint8], limit_px: int, source: str | Path) -> None:
    """Refuse an encoded image before decoding.

    A declared size above ``limit_px``, a PNG/JPEG/BMP/PNM/TIFF whose header names no size (a
    decoder skipping damaged bytes could still find a huge one), or another format (its size is
    not read here).
    """
    raw = data.tobytes() if isinstance(data, np.ndarray) else bytes(data)
    size = declared_image_size(raw)
    if size is not None:
        check_declared_size(size[0], size[1], limit_px, source)
    elif is_sized_format(raw):
        raise InputError(source, "damaged image header (no image size before the image data)")
    elif raw:  # WebP, GIF, JPEG 2000, ...: a decoder would allocate what they declare, unchecked
        raise InputError(source, f"cannot read image (corrupt or of an unknown format; {SIZED_FORMATS} are read)")


def check_image_file_header(path: Path, limit_px: int = MAX_IMAGE_PIXELS) -> None:
    """Check the size a PNG/JPEG file declares before it is decoded."""
    size = declared_image_size(read_image_bytes(path))
    if size is not None:
        check_declared_size(size[0], size[1], limit_px, path)
