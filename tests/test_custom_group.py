"""Groups defined outside the library pass the same one-call suite, and broken ones fail it.

* The tutorial's complete code, ``docs/examples/custom_group_so2_complex.py`` (SO(2) as unit
  complex numbers), is run as a script, so the tutorial cannot rot.
* Aff+(1), the orientation-preserving affine maps ``s -> a s + b`` of the line, subclassed here
  from :class:`~groups.MatrixLieGroup`: non-compact, non-abelian, with no rotation angle.
* Deliberately broken subclasses, one per classic bug (wrong product, a single ``torch.where``,
  a wrong Taylor branch, jaxlie's ``V ~ R`` near zero, ``acos`` of the trace, a transposed
  adjoint, no membership test, an in-place inverse, a false ``embedding_is_flat``): each must
  make ``check_group`` raise an AssertionError that names the property that catches it. This is
  what proves the suite can fail.
"""

from __future__ import annotations

import re
import runpy
from pathlib import Path

import pytest
import torch

from groups import SE2, SE3, SO3, Euclidean, LieGroup, MatrixLieGroup, Product
from groups.so3 import unskew
from groups.testing import check_group, check_membership

TUTORIAL = Path(__file__).resolve().parents[1] / "docs" / "examples" / "custom_group_so2_complex.py"


def _tutorial_namespace(run_name: str = "tutorial") -> dict:
    return runpy.run_path(str(TUTORIAL), run_name=run_name)


ComplexSO2 = _tutorial_namespace()["ComplexSO2"]


def test_tutorial_runs_and_passes_check_group(capsys) -> None:
    """Runs the tutorial file as ``python docs/examples/custom_group_so2_complex.py`` would."""
    _tutorial_namespace(run_name="__main__")
    assert "ComplexSO2() passes" in capsys.readouterr().out


def test_tutorial_page_quotes_the_tested_file_verbatim() -> None:
    """Every ```python block of docs/custom_group.md is an excerpt of the example file."""
    page = (TUTORIAL.parents[1] / "custom_group.md").read_text()
    source = TUTORIAL.read_text()
    blocks = re.findall(r"```python\n(.*?)```", page, flags=re.S)
    assert len(blocks) >= 6
    for block in blocks:
        assert block in source, f"not in {TUTORIAL.name}, but quoted by the page:\n{block}"


def test_custom_group_is_a_product_factor() -> None:
    G = Product(ComplexSO2(), Euclidean(2))
    check_group(G, max_examples=2)


# ---------------------------------------------------------------------------------- Aff+(1)


def _expm1_over_x(a: torch.Tensor) -> torch.Tensor:
    """``(e^a - 1) / a``; a series below 1e-2 (double where: finite value and gradient at 0)."""
    small = a.abs() < 1e-2
    a_safe = torch.where(small, torch.ones_like(a), a)
    exact = torch.expm1(a_safe) / a_safe
    series = 1 + a / 2 * (1 + a / 3 * (1 + a / 4 * (1 + a / 5 * (1 + a / 6))))
    return torch.where(small, series, exact)


class PositiveAffine1D(MatrixLieGroup):
    """``s -> a s + b`` with ``a > 0`` as ``[[a, b], [0, 1]]``; tangent ``(alpha, beta)``,
    ``hat = [[alpha, beta], [0, 0]]``, so ``a = e^alpha`` and ``b = beta (e^alpha - 1) / alpha``."""

    matrix_dim = 2
    tangent_dim = 2
    embedding_dim = 4
    #: exp grows like e^alpha: a magnitude of 1e3 would overflow, so the largest is 3
    tangent_magnitudes = (0.0, 1e-3, 1.0, 3.0)

    def hat(self, v: torch.Tensor) -> torch.Tensor:
        self.check_tangent(v, "hat")
        o = torch.zeros_like(v[..., 0])
        return torch.stack((v[..., 0], v[..., 1], o, o), -1).unflatten(-1, (2, 2))

    def vee(self, m: torch.Tensor) -> torch.Tensor:
        self.check_element(m, "vee")
        return m[..., 0, :]

    def exp(self, v: torch.Tensor) -> torch.Tensor:
        self.check_tangent(v, "exp")
        alpha, beta = v.unbind(-1)
        a, b = torch.exp(alpha), beta * _expm1_over_x(alpha)
        o = torch.zeros_like(a)
        return torch.stack((a, b, o, torch.ones_like(a)), -1).unflatten(-1, (2, 2))

    def log(self, x: torch.Tensor) -> torch.Tensor:
        self.check_element(x, "log")
        alpha = torch.log(x[..., 0, 0])
        return torch.stack((alpha, x[..., 0, 1] / _expm1_over_x(alpha)), -1)

    def embed(self, x: torch.Tensor) -> torch.Tensor:
        self.check_element(x, "embed")
        return x.flatten(-2)

    def unembed(self, z: torch.Tensor) -> torch.Tensor:
        self.check_shape(z, (4,), "unembed", "an embedded element")
        return z.unflatten(-1, (2, 2))

    def membership_error(self, x: torch.Tensor) -> torch.Tensor:
        """``|x_10| + |x_11 - 1| + max(-x_00, 0)``: the bottom row and the sign of ``a``."""
        self.check_element(x, "membership_error")
        return x[..., 1, 0].abs() + (x[..., 1, 1] - 1).abs() + torch.relu(-x[..., 0, 0])


def test_positive_affine_group_passes_check_group() -> None:
    # its declared tangent_magnitudes are the suite's defaults for it
    results = check_group(PositiveAffine1D())
    assert all(r.worst_ratio <= 1.0 for r in results)
    assert any(r.prop == "matrix_exp" and not r.skipped for r in results)


def test_an_exponential_group_without_declared_magnitudes_says_how_to_fix_it() -> None:
    class Undeclared(PositiveAffine1D):
        tangent_magnitudes = None

    with pytest.raises(AssertionError, match="declare the group's tangent_magnitudes"):
        check_group(Undeclared(), checks=["membership"], dtypes=(torch.float32,))


# ---------------------------------------------------------------------------------- broken groups


class WrongCompose(ComplexSO2):
    """``x · conj(y)`` instead of ``x · y``."""

    def compose(self, x, y):
        return super().compose(x, self.inverse(y))


class SingleWhereSO3(SO3):
    """``where(t > 0, sin t / t, 1)``: right values, NaN gradient at 0 (no double where)."""

    def exp(self, v):
        t2 = (v * v).sum(-1)[..., None, None]
        t = t2.sqrt()
        a = torch.where(t > 0, torch.sin(t) / t, torch.ones_like(t))
        b = torch.where(t > 0, (1 - torch.cos(t)) / t2, torch.full_like(t, 0.5))
        k = self.hat(v)
        return torch.eye(3, dtype=v.dtype) + a * k + b * (k @ k)


class WrongTaylorSO3(SO3):
    """``sin(t)/t ~ 1 - t^2/3`` (should be ``/6``) below ``t = 1e-2``."""

    def exp(self, v):
        t2 = (v * v).sum(-1)[..., None, None]
        small = t2 < 1e-4
        ts = torch.where(small, torch.ones_like(t2), t2).sqrt()
        a = torch.where(small, 1 - t2 / 3, torch.sin(ts) / ts)
        b = torch.where(small, 0.5 - t2 / 24, (1 - torch.cos(ts)) / ts**2)
        k = self.hat(v)
        return torch.eye(3, dtype=v.dtype) + a * k + b * (k @ k)


class VIsRotationSE3(SE3):
    """jaxlie's small-angle branch: translation ``R rho`` instead of ``V rho`` below 1e-2."""

    def exp(self, v):
        x = super().exp(v).clone()
        small = (v[..., 3:].norm(dim=-1) < 1e-2)[..., None]
        rotated = (x[..., :3, :3] @ v[..., :3, None])[..., 0]
        x[..., :3, 3] = torch.where(small, rotated, x[..., :3, 3])
        return x


class AcosLogSO3(SO3):
    """The textbook log: ``acos((tr R - 1) / 2)`` and the axis from ``(R - R^T) / (2 sin t)``."""

    def log(self, x):
        c = ((x.diagonal(dim1=-2, dim2=-1).sum(-1) - 1) / 2).clamp(-1, 1)
        t = torch.acos(c)
        small = t < 1e-3
        ts = torch.where(small, torch.ones_like(t), t)
        return unskew(x) * torch.where(small, 1 + t * t / 6, ts / torch.sin(ts))[..., None]


class TransposedAdjointSO3(SO3):
    def adjoint(self, x):
        return x.transpose(-1, -2)


class NoMembershipTest(ComplexSO2):
    """Says every finite tensor is on the group, so ``from_embedding`` accepts anything."""

    def membership_error(self, x):
        return (x - x).sum(-1)


class InPlaceInverse(ComplexSO2):
    """Conjugates its argument in place (and returns it)."""

    def inverse(self, x):
        x[..., 1].neg_()
        return x


class ColumnMajorSO3(SO3):
    """Embeds ``R`` column by column while SO3 declares ``embedding_is_flat``: a fine embedding,
    but not the flattened element that code trusting the declaration reads."""

    def embed(self, x):
        return super().embed(x.transpose(-1, -2))

    def unembed(self, z):
        return super().unembed(z).transpose(-1, -2)


class SwappedComposeSO3(SO3):
    """``compose(x, y) = y x``: the opposite group, itself a valid group; only the matrix form
    tells it from SO(3)."""

    def compose(self, x, y):
        return y @ x


class FlatClaimSE2(SE2):
    """Declares ``embedding_is_flat``, but embeds ``(R, t)`` in 6 numbers, not the 9 of a 3 x 3
    element."""

    embedding_is_flat = True


BROKEN = [
    # (group, the checks to run, the property that must be named, a phrase of the message)
    (SingleWhereSO3(), ["exp_log", "gradients_finite"], "gradients_finite", "non-finite"),
    (WrongTaylorSO3(), ["matrix_exp"], "matrix_exp", "matrix_exp"),
    (VIsRotationSE3(), ["matrix_exp"], "matrix_exp", "matrix_exp"),
    (AcosLogSO3(), ["log_exp"], "log_exp", "log(exp(v)) == v"),
    (TransposedAdjointSO3(), ["adjoint"], "adjoint", "exp(adjoint(x) v)"),
    (NoMembershipTest(), ["embedding"], "embedding", "off the group"),
    (InPlaceInverse(), ["membership"], "membership", "in place"),
    (ColumnMajorSO3(), ["embedding"], "embedding", "embedding_is_flat is True, but embed(x)"),
    (FlatClaimSE2(), ["embedding"], "embedding", "embedding_is_flat is True, but embedding_dim"),
    (SwappedComposeSO3(), ["matrix_compose"], "matrix_compose", "matrix(x) @ matrix(y)"),
]


@pytest.mark.parametrize(
    "group, checks, prop, phrase", BROKEN, ids=[type(b[0]).__name__ for b in BROKEN]
)
def test_broken_group_is_caught(group: LieGroup, checks: list, prop: str, phrase: str) -> None:
    with pytest.raises(AssertionError) as info:
        check_group(group, checks=checks, max_examples=3)
    msg = str(info.value)
    failed = set(re.findall(r"property '(\w+)' fails", msg))
    assert failed == {prop}, msg
    assert phrase in msg, msg


def test_wrong_compose_fails_the_one_line_call() -> None:
    """The full ``check_group`` call fails, naming property, group, dtype, batch shape, error."""
    with pytest.raises(AssertionError) as info:
        check_group(WrongCompose())
    msg = str(info.value)
    first = msg.splitlines()[1]
    assert "property 'identity' fails for WrongCompose() in torch.float32" in first
    assert "batch shape" in first and "worst error" in first and "> tolerance" in first
    failed = set(re.findall(r"property '(\w+)' fails", msg))
    assert {"identity", "inverse", "associativity"} <= failed
    assert "exp_log" not in failed  # exp and log are right; only the product is wrong


class NaNAtZeroSO3(SO3):
    """The textbook ``sin(t) / t`` without a series: ``exp`` returns NaN at angle 0 (0 / 0)."""

    def exp(self, v):
        t2 = (v * v).sum(-1)[..., None, None]
        t = t2.sqrt()
        k = self.hat(v)
        return torch.eye(3, dtype=v.dtype) + torch.sin(t) / t * k + (1 - torch.cos(t)) / t2 * (k @ k)


def test_nan_from_exp_is_reported_as_nan_not_as_in_place() -> None:
    """Message: ``property 'membership' fails for NaNAtZeroSO3() in torch.float32 on the
    adversarial grid (batch shape (72,)): exp(v) returned NaN or Inf at batch index (15,) (...)
    v[(15,)] = [0, -0, 0]``; it used to say ``identity(batch_shape) modified its input x in
    place`` (torch.equal is False for tensors holding NaN)."""
    with pytest.raises(AssertionError) as info:
        check_group(NaNAtZeroSO3(), checks=["membership"], max_examples=3)
    msg = str(info.value)
    assert "in place" not in msg, msg
    assert re.search(r"exp\(v\) returned NaN or Inf at batch index \(\d+,\)", msg), msg
    assert re.search(r"v\[\(\d+,\)\] = \[-?0, -?0, -?0\]", msg), msg
    # drawn by hypothesis (no grid): the angle-0 examples are caught the same way
    with pytest.raises(AssertionError, match=r"exp\(v\) returned NaN or Inf"):
        check_membership(NaNAtZeroSO3(), batch_shape=(4,), max_examples=20, grid=False)

