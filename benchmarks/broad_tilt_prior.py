"""The complementary prior alone on BROAD: the tilt a fixed correction towards the low-passed
accelerometer reaches, for a grid of time constants (how ``broad.train --tilt-tau`` was chosen).

Run by hand from the repository root (not by CI), with BROAD's ``.mat`` files where the split
file says (``configs/broad/trials.yaml``) or under ``--data-dir``::

    python benchmarks/broad_tilt_prior.py --split train --taus 1,2,3,5,10 \\
        --write benchmarks/results/broad_tilt_prior_train.md

The observer is the BROAD observer of ``broad.train --tilt-tau TAU --rest-bias 1 --acc-lowpass
1.0`` with its core's output at zero, as a run starts before any training (``make_observer``):
the gyroscope integrated at the observer's step, 35.7 Hz (less its bias from rest), then the
tilt correction towards the accelerometer low-passed over 1 s; nothing corrects the heading.
Every trial of the split from TRIAD of its first sample, scored by the benchmark's metric
(:mod:`manifold_nets_examples.broad.metric`); the inclination is the column to read.
"""

from __future__ import annotations

import argparse
import os
import time

os.environ.setdefault("OMP_NUM_THREADS", "1")

import torch  # noqa: E402
from broad_scores import scores, split_of  # noqa: E402

from manifold_nets.atomic import write_text_atomic  # noqa: E402
from manifold_nets_examples.broad.compare import ATTRIBUTION  # noqa: E402
from manifold_nets_examples.broad.evaluate import observer_quaternions  # noqa: E402
from manifold_nets_examples.broad.learning import make_observer, model_config  # noqa: E402
from manifold_nets_examples.broad.simulator import BROAD_DT, BroadSimulator  # noqa: E402


def rows(trials, taus, lowpass: float) -> list[dict]:
    system = BroadSimulator(dt=8 * BROAD_DT, acc_lowpass=lowpass, rest_bias=True)
    out = []
    for tau in taus:
        observer = make_observer(system, model_config(tilt_tau=tau))
        assert not observer.core.head.weight.any()  # the core says nothing: the prior alone
        with torch.no_grad():
            quats = observer_quaternions(observer, system, trials)
        out.append({"tau": tau, **scores(quats, trials, "inclination")})
    return out


def table(result: list[dict], split: str, lowpass: float) -> str:
    names = list(result[0]["trials"])
    lines = [f"Inclination RMSE (deg) of the complementary prior alone (a zero core) on the {split} "
             f"trials, accelerometer low-passed over {lowpass:g} s, rest bias removed; mean over "
             "trials, then per trial (total and heading: the heading is never corrected).", "",
             "| tau (s) | inclination | total | heading | " + " | ".join(names) + " |",
             "|---" * (4 + len(names)) + "|"]
    for r in result:
        lines.append(f"| {r['tau']:g} | {r['inclination']:.3f} | {r['total']:.2f} | "
                     f"{r['heading']:.2f} | " + " | ".join(f"{v:.2f}" for v in r["trials"].values())
                     + " |")
    lines += ["", ATTRIBUTION]
    return "\n".join(lines) + "\n"


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--split", default="train")
    p.add_argument("--taus", default="1,2,3,5,10", help="time constants in seconds")
    p.add_argument("--lowpass", type=float, default=1.0, help="the accelerometer's low-pass (s)")
    p.add_argument("--data-dir", default=None)
    p.add_argument("--write", default=None, help="a markdown file for the table")
    a = p.parse_args(argv)
    torch.set_num_threads(1)
    trials = split_of(a.split, a.data_dir)
    t0 = time.perf_counter()
    text = table(rows(trials, [float(t) for t in a.taus.split(",")], a.lowpass), a.split, a.lowpass)
    print(text + f"\n({time.perf_counter() - t0:.0f} s)")
    if a.write:
        write_text_atomic(a.write, text)


if __name__ == "__main__":
    main()
