"""Chessboard corners: detection with sub-pixel refinement, and the board's metric grid.

A board ``W x H`` names its inner corners (OpenCV ``patternSize``). Board frame: the first
detected corner at the origin, x along the first row, y along the columns, z = 0 on the
board (metres). Pixel coordinates follow OpenCV (centre of pixel (u, v) at (u, v)).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from numpy.typing import NDArray

from loopmodel.errors import InputError
from loopmodel.io.images import read_image

F64 = NDArray[np.float64]

#: cornerSubPix stop rule: 40 iterations or 1e-3 px.
SUBPIX_CRITERIA = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 40, 1e-3)
#: images larger than this (pixels, longer side) are searched at half size
DETECT_MAX_SIDE_PX = 1000


def parse_board(text: str, source: str = "--board") -> tuple[int, int]:
    """``"9x6"`` -> (9, 6) inner corners (each at least 2)."""
    parts = text.lower().replace("*", "x").split("x")
    try:
        w, h = (int(p) for p in parts)
    except ValueError:
        raise InputError(source, f"expected inner corners as WxH (e.g. 9x6), got '{text}'") from None
    if w < 2 or h < 2:
        raise InputError(source, f"a board needs at least 2x2 inner corners, got '{text}'")
    return w, h


def board_points(board: tuple[int, int], square_m: float) -> F64:
    """(W*H) x 3 board-frame corner positions (metres), in OpenCV's detection order."""
    w, h = board
    g = np.mgrid[0:w, 0:h].T.reshape(-1, 2).astype(np.float64)
    return np.column_stack([g * square_m, np.zeros(len(g))])


def grey_of(image: NDArray) -> NDArray[np.uint8]:  # type: ignore[type-arg]
    """8-bit grey image of a grey or BGR image."""
    img = np.asarray(image)
    if img.ndim == 3:
        img = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
    if img.dtype != np.uint8:
        img = cv2.normalize(img, None, 0, 255, cv2.NORM_MINMAX).astype(np.uint8)
    return np.asarray(img)


@dataclass
class Corners:
    """Corners found in one image: N x 2 pixels, the grid they span and its board positions."""

    path: str
    image_size: tuple[int, int]
    uv_px: F64
    grid: tuple[int, int]
    board_m: F64
    partial: bool = False


def _find(grey: NDArray[np.uint8], grid: tuple[int, int]) -> NDArray[np.float32] | None:
    flags = cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE
    ok, c = cv2.findChessboardCorners(grey, grid, flags=flags)
    if ok:
        return np.asarray(c, dtype=np.float32)
    return None


def _candidates(grey: NDArray[np.uint8]) -> list[NDArray[np.uint8]]:
    """The image as given, contrast-stretched, and locally equalised (dark real captures)."""
    stretched = cv2.normalize(grey, None, 0, 255, cv2.NORM_MINMAX)
    clahe = cv2.createCLAHE(2.0, (8, 8)).apply(grey)
    return [grey, np.asarray(stretched, dtype=np.uint8), np.asarray(clahe, dtype=np.uint8)]


def detect_corners(
    image: NDArray,  # type: ignore[type-arg]
    board: tuple[int, int],
    square_m: float,
    path: str = "",
    allow_partial: bool = False,
    min_partial: tuple[int, int] = (4, 4),
) -> Corners | None:
    """Chessboard corners refined to sub-pixel (``cv2.cornerSubPix``), or None.

    With ``allow_partial`` a board cut by the image border is accepted as its largest
    visible sub-grid (at least ``min_partial``): any part of the grid fixes the board's
    plane, which is all the laser-plane calibration needs.
    """
    grey = grey_of(image)
    size = (int(grey.shape[1]), int(grey.shape[0]))
    # large images: search on a half-size copy, refine at full resolution
    scale = 0.5 if max(size) > DETECT_MAX_SIDE_PX else 1.0
    small = cv2.resize(grey, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA) if scale != 1.0 else grey
    grids = [board]
    if allow_partial:
        w, h = board
        subs = [(a, b) for a in range(w, min_partial[0] - 1, -1) for b in range(h, min_partial[1] - 1, -1)]
        subs = sorted(set(subs) - {board}, key=lambda g: -g[0] * g[1])
        grids += subs
    for grid in grids:
        for cand in _candidates(small) if allow_partial else [small]:
            for g in (grid, grid[::-1]) if grid[0] != grid[1] else (grid,):
                c = _find(cand, g)
                if c is None:
                    continue
                c = (c / scale).astype(np.float32)
                # the refinement window scales with the square size in the image
                spacing = float(np.median(np.linalg.norm(np.diff(c.reshape(-1, 2), axis=0), axis=1)))
                half = int(np.clip(round(spacing / 4), 3, 11))
                c = cv2.cornerSubPix(grey, c, (half, half), (-1, -1), SUBPIX_CRITERIA)
                uv = c.reshape(-1, 2).astype(np.float64)
                return Corners(path, size, uv, g, board_points(g, square_m), grid != board)
        if not allow_partial:
            break
    return None


def detect_in_file(
    path: Path, board: tuple[int, int], square_m: float, allow_partial: bool = False
) -> tuple[Corners | None, tuple[int, int]]:
    """Corners of one image file (None when not found) and the image size (width, height)."""
    img = read_image(path)
    corners = detect_corners(img, board, square_m, str(path), allow_partial)
    return corners, (int(img.shape[1]), int(img.shape[0]))
