"""Shared test helpers for observer options: rollout = online = pieces = exported step; a tiny train
command run loaded back; a small SO(3) dataset; a random output layer for an untrained observer."""

from __future__ import annotations

from pathlib import Path

import torch

from groups import SO3
from manifold_nets.data import TrajectoryDataset


def randomise_head(obs, seed: int | None = None, scale: float = 1.0) -> None:
    """Gives ``obs.core.head`` (a :class:`~manifold_nets.cores.GRUCore`'s output layer) random
    weights, ``nn.Linear``'s own initialisation times ``scale``, drawn under ``seed`` when given
    (else from the global generator). A core the observer makes starts with that layer at zero
    (an untrained observer holds still); a test that needs an untrained observer that moves
    calls this."""
    head = obs.core.head
    with torch.no_grad():
        if seed is None:
            head.reset_parameters()
        else:
            with torch.random.fork_rng(devices=[]):
                torch.manual_seed(seed)
                head.reset_parameters()
        head.weight.mul_(scale)
        head.bias.mul_(scale)


def assert_online_matches_rollout(obs, measurements: torch.Tensor, atol: float = 1e-12):
    """Rolls ``obs`` over ``measurements`` (N, T, l), steps it online and through
    ``online_step_module()`` (what the exporters trace), and asserts every estimate agrees to
    ``atol``. Returns the rollout's estimates."""
    n, t = measurements.shape[:2]
    with torch.no_grad():
        est = obs(measurements)
        state = obs.init_state(n)
        for k in range(t):
            state = obs.step(state, measurements[:, k])
            assert torch.allclose(state.estimate, est[:, k + 1], atol=atol), k
        step = obs.online_step_module()
        x, *hidden = step.initial_state(n)
        for k in range(t):
            x, *hidden = step(x, *hidden, measurements[:, k])
    assert torch.allclose(x, est[:, -1].reshape(n, -1), atol=atol)
    return est


def assert_pieces_and_export_match(obs, measurements: torch.Tensor, tmp_path, split: int = 4):
    """:func:`assert_online_matches_rollout`, then the rollout in two pieces (the state carried at
    ``split``) and the exported step (``export_observer``) against it. Returns the estimates."""
    from manifold_nets import export_observer
    from manifold_nets.deploy import load_exported_step

    n, t = measurements.shape[:2]
    est = assert_online_matches_rollout(obs, measurements, atol=1e-10)
    with torch.no_grad():
        head, state = obs(measurements[:, :split], return_state=True)
        tail = obs(measurements[:, split:], state=state)
    torch.testing.assert_close(torch.cat([head, tail[:, 1:]], 1), est, rtol=0, atol=1e-12)
    export_observer(obs, tmp_path / "step.pt2")
    step = load_exported_step(tmp_path / "step.pt2")
    x, *state = step.initial_state(n)
    for k in range(t):
        x, *state = step(x, *state, measurements[:, k])
    torch.testing.assert_close(x, est[:, -1].reshape(n, -1), rtol=0, atol=1e-10)
    return est


def run_tiny(experiment: str, tmp_path, out, *more: str):
    """Runs the train command on ``experiment`` with ``debug=tiny`` (and the overrides ``more``)
    into ``out``, its datasets cached under ``tmp_path / "data"``. Returns the composed config."""
    from hydra import compose, initialize_config_dir

    from manifold_nets.cli.train import run

    root = Path(__file__).resolve().parents[1]
    overrides = [
        f"experiment={experiment}", "debug=tiny", f"dataset.cache_dir={tmp_path / 'data'}", *more
    ]
    with initialize_config_dir(config_dir=str(root / "configs"), version_base="1.3"):
        cfg = compose("train", overrides=overrides)
    run(cfg, out)
    return cfg


def train_tiny_and_load(experiment: str, tmp_path, *more: str):
    """:func:`run_tiny` into ``tmp_path / "run"``, loaded back: ``(observer, system, config)``
    from ``manifold_nets.load_observer``."""
    from manifold_nets import load_observer

    run_tiny(experiment, tmp_path, tmp_path / "run", *more)
    return load_observer(tmp_path / "run")


def so3_walk(n: int, t: int, seed: int) -> TrajectoryDataset:
    """A random walk on SO(3) from the identity, ``n`` sequences of ``t`` steps, measured
    (``vec R``) at noise levels 0 .. 0.5 (one per sequence)."""
    G = SO3()
    g = torch.Generator().manual_seed(seed)
    steps = G.exp(0.2 * torch.randn(n, t, 3, generator=g, dtype=torch.float64))
    states = [G.identity((n,), dtype=torch.float64)]
    for k in range(t):
        states.append(G.compose(states[-1], steps[:, k]))
    states = torch.stack(states, 1)
    sigma = torch.linspace(0.0, 0.5, n, dtype=torch.float64).reshape(n, 1, 1)
    noise = torch.randn(n, t, 9, generator=g, dtype=torch.float64)
    meas = states[:, 1:].flatten(-2) + sigma * noise
    return TrajectoryDataset(states, meas, torch.zeros(n, t, 0, dtype=torch.float64), {})


def rigid_readings(n: int = 5, t: int = 7, seed: int = 1):
    """``(y, x)``: ``n`` sequences of ``t`` random rigid-body readings (a rotation's 9 entries
    and 9 numbers, float64) and ``t + 1`` random states of :func:`rigid_short`."""
    from groups import SO3

    g = torch.Generator().manual_seed(seed)
    y = torch.cat([SO3().random((n, t), generator=g, dtype=torch.float64).flatten(-2),
                   torch.randn(n, t, 9, generator=g, dtype=torch.float64)], -1)
    return y, rigid_short().random((n, t + 1), generator=g, dtype=torch.float64)


def rigid_short():
    """``SO(3) x R^3 x R^3 x R^3`` named ``R, p, bw, bv``."""
    from groups import SO3, Euclidean, Product

    return Product(SO3(), Euclidean(3), Euclidean(3), Euclidean(3), names=("R", "p", "bw", "bv"))


def assert_covariances_close(got: torch.Tensor, want: torch.Tensor, tol: float = 1e-5) -> None:
    """``got`` and ``want`` ``(..., n, n)`` agree entry by entry to ``tol`` of each entry's own
    scale ``sqrt(P_ii P_jj)`` (a float32 readout's GRU over a sequence and its cell round
    differently: up to 2e-5 relative in a small off-diagonal entry on some CPUs)."""
    s = want.diagonal(dim1=-2, dim2=-1).sqrt()
    scale = s.unsqueeze(-1) * s.unsqueeze(-2)
    torch.testing.assert_close(got / scale, want / scale, rtol=0, atol=tol)


def assert_step_covariances_follow(step, flat, measurements: torch.Tensor, cov: torch.Tensor) -> None:
    """Runs an exported-style ``step`` from the state tensors ``flat`` over ``measurements``
    ``(B, T, l)``: its ``P`` after step ``k`` is ``cov[:, k + 1]`` (a rollout's)."""
    with torch.no_grad():
        for k in range(measurements.shape[1]):
            *flat, P = step(*flat, measurements[:, k])
            assert_covariances_close(P, cov[:, k + 1])


def noisy_walk(group, n: int, t: int, step: float, noise, seed: int = 0):
    """States ``(n, t+1, *element_shape)`` of a random walk on ``group`` (``step`` rad per axis
    and step) and measurements ``(n, t, embedding_dim)``: each state's embedding after a tangent
    perturbation of std ``noise`` (a number, or ``(n,)``, one per sequence). float64."""
    g = torch.Generator().manual_seed(seed)
    d = group.tangent_dim
    sd = torch.as_tensor(noise, dtype=torch.float64)
    sd = sd[:, None] if sd.dim() else sd
    x = group.random((n,), generator=g, dtype=torch.float64)
    states, ys = [x], []
    for _ in range(t):
        x = group.rplus(x, step * torch.randn(n, d, generator=g, dtype=torch.float64))
        states.append(x)
        ys.append(group.embed(group.rplus(x, sd * torch.randn(n, d, generator=g, dtype=torch.float64))))
    return torch.stack(states, 1), torch.stack(ys, 1)
