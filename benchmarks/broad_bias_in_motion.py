"""Does a gyroscope bias estimated in motion help the fixed tilt correction on BROAD?

Run by hand from the repository root (not by CI), with BROAD's ``.mat`` files where the split
file says (``configs/broad/trials.yaml``) or under ``--data-dir``::

    python benchmarks/broad_bias_in_motion.py --split train --gains 0,0.001,0.003,0.01 \\
        --write benchmarks/results/broad_bias_in_motion.md

The bias: Mahony's integral term (Mahony, Hamel and Pflimlin, IEEE TAC 2008), ``b <- b - k_I e h``
with ``e = a x R^T e_z`` the tilt error between the low-passed accelerometer's direction ``a``
and the estimate's "up" in the body frame, from its own tilt-only complementary filter (time
constant ``--tau-c`` s, step ``h`` = the observer's 8 samples, started from the first sample's
tilt, ``|b|`` clipped to 0.02 rad/s per axis), on the gyroscope less its bias from rest; causal:
each step's gyroscope is corrected by the bias of the steps before. The corrected gyroscope then
drives the complementary prior alone (``benchmarks/broad_tilt_prior.py``'s observer, tau 3 s, a
zero core), whose inclination is the column to read; gain 0 is that prior with the rest bias only.
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import time

os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np  # noqa: E402
import torch  # noqa: E402
from broad_scores import scores, split_of  # noqa: E402
from scipy.spatial.transform import Rotation  # noqa: E402

from manifold_nets.atomic import write_text_atomic  # noqa: E402
from manifold_nets_examples.broad.compare import ATTRIBUTION  # noqa: E402
from manifold_nets_examples.broad.evaluate import observer_quaternions  # noqa: E402
from manifold_nets_examples.broad.learning import make_observer, model_config  # noqa: E402
from manifold_nets_examples.broad.prefilter import prefiltered  # noqa: E402
from manifold_nets_examples.broad.simulator import BROAD_DT, BroadSimulator  # noqa: E402

STEP = 8  # samples per observer step


def bias_in_motion(trial, tau_c: float, gain: float, limit: float = 0.02) -> np.ndarray:
    """``(T, 3)``: the causal bias estimate at each sample of the pre-filtered ``trial``."""
    h = STEP / trial.rate
    a0 = trial.acc[0] / np.linalg.norm(trial.acc[0])
    R = Rotation.align_vectors([[0.0, 0.0, 1.0]], [a0])[0].as_matrix()
    b, out = np.zeros(3), np.zeros_like(trial.gyr)
    for i in range(0, len(trial.gyr), STEP):
        out[i:i + STEP] = b
        R = R @ Rotation.from_rotvec((trial.gyr[i:i + STEP].mean(0) - b) * h).as_matrix()
        a = trial.acc[min(i + STEP, len(trial.acc)) - 1]
        e = np.cross(a / np.linalg.norm(a), R[2])
        R = R @ Rotation.from_rotvec(e * h / tau_c).as_matrix()
        b = np.clip(b - gain * e * h, -limit, limit)
    return out


def rows(trials, gains, tau_c: float) -> list[dict]:
    pre = [prefiltered(t, tau=1.0, rest=True) for t in trials]
    system = BroadSimulator(dt=STEP * BROAD_DT, acc_lowpass=1.0, rest_bias=False)
    observer = make_observer(system, model_config(tilt_tau=3.0))
    out = []
    for gain in gains:
        fed = [dataclasses.replace(t, gyr=p.gyr - (bias_in_motion(p, tau_c, gain) if gain else 0))
               for t, p in zip(trials, pre)]  # fmt: skip
        with torch.no_grad():
            quats = observer_quaternions(observer, system, fed)
        out.append({"gain": gain, **scores(quats, fed, "inclination")})
    return out


def table(result: list[dict], split: str, tau_c: float) -> str:
    names = list(result[0]["trials"])
    lines = [f"Inclination RMSE (deg) of the complementary prior alone (tau 3 s) on the {split} "
             f"trials, its gyroscope less the rest bias and a bias estimated in motion (Mahony's "
             f"integral term of gain k_I, its own filter's time constant {tau_c:g} s; gain 0: the "
             "rest bias only); mean over trials, then per trial.", "",
             "| k_I | inclination | " + " | ".join(names) + " |", "|---" * (2 + len(names)) + "|"]
    for r in result:
        lines.append(f"| {r['gain']:g} | {r['inclination']:.3f} | "
                     + " | ".join(f"{v:.2f}" for v in r["trials"].values()) + " |")
    lines += ["", ATTRIBUTION]
    return "\n".join(lines) + "\n"


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--split", default="train")
    p.add_argument("--gains", default="0,0.001,0.003,0.01", help="integral gains k_I")
    p.add_argument("--tau-c", type=float, default=3.0, help="the bias filter's time constant (s)")
    p.add_argument("--data-dir", default=None)
    p.add_argument("--write", default=None, help="a markdown file for the table")
    a = p.parse_args(argv)
    torch.set_num_threads(1)
    trials = split_of(a.split, a.data_dir)
    t0 = time.perf_counter()
    text = table(rows(trials, [float(g) for g in a.gains.split(",")], a.tau_c), a.split, a.tau_c)
    text += f"\nCommand: `python benchmarks/broad_bias_in_motion.py --split {a.split} --gains " \
            f"{a.gains} --tau-c {a.tau_c:g}` ({time.perf_counter() - t0:.0f} s)\n"
    print(text)
    if a.write:
        write_text_atomic(a.write, text)


if __name__ == "__main__":
    main()
