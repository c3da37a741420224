"""The step's group arithmetic as one autograd node each, for states whose factors are SO(3) and
R^n (the rigid body's SO(3) x R^3 x R^3 x R^3).

The generic update (:class:`~manifold_nets.observer.update.GroupUpdate`) and innovations
(:meth:`~manifold_nets.observer.measurement.Measurement.innovations`) slice the flat state into
its factors, move each and concatenate: a dozen small autograd nodes a step (slices, views, one
per factor, the concatenation), each a kernel launch forward and backward. Here the same
operations run inside one :class:`torch.autograd.Function` each (the values bitwise those of the
generic path), and the backward is each factor's analytic one
(:func:`groups.so3_kernels.rplus_grads`, :func:`~groups.so3_kernels.rminus_grads`; R^n's is a
slice). Used while autograd records (``groups.so3_kernels.records``); a second derivative goes
through the generic path.

:func:`fused_features` goes one node further for the paper's embedding and readings with the
innovation feature (``experiment=default``): the core's input ``cat(x, (y, u), nu)`` and the
innovations in one node, in place of the innovations', the embedding's cast and the
concatenation (:class:`~manifold_nets.observer.measurement.DeferredView`). Each node hands
autograd its gradients in the order the nodes it replaces did, so that the sums autograd forms
from them round alike: the losses, gradients and trained weights are those of the generic
features to the last bit (``tests/test_observer_lean.py``).
"""

from __future__ import annotations

import math

import torch

from groups import SO3, Euclidean
from groups import so3_kernels as so3k

__all__ = [
    "fusable_update", "fusable_innovations", "fused_update", "fused_innovations",
    "fused_features", "gradient_layout", "cast",
]


def fusable_update(update) -> bool:
    """Whether a bound update's blocks are R^n runs and residual SO(3) factors (one at least)."""
    blocks = update.blocks
    return any(b.factor is not None for b in blocks) and all(
        b.factor is None or (type(b.factor) is SO3 and b.rule == "residual") for b in blocks
    )


def fusable_innovations(measurement) -> bool:
    """Whether a bound measurement measures SO(3) factors (one at least) and R^n factors only."""
    kinds = [type(f) for f, _, _ in measurement.spans]
    return SO3 in kinds and all(k in (SO3, Euclidean) for k in kinds)


_CASTS = {torch.float32: torch.Tensor.float, torch.float64: torch.Tensor.double}


def cast(t: torch.Tensor, dtype: torch.dtype) -> torch.Tensor:
    """``t.to(dtype)`` through the dtype's own method where it has one (the same operation and
    autograd node; ``to``'s overloads take three times its Python time to parse)."""
    method = _CASTS.get(dtype)
    return t.to(dtype) if method is None else method(t)


class _Update(torch.autograd.Function):
    @staticmethod
    def forward(ctx, x, v_net, update):
        v = cast(v_net, x.dtype)  # the cast folded in: one node fewer
        parts, saved = [], []
        for b in update.blocks:
            vf = v[:, b.tangent]
            if b.factor is None:
                parts.append(vf if b.rule == "absolute" else torch.add(x[:, b.element], vf))
            else:  # (view: unflatten's operation, without its Python)
                out, keep = so3k.rplus_values(x[:, b.element].view(-1, 3, 3), vf)
                parts.append(out.flatten(-2))
                saved.extend((vf, *keep))  # the factor's v: no slice in the backward
        ctx.update, ctx.inputs, ctx.dtype = update, so3k.Inputs(x, v_net), v_net.dtype
        ctx.save_for_backward(*saved)
        return torch.cat(parts, dim=-1)

    @staticmethod
    def backward(ctx, grad):
        update, needs = ctx.update, ctx.needs_input_grad[:2]
        if torch.is_grad_enabled():  # create_graph: the generic path, differentiated
            generic = lambda x_, v_: update.generic(x_, v_.to(x_.dtype))  # noqa: E731
            return (*so3k.recorded_grad(generic, ctx.inputs, needs, grad), None)
        saved = ctx.saved_tensors
        gx, gv, at = [], [], 0
        for b in update.blocks:
            g = grad[:, b.element]
            if b.factor is None:
                gx.append(torch.zeros_like(g) if b.rule == "absolute" else g)
                gv.append(g)
            else:
                gxf, gvf = so3k.rplus_grads(saved[at], saved[at + 1 : at + 5], g.view(-1, 3, 3))
                gx.append(gxf.flatten(-2))
                gv.append(gvf)
                at += 5
        return torch.cat(gx, dim=-1), cast(torch.cat(gv, dim=-1), ctx.dtype), None


# Function.apply less its torch.func handling (unwrapping dead functorch wrappers, a pytree map
# of the arguments): the callers run the Functions only where no transform is active
# (groups.so3_kernels.records); torch.compile traces Function.apply itself
_update_apply = super(torch.autograd.Function, _Update).apply


def fused_update(update, x: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """``update(x, v)`` (a fusable :class:`GroupUpdate`; ``v`` in any dtype, cast to the
    state's) as one autograd node."""
    if torch.compiler.is_compiling():
        return _Update.apply(x, v, update)
    return _update_apply(x, v, update)


def gradient_layout(measurement) -> tuple:
    """How the innovations' gradient in the flat state is put together (at ``bind``): its
    columns in order, ``i`` for the ``i``-th measured factor's and ``-width`` for a run the
    innovations do not read (one ``cat``; not a zero tensor written into slice by slice)."""
    out, at = [], 0
    for i, (_, xs, _) in sorted(enumerate(measurement.spans), key=lambda e: e[1][1].start):
        if xs.start > at:
            out.append(at - xs.start)
        out.append(i)
        at = xs.stop
    numel = math.prod(measurement.group.element_shape)
    return tuple(out + ([at - numel] if numel > at else []))


def _innovation_values(x, measurement, measured):
    """The innovations concatenated ``(B, innovation_dim)`` in the state dtype, and what
    :func:`_innovation_grads` reads."""
    parts, saved = [], []
    for (f, xs, _), m in zip(measurement.spans, measured):
        if type(f) is SO3:  # (view: unflatten's operation, without its Python)
            out, keep = so3k.rminus_values(m, x[:, xs].view(-1, 3, 3))
            parts.append(out)
            saved.extend(keep)
        else:
            parts.append(m - x[:, xs])
    return torch.cat(parts, dim=-1), saved


def _innovation_grads(meas, x, rest, grad, need_x, needs):
    """The gradients by ``x`` (or ``None``) and by each measured element (``needs``) of
    ``<grad, innovations>``, ``grad`` in the state dtype; ``x, rest``: what the forward saved."""
    measured, saved = rest[: len(meas.spans)], rest[len(meas.spans) :]
    gxs, gm, at, col = [], [], 0, 0
    for (f, xs, _), m, need in zip(meas.spans, measured, needs):
        g = grad[:, col : col + f.tangent_dim]
        col += f.tangent_dim
        if type(f) is SO3:
            xf = x[:, xs].view(-1, 3, 3) if need else None
            gmf, gxf = so3k.rminus_grads(m, xf, saved[at : at + 5], g, (need, need_x))
            at += 5
            gxs.append(gxf.flatten(-2) if need_x else None)
        else:
            gmf = g if need else None
            gxs.append(g.neg() if need_x else None)
        gm.append(gmf)
    gx = None
    if need_x:
        gx = torch.cat([gxs[i] if i >= 0 else grad.new_zeros(grad.shape[0], -i)
                        for i in meas._layout], dim=-1)
    return gx, gm


class _Innovations(torch.autograd.Function):
    @staticmethod
    def forward(ctx, x, measurement, dtype, *measured):
        nu, saved = _innovation_values(x, measurement, measured)
        ctx.measurement, ctx.inputs = measurement, so3k.Inputs(x, *measured)
        ctx.x_dtype = x.dtype
        # x only for the measured elements' gradient (as autograd would save it)
        ctx.save_for_backward(x if any(ctx.needs_input_grad[3:]) else None, *measured, *saved)
        return cast(nu, dtype)  # the cast folded in: one node fewer

    @staticmethod
    def backward(ctx, grad):
        meas = ctx.measurement
        if torch.is_grad_enabled():  # create_graph: the generic path, differentiated
            needs = ctx.needs_input_grad[:1] + ctx.needs_input_grad[3:]
            grads = so3k.recorded_grad(
                lambda x_, *m_: torch.cat(meas.innovations(x_, m_), -1).to(grad.dtype),
                ctx.inputs, needs, grad,
            )
            return grads[0], None, None, *grads[1:]
        x, *rest = ctx.saved_tensors
        gx, gm = _innovation_grads(meas, x, rest, cast(grad, ctx.x_dtype),
                                   ctx.needs_input_grad[0], ctx.needs_input_grad[3:])
        return gx, None, None, *gm


class _Features(torch.autograd.Function):
    """``cat(x, yu, innovations)`` in ``yu``'s dtype: the embedding (a flat one), readings and
    innovation features over a fusable measurement. ``x`` comes twice, the embedding's and the
    innovations': autograd adds their gradients to ``x``'s in that order, as it added those of
    the embedding's cast and of the innovations' node this one replaces (the same bits)."""

    @staticmethod
    def forward(ctx, x_emb, x, yu, measurement, *measured):
        nu, saved = _innovation_values(x, measurement, measured)
        ctx.measurement, ctx.inputs = measurement, so3k.Inputs(x_emb, x, yu, *measured)
        ctx.x_dtype, ctx.widths = x.dtype, (x.shape[1], yu.shape[1])
        ctx.save_for_backward(x if any(ctx.needs_input_grad[4:]) else None, *measured, *saved)
        return torch.cat((cast(x_emb, yu.dtype), yu, cast(nu, yu.dtype)), dim=-1)

    @staticmethod
    def backward(ctx, grad):
        meas, needs = ctx.measurement, ctx.needs_input_grad
        if torch.is_grad_enabled():  # create_graph: the generic path, differentiated
            grads = so3k.recorded_grad(
                lambda xe, x_, yu_, *m_: torch.cat(
                    (xe.to(yu_.dtype), yu_, torch.cat(meas.innovations(x_, m_), -1).to(yu_.dtype)),
                    -1),
                ctx.inputs, needs[:3] + needs[4:], grad,
            )
            return *grads[:3], None, *grads[3:]
        n, w = ctx.widths
        x, *rest = ctx.saved_tensors
        g64 = cast(grad, ctx.x_dtype)  # one cast, then the embedding's and innovations' columns
        gx, gm = _innovation_grads(meas, x, rest, g64[:, n + w :], needs[1], needs[4:])
        g_emb = g64[:, :n] if needs[0] else None
        return g_emb, gx, grad[:, n : n + w] if needs[2] else None, None, *gm


def fused_features(measurement, x: torch.Tensor, yu: torch.Tensor, measured) -> torch.Tensor:
    """``cat(x, yu, innovations)`` ``(B, numel + l + m + innovation_dim)`` in ``yu``'s dtype
    (the paper's embedding and readings and the innovation feature of a fusable measurement,
    ``x`` a flat embedding) as one autograd node. Not for ``torch.compile``: dynamo does not
    trace a Function given one tensor twice."""
    return _features_apply(x, x, yu, measurement, *measured)


def fused_innovations(measurement, x: torch.Tensor, measured, dtype) -> torch.Tensor:
    """The innovations of a fusable measurement, concatenated ``(B, innovation_dim)`` and cast
    to ``dtype``, as one autograd node."""
    if torch.compiler.is_compiling():
        return _Innovations.apply(x, measurement, dtype, *measured)
    return _innovations_apply(x, measurement, dtype, *measured)


_innovations_apply = super(torch.autograd.Function, _Innovations).apply  # as _update_apply
_features_apply = super(torch.autograd.Function, _Features).apply
