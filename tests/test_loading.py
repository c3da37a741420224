"""Trained observers as artefacts: ``load_observer`` rebuilds a run, and refuses hostile files.

A run folder's config is data: the system and the core it names are looked up among the classes
the program imported, never imported or called by name. Each hostile case below would write a
marker file if anything it names ran; the marker must not exist afterwards.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml
from hydra import compose, initialize_config_dir

import manifold_nets_examples.rigid_body  # noqa: F401  (registers RigidBody)
from manifold_nets import System, load_dataset, load_observer, save_checkpoint, save_dataset
from manifold_nets.builders import build_observer, build_system
from manifold_nets.checkpoint import load_checkpoint, load_weights
from manifold_nets.cli import apply
from manifold_nets.cli.train import run
from manifold_nets.loading import ArtefactError
from manifold_nets.registry import UnknownTargetError
from manifold_nets.system import SYSTEMS

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory) -> Path:
    """A run folder of the train command on tiny sizes (``experiment=default debug=tiny``)."""
    tmp = tmp_path_factory.mktemp("tiny")
    overrides = ["experiment=default", "debug=tiny", f"dataset.cache_dir={tmp / 'data'}"]
    with initialize_config_dir(config_dir=str(ROOT / "configs"), version_base="1.3"):
        cfg = compose("train", overrides=overrides)
    run(cfg, tmp / "run")
    return tmp / "run"


def _data(system, n=3, t=12, seed=5):
    return system.simulate(n, t, 0.1, torch.Generator().manual_seed(seed))


def test_a_run_folder_loads_into_the_trained_observer(tiny_run):
    observer, system, config = load_observer(tiny_run)
    assert type(system).__name__ == "RigidBody" and config.name == "default"
    assert not observer.training and config.model.hidden_size == 8
    # the same model the commands build (build_system, build_observer, load_weights)
    ref = build_system(config.system)
    model = build_observer(ref.group, ref.measurement_dim, ref.input_dim, config.model)
    load_weights(model, tiny_run)
    for a, b in zip(observer.state_dict().values(), model.state_dict().values()):
        assert torch.equal(a, b)
    data = _data(system)
    with torch.inference_mode():
        assert torch.equal(observer(data.measurements), model(data.measurements))
    # a checkpoint file alone (its config entry) gives the same observer
    again, _, cfg2 = load_observer(tiny_run / "checkpoints" / "best.pt")
    with torch.inference_mode():
        assert torch.equal(again(data.measurements), model(data.measurements))
    assert cfg2.system == config.system


def test_the_loaded_observer_reproduces_the_runs_own_evaluation(tiny_run):
    from omegaconf import OmegaConf

    from manifold_nets.datasets import inference_data
    from manifold_nets.evaluation import ObserverEstimator, evaluate

    observer, system, config = load_observer(tiny_run)
    (row,) = json.loads((tiny_run / "results" / "metrics.json").read_text())["table"]
    dataset = OmegaConf.to_object(config.dataset)
    data = inference_data(system, dataset, config.eval, 0.1, cache_dir=dataset.cache_dir)
    again = evaluate(ObserverEstimator(observer), data, system, skip=config.eval.skip_steps).row
    for key in ("R est", "p est", "b_omega est", "b_v est"):
        assert again[key] == pytest.approx(row[key], rel=1e-9), key


def _hostile_copy(run_dir: Path, dest: Path, edit) -> Path:
    """A copy of the run folder whose config.yaml is ``edit(config dict)``."""
    dest.mkdir()
    (dest / "checkpoints").mkdir()
    best = run_dir / "checkpoints" / "best.pt"
    (dest / "checkpoints" / "best.pt").write_bytes(best.read_bytes())
    cfg = yaml.safe_load((run_dir / "config.yaml").read_text())
    edit(cfg)
    (dest / "config.yaml").write_text(yaml.safe_dump(cfg))
    return dest


def _evil_pickle(tmp_path: Path, marker: Path) -> Path:
    """A pickle that writes ``marker`` when it is unpickled."""

    class Evil:
        def __reduce__(self):
            return (open, (str(marker), "w"))

    torch.save(Evil(), tmp_path / "evil.pt")
    assert not marker.exists()
    return tmp_path / "evil.pt"


def _torch_load(path: Path) -> dict:
    return {"_target_": "torch.load", "f": str(path), "weights_only": False}


def test_the_hostile_configs_do_run_code_through_hydra_instantiate(tmp_path):
    """The control: the old way (hydra's instantiate of a run folder's config) runs them."""
    from hydra.utils import instantiate

    marker = tmp_path / "ran"
    instantiate(_torch_load(_evil_pickle(tmp_path, marker)))
    assert marker.exists()
    instantiate({"_target_": "builtins.open", "file": str(tmp_path / "ran2"), "mode": "w"})
    assert (tmp_path / "ran2").exists()


@pytest.mark.parametrize("target", ["os.system", "subprocess.getoutput", "builtins.open",
                                    "torch.load"])
def test_a_config_naming_a_function_is_refused_and_nothing_runs(tiny_run, tmp_path, target):
    marker = tmp_path / "ran"
    system = {
        "os.system": {"_target_": "os.system", "command": f"touch {marker}"},
        "subprocess.getoutput": {"_target_": "subprocess.getoutput", "cmd": f"touch {marker}"},
        "builtins.open": {"_target_": "builtins.open", "file": str(marker), "mode": "w"},
        "torch.load": _torch_load(_evil_pickle(tmp_path, marker)),
    }[target]

    def edit(cfg):
        cfg["system"] = system

    bad = _hostile_copy(tiny_run, tmp_path / "bad", edit)
    with pytest.raises(UnknownTargetError, match="not a registered System.*import the module"):
        load_observer(bad)
    assert not marker.exists()


def test_an_unimported_class_is_refused_and_its_module_not_imported(
    tiny_run, tmp_path, monkeypatch
):
    marker = tmp_path / "ran"
    (tmp_path / "evil_mod.py").write_text(
        f"open({str(marker)!r}, 'w').close()\nclass Evil:\n    pass\n"
    )
    monkeypatch.syspath_prepend(str(tmp_path))

    def edit_system(cfg):
        cfg["system"]["_target_"] = "evil_mod.Evil"

    def edit_core(cfg):
        cfg["model"]["core"] = "evil_mod.Evil"

    for name, edit in (("system", edit_system), ("core", edit_core)):
        bad = _hostile_copy(tiny_run, tmp_path / name, edit)
        with pytest.raises(UnknownTargetError, match="never imports a module a file names"):
            load_observer(bad)
        assert not marker.exists() and "evil_mod" not in sys.modules


@pytest.mark.parametrize(
    "param",
    [
        {"_target_": "os.system", "command": "touch {marker}"},
        [{"_target_": "os.system", "command": "touch {marker}"}],
        {"inner": {"_target_": "os.system", "command": "touch {marker}"}},
        {"_partial_": True},
    ],
    ids=["nested", "in a list", "deeper", "hydra key"],
)
def test_nested_targets_in_the_system_parameters_are_refused(tiny_run, tmp_path, param):
    marker = tmp_path / "ran"
    param = json.loads(json.dumps(param).replace("{marker}", str(marker)))

    def edit(cfg):
        cfg["system"]["integrator"] = param

    bad = _hostile_copy(tiny_run, tmp_path / "bad", edit)
    with pytest.raises(ArtefactError, match="never objects to build"):
        load_observer(bad)
    assert not marker.exists()


def test_interpolations_and_hydra_keys_are_refused(tiny_run, tmp_path):
    def interpolation(cfg):
        cfg["system"]["integrator"] = "${oc.env:HOME}"

    def convert(cfg):
        cfg["system"]["_convert_"] = "all"

    bad = _hostile_copy(tiny_run, tmp_path / "a", interpolation)
    with pytest.raises(ArtefactError, match="interpolation"):
        load_observer(bad)
    bad = _hostile_copy(tiny_run, tmp_path / "b", convert)
    with pytest.raises(ArtefactError, match=r"\['_convert_'\]"):
        load_observer(bad)


def test_a_checkpoint_whose_config_names_a_function_is_refused(tiny_run, tmp_path):
    marker = tmp_path / "ran"
    ckpt = load_checkpoint(tiny_run / "checkpoints" / "best.pt")
    ckpt["config"]["system"] = {"_target_": "os.system", "command": f"touch {marker}"}
    ckpt.pop("format")
    save_checkpoint(tmp_path / "bad.pt", ckpt)
    with pytest.raises(UnknownTargetError):
        load_observer(tmp_path / "bad.pt")
    assert not marker.exists()


def test_system_subclasses_register_under_their_dotted_path():
    from manifold_nets_examples.rigid_body.system import RigidBody

    assert SYSTEMS.lookup("manifold_nets_examples.rigid_body.system.RigidBody") is RigidBody

    class Mine(System):  # abstract, but registered as soon as it is defined
        pass

    assert f"{__name__}.{Mine.__qualname__}" in SYSTEMS
    with pytest.raises(UnknownTargetError, match="manifold_nets_examples.rigid_body.system.RigidBody"):
        SYSTEMS.lookup("not.a.System")


def test_the_apply_command_round_trips(tiny_run, tmp_path):
    observer, system, _ = load_observer(tiny_run)
    data = _data(system, n=5, t=23)
    save_dataset(data, tmp_path / "data.npz")
    out = apply.run(
        [str(tiny_run), str(tmp_path / "data.npz"), "--out", str(tmp_path / "est.npz"),
         "--batch-size", "2", "--chunk", "7", "--no-progress"]
    )
    with np.load(out, allow_pickle=False) as f:
        est, meta = torch.from_numpy(f["estimates"]), json.loads(str(f["meta"]))
    y = load_dataset(tmp_path / "data.npz").measurements
    with torch.inference_mode():  # the same batches of 2 (GEMM rounding depends on the batch)
        ref = torch.cat([observer(y[s : s + 2]) for s in range(0, 5, 2)])
    assert est.shape == (5, 24, 18) and meta["signature"] == observer.signature()
    assert torch.equal(est, ref)  # chunked in time: the same steps from the same state
