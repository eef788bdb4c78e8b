"""Encoded image bytes: the size a PNG/JPEG header declares, and decoding without the libraries' own lines.

No files are read here (the readers in ``io/`` and a session map's stored keyframe images use it).
"""

from __future__ import annotations

import os
import struct
import sys
import tempfile
import threading
import zlib
from collections.abc import Callable
from typing import Any, Literal

import cv2
import numpy as np
from numpy.typing import NDArray

_STDERR_LOCK = threading.Lock()
#: the file stderr goes to while an image decodes (one per process, opened at first use, emptied
#: after use when something was written: a temporary file per image cost 0.3-0.7 ms of CPU, issue 33)
_CAPTURE: dict[int, Any] = {}
#: lines the image libraries print on their own (libpng, libjpeg, OpenCV's log: a truncated BMP or
#: PGM gave "[ERROR:0@0.3] global loadsave.cpp ... can't read data" and an empty line)
_LIBRARY_NOISE = (b"libpng ", b"Corrupt JPEG", b"Premature end of JPEG", b"Invalid SOS", b"Bogus ", b"[ERROR:")


_inflater: Callable[[], Any]  # a zlib-compatible decompressobj factory
try:  # ISA-L's inflate: the same bytes, about twice as fast as zlib's (KITTI image 2.0 -> 1.0 ms)
    from isal.isal_zlib import decompressobj as _isal_inflater

    _inflater = _isal_inflater
except ImportError:  # pragma: no cover - a dependency; zlib when an install lacks it
    _inflater = zlib.decompressobj

_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
#: ancillary chunks that do not change the pixels OpenCV returns (no gamma or bit shifts applied
#: there); any other chunk sends the image to OpenCV
_PNG_IGNORED = frozenset(
    (b"gAMA", b"cHRM", b"sRGB", b"iCCP", b"pHYs", b"tEXt", b"zTXt", b"iTXt", b"tIME", b"bKGD", b"eXIf", b"hIST")
)


def decode_png_8bit(data: bytes | NDArray[np.uint8]) -> NDArray[np.uint8] | None:
    """An 8-bit grey or RGB non-interlaced PNG as ``cv2.imdecode(..., IMREAD_UNCHANGED)`` gives it.

    (H, W) grey or (H, W, 3) in OpenCV's BGR order, the same bytes as OpenCV (tests). Every chunk's
    CRC and the stream's checksum and length are checked; None for any other PNG, any chunk it does
    not know (transparency, palette, significant bits, an animation) and any damage, which the caller
    decodes with OpenCV (and its errors) instead. Cheaper than libpng (issue 36: a KITTI image 3.0 ->
    1.1 ms of CPU, 2.2 ms without ISA-L): ISA-L's inflate where installed, rows unfiltered in a compiled kernel.
    """
    mv = (np.ascontiguousarray(data, np.uint8).reshape(-1).data if isinstance(data, np.ndarray) else memoryview(data))
    mv = mv.cast("B")
    n = len(mv)
    if n < 45 or bytes(mv[:8]) != _PNG_SIGNATURE or bytes(mv[12:16]) != b"IHDR":
        return None
    width, height, depth, colour, method, filt, interlace = struct.unpack(">IIBBBBB", mv[16:29])
    if depth != 8 or colour not in (0, 2) or method or filt or interlace or not width or not height:
        return None
    channels = 1 if colour == 0 else 3
    parts = _png_data_chunks(mv)
    if parts is None:
        return None
    row_bytes = width * channels
    raw = _inflate(parts, height * (row_bytes + 1))
    if raw is None:
        return None
    from loopmodel.imaging._png_kernels import unfilter  # numba: imported when first needed

    img, ok = unfilter(np.frombuffer(raw, np.uint8), height, row_bytes, channels)
    if not ok:
        return None
    if channels == 1:
        return img
    return np.ascontiguousarray(img.reshape(height, width, 3)[:, :, ::-1])


def _png_data_chunks(mv: memoryview) -> list[memoryview] | None:
    """The IDAT chunks' data of a PNG, up to IEND; None for a bad CRC, a cut file or a chunk that changes pixels."""
    n = len(mv)
    parts: list[memoryview] = []
    at = 8
    while True:
        if at + 12 > n:
            return None
        (length,) = struct.unpack(">I", mv[at : at + 4])
        kind = bytes(mv[at + 4 : at + 8])
        end = at + 8 + length
        if end + 4 > n or zlib.crc32(mv[at + 4 : end]) != struct.unpack(">I", mv[end : end + 4])[0]:
            return None
        if kind == b"IDAT":
            parts.append(mv[at + 8 : end])
        elif kind == b"IEND":
            return parts
        elif at > 8 and kind not in _PNG_IGNORED:
            return None
        at = end + 4


def _inflate(parts: list[memoryview], size: int) -> bytes | None:
    """The zlib stream of ``parts`` inflated: exactly ``size`` bytes and complete, else None."""
    try:  # never more than the declared image (a small file can inflate to gigabytes); the stream complete
        inflater = _inflater()
        raw = inflater.decompress(b"".join(parts), size)
        if len(raw) != size or inflater.decompress(inflater.unconsumed_tail, 1) or not inflater.eof:
            return None
    except Exception:  # isal and zlib raise their own error types
        return None
    return bytes(raw)


def decode_quietly(data: bytes | NDArray[np.uint8], flags: int = cv2.IMREAD_UNCHANGED) -> NDArray[Any] | None:
    """``cv2.imdecode`` without libpng's and libjpeg's own lines on stderr (issue 34).

    The process's stderr goes to a temporary file while the image decodes; what others wrote there
    in the meantime is copied back, the libraries' lines are dropped (the caller's one line says
    what went wrong). An 8-bit grey or RGB PNG read unchanged is decoded by :func:`decode_png_8bit`
    (the same pixels, less CPU).
    """
    if flags == cv2.IMREAD_UNCHANGED:
        fast = decode_png_8bit(data)
        if fast is not None:
            return fast
    buf = np.frombuffer(data, np.uint8) if isinstance(data, bytes | bytearray) else data
    with _STDERR_LOCK:
        try:
            sys.stderr.flush()
            saved = os.dup(2)
        except (OSError, ValueError, AttributeError):  # no stderr to guard
            return cv2.imdecode(buf, flags)
        pid = os.getpid()  # (a forked child opens its own)
        capture = _CAPTURE.get(pid)
        if capture is None:
            capture = _CAPTURE[pid] = tempfile.TemporaryFile()
        try:
            os.dup2(capture.fileno(), 2)
            img = cv2.imdecode(buf, flags)
        finally:
            os.dup2(saved, 2)
            os.close(saved)
        if os.fstat(capture.fileno()).st_size:
            capture.seek(0)
            lines = capture.read().splitlines(keepends=True)
            capture.seek(0)
            capture.truncate()
            others = [ln for ln in lines if ln.strip() and not ln.startswith(_LIBRARY_NOISE)]
            if others:
                os.write(2, b"".join(others))
    return img


def declared_image_size(header: bytes) -> tuple[int, int] | None:
    """(width, height) a PNG, JPEG, BMP, PNM or TIFF stream declares in its header.

    None: another format, or no size found in ``header``. Reads only the bytes given (PNG: 24; JPEG:
    up to the first start-of-frame marker, however far in: give the whole stream, APP segments
    of 64 KiB each may come before it; TIFF: its first image file directory).
    """
    if header[:8] == b"\x89PNG\r\n\x1a\n" and len(header) >= 24 and header[12:16] == b"IHDR":
        return int.from_bytes(header[16:20], "big"), int.from_bytes(header[20:24], "big")
    if header[:2] == b"\xff\xd8":
        i = 2
        while i + 9 <= len(header):
            if header[i] != 0xFF:
                return None
            marker = header[i + 1]
            if marker == 0xFF:  # fill byte before a marker
                i += 1
                continue
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
    if header[:2] == b"BM" and len(header) >= 26:  # BMP: a 1 KiB RLE file can declare 30000 x 30000 (issue 34)
        if int.from_bytes(header[14:18], "little") == 12:  # OS/2 core header: 16-bit sizes
            return int.from_bytes(header[18:20], "little"), int.from_bytes(header[20:22], "little")
        w = int.from_bytes(header[18:22], "little", signed=True)
        return w, abs(int.from_bytes(header[22:26], "little", signed=True))  # negative height: top-down
    if header[:1] == b"P" and header[1:2] in (b"1", b"2", b"3", b"4", b"5", b"6", b"7", b"F", b"f"):
        return _pnm_size(header[:4096])
    if header[:4] in (b"II*\0", b"MM\0*"):
        return _tiff_size(header)
    return None


#: formats whose declared size :func:`declared_image_size` reads (the others are not decoded)
SIZED_FORMATS = "PNG, JPEG, BMP, PNM, TIFF"


def is_sized_format(header: bytes) -> bool:
    """Whether ``header`` starts like a format of :data:`SIZED_FORMATS`."""
    return (
        header[:8] == b"\x89PNG\r\n\x1a\n"
        or header[:2] in (b"\xff\xd8", b"BM")
        or (header[:1] == b"P" and header[1:2] in (b"1", b"2", b"3", b"4", b"5", b"6", b"7", b"F", b"f"))
        or header[:4] in (b"II*\0", b"MM\0*")
    )


def _pnm_size(header: bytes) -> tuple[int, int] | None:
    """Netpbm (P1-P6, PFM): the first two numbers after the magic; PAM (P7): WIDTH and HEIGHT lines."""
    text = header.decode("latin-1")
    if text[1] == "7":
        fields = dict(ln.split(None, 1) for ln in text.splitlines()[1:] if len(ln.split(None, 1)) == 2)
        try:
            return int(fields["WIDTH"]), int(fields["HEIGHT"])
        except (KeyError, ValueError):
            return None
    tokens = [t for ln in text[2:].splitlines() for t in ln.split("#", 1)[0].split()][:2]
    if len(tokens) < 2 or not all(t.isdigit() for t in tokens):
        return None
    return int(tokens[0]), int(tokens[1])


def _tiff_size(data: bytes) -> tuple[int, int] | None:
    """ImageWidth (256) and ImageLength (257) of a TIFF's first image file directory."""
    order: Literal["little", "big"] = "little" if data[:2] == b"II" else "big"
    at = int.from_bytes(data[4:8], order)
    if at + 2 > len(data):
        return None
    n = int.from_bytes(data[at : at + 2], order)
    size: dict[int, int] = {}
    for k in range(n):
        e = data[at + 2 + 12 * k : at + 14 + 12 * k]
        if len(e) < 12:
            return None
        tag, typ = int.from_bytes(e[0:2], order), int.from_bytes(e[2:4], order)
        if tag in (256, 257):
            size[tag] = int.from_bytes(e[8:10], order) if typ == 3 else int.from_bytes(e[8:12], order)
    return (size[256], size[257]) if len(size) == 2 else None
