"""Mapping: laser-stripe extraction, stripe-to-world integration, open3d meshing, accuracy.

Pipeline use (poses ``world_from_*`` 4x4 in metres, times in ns)::

    poses = AnchoredTrajectory()                        # frame poses relative to keyframes
    smap = StripeMap(config.mapping, poses)             # stripes placed with those poses
    poses.set_keyframe(kf_id, world_from_kf)            # each new keyframe
    poses.add_frame(t_ns, kf_id=kf_id, kf_from_cam=T)   # each tracked frame, in time order
    smap.add(stripe)                                    # each StripeProfile (left-camera frame)
    live = smap.update_live_mesh()                      # chunked live mesh (dirty blocks only)
    poses.update_keyframes({kf: world_from_kf})         # after iSAM2 / loop closure: stripes follow
    poses.update_poses(final_trajectory)                # or: frame poses by timestamp
    mesh = smap.mesh()                                  # whole surface (Poisson or BPA)
    io.stripes_io.save_stripes(results / "stripes.npz", smap.stripes())  # sensor frame
    io.mesh_io.write_mesh(results / "mesh.ply", mesh)   # binary PLY, metres, world frame
    metrics.update(mesh_error_metrics(stripes, {"gt": gt, "before": online, "after": final},
                                      read_mesh(mcap_path)))   # scene.ply attachment

Offline: ``StripeMap.from_trajectory(trajectory, stripes, config)``.
"""

from typing import Any

from loopmodel.mapping.anchored import AnchoredTrajectory
from loopmodel.mapping.extraction import (
    LightPlane,
    extract_laser_peaks,
    stripe_from_image,
    triangulate_with_plane,
)
from loopmodel.mapping.stripe_map import StripeMap

__all__ = [
    "LightPlane",
    "MeshAccuracy",
    "AnchoredTrajectory",
    "StripeMap",
    "extract_laser_peaks",
    "mesh_accuracy",
    "mesh_error_metrics",
    "stripe_from_image",
    "triangulate_with_plane",
]


def __getattr__(name: str) -> Any:
    """The accuracy functions import open3d (about 1 s): loaded on first use only."""
    if name in ("MeshAccuracy", "mesh_accuracy", "mesh_error_metrics"):
        from loopmodel.mapping import accuracy

        return getattr(accuracy, name)
    raise AttributeError(f"module 'loopmodel.mapping' has no attribute {name!r}")
