"""``loopmodel view``: a rerun recording of a finished run."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from loopmodel.errors import InputError
from loopmodel.listener import RunListener
from loopmodel.types import StereoCalibration, Trajectory


def view(
    results: Annotated[Path, typer.Argument(help="Results folder of 'loopmodel run'")],
    out: Annotated[Path | None, typer.Option("--out", "-o", help="Output .rrd file (default RESULTS/run.rrd)")] = None,
    images: Annotated[bool, typer.Option("--images/--no-images", help="Log the sequence's left images")] = True,
    image_every: Annotated[int, typer.Option("--image-every", help="Log every N-th image")] = 1,
) -> None:
    """Build a rerun recording (.rrd) of a past run.

    Paths before/after correction, keyframes, landmarks, stripes, mesh, loop events, and the images
    when the sequence is still there.
    """
    from loopmodel.cli.common import console
    from loopmodel.viz.from_results import record_results

    target = out or results / "run.rrd"
    if target.suffix.lower() != ".rrd":
        raise InputError(target, "output must end in .rrd")
    if image_every < 1:
        raise InputError("--image-every", f"must be >= 1, got {image_every}")
    s = record_results(results, target, with_images=images, image_every=image_every)
    for note in s.notes:
        console.print(f"note: {note}")
    console.print(
        f"wrote {target} ({target.stat().st_size / 2**20:.1f} MiB): {s.frames} frames, {s.images} images, "
        f"{s.keyframes} keyframes, {s.landmarks} landmarks, {s.stripe_points} stripe points, "
        f"{s.mesh_triangles} mesh triangles, {s.events} loop events; open it with: rerun {target}"
    )


RerunFileOption = Annotated[Path | None, typer.Option("--rerun", help="Record the run to this .rrd file (rerun)")]
RerunSpawnOption = Annotated[bool, typer.Option("--rerun-spawn", help="Stream the run live to a new rerun viewer")]
RerunConnectOption = Annotated[
    str | None, typer.Option("--rerun-connect", help="Stream the run live to a rerun viewer at HOST:PORT (or URL)")
]


def check_writable_file(path: Path, what: str) -> None:
    """Refuse, before any work, a file that cannot be created at ``path`` (read-only place, no folder).

    A probe file beside it is created and removed (permission bits alone say nothing to root).
    """
    import os

    parent = path.parent if str(path.parent) else Path(".")
    if path.is_dir():
        raise InputError(path, f"{what} names a folder, not a file")
    if not parent.is_dir():
        raise InputError(path, f"{what}: {parent} is not an existing folder")
    probe = parent / f".{path.name}.probe-{os.getpid()}"
    try:
        probe.open("wb").close()
        probe.unlink()
    except OSError as exc:
        raise InputError(path, f"{what}: cannot write in {parent} ({exc.strerror or type(exc).__name__})") from None


def rerun_listeners(
    calibration: StereoCalibration,
    rrd: Path | None,
    spawn: bool,
    connect: str | None,
    ground_truth: Trajectory | None = None,
) -> list[RunListener]:
    """The run's rerun listener when any rerun option is given (none otherwise)."""
    from loopmodel.viz.recorder import RerunSink

    if rrd is not None:
        check_writable_file(rrd, "--rerun")

    sink = RerunSink(path=rrd, spawn=spawn, connect=connect)
    if not sink.enabled:
        return []
    if rrd is not None and rrd.suffix.lower() != ".rrd":
        raise InputError(rrd, "--rerun file must end in .rrd")
    from loopmodel.imaging.rectify import Rectifier
    from loopmodel.viz.recorder import RerunListener, RerunRecorder

    rect = Rectifier(calibration).calibration
    return [RerunListener(RerunRecorder(sink), rect.K_left, rect.image_size, ground_truth=ground_truth)]
