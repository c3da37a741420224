"""The learned observer's error floor: its errors when the measurements are exact (sigma 0),
where the raw measurement's attitude and position errors are zero (docs/comparison.md, "The gain
head").

Each observer (a run folder or a shipped one) rolls over 200 new sequences of 1000 steps of its
system (seed 5) at sigma 0, 0.1 and 0.3, from the identity (as evaluated) and from the true
state; the table gives the mean ``||Rhat - R||_F`` and ``||bhat_Omega - b_Omega||`` over steps
500-1000, the median over sequences of the per-sequence R error, the bias error one step
after a start at the truth, and the bias error 1 and 10 steps after the estimate is reset to the
truth at step 500 with the hidden state kept (what the observer does with a state that needs no
correction, once it has settled)::

    python benchmarks/bench_error_floor.py LABEL=RUN [LABEL=RUN ...]   # ~1 min per observer
"""

from __future__ import annotations

import argparse
from pathlib import Path

import torch

import manifold_nets_examples.rigid_body  # noqa: F401  (registers the systems)
from manifold_nets import load_observer

SIGMAS = (0.0, 0.1, 0.3)


def floor_rows(label: str, run: str, n: int = 200, t: int = 1000, seed: int = 5) -> list[str]:
    obs, system, _ = load_observer(run)
    rows = []
    for sigma in SIGMAS:
        data = system.simulate(n, t, sigma, torch.Generator().manual_seed(seed))
        cells = []
        for start in ("identity", "truth"):
            state = obs.init_state(n)
            if start == "truth":
                state = state._replace(estimate=data.states[:, 0].clone())
            with torch.inference_mode():
                est = obs(data.measurements, state=state)
            r = (est[..., :9] - data.states[..., :9]).norm(dim=-1)
            b = (est[..., 12:15] - data.states[..., 12:15]).norm(dim=-1)
            late = slice(t // 2, t + 1)
            cells += [
                f"{float(r[:, late].mean()):.4f}",
                f"{float(r[:, late].mean(1).median()):.4f}",
                f"{float(b[:, late].mean()):.4f}",
            ]
            if start == "truth":
                cells.append(f"{float(b[:, 1].mean()):.3f}")
        cells += [f"{e:.4f}" for e in reset_errors(obs, data, t // 2)]
        rows.append(f"| {label} | {sigma} | " + " | ".join(cells) + " |")
    return rows


def reset_errors(obs, data, k: int, after: tuple[int, ...] = (1, 10)) -> list[float]:
    """The mean b_Omega error ``after`` steps past a reset of the estimate to the truth at step
    ``k``, the hidden state that of the run from the identity up to ``k``."""
    with torch.inference_mode():
        _, state = obs(data.measurements[:, :k], return_state=True)
        state = state._replace(estimate=data.states[:, k].clone())
        est = obs(data.measurements[:, k:], state=state)
    b = (est[..., 12:15] - data.states[:, k:, 12:15]).norm(dim=-1)
    return [float(b[:, j].mean()) for j in after]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("observers", nargs="+", help="LABEL=RUN (a run folder or checkpoint)")
    parser.add_argument("--out", default="benchmarks/results/error_floor.md")
    args = parser.parse_args()
    torch.set_num_threads(1)
    lines = [
        "# The learned observer's error floor (`python benchmarks/bench_error_floor.py "
        + " ".join(args.observers) + "`)",
        "",
        "200 sequences x 1000 steps per sigma (seed 5); means over steps 500-1000. From the "
        "identity: as the observer is evaluated; from the truth: started at the true state "
        "(true biases). At sigma 0 the measurement's R and p errors are zero.",
        "",
        "| observer | sigma | R, from identity | R median over sequences | b_Omega | R, from the "
        "truth | R median | b_Omega | b_Omega after 1 step from the truth | b_Omega 1 step after a "
        "reset to the truth at step 500 | 10 steps after |",
        "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for item in args.observers:
        label, _, run = item.partition("=")
        if not run:
            parser.error(f"{item!r}: give LABEL=RUN")
        lines += floor_rows(label, run)
        print("\n".join(lines[-len(SIGMAS):]), flush=True)
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text("\n".join(lines) + "\n")
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
