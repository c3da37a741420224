"""Priors: where the estimate goes before the learned correction, ``x^- = prior(x_k, y, u)``.

The paper has none (:class:`NoPrior`): the core's output moves the estimate alone. With a prior
the core learns what a filter's update adds to the prediction, not the prediction:

* :class:`SystemPrior`: the system's nominal model, ``System.predict(x, y, u)`` (for the rigid
  body the step with the bias-corrected readings);
* :class:`RobustSystemPrior`: the same step taken with each component of the drive weighted by a
  learned M-estimator weight function, ``d_i <- w_i(|d_i|) d_i``, ``d = System.compensated_drive``
  (a reading the motion cannot produce, an outlier, is pulled in before it moves anything);
* :class:`KinematicPrior`: named factors move by a measured velocity, ``x_f <- x_f exp(dt u_f)``
  (a gyroscope's rate), the rest stays;
* :class:`ComplementaryPrior`: after another prior, an attitude factor turns a fixed fraction of
  the way that aligns a measured direction with its known reference (the correction of Mahony's
  explicit complementary filter: an accelerometer's "up"); the network learns what it misses.

Interface: ``forward(x (B, numel) state dtype, yu (B, l + m) network dtype, ys (B, l + m) state
dtype) -> x^- (B, numel)``.
"""

from __future__ import annotations


import torch

from groups import SO3, Euclidean

from .piece import Piece, check_factor, check_int, check_number, check_spans
from .robust import MAX_SIZE, RobustWeights

__all__ = [
    "Prior", "NoPrior", "SystemPrior", "RobustSystemPrior", "KinematicPrior", "ComplementaryPrior",
]


class Prior(Piece):
    """``forward(x, yu, ys) -> x^-``: see the module docstring."""

    kind = "prior"
    #: Whether ``x^-`` is a prediction of the measurement (a centred head needs one).
    predicts = True


class NoPrior(Prior):
    """The paper's: ``x^- = x_k``."""

    name, predicts = "none", False

    def forward(self, x, yu, ys):
        return x


class SystemPrior(Prior):
    """``x^- = system.predict(x, y, u)``, the system's nominal model (differentiable in ``x``).

    The signature records that there is one (``{type: system}``), not which system.
    """

    name = "system"

    def __init__(self, system):
        super().__init__()
        if not callable(getattr(system, "predict", None)):
            raise TypeError(f"SystemPrior needs a System, got {type(system).__name__}.")
        self.system = system

    def bind(self, group, measurement):
        if repr(self.system.group) != repr(group):
            raise ValueError(
                f"the system prior predicts on {self.system.group!r}, but the observer's group is "
                f"{group!r} (a prior cannot be combined with factors taken off the group)."
            )
        self.l, self.m, self.shape = measurement.dim, measurement.input_dim, group.element_shape
        return self

    def _yu(self, x, ys):
        return x.unflatten(-1, self.shape), ys[:, : self.l], ys[:, self.l :] if self.m else None

    def forward(self, x, yu, ys):
        return self.system.predict(*self._yu(x, ys)).flatten(1)


class RobustSystemPrior(SystemPrior):
    """The system's step with a robustly weighted drive (module docstring).

    Args:
        system: a System whose ``predict`` is the base class's (``step(x, compensated_drive)``).
        width: steps of each learned weight function (>= 1); span: where they start (> 0).
    """

    name = "robust_system"

    def __init__(self, system, width: int = 16, span: float = 4.0):
        super().__init__(system)
        from manifold_nets.system import System

        if type(system).predict is not System.predict:
            raise ValueError(
                f"the robust system prior steps the weighted drive with {type(system).__name__}"
                f".step, but {type(system).__name__} overrides predict, so its prior may not be "
                "step(x, compensated_drive(x, y, u)). Write the prediction's drive in "
                "compensated_drive and leave predict to the base class, or use the plain "
                "system prior."
            )
        width = check_int("robust system prior: width", width, 1, high=MAX_SIZE)
        span = check_number("robust system prior: span", span, 1e-12, 1e12)
        self.robust = RobustWeights(system.drive_dim, width, span)

    def settings(self):
        return {"width": self.robust.width, "span": self.robust.span}

    def forward(self, x, yu, ys):
        x, y, u = self._yu(x, ys)
        d = self.system.compensated_drive(x, y, u)
        w = self.robust(d.abs().to(yu.dtype)).to(d.dtype)  # d_i <- w_i(|d_i|) d_i
        return self.system.step(x, w * d).flatten(1)

    def widen(self, state, prefix, old):
        """From the plain system prior: the weights start as the identity."""
        if old is not None and old.get("type") == self.name:
            return state
        new = RobustWeights(self.robust.channels, self.robust.width, self.robust.span)
        new = new.to(self.robust.amplitude)
        return {**state, **{f"{prefix}robust.{k}": v for k, v in new.state_dict().items()}}


class KinematicPrior(Prior):
    """``x_f <- x_f exp(dt u_f)`` for each named factor, ``u_f = (y, u)[start:stop]``.

    Args:
        velocities: ``{factor name: (start, stop)}``, the span of ``(y, u)`` holding the
            factor's velocity (``tangent_dim`` entries).
        dt: the step length in seconds (> 0).
    """

    name = "kinematic"

    def __init__(self, velocities: dict, dt: float):
        super().__init__()
        self.velocities = check_spans("kinematic prior: velocities", velocities, "(y, u)")
        if not self.velocities:
            raise ValueError("kinematic prior: name at least one factor's velocity span.")
        self.dt = check_number(
            "kinematic prior: dt", dt, 1e-12, 1e6, " (the step length in seconds, e.g. "
            "1/285.714 for a 285.714 Hz IMU)",
        )

    def bind(self, group, measurement):
        width = measurement.dim + measurement.input_dim
        self._moves = []
        for fname, (a, b) in self.velocities.items():
            check_factor("kinematic prior: velocities", group, fname)
            f = group.factor(fname)
            if not (0 <= a and b <= width and b - a == f.tangent_dim):
                raise ValueError(
                    f"kinematic prior: velocities[{fname!r}] = ({a}, {b}) must be a span of "
                    f"(y, u) (size {width}) of the factor's tangent_dim = {f.tangent_dim} entries."
                )
            self._moves.append((f, group.element_slice(fname), slice(a, b)))
        return self

    def settings(self):
        return {"velocities": {k: list(v) for k, v in self.velocities.items()}, "dt": self.dt}

    def forward(self, x, yu, ys):
        # assembled out of place: writing into x after handing a view of it to an SO(3) kernel
        # would tie the step's graph into a cycle no garbage collector frees
        # (tests/test_graph_release.py)
        moved = {}
        for f, xs, cols in self._moves:
            w = yu[:, cols].to(x.dtype) * self.dt
            if isinstance(f, Euclidean):
                moved[xs.start] = (xs.stop, x[:, xs] + w)
            else:
                moved[xs.start] = (xs.stop, f.rplus(x[:, xs].unflatten(-1, f.element_shape), w))
        pieces, at = [], 0
        for start in sorted(moved):
            stop, new = moved[start]
            pieces += [x[:, at:start], new.flatten(1)]
            at = stop
        return torch.cat([*pieces, x[:, at:]], dim=1)


class ComplementaryPrior(Prior):
    """After ``inner``, the SO(3) factor ``R`` turns towards a measured direction's reference:

    ``R^- <- exp((dt / tau) (R^- v / |v|) x r) R^-``, ``v = (y, u)[start:stop]`` a body-frame
    vector whose world-frame direction is the unit ``r`` (an accelerometer reads "up" at rest),
    the explicit complementary filter's correction (Mahony, Hamel and Pflimlin, IEEE TAC 2008)
    in the world frame with time constant ``tau``: a tilt off by a small angle decays as
    ``exp(-t / tau)``. The correction has no weights; the core sees ``R^-`` and learns what it
    misses (linear acceleration, the heading, the rest). A zero ``v`` (a zeroed sensor) corrects
    nothing.

    With ``about`` (a world-frame axis ``a``) it turns about ``a`` only, towards ``r``'s part
    normal to ``a``, from ``R^- v``'s part normal to ``a``: with ``a`` "up" and ``v`` a
    magnetometer, a correction of the heading that cannot tilt the estimate (VQF's separation of
    the two). With ``gate`` it corrects only at steps where ``v`` looks like its undisturbed self:
    ``| |v| / norm - 1 | <= norm_tol`` and, with ``about``, the elevation of ``R^- v`` above the
    plane normal to ``a`` within ``elevation_tol`` degrees of ``elevation`` (a magnetometer's
    field strength and dip: a nearby magnet changes them, the estimate's heading does not).
    Priors of this kind nest (a heading correction after a tilt correction).

    Args:
        factor: the SO(3) factor it corrects.
        vector: ``(start, stop)``, the 3 entries of ``(y, u)`` holding ``v`` (low-passed
            readings make a better ``v``; the correction is only as good as its direction).
        tau: the time constant in seconds (>= dt: a step turns ``dt / tau <= 1`` of the way);
            dt: the step length in seconds (> 0; a builder gives the system's); reference: ``r`` (any non-zero length; default up, ``(0, 0, 1)``).
        inner: the prior it follows (default none; a kinematic prior integrates the gyroscope).
        about: ``a`` (any non-zero length) or ``None`` (default: turn about any axis).
        gate: ``None`` (default: correct at every step) or a mapping with ``norm`` (> 0, the
            units of ``v``), ``norm_tol`` (a fraction, > 0), and with ``about`` optionally
            ``elevation`` and ``elevation_tol`` (degrees; a magnetometer in the north's
            East-North-Up frame: elevation = minus the dip).
    """

    name = "complementary"
    _GATE_KEYS = ("norm", "norm_tol", "elevation", "elevation_tol")

    def __init__(self, factor: str, vector, tau: float, dt: float, reference=(0.0, 0.0, 1.0),
                 inner: Prior | None = None, about=None, gate=None):
        super().__init__()
        self.factor = str(factor)
        self.vector = check_spans("complementary prior: vector", {"v": vector}, "(y, u)")["v"]
        self.tau = check_number("complementary prior: tau", tau, 1e-9, 1e9, " (seconds)")
        self.dt = check_number("complementary prior: dt", dt, 1e-12, 1e6, " (seconds)")
        self.reference = _direction("reference", reference, "up is [0, 0, 1]")
        self.register_buffer("_r", _unit(self.reference), persistent=False)
        self.about = None if about is None else _direction("about", about, "up is [0, 0, 1]")
        if self.about is not None:  # r's part normal to a: both in the plane, w along a
            self.register_buffer("_a", _unit(self.about), persistent=False)
            r = self._r - (self._r @ self._a) * self._a
            if float(r.norm()) < 1e-6:
                raise ValueError("complementary prior: reference is along about; a turn about "
                                 "it cannot move anything towards it (a heading correction's "
                                 "reference is horizontal: north is [0, 1, 0]).")
            self._r = r / r.norm()
        self.gate = self._check_gate(gate)
        self.inner = NoPrior() if inner is None else inner
        if not isinstance(self.inner, Prior):
            raise ValueError("complementary prior: inner must be a prior (none, system, "
                             "robust_system, kinematic, complementary).")

    def _check_gate(self, gate) -> dict | None:
        if gate is None:
            return None
        if not hasattr(gate, "items") or set(gate) - set(self._GATE_KEYS):
            raise ValueError(f"complementary prior: gate must be a mapping of {self._GATE_KEYS}, "
                             f"got {gate!r}.")
        g = dict(gate)
        if "norm" not in g or "norm_tol" not in g:
            raise ValueError("complementary prior: gate needs norm and norm_tol (e.g. {norm: "
                             f"44.0, norm_tol: 0.1}} for a magnetometer in uT), got {gate!r}.")
        out = {"norm": check_number("complementary prior: gate.norm", g["norm"], 1e-12, 1e12),
               "norm_tol": check_number("complementary prior: gate.norm_tol", g["norm_tol"],
                                        1e-12, 1e12, " (a fraction of norm)")}
        if ("elevation" in g) != ("elevation_tol" in g):
            raise ValueError("complementary prior: gate's elevation and elevation_tol go "
                             f"together, got {gate!r}.")
        if "elevation" in g:
            if self.about is None:
                raise ValueError("complementary prior: gate.elevation is measured from the plane "
                                 "normal to about; give about (up: [0, 0, 1]).")
            out["elevation"] = check_number("complementary prior: gate.elevation",
                                            g["elevation"], -90.0, 90.0, " (degrees)")
            out["elevation_tol"] = check_number("complementary prior: gate.elevation_tol",
                                                g["elevation_tol"], 0.0, 180.0, " (degrees)")
        return out

    def bind(self, group, measurement):
        self.inner.bind(group, measurement)
        check_factor("complementary prior: factor", group, self.factor)
        if not isinstance(group.factor(self.factor), SO3):
            raise ValueError(f"complementary prior: factor {self.factor!r} is "
                             f"{group.factor(self.factor)!r}; it corrects an SO(3) factor.")
        a, b = self.vector
        width = measurement.dim + measurement.input_dim
        if not (0 <= a and b <= width and b - a == 3):
            raise ValueError(f"complementary prior: vector = ({a}, {b}) must be a span of (y, u) "
                             f"(size {width}) of 3 entries.")
        if self.tau < self.dt:  # after the factor checks: a prior for another system says so first
            raise ValueError(
                f"complementary prior: tau = {self.tau:g} s is shorter than the step dt = "
                f"{self.dt:g} s, so each step would turn by dt / tau = {self.dt / self.tau:.3g} "
                "times the error and overshoot (diverging beyond 2); give tau >= dt (tau = dt "
                "corrects the whole error in one step)."
            )
        self._slice, self._so3 = group.element_slice(self.factor), group.factor(self.factor)
        return self

    def settings(self):
        out = {"factor": self.factor, "vector": list(self.vector), "tau": self.tau, "dt": self.dt,
               "reference": self.reference}
        if self.about is not None:
            out["about"] = self.about
        if self.gate is not None:
            out["gate"] = dict(self.gate)
        if not isinstance(self.inner, NoPrior):
            out["inner"] = self.inner.signature()
        return out

    def widen(self, state, prefix, old):
        """From its inner prior (it adds no weight; it computes what its settings say)."""
        inner_old = old.get("inner", {"type": "none"}) if (old or {}).get("type") == self.name else old
        return self.inner.widen(state, prefix + "inner.", inner_old)

    def forward(self, x, yu, ys):
        x = self.inner(x, yu, ys)
        R = x[:, self._slice].unflatten(-1, (3, 3))
        body = ys[:, self.vector[0] : self.vector[1]].to(x.dtype)
        v = (R @ body[..., None])[..., 0]
        if self.about is None:
            n = torch.linalg.vector_norm(v, dim=-1, keepdim=True)
            w = torch.linalg.cross(v / n.clamp_min(1e-30), self._r.to(x).expand_as(v))
        else:
            a = self._a.to(x)
            along = v @ a
            h = v - along[:, None] * a
            n = torch.linalg.vector_norm(h, dim=-1, keepdim=True)
            w = torch.linalg.cross(h / n.clamp_min(1e-30), self._r.to(x).expand_as(h))
        if self.gate is not None:
            w = w * self._open(body, v).to(x)[:, None]
        x = x.clone()  # R stays a view of the inner prior's output, which autograd needs
        x[:, self._slice] = (self._so3.exp(w * (self.dt / self.tau)) @ R).flatten(-2)
        return x

    def _open(self, body, v):
        """Where the gate lets the correction through: ``(B,)`` booleans."""
        g = self.gate
        norm = torch.linalg.vector_norm(body, dim=-1)
        ok = (norm / g["norm"] - 1).abs() <= g["norm_tol"]
        if "elevation" in g:
            sine = (v @ self._a.to(v)) / norm.clamp_min(1e-30)
            elevation = torch.rad2deg(torch.asin(sine.clamp(-1.0, 1.0)))
            ok = ok & ((elevation - g["elevation"]).abs() <= g["elevation_tol"])
        return ok


def _direction(what: str, value, example: str) -> list[float]:
    try:
        out = [float(c) for c in value]
    except (TypeError, ValueError):
        out = []
    norm = sum(c * c for c in out) ** 0.5
    if len(out) != 3 or not 0 < norm < float("inf"):
        raise ValueError(f"complementary prior: {what} must be 3 finite numbers, not all zero (a "
                         f"direction; {example}), got {value!r}.")
    return out


def _unit(direction: list[float]) -> torch.Tensor:
    norm = sum(c * c for c in direction) ** 0.5
    return torch.tensor([c / norm for c in direction], dtype=torch.float64)
