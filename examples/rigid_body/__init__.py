"""The paper's rigid body on SO(3) x R^3 x R^3 x R^3: exact kinematics and its measurement model."""

from .system import RigidBody

__all__ = ["RigidBody"]
