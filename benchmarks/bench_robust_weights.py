"""Robust weights on a trained observer: learned ones taken away, and Huber's set by hand.

The observer (a zoo entry, a run folder or a checkpoint; default ``zoo:rigid_body/outliers``)
rolls over ``--sequences`` new sequences of 1000 steps of its own system, or of another
observer's (``--system-of``: e.g. ``zoo:rigid_body/nominal`` on ``zoo:rigid_body/outliers``'
system), seed 1 (for the outliers' system the sequences of ``bench_outlier_filters.py``), at each
sigma, next to the nominal EKF on the same sequences, in these forms (docs/results.md, "Model
mismatch"):

* as trained;
* if it has learned robust weights (``observer.prior.robust`` of a
  :class:`~manifold_nets.observer.RobustSystemPrior`, ``observer.measurement.robust`` of a
  :class:`~manifold_nets.observer.RobustMeasurement`): each map, then both, set back to the
  identity (what they add);
* Huber's weights set by hand, ``w(r) = min(1, c / r)``, in place of the maps (the observer
  widened with them if it has none: its system prior and measurement rebuilt robust, the weights
  copied, the new maps the identity): on the drive the prior steps with (``--drive-bound``: a
  bias-corrected reading clipped to ``|d_i| <= c``, the paper's motion keeps ``|Omega|, |v| <=
  1``), on the innovation (``--innovation-bound``: its norm clipped), and both. Told the box and
  a threshold, these are not learned figures: they say what the two weights can do with no
  training.

It also draws each learned weight function over ``[0, --span]`` (``--plot``), and with
``--timing`` measures what the maps cost: the rollout of 200 sequences of 1000 steps
(``torch.inference_mode``) and a training step (forward, backward, 32 sequences of 200 steps) with
the maps and with them removed (the plain system prior and measurement, the same weights),
interleaved over ``--reps`` repetitions on one thread; the ratio of medians::

    python benchmarks/bench_robust_weights.py [RUN] --sigmas 0.1 0.3 0.5 [--sequences 200] \
        [--system-of RUN2] [--drive-bound 1.0] [--innovation-bound 0.5] [--out FILE] [--plot FILE] \
        [--timing] [--reps 5]
    # about 30 s per sigma on one core
"""

from __future__ import annotations

import argparse
import copy
from pathlib import Path

import torch

from manifold_nets import load_observer
from manifold_nets.evaluation import evaluate
from manifold_nets.observer import (
    Measurement,
    ResidualObserver,
    RobustMeasurement,
    RobustSystemPrior,
    RobustWeights,
    SystemPrior,
)
from manifold_nets_examples.rigid_body.filters import RigidBodyEKF

# the learned maps: label -> the piece that holds it (``observer.<piece>.robust``)
MAPS = {"drive": "prior", "innovation": "measurement"}
_ROBUST = {"drive": RobustSystemPrior, "innovation": RobustMeasurement}


class HuberWeights(RobustWeights):
    """Huber's weight ``min(1, c / r)`` on every channel, nothing learned."""

    def __init__(self, channels: int, bound: float):
        super().__init__(channels, width=1)
        self.bound = float(bound)

    def forward(self, r: torch.Tensor) -> torch.Tensor:
        return (self.bound / r.clamp(min=1e-30)).clamp(max=1.0)


def learned_maps(obs: ResidualObserver) -> list[str]:
    """Which of ``MAPS`` the observer has learned weights for."""
    return [n for n, piece in MAPS.items() if isinstance(getattr(obs, piece), _ROBUST[n])]


def rebuilt(obs: ResidualObserver, robust: bool, width: int = 1) -> ResidualObserver:
    """``obs`` with its system prior and measurement robust (``robust``: the maps it lacks new,
    the identity, of ``width`` steps) or plain (its maps dropped), every other weight copied."""
    m, prior = obs.measurement, obs.prior
    if not isinstance(prior, SystemPrior):
        raise SystemExit(
            f"the observer's prior is {type(prior).__name__}: the drive's weights need the "
            "system's prior (model prior: {type: system})."
        )
    if robust:
        if not isinstance(m, RobustMeasurement):
            m = RobustMeasurement(m.dim, m.input_dim, m.factors, width=width)
        if not isinstance(prior, RobustSystemPrior):
            prior = RobustSystemPrior(prior.system, width=width)
    else:
        m = Measurement(m.dim, m.input_dim, m.factors)
        prior = SystemPrior(prior.system)
    new = ResidualObserver(
        obs.group, m, copy.deepcopy(obs.core), update=copy.deepcopy(obs.update), prior=prior,
        features=copy.deepcopy(list(obs.features)), head=copy.deepcopy(obs.head),
        scales=copy.deepcopy(list(obs.scales)),
    ).to(obs.device)
    state = new.state_dict()
    mine = {k: v for k, v in obs.state_dict().items() if k in state}
    dropped = set(obs.state_dict()) - set(mine)
    if robust and dropped:
        raise RuntimeError(f"widening dropped weights: {sorted(dropped)}")
    new.load_state_dict({**state, **mine})
    return new.eval()


def with_maps(run: str):
    """The observer of ``run`` with both maps (its own, or new ones: the identity), its system
    and which maps it learned."""
    obs, system, _ = load_observer(run)
    learned = learned_maps(obs)
    if len(learned) == len(MAPS):
        return obs, system, learned
    return rebuilt(obs, robust=True), system, learned


def errors(obs, system, data) -> dict[str, float]:
    row = evaluate(obs, data, system).row
    return {k[: -len(" est")]: v for k, v in row.items() if k.endswith(" est")}


def _set(o: ResidualObserver, name: str, weights: RobustWeights) -> None:
    """``weights`` in place of the observer's map ``name``, in its dtype and on its device."""
    piece = getattr(o, MAPS[name])
    piece.robust = weights.to(piece.robust.amplitude)


def forms(obs, learned: list[str], drive: float, innovation: float) -> dict:
    """``{label: observer}``: as trained, each learned map taken away, Huber's by hand."""
    out = {"as trained": obs}
    for names in [[n] for n in learned] + ([learned] if len(learned) > 1 else []):
        o = copy.deepcopy(obs)
        for n in names:
            old = getattr(o, MAPS[n]).robust
            _set(o, n, RobustWeights(old.channels, old.width, old.span))
        out[" and ".join(f"{MAPS[n]}.robust" for n in names) + " set to the identity"] = o
    bound = {"drive": drive, "innovation": innovation}
    label = {"drive": f"drive clipped at {drive:g}",
             "innovation": f"innovation norms clipped at {innovation:g}"}
    for names in (["drive"], ["innovation"], list(MAPS)):
        o = copy.deepcopy(obs)
        for n in names:
            _set(o, n, HuberWeights(getattr(o, MAPS[n]).robust.channels, bound[n]))
        out["Huber by hand: " + ", ".join(label[n] for n in names)] = o
    return out


def plot(obs, learned: list[str], span: float, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = {"drive": ["Omega_x", "Omega_y", "Omega_z", "v_x", "v_y", "v_z"],
             "innovation": list(obs.measurement.factors)}
    fig, axes = plt.subplots(1, len(learned), figsize=(5.5 * len(learned), 4), squeeze=False)
    r = torch.linspace(0, span, 400)
    for ax, name in zip(axes[0], learned):
        m = getattr(obs, MAPS[name]).robust
        with torch.no_grad():
            w = m(r.unsqueeze(-1).expand(-1, m.channels).to(obs.net_dtype)).float()
        for i in range(m.channels):
            label = names[name][i] if i < len(names[name]) else str(i)
            ax.plot(r, w[:, i], label=label)
            ax.plot(r, w[:, i] * r, ls=":", color=ax.lines[-1].get_color())
        ax.axhline(1.0, color="grey", lw=0.5)
        ax.set_title(f"{MAPS[name]}.robust: w(r) (solid), w(r) r (dotted)")
        ax.set_xlabel("r = |d_i|" if name == "drive" else "r = ||nu_f||")
        ax.legend(fontsize=8)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)


def timing(obs, system, reps: int) -> list[str]:
    """Markdown rows: median and minimum seconds of a rollout and of a training step, with the
    maps and without them, and the ratio of medians."""
    import statistics
    import time

    bare = rebuilt(obs, robust=False)
    g = torch.Generator().manual_seed(3)
    long = system.simulate(200, 1000, 0.3, g)
    short = system.simulate(32, 200, 0.3, g)

    def rollout(o):
        with torch.inference_mode():
            o(long.measurements)

    def train_step(o):
        o.zero_grad()
        est = o(short.measurements)
        (est[:, 1:] - short.states[:, 1:]).pow(2).mean().backward()

    rows = []
    work = (("rollout, 200 x 1000 steps", rollout), ("training step, 32 x 200", train_step))
    for label, fn in work:
        times = {"with the maps": [], "without": []}
        for _ in range(reps):  # interleaved, so load from elsewhere hits both alike
            for key, o in (("with the maps", obs), ("without", bare)):
                t0 = time.perf_counter()
                fn(o)
                times[key].append(time.perf_counter() - t0)
        a, b = (statistics.median(times[k]) for k in ("with the maps", "without"))
        rows.append(
            f"| {label} | {a:.3f} ({min(times['with the maps']):.3f}) | "
            f"{b:.3f} ({min(times['without']):.3f}) | {a / b:.3f} |"
        )
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument(
        "run", nargs="?", default="zoo:rigid_body/outliers",
        help="a zoo entry, run folder or checkpoint (default zoo:rigid_body/outliers)",
    )
    ap.add_argument("--sigmas", type=float, nargs="+", default=[0.1, 0.3, 0.5])
    ap.add_argument("--sequences", type=int, default=200)
    ap.add_argument(
        "--system-of", default=None, help="simulate with this observer's system instead"
    )
    ap.add_argument("--drive-bound", type=float, default=1.0)
    ap.add_argument("--innovation-bound", type=float, default=0.5)
    ap.add_argument("--span", type=float, default=4.0)
    ap.add_argument("--out", default=str(Path(__file__).parent / "results" / "robust_weights.md"))
    ap.add_argument("--plot", default=None, help="a PNG of the learned weight functions")
    ap.add_argument("--timing", action="store_true", help="also time the maps' cost")
    ap.add_argument("--reps", type=int, default=5)
    args = ap.parse_args()
    torch.set_num_threads(1)
    obs, system, learned = with_maps(args.run)
    if args.system_of:
        system = load_observer(args.system_of).system
    cmd = " ".join(
        ["python benchmarks/bench_robust_weights.py", args.run, "--sigmas",
         *map(str, args.sigmas), "--sequences", str(args.sequences),
         *(["--system-of", args.system_of] if args.system_of else []), "--drive-bound",
         f"{args.drive_bound:g}", "--innovation-bound", f"{args.innovation_bound:g}",
         *(["--timing", "--reps", str(args.reps)] if args.timing else [])]
    )
    lines = [
        "# Robust weights on a trained observer: learned ones taken away, Huber's by hand", "",
        f"`{cmd}` ({args.sequences} x 1000 per sigma of `{system!r}`, seed 1, "
        f"steps >= 10; torch {torch.__version__}, one thread). Learned maps: "
        f"{', '.join(f'{MAPS[n]}.robust' for n in learned) or 'none'}.", "",
        "| sigma | estimator | R | p | b_omega | b_v | R vs nominal EKF | p vs nominal EKF |",
        "|---:|---|---:|---:|---:|---:|---:|---:|",
    ]
    for sigma in args.sigmas:
        data = system.simulate(args.sequences, 1000, sigma, torch.Generator().manual_seed(1))
        base = errors(RigidBodyEKF(system, sigma), system, data)
        rows = {"EKF, nominal (ekf)": base}
        for label, o in forms(obs, learned, args.drive_bound, args.innovation_bound).items():
            with torch.no_grad():
                rows[label] = errors(o, system, data)
        for label, e in rows.items():
            lines.append(
                f"| {sigma:g} | {label} | {e['R']:.4f} | {e['p']:.4f} | {e['b_omega']:.4f} | "
                f"{e['b_v']:.4f} | {100 * (e['R'] / base['R'] - 1):+.1f} % | "
                f"{100 * (e['p'] / base['p'] - 1):+.1f} % |"
            )
        print("\n".join(lines[-len(rows):]), flush=True)
    if args.timing:
        lines += [
            "", f"What the maps cost (`--timing`, {args.reps} interleaved repetitions, one "
            "thread): median (minimum) seconds", "",
            "| work | with the maps | without | ratio |", "|---|---:|---:|---:|",
            *timing(obs, system, args.reps),
        ]
        print("\n".join(lines[-2:]), flush=True)
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text("\n".join(lines) + "\n")
    print(f"wrote {args.out}")
    if args.plot and learned:
        plot(obs, learned, args.span, Path(args.plot))
        print(f"wrote {args.plot}")


if __name__ == "__main__":
    main()
