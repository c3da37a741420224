"""The training step as a CUDA graph (``train.cuda_graph=true``): one launch a batch.

On a GPU the eager closed loop is bound by the host launching each time step's few hundred small
kernels and their backward one by one (``benchmarks/results/gpu.md``: the 2x512 training step
5.98x cuDNN's open-loop ``nn.GRU`` eager, 1.73x as one graph). :class:`GraphedStep` captures the
whole step of one batch shape, rollout, loss, backward, gradient clipping and the optimizer step
(an optimizer made with ``capturable=True``), with ``torch.cuda.graph`` and replays it for
every batch of that shape, the batch copied into the graph's static input tensors first.

- Each batch shape gets its own graph after ``WARMUP`` eager steps of that shape (real training
  steps, on a side stream, as ``torch.cuda.graph`` asks): the full batches early in the first
  epoch, the last, partial batch of an epoch after as many epochs. All are captured again
  whenever a learning rate changes (the optimizer's rates are constants inside a graph: the
  cosine schedule captures once an epoch).
- The loss is read back after each replay, as the eager step reads it; a non-finite loss has
  already been applied to the weights (the eager step skips it), and training stops as it does
  then, with the checkpoints of the last good epoch.
- Without ``start`` and truncated BPTT only (:func:`check_graphable`): both read the batch on
  the host.
"""

from __future__ import annotations

import torch

from .data import TrajectoryDataset
from .training_losses import batch_loss

__all__ = ["GraphedStep", "check_graphable"]

#: eager steps of a batch shape before its graph is captured
WARMUP = 3


def check_graphable(device: torch.device, tbptt, start) -> None:
    """Raises ``ValueError`` naming ``train.cuda_graph`` unless it can run here."""
    if device.type != "cuda":
        raise ValueError(
            f"train.cuda_graph=true needs the model on a CUDA device, it is on {device}; set "
            "train.device=cuda, or train.cuda_graph=false."
        )
    if tbptt is not None or start is not None:
        raise ValueError(
            "train.cuda_graph=true captures whole-sequence steps started at the identity: it "
            "cannot be combined with train.tbptt or a start function; leave train.cuda_graph "
            "false for those."
        )


class GraphedStep:
    """``step(batch) -> loss`` (a float) for ``model`` and its ``optimizer``: see the module
    docstring. ``eager(loss) -> float`` is the trainer's own step, used for warm-up and for
    batches of another shape."""

    def __init__(self, model, optimizer, settings, eager):
        self.model, self.opt, self.settings, self.eager = model, optimizer, settings, eager
        self.graphs: dict[tuple, tuple] = {}
        self.seen: dict[tuple, int] = {}
        self.rates: tuple | None = None

    def __call__(self, batch: TrajectoryDataset) -> float:
        rates = tuple(float(g["lr"]) for g in self.opt.param_groups)
        if rates != self.rates:  # the rates are constants of a graph
            self.graphs.clear()
            self.seen.clear()
            self.rates = rates
        key = (len(batch), batch.length, batch.mask is not None)
        if key in self.graphs:
            static, graph, loss = self.graphs[key]
            self._copy(static, batch)
            graph.replay()
            return loss.item()
        if self.seen.get(key, 0) < WARMUP:
            self.seen[key] = self.seen.get(key, 0) + 1
            return self._side_stream(lambda: self.eager(self._loss(batch)))
        static = self._static(batch)
        self.opt.zero_grad(set_to_none=True)  # the graph owns the gradients it writes
        graph = torch.cuda.CUDAGraph()
        with torch.cuda.graph(graph):
            loss = self._loss(static)
            loss.backward()
            if self.settings.grad_clip is not None:
                torch.nn.utils.clip_grad_norm_(self.model.parameters(), self.settings.grad_clip)
            self.opt.step()
        self.graphs[key] = (static, graph, loss)
        graph.replay()  # capturing ran nothing: this batch's step
        return loss.item()

    def _loss(self, batch: TrajectoryDataset) -> torch.Tensor:
        s = self.settings
        return batch_loss(self.model, batch, None, s.loss, s.skip_steps, s.loss_weights)

    @staticmethod
    def _side_stream(fn):
        side = torch.cuda.Stream()
        side.wait_stream(torch.cuda.current_stream())
        with torch.cuda.stream(side):
            out = fn()
        torch.cuda.current_stream().wait_stream(side)
        return out

    @staticmethod
    def _static(batch: TrajectoryDataset) -> TrajectoryDataset:
        """The graph's own input tensors, holding ``batch``."""
        return TrajectoryDataset(
            batch.states.clone(), batch.measurements.clone(), batch.inputs.clone(),
            dict(batch.meta), None if batch.mask is None else batch.mask.clone(),
        )

    @staticmethod
    def _copy(static: TrajectoryDataset, batch: TrajectoryDataset) -> None:
        for name in ("states", "measurements", "inputs", "mask"):
            dst = getattr(static, name)
            if dst is not None:
                dst.copy_(getattr(batch, name))
