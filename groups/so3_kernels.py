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
    "rminus_grads", "rplus_parts", "rminus_parts", "exp_coefficients", "log_coefficients",
    "records", "recorded_grad", "Inputs", "constant",
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
    "four": lambda: torch.tensor(4.0, dtype=torch.float64),
    "minus_four": lambda: torch.tensor(-4.0, dtype=torch.float64),
    # the rows of pivot k as a column (4, 1)
    **{f"pivot_rows{k}": (lambda k=k: torch.tensor(_PIVOT_ROWS[k], dtype=torch.int64)[:, None])
       for k in range(4)},
}


class _Tables(dict):
    """The tables in one dtype and device by name, each made by :func:`constant` when first
    read: one lookup per kernel call instead of one per table."""

    def __init__(self, like: torch.Tensor, keep: bool):
        super().__init__()
        self.like, self.keep = like, keep

    def __missing__(self, name: str) -> torch.Tensor:
        table = constant(name, self.like)
        if self.keep:
            self[name] = table
        return table


_TABLES: dict[tuple, _Tables] = {}


def _tables(like: torch.Tensor) -> _Tables:
    """The tables in ``like``'s dtype and device (made afresh, uncached, where :func:`constant`
    makes them afresh: while ``torch.compile`` traces, for a tensor subclass)."""
    if torch.compiler.is_compiling() or type(like) is not torch.Tensor:
        return _Tables(like, keep=False)
    key = (like.dtype, like.device)
    tables = _TABLES.get(key)
    if tables is None:
        with torch.inference_mode(False), torch.no_grad():  # like constant's own tables
            tables = _TABLES[key] = _Tables(torch.empty(0, dtype=like.dtype, device=like.device),
                                            keep=True)
    return tables


def constant(name: str, like: torch.Tensor) -> torch.Tensor:
    """The table ``name`` in ``like``'s dtype (int64 for an index table) and device, cached
    (:func:`groups.numerics.cached_constant`)."""
    dtype = torch.int64 if name.startswith("pivot_rows") else like.dtype
    return nx.cached_constant("so3." + name, _BUILDERS[name], like, dtype)


def _matmul(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """``a @ b`` of one batch shape; ``bmm`` for a batch of one dimension (the observer's):
    ``matmul`` calls the same ``bmm`` on the same strides after four more operations."""
    return torch.bmm(a, b) if a.dim() == 3 and b.dim() == 3 else torch.matmul(a, b)


def _values(t: torch.Tensor) -> torch.Tensor:
    """``t`` without its graph, for a comparison (no operation when nothing records)."""
    return t.detach() if t.requires_grad else t


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
    needs it, with autograd's own message. The context holds them as plain attributes: a caller
    that writes in place into a tensor after handing a view of it to one of these Functions
    makes a reference cycle through the C++ graph that no garbage collector frees (assemble the
    result out of place instead; ``tests/test_graph_release.py``)."""

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


def _rodrigues(t2: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """``(nx.sin_over_t(t2), nx.one_minus_cos_over_t2(t2))``; when nothing records, their closed
    forms with the clamp of ``t2`` and its square root shared (the same operations, two fewer;
    ``tests/test_observer_lean.py`` holds them equal)."""
    if nx.records(t2):
        return nx.sin_over_t(t2), nx.one_minus_cos_over_t2(t2)
    t2 = torch.clamp_min(t2, torch.finfo(t2.dtype).eps ** 2)  # nx._away_from_zero
    t = t2.sqrt()
    s = torch.sin(0.5 * t)
    return torch.sin(t) / t, 2.0 * s * s / t2


def _exp_rows(v: torch.Tensor, derivative: bool = False):
    """``exp(v)`` ``(*batch, 3, 3)`` for ``v`` ``(*batch, 3)`` and (``derivative``) what the
    coefficients of its derivative are made from, ``(t2, b, c, over)`` ``(N,)`` each
    (:func:`exp_coefficients`), ``b = sin(t) / t``, ``c = (1 - cos t) / t^2``, ``over`` where
    the angle overflowed; else ``None``.

    A finite angle whose square overflows (``|v| >= sqrt(finfo.max)``) is taken as a whole number
    of turns: its rotation is the identity (``SO3.exp``).
    """
    tab = _tables(v)
    w = torch.mm(tab["eye"], (v if v.dim() == 2 else v.reshape(-1, 3)).t())  # (3, N): rows x, y, z
    x, y, z = w.unbind(0)  # (the product is a transposing copy)
    sq = w * w
    t2 = sq.sum(0)
    b, c = _rodrigues(t2)
    cx, cy = c * x, c * y
    # (9, N), the rows of the table in order, as one product: (t2 - v_i^2) c (t2 - v_i^2 =
    # v_j^2 + v_k^2), (c x) y, (c x) z, (c y) z, b v
    terms = torch.cat((t2 - sq, torch.stack((cx, cx, cy)), w))
    terms = terms * torch.stack((c, c, c, y, z, z, b, b, b))
    over = torch.isinf(t2)  # the terms are NaN there: zero, so that R = I
    terms = terms.masked_fill_(over, 0.0)
    r = torch.addmm(tab["eye9"], terms.t(), tab["exp_table"])
    r = r.reshape(*v.shape[:-1], 3, 3)
    return r, ((t2, b, c, over) if derivative else None)


def exp_coefficients(t2, b, c, over):
    """What :func:`_exp_grad` reads, ``(over (..., 1), coef = (b, c, (1 - b) / t2) (..., 3))``,
    from :func:`_exp_rows`' ``(t2, b, c, over)`` of any one shape (elementwise: one call for
    many steps' gives each step's values)."""
    # (1 - b) / t2 = (t - sin t) / t^3 loses digits to cancellation at small t, but it multiplies
    # (v . a) v, of size t^2 |a|: the product keeps an absolute error of a few eps |a|
    d = (1.0 - b) / torch.clamp_min(t2, torch.finfo(t2.dtype).tiny)
    return over.unsqueeze(-1), torch.stack((b, c, d), dim=-1)


def _exp_grad(v, r, over, coef, g):
    """``d/dv <G, exp(v)> = J_l(v) vee(R^T G)``, ``J_l(v) a = b a + c (v x a) + (1 - b) / t2
    (v . a) v``; zero where the angle overflowed (the identity is constant there)."""
    flat = g.dim() == 3  # a batch of one dimension: no reshape
    v, r, g2 = (v, r, g) if flat else (v.reshape(-1, 3), r.reshape(-1, 3, 3), g.reshape(-1, 3, 3))
    a = torch.mm(torch.bmm(r.transpose(1, 2), g2).reshape(-1, 9), _tables(g)["vee"])
    b, c, d = coef.split_with_sizes((1, 1, 1), dim=1)  # (N, 1) each (split is Python)
    out = torch.addcmul(b * a, c, torch.linalg.cross(v, a))
    out = torch.addcmul(out, d * (v * a).sum(-1, keepdim=True), v)
    out = out.masked_fill_(over, 0.0)
    return out if flat else out.reshape(g.shape[:-2] + (3,))


class _Exp(torch.autograd.Function):
    @staticmethod
    def forward(ctx, v):
        r, raw = _exp_rows(v, derivative=True)
        over, coef = exp_coefficients(*raw)
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


def rplus_parts(x: torch.Tensor, v: torch.Tensor) -> tuple:
    """``(x exp(v), exp(v), raw)``, ``raw`` what :func:`exp_coefficients` reads (no graph)."""
    e, raw = _exp_rows(v, derivative=True)
    return _matmul(x, e), e, raw


def rplus_values(x: torch.Tensor, v: torch.Tensor) -> tuple[torch.Tensor, tuple]:
    """``(x exp(v), saved)``: the value and what :func:`rplus_grads` reads (no graph)."""
    out, e, raw = rplus_parts(x, v)
    return out, (out, e, *exp_coefficients(*raw))


def rplus_grads(v: torch.Tensor, saved: tuple, grad: torch.Tensor, needs=(True, True)):
    """``(d/dx, d/dv) <G, x exp(v)>``: ``G E^T`` and ``J_l(v) vee((x E)^T G)``."""
    out, e, over, coef = saved
    gx = _matmul(grad, e.transpose(-1, -2)) if needs[0] else None
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
    its derivative reads, ``(rows, qv, k2, e, h)``, else ``None``: the rows of the candidate
    table the pivot picked ``(4, N)``, the vector part ``qv = (x, y, z)`` ``(3, N)`` of the
    candidate quaternion ``q = (w, x, y, z)`` and ``k2, e, h`` ``(N,)``, with
    ``d out_j = k2 dq_j + q_j (e d + h dw)``, ``d = <q_xyz, dq_xyz>``, ``j = x, y, z``.
    """
    out, rows, qv, raw = _log_terms(r)
    return out, ((rows, qv, *log_coefficients(*raw)) if derivative else None)


def _log_terms(r: torch.Tensor):
    """:func:`_log_parts`' ``(out, rows, qv, raw)``, ``raw`` what :func:`log_coefficients`
    makes ``k2, e, h`` from."""
    tab = _tables(r)
    f = torch.addmm(tab["quat_one"], tab["quat_table"], r.reshape(-1, 9).t())
    # the candidate of the largest pivot 4 q_k^2 (the first on ties): no square root of a small
    # number is taken, and the gradient is finite
    p0, p1, p2, p3 = _values(f).unbind(0)[:4]  # (argmax over the rows is slow on the CPU)
    hi = torch.maximum(p2, p3) > torch.maximum(p0, p1)
    rows = torch.where(  # (4, N), the rows of the first of the largest
        hi,
        torch.where(p3 > p2, tab["pivot_rows3"], tab["pivot_rows2"]),
        torch.where(p1 > p0, tab["pivot_rows1"], tab["pivot_rows0"]),
    )
    q = f.gather(0, rows)
    qw, qx, qy, qz = q.unbind(0)
    qv = q[1:]
    s2 = torch.addcmul(torch.addcmul(qx * qx, qy, qy), qz, qz)
    cw = qw.abs()
    if nx.records(s2):  # (cw derives from the same q)
        k = nx.atan2_over_s(s2, cw)
    else:  # its closed form, as it computes it when nothing records
        s = torch.clamp_min(s2, torch.finfo(s2.dtype).eps ** 2).sqrt()
        k = torch.atan2(s, cw) / s
    # copysign(k, qw) for k > 0, written with ops that export to ONNX (copysign lowers to
    # signbit, which has none): 1 / qw keeps the sign bit of qw, -0.0 included (-inf).
    neg = torch.reciprocal(_values(qw)) < 0
    ks = torch.where(neg, -k, k)
    out = torch.mm((ks * qv).t(), tab["two"]).reshape(*r.shape[:-2], 3)
    return out, rows, qv, (s2, cw, k, ks, neg, qw)


def log_coefficients(s2, cw, k, ks, neg, qw):
    """``(k2, e, h)`` of :func:`_log_parts` from :func:`_log_terms`' ``raw``, of any one shape
    (elementwise: one call for many steps' gives each step's values)."""
    # d k / d s2 and d k / d|w| of k = atan2(s, c) / s: (c / (s2 + c^2) - k) / (2 s2) loses
    # digits to cancellation at small s, but it multiplies q_xyz <q_xyz, g>, of size s^2 |g|:
    # the product keeps an absolute error of a few eps |g|
    tab = _tables(s2)
    recip = torch.reciprocal(s2 + cw * cw)
    k_s2 = (cw * recip - k) / (2.0 * torch.clamp_min(s2, torch.finfo(s2.dtype).tiny))
    e = torch.where(neg, tab["minus_four"], tab["four"]) * k_s2
    # abs' derivative at w = 0 is 0 (autograd's sgn)
    return 2.0 * ks, e, -2.0 * recip * torch.sign(qw).abs()


def _log_grad(r_shape, rows, qv, k2, e, h, grad):
    """``d/dr <g, log(r)>``: the chain rule back to ``q``, scattered to the candidate table's
    rows the pivot picked, then through the table to the entries of ``r``."""
    return _log_grad_rows(rows, qv, k2, e, h, grad).t().reshape(r_shape)


def _log_grad_rows(rows, qv, k2, e, h, grad):
    """:func:`_log_grad` as ``(9, N)``, row ``3 i + j`` the derivative by ``r_ij``."""
    g = (grad if grad.dim() == 2 else grad.reshape(-1, 3)).t()  # (3, N)
    d = (g * qv).sum(0)
    gq = torch.cat(((h * d).unsqueeze(0), torch.addcmul(k2 * g, qv, e * d)))  # (4, N)
    gf = torch.zeros(10, gq.shape[1], dtype=gq.dtype, device=gq.device).scatter_(0, rows, gq)
    return torch.mm(_tables(grad)["quat_table_t"], gf)


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


def rminus_parts(y: torch.Tensor, x: torch.Tensor) -> tuple:
    """``(log(x^T y), (rows, qv), raw)``: :func:`rminus_values` with ``raw`` what
    :func:`log_coefficients` makes the rest of its ``saved`` from (no graph)."""
    out, rows, qv, raw = _log_terms(_matmul(x.transpose(-1, -2), y))
    return out, (rows, qv), raw


def rminus_values(y: torch.Tensor, x: torch.Tensor) -> tuple[torch.Tensor, tuple]:
    """``(log(x^T y), saved)``: the value and what :func:`rminus_grads` reads (no graph)."""
    out, saved = _log_parts(_matmul(x.transpose(-1, -2), y), derivative=True)
    return out, saved


def rminus_grads(y: torch.Tensor, x: torch.Tensor, saved: tuple, grad: torch.Tensor,
                 needs=(True, True)):
    """``(d/dy, d/dx) <g, log(x^T y)>``: ``x G_D`` and ``y G_D^T``, ``G_D`` the logarithm's."""
    if grad.dim() == 2:  # a batch of one dimension: G_D and G_D^T as views of the rows
        rows = _log_grad_rows(*saved, grad).view(3, 3, -1)
        gy = torch.bmm(x, rows.permute(2, 0, 1)) if needs[0] else None
        gx = torch.bmm(y, rows.permute(2, 1, 0)) if needs[1] else None
        return gy, gx
    gd = _log_grad(grad.shape[:-1] + (3, 3), *saved, grad)
    gy = _matmul(x, gd) if needs[0] else None
    gx = _matmul(y, gd.transpose(-1, -2)) if needs[1] else None
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
