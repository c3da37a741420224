"""Training a covariance readout on a frozen observer: the Gaussian negative log-likelihood of
its errors.

The observer is rolled out once over the training sequences (no gradient), keeping what the
readout reads after every step (:func:`~manifold_nets.observer.covariance.readout_inputs`) and
the error ``xi_k = Log(xhat_k^-1 x_k)``. The readout, its inputs standardised by their statistics
over the training data, then runs over them from its initial memory and is fitted by minimising the mean of ``-log N(xi_k; 0, P_k)``
(:func:`~manifold_nets.observer.covariance.gaussian_nll`) over the steps ``k >= skip`` whose true
state is known, in shuffled mini-batches of sequences, with the best validation epoch kept.
Since the observer is frozen its estimates do not change at all (a joint fine-tuning would move
them; this stage cannot).
"""

from __future__ import annotations

import copy
import math
from typing import NamedTuple

import torch

from .calibration import tangent_errors
from .data import TrajectoryDataset
from .observer import CovarianceReadout, LevelScale, ResidualObserver
from .observer.covariance import gaussian_nll, readout_inputs
from .observer.level_scale import hat_clock_basis
from .progress import progress

__all__ = [
    "Sequences", "readout_sequences", "fit_covariance", "mean_nll", "factor_nees", "scale_to_heldout",
    "step_nees", "scale_to_share", "LevelSteps", "level_steps", "fit_level_scale",
]


class Sequences(NamedTuple):
    """What a readout is fitted to, for steps ``1 .. T``: its inputs ``features`` ``(N, T, W)``
    (float32), the errors ``(N, T, n)`` (float64), ``known`` ``(N, T)``, the steps that count,
    and ``start`` ``(N,)`` (int64), the steps each sequence's first one comes after (all 0 for
    whole sequences; a window cut from one starts later: a readout's clock reads it)."""

    features: torch.Tensor
    errors: torch.Tensor
    known: torch.Tensor
    start: torch.Tensor | None = None

    def __len__(self) -> int:
        return len(self.features)

    @property
    def starts(self) -> torch.Tensor:
        """``start``, zeros where it was not given."""
        return torch.zeros(len(self), dtype=torch.int64) if self.start is None else self.start

    def select(self, idx: torch.Tensor) -> Sequences:
        return Sequences(self.features[idx], self.errors[idx], self.known[idx], self.starts[idx])

    @staticmethod
    def cat(parts: list[Sequences]) -> Sequences:
        return Sequences(*(torch.cat(t) for t in zip(*(p[:3] + (p.starts,) for p in parts))))


@torch.no_grad()
def readout_sequences(
    observer: ResidualObserver, data: TrajectoryDataset, source: str = "residual", skip: int = 1,
    batch_size: int = 250, start=None, context: torch.Tensor | None = None,
) -> Sequences:
    """``data``'s sequences as a readout of ``source`` sees them, the observer started at
    ``start(batch)`` (a :data:`~manifold_nets.training_losses.StartFn`) or its own start; the
    steps ``k >= skip`` (and ``data.mask``, when it has one) count. An observer other than a
    :class:`ResidualObserver` (an ensemble, a filtered observer) is read by ``"readings"``.
    ``context`` ``(N, T, C)``: side information of each step, appended to the features (for a
    readout of ``context=C``)."""
    if context is not None and tuple(context.shape[:2]) != (len(data), data.length):
        raise ValueError(f"context must be ({len(data)}, {data.length}, C) for these sequences, "
                         f"got {tuple(context.shape)}.")
    if not isinstance(observer, ResidualObserver) and source != "readings":
        raise ValueError(f"a {type(observer).__name__} has no one core or measured factors to "
                         f"read; its readout reads source='readings', got {source!r}.")
    if isinstance(skip, bool) or not isinstance(skip, int) or not 1 <= skip <= data.length:
        raise ValueError(f"skip must be an integer in [1, {data.length}], got {skip!r}.")
    was = observer.training
    observer.eval()
    parts = []
    try:
        for s in range(0, len(data), batch_size):
            part = data[torch.arange(s, min(len(data), s + batch_size))]
            inputs = part.inputs if part.inputs.shape[-1] else None
            state = None if start is None else observer.init_state(len(part), estimate=start(part))
            if isinstance(observer, ResidualObserver):
                run = observer.rollout(part.measurements, inputs, state=state, keep_hidden=True)
                estimates = run.estimates
                z = readout_inputs(
                    observer, source, estimates[:, 1:].flatten(2), part.measurements, inputs,
                    tuple(h[:, 1:] for h in run.hidden),
                )
            else:  # an ensemble or a filtered observer: its own rollout, its readings
                estimates = observer(part.measurements, inputs, state=state)
                z = readout_inputs(observer, source, None, part.measurements, inputs, None)
            if context is not None:
                z = torch.cat([z, context[s : s + len(part)].to(z)], dim=-1)
            xi = tangent_errors(observer.group, estimates, part.states)[:, 1:]
            known = torch.zeros(xi.shape[:2], dtype=torch.bool)
            known[:, skip - 1 :] = True
            if part.mask is not None:
                known &= part.mask[:, 1:].bool()
            parts.append(Sequences(z, xi.double(), known))
    finally:
        observer.train(was)
    return Sequences.cat(parts)


def _nll(readout: CovarianceReadout, seqs: Sequences) -> tuple[torch.Tensor, int]:
    chol, log_diag = readout.log_scale(seqs.features, seqs.starts)
    nll = gaussian_nll(seqs.errors, chol, log_diag)
    return nll[seqs.known].sum(), int(seqs.known.sum())


def mean_nll(readout: CovarianceReadout, seqs: Sequences, batch_size: int = 200) -> float:
    """The mean negative log-likelihood (less ``n/2 log 2 pi``) of ``seqs``' known steps."""
    total, count = 0.0, 0
    with torch.no_grad():
        for s in range(0, len(seqs), batch_size):
            t, c = _nll(readout, seqs.select(torch.arange(s, min(len(seqs), s + batch_size))))
            total, count = total + float(t), count + c
    return total / max(count, 1)


def fit_covariance(
    readout: CovarianceReadout,
    train: Sequences,
    val: Sequences,
    epochs: int = 20,
    lr: float = 3e-3,
    batch_size: int = 16,
    seed: int = 0,
    show_progress: bool = True,
) -> list[dict]:
    """Fits ``readout`` to ``train`` (its inputs standardised by ``train``'s known steps, every
    ``P`` starting at the errors' own diagonal covariance), keeps the epoch of lowest validation NLL; returns the history (``epoch``,
    ``train_nll``, ``val_nll`` per epoch; epoch 0 is the start)."""
    for name, v in (("epochs", epochs), ("batch_size", batch_size)):
        if isinstance(v, bool) or not isinstance(v, int) or v < 1:
            raise ValueError(f"{name} must be a positive integer, got {v!r}.")
    if not (isinstance(lr, (int, float)) and math.isfinite(lr) and lr > 0):
        raise ValueError(f"lr must be a positive number, got {lr!r}.")
    if not train.known.any() or not val.known.any():
        raise ValueError("the training and validation sequences must have known steps.")
    readout.set_input_stats(train.features[train.known])
    readout.set_scale(train.errors[train.known].pow(2).mean(0).sqrt().clamp_min(1e-12))
    opt = torch.optim.Adam(readout.parameters(), lr=lr)
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, epochs)
    gen = torch.Generator().manual_seed(seed)
    best = mean_nll(readout, val)
    history = [{"epoch": 0, "train_nll": mean_nll(readout, train), "val_nll": best}]
    best_state = copy.deepcopy(readout.state_dict())
    for epoch in progress(range(1, epochs + 1), desc="covariance epochs", enabled=show_progress):
        order = torch.randperm(len(train), generator=gen)
        total, count = 0.0, 0
        for s in range(0, len(order), batch_size):
            t, c = _nll(readout, train.select(order[s : s + batch_size]))
            if not c:
                continue
            opt.zero_grad(set_to_none=True)
            (t / c).backward()
            torch.nn.utils.clip_grad_norm_(readout.parameters(), 1.0)
            opt.step()
            total, count = total + float(t.detach()), count + c
        sched.step()
        v = mean_nll(readout, val)
        history.append({"epoch": epoch, "train_nll": total / count, "val_nll": v})
        if v < best:
            best, best_state = v, copy.deepcopy(readout.state_dict())
    readout.load_state_dict(best_state)
    return history


def _nees_names(readout: CovarianceReadout) -> list[str]:
    return [*readout.group.factor_names, *(["joint"] if readout.structure == "joint" else [])]


def _batch_nees(readout: CovarianceReadout, seqs: Sequences, batch_size: int,
                level_scale: LevelScale | None = None):
    """Per batch of ``seqs``: ``{factor (and "joint" for a joint readout): the NEES at the
    batch's known steps}``, under ``level_scale`` when one is given."""
    from .calibration import nees

    group, names = readout.group, _nees_names(readout)
    for s in range(0, len(seqs), batch_size):
        part = seqs.select(torch.arange(s, min(len(seqs), s + batch_size)))
        chol = readout.log_scale(part.features, part.starts)[0]
        if level_scale is not None:
            start = level_scale.initial(readout.initial_cholesky((len(part),)))
            chol, _ = level_scale(chol, start, part.starts)
        cov = CovarianceReadout.covariance(chol)
        slices = {name: slice(None) if name == "joint" else group.tangent_slice(name) for name in names}
        yield {name: nees(part.errors[..., sl], cov[..., sl, sl])[part.known]
               for name, sl in slices.items()}


@torch.no_grad()
def factor_nees(readout: CovarianceReadout, seqs: Sequences, batch_size: int = 200,
                level_scale: LevelScale | None = None) -> dict[str, float]:
    """Per factor ``f`` of dimension ``d``: the mean of ``xi_f^T P_f^-1 xi_f / d`` over ``seqs``'
    known steps (1 when the readout, with ``level_scale`` when one is given, is calibrated on
    them)."""
    group, totals, count = readout.group, dict.fromkeys(readout.group.factor_names, 0.0), 0
    for q in _batch_nees(readout, seqs, batch_size, level_scale):
        for name in totals:
            totals[name] += float(q[name].sum()) / group.factor(name).tangent_dim
        count += len(q[group.factor_names[0]])
    if not count:
        raise ValueError("the sequences have no known step to measure the readout on.")
    return {name: t / count for name, t in totals.items()}


def scale_to_heldout(readout: CovarianceReadout, heldout: Sequences) -> dict[str, float]:
    """Scales each factor's block of ``P`` by its mean ``NEES / d`` on ``heldout`` (sequences
    neither fitted nor used to pick the epoch), so that it is 1 there: the likelihood fit's
    overall over- or under-confidence on fresh data, removed by one number per factor
    (:meth:`CovarianceReadout.rescale`; a ``"joint"`` readout takes their mean for all).
    Returns the scales applied."""
    scales = factor_nees(readout, heldout)
    if readout.structure == "joint":
        mean = sum(scales.values()) / len(scales)
        scales = dict.fromkeys(scales, mean)
    readout.rescale(scales)
    return scales


@torch.no_grad()
def step_nees(readout: CovarianceReadout, seqs: Sequences, batch_size: int = 200) -> dict:
    """Per factor ``f``: ``xi_f^T P_f^-1 xi_f`` at each of ``seqs``' known steps (1-D float64;
    a ``"joint"`` readout also gives ``"joint"``, the whole error's)."""
    batches = list(_batch_nees(readout, seqs, batch_size))
    return {name: torch.cat([q[name] for q in batches] or [torch.zeros(0, dtype=torch.float64)])
            for name in _nees_names(readout)}


def scale_to_share(readout: CovarianceReadout, heldout, sigma: float = 3.0) -> dict[str, float]:
    """Scales each factor's block of ``P`` so that the Gaussian share of ``heldout``'s errors
    lies inside its ``sigma``-sigma ellipsoid (97.1 % at 3 sigma for a 3-D error):
    :func:`~manifold_nets.calibration.conformal_scale` of their NEES. Where the errors have
    heavier tails than a Gaussian, the 1 and 2 sigma shares come out above theirs: it holds
    the share at ``sigma``, not the shape. ``heldout``: :class:`Sequences` neither fitted nor
    used to pick the epoch, or the NEES values per factor (:func:`step_nees` of other
    readouts, e.g. cross-fitted). A ``"joint"`` readout takes one scale from the whole
    error. Returns the scales applied."""
    from .calibration import conformal_scale

    q = step_nees(readout, heldout) if isinstance(heldout, Sequences) else dict(heldout)
    if readout.structure == "joint":
        scale = conformal_scale(q["joint"], readout.n, sigma)
        scales = dict.fromkeys(readout.group.factor_names, scale)
    else:
        scales = {name: conformal_scale(q[name], readout.group.factor(name).tangent_dim, sigma)
                  for name in readout.group.factor_names}
    readout.rescale(scales)
    return scales


class LevelSteps(NamedTuple):
    """Held-out steps reduced to what a level scale is fitted on: each factor's ``q = NEES / d``
    under the readout alone and its averaged level ``lbar`` (both ``(S, F)``, float64), and the
    step ``k`` ``(S,)``, over ``S`` known steps in sequence order; ``tau`` the steps the level is
    averaged over. Small beside the sequences (a few numbers a step), so a fit over many held-out
    sequences can roll them out a part at a time (:func:`level_steps` of each, then ``cat``)."""

    q: torch.Tensor
    lbar: torch.Tensor
    k: torch.Tensor
    tau: float

    @staticmethod
    def cat(parts: list[LevelSteps]) -> LevelSteps:
        if not parts or len({p.tau for p in parts}) != 1:
            raise ValueError("LevelSteps.cat: give one or more parts averaged over the same tau.")
        return LevelSteps(*(torch.cat(t) for t in zip(*(p[:3] for p in parts))), parts[0].tau)

    def nees(self, level_scale: LevelScale | None = None) -> torch.Tensor:
        """Each factor's mean ``NEES / d`` ``(F,)`` over the steps, scaled by ``level_scale``."""
        if level_scale is None:
            return self.q.mean(0)
        return (self.q * torch.exp(-level_scale.log_scale(self.lbar, self.k))).mean(0)


@torch.no_grad()
def level_steps(readout: CovarianceReadout, heldout: Sequences, tau: float = 100.0,
                batch_size: int = 200) -> LevelSteps:
    """``heldout``'s known steps as :func:`fit_level_scale` reads them (whole sequences, each
    averaged level starting at the start's)."""
    from .calibration import nees

    group, names = readout.group, readout.group.factor_names
    probe = LevelScale(group, torch.arange(2.0).repeat(len(names), 1),
                       torch.zeros(len(names), 2, 1, dtype=torch.float64), (), tau)
    qs, lbars, ks = [], [], []
    for s in range(0, len(heldout), batch_size):
        part = heldout.select(torch.arange(s, min(len(heldout), s + batch_size)))
        chol = readout.log_scale(part.features, part.starts)[0]
        cov = CovarianceReadout.covariance(chol)
        lbar = probe.averaged(probe.level(chol), probe.initial(readout.initial_cholesky((len(part),))))
        q = torch.stack([nees(part.errors[..., sl], cov[..., sl, sl]) / (sl.stop - sl.start)
                         for sl in map(group.tangent_slice, names)], -1)
        k = part.starts.double().unsqueeze(1) + torch.arange(1, chol.shape[1] + 1, dtype=torch.float64)
        qs.append(q[part.known])
        lbars.append(lbar[part.known])
        ks.append(k[part.known])
    return LevelSteps(torch.cat(qs), torch.cat(lbars), torch.cat(ks), probe.tau)


@torch.no_grad()
def fit_level_scale(
    readout: CovarianceReadout, heldout: Sequences | LevelSteps, knots: int = 8, tau: float = 100.0,
    clock: tuple[float, ...] = (10.0, 50.0, 250.0, 1000.0), thin: int = 1, ridge: float = 1e-4,
    batch_size: int = 200,
) -> LevelScale:
    """A :class:`~manifold_nets.observer.LevelScale` of ``readout`` fitted to ``heldout``
    (sequences neither fitted nor used to pick the epoch or the scale, or their
    :class:`LevelSteps`, averaged over ``tau``): per factor, ``knots`` points at the 0.1 ... 99.9 %
    quantiles of the held-out averaged levels (so every hat has steps under it, and a level
    between two clusters of them is interpolated between fitted knots), and the weights that
    minimise the mean Gaussian negative log-likelihood of the scaled covariance over the known
    steps (every ``thin``-th), ``mean(u + q exp(-u)) + ridge |w|^2 / 2`` with ``q = NEES / d``
    (one factor's basis ``(steps, knots (1 + len(clock)))`` at a time, in float64: thin long
    sets): convex in ``w``, solved by damped Newton steps. At the minimum the scaled ``NEES / d``
    averages 1 on every basis function, so on the held-out steps the level is right at every
    averaged level and along the clock (from the first known step on; earlier steps take its
    scale)."""
    if isinstance(knots, bool) or not isinstance(knots, int) or knots < 2:
        raise ValueError(f"fit_level_scale: knots must be an integer >= 2, got {knots!r}.")
    if isinstance(thin, bool) or not isinstance(thin, int) or thin < 1:
        raise ValueError(f"fit_level_scale: thin must be a positive integer, got {thin!r}.")
    group, names = readout.group, readout.group.factor_names
    zeros = torch.zeros(len(names), knots, 1 + len(clock), dtype=torch.float64)
    LevelScale(group, torch.arange(float(knots)).repeat(len(names), 1), zeros, clock, tau)  # checks
    if not isinstance(heldout, LevelSteps):
        heldout = level_steps(readout, heldout, tau, batch_size)
    elif heldout.tau != float(tau):
        raise ValueError(f"fit_level_scale: the steps' levels are averaged over tau={heldout.tau:g}, "
                         f"not {float(tau):g}; reduce them again with level_steps(..., tau={tau!r}).")
    q, lbar, k = (t[::thin] for t in heldout[:3])
    if len(q) < 10 * knots * (1 + len(clock)):
        raise ValueError(f"fit_level_scale: {len(q)} known steps are too few for {knots} knots "
                         f"and a clock of {len(clock)}; give more held-out sequences.")
    every = lbar[:: max(1, len(lbar) // 200_000)]  # torch.quantile's input has a size limit
    grid = torch.linspace(0.001, 0.999, knots, dtype=torch.float64)
    at = torch.quantile(every, grid, dim=0).T.contiguous()  # (F, knots)
    if not bool((at.diff(dim=1) > 0).all()):
        raise ValueError("fit_level_scale: the readout's level hardly varies over the held-out "
                         "steps (its quantiles coincide); use fewer knots, or a constant scale "
                         "(scale_to_heldout).")
    first = int(k.min())
    scale = LevelScale(group, at, zeros, clock, tau, first)
    weights = torch.stack([  # one factor's basis at a time: (steps, K (1 + len(clock))) each
        _newton_log_scale(q[:, f], hat_clock_basis(scale.knots[f:f + 1], scale.taus, first,
                                                   lbar[:, f:f + 1], k)[:, 0].flatten(1), ridge)
        for f in range(len(names))]).reshape(zeros.shape)
    return LevelScale(group, scale.knots, weights, clock, tau, first)


def _newton_log_scale(q: torch.Tensor, phi: torch.Tensor, ridge: float) -> torch.Tensor:
    """``w`` minimising ``mean(phi w + q exp(-phi w)) + ridge |w|^2 / 2`` (damped Newton)."""
    def loss(w):
        u = phi @ w
        return float((u + q * torch.exp(-u)).mean() + 0.5 * ridge * w @ w)

    w = torch.zeros(phi.shape[1], dtype=torch.float64)
    eye = torch.eye(len(w), dtype=torch.float64)
    for _ in range(100):
        r = q * torch.exp(-phi @ w)
        grad = phi.T @ (1 - r) / len(q) + ridge * w
        if float(grad.abs().max()) < 1e-9:
            return w
        step = torch.linalg.solve((phi * r[:, None]).T @ phi / len(q) + ridge * eye, grad)
        t, now = 1.0, loss(w)
        while loss(w - t * step) > now - 0.25 * t * float(grad @ step) and t > 1e-6:
            t /= 2
        w = w - t * step
    raise RuntimeError("fit_level_scale: the Newton iteration did not converge in 100 steps.")


#: The format of a readout file (:func:`save_readout`).
READOUT_FORMAT = "manifold_nets.covariance/1"


def save_readout(path, readout: CovarianceReadout, observer: str = "",
                 level_scale: LevelScale | None = None) -> None:
    """Writes ``readout`` (its signature and weights; ``observer`` a note of which observer it
    belongs to; ``level_scale``, when given, its signature, knots and weights) to ``path``,
    atomically."""
    from .atomic import atomic_open

    payload = {
        "format": READOUT_FORMAT, "signature": readout.signature(), "observer": str(observer),
        "model": {k: v.detach().cpu() for k, v in readout.state_dict().items()},
    }
    if level_scale is not None:
        payload["level_scale"] = {"signature": level_scale.signature(),
                                  "knots": level_scale.knots.detach().cpu(),
                                  "weights": level_scale.weights.detach().cpu()}
    with atomic_open(path, "wb") as f:
        torch.save(payload, f)


def load_readout(path, observer: ResidualObserver):
    """The :class:`~manifold_nets.observer.CalibratedObserver` of ``observer`` and the readout at
    ``path`` (from :func:`save_readout`; read with ``torch.load(weights_only=True)``, its
    signature checked against ``observer`` before anything is built, its weights by
    :func:`manifold_nets.checkpoint.load_state`). A :class:`~manifold_nets.checkpoint.
    CheckpointError` names the file and the problem."""
    from pathlib import Path

    from .checkpoint import CheckpointError, load_state
    from .observer import CalibratedObserver
    from .observer.covariance import (
        MAX_CONTEXT, MAX_MEMORY, SOURCES, STRUCTURES, check_clock, input_width,
    )

    path = Path(path)
    if not path.is_file():
        raise CheckpointError(f"no covariance readout at {path}; fit one first or fix the path.")
    try:
        ckpt = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as err:  # unpickling errors come in many types
        raise CheckpointError(
            f"{path} is not a loadable readout ({type(err).__name__}: {str(err)[:300]})."
        ) from None
    if not isinstance(ckpt, dict) or ckpt.get("format") != READOUT_FORMAT:
        raise CheckpointError(f"{path} is not a covariance readout (format {READOUT_FORMAT!r}).")
    sig, state = ckpt.get("signature"), ckpt.get("model")
    if not isinstance(sig, dict) or not isinstance(state, dict):
        raise CheckpointError(f"{path}: the signature or the weights are missing.")
    # what the file may choose, checked; the rest must be what this observer fixes
    source, structure, memory = sig.get("source"), sig.get("structure"), sig.get("memory")
    context = sig.get("context", 0)
    try:
        clock = check_clock(sig.get("clock", ()))
    except ValueError:
        clock = None
    choices_ok = (source in SOURCES and structure in STRUCTURES and type(memory) is int
                  and 0 <= memory <= MAX_MEMORY and clock is not None
                  and type(context) is int and 0 <= context <= MAX_CONTEXT)
    want = {"type": "cholesky", "group": repr(observer.group), "source": source,
            "structure": structure, "memory": memory,
            "width": input_width(observer, source) if source == "readings" or (
                source in SOURCES and isinstance(observer, ResidualObserver)) else None,
            **({"clock": sig.get("clock")} if clock else {}),
            **({"context": context} if choices_ok and context else {})}
    if not choices_ok or sig != want:
        diff = sorted(k for k in set(sig) | set(want) if sig.get(k) != want.get(k))
        raise CheckpointError(
            f"{path}: the readout does not fit this observer (its signature {sig!r}; "
            f"{', '.join(diff) or 'source, structure or memory'} differ from {want!r})."[:2000]
        )
    readout = CovarianceReadout(observer.group, want["width"], structure, memory, source, clock,
                                context)
    load_state(readout, {"model": state}, path)
    return CalibratedObserver(observer, readout, _load_level_scale(ckpt, readout.group, path))


def _load_level_scale(ckpt: dict, group, path) -> LevelScale | None:
    """The file's level scale (``None`` where it has none), checked before it is built."""
    from .checkpoint import CheckpointError

    if "level_scale" not in ckpt:
        return None
    entry = ckpt["level_scale"]
    sig = entry.get("signature") if isinstance(entry, dict) else None
    knots, weights = (entry.get(k) if isinstance(entry, dict) else None for k in ("knots", "weights"))
    if not (isinstance(sig, dict) and set(sig) == {"knots", "clock", "tau", "first"}
            and isinstance(knots, torch.Tensor) and isinstance(weights, torch.Tensor)
            and knots.dim() == 2 and knots.shape[1] == sig["knots"]):
        raise CheckpointError(f"{path}: the level scale is malformed (it needs a signature of "
                              "knots, clock, tau and first, and its knots and weights as tensors).")
    try:
        return LevelScale(group, knots, weights, tuple(sig["clock"]), sig["tau"], sig["first"])
    except (TypeError, ValueError) as err:
        raise CheckpointError(f"{path}: the level scale does not fit the readout ({err})") from None
