"""Loop detection: vocabulary, database, verified loops on a revisit, none without one."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from loopmodel.geometry.camera import CentralCamera
from loopmodel.geometry.se3 import invert_pose, make_pose, so3_exp, so3_log
from loopmodel.loop.closure import LoopDetector, LoopParams
from loopmodel.loop.database import PlaceParams
from loopmodel.loop.features import FeatureSet, detect_and_describe
from loopmodel.loop.vocabulary import Vocabulary, bow_score

CAM = CentralCamera(400.0, 400.0, 319.5, 239.5)


def test_vocabulary_tree_separates_prototypes(rng: np.random.Generator, tmp_path: Path) -> None:
    """Vocabulary training on noisy copies of 27 hierarchical binary prototypes.

    The prototypes are built as a 3-level hierarchy (3 random roots, each with 3 children 25 % of
    bits away, each with 3 children 12 % away): after training (k=3, 3 levels) every copy of a
    prototype falls into that prototype's word and different prototypes do not share one.
    """

    def children(parents: np.ndarray, p_flip: float) -> np.ndarray:
        kids = np.repeat(parents, 3, axis=0)
        flips = rng.random(kids.shape + (8,)) < p_flip
        return kids ^ np.packbits(flips, axis=-1).reshape(kids.shape)

    protos = children(children(rng.integers(0, 256, (3, 32), dtype=np.uint8), 0.25), 0.12)
    labels = np.repeat(np.arange(27), 40)
    desc = protos[labels].copy()
    flips = rng.random(desc.shape + (8,)) < 0.02
    desc ^= np.packbits(flips, axis=-1).reshape(desc.shape)
    voc = Vocabulary.train(desc, branching=3, levels=3, rng=rng)
    words = voc.transform(desc)
    for p in range(27):
        assert np.unique(words[labels == p]).size == 1
    assert np.unique(words).size == 27
    from loopmodel.io.vocabulary_file import read_vocabulary, save_vocabulary

    save_vocabulary(tmp_path / "voc.npz", voc)
    again = read_vocabulary(tmp_path / "voc.npz")
    assert np.array_equal(again.transform(desc), words)
    a = voc.bow(desc[labels < 10])
    b = voc.bow(desc[labels >= 10])
    assert bow_score(a, a) == pytest.approx(1.0)
    assert bow_score(a, b) == pytest.approx(0.0)


def test_vocabulary_float_descriptors(rng: np.random.Generator) -> None:
    centres = rng.normal(0, 10, (8, 16)).astype(np.float32)
    labels = np.repeat(np.arange(8), 30)
    desc = centres[labels] + rng.normal(0, 0.3, (240, 16)).astype(np.float32)
    voc = Vocabulary.train(desc, branching=8, levels=1, rng=rng)
    words = voc.transform(desc)
    assert all(np.unique(words[labels == c]).size == 1 for c in range(8))


class _World:
    """Landmarks on the inside of a cylinder (radius 6 m) with random binary descriptors.

    A camera at the centre, looking outwards, sees them with 0.5 px noise and stereo depth with 1 %
    noise.
    """

    def __init__(self, rng: np.random.Generator, n: int = 4000) -> None:
        ang = rng.uniform(0, 2 * np.pi, n)
        self.p_world = np.column_stack([6 * np.cos(ang), rng.uniform(-2, 2, n), 6 * np.sin(ang)])
        self.desc = rng.integers(0, 256, (n, 32), dtype=np.uint8)
        self.rng = rng

    def pose(self, yaw: float, x: float = 0.0) -> np.ndarray:
        """world_from_cam: camera at (x, 0, 0) with its z axis at angle ``yaw`` in x-z."""
        R = so3_exp([0.0, -yaw + np.pi / 2, 0.0])  # z axis -> (cos yaw, 0, sin yaw)
        return make_pose(R, [x, 0.0, 0.0])

    def keyframe(self, world_from_cam: np.ndarray) -> FeatureSet:
        cam_from_world = invert_pose(world_from_cam)
        p = self.p_world @ cam_from_world[:3, :3].T + cam_from_world[:3, 3]
        uv = CAM.project(np.where(p[:, 2:] > 0.1, p, 1.0))
        vis = (p[:, 2] > 0.5) & np.all((uv > 0) & (uv < [640, 480]), axis=1)
        idx = np.flatnonzero(vis)
        idx = idx[self.rng.random(idx.size) < 0.7]
        uvn = uv[idx] + self.rng.normal(0, 0.5, (idx.size, 2))
        pts = p[idx] * (1 + self.rng.normal(0, 0.01, idx.size))[:, None]
        d = self.desc[idx].copy()
        flips = self.rng.random(d.shape + (8,)) < 0.03
        d ^= np.packbits(flips, axis=-1).reshape(d.shape)
        return FeatureSet(uvn, d, "orb", pts)


def _params() -> LoopParams:
    return LoopParams(place=PlaceParams(min_gap=6, train_after=5, branching=8, levels=3))


def test_orbit_loop_found_with_correct_relative_pose(rng: np.random.Generator) -> None:
    world = _World(rng)
    det = LoopDetector(CAM, _params())
    yaws = np.radians(np.arange(0, 400, 15))  # one turn and a bit: revisits the start
    loops = []
    poses = [world.pose(y) for y in yaws]
    for k, T in enumerate(poses):
        ev = det.process(k, world.keyframe(T))
        if ev is not None:
            loops.append(ev)
    assert loops, [e.reason for e in det.rejected]
    for ev in loops:
        assert ev.query_id - ev.match_id >= 6
        assert abs(((yaws[ev.query_id] - yaws[ev.match_id]) + np.pi) % (2 * np.pi) - np.pi) < np.radians(
            70
        )  # views overlap
        true_rel = invert_pose(poses[ev.match_id]) @ poses[ev.query_id]
        assert ev.match_from_query is not None
        err = invert_pose(true_rel) @ ev.match_from_query
        assert np.degrees(np.linalg.norm(so3_log(err[:3, :3]))) < 0.5
        assert np.linalg.norm(err[:3, 3]) < 0.05


def test_no_revisit_closes_no_loop(rng: np.random.Generator) -> None:
    world = _World(rng)
    det = LoopDetector(CAM, _params())
    for k, y in enumerate(np.radians(np.arange(0, 240, 15))):  # views never overlap the first again
        assert det.process(k, world.keyframe(world.pose(y))) is None
    assert not det.accepted


def test_false_place_candidates_are_rejected_and_logged(rng: np.random.Generator) -> None:
    """A keyframe with copied descriptors but scrambled geometry fails verification.

    Its descriptors copy an old one but its geometry is scrambled; it passes place recognition and
    must fail verification (logged, not used).
    """
    world = _World(rng)
    det = LoopDetector(CAM, _params())
    kfs = [world.keyframe(world.pose(y)) for y in np.radians(np.arange(0, 200, 15))]
    for k, f in enumerate(kfs):
        det.process(k, f)
    n0 = len(kfs)
    for j in range(3):  # three consecutive impostors of keyframes 1, 2, 3
        src = kfs[1 + j]
        perm = rng.permutation(len(src))
        fake = FeatureSet(src.keypoints_px[perm], src.descriptors, "orb", src.points_in_kf[perm])
        assert det.process(n0 + j, fake) is None
    assert det.rejected
    assert not det.accepted


@pytest.mark.slow
def test_no_loop_without_revisit_on_real_images(shared_data: Path) -> None:
    """RTAB-Map corridor images 1-30 walk away without coming back: no loop."""
    folder = shared_data / "loop_images" / "samples"
    det = LoopDetector(None, LoopParams(place=PlaceParams(min_gap=6, train_after=8)), image_width_px=512)
    for i in range(30):
        img = cv2.imread(str(folder / f"{i + 1}.jpg"), cv2.IMREAD_GRAYSCALE)
        assert det.process(i, detect_and_describe(img, "orb", 700)) is None


def test_cli_loop_detect_errors(tmp_path: Path) -> None:
    from loopmodel.cli import main

    assert main(["loop", "detect", str(tmp_path / "missing")]) == 2
    assert main(["loop", "detect", str(tmp_path)]) == 2  # no images
