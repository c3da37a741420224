"""The sequences of one rigid-body set where a zoo observer's readout is least calibrated: the
largest mean ``NEES / d`` of a factor over steps ``k >= 10``, beside the sequence's mean and last
error, against the set's median, and the set's ANEES with and without the worst; for an observer
with learned robust weights on its measurement, the worst sequence's innovation norms and the
weights they get along the run::

    python benchmarks/worst_sequences.py --case outliers --sigma 0.5 --seed 8004

(``--seed`` as :mod:`benchmarks.calibration_in_band` draws them: 8000 + the sigma's index.)
``--lock-out`` also runs the observer behind a :class:`~manifold_nets.observer.LockOutGuard`
(tau 20, floor 0.1) over the set: where it re-acquired a factor, and the worst sequence's mean
and last error with it.
"""

from __future__ import annotations

import argparse
import sys

import torch

from manifold_nets.calibration import nees, tangent_errors
from manifold_nets.observer import LockOutGuard
from manifold_nets.threads import use_threads
from manifold_nets_examples.rigid_body.calibration import CASES, SKIP, _sim
from manifold_nets_examples.rigid_body.level_scale import zoo_readout


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--case", default="outliers", choices=list(CASES))
    p.add_argument("--sigma", type=float, default=0.5)
    p.add_argument("--seed", type=int, default=8004)
    p.add_argument("--sequences", type=int, default=1000)
    p.add_argument("--factor", default="p", choices=["R", "p"])
    p.add_argument("--top", type=int, default=5)
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--lock-out", action="store_true", help="also run it behind a LockOutGuard")
    args = p.parse_args(argv)
    use_threads(args.threads)
    cal, system = zoo_readout(args.case)
    cal.eval()
    data, g = _sim(system, args.sequences, 1000, args.sigma, args.seed), system.group
    s = g.tangent_slice(args.factor)
    errs, qs = [], []
    with torch.no_grad():
        for b in range(0, args.sequences, 100):
            est, cov = cal(data.measurements[b:b + 100])
            xi = tangent_errors(g, est, data.states[b:b + 100])[:, SKIP:, s]
            errs.append(xi.norm(dim=-1))
            qs.append(nees(xi, cov[:, SKIP:, s, s]) / (s.stop - s.start))
    err, q = torch.cat(errs), torch.cat(qs)
    per_seq = q.mean(1)
    print(f"{args.case}, sigma {args.sigma}, seed {args.seed}, {args.sequences} sequences, "
          f"factor {args.factor}: median sequence's mean error {float(err.mean(1).median()):.3f}; "
          f"ANEES {float(q.mean()):.3f}")
    order = torch.argsort(per_seq, descending=True)
    for i in order[: args.top].tolist():
        print(f"  sequence {i}: mean NEES/d {float(per_seq[i]):.1f}, mean error "
              f"{float(err[i].mean()):.3f}, last {float(err[i, -1]):.3f}, ANEES without it "
              f"{float(q[torch.arange(len(q)) != i].mean()):.3f}")

    robust = getattr(cal.observer.measurement, "robust", None)
    if robust is not None:
        _weights(cal.observer, data.measurements[int(order[0])])
    if args.lock_out:
        _guarded(LockOutGuard(cal.observer), data, s, int(order[0]))


@torch.no_grad()
def _guarded(guard: LockOutGuard, data, s: slice, worst: int) -> None:
    """Where the guard re-acquires a factor over the set, and the worst sequence's error with it."""
    g, resets = guard.group, []
    for b in range(0, len(data.measurements), 100):
        run = guard.rollout(data.measurements[b:b + 100])
        resets += [(b + i, k + 1, guard.factors[f]) for i, k, f in run.resets.nonzero().tolist()]
        if b <= worst < b + 100:
            xi = tangent_errors(g, run.estimates[worst - b], data.states[worst])[SKIP:, s]
            err = xi.norm(dim=-1)
    print(f"  behind a LockOutGuard (tau {guard.tau:g}, floor {guard.floor:g}): "
          f"{len(resets)} re-acquisitions (sequence, after step, factor): {resets}")
    print(f"    sequence {worst}: mean error {float(err.mean()):.3f}, last {float(err[-1]):.3f}")


@torch.no_grad()
def _weights(obs, y: torch.Tensor) -> None:
    """The innovation norm of each measured factor against the estimate after each step, and
    the learned robust weight it gets, at a few steps of one sequence ``y`` ``(T, l)``."""
    m = obs.measurement
    x = obs(y[None])[0, 1:].flatten(1).to(obs.state_dtype)
    norms = torch.stack([n.norm(dim=-1) for n in m.innovations(x, m.elements(y.to(obs.state_dtype)))], -1)
    w = m.robust(norms.float())
    names = list(m.factors)
    print(f"  the worst sequence's innovation norms and robust weights ({', '.join(names)}):")
    for k in (50, 100, 200, 300, 500, len(y) - 1):
        print(f"    step {k + 1}: " + ", ".join(f"{n} |nu| {float(norms[k, j]):.2f} weight "
                                               f"{float(w[k, j]):.3f}" for j, n in enumerate(names)))


if __name__ == "__main__":
    sys.exit(main())
