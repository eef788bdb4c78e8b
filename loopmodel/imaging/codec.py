"""Encoded image bytes: the size a PNG/JPEG header declares, and decoding without the libraries' own lines.

No files are read here (the readers in ``io/`` and a session map's stored keyframe images use it).
"""

from __future__ import annotations

import os
import sys
import tempfile
import threading
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

_STDERR_LOCK = threading.Lock()
#: lines the image libraries print on their own (libpng, libjpeg through OpenCV)
_LIBRARY_NOISE = (b"libpng ", b"Corrupt JPEG", b"Premature end of JPEG", b"Invalid SOS", b"Bogus ")


def decode_quietly(data: bytes | NDArray[np.uint8], flags: int = cv2.IMREAD_UNCHANGED) -> NDArray[Any] | None:
    """``cv2.imdecode`` without libpng's and libjpeg's own lines on stderr (issue 34).

    The process's stderr goes to a temporary file while the image decodes; what others wrote there
    in the meantime is copied back, the libraries' lines are dropped (the caller's one line says
    what went wrong).
    """
    buf = np.frombuffer(data, np.uint8) if isinstance(data, bytes | bytearray) else data
    with _STDERR_LOCK, tempfile.TemporaryFile() as capture:
        try:
            sys.stderr.flush()
            saved = os.dup(2)
        except (OSError, ValueError, AttributeError):  # no stderr to guard
            return cv2.imdecode(buf, flags)
        try:
            os.dup2(capture.fileno(), 2)
            img = cv2.imdecode(buf, flags)
        finally:
            os.dup2(saved, 2)
            os.close(saved)
        capture.seek(0)
        others = [ln for ln in capture.read().splitlines(keepends=True) if not ln.startswith(_LIBRARY_NOISE)]
        if others:
            os.write(2, b"".join(others))
    return img


def declared_image_size(header: bytes) -> tuple[int, int] | None:
    """(width, height) a PNG or JPEG stream declares in its header.

    None: another format, or no size found in ``header``. Reads only the bytes given (PNG: 24; JPEG:
    up to the first start-of-frame marker, however far in: give the whole stream, APP segments
    of 64 KiB each may come before it).
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
