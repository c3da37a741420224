"""Speed of the residual observer against an open-loop ``torch.nn.GRU`` of the same size.

Run by hand from the repository root (not by CI)::

    python benchmarks/bench_observer.py                     # 2x128 and 2x512, prints a table
    python benchmarks/bench_observer.py --write     # also writes benchmarks/results/observer.md
    python benchmarks/bench_observer.py --sizes 128 --reps 3 --skip-inference   # quick look

What is measured, all float32 networks on the CPU (``--threads``, default 2):

* **train step**: one forward + backward + AdamW step on a batch of 256 sequences of 100 steps
  (the paper's rigid body: group SO(3) x R^3 x R^3 x R^3, 18 measurements, 12 outputs), for

  - ``open-loop nn.GRU``: ``nn.GRU(36, H, 2)`` + ``Linear(H, 12)`` over precomputed inputs,
    mean squared error against a target (the fused, loop-in-C++ reference: the limit);
  - ``closed loop, float32 state``: :class:`manifold_nets.observer.ResidualObserver`, the
    estimate fed back every step and updated on the group (the paper's update rules), loss
    the embedding MSE; everything float32;
  - ``closed loop, float64 state``: the same with the group state in float64.

  The variants run interleaved (A, B, C, A, B, C, ...) so that load from other processes hits
  them alike; the table gives the median and the minimum over ``--reps`` repetitions and the
  ratio of medians to the open-loop GRU.

  With ``--compile`` also ``closed loop, float64 state, compiled``
  (:meth:`ResidualObserver.compile_step`, ``torch.compile``; compiled in the warm-up), and with
  ``--innovation`` the observer with innovation inputs ``{R: y[0:9], p: y[9:12]}``, eager and
  compiled (the measurements' first nine entries are rotations).

* **inference**: the observer over 1000 sequences of 1000 steps (``torch.inference_mode``),
  float32 network, float64 state; the distance of the last estimate from the group, and the
  same with an all-float32 observer (200 sequences). The untrained network's steps are of
  random size (the weights are random: its output layer too, which a core the observer makes
  starts at zero), so the float32 drift is indicative only.
* **online step latency**: one :meth:`ResidualObserver.step` at batch 1 (median over 1000 steps).
"""

from __future__ import annotations

import argparse
import functools
import os
import platform
import statistics
import sys
import time
from pathlib import Path

import torch

from groups import SO3, Euclidean, Product
from manifold_nets.losses import embedding_mse
from manifold_nets import GRUCore, ResidualObserver
from manifold_nets.observer import Embedding, GroupUpdate, Innovation, Measurement, Readings

GROUP = Product(SO3(), Euclidean(3), Euclidean(3), Euclidean(3), names=("R", "p", "b_omega", "b_v"))
UPDATE = {"b_omega": "absolute", "b_v": "absolute"}
MEAS = 18
INNOV = {"R": (0, 9), "p": (9, 12)}  # the innovation inputs of experiment=default / paper_cpu
COMPILE = False  # --compile: also the observer with its step compiled (torch.compile)
INNOVATION = False  # --innovation (with --compile): also with innovation inputs


def _observer(hidden: int, state_dtype=torch.float64, innovation=None) -> ResidualObserver:
    """The rigid body's observer with a 2 x ``hidden`` GRU (innovation inputs on ``innovation``),
    all its weights random: the output layer, which starts at zero in a core the observer makes,
    gets ``nn.Linear``'s initialisation, so that the untrained observer moves (and drifts)."""
    torch.manual_seed(0)
    measurement, features = Measurement(MEAS), None
    if innovation:
        measurement = Measurement(MEAS, factors=innovation)
        features = [Embedding(), Readings(), Innovation()]
    obs = ResidualObserver(
        GROUP, measurement, functools.partial(GRUCore, hidden_size=hidden, num_layers=2),
        update=GroupUpdate(UPDATE, state_dtype=state_dtype), features=features,
    )
    obs.core.head.reset_parameters()
    return obs


def _optimizer(params):
    return torch.optim.AdamW(params, lr=3e-4, weight_decay=0.1)


def train_step_variants(hidden: int, batch: int, steps: int) -> dict:
    """``{name: closure}``: one forward + backward + AdamW step each."""
    g = torch.Generator().manual_seed(0)
    torch.manual_seed(0)
    y = torch.randn(batch, steps, MEAS, generator=g)
    y[..., :9] = SO3().random((batch, steps), generator=g).flatten(-2)  # R^m: a rotation
    truth = GROUP.random((batch, steps + 1), generator=g, dtype=torch.float64)

    gru = torch.nn.GRU(GROUP.embedding_dim + MEAS, hidden, 2, batch_first=True)
    head = torch.nn.Linear(hidden, GROUP.tangent_dim)
    x_open = torch.randn(batch, steps, GROUP.embedding_dim + MEAS, generator=g)
    t_open = torch.randn(batch, steps, GROUP.tangent_dim, generator=g)
    opt_open = _optimizer([*gru.parameters(), *head.parameters()])

    def open_loop():
        out, _ = gru(x_open)
        loss = ((head(out) - t_open) ** 2).mean()
        opt_open.zero_grad(set_to_none=True)
        loss.backward()
        opt_open.step()

    def closed(state_dtype, compiled=False, innovation=None):
        obs = _observer(hidden, state_dtype, innovation)
        if compiled:
            obs.compile_step()
        opt = _optimizer(obs.parameters())
        target = truth.to(state_dtype)

        def run():
            loss = embedding_mse(GROUP, obs(y), target)
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()

        return run

    out = {
        "open-loop nn.GRU": open_loop,
        "closed loop, float32 state": closed(torch.float32),
        "closed loop, float64 state": closed(torch.float64),
    }
    if COMPILE:
        out["closed loop, float64 state, compiled"] = closed(torch.float64, compiled=True)
        if INNOVATION:
            out["closed loop + innovation, float64 state"] = closed(torch.float64, innovation=INNOV)
            out["closed loop + innovation, float64 state, compiled"] = closed(
                torch.float64, compiled=True, innovation=INNOV
            )
    return out


def time_interleaved(fns: dict, reps: int) -> dict[str, list[float]]:
    for f in fns.values():  # warm-up (allocator, MKL)
        f()
    out = {k: [] for k in fns}
    for _ in range(reps):
        for k, f in fns.items():
            t0 = time.perf_counter()
            f()
            out[k].append(time.perf_counter() - t0)
    return out


def inference_time(
    hidden: int, n: int, steps: int, state_dtype: torch.dtype = torch.float64
) -> tuple[float, float]:
    """Seconds for the observer over ``n`` sequences of ``steps``, and the largest membership error."""
    obs = _observer(hidden, state_dtype)
    y = torch.randn(n, steps, MEAS, generator=torch.Generator().manual_seed(1))
    with torch.inference_mode():
        obs(y[:8, :10])
        t0 = time.perf_counter()
        est = obs(y)
        dt = time.perf_counter() - t0
        err = float(GROUP.membership_error(est[:, -1]).max())
    return dt, err


def online_latency(hidden: int, steps: int = 1000) -> float:
    """Median seconds of one ``step`` at batch 1."""
    obs = _observer(hidden)
    ys = torch.randn(steps, 1, MEAS)
    times = []
    with torch.inference_mode():
        state = obs.init_state(1)
        for y in ys:
            t0 = time.perf_counter()
            state = obs.step(state, y)
            times.append(time.perf_counter() - t0)
    return statistics.median(times[10:])


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=[128, 512], help="GRU hidden sizes")
    ap.add_argument("--reps", type=int, default=5)
    ap.add_argument("--batch", type=int, default=256)
    ap.add_argument("--steps", type=int, default=100)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--skip-inference", action="store_true")
    ap.add_argument("--write", action="store_true", help="write benchmarks/results/observer.md")
    ap.add_argument("--compile", action="store_true", help="also the compiled step")
    ap.add_argument("--innovation", action="store_true", help="with --compile: innovation too")
    args = ap.parse_args(argv)
    global COMPILE, INNOVATION
    COMPILE, INNOVATION = args.compile, args.innovation
    torch.set_num_threads(args.threads)

    cmd = " ".join(["benchmarks/bench_observer.py", *(sys.argv[1:] if argv is None else argv)])
    wait = os.environ.get("OMP_WAIT_POLICY", "(unset)")
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    lines = [
        "# Observer speed: closed loop against an open-loop nn.GRU",
        "",
        f"`python {cmd}`",
        "",
        f"torch {torch.__version__}, {args.threads} thread(s), OMP_WAIT_POLICY={wait}, "
        f"{platform.processor() or platform.machine()}, load average {load:.1f} at the start; "
        f"float32 networks, batch {args.batch} x {args.steps} steps, forward + backward + AdamW; "
        f"median (min) of {args.reps} interleaved repetitions.",
        "",
        "| GRU | variant | median s/step | min s/step | ratio to nn.GRU (median) |",
        "|---|---|---:|---:|---:|",
    ]
    for h in args.sizes:
        res = time_interleaved(train_step_variants(h, args.batch, args.steps), args.reps)
        ref = statistics.median(res["open-loop nn.GRU"])
        for name, ts in res.items():
            med = statistics.median(ts)
            row = f"| 2x{h} | {name} | {med:.3f} | {min(ts):.3f} | {med / ref:.2f} |"
            lines.append(row)
            print(row, flush=True)
    if not args.skip_inference:
        lines += [
            "",
            "| GRU | inference 1000 x 1000 (s) | max membership error at k=1000, float64 "
            "state | the same, all float32 | online step, batch 1 (ms) |",
            "|---|---:|---:|---:|---:|",
        ]
        for h in args.sizes:
            t, err = inference_time(h, 1000, 1000)
            _, err32 = inference_time(h, 200, 1000, torch.float32)
            lat = online_latency(h)
            row = f"| 2x{h} | {t:.1f} | {err:.1e} | {err32:.1e} | {lat * 1e3:.2f} |"
            lines.append(row)
            print(row, flush=True)
    text = "\n".join(lines) + "\n"
    print(text)
    if args.write:
        out = Path(__file__).parent / "results" / "observer.md"
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_text(text)
        print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
