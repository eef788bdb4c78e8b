"""Procedural, seeded, multi-scale textures (albedo in [0, 1]) for the synthetic scene.

A texture is a square float32 image that tiles seamlessly (it is built in the Fourier
domain), so it can be sampled with wrap-around. Its content mixes band-limited fractal
noise, a warped ridge pattern and anti-aliased blobs of many sizes: natural-looking,
non-periodic over the area it covers, and rich in corners for KLT and ORB.
"""

from __future__ import annotations

import cv2
import numpy as np
from numpy.typing import NDArray

F32 = NDArray[np.float32]

STYLES = ("stone", "wood", "poster", "foliage", "fence", "facade")


def _fractal_noise(rng: np.random.Generator, n: int, beta: float, fmin: float, fmax: float) -> F32:
    """Periodic n x n noise with amplitude spectrum ~ f^-beta between fmin and fmax.

    Frequencies in cycles per texel; normalised to zero mean and unit standard deviation.
    """
    white = rng.standard_normal((n, n))
    spec = np.fft.rfft2(white)
    fy = np.fft.fftfreq(n)[:, None]
    fx = np.fft.rfftfreq(n)[None, :]
    f = np.sqrt(fx * fx + fy * fy)
    gain = np.where((f >= fmin) & (f <= fmax), np.power(np.maximum(f, 1e-9), -beta), 0.0)
    # soft roll-off at the top of the band (anti-aliasing when sampled)
    gain *= np.exp(-((f / fmax) ** 4))
    out = np.fft.irfft2(spec * gain, s=(n, n))
    out -= out.mean()
    std = out.std()
    return (out / (std if std > 0 else 1.0)).astype(np.float32)


def _blobs(rng: np.random.Generator, n: int, count: int, rmin: float, rmax: float) -> F32:
    """Anti-aliased ellipses of log-uniform sizes and random grey levels in [-1, 1].

    Painted over each other with wrap-around so the texture stays seamless.
    """
    canvas = np.zeros((n, n), np.float32)
    shift = 4
    scale = 1 << shift
    for _ in range(count):
        r = float(np.exp(rng.uniform(np.log(rmin), np.log(rmax))))
        ratio = float(rng.uniform(0.3, 1.0))
        angle = float(rng.uniform(0, 180))
        cx, cy = rng.uniform(0, n, size=2)
        value = float(rng.uniform(-1, 1))
        half = int(np.ceil(r)) + 2
        side = 2 * half + 1
        patch = np.zeros((side, side), np.float32)
        fx, fy = cx - np.floor(cx), cy - np.floor(cy)
        centre = (int((half + fx) * scale), int((half + fy) * scale))
        axes = (max(int(r * scale), 1), max(int(r * ratio * scale), 1))
        cv2.ellipse(patch, centre, axes, angle, 0, 360, 1.0, -1, cv2.LINE_AA, shift)
        rows = (np.arange(side) + int(np.floor(cy)) - half) % n
        cols = (np.arange(side) + int(np.floor(cx)) - half) % n
        if side > n:  # a blob larger than the texture: clip it to one period
            rows, cols, patch = rows[:n], cols[:n], patch[:n, :n]
        ix = np.ix_(rows, cols)
        canvas[ix] = canvas[ix] * (1.0 - patch) + value * patch
    return canvas


def _blur_wrap(img: F32, sigma: float) -> F32:
    """Gaussian blur with periodic borders."""
    pad = int(np.ceil(4 * sigma)) + 1
    big = np.pad(img, pad, mode="wrap")
    out = cv2.GaussianBlur(big, (0, 0), sigma)
    return np.ascontiguousarray(out[pad:-pad, pad:-pad])


def make_texture(seed: int | np.random.SeedSequence, size: int = 2048, style: str = "stone") -> F32:
    """Seamless size x size albedo texture (float32 in about [0.08, 0.92]).

    ``style``: ``stone`` (granite-like speckles and blobs), ``wood`` (warped ridges),
    ``poster`` (large flat patches with fine print, for walls); for the street scene (issue 36):
    ``foliage`` (dense leaves of a few sizes: stochastic and self-similar), ``fence`` (vertical bars
    with a 16-texel period and rails: periodic along the row), ``facade`` (a grid of windows, 64 x 128
    texels: periodic in both directions)."""
    if style not in STYLES:
        raise ValueError(f"unknown texture style {style!r}; expected one of {STYLES}")
    rng = np.random.default_rng(seed)
    n = int(size)
    k = n / 2048.0  # features scale with the texture so each covers the same area
    if style == "stone":
        base = _fractal_noise(rng, n, 1.2, 1.5 / n, 0.2)
        fine = _fractal_noise(rng, n, 0.5, 0.03, 0.22)
        blobs = _blobs(rng, n, int(900 * k * k) + 40, 4.0 * k + 1.0, 70.0 * k + 2.0)
        img = 0.6 * base + 0.15 * fine + 1.3 * blobs
    elif style == "wood":
        warp = _fractal_noise(rng, n, 1.4, 1.0 / n, 0.05)
        yy = np.arange(n, dtype=np.float32)[:, None] * np.ones((1, n), np.float32)
        rings = np.sin(2 * np.pi * (yy / n * int(24 * k + 3)) + 6.0 * warp)
        grain = _fractal_noise(rng, n, 1.0, 0.005, 0.2)
        knots = _blobs(rng, n, int(400 * k * k) + 20, 3.0 * k + 1.0, 30.0 * k + 2.0)
        img = 0.6 * rings + 0.5 * grain + 1.2 * knots
    elif style == "foliage":
        # leaves: band-pass noise squashed into dark and lit patches, at two sizes
        big = np.tanh(3.0 * _fractal_noise(rng, n, 0.0, 0.03 / k, 0.08 / k))
        small = np.tanh(3.0 * _fractal_noise(rng, n, 0.0, 0.08 / k, 0.2))
        shade = _fractal_noise(rng, n, 1.3, 1.0 / n, 0.03)
        img = big + 0.6 * small + 0.5 * shade
    elif style in ("fence", "facade"):
        xx = np.arange(n, dtype=np.float32)[None, :] * np.ones((n, 1), np.float32)
        yy = xx.T
        if style == "fence":  # bars 6 of 16 texels wide, two rails
            bars = ((xx % 16) < 6).astype(np.float32)
            rails = (((yy % 128) < 10) | (((yy + 64) % 128) < 6)).astype(np.float32)
            img = np.maximum(bars, rails) - 0.5 + 0.15 * _fractal_noise(rng, n, 1.0, 0.01, 0.2)
        else:  # windows 36 x 72 texels on a 64 x 128 grid, frames and a little dirt
            win = ((xx % 64) > 14) & ((xx % 64) < 50) & ((yy % 128) > 28) & ((yy % 128) < 100)
            frame = ((xx % 64) > 30) & ((xx % 64) < 34) & win
            img = -0.8 * win.astype(np.float32) + 0.6 * frame + 0.2 * _fractal_noise(rng, n, 1.2, 2.0 / n, 0.2)
    else:  # poster
        patches = _blobs(rng, n, int(260 * k * k) + 30, 20.0 * k + 2.0, 220.0 * k + 4.0)
        print_ = _fractal_noise(rng, n, 0.3, 0.03, 0.25)
        mid = _fractal_noise(rng, n, 1.2, 2.0 / n, 0.08)
        img = 1.2 * patches + 0.35 * print_ + 0.4 * mid
    img = _blur_wrap(img.astype(np.float32), 0.7)
    lo, hi = np.percentile(img, [1.0, 99.0])
    img = (img - lo) / max(hi - lo, 1e-6)
    return np.clip(0.1 + 0.8 * img, 0.03, 0.97).astype(np.float32)
