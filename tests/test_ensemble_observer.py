"""EnsembleObserver: the members' barycentre at every step, the same online, in pieces and exported;
one member is that member; members behind their readings filter; its refusals."""

from __future__ import annotations

import pytest
import torch

from groups import SE3, SO3, Euclidean, Product
from manifold_nets.observer import PIECES, EnsembleObserver, PlainHead, ResidualObserver
from observer_checks import assert_pieces_and_export_match, randomise_head, so3_walk


def _members(group, width: int, k: int, seed: int = 0) -> list[ResidualObserver]:
    out = []
    for i in range(k):
        torch.manual_seed(seed + i)
        obs = ResidualObserver(group, width, core=None).eval()
        randomise_head(obs, seed=seed + i, scale=0.3)
        out.append(obs)
    return out


def _broad_member():
    """One observer of the zoo's BROAD ensemble: its first member's run folder."""
    from manifold_nets.loading import ensemble_members
    from manifold_nets.plugins import zoo_path

    return ensemble_members(zoo_path("broad/attitude"))[0]


def _walk(group, n: int = 2, t: int = 12, seed: int = 0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    x = group.random((n,), generator=g, dtype=torch.float64)
    out = []
    for _ in range(t):
        x = group.rplus(x, 0.1 * torch.randn(n, group.tangent_dim, generator=g, dtype=torch.float64))
        out.append(group.embed(x))
    return torch.stack(out, 1)


@pytest.mark.parametrize("group", [SO3(), SE3(), Product(SO3(), Euclidean(3))], ids=repr)
def test_rollout_is_the_members_barycentre(group):
    members = _members(group, group.embedding_dim, 3)
    y = _walk(group)
    ens = EnsembleObserver(members)
    with torch.no_grad():
        got = ens(y)
        each = torch.stack([m(y) for m in members])
    torch.testing.assert_close(got, group.mean(each, 0), rtol=0, atol=0)
    spread = group.rminus(each, got.unsqueeze(0)).norm(dim=-1)
    assert spread.max() > 1e-3  # the members differ: the test can tell a mean from a member
    residual = group.rminus(each, got.unsqueeze(0)).mean(0).norm(dim=-1)
    assert residual.max() < 1e-10  # the barycentre condition


def test_online_pieces_and_export_match_the_rollout(tmp_path):
    """Also: exporting leaves the registry of pieces as it was (torch.export's tracer subclasses
    a module it reaches by two paths; such a subclass once replaced the piece, and a config
    loaded afterwards in the same process failed)."""
    before = dict(PIECES)
    ens = EnsembleObserver(_members(SO3(), 9, 3))
    assert_pieces_and_export_match(ens, so3_walk(2, 10, seed=1).measurements, tmp_path)
    assert PIECES == before


def test_a_subclass_that_does_not_name_itself_is_not_registered():
    before = dict(PIECES)

    class Quieter(PlainHead):  # inherits the name "plain"
        pass

    assert PIECES == before and PIECES["head", "plain"] is PlainHead


def test_one_member_is_that_member():
    (member,) = _members(SO3(), 9, 1)
    y = so3_walk(2, 10, seed=2).measurements
    with torch.no_grad():
        torch.testing.assert_close(EnsembleObserver([member])(y), member(y), rtol=0, atol=0)


def test_a_measured_start_starts_every_member_there():
    members = _members(SO3(), 9, 2)
    ens = EnsembleObserver(members)
    x0 = SO3().random((2,), generator=torch.Generator().manual_seed(3), dtype=torch.float64)
    y = so3_walk(2, 6, seed=3).measurements
    with torch.no_grad():
        got = ens(y, state=ens.init_state(2, estimate=x0))
        each = [m(y, state=m.init_state(2)._replace(estimate=x0)) for m in members]
    torch.testing.assert_close(got[:, 0], x0)
    torch.testing.assert_close(got, SO3().mean(torch.stack(each), 0), rtol=0, atol=0)


def test_members_behind_their_readings_filter(tmp_path):
    """One BROAD observer behind its pre-filter, twice: the ensemble is that observer, online as
    well."""
    from manifold_nets import load_observer

    filtered = load_observer(_broad_member()).filtered()
    ens = EnsembleObserver([filtered, filtered])
    g = torch.Generator().manual_seed(4)
    y = torch.randn(2, 30, filtered.measurement_dim, generator=g, dtype=torch.float64)
    u = torch.randn(2, 30, filtered.input_dim, generator=g, dtype=torch.float64)
    with torch.no_grad():
        torch.testing.assert_close(ens(y, u), filtered(y, u), rtol=0, atol=1e-12)
        state = ens.init_state(2)
        for k in range(30):
            state = ens.step(state, y[:, k], u[:, k])
    torch.testing.assert_close(state.estimate, filtered(y, u)[:, -1], rtol=0, atol=1e-10)


def test_an_ensemble_behind_one_readings_filter(tmp_path):
    """The filter runs once, in front of the ensemble: the same estimates as the members each
    behind their own filter; online and exported alike."""
    from manifold_nets import load_observer
    from manifold_nets.observer import FilteredObserver

    loaded = load_observer(_broad_member())
    member = loaded.filtered()
    ens = FilteredObserver(member.prefilter, EnsembleObserver([loaded.observer, loaded.observer]))
    g = torch.Generator().manual_seed(5)
    y = torch.randn(2, 20, member.measurement_dim, generator=g, dtype=torch.float64)
    u = torch.randn(2, 20, member.input_dim, generator=g, dtype=torch.float64)
    with torch.no_grad():
        want = member(y, u)
        torch.testing.assert_close(ens(y, u), want, rtol=0, atol=1e-12)
    from manifold_nets import export_observer
    from manifold_nets.deploy import load_exported_step

    export_observer(ens, tmp_path / "ens.pt2")
    step = load_exported_step(tmp_path / "ens.pt2")
    x, *state = step.initial_state(2)
    for k in range(20):
        x, *state = step(x, *state, y[:, k], u[:, k])
    torch.testing.assert_close(x, want[:, -1].reshape(2, -1), rtol=0, atol=1e-10)


def test_refusals():
    so3, se3 = _members(SO3(), 9, 1)[0], _members(SE3(), 12, 1)[0]
    with pytest.raises(ValueError, match="non-empty list of observers"):
        EnsembleObserver([])
    with pytest.raises(TypeError, match="member 1 is a Linear"):
        EnsembleObserver([so3, torch.nn.Linear(2, 2)])
    with pytest.raises(ValueError, match="member 1's group is SE3"):
        EnsembleObserver([so3, se3])
    with pytest.raises(ValueError, match="member 1's measurement_dim is 3"):
        EnsembleObserver([so3, ResidualObserver(SO3(), 3)])
    with pytest.raises(ValueError, match="iterations must be an int >= 1"):
        EnsembleObserver([so3], iterations=0)
    ens = EnsembleObserver([so3, so3])
    with pytest.raises(ValueError, match="state holds 1 member states; the ensemble has 2"):
        ens.step(EnsembleObserver([so3]).init_state(1), torch.zeros(1, 9, dtype=torch.float64))


def _ensemble_folder(root, names=("seed0", "seed1")):
    """An ensemble folder of copies of one BROAD observer."""
    import shutil

    src = _broad_member()
    for name in names:
        dst = root / "members" / name
        (dst / "checkpoints").mkdir(parents=True)
        shutil.copy(src / "config.yaml", dst / "config.yaml")
        shutil.copy(src / "checkpoints" / "best.pt", dst / "checkpoints" / "best.pt")
    return root


def test_an_ensemble_folder_loads_as_an_ensemble(tmp_path):
    from manifold_nets import load_observer

    loaded = load_observer(_ensemble_folder(tmp_path / "ens"))
    assert isinstance(loaded.observer, EnsembleObserver) and len(loaded.observer.members) == 2
    single = load_observer(_broad_member())
    g = torch.Generator().manual_seed(6)
    y = torch.randn(1, 15, single.observer.measurement_dim, generator=g, dtype=torch.float64)
    u = torch.randn(1, 15, single.observer.input_dim, generator=g, dtype=torch.float64)
    with torch.no_grad():
        torch.testing.assert_close(loaded.filtered()(y, u), single.filtered()(y, u), rtol=0,
                                   atol=1e-12)


def test_an_ensemble_folder_is_checked_before_anything_loads(tmp_path):
    import yaml

    from manifold_nets import load_observer
    from manifold_nets.loading import MAX_MEMBERS, ArtefactError

    empty = tmp_path / "empty"
    (empty / "members").mkdir(parents=True)
    with pytest.raises(ArtefactError, match="holds 0 entries"):
        load_observer(empty)
    both = _ensemble_folder(tmp_path / "both")
    (both / "config.yaml").write_text("system: {}\n")
    with pytest.raises(ArtefactError, match="both a config.yaml and members/"):
        load_observer(both)
    linked = _ensemble_folder(tmp_path / "linked")
    (linked / "members" / "seed2").symlink_to(linked / "members" / "seed0")
    with pytest.raises(ArtefactError, match="is not a run folder"):
        load_observer(linked)
    nested = _ensemble_folder(tmp_path / "nested")
    _ensemble_folder(nested / "members" / "seed1", names=("inner",))
    with pytest.raises(ArtefactError, match="seed1 is itself an ensemble folder"):
        load_observer(nested)
    many = tmp_path / "many" / "members"
    for i in range(MAX_MEMBERS + 1):
        (many / f"m{i:02d}").mkdir(parents=True)
    with pytest.raises(ArtefactError, match=f"holds {MAX_MEMBERS + 1} entries"):
        load_observer(many.parent)
    other = _ensemble_folder(tmp_path / "other")
    cfg_file = other / "members" / "seed1" / "config.yaml"
    cfg = yaml.safe_load(cfg_file.read_text())
    cfg["system"]["acc_lowpass"] = 3.0
    cfg_file.write_text(yaml.safe_dump(cfg))
    with pytest.raises(ArtefactError, match="seed1's system differs from"):
        load_observer(other)


def test_one_checkpoint_asked_of_an_ensemble_names_its_members():
    """Where one checkpoint is needed (``train.init_from``, ``eval.checkpoint``), an ensemble
    folder is refused with the way out: one member."""
    from manifold_nets.checkpoint import CheckpointError, resolve_checkpoint

    with pytest.raises(CheckpointError, match="is an ensemble folder .* name one member"):
        resolve_checkpoint("zoo:broad/attitude", name="best.pt")


def test_onnx_export_of_an_ensemble_names_the_way_that_works():
    from manifold_nets.deploy import export_onnx

    pytest.importorskip("onnxscript")
    with pytest.raises(TypeError, match="export_onnx exports one ResidualObserver's step, got "
                       "EnsembleObserver; export an ensemble .* with export_observer"):
        export_onnx(EnsembleObserver(_members(SO3(), 9, 2)), "unused.onnx")


@pytest.mark.skipif(not any(map(__import__("shutil").which, ("c++", "g++", "clang++"))),
                    reason="AOTInductor compiles C++: no compiler on this machine")
def test_an_ensembles_exported_step_compiled_ahead_of_time_steps_as_exported(tmp_path):
    """docs/deployment.md's fast path: the exported program compiled by AOTInductor runs the
    same steps as the exported program (a float32 core's roundings apart), barycentre first."""
    from torch._inductor import aoti_compile_and_package, aoti_load_package

    from manifold_nets import export_observer
    from manifold_nets.deploy import load_exported_step

    ens = EnsembleObserver(_members(SO3(), 9, 2))
    program = export_observer(ens, tmp_path / "ens.pt2", batch=1)
    exported = load_exported_step(tmp_path / "ens.pt2")
    native = aoti_load_package(aoti_compile_and_package(
        program, package_path=str(tmp_path / "ens_aoti.pt2")))
    ys = so3_walk(1, 10, seed=2).measurements.to(torch.float64)
    a = b = exported.initial_state()
    moved = 0.0
    with torch.inference_mode():
        for t in range(ys.shape[1]):
            a, b = exported(*a, ys[:, t]), native(*b, ys[:, t])
            for p, q in zip(a, b):
                torch.testing.assert_close(q, p, rtol=1e-5, atol=1e-6)
            moved = max(moved, float((a[0] - exported.initial_state()[0]).abs().max()))
    assert moved > 1e-2  # the estimate moved: equal steps are not two stuck states
    x = a[0].reshape(3, 3)
    torch.testing.assert_close(x.T @ x, torch.eye(3, dtype=x.dtype), rtol=0, atol=1e-12)
