"""The sequence interface every reader implements, and the common part of the folder readers."""

from __future__ import annotations

import abc
import functools
from collections.abc import Iterator
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from loopmodel.errors import InputError
from loopmodel.types import ScanFrame, StereoCalibration, StereoFrame, StripeProfile, Trajectory


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

    def scan(self) -> Iterator[ScanFrame]:
        """Each stereo frame once, in time order, with the laser data taken up to its time.

        The stripe messages when the sequence has them, else its laser-line images (none without
        either). An item goes with the first frame at or after its time; items after the last frame
        read are not read. The one pass over a sequence a run makes.
        """
        stripes = bool(self.stripe_count())
        laser: Iterator[tuple[int, object]] = iter(())
        if stripes:
            laser = ((s.timestamp_ns, s) for s in self.stripes())
        elif self.laser_image_count():
            laser = iter(self.laser_images())
        pending: tuple[int, object] | None = None
        try:
            for frame in self.frames():
                taken: list[object] = []
                while True:
                    if pending is None:
                        pending = next(laser, None)
                    if pending is None or pending[0] > frame.timestamp_ns:
                        break
                    taken.append(pending[1] if stripes else pending)
                    pending = None
                if stripes:
                    yield ScanFrame(frame, stripes=taken)  # type: ignore[arg-type]
                else:
                    yield ScanFrame(frame, laser_images=taken)  # type: ignore[arg-type]
        finally:
            close = getattr(laser, "close", None)
            if close is not None:
                close()

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
    #: the declared-size limit of an image (``sequence.max_image_pixels``)
    max_image_pixels: int = 100_000_000

    def _check_image_files(self) -> None:
        """Every image of the pairs must be a regular file (a FIFO would block its reading)."""
        from loopmodel.io.text import require_regular_file

        for _, lp, rp in self._pairs:
            require_regular_file(lp, "image file")
            require_regular_file(rp, "image file")

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
        """The pairs; each right image read with its frame, decoded when first used (:class:`DeferredRightFrame`)."""
        from loopmodel.io.images import (
            DeferredRightFrame,
            check_image_bytes,
            decode_of_size,
            read_image_bytes,
            read_image_of_size,
        )

        size, limit = self._calibration.image_size, self.max_image_pixels
        for i, (t, lp, rp) in enumerate(self._pairs):
            left = read_image_of_size(lp, size, limit)
            data = read_image_bytes(rp)
            check_image_bytes(data, limit, rp)
            yield DeferredRightFrame(t, left, None, i, right_decode=functools.partial(decode_of_size, data, rp, size))
