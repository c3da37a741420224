"""The projection scale (``Projection``): the core's correction of a factor projected onto the
span of given tangent directions. For an attitude corrected in the world frame (``left``) and
projected onto "up", the core turns the estimate about the vertical only: its tilt is whatever
the prior makes it, whatever the core says."""

from __future__ import annotations

import functools

import pytest
import torch

from groups import SO3, Euclidean, Product
from manifold_nets.cores import GRUCore
from manifold_nets.observer import (
    ComplementaryPrior,
    Embedding,
    GroupUpdate,
    KinematicPrior,
    Measurement,
    OutputScale,
    Projection,
    Readings,
    ResidualObserver,
)

G = Product(SO3(), Euclidean(3), names=("R", "b"))
DT = 0.01


def bound(factors):
    return Projection(factors).bind(G, Measurement(6, 3).bind(G))


def test_onto_one_direction_only_its_component_stays_and_other_factors_pass():
    v = torch.randn(50, 6, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    out = bound({"R": [[0, 0, 2.0]]})(v)
    assert torch.equal(out[:, :2], torch.zeros(50, 2, dtype=torch.float64))
    assert torch.allclose(out[:, 2:], v[:, 2:], rtol=0, atol=1e-15)


def test_onto_a_plane_it_is_the_orthogonal_projection():
    dirs = [[1.0, 2.0, 0.5], [0.0, 1.0, -1.0]]
    p = bound({"R": dirs})
    v = torch.randn(50, 6, dtype=torch.float64, generator=torch.Generator().manual_seed(1))
    out = p(v)
    assert torch.allclose(p(out), out, atol=1e-14)  # idempotent
    a = torch.tensor(dirs, dtype=torch.float64)
    assert torch.allclose((v - out)[:, :3] @ a.T, torch.zeros(50, 2, dtype=torch.float64),
                          atol=1e-14)  # fmt: skip  the rest is orthogonal to the plane
    inside = torch.randn(50, 2, dtype=torch.float64) @ a  # a vector in the plane stays
    assert torch.allclose(p(torch.cat((inside, v[:, 3:]), -1))[:, :3], inside, atol=1e-14)
    assert torch.equal(out[:, 3:], v[:, 3:])


@pytest.mark.parametrize("factors, message", [
    ({}, r"name at least one factor, e\.g\. \{x: \[\[0, 0, 1\]\]\}"),
    ({"R": [[0, 0, 0]]}, r"factors\['R'\] must be a list of linearly independent directions"),
    ({"R": [[1, 0, 0], [2, 0, 0]]}, "linearly independent"),
    ({"R": [[1, 0, 0], [0, 1, 0], [0, 0, 1]]}, "fewer than the tangent's size"),
    ({"R": [[0, 0, float("nan")]]}, "linearly independent"),
    ({"R": "up"}, "must be a list of linearly independent directions"),
])
def test_bad_directions_say_what_is_wrong(factors, message):
    with pytest.raises(ValueError, match=message):
        Projection(factors)


def test_a_direction_of_the_wrong_size_or_an_unknown_factor_is_refused_at_bind():
    with pytest.raises(ValueError, match=r"factors\['R'\]: each direction must have the factor's "
                                         r"tangent_dim = 3 numbers"):
        bound({"R": [[0, 1]]})
    with pytest.raises(ValueError, match="names a factor 'q'"):
        bound({"q": [[0, 0, 1]]})


def _attitude_observer(seed, heading_only=True):
    torch.manual_seed(seed)
    obs = ResidualObserver(
        G, Measurement(6, 3), functools.partial(GRUCore, hidden_size=8, num_layers=1),
        update=GroupUpdate({"R": "left"}),
        prior=ComplementaryPrior("R", (0, 3), 0.3, DT, inner=KinematicPrior({"R": (6, 9)}, DT)),
        features=[Embedding(), Readings()],
        scales=([Projection({"R": [[0, 0, 1]]})] if heading_only else []) + [OutputScale(0.5)],
    ).double()
    with torch.no_grad():
        obs.core.head.reset_parameters()  # a core that says something
    return obs


def test_a_heading_only_core_leaves_the_tilt_to_the_prior():
    """Two observers with different random cores, both heading-only: their estimates' "up" in
    the body frame (``R^T e_z``, all the inclination depends on) agree exactly; without the
    projection they do not."""
    g = torch.Generator().manual_seed(2)
    y = torch.randn(3, 30, 6, generator=g, dtype=torch.float64)
    u = torch.randn(3, 30, 3, generator=g, dtype=torch.float64)

    def up(obs):
        with torch.no_grad():
            return obs(y, u)[..., 6:9]  # rows of R: R^T e_z is its third row

    assert torch.allclose(up(_attitude_observer(0)), up(_attitude_observer(1)), atol=1e-12)
    free = up(_attitude_observer(0, False)) - up(_attitude_observer(1, False))
    assert free.abs().max() > 1e-3
