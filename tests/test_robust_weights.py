"""Learned robust weights (``manifold_nets.observer.robust``; the pieces ``RobustSystemPrior``
and ``RobustMeasurement``, ``prior: {type: robust_system}``, ``measurement: {type: robust}``) and
per-parameter learning rates (``train.param_lr``). Pinned: the weight function against its
formula, the identity when new, a norm whose gradient is finite at zero; the prior steps with the
weighted drive and the core reads the weighted innovation and the measurement it implies, each
computed apart; new maps change nothing; rollout, pieces, online and exported steps agree;
gradients reach the maps; a checkpoint without them widens only for fine-tuning; bad settings
say what is wrong; each parameter group trains at its own rate on the same schedule; the train
command trains and reloads it."""

from __future__ import annotations

import math

import pytest
import torch
from omegaconf import OmegaConf

from groups import SO3
from manifold_nets import TrainSettings, build_observer, fit
from manifold_nets.builders import build_piece
from manifold_nets.checkpoint import CheckpointError, load_checkpoint, load_weights
from manifold_nets.config import ModelConfig
from manifold_nets.observer import (
    CentredHead,
    FramedInnovation,
    PlainHead,
    RobustMeasurement,
    RobustSystemPrior,
)
from manifold_nets.observer.robust import RobustWeights, check_span, safe_norm
from manifold_nets.training import check_settings, param_groups
from manifold_nets_examples.rigid_body import RigidBody
from tests.observer_checks import assert_pieces_and_export_match, train_tiny_and_load
from tests.test_centred_update import MEASURED, block_overrides, rigid_observer, save, simulate
from tests.test_innovation_frame import _core_inputs

FRAME = {"p": "R"}
#: a learning rate for each piece holding learned weight functions (its parameters are theirs)
MAPS = {"prior": 1e-2, "measurement": 1e-2}


def maps(piece) -> RobustWeights:
    """The learned weight functions a robust piece holds."""
    found = [m for m in piece.modules() if isinstance(m, RobustWeights)]
    assert len(found) == 1, found
    return found[0]


def prefix(obs, where: str) -> str:
    """The parameter-name prefix of the weight functions of ``obs``'s piece ``where``."""
    return next(n for n, m in obs.named_modules()
                if isinstance(m, RobustWeights) and n.startswith(where + "."))


def shaped(m: RobustWeights, seed: int = 0) -> RobustWeights:
    """``m`` with random heights, knots and widths: a weight function far from the identity."""
    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        m.amplitude.copy_(-0.4 * torch.rand(m.amplitude.shape, generator=g, dtype=torch.float64))
        m.knots.add_(0.3 * torch.randn(m.knots.shape, generator=g, dtype=torch.float64))
        m.log_width.add_(0.2 * torch.randn(m.log_width.shape, generator=g, dtype=torch.float64))
    return m


# ---------------------------------------------------------------------- the weight function


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_a_new_map_is_the_identity_and_a_shaped_one_its_formula(dtype):
    m = RobustWeights(3, width=5, span=2.0).to(dtype)
    r = torch.rand(4, 7, 3, dtype=dtype) * 5
    assert torch.equal(m(r), torch.ones_like(r))
    assert m.knots[0].tolist() == pytest.approx([0.0, 0.5, 1.0, 1.5, 2.0])
    assert torch.exp(m.log_width).tolist()[0][0] == pytest.approx(1.0)  # twice the spacing
    shaped(m)
    a, k, h = m.amplitude.detach(), m.knots.detach(), torch.exp(m.log_width.detach())
    want = torch.empty_like(r)
    for i in range(3):  # channel by channel, step by step
        total = torch.ones_like(r[..., i])
        for j in range(5):
            total = total + a[i, j] * torch.tanh((r[..., i] - k[i, j]) / h[i, j])
        want[..., i] = total
    torch.testing.assert_close(m(r), want)
    assert m.signature() == {"channels": 3, "width": 5, "span": 2.0}


def test_bad_maps_say_what_is_wrong():
    for bad in (0, -1, True, 2.0, 10**9):  # 10**9: refused before anything is allocated
        with pytest.raises(ValueError, match=r"channels must be an integer in 1 \.\. 4096"):
            RobustWeights(bad)
        with pytest.raises(ValueError, match=r"width must be an integer in 1 \.\. 4096"):
            RobustWeights(2, width=bad)
    for bad in (0, -1.0, math.inf, True):
        with pytest.raises(ValueError, match="span must be a number > 0"):
            RobustWeights(2, span=bad)
        with pytest.raises(ValueError, match="model.robust_span must be a number > 0"):
            check_span(bad, "model.robust_span")
    with pytest.raises(ValueError, match=r"r must have shape \(\.\.\., 2\)"):
        RobustWeights(2)(torch.ones(4, 3))
    one = RobustWeights(1, width=1)  # one step: no spacing to speak of, still a finite width
    assert math.isfinite(float(one.log_width.detach()))


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_safe_norm_is_the_norm_with_a_finite_gradient_at_zero(dtype):
    v = torch.randn(5, 3, dtype=dtype)
    v[2] = 0.0
    v.requires_grad_(True)
    n = safe_norm(v)
    torch.testing.assert_close(n, torch.linalg.vector_norm(v.detach(), dim=-1))
    n.sum().backward()
    assert torch.isfinite(v.grad).all() and torch.equal(v.grad[2], torch.zeros(3, dtype=dtype))
    torch.testing.assert_close(v.grad[0], v.detach()[0] / n.detach()[0])
    w = torch.randn(4, 3, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(safe_norm, (w,))


# ---------------------------------------------------------------------- in the observer


def robust_observer(system, seed=0, drive=0, innovation=0, span=2.0, **changes):
    """:func:`rigid_observer` with a robust system prior of ``drive`` steps per weight function
    and a robust measurement of ``innovation`` steps (0: the plain piece)."""
    if drive:
        changes["prior"] = RobustSystemPrior(system, width=drive, span=span)
    if innovation:
        changes["measurement"] = RobustMeasurement(18, 0, MEASURED, width=innovation, span=span)
    return rigid_observer(system, seed=seed, **changes)


def test_new_maps_change_nothing():
    system = RigidBody()
    data = simulate(system, n=3, t=15, sigma=0.3)
    settings = dict(head=CentredHead(0.85, ramp=4), extra=[FramedInnovation(FRAME)])
    plain = rigid_observer(system, seed=4, **settings)
    robust = robust_observer(system, seed=4, drive=6, innovation=4, **settings)
    sig = robust.signature()
    assert sig["prior"] == {"type": "robust_system", "width": 6, "span": 2.0}
    assert sig["measurement"] == {"type": "robust", "dim": 18, "input_dim": 0,
                                  "factors": {"R": [0, 9], "p": [9, 12]}, "width": 4, "span": 2.0}
    assert maps(robust.prior).signature() == {"channels": 6, "width": 6, "span": 2.0}
    assert maps(robust.measurement).signature() == {"channels": 2, "width": 4, "span": 2.0}
    assert plain.signature()["prior"] == {"type": "system"}
    assert plain.signature()["measurement"]["type"] == "measurement"
    with torch.no_grad():
        gap = (robust(data.measurements) - plain(data.measurements)).abs().max()
    assert float(gap) < 1e-12  # an exp(log(.)) round trip of the measured attitude


def test_the_prior_steps_with_the_weighted_drive():
    """With the core's output zero the estimate is the prediction alone:
    ``x_{k+1} = step(x_k, w(|d_k|) d_k)``, ``d_k`` the bias-corrected readings, followed apart."""
    system = RigidBody()
    data = simulate(system, n=3, t=10, sigma=0.4)
    obs = robust_observer(system, seed=1, drive=5, head=PlainHead())
    shaped(maps(obs.prior))
    with torch.no_grad():
        obs.core.head.weight.zero_()
        obs.core.head.bias.zero_()
        est = obs(data.measurements)
        w_map = maps(obs.prior)
        x = system.group.identity((3,), dtype=torch.float64)
        for k in range(10):
            d = system.compensated_drive(x, data.measurements[:, k], None)
            x = system.step(x, w_map(d.abs()) * d)
            torch.testing.assert_close(est[:, k + 1], x, rtol=0, atol=1e-12)
        # the map mattered: the plain prediction goes elsewhere
        x0 = system.group.identity((3,), dtype=torch.float64)
        plain = system.predict(x0, data.measurements[:, 0], None)
        assert float((plain - est[:, 1]).abs().max()) > 1e-3


@pytest.mark.parametrize("centred", [False, True])
def test_the_core_reads_the_weighted_innovation_and_the_measurement_it_implies(centred):
    system = RigidBody()
    data = simulate(system, n=3, t=8, sigma=0.5)
    head = CentredHead(0.8) if centred else PlainHead()
    obs = robust_observer(system, seed=2, innovation=6, head=head,
                          extra=[FramedInnovation(FRAME)])
    shaped(maps(obs.measurement), seed=3)
    seen, est = _core_inputs(obs, data.measurements)
    R, G = SO3(), system.group
    n, w_map = 3, maps(obs.measurement)
    for k in range(8):
        xp = system.predict(est[:, k], data.measurements[:, k], None)  # the prior's x^-
        y = data.measurements[:, k]
        Rp = xp[:, :9].reshape(n, 3, 3)
        nu_R = R.log(R.compose(R.inverse(Rp), y[:, :9].reshape(n, 3, 3)))
        nu_p = y[:, 9:12] - xp[:, 9:12]
        w = w_map(torch.stack([nu_R.norm(dim=-1), nu_p.norm(dim=-1)], -1))
        nu_R, nu_p = nu_R * w[:, :1], nu_p * w[:, 1:]
        z = seen[k, :n]
        # embed(x^-) less p (15), y less p^m (15: R^m, the readings), nu_R, nu_p, framed nu_p
        torch.testing.assert_close(z[:, 30:33], nu_R, rtol=1e-6, atol=1e-9)
        torch.testing.assert_close(z[:, 33:36], nu_p, rtol=1e-6, atol=1e-9)
        torch.testing.assert_close(z[:, 36:39], (nu_p.unsqueeze(-2) @ Rp).squeeze(-2),
                                   rtol=1e-6, atol=1e-9)
        m_R = R.compose(Rp, R.exp(nu_R)).flatten(-2)  # the measured attitude the core reads
        torch.testing.assert_close(z[:, 15:24], m_R, rtol=1e-6, atol=1e-9)
        torch.testing.assert_close(z[:, 24:30], y[:, 12:18], rtol=1e-6, atol=1e-9)  # as read
        if centred:  # z^0: the prediction and no innovation, as without the map
            z0 = seen[k, n:]
            torch.testing.assert_close(z0[:, 15:24], Rp.flatten(-2), rtol=1e-6, atol=1e-9)
            assert torch.equal(z0[:, 30:], torch.zeros_like(z0[:, 30:]))
    G.check_member(est)


def test_rollout_pieces_online_and_exported_steps_agree(tmp_path):
    system = RigidBody()
    data = simulate(system, n=2, t=9, sigma=0.3)
    obs = robust_observer(system, drive=4, innovation=4, head=CentredHead(0.85, ramp=3),
                          extra=[FramedInnovation(FRAME)])
    shaped(maps(obs.prior))
    shaped(maps(obs.measurement), seed=1)
    est = assert_pieces_and_export_match(obs, data.measurements, tmp_path)
    system.group.check_member(est)


@pytest.mark.parametrize("sigma", [0.0, 0.3])
def test_gradients_reach_the_maps_and_stay_finite(sigma):
    system = RigidBody()
    data = simulate(system, n=3, t=12, sigma=sigma)
    obs = robust_observer(system, drive=4, innovation=4, head=CentredHead(0.85)).float()
    est = obs(data.measurements)
    loss = (est[:, 1:] - data.states[:, 1:]).pow(2).mean()
    loss.backward()
    for m in (maps(obs.prior), maps(obs.measurement)):
        grads = [p.grad for p in m.parameters()]
        assert all(g is not None and torch.isfinite(g).all() for g in grads)
        assert float(m.amplitude.grad.abs().sum()) > 0  # the heights learn first


def test_a_checkpoint_without_them_widens_only_for_fine_tuning(tmp_path):
    system = RigidBody()
    data = simulate(system, n=3, t=12, sigma=0.2)
    settings = dict(head=CentredHead(0.85, ramp=5), extra=[FramedInnovation(FRAME)])
    plain = rigid_observer(system, seed=1, **settings)
    path = save(plain, tmp_path / "plain.pt")
    robust = robust_observer(system, seed=2, drive=4, innovation=3, **settings)
    shaped(maps(robust.prior))  # whatever it held is replaced by the identity
    shaped(maps(robust.measurement))
    with pytest.raises(CheckpointError, match="prior.type: checkpoint 'system', model "
                                              "'robust_system'"):  # evaluation
        load_weights(robust, path)
    load_weights(robust, path, widen=True)  # train.init_from
    assert float(maps(robust.prior).amplitude.detach().abs().sum()) == 0
    assert float(maps(robust.measurement).amplitude.detach().abs().sum()) == 0
    with torch.no_grad():
        gap = (robust(data.measurements) - plain(data.measurements)).abs().max()
    assert float(gap) < 1e-12
    shaped(maps(robust.measurement))
    trained = save(robust, tmp_path / "robust.pt")
    again = robust_observer(system, seed=5, drive=4, innovation=3, **settings)
    load_weights(again, trained, widen=True)  # the same maps: loaded as they are
    torch.testing.assert_close(maps(again.measurement).amplitude,
                               maps(robust.measurement).amplitude, rtol=0, atol=0)
    with pytest.raises(CheckpointError, match="the checkpoint's prior is 'robust_system', this "
                                              "observer's 'system'"):  # not dropped silently
        load_weights(plain, trained, widen=True)
    only_prior = robust_observer(system, seed=5, drive=4, **settings)
    with pytest.raises(CheckpointError, match="the checkpoint's measurement is 'robust', this "
                                              "observer's 'measurement'"):
        load_weights(only_prior, trained, widen=True)
    wider = robust_observer(system, seed=2, drive=5, innovation=3, **settings)
    name = prefix(wider, "prior")
    with pytest.raises(CheckpointError, match=rf"{name}\.amplitude: checkpoint \(6, 4\), "
                                              r"model \(6, 5\)"):
        load_weights(wider, trained, widen=True)


def test_bad_settings_say_what_is_wrong():
    system = RigidBody()
    with pytest.raises(TypeError, match="SystemPrior needs a System, got function"):
        RobustSystemPrior(lambda x, y, u: x)
    with pytest.raises(ValueError, match="a robust measurement weighs the innovations of the "
                                         "measured factors, but it names none"):
        RobustMeasurement(18, 0, {})
    for bad in (-1, 0, True, 2.5, 10**9):  # 10**9: refused before anything is allocated
        with pytest.raises(ValueError, match=r"robust system prior: width must be an integer in "
                                             r"1 \.\. 4096"):
            RobustSystemPrior(system, width=bad)
        with pytest.raises(ValueError, match=r"robust measurement: width must be an integer in "
                                             r"1 \.\. 4096"):
            RobustMeasurement(18, 0, MEASURED, width=bad)
    for bad in (0.0, -1.0, True):
        with pytest.raises(ValueError, match="robust system prior: span must be a number"):
            RobustSystemPrior(system, span=bad)
        with pytest.raises(ValueError, match="robust measurement: span must be a number"):
            RobustMeasurement(18, 0, MEASURED, span=bad)
    with pytest.raises(ValueError, match="robust system prior: span must be a number"):
        RobustSystemPrior(system, span=math.inf)  # refused by the piece, naming it
    with pytest.raises(ValueError, match="robust measurement: span must be a number in "
                                         r"\[1e-12, 1e\+12\]"):
        RobustMeasurement(18, 0, MEASURED, span=0.0)  # a finite span is a number > 0
    # the robust measurement's channels are its factors: one map per measured factor
    assert maps(RobustMeasurement(18, 0, {"R": (0, 9)})).channels == 1

    with pytest.raises(ValueError, match="OwnPrediction overrides predict"):
        RobustSystemPrior(OwnPrediction())

    context = {"system": system, "dim": 18, "input_dim": 0}
    with pytest.raises(ValueError, match=r"model.prior \(robust_system\): needs \['system'\] "
                                         r"\(pass build_observer\(\.\.\., system=system\)\)"):
        build_piece("prior", {"type": "robust_system", "width": 4}, "model.prior")
    with pytest.raises(ValueError, match=r"model.prior \(robust_system\): the robust system "
                                         "prior .* OwnPrediction overrides predict"):
        build_piece("prior", {"type": "robust_system"}, "model.prior",
                    {**context, "system": OwnPrediction()})
    for block, match in (
        ({"type": "robust_system", "width": -1}, r"model.prior \(robust_system\): robust system "
                                                 "prior: width must be an integer in 1 .. 4096"),
        ({"type": "robust_system", "span": 0.0}, r"model.prior \(robust_system\): robust system "
                                                 "prior: span must be a number"),
    ):
        with pytest.raises(ValueError, match=match):
            build_piece("prior", block, "model.prior", context)
    for block, match in (
        ({"type": "robust", "width": 4}, r"model.measurement \(robust\): a robust measurement "
                                         "weighs"),
        ({"type": "robust", "factors": {"R": [0, 9]}, "width": True},
         r"model.measurement \(robust\): robust measurement: width must be an integer in 1 "
         r"\.\. 4096"),
    ):
        with pytest.raises(ValueError, match=match):
            build_piece("measurement", block, "model.measurement", context)


class OwnPrediction(RigidBody):
    """A system whose prediction is its own (a robust system prior cannot weigh its drive)."""

    def predict(self, x, y, u):
        return super().predict(x, y, u)


def _flat(**kw):
    return OmegaConf.structured(ModelConfig(hidden_size=4, num_layers=1, **kw))


def test_bad_flat_settings_say_what_is_wrong():
    """The first format's keys, translated: their errors name the piece they became."""
    system = RigidBody()
    with pytest.warns(FutureWarning), pytest.raises(
        ValueError, match=r"model.measurement \(robust\): a robust measurement weighs"
    ):
        build_observer(system.group, 18, 0, _flat(robust_innovation=4), system=system)
    with pytest.warns(FutureWarning), pytest.raises(
        ValueError,
        match=r"model.prior \(robust_system\): the robust system prior .* OwnPrediction overrides",
    ):
        build_observer(system.group, 18, 0, _flat(robust_drive=4, prior="system"),
                       system=OwnPrediction())
    raw = OmegaConf.to_container(_flat(prior="system", innovation={"R": [0, 9]}))
    for key, bad, piece in (("robust_drive", -1, "prior"), ("robust_innovation", -2,
                                                            "measurement")):
        cfg = OmegaConf.create({**raw, key: bad})  # a config read from a file
        with pytest.warns(FutureWarning), pytest.raises(ValueError, match=rf"model.{piece} "
                                                                          r"\(robust"):
            build_observer(system.group, 18, 0, cfg, system=system)
    cfg = OmegaConf.create({**raw, "robust_drive": 2, "robust_span": 0.0})
    with pytest.warns(FutureWarning), pytest.raises(ValueError, match="span must be a number"):
        build_observer(system.group, 18, 0, cfg, system=system)


def test_a_flat_robust_drive_without_the_system_prior_says_so():
    """The first format's ``robust_drive`` weighs the system prior's drive: without
    ``prior: system`` there is none, and the translated config must refuse it (as the first
    format did: "there is no model prior; set model.prior=system"), not drop it."""
    system = RigidBody()
    with pytest.raises(ValueError, match="prior"):
        build_observer(system.group, 18, 0, _flat(robust_drive=4), system=system)


# ---------------------------------------------------------------------- per-parameter rates


def test_param_groups_give_the_named_parameters_their_rate():
    obs = robust_observer(RigidBody(), drive=3, innovation=3)
    robust = {id(p) for m in obs.modules() if isinstance(m, RobustWeights) for p in m.parameters()}
    assert len(robust) == 6
    # "robust" names every learned robust weight, wherever its piece holds it
    groups = param_groups(obs, 1e-4, {"robust": 1e-2})
    assert [g["lr_scale"] for g in groups] == [1.0, pytest.approx(100.0)]
    assert {id(p) for p in groups[1]["params"]} == robust
    assert not robust & {id(p) for p in groups[0]["params"]}
    # a key is also the start of parameter names: one rate per piece
    groups = param_groups(obs, 1e-4, MAPS)
    assert [g["lr_scale"] for g in groups] == [1.0, pytest.approx(100.0), pytest.approx(100.0)]
    assert {id(p) for g in groups[1:] for p in g["params"]} == robust
    assert {id(p) for p in groups[1]["params"]} == {id(p) for p in obs.prior.parameters()}
    assert sum(len(g["params"]) for g in groups) == len(list(obs.parameters()))
    assert len(param_groups(obs, 1e-4, {})) == 1
    with pytest.raises(ValueError, match=r"param_lr\['gain'\] names no parameter.*'core'"):
        param_groups(obs, 1e-4, {"gain": 1e-2})
    name = prefix(obs, "prior")
    for two in ({"prior": 1e-2, name: 1e-3}, {"robust": 1e-2, name: 1e-3}):
        first = next(iter(two))
        with pytest.raises(ValueError, match=f"both '{first}' and '{name}'"):
            param_groups(obs, 1e-4, two)
    for bad in (0.0, -1e-3, math.inf, True):
        with pytest.raises(ValueError, match=r"param_lr\['robust'\] must be a positive"):
            check_settings(TrainSettings(param_lr={"robust": bad}))
    with pytest.raises(ValueError, match="each key must be a parameter-name prefix"):
        check_settings(TrainSettings(param_lr={"": 1e-2}))


def test_each_group_trains_at_its_rate_on_the_same_schedule(tmp_path):
    system = RigidBody()
    data = simulate(system, n=8, t=6, sigma=0.2)
    torch.manual_seed(0)
    obs = robust_observer(system, drive=3, innovation=3).float()
    settings = TrainSettings(epochs=2, batch_size=4, lr=1e-3, schedule="cosine", progress=False,
                             param_lr={"robust": 5e-2}, eval_batch_size=8)
    fit(obs, data, data, settings, out_dir=tmp_path)
    last = load_checkpoint(tmp_path / "checkpoints" / "last.pt")
    rates = [g["lr"] for g in last["optimizer"]["param_groups"]]
    assert rates == pytest.approx([5e-4, 2.5e-2])  # epoch 2 of 2 on the half cosine: lr / 2
    assert float(maps(obs.prior).amplitude.detach().abs().max()) > 1e-3  # it moved


def test_the_train_command_takes_them_and_load_observer_rebuilds_them(tmp_path):
    observer, system, cfg = train_tiny_and_load(
        "paper_cpu_prior", tmp_path,
        *block_overrides(
            "++train.param_lr={robust:1.0e-2}",
            measurement="{type:robust,factors:{R:[0,9],p:[9,12]},width:4}",
            prior="{type:robust_system,width:4}", head="{type:centred,c:0.85}",
        ),
    )
    assert maps(observer.prior).signature() == {"channels": 6, "width": 4, "span": 4.0}
    assert maps(observer.measurement).channels == 2
    assert cfg.train.param_lr == {"robust": 1.0e-2}
    assert float(maps(observer.prior).amplitude.detach().abs().max()) > 0  # trained
    data = simulate(system, n=2, t=8, sigma=0.1)
    with torch.inference_mode():
        est = observer(data.measurements)
    system.group.check_member(est)
