"""The paper's rigid body on SO(3) x R^3 x R^3 x R^3: exact kinematics and its measurement model,
and the same body measured by sensors that break that model (the mismatch benchmark)."""

from .mismatch import MismatchedRigidBody
from .system import RigidBody

__all__ = ["MismatchedRigidBody", "RigidBody"]
