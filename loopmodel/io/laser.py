"""The laser profiles of a sequence or a results folder, and the poses that place them.

A sequence's stripe messages, or profiles extracted from its laser-line images with the light plane
(:class:`~loopmodel.mapping.extraction.StripeExtractor`); a results folder's ``stripes.npz`` and
trajectory. A run does not use these (it takes the laser data of each frame as it reads it,
:meth:`~loopmodel.io.base.Sequence.scan`): they serve the commands that mesh or show stripes after
a run, and the tools.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

from loopmodel.config import MappingConfig, SequenceConfig
from loopmodel.errors import InputError
from loopmodel.io.base import Sequence
from loopmodel.io.stripes_io import STRIPES_FILE, load_stripes
from loopmodel.types import StripeProfile, Trajectory


def sequence_stripe_count(sequence: Sequence) -> int:
    """Number of laser profiles a sequence gives: its stripe messages, else its laser images."""
    return int(sequence.stripe_count() or 0) or sequence.laser_image_count()


def sequence_stripes(sequence: Sequence, config: MappingConfig | None = None) -> Iterator[StripeProfile]:
    """The laser profiles of a sequence in time order (left-camera frame, metres).

    Its stripe messages when it has them, else profiles extracted from its laser-line images with
    the configured light plane and the left camera's calibration (empty profiles dropped).
    """
    if sequence.stripe_count():
        yield from sequence.stripes()
        return
    if sequence.laser_image_count() == 0:
        return
    from loopmodel.mapping.extraction import StripeExtractor

    extractor = StripeExtractor(sequence.calibration, config)
    for t_ns, image in sequence.laser_images():
        profile = extractor.from_image(t_ns, image)
        if profile.points_in_cam.shape[0]:
            yield profile


def load_stripes_and_poses(
    source: str | Path,
    trajectory: str = "final",
    sequence_config: SequenceConfig | None = None,
    mapping_config: MappingConfig | None = None,
) -> tuple[list[StripeProfile], Trajectory, str]:
    """Stripes and the poses to place them with, from a results folder or a recorded sequence.

    A results folder: ``stripes.npz`` and ``trajectory_<final|online>.tum`` (final falls back to
    online). A recorded sequence: with stripes (or laser-line images, extracted with
    ``mapping_config``'s light plane) and ground truth (e.g. a simulator MCAP). Returns the stripes,
    the ``world_from_cam`` trajectory and a name for the poses used.
    """
    from loopmodel.io.trajectory_io import read_trajectory

    p = Path(source)
    if not p.exists():
        raise InputError(p, "results folder does not exist")
    run_files = (STRIPES_FILE, "trajectory_final.tum", "trajectory_online.tum")
    if p.is_dir() and any((p / f).exists() for f in run_files):
        if trajectory not in ("final", "online"):
            raise InputError(p, f"a results folder has final or online poses, not '{trajectory}'")
        traj_path = p / f"trajectory_{trajectory}.tum"
        if trajectory == "final" and not traj_path.is_file():
            traj_path = p / "trajectory_online.tum"
        if not traj_path.is_file():
            raise InputError(p, f"no trajectory_{trajectory}.tum in the results folder")
        stripes = load_stripes(p)
        if not stripes:
            raise InputError(p / STRIPES_FILE, "no laser stripes in the stripe file")
        return stripes, read_trajectory(traj_path), traj_path.name
    from loopmodel.io.sequence import open_sequence

    try:
        seq = open_sequence(p, sequence_config)
    except InputError:
        if p.is_dir():
            raise InputError(p, f"no laser stripes here (expected a results folder with {STRIPES_FILE})") from None
        raise
    gt = seq.ground_truth
    if gt is None:
        raise InputError(p, "sequence has no ground-truth poses to place its stripes with")
    stripes = list(sequence_stripes(seq, mapping_config))
    if not stripes:
        raise InputError(p, "no laser stripes in this sequence")
    return stripes, gt, "ground truth"
