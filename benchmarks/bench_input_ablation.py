"""How much a trained observer uses an input it reads last: the clock (``model.clock``), the
framed innovation (``model.innovation_frame``) or the prior's drive (``model.prior_drive``).

The observer (a run folder or a shipped one) rolls over ``--sequences`` new sequences of 1000
steps of its own system (seed 5) at each sigma, once as trained and once with the first GRU
layer's weights on that input's columns set to zero (what it computed before
``train.init_from`` widened it); the table gives the mean errors over steps >= 10 and the change,
and the header the norms of those weight columns against the other columns'. A change near zero
says the trained weights do not use the input::

    python benchmarks/bench_input_ablation.py RUN --input prior_drive --sigmas 0.1 0.3 \
        [--sequences 300] [--out FILE]      # about 20 s per sigma on one core
"""

from __future__ import annotations

import argparse
from pathlib import Path

import torch

import manifold_nets_examples.rigid_body  # noqa: F401  (registers the systems)
from manifold_nets import load_observer
from manifold_nets.cores import GRUCore
from manifold_nets.evaluation import evaluate


def input_columns(obs, name: str) -> slice:
    """The columns of the core's input that ``name`` (an appended input) fills."""
    appended = obs.inputs.appended()
    names = [entry[0] for entry in appended]
    if name not in names:
        raise SystemExit(f"the observer reads no {name!r} input; it appends {names or 'none'}.")
    if not isinstance(obs.core, GRUCore):
        raise SystemExit("the ablation zeroes a GRU core's first-layer weights; this core is not one.")
    i = names.index(name)
    stop = obs.core.input_size - sum(width for *_, width in appended[i + 1:])
    return slice(stop - appended[i][2], stop)


def errors(obs, system, data) -> dict[str, float]:
    row = evaluate(obs, data, system).row
    return {k[: -len(" est")]: v for k, v in row.items() if k.endswith(" est")}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run")
    ap.add_argument("--input", required=True, choices=["clock", "innovation_frame", "prior_drive"])
    ap.add_argument("--sigmas", type=float, nargs="+", default=[0.1, 0.3])
    ap.add_argument("--sequences", type=int, default=300)
    ap.add_argument("--out", default=str(Path(__file__).parent / "results" / "input_ablation.md"))
    args = ap.parse_args()
    torch.set_num_threads(1)
    obs, system, _ = load_observer(args.run)
    obs.eval()
    cols = input_columns(obs, args.input)
    weight = obs.core.gru.weight_ih_l0
    norms = weight.detach().norm(dim=0)
    others = torch.cat([norms[: cols.start], norms[cols.stop :]])
    lines = [
        f"# `{args.input}` zeroed in a trained observer",
        "",
        f"`python benchmarks/bench_input_ablation.py {args.run} --input {args.input} --sigmas "
        f"{' '.join(map(str, args.sigmas))} --sequences {args.sequences}` (columns "
        f"{cols.start}-{cols.stop - 1} of the core's input; {args.sequences} x 1000 per sigma of "
        f"{type(system).__name__}, seed 5, steps >= 10; torch {torch.__version__}, one thread)",
        "",
        f"Norm of each of its weight columns: {', '.join(f'{v:.4f}' for v in norms[cols].tolist())}; "
        f"the other {len(others)} columns: {float(others.mean()):.4f} on average.",
        "",
        "| sigma | factor | as trained | input zeroed | change |",
        "|---:|---|---:|---:|---:|",
    ]
    for sigma in args.sigmas:
        data = system.simulate(args.sequences, 1000, sigma, torch.Generator().manual_seed(5))
        trained = errors(obs, system, data)
        kept = weight[:, cols].detach().clone()
        with torch.no_grad():
            weight[:, cols] = 0
        zeroed = errors(obs, system, data)
        with torch.no_grad():
            weight[:, cols] = kept
        for k in trained:
            row = (f"| {sigma:g} | {k} | {trained[k]:.4f} | {zeroed[k]:.4f} | "
                   f"{100 * (zeroed[k] / trained[k] - 1):+.1f} % |")
            print(row, flush=True)
            lines.append(row)
    Path(args.out).write_text("\n".join(lines) + "\n")
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
