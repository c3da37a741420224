"""How much each model mismatch costs the nominal EKF: how the mismatch benchmark's magnitudes
were chosen (docs/comparison.md, "Model mismatch").

For each candidate mismatch of ``MismatchedRigidBody``, the rigid body's EKF with the nominal
model and noise level runs on 100 sequences of 1000 steps (seed 1) at sigma 0.1 and the mean
errors over steps >= 10 are written to ``benchmarks/results/mismatch_ekf.md``::

    python benchmarks/bench_mismatch_ekf.py            # about 2 minutes on one core
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import torch

from manifold_nets_examples.rigid_body import MismatchedRigidBody
from manifold_nets_examples.rigid_body.filters import RigidBodyEKF

CASES = {
    "nominal": {},
    "sensor 5 % / 0.03 rad": dict(scale_factor=0.05, misalignment=0.03),
    "sensor 10 % / 0.05 rad (mismatch_sensor)": dict(scale_factor=0.1, misalignment=0.05),
    "bias walk 0.05 (mismatch_bias_walk)": dict(bias_walk=0.05),
    "bias walk 0.2": dict(bias_walk=0.2),
    "Student-t 3 dof": dict(noise_dof=3),
    "Student-t 3 dof + 5 % outliers x10 (mismatch_outliers)": dict(
        noise_dof=3, outlier_prob=0.05, outlier_scale=10.0
    ),
    "AR(1) 0.8 (mismatch_correlated)": dict(noise_correlation=0.8),
    "AR(1) 0.95": dict(noise_correlation=0.95),
}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sigma", type=float, default=0.1)
    ap.add_argument("--sequences", type=int, default=100)
    ap.add_argument("--length", type=int, default=1000)
    ap.add_argument("--out", default=str(Path(__file__).parent / "results" / "mismatch_ekf.md"))
    args = ap.parse_args()
    torch.set_num_threads(1)
    lines = [
        "# The nominal EKF on mismatched data",
        "",
        f"`python benchmarks/bench_mismatch_ekf.py` ({args.sequences} x {args.length} at sigma "
        f"{args.sigma}, seed 1, steps >= 10; torch {torch.__version__}, one thread)",
        "",
        "| mismatch | EKF R | EKF p | EKF b_omega | EKF b_v | raw R | raw p |",
        "|---|---:|---:|---:|---:|---:|---:|",
    ]
    for name, kwargs in CASES.items():
        system = MismatchedRigidBody(**kwargs)
        data = system.simulate(
            args.sequences, args.length, args.sigma, torch.Generator().manual_seed(1)
        )
        t0 = time.perf_counter()
        ekf = RigidBodyEKF(system, args.sigma)
        ekf.ekf.progress = False
        metrics = system.metrics(ekf.estimate(data), data)
        err = {k: float(v[:, 10:].mean()) for k, v in metrics.items()}
        raw = {k: float(v[:, 10:].mean()) for k, v in system.measurement_errors(data).items()}
        row = (
            f"| {name} | {err['R']:.4f} | {err['p']:.4f} | {err['b_omega']:.4f} | "
            f"{err['b_v']:.4f} | {raw['R']:.4f} | {raw['p']:.4f} |"
        )
        print(row, f"({time.perf_counter() - t0:.1f} s)", flush=True)
        lines.append(row)
    Path(args.out).write_text("\n".join(lines) + "\n")
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
