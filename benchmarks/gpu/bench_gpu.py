"""The paper's observer on a GPU: its closed-loop training step and its inference against cuDNN.

Run by hand on a machine with an NVIDIA GPU (``benchmarks/gpu/run.sh`` runs it)::

    python benchmarks/gpu/bench_gpu.py --json gpu_bench.json --write gpu.md
    python benchmarks/gpu/bench_gpu.py --device cpu --batch 8 --steps 5 --infer-batch 4 \
        --infer-steps 6 --reps 2          # a dry run of every variant on the CPU (no graphs)

The observer is ``experiment=paper_rigid_body``'s (2 x 512 GRU, the paper's inputs, float64
group state behind a float32 network), built by the project's builders. What is timed:

* **training step** (forward, backward, AdamW at the experiment's lr and weight decay) over a
  batch of ``--batch`` (1024) simulated sequences of ``--steps`` (100) steps, scored by the
  training loss (``training_losses.batch_loss``):
  ``closed loop`` (eager), ``closed loop, compiled`` (``ResidualObserver.compile_step()``,
  ``train.compile=true``), ``closed loop, CUDA graph`` (the whole step, forward, backward and
  AdamW(capturable=True), captured once and replayed; the rollout is the observer's own
  ``step_unchecked`` loop, as ``rollout`` runs it after its one input check: the figures of
  ``benchmarks/results/gpu.md`` were measured so; ``train.cuda_graph`` captures the rollout
  itself, whose check stands aside while a stream captures); against ``cuDNN nn.GRU`` (the open-loop
  ``torch.nn.GRU`` of the same size over precomputed inputs, the same head, MSE and AdamW) and
  the ``GRUCell loop`` (two ``nn.GRUCell`` called step by step, open loop);
* **inference** over ``--infer-batch`` x ``--infer-steps`` (1000 x 1000) sequences, estimates
  kept on the device: ``closed loop`` (eager ``observer(y, u)`` under ``inference_mode``),
  ``closed loop, compiled`` (``torch.compile`` of ``step_unchecked`` in the same loop), ``closed
  loop, CUDA graph`` (the whole rollout captured); against ``cuDNN nn.GRU`` over the sequence.

Each variant is warmed up (compilation and capture happen there; their seconds are reported),
then every round runs each variant once in a shuffled order, timed by CUDA events around it;
the table gives medians and interquartile ranges over ``--reps`` rounds and the ratios taken
within a round. TF32 is off for both cuBLAS and cuDNN (``--tf32`` turns it on for both), so
the closed loop and cuDNN do the same float32 arithmetic. A variant that fails (a compiler or
capture error) is reported with its error and the others go on; results are written after
every variant, so a run stopped by its time limit keeps what it measured.
"""

from __future__ import annotations

import argparse
import copy
import json
import random
import statistics
import sys
import time
import traceback
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[2]


def build(device, batch: int, steps: int, seed: int, sigma: float | None = None):
    """``(cfg, observer, data)``: the paper experiment's observer on ``device`` and a simulated
    batch there (states in the state dtype)."""
    from hydra import compose, initialize_config_dir

    from manifold_nets.builders import build_observer, build_system

    with initialize_config_dir(config_dir=str(ROOT / "configs"), version_base="1.3"):
        cfg = compose("train", overrides=["experiment=paper_rigid_body"])
    system = build_system(cfg.system)
    torch.manual_seed(seed)
    obs = build_observer(system.group, system.measurement_dim, system.input_dim, cfg.model,
                         dt=getattr(system, "dt", None), system=system).to(device)
    s = float(cfg.dataset.sigma if sigma is None else sigma)
    data = system.simulate(batch, steps, s, torch.Generator().manual_seed(seed))
    data.states = data.states.to(device=device, dtype=obs.state_dtype)
    data.measurements, data.inputs = data.measurements.to(device), data.inputs.to(device)
    return cfg, obs, data


def _inputs(obs, data):
    from manifold_nets.observer.checks import check_sequences

    return check_sequences(obs, data.measurements, data.inputs if obs.input_dim else None)


def unchecked_rollout(obs, yu, ys, step=None) -> torch.Tensor:
    """The estimates ``(N, T+1, numel)`` of ``rollout``'s loop on checked inputs (no host read)."""
    step = step or obs.step_unchecked
    n, steps = yu.shape[1], yu.shape[0]
    state = obs.init_state(n, device=yu.device)
    x, hidden = state.estimate.reshape(n, obs.update.numel), state.hidden
    measured = list(zip(*(m.unbind(0) for m in obs.measurement.elements(ys)))) or [()] * steps
    xs = [x]
    for yu_k, ys_k, m_k, t_k in zip(yu.unbind(0), ys.unbind(0), measured, obs.schedule(0, steps)):
        x, hidden = step(x, hidden, yu_k, ys_k, m_k, t_k)
        xs.append(x)
    return torch.stack(xs, dim=1)


def _optimizer(params, t, **extra):
    return torch.optim.AdamW(params, lr=float(t.lr), weight_decay=float(t.weight_decay), **extra)


def training_variants(cfg, obs, data, with_graph: bool) -> dict:
    """``{name: factory}``; each factory returns the step to time (built lazily, so a failing
    variant costs only itself)."""
    from manifold_nets.training_losses import LOSSES, batch_loss

    t = cfg.train

    def closed(compiled: bool):
        def make():
            model = copy.deepcopy(obs)
            if compiled:
                model.compile_step()
            opt = _optimizer(model.parameters(), t)

            def step():
                loss = batch_loss(model, data, None, t.loss, t.skip_steps)
                opt.zero_grad(set_to_none=True)
                loss.backward()
                opt.step()
            return step
        return make

    def graphed():
        model = copy.deepcopy(obs)
        opt = _optimizer(model.parameters(), t, capturable=True)
        yu, ys = _inputs(model, data)
        target = data.states

        def loss_and_step():
            est = unchecked_rollout(model, yu, ys).unflatten(-1, model.group.element_shape)
            loss = LOSSES[t.loss](model.group, est, target, skip=t.skip_steps, mask=None)
            loss.backward()
            opt.step()

        side = torch.cuda.Stream()
        side.wait_stream(torch.cuda.current_stream())
        with torch.cuda.stream(side):  # warm-up on a side stream, as torch.cuda.graph asks
            for _ in range(3):
                opt.zero_grad(set_to_none=True)
                loss_and_step()
        torch.cuda.current_stream().wait_stream(side)
        opt.zero_grad(set_to_none=True)
        graph = torch.cuda.CUDAGraph()
        with torch.cuda.graph(graph):
            loss_and_step()
        return graph.replay

    out = {"closed loop": closed(False), "closed loop, compiled": closed(True)}
    if with_graph:
        out["closed loop, CUDA graph"] = graphed
    out.update(open_loop_training(obs, data, t))
    return out


def open_loop_training(obs, data, t) -> dict:
    """cuDNN's ``nn.GRU`` and the ``GRUCell`` loop of the core's size, trained open loop."""
    core, dev, dtype = obs.core, obs.device, obs.net_dtype
    n, steps = data.measurements.shape[:2]
    g = torch.Generator().manual_seed(1)
    x = torch.randn(n, steps, core.input_size, generator=g, dtype=dtype).to(dev)
    target = torch.randn(n, steps, core.output_size, generator=g, dtype=dtype).to(dev)

    def cudnn():
        gru = torch.nn.GRU(core.input_size, core.hidden_size, core.num_layers,
                           batch_first=True).to(dev, dtype)
        head = torch.nn.Linear(core.hidden_size, core.output_size).to(dev, dtype)
        opt = _optimizer([*gru.parameters(), *head.parameters()], t)

        def step():
            y, _ = gru(x)
            loss = ((head(y) - target) ** 2).mean()
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
        return step

    def cells():
        hid = core.hidden_size
        layers = [torch.nn.GRUCell(core.input_size if i == 0 else hid, hid).to(dev, dtype)
                  for i in range(core.num_layers)]
        head = torch.nn.Linear(hid, core.output_size).to(dev, dtype)
        opt = _optimizer([*(p for c in layers for p in c.parameters()), *head.parameters()], t)
        xt = x.transpose(0, 1).contiguous()

        def step():
            h = [torch.zeros(n, hid, dtype=dtype, device=dev) for _ in layers]
            outs = []
            for x_k in xt.unbind(0):
                z = x_k
                for i, cell in enumerate(layers):
                    h[i] = z = cell(z, h[i])
                outs.append(head(z))
            loss = ((torch.stack(outs, 1) - target) ** 2).mean()
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
        return step

    return {"cuDNN nn.GRU": cudnn, "GRUCell loop": cells}


def inference_variants(obs, data, with_graph: bool) -> dict:
    yu, ys = _inputs(obs, data)
    core, dev = obs.core, obs.device

    def eager():
        def run():
            with torch.inference_mode():
                obs(data.measurements, data.inputs if obs.input_dim else None)
        return run

    def compiled():
        from manifold_nets.observer.compiling import compiled as compile_step

        step = compile_step(obs.step_unchecked)

        def run():
            with torch.no_grad():
                unchecked_rollout(obs, yu, ys, step)
        return run

    def graphed():
        with torch.no_grad():
            side = torch.cuda.Stream()
            side.wait_stream(torch.cuda.current_stream())
            with torch.cuda.stream(side):
                unchecked_rollout(obs, yu, ys)
            torch.cuda.current_stream().wait_stream(side)
            graph = torch.cuda.CUDAGraph()
            with torch.cuda.graph(graph):
                unchecked_rollout(obs, yu, ys)
        return graph.replay

    def cudnn():
        gru = torch.nn.GRU(core.input_size, core.hidden_size, core.num_layers,
                           batch_first=True).to(dev, obs.net_dtype)
        x = torch.randn(yu.shape[1], yu.shape[0], core.input_size, dtype=obs.net_dtype,
                        device=dev)

        def run():
            with torch.inference_mode():
                gru(x)
        return run

    out = {"closed loop": eager, "closed loop, compiled": compiled}
    if with_graph:
        out["closed loop, CUDA graph"] = graphed
    out["cuDNN nn.GRU"] = cudnn
    return out


def _sync(device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def _timed(fn, device) -> float:
    """Seconds of one call: CUDA events around it on a GPU, the host clock on the CPU."""
    if device.type != "cuda":
        t0 = time.perf_counter()
        fn()
        return time.perf_counter() - t0
    start, end = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
    start.record()
    fn()
    end.record()
    end.synchronize()
    return start.elapsed_time(end) / 1e3


def measure(variants: dict, device, reps: int, seed: int, report) -> dict:
    """Builds and warms up each variant (seconds reported), then ``reps`` shuffled rounds."""
    ready, res = {}, {}
    for name, make in variants.items():
        t0 = time.perf_counter()
        try:
            fn = make()
            fn()
            fn()
            _sync(device)
        except Exception as err:  # noqa: BLE001 - a variant that fails is reported, not fatal
            res[name] = {"error": f"{type(err).__name__}: {err}"[:2000]}
            traceback.print_exc()
        else:
            ready[name] = fn
            res[name] = {"setup_s": time.perf_counter() - t0, "times": []}
        report(res)
    rng = random.Random(seed)
    for _ in range(reps):
        names = list(ready)
        rng.shuffle(names)
        for name in names:
            res[name]["times"].append(_timed(ready[name], device))
        report(res)
    if device.type == "cuda":
        res["peak_memory_gib"] = torch.cuda.max_memory_allocated(device) / 2**30
    return res


def _q(xs):
    if len(xs) < 2:
        return xs[0], xs[0], xs[0]
    q1, q2, q3 = statistics.quantiles(xs, n=4, method="inclusive")
    return q1, q2, q3


def table(res: dict, reference: str) -> list[str]:
    lines = ["| variant | seconds, median [q1, q3] | / " + reference + ", paired median [q1, q3] "
             "| warm-up s |", "|---|---:|---:|---:|"]
    ref = res.get(reference, {}).get("times") or []
    for name, r in res.items():
        if not isinstance(r, dict):
            continue
        if "error" in r:
            lines.append(f"| {name} | failed: {r['error'].splitlines()[0][:160]} | | |")
            continue
        if not r["times"]:
            continue
        q = _q(r["times"])
        ratio = ""
        if ref and len(ref) == len(r["times"]):
            p = _q([a / b for a, b in zip(r["times"], ref)])
            ratio = f"{p[1]:.2f} [{p[0]:.2f}, {p[2]:.2f}]"
        lines.append(f"| {name} | {q[1]:.4f} [{q[0]:.4f}, {q[2]:.4f}] | {ratio} | "
                     f"{r['setup_s']:.1f} |")
    return lines


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--device", default="cuda")
    ap.add_argument("--batch", type=int, default=1024)
    ap.add_argument("--steps", type=int, default=100)
    ap.add_argument("--infer-batch", type=int, default=1000)
    ap.add_argument("--infer-steps", type=int, default=1000)
    ap.add_argument("--reps", type=int, default=7)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--tf32", action="store_true", help="TF32 in cuBLAS and cuDNN (default off)")
    ap.add_argument("--skip", action="append", default=[], choices=["training", "inference"])
    ap.add_argument("--json", default=None, help="write every figure here (after each variant)")
    ap.add_argument("--write", default=None, help="write the tables here (markdown)")
    args = ap.parse_args(argv)
    device = torch.device(args.device)
    torch.backends.cuda.matmul.allow_tf32 = args.tf32
    torch.backends.cudnn.allow_tf32 = args.tf32
    graphs = device.type == "cuda"
    name = torch.cuda.get_device_name(device) if graphs else "CPU"
    cmd = " ".join(["python benchmarks/gpu/bench_gpu.py", *(sys.argv[1:] if argv is None else argv)])
    out = {"command": cmd, "device": name, "torch": torch.__version__,
           "cudnn": torch.backends.cudnn.version() if graphs else None, "tf32": args.tf32}

    def report(_=None):
        if args.json:
            Path(args.json).write_text(json.dumps(out, indent=1))

    if "training" not in args.skip:
        cfg, obs, data = build(device, args.batch, args.steps, args.seed)
        out["training"] = {}
        out["training"] = measure(training_variants(cfg, obs, data, graphs), device, args.reps,
                                  args.seed, lambda r: (out["training"].update(r), report()))
        del obs, data
    if "inference" not in args.skip:
        cfg, obs, data = build(device, args.infer_batch, args.infer_steps, args.seed, sigma=0.1)
        obs.eval()
        out["inference"] = {}
        out["inference"] = measure(inference_variants(obs, data, graphs), device, args.reps,
                                   args.seed, lambda r: (out["inference"].update(r), report()))
    report()
    lines = [f"`{cmd}`", "", f"{name}, torch {out['torch']}, cuDNN {out['cudnn']}, TF32 "
             f"{'on' if args.tf32 else 'off'}; {args.reps} rounds, order shuffled per round.", ""]
    for part, size in (("training", f"{args.batch} x {args.steps}"),
                       ("inference", f"{args.infer_batch} x {args.infer_steps}")):
        if part in out:
            peak = out[part].get("peak_memory_gib")
            lines += [f"**{part}** ({size} sequences x steps"
                      + (f"; peak GPU memory {peak:.1f} GiB" if peak else "") + ")", "",
                      *table(out[part], "cuDNN nn.GRU"), ""]
    text = "\n".join(lines)
    print(text)
    if args.write:
        Path(args.write).write_text(text + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
