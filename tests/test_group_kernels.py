"""SO(3)'s kernels (``groups.so3_kernels``): one value whatever the mode, an analytic backward
equal to autograd's through the formula, second derivatives and ``torch.func`` through the
formula, cached tables that survive inference mode; and (issue #36) every group's ``exp`` of an
angle whose square overflows is finite.

The reference of a gradient is autograd through the formula itself: the kernels' value functions
called on an input that requires grad record every operation (the double-``where`` series of
``groups.numerics`` included), which is what ``exp``/``log`` did before they had a backward.
"""

from __future__ import annotations

import math

import pytest
import torch

from groups import SE2, SE3, SE23, SO2, SO3, Euclidean, Product
from groups import numerics as nx
from groups import so3_kernels as K

DTYPES = [torch.float32, torch.float64]
ANGLES = (0.0, 1e-8, 1e-5, 3e-3, 5e-3, 1e-2, 2e-2, 0.25, 0.5, 1.0, 2.0, 3.0, math.pi - 1e-7, math.pi)
G = SO3()


def _tangents(dtype, seed=0, scale=1.0):
    """``(len(ANGLES) * 8 + 64, 3)``: each adversarial angle about 8 random axes, then random."""
    g = torch.Generator().manual_seed(seed)
    angles = torch.tensor(ANGLES, dtype=torch.float64).repeat_interleave(8)
    axes = torch.randn(len(angles), 3, generator=g, dtype=torch.float64)
    v = angles[:, None] * axes / torch.linalg.vector_norm(axes, dim=-1, keepdim=True)
    v = torch.cat([v, scale * torch.randn(64, 3, generator=g, dtype=torch.float64)])
    return v.to(dtype)


def _grads(fn, inputs, weight):
    inputs = [t.detach().clone().requires_grad_() for t in inputs]
    return torch.autograd.grad((fn(*inputs) * weight).sum(), inputs)


def _tol(dtype):
    return {"rtol": 0, "atol": 1e-12 if dtype == torch.float64 else 2e-5}


@pytest.mark.parametrize("dtype", DTYPES)
def test_a_value_is_the_same_with_and_without_a_recorded_gradient(dtype):
    v = _tangents(dtype)
    x = G.random((len(v),), generator=torch.Generator().manual_seed(1), dtype=dtype)
    y = G.exp(v)
    for name, fn, args in (("exp", G.exp, (v,)), ("log", G.log, (y,)),
                           ("rplus", G.rplus, (x, v)), ("rminus", G.rminus, (y, x))):
        with torch.no_grad():
            plain = fn(*args)
        recorded = fn(*[a.detach().clone().requires_grad_() for a in args])
        assert recorded.grad_fn is not None and torch.equal(recorded.detach(), plain), name


@pytest.mark.parametrize("dtype", DTYPES)
def test_the_analytic_backward_equals_autograd_through_the_formula(dtype):
    """At the adversarial angles (0, the thresholds of the series, pi) and at random ones."""
    v = _tangents(dtype)
    n = len(v)
    gen = torch.Generator().manual_seed(2)
    x = G.random((n,), generator=gen, dtype=dtype)
    y = G.exp(v)
    w3 = torch.randn(n, 3, generator=gen, dtype=torch.float64).to(dtype)
    w33 = torch.randn(n, 3, 3, generator=gen, dtype=torch.float64).to(dtype)
    cases = {
        "exp": (G.exp, lambda a: K._exp_rows(a)[0], (v,), w33),
        "log": (G.log, lambda a: K._log_parts(a)[0], (y,), w3),
        "rplus": (G.rplus, lambda a, b: a @ K._exp_rows(b)[0], (x, v), w33),
        "rminus": (G.rminus, lambda a, b: K._log_parts(b.transpose(-1, -2) @ a)[0], (y, x), w3),
    }
    for name, (fast, formula, args, weight) in cases.items():
        got, want = _grads(fast, args, weight), _grads(formula, args, weight)
        for a, b in zip(got, want):
            torch.testing.assert_close(a, b, **_tol(dtype), msg=name)


def test_a_kernel_is_one_autograd_node():
    v = _tangents(torch.float64).requires_grad_()
    assert type(G.exp(v).grad_fn).__name__ == "_ExpBackward"
    assert type(G.log(G.exp(v)).grad_fn).__name__ == "_LogBackward"


def test_second_derivatives_and_torch_func_go_through_the_formula():
    gen = torch.Generator().manual_seed(3)
    v = (0.7 * torch.randn(3, 3, generator=gen, dtype=torch.float64)).requires_grad_()
    v.data[0] = torch.tensor([1e-4, 0.0, 2e-4], dtype=torch.float64)  # in the series
    x = G.random((3,), generator=gen, dtype=torch.float64).requires_grad_()
    y = G.exp(v.detach()).requires_grad_()
    for fn, args in ((G.exp, (v,)), (G.log, (y,)), (G.rplus, (x, v)), (G.rminus, (y, x))):
        assert torch.autograd.gradcheck(fn, args)
        assert torch.autograd.gradgradcheck(fn, args)
    jac = torch.func.jacrev(G.rplus, argnums=1)(x.detach()[0], v.detach()[0])
    ref = torch.autograd.functional.jacobian(lambda b: x.detach()[0] @ K._exp_rows(b)[0], v[0])
    torch.testing.assert_close(jac, ref, rtol=0, atol=1e-12)
    hess = torch.func.hessian(lambda b: G.exp(b).sum())(v.detach()[1])
    assert hess.shape == (3, 3) and bool(torch.isfinite(hess).all())
    # under a torch.func transform the numerics take their series below the threshold (they
    # cannot tell vmap from a derivative): the same values to an ulp
    batched = torch.func.vmap(G.exp)(v.detach())
    torch.testing.assert_close(batched, G.exp(v.detach()), rtol=0, atol=1e-15)


def test_a_table_first_made_in_inference_mode_serves_a_recorded_graph():
    nx._CACHE.clear()
    v = torch.randn(4, 3, dtype=torch.float64)
    with torch.inference_mode():
        G.exp(v), G.log(G.exp(v))
    vr = v.clone().requires_grad_()
    G.log(G.exp(vr)).sum().backward()  # a cached inference tensor here would fail to save
    assert vr.grad is not None and bool(torch.isfinite(vr.grad).all())


# ------------------------------------------------------------------ #36: huge angles

# angles whose square overflows; in float64 3e19 and 1e30 do not (their rotation is computed)
HUGE = {torch.float32: (3e19, 1e30, torch.finfo(torch.float32).max),
        torch.float64: (1.4e154, 1e200, torch.finfo(torch.float64).max)}
LARGE = {torch.float32: (), torch.float64: (3e19, 1e30)}


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("group", [SO2(), SO3(), SE2(), SE3(), SE23(),
                                   Product(SO3(), Euclidean(3))], ids=repr)
def test_exp_of_an_angle_whose_square_overflows_is_finite_and_on_the_group(group, dtype):
    """Angles 3e19, 1e30 and finfo.max in float32 (their squares overflow); 3e19, 1e30 (no
    overflow there), 1.4e154, 1e200 and finfo.max in float64; about a generic and an axis
    direction."""
    axes = torch.tensor([[0.48, -0.6, 0.64], [0.0, 0.0, -1.0]], dtype=torch.float64)
    for angle in (*LARGE[dtype], *HUGE[dtype]):
        v = torch.zeros(2, group.tangent_dim, dtype=dtype)
        for s in group.angle_slices:
            k = s.stop - s.start
            axis = axes if k == 3 else torch.tensor([[1.0], [-1.0]], dtype=torch.float64)
            v[:, s] = (axis * angle).to(dtype)
        free = [i for i in range(group.tangent_dim)
                if not any(s.start <= i < s.stop for s in group.angle_slices)]
        v[:, free] = 0.5
        x = group.exp(v)
        assert bool(torch.isfinite(x).all()), (angle, x)
        assert float(group.membership_error(x).max()) < 1e-5, angle
        vr = v.clone().requires_grad_()
        group.exp(vr).sum().backward()
        assert bool(torch.isfinite(vr.grad).all()) or angle in HUGE[dtype]
        if isinstance(group, SO3) and angle in HUGE[dtype]:
            assert torch.equal(x, torch.eye(3, dtype=dtype).expand(2, 3, 3))  # whole turns
            assert torch.equal(vr.grad, torch.zeros_like(v))


@pytest.mark.parametrize("dtype", DTYPES)
def test_a_pose_of_whole_turns_keeps_its_translation_along_the_axis(dtype):
    """SE(3): R = I and t = n n^T rho, which J_l is at any whole number of turns."""
    n = torch.tensor([0.48, -0.6, 0.64], dtype=torch.float64)
    rho = torch.tensor([1.0, 2.0, -0.5], dtype=torch.float64)
    for angle in HUGE[dtype]:
        x = SE3().exp(torch.cat([rho, angle * n]).to(dtype))
        torch.testing.assert_close(x[:3, :3], torch.eye(3, dtype=dtype))
        torch.testing.assert_close(x[:3, 3], (n * (n @ rho)).to(dtype))
    # a whole number of turns is exactly that, within range too
    turns = 2 * math.pi * 3
    x = SE3().exp(torch.cat([rho, turns * n]).double())
    torch.testing.assert_close(x[:3, 3], n * (n @ rho), rtol=0, atol=1e-12)


def test_an_input_written_in_place_after_the_step_still_has_a_first_derivative():
    """A prior's pattern ``x[:, s] = rplus(x[:, s], w)`` (the kernel's input is a view of what is
    then written): the first-order backward reads only what autograd through the formula would."""
    w = torch.randn(4, 3, dtype=torch.float64, requires_grad=True)
    base = torch.eye(3, dtype=torch.float64).repeat(4, 2, 1).flatten(1).requires_grad_()
    x = base.clone()
    x[:, :9] = G.rplus(x[:, :9].unflatten(-1, (3, 3)), w).flatten(-2)
    y = G.exp(w.detach())
    x[:, 9:] = G.rminus(y, x[:, 9:].unflatten(-1, (3, 3))).repeat(1, 3)
    x.sum().backward()
    assert bool(torch.isfinite(w.grad).all()) and bool(torch.isfinite(base.grad).all())


def test_a_second_derivative_takes_each_formula_s_partial_derivatives():
    """``v`` a function of ``x`` elsewhere in the graph (an observer's network output of its
    estimate): the kernel's second-order backward must not add the path through ``v`` twice."""
    x = G.exp(torch.tensor([[0.3, -0.2, 0.5], [1.0, 0.4, -0.7]], dtype=torch.float64))
    x.requires_grad_()
    weight = torch.tensor([[0.2, -1.0, 0.7]], dtype=torch.float64)

    def loss(fast):
        v = torch.tanh(x.flatten(-2)[:, :3] @ weight.t() * weight)  # v depends on x
        out = G.rplus(x, v) if fast else x @ K._exp_rows(v)[0]
        return (out * out.detach().roll(1, -1)).sum()

    def hess(fast):
        (g,) = torch.autograd.grad(loss(fast), x, create_graph=True)
        return torch.autograd.grad((g * g).sum(), x)[0]

    torch.testing.assert_close(hess(True), hess(False), rtol=1e-10, atol=1e-12)
