"""The sequence interface every reader implements, and the common part of the folder readers."""

from __future__ import annotations

import abc
from collections.abc import Iterator
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from loopmodel.errors import InputError
from loopmodel.types import StereoCalibration, StereoFrame, StripeProfile, Trajectory


class Sequence(abc.ABC):
    """A recorded stereo sequence.

    Frames and stripes stream in time order; nothing but the calibration and the ground truth is
    held in memory.
    """

    format_name: str = "?"

    def __init__(self, path: Path) -> None:
        self.path = path

    @property
    @abc.abstractmethod
    def calibration(self) -> StereoCalibration:
        """Stereo calibration of the sequence."""

    @property
    def ground_truth(self) -> Trajectory | None:
        """Ground-truth ``world_from_cam0`` poses, or None."""
        return None

    @abc.abstractmethod
    def frames(self) -> Iterator[StereoFrame]:
        """Stereo pairs in time order (images loaded one pair at a time)."""

    def stripes(self) -> Iterator[StripeProfile]:
        """Laser-stripe profiles in time order (none for formats without stripes)."""
        return iter(())

    def stripe_count(self) -> int | None:
        """Number of stripe profiles when known without reading them."""
        return 0

    def laser_images(self) -> Iterator[tuple[int, NDArray[np.uint8]]]:
        """Images of a laser-line camera (the left camera's view), ``(timestamp_ns, image)`` in time order.

        None for formats without them.
        """
        return iter(())

    def laser_image_count(self) -> int:
        """Number of laser-line images."""
        return 0

    @property
    def attachment_names(self) -> list[str]:
        """Names of the files attached to the sequence (e.g. a ground-truth ``scene.ply``).

        None for formats without attachments.
        """
        return []

    def read_attachment(self, name: str) -> bytes:
        """Bytes of the attachment called ``name``."""
        raise InputError(self.path, f"no attachment '{name}'")

    @abc.abstractmethod
    def __len__(self) -> int:
        """Number of stereo frames."""

    def frame_times_ns(self) -> list[int] | None:
        """Frame timestamps when the format lists them without decoding images."""
        return None

    def describe(self) -> dict[str, object]:
        """Summary for ``loopmodel info``."""
        times = self.frame_times_ns()
        duration = (times[-1] - times[0]) * 1e-9 if times and len(times) > 1 else None
        cal = self.calibration
        return {
            "path": str(self.path),
            "format": self.format_name,
            "frames": len(self),
            "duration_s": duration,
            "image_size": list(cal.image_size),
            "calibration": cal.summary(),
            "ground_truth": self.ground_truth is not None,
            "ground_truth_poses": len(self.ground_truth) if self.ground_truth is not None else 0,
            "stripes": self.stripe_count(),
            "laser_images": self.laser_image_count(),
        }


class FolderSequence(Sequence):
    """A sequence of left/right image files (EuRoC, KITTI).

    Subclasses fill ``_pairs`` (time in ns, left path, right path), ``_calibration`` and ``_gt``.
    """

    _pairs: list[tuple[int, Path, Path]]
    _calibration: StereoCalibration
    _gt: Trajectory | None = None

    @property
    def calibration(self) -> StereoCalibration:
        return self._calibration

    @property
    def ground_truth(self) -> Trajectory | None:
        return self._gt

    def __len__(self) -> int:
        return len(self._pairs)

    def frame_times_ns(self) -> list[int]:
        return [t for t, _, _ in self._pairs]

    def frames(self) -> Iterator[StereoFrame]:
        from loopmodel.io.images import read_image_of_size

        size = self._calibration.image_size
        for i, (t, lp, rp) in enumerate(self._pairs):
            yield StereoFrame(t, read_image_of_size(lp, size), read_image_of_size(rp, size), i)
