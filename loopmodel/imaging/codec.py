"""Encoded image bytes: the size a PNG/JPEG header declares, and decoding without the libraries' own lines.

No files are read here (the readers in ``io/`` and a session map's stored keyframe images use it).
"""

from __future__ import annotations

import os
import sys
import tempfile
import threading
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


def decode_quietly(data: bytes | NDArray[np.uint8], flags: int = cv2.IMREAD_UNCHANGED) -> NDArray[Any] | None:
    """``cv2.imdecode`` without libpng's and libjpeg's own lines on stderr (issue 34).

    The process's stderr goes to a temporary file while the image decodes; what others wrote there
    in the meantime is copied back, the libraries' lines are dropped (the caller's one line says
    what went wrong).
    """
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
