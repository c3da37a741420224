"""Baselines on the rigid body: 100 x 1000 sequences per sigma, steps k >= 10, one torch thread.

Run by hand from the repo root: ``python benchmarks/bench_baselines.py``. Prints one JSON row per
(sigma, method) and writes them all to ``benchmarks/results/baselines.json`` (atomically). The
table in ``docs/baselines.md`` was made from it.
"""
import json
import os
import time

import torch
from manifold_nets_examples.rigid_body import RigidBody
from manifold_nets_examples.rigid_body.filters import (
    ComplementaryFilter,
    RigidBodyEKF,
    tune_complementary_gains,
)
from groups import SO3
from manifold_nets.baselines import DeadReckoning, RawMeasurement

torch.set_num_threads(1)
N, T, SKIP = 100, 1000, 10
system = RigidBody()
so3 = SO3()
rows = []
for sigma in (0.1, 0.2, 0.3, 0.4, 0.5):
    data = system.simulate(N, T, sigma, torch.Generator().manual_seed(1))
    t0 = time.perf_counter()
    gains, _ = tune_complementary_gains(system, sigma)
    tune_s = time.perf_counter() - t0
    methods = [RawMeasurement(system), DeadReckoning(system), ComplementaryFilter(system, gains),
               RigidBodyEKF(system, sigma), RigidBodyEKF(system, sigma, init_steps=0)]
    for est in methods:
        t0 = time.perf_counter()
        x = est.estimate(data)
        sec = time.perf_counter() - t0
        m = system.metrics(x, data)
        R, Rt = x[:, :, :9].unflatten(-1, (3, 3)), data.states[:, :, :9].unflatten(-1, (3, 3))
        ang = so3.distance(R, Rt)
        name = est.name + ("" if not isinstance(est, RigidBodyEKF) else f"(init_steps={est.init_steps})")
        row = {"sigma": sigma, "method": name}
        row.update({k: float(v[:, SKIP:].mean()) for k, v in m.items()})
        row["R angle"] = float(ang[:, SKIP:].mean())
        row["R angle k>50"] = float(ang[:, 51:].mean())
        row["diverged"] = int((m["R"][:, 500:].mean(1) > 1.0).sum())
        row["ms/step"] = 1e3 * sec / T
        if isinstance(est, ComplementaryFilter):
            row["gains"] = [gains.k_P, gains.k_I, gains.k_p, gains.k_b]
            row["tune s"] = tune_s
        rows.append(row)
        print(json.dumps(row), flush=True)
out = "benchmarks/results/baselines.json"
with open(out + ".tmp", "w") as f:
    json.dump(rows, f, indent=1)
os.replace(out + ".tmp", out)
