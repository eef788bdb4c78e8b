"""A folder reader's right images decoded only where the front end uses them: its keyframes (issue 36's CPU)."""

from __future__ import annotations

import pickle
import threading
from pathlib import Path

import numpy as np
import pytest
from frontend_scene import write_kitti_folder

import loopmodel.io.images as images_mod
from loopmodel.config import FrontendConfig
from loopmodel.errors import InputError
from loopmodel.frontend import FrontEnd
from loopmodel.io.images import DeferredRightFrame, read_image
from loopmodel.io.sequence import open_sequence
from loopmodel.types import StereoFrame

# a keyframe every few frames (max_parallax_ratio): some frames are keyframes, most are not
CFG = FrontendConfig(
    max_disparity_px=64, max_features=400, grid_cols=6, grid_rows=3, min_tracked=60, max_parallax_ratio=0.03
)


def _decoded_paths(monkeypatch: pytest.MonkeyPatch) -> list[tuple[str, int]]:
    """(folder, thread) of each image decoded from now on."""
    seen: list[tuple[str, int]] = []
    inner = images_mod.decode_image

    def counting(data: bytes, source: str | Path) -> np.ndarray:
        seen.append((Path(source).parent.name, threading.get_ident()))
        return inner(data, source)

    monkeypatch.setattr(images_mod, "decode_image", counting)
    return seen


def test_right_images_are_decoded_at_keyframes_only_with_the_same_poses(
    tmp_path: Path, rng: np.random.Generator, monkeypatch: pytest.MonkeyPatch
) -> None:
    write_kitti_folder(tmp_path / "seq", 16, rng)
    seq = open_sequence(tmp_path / "seq")
    eager = [StereoFrame(f.timestamp_ns, f.left, f.right, f.index) for f in seq.frames()]  # decoded now
    seen = _decoded_paths(monkeypatch)
    fe = FrontEnd(seq.calibration, CFG)
    deferred = [fe.process(f) for f in seq.frames()]
    keyframes = sum(r.is_keyframe for r in deferred)
    # measured: 16 left images decoded, 4 right ones (the 4 keyframes: frames 0, 5, 9, 13), the right
    # ones on a keyframe thread beside the corner detection, never on the tracking thread
    folders = [name for name, _ in seen]
    assert folders.count("image_0") == 16
    assert 2 <= keyframes < 16 and folders.count("image_1") == keyframes
    assert all(t != threading.get_ident() for name, t in seen if name == "image_1")
    fe = FrontEnd(seq.calibration, CFG)
    for a, b in zip(deferred, [fe.process(f) for f in eager], strict=True):
        assert a.is_keyframe == b.is_keyframe
        np.testing.assert_array_equal(a.world_from_cam, b.world_from_cam)


def test_a_corrupt_right_image_is_reported_where_it_is_used(tmp_path: Path, rng: np.random.Generator) -> None:
    """Never at a frame that does not use it; at a keyframe, an input error naming its file."""
    write_kitti_folder(tmp_path / "seq", 16, rng)
    seq = open_sequence(tmp_path / "seq")
    fe = FrontEnd(seq.calibration, CFG)
    kf = [fe.process(f).is_keyframe for f in seq.frames()]
    j = next(i for i in range(1, 16) if kf[i] and not all(kf[1:i]))  # a keyframe after a frame that is none
    k = next(i for i in range(1, j) if not kf[i])
    for i in (j, k):
        bad = tmp_path / "seq" / "image_1" / f"{i:06d}.png"
        bad.write_bytes(bad.read_bytes()[:200])  # header intact (the declared size read), data cut
    fe = FrontEnd(seq.calibration, CFG)
    frames = iter(open_sequence(tmp_path / "seq").frames())
    for _ in range(j):
        fe.process(next(frames))  # frame k's right image is never decoded
    frame = next(frames)
    assert isinstance(frame, DeferredRightFrame) and not frame.right_decoded
    with pytest.raises(InputError, match=f"{j:06d}.png"):
        fe.process(frame)


def test_a_deferred_frame_pickles_and_replaces_as_a_stereo_frame(tmp_path: Path, rng: np.random.Generator) -> None:
    import dataclasses

    write_kitti_folder(tmp_path / "seq", 2, rng)
    frame = next(iter(open_sequence(tmp_path / "seq").frames()))
    truth = read_image(tmp_path / "seq" / "image_1" / "000000.png")
    back = pickle.loads(pickle.dumps(frame))
    assert type(back) is StereoFrame and back.index == 0
    np.testing.assert_array_equal(back.right, truth)
    moved = dataclasses.replace(frame, index=7)
    assert moved.index == 7
    np.testing.assert_array_equal(moved.right, truth)


def test_prepare_decodes_an_expected_keyframes_right_image_before_its_frame(
    tmp_path: Path, rng: np.random.Generator, monkeypatch: pytest.MonkeyPatch
) -> None:
    """fe7: ``FrontEnd.prepare`` decodes an expected keyframe's right image before its frame.

    (The pipeline's frame loop, outside the frame's time.) The poses are those without it.
    """
    write_kitti_folder(tmp_path / "seq", 16, rng)
    seq = open_sequence(tmp_path / "seq")
    fe = FrontEnd(seq.calibration, CFG)
    plain = [fe.process(f) for f in seq.frames()]
    seen = _decoded_paths(monkeypatch)
    fe = FrontEnd(seq.calibration, CFG)
    prepared, ahead, within = [], 0, 0
    for f in seq.frames():
        before = len(seen)
        fe.prepare(f)
        ahead += sum(name == "image_1" for name, _ in seen[before:])
        assert isinstance(f, DeferredRightFrame)
        was_decoded = f.right_decoded
        prepared.append(fe.process(f))
        within += prepared[-1].is_keyframe and not was_decoded
    keyframes = sum(r.is_keyframe for r in prepared)
    # measured: 4 keyframes (frames 0, 5, 9, 13), the last three expected a frame ahead (frame 0 cannot
    # be), no right image decoded for a frame that made none
    assert [r.is_keyframe for r in prepared] == [r.is_keyframe for r in plain]
    assert ahead == keyframes - 1 and within == 1
    assert sum(name == "image_1" for name, _ in seen) == keyframes
    for a, b in zip(prepared, plain, strict=True):
        np.testing.assert_array_equal(a.world_from_cam, b.world_from_cam)


def test_an_mcap_scans_right_images_are_decoded_at_keyframes_only(
    tmp_path: Path, rng: np.random.Generator, monkeypatch: pytest.MonkeyPatch
) -> None:
    """orb13: the MCAP reader defers its PNG right images too; the same poses as with every image decoded."""
    import loopmodel.io.mcap_io as mcap_mod
    from loopmodel.io.convert import convert_sequence

    write_kitti_folder(tmp_path / "seq", 16, rng)
    path = convert_sequence(open_sequence(tmp_path / "seq"), tmp_path / "seq.mcap", "mcap")
    seq = open_sequence(path)
    eager = [StereoFrame(f.timestamp_ns, f.left, f.right, f.index) for f in seq.frames()]
    kitti = [f.right for f in open_sequence(tmp_path / "seq").frames()]
    for f, right in zip(eager, kitti, strict=True):
        np.testing.assert_array_equal(f.right, right)  # the deferred decode is the file's image
    seen: list[str] = []
    inner = mcap_mod.decode_image

    def counting(msg: object, schema: str, topic: str, max_pixels: int = 0) -> np.ndarray:
        seen.append(topic.split()[0])
        return inner(msg, schema, topic, max_pixels)

    monkeypatch.setattr(mcap_mod, "decode_image", counting)
    fe = FrontEnd(seq.calibration, CFG)
    deferred = [fe.process(f) for f in seq.frames()]
    keyframes = sum(r.is_keyframe for r in deferred)
    assert seen.count("/cam0/image_raw") == 16
    assert 2 <= keyframes < 16 and seen.count("/cam1/image_raw") == keyframes
    fe = FrontEnd(seq.calibration, CFG)
    for a, b in zip(deferred, [fe.process(f) for f in eager], strict=True):
        assert a.is_keyframe == b.is_keyframe
        np.testing.assert_array_equal(a.world_from_cam, b.world_from_cam)
