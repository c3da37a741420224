"""The public axiom suite for any :class:`~groups.LieGroup`: ``check_group(MyGroup())``.

::

    from groups.testing import check_group
    check_group(MyGroup())   # raises AssertionError naming the property, dtype, batch shape, error

It checks, in float32 and float64 and over several batch shapes, every law a group must keep
(membership, identity, inverse, associativity, ``exp``/``log``, ``exp`` against ``matrix_exp``,
the adjoint, the embedding, ``rplus``/``rminus``, the barycentre ``mean``, finite gradients at
angles 0 and pi, ``gradcheck``, batched equals looped, broadcasting) on adversarial inputs. Four layers, each a
module, each importing only the ones before it:

* :mod:`~groups.testing.strategies`: the inputs (hypothesis strategies, the adversarial angles
  and magnitudes, the deterministic grid);
* :mod:`~groups.testing.comparison`: tolerances per dtype, :class:`CheckResult`, and the case
  that compares and formats a failure;
* :mod:`~groups.testing.properties`: the axioms, one function each;
* :mod:`~groups.testing.runner`: one public ``check_*`` per axiom, and :func:`check_group`.

hypothesis comes with the ``testing`` extra (``pip install 'manifold_nets[testing]'``). It is
imported here and only here: ``import groups`` never imports this package, so the library itself
runs without it.
"""

try:
    import hypothesis  # noqa: F401 - only to fail early with the fix
except ImportError as _err:  # pragma: no cover - depends on the environment
    raise ImportError(
        "groups.testing needs hypothesis, which the `testing` extra brings: "
        "`pip install 'manifold_nets[testing]'` (from a checkout: `pip install -e '.[testing]'`)."
    ) from _err

from .comparison import TOLERANCES, CheckResult, Tolerances
from .runner import (
    CHECKS,
    DEFAULT_MAX_EXAMPLES,
    check_adjoint,
    check_associativity,
    check_batched_vs_looped,
    check_broadcasting,
    check_embedding,
    check_exp_log,
    check_gradcheck,
    check_gradients_finite,
    check_group,
    check_identity,
    check_inverse,
    check_log_exp,
    check_matrix_exp,
    check_matrix_compose,
    check_membership,
    check_rplus_rminus,
    check_mean,
)
from .strategies import (
    ADVERSARIAL_ANGLES,
    BATCH_SHAPES,
    GRID_SIZE,
    MAGNITUDES,
    batch_shapes,
    elements,
    tangent_vectors,
)

__all__ = [
    "ADVERSARIAL_ANGLES",
    "MAGNITUDES",
    "BATCH_SHAPES",
    "DEFAULT_MAX_EXAMPLES",
    "GRID_SIZE",
    "TOLERANCES",
    "Tolerances",
    "CheckResult",
    "batch_shapes",
    "tangent_vectors",
    "elements",
    "check_group",
    "CHECKS",
    "check_membership",
    "check_identity",
    "check_inverse",
    "check_associativity",
    "check_exp_log",
    "check_log_exp",
    "check_matrix_exp",
    "check_matrix_compose",
    "check_adjoint",
    "check_embedding",
    "check_rplus_rminus",
    "check_mean",
    "check_gradients_finite",
    "check_gradcheck",
    "check_batched_vs_looped",
    "check_broadcasting",
]
