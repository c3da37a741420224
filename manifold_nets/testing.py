"""The contract suite for systems: ``check_system(MySystem())``, as ``groups.testing.check_group``
is for groups.

A :class:`~manifold_nets.system.System` promises more than its methods' signatures: the same seed
gives the same data, states stay on the group, an overridden ``rollout`` agrees with ``step``,
the measurements of ``simulate`` are ``measure(x_{k+1}, w_k, sigma * nu)``, the noise enters the
measurement, ``step`` and ``measure`` keep the dtype, take batches and are differentiable (an
error-state EKF linearises them). One call checks all of it on a few short sequences (about a
second for the shipped systems). From your own test::

    from manifold_nets.testing import check_system

    def test_my_system_keeps_the_contract():
        check_system(MySystem())        # raises AssertionError naming each broken property

Each property is also a public function of the same arguments (``check_rollout_matches_step``,
``check_noise_enters``, ...; :data:`CHECKS` maps the names to them), so one can be run alone or
left out with ``check_system(system, checks=[...])``. A failure says the property, the system,
what was found and the likely fix. Comparisons are relative, ``|a - b| <= atol (1 + |b|)``.
Nothing here checks physics: a system's own laws (its reference integrator, its noise law's
statistics) belong in its own tests.
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable, Iterable

import torch

from groups import GroupMembershipError, LieGroup

from .system import System

__all__ = [
    "CHECKS",
    "check_system",
    "check_attributes",
    "check_config",
    "check_determinism",
    "check_shapes",
    "check_on_group",
    "check_rollout_matches_step",
    "check_measure_matches_model",
    "check_noise_enters",
    "check_dtypes",
    "check_batching",
    "check_gradients",
]

F64 = torch.float64


# ---------------------------------------------------------------------------------------- helpers


def _who(system: object) -> str:
    try:
        return repr(system)
    except Exception:  # a broken config() must not hide the failure being reported
        return type(system).__name__


def _fail(prop: str, system: object, found: str, fix: str) -> None:
    raise AssertionError(f"{prop}: {_who(system)}: {found}. Fix: {fix}")


def _gen(seed: int) -> torch.Generator:
    return torch.Generator().manual_seed(seed)


def _draw(system: System, n: int, t: int, seed: int):
    """``x0``, the drives and the unit noise ``(n, t, noise_dim)`` in :meth:`System.simulate`'s
    order from one generator seeded with ``seed``."""
    g = _gen(seed)
    x0 = system.sample_initial_state(n, g)
    drive = system.sample_drive(n, t, g)
    noise = torch.randn(n, t, system.noise_dim, generator=g, dtype=F64)
    return x0, drive, noise


def _rel_err(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Elementwise ``|a - b| / (1 + |b|)`` in float64."""
    a, b = a.to(F64), b.to(F64)
    return (a - b).abs() / (1.0 + b.abs())


def _worst(a: torch.Tensor, b: torch.Tensor) -> float:
    if a.shape != b.shape:
        return math.inf
    err = _rel_err(a, b)
    return float(err.max()) if err.numel() else 0.0


def _shape(t: object) -> str:
    return str(tuple(t.shape)) if isinstance(t, torch.Tensor) else type(t).__name__


# ---------------------------------------------------------------------------------------- checks


def check_attributes(system: System, num_sequences=3, length=5, seed=0, sigma=0.1, atol=1e-9):
    """The declared attributes: ``group`` a :class:`groups.LieGroup`, ``measurement_dim >= 1``,
    ``input_dim``, ``drive_dim``, ``noise_dim`` integers ``>= 0``, ``dt`` finite and ``> 0``,
    ``name`` a non-empty string usable in a file name."""
    prop = "attributes"
    if not isinstance(getattr(system, "group", None), LieGroup):
        _fail(prop, system, f"group is {type(getattr(system, 'group', None)).__name__}",
              "set self.group to a groups.LieGroup (e.g. Product(SO3(), Euclidean(3)))")
    for attr, low in (("measurement_dim", 1), ("input_dim", 0), ("drive_dim", 0),
                      ("noise_dim", 0)):
        v = getattr(system, attr, None)
        if isinstance(v, bool) or not isinstance(v, int) or v < low:
            _fail(prop, system, f"{attr} is {v!r}", f"set {attr} to an integer >= {low}")
    dt = getattr(system, "dt", None)
    if isinstance(dt, bool) or not isinstance(dt, (int, float)) or not 0 < dt < math.inf:
        _fail(prop, system, f"dt is {dt!r}", "set dt, the step length in seconds, finite > 0")
    name = getattr(system, "name", None)
    if not isinstance(name, str) or not name or any(c in name for c in "/\\ "):
        _fail(prop, system, f"name is {name!r}",
              "set name to a short string without spaces or slashes (it names files)")


def check_config(system: System, num_sequences=3, length=5, seed=0, sigma=0.1, atol=1e-9):
    """``config()`` is a dict of JSON-able values, the same on every call (the dataset cache
    hashes it), and ``repr(system)`` works."""
    prop = "config"
    first, second = system.config(), system.config()
    if not isinstance(first, dict):
        _fail(prop, system, f"config() returned {type(first).__name__}",
              "return a dict of the parameters that change the data")
    try:
        text = json.dumps(first, sort_keys=True, allow_nan=False)
    except (TypeError, ValueError) as err:
        _fail(prop, system, f"config() is not JSON-able ({err})",
              "return plain floats, ints, strings, bools and lists (tensor.tolist(), not tensors)")
    if json.dumps(second, sort_keys=True, allow_nan=False) != text:
        _fail(prop, system, f"two calls of config() differ: {first} and {second}",
              "config() must be deterministic: no random or time-dependent values")
    repr(system)


def check_determinism(system: System, num_sequences=3, length=5, seed=0, sigma=0.1, atol=1e-9):
    """The same seed gives the same data, another seed other data, the states do not depend on
    ``sigma``, and ``simulate`` draws only from its generator (torch's global one untouched)."""
    prop = "determinism"
    n, t = num_sequences, length
    state = torch.random.get_rng_state()
    a = system.simulate(n, t, sigma, _gen(seed))
    if not torch.equal(torch.random.get_rng_state(), state):
        _fail(prop, system, "simulate drew from torch's global random generator",
              "draw only from the generator passed to sample_initial_state and sample_drive "
              "(torch.rand(..., generator=generator))")
    b = system.simulate(n, t, sigma, _gen(seed))
    for field in ("states", "measurements", "inputs"):
        if not torch.equal(getattr(a, field), getattr(b, field)):
            _fail(prop, system, f"the same seed {seed} gave different {field}",
                  "draw every random quantity from the generator you are given, nothing else")
    c = system.simulate(n, t, sigma, _gen(seed + 1))
    if torch.equal(a.states, c.states) and torch.equal(a.measurements, c.measurements):
        _fail(prop, system, f"seeds {seed} and {seed + 1} gave identical data",
              "the samplers must use the generator they are given")
    clean = system.simulate(n, t, 0.0, _gen(seed))
    if not torch.equal(clean.states, a.states):
        _fail(prop, system, f"the states at sigma=0 differ from those at sigma={sigma}",
              "the noise is drawn by simulate after the states and drives; draw nothing "
              "random in step, rollout or measure")


def check_shapes(system: System, num_sequences=3, length=5, seed=0, sigma=0.1, atol=1e-9):
    """Shapes and dtypes: the samplers' ``(N, *element_shape)`` and ``(N, T, drive_dim)``
    float64; ``simulate``'s states ``(N, T+1, *element_shape)``, measurements ``(N, T,
    measurement_dim)``, inputs ``(N, T, input_dim)``, float64 and finite; ``inputs(drive)``
    ``(*batch, input_dim)``; ``step`` and ``measure`` of one batch."""
    prop, n, t = "shapes", num_sequences, length
    el, m = tuple(system.group.element_shape), system.measurement_dim
    x0, drive, noise = _draw(system, n, t, seed)
    data = system.simulate(n, t, sigma, _gen(seed))
    wants = {
        "sample_initial_state(N, generator)": (x0, (n, *el)),
        "sample_drive(N, T, generator)": (drive, (n, t, system.drive_dim)),
        "simulate(...).states": (data.states, (n, t + 1, *el)),
        "simulate(...).measurements": (data.measurements, (n, t, m)),
        "simulate(...).inputs": (data.inputs, (n, t, system.input_dim)),
    }
    for what, (got, shape) in wants.items():
        if not isinstance(got, torch.Tensor) or tuple(got.shape) != shape or got.dtype != F64:
            dtype = getattr(got, "dtype", None)
            _fail(prop, system, f"{what} is {_shape(got)} {dtype}, expected {shape} float64",
                  "return float64 tensors of the documented shapes (see System's docstrings)")
        if not bool(torch.isfinite(got).all()):
            _fail(prop, system, f"{what} holds NaN or Inf", "keep the simulation finite")
    calls = {
        "inputs(drive)": (lambda: system.inputs(drive), (n, t, system.input_dim)),
        "inputs(drive[:, 0])": (lambda: system.inputs(drive[:, 0]), (n, system.input_dim)),
        "step(x, w)": (lambda: system.step(x0, drive[:, 0]), (n, *el)),
        "measure(x, w)": (lambda: system.measure(x0, drive[:, 0]), (n, m)),
        "measure(x, w, noise)": (lambda: system.measure(x0, drive[:, 0], noise[:, 0]), (n, m)),
    }
    for what, (call, shape) in calls.items():
        got = call()
        if not isinstance(got, torch.Tensor) or tuple(got.shape) != shape:
            _fail(prop, system, f"{what} with a batch of {n} is {_shape(got)}, expected {shape}",
                  "keep the batch dimensions leading: (*batch, ...) in, (*batch, ...) out")


def check_on_group(system: System, num_sequences=3, length=5, seed=0, sigma=0.1, atol=1e-9):
    """Every state is on the group (``group.check_member`` at its default tolerance for the
    dtype): the initial states, one ``step`` from them in float64 and in float32, and every
    state ``simulate`` returns."""
    prop = "on_group"
    x0, drive, _ = _draw(system, num_sequences, length, seed)
    candidates = {
        "sample_initial_state": lambda: x0,
        "step(x0, w_0)": lambda: system.step(x0, drive[:, 0]),
        "step(x0, w_0) in float32": lambda: system.step(x0.float(), drive[:, 0].float()),
        "simulate(...).states": lambda: system.simulate(
            num_sequences, length, sigma, _gen(seed)).states,
    }
    for what, get in candidates.items():
        try:
            system.group.check_member(get())
        except GroupMembershipError as err:
            _fail(prop, system, f"{what} is off the group ({err})",
                  "integrate on the group (x exp(v dt) is exact for a held velocity) or project "
                  "back onto it after each step; sample initial states with group.random or a "
                  "law that stays on the group")


def check_rollout_matches_step(
    system: System, num_sequences=3, length=5, seed=0, sigma=0.1, atol=1e-9
):
    """``rollout(x0, w)`` is ``(N, T+1, *element_shape)``, starts at ``x0`` and agrees with
    ``step`` applied ``T`` times, to ``atol`` (relative)."""
    prop, n, t = "rollout_matches_step", num_sequences, length
    x0, drive, _ = _draw(system, n, t, seed)
    states = system.rollout(x0, drive)
    want = (n, t + 1, *system.group.element_shape)
    if not isinstance(states, torch.Tensor) or tuple(states.shape) != want:
        _fail(prop, system, f"rollout returned {_shape(states)}, expected {want}",
              "return x_0 .. x_T as (N, T+1, *element_shape)")
    if not torch.equal(states[:, 0], x0):
        _fail(prop, system, "rollout's first state is not x0", "states[:, 0] must be x0 itself")
    x = x0
    for k in range(t):
        x = system.step(x, drive[:, k])
        worst = _worst(states[:, k + 1], x)
        if not worst <= atol:
            _fail(prop, system,
                  f"rollout disagrees with step at k={k + 1} by {worst:.3g} (atol {atol:g})",
                  "an overridden rollout must agree with step (same formula, same dt); raise "
                  "atol only for a reference integrator with its own tolerance")


def check_measure_matches_model(
    system: System, num_sequences=3, length=5, seed=0, sigma=0.1, atol=1e-9
):
    """``simulate``'s measurements are ``measure(x_{k+1}, w_k, sigma * nu_k)`` (noise drawn after
    the states and drives) and ``measure(x_{k+1}, w_k)`` at ``sigma = 0``;
    ``measure(x, w, 0) == measure(x, w)``; and, for a system that writes ``measure`` itself and
    has ``apply_noise``, ``apply_noise(measure(x, w), nu) == measure(x, w, nu)``."""
    prop, n, t = "measure_matches_model", num_sequences, length
    x0, drive, noise = _draw(system, n, t, seed)
    for s in (sigma, 0.0):
        data = system.simulate(n, t, s, _gen(seed))
        nz = noise * s if s > 0 else None
        worst = _worst(data.measurements, system.measure(data.states[:, 1:], drive, nz))
        if not worst <= atol:
            _fail(prop, system, f"simulate's measurements at sigma={s} differ from "
                  f"measure(x_{{k+1}}, w_k, sigma * noise) by {worst:.3g}",
                  "y_{k+1} is measure of the state after step k with the drive of step k; an "
                  "overridden simulate must draw x0, drives, then noise, from one generator")
    x1, w = system.step(x0, drive[:, 0]), drive[:, 0]
    worst = _worst(system.measure(x1, w, torch.zeros_like(noise[:, 0])), system.measure(x1, w))
    if not worst <= atol:
        _fail(prop, system, f"measure(x, w, zeros) differs from measure(x, w) by {worst:.3g}",
              "apply_noise(y, 0) must give y back: zero noise is the noise-free model")
    if type(system).measure is not System.measure:
        try:
            via = system.apply_noise(system.measure(x1, w), sigma * noise[:, 0])
        except NotImplementedError:
            return  # no noise rule to compare with: measure is the only model
        worst = _worst(via, system.measure(x1, w, sigma * noise[:, 0]))
        if not worst <= atol:
            _fail(prop, system, f"apply_noise(measure(x, w), nu) differs from measure(x, w, nu) "
                  f"by {worst:.3g}", "write observe(x, w) and apply_noise and let System derive "
                  "measure, so noise-augmented training adds the same noise as simulate")


def check_noise_enters(system: System, num_sequences=3, length=5, seed=0, sigma=0.1, atol=1e-9):
    """Every component of the noise changes the measurement: ``measure(x, w, 0.1 e_j)`` differs
    from ``measure(x, w)`` for each ``j < noise_dim``."""
    prop, d = "noise_enters", system.noise_dim
    if d == 0:
        return
    x0, drive, _ = _draw(system, 1, 1, seed)
    x = system.step(x0, drive[:, 0])
    y0 = system.measure(x, drive[:, 0])
    el = system.group.element_shape
    xs, ws = x.expand(d, *el), drive[:, 0].expand(d, system.drive_dim)
    y = system.measure(xs, ws, 0.1 * torch.eye(d, dtype=F64))
    change = (y - y0).abs().flatten(1).amax(-1)
    dead = [j for j in range(d) if not float(change[j]) > 1e-12]
    if dead:
        _fail(prop, system, f"noise component(s) {dead} of {d} do not change the measurement",
              "measure(x, w, noise) must use every entry of noise: write apply_noise (or check "
              "that measure passes noise on) and make noise_dim its size")


def check_dtypes(system: System, num_sequences=3, length=5, seed=0, sigma=0.1, atol=1e-9):
    """``step``, ``measure`` (with and without noise) and ``inputs`` return the dtype they are
    given, float32 and float64, with finite values."""
    prop = "dtypes"
    x0, drive, noise = _draw(system, num_sequences, 1, seed)
    for dtype in (torch.float32, F64):
        x, w, nz = x0.to(dtype), drive[:, 0].to(dtype), (sigma * noise[:, 0]).to(dtype)
        calls = {
            "step(x, w)": lambda: system.step(x, w),
            "measure(x, w)": lambda: system.measure(x, w),
            "measure(x, w, noise)": lambda: system.measure(x, w, nz),
            "inputs(w)": lambda: system.inputs(w),
        }
        for what, call in calls.items():
            out = call()
            if out.dtype != dtype or not bool(torch.isfinite(out).all()):
                _fail(prop, system, f"{what} in {dtype} returned {out.dtype}"
                      + ("" if out.dtype != dtype else " with NaN or Inf"),
                      "build constants in the input's dtype and device (torch.tensor(c, "
                      "dtype=x.dtype, device=x.device)); no float64 literals tensors")


def check_batching(system: System, num_sequences=3, length=5, seed=0, sigma=0.1, atol=1e-9):
    """``step`` and ``measure`` broadcast batch dimensions like torch: states ``(A, 1, ...)``
    with drives ``(1, B, drive_dim)`` (and noise ``(A, B, noise_dim)``) give ``(A, B, ...)``,
    equal (to ``atol``) to the results for each unbatched pair."""
    prop, a = "batching", num_sequences
    x0, drive, noise = _draw(system, a, max(length, 2), seed)
    w = drive[0, : min(3, drive.shape[1])]  # (B, drive_dim)
    b, el = w.shape[0], tuple(system.group.element_shape)
    nz = sigma * noise[:, :b]  # (A, B, noise_dim)
    xs = x0.reshape(a, 1, *el)
    fix = ("broadcast the batch dimensions of every argument (torch.broadcast_shapes, "
           "Tensor.expand) before concatenating or stacking")
    cases = {
        "step": (lambda: system.step(xs, w[None]), lambda i, j: system.step(x0[i], w[j]), el),
        "measure": (lambda: system.measure(xs, w[None], nz),
                    lambda i, j: system.measure(x0[i], w[j], nz[i, j]),
                    (system.measurement_dim,)),
    }
    for what, (batched, single, tail) in cases.items():
        args = f"states {tuple(xs.shape)} and drives {(1, *w.shape)}"
        try:
            got = batched()
        except (RuntimeError, ValueError) as err:
            _fail(prop, system, f"{what} of {args} raised {type(err).__name__}: {err}", fix)
        if tuple(got.shape) != (a, b, *tail):
            _fail(prop, system, f"{what} of {args} is {tuple(got.shape)}, expected "
                  f"{(a, b, *tail)}", fix)
        for i in range(a):
            for j in range(b):
                worst = _worst(got[i, j], single(i, j))
                if not worst <= atol:
                    _fail(prop, system, f"batched {what} differs from the unbatched result at "
                          f"({i}, {j}) by {worst:.3g}", "treat every batch element "
                          "independently; index the last dimensions only (x[..., k])")


def check_gradients(system: System, num_sequences=3, length=5, seed=0, sigma=0.1, atol=1e-9):
    """In float64 on a batch of 2: ``step(x exp(d), w)`` in the right perturbation ``d`` and the
    drive ``w``, and ``measure(x exp(d), w, nu)`` in ``d``, ``w`` and ``nu`` pass
    ``torch.autograd.gradcheck``, and their Jacobians at ``d = 0, nu = 0`` (where an EKF
    linearises) are finite."""
    prop, g = "gradients", system.group
    x0, drive, noise = _draw(system, 2, 1, seed)
    x, w = x0, drive[:, 0].clone()
    d = 0.1 * torch.randn(2, g.tangent_dim, generator=_gen(seed + 2), dtype=F64)
    nu = sigma * noise[:, 0]
    f = lambda d, w: system.step(g.rplus(x, d), w)  # noqa: E731
    h = lambda d, w, nu: system.measure(g.rplus(x, d), w, nu)  # noqa: E731
    for what, fn, args in (("step", f, (d, w)), ("measure", h, (d, w, nu))):
        zero = [torch.zeros_like(a) if i != 1 else a for i, a in enumerate(args)]
        jac = torch.autograd.functional.jacobian(fn, tuple(zero), vectorize=True)
        if not all(bool(torch.isfinite(j).all()) for j in jac):
            _fail(prop, system, f"the Jacobian of {what} at zero perturbation and noise holds "
                  "NaN or Inf", "use NaN-safe formulas (the groups' exp/log are) at 0")
        inputs = tuple(a.detach().clone().requires_grad_(True) for a in args)
        try:
            torch.autograd.gradcheck(fn, inputs, eps=1e-6, atol=1e-5, rtol=1e-4, fast_mode=True)
        except Exception as err:  # GradcheckError, or a RuntimeError of a detached graph
            first = str(err).strip().splitlines()[0][:300]
            _fail(prop, system, f"{what} fails gradcheck in float64 ({first})",
                  f"keep {what} plain differentiable torch: no .item(), numpy, .detach() or "
                  "in-place writes into inputs")


# ---------------------------------------------------------------------------------------- runner

#: Every property by name, in the order :func:`check_system` runs them.
CHECKS: dict[str, Callable[..., None]] = {
    "attributes": check_attributes,
    "config": check_config,
    "determinism": check_determinism,
    "shapes": check_shapes,
    "on_group": check_on_group,
    "rollout_matches_step": check_rollout_matches_step,
    "measure_matches_model": check_measure_matches_model,
    "noise_enters": check_noise_enters,
    "dtypes": check_dtypes,
    "batching": check_batching,
    "gradients": check_gradients,
}


def check_system(
    system: System,
    *,
    num_sequences: int = 3,
    length: int = 5,
    seed: int = 0,
    sigma: float = 0.1,
    atol: float = 1e-9,
    checks: Iterable[str] | None = None,
) -> None:
    """Checks ``system`` against the :class:`~manifold_nets.system.System` contract.

    Args:
        system: the system to check, e.g. ``MySystem()``.
        num_sequences, length: the size of the simulated batches (small is enough).
        seed: the generator seed of every draw.
        sigma: the noise level of the noisy draws (> 0).
        atol: relative tolerance of the value comparisons (rollout against step, simulated
            against recomputed measurements, batched against unbatched); raise it for a
            reference integrator with a tolerance of its own.
        checks: names from :data:`CHECKS` to run (default: all).

    Raises:
        AssertionError: listing every failing property, each with the system, what was found
            and the likely fix. An exception raised by the system inside a check is reported
            as that check's failure.
        ValueError: bad arguments (an unknown check, ``sigma <= 0``, sizes < 1).
    """
    names = list(CHECKS) if checks is None else list(checks)
    unknown = [c for c in names if c not in CHECKS]
    if unknown:
        raise ValueError(f"unknown checks {unknown}; choose from {list(CHECKS)}.")
    for arg, val in (("num_sequences", num_sequences), ("length", length)):
        if isinstance(val, bool) or not isinstance(val, int) or val < 1:
            raise ValueError(f"{arg} must be a positive integer, got {val!r}.")
    if not (isinstance(sigma, (int, float)) and 0 < sigma < math.inf):
        raise ValueError(f"sigma must be finite and > 0 (the noise checks need it), got {sigma!r}.")
    kwargs = dict(num_sequences=num_sequences, length=length, seed=seed, sigma=sigma, atol=atol)
    failures = []
    for name in names:
        try:
            CHECKS[name](system, **kwargs)
        except AssertionError as err:
            failures.append(str(err))
        except Exception as err:
            failures.append(f"{name}: {_who(system)}: raised {type(err).__name__}: {err}. Fix: "
                            f"see check_{name}'s docstring for how the check calls the system")
    if failures:
        raise AssertionError(
            f"check_system({_who(system)}): {len(failures)} of {len(names)} check(s) failed.\n"
            + "\n".join(f"- {f}" for f in failures)
        )
