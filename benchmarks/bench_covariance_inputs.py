"""What a covariance readout should read: the measured factors' residuals, the core's hidden
state, or both; with and without a memory of its own.

Run by hand from the repository root (not by CI)::

    python benchmarks/bench_covariance_inputs.py            # writes benchmarks/results/covariance_inputs.md
    python benchmarks/bench_covariance_inputs.py --train 8 --epochs 2 --out /tmp/ci.md   # a quick look

On ``zoo:rigid_body/nominal`` (frozen), ``--train`` sequences of 300 steps per noise level
0.1 ... 0.5 (seeds 100 + i) to fit, a quarter as many (seeds 200 + i) to validate, and 100 fresh
sequences per level (seed 999) to score: each variant's best validation NLL (the mean of
``0.5 xi^T P^-1 xi + 0.5 log det P`` over the known steps k >= 10, less the constant), and the
ANEES of R at sigma 0.1 and 0.5 (1 is calibrated; a readout that cannot tell the noise levels
apart is far below 1 at 0.1 and above at 0.5). Every variant: per-factor blocks, 30 epochs,
lr 3e-3, batches of 4 sequences, the same data.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import torch

from manifold_nets import load_observer
from manifold_nets.calibration import calibration
from manifold_nets.covariance_training import Sequences, fit_covariance, readout_sequences
from manifold_nets.observer import CovarianceReadout
from manifold_nets.threads import use_threads

SIGMAS = (0.1, 0.2, 0.3, 0.4, 0.5)
#: name -> (inputs, memory)
VARIANTS = {
    "hidden, memoryless": ("hidden", 0),
    "hidden, GRU 32": ("hidden", 32),
    "residual, memoryless": ("residual", 0),
    "residual, GRU 32": ("residual", 32),
    "hidden + residual, GRU 32": ("both", 32),
}


def _data(observer, system, n, seed0, sigmas=SIGMAS, skip=10):
    """Per source: the sequences of every noise level of ``sigmas``, concatenated."""
    out = {"hidden": [], "residual": []}
    for i, s in enumerate(sigmas):
        data = system.simulate(n, 300, s, torch.Generator().manual_seed(seed0 + i))
        for source in out:
            out[source].append(readout_sequences(observer, data, source, skip=skip))
    out = {k: Sequences.cat(v) for k, v in out.items()}
    h, r = out["hidden"], out["residual"]
    out["both"] = Sequences(torch.cat([h.features, r.features], -1), r.errors, r.known)
    return out


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--train", type=int, default=40)
    p.add_argument("--epochs", type=int, default=30)
    p.add_argument("--out", default="benchmarks/results/covariance_inputs.md")
    args = p.parse_args()
    use_threads()
    observer, system, _ = load_observer("zoo:rigid_body/nominal")
    train = _data(observer, system, args.train, 100)
    val = _data(observer, system, max(2, args.train // 4), 200)
    test = {s: _data(observer, system, 100, 999 + 10 * i, (s,)) for i, s in enumerate((0.1, 0.5))}
    rows = []
    for name, (source, memory) in VARIANTS.items():
        t0 = time.perf_counter()
        width = train[source].features.shape[-1]
        torch.manual_seed(0)  # the initial weights (torch seeds itself at random per process)
        readout = CovarianceReadout(observer.group, width, "factor", memory,
                                    "hidden" if source == "both" else source)
        history = fit_covariance(readout, train[source], val[source], epochs=args.epochs,
                                 lr=3e-3, batch_size=4, show_progress=False)
        anees = []
        with torch.no_grad():
            for sigma in (0.1, 0.5):
                seqs = test[sigma][source]
                chol, _ = readout.log_scale(seqs.features)
                cov = chol @ chol.transpose(-1, -2)
                k = seqs.known[0].nonzero().squeeze(-1)
                anees.append(calibration(observer.group, seqs.errors[:, k], cov[:, k])["R"].anees)
        best = min(h["val_nll"] for h in history)
        rows.append((name, history[0]["val_nll"], best, *anees, time.perf_counter() - t0))
        print(rows[-1], flush=True)
    lines = [
        "# What a covariance readout reads", "",
        f"`python benchmarks/bench_covariance_inputs.py --train {args.train} --epochs "
        f"{args.epochs}` (zoo:rigid_body/nominal frozen; {args.train} x 300 steps per sigma "
        "0.1 ... 0.5 to fit; a shared 2-core CPU).", "",
        "| readout | val NLL at the start | best val NLL | ANEES R, sigma 0.1 | ANEES R, sigma 0.5 | seconds |",
        "|---|---|---|---|---|---|",
        *[f"| {n} | {a:.3f} | {b:.3f} | {c:.3f} | {d:.3f} | {e:.0f} |" for n, a, b, c, d, e in rows],
        "",
    ]
    Path(args.out).write_text("\n".join(lines))
    print("\n".join(lines))


if __name__ == "__main__":
    main()
