"""Readers and writers: sequences (MCAP, EuRoC, KITTI), trajectories, results folder."""

from loopmodel.io.sequence import Sequence, open_sequence
from loopmodel.io.trajectory_io import read_trajectory, write_trajectory

__all__ = ["Sequence", "open_sequence", "read_trajectory", "write_trajectory"]
