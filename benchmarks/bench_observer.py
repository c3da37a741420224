"""Speed of the observer an experiment trains: its closed-loop training step against the fused
``torch.nn.GRU`` and against the per-step ``GRUCell`` loop of the same size.

Run by hand from the repository root (not by CI)::

    python benchmarks/bench_observer.py                     # experiment=default, prints a table
    python benchmarks/bench_observer.py --compile           # also the compiled step
    python benchmarks/bench_observer.py --profile           # where the closed loop's time goes
    python benchmarks/bench_observer.py --write run.md      # also writes the tables to run.md
    python benchmarks/bench_observer.py --experiment paper_cpu --override model.hidden_size=256

What is measured, one training step each (forward, backward, gradient clipping, AdamW):

* ``closed loop``: the observer of ``configs/experiment/<experiment>`` built by the project's
  own builders (``build_system``, ``build_observer``: its pieces, sizes and dtypes), rolled out
  over a batch the system simulates (``--batch`` sequences, default the experiment's
  ``train.batch_size``, of ``--steps`` steps at the dataset's sigma) and scored by the training
  loss (``training_losses.batch_loss`` with the experiment's loss and skip), clipped at
  ``train.grad_clip``, AdamW at ``train.lr`` / ``train.weight_decay``;
* ``closed loop, compiled`` (``--compile``): the same with ``ResidualObserver.compile_step()``
  (``train.compile=true``), compiled during the warm-up;
* ``GRUCell loop``: the open-loop floor of any closed loop, ``num_layers`` ``nn.GRUCell`` s and
  the ``nn.Linear`` head called step by step over precomputed inputs of the core's input width
  (a closed loop cannot fuse its input projections over time: each step's input depends on
  the previous step's output), MSE against a random target;
* ``nn.GRU (fused)``: ``nn.GRU`` over the whole sequence at once, the same head and loss.

Every round runs each variant once, in an order shuffled per round (a seeded RNG), so that load
from other processes falls on all of them alike; wall time and this process's CPU time are
recorded per run. The table gives each variant's median and interquartile range over
``--reps`` rounds, and the ratios of the closed loop to each reference taken *within* a round
(paired), as median and interquartile range. ``--threads`` (default 1, what the CPU training
configs use) sets torch's thread count.

``--profile`` runs ``torch.profiler`` over one step of the closed loop and of the ``GRUCell``
loop after the timing and prints the profiler events per time step and the closed loop's
operators by self CPU time.
"""

from __future__ import annotations

import argparse
import os
import platform
import random
import statistics
import sys
import time
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]


def build(experiment: str, overrides: list[str], batch: int | None, steps: int, seed: int):
    """``(cfg, observer, data, step)``: the experiment's observer and one training step on a
    simulated batch."""
    from hydra import compose, initialize_config_dir

    from manifold_nets.builders import build_observer, build_system
    from manifold_nets.training_losses import batch_loss
    from manifold_nets.training_settings import param_groups

    with initialize_config_dir(config_dir=str(ROOT / "configs"), version_base="1.3"):
        cfg = compose("train", overrides=[f"experiment={experiment}", *overrides])
    system = build_system(cfg.system)
    torch.manual_seed(seed)
    obs = build_observer(system.group, system.measurement_dim, system.input_dim, cfg.model,
                         dt=getattr(system, "dt", None), system=system)
    t = cfg.train
    n = int(batch or t.batch_size)
    data = system.simulate(n, steps, float(cfg.dataset.sigma), torch.Generator().manual_seed(seed))
    data.states = data.states.to(obs.state_dtype)
    opt = torch.optim.AdamW(param_groups(obs, float(t.lr), t.param_lr), lr=float(t.lr),
                            weight_decay=float(t.weight_decay))

    def step():
        loss = batch_loss(obs, data, None, t.loss, t.skip_steps)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        if t.grad_clip is not None:
            torch.nn.utils.clip_grad_norm_(obs.parameters(), t.grad_clip)
        opt.step()

    return cfg, obs, data, step


def references(obs, batch: int, steps: int, lr: float, wd: float, clip: float | None, seed: int):
    """``{name: step}`` of the open-loop references of the observer's core's size."""
    core = obs.core
    inp, hid, layers, out = core.input_size, core.hidden_size, core.num_layers, core.output_size
    g = torch.Generator().manual_seed(seed)
    dtype = obs.net_dtype
    x = torch.randn(batch, steps, inp, generator=g, dtype=dtype)
    xt = x.transpose(0, 1).contiguous()
    target = torch.randn(batch, steps, out, generator=g, dtype=dtype)
    torch.manual_seed(seed)
    gru = torch.nn.GRU(inp, hid, layers, batch_first=True).to(dtype)
    head = torch.nn.Linear(hid, out).to(dtype)
    cells = [torch.nn.GRUCell(inp if i == 0 else hid, hid).to(dtype) for i in range(layers)]
    head2 = torch.nn.Linear(hid, out).to(dtype)

    def trainer(params, loss_fn):
        params = list(params)
        opt = torch.optim.AdamW(params, lr=lr, weight_decay=wd)

        def step():
            loss = loss_fn()
            opt.zero_grad(set_to_none=True)
            loss.backward()
            if clip is not None:
                torch.nn.utils.clip_grad_norm_(params, clip)
            opt.step()

        return step

    def fused():
        y, _ = gru(x)
        return ((head(y) - target) ** 2).mean()

    def per_step():
        h = [torch.zeros(batch, hid, dtype=dtype) for _ in cells]
        outs = []
        for x_k in xt.unbind(0):
            z = x_k
            for i, cell in enumerate(cells):
                h[i] = z = cell(z, h[i])
            outs.append(head2(z))
        return ((torch.stack(outs, dim=1) - target) ** 2).mean()

    return {
        "GRUCell loop": trainer([*(p for c in cells for p in c.parameters()), *head2.parameters()],
                                per_step),
        "nn.GRU (fused)": trainer([*gru.parameters(), *head.parameters()], fused),
    }


def time_rounds(fns: dict, reps: int, seed: int) -> dict[str, dict[str, list[float]]]:
    """``{name: {"wall": [...], "cpu": [...]}}``, one entry per round; order shuffled per round."""
    for f in fns.values():  # warm-up: allocator, compilation
        f()
        f()
    out = {k: {"wall": [], "cpu": []} for k in fns}
    rng = random.Random(seed)
    for _ in range(reps):
        names = list(fns)
        rng.shuffle(names)
        for k in names:
            c0, t0 = time.process_time(), time.perf_counter()
            fns[k]()
            out[k]["wall"].append(time.perf_counter() - t0)
            out[k]["cpu"].append(time.process_time() - c0)
    return out


def _quartiles(xs: list[float]) -> tuple[float, float, float]:
    if len(xs) < 2:
        return xs[0], xs[0], xs[0]
    q1, q2, q3 = statistics.quantiles(xs, n=4, method="inclusive")
    return q1, q2, q3


def table(res: dict, closed: list[str], refs: list[str]) -> list[str]:
    lines = [
        "| variant | wall s, median [q1, q3] | CPU s, median [q1, q3] |",
        "|---|---:|---:|",
    ]
    for k, r in res.items():
        w, c = _quartiles(r["wall"]), _quartiles(r["cpu"])
        lines.append(f"| {k} | {w[1]:.3f} [{w[0]:.3f}, {w[2]:.3f}] | "
                     f"{c[1]:.3f} [{c[0]:.3f}, {c[2]:.3f}] |")
    lines += ["", "| ratio (paired within each round) | wall, median [q1, q3] | "
              "CPU, median [q1, q3] |", "|---|---:|---:|"]
    for a in closed:
        for b in refs:
            cells = []
            for kind in ("wall", "cpu"):
                ratios = [x / y for x, y in zip(res[a][kind], res[b][kind])]
                q = _quartiles(ratios)
                cells.append(f"{q[1]:.2f} [{q[0]:.2f}, {q[2]:.2f}]")
            lines.append(f"| {a} / {b} | {cells[0]} | {cells[1]} |")
    return lines


def profile(fns: dict, steps: int, top: int = 15) -> list[str]:
    """Profiler events per time step of each variant, and the first's operators by self CPU."""
    from torch.profiler import ProfilerActivity
    from torch.profiler import profile as torch_profile

    lines = []
    first = None
    for name, f in fns.items():
        f()
        with torch_profile(activities=[ProfilerActivity.CPU]) as prof:
            f()
        ev = prof.key_averages()
        total = sum(e.count for e in ev)
        lines.append(f"- {name}: {total} profiler events, {total / steps:.0f} per time step")
        first = first or (name, ev)
    name, ev = first
    busy = sum(e.self_cpu_time_total for e in ev)
    rows = sorted(ev, key=lambda e: e.self_cpu_time_total, reverse=True)[:top]
    lines += ["", f"{name}, operators by self CPU time (one step under the profiler):", "",
              "| operator | calls per time step | self CPU % |", "|---|---:|---:|"]
    for e in rows:
        lines.append(f"| `{e.key}` | {e.count / steps:.1f} | {100 * e.self_cpu_time_total / busy:.1f} |")
    return lines


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--experiment", default="default")
    ap.add_argument("--override", action="append", default=[], help="a hydra override (repeat)")
    ap.add_argument("--batch", type=int, default=None, help="default: the experiment's")
    ap.add_argument("--steps", type=int, default=100)
    ap.add_argument("--reps", type=int, default=15)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--compile", action="store_true", help="also the compiled step")
    ap.add_argument("--profile", action="store_true", help="profiler events per time step")
    ap.add_argument("--write", metavar="PATH", default=None,
                    help="also write the tables to PATH (benchmarks/results/observer.md is put "
                    "together from such runs, before and after a change)")
    args = ap.parse_args(argv)
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")  # as the commands set it
    torch.set_num_threads(args.threads)
    cfg, obs, data, closed = build(args.experiment, args.override, args.batch, args.steps,
                                   args.seed)
    t = cfg.train
    fns = {"closed loop": closed}
    if args.compile:
        _, c_obs, _, c_step = build(args.experiment, args.override, args.batch, args.steps,
                                    args.seed)
        c_obs.compile_step()
        fns["closed loop, compiled"] = c_step
    refs = references(obs, len(data), args.steps, float(t.lr), float(t.weight_decay),
                      t.grad_clip, args.seed)
    fns.update(refs)
    load0 = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    res = time_rounds(fns, args.reps, args.seed)
    load1 = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    cmd = " ".join(["benchmarks/bench_observer.py", *(sys.argv[1:] if argv is None else argv)])
    core = obs.core
    lines = [
        f"`python {cmd}`",
        "",
        f"experiment={args.experiment} {' '.join(args.override)}: {obs.group!r}, core "
        f"{core.input_size} -> {core.num_layers} x {core.hidden_size} -> {core.output_size}, "
        f"features {[f.name for f in obs.features]}, batch {len(data)} x {args.steps} steps; "
        f"torch {torch.__version__}, {args.threads} thread(s), OMP_WAIT_POLICY="
        f"{os.environ.get('OMP_WAIT_POLICY')}, {platform.machine()}, load average "
        f"{load0:.1f} at the start and {load1:.1f} at the end; {args.reps} rounds.",
        "",
        *table(res, [k for k in fns if k.startswith("closed")], list(refs)),
    ]
    if args.profile:
        lines += ["", *profile({"closed loop": closed, "GRUCell loop": refs["GRUCell loop"]},
                               args.steps)]
    text = "\n".join(lines) + "\n"
    print(text)
    if args.write:
        Path(args.write).write_text(text)
        print(f"wrote {args.write}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
