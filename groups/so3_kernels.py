"""SO(3)'s ``exp``, ``log``, ``rplus`` and ``rminus`` arithmetic, each with an analytic backward.

:class:`~groups.SO3` calls these. Each computes its value with the same operations whether or
not autograd records. When it records (grad mode on, an input that requires grad, no
``torch.func`` transform active) each runs as one :class:`torch.autograd.Function` node whose
forward records nothing and whose backward is a dozen batched operations, instead of the ~50
nodes autograd records through the formula: the observer's closed loop calls them every step of
every training rollout, and that backward was most of its time. ``rplus`` and ``rminus`` fuse
the group product with the exponential and the logarithm.

The backward is the derivative of the formula the forward evaluates, equal to autograd's
through that formula to rounding (``tests/test_group_kernels.py``):

* ``exp``: ``d/dv <G, R> = J_l(v) vee(R^T G)`` with ``vee(M) = (M21 - M12, M02 - M20, M10 - M01)``
  (``dR = R hat(J_r(v) dv)`` and ``J_r^T = J_l``); ``rplus(x, v) = x exp(v)`` adds
  ``d/dx = G exp(v)^T``;
* ``log``: the chain rule through Shepperd's quaternion (linear in the entries, the pivot fixed),
  the scale-free ``atan2`` ratio and its sign, so it also holds off the group (``gradcheck``);
  ``rminus(y, x) = log(x^T y)`` adds the product's.

A second derivative (``create_graph=True``) differentiates the formula itself (autograd through
it, as without the Functions), and so do ``torch.func`` transforms and forward-mode AD; there
the coefficients take their series below the threshold (``groups.numerics``): the same values to
an ulp.

Constant tables (the ``0/+-1`` tables, the identity) are built once per dtype and device and
cached, except while ``torch.compile`` / ``torch.export`` trace (then built in the graph).

Layout, for speed on the CPU: the batch is transposed into rows of length ``N`` once (by a
product with a table) and every elementwise kernel works on one contiguous row.
"""

from __future__ import annotations

import torch

from . import numerics as nx

__all__ = [
    "exp", "log", "rplus", "rminus", "rplus_values", "rplus_grads", "rminus_values",
    "rminus_grads", "records", "recorded_grad", "Inputs", "constant",
]

# R = I + terms^T @ _EXP_TABLE: each entry of R is a sum of at most two nonzero terms, so the
# product rounds it once, like the plain sum
_EXP_TABLE = (
    # R00 R01 R02 R10 R11 R12 R20 R21 R22
    (-1, 0, 0, 0, 0, 0, 0, 0, 0),  # c (t2 - x^2)
    (0, 0, 0, 0, -1, 0, 0, 0, 0),  # c (t2 - y^2)
    (0, 0, 0, 0, 0, 0, 0, 0, -1),  # c (t2 - z^2)
    (0, 1, 0, 1, 0, 0, 0, 0, 0),  # c x y
    (0, 0, 1, 0, 0, 0, 1, 0, 0),  # c x z
    (0, 0, 0, 0, 0, 1, 0, 1, 0),  # c y z
    (0, 0, 0, 0, 0, -1, 0, 1, 0),  # b x
    (0, 0, 1, 0, 0, 0, -1, 0, 0),  # b y
    (0, -1, 0, 1, 0, 0, 0, 0, 0),  # b z
)
# the ten distinct entries of the candidates 4 q_k q of Shepperd's method, affine in R
_QUAT_TABLE = (
    # m00 m01 m02 m10 m11 m12 m20 m21 m22
    (1, 0, 0, 0, 1, 0, 0, 0, 1),  # d0 - 1 = 4 w^2 - 1
    (1, 0, 0, 0, -1, 0, 0, 0, -1),  # d1 - 1 = 4 x^2 - 1
    (-1, 0, 0, 0, 1, 0, 0, 0, -1),  # d2 - 1 = 4 y^2 - 1
    (-1, 0, 0, 0, -1, 0, 0, 0, 1),  # d3 - 1 = 4 z^2 - 1
    (0, 0, 0, 0, 0, -1, 0, 1, 0),  # m21 - m12 = 4 w x
    (0, 0, 1, 0, 0, 0, -1, 0, 0),  # m02 - m20 = 4 w y
    (0, -1, 0, 1, 0, 0, 0, 0, 0),  # m10 - m01 = 4 w z
    (0, 1, 0, 1, 0, 0, 0, 0, 0),  # m10 + m01 = 4 x y
    (0, 0, 1, 0, 0, 0, 1, 0, 0),  # m02 + m20 = 4 x z
    (0, 0, 0, 0, 0, 1, 0, 1, 0),  # m21 + m12 = 4 y z
)
# the rows of _QUAT_TABLE that pivot k (w, x, y, z) picks for the components (w, x, y, z)
_PIVOT_ROWS = ((0, 4, 5, 6), (4, 1, 7, 8), (5, 7, 2, 9), (6, 8, 9, 3))
# vee(M) = (M21 - M12, M02 - M20, M10 - M01) of a row-major (N, 9) M, as a (9, 3) table
_VEE = ((0, 0, 0), (0, 0, -1), (0, 1, 0), (0, 0, 1), (0, 0, 0), (-1, 0, 0), (0, -1, 0), (1, 0, 0),
        (0, 0, 0))  # fmt: skip


_BUILDERS = {
    "eye": lambda: torch.eye(3, dtype=torch.float64),
    "eye9": lambda: torch.eye(3, dtype=torch.float64).flatten(),
    "two": lambda: 2.0 * torch.eye(3, dtype=torch.float64),
    "exp_table": lambda: torch.tensor(_EXP_TABLE, dtype=torch.float64),
    "quat_table": lambda: torch.tensor(_QUAT_TABLE, dtype=torch.float64),
    "quat_one": lambda: torch.tensor([[1.0]] * 4 + [[0.0]] * 6, dtype=torch.float64),
    "quat_table_t": lambda: torch.tensor(_QUAT_TABLE, dtype=torch.float64).t().contiguous(),
    "vee": lambda: torch.tensor(_VEE, dtype=torch.float64),
    "pivot_rows": lambda: torch.tensor(_PIVOT_ROWS, dtype=torch.int64),
}


def constant(name: str, like: torch.Tensor) -> torch.Tensor:
    """The table ``name`` in ``like``'s dtype (int64 for an index table) and device, cached
    (:func:`groups.numerics.cached_constant`)."""
    dtype = torch.int64 if name == "pivot_rows" else like.dtype
    return nx.cached_constant("so3." + name, _BUILDERS[name], like, dtype)


def records(*ts: torch.Tensor) -> bool:
    """Whether to run the Function: autograd records (grad mode, an input that requires grad)
    and no ``torch.func`` transform is active (those differentiate the formula itself)."""
    return (
        torch.is_grad_enabled()
        and any(t.requires_grad for t in ts)
        and not torch._C._are_functorch_transforms_active()
    )


class Inputs:
    """A Function's inputs kept for a second derivative only (:func:`recorded_grad`), with their
    versions: the first-order backward saves just what it reads (as autograd through the formula
    would), so an input modified in place afterwards is refused only if a second derivative
    needs it, with autograd's own message."""

    def __init__(self, *tensors: torch.Tensor):
        self.tensors = tensors
        # not while torch.compile traces (its backward has no second derivative)
        self.versions = None if torch.compiler.is_compiling() else [t._version for t in tensors]

    def get(self) -> tuple[torch.Tensor, ...]:
        for t, version in zip(self.tensors, self.versions or ()):
            if t._version != version:
                raise RuntimeError(
                    "one of the variables needed for gradient computation has been modified by "
                    f"an inplace operation: {tuple(t.shape)} at version {t._version}; expected "
                    f"version {version} instead (a second derivative of groups.so3_kernels)."
                )
        return self.tensors


def recorded_grad(formula, inputs, needs, grad):
    """The vector-Jacobian product of ``formula(*inputs)`` by autograd through the formula, with
    ``create_graph``: a Function's backward when a second derivative is asked for. ``inputs``:
    the tensors or an :class:`Inputs`."""
    if isinstance(inputs, Inputs):
        inputs = inputs.get()
    with torch.enable_grad():
        # aliases: the partial derivatives of this formula only (one input may depend on
        # another elsewhere in the graph, as the observer's v on its x), still functions of
        # the inputs for the next derivative
        inputs = [t.view_as(t) for t in inputs]
        wrt = [t for t, n in zip(inputs, needs) if n]
        got = iter(torch.autograd.grad(formula(*inputs), wrt, grad, create_graph=True))
    return tuple(next(got) if n else None for n in needs)


# ------------------------------------------------------------------------------------ exp


def _exp_rows(v: torch.Tensor, derivative: bool = False):
    """``exp(v)`` ``(*batch, 3, 3)`` for ``v`` ``(*batch, 3)`` and (``derivative``) what its
    derivative reads, ``(over, coef)``: where the angle overflowed ``(N, 1)`` and
    ``coef = (b, c, (1 - b) / t2)`` ``(3, N)``,
    ``b = sin(t) / t``, ``c = (1 - cos t) / t^2``; else ``None``.

    A finite angle whose square overflows (``|v| >= sqrt(finfo.max)``) is taken as a whole number
    of turns: its rotation is the identity (``SO3.exp``).
    """
    eye = constant("eye", v)
    w = torch.mm(eye, v.reshape(-1, 3).t())  # (3, N): rows x, y, z (a transposing copy)
    x, y, z = w.unbind(0)
    sq = w * w
    t2 = sq.sum(0)
    b = nx.sin_over_t(t2)
    c = nx.one_minus_cos_over_t2(t2)
    cx, cy = c * x, c * y
    # (9, N), the rows of the table in order; t2 - v_i^2 = v_j^2 + v_k^2
    terms = torch.cat(((t2 - sq) * c, torch.stack((cx * y, cx * z, cy * z)), b * w))
    over = torch.isinf(t2)  # the terms are NaN there: zero, so that R = I
    terms = terms.masked_fill_(over, 0.0)
    r = torch.addmm(constant("eye9", v), terms.t(), constant("exp_table", v))
    r = r.reshape(*v.shape[:-1], 3, 3)
    if not derivative:
        return r, None
    # (1 - b) / t2 = (t - sin t) / t^3 loses digits to cancellation at small t, but it multiplies
    # (v . a) v, of size t^2 |a|: the product keeps an absolute error of a few eps |a|
    d = (1.0 - b) / t2.clamp(min=torch.finfo(t2.dtype).tiny)
    return r, (over.unsqueeze(-1), torch.stack((b, c, d)))


def _exp_grad(v, r, over, coef, g):
    """``d/dv <G, exp(v)> = J_l(v) vee(R^T G)``, ``J_l(v) a = b a + c (v x a) + (1 - b) / t2
    (v . a) v``; zero where the angle overflowed (the identity is constant there)."""
    v, r, g2 = v.reshape(-1, 3), r.reshape(-1, 3, 3), g.reshape(-1, 3, 3)
    a = torch.mm(torch.bmm(r.transpose(1, 2), g2).reshape(-1, 9), constant("vee", g))
    b, c, d = coef.unsqueeze(-1).unbind(0)
    out = torch.addcmul(b * a, c, torch.linalg.cross(v, a))
    out = torch.addcmul(out, d * (v * a).sum(-1, keepdim=True), v)
    return torch.where(over, 0.0, out).reshape(g.shape[:-2] + (3,))


class _Exp(torch.autograd.Function):
    @staticmethod
    def forward(ctx, v):
        r, (over, coef) = _exp_rows(v, derivative=True)
        ctx.inputs = Inputs(v)
        ctx.save_for_backward(v, r, over, coef)
        return r

    @staticmethod
    def backward(ctx, grad):
        if torch.is_grad_enabled():  # create_graph
            return recorded_grad(lambda v_: _exp_rows(v_)[0], ctx.inputs, (True,), grad)
        return _exp_grad(*ctx.saved_tensors, grad)


def exp(v: torch.Tensor) -> torch.Tensor:
    """``(*batch, 3) -> (*batch, 3, 3)``, Rodrigues' formula (``SO3.exp``'s docstring)."""
    if records(v):
        return _Exp.apply(v)
    return _exp_rows(v)[0]


def _rplus_formula(x, v):
    return torch.matmul(x, _exp_rows(v)[0])


def rplus_values(x: torch.Tensor, v: torch.Tensor) -> tuple[torch.Tensor, tuple]:
    """``(x exp(v), saved)``: the value and what :func:`rplus_grads` reads (no graph)."""
    e, (over, coef) = _exp_rows(v, derivative=True)
    out = torch.matmul(x, e)
    return out, (out, e, over, coef)


def rplus_grads(v: torch.Tensor, saved: tuple, grad: torch.Tensor, needs=(True, True)):
    """``(d/dx, d/dv) <G, x exp(v)>``: ``G E^T`` and ``J_l(v) vee((x E)^T G)``."""
    out, e, over, coef = saved
    gx = torch.matmul(grad, e.transpose(-1, -2)) if needs[0] else None
    gv = _exp_grad(v, out, over, coef, grad) if needs[1] else None
    return gx, gv


class _Rplus(torch.autograd.Function):
    @staticmethod
    def forward(ctx, x, v):
        out, (_, e, over, coef) = rplus_values(x, v)
        ctx.inputs = Inputs(x, v)
        ctx.save_for_backward(v, out, e, over, coef)
        return out

    @staticmethod
    def backward(ctx, grad):
        if torch.is_grad_enabled():  # create_graph
            return recorded_grad(_rplus_formula, ctx.inputs, ctx.needs_input_grad, grad)
        v, *saved = ctx.saved_tensors
        return rplus_grads(v, saved, grad, ctx.needs_input_grad)


def rplus(x: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """``x exp(v)`` for ``x`` ``(*batch, 3, 3)``, ``v`` ``(*batch, 3)`` of one batch shape."""
    if records(x, v):
        return _Rplus.apply(x, v)
    return _rplus_formula(x, v)


# ------------------------------------------------------------------------------------ log


def _log_parts(r: torch.Tensor, derivative: bool = False):
    """The logarithm of ``r`` ``(*batch, 3, 3)``, ``(*batch, 3)``, and (``derivative``) what
    its derivative reads, ``(rows, q, coef)``, else ``None``: the rows of the candidate table
    the pivot picked ``(4, N)``, the candidate quaternion ``q = (w, x, y, z)`` ``(4, N)`` and
    ``coef = (k2, e, h)`` ``(3, N)``, with ``d out_j = k2 dq_j + q_j (e d + h dw)``,
    ``d = <q_xyz, dq_xyz>``, ``j = x, y, z``.
    """
    f = torch.addmm(constant("quat_one", r), constant("quat_table", r), r.reshape(-1, 9).t())
    # the candidate of the largest pivot 4 q_k^2 (the first on ties): no square root of a small
    # number is taken, and the gradient is finite
    p0, p1, p2, p3 = f[:4].detach().unbind(0)  # (argmax over the rows is slow on the CPU)
    hi = torch.maximum(p2, p3) > torch.maximum(p0, p1)
    pivot = torch.where(hi, (p3 > p2) + 2, (p1 > p0).long())  # the first of the largest
    rows = constant("pivot_rows", r)[pivot].t()  # (4, N)
    q = f.gather(0, rows)
    qw, qx, qy, qz = q.unbind(0)
    qv = q[1:]
    s2 = torch.addcmul(torch.addcmul(qx * qx, qy, qy), qz, qz)
    cw = qw.abs()
    k = nx.atan2_over_s(s2, cw)
    # copysign(k, qw) for k > 0, written with ops that export to ONNX (copysign lowers to
    # signbit, which has none): 1 / qw keeps the sign bit of qw, -0.0 included (-inf).
    neg = torch.reciprocal(qw.detach()) < 0
    ks = torch.where(neg, -k, k)
    out = torch.mm((ks * qv).t(), constant("two", r)).reshape(*r.shape[:-2], 3)
    if not derivative:
        return out, None
    # d k / d s2 and d k / d|w| of k = atan2(s, c) / s: (c / (s2 + c^2) - k) / (2 s2) loses
    # digits to cancellation at small s, but it multiplies q_xyz <q_xyz, g>, of size s^2 |g|:
    # the product keeps an absolute error of a few eps |g|
    recip = torch.reciprocal(s2 + cw * cw)
    k_s2 = (cw * recip - k) / (2.0 * s2.clamp(min=torch.finfo(s2.dtype).tiny))
    sigma = torch.where(neg, -4.0, 4.0)
    # abs' derivative at w = 0 is 0 (autograd's sgn)
    coef = torch.stack((2.0 * ks, sigma * k_s2, -2.0 * recip * torch.sign(qw).abs()))
    return out, (rows, q, coef)


def _log_grad(r_shape, rows, q, coef, grad):
    """``d/dr <g, log(r)>``: the chain rule back to ``q``, scattered to the candidate table's
    rows the pivot picked, then through the table to the entries of ``r``."""
    g = grad.reshape(-1, 3).t()  # (3, N)
    k2, e, h = coef.unbind(0)
    qv = q[1:]
    d = (g * qv).sum(0)
    gq = torch.cat(((h * d).unsqueeze(0), torch.addcmul(k2 * g, qv, e * d)))  # (4, N)
    gf = torch.zeros(10, gq.shape[1], dtype=gq.dtype, device=gq.device).scatter_(0, rows, gq)
    return torch.mm(constant("quat_table_t", grad), gf).t().reshape(r_shape)


class _Log(torch.autograd.Function):
    @staticmethod
    def forward(ctx, r):
        out, saved = _log_parts(r, derivative=True)
        ctx.inputs, ctx.shape = Inputs(r), r.shape
        ctx.save_for_backward(*saved)
        return out

    @staticmethod
    def backward(ctx, grad):
        if torch.is_grad_enabled():  # create_graph
            return recorded_grad(lambda r_: _log_parts(r_)[0], ctx.inputs, (True,), grad)
        return _log_grad(ctx.shape, *ctx.saved_tensors, grad)


def log(r: torch.Tensor) -> torch.Tensor:
    """``(*batch, 3, 3) -> (*batch, 3)`` through Shepperd's quaternion (``SO3.log``'s docstring)."""
    if records(r):
        return _Log.apply(r)
    return _log_parts(r)[0]


def _rminus_formula(y, x):
    return _log_parts(torch.matmul(x.transpose(-1, -2), y))[0]


def rminus_values(y: torch.Tensor, x: torch.Tensor) -> tuple[torch.Tensor, tuple]:
    """``(log(x^T y), saved)``: the value and what :func:`rminus_grads` reads (no graph)."""
    out, saved = _log_parts(torch.matmul(x.transpose(-1, -2), y), derivative=True)
    return out, saved


def rminus_grads(y: torch.Tensor, x: torch.Tensor, saved: tuple, grad: torch.Tensor,
                 needs=(True, True)):
    """``(d/dy, d/dx) <g, log(x^T y)>``: ``x G_D`` and ``y G_D^T``, ``G_D`` the logarithm's."""
    gd = _log_grad(grad.shape[:-1] + (3, 3), *saved, grad)
    gy = torch.matmul(x, gd) if needs[0] else None
    gx = torch.matmul(y, gd.transpose(-1, -2)) if needs[1] else None
    return gy, gx


class _Rminus(torch.autograd.Function):
    @staticmethod
    def forward(ctx, y, x):
        out, saved = rminus_values(y, x)
        ctx.inputs = Inputs(y, x)
        need_y, need_x = ctx.needs_input_grad
        # what the products' backward reads, as autograd would save it: x for y's, y for x's
        ctx.save_for_backward(y if need_x else None, x if need_y else None, *saved)
        return out

    @staticmethod
    def backward(ctx, grad):
        if torch.is_grad_enabled():  # create_graph
            return recorded_grad(_rminus_formula, ctx.inputs, ctx.needs_input_grad, grad)
        y, x, *saved = ctx.saved_tensors
        return rminus_grads(y, x, saved, grad, ctx.needs_input_grad)


def rminus(y: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
    """``log(x^T y)`` for ``y``, ``x`` ``(*batch, 3, 3)`` of one batch shape."""
    if records(y, x):
        return _Rminus.apply(y, x)
    return _rminus_formula(y, x)
