"""An AHRS on SO(3) x R^3: attitude and gyro bias from two body-frame directions and a gyro.

``system`` (the model), ``motion`` (smooth random rate profiles, also used by the planar
vehicle), ``triad`` (the raw baseline), ``filters`` (the error-state EKF) and ``compare`` (the
learned observer next to the classical estimators, for any system). docs/examples_systems.md.
"""

from .system import Attitude

__all__ = ["Attitude"]
