"""Hand-held camera paths around an object at close range, with hand shake.

World frame: z up, object axis along z through the origin (table top at z = 0). A path is a
smooth function of time; :meth:`HandheldPath.pose` returns ``world_from_cam0`` (camera x
right, y down, z forward) at any time, so exposure intervals can be sampled for motion blur.

Kinds: ``orbit`` (one full turn that returns to the start view), ``sweeps`` (back-and-forth
sweeps over 90 degrees of yaw at rising then falling height, ending at the start view),
``browse`` (a monotone 240-degree arc with a height change: no view is revisited),
``modeler`` (in the spirit of seed 004's scan of a 50 cm sculpture: four sweeps over about
90 degrees of yaw, a return that closes the loop on the start view, then a full orbit at
another height that revisits the swept side), ``rounds`` (a long scan that keeps finding new views,
issue 33: ``sweeps`` full turns, each at its own height and distance, each running 40 degrees past
its own start, which it revisits, while it moves to the next round's height and distance; every
round passes the views of the earlier ones from another height).

Pace ``handheld`` (realistic world) replaces the even progress along the path by a hand's:
pauses (0.4-1.2 s at a tenth of the speed) and saccades (0.25-0.5 s at 2.5x) drawn from the
seed, about one event every 3 s; the mean speed over the path is unchanged. Human hand-held
scanning alternates fixations and quick re-orientations in this way (seed 004: "jerky
motion", "saccadic motion"). ``revisit_offset_m`` makes revisits inexact: the path drifts
linearly in radius, height and aim so that the end view misses the start view by about that
distance (a person never returns exactly).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from loopmodel.geometry.se3 import look_at, so3_exp

F64 = NDArray[np.float64]

KINDS = ("orbit", "sweeps", "browse", "modeler", "rounds")
TARGET_HEIGHT_FRACTION = 0.45  # look-at point on the object axis, fraction of its height


class _Shake:
    """Band-limited hand tremor: sums of sinusoids (0.4-8 Hz, amplitude ~ 1/f) per axis."""

    def __init__(self, rng: np.random.Generator, dims: int, terms: int = 12) -> None:
        self.f = np.exp(rng.uniform(np.log(0.4), np.log(8.0), size=(dims, terms)))
        self.phase = rng.uniform(0, 2 * np.pi, size=(dims, terms))
        amp = 1.0 / self.f
        self.amp = amp / np.sqrt(0.5 * np.sum(amp**2, axis=1, keepdims=True))  # unit RMS per axis

    def __call__(self, t_s: float) -> F64:
        return np.sum(self.amp * np.sin(2 * np.pi * self.f * t_s + self.phase), axis=1)


class HandheldPath:
    """A hand-held scanning path of ``kind`` lasting ``duration_s`` seconds."""

    def __init__(
        self,
        kind: str,
        duration_s: float,
        seed: int,
        radius_m: float = 0.65,
        height_m: float = 0.35,
        object_height_m: float = 0.5,
        sweeps: int = 3,
        shake_translation_m: float = 0.002,
        shake_rotation_deg: float = 0.3,
        pace: str = "smooth",
        revisit_offset_m: float = 0.0,
        start_azimuth_deg: float | None = None,
    ) -> None:
        if kind not in KINDS:
            raise ValueError(f"unknown trajectory kind {kind!r}; expected one of {KINDS}")
        if duration_s <= 0:
            raise ValueError("duration must be positive")
        self.kind = kind
        self.duration_s = float(duration_s)
        self.radius_m = float(radius_m)
        self.height_m = float(height_m)
        self.object_height_m = float(object_height_m)
        self.sweeps = int(sweeps)
        rng = np.random.default_rng(np.random.SeedSequence([int(seed), 5]))
        self.phi0 = float(rng.uniform(-np.pi, np.pi))
        if start_azimuth_deg is not None:  # a chosen start (a second session 90 deg around, issue 20)
            self.phi0 = float(np.radians(start_azimuth_deg))
        self._wobble = rng.uniform(0, 2 * np.pi, size=6)
        self._shake = _Shake(rng, 6)
        self.shake_translation_m = float(shake_translation_m)
        self.shake_rotation_rad = float(np.radians(shake_rotation_deg))
        self.revisit_offset_m = float(revisit_offset_m)
        self._warp: tuple[F64, F64] | None = None
        if pace == "handheld":
            self._warp = _handheld_pace(np.random.default_rng(np.random.SeedSequence([int(seed), 7])), duration_s)
        elif pace != "smooth":
            raise ValueError(f"unknown pace {pace!r}; expected 'smooth' or 'handheld'")

    def progress(self, t_s: float) -> float:
        """Path parameter s in [0, 1] at time ``t_s`` (even, or the hand's pace)."""
        s = float(np.clip(t_s / self.duration_s, 0.0, 1.0))
        if self._warp is None:
            return s
        return float(np.interp(s, self._warp[0], self._warp[1]))

    def _nominal(self, s: float) -> tuple[float, float, float, F64]:
        """Azimuth (rad), radius (m), height (m) and look-at target at path parameter s in [0, 1]."""
        w = self._wobble
        two_pi = 2 * np.pi
        target = np.array([0.0, 0.0, TARGET_HEIGHT_FRACTION * self.object_height_m])
        if self.kind == "orbit":
            # ease in and out; all wobbles periodic in s, so the end view equals the start view
            u = s - 0.12 * np.sin(two_pi * s) / two_pi
            phi = self.phi0 + two_pi * u
            r = self.radius_m * (1 + 0.12 * np.sin(two_pi * 2 * s + w[0]) - 0.12 * np.sin(w[0]))
            h = self.height_m + 0.12 * (np.sin(two_pi * 3 * s + w[1]) - np.sin(w[1]))
            target = target + 0.03 * np.array(
                [
                    np.sin(two_pi * 2 * s + w[2]) - np.sin(w[2]),
                    np.sin(two_pi * 3 * s + w[3]) - np.sin(w[3]),
                    0.0,
                ]
            )
        elif self.kind == "sweeps":
            # n back-and-forth sweeps over [-45, +45] deg around phi0, height up then down
            phi = self.phi0 + np.radians(45.0) * np.sin(two_pi * self.sweeps * s)
            r = self.radius_m * (1 + 0.08 * np.sin(two_pi * 2 * s + w[0]) - 0.08 * np.sin(w[0]))
            h = self.height_m + 0.15 * np.sin(np.pi * s) ** 2 * np.sin(np.pi * s)
            target = target + 0.02 * np.array([np.sin(two_pi * s + w[2]) - np.sin(w[2]), 0.0, 0.0])
        elif self.kind == "modeler":
            phi, r, h, target = self._modeler(s)
        elif self.kind == "rounds":
            phi, r, h, target = self._rounds(s)
        else:  # browse: monotone arc, no revisit
            u = s - 0.1 * np.sin(two_pi * s) / two_pi
            phi = self.phi0 + np.radians(240.0) * u
            r = self.radius_m * (1.1 - 0.25 * s)
            h = self.height_m - 0.1 + 0.3 * s
        if self.revisit_offset_m > 0 and self.kind != "browse":
            # inexact revisit: a slow drift away from the periodic path (zero at the start)
            d = self.revisit_offset_m * s
            r += 0.6 * d
            h += 0.6 * d
            target = target + np.array([0.0, 0.0, 0.5 * d])
        return float(phi), float(r), float(h), target

    def _modeler(self, s: float) -> tuple[float, float, float, F64]:
        """Seed-004-like scan.

        S in [0, 0.5): four sweeps over 90 deg of yaw (two back and forth, height rising by 8 cm);
        [0.5, 0.6): back to the start view (the loop closes); [0.6, 1]: one full orbit 15 cm higher,
        passing over the swept side again.
        """
        two_pi = 2 * np.pi
        w = self._wobble
        target = np.array([0.0, 0.0, TARGET_HEIGHT_FRACTION * self.object_height_m])
        r = self.radius_m * (1 + 0.06 * np.sin(two_pi * 3 * s + w[0]) - 0.06 * np.sin(w[0]))
        if s < 0.5:
            u = s / 0.5
            phi = self.phi0 + np.radians(90.0) * 0.5 * (1 - np.cos(two_pi * 2 * u))  # 0 -> 90 -> 0 -> 90 -> 0
            h = self.height_m + 0.08 * u
        elif s < 0.6:
            u = (s - 0.5) / 0.1
            phi = self.phi0 - np.radians(10.0) * np.sin(np.pi * u)  # a short look past the start
            h = self.height_m + 0.08 * (1 - u)
        else:
            u = (s - 0.6) / 0.4
            e = u - 0.1 * np.sin(two_pi * u) / two_pi
            phi = self.phi0 - two_pi * e
            h = self.height_m + 0.15 * np.sin(np.pi * min(4 * u, 1.0) / 2) ** 2 * (1 - np.clip((u - 0.85) / 0.15, 0, 1))
        return float(phi), float(r), float(h), target

    def _rounds(self, s: float) -> tuple[float, float, float, F64]:
        """``sweeps`` rounds; round i: a full turn at its own height and radius, then 40 deg more.

        The first 85 % of a round turns once around the object; the rest runs 40 deg past the
        round's start (a revisit) while height, radius and aim ease to the next round's. Heights
        and radii follow fixed cycles (7 and 5 values) so that later rounds repeat earlier
        heights at other distances.
        """
        two_pi = 2 * np.pi
        n = max(self.sweeps, 1)
        x = min(s, 1.0 - 1e-12) * n
        i, u = int(x), x - int(x)
        dh = (0.0, 0.14, -0.1, 0.07, -0.05, 0.18, 0.03)
        fr = (1.0, 1.2, 0.9, 1.35, 1.1)
        dz = (0.0, 0.04, -0.03, 0.02, -0.01, 0.05, -0.02)

        def level(k: int) -> tuple[float, float, float]:
            return self.height_m + dh[k % 7], self.radius_m * fr[k % 5], dz[k % 7] * self.object_height_m

        extra = np.radians(40.0)
        if u < 0.85:
            phi = self.phi0 + i * extra + two_pi * u / 0.85
            h, r, z = level(i)
        else:
            v = (u - 0.85) / 0.15
            w = v * v * (3 - 2 * v)  # smoothstep to the next round's level
            phi = self.phi0 + i * extra + two_pi + extra * v
            (h0, r0, z0), (h1, r1, z1) = level(i), level(i + 1)
            h, r, z = h0 + w * (h1 - h0), r0 + w * (r1 - r0), z0 + w * (z1 - z0)
        target = np.array([0.0, 0.0, TARGET_HEIGHT_FRACTION * self.object_height_m + z])
        return float(phi), float(r), float(h), target

    def nominal_pose(self, t_s: float) -> F64:
        """``world_from_cam0`` without hand shake at time ``t_s``."""
        phi, r, h, target = self._nominal(self.progress(t_s))
        pos = np.array([r * np.cos(phi), r * np.sin(phi), h])
        return look_at(pos, target)

    def pose(self, t_s: float) -> F64:
        """``world_from_cam0`` (4x4, metres) at time ``t_s`` (seconds from the start)."""
        T = self.nominal_pose(t_s)
        sh = self._shake(t_s)
        T[:3, 3] += self.shake_translation_m * sh[:3]
        T[:3, :3] = T[:3, :3] @ so3_exp(self.shake_rotation_rad * sh[3:])
        return T


def _handheld_pace(rng: np.random.Generator, duration_s: float) -> tuple[F64, F64]:
    """Monotone map (time fraction -> path fraction) of a hand's pace.

    Unit speed with pauses (0.4-1.2 s at 0.1x) and saccades (0.25-0.5 s at 2.5x), one event per 3 s
    on average, smoothed over 0.12 s (arm inertia) and normalised to end at 1.
    """
    n = max(int(duration_s * 200), 50)
    t = np.linspace(0.0, duration_s, n)
    speed = np.ones(n)
    k = 0.0
    while True:
        k += rng.exponential(3.0)
        if k >= duration_s - 0.5:
            break
        if rng.random() < 0.5:
            speed[(t >= k) & (t < k + rng.uniform(0.4, 1.2))] = 0.1
        else:
            speed[(t >= k) & (t < k + rng.uniform(0.25, 0.5))] = 2.5
    dt = t[1] - t[0]
    half = max(int(0.12 / dt), 1)
    kern = np.exp(-0.5 * (np.arange(-3 * half, 3 * half + 1) / half) ** 2)
    speed = np.convolve(np.pad(speed, 3 * half, mode="edge"), kern / kern.sum(), mode="valid")
    cum = np.concatenate([[0.0], np.cumsum(0.5 * (speed[1:] + speed[:-1]) * dt)])
    return t / duration_s, cum / cum[-1]
