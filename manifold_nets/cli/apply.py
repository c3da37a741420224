"""``python -m manifold_nets.cli.apply``: a trained observer over a data file, estimates to a file.

::

    python -m manifold_nets.cli.apply outputs/default/<run id> data/recording.npz --out est.npz
    python -m manifold_nets.cli.apply run/checkpoints/best.pt data.npz --out est.npz --chunk 500

The observer comes from a run folder or a checkpoint (:func:`manifold_nets.load_observer`: the
system and the model rebuilt from the run's config, nothing a file names executed); the data is
a dataset file of the system's own format (:func:`manifold_nets.load_dataset`). The estimates
``xhat_0 .. xhat_T`` of every sequence, from the identity, are written atomically to a
pickle-free ``.npz``: ``estimates`` ``(N, T+1, *element_shape)`` float64 and ``meta``, a JSON
string (the observer's signature, the checkpoint, the data file). Read it back with
``numpy.load(path, allow_pickle=False)``.

The sequences are run ``--batch-size`` at a time and each batch ``--chunk`` steps at a time
(the observer's state carried over), with a progress bar on a terminal, on one torch thread
unless ``--threads`` (or ``OMP_NUM_THREADS``) asks for more (:mod:`manifold_nets.threads`).
An observer whose system has a pre-filter of the readings (one it was trained behind,
:meth:`manifold_nets.System.readings_filter`, e.g. ``zoo:broad/attitude``'s) reads the file's
readings through it (:class:`manifold_nets.observer.FilteredObserver`; the filter's state carried
over the chunks like the observer's); ``--preprocessed`` says they went through it already and
skips it. A system that names a ``preprocessing`` but has no filter to run is refused unless
``--preprocessed``. ``--out`` is checked before any work (:func:`manifold_nets.destination.check_destination`);
non-finite estimates are an error and nothing is written. ``mn-apply`` ends an error with
``error: ...`` and exit status 1, not a traceback.

The run's system is found by the registry: the project's example systems and those an installed
package declares as entry points (:mod:`manifold_nets.plugins`) load with no import by hand; the
run may be a zoo entry, ``zoo:rigid_body/nominal``.
"""

from __future__ import annotations

import argparse
import json
import logging
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import torch

from manifold_nets.atomic import atomic_open
from manifold_nets.data import load_dataset
from manifold_nets.destination import check_destination
from manifold_nets.loading import load_observer
from manifold_nets.observer import FilteredObserver, ResidualObserver, with_readings_filter
from manifold_nets.progress import progress
from manifold_nets.threads import use_threads

__all__ = ["apply_observer", "main", "run"]

log = logging.getLogger(__name__)


def apply_observer(
    observer: ResidualObserver | FilteredObserver,
    measurements: torch.Tensor,
    inputs: torch.Tensor | None = None,
    batch_size: int = 256,
    chunk: int = 1000,
    show_progress: bool = True,
) -> torch.Tensor:
    """The estimates ``(N, T+1, *element_shape)`` of ``observer`` over ``measurements``
    ``(N, T, l)`` (and ``inputs``), ``batch_size`` sequences and ``chunk`` steps at a time."""
    n, t = measurements.shape[:2]
    starts = [(s, k) for s in range(0, n, batch_size) for k in range(0, t, chunk)]
    out = torch.empty(n, t + 1, *observer.group.element_shape, dtype=observer.state_dtype)
    state = None
    with torch.inference_mode():
        for s, k in progress(starts, desc="apply", enabled=show_progress):
            e = min(n, s + batch_size)
            y = measurements[s:e, k : k + chunk]
            u = None if inputs is None or not observer.input_dim else inputs[s:e, k : k + chunk]
            est, state = observer(y, u, state=None if k == 0 else state, return_state=True)
            out[s:e, k : k + est.shape[1]] = est.cpu()
    return out


def run(argv: Sequence[str] | None = None) -> Path:
    """The command line (module docstring). Returns the file written."""
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("model", help="a run folder of the train command, or a checkpoint file")
    p.add_argument("data", help="a dataset file (.npz) of the system the observer was trained on")
    p.add_argument("--out", required=True, help="where to write the estimates (.npz)")
    p.add_argument("--batch-size", type=int, default=256, help="sequences run at once")
    p.add_argument("--chunk", type=int, default=1000, help="steps run at once")
    p.add_argument("--threads", type=int, default=None,
                   help="torch threads (default: one, or OMP_NUM_THREADS)")
    p.add_argument("--no-progress", action="store_true")
    p.add_argument("--preprocessed", action="store_true",
                   help="the data file's readings went through the observer's pre-filter "
                   "(its system's preprocessing) already: do not filter them again")
    a = p.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    if a.batch_size < 1 or a.chunk < 1:
        p.error("--batch-size and --chunk must be positive")
    if a.threads is not None and a.threads < 1:
        p.error(f"--threads must be an integer >= 1 (or left out), got {a.threads}")
    try:
        out = check_destination(a.out, suffixes=(".npz",))
    except ValueError as err:
        p.error(str(err))
    use_threads(a.threads)
    observer, system, _ = load_observer(a.model)
    observer = _prefiltered(observer, system, a)
    data = load_dataset(a.data, group=system.group)
    log.info("%s: %d sequences of %d steps", a.data, len(data), data.length)
    dt = data.meta.get("dt") if isinstance(data.meta, dict) else None
    if isinstance(observer, FilteredObserver) and isinstance(dt, (int, float)) \
            and abs(dt - system.dt) > 1e-6 * system.dt:  # fmt: skip
        log.warning("warning: %s has a step of %g s, the observer's system %g s: its pre-filter "
                    "runs at the system's rate", a.data, dt, system.dt)
    est = apply_observer(
        observer, data.measurements, data.inputs, a.batch_size, a.chunk, not a.no_progress
    )
    bad = int((~torch.isfinite(est.flatten(2)).all(-1)).sum())
    if bad:
        raise ValueError(
            f"{a.model} gave non-finite estimates at {bad} of {est.shape[0] * est.shape[1]} steps "
            f"(NaN or Inf weights, or a diverging observer); nothing was written to {out}."
        )
    meta = {
        "model": str(a.model),
        "data": str(a.data),
        "signature": observer.signature(),
        "element_shape": list(system.group.element_shape),
    }
    with atomic_open(out, "wb") as f:
        np.savez(f, estimates=est.double().numpy(), meta=np.array(json.dumps(meta)))
    log.info("estimates %s written to %s", tuple(est.shape), out)
    return out


def _prefiltered(observer: ResidualObserver, system, a: argparse.Namespace):
    """``observer`` behind its system's readings filter unless ``--preprocessed``; an error when
    the system names a preprocessing it gives no filter for (and not ``--preprocessed``)."""
    if a.preprocessed:
        return observer
    filtered = with_readings_filter(observer, system)
    if filtered is not observer:
        log.info("readings pre-filtered as %s's system says: %s", a.model,
                 getattr(system, "preprocessing", None) or filtered.prefilter.name)
        return filtered
    pre = getattr(system, "preprocessing", None)
    if pre:
        raise ValueError(
            f"{a.model}'s observer was trained on readings preprocessed as: {pre}, and its "
            f"system gives no readings_filter() to run; preprocess {a.data}'s readings so (then "
            "pass --preprocessed), or use the command named."
        )
    return observer


def main(argv: Sequence[str] | None = None) -> int:
    """The console script ``mn-apply``: :func:`run`, exit status 0; an error (a file that is
    refused, non-finite estimates) ends it with ``error: ...`` and status 1."""
    try:
        run(argv)
    except (ValueError, OSError) as err:
        raise SystemExit(f"error: {err}") from None
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
