"""A trained observer's weights under other centerings (the centred head,
:class:`~manifold_nets.observer.CentredHead`: ``v = T(z) - c T(z^0)``; docs/results.md, "The
nominal system"), with no training, and with the centring ramped in over the first ``K`` steps
(the head's ``ramp``, ``--ramp``), with some factors centred by their own ``c_f`` (the head's
``factors``, ``--factors``), and with some factors' step size decayed after ``K_f`` steps (a
:class:`~manifold_nets.observer.StepDecay` among the scales, ``--decay``).

Each observer (a zoo entry, a run folder or a checkpoint; default ``zoo:rigid_body/nominal``) is
rebuilt at every ``c`` given: a new :class:`~manifold_nets.observer.ResidualObserver` with the
same core, measurement, prior, features and group update (the same weights, shared) and another
head and step scales. ``c = 0`` is the head inside the centring (plain, or a gain head) and then
``--ramp`` and ``--factors`` do not apply. Not given, ``--factors`` keeps the trained head's
per-factor levels and ``--decay`` the trained step decay; ``--ramp`` defaults to 0 (no ramp).
Each rolls over 200 new sequences of 1000 steps of its system (seed 5) at sigma 0, 0.1 and 0.3
from the identity; the table gives the mean ``||Rhat - R||_F``, ``||phat - p||`` and
``||bhat_Omega - b_Omega||`` (and ``||bhat_v - b_v||`` with ``--factors`` or ``--decay``) over
steps 10-1000 (as evaluated) and over steps 500-1000 (settled)::

    python benchmarks/bench_centering.py [RUN] --centering 0 0.3 0.7 1 [--ramp 0 50] [--out FILE]
    python benchmarks/bench_centering.py RUN --centering 0.85 --ramp 50 \
        --factors none b_omega=0.95,b_v=0.95 b_omega=1      # "none": every factor at c
    python benchmarks/bench_centering.py RUN --centering 0.85 --ramp 50 \
        --factors b_omega=0.97,b_v=0.97 --decay none b_omega=50,b_v=100   # "none": no decay
    # ~1 min per (c, K, factors, decay); --sequences and --sigmas for a quick look
"""

from __future__ import annotations

import argparse
from pathlib import Path

import torch

from manifold_nets import load_observer
from manifold_nets.observer import CentredHead, ResidualObserver, StepDecay

SIGMAS = (0.0, 0.1, 0.3)


def parse_factors(text: str, value=float, flag: str = "--factors") -> dict:
    """``"b_omega=0.95,b_v=0.95"`` -> ``{"b_omega": 0.95, "b_v": 0.95}``; ``"none"`` -> ``{}``
    (``value=int``: ``"b_v=100"`` -> ``{"b_v": 100}``, for ``--decay``)."""
    if text == "none":
        return {}
    out = {}
    for item in text.split(","):
        name, _, number = item.partition("=")
        try:
            out[name.strip()] = value(number)
        except ValueError:
            raise SystemExit(
                f"{flag} {text!r}: expected NAME=VALUE[,NAME=VALUE..], e.g. "
                + ("b_v=0.95" if value is float else "b_v=100")
            ) from None
    return out


def recentred(obs: ResidualObserver, c: float, ramp: int, factors=None, decay=None):
    """``obs`` with the centred head ``(c, ramp, factors)`` (``c = 0``: the head inside the
    centring) and its step decay ``decay`` (``{}``: none), sharing every other piece and the
    weights. ``factors``/``decay`` ``None``: the trained observer's."""
    inner = obs.head.inner if isinstance(obs.head, CentredHead) else obs.head
    if factors is None:
        factors = dict(obs.head.factors) if isinstance(obs.head, CentredHead) else {}
    head = CentredHead(c, ramp, factors, inner=inner) if c else inner
    scales = list(obs.scales)
    if decay is not None:  # the old order: the decay first, then an output scale
        scales = [s for s in scales if not isinstance(s, StepDecay)]
        scales = ([StepDecay(decay)] if decay else []) + scales
    try:
        other = ResidualObserver(
            obs.group, obs.measurement, obs.core, update=obs.update, prior=obs.prior,
            features=list(obs.features), head=head, scales=scales,
        )
    except ValueError as err:
        raise SystemExit(
            f"c = {c:g}, ramp {ramp}, factors {factors}, decay {decay}: {err}"
        ) from None
    return other.eval()


def rows(
    run: str, centerings: list[float], ramps=(0,), n: int = 200, t: int = 1000, seed: int = 5,
    factor_sets=None, decay_sets=None, sigmas=SIGMAS,
):
    obs, system, _ = load_observer(run)
    data = {s: system.simulate(n, t, s, torch.Generator().manual_seed(seed)) for s in sigmas}
    wide = factor_sets is not None or decay_sets is not None
    spans = ((0, 9), (9, 12), (12, 15)) + (((15, 18),) if wide else ())
    variants = (
        (c, r, f, d) for c in centerings for r in ramps for f in factor_sets or [None]
        for d in decay_sets or [None]
    )
    for c, ramp, factors, decay in ((c, r, f, d) for c, r, f, d in variants if c or not r):
        other = recentred(obs, c, ramp, factors, decay)
        for sigma in sigmas:
            d = data[sigma]
            with torch.inference_mode():
                est = other(d.measurements)
            cells = []
            for span in (slice(10, t + 1), slice(t // 2, t + 1)):
                for a, b in spans:
                    err = (est[..., a:b] - d.states[..., a:b]).norm(dim=-1)[:, span].mean()
                    cells.append(f"{float(err):.4g}")
            named = "".join(
                f" {_describe(x)} |" for x, given in ((factors, factor_sets), (decay, decay_sets))
                if given is not None
            )
            yield f"| {c:g} | {ramp} |{named} {sigma} | " + " | ".join(cells) + " |"


def _describe(factors: dict) -> str:
    return ", ".join(f"{k} {v:g}" for k, v in factors.items()) or "-"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument(
        "run", nargs="?", default="zoo:rigid_body/nominal",
        help="a zoo entry, run folder or checkpoint (default zoo:rigid_body/nominal)",
    )
    parser.add_argument("--centering", type=float, nargs="+", required=True)
    parser.add_argument("--ramp", type=int, nargs="+", default=[0], help="the centring's ramp K")
    parser.add_argument(
        "--factors", nargs="+", default=None,
        help="per-factor centring variants, each NAME=C[,NAME=C..] or none",
    )
    parser.add_argument(
        "--decay", nargs="+", default=None,
        help="step decay variants, each NAME=K[,NAME=K..] or none",
    )
    parser.add_argument("--sequences", type=int, default=200)
    parser.add_argument("--sigmas", type=float, nargs="+", default=list(SIGMAS))
    parser.add_argument("--out", default="benchmarks/results/centering.md")
    args = parser.parse_args()
    torch.set_num_threads(1)
    factor_sets = None if args.factors is None else [parse_factors(f) for f in args.factors]
    decay_sets = (
        None if args.decay is None else [parse_factors(d, int, "--decay") for d in args.decay]
    )
    extra = "".join(
        f" --{flag} " + " ".join(given)
        for flag, given in (("factors", args.factors), ("decay", args.decay)) if given
    )
    if args.sequences != 200:
        extra += f" --sequences {args.sequences}"
    if args.sigmas != list(SIGMAS):
        extra += " --sigmas " + " ".join(f"{s:g}" for s in args.sigmas)
    lines = [
        f"# `{args.run}` at other centerings, no training (`python benchmarks/bench_centering.py "
        f"{args.run} --centering {' '.join(f'{c:g}' for c in args.centering)}"
        f"{' --ramp ' + ' '.join(map(str, args.ramp)) if args.ramp != [0] else ''}{extra}`)",
        "",
        f"{args.sequences} sequences x 1000 steps per sigma (seed 5), from the identity. Means "
        "over steps 10-1000 (as evaluated) and 500-1000 (settled).",
        "",
        "| centering | ramp | sigma | R, k >= 10 | p | b_Omega | R, k >= 500 | p | b_Omega |",
        "|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    if factor_sets is not None or decay_sets is not None:
        named = [n for n, x in (("factors", factor_sets), ("decay", decay_sets)) if x is not None]
        lines[-2:] = [
            "| centering | ramp | " + "".join(f"{n} | " for n in named)
            + "sigma | R, k >= 10 | p | b_Omega | b_v | R, k >= 500 | p | b_Omega | b_v |",
            "|---:|---:|" + "---|" * len(named) + "---:|" * 9,
        ]
    rows_ = rows(
        args.run, args.centering, args.ramp, n=args.sequences, factor_sets=factor_sets,
        decay_sets=decay_sets, sigmas=tuple(args.sigmas),
    )
    for row in rows_:
        lines.append(row)
        print(row, flush=True)
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text("\n".join(lines) + "\n")
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
