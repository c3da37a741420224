"""The abstract Lie group interface: the minimum a subclass writes, and everything derived from it.

A group is a small, stateless object (``SO3()``, ``Euclidean(3)``, ``Product(SO3(), Euclidean(3))``)
whose methods take and return plain ``torch.Tensor`` s. An element has the shape
``(*batch, *element_shape)``, a tangent vector ``(*batch, tangent_dim)`` and an embedded element
``(*batch, embedding_dim)``. Batch dimensions broadcast like torch's.

The minimum a subclass writes (manif's "minimum API"):

* ``element_shape``, ``tangent_dim``, ``embedding_dim``
* ``identity``, ``compose``, ``inverse``, ``exp``, ``log``
* ``embed`` (the paper's map ``pi`` into ``R^n``) and ``unembed`` (its inverse on the image)
* ``membership_error`` (how far a tensor is from the group; 0 on it)

Derived once here, overridable for speed: ``rplus``, ``rminus``, ``between``, ``adjoint``,
``distance``, ``random``, ``check_member``, ``from_embedding``. ``element_difference`` (``x - y``)
says when two tensors are the same element; a double cover (unit quaternions) overrides it.

Input validation for authors of a group or a system: ``check_element``, ``check_tangent`` and
``check_shape`` raise ``TypeError`` / ``ValueError`` naming the expected shape and dtype (float32
or float64, the only supported dtypes); ``check_pair`` also asks two elements for one dtype and
broadcastable batch shapes.

The factors view: every group is a product of named factors. A :class:`~groups.Product` has its
own; any other group is its single factor named ``"x"``. ``factors``, ``factor_names``,
``index``, ``factor``, ``element_slice``, ``tangent_slice`` and ``embedding_slice`` answer
"which factor, and where does it sit" in a flattened element, a tangent vector and an
embedding, so code that works factor by factor (an observer's per-factor update, per-factor
errors) never asks whether a group is a product. ``embedding_is_flat`` says whether ``embed``
is the flattened element (SO(2), SO(3), R^n and products of them; not SE(3)): declared by the
group, checked by ``groups.testing``.

Perturbations are on the **right**, as in manif and Theseus: ``rplus(x, v) = x · exp(v)`` is the
observer's update, ``rminus(y, x) = log(x^-1 · y)`` so that ``rplus(x, rminus(y, x)) == y``.
"""

from __future__ import annotations

import abc
import math
from collections.abc import Sequence

import torch

__all__ = ["LieGroup", "MatrixLieGroup", "GroupMembershipError"]

BatchShape = Sequence[int] | torch.Size


class GroupMembershipError(ValueError):
    """A tensor that was required to be a group element is not one (or holds NaN/Inf)."""


#: The dtypes the groups support: float16/bfloat16 have no tolerances, thresholds or tests.
_DTYPES = (torch.float32, torch.float64)


def _default_atol(dtype: torch.dtype) -> float:
    # float32 chains of many updates drift to ~1e-5; float64 stays near 1e-14.
    return 1e-9 if dtype == torch.float64 else 1e-4


class LieGroup(abc.ABC):
    """Abstract base of every group. See the module docstring for the contract."""

    #: Shape of one element, e.g. ``(3, 3)`` for SO(3) as rotation matrices.
    element_shape: tuple[int, ...]
    #: Dimension of the Lie algebra (the tangent space at the identity).
    tangent_dim: int
    #: Dimension ``n`` of the Euclidean space the group is embedded in by ``embed``.
    embedding_dim: int
    #: Slices of the tangent vector whose norm is a rotation angle (used by ``groups.testing``
    #: to place adversarial angles such as 0 and pi, and to know where ``log`` is injective).
    #: Empty for vector spaces.
    angle_slices: tuple[slice, ...] = ()
    #: Whether ``embed(x)`` is ``x`` flattened (row-major), so ``embedding_dim`` equals the number
    #: of entries of an element. Declared by the group (False unless it says so) and checked by
    #: ``groups.testing.check_embedding``; the observer then feeds the flat state to its network
    #: without embedding it factor by factor.
    embedding_is_flat: bool = False
    #: Whether ``embed(x)`` is a square matrix (flattened row-major) that represents ``x``:
    #: ``compose`` is then its matrix product, which ``groups.testing`` checks (a group of your
    #: own that is not a :class:`MatrixLieGroup` but embeds as one should say so: without a
    #: matrix form the suite cannot tell ``compose`` from its opposite, itself a valid group).
    embedding_is_matrix: bool = False
    #: The scales of the non-angle tangent coordinates at which ``exp`` is meaningful, for the
    #: axiom suite (``groups.testing``) to draw at; ``None``: its defaults, (0, 1e-3, 1, 1e3).
    #: A group whose ``exp`` grows exponentially (a scale direction, ``e^lambda``) declares
    #: smaller ones, e.g. ``(0.0, 1e-3, 0.1, 3.0)``.
    tangent_magnitudes: tuple[float, ...] | None = None

    # ------------------------------------------------------------------ minimum API

    @abc.abstractmethod
    def identity(
        self,
        batch_shape: BatchShape = (),
        dtype: torch.dtype = torch.float32,
        device: torch.device | str | None = None,
    ) -> torch.Tensor:
        """The identity element, shape ``(*batch_shape, *element_shape)``.

        Call ``self.check_dtype(dtype, "identity")`` first (float32/float64 only)."""

    @abc.abstractmethod
    def compose(self, x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
        """The group product ``x · y``; batch dimensions broadcast."""

    @abc.abstractmethod
    def inverse(self, x: torch.Tensor) -> torch.Tensor:
        """The inverse ``x^-1``."""

    @abc.abstractmethod
    def exp(self, v: torch.Tensor) -> torch.Tensor:
        """The exponential map, ``(*batch, tangent_dim) -> (*batch, *element_shape)``."""

    @abc.abstractmethod
    def log(self, x: torch.Tensor) -> torch.Tensor:
        """The logarithm (inverse of ``exp`` inside its injectivity radius)."""

    @abc.abstractmethod
    def embed(self, x: torch.Tensor) -> torch.Tensor:
        """The embedding ``pi``, ``(*batch, *element_shape) -> (*batch, embedding_dim)``."""

    @abc.abstractmethod
    def unembed(self, z: torch.Tensor) -> torch.Tensor:
        """The inverse of ``embed`` on its image, without a membership check.

        Use :meth:`from_embedding` for data from outside: it checks membership.
        """

    @abc.abstractmethod
    def membership_error(self, x: torch.Tensor) -> torch.Tensor:
        """How far ``x`` is from the group, shape ``(*batch,)``; 0 on the group, NaN for NaN input."""

    # ------------------------------------------------------------------ derived API

    def rplus(self, x: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
        """Right perturbation ``x · exp(v)`` (the observer's update)."""
        return self.compose(x, self.exp(v))

    def rminus(self, y: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
        """``log(x^-1 · y)``, the tangent vector ``v`` with ``rplus(x, v) == y``."""
        return self.log(self.between(x, y))

    def between(self, x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
        """``x^-1 · y``, the relative element from ``x`` to ``y``."""
        self.check_pair(x, y, "between")
        return self.compose(self.inverse(x), y)

    def distance(self, x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
        """The geodesic-like distance ``||rminus(y, x)||``, shape ``(*batch,)``."""
        return torch.linalg.vector_norm(self.rminus(y, x), dim=-1)

    def mean(self, x: torch.Tensor, dim: int = 0, iterations: int = 4) -> torch.Tensor:
        """The barycentre of the elements along the batch dimension ``dim`` (removed from the
        result): the ``m`` with ``sum_i log(m^-1 · x_i) = 0``, by ``iterations`` of
        ``m <- m · exp(mean_i log(m^-1 · x_i))`` from the first element.

        Equivariant, ``mean(g · x_i) == g · mean(x_i)``; on a vector space the arithmetic mean
        (after one iteration); on rotations the geodesic (Karcher) mean, unique when the
        elements lie in a ball of radius below pi/2. Each iteration shrinks the error by a
        factor of the order of the spread squared (radians): the default four reach float64's
        precision for elements within 0.1 rad (6 degrees) of each other, such as an ensemble's
        estimates; wider spreads need more. The count is fixed, not a test on the data: the same
        operations run every call (traceable and exportable).
        """
        self.check_element(x, "mean")
        batch = x.dim() - len(self.element_shape)
        if isinstance(iterations, bool) or not isinstance(iterations, int) or iterations < 1:
            raise ValueError(f"{self.name}.mean: iterations must be an int >= 1, got {iterations!r}.")
        if isinstance(dim, bool) or not isinstance(dim, int) or not -batch <= dim < batch:
            raise ValueError(
                f"{self.name}.mean: dim must name one of the {batch} batch dimensions of x "
                f"(shape {tuple(x.shape)}), got {dim!r}; stack the elements along one first."
            )
        dim %= batch
        if x.shape[dim] == 0:
            raise ValueError(f"{self.name}.mean: no elements along dim {dim} (shape {tuple(x.shape)}).")
        m = x.select(dim, 0)
        for _ in range(iterations):
            m = self.rplus(m, self.rminus(x, m.unsqueeze(dim)).mean(dim))
        return m

    def element_difference(self, x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
        """How ``x`` differs from ``y`` entry by entry, shape ``(*batch, *element_shape)``: small
        exactly when ``x`` and ``y`` are close as group elements. ``groups.testing`` compares
        every pair of elements through it (the error is its largest entry).

        The default is ``x - y``: one tensor per element. A group whose tensors represent each
        element more than once overrides it; unit quaternions, a double cover where ``q`` and
        ``-q`` are one rotation, return ``x - s y`` with ``s = +-1`` the sign of ``<x, y>``.
        """
        return x - y

    def adjoint(self, x: torch.Tensor) -> torch.Tensor:
        """The adjoint matrix ``Ad_x``, ``(*batch, tangent_dim, tangent_dim)``.

        Defined by ``x · exp(v) · x^-1 = exp(Ad_x v)``. The generic version differentiates
        ``v -> log(x · exp(v) · x^-1)`` at ``v = 0`` with forward-mode autograd, one column per
        tangent direction; subclasses override it with a closed form.
        """
        self.check_element(x, "adjoint")
        batch = x.shape[: x.dim() - len(self.element_shape)]
        if not batch:  # 0-dim arithmetic can promote dtypes under forward AD: a batch of one
            return LieGroup.adjoint(self, x.unsqueeze(0))[0]
        x_inv = self.inverse(x)

        def conj(v: torch.Tensor) -> torch.Tensor:
            return self.log(self.compose(self.compose(x, self.exp(v)), x_inv))

        zero = torch.zeros(*batch, self.tangent_dim, dtype=x.dtype, device=x.device)
        eye = torch.eye(self.tangent_dim, dtype=x.dtype, device=x.device)
        cols = [
            torch.func.jvp(conj, (zero,), (eye[i].expand_as(zero),))[1]
            for i in range(self.tangent_dim)
        ]
        # a subclass's scalar arithmetic on 0-dim tensors may promote under forward AD: the
        # matrix is in the element's dtype whatever the subclass computed in
        return torch.stack(cols, dim=-1).to(x.dtype)

    def random(
        self,
        batch_shape: BatchShape = (),
        generator: torch.Generator | None = None,
        dtype: torch.dtype = torch.float32,
        device: torch.device | str | None = None,
    ) -> torch.Tensor:
        """A random element: ``exp`` of a standard normal tangent vector (SO(n) overrides with Haar)."""
        self.check_dtype(dtype, "random")
        v = torch.randn(
            *batch_shape, self.tangent_dim, generator=generator, dtype=dtype, device=device
        )
        return self.exp(v)

    def check_member(self, x: torch.Tensor, atol: float | None = None) -> torch.Tensor:
        """Raises :class:`GroupMembershipError` unless every element of ``x`` is on the group.

        ``atol`` defaults to 1e-4 for float32 and 1e-9 for float64; another value must be a
        finite number >= 0 (else ``ValueError``). Returns ``x`` unchanged.
        """
        self.check_element(x, "check_member")
        if not bool(torch.isfinite(x).all()):
            raise GroupMembershipError(
                f"{self.name}: the element holds NaN or Inf; a group element must be finite."
            )
        if atol is not None and (
            isinstance(atol, bool)
            or not isinstance(atol, (int, float))
            or not math.isfinite(atol)
            or atol < 0
        ):
            raise ValueError(
                f"{self.name}.check_member: atol must be a finite number >= 0, got {atol!r}; "
                f"pass e.g. atol=1e-5, or None for the default (1e-4 in float32, 1e-9 in "
                f"float64)."
            )
        tol = _default_atol(x.dtype) if atol is None else float(atol)
        err = self.membership_error(x)
        worst = float(err.max()) if err.numel() else 0.0
        if not worst <= tol:
            raise GroupMembershipError(
                f"{self.name}: {int((err > tol).sum())} of {err.numel()} element(s) are not on the "
                f"group (largest membership error {worst:.3g} > atol {tol:.3g})."
                f"{self._membership_detail(x, err)} Pass group "
                f"elements (for rotations: orthonormal with det +1), or raise atol if the "
                f"data were rounded."
            )
        return x

    def _membership_detail(self, x: torch.Tensor, err: torch.Tensor) -> str:
        """Extra words for :meth:`check_member`'s message about the worst element (" ..." or "")."""
        return ""

    def from_embedding(self, z: torch.Tensor, atol: float | None = None) -> torch.Tensor:
        """The inverse of ``embed``, checked: raises :class:`GroupMembershipError` off the group."""
        self.check_shape(z, (self.embedding_dim,), "from_embedding", "an embedded element")
        return self.check_member(self.unembed(z), atol=atol)

    # ------------------------------------------------------------------ the factors view

    @property
    def factors(self) -> tuple[LieGroup, ...]:
        """The factor groups: a :class:`~groups.Product`'s, or ``(self,)``."""
        return (self,)

    @property
    def factor_names(self) -> tuple[str, ...]:
        """One name per factor: a Product's ``names`` (``factor0``, ... when unnamed), or ``("x",)``."""
        return ("x",)

    def index(self, key: int | str) -> int:
        """The position of a factor given by name or index (negative counts from the end).

        Raises ``KeyError`` for an unknown name, ``IndexError`` for an index out of range; both
        name the factors there are.
        """
        names = self.factor_names
        if isinstance(key, str):
            if key not in names:
                raise KeyError(f"{self!r} has no factor named {key!r}; its factors: {list(names)}.")
            return names.index(key)
        if isinstance(key, bool) or not isinstance(key, int) or not -len(names) <= key < len(names):
            raise IndexError(
                f"{self!r} has {len(names)} factor{'s' if len(names) != 1 else ''} {list(names)}, "
                f"no factor {key!r}."
            )
        return key % len(names)

    def factor(self, key: int | str) -> LieGroup:
        """A factor group by name or index."""
        return self.factors[self.index(key)]

    def _factor_offsets(self, sizes: Sequence[int], key: int | str) -> slice:
        i = self.index(key)
        start = sum(sizes[:i])
        return slice(start, start + sizes[i])

    def element_slice(self, key: int | str) -> slice:
        """Where factor ``key``'s flattened element sits in the flattened element."""
        return self._factor_offsets([math.prod(f.element_shape) for f in self.factors], key)

    def tangent_slice(self, key: int | str) -> slice:
        """Where factor ``key`` sits in a tangent vector."""
        return self._factor_offsets([f.tangent_dim for f in self.factors], key)

    def embedding_slice(self, key: int | str) -> slice:
        """Where factor ``key`` sits in an embedded element."""
        return self._factor_offsets([f.embedding_dim for f in self.factors], key)

    # ------------------------------------------------------------------ helpers

    @property
    def name(self) -> str:
        return type(self).__name__

    def __repr__(self) -> str:
        return f"{self.name}()"

    def __eq__(self, other: object) -> bool:
        return type(self) is type(other) and repr(self) == repr(other)

    def __hash__(self) -> int:
        return hash(repr(self))

    def batch_shape(self, x: torch.Tensor) -> torch.Size:
        """The batch shape of an element ``x``."""
        return x.shape[: x.dim() - len(self.element_shape)]

    # ------------------------------------------------------------------ input validation
    # Public for authors of a group (call them first in every method that takes a tensor) and of
    # a system (``self.group.check_element(x, "step")``): they raise the library's clear errors.

    def check_shape(
        self, t: torch.Tensor, trailing: tuple[int, ...], where: str, what: str
    ) -> None:
        """Raises unless ``t`` is a floating-point tensor of shape ``(*batch, *trailing)``.

        ``where`` names the method being called and ``what`` the argument, for the message, e.g.
        ``check_shape(z, (4,), "unembed", "an embedded element")``. Raises ``TypeError`` for a
        non-tensor or a dtype other than float32 and float64 (integers, float16, bfloat16, complex),
        ``ValueError`` for a
        wrong trailing shape (naming the expected ``(*batch, ...)`` and the shape received).
        """
        if not isinstance(t, torch.Tensor):
            raise TypeError(
                f"{self.name}.{where} expects {what} as a torch.Tensor, got {type(t).__name__}."
            )
        if t.dtype not in _DTYPES:
            kind = "floating-point tensor" if not t.is_floating_point() else "tensor"
            raise TypeError(
                f"{self.name}.{where} expects a {kind} of dtype float32 or float64 (the only "
                f"supported dtypes), got {t.dtype}; convert it first, e.g. with .float() or "
                f".double()."
            )
        n = len(trailing)
        if t.dim() < n or tuple(t.shape[t.dim() - n :]) != trailing:
            want = ", ".join(["*batch", *map(str, trailing)])
            raise ValueError(
                f"{self.name}.{where} expects {what} of shape ({want}), got {tuple(t.shape)}."
            )

    def check_dtype(self, dtype: torch.dtype, where: str) -> None:
        """Raises ``TypeError`` unless ``dtype`` is float32 or float64, for methods that take a
        ``dtype`` argument (``identity``, ``random``): the message :meth:`check_shape` gives a
        tensor of another dtype (float16, bfloat16, integers, complex)."""
        if dtype not in _DTYPES:
            raise TypeError(
                f"{self.name}.{where} expects dtype float32 or float64 (the only supported "
                f"dtypes), got {dtype}; ask for torch.float32 or torch.float64 and convert the "
                f"result afterwards if you need another dtype."
            )

    def check_tangent(self, v: torch.Tensor, where: str) -> None:
        """Raises unless ``v`` is a tangent vector ``(*batch, tangent_dim)``.

        Errors as :meth:`check_shape`; ``where`` names the calling method
        (``check_tangent(v, "exp")``). Checks shape and dtype only; any real vector of that shape
        is a tangent vector.
        """
        self.check_shape(v, (self.tangent_dim,), where, "a tangent vector")

    def check_element(self, x: torch.Tensor, where: str) -> None:
        """Raises unless ``x`` has an element's shape ``(*batch, *element_shape)``, as
        :meth:`check_shape` (``TypeError`` / ``ValueError``).

        ``where`` names the calling method (``check_element(x, "log")``). Checks shape and dtype
        only, cheaply, so every operation can call it; :meth:`check_member` is the membership test.
        """
        self.check_shape(x, tuple(self.element_shape), where, "a group element")

    def check_pair(self, x: torch.Tensor, y: torch.Tensor, where: str) -> None:
        """Raises unless ``x`` and ``y`` are elements (:meth:`check_element`) of one dtype whose
        batch shapes broadcast: ``TypeError`` naming both dtypes, ``ValueError`` naming both
        shapes. For methods of two elements (``compose``, ``between``); static checks only."""
        self.check_element(x, where)
        self.check_element(y, where)
        if x.dtype != y.dtype:
            raise TypeError(
                f"{self.name}.{where} expects x and y of one dtype, got x {x.dtype} and y "
                f"{y.dtype}; convert one first, e.g. y.to(x.dtype)."
            )
        bx, by = self.batch_shape(x), self.batch_shape(y)
        if bx == by:  # the common case, without broadcast_shapes' Python (a hot path)
            return
        try:
            torch.broadcast_shapes(bx, by)
        except RuntimeError:
            raise ValueError(
                f"{self.name}.{where}: the batch shapes of x {tuple(bx)} and y {tuple(by)} do not "
                f"broadcast (x has shape {tuple(x.shape)}, y {tuple(y.shape)}); batch dimensions "
                f"must be equal or 1, as in torch broadcasting."
            ) from None


class MatrixLieGroup(LieGroup):
    """A group of ``(d, d)`` matrices: compose is the matrix product, identity the unit matrix.

    A subclass adds ``hat`` (``R^tangent_dim -> `` the Lie algebra as ``d x d`` matrices) and
    ``vee`` (its inverse), and gets ``compose``, ``identity``, a generic ``inverse`` and
    ``adjoint(x) v = vee(x hat(v) x^-1)``.
    """

    #: Side ``d`` of the square matrices.
    matrix_dim: int

    @property
    def element_shape(self) -> tuple[int, ...]:  # type: ignore[override]
        return (self.matrix_dim, self.matrix_dim)

    @abc.abstractmethod
    def hat(self, v: torch.Tensor) -> torch.Tensor:
        """``(*batch, tangent_dim) -> (*batch, d, d)``, the Lie algebra element of ``v``."""

    @abc.abstractmethod
    def vee(self, m: torch.Tensor) -> torch.Tensor:
        """``(*batch, d, d) -> (*batch, tangent_dim)``, the inverse of ``hat``."""

    def identity(self, batch_shape=(), dtype=torch.float32, device=None) -> torch.Tensor:
        self.check_dtype(dtype, "identity")
        eye = torch.eye(self.matrix_dim, dtype=dtype, device=device)
        return eye.expand(*batch_shape, self.matrix_dim, self.matrix_dim).clone()

    def compose(self, x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
        self.check_pair(x, y, "compose")
        return x @ y

    def inverse(self, x: torch.Tensor) -> torch.Tensor:
        self.check_element(x, "inverse")
        return torch.linalg.inv(x)

    def adjoint(self, x: torch.Tensor) -> torch.Tensor:
        self.check_element(x, "adjoint")
        eye = torch.eye(self.tangent_dim, dtype=x.dtype, device=x.device)
        basis = self.hat(eye)  # (k, d, d)
        conj = x.unsqueeze(-3) @ basis @ self.inverse(x).unsqueeze(-3)  # (*batch, k, d, d)
        return self.vee(conj).transpose(-1, -2)
