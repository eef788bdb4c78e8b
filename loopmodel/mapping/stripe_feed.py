"""The run's laser stripes extracted in a worker process and taken without waiting (issue 33).

Extracting the stripe of a laser-line image costs 40-50 ms a frame on the realistic orbit (2-core
machine, load 10): more than tracking the frame. The reader delivers each frame's laser images once
(issue 32); :class:`ExtractionWorker` takes them as values and hands the profiles back in order.
"""

from __future__ import annotations

import logging
import multiprocessing as mp
import signal
from typing import Any

from loopmodel.config import MappingConfig
from loopmodel.types import StripeProfile

logger = logging.getLogger(__name__)

__all__ = ["ExtractionWorker"]

# images in, profiles out
_EXTRACT: tuple[Any, ...] | None = None


def _extract_start(K: Any, dist: Any, config: MappingConfig) -> None:
    """The extraction process: its light plane and camera, Ctrl-C left to the run."""
    global _EXTRACT
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    from loopmodel.mapping.extraction import LightPlane

    _EXTRACT = (K, dist, LightPlane.from_config(config), config)


def _extract(timestamp_ns: int, image: Any) -> StripeProfile:
    from loopmodel.mapping.extraction import stripe_from_image

    assert _EXTRACT is not None
    K, dist, plane, config = _EXTRACT
    return stripe_from_image(image, timestamp_ns, K, plane, config, dist)


class ExtractionWorker:
    """Laser-line images handed over as values, their profiles extracted in a worker process.

    For a run whose reader delivers each frame's laser images: :meth:`submit` never waits,
    :meth:`ready` returns the profiles finished so far in submission order (empty profiles dropped),
    :meth:`wait` all of them (the end of a run). The left camera's ``K`` and distortion ``dist``
    (None when rectified) and ``config``'s light plane are the worker's.
    """

    def __init__(self, K: Any, dist: Any, config: MappingConfig) -> None:
        from concurrent.futures import ProcessPoolExecutor

        self._pool = ProcessPoolExecutor(
            1, mp_context=mp.get_context("spawn"), initializer=_extract_start, initargs=(K, dist, config)
        )
        self._pool.submit(int, 0)  # start it now: its imports overlap the first frames
        self._jobs: list[Any] = []
        self.failed = 0

    def submit(self, timestamp_ns: int, image: Any) -> None:
        """Queue one laser-line image (uint8, left camera)."""
        self._jobs.append(self._pool.submit(_extract, int(timestamp_ns), image))

    def _take(self, n: int) -> list[StripeProfile]:
        out: list[StripeProfile] = []
        for fut in self._jobs[:n]:
            try:
                profile = fut.result()
            except Exception as exc:  # noqa: BLE001 - one bad image loses its profile, logged
                self.failed += 1
                logger.error("laser stripe extraction failed: %s", exc)
                continue
            if profile.points_in_cam.shape[0]:
                out.append(profile)
        del self._jobs[:n]
        return out

    def ready(self) -> list[StripeProfile]:
        """The finished profiles at the head of the queue, in order; never waits."""
        n = 0
        while n < len(self._jobs) and self._jobs[n].done():
            n += 1
        return self._take(n)

    def wait(self) -> list[StripeProfile]:
        """Every remaining profile (waits), then the worker stops."""
        out = self._take(len(self._jobs))
        self.close()
        return out

    def close(self) -> None:
        """Stop the worker; queued images are dropped."""
        self._pool.shutdown(wait=False, cancel_futures=True)
