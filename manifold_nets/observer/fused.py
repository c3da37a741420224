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
"""

from __future__ import annotations

import torch

from groups import SO3, Euclidean
from groups import so3_kernels as so3k

__all__ = ["fusable_update", "fusable_innovations", "fused_update", "fused_innovations"]


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


class _Update(torch.autograd.Function):
    @staticmethod
    def forward(ctx, x, v_net, update):
        v = v_net.to(x.dtype)  # the cast folded in: one node fewer
        parts, saved = [], []
        for b in update.blocks:
            xf, vf = x[:, b.element], v[:, b.tangent]
            if b.factor is None:
                parts.append(vf if b.rule == "absolute" else torch.add(xf, vf))
            else:
                out, keep = so3k.rplus_values(xf.unflatten(-1, (3, 3)), vf)
                parts.append(out.flatten(-2))
                saved.extend(keep)
        ctx.update, ctx.inputs, ctx.dtype = update, so3k.Inputs(x, v_net), v_net.dtype
        ctx.save_for_backward(v, *saved)
        return torch.cat(parts, dim=-1)

    @staticmethod
    def backward(ctx, grad):
        update, needs = ctx.update, ctx.needs_input_grad[:2]
        if torch.is_grad_enabled():  # create_graph: the generic path, differentiated
            generic = lambda x_, v_: update.generic(x_, v_.to(x_.dtype))  # noqa: E731
            return (*so3k.recorded_grad(generic, ctx.inputs, needs, grad), None)
        v, *saved = ctx.saved_tensors
        gx, gv, at = [], [], 0
        for b in update.blocks:
            g = grad[:, b.element]
            if b.factor is None:
                gx.append(torch.zeros_like(g) if b.rule == "absolute" else g)
                gv.append(g)
            else:
                gxf, gvf = so3k.rplus_grads(v[:, b.tangent], saved[at : at + 4],
                                            g.unflatten(-1, (3, 3)))
                gx.append(gxf.flatten(-2))
                gv.append(gvf)
                at += 4
        return torch.cat(gx, dim=-1), torch.cat(gv, dim=-1).to(ctx.dtype), None


def fused_update(update, x: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """``update(x, v)`` (a fusable :class:`GroupUpdate`; ``v`` in any dtype, cast to the
    state's) as one autograd node."""
    return _Update.apply(x, v, update)


class _Innovations(torch.autograd.Function):
    @staticmethod
    def forward(ctx, x, measurement, dtype, *measured):
        parts, saved = [], []
        for (f, xs, _), m in zip(measurement.spans, measured):
            if type(f) is SO3:
                out, keep = so3k.rminus_values(m, x[:, xs].unflatten(-1, (3, 3)))
                parts.append(out)
                saved.extend(keep)
            else:
                parts.append(m - x[:, xs])
        ctx.measurement, ctx.inputs = measurement, so3k.Inputs(x, *measured)
        ctx.x_shape, ctx.x_dtype = x.shape, x.dtype
        # x only for the measured elements' gradient (as autograd would save it)
        ctx.save_for_backward(x if any(ctx.needs_input_grad[3:]) else None, *measured, *saved)
        return torch.cat(parts, dim=-1).to(dtype)  # the cast folded in: one node fewer

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
        grad = grad.to(ctx.x_dtype)
        measured, saved = rest[: len(meas.spans)], rest[len(meas.spans) :]
        gx = grad.new_zeros(ctx.x_shape) if ctx.needs_input_grad[0] else None
        gm, at, col = [], 0, 0
        for (f, xs, _), m, need in zip(meas.spans, measured, ctx.needs_input_grad[3:]):
            width = f.tangent_dim
            g = grad[:, col : col + width]
            col += width
            if type(f) is SO3:
                xf = x[:, xs].unflatten(-1, (3, 3)) if need else None
                gmf, gxf = so3k.rminus_grads(m, xf, saved[at : at + 3], g, (need, gx is not None))
                at += 3
                if gx is not None:
                    gx[:, xs] = gxf.flatten(-2)
            else:
                gmf = g if need else None
                if gx is not None:
                    gx[:, xs] = -g
            gm.append(gmf)
        return gx, None, None, *gm


def fused_innovations(measurement, x: torch.Tensor, measured, dtype) -> torch.Tensor:
    """The innovations of a fusable measurement, concatenated ``(B, innovation_dim)`` and cast
    to ``dtype``, as one autograd node."""
    return _Innovations.apply(x, measurement, dtype, *measured)
