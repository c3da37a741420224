"""Define your own group: SO(2) as unit complex numbers, checked with one call.

The complete code of the tutorial ``docs/custom_group.md``. It lives outside the library
(nothing in ``groups`` changes), subclasses :class:`groups.LieGroup`, writes only the minimum API,
and ends with ``check_group``, the same axiom suite every shipped group passes.
``tests/test_custom_group.py`` runs this file, so the tutorial cannot rot.

An element is the unit complex number ``z = cos t + i sin t`` stored as a real tensor
``(*batch, 2)`` = ``(cos t, sin t)``; composition is complex multiplication, the inverse is the
conjugate, the tangent vector is the angle ``t`` of shape ``(*batch, 1)``, ``exp(t) = e^{i t}`` and
``log(z) = atan2(Im z, Re z)``. The embedding into R^2 is the pair itself.

Run it with ``python docs/examples/custom_group_so2_complex.py``.
"""

from __future__ import annotations

import torch

from groups import SO2, LieGroup


class ComplexSO2(LieGroup):
    """Planar rotations as unit complex numbers ``(*batch, 2)``; tangent: angles ``(*batch, 1)``."""

    element_shape = (2,)
    tangent_dim = 1
    embedding_dim = 2
    # The whole tangent vector is a rotation angle: groups.testing puts 0, 1e-8, ..., pi there.
    angle_slices = (slice(0, 1),)
    # embed(x) is x itself (flattened): declared, so code reading the state can skip embedding
    # it; groups.testing checks the declaration.
    embedding_is_flat = True

    # -- the minimum API ---------------------------------------------------------------------

    def identity(self, batch_shape=(), dtype=torch.float32, device=None) -> torch.Tensor:
        one = torch.tensor([1.0, 0.0], dtype=dtype, device=device)
        return one.expand(*batch_shape, 2).clone()

    def compose(self, x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
        """Complex multiplication; batch dimensions broadcast like torch's."""
        self.check_element(x, "compose")  # clear ValueError/TypeError on a wrong shape or dtype
        self.check_element(y, "compose")
        a, b = x.unbind(-1)
        c, d = y.unbind(-1)
        return torch.stack((a * c - b * d, a * d + b * c), dim=-1)

    def inverse(self, x: torch.Tensor) -> torch.Tensor:
        """The complex conjugate (the inverse of a unit complex number)."""
        self.check_element(x, "inverse")
        return torch.stack((x[..., 0], -x[..., 1]), dim=-1)

    def exp(self, v: torch.Tensor) -> torch.Tensor:
        """``(*batch, 1) -> (*batch, 2)``, ``(cos t, sin t)``: no singularity, nothing to guard."""
        self.check_tangent(v, "exp")
        t = v[..., 0]
        return torch.stack((torch.cos(t), torch.sin(t)), dim=-1)

    def log(self, x: torch.Tensor) -> torch.Tensor:
        """``(*batch, 2) -> (*batch, 1)``, the angle in ``(-pi, pi]``.

        ``atan2`` stays accurate at and near pi (``acos(Re z)`` would not), and its gradient is
        finite everywhere on the group (``|z| = 1``, never 0).
        """
        self.check_element(x, "log")
        return torch.atan2(x[..., 1], x[..., 0]).unsqueeze(-1)

    def embed(self, x: torch.Tensor) -> torch.Tensor:
        self.check_element(x, "embed")
        return x

    def unembed(self, z: torch.Tensor) -> torch.Tensor:
        self.check_shape(z, (2,), "unembed", "an embedded element")
        return z

    def membership_error(self, x: torch.Tensor) -> torch.Tensor:
        """``| |z|^2 - 1 |``, shape ``(*batch,)``: 0 on the unit circle, NaN for NaN input."""
        self.check_element(x, "membership_error")
        return ((x * x).sum(-1) - 1.0).abs()

    # -- optional: a derived method overridden for speed or for a better distribution ----------

    def random(self, batch_shape=(), generator=None, dtype=torch.float32, device=None):
        """Uniform (Haar) rotations, instead of the default ``exp`` of a standard normal."""
        t = torch.rand(*batch_shape, 1, generator=generator, dtype=dtype, device=device)
        return self.exp((2.0 * t - 1.0) * torch.pi)


def main() -> None:
    from groups.testing import check_group  # needs hypothesis: pip install -e '.[dev]'

    G = ComplexSO2()

    # What the subclass gets for free: rplus (the observer's update x · exp(v)), rminus,
    # between, distance, adjoint (by autograd), check_member, from_embedding.
    x = G.random((4,), dtype=torch.float64)
    v = torch.full((4, 1), 0.3, dtype=torch.float64)
    y = G.rplus(x, v)
    assert torch.allclose(G.rminus(y, x), v)
    assert torch.allclose(G.adjoint(x), torch.ones(4, 1, 1, dtype=torch.float64))

    # The same rotation as the library's SO(2): e^{i t} is the first column of R(t).
    assert torch.allclose(G.exp(v), SO2().exp(v)[..., :, 0])

    # The whole axiom suite in float32 and float64, batch shapes (), (1,) and (3, 1, 2).
    results = check_group(G)
    worst = max(results, key=lambda r: r.worst_ratio)
    print(f"{G!r} passes {len(results)} checks; closest to its tolerance: {worst}")


if __name__ == "__main__":
    main()
