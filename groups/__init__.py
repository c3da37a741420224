"""Lie groups as math on batched torch tensors: no nn.Module, no training.

Shipped groups: :class:`SO2`, :class:`SO3`, :class:`SE2`, :class:`SE3`, :class:`SE23` (extended
poses), :class:`Euclidean` (R^n) and :class:`Product` of any of them. Define your own by
subclassing :class:`LieGroup` (or :class:`MatrixLieGroup`) and check it with
``groups.testing.check_group``. Every group is also a product of named factors (the factors
view: ``factor_names``, ``index``, ``tangent_slice``, ...; a non-product group is one factor "x").
"""

from .base import GroupMembershipError, LieGroup, MatrixLieGroup
from .euclidean import Euclidean
from .product import Product
from .se2 import SE2
from .se3 import SE3
from .se23 import SE23
from .so2 import SO2
from .so3 import SO3

__all__ = [
    "LieGroup",
    "MatrixLieGroup",
    "GroupMembershipError",
    "Euclidean",
    "Product",
    "SO2",
    "SO3",
    "SE2",
    "SE3",
    "SE23",
]
