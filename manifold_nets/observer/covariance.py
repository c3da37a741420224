"""A learned covariance of the observer's error, read off what each step left unexplained.

The error of the estimate ``xhat_k`` is the tangent vector ``xi_k = Log(xhat_k^-1 x_k)`` (the
right perturbation, as in the project's EKF: :mod:`manifold_nets.ekf`). A
:class:`CovarianceReadout` maps what the observer saw up to step ``k`` to a Cholesky factor
``L_k``, and the observer reports ``xi_k ~ N(0, L_k L_k^T)``. It reads, per step (``source``):

* ``"residual"`` (default where the measurement names measured factors): the residual of the
  step's measurement against the new estimate, ``log(xhat_{k,f}^-1 m_{k,f})`` per measured factor
  (what the update left unexplained: its size follows the noise level);
* ``"residual_size"``: the same residuals and, per measured factor, the log of their squared size
  ``log(|nu_f|^2 + 1e-12)``, which reads a small residual's size as sharply as a large one's
  (the signed residuals, standardised over every noise level, reach the GRU's nonlinearity only
  as a second-order effect when they are small);
* ``"hidden"``: the core's hidden state after the step;
* ``"readings"``: the step's measurement and input ``(y_k, u_{k-1})`` as they are (for observers
  that measure no factor, e.g. an IMU's: how fast it turns and how far the accelerometer is from
  gravity say how hard the step was).

Its inputs are standardised (a shift and a scale fixed from the training data), a small GRU
(``memory`` wide; the readout's own memory of how noisy the recent steps were) runs over them and
a linear map reads ``L_k`` off it. On the paper's rigid body the residual was the better input
(validation NLL -28.4 against -27.7 for residual and hidden state together and -27.2 for the
hidden state alone, which could not tell the noise levels apart: ANEES 0.39 at sigma 0.1, 1.53
at 0.5; ``benchmarks/bench_covariance_inputs.py``). Structures:

* ``structure="diagonal"``: ``L`` diagonal (one variance per tangent component);
* ``"factor"``: block diagonal, one full block per factor of the group (SO(3)'s three angles
  correlated among themselves, not with the position);
* ``"joint"``: a full lower triangle over the whole tangent space.

``L = C diag(exp(d))`` with ``C`` unit lower triangular: ``d`` and the entries of ``C`` below the
diagonal are the readout (so ``log det P = 2 sum d`` exactly, and the correlations are free of
the errors' scale). Step 0 (the start, before any measurement) has its own learned factor.

A ``"readings"`` readout reads nothing of the observer, so it serves any observer: a
:class:`~manifold_nets.observer.CalibratedObserver` may wrap an
:class:`~manifold_nets.observer.EnsembleObserver` (whose
members have no one core to read) or a :class:`~manifold_nets.observer.FilteredObserver` with
one, its covariance fitted to that observer's own errors.

A readout may also read *context* (``context=C``): ``C`` numbers a step of side information
that the observer does not read, given beside its readings (``cal(y, u, context=c)``,
``cal.step(state, y, u, context=c_k)``, the last argument of the exported step). An observer
run at every ``k``-th sample sees one sample of each block; how far the block's ``k`` samples
spread (a vibration that a low-pass and the step's average hide) is such context
(``examples/broad/calibration.py``).

:class:`~manifold_nets.observer.CalibratedObserver` (:mod:`manifold_nets.observer.calibrated`)
puts an observer and a readout together. The readout does not change the estimate: fitted on a
frozen observer (:func:`manifold_nets.covariance_training.fit_covariance`), the point estimates
are the observer's to the last bit.
"""

from __future__ import annotations

import math
import torch
from torch import nn

from groups import LieGroup

from ..cores import Hidden
from .observer import ObserverState, ResidualObserver

__all__ = [
    "STRUCTURES", "SOURCES", "CovarianceReadout", "hidden_features", "readout_inputs",
    "with_context", "gaussian_nll",
]

STRUCTURES = ("diagonal", "factor", "joint")
#: The widest memory a readout may have (the shipped ones: 32); a file asking for more is refused.
MAX_MEMORY = 4096
SOURCES = ("residual", "residual_size", "hidden", "readings")
#: Added to a squared residual before its log (``"residual_size"``).
SIZE_FLOOR = 1e-12


def hidden_features(hidden: Hidden) -> torch.Tensor:
    """The core's state as one ``(*batch, W)`` tensor: each hidden tensor flattened after the
    batch dimensions it shares with the others (``(B, H)`` or ``(B, T, H)``), concatenated."""
    lead = hidden[0].dim() - 1
    return torch.cat([h.flatten(lead) for h in hidden], dim=-1)


def input_width(observer: ResidualObserver, source: str) -> int:
    """How many numbers a readout of ``source`` reads per step of ``observer``."""
    if source == "hidden":
        return hidden_features(observer.core.initial_hidden(1)).shape[-1]
    if source == "readings":
        return observer.measurement_dim + observer.input_dim
    sizes = len(observer.measurement.factors) if source == "residual_size" else 0
    return observer.measurement.innovation_dim + sizes


def readout_inputs(observer: ResidualObserver, source: str, x: torch.Tensor, y: torch.Tensor,
                   u: torch.Tensor | None, hidden: Hidden) -> torch.Tensor:
    """A readout's inputs ``(*batch, W)`` (float32) for estimates ``x`` ``(*batch, numel)`` after
    measurements ``y`` ``(*batch, l)`` (inputs ``u`` ``(*batch, m)`` or ``None``) and the core's
    states ``hidden`` (each ``(*batch, ...)``)."""
    if source == "hidden":
        return hidden_features(hidden).float()
    if source == "readings":
        return (y if u is None or not observer.input_dim else torch.cat([y, u.to(y)], -1)).float()
    m = observer.measurement
    lead = x.shape[:-1]
    ys = y.reshape(-1, y.shape[-1]).to(observer.state_dtype)
    nu = list(m.innovations(x.reshape(-1, x.shape[-1]), m.elements(ys)))
    if source == "residual_size":
        nu += [(v.square().sum(-1, keepdim=True) + SIZE_FLOOR).log() for v in nu]
    return torch.cat(nu, dim=-1).reshape(*lead, -1).float()


def _mask(group: LieGroup, structure: str) -> torch.Tensor:
    n = group.tangent_dim
    if structure == "diagonal":
        return torch.eye(n, dtype=torch.bool)
    if structure == "joint":
        return torch.ones(n, n, dtype=torch.bool).tril()
    m = torch.zeros(n, n, dtype=torch.bool)
    for name in group.factor_names:
        s = group.tangent_slice(name)
        m[s, s] = True
    return m.tril()


#: The most numbers of context a readout may read per step.
MAX_CONTEXT = 256
#: The most time constants a readout's clock may have.
MAX_CLOCK = 8


def check_clock(clock) -> tuple[float, ...]:
    """``clock`` as a tuple of time constants in steps (finite, positive; at most
    :data:`MAX_CLOCK`), or ``ValueError`` naming the problem."""
    values = tuple(clock) if isinstance(clock, (list, tuple)) else None
    if values is None or len(values) > MAX_CLOCK or not all(
        isinstance(t, (int, float)) and not isinstance(t, bool) and math.isfinite(t) and t > 0
        for t in values
    ):
        raise ValueError(
            f"covariance: clock must be a list of at most {MAX_CLOCK} positive time constants in "
            f"steps (e.g. [10, 50, 250, 1000]), got {clock!r}."
        )
    return tuple(float(t) for t in values)


def _check_int(name, v, lo, hi):
    if isinstance(v, bool) or not isinstance(v, int) or not lo <= v <= hi:
        raise ValueError(f"covariance: {name} must be an integer in [{lo}, {hi}], got {v!r}.")


class CovarianceReadout(nn.Module):
    """``L_k`` from the readout's inputs up to step ``k`` (module docstring).

    Args:
        group: the observer's group (the tangent space and its factors).
        width: how many numbers it reads per step (:func:`input_width`).
        structure: ``"diagonal"``, ``"factor"`` or ``"joint"``.
        memory: the width of the readout's own GRU; 0 for a memoryless linear readout.
        source: ``"residual"``, ``"residual_size"``, ``"hidden"`` or ``"readings"`` (what it
            reads; module docstring).
        clock: time constants in steps; the readout also reads ``exp(-k / tau)`` at step ``k``.
        context: how many numbers of side information it reads per step beside the source's
            (0: none; module docstring).
    """

    def __init__(self, group: LieGroup, width: int, structure: str = "factor", memory: int = 32,
                 source: str = "residual", clock: tuple[float, ...] = (), context: int = 0):
        super().__init__()
        if structure not in STRUCTURES:
            raise ValueError(f"covariance: structure must be one of {STRUCTURES}, got {structure!r}.")
        if source not in SOURCES:
            raise ValueError(f"covariance: source must be one of {SOURCES}, got {source!r}.")
        _check_int("width", width, 1, 16384)
        _check_int("memory", memory, 0, MAX_MEMORY)
        _check_int("context", context, 0, MAX_CONTEXT)
        self.clock, self.context = check_clock(clock), context
        self.group, self.structure, self.memory, self.source = group, structure, memory, source
        self.width, self.n = width, group.tangent_dim
        # each its own tensor: as views of one, torch.export's archive warns on saving them
        rows, cols = (t.clone() for t in torch.nonzero(_mask(group, structure), as_tuple=True))
        self.register_buffer("rows", rows, persistent=False)
        self.register_buffer("cols", cols, persistent=False)
        self.register_buffer("on_diagonal", rows == cols, persistent=False)
        # the diagonal's positions as integers: a boolean mask's count is data to torch.export
        self.register_buffer("diagonal", torch.nonzero(rows == cols).squeeze(-1), persistent=False)
        self.register_buffer("shift", torch.zeros(width + context))
        self.register_buffer("scale", torch.ones(width + context))
        reads = width + context + len(self.clock)
        if self.clock:
            self.register_buffer("taus", torch.tensor(self.clock), persistent=False)
        self.gru = nn.GRU(reads, memory, batch_first=True) if memory else None
        self.out = nn.Linear(memory or reads, len(rows))
        self.initial = nn.Parameter(torch.zeros(len(rows)))

    def signature(self) -> dict:
        return {
            "type": "cholesky", "structure": self.structure, "memory": self.memory,
            "source": self.source, "width": self.width, "group": repr(self.group),
            **({"clock": list(self.clock)} if self.clock else {}),
            **({"context": self.context} if self.context else {}),
        }

    def check_width(self, inputs: torch.Tensor) -> None:
        """``ValueError`` naming the fix unless ``inputs`` ``(..., W)`` are as wide as what this
        readout reads (sequences read for another source or without the context)."""
        want = self.width + self.context
        if inputs.shape[-1] != want:
            context = f", context=<{self.context} numbers a step>" if self.context else ""
            raise ValueError(
                f"this readout reads {want} numbers a step, the sequences give {inputs.shape[-1]}: "
                f"read them as it does, readout_sequences(observer, data, {self.source!r}{context})."
            )

    def set_input_stats(self, inputs: torch.Tensor) -> None:
        """Standardises the inputs by their mean and standard deviation over ``inputs``
        ``(M, width + context)`` (the training data's known steps)."""
        self.check_width(inputs)
        with torch.no_grad():
            self.shift.copy_(inputs.mean(0))
            self.scale.copy_(inputs.std(0).clamp_min(1e-12))

    def set_scale(self, std: torch.Tensor) -> None:
        """Starts every ``P`` (and the start's) at ``diag(std^2)``: the output layer's weights
        zero, its bias ``log std`` on the diagonal (``std`` ``(n,)``, positive)."""
        raw = torch.zeros(len(self.rows), dtype=self.out.bias.dtype)
        raw[self.on_diagonal] = std.to(raw.dtype).log()[self.rows[self.on_diagonal]]
        with torch.no_grad():
            self.out.weight.zero_()
            self.out.bias.copy_(raw)
            self.initial.copy_(raw)

    def rescale(self, factor_scales: dict[str, float]) -> None:
        """Multiplies every ``P`` (and the start's) by ``factor_scales[f]`` on factor ``f``'s
        block (positive; a factor not named keeps its scale) by moving the log-diagonal's bias
        (``L = C diag(exp(d))``: ``d`` of ``f``'s components plus ``log(s_f) / 2``; the same
        ``P`` to rounding). Blocks of ``C`` do not mix factors unless the structure is
        ``"joint"``, whose factors must then share one scale."""
        log_half = torch.zeros(self.n, dtype=torch.float64)
        for name, s in factor_scales.items():
            if name not in self.group.factor_names or isinstance(s, bool) or not (
                isinstance(s, (int, float)) and math.isfinite(s) and s > 0
            ):
                raise ValueError(
                    f"rescale: expected positive finite scales of the factors "
                    f"{list(self.group.factor_names)}, got {name!r}: {s!r}."
                )
            log_half[self.group.tangent_slice(name)] = 0.5 * math.log(s)
        if self.structure == "joint" and len(set(log_half.tolist())) > 1:
            raise ValueError("rescale: a joint readout's factors are correlated; give every "
                             "factor the same scale.")
        shift = log_half[self.rows[self.on_diagonal]].to(self.out.bias.dtype)
        with torch.no_grad():
            self.out.bias[self.on_diagonal] += shift
            self.initial[self.on_diagonal] += shift

    def initial_memory(self, batch: int, device=None) -> torch.Tensor:
        """The readout's own state before the first step, ``(B, memory)``."""
        w = self.out.weight
        return torch.zeros(batch, self.memory, dtype=w.dtype, device=w.device if device is None else device)

    def clock_inputs(self, start, steps: int) -> torch.Tensor:
        """``exp(-k / tau)`` for each time constant of the clock, at the steps ``k = start + 1 ..
        start + steps``: ``(B or 1, steps, len(clock))`` (``start`` an int or ``(B,)``)."""
        ks = torch.arange(1, steps + 1, dtype=torch.float64, device=self.taus.device)
        ks = (start.to(ks).reshape(-1, 1) if isinstance(start, torch.Tensor) else float(start)) + ks
        return torch.exp(-ks.reshape(-1, steps, 1) / self.taus.double()).to(self.out.weight.dtype)

    def raw(self, inputs: torch.Tensor, memory: torch.Tensor, start=0) -> tuple[torch.Tensor, torch.Tensor]:
        """The readout ``(B, T, count)`` of ``inputs`` ``(B, T, width + context)`` from ``memory``
        ``(B, memory)``, and the memory after them; ``start``: the steps taken before the first
        input (an int or ``(B,)``; read only by a clock)."""
        z = (inputs - self.shift) / self.scale
        if self.clock:
            c = self.clock_inputs(start, z.shape[1])
            z = torch.cat([z, c.expand(z.shape[0], -1, -1)], -1)
        if self.gru is None:
            return self.out(z), memory
        g = self.gru
        if z.shape[1] == 1:  # one step (online, exported): the cell, as the core steps
            h = torch.gru_cell(z[:, 0], memory, g.weight_ih_l0, g.weight_hh_l0, g.bias_ih_l0, g.bias_hh_l0)
            return self.out(h).unsqueeze(1), h
        seq, last = g(z, memory.unsqueeze(0).contiguous())
        return self.out(seq), last.squeeze(0)

    def _factor(self, raw: torch.Tensor) -> torch.Tensor:
        raw = raw.double()
        unit = torch.where(self.on_diagonal, 1.0, raw)
        C = raw.new_zeros(*raw.shape[:-1], self.n, self.n)
        C[..., self.rows, self.cols] = unit  # unit lower triangular
        return C * raw[..., self.diagonal].exp().unsqueeze(-2)  # C diag(exp(d))

    def cholesky(self, inputs: torch.Tensor, memory: torch.Tensor, start=0) -> tuple[torch.Tensor, torch.Tensor]:
        """``L`` ``(B, T, n, n)`` (float64) of ``inputs`` ``(B, T, width)`` from ``memory`` after
        ``start`` steps, and the memory after them."""
        raw, memory = self.raw(inputs, memory, start)
        return self._factor(raw), memory

    def initial_cholesky(self, batch: tuple[int, ...] = ()) -> torch.Tensor:
        """The start's ``L`` ``(*batch, n, n)``."""
        return self._factor(self.initial.expand(*batch, -1))

    def log_scale(self, inputs: torch.Tensor, start=0) -> tuple[torch.Tensor, torch.Tensor]:
        """For the likelihood, over sequences from the initial memory (``start`` steps after the
        observer's start): ``(L, log diag L)``; ``ValueError`` naming the fix when ``inputs`` are
        not as wide as what this readout reads."""
        self.check_width(inputs)
        raw, _ = self.raw(inputs, self.initial_memory(inputs.shape[0], inputs.device), start)
        raw = raw.double()
        return self._factor(raw), raw[..., self.diagonal]

    @staticmethod
    def covariance(chol: torch.Tensor) -> torch.Tensor:
        return chol @ chol.transpose(-1, -2)


def gaussian_nll(errors: torch.Tensor, chol: torch.Tensor, log_diag: torch.Tensor) -> torch.Tensor:
    """``-log N(xi; 0, L L^T)`` less ``n/2 log 2 pi``, per element: ``(*batch,)`` for errors
    ``(*batch, n)``, factors ``(*batch, n, n)`` and their log diagonals ``(*batch, n)``."""
    w = torch.linalg.solve_triangular(chol, errors.to(chol.dtype).unsqueeze(-1), upper=False)
    return 0.5 * w.squeeze(-1).square().sum(-1) + log_diag.sum(-1)


def steps_taken(state) -> int:
    """The steps an observer's online state has taken (an :class:`ObserverState`'s count; a
    filtered observer's or an ensemble's, that of its first observer)."""
    while not isinstance(state, ObserverState):
        state = state.members[0] if hasattr(state, "members") else state.observer
    return state.steps


def with_context(readout: CovarianceReadout, z: torch.Tensor, context: torch.Tensor | None
                 ) -> torch.Tensor:
    """The readout's inputs ``z`` ``(..., width)`` and, for a readout that reads context, the
    step's ``context`` ``(..., context)`` after them; ``ValueError`` naming the shape needed when
    one is missing, misshapen, or given to a readout that reads none."""
    want = readout.context
    if not want:
        if context is not None:
            raise ValueError("this readout reads no context; call without one (or fit a readout "
                             "with context=...).")
        return z
    if context is None or tuple(context.shape) != (*z.shape[:-1], want):
        got = "none" if context is None else tuple(context.shape)
        raise ValueError(f"this readout reads {want} numbers of context per step: give context "
                         f"of shape {(*z.shape[:-1], want)}, got {got}.")
    return torch.cat([z, context.to(z)], dim=-1)
