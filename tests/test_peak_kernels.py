"""The compiled laser-line peak finder against the numpy one (``extract_laser_peaks(compiled=False)``)."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from loopmodel.mapping.extraction import extract_laser_peaks


def _laser_image(rng: np.random.Generator, h: int = 240, w: int = 320, saturate: bool = False) -> np.ndarray:
    """A dim textured scene with a broken, curved laser line (speckle, blooming core when ``saturate``)."""
    yy, xx = np.mgrid[0:h, 0:w].astype(float)
    img = 14.0 + 6.0 * np.sin(xx / 7.0) * np.cos(yy / 11.0) + rng.normal(0, 2.0, (h, w))
    centre = 0.45 * w + 0.25 * w * np.sin(yy[:, :1] / h * 5.0) + 0.3 * (yy[:, :1] - h / 2)  # oblique, curved
    lit = ((yy[:, :1] // 37) % 4 != 3) & (yy[:, :1] > 2)  # pieces, the first rows dark
    line = 240.0 * np.exp(-0.5 * ((xx - centre) / 1.4) ** 2) * rng.uniform(0.5, 1.0, (h, w))
    img += np.where(lit, line, 0.0)
    # a second, fainter reflection in some rows, and a line touching the image's left edge
    img[h // 3 : h // 2] += 60.0 * np.exp(-0.5 * ((xx[h // 3 : h // 2] - 0.8 * w) / 2.0) ** 2)
    img[h - 20 :] += 200.0 * np.exp(-0.5 * (xx[h - 20 :] / 1.5) ** 2)
    if saturate:
        img *= 1.6
    return np.clip(np.round(img), 0, 255).astype(np.uint8)


@pytest.mark.parametrize("seed", [0, 1])
def test_compiled_peaks_equal_the_numpy_ones(seed: int) -> None:
    rng = np.random.default_rng(seed)
    images = [_laser_image(rng), _laser_image(rng, saturate=True)]
    images.append(np.dstack([images[0] // 3, images[0], images[0] // 2]))  # BGR: the maximum channel
    checked = 0
    for img, axis, smooth, local, across, window in itertools.product(
        images, ["rows", "columns"], [0.0, 1.5, 0.6], [True, False], [True, False], [4, 2]
    ):
        kw = dict(smooth_along_px=smooth, local_background=local, across_line=across)
        ref = extract_laser_peaks(img, axis, 20.0, window, "cog", compiled=False, **kw)  # type: ignore[arg-type]
        got = extract_laser_peaks(img, axis, 20.0, window, "cog", **kw)  # type: ignore[arg-type]
        assert got.shape == ref.shape, (axis, smooth, local, across, window)
        np.testing.assert_allclose(got, ref, rtol=0, atol=1e-9)
        checked += ref.shape[0]
    assert checked > 10_000  # the images do have lines in both orientations' profiles


def test_compiled_peaks_plateaus_borders_and_empty_images() -> None:
    img = np.full((40, 50), 10, np.uint8)
    img[:, 20:24] = 255  # a saturated plateau: the first of the equal maxima, as np.argmax
    img[0, 3] = img[-1, 47] = 255  # lone bright pixels in the first and last rows
    for smooth, axis in itertools.product([0.0, 1.5], ["rows", "columns"]):
        ref = extract_laser_peaks(img, axis, 20.0, 3, "cog", smooth_along_px=smooth, compiled=False)
        np.testing.assert_allclose(extract_laser_peaks(img, axis, 20.0, 3, "cog", smooth_along_px=smooth), ref)
    assert extract_laser_peaks(np.full((30, 30), 40, np.uint8), min_contrast=10).shape == (0, 2)
    # images smaller than the smoothing's reach take the numpy path
    small = np.zeros((5, 8), np.uint8)
    small[:, 4] = 200
    np.testing.assert_allclose(
        extract_laser_peaks(small, "rows", 20.0, 1, "cog", smooth_along_px=1.5),
        extract_laser_peaks(small, "rows", 20.0, 1, "cog", smooth_along_px=1.5, compiled=False),
    )
