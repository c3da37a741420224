"""A trained observer's weights under other centerings (``model.centering``, the centred update
``v = T(z) - c T(z^0)``; docs/comparison.md, "The centred update"), with no training, and with
the centring ramped in over the first ``K`` steps (``model.centering_ramp``, ``--ramp``).

Each observer (a run folder or a shipped one) is rebuilt at every ``c`` given, with the same
weights, and rolls over 200 new sequences of 1000 steps of its system (seed 5) at sigma 0, 0.1
and 0.3 from the identity; the table gives the mean ``||Rhat - R||_F``, ``||phat - p||`` and
``||bhat_Omega - b_Omega||`` over steps 10-1000 (as evaluated) and over steps 500-1000 (settled)::

    python benchmarks/bench_centering.py RUN --centering 0 0.3 0.7 1 [--ramp 0 50] [--out FILE]
    # ~1 min per (c, K)
"""

from __future__ import annotations

import argparse
from pathlib import Path

import torch
from omegaconf import OmegaConf

import manifold_nets_examples.rigid_body  # noqa: F401  (registers the systems)
from manifold_nets import load_observer
from manifold_nets.builders import build_observer

SIGMAS = (0.0, 0.1, 0.3)


def rows(
    run: str, centerings: list[float], ramps=(0,), n: int = 200, t: int = 1000, seed: int = 5
):
    obs, system, cfg = load_observer(run)
    data = {s: system.simulate(n, t, s, torch.Generator().manual_seed(seed)) for s in SIGMAS}
    for c, ramp in ((c, r) for c in centerings for r in ramps if c or not r):
        model = OmegaConf.merge(cfg.model, {"centering": float(c), "centering_ramp": int(ramp)})
        other = build_observer(
            system.group, system.measurement_dim, system.input_dim, model, import_core=False,
            dt=getattr(system, "dt", None), system=system,
        )
        other.load_state_dict(obs.state_dict())
        other.eval()
        for sigma in SIGMAS:
            d = data[sigma]
            with torch.inference_mode():
                est = other(d.measurements)
            cells = []
            for span in (slice(10, t + 1), slice(t // 2, t + 1)):
                for a, b in ((0, 9), (9, 12), (12, 15)):
                    err = (est[..., a:b] - d.states[..., a:b]).norm(dim=-1)[:, span].mean()
                    cells.append(f"{float(err):.4g}")
            yield f"| {c:g} | {ramp} | {sigma} | " + " | ".join(cells) + " |"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("run", help="a run folder or checkpoint")
    parser.add_argument("--centering", type=float, nargs="+", required=True)
    parser.add_argument("--ramp", type=int, nargs="+", default=[0], help="centering_ramp K")
    parser.add_argument("--out", default="benchmarks/results/centering.md")
    args = parser.parse_args()
    torch.set_num_threads(1)
    lines = [
        f"# `{args.run}` at other centerings, no training (`python benchmarks/bench_centering.py "
        f"{args.run} --centering {' '.join(f'{c:g}' for c in args.centering)}"
        f"{' --ramp ' + ' '.join(map(str, args.ramp)) if args.ramp != [0] else ''}`)",
        "",
        "200 sequences x 1000 steps per sigma (seed 5), from the identity. Means over steps "
        "10-1000 (as evaluated) and 500-1000 (settled).",
        "",
        "| centering | ramp | sigma | R, k >= 10 | p | b_Omega | R, k >= 500 | p | b_Omega |",
        "|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for row in rows(args.run, args.centering, args.ramp):
        lines.append(row)
        print(row, flush=True)
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text("\n".join(lines) + "\n")
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
