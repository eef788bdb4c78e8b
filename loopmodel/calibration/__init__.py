"""Calibration of real rigs: stereo cameras from chessboards, the laser light plane."""
