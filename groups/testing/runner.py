"""Running the axioms: one public ``check_*`` per property, and :func:`check_group` over them all.

Every ``check_*(group, dtype, batch_shape, **options)`` (options: :func:`run_property`) runs
its property in one ``dtype``: first (if ``grid``) once on the deterministic adversarial batch of
``GRID_SIZE`` elements (every adversarial angle with every magnitude), then on ``max_examples``
hypothesis examples of shape ``batch_shape`` (derandomized by default, so CI is reproducible). It
raises AssertionError naming the property, group, dtype, batch shape, the worst error and the
input where it occurred, and returns a :class:`~groups.testing.comparison.CheckResult`.
:func:`check_group` runs every check for each dtype and batch shape and reports every failure.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Sequence

import hypothesis
import torch
from hypothesis import strategies as st

from ..base import LieGroup
from .comparison import Case, CheckResult
from .properties import DETERMINISTIC, PROPERTIES
from .strategies import BATCH_SHAPES, GRID_SIZE, MAGNITUDES

__all__ = [
    "DEFAULT_MAX_EXAMPLES",
    "run_property",
    "CHECKS",
    "check_group",
    "check_membership",
    "check_identity",
    "check_inverse",
    "check_associativity",
    "check_exp_log",
    "check_log_exp",
    "check_matrix_exp",
    "check_adjoint",
    "check_embedding",
    "check_rplus_rminus",
    "check_gradients_finite",
    "check_gradcheck",
    "check_batched_vs_looped",
    "check_broadcasting",
]

#: Examples per property, dtype and batch shape drawn by hypothesis in ``check_group``.
DEFAULT_MAX_EXAMPLES = 6


def _settings(max_examples: int, derandomize: bool) -> hypothesis.settings:
    return hypothesis.settings(
        max_examples=max_examples,
        deadline=None,
        derandomize=derandomize,
        database=None,
        print_blob=False,
        # no shrinking: the message already shows the failing element, and shrinking a
        # failure of several properties costs tens of seconds
        phases=(hypothesis.Phase.explicit, hypothesis.Phase.reuse, hypothesis.Phase.generate),
        suppress_health_check=[
            hypothesis.HealthCheck.too_slow,
            hypothesis.HealthCheck.data_too_large,
            hypothesis.HealthCheck.large_base_example,
        ],
    )


def run_property(
    prop: str,
    group: LieGroup,
    *,
    dtype: torch.dtype = torch.float64,
    batch_shape: Sequence[int] = (),
    max_examples: int = DEFAULT_MAX_EXAMPLES,
    magnitudes: Sequence[float] | None = None,
    derandomize: bool = True,
    grid: bool = True,
    device: torch.device | str = "cpu",
) -> CheckResult:
    """Runs property ``prop`` (a name in :data:`~groups.testing.properties.PROPERTIES`) as the
    module docstring describes; what every ``check_*`` calls, with its ``**options``:
    ``max_examples`` (hypothesis examples), ``magnitudes`` (tangent-vector scales; default the
    group's ``tangent_magnitudes`` when it declares them, else :data:`MAGNITUDES`),
    ``derandomize`` (reproducible examples), ``grid`` (the adversarial batch first) and
    ``device`` (where the inputs are put: ``"cuda"`` checks the group's kernels on a GPU, and
    that every output stays on the inputs' device)."""
    if not isinstance(group, LieGroup):
        raise TypeError(f"check_{prop} needs a LieGroup instance, got {group!r}.")
    bs = tuple(int(b) for b in batch_shape)
    mags = tuple(default_magnitudes(group) if magnitudes is None else magnitudes)
    result = CheckResult(prop=prop, group=repr(group), dtype=dtype, batch_shape=bs)

    def once(case: Case, data) -> None:
        try:
            PROPERTIES[prop](case, data)
        except AssertionError:
            raise
        except Exception as err:  # a crash inside the group is a failure of this property
            raise AssertionError(f"{case.header()}: raised {type(err).__name__}: {err}") from err

    def new_case(batch: tuple[int, ...], on_grid: bool = False) -> Case:
        return Case(group, dtype=dtype, batch_shape=batch, magnitudes=mags, result=result,
                    grid=on_grid, device=device)

    if prop in DETERMINISTIC:
        once(new_case(bs), None)
        return result
    if grid:
        once(new_case((GRID_SIZE,), on_grid=True), None)
    if max_examples > 0:
        case = new_case(bs)
        # With derandomize, hypothesis seeds its examples from the source line of the test
        # function: the next line is kept character for character, so the examples are the ones
        # this suite has always drawn.
        run = _settings(
            max_examples, derandomize
        )(hypothesis.given(st.data())(lambda data: once(case, data)))
        run()
    return result


# ---------------------------------------------------------------------------------- the checks
# One function per property, each stating its axiom. Arguments and behaviour: the module docstring.


def check_membership(
    group: LieGroup, dtype: torch.dtype = torch.float64, batch_shape: Sequence[int] = (), **options
) -> CheckResult:
    """Outputs of identity, compose, inverse, exp, rplus, between and random are on the group
    (within ``TOLERANCES[dtype].member``), every output has its documented shape and dtype, and
    no operation modifies its inputs."""
    return run_property("membership", group, dtype=dtype, batch_shape=batch_shape, **options)


def check_identity(
    group: LieGroup, dtype: torch.dtype = torch.float64, batch_shape: Sequence[int] = (), **options
) -> CheckResult:
    """``e x = x e = x``, ``e^-1 = e``, ``exp(0) = e``, ``log(e) = 0``, ``rminus(x, x) = 0``."""
    return run_property("identity", group, dtype=dtype, batch_shape=batch_shape, **options)


def check_inverse(
    group: LieGroup, dtype: torch.dtype = torch.float64, batch_shape: Sequence[int] = (), **options
) -> CheckResult:
    """``x x^-1 = x^-1 x = e``, ``(x^-1)^-1 = x``, ``(x y)^-1 = y^-1 x^-1``."""
    return run_property("inverse", group, dtype=dtype, batch_shape=batch_shape, **options)


def check_associativity(
    group: LieGroup, dtype: torch.dtype = torch.float64, batch_shape: Sequence[int] = (), **options
) -> CheckResult:
    """``(x y) z = x (y z)``."""
    return run_property("associativity", group, dtype=dtype, batch_shape=batch_shape, **options)


def check_exp_log(
    group: LieGroup, dtype: torch.dtype = torch.float64, batch_shape: Sequence[int] = (), **options
) -> CheckResult:
    """``exp(log(x)) = x`` for every element, angle pi included."""
    return run_property("exp_log", group, dtype=dtype, batch_shape=batch_shape, **options)


def check_log_exp(
    group: LieGroup, dtype: torch.dtype = torch.float64, batch_shape: Sequence[int] = (), **options
) -> CheckResult:
    """``log(exp(v)) = v`` where every angle is below ``pi - pi_margin`` (tolerance grown by
    ``near_pi * eps / (pi - angle)``), and ``exp(log(exp(v))) = exp(v)`` everywhere."""
    return run_property("log_exp", group, dtype=dtype, batch_shape=batch_shape, **options)


def check_matrix_exp(
    group: LieGroup, dtype: torch.dtype = torch.float64, batch_shape: Sequence[int] = (), **options
) -> CheckResult:
    """For a :class:`~groups.MatrixLieGroup`: ``exp(v)`` (in ``dtype``) against
    ``torch.linalg.matrix_exp(hat(v))`` in float64, and ``vee(hat(v)) = v``. Skipped otherwise."""
    return run_property("matrix_exp", group, dtype=dtype, batch_shape=batch_shape, **options)


def check_matrix_compose(
    group: LieGroup, dtype: torch.dtype = torch.float64, batch_shape: Sequence[int] = (), **options
) -> CheckResult:
    """``compose(x, y)`` against the matrix product, for a :class:`~groups.MatrixLieGroup` or a
    group whose embedding is a matrix (``embedding_is_matrix``). Skipped otherwise: then the
    suite cannot tell ``compose`` from its opposite."""
    return run_property("matrix_compose", group, dtype=dtype, batch_shape=batch_shape, **options)


def check_adjoint(
    group: LieGroup, dtype: torch.dtype = torch.float64, batch_shape: Sequence[int] = (), **options
) -> CheckResult:
    """``x exp(v) x^-1 = exp(Ad_x v)``, ``Ad_{xy} = Ad_x Ad_y`` and ``Ad_x Ad_{x^-1} = I``."""
    return run_property("adjoint", group, dtype=dtype, batch_shape=batch_shape, **options)


def check_embedding(
    group: LieGroup, dtype: torch.dtype = torch.float64, batch_shape: Sequence[int] = (), **options
) -> CheckResult:
    """``unembed(embed(x)) = x``, ``from_embedding(embed(x)) = x``, and ``from_embedding`` raises
    GroupMembershipError for NaN and (if ``embedding_dim > tangent_dim``) off the group. If the
    group declares ``embedding_is_flat``, ``embedding_dim`` is the number of entries of an
    element and ``embed(x)`` is ``x`` flattened row-major, exactly."""
    return run_property("embedding", group, dtype=dtype, batch_shape=batch_shape, **options)


def check_rplus_rminus(
    group: LieGroup, dtype: torch.dtype = torch.float64, batch_shape: Sequence[int] = (), **options
) -> CheckResult:
    """``rplus = compose(x, exp(v))``, ``between``, ``rplus(x, rminus(y, x)) = y``,
    ``rminus(rplus(x, v), x) = v`` inside the injectivity radius, and ``distance``."""
    return run_property("rplus_rminus", group, dtype=dtype, batch_shape=batch_shape, **options)


def check_mean(
    group: LieGroup, dtype: torch.dtype = torch.float64, batch_shape: Sequence[int] = (), **options
) -> CheckResult:
    """``mean`` is the barycentre of elements near each other, idempotent and equivariant."""
    return run_property("mean", group, dtype=dtype, batch_shape=batch_shape, **options)


def check_gradients_finite(
    group: LieGroup, dtype: torch.dtype = torch.float64, batch_shape: Sequence[int] = (), **options
) -> CheckResult:
    """No NaN/Inf in the gradients of ``sum(exp(v))``, ``sum(log(exp(v)))`` and
    ``sum(embed(rplus(x, v)))``, at drawn points and at angles of exactly 0 and pi."""
    return run_property("gradients_finite", group, dtype=dtype, batch_shape=batch_shape, **options)


def check_gradcheck(
    group: LieGroup, dtype: torch.dtype = torch.float64, batch_shape: Sequence[int] = (), **options
) -> CheckResult:
    """``torch.autograd.gradcheck`` of ``exp``, ``log(exp(v))`` and ``embed(rplus(x, v))`` at
    generic points in float64 (skipped for other dtypes). Draws nothing: it runs once, at fixed
    points, whatever ``max_examples`` and ``grid`` say."""
    return run_property("gradcheck", group, dtype=dtype, batch_shape=batch_shape, **options)


def check_batched_vs_looped(
    group: LieGroup, dtype: torch.dtype = torch.float64, batch_shape: Sequence[int] = (), **options
) -> CheckResult:
    """Batched compose, inverse, exp, log, rplus, rminus, embed and adjoint equal the
    per-element results."""
    return run_property("batched_vs_looped", group, dtype=dtype, batch_shape=batch_shape, **options)


def check_broadcasting(
    group: LieGroup, dtype: torch.dtype = torch.float64, batch_shape: Sequence[int] = (), **options
) -> CheckResult:
    """compose and rplus broadcast batch shapes (3, 1) with (1, 2), and () with ``batch_shape``."""
    return run_property("broadcasting", group, dtype=dtype, batch_shape=batch_shape, **options)


#: Every check of :func:`check_group`, by property name, in the order it runs them.
CHECKS: dict[str, Callable[..., CheckResult]] = {
    "membership": check_membership,
    "identity": check_identity,
    "inverse": check_inverse,
    "associativity": check_associativity,
    "exp_log": check_exp_log,
    "log_exp": check_log_exp,
    "matrix_exp": check_matrix_exp,
    "matrix_compose": check_matrix_compose,
    "adjoint": check_adjoint,
    "embedding": check_embedding,
    "rplus_rminus": check_rplus_rminus,
    "mean": check_mean,
    "gradients_finite": check_gradients_finite,
    "gradcheck": check_gradcheck,
    "batched_vs_looped": check_batched_vs_looped,
    "broadcasting": check_broadcasting,
}
assert list(CHECKS) == list(PROPERTIES), "one check_* per property, in the same order"


def default_magnitudes(group: LieGroup) -> tuple[float, ...]:
    """The tangent scales the suite draws at: the group's ``tangent_magnitudes`` when it
    declares them (a group whose ``exp`` grows exponentially), else :data:`MAGNITUDES`."""
    declared = getattr(group, "tangent_magnitudes", None)
    return tuple(MAGNITUDES if not declared else declared)


def check_group(
    group: LieGroup,
    dtypes: Iterable[torch.dtype] = (torch.float32, torch.float64),
    batch_shapes: Iterable[Sequence[int]] = BATCH_SHAPES,
    max_examples: int = DEFAULT_MAX_EXAMPLES,
    magnitudes: Sequence[float] | None = None,
    checks: Iterable[str] | None = None,
    derandomize: bool = True,
    device: torch.device | str = "cpu",
) -> list[CheckResult]:
    """Runs every axiom check on ``group`` for each dtype and batch shape.

    Args:
        group: the group to check, e.g. ``MyGroup()``.
        dtypes: floating dtypes to run in (tolerances from :data:`TOLERANCES`).
        batch_shapes: batch shapes of the drawn elements and tangent vectors. The adversarial
            grid runs once per dtype, with the first of them.
        max_examples: hypothesis examples per property, dtype and batch shape.
        magnitudes: scales of the non-angle tangent coordinates (default: the group's
            ``tangent_magnitudes`` when it declares them, else :data:`MAGNITUDES`); a group
            whose ``exp`` grows exponentially (a scale, e^lambda) declares smaller ones.
        checks: names from :data:`CHECKS` to run (default: all).
        derandomize: fixed hypothesis examples (reproducible); False explores new ones each run.
        device: where the inputs are put (``"cuda"``: the group on a GPU); every output must
            stay there.

    Returns:
        One :class:`CheckResult` per property, dtype and batch shape (worst errors seen).

    Raises:
        AssertionError: listing every failing property with its group, dtype, batch shape, the
            worst error and the input where it occurred.
    """
    names = list(CHECKS) if checks is None else list(checks)
    unknown = [n for n in names if n not in CHECKS]
    if unknown:
        raise ValueError(f"unknown checks {unknown}; choose from {list(CHECKS)}.")
    results, failures = [], {}
    for dtype in dtypes:
        for i, bs in enumerate(batch_shapes):
            for name in names:
                if (name, dtype) in failures:  # one failure per property and dtype is enough
                    continue
                try:
                    result = CHECKS[name](
                        group, dtype=dtype, batch_shape=bs, max_examples=max_examples,
                        magnitudes=magnitudes, derandomize=derandomize, grid=i == 0,
                        device=device,
                    )  # fmt: skip
                except AssertionError as err:
                    failures[name, dtype] = str(err)
                else:
                    results.append(result)
    if failures:
        raise AssertionError(
            f"check_group({group!r}): {len(failures)} check(s) failed.\n"
            + "\n".join(f"- {f}" for f in failures.values())
        )
    return results
