"""The PNG fast path (:func:`loopmodel.imaging.codec.decode_png_8bit`) against OpenCV's decoder."""

from __future__ import annotations

import struct
import zlib
from pathlib import Path

import cv2
import numpy as np
import pytest

from loopmodel.imaging.codec import decode_png_8bit, decode_quietly


def _chunk(kind: bytes, body: bytes) -> bytes:
    return struct.pack(">I", len(body)) + kind + body + struct.pack(">I", zlib.crc32(kind + body))


def _filtered_row(row: np.ndarray, above: np.ndarray, ft: int, bpp: int) -> bytes:
    """One scanline filtered with PNG filter ``ft`` (written from the specification, independent of the decoder)."""
    x = row.astype(np.int64)
    a = np.concatenate([np.zeros(bpp, np.int64), x[:-bpp]])
    b = above.astype(np.int64)
    c = np.concatenate([np.zeros(bpp, np.int64), b[:-bpp]])
    if ft == 0:
        pred = np.zeros_like(x)
    elif ft == 1:
        pred = a
    elif ft == 2:
        pred = b
    elif ft == 3:
        pred = (a + b) // 2
    else:
        p = a + b - c
        pa, pb, pc = np.abs(p - a), np.abs(p - b), np.abs(p - c)
        pred = np.where((pa <= pb) & (pa <= pc), a, np.where(pb <= pc, b, c))
    return bytes([ft]) + ((x - pred) % 256).astype(np.uint8).tobytes()


def _encode(img: np.ndarray, filters: list[int], extra: list[bytes] | None = None) -> bytes:
    """A PNG of an 8-bit grey (H, W) or RGB (H, W, 3) image, row y filtered with ``filters[y % len]``."""
    h, w = img.shape[:2]
    bpp = 1 if img.ndim == 2 else 3
    rows = img.reshape(h, w * bpp)
    raw = b"".join(
        _filtered_row(rows[y], rows[y - 1] if y else np.zeros(w * bpp, np.uint8), filters[y % len(filters)], bpp)
        for y in range(h)
    )
    ihdr = struct.pack(">IIBBBBB", w, h, 8, 0 if bpp == 1 else 2, 0, 0, 0)
    body = zlib.compress(raw, 6)
    idat = [_chunk(b"IDAT", body[: len(body) // 2]), _chunk(b"IDAT", body[len(body) // 2 :])]  # two IDATs
    return b"\x89PNG\r\n\x1a\n" + _chunk(b"IHDR", ihdr) + b"".join(extra or []) + b"".join(idat) + _chunk(b"IEND", b"")


def _stream(width: int, height: int, colour: int, raw: bytes) -> bytes:
    """A PNG of 8-bit samples of colour type ``colour`` whose scanlines (filter bytes included) are ``raw``."""
    ihdr = struct.pack(">IIBBBBB", width, height, 8, colour, 0, 0, 0)
    return b"\x89PNG\r\n\x1a\n" + _chunk(b"IHDR", ihdr) + _chunk(b"IDAT", zlib.compress(raw)) + _chunk(b"IEND", b"")


def _opencv(data: bytes) -> np.ndarray | None:
    return cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)


@pytest.mark.parametrize("channels", [1, 3])
def test_every_filter_type_as_opencv(channels: int) -> None:
    rng = np.random.default_rng(3)
    base = cv2.GaussianBlur(rng.integers(0, 256, (37, 53), dtype=np.uint8), (5, 5), 0)
    img = base if channels == 1 else np.dstack([base, 255 - base, rng.integers(0, 256, base.shape, dtype=np.uint8)])
    for filters in ([0], [1], [2], [3], [4], [4, 3, 2, 1, 0]):
        data = _encode(img, filters)
        ours, ref = decode_png_8bit(data), _opencv(data)
        assert ref is not None and ours is not None
        assert ours.dtype == ref.dtype and ours.shape == ref.shape
        assert np.array_equal(ours, ref), filters


def test_real_images_and_opencv_encodings(shared_data: Path) -> None:
    """KITTI's PNGs (Sub rows) and OpenCV's own encodings of them (adaptive: Sub, Average, Paeth), grey and colour."""
    kitti = shared_data / "kitti_clip"
    files = sorted((kitti / "image_l").glob("*.png"))[:3] + sorted((kitti / "image_r").glob("*.png"))[:2]
    assert files
    for f in files:
        data = f.read_bytes()
        assert np.array_equal(decode_png_8bit(data), _opencv(data))
    grey = _opencv(files[0].read_bytes())
    assert grey is not None
    colour = np.dstack([grey, np.roll(grey, 3, axis=1), 255 - grey])
    for img in (grey, colour):
        for level in (1, 9):
            data = cv2.imencode(".png", img, [cv2.IMWRITE_PNG_COMPRESSION, level])[1].tobytes()
            ours = decode_png_8bit(data)
            assert ours is not None and np.array_equal(ours, _opencv(data)) and np.array_equal(ours, img)
            assert np.array_equal(decode_quietly(np.frombuffer(data, np.uint8)), img)  # an array given


def test_other_pngs_and_damage_go_to_opencv() -> None:
    """What the fast path does not take (None) decodes as OpenCV decodes it, errors included."""
    rng = np.random.default_rng(4)
    img = rng.integers(0, 256, (9, 11), dtype=np.uint8)
    good = _encode(img, [1])
    others = {
        "16-bit": cv2.imencode(".png", img.astype(np.uint16) * 257)[1].tobytes(),
        "grey and alpha": _stream(11, 9, 4, b"".join(b"\x00" + np.repeat(img[y], 2).tobytes() for y in range(9))),
        "RGBA": cv2.imencode(".png", np.dstack([img, img, img, img]))[1].tobytes(),
        "transparency": _encode(img, [1], [_chunk(b"tRNS", b"\x00\x07")]),
        "bad CRC": good[:-20] + bytes([good[-20] ^ 1]) + good[-19:],
        "truncated": good[: len(good) - 30],
        "JPEG": cv2.imencode(".jpg", img)[1].tobytes(),
    }
    for name, data in others.items():
        assert decode_png_8bit(data) is None, name
        ref = _opencv(data)
        ours = decode_quietly(data)
        assert (ours is None and ref is None) or np.array_equal(ours, ref), name
    # an unknown filter type (7) in an otherwise valid stream
    bad = _stream(11, 9, 0, b"".join(b"\x07" + img[y].tobytes() for y in range(img.shape[0])))
    assert decode_png_8bit(bad) is None
    assert decode_quietly(bad) is None and _opencv(bad) is None
    assert np.array_equal(decode_png_8bit(good), img)


def test_a_stream_longer_than_the_image_is_not_inflated_whole() -> None:
    """A small file whose stream inflates far beyond its declared size goes to OpenCV (as libpng, it stops there)."""
    img = np.zeros((9, 11), np.uint8)
    raw = b"".join(b"\x00" + img[y].tobytes() for y in range(9)) + bytes(5_000_000)
    data = _stream(11, 9, 0, raw)
    assert len(data) < 20_000
    assert decode_png_8bit(data) is None
    ref = _opencv(data)
    ours = decode_quietly(data)
    assert (ours is None and ref is None) or np.array_equal(ours, ref)
