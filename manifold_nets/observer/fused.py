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

:func:`lean_steps` is the rollout's loop for such an observer while it trains
(:func:`runs_lean`): each step's update and the next step's core input as one node
(:class:`_UpdateFeatures`), whose SO(3) derivatives read coefficients made for all the steps at
once (:class:`_Tape`), in place of the step's pieces and two nodes; the same bits
(``tests/test_observer_lean_loop.py``).
"""

from __future__ import annotations

import math

import torch

from groups import SO3, Euclidean
from groups import so3_kernels as so3k

__all__ = [
    "fusable_update", "fusable_innovations", "fused_update", "fused_innovations",
    "fused_features", "gradient_layout", "cast", "lean_steps", "runs_lean",
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


def _update_values(x, v_net, update, rplus=so3k.rplus_values):
    """``update(x, v_net)`` ``(B, numel)`` in ``x``'s dtype and what :func:`_update_grads` reads;
    ``rplus`` moves an SO(3) factor (``so3_kernels.rplus_values`` or :meth:`_Tape.rplus`)."""
    v = cast(v_net, x.dtype)  # the cast folded in: one node fewer
    parts, saved = [], []
    for b in update.blocks:
        vf = v[:, b.tangent]
        if b.factor is None:
            parts.append(vf if b.rule == "absolute" else torch.add(x[:, b.element], vf))
        else:  # (view: unflatten's operation, without its Python)
            out, keep = rplus(x[:, b.element].view(-1, 3, 3), vf)
            parts.append(out.flatten(-2))
            saved.extend((vf, *keep))  # the factor's v: no slice in the backward
    return torch.cat(parts, dim=-1), saved


def _update_grads(update, saved, grad, dtype):
    """The gradients by ``x`` and by ``v`` (in ``dtype``) of ``<grad, update(x, v)>``."""
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
    return torch.cat(gx, dim=-1), cast(torch.cat(gv, dim=-1), dtype)


class _Update(torch.autograd.Function):
    @staticmethod
    def forward(ctx, x, v_net, update):
        out, saved = _update_values(x, v_net, update)
        ctx.update, ctx.inputs, ctx.dtype = update, so3k.Inputs(x, v_net), v_net.dtype
        ctx.save_for_backward(*saved)
        return out

    @staticmethod
    def backward(ctx, grad):
        update, needs = ctx.update, ctx.needs_input_grad[:2]
        if torch.is_grad_enabled():  # create_graph: the generic path, differentiated
            generic = lambda x_, v_: update.generic(x_, v_.to(x_.dtype))  # noqa: E731
            return (*so3k.recorded_grad(generic, ctx.inputs, needs, grad), None)
        return (*_update_grads(update, ctx.saved_tensors, grad, ctx.dtype), None)


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


def _innovation_values(x, measurement, measured, rminus=so3k.rminus_values):
    """The innovations concatenated ``(B, innovation_dim)`` in the state dtype, and what
    :func:`_innovation_grads` reads (``rminus``: as :func:`_update_values`' ``rplus``)."""
    parts, saved = [], []
    for (f, xs, _), m in zip(measurement.spans, measured):
        if type(f) is SO3:  # (view: unflatten's operation, without its Python)
            out, keep = rminus(m, x[:, xs].view(-1, 3, 3))
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


# ------------------------------------------------------------------ the lean rollout


def _core_input(x, yu, measurement, measured, rminus):
    """``cat(x, yu, innovations(x))`` in ``yu``'s dtype (:class:`_Features`' value) and what
    :func:`_innovation_grads` reads."""
    nu, saved = _innovation_values(x, measurement, measured, rminus)
    return torch.cat((cast(x, yu.dtype), yu, cast(nu, yu.dtype)), dim=-1), saved


def _stepped(update, measurement):
    """:class:`_UpdateFeatures`' formula through the generic path (for a second derivative)."""

    def formula(x, v, yu, *measured):
        x_new = update.generic(x, v.to(x.dtype))
        nu = torch.cat(measurement.innovations(x_new, measured), -1)
        return x_new, torch.cat((x_new.to(yu.dtype), yu, nu.to(yu.dtype)), -1)

    return formula


class _Tape:
    """A rollout's SO(3) intermediates of which the backward's coefficients are made
    (:func:`groups.so3_kernels.exp_coefficients`, :func:`~groups.so3_kernels.log_coefficients`),
    made for all the steps at once when a backward first reads them: a few operations a rollout
    instead of twenty a step, each step's values (elementwise arithmetic)."""

    def __init__(self):
        self.exp, self.log, self._made = [], [], None

    def rplus(self, x, v):
        """:func:`groups.so3_kernels.rplus_values`, the coefficients left to the tape."""
        out, e, raw = so3k.rplus_parts(x, v)
        self.exp.append(raw)
        return out, (out, e)

    def rminus(self, y, x):
        """:func:`groups.so3_kernels.rminus_values`, likewise."""
        out, picked, raw = so3k.rminus_parts(y, x)
        self.log.append(raw)
        return out, picked

    def read(self, at, saved, count, kind):
        """A node's ``saved`` (``count`` tensors an SO(3) factor, its factors the ``kind``
        entries ``at``, ``at + 1``, ...) with each factor's coefficients after its tensors: the
        layout of :func:`groups.so3_kernels.rplus_values`' (``"exp"``) or ``rminus_values``'
        (``"log"``) ``saved``."""
        if self._made is None:  # all the steps' at once; each entry's as views of them
            stack = lambda entries: [torch.stack(t) for t in zip(*entries)]  # noqa: E731
            self._made = {
                name: list(zip(*(c.unbind(0) for c in made))) for name, made in (
                    ("exp", so3k.exp_coefficients(*stack(self.exp))),
                    ("log", so3k.log_coefficients(*stack(self.log))))
            }
            self.exp = self.log = None
        made = self._made[kind]
        return [t for i in range(len(saved) // count)
                for t in (*saved[i * count : (i + 1) * count], *made[at + i])]


class _UpdateFeatures(torch.autograd.Function):
    """``x' = update(x, v)`` and the next step's core input ``cat(x', yu, innovations(x'))``:
    :class:`_Update` and :class:`_Features` as one node, the coefficients of the SO(3)
    derivatives from the rollout's :class:`_Tape`. The gradient by ``x'`` is summed as autograd
    summed it before: what the later nodes give (the loss's, the next update's), plus the
    embedding's, plus the innovations' (the same bits)."""

    @staticmethod
    def forward(ctx, x, v_net, yu, update, measurement, tape, *measured):
        ctx.set_materialize_grads(False)
        ctx.at = len(tape.exp), len(tape.log)
        x_new, saved = _update_values(x, v_net, update, tape.rplus)
        z, kept = _core_input(x_new, yu, measurement, measured, tape.rminus)
        ctx.update, ctx.measurement, ctx.tape = update, measurement, tape
        ctx.inputs, ctx.count = so3k.Inputs(x, v_net, yu, *measured), len(saved)
        ctx.dtypes, ctx.widths = (x.dtype, v_net.dtype), (x.shape[1], yu.shape[1])
        ctx.save_for_backward(x_new if any(ctx.needs_input_grad[6:]) else None, *measured,
                              *kept, *saved)
        return x_new, z

    @staticmethod
    def backward(ctx, g_new, gz):
        needs, meas, (n, w) = ctx.needs_input_grad, ctx.measurement, ctx.widths
        if torch.is_grad_enabled():  # create_graph: the generic path, differentiated
            x, _, yu = ctx.inputs.tensors[:3]
            g_new = torch.zeros_like(x) if g_new is None else g_new
            gz = yu.new_zeros(yu.shape[0], n + w + meas.innovation_dim) if gz is None else gz
            grads = so3k.recorded_grad(_stepped(ctx.update, meas), ctx.inputs,
                                       needs[:3] + needs[6:], (g_new, gz))
            return *grads[:3], None, None, None, *grads[3:]
        x_new, *rest = ctx.saved_tensors
        spans, tape = len(meas.spans), ctx.tape
        rest, saved = rest[: len(rest) - ctx.count], rest[len(rest) - ctx.count :]
        g_yu, gm = None, [None] * spans
        if gz is not None:
            g64 = cast(gz, ctx.dtypes[0])  # as _Features: the embedding's, then the innovations'
            rest = [*rest[:spans], *tape.read(ctx.at[1], rest[spans:], 2, "log")]
            gi, gm = _innovation_grads(meas, x_new, rest, g64[:, n + w :], True, needs[6:])
            g_new = g64[:, :n] if g_new is None else g_new + g64[:, :n]
            g_new = g_new + gi
            g_yu = gz[:, n : n + w] if needs[2] else None
        if g_new is None:
            return None, None, g_yu, None, None, None, *gm
        grads = _update_grads(ctx.update, tape.read(ctx.at[0], saved, 3, "exp"), g_new,
                              ctx.dtypes[1])
        return *grads, g_yu, None, None, None, *gm


_update_features_apply = super(torch.autograd.Function, _UpdateFeatures).apply


def lean_steps(observer, x, hidden, inputs, keep_hidden):
    """:meth:`ResidualObserver._steps <manifold_nets.observer.ResidualObserver>` for an observer
    that :func:`runs_lean`: the core's input at ``x_0`` as its step makes it, then each step's
    update and the next step's core input as one node (:class:`_UpdateFeatures`)."""
    core, update, meas, tape = observer.core, observer.update, observer.measurement, _Tape()
    xs, hs = [x], [hidden]
    inputs = iter(inputs)
    first = next(inputs, None)
    if first is None:
        return xs, hs, hidden
    yu, _, measured, _ = first
    z = observer._features(observer._view(x, yu, measured))
    for yu, _, measured, _ in inputs:
        v, hidden = core.step(z, hidden)
        x, z = _update_features_apply(x, v, yu, update, meas, tape, *measured)
        xs.append(x)
        if keep_hidden:
            hs.append(hidden)
    v, hidden = core.step(z, hidden)
    xs.append(update(x, v))
    if keep_hidden:
        hs.append(hidden)
    return xs, hs, hidden


def runs_lean(observer) -> bool:
    """Whether ``observer``'s rollout can run :func:`lean_steps` now: its step is the prior-free
    update of a fusable state after the core (its features read as one, the plain head, no
    scale), autograd records with no ``torch.func`` transform, and the step is not compiled."""
    from .priors import NoPrior

    return (
        observer._view == observer.measurement.deferred_view  # (features.reads_as_one)
        and observer.update._fused and observer.measurement._fused
        and type(observer.prior) is NoPrior and not observer.scales
        and observer._compiled_step is None
        and torch.is_grad_enabled() and not torch._C._are_functorch_transforms_active()
    )
