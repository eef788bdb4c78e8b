"""Session maps (issue 20): save -> load, damaged or newer maps, localization in a map, merging two maps."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from loopmodel.config import Config, LoopConfig, config_from_dict
from loopmodel.errors import InputError
from loopmodel.geometry.se3 import invert_pose, make_pose, so3_log
from loopmodel.io.map_file import ARRAYS_FILE, META_FILE, load_session_map, read_map_file, save_session_map
from loopmodel.loop.session_map import MapInputs, SessionMap, build_session_map
from loopmodel.types import Keyframe, StereoCalibration, StripeAnchors, StripeProfile


def _rot_z(deg: float) -> np.ndarray:
    c, s = np.cos(np.radians(deg)), np.sin(np.radians(deg))
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])


def _small_map(n: int = 4) -> SessionMap:
    """A map of ``n`` keyframes with textured random images (ORB finds features in them)."""
    rng = np.random.default_rng(3)
    K = np.array([[250.0, 0, 159.5], [0, 250.0, 119.5], [0, 0, 1]])
    cal = StereoCalibration(K, K, make_pose(np.eye(3), np.array([-0.06, 0, 0])), (320, 240))
    import cv2

    kfs = []
    for i in range(n):
        img = cv2.GaussianBlur((rng.random((240, 320)) * 255).astype(np.uint8), (3, 3), 0)
        m = 30
        uv = rng.uniform([20, 20], [300, 220], size=(m, 2))
        z = rng.uniform(0.4, 0.8, m)
        pts = np.column_stack([(uv[:, 0] - 159.5) * z / 250, (uv[:, 1] - 119.5) * z / 250, z])
        stereo = np.column_stack([uv[:, 0], uv[:, 0] - 250 * 0.06 / z, uv[:, 1]])
        kfs.append(
            Keyframe(
                i,
                1000 + i,
                make_pose(_rot_z(5 * i), np.array([0.01 * i, 0, 0])),
                np.arange(m) + 100 * i,
                pts,
                stereo,
                image=img,
                frame_index=3 * i,
                prev_keyframe_id=i - 1 if i else None,
                kf_prev_from_kf=make_pose(_rot_z(5), np.array([0.01, 0, 0])) if i else None,
            )
        )
    stripes = [StripeProfile(2000 + s, rng.normal(size=(10 + s, 3))) for s in range(3)]
    kf_from_cam = np.stack([make_pose(_rot_z(s), np.zeros(3)) for s in range(3)])
    anchors = StripeAnchors(stripes, np.array([0, 1, 3]), kf_from_cam)
    inputs = MapInputs(
        cal,
        kfs,
        {k.id: k.world_from_kf for k in kfs},
        np.arange(7),
        rng.normal(size=(7, 3)),
        [(3, 0, make_pose(_rot_z(-15), np.array([-0.03, 0, 0])))],
        anchors,
        "loop: {}\n",
        {"sequence": "synthetic"},
    )
    return build_session_map(inputs, LoopConfig())


def test_map_save_load_round_trip_every_array(tmp_path: Path) -> None:
    smap = _small_map()
    path = save_session_map(tmp_path / "m", smap)
    loaded = load_session_map(path)
    a, b = smap.to_file_data(), loaded.to_file_data()
    assert set(a.arrays) == set(b.arrays) and len(a.arrays) > 30
    for k, v in a.arrays.items():
        assert v.dtype == b.arrays[k].dtype and v.shape == b.arrays[k].shape, k
        assert np.array_equal(v, b.arrays[k], equal_nan=v.dtype.kind == "f"), k
    assert {k: v for k, v in b.meta.items() if k != "info"} == {k: v for k, v in a.meta.items() if k != "info"}
    # what the arrays mean comes back too: features with 3-D points, images, stripe poses
    assert len(loaded.features.feature_set(1)) > 50 and loaded.features.feature_set(1).has_3d.sum() > 10
    assert np.array_equal(loaded.image(2), smap.image(2))
    _, poses = loaded.stripes_with_poses()
    assert np.allclose(poses[2], smap.world_from_kf[3] @ make_pose(_rot_z(2), np.zeros(3)))
    assert loaded.summary()["pose_graph_edges"] == {"odometry": 3, "loop": 1, "between_sessions": 0}
    # no pickle: the arrays load with allow_pickle=False
    with np.load(path / ARRAYS_FILE, allow_pickle=False) as z:
        assert z["world_from_kf"].shape == (4, 4, 4)
    # the database built from the saved bags of words scores a keyframe best against itself
    db = loaded.database()
    ids, scores = db.score_all(loaded.features.feature_set(2))
    assert int(ids[np.argmax(scores)]) == 2


def test_damaged_or_newer_map_one_line_exit_2(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from loopmodel.cli import main

    path = save_session_map(tmp_path / "m", _small_map())
    assert main(["map", "info", str(path)]) == 0
    meta = json.loads((path / META_FILE).read_text())
    meta["version"] = 99
    (path / META_FILE).write_text(json.dumps(meta))
    capsys.readouterr()
    assert main(["map", "info", str(path)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "map.json" in err and "newer" in err
    meta["version"] = 1
    (path / META_FILE).write_text(json.dumps(meta))
    data = (path / ARRAYS_FILE).read_bytes()
    (path / ARRAYS_FILE).write_bytes(data[: len(data) // 2])
    assert main(["map", "info", str(path)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and ARRAYS_FILE in err and "damaged" in err
    (path / META_FILE).write_text("{not json")
    assert main(["map", "info", str(path)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "map.json" in err
    with pytest.raises(InputError, match="does not exist"):
        read_map_file(tmp_path / "nothing")


# ---------------------------------------------------------------------- with a simulated scan
def _session(tmp: Path, name: str, seed: int, azimuth_deg: float, frames: int) -> Path:
    from loopmodel.sim import generate as gen

    cfg = config_from_dict(
        {
            "simulation": {
                "seed": seed,
                "workers": 1,
                "camera": {"width_px": 320, "height_px": 240, "fx_px": 250.0},
                "scene": {"seed": 5},
                "trajectory": {"kind": "browse", "frames": frames, "start_azimuth_deg": azimuth_deg},
            }
        }
    )
    path = tmp / f"{name}.mcap"
    gen.simulate_scan(cfg.simulation, path)
    return path


@pytest.fixture(scope="module")
def first_session(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """A 60-frame browse of the object and its run's results folder (with its map)."""
    from loopmodel.io.sequence import open_sequence
    from loopmodel.pipeline import run_pipeline

    tmp = tmp_path_factory.mktemp("sessions")
    seq = _session(tmp, "a", 11, 0.0, 60)
    out = run_pipeline(open_sequence(seq), Config(), tmp / "runs", "a", handle_signals=False)
    return seq, out.folder


@pytest.fixture(scope="module")
def second_session(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """A 30-frame browse of the same object starting 60 deg further round, and its normal run."""
    from loopmodel.io.sequence import open_sequence
    from loopmodel.pipeline import run_pipeline

    tmp = tmp_path_factory.mktemp("sessions_b")
    seq = _session(tmp, "b", 12, 60.0, 30)
    out = run_pipeline(open_sequence(seq), Config(), tmp / "runs", "b", handle_signals=False)
    return seq, out.folder


def _truth_from_run(folder: Path, seq_path: Path) -> np.ndarray:
    from loopmodel.geometry.align import umeyama_alignment
    from loopmodel.io.sequence import open_sequence
    from loopmodel.io.trajectory_io import read_trajectory

    est = read_trajectory(folder / "trajectory_final.tum")
    gt = open_sequence(seq_path).ground_truth
    _, ia, ib = np.intersect1d(est.timestamps_ns, gt.timestamps_ns, return_indices=True)
    R, t, _ = umeyama_alignment(est.positions_m[ia], gt.positions_m[ib], with_scale=False)
    return make_pose(np.asarray(R), np.asarray(t))


@pytest.mark.slow
def test_second_session_localizes_in_the_map(
    first_session: tuple[Path, Path], second_session: tuple[Path, Path], tmp_path: Path
) -> None:
    from loopmodel.io.sequence import open_sequence
    from loopmodel.pipeline import run_pipeline

    seq_a, folder_a = first_session
    smap = load_session_map(folder_a)
    seq_b = second_session[0]
    cfg = Config()
    cfg.session.mode = "localize"
    res = run_pipeline(open_sequence(seq_b), cfg, tmp_path / "runs", "b", handle_signals=False, base_map=smap)
    m = res.metrics
    assert m["map_localized"] and m["map_first_localized_frame"] <= 5
    assert (res.folder / "trajectory_in_map.tum").is_file() and not (res.folder / "map").exists()
    assert m["localization_status"].count("MAP") >= 25
    truth_from_map = _truth_from_run(folder_a, seq_a)
    gt = open_sequence(seq_b).ground_truth
    idx = {int(t): i for i, t in enumerate(gt.timestamps_ns)}
    rot, pos = [], []
    for t, T in zip(res.localized.timestamps_ns, res.localized.world_from_cam, strict=True):
        d = invert_pose(gt.world_from_cam[idx[int(t)]]) @ truth_from_map @ T
        rot.append(np.degrees(np.linalg.norm(so3_log(d[:3, :3]))))
        pos.append(np.linalg.norm(d[:3, 3]) * 1e3)
    # measured (clean world, 320x240): first localized frame 2, 30 of 30 frames in the map,
    # median errors 0.042 deg / 0.55 mm after aligning A's map to the truth by A's trajectory
    assert np.median(rot) < 0.15 and np.median(pos) < 1.5
    # every localized frame, also those before the first success (moved with their keyframe): the
    # end of the run keeps the relocalized poses (measured: largest 0.082 deg / 1.05 mm)
    assert max(rot) < 0.15 and max(pos) < 2.0


@pytest.mark.slow
def test_merge_recovers_known_offset(first_session: tuple[Path, Path], second_session: tuple[Path, Path]) -> None:
    import dataclasses

    from loopmodel.loop.merge import merge_maps

    (seq_a, folder_a), (seq_b, folder_b) = first_session, second_session
    a, b = load_session_map(folder_a), load_session_map(folder_b)
    # B's world moved by a known offset on top of where B's own run put it
    offset = make_pose(_rot_z(30.0), np.array([0.2, -0.1, 0.05]))
    b = dataclasses.replace(b, world_from_kf=offset[None] @ b.world_from_kf)
    merged, report = merge_maps(a, b, LoopConfig())
    # the truth, independently: each run's own trajectory aligned to its ground truth
    truth_from_a, truth_from_b = _truth_from_run(folder_a, seq_a), _truth_from_run(folder_b, seq_b)
    expected = invert_pose(truth_from_a) @ truth_from_b @ invert_pose(offset)
    err = invert_pose(expected) @ report.world_a_from_world_b
    # measured: 9 links of 9 relocalized keyframes; 0.77 mm / 0.033 deg off the truth's offset
    assert report.links >= 5
    assert np.linalg.norm(err[:3, 3]) < 0.0025 and np.degrees(np.linalg.norm(so3_log(err[:3, :3]))) < 0.15
    assert len(merged) == len(a) + len(b) and set(merged.session.tolist()) == {0, 1}
    assert int(np.sum(merged.edge_kind == 2)) == report.links
    merged_back = load_session_map(save_session_map(folder_a.parent / "merged", merged))
    assert np.array_equal(merged_back.world_from_kf, merged.world_from_kf)


@pytest.mark.slow
def test_resume_continues_from_the_last_keyframe(first_session: tuple[Path, Path], tmp_path: Path) -> None:
    from loopmodel.io.map_file import read_resume_point
    from loopmodel.io.sequence import open_sequence
    from loopmodel.io.trajectory_io import read_trajectory
    from loopmodel.pipeline import run_pipeline

    seq_path, folder_full = first_session
    # max_frames stands for an interruption there, whose last frame is not made a keyframe (tail14)
    interrupted = Config()
    interrupted.frontend.last_frame_keyframe = False
    part = run_pipeline(open_sequence(seq_path), interrupted, tmp_path, "part", max_frames=30, handle_signals=False)
    point = read_resume_point(part.folder)
    assert 0 < point.frame_index < 30
    resumed = run_pipeline(open_sequence(seq_path), Config(), tmp_path, "part", handle_signals=False, resume=point)
    # only the frames from the last keyframe on were processed again
    assert len(resumed.frames) == 60 - point.frame_index
    full = read_trajectory(folder_full / "trajectory_final.tum")
    res = read_trajectory(resumed.folder / "trajectory_final.tum")
    assert np.array_equal(res.timestamps_ns, full.timestamps_ns)
    d_mm = np.linalg.norm(res.positions_m - full.positions_m, axis=1) * 1e3
    # measured: resumed at frame 25; 0.27 mm median, 0.39 mm largest position difference
    assert np.median(d_mm) < 1.0 and d_mm.max() < 1.5
    smap = load_session_map(resumed.folder)
    assert len(smap) == len(point.map) - 1 + resumed.metrics["keyframes"]


def _raw_rig(fx: float = 500.0, cx_right: float = 322.0, k1: float = -0.28) -> StereoCalibration:
    KL = np.array([[fx, 0, 319.5], [0, fx, 239.5], [0, 0, 1.0]])
    KR = np.array([[fx * 0.9977, 0, cx_right], [0, fx * 0.9975, 241.5], [0, 0, 1.0]])
    c, s = np.cos(np.radians(0.3)), np.sin(np.radians(0.3))
    Ry = np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])
    dist = np.array([k1, 0.075, 0.0, 0.0, 0.0])
    return StereoCalibration(KL, KR, make_pose(Ry, np.array([-0.06, 0.0004, 0.0004])), (640, 480), dist, dist, False)


def test_map_carries_the_refined_calibration_and_a_same_rig_session_starts_from_it(tmp_path: Path) -> None:
    """Issue 31 item 4: the map file keeps the refined calibration (old maps load without it); the rig check."""
    from loopmodel.calibration.refine_rig import PARAM_NAMES
    from loopmodel.config import SelfCalibrationConfig
    from loopmodel.loop.session_map import MapCalibration
    from loopmodel.sessions import rig_difference_sigma, session_calibration

    smap = _small_map()
    old_path = save_session_map(tmp_path / "old", smap)
    assert load_session_map(old_path).refined_calibration is None  # a map without it loads as before
    recorded, refined = _raw_rig(), _raw_rig(fx=500.25, cx_right=321.7, k1=-0.2795)
    sigma = {n: 0.1 for n in PARAM_NAMES[:12]} | {"rot_x_deg": 0.01, "rot_y_deg": 0.01, "rot_z_deg": 0.01,
                                                   "baseline_m": 4e-5}
    smap.refined_calibration = MapCalibration(refined, recorded, sigma, {n: 2 * v for n, v in sigma.items()})
    loaded = load_session_map(save_session_map(tmp_path / "new", smap))
    mc = loaded.refined_calibration
    assert mc is not None and mc.sigma == sigma and mc.sigma_prior["baseline_m"] == 8e-5
    for a, b in ((mc.refined, refined), (mc.recorded, recorded)):
        assert np.array_equal(a.K_left, b.K_left) and np.array_equal(a.K_right, b.K_right)
        assert np.array_equal(a.right_from_left, b.right_from_left) and np.array_equal(a.dist_right, b.dist_right)
        assert a.image_size == b.image_size and not a.rectified
    assert loaded.summary()["calibration_refined"] is True
    cfg = SelfCalibrationConfig()
    # the same rig, recorded again 0.3 px / 0.002 off (the configured priors): the map's refined one
    same = _raw_rig(fx=499.8, cx_right=322.3, k1=-0.282)
    diff = rig_difference_sigma(same, mc, cfg)
    # fx: 0.45 px over hypot(0.3, 0.1) = 1.42 sigma; cx_right 0.6 px: 1.90; k1 0.0025 over hypot(0.002, 0.1)
    assert diff["fx_left_px"] == pytest.approx(0.45 / np.hypot(0.3, 0.1))
    assert diff["cx_right_px"] == pytest.approx(0.6 / np.hypot(0.3, 0.1))
    assert diff["rot_y_deg"] == pytest.approx(0.0, abs=1e-9)
    cal, info = session_calibration(same, loaded, cfg)
    assert cal is mc.refined and info["session_calibration"] == "map"
    assert session_calibration(same, loaded, cfg, same_rig_sigma=0.0)[0] is same  # session.same_rig_sigma 0: never
    # another camera of the model: focal lengths 2 px apart (6.3 sigma): the session keeps its own
    other = _raw_rig(fx=502.0)
    cal, info = session_calibration(other, loaded, cfg)
    assert cal is other and info["session_calibration"] == "own" and info["session_calibration_max_sigma"] > 4.0
    # another image size, or a map without a refined calibration: its own
    assert session_calibration(_raw_rig(), load_session_map(old_path), cfg)[1]["session_calibration"] == "own"


@pytest.mark.slow
def test_refined_map_points_and_a_second_session_on_the_same_rig(tmp_path: Path) -> None:
    """Issue 31 item 4 in runs: a refined session's map, then a session of the same rig localizing in it.

    A rendered rig whose right camera's cx is 0.6 px off what ``calib.txt`` says: the front end's
    stereo points are 2-3 % too far. Their true depth follows from the rendering (the measured
    disparity plus 0.6 px); the map keeps them as the refined calibration places them.
    """
    import sys

    sys.path.insert(0, str(Path(__file__).parent))
    from frontend_scene import write_kitti_folder

    from loopmodel.io.sequence import open_sequence
    from loopmodel.pipeline import run_pipeline

    folder = tmp_path / "seq"
    write_kitti_folder(folder, 16, np.random.default_rng(7), cx_right_error_px=0.6)
    cfg = Config()
    cfg.frontend.max_disparity_px = 64
    cfg.frontend.max_features = 400
    cfg.frontend.min_tracked_fraction = 0.95
    cfg.calibration.refine = "final"  # type: ignore[assignment]
    cfg.mapping.write_mesh = False
    a = run_pipeline(open_sequence(folder), cfg, tmp_path, "A")
    assert a.folder is not None
    smap = load_session_map(a.folder / "map")
    mc = smap.refined_calibration
    assert mc is not None and np.array_equal(mc.refined.K_right, a.calibration_refined.K_right)
    # every keyframe point against its true depth (the front end's from the same stereo match)
    f_b = 450.0 * 0.3
    z_rec = f_b / (smap.lm_stereo_px[:, 0] - smap.lm_stereo_px[:, 1])
    z_true = f_b / (smap.lm_stereo_px[:, 0] - smap.lm_stereo_px[:, 1] + 0.6)
    err_rec = np.median(np.abs(z_rec / z_true - 1.0))
    err_map = np.median(np.abs(smap.lm_points_in_kf[:, 2] / z_true - 1.0))
    # measured: the front end's points 4.05 % off (median), the map's 0.067 %
    assert err_map < 0.05 * err_rec, (err_map, err_rec)
    # a second session of the rig (the same recorded calibration) starts from the map's refined one
    cfg.session.mode = "localize"  # type: ignore[assignment]
    b = run_pipeline(open_sequence(folder), cfg, tmp_path, "B", base_map=smap)
    m = b.metrics
    # measured: 0.855 sigma at most (cx_right_px)
    assert m["session_calibration"] == "map" and m["session_calibration_max_sigma"] < 2.0
    assert m["localized_frames"] == 16


def test_map_archiver_encodes_keyframe_images_after_the_frames(monkeypatch: pytest.MonkeyPatch) -> None:
    """fe8: no PNG encoding while keyframes arrive (the tracking thread's cores); at take(), lossless."""
    from concurrent.futures import Future
    from types import SimpleNamespace

    import cv2

    import loopmodel.loop.session_map as sm
    from loopmodel.loop.features import empty_features

    encoded: list[int] = []
    png = sm._png
    monkeypatch.setattr(sm, "_png", lambda image: encoded.append(image.size) or png(image))
    rng = np.random.default_rng(5)
    K = np.array([[250.0, 0, 159.5], [0, 250.0, 119.5], [0, 0, 1]])
    cal = StereoCalibration(K, K, make_pose(np.eye(3), np.array([-0.06, 0, 0])), (320, 240))
    archiver = sm.KeyframeArchiver(cal, LoopConfig())
    images = [cv2.GaussianBlur((rng.random((240, 320)) * 255).astype(np.uint8), (3, 3), 0) for _ in range(3)]
    features = empty_features(LoopConfig().descriptor)
    for i, img in enumerate(images):
        detection: Future[SimpleNamespace] = Future()
        detection.set_result(SimpleNamespace(features=features))
        archiver.add(Keyframe(i, 1000 + i, np.eye(4), np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros((0, 3)),
                              image=img), detection)
    archiver._pool.submit(lambda: None).result()  # the worker has taken every keyframe's features
    assert encoded == []
    content = archiver.take()
    assert sorted(content) == [0, 1, 2] and len(encoded) == 3
    for i, img in enumerate(images):
        assert content[i].features is features
        assert np.array_equal(cv2.imdecode(content[i].png, cv2.IMREAD_UNCHANGED), img)
