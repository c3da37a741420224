"""A rollout's autograd graph is freed once nothing refers to it, backpropagated or not, for
every observer of :data:`tests.test_pieces.COMBOS` (between them every registered piece).

The SO(3) kernels keep their inputs on the Function's context for a second derivative
(:class:`groups.so3_kernels.Inputs`); a piece that writes in place into a tensor after handing
a view of it to one of them closes a reference cycle through the C++ graph, which Python's
garbage collector cannot see: training then keeps every step's graph alive (a full BROAD
fine-tuning grew by about 1 GB per epoch that way, through the kinematic prior).
"""

from __future__ import annotations

import gc

import pytest

from groups import so3_kernels as so3k

from tests.test_pieces import COMBOS, _data, _inputs, combo


def _live_inputs() -> int:
    gc.collect()
    return sum(type(o) is so3k.Inputs for o in gc.get_objects())


def _loss(obs, system):
    data = _data(system, n=2, t=6)
    est = obs(data.measurements, _inputs(system, data))
    return est.square().sum()


@pytest.mark.parametrize("backward", [True, False], ids=["backpropagated", "dropped"])
@pytest.mark.parametrize("name", sorted(COMBOS))
def test_the_rollouts_graph_is_freed_when_dropped(name, backward):
    system, obs = combo(name)
    before = _live_inputs()
    loss = _loss(obs, system)
    recorded = _live_inputs() - before
    if backward:
        loss.backward()
    del loss
    assert _live_inputs() == before, f"{name}: the graph outlived its loss"
    if name.endswith("kinematic") or "kinematic" in name:  # the case that leaked
        assert recorded > 0, "the rollout ran no SO(3) kernel: the test checks nothing"
