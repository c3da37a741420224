"""The complementary prior alone on BROAD: the tilt a fixed correction towards the low-passed
accelerometer reaches, for a grid of time constants (how ``broad.train --tilt-tau`` was chosen).

Run by hand from the repository root (not by CI), with BROAD's ``.mat`` files where the split
file says (``configs/broad/trials.yaml``) or under ``--data-dir``::

    python benchmarks/broad_tilt_prior.py --split train --taus 1,2,3,5,10 \\
        --write benchmarks/results/broad_tilt_prior_train.md
    python benchmarks/broad_tilt_prior.py --split train --order 2 --lowpass 2,2.5,3,3.5 \\
        --taus 0.03,0.1,0.25,0.5,1 --write benchmarks/results/broad_tilt_prior_order2_train.md

The observer is the BROAD observer of ``broad.train --tilt-tau TAU --rest-bias 1 --acc-lowpass
1.0`` with its core's output at zero, as a run starts before any training (``make_observer``):
the gyroscope integrated at the observer's step, 35.7 Hz (less its bias from rest), then the
tilt correction towards the accelerometer low-passed over 1 s (``--lowpass``; ``--order 2``
VQF's second-order Butterworth filter instead of the first-order one,
:func:`manifold_nets_examples.broad.prefilter.lowpass_acc`); nothing corrects the heading.
Every trial of the split from TRIAD of its first sample, scored by the benchmark's metric
(:mod:`manifold_nets_examples.broad.metric`); the inclination is the column to read.
"""

from __future__ import annotations

import argparse
import os
import time

os.environ.setdefault("OMP_NUM_THREADS", "1")

import torch  # noqa: E402
from broad_scores import scores, split_of, vqf_scores  # noqa: E402

from manifold_nets.atomic import write_text_atomic  # noqa: E402
from manifold_nets_examples.broad.compare import ATTRIBUTION  # noqa: E402
from manifold_nets_examples.broad.evaluate import observer_quaternions  # noqa: E402
from manifold_nets_examples.broad.learning import make_observer, model_config  # noqa: E402
from manifold_nets_examples.broad.prefilter import prefiltered  # noqa: E402
from manifold_nets_examples.broad.simulator import BROAD_DT, BroadSimulator  # noqa: E402


def rows(trials, taus, lowpasses, order: int = 1) -> list[dict]:
    # the readings pre-filtered here, once per low-pass for every tau, so the system (without
    # filters of its own) passes them on as they are
    system = BroadSimulator(dt=8 * BROAD_DT)
    out = []
    for lowpass in lowpasses:
        filtered = [prefiltered(t, lowpass, True, order) for t in trials]
        for tau in taus:
            observer = make_observer(system, model_config(tilt_tau=tau))
            assert not observer.core.head.weight.any()  # the core says nothing: the prior alone
            with torch.no_grad():
                quats = observer_quaternions(observer, system, filtered)
            out.append({"lowpass": lowpass, "tau": tau,
                        **scores(quats, trials, "inclination")})  # fmt: skip
    return out


def vqf_row(trials) -> dict | None:
    """VQF (6-D, online, default settings: its tilt) on the same trials, when ``vqf`` is there."""
    row = vqf_scores(trials, "inclination", six_d=True)
    return None if row is None else {"lowpass": "VQF", "tau": "-", **row}


def table(result: list[dict], split: str, order: int = 1) -> str:
    names = list(result[0]["trials"])
    kind = "first-order filter" if order == 1 else "second-order Butterworth filter (VQF's)"
    lines = [f"Inclination RMSE (deg) of the complementary prior alone (a zero core) on the {split} "
             f"trials, the accelerometer low-passed by the {kind} in the strapdown frame, rest "
             "bias removed; mean over trials, then per trial (total and heading: the heading is "
             "never corrected). VQF 6-D (its tilt) on the same trials for reference.", "",
             "| low-pass (s) | tau (s) | inclination | total | heading | " + " | ".join(names)
             + " |", "|---" * (5 + len(names)) + "|"]  # fmt: skip
    for r in result:
        lines.append(f"| {r['lowpass']:g} | {r['tau']:g} | " if r["tau"] != "-" else "| VQF | - | ")
        lines[-1] += (f"{r['inclination']:.3f} | {r['total']:.2f} | {r['heading']:.2f} | "
                      + " | ".join(f"{v:.2f}" for v in r["trials"].values()) + " |")  # fmt: skip
    lines += ["", ATTRIBUTION]
    return "\n".join(lines) + "\n"


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--split", default="train")
    p.add_argument("--taus", default="1,2,3,5,10", help="time constants in seconds")
    p.add_argument("--lowpass", default="1", help="the accelerometer's low-pass time constants (s)")
    p.add_argument("--order", type=int, choices=(1, 2), default=1,
                   help="the low-pass: 1 first order, 2 VQF's second-order Butterworth")
    p.add_argument("--data-dir", default=None)
    p.add_argument("--write", default=None, help="a markdown file for the table")
    a = p.parse_args(argv)
    torch.set_num_threads(1)
    trials = split_of(a.split, a.data_dir)
    t0 = time.perf_counter()
    taus, lowpasses = ([float(t) for t in v.split(",")] for v in (a.taus, a.lowpass))
    result = rows(trials, taus, lowpasses, a.order)
    text = table(result + [r for r in [vqf_row(trials)] if r is not None], a.split, a.order)
    print(text + f"\n({time.perf_counter() - t0:.0f} s)")
    if a.write:
        write_text_atomic(a.write, text)


if __name__ == "__main__":
    main()
