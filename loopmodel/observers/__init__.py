"""Lyapunov-based adaptive estimation of Euclidean feature positions from one moving camera.

Seed 003, Chitrakaran & Dawson.
"""

from loopmodel.observers.depth_observer import DepthObserver, ObserverConfig, ViewMeasurement
from loopmodel.observers.kinematics import feature_jacobian, l_omega

__all__ = ["DepthObserver", "ObserverConfig", "ViewMeasurement", "feature_jacobian", "l_omega"]
