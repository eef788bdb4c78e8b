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

from loopmodel.mapping.extraction import StripeExtractor
from loopmodel.types import StripeProfile

logger = logging.getLogger(__name__)

__all__ = ["ExtractionWorker"]

# the worker process's extractor (the run's, a copy): images in, profiles out
_EXTRACTOR: StripeExtractor | None = None


def _extract_start(extractor: StripeExtractor) -> None:
    """The extraction process: the run's extractor (camera, light plane), Ctrl-C left to the run."""
    global _EXTRACTOR
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    _EXTRACTOR = extractor
    from loopmodel.mapping import _peak_kernels

    _peak_kernels.warm_up()  # the compiled peak finder loaded before the first image


def _extract(timestamp_ns: int, image: Any) -> StripeProfile:
    assert _EXTRACTOR is not None
    return _EXTRACTOR.from_image(timestamp_ns, image)


class ExtractionWorker:
    """Laser-line images handed over as values, their profiles extracted in a worker process.

    For a run whose reader delivers each frame's laser images: :meth:`submit` never waits,
    :meth:`ready` returns the profiles finished so far in submission order (empty profiles dropped),
    :meth:`wait` all of them (the end of a run). ``extractor`` (the run's: left camera, light plane)
    is copied into the worker.
    """

    def __init__(self, extractor: StripeExtractor) -> None:
        from concurrent.futures import ProcessPoolExecutor

        self._pool: Any = ProcessPoolExecutor(
            1, mp_context=mp.get_context("spawn"), initializer=_extract_start, initargs=(extractor,)
        )
        self._started = self._pool.submit(int, 0)  # start it now (its imports: :meth:`wait_started`)
        self._jobs: list[Any] = []
        self.failed = 0

    def wait_started(self, timeout_s: float | None = None) -> None:
        """Wait until the worker has started (its imports and compiled kernels loaded); a failure is logged.

        A run waits before its first frame (tail11): the start, 1.2 s of CPU, then does not share the
        machine's two cores with the first frames.
        """
        try:
            self._started.result(timeout_s)
        except Exception as exc:  # noqa: BLE001 - the images' extraction reports it again; the run goes on
            logger.warning("laser stripe extraction worker not started: %s", exc)

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

    def wait(self, keep_process: bool = False) -> list[StripeProfile]:
        """Every remaining profile (waits), then the worker stops (its process kept for :meth:`take_pool`)."""
        out = self._take(len(self._jobs))
        if not keep_process:
            self.close()
        return out

    def take_pool(self) -> Any:
        """The worker's process pool, idle after :meth:`wait`, for other work of the run (None once closed).

        Issue 32: the finish's helper process (no new process to start); the caller shuts it down.
        """
        pool, self._pool = self._pool, None
        return pool

    def close(self) -> None:
        """Stop the worker; queued images are dropped."""
        if self._pool is not None:
            self._pool.shutdown(wait=False, cancel_futures=True)
