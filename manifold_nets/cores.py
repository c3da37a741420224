"""Recurrent cores: the network ``T`` of the observer, one step at a time.

A core maps ``(input (B, input_size), hidden) -> (output (B, output_size), hidden)``; the
observer feeds it ``cat(embed(xhat_k), y_{k+1}, u_k, ...)`` and reads ``v_k`` off its output.
:class:`GRUCore` is the paper's (GRU 36 -> 512, GRU 512 -> 512, Linear 512 -> 12 for the rigid
body; sizes and layer count configurable). Any :class:`RecurrentCore` subclass (an LSTM, a
transformer over a window) plugs in: it writes ``initial_hidden`` and ``step``.
"""

from __future__ import annotations

import abc

import torch
from torch import nn

from .registry import Registry

__all__ = ["CORES", "Hidden", "RecurrentCore", "GRUCore"]

#: Every imported :class:`RecurrentCore` subclass by ``module.qualname``: what a file's
#: ``model.core`` may name (:mod:`manifold_nets.registry`).
CORES = Registry("RecurrentCore", "manifold_nets.RecurrentCore", plugins="manifold_nets.cores")

#: A core's hidden state: a tuple of tensors whose first dimension is the batch.
Hidden = tuple[torch.Tensor, ...]


class RecurrentCore(nn.Module, abc.ABC):
    """A recurrent map ``(input (B, input_size), hidden) -> (output (B, output_size), hidden)``.

    The observer's input is ``cat(embed(xhat_k), y_{k+1}, u_k)`` and its output ``v_k``.
    ``hidden`` is a tuple of tensors whose first dimension is the batch. Subclass it to replace
    the paper's GRU stack; ``signature()`` identifies the architecture in checkpoints.
    """

    input_size: int
    output_size: int

    def __init_subclass__(cls, **kwargs) -> None:
        super().__init_subclass__(**kwargs)
        CORES.add(cls)  # a file's model.core may name it once its module is imported

    @abc.abstractmethod
    def initial_hidden(
        self, batch: int, device: torch.device | str | None = None, dtype: torch.dtype | None = None
    ) -> Hidden:
        """The hidden state before the first step (zeros for a GRU)."""

    @abc.abstractmethod
    def step(self, inp: torch.Tensor, hidden: Hidden) -> tuple[torch.Tensor, Hidden]:
        """One step; no validation (the observer checks its inputs once, before the loop)."""

    def signature(self) -> dict:
        """What must match for a checkpoint of this core to load: type and sizes."""
        return {
            "type": type(self).__name__,
            "input_size": self.input_size,
            "output_size": self.output_size,
        }


class GRUCore(RecurrentCore):
    """A stack of GRU layers and a linear head (the paper's Table): ``input -> H -> ... -> output``.

    Parameters live in a ``torch.nn.GRU`` (same names, same initialisation, so an open-loop
    ``nn.GRU`` run over the same inputs gives the same hidden states) and an ``nn.Linear``;
    a step calls ``torch.gru_cell`` once per layer.
    """

    def __init__(
        self, input_size: int, output_size: int, hidden_size: int = 512, num_layers: int = 2
    ):
        super().__init__()
        for name, val in (
            ("input_size", input_size),
            ("output_size", output_size),
            ("hidden_size", hidden_size),
            ("num_layers", num_layers),
        ):
            if isinstance(val, bool) or not isinstance(val, int) or val < 1:
                raise ValueError(f"GRUCore: {name} must be a positive integer, got {val!r}.")
        self.input_size = input_size
        self.output_size = output_size
        self.hidden_size = hidden_size
        self.num_layers = num_layers
        self.gru = nn.GRU(input_size, hidden_size, num_layers)
        self.head = nn.Linear(hidden_size, output_size)

    def initial_hidden(self, batch, device=None, dtype=None) -> Hidden:
        w = self.head.weight
        shape = (batch, self.hidden_size)
        return tuple(
            torch.zeros(
                shape,
                device=w.device if device is None else device,
                dtype=w.dtype if dtype is None else dtype,
            )
            for _ in range(self.num_layers)
        )

    def _layers(self) -> list[tuple[torch.Tensor, ...]]:
        g = self.gru
        return [
            (
                getattr(g, f"weight_ih_l{i}"),
                getattr(g, f"weight_hh_l{i}"),
                getattr(g, f"bias_ih_l{i}"),
                getattr(g, f"bias_hh_l{i}"),
            )
            for i in range(self.num_layers)
        ]

    def step(self, inp: torch.Tensor, hidden: Hidden) -> tuple[torch.Tensor, Hidden]:
        # nn.GRU's own list of its parameters (w_ih, w_hh, b_ih, b_hh per layer, kept current
        # by the module): no attribute lookup by name per step
        w = self.gru._flat_weights if not torch.compiler.is_compiling() else None
        out = []
        h = inp
        for i, h_prev in enumerate(hidden):
            p = w[4 * i : 4 * i + 4] if w is not None else self._layers()[i]
            h = torch.gru_cell(h, h_prev, *p)
            out.append(h)
        return self.head(h), tuple(out)

    def zero_output(self, start: int = 0) -> None:
        """Sets the output layer's rows from ``start`` on to zero (where a head starts)."""
        with torch.no_grad():
            self.head.weight[start:].zero_()
            self.head.bias[start:].zero_()

    def signature(self) -> dict:
        return {
            **super().signature(),
            "hidden_size": self.hidden_size,
            "num_layers": self.num_layers,
        }
