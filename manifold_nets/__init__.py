"""Learning on Lie groups: the residual-on-algebra observer, its data, training and evaluation.

Generic over any :class:`groups.LieGroup`; concrete systems live in ``examples/``.
"""

__version__ = "0.1.0"
