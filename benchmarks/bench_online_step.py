"""Latency of the observer's online step at batch 1: eager, compiled, exported.

Run by hand from the repository root (not by CI)::

    python benchmarks/bench_online_step.py            # prints the table
    python benchmarks/bench_online_step.py --profile --write   # writes results/online_step.md

The observer is the rigid body's of ``experiment=default`` (the config composed from
``configs/``): a 2x128 GRU, innovation inputs ``{R: [0, 9], p: [9, 12]}``, biases absolute,
float32 network, float64 state, untrained (the speed does not depend on the weights; its output
layer, which starts at zero in a core the observer makes, gets random weights, so that the
estimate moves and the variants' agreement means something), fed a simulated noisy stream. One
torch thread, ``torch.inference_mode``. Variants, each one step at batch 1, timed step by step:

* ``eager observer.step``: the checked step (:meth:`ResidualObserver.step`), the reference;
* ``eager OnlineStep``: the same step without checks (``observer.online_step_module()``);
* ``torch.compile(OnlineStep)``: inductor, ``dynamic=False``; Dynamo breaks the graph three
  times at the core's ``nn.GRU`` (it refuses to wrap RNN modules, even to read their weights;
  ``torch._dynamo.config.allow_rnn=True`` makes it one graph, not measured here because the
  setting is global to the process);
* ``exported program``: ``export_observer`` -> ``load_exported_step``, its ``module()`` (an
  interpreted FX graph);
* ``exported, AOTInductor``: the same program compiled ahead of time to a shared library
  (``torch._inductor.aoti_compile_and_package``) and loaded with ``aoti_load_package``;
* ``core alone, eager``: the two ``gru_cell`` and the head without the group part, a floor for
  eager code.

The variants run interleaved (a round of ``--steps`` steps each, ``--rounds`` rounds, the first
round a warm-up that is not counted) so that load from other processes hits them alike; the
table gives the median and the 10th percentile of the per-step times and their ratios to the
eager step's (the 10th percentile is the less sensitive to other processes). ``--profile``
adds the top operators of the eager step (``torch.profiler``).
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(Path(__file__).resolve().parent))  # the helpers beside this file
from machine import describe as describe_machine  # noqa: E402


def _observer():
    from hydra import compose, initialize_config_dir

    import manifold_nets_examples.rigid_body  # noqa: F401  (registers the system)
    from manifold_nets.builders import build_observer
    from manifold_nets.loading import build_system_safely

    with initialize_config_dir(config_dir=str(ROOT / "configs"), version_base="1.3"):
        cfg = compose("train", overrides=["experiment=default"])
    system = build_system_safely(dict(cfg.system))
    torch.manual_seed(0)
    obs = build_observer(system.group, system.measurement_dim, system.input_dim, cfg.model)
    obs.core.head.reset_parameters()  # random, as the other weights: the estimate moves
    return obs.eval(), system, cfg.model


def _variants(obs, tmp: Path, aoti: bool) -> dict:
    """``{name: (init, step)}``: ``init()`` a fresh state, ``step(state, y) -> state``."""
    from manifold_nets.deploy import export_observer, load_exported_step
    from manifold_nets.observer import ObserverState

    online = obs.online_step_module()
    out = {
        "eager observer.step": (lambda: obs.init_state(1), obs.step),
        "eager OnlineStep": (online.initial_state, lambda s, y: online(*s, y)),
    }
    t0 = time.perf_counter()
    compiled = torch.compile(online, dynamic=False)
    with torch.inference_mode():
        compiled(*online.initial_state(), torch.zeros(1, obs.measurement_dim, dtype=torch.float64))
    build = {"torch.compile(OnlineStep)": time.perf_counter() - t0}
    out["torch.compile(OnlineStep)"] = (online.initial_state, lambda s, y: compiled(*s, y))
    t0 = time.perf_counter()
    program = export_observer(obs, tmp / "step.pt2", batch=1)
    exported = load_exported_step(tmp / "step.pt2")
    build["exported program"] = time.perf_counter() - t0
    out["exported program"] = (exported.initial_state, lambda s, y: exported(*s, y))
    if aoti:
        from torch._inductor import aoti_compile_and_package, aoti_load_package

        t0 = time.perf_counter()
        pkg = aoti_compile_and_package(program, package_path=str(tmp / "step_aoti.pt2"))
        native = aoti_load_package(pkg)
        build["exported, AOTInductor"] = time.perf_counter() - t0
        out["exported, AOTInductor"] = (exported.initial_state, lambda s, y: native(*s, y))
    core = obs.core
    inp = torch.zeros(1, core.input_size)
    out["core alone, eager"] = (
        lambda: ObserverState(None, core.initial_hidden(1)),
        lambda s, y: ObserverState(None, core.step(inp, s.hidden)[1]),
    )
    return out, build


def _time(variants: dict, ys: torch.Tensor, rounds: int) -> dict[str, list[float]]:
    times = {k: [] for k in variants}
    perf = time.perf_counter
    with torch.inference_mode():
        for r in range(rounds):
            for name, (init, step) in variants.items():
                state, ts = init(), []
                for y in ys:
                    t0 = perf()
                    state = step(state, y)
                    ts.append(perf() - t0)
                if r:  # round 0: warm-up
                    times[name] += ts
    return times


def _check_agreement(variants: dict, ys: torch.Tensor) -> dict[str, float]:
    """Largest difference of each variant's estimate from the eager step's over the stream."""
    def run(init, step):
        state = init()
        with torch.inference_mode():
            for y in ys:
                state = step(state, y)
        x = state.estimate if hasattr(state, "estimate") else state[0]
        return x.reshape(1, -1)

    ref = run(*variants["eager observer.step"])
    return {
        k: float((run(*v) - ref).abs().max())
        for k, v in variants.items() if k not in ("eager observer.step", "core alone, eager")
    }


def _profile(obs, ys: torch.Tensor, top: int = 12) -> str:
    from torch.profiler import ProfilerActivity, profile

    state = obs.init_state(1)
    with torch.inference_mode(), profile(activities=[ProfilerActivity.CPU]) as prof:
        for y in ys:
            state = obs.step(state, y)
    return prof.key_averages().table(sort_by="self_cpu_time_total", row_limit=top)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--steps", type=int, default=200, help="steps per round and variant")
    ap.add_argument("--rounds", type=int, default=11, help="rounds (the first is a warm-up)")
    ap.add_argument("--no-aoti", action="store_true", help="skip AOTInductor (needs a compiler)")
    ap.add_argument("--profile", action="store_true", help="add the eager step's top operators")
    ap.add_argument("--write", action="store_true", help="write benchmarks/results/online_step.md")
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    load0 = os.getloadavg()[0]
    obs, system, model = _observer()
    data = system.simulate(1, args.steps, 0.1, torch.Generator().manual_seed(0))
    ys = data.measurements.transpose(0, 1).contiguous()  # (T, 1, 18) float64
    with tempfile.TemporaryDirectory() as tmp:
        variants, build = _variants(obs, Path(tmp), aoti=not args.no_aoti)
        agree = _check_agreement(variants, ys)
        times = _time(variants, ys, args.rounds)
    load1 = os.getloadavg()[0]
    ref = statistics.median(times["eager observer.step"])
    ref10 = statistics.quantiles(times["eager observer.step"], n=10)[0]
    given = sys.argv[1:] if argv is None else argv
    cmd = " ".join(["python benchmarks/bench_online_step.py", *given])
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True,
                            text=True).stdout.strip()
    lines = [
        "# The online step at batch 1: eager, compiled, exported",
        "",
        f"`{cmd}` (commit {commit}, {time.strftime('%Y-%m-%d %H:%M')})",
        "",
        f"{describe_machine()}; torch {torch.__version__}, 1 thread, OMP_WAIT_POLICY="
        f"{os.environ.get('OMP_WAIT_POLICY', '(unset)')}; load average {load0:.1f} at the start, "
        f"{load1:.1f} at the end (a shared machine: compare the ratios, not the times).",
        "",
        f"The rigid body's observer of `experiment=default`: a {model.num_layers}x"
        f"{model.hidden_size} GRU, innovation {obs.signature()['measurement']['factors']}, updates "
        f"{dict(model.updates)}, {model.net_dtype} network, {model.state_dtype} state; "
        f"{args.steps} steps per round, {args.rounds - 1} rounds counted (the first is a warm-up), "
        "variants interleaved; median and 10th percentile of the per-step times.",
        "",
        "| variant | median (us) | p10 (us) | ratio to eager step (median) | ratio (p10) "
        "| max diff from eager | build (s) |",
        "|---|---:|---:|---:|---:|---:|---:|",
    ]
    for name, ts in times.items():
        med, p10 = statistics.median(ts), statistics.quantiles(ts, n=10)[0]
        diff = f"{agree[name]:.1e}" if name in agree else "-"
        b = f"{build[name]:.1f}" if name in build else "-"
        lines.append(
            f"| {name} | {med * 1e6:.1f} | {p10 * 1e6:.1f} | {med / ref:.3f} | {p10 / ref10:.3f} "
            f"| {diff} | {b} |"
        )
    if args.profile:
        lines += ["", "Top operators of the eager step (self CPU time, "
                  f"{args.steps} steps, torch.profiler):", "", "```",
                  _profile(obs, ys), "```"]
    text = "\n".join(lines) + "\n"
    print(text)
    if args.write:
        out = ROOT / "benchmarks" / "results" / "online_step.md"
        out.write_text(text)
        print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
