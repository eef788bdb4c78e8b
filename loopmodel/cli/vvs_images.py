"""``loopmodel vvs render`` and ``loopmodel vvs track``: model-based tracking from images."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from loopmodel.errors import InputError

_IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".pgm")


def vvs_render(
    out: Annotated[Path, typer.Option("--out", "-o", help="Output folder")],
    seed: Annotated[int, typer.Option(help="Scenario seed")] = 0,
    frames: Annotated[int, typer.Option(help="Frames (10 per second)")] = 60,
    clutter: Annotated[bool, typer.Option("--clutter/--no-clutter", help="Clutter in the room")] = True,
    init_rot_deg: Annotated[float, typer.Option(help="Rotation error of the start pose written to init.txt")] = 6.0,
    init_pos_m: Annotated[float, typer.Option(help="Position error of the start pose (m)")] = 0.025,
) -> None:
    """Render a seeded scenario of the 4-mirror sensor as a folder 'vvs track' reads.

    The folder holds images/, rig.yaml + mask.png, model.yaml, truth.tum (rig_from_model) and
    init.txt (a perturbed start).
    """
    import cv2
    import numpy as np

    from loopmodel.cli.common import console, progress_bar
    from loopmodel.io.atomic import write_text_atomic
    from loopmodel.io.rig_yaml import format_pose, write_model, write_rig
    from loopmodel.io.trajectory_io import write_trajectory
    from loopmodel.sim.omni_images import OmniRenderer, omni_scenario, perturbed_pose, sensor_mask
    from loopmodel.types import Trajectory

    if frames < 1:
        raise InputError("--frames", f"must be >= 1, got {frames}")
    sc = omni_scenario(seed, frames, clutter=clutter)
    (out / "images").mkdir(parents=True, exist_ok=True)
    renderer = OmniRenderer(sc)
    with progress_bar() as bar:
        task = bar.add_task("render", total=frames)
        for k in range(frames):
            cv2.imwrite(str(out / "images" / f"{k:06d}.png"), renderer.render(k))
            bar.update(task, completed=k + 1)
    write_rig(out / "rig.yaml", sc.sensor.rig(), sensor_mask(sc.sensor))
    write_model(out / "model.yaml", sc.box_size_m)
    times = (np.arange(frames) * 100_000_000).astype(np.int64)
    write_trajectory(out / "truth.tum", Trajectory(times, np.stack(sc.sensor_from_box)), "tum")
    start = perturbed_pose(sc.sensor_from_box[0], init_rot_deg, init_pos_m, np.random.default_rng(10_000 + seed))
    write_text_atomic(out / "init.txt", format_pose(start) + "\n")
    console.print(f"wrote {out}: {frames} images, rig.yaml, mask.png, model.yaml, truth.tum, init.txt")


def vvs_track(
    images: Annotated[Path, typer.Argument(help="Folder of images (all cameras of the rig in each image)")],
    rig: Annotated[Path, typer.Option("--rig", help="rig.yaml (cameras, cam_from_rig, optional mask)")],
    model: Annotated[Path, typer.Option("--model", help="model.yaml (a box)")],
    init: Annotated[str, typer.Option("--init", help="Start pose 'tx ty tz qx qy qz qw' or a file with it")],
    out: Annotated[Path, typer.Option("--out", "-o", help="Output folder")],
    truth: Annotated[Path | None, typer.Option("--truth", help="Ground truth (TUM) to report errors")] = None,
    rate_hz: Annotated[float, typer.Option("--rate", help="Frame rate for the output times")] = 10.0,
) -> None:
    """Track a box model through a folder of images by moving edges and robust VVS.

    Writes poses.tum (rig_from_model per frame) and track.csv.
    """
    import numpy as np

    from loopmodel.cli.common import console, progress_bar
    from loopmodel.geometry.se3 import so3_log
    from loopmodel.io.atomic import write_text_atomic
    from loopmodel.io.images import read_grey_image
    from loopmodel.io.rig_yaml import parse_pose, read_model, read_rig
    from loopmodel.io.trajectory_io import read_trajectory, write_trajectory
    from loopmodel.pose.image_tracking import ImageTracker, ImageTrackingOptions, mask_valid
    from loopmodel.types import Trajectory

    if not images.is_dir():
        raise InputError(images, "expected a folder of images")
    files = sorted(p for p in images.iterdir() if p.suffix.lower() in _IMAGE_SUFFIXES)
    if not files:
        raise InputError(images, f"no images ({', '.join(_IMAGE_SUFFIXES)}) in the folder")
    the_rig, mask = read_rig(rig)
    the_model = read_model(model)
    start = parse_pose(init)
    first = read_grey_image(files[0])  # the declared size checked before decoding
    if mask is not None and mask.shape != first.shape:
        raise InputError(
            rig, f"mask is {mask.shape[1]}x{mask.shape[0]} but the images are {first.shape[1]}x{first.shape[0]}"
        )

    edges = ImageTrackingOptions().edges
    margin = edges.range_px + edges.half_depth_px
    tracker = ImageTracker(the_rig, the_model, start, mask_valid(mask, first.shape, margin))
    poses, rows = [], ["frame,ok,matched,inliers,search_ms,frame_ms"]
    with progress_bar() as bar:
        task = bar.add_task("track", total=len(files))
        for k, f in enumerate(files):
            img = first if k == 0 else read_grey_image(f)
            if img.shape != first.shape:
                raise InputError(f, f"expected a {first.shape[1]}x{first.shape[0]} image like {files[0].name}")
            ft = tracker.track(img)
            poses.append(ft.rig_from_ref)
            rows.append(f"{k},{int(ft.ok)},{ft.num_matched},{ft.num_inliers},{ft.search_ms:.3f},{ft.frame_ms:.3f}")
            bar.update(task, completed=k + 1)
    out.mkdir(parents=True, exist_ok=True)
    times = (np.arange(len(poses)) * (1e9 / rate_hz)).astype(np.int64)
    est = Trajectory(times, np.stack(poses))
    write_trajectory(out / "poses.tum", est, "tum")
    write_text_atomic(out / "track.csv", "\n".join(rows) + "\n")
    ok = sum(r.split(",")[1] == "1" for r in rows[1:])
    msg = f"wrote {out}: {len(poses)} frames, {ok} tracked"
    if truth is not None:
        gt = read_trajectory(truth)
        n = min(len(gt), len(est))
        rot = [
            np.degrees(np.linalg.norm(so3_log(est.world_from_cam[i][:3, :3].T @ gt.world_from_cam[i][:3, :3])))
            for i in range(n)
        ]
        pos = np.linalg.norm(est.world_from_cam[:n, :3, 3] - gt.world_from_cam[:n, :3, 3], axis=1) * 1e3
        msg += f"; against {truth.name}: rotation {np.median(rot):.3f} deg, position {np.median(pos):.2f} mm (median)"
    console.print(msg)
