"""Deployment: the observer's online step as a check-free module, exported with ``torch.export``.

:meth:`ResidualObserver.step` validates its arguments every call (types, shapes, finite values):
right for interactive use, but a data-dependent ``if`` (``bool(isfinite(y).all())``) cannot be
traced into a graph, and the checks cost more than the arithmetic at batch 1. :class:`OnlineStep`
is the same step on plain tensors, with nothing checked::

    step = observer.online_step_module()          # an nn.Module
    x, *hidden = step.initial_state()             # the identity, the core's zero state
    for y in stream:                              # y: (1, measurement_dim), the state dtype
        x, *hidden = step(x, *hidden, y)          # (..., u) when the observer reads inputs
        estimate = x.view(1, *observer.group.element_shape)

:func:`export_observer` traces it with ``torch.export`` and writes the program
(``torch.export.save``, a ``.pt2`` file that needs torch but no manifold_nets code to run), with
a JSON description beside the graph; :func:`load_exported_step` reads it back.
:func:`export_onnx` writes an ONNX model (needs ``onnx`` and ``onnxscript``: the ``export``
extra); ``docs/deployment.md`` says which runtimes run which dtypes.

The step's tensors: ``x`` ``(B, numel)`` the flattened estimate in the state dtype; ``hidden``
the core's state, each ``(B, ...)`` in the network dtype; ``y`` ``(B, measurement_dim)`` in the
state dtype (the measured factors of innovation inputs are read in it; the network reads ``y``
cast to its dtype); ``u`` ``(B, input_dim)`` in the network dtype, only when ``input_dim > 0``.
It returns ``(x_next, *hidden_next)``, the same values as :meth:`ResidualObserver.step`. An
observer with a piece that depends on the step count (a centred head, a step decay) has one
more state tensor after the hidden ones, ``steps`` ``(B,)`` in the network dtype: the steps
taken, exact in float32 up to 2^24 steps. ``y`` and ``u`` may be any views (they are made
contiguous before use).

An observer trained behind a pre-filter of its readings
(:class:`~manifold_nets.observer.FilteredObserver`, from
:func:`~manifold_nets.observer.with_readings_filter`) exports the filter with it: the step then
takes the raw ``y`` and ``u`` (both in the filter's dtype, float64 by default), the filter's
state tensors after the observer's (named ``filter_*`` in the description, which also holds the
filter's signature under ``readings_filter`` and every state tensor's dtype under
``state_dtypes``), and returns them updated after the observer's.

An :class:`~manifold_nets.observer.EnsembleObserver` exports every member's state after the
barycentre ``x``; a :class:`~manifold_nets.observer.CalibratedObserver` exports its observer's
step with the readout's ``memory`` (then a level scale's averaged ``level``, and ``clock_steps``)
after the observer's state, a ``context`` input last for a readout that reads some, and the
covariance ``P`` as the last output (the description names the inputs and holds the readout's
signature under ``covariance_readout``, a level scale's under ``level_scale``).
"""

from __future__ import annotations

import contextlib
import io
import json
import logging
import os
import sys
import warnings
from collections.abc import Iterator
from pathlib import Path
from typing import TYPE_CHECKING, Any

import torch
from torch import nn

from .atomic import atomic_open

if TYPE_CHECKING:
    from .observer import FilteredObserver, ResidualObserver

__all__ = ["OnlineStep", "ExportedStep", "export_observer", "load_exported_step", "export_onnx"]

#: The name of the JSON description inside an exported ``.pt2`` file.
META_NAME = "manifold_nets.json"


class OnlineStep(nn.Module):
    """One unchecked step of ``observer``: ``forward(x, *hidden, y[, u]) -> (x, *hidden)``.

    See the module docstring for the shapes and dtypes. The observer's parameters are shared,
    not copied. It runs :meth:`ResidualObserver.step_unchecked` with
    :meth:`ResidualObserver.schedule_at`, the rollout's own step and schedule.
    """

    def __init__(self, observer: ResidualObserver):
        super().__init__()
        self.observer = observer
        #: a piece that depends on the step count (a centred head, a step decay) needs the
        #: count: one more state tensor, ``steps`` ``(B,)``
        self.clock = observer.uses_step_count
        self.num_hidden = len(observer.core.initial_hidden(1)) + self.clock

    def state_names(self) -> list[str]:
        """The names of the state tensors after ``x``: ``hidden0, ..`` and ``steps``."""
        names = [f"hidden{i}" for i in range(self.num_hidden - self.clock)]
        return names + (["steps"] if self.clock else [])

    def initial_state(self, batch: int = 1) -> tuple[torch.Tensor, ...]:
        """``(x, *hidden)`` before the first step: the identity and the core's initial state (and
        the step count, 0, when a piece depends on it)."""
        obs = self.observer
        x, hidden, _ = obs.init_state(batch)
        steps = (torch.zeros(batch, dtype=obs.net_dtype, device=obs.device),) if self.clock else ()
        return (x.reshape(batch, -1), *hidden, *steps)

    def example_inputs(self, batch: int = 1) -> tuple[torch.Tensor, ...]:
        """Arguments of the right shapes and dtypes for tracing (the initial state, zero y, u)."""
        obs = self.observer
        y = torch.zeros(batch, obs.measurement_dim, dtype=obs.state_dtype, device=obs.device)
        u = torch.zeros(batch, obs.input_dim, dtype=obs.net_dtype, device=obs.device)
        return (*self.initial_state(batch), y, *((u,) if obs.input_dim else ()))

    def forward(self, x: torch.Tensor, *args: torch.Tensor) -> tuple[torch.Tensor, ...]:
        obs = self.observer
        want = self.num_hidden + 1 + (1 if obs.input_dim else 0)
        if len(args) != want:
            raise TypeError(
                f"OnlineStep takes (x, {self.num_hidden} hidden tensors, y"
                + (", u)" if obs.input_dim else ")")
                + f", got {1 + len(args)} tensors."
            )
        hidden, y = tuple(args[: self.num_hidden]), args[self.num_hidden].contiguous()
        parts = [y] if not obs.input_dim else [y, args[-1].contiguous()]
        yu = torch.cat([p.to(obs.net_dtype) for p in parts], -1)
        ys = torch.cat([p.to(obs.state_dtype) for p in parts], -1)
        timed, count = [None] * (1 + len(obs.scales)), ()
        if self.clock:  # per sequence, in float64 like the rollout's schedule
            hidden, k = hidden[:-1], hidden[-1]
            timed, count = obs.schedule_at(k.to(torch.float64)), (k + 1,)
        x, hidden = obs.step_unchecked(x, hidden, yu, ys, obs.measurement.elements(ys), timed)
        return (x, *hidden, *count)


def _meta(step: nn.Module, batch: int | None) -> dict[str, Any]:
    obs = step.observer
    prefilter, readout = getattr(step, "prefilter", None), getattr(step, "readout", None)
    initial = step.initial_state(1)
    # a LockOutGuard's step, alone or under a readout's
    guard = next((s for s in (step, getattr(step, "step", None)) if hasattr(s, "lock_out")), None)
    return {
        "format": "manifold_nets.online_step/1",
        "signature": obs.signature(),
        "element_shape": list(obs.group.element_shape),
        "state_dtype": str(obs.state_dtype).removeprefix("torch."),
        "net_dtype": str(obs.net_dtype).removeprefix("torch."),
        "measurement_dim": obs.measurement_dim,
        "input_dim": obs.input_dim,
        "batch": batch,
        "inputs": ["x", *step.state_names(), "y"]
        + (["u"] if obs.input_dim else []) + list(getattr(step, "extra_inputs", list)()),
        "initial_state": [t[0].tolist() for t in initial],
        "state_dtypes": [str(t.dtype).removeprefix("torch.") for t in initial],
        "readings_filter": None if prefilter is None else prefilter.signature(),
        "covariance_readout": None if readout is None else readout.signature(),
        **({"level_scale": step.level_scale.signature()}
           if getattr(step, "level_scale", None) is not None else {}),
        **({"lock_out": guard.lock_out()} if guard is not None else {}),
    }


def _online_step(observer) -> nn.Module:
    """The check-free step of ``observer`` that the exporters trace: :class:`OnlineStep` of a
    :class:`~manifold_nets.observer.ResidualObserver`, the filter's step then it of a
    :class:`~manifold_nets.observer.FilteredObserver`."""
    make = getattr(observer, "online_step_module", None)
    step = make() if callable(make) else None
    if not all(hasattr(step, name) for name in ("example_inputs", "state_names", "observer")):
        raise TypeError(
            f"export a ResidualObserver, an EnsembleObserver, a FilteredObserver (an observer "
            f"behind its readings filter), a LockOutGuard or a CalibratedObserver, got "
            f"{type(observer).__name__}."
        )
    return step.eval()


def export_observer(
    observer: ResidualObserver | FilteredObserver, path: str | os.PathLike,
    batch: int | None = None,
) -> torch.export.ExportedProgram:
    """Traces ``observer``'s online step (:class:`OnlineStep`) with ``torch.export`` and writes
    the program to ``path`` (``torch.export.save``, atomically), with the description
    :func:`load_exported_step` reads. Returns the program.

    ``observer`` may be a :class:`~manifold_nets.observer.FilteredObserver`: the exported step
    then takes the raw readings, with the filter's state tensors after the observer's
    (:class:`~manifold_nets.observer.filtered.FilteredStep`); an ensemble, or a
    :class:`~manifold_nets.observer.CalibratedObserver` whose step also returns ``P`` (module
    docstring).

    ``batch``: ``None`` (default) exports for any batch size (a dynamic first dimension, traced
    at 2), an integer for that batch size only.
    """
    step = _online_step(observer)
    args = step.example_inputs(2 if batch is None else batch)
    dynamic = None
    if batch is None:
        dim = torch.export.Dim("batch", min=1)
        dynamic = ({0: dim}, tuple({0: dim} for _ in args[1:]))
    with torch.no_grad():
        program = torch.export.export(step, args, dynamic_shapes=dynamic)
    path = Path(path)
    with atomic_open(path, "wb") as f:
        torch.export.save(program, f, extra_files={META_NAME: json.dumps(_meta(step, batch))})
    return program


class ExportedStep:
    """An exported online step read back: call it as ``step(x, *hidden, y[, u])``.

    ``meta`` is the description written beside the graph (the observer's signature, shapes,
    dtypes, ``batch``: ``None`` for any, the input names, ``readings_filter``: the signature of
    a pre-filter exported with it or ``None``); :meth:`initial_state` the identity, the zero
    hidden state and a pre-filter's start.
    """

    def __init__(self, program: torch.export.ExportedProgram, meta: dict[str, Any]):
        self.program, self.meta = program, meta
        self.module = program.module()

    def initial_state(self, batch: int | None = None) -> tuple[torch.Tensor, ...]:
        """``(x, *hidden)`` before the first step, the identity and the core's zero state (and a
        pre-filter's start), for ``batch`` (default: the exported batch, or 1 for a program of
        any batch)."""
        batch = batch or self.meta["batch"] or 1
        dtypes = self.meta.get("state_dtypes") or [self.meta["state_dtype"]] + [
            self.meta["net_dtype"]] * (len(self.meta["initial_state"]) - 1)  # older files
        return tuple(
            torch.tensor([v] * batch, dtype=getattr(torch, d))
            for v, d in zip(self.meta["initial_state"], dtypes)
        )

    def __call__(self, *args: torch.Tensor) -> tuple[torch.Tensor, ...]:
        return self.module(*args)


def load_exported_step(path: str | os.PathLike) -> ExportedStep:
    """Reads a file of :func:`export_observer` (``torch.export.load``)."""
    extra = {META_NAME: ""}
    program = torch.export.load(path, extra_files=extra)
    if not extra[META_NAME]:
        raise ValueError(f"{path} has no {META_NAME}: not written by export_observer.")
    return ExportedStep(program, json.loads(extra[META_NAME]))


def export_onnx(observer: ResidualObserver, path: str | os.PathLike, batch: int = 1) -> Path:
    """Writes ``observer``'s online step as an ONNX model (``torch.onnx.export(dynamo=True)``).

    Inputs and outputs are named ``x, hidden0.., [steps,] y[, u]`` and ``x_next, hidden0_next,
    ..`` (``steps``: the step count of a centring ramp or clock inputs).
    Needs ``onnx`` and ``onnxscript`` (``pip install manifold_nets[export]``).
    """
    try:
        import onnx  # noqa: F401
        import onnxscript  # noqa: F401
    except ImportError as err:
        raise ImportError(
            f"export_onnx needs onnx and onnxscript ({err}); pip install 'manifold_nets[export]'."
        ) from None
    if not hasattr(observer, "uses_step_count"):  # a ResidualObserver's (no import: no cycle)
        raise TypeError(
            f"export_onnx exports one ResidualObserver's step, got {type(observer).__name__}; "
            "export an ensemble or an observer behind its readings filter with export_observer "
            "(torch.export), or pass its bare observer."
        )
    step = OnlineStep(observer).eval()
    names = _meta(step, batch)["inputs"]
    outputs = ["x_next"] + [f"{name}_next" for name in step.state_names()]
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with torch.no_grad(), _quiet_exporter():
        program = torch.onnx.export(
            step, step.example_inputs(batch), dynamo=True, input_names=names,
            output_names=outputs, verbose=False, report=False,
        )
        program.save(str(path))
    return path


@contextlib.contextmanager
def _quiet_exporter() -> Iterator[None]:
    """Silences what ``torch.onnx.export``, onnxscript and onnx_ir say while they work: that
    torchvision's operators are skipped, torch's own deprecation warnings, and, in a program
    that logs at INFO, some 450 lines of their optimisation passes (a line per initializer
    deduplicated or folded). The export's result is the file, or an exception; what they
    printed is written to stderr when it fails."""
    loggers = [logging.getLogger(name) for name in ("torch.onnx", "onnxscript", "onnx_ir")]
    levels = [logger.level for logger in loggers]
    printed = io.StringIO()
    try:
        for logger in loggers:
            logger.setLevel(logging.ERROR)
        with warnings.catch_warnings(), contextlib.redirect_stdout(printed):
            warnings.simplefilter("ignore", FutureWarning)
            warnings.simplefilter("ignore", DeprecationWarning)
            yield
    except Exception:
        sys.stderr.write(printed.getvalue())
        raise
    finally:
        for logger, level in zip(loggers, levels):
            logger.setLevel(level)
