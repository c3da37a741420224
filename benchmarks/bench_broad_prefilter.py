"""BROAD's pre-filters as the library's readings filter (``broad.imu_prefilter``): equality with
the numpy ones, speed over a whole trial, and what filtering at the observer's rate costs.

Run by hand from the repository root (not by CI), with BROAD's ``.mat`` files where the split
file says (``configs/broad/trials.yaml``) or under ``--data-dir``::

    python benchmarks/bench_broad_prefilter.py --write        # writes results/broad_prefilter.md

* **equality and speed** on trial 01 (57,000 samples at 285.7 Hz, the zoo entry's filters):
  ``ImuPrefilter``'s whole-sequence method against ``prefiltered`` (numpy, batch) and
  ``OnlinePrefilter`` (numpy, a sample at a time), and its own step looped over the trial;
* **the observer's rate**: ``zoo:broad/attitude`` on the ``--split`` trials, scored (the
  benchmark's RMSE) at its own steps, every 8th sample, where (a) the full-rate readings are
  pre-filtered, then decimated (what the BROAD commands do) and (b) the decimated raw readings
  go through its system's ``readings_filter()`` at 35.7 Hz (what ``mn-apply`` and the exported
  step of ``with_readings_filter`` do), each from TRIAD of the first step's readings it reads.
"""

from __future__ import annotations

import argparse
import os
import time
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np  # noqa: E402
import torch  # noqa: E402

from manifold_nets import load_observer  # noqa: E402
from manifold_nets.observer import with_readings_filter  # noqa: E402
from manifold_nets_examples.broad.data import G0, M0, read_trials, split_trials  # noqa: E402
from manifold_nets_examples.broad.evaluate import observer_quaternions, pad_trials  # noqa: E402
from manifold_nets_examples.broad.imu_prefilter import ImuPrefilter  # noqa: E402
from manifold_nets_examples.broad.learning import measured_start  # noqa: E402
from manifold_nets_examples.broad.metric import matrix_to_quat, rmse  # noqa: E402
from manifold_nets_examples.broad.prefilter import OnlinePrefilter, prefiltered  # noqa: E402
from manifold_nets_examples.broad.rate import decimate  # noqa: E402

RESULTS = Path(__file__).resolve().parent / "results"


def _timed(fn):
    t0 = time.perf_counter()
    out = fn()
    return out, time.perf_counter() - t0


def equality_and_speed(trial, step_samples: int, tau: float, order: int) -> list[str]:
    y = torch.from_numpy(np.concatenate((trial.acc / G0, trial.mag / M0), 1))[None]
    u = torch.from_numpy(trial.gyr)[None]
    f = ImuPrefilter(trial.rate, tau, rest=True, order=order)
    (yf, uf, _), t_seq = _timed(lambda: f(y, u))
    want, t_batch = _timed(lambda: prefiltered(trial, tau, rest=True, order=order))
    online = OnlinePrefilter(trial.rate, tau, rest=True, order=order)
    got, t_online = _timed(lambda: [online.update(g, a) for g, a in zip(trial.gyr, trial.acc)])
    state, ys = f.init_state(1), []
    t0 = time.perf_counter()
    with torch.inference_mode():
        for k in range(step_samples):
            state, y_k, _ = f.step_unchecked(state, y[:, k].contiguous(), u[:, k].contiguous())
            ys.append(y_k)
    t_step = (time.perf_counter() - t0) / step_samples
    acc = yf[0, :, :3].numpy() * G0
    n = len(trial.gyr)
    return [
        f"Trial {trial.name}, {n} samples at {trial.rate:.1f} Hz, the shipped entry's filters "
        f"(tau {tau:g} s, order {order}, rest bias), float64:",
        "",
        "| | max abs difference of the piece's sequence: acc (m/s^2) | gyr (rad/s) | time |",
        "|---|---|---|---|",
        f"| `ImuPrefilter` whole sequence | - | - | {t_seq:.3f} s |",
        f"| `prefiltered` (numpy batch) | {np.abs(acc - want.acc).max():.2g} | "
        f"{np.abs(uf[0].numpy() - want.gyr).max():.2g} | {t_batch:.3f} s |",
        f"| `OnlinePrefilter` (numpy, per sample) | "
        f"{np.abs(acc - np.array([a for _, a in got])).max():.2g} | "
        f"{np.abs(uf[0].numpy() - np.array([g for g, _ in got])).max():.2g} | {t_online:.2f} s |",
        f"| `ImuPrefilter.step_unchecked` looped (first {step_samples}) | "
        f"{(torch.cat(ys)[:, :3] - yf[0, :step_samples, :3]).abs().max().item() * G0:.2g} | - | "
        f"{t_step * 1e6:.0f} us per sample |",
        "",
    ]


def observer_rate(trials) -> list[str]:
    observer, system, _ = load_observer("zoo:broad/attitude")
    k = round(system.dt * trials[0].rate)
    full = observer_quaternions(observer, system, trials)
    filtered = with_readings_filter(observer, system)
    batch, lengths = pad_trials(trials)
    dec = decimate(batch, k, 1 / trials[0].rate)
    x0 = measured_start(system)(dec).to(observer.state_dtype)
    start = filtered.init_state(len(dec), estimate=x0)
    with torch.inference_mode():
        library = matrix_to_quat(filtered(dec.measurements, dec.inputs, state=start).numpy())
    lines = [f"`zoo:broad/attitude`, scored at its steps (every {k}th sample):", "",
             "| trial | full-rate filters: total | incl. | at the observer's rate: total | incl. |",
             "|---|---|---|---|---|"]
    rows = []
    for i, t in enumerate(trials):
        n = (lengths[i] - 1) // k + 1
        at = slice(0, n * k, k)
        a = rmse(full[i][at], t.quat[at], t.movement[at])
        b = rmse(library[i, :n], t.quat[at], t.movement[at])
        rows.append((a["total"], a["inclination"], b["total"], b["inclination"]))
        lines.append(f"| {t.name} | {a['total']:.3f} | {a['inclination']:.3f} | "
                     f"{b['total']:.3f} | {b['inclination']:.3f} |")
    m = np.mean(rows, 0)
    lines.append(f"| **mean** | {m[0]:.3f} | {m[1]:.3f} | {m[2]:.3f} | {m[3]:.3f} |")
    return lines + [""]


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--data-dir", default=None)
    p.add_argument("--split", default="test")
    p.add_argument("--step-samples", type=int, default=3000)
    p.add_argument("--write", action="store_true", help="write results/broad_prefilter.md")
    a = p.parse_args(argv)
    torch.set_num_threads(1)
    data_dir, split = split_trials(None)
    data_dir = a.data_dir or data_dir
    (trial,) = read_trials(data_dir, ["01_undisturbed_slow_rotation_A"])
    lines = ["# BROAD's pre-filters as the library's readings filter", "",
             "`python benchmarks/bench_broad_prefilter.py --write`: one CPU thread, the shared "
             "2-core machine.", ""]
    system = load_observer("zoo:broad/attitude").system
    lines += equality_and_speed(trial, a.step_samples, system.acc_lowpass, system.acc_lowpass_order)
    lines += observer_rate(read_trials(data_dir, split[a.split]))
    text = "\n".join(lines)
    print(text)
    if a.write:
        (RESULTS / "broad_prefilter.md").write_text(text)


if __name__ == "__main__":
    main()
