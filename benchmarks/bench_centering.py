"""A trained observer's weights under other centerings (``model.centering``, the centred update
``v = T(z) - c T(z^0)``; docs/comparison.md, "The centred update"), with no training, and with
the centring ramped in over the first ``K`` steps (``model.centering_ramp``, ``--ramp``), and with
some factors centred by their own ``c_f`` (``model.centering_factors``, ``--factors``).

Each observer (a run folder or a shipped one) is rebuilt at every ``c`` given, with the same
weights, and rolls over 200 new sequences of 1000 steps of its system (seed 5) at sigma 0, 0.1
and 0.3 from the identity; the table gives the mean ``||Rhat - R||_F``, ``||phat - p||`` and
``||bhat_Omega - b_Omega||`` (and ``||bhat_v - b_v||`` with ``--factors``) over steps 10-1000
(as evaluated) and over steps 500-1000 (settled)::

    python benchmarks/bench_centering.py RUN --centering 0 0.3 0.7 1 [--ramp 0 50] [--out FILE]
    python benchmarks/bench_centering.py RUN --centering 0.85 --ramp 50 \
        --factors none b_omega=0.95,b_v=0.95 b_omega=1      # "none": every factor at c
    # ~1 min per (c, K, factors)
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


def parse_factors(text: str) -> dict[str, float]:
    """``"b_omega=0.95,b_v=0.95"`` -> ``{"b_omega": 0.95, "b_v": 0.95}``; ``"none"`` -> ``{}``."""
    if text == "none":
        return {}
    out = {}
    for item in text.split(","):
        name, _, value = item.partition("=")
        try:
            out[name.strip()] = float(value)
        except ValueError:
            raise SystemExit(f"--factors {text!r}: expected NAME=C[,NAME=C..], e.g. b_v=0.95")
    return out


def rows(
    run: str, centerings: list[float], ramps=(0,), n: int = 200, t: int = 1000, seed: int = 5,
    factor_sets=None,
):
    obs, system, cfg = load_observer(run)
    data = {s: system.simulate(n, t, s, torch.Generator().manual_seed(seed)) for s in SIGMAS}
    spans = ((0, 9), (9, 12), (12, 15)) + (((15, 18),) if factor_sets else ())
    variants = ((c, r, f) for c in centerings for r in ramps for f in factor_sets or [None])
    for c, ramp, factors in ((c, r, f) for c, r, f in variants if c or not r):
        change = {"centering": float(c), "centering_ramp": int(ramp)}
        if factors is not None:
            change["centering_factors"] = factors
        model = OmegaConf.merge(cfg.model, change)
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
                for a, b in spans:
                    err = (est[..., a:b] - d.states[..., a:b]).norm(dim=-1)[:, span].mean()
                    cells.append(f"{float(err):.4g}")
            named = "" if factors is None else " " + _describe(factors) + " |"
            yield f"| {c:g} | {ramp} |{named} {sigma} | " + " | ".join(cells) + " |"


def _describe(factors: dict[str, float]) -> str:
    return ", ".join(f"{k} {v:g}" for k, v in factors.items()) or "-"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("run", help="a run folder or checkpoint")
    parser.add_argument("--centering", type=float, nargs="+", required=True)
    parser.add_argument("--ramp", type=int, nargs="+", default=[0], help="centering_ramp K")
    parser.add_argument(
        "--factors", nargs="+", default=None,
        help="centering_factors variants, each NAME=C[,NAME=C..] or none",
    )
    parser.add_argument("--out", default="benchmarks/results/centering.md")
    args = parser.parse_args()
    torch.set_num_threads(1)
    factor_sets = None if args.factors is None else [parse_factors(f) for f in args.factors]
    extra = "" if args.factors is None else " --factors " + " ".join(args.factors)
    lines = [
        f"# `{args.run}` at other centerings, no training (`python benchmarks/bench_centering.py "
        f"{args.run} --centering {' '.join(f'{c:g}' for c in args.centering)}"
        f"{' --ramp ' + ' '.join(map(str, args.ramp)) if args.ramp != [0] else ''}{extra}`)",
        "",
        "200 sequences x 1000 steps per sigma (seed 5), from the identity. Means over steps "
        "10-1000 (as evaluated) and 500-1000 (settled).",
        "",
        "| centering | ramp | sigma | R, k >= 10 | p | b_Omega | R, k >= 500 | p | b_Omega |",
        "|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    if factor_sets is not None:
        lines[-2:] = [
            "| centering | ramp | factors | sigma | R, k >= 10 | p | b_Omega | b_v | "
            "R, k >= 500 | p | b_Omega | b_v |",
            "|---:|---:|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
        ]
    for row in rows(args.run, args.centering, args.ramp, factor_sets=factor_sets):
        lines.append(row)
        print(row, flush=True)
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text("\n".join(lines) + "\n")
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
