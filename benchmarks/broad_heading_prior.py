"""The heading correction alone on BROAD: the heading a fixed, gated turn towards magnetic north
reaches under the shipped tilt correction, for a grid of time constants, gated and not (how
``broad.train --heading-tau`` and ``--heading-gate`` were chosen).

Run by hand from the repository root (not by CI), with BROAD's ``.mat`` files where the split
file says (``configs/broad/trials.yaml``) or under ``--data-dir``::

    python benchmarks/broad_heading_prior.py --split train --taus 2,5,10,20,40 \\
        --write benchmarks/results/broad_heading_prior_train.md

The observer is the BROAD observer of ``broad.train --tilt-tau 3 --heading-tau TAU
[--heading-gate 1] --rest-bias 1 --acc-lowpass 1.0`` with its core's output at zero, as a run
starts before any training: the gyroscope integrated at 35.7 Hz (less its bias from rest), the
tilt correction towards the accelerometer low-passed over 1 s, then the heading correction
towards the magnetometer's horizontal part (gated: only where its strength and dip are within
10 % and 10 deg of the system's, ``learning.field_gate``). The first row (tau 0) corrects no
heading; the last is VQF's (9-D, default settings) on the same trials. Every trial of the split from TRIAD of its first sample, scored by the benchmark's
metric; the heading is the column to read.
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
from manifold_nets_examples.broad.learning import field_gate, make_observer, model_config  # noqa: E402
from manifold_nets_examples.broad.simulator import BROAD_DT, BroadSimulator  # noqa: E402


def vqf_row(trials) -> dict | None:
    """VQF (9-D, online, default settings) on the same trials, when the ``vqf`` package is there."""
    row = vqf_scores(trials, "heading")
    return None if row is None else {"tau": "VQF", "gate": None, **row}


def rows(trials, taus, tilt_tau: float) -> list[dict]:
    system = BroadSimulator(dt=8 * BROAD_DT, acc_lowpass=1.0, rest_bias=True)
    grid = [(0.0, False)] + [(tau, gate) for tau in taus for gate in (False, True)]
    out = []
    for tau, gate in grid:
        model = model_config(tilt_tau=tilt_tau, heading_tau=tau,
                             heading_gate=field_gate(system) if gate else None)
        observer = make_observer(system, model)
        assert not observer.core.head.weight.any()  # the core says nothing: the priors alone
        with torch.no_grad():
            quats = observer_quaternions(observer, system, trials)
        out.append({"tau": tau, "gate": gate, **scores(quats, trials, "heading")})
        print(f"tau {tau:g} gate {gate}: heading {out[-1]['heading']:.3f}", flush=True)
    return out


def table(result: list[dict], split: str, tilt_tau: float) -> str:
    names = list(result[0]["trials"])
    lines = [f"Heading RMSE (deg) of the priors alone (a zero core) on the {split} trials: the "
             f"tilt correction (tau {tilt_tau:g} s) and the heading correction (tau below; "
             "gated: the magnetometer's strength and dip within 10 % and 10 deg); mean over "
             "trials, then per trial.", "",
             "| heading tau (s) | gated | heading | total | inclination | " + " | ".join(names)
             + " |", "|---" * (5 + len(names)) + "|"]
    for r in result:
        tau, gate = (r["tau"], "") if r["gate"] is None else (f"{r['tau']:g}", "yes" if r["gate"]
                                                               else "no")  # fmt: skip
        lines.append(f"| {tau} | {gate} | {r['heading']:.3f} | "
                     f"{r['total']:.2f} | {r['inclination']:.2f} | "
                     + " | ".join(f"{v:.2f}" for v in r["trials"].values()) + " |")
    lines += ["", ATTRIBUTION]
    return "\n".join(lines) + "\n"


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--split", default="train")
    p.add_argument("--taus", default="2,5,10,20,40", help="heading time constants in seconds")
    p.add_argument("--tilt-tau", type=float, default=3.0)
    p.add_argument("--data-dir", default=None)
    p.add_argument("--write", default=None, help="a markdown file for the table")
    a = p.parse_args(argv)
    torch.set_num_threads(1)
    trials = split_of(a.split, a.data_dir)
    t0 = time.perf_counter()
    result = rows(trials, [float(t) for t in a.taus.split(",")], a.tilt_tau)
    result += [r for r in [vqf_row(trials)] if r is not None]
    text = table(result, a.split, a.tilt_tau)
    print(text + f"\n({time.perf_counter() - t0:.0f} s)")
    if a.write:
        write_text_atomic(a.write, text)


if __name__ == "__main__":
    main()
