"""Compiled PNG row unfiltering for :func:`loopmodel.imaging.codec.decode_png_8bit` (numba, GIL released)."""

from __future__ import annotations

import numba
import numpy as np


def _paeth_py(a, b, c):  # type: ignore[no-untyped-def]
    """The Paeth predictor of left ``a``, above ``b`` and upper-left ``c``."""
    p = a + b - c
    pa, pb, pc = abs(p - a), abs(p - b), abs(p - c)
    if pa <= pb and pa <= pc:
        return a
    if pb <= pc:
        return b
    return c


_paeth = numba.njit(cache=True, nogil=True, inline="always")(_paeth_py)


def _average_paeth_row_py(raw, src, out, o, up, y, row_bytes, bpp, ft):  # type: ignore[no-untyped-def]
    """Filters 3 (Average) and 4 (Paeth): predictors from the left, above and upper-left bytes."""
    a = np.int32(0)
    for x in range(row_bytes):
        if bpp != 1:
            a = np.int32(out[o + x - bpp]) if x >= bpp else np.int32(0)
        b = np.int32(out[up + x]) if y > 0 else np.int32(0)
        if ft == 3:
            pred = (a + b) >> 1
        else:
            c = np.int32(out[up + x - bpp]) if (x >= bpp and y > 0) else np.int32(0)
            pred = _paeth(a, b, c)
        a = (np.int32(raw[src + x]) + pred) & 0xFF
        out[o + x] = a


_average_paeth_row = numba.njit(cache=True, nogil=True, inline="always")(_average_paeth_row_py)


def _unfilter_py(raw, height, row_bytes, bpp):  # type: ignore[no-untyped-def]
    """The image bytes (height, row_bytes) of inflated PNG scanlines ``raw`` (a filter byte, then the row).

    Filters 0-4 of the PNG specification (None, Sub, Up, Average, Paeth) with ``bpp`` bytes per
    pixel, arithmetic modulo 256. Returns (image, ok); ok is False for an unknown filter type. The
    left neighbour of a one-byte pixel is kept in a register (the chain along the row is the cost).
    The Average and Paeth rows are a helper inlined here (issue 32: every per-frame function at complexity <= 12).
    """
    out = np.empty(height * row_bytes, np.uint8)
    stride = row_bytes + 1
    for y in range(height):
        ft = raw[y * stride]
        src = y * stride + 1
        o = y * row_bytes
        up = o - row_bytes  # the row above (y > 0)
        if ft == 0 or (ft == 2 and y == 0):
            for x in range(row_bytes):
                out[o + x] = raw[src + x]
        elif ft == 1:
            if bpp == 1:
                a = np.int32(0)
                for x in range(row_bytes):
                    a = (a + np.int32(raw[src + x])) & 0xFF
                    out[o + x] = a
            else:
                for x in range(bpp):
                    out[o + x] = raw[src + x]
                for x in range(bpp, row_bytes):
                    out[o + x] = (np.int32(raw[src + x]) + np.int32(out[o + x - bpp])) & 0xFF
        elif ft == 2:
            for x in range(row_bytes):
                out[o + x] = (np.int32(raw[src + x]) + np.int32(out[up + x])) & 0xFF
        elif ft == 3 or ft == 4:
            _average_paeth_row(raw, src, out, o, up, y, row_bytes, bpp, ft)
        else:
            return out.reshape(height, row_bytes), False
    return out.reshape(height, row_bytes), True


unfilter = numba.njit(cache=True, nogil=True)(_unfilter_py)


def warm_up() -> None:
    """Compile (or load from numba's cache) the kernel with the argument types it is called with.

    The decoder passes the inflated bytes as a read-only array (``np.frombuffer``): a writable one is
    another signature, which every cold run compiled at its first image (fin13: 1.4 s).
    """
    unfilter(np.frombuffer(bytes(4), np.uint8), 1, 3, 1)
