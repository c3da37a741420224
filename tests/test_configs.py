"""hydra configs: every experiment composes, typos fail, the whole command runs on tiny sizes."""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from hydra import compose, initialize_config_dir
from hydra.errors import ConfigCompositionException
from omegaconf import OmegaConf

import manifold_nets.config  # noqa: F401  (registers the schema)
from manifold_nets.cli import sweep
from manifold_nets.checkpoint import CheckpointError
from manifold_nets.cli.train import run
from manifold_nets.config import RunConfig

ROOT = Path(__file__).resolve().parents[1]
CONFIGS = ROOT / "configs"
EXPERIMENTS = sorted(p.stem for p in (CONFIGS / "experiment").glob("*.yaml"))


def _compose(*overrides: str):
    with initialize_config_dir(config_dir=str(CONFIGS), version_base="1.3"):
        return compose("train", overrides=list(overrides))


def _tiny(cache: Path, *more: str) -> list[str]:
    """The tiny run of experiment=default (``configs/debug/tiny.yaml``), its data in ``cache``."""
    return ["experiment=default", "debug=tiny", f"dataset.cache_dir={cache}", *more]


def test_there_are_experiments():
    assert {"default", "paper_rigid_body"} <= set(EXPERIMENTS)


@pytest.mark.parametrize("name", EXPERIMENTS)
def test_every_experiment_composes_into_the_schema(name):
    cfg = _compose(f"experiment={name}")
    obj = OmegaConf.to_object(cfg)
    assert isinstance(obj, RunConfig)
    assert cfg.system._target_ and cfg.name == name
    assert cfg.model.hidden_size > 0 and cfg.eval.sigmas


GROUPS = ("system", "dataset", "model", "train", "eval")


def _defaults(group: str, name: str) -> list:
    return OmegaConf.to_container(OmegaConf.load(CONFIGS / group / f"{name}.yaml")).get(
        "defaults", []
    )


def _parents(group: str, name: str) -> list[str]:
    """The files of its own group that ``group/name.yaml`` merges in (``- other`` in defaults)."""
    parents = []
    for entry in _defaults(group, name):
        if isinstance(entry, dict):  # `/group: file` names a file of another group, or this one
            ((key, value),) = entry.items()
            if key.startswith(("override ", "optional ")) or key.lstrip("/") != group:
                continue
            entry = str(value)
        entry = entry.removeprefix(f"/{group}/")
        if entry != "_self_" and (CONFIGS / group / f"{entry}.yaml").is_file():
            parents.append(entry)
    return parents


def _inheritance_depth(group: str, name: str, seen: tuple = ()) -> int:
    assert name not in seen, f"{group}/{name}.yaml inherits from itself via {seen}"
    parents = _parents(group, name)
    return 1 + max(_inheritance_depth(group, p, (*seen, name)) for p in parents) if parents else 0


@pytest.mark.parametrize(
    "group, name",
    sorted((p.parent.name, p.stem) for p in CONFIGS.glob("*/*.yaml")),
    ids=lambda x: x,
)
def test_no_config_inherits_from_another_of_its_group_more_than_one_level(group, name):
    # flat like lightning-hydra-template: what a run uses is read off one or two files
    assert _inheritance_depth(group, name) <= 1, (group, name, _parents(group, name))


@pytest.mark.parametrize("name", EXPERIMENTS)
def test_every_experiment_names_its_group_files(name):
    named = {
        k.removeprefix("override /")
        for entry in _defaults("experiment", name)
        if isinstance(entry, dict)
        for k in entry
    }
    assert set(GROUPS) <= named, f"experiment/{name}.yaml does not name {set(GROUPS) - named}"


@pytest.mark.parametrize("name", EXPERIMENTS)
def test_debug_tiny_composes_with_every_experiment(name):
    full = _compose(f"experiment={name}")
    cfg = _compose(f"experiment={name}", "debug=tiny")
    assert isinstance(OmegaConf.to_object(cfg), RunConfig) and cfg.name == name
    # the toy sizes win over the experiment's (debug comes after it in train.yaml's defaults)...
    assert (cfg.dataset.num_sequences, cfg.dataset.length) == (40, 8)
    assert (cfg.model.hidden_size, cfg.model.num_layers, cfg.train.epochs) == (8, 1, 1)
    assert list(cfg.eval.sigmas) == [0.1] and (cfg.eval.num_sequences, cfg.eval.length) == (4, 16)
    assert cfg.train.device == "cpu" and not cfg.train.compile
    # ...and everything else is the experiment's
    tiny = OmegaConf.load(CONFIGS / "debug" / "tiny.yaml")
    assert OmegaConf.to_container(cfg) == OmegaConf.to_container(OmegaConf.merge(full, tiny))


def test_paper_experiment_has_the_paper_sizes():
    cfg = _compose("experiment=paper_rigid_body")
    assert (cfg.model.hidden_size, cfg.model.num_layers) == (512, 2)
    assert dict(cfg.model.updates) == {"b_omega": "absolute", "b_v": "absolute"}
    assert (cfg.train.lr, cfg.train.weight_decay) == (3e-4, 0.1)
    assert (cfg.dataset.num_sequences, cfg.dataset.length, cfg.dataset.sigma) == (20000, 100, 0.0)
    assert dict(cfg.dataset.splits) == {"train": 0.8, "val": 0.1, "test": 0.1}
    assert list(cfg.eval.sigmas) == [0.1, 0.2, 0.3, 0.4, 0.5]
    assert (cfg.eval.num_sequences, cfg.eval.length, cfg.eval.skip_steps) == (1000, 1000, 10)


@pytest.mark.parametrize(
    "override, match",
    [
        ("model.hiden_size=64", "hiden_size"),
        ("train.epochs=ten", "epochs"),
        ("eval.sigmas=0.1", "sigmas"),
        ("lr=0.1", "lr"),
        ("experiment=no_such_experiment", "no_such_experiment"),
    ],
)
def test_typos_and_wrong_types_fail_when_composing(override, match):
    with pytest.raises(ConfigCompositionException, match=match):
        _compose(override)


def test_keys_appended_with_plus_are_checked_before_any_work(tmp_path):
    cfg = _compose("+model.dropout=0.1")  # hydra lets an explicit append through...
    with pytest.raises(ValueError, match="dropout.*not in the schema"):  # ...run() does not
        run(cfg, tmp_path)
    assert not (tmp_path / "checkpoints").exists()


@pytest.mark.parametrize(
    "override, match",
    [("train.schedule=linear", "train.schedule='linear'"), ("train.lr_min=1", "train.lr_min")],
)
def test_bad_schedules_fail_before_any_work(tmp_path, override, match):
    with pytest.raises(ValueError, match=match):
        run(_compose(*_tiny(tmp_path / "data", override)), tmp_path / "run")
    assert not (tmp_path / "run" / "checkpoints").exists()
    assert not (tmp_path / "data").exists()  # no data generated either


@pytest.mark.parametrize(
    "dataset, evaluation", [("small_inference", "small"), ("paper_inference", "paper")]
)
def test_the_generate_command_writes_the_inference_sets_of_eval(dataset, evaluation):
    with initialize_config_dir(config_dir=str(CONFIGS), version_base="1.3"):
        d = compose("generate", overrides=[f"dataset={dataset}"]).dataset
    e = _compose(f"eval={evaluation}").eval
    assert (d.num_sequences, d.length, d.seed) == (e.num_sequences, e.length, e.seed)
    assert dict(d.splits) == {"inference": 1.0} and d.sigma == e.sigmas[0]


def test_the_train_command_reads_the_file_of_dataset_small_inference(tmp_path):
    from hydra.utils import instantiate

    from manifold_nets.datasets import inference_data, load_or_generate

    with initialize_config_dir(config_dir=str(CONFIGS), version_base="1.3"):
        gen = compose("generate", overrides=["dataset=small_inference", "dataset.progress=false"])
    system = instantiate(gen.system)
    written = load_or_generate(system, gen.dataset, cache_dir=tmp_path)["inference"]
    cfg = _compose("experiment=default", f"dataset.cache_dir={tmp_path}")  # eval=small
    dataset = OmegaConf.to_object(cfg.dataset)
    read = inference_data(system, dataset, cfg.eval, cfg.eval.sigmas[0], cache_dir=tmp_path)
    assert read.meta["path"] == written.meta["path"] and read == written
    assert len(list(tmp_path.glob("*.npz"))) == 1  # read from the cache, nothing generated


def test_run_folders_cannot_collide():
    with initialize_config_dir(config_dir=str(CONFIGS), version_base="1.3"):
        cfg = compose("train", overrides=["experiment=default"], return_hydra_config=True)
    run_dir = cfg.hydra.run.dir
    assert run_dir.startswith("outputs/default/") and run_dir.endswith(f"_{os.getpid()}")
    assert OmegaConf.to_container(cfg.hydra.sweep)["subdir"] == "${hydra.job.num}"


def test_both_commands_take_their_folders_from_configs_hydra():
    with initialize_config_dir(config_dir=str(CONFIGS), version_base="1.3"):
        gen = compose("generate", return_hydra_config=True)
        train = compose("train", overrides=["experiment=paper_cpu"], return_hydra_config=True)
    for cfg, name in ((gen, "generate"), (train, "paper_cpu")):
        assert cfg.hydra.run.dir.startswith(f"outputs/{name}/")
        assert cfg.hydra.sweep.dir.startswith(f"multirun/{name}/")
        assert cfg.hydra.job.chdir is False
    assert OmegaConf.to_container(gen.hydra.sweep)["subdir"] == "${hydra.job.num}"


def test_the_generate_command_writes_into_its_own_run_folder(tmp_path):
    cmd = [
        sys.executable, "-m", "manifold_nets.cli.generate", f"dataset.cache_dir={tmp_path / 'data'}",
        "dataset.num_sequences=10", "dataset.length=4", "dataset.progress=false",
    ]  # fmt: skip
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    out = subprocess.run(
        cmd, cwd=tmp_path, env=env, capture_output=True, text=True, timeout=120, check=False
    )
    assert out.returncode == 0, out.stderr[-3000:]
    (run_dir,) = (tmp_path / "outputs" / "generate").iterdir()
    assert re.fullmatch(r"\d{4}-\d\d-\d\d_\d\d-\d\d-\d\d_\d+", run_dir.name), run_dir.name


def test_the_whole_command_on_tiny_sizes(tmp_path):
    cache = tmp_path / "data"
    metrics = run(_compose(*_tiny(cache)), tmp_path / "run")
    res = tmp_path / "run" / "results"
    for name in ("table.csv", "table.md", "metrics.json", "curves.json", "errors_sigma0.1.png"):
        assert (res / name).is_file(), name
    (row,) = metrics["table"]
    assert row["sigma"] == 0.1 and row["steps"] == 16 and row["membership max"] < 1e-12
    assert {"R est", "R meas", "p est", "p meas", "b_omega est", "b_v est"} <= set(row)
    assert (tmp_path / "run" / "checkpoints" / "best.pt").is_file()
    assert json.loads((res / "metrics.json").read_text())["table"] == metrics["table"]

    # evaluating the checkpoint gives the same table, at another sigma too
    again = run(_compose(*_tiny(cache, f"eval.checkpoint={tmp_path / 'run'}")), tmp_path / "ev")
    assert again["table"][0]["R est"] == pytest.approx(row["R est"], rel=1e-6)
    other = run(
        _compose(*_tiny(cache, f"eval.checkpoint={tmp_path / 'run'}", "eval.sigmas=[0.3]")),
        tmp_path / "ev3",
    )
    assert other["table"][0]["sigma"] == 0.3 and other["table"][0]["R meas"] > row["R meas"]

    # eval.checkpoint is the observer its own config describes: the command's model settings
    # do not apply to it
    same = run(
        _compose(*_tiny(cache, f"eval.checkpoint={tmp_path / 'run'}", "model.hidden_size=16")),
        tmp_path / "ev16",
    )
    assert same["table"][0]["R est"] == row["R est"]
    # starting another model from it, a missing checkpoint, a missing dataset: clear errors
    with pytest.raises(CheckpointError, match="cannot start this model.*core.hidden_size"):
        run(
            _compose(*_tiny(cache, f"train.init_from={tmp_path / 'run'}", "model.hidden_size=16")),
            tmp_path / "bad",
        )
    with pytest.raises(CheckpointError, match="no best.pt"):
        run(_compose(*_tiny(cache, f"eval.checkpoint={tmp_path}")), tmp_path / "bad")
    with pytest.raises(FileNotFoundError, match="no dataset at"):
        run(_compose(*_tiny(cache, f"data_file={tmp_path / 'none.npz'}")), tmp_path / "bad")
    with pytest.raises(ValueError, match="model.updates names factors"):
        run(_compose(*_tiny(cache, "+model.updates.bias=absolute")), tmp_path / "bad")


def test_multirun_and_sweep_table(tmp_path):
    """The real command line: a 2-job multirun into its own folder, then the sweep table."""
    sweep_dir = tmp_path / "multirun"
    cmd = [
        sys.executable,
        "-m",
        "manifold_nets.cli.train",
        "-m",
        *_tiny(tmp_path / "data"),
        "seed=0,1",
        "train.max_batches=1",  # one step: epochs=0 is refused
        f"hydra.sweep.dir={sweep_dir}",
    ]
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    out = subprocess.run(
        cmd, cwd=ROOT, env=env, capture_output=True, text=True, timeout=300, check=False
    )
    assert out.returncode == 0, out.stderr[-3000:]
    assert (sweep_dir / "0" / "results" / "metrics.json").is_file()
    assert (sweep_dir / "1" / "results" / "metrics.json").is_file()
    assert sweep.main([str(sweep_dir)]) == 0
    text = (sweep_dir / "sweep.md").read_text()
    assert text.count("\n| ") == 3  # header + 2 jobs
    summary = (sweep_dir / "sweep_summary.md").read_text()
    assert "R est mean" in summary and "| 0.1 |" in summary.replace("| 0.1000 |", "| 0.1 |")
    assert sweep.main([str(tmp_path / "nothing")]) == 1


@pytest.mark.parametrize(
    "override, message",
    [
        ("train.grad_clip=-1", "train.grad_clip must be > 0 or None (null: no clipping), got -1.0"),
        ("train.grad_clip=0", "train.grad_clip must be > 0 or None (null: no clipping), got 0.0"),
        ("train.max_batches=0", "train.max_batches must be an integer >= 1 or None (null: the "
                                "whole training split), got 0."),
        ("train.epochs=-1", "train.epochs must be an integer >= 0 (0: no step, the starting "
                            "model is kept), got -1."),
        ("train.epochs=0", "train.epochs=0 trains nothing: it evaluates train.init_from's "
                           "weights as they are"),
        ("train.threads=0", "train.threads must be an integer >= 1 or None (null: one thread, "
                            "or OMP_NUM_THREADS when set), got 0."),
        ("train.device=tpu", "train.device='tpu' is not a device; use cpu, cuda, cuda:<index> "
                             "or auto"),
        ("system.dt=1", "RigidBody: one step can turn by up to sqrt(3) * (omega_range + "
                        "bias_range) * dt = sqrt(3) * (1 + 10) * 1 = 19.05 rad, which must be < "
                        "pi"),
        ("system.bias_range=100", "RigidBody: one step can turn by up to sqrt(3) * (omega_range "
                                  "+ bias_range) * dt = sqrt(3) * (1 + 100) * 0.1 = 17.49 rad"),
        ("system.dt=1e300", "RigidBody: one step can turn by up to"),
        ("train.noise.sigma_max=nan", "train.noise.sigma_max must be a number in [0, 1000]"),
        ("train.noise.sigma_max=inf", "train.noise.sigma_max must be a number in [0, 1000]"),
        ("train.weight_decay=-1", "train.weight_decay must be a finite number >= 0"),
        ("train.weight_decay=nan", "train.weight_decay must be a finite number >= 0"),
        ("eval.skip_steps=16", "eval.skip_steps=16 leaves no step of eval.length=16"),
        ("train.skip_steps=9", "train.skip_steps=9 is longer than a training sequence"),
        ("++train.param_lr={nope:0.1}", "train.param_lr['nope'] names no parameter"),
        ("eval.seed=-1", "eval.seed must be an integer >= 0"),
        ("eval.length=0", "eval.length must be an integer >= 1"),
        ("eval.sigmas=[1e300]", "eval.sigmas must be finite numbers in [0, 1000]"),
        ("dataset.length=1000000000", "dataset.num_sequences x dataset.length = 40 x 1000000000"),
    ],
)
def test_nonsense_values_fail_before_any_work_and_write_nothing(tmp_path, override, message):
    with pytest.raises(ValueError) as err:
        run(_compose(*_tiny(tmp_path / "data", override)), tmp_path / "run")
    assert str(err.value).startswith(message), str(err.value)
    assert not (tmp_path / "run").exists()  # not even config.yaml
    assert not (tmp_path / "data").exists()


def test_a_system_that_generates_nan_is_named_not_a_file(tmp_path):
    from manifold_nets.data import DatasetError

    # the turn bound holds (no rotation), but positions of 1e10 m/s * 1e300 s overflow
    over = ["system.omega_range=0", "system.bias_range=0", "system.velocity_range=1e10",
            "system.dt=1e300"]  # fmt: skip
    with pytest.raises(DatasetError) as err:  # was: "... regenerate the data (a corrupt file:
        run(_compose(*_tiny(tmp_path / "data", *over)), tmp_path / "run")  # delete it) ..."
    msg = str(err.value)
    assert msg.startswith("the system RigidBody(") and "generated non-finite values (NaN/Inf) in"
    assert "nothing was written to" in msg and "Check the system's parameters (system.*" in msg
    assert "corrupt" not in msg
    assert not list((tmp_path / "data").glob("*.npz"))


def test_results_json_is_valid_json_with_undefined_values_as_null(tmp_path):
    # at sigma 0 the measurement error is 0 and the reduction undefined: it was a bare NaN
    run(_compose(*_tiny(tmp_path / "data", "method=raw", "eval.sigmas=[0.0]")), tmp_path / "run")

    def strict(name):
        def refuse(const):
            raise ValueError(f"{name} holds {const}: not JSON")

        return json.loads((tmp_path / "run" / "results" / name).read_text(), parse_constant=refuse)

    (row,) = strict("metrics.json")["table"]
    assert row["R meas"] == 0.0 and row["R reduction %"] is None
    assert strict("curves.json")["0"]["R meas"][0] is None  # no measurement at k = 0
    from manifold_nets.results import collect

    (read,) = collect(tmp_path / "run")  # the sweep tables read the null back as NaN
    assert read["R reduction %"] != read["R reduction %"]


def test_a_checkpoint_with_nan_weights_fails_the_evaluation_and_writes_no_results(tmp_path):
    from manifold_nets.checkpoint import save_checkpoint
    from manifold_nets.evaluation import EstimatesNotFinite

    cache = tmp_path / "data"
    run(_compose(*_tiny(cache)), tmp_path / "run")
    ckpt = torch.load(tmp_path / "run" / "checkpoints" / "best.pt", weights_only=True)
    name = next(iter(ckpt["model"]))
    ckpt["model"][name].view(-1)[0] = float("nan")
    save_checkpoint(tmp_path / "nan.pt", {k: v for k, v in ckpt.items() if k != "format"})
    with pytest.raises(EstimatesNotFinite, match=r"^default: the estimates are not finite "
                       r"\(NaN/Inf\) in 4 of 4 sequences, the first in sequence 0"):
        run(_compose(*_tiny(cache, f"eval.checkpoint={tmp_path / 'nan.pt'}")), tmp_path / "ev")
    assert not (tmp_path / "ev" / "results" / "metrics.json").exists()  # was: NaN rows, exit 0


def test_the_command_refuses_a_negative_grad_clip_and_leaves_no_run_folder(tmp_path):
    out_dir = tmp_path / "outputs" / "run"
    cmd = [sys.executable, "-m", "manifold_nets.cli.train", *_tiny(tmp_path / "data"),
           "train.grad_clip=-1", f"hydra.run.dir={out_dir}"]  # fmt: skip
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    out = subprocess.run(
        cmd, cwd=tmp_path, env=env, capture_output=True, text=True, timeout=120, check=False
    )
    assert out.returncode != 0  # was: exit 0, epoch 0 as the best
    assert "train.grad_clip must be > 0 or None (null: no clipping), got -1.0" in out.stderr
    assert f"the run failed before any work; its folder {out_dir} is removed" in (
        out.stdout + out.stderr
    )
    # hydra had made it (.hydra/, train.log): removed, with outputs/ that it left empty
    assert not (tmp_path / "outputs").exists()


def test_a_typoed_eval_checkpoint_is_refused_before_the_run_folder_gets_a_file(tmp_path):
    """The evaluate command with ``eval.checkpoint`` naming no file fails with
    ``no checkpoint at <path>; train first or fix the path.`` and writes no config.yaml (was:
    config.yaml written, then the error)."""
    out_dir, typo = tmp_path / "out", tmp_path / "runs" / "bset.pt"
    cmd = [sys.executable, "-m", "manifold_nets.cli.evaluate", *_tiny(tmp_path / "data"),
           f"eval.checkpoint={typo}", f"hydra.run.dir={out_dir}"]  # fmt: skip
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    out = subprocess.run(
        cmd, cwd=tmp_path, env=env, capture_output=True, text=True, timeout=120, check=False
    )
    assert out.returncode != 0
    assert f"no checkpoint at {typo}; train first or fix the path." in out.stderr
    assert not out_dir.exists()  # hydra had made it (.hydra/, evaluate.log): removed
    # a run folder without best.pt is refused the same way
    with pytest.raises(CheckpointError, match=r"^no best\.pt in the run folder"):
        run(_compose(*_tiny(tmp_path / "data", f"eval.checkpoint={tmp_path}")), tmp_path / "ev")
    assert not (tmp_path / "ev").exists()


@pytest.mark.parametrize("key, name", [("train.init_from", "best.pt"), ("train.resume", "last.pt")])
def test_a_typoed_init_from_or_resume_is_refused_before_the_run_folder_gets_a_file(
    tmp_path, key, name
):
    """Like eval.checkpoint: the checkpoint to start from is read before config.yaml is written."""
    typo = tmp_path / "runs" / "nowhere"
    with pytest.raises(CheckpointError, match=r"no checkpoint at .*nowhere; train first or fix"):
        run(_compose(*_tiny(tmp_path / "data", f"{key}={typo}")), tmp_path / "r1")
    assert not (tmp_path / "r1").exists()
    with pytest.raises(CheckpointError, match=rf"^no {name.replace('.', '[.]')} in the run folder"):
        run(_compose(*_tiny(tmp_path / "data", f"{key}={tmp_path}")), tmp_path / "r2")
    assert not (tmp_path / "r2").exists()
