"""loopmodel: close-range 3-D modelling with a hand-held stereo camera and a laser-stripe profiler."""

import logging

from loopmodel._version import __version__

logging.getLogger(__name__).addHandler(logging.NullHandler())

__all__ = ["__version__"]
