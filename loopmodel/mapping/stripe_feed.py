"""The run's laser stripes made in a worker process and taken without waiting (issue 33).

Reading a laser-line image and extracting its stripe costs 40-50 ms a frame on the realistic orbit
(2-core machine, load 10): more than tracking the frame. :class:`StripeFeed` runs the stripe
iterator a ``factory`` makes (e.g. ``functools.partial(sequence_stripes, sequence, config)``; the
sequence object is pickled into the worker, which reads with its own reader) in a spawned process,
and hands the profiles over as they come. Its ``next()`` never waits: when no profile is ready it
raises ``StopIteration`` for now, and a later ``next()`` goes on (``LiveMapping.feed`` calls it once
per frame). The worker runs at most ``ahead`` profiles ahead of the consumer.

:class:`ExtractionWorker` is the same work for a reader that already delivers each frame's laser
images (one pass over the data): the images go to the worker as values, the profiles come back.
"""

from __future__ import annotations

import logging
import multiprocessing as mp
import queue
import signal
from collections.abc import Callable, Iterable, Iterator
from typing import Any

from loopmodel.config import MappingConfig
from loopmodel.errors import LoopmodelError
from loopmodel.types import StripeProfile

logger = logging.getLogger(__name__)

__all__ = ["ExtractionWorker", "StripeFeed"]

_END = "end"
_ERROR = "error"


def _produce(factory: Callable[[], Iterable[StripeProfile]], out: Any, batch: int) -> None:
    """The worker: put the iterator's profiles on ``out`` in small batches, then the end (or the error)."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the run's: it stops between frames
    chunk: list[StripeProfile] = []
    try:
        for profile in factory():
            chunk.append(profile)
            if len(chunk) >= batch:
                out.put(("stripes", chunk))
                chunk = []
        if chunk:
            out.put(("stripes", chunk))
        out.put((_END,))
    except Exception as exc:  # noqa: BLE001 - handed to the consumer, which logs it
        if chunk:
            out.put(("stripes", chunk))
        out.put((_ERROR, f"{type(exc).__name__}: {exc}"))


class StripeFeed(Iterator[StripeProfile]):
    """Stripe profiles from a worker process; ``next()`` raises ``StopIteration`` while none is ready.

    A failure in the worker is raised as :class:`LoopmodelError` by the ``next()`` that reaches it.
    """

    def __init__(self, factory: Callable[[], Iterable[StripeProfile]], ahead: int = 64, batch: int = 4) -> None:
        ctx = mp.get_context("spawn")
        self._queue: Any = ctx.Queue(maxsize=max(ahead // batch, 1))
        self._worker: Any = ctx.Process(
            target=_produce, args=(factory, self._queue, batch), name="loopmodel-stripes", daemon=True
        )
        self._worker.start()  # pickles the factory: raises here when it cannot be sent
        self._ready: list[StripeProfile] = []
        self._done = False
        self.taken = 0

    def __next__(self) -> StripeProfile:
        if not self._ready and not self._done:
            self._poll()
        if not self._ready:
            raise StopIteration
        self.taken += 1
        return self._ready.pop(0)

    def _poll(self) -> None:
        while True:
            try:
                msg = self._queue.get_nowait()
            except queue.Empty:
                if not self._worker.is_alive() and self._queue.empty():
                    self._done = True
                    raise LoopmodelError("the laser-stripe worker stopped unexpectedly") from None
                return
            if msg[0] == "stripes":
                self._ready.extend(msg[1])
                return
            self._done = True
            self._stop()
            if msg[0] == _ERROR:
                raise LoopmodelError(f"laser stripes: {msg[1]}")
            return

    def wait(self, timeout_s: float = 60.0) -> list[StripeProfile]:
        """Every remaining profile, waiting for the worker (at most ``timeout_s``; the end of a run)."""
        out, self._ready = self._ready, []
        while not self._done:
            try:
                msg = self._queue.get(timeout=timeout_s)
            except queue.Empty:
                logger.warning("laser stripes: the worker did not finish within %.0f s", timeout_s)
                break
            if msg[0] == "stripes":
                out.extend(msg[1])
            else:
                self._done = True
                if msg[0] == _ERROR:
                    logger.error("laser stripes: %s", msg[1])
        self.close()
        self.taken += len(out)
        return out

    def _stop(self) -> None:
        self._worker.join(timeout=5.0)

    def close(self) -> None:
        """Stop the worker (at once) and let go of the queue."""
        self._done = True
        if self._worker.is_alive():
            self._worker.terminate()
        self._worker.join(timeout=5.0)
        self._queue.cancel_join_thread()
        self._queue.close()


# --------------------------------------------------------------------------- images in, profiles out
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
