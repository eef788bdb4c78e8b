"""The loop-closing descriptor kinds, one module each, behind one registry (issue 32, as pySLAM's factory).

Adding a kind: a module with a :class:`~loopmodel.loop.descriptors.base.Descriptor`, an entry in
:data:`DESCRIPTORS`, its name in ``config.DescriptorKind`` (``tests/test_descriptors.py`` checks the two
agree) and a shipped vocabulary (``loopmodel loop vocabulary``).
"""

from __future__ import annotations

from loopmodel.errors import ConfigError
from loopmodel.loop.descriptors.base import Described, Descriptor
from loopmodel.loop.descriptors.orb import ORB
from loopmodel.loop.descriptors.sift import SIFT
from loopmodel.loop.descriptors.surf import SURF

__all__ = ["DESCRIPTORS", "Described", "Descriptor", "descriptor"]

#: Every descriptor kind by its ``loop.descriptor`` name.
DESCRIPTORS: dict[str, Descriptor] = {d.name: d for d in (ORB, SIFT, SURF)}


def descriptor(kind: str) -> Descriptor:
    """The descriptor kind named ``kind`` (case-insensitive); :class:`ConfigError` for an unknown one."""
    try:
        return DESCRIPTORS[kind.lower()]
    except KeyError:
        raise ConfigError(
            "loop.descriptor", f"unknown descriptor '{kind}', expected one of {tuple(DESCRIPTORS)}"
        ) from None
