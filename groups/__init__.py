"""Lie groups as math on batched torch tensors: no nn.Module, no training.

Shipped groups: :class:`SO2`, :class:`SO3`, :class:`SE2`, :class:`SE3`, :class:`SE23` (extended
poses), :class:`Euclidean` (R^n) and :class:`Product` of any of them. Define your own by
subclassing :class:`LieGroup` (or :class:`MatrixLieGroup`) and check it with
``groups.testing.check_group``.
"""

from .base import GroupMembershipError, LieGroup, MatrixLieGroup
from .euclidean import Euclidean
from .product import Product
from .so3 import SO3

__all__ = [
    "LieGroup",
    "MatrixLieGroup",
    "GroupMembershipError",
    "Euclidean",
    "Product",
    "SO3",
]
