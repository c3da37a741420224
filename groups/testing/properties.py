"""The axioms, one function each: ``property(case, data)`` checks one law on one case.

``case`` is a :class:`~groups.testing.comparison.Case` (the group, dtype and batch shape, and the
comparisons); ``data`` is hypothesis' ``st.data()``, or None on the deterministic grid and for
:data:`DETERMINISTIC` properties, and is only passed back to ``case.x``/``case.v``/``case.seed``.
:data:`PROPERTIES` lists them in the order ``check_group`` runs them.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from functools import partial

import torch

from ..base import GroupMembershipError, LieGroup
from .comparison import Case, element_magnitude, format_tensor, magnitude
from .matrix_properties import matrix_compose, matrix_exp

__all__ = [
    "PROPERTIES",
    "DETERMINISTIC",
    "membership",
    "identity",
    "inverse",
    "associativity",
    "exp_log",
    "log_exp",
    "matrix_exp",
    "matrix_compose",
    "adjoint",
    "embedding",
    "rplus_rminus",
    "mean",
    "gradients_finite",
    "gradcheck",
    "batched_vs_looped",
    "broadcasting",
]


def _matvec(m: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    return (m @ v.unsqueeze(-1)).squeeze(-1)


def _max_angle(group: LieGroup, v: torch.Tensor) -> torch.Tensor:
    """The largest rotation angle of each tangent vector, ``(*batch,)`` in float64 (0 if none)."""
    v = v.detach().double()
    if not group.angle_slices:
        return v.new_zeros(v.shape[:-1])
    norms = [torch.linalg.vector_norm(v[..., s], dim=-1) for s in group.angle_slices]
    return torch.stack(norms, -1).amax(-1)


def membership(c: Case, data) -> None:
    """Outputs are on the group and have their documented shapes; no input is modified."""
    G, dt, bs, k = c.group, c.dtype, c.batch_shape, c.group.tangent_dim
    x, y, v = c.x(data, "x"), c.x(data, "y"), c.v(data, "v")
    gen = torch.Generator(c.device).manual_seed(c.seed(data, "random seed"))
    inputs = {"x": x, "y": y, "v": v}
    saved = {name: t.clone() for name, t in inputs.items()}
    el = tuple(G.element_shape)
    # name -> (operation, trailing shape of its output, is the output a group element?)
    # The first three make elements from nothing but their arguments; the drawn x and y are made
    # by them (strategies.elements), so they are checked first and a NaN in x is blamed on them.
    makers: dict[str, tuple[Callable[[], torch.Tensor], tuple[int, ...], bool]] = {
        "identity(batch_shape)": (lambda: G.identity(bs, dtype=dt, device=c.device), el, True),
        "exp(v)": (lambda: G.exp(v), el, True),
        "random(batch_shape)": (
            lambda: G.random(bs, generator=gen, dtype=dt, device=c.device), el, True
        ),
    }
    ops: dict[str, tuple[Callable[[], torch.Tensor], tuple[int, ...], bool]] = {
        "compose(x, y)": (lambda: G.compose(x, y), el, True),
        "inverse(x)": (lambda: G.inverse(x), el, True),
        "rplus(x, v)": (lambda: G.rplus(x, v), el, True),
        "log(x)": (lambda: G.log(x), (k,), False),
        "rminus(y, x)": (lambda: G.rminus(y, x), (k,), False),
        "between(x, y)": (lambda: G.between(x, y), el, True),
        "embed(x)": (lambda: G.embed(x), (G.embedding_dim,), False),
        "adjoint(x)": (lambda: G.adjoint(x), (k, k), False),
        "distance(x, y)": (lambda: G.distance(x, y), (), False),
    }

    def run(table, shown: dict[str, torch.Tensor]) -> None:
        for name, (op, trailing, is_element) in table.items():
            out = op()
            for arg, before in saved.items():
                if not _unchanged(before, inputs[arg]):
                    c.fail(f"{name} modified its input {arg} in place")
            c.shape(name, out, trailing)
            big = any(t.is_floating_point() and bool((t.abs() > 30).any()) for t in shown.values())
            hint = (" (from large tangent vectors: if exp grows exponentially, declare the "
                    "group's tangent_magnitudes or pass magnitudes=)") if big else ""
            c.finite(f"{name} returned NaN or Inf{hint}", out, len(trailing), inputs=shown)
            if is_element:
                err = G.membership_error(out)
                c.shape(f"membership_error({name})", err, ())
                c.within(f"membership_error({name})", err, c.tol.member, inputs=inputs)

    run(makers, {"v": v})
    for arg in ("x", "y"):
        c.finite(
            f"the drawn element {arg} holds NaN or Inf (it was made by the group's exp or random)",
            inputs[arg], len(el), inputs={arg: inputs[arg]},
        )  # fmt: skip
    run(ops, inputs)


def _unchanged(before: torch.Tensor, after: torch.Tensor) -> bool:
    """``torch.equal`` with NaN equal to NaN (``torch.equal`` is False for a tensor holding NaN,
    which would blame a NaN on an in-place modification)."""
    return before.shape == after.shape and bool(
        torch.isclose(before, after, rtol=0.0, atol=0.0, equal_nan=True).all()
    )


def identity(c: Case, data) -> None:
    """``e x = x e = x``, ``e^-1 = e``, ``exp(0) = e``, ``log(e) = 0``, ``rminus(x, x) = 0``."""
    G, dt, bs = c.group, c.dtype, c.batch_shape
    x = c.x(data, "x")
    e = G.identity(bs, dtype=dt, device=c.device)
    zero = torch.zeros(*bs, G.tangent_dim, dtype=dt, device=c.device)
    c.close_elements("compose(identity, x) == x", G.compose(e, x), x, inputs={"x": x})
    c.close_elements("compose(x, identity) == x", G.compose(x, e), x, inputs={"x": x})
    c.close_elements("inverse(identity) == identity", G.inverse(e), e)
    c.close_elements("exp(0) == identity", G.exp(zero), e)
    c.close_tangent("log(identity) == 0", G.log(e), zero)
    c.close_tangent(
        "rminus(x, x) == 0", G.rminus(x, x), zero, scale=element_magnitude(G, x) ** 2,
        inputs={"x": x},
    )  # fmt: skip


def inverse(c: Case, data) -> None:
    """``x x^-1 = x^-1 x = e``, ``(x^-1)^-1 = x``, ``(x y)^-1 = y^-1 x^-1``."""
    G, dt, bs = c.group, c.dtype, c.batch_shape
    x, y = c.x(data, "x"), c.x(data, "y")
    e = G.identity(bs, dtype=dt, device=c.device)
    xi, yi = G.inverse(x), G.inverse(y)
    s = element_magnitude(G, x) * element_magnitude(G, xi)
    ins = {"x": x}
    c.close_elements("compose(x, inverse(x)) == identity", G.compose(x, xi), e, scale=s,
            inputs=ins)
    c.close_elements("compose(inverse(x), x) == identity", G.compose(xi, x), e, scale=s,
            inputs=ins)
    c.close_elements("inverse(inverse(x)) == x", G.inverse(xi), x, scale=s, inputs=ins)
    s2 = s * element_magnitude(G, y) * element_magnitude(G, yi)
    c.close_elements(
        "inverse(compose(x, y)) == compose(inverse(y), inverse(x))",
        G.inverse(G.compose(x, y)), G.compose(yi, xi), scale=s2,
        inputs={"x": x, "y": y},
    )  # fmt: skip


def associativity(c: Case, data) -> None:
    """``(x y) z = x (y z)``."""
    G = c.group
    x, y, z = c.x(data, "x"), c.x(data, "y"), c.x(data, "z")
    s = element_magnitude(G, x) * element_magnitude(G, y) * element_magnitude(G, z)
    c.close_elements(
        "compose(compose(x, y), z) == compose(x, compose(y, z))",
        G.compose(G.compose(x, y), z), G.compose(x, G.compose(y, z)), scale=s,
        inputs={"x": x, "y": y, "z": z},
    )  # fmt: skip


def exp_log(c: Case, data) -> None:
    """``exp(log(x)) = x`` for every element, angle pi included."""
    G = c.group
    x = c.x(data, "x")
    c.close_elements("exp(log(x)) == x", G.exp(G.log(x)), x,
            inputs={"x": x, "log(x)": G.log(x)})


def _log_exp_tolerance(c: Case, v: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """``(mask, tol)``: where ``log(exp v) = v`` is required, and the tolerance grown near pi."""
    theta = _max_angle(c.group, v)
    gap = math.pi - theta
    mask = gap > c.tol.pi_margin
    gap = torch.where(mask, gap, torch.ones_like(gap))
    return mask, c.tol.value + c.tol.near_pi * c.eps / gap


def log_exp(c: Case, data) -> None:
    """``log(exp(v)) = v`` below ``pi - pi_margin``; ``exp(log(exp(v))) = exp(v)`` everywhere."""
    G = c.group
    v = c.v(data, "v")
    mask, tol = _log_exp_tolerance(c, v)
    got = G.log(G.exp(v))
    got = torch.where(mask.unsqueeze(-1), got, v)  # elements at the cut locus are not compared
    c.close_tangent("log(exp(v)) == v (angles < pi - margin)", got, v, tol=tol, inputs={"v": v})
    # At and beyond the margin the log may pick the other branch, but it must stay on the group.
    c.close_elements(
        "exp(log(exp(v))) == exp(v)", G.exp(G.log(G.exp(v))), G.exp(v), inputs={"v": v}
    )


def adjoint(c: Case, data) -> None:
    """``x exp(v) x^-1 = exp(Ad_x v)``, ``Ad_{xy} = Ad_x Ad_y``, ``Ad_x Ad_{x^-1} = I``."""
    G, k = c.group, c.group.tangent_dim
    x, y, v = c.x(data, "x"), c.x(data, "y"), c.v(data, "v")
    ad_x = G.adjoint(x)
    c.shape("adjoint(x)", ad_x, (k, k))
    xi, ev = G.inverse(x), G.exp(v)
    lhs = G.compose(G.compose(x, ev), xi)
    rhs = G.exp(_matvec(ad_x, v))
    s = element_magnitude(G, x) * element_magnitude(G, xi) * element_magnitude(G, ev)
    c.close_elements("compose(x, exp(v), inverse(x)) == exp(adjoint(x) v)", rhs, lhs,
            scale=s, inputs={"x": x, "v": v})
    ad_y = G.adjoint(y)
    c.close("adjoint(compose(x, y)) == adjoint(x) adjoint(y)", G.adjoint(G.compose(x, y)),
            ad_x @ ad_y, trailing=2, scale=magnitude(ad_x, 2) * magnitude(ad_y, 2),
            inputs={"x": x, "y": y})
    eye = torch.eye(k, dtype=c.dtype, device=c.device).expand_as(ad_x)
    ad_xi = G.adjoint(xi)
    c.close("adjoint(x) adjoint(inverse(x)) == I", ad_x @ ad_xi, eye, trailing=2,
            scale=magnitude(ad_x, 2) * magnitude(ad_xi, 2), inputs={"x": x})


def _flat_embedding(c: Case, x: torch.Tensor, z: torch.Tensor) -> None:
    """A group declaring ``embedding_is_flat`` embeds ``x`` as ``x`` flattened, exactly."""
    G = c.group
    numel = math.prod(G.element_shape)
    if G.embedding_dim != numel:
        c.fail(
            f"embedding_is_flat is True, but embedding_dim {G.embedding_dim} is not the "
            f"{numel} entries of an element of shape {tuple(G.element_shape)}; declare "
            f"embedding_is_flat = False, or embed as x flattened"
        )
    flat = x.reshape(*G.batch_shape(x), numel)
    differs = (z != flat).reshape(-1, numel).any(-1)
    if differs.any():
        first = int(differs.nonzero()[0, 0])
        index = torch.unravel_index(torch.tensor(first), c.batch_shape) if c.batch_shape else ()
        index = tuple(int(j) for j in index)
        c.fail(
            f"embedding_is_flat is True, but embed(x) is not x flattened row-major in "
            f"{int(differs.sum())} of {differs.numel()} element(s); the first at batch index "
            f"{index}: x = {format_tensor(flat.reshape(-1, numel)[first])}, "
            f"embed(x) = {format_tensor(z.reshape(-1, numel)[first])}"
        )


def _embedding_rejects(c: Case, data, z: torch.Tensor) -> None:
    """``from_embedding`` raises GroupMembershipError for NaN and (where the image is a proper
    submanifold, ``embedding_dim > tangent_dim``) for a random push off the group."""
    G = c.group
    bad = z.clone().reshape(-1, G.embedding_dim)
    bad[0, 0] = torch.nan
    off = {"NaN in the first element": bad.reshape(z.shape)}
    if G.embedding_dim > G.tangent_dim:
        gen = torch.Generator().manual_seed(c.seed(data, "push seed"))
        push = torch.randn(z.shape, generator=gen, dtype=torch.float64).to(z)
        off["a random push off the group"] = z + 0.5 * push * (1 + z.abs())
    for what, zb in off.items():
        try:
            G.from_embedding(zb)
        except GroupMembershipError:
            continue
        except Exception as err:  # noqa: BLE001 - the wrong exception type is the failure
            c.fail(
                f"from_embedding with {what} raised {type(err).__name__}, expected "
                f"GroupMembershipError: {err}"
            )
        c.fail(
            f"from_embedding accepted an embedding with {what}; expected GroupMembershipError "
            f"(membership_error {format_tensor(G.membership_error(G.unembed(zb)))})"
        )


def embedding(c: Case, data) -> None:
    """The embedding round trips, ``from_embedding`` rejects what is off the group, and a group
    declaring ``embedding_is_flat`` embeds an element as itself flattened."""
    G = c.group
    x = c.x(data, "x")
    z = G.embed(x)
    c.shape("embed(x)", z, (G.embedding_dim,))
    if G.embedding_is_flat:
        _flat_embedding(c, x, z)
    c.close_elements("unembed(embed(x)) == x", G.unembed(z), x, inputs={"x": x})
    try:
        back = G.from_embedding(z)
    except GroupMembershipError as err:
        c.fail(f"from_embedding(embed(x)) rejected an element of the group: {err}")
    c.close_elements("from_embedding(embed(x)) == x", back, x, inputs={"x": x})
    c.close("embed(unembed(embed(x))) == embed(x)", G.embed(G.unembed(z)), z, trailing=1)
    _embedding_rejects(c, data, z)


def rplus_rminus(c: Case, data) -> None:
    """``rplus``, ``between``, ``rminus`` and ``distance`` agree with compose, exp and log."""
    G = c.group
    x, y, v = c.x(data, "x"), c.x(data, "y"), c.v(data, "v")
    xi = G.inverse(x)
    sx = element_magnitude(G, x) * element_magnitude(G, xi)
    ins = {"x": x, "y": y}
    c.close_elements("rplus(x, v) == compose(x, exp(v))", G.rplus(x, v), G.compose(x, G.exp(v)),
                     scale=sx, inputs={"x": x, "v": v})
    c.close_elements("between(x, y) == compose(inverse(x), y)", G.between(x, y),
                     G.compose(xi, y), scale=sx, inputs=ins)
    d = G.rminus(y, x)
    c.close_elements("rplus(x, rminus(y, x)) == y", G.rplus(x, d), y,
            scale=sx * element_magnitude(G, y), inputs=ins)
    mask, tol = _log_exp_tolerance(c, v)
    got = torch.where(mask.unsqueeze(-1), G.rminus(G.rplus(x, v), x), v)
    c.close_tangent("rminus(rplus(x, v), x) == v (angles < pi - margin)", got, v, scale=sx,
                    tol=tol, inputs={"x": x, "v": v})
    dist = G.distance(x, y)
    c.shape("distance(x, y)", dist, ())
    c.within("distance(x, y) >= 0", -dist, 0.0, inputs=ins)
    c.close("distance(x, y) == |rminus(y, x)|", dist, torch.linalg.vector_norm(d, dim=-1),
            trailing=0, inputs=ins)


def _spread(v: torch.Tensor, radius: float = 0.1) -> torch.Tensor:
    """``v`` shrunk to norm at most ``radius``: elements ``x · exp(v)`` near ``x``, where the
    default four iterations of ``mean`` reach float64's precision (wider spreads need more)."""
    norm = torch.linalg.vector_norm(v, dim=-1, keepdim=True)
    return v * (radius / norm.clamp_min(radius))


def mean(c: Case, data) -> None:
    """``mean`` of three elements near ``x`` is their barycentre (``sum_i log(m^-1 x_i) == 0``),
    of three copies of ``x`` is ``x``, and is equivariant: ``mean(g x_i) == g mean(x_i)``."""
    G = c.group
    x, g = c.x(data, "x"), c.x(data, "g")
    xs = G.rplus(x.unsqueeze(0), torch.stack([_spread(c.v(data, f"v{i}")) for i in range(3)]))
    m = G.mean(xs, 0)
    c.shape("mean(x_i)", m, tuple(G.element_shape))
    sx = element_magnitude(G, x) * element_magnitude(G, G.inverse(x))
    ins = {"x": x}
    residual = G.rminus(xs, m.unsqueeze(0)).mean(0)
    c.close_tangent("mean(x_i) = m with sum_i log(m^-1 x_i) == 0", residual,
                    torch.zeros_like(residual), scale=sx, inputs=ins)
    c.close_elements("mean([x, x, x]) == x", G.mean(torch.stack([x, x, x]), 0), x, scale=sx,
                     inputs=ins)
    sg = element_magnitude(G, g) * element_magnitude(G, G.inverse(g)) * sx
    c.close_elements("mean(g x_i) == g mean(x_i)", G.mean(G.compose(g.unsqueeze(0), xs), 0),
                     G.compose(g, m), scale=sg, inputs={"x": x, "g": g})


def gradients_finite(c: Case, data) -> None:
    """No NaN/Inf in the gradients of ``exp``, ``log(exp(v))`` and ``embed(rplus(x, v))``."""
    G = c.group
    x = c.x(data, "x")
    v = c.v(data, "v")
    fns: dict[str, Callable[..., torch.Tensor]] = {
        "sum(exp(v))": lambda x_, v_: G.exp(v_).sum(),
        "sum(log(exp(v)))": lambda x_, v_: G.log(G.exp(v_)).sum(),
        "sum(embed(rplus(x, v)))": lambda x_, v_: G.embed(G.rplus(x_, v_)).sum(),
    }
    for name, fn in fns.items():
        xr = x.detach().clone().requires_grad_(True)
        vr = v.detach().clone().requires_grad_(True)
        gx, gv = torch.autograd.grad(fn(xr, vr), (xr, vr), allow_unused=True)
        for wrt, g in (("v", gv), ("x", gx)):
            if g is None:
                continue
            bad = ~torch.isfinite(g)
            if bad.any():
                first = tuple(int(i) for i in bad.nonzero()[0][: len(c.batch_shape)])
                c.fail(
                    f"the gradient of {name} with respect to {wrt} has {int(bad.sum())} "
                    f"non-finite entries; the first at batch index {first}: "
                    f"v = {format_tensor(v[first])}, x = {format_tensor(x[first])}, "
                    f"grad = {format_tensor(g[first])}"
                )
    c.result.worst_what = "all gradients finite"


def _generic_tangents(group: LieGroup, n: int, gen: torch.Generator) -> torch.Tensor:
    """``(n, tangent_dim)`` in float64: angles in [0.2, pi - 0.2], other coordinates ~1."""
    v = torch.randn(n, group.tangent_dim, generator=gen, dtype=torch.float64)
    for s in group.angle_slices:
        theta = 0.2 + (math.pi - 0.4) * torch.rand(n, 1, generator=gen, dtype=torch.float64)
        v[:, s] = v[:, s] / torch.linalg.vector_norm(v[:, s], dim=-1, keepdim=True) * theta
    return v


def gradcheck(c: Case, data) -> None:
    """``torch.autograd.gradcheck`` in float64 at generic points (skipped in other dtypes)."""
    G, bs = c.group, c.batch_shape
    if c.dtype != torch.float64:
        c.result.skipped = "gradcheck runs in float64 only"
        return
    gen = torch.Generator().manual_seed(1234)
    n = math.prod(bs)
    v = _generic_tangents(G, n, gen).reshape(*bs, G.tangent_dim).to(c.device)
    x = G.random(bs, generator=gen, dtype=torch.float64).to(c.device).requires_grad_(True)
    v.requires_grad_(True)
    checks = {
        "exp(v)": (lambda v_: G.exp(v_), (v,)),
        "log(exp(v))": (lambda v_: G.log(G.exp(v_)), (v,)),
        "embed(rplus(x, v))": (lambda x_, v_: G.embed(G.rplus(x_, v_)), (x, v)),
    }
    first = tuple(0 for _ in bs)
    for name, (fn, args) in checks.items():
        # the full Jacobian of one element, and a random projection (fast mode) of the batch
        runs = [(tuple(a[first].detach().requires_grad_(True) for a in args), False)]
        if n > 1:
            runs.append((args, True))
        for inputs, fast in runs:
            try:
                torch.autograd.gradcheck(fn, inputs, eps=1e-6, atol=1e-6, rtol=1e-5,
                                         fast_mode=fast)
            except torch.autograd.gradcheck.GradcheckError as err:
                c.fail(f"torch.autograd.gradcheck of {name} at v = "
                       f"{format_tensor(inputs[-1])}:\n{err}")
    c.result.worst_what = "gradcheck passed (eps 1e-6, atol 1e-6, rtol 1e-5)"


def batched_vs_looped(c: Case, data) -> None:
    """Batched operations equal the same operations applied element by element."""
    G, bs = c.group, c.batch_shape
    x, y, v = c.x(data, "x"), c.x(data, "y"), c.v(data, "v")
    # name -> (operation, number of trailing dimensions of its output; None: an element)
    ops: dict[str, tuple[Callable[..., torch.Tensor], int | None]] = {
        "compose(x, y)": (lambda x_, y_, v_: G.compose(x_, y_), None),
        "inverse(x)": (lambda x_, y_, v_: G.inverse(x_), None),
        "exp(v)": (lambda x_, y_, v_: G.exp(v_), None),
        "log(x)": (lambda x_, y_, v_: G.log(x_), 1),
        "rplus(x, v)": (lambda x_, y_, v_: G.rplus(x_, v_), None),
        "rminus(y, x)": (lambda x_, y_, v_: G.rminus(y_, x_), 1),
        "embed(x)": (lambda x_, y_, v_: G.embed(x_), 1),
        "adjoint(x)": (lambda x_, y_, v_: G.adjoint(x_), 2),
    }
    n = math.prod(bs)
    xs = x.reshape(n, *G.element_shape)
    ys = y.reshape(n, *G.element_shape)
    vs = v.reshape(n, G.tangent_dim)
    # every element of a drawn batch; 12 spread-out elements of the (large) grid
    idx = list(range(n)) if not c.grid else list(range(0, n, max(1, n // 12)))
    scale = element_magnitude(G, x) * element_magnitude(G, y) * magnitude(v, 1)
    scale = scale.reshape(n)[idx]
    for name, (fn, trailing) in ops.items():
        batched = fn(x, y, v)
        looped = torch.stack([fn(xs[i], ys[i], vs[i]) for i in idx])
        picked = batched.reshape(n, *batched.shape[len(bs):])[idx]
        close = c.close_elements if trailing is None else partial(c.close, trailing=trailing)
        close(f"batched {name} == per-element {name}", picked, looped, scale=scale,
              inputs={"x": xs[idx], "y": ys[idx], "v": vs[idx]})


def broadcasting(c: Case, data) -> None:
    """compose and rplus broadcast ``(3, 1)`` with ``(1, 2)``, and ``()`` with the batch."""
    G = c.group
    el = tuple(G.element_shape)
    x = c.x(data, "x (3, 1)", batch_shape=(3, 1))
    y = c.x(data, "y (1, 2)", batch_shape=(1, 2))
    v = c.v(data, "v (1, 2)", batch_shape=(1, 2))
    xe, ye, ve = x.expand(3, 2, *el), y.expand(3, 2, *el), v.expand(3, 2, G.tangent_dim)
    s = element_magnitude(G, xe) * element_magnitude(G, ye)
    out = G.compose(x, y)
    c.shape("compose(x (3, 1), y (1, 2))", out, el, batch=(3, 2))
    c.close_elements("compose broadcast (3, 1) x (1, 2)", out, G.compose(xe, ye), scale=s)
    out = G.rplus(x, v)
    c.shape("rplus(x (3, 1), v (1, 2))", out, el, batch=(3, 2))
    c.close_elements("rplus broadcast (3, 1) x (1, 2)", out, G.rplus(xe, ve),
            scale=s * magnitude(ve, 1))
    # an unbatched element against a batch of the case's shape
    x0, yb = c.x(data, "x ()", batch_shape=()), c.x(data, "y")
    out = G.compose(x0, yb)
    c.shape("compose(x (), y batch)", out, el)
    x0e = x0.expand(*c.batch_shape, *el)
    c.close_elements("compose broadcast () x batch", out, G.compose(x0e, yb),
            scale=element_magnitude(G, x0e) * element_magnitude(G, yb))


#: Every property, by name, in the order ``check_group`` runs them.
PROPERTIES: dict[str, Callable[[Case, object], None]] = {
    "membership": membership,
    "identity": identity,
    "inverse": inverse,
    "associativity": associativity,
    "exp_log": exp_log,
    "log_exp": log_exp,
    "matrix_exp": matrix_exp,
    "matrix_compose": matrix_compose,
    "adjoint": adjoint,
    "embedding": embedding,
    "rplus_rminus": rplus_rminus,
    "mean": mean,
    "gradients_finite": gradients_finite,
    "gradcheck": gradcheck,
    "batched_vs_looped": batched_vs_looped,
    "broadcasting": broadcasting,
}

#: Properties that draw nothing: they run once, at fixed generic points, not on the grid or on
#: hypothesis' examples.
DETERMINISTIC = frozenset({"gradcheck"})
