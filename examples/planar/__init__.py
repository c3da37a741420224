"""A planar vehicle on SE(2) x R x R (or SO(2) x R^2 x R x R): pose and odometry biases from
GPS-like fixes and biased odometry.

``system`` (the model), ``filters`` (the error-state EKF) and ``compare`` (the learned observer
next to the EKF, dead reckoning and the raw fixes). docs/examples_systems.md.
"""

from .system import Planar

__all__ = ["Planar"]
