"""``loopmodel loop``: place recognition, loop detection and vocabularies on image folders."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Any

import typer

from loopmodel.cli.common import (
    ConfigOption,
    app,
    console,
    progress_bar,
)
from loopmodel.config import apply_overrides, load_config
from loopmodel.errors import InputError

loop_app = typer.Typer(help="Place recognition, relocalization and loop detection.", no_args_is_help=True)

app.add_typer(loop_app, name="loop")


def _image_files(folder: Path) -> list[Path]:
    import re

    if not folder.is_dir():
        raise InputError(folder, "is not a folder of images")
    files = [p for p in folder.iterdir() if p.suffix.lower() in (".png", ".jpg", ".jpeg", ".bmp", ".pgm")]
    if not files:
        raise InputError(folder, "holds no .png/.jpg/.bmp/.pgm image")

    def key(p: Path) -> tuple[int, str]:
        m = re.search(r"(\d+)", p.stem)
        return (int(m.group(1)) if m else -1, p.name)

    return sorted(files, key=key)


@loop_app.command("detect")
def loop_detect(
    folder: Annotated[Path, typer.Argument(help="Folder of images in time order (numbered names)")],
    out: Annotated[Path | None, typer.Option("--out", help="CSV of accepted loops")] = None,
    vocabulary: Annotated[Path | None, typer.Option("--vocabulary", help="trained vocabulary .npz")] = None,
    config: ConfigOption = None,
) -> None:
    """Loop detection on an image sequence (monocular: fundamental-matrix verification)."""
    from loopmodel.io.atomic import write_text_atomic
    from loopmodel.io.images import read_grey_image
    from loopmodel.io.vocabulary_file import loop_vocabulary
    from loopmodel.loop.closure import detector_from_config
    from loopmodel.loop.features import detect_and_describe, make_extractor

    cfg = load_config(config).loop
    if vocabulary is not None:
        cfg = apply_overrides(cfg, {"vocabulary_path": str(vocabulary)}, {"vocabulary_path": "--vocabulary"})
    files = _image_files(folder)
    voc = loop_vocabulary(cfg)
    ex = make_extractor(cfg.descriptor, cfg.n_features, cfg.surf)
    det = None
    rows = ["query_index,query_file,match_index,match_file,inliers"]
    with progress_bar() as bar:
        task = bar.add_task("images", total=len(files))
        for i, f in enumerate(files):
            img = read_grey_image(f)  # the declared size checked before decoding
            if det is None:
                det = detector_from_config(cfg, None, float(img.shape[1]), voc)
            ev = det.process(i, detect_and_describe(img, cfg.descriptor, cfg.n_features, ex))
            if ev is not None:
                rows.append(f"{i},{f.name},{ev.match_id},{files[ev.match_id].name},{ev.n_inliers}")
            bar.advance(task)
    assert det is not None
    for r in rows[1:]:
        q, qf, m, mf, n = r.split(",")
        console.print(f"loop: {qf} -> {mf} ({n} inliers)")
    console.print(f"{len(rows) - 1} loops accepted, {len(det.rejected)} candidates rejected")
    if out is not None:
        write_text_atomic(out, "\n".join(rows) + "\n")
        console.print(f"loops written to {out}")


@loop_app.command("vocabulary")
def loop_vocabulary(
    folder: Annotated[Path, typer.Argument(help="Folder of training images")],
    out: Annotated[Path, typer.Argument(help="Output vocabulary (.npz)")],
    source: Annotated[str, typer.Option("--source", help="what the images are (kept in the file)")] = "",
    seed: Annotated[int, typer.Option("--seed", help="random seed of the clustering")] = 0,
    config: ConfigOption = None,
) -> None:
    """Train a vocabulary tree on a folder of images (reproducible).

    By k-majority for ORB, k-means for SIFT/SURF; for ``loop.descriptor`` with ``loop.n_features``
    per image.
    """
    from collections.abc import Iterator

    from loopmodel.io.images import read_grey_image
    from loopmodel.loop.vocabulary import train_from_images

    cfg = load_config(config).loop
    files = _image_files(folder)

    def images() -> Iterator[Any]:
        for f in files:
            img = read_grey_image(f)  # the declared size checked before decoding
            yield img

    voc = train_from_images(
        images(),
        cfg.descriptor,
        cfg.n_features,
        cfg.vocabulary_branching,
        cfg.vocabulary_levels,
        seed,
        source=source or folder.name,
    )
    from loopmodel.io.vocabulary_file import save_vocabulary

    save_vocabulary(out, voc)
    console.print(f"{voc.n_words} {cfg.descriptor} words from {voc.info['images']} images written to {out}")
