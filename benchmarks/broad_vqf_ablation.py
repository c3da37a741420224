"""Where VQF's tilt comes from on BROAD: VQF with one of its parts switched off or retuned.

Run by hand from the repository root (not by CI), with BROAD's ``.mat`` files where the split
file says (``configs/broad/trials.yaml``) or under ``--data-dir``, and the ``vqf`` package
(``pip install 'manifold_nets[broad]'``)::

    python benchmarks/broad_vqf_ablation.py --splits train,val \\
        --write benchmarks/results/broad_vqf_ablation_trainval.md

The online ``vqf.VQF`` (9-D) with its default parameters, then with its gyroscope bias
estimation in motion off (``motionBiasEstEnabled``), at rest off (``restBiasEstEnabled``), both
off, and its accelerometer low-pass's time constant ``tauAcc`` at 1 and 6 s (default 3 s), each
scored by the benchmark's metric on every trial of the splits (the mean over trials; the
inclination of the 9-D output is the 6-D one's: VQF's magnetometer turns the heading only).
"""

from __future__ import annotations

import argparse
import time

import numpy as np
from broad_scores import scores, split_of

from manifold_nets.atomic import write_text_atomic
from manifold_nets_examples.broad.compare import ATTRIBUTION

#: label -> VQF parameters that differ from its defaults
VARIANTS = {
    "default": {},
    "no bias estimation in motion": {"motionBiasEstEnabled": False},
    "no bias estimation at rest": {"restBiasEstEnabled": False},
    "no bias estimation": {"motionBiasEstEnabled": False, "restBiasEstEnabled": False},
    "tauAcc 1 s": {"tauAcc": 1.0},
    "tauAcc 6 s": {"tauAcc": 6.0},
}


def variant_quats(trials, params: dict) -> list[np.ndarray]:
    import vqf

    out = []
    for t in trials:
        args = [np.ascontiguousarray(a, dtype=np.float64) for a in (t.gyr, t.acc, t.mag)]
        out.append(np.asarray(vqf.VQF(1.0 / t.rate, **params).updateBatch(*args)["quat9D"]))
    return out


def table(result: dict, splits: str, names: list[str]) -> str:
    lines = [f"VQF (online, 9-D) on the {splits} trials with one part off or retuned: RMSE in "
             "degrees over the movement phases, mean over trials, then each trial's inclination.",
             "", "| VQF | inclination | total | heading | " + " | ".join(names) + " |",
             "|---" * (4 + len(names)) + "|"]  # fmt: skip
    for label, r in result.items():
        lines.append(f"| {label} | {r['inclination']:.3f} | {r['total']:.2f} | "
                     f"{r['heading']:.2f} | " + " | ".join(f"{v:.2f}" for v in r["trials"].values())
                     + " |")  # fmt: skip
    return "\n".join(lines + ["", ATTRIBUTION]) + "\n"


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--splits", default="train,val", help="comma-separated splits of trials.yaml")
    p.add_argument("--data-dir", default=None)
    p.add_argument("--write", default=None, help="a markdown file for the table")
    a = p.parse_args(argv)
    trials = [t for s in a.splits.split(",") for t in split_of(s, a.data_dir)]
    t0 = time.perf_counter()
    result = {label: scores(variant_quats(trials, params), trials, "inclination")
              for label, params in VARIANTS.items()}  # fmt: skip
    text = table(result, a.splits.replace(",", " and "), [t.name[:2] for t in trials])
    print(text + f"\n({time.perf_counter() - t0:.0f} s)")
    if a.write:
        write_text_atomic(a.write, text)


if __name__ == "__main__":
    main()
