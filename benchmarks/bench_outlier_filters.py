"""What a classical filter gains on the outliers (``mismatch_outliers``) from the motion's law:
the nominal and the gated EKF (``ekf``, ``ekf_robust``), each also with its velocity readings
clipped to what the motion can do (docs/comparison.md, "The prior's drive").

The paper's motion keeps ``|Omega|, |v| <= 1`` per axis (``omega_range``, ``velocity_range``),
so a bias-corrected reading ``Omega^m - bhat_Omega`` far outside that box is an outlier. The
clipped filters step with the reading clamped to the box widened by ``margin`` (``--margins``, in
multiples of sigma), in the prediction and its Jacobians alike. A filter told this is told more
than the nominal model: the table says whether that information is in the data at all, which a
learned observer can then find. Each filter runs on ``--sequences`` new sequences of 1000 steps
of ``mismatch_outliers``' system (seed 1) at each sigma; mean errors over steps >= 10::

    python benchmarks/bench_outlier_filters.py --sigmas 0.1 0.2 0.3 0.4 0.5 --sequences 200
    # about 40 s per sigma on one core
"""

from __future__ import annotations

import argparse
from pathlib import Path

import torch

from manifold_nets.evaluation import evaluate
from manifold_nets_examples.rigid_body import MismatchedRigidBody
from manifold_nets_examples.rigid_body.filters import RigidBodyEKF

OUTLIERS = dict(noise_dof=3, outlier_prob=0.05, outlier_scale=10.0)  # mismatch_outliers


def clip_readings(ekf: RigidBodyEKF, margin: float) -> RigidBodyEKF:
    """``ekf`` with its bias-corrected readings clamped to the motion's box widened by
    ``margin``: ``|Omega| <= omega_range + margin``, ``|v| <= velocity_range + margin``."""
    model, system = ekf.model, ekf.system
    ranges = [system.omega_range] * 3 + [system.velocity_range] * 3
    plain = model.drive  # the readings less the estimated biases

    def drive(x, y, u, noise=None):
        w = plain(x, y, u)
        bound = w.new_tensor(ranges) + margin
        w = w.clamp(-bound, bound)
        return w if noise is None else w - noise

    model.drive = drive  # the prediction and its Jacobians both read model.drive
    return ekf


def filters(system, sigma: float, margins: list[float]) -> dict:
    out = {"EKF, nominal (ekf)": RigidBodyEKF(system, sigma),
           "EKF, gated (ekf_robust)": RigidBodyEKF.robust(system, sigma)}
    for m in margins:
        name = f"readings clipped to the box + {m:g} sigma"
        out[f"nominal, {name}"] = clip_readings(RigidBodyEKF(system, sigma), m * sigma)
        out[f"gated, {name}"] = clip_readings(RigidBodyEKF.robust(system, sigma), m * sigma)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sigmas", type=float, nargs="+", default=[0.1])
    ap.add_argument("--sequences", type=int, default=200)
    ap.add_argument("--margins", type=float, nargs="+", default=[0.0, 2.0])
    ap.add_argument("--out", default=str(Path(__file__).parent / "results" / "outlier_filters.md"))
    args = ap.parse_args()
    torch.set_num_threads(1)
    system = MismatchedRigidBody(**OUTLIERS)
    lines = [
        "# Classical filters on the outliers, told the motion's box",
        "",
        f"`python benchmarks/bench_outlier_filters.py --sigmas {' '.join(map(str, args.sigmas))} "
        f"--sequences {args.sequences} --margins {' '.join(map(str, args.margins))}` "
        f"({args.sequences} x 1000 per sigma, seed 1, steps >= 10; torch {torch.__version__}, "
        "one thread)",
        "",
        "| sigma | filter | R | p | b_omega | b_v | R vs nominal | p vs nominal |",
        "|---:|---|---:|---:|---:|---:|---:|---:|",
    ]
    for sigma in args.sigmas:
        data = system.simulate(args.sequences, 1000, sigma, torch.Generator().manual_seed(1))
        base = None
        for name, ekf in filters(system, sigma, args.margins).items():
            ekf.ekf.progress = False
            res = evaluate(ekf, data, system)
            err = {k: res.row[f"{k} est"] for k in ("R", "p", "b_omega", "b_v")}
            base = base or err
            row = (
                f"| {sigma:g} | {name} | {err['R']:.4f} | {err['p']:.4f} | "
                f"{err['b_omega']:.4f} | {err['b_v']:.4f} | "
                f"{100 * (err['R'] / base['R'] - 1):+.1f} % | "
                f"{100 * (err['p'] / base['p'] - 1):+.1f} % |"
            )
            print(row, f"({res.seconds:.1f} s)", flush=True)
            lines.append(row)
    Path(args.out).write_text("\n".join(lines) + "\n")
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
