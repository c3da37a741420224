"""The config schema: typed dataclasses for a run, which are also the library's settings objects.

``configs/train.yaml`` starts from :class:`RunConfig` (stored in hydra's ConfigStore as
``run_schema``; :class:`DatasetConfig` as ``dataset/dataset_schema``), so every key of the
``dataset``, ``model``, ``train``, ``eval`` and ``method`` groups and every command-line
override is checked when the config is composed: a misspelt key (``model.hiden_size=64``) or a
wrong type (``train.epochs=ten``) fails with hydra's message naming the key and the schema,
before any work. ``system`` is free-form: a ``_target_`` class and its own parameters.

The same dataclasses are what the library takes: :func:`manifold_nets.training.fit` a
:class:`TrainSettings`, :func:`manifold_nets.builders.build_observer` a :class:`ModelConfig`,
:func:`manifold_nets.datasets.load_or_generate` a :class:`DatasetConfig`.

Importing this module registers the schema and the ``mn_run_id`` resolver used in the output
folder names (a timestamp and the process id, so two runs can never share a folder).
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass, field
from typing import Any, Optional

from hydra.core.config_store import ConfigStore
from omegaconf import MISSING, OmegaConf

__all__ = [
    "DatasetConfig",
    "MethodConfig",
    "ModelConfig",
    "NoiseConfig",
    "TrainSettings",
    "EvalConfig",
    "RunConfig",
    "register_configs",
    "DTYPES",
]

DTYPES = ("float32", "float64")


@dataclass
class DatasetConfig:
    """One simulated dataset file (``configs/dataset/``): sizes, noise, seed, splits, cache."""

    #: A label for logs; not part of the cache key.
    name: str = "custom"
    num_sequences: int = 2000
    length: int = 50
    #: Standard deviation of every measurement noise component (0: noise-free).
    sigma: float = 0.0
    seed: int = 0
    #: Fractions of the sequences, in order, as contiguous ranges; must sum to 1.
    #: ``None`` means ``{train: 0.8, val: 0.1, test: 0.1}``. (A command-line dict override merges
    #: into the existing one: drop a split with ``~dataset.splits.test``.)
    splits: Optional[dict[str, float]] = None
    #: Where the files go; relative paths are taken from the directory the command ran in.
    cache_dir: str = "data"
    #: Write the files again even when a cached file exists.
    regenerate: bool = False
    #: Show a progress bar (only on a terminal).
    progress: bool = True


@dataclass
class ModelConfig:
    """The observer (``configs/model/``): the core, the group update and the pieces it is made of.

    Each piece is a block naming a registered piece by ``type`` with that piece's arguments
    (:mod:`manifold_nets.observer`; docs/observer.md lists them)::

        measurement: {factors: {R: [0, 9], p: [9, 12]}}        # type: measurement | robust
        prior: {type: system}                # none | system | robust_system | kinematic | complementary
        features: [embedding, readings, innovation]              # or {type: embedding, drop: [p]}
        head: {type: centred, c: 0.85, ramp: 50}                 # plain | gain | centred
        scales: [{type: step_decay, factors: {b_v: 70}}]         # output | step_decay

    The flat keys of the first format (``innovation``, ``relative_only``, ``rotated``,
    ``propagate``, ``gain``, ``gain_offset``, ``centering``, ``centering_ramp``,
    ``centering_factors``, ``step_decay``, ``robust_drive``, ``robust_innovation``,
    ``robust_span``, ``output_scale``, and ``prior: system``) still work, with a deprecation
    warning that shows the blocks they mean (:mod:`manifold_nets.observer.legacy`).
    """

    #: ``gru`` (the paper's GRU stack + linear head) or a registered
    #: :class:`manifold_nets.cores.RecurrentCore` subclass by dotted path, called with
    #: ``(input_size, output_size, hidden_size=, num_layers=)``.
    core: str = "gru"
    hidden_size: int = 512
    num_layers: int = 2
    #: Rule of every factor not named in ``updates``: ``residual`` (x·exp(v)), ``absolute``, ``left``.
    default_update: str = "residual"
    #: Per-factor rules by factor name, e.g. ``{b_omega: absolute, b_v: absolute}`` (the paper).
    updates: dict[str, str] = field(default_factory=dict)
    #: Factors taken off their group (an ablation): each named factor is replaced by the vector
    #: space of its embedding (``manifold_nets.relax``). Empty: the observer of the paper.
    relax: list[str] = field(default_factory=list)
    #: The measurement block: ``factors: {name: [start, stop]}``, the spans of ``y`` that hold a
    #: factor's embedding (its innovation is then read); ``type: robust`` (with ``width``,
    #: ``span``) weighs each innovation by a learned robust weight. Empty: nothing measured.
    measurement: dict[str, Any] = field(default_factory=dict)
    #: The prior block (``type: none | system | robust_system | kinematic | complementary``);
    #: ``null``: none.
    #: (A string ``none``/``system`` is the first format's.)
    prior: Any = None
    #: The feature blocks, in order (a name alone is ``{type: name}``); ``null``: the paper's
    #: ``[embedding, readings]``, with ``innovation`` when the measurement names factors.
    features: Optional[list[Any]] = None
    #: The head block (``type: plain | gain | centred``); empty: plain.
    head: dict[str, Any] = field(default_factory=dict)
    #: The step-scale blocks, in order (``type: output | step_decay``).
    scales: list[Any] = field(default_factory=list)
    #: dtype of the group state (``float64`` keeps the estimate on the group to ~1e-14).
    state_dtype: str = "float64"
    #: dtype of the network's parameters.
    net_dtype: str = "float32"
    # the first format's flat keys (deprecated; manifold_nets.observer.legacy)
    innovation: dict[str, list[int]] = field(default_factory=dict)
    relative_only: list[str] = field(default_factory=list)
    rotated: dict[str, list[list[int]]] = field(default_factory=dict)
    propagate: dict[str, list[int]] = field(default_factory=dict)
    clock: list[float] = field(default_factory=list)
    innovation_frame: dict[str, str] = field(default_factory=dict)
    prior_drive: bool = False
    gain: bool = False
    gain_offset: bool = True
    centering: float = 0.0
    centering_ramp: int = 0
    centering_factors: dict[str, float] = field(default_factory=dict)
    step_decay: dict[str, int] = field(default_factory=dict)
    robust_drive: int = 0
    robust_innovation: int = 0
    robust_span: float = 4.0
    output_scale: float = 1.0


@dataclass
class NoiseConfig:
    """Noise-augmented training: each training sequence gets measurement noise of its own sigma.

    Two ways, both off by default (the paper's noise-free protocol):

    * ``levels``: the training data (every split) is generated once per level (same seed, so the
      same trajectories) and each sequence takes its measurements from one level drawn at
      random (seeded by ``dataset.seed``): sigma per sequence, fixed over the epochs; needs
      nothing from the system but disk for one cached file per level.
    * ``sigma_max > 0``: fresh noise every epoch, ``sigma ~ U[sigma_min, sigma_max]`` per
      sequence, applied to the noise-free training data through ``system.apply_noise``.
    """

    levels: list[float] = field(default_factory=list)
    sigma_min: float = 0.0
    sigma_max: float = 0.0


@dataclass
class TrainSettings:
    """The training loop (``configs/train/``): AdamW, BPTT through the whole rollout."""

    #: Epochs of training. 0 (only with ``init_from``): no step; ``init_from``'s weights are
    #: evaluated as they are under this run's model config, e.g. another centring
    #: (``model.head``) or step decay (``model.scales``), which add no weight.
    epochs: int = 10
    batch_size: int = 256
    lr: float = 3.0e-4
    #: Other learning rates for some parameters, ``{name: lr}``: those whose name
    #: (``model.named_parameters()``) starts with it or has it as a dotted part, e.g.
    #: ``{robust: 1.0e-2}`` for every learned robust weight (``prior.robust.*``,
    #: ``measurement.robust.*``); scaled by the same schedule. Empty: ``lr`` for all.
    param_lr: dict[str, float] = field(default_factory=dict)
    weight_decay: float = 0.1
    #: Learning-rate schedule over the epochs: ``constant`` (the paper names none) or
    #: ``cosine`` (a half cosine from ``lr`` in the first epoch down towards ``lr_min``, which
    #: it would reach after the last).
    schedule: str = "constant"
    lr_min: float = 0.0
    #: Clip the gradient's global norm to this value (``null``: no clipping, as the paper).
    grad_clip: Optional[float] = None
    #: The training loss, also the validation loss that picks ``best.pt``: ``mse`` (the paper's
    #: ``L``) or ``log_mse`` (the mean of each sequence's ``log L_i``: the sequences at low noise
    #: weigh as much as the noisy ones) or ``factor_log_mse`` (the mean of each sequence's
    #: per-factor ``log L_if``: a product group's factors weigh alike too, whatever their
    #: units; :mod:`manifold_nets.losses`). The test loss the train command reports is ``L``.
    loss: str = "mse"
    #: One weight >= 0 per embedding coordinate of the group, multiplying its squared error in
    #: the training and validation loss (``null``: all 1). E.g. an attitude without a
    #: magnetometer: ``[0, 0, 0, 0, 0, 0, 1, 1, 1]``, SO(3)'s third row ``R^T e_z`` alone, scores
    #: the inclination and leaves the unobservable heading free (:mod:`manifold_nets.losses`).
    loss_weights: Optional[list[float]] = None
    #: Steps left out at the start of every sequence in the training and validation loss: 1,
    #: the fixed start ``x_0`` only (the paper's ``L``); 10 matches the evaluation
    #: (``eval.skip_steps``), so the start-up transient does not decide the gradient. With
    #: ``tbptt`` at most that long (it applies to the first piece).
    skip_steps: int = 1
    #: Truncated backpropagation through time: an optimizer step per this many steps of each
    #: training rollout, the estimate and the hidden state carried (detached) from one piece to
    #: the next, so sequences of thousands of steps train in bounded memory (``null``: BPTT
    #: through the whole rollout, the paper's). Validation rolls out whole sequences.
    tbptt: Optional[int] = None
    #: Stop an epoch after this many batches (``null``: the whole training split); for quick looks.
    max_batches: Optional[int] = None
    #: Stop after the epoch past which the next would end beyond this many minutes of training
    #: (judged by the last epoch's time; ``null``: all ``epochs``): a run on a lent machine
    #: trains as far as its time allows, keeps ``best.pt`` and is evaluated; ``resume`` goes on.
    time_limit: Optional[float] = None
    #: Sequences per forward pass in validation and evaluation.
    eval_batch_size: int = 500
    noise: NoiseConfig = field(default_factory=NoiseConfig)
    #: Fresh training sequences every epoch: the training split's size (``dataset.num_sequences``
    #: x its train fraction) and ``dataset.length``, simulated from (seed, epoch) with the
    #: system's noise model at ``train.noise.levels`` (one per sequence) or ``dataset.sigma``;
    #: validation and test stay the cached dataset's (:mod:`manifold_nets.streaming`).
    stream: bool = False
    #: ``cpu``, ``cuda``, ``cuda:1``, ... or ``auto`` (cuda when available).
    device: str = "cpu"
    #: torch intra-op threads (``null``: one, or ``OMP_NUM_THREADS`` when set;
    #: :func:`manifold_nets.threads.use_threads`).
    threads: Optional[int] = None
    #: Compile the observer's step with ``torch.compile`` for training (fused kernels, faster
    #: epochs after a one-off compilation; needs a C++ compiler).
    compile: bool = False
    #: On a CUDA device: capture each batch shape's whole training step as a CUDA graph and
    #: replay it (:mod:`manifold_nets.graphed_step`; not with ``tbptt``).
    cuda_graph: bool = False
    #: Continue from a checkpoint: a ``last.pt`` file or the run folder that holds one.
    resume: Optional[str] = None
    #: Start from a trained model's weights (a checkpoint, a run folder: its ``best.pt``,
    #: or a zoo entry, ``zoo:rigid_body/nominal``) with a fresh optimizer and epoch count:
    #: fine-tuning, e.g. on other data. The model is this run's ``model``; it may add pieces to
    #: the checkpoint's (a feature, learned robust weights, a gain head: they start where the
    #: checkpoint's observer is) or set weightless pieces otherwise (a centring, a step decay;
    #: :func:`manifold_nets.checkpoint.load_weights`); not together with ``resume``. With
    #: ``epochs=0`` the run only evaluates those weights and saves them with its own config.
    init_from: Optional[str] = None
    #: Show a progress bar with the running loss (on a terminal).
    progress: bool = True
    #: Write TensorBoard event files into ``<run folder>/tensorboard/``: losses and learning
    #: rate per epoch, the evaluation's metrics (needs ``pip install 'manifold_nets[logging]'``).
    tensorboard: bool = False


@dataclass
class EvalConfig:
    """Evaluation on noisy inference sets (``configs/eval/``), the paper's table and figure."""

    #: Noise levels of the inference sets, one table row each (one per job in a sweep:
    #: ``-m 'eval.sigmas=[0.1],[0.2]'``).
    sigmas: list[float] = field(default_factory=lambda: [0.1])
    #: Size and seed of each inference set (the paper: 1000 sequences of 1000 steps).
    num_sequences: int = 1000
    length: int = 1000
    seed: int = 1
    #: Steps left out at the start of every sequence (the paper skips the first 10).
    skip_steps: int = 10
    #: Evaluate this checkpoint instead of training (a ``.pt`` file, a run folder or a zoo entry,
    #: ``zoo:rigid_body/nominal``), as the observer its own config describes.
    checkpoint: Optional[str] = None
    #: Write the figures (PNG).
    plots: bool = True
    #: Also report the loss on the test split of the training data.
    test_split: bool = True
    #: Show progress bars (sequences done, a filter's steps) on a terminal, for long evaluations.
    progress: bool = True
    #: Reference methods evaluated on the same sets, their rows in the same table (not in the
    #: objective), e.g. ``[raw, ekf]``: the raw measurement and the model-based EKF.
    baselines: list[str] = field(default_factory=list)
    #: Also score the covariances of the estimators that give them (per factor the ANEES and the
    #: share of errors inside the 3-sigma ellipsoid; docs/calibration.md): the EKF, and the
    #: learned observer with ``covariance``.
    calibration: bool = False
    #: A covariance readout for the learned observer: a ``covariance.pt`` file
    #: (``covariance_training.save_readout``) or a zoo entry (``zoo:rigid_body/nominal``: its
    #: ``covariance.pt``; ``zoo:rigid_body/nominal/covariance_sensor.pt``: another readout the
    #: entry ships). Needs ``calibration=true``.
    covariance: Optional[str] = None
    #: Guard the learned observer against lock-out (``manifold_nets.observer.LockOutGuard``; an
    #: observer with ``model.measurement={type: robust}``): ``{tau: 20, floor: 0.1}`` re-acquires
    #: a measured factor when its learned robust weight averages below ``floor`` over ``tau``
    #: steps (a setting left out takes that default). ``null`` (or ``{}``): no guard.
    lock_out: Optional[Any] = None


@dataclass
class MethodConfig:
    """What produces the estimates (``configs/method/``): the learned observer or a baseline.

    Every method runs through the same evaluation (the same inference sets, metrics, table and
    figures), so runs with different ``method=`` compare row by row
    (``python -m manifold_nets.cli.compare``).
    """

    #: ``learned``: train the observer (or load ``eval.checkpoint``) and evaluate it;
    #: ``untrained``: the observer at its seeded initialisation, no training (an ablation);
    #: any other name: an estimator of the system, ``system.estimators()[name]`` (``raw``,
    #: ``dead_reckoning`` for every system; ``ekf``, ``complementary`` where the system has them).
    name: str = "learned"
    #: The dotted path of an estimator factory ``(system, sigma=..., **params) -> Estimator`` for
    #: one the system does not list; ``name`` is then only its label.
    target: Optional[str] = None
    #: Keyword arguments of the estimator factory (e.g. ``{init_steps: 0}`` for the rigid body's EKF).
    params: dict[str, Any] = field(default_factory=dict)
    #: The label of its rows in tables and comparisons (default: ``name``; in a comparison a
    #: ``learned`` observer is named by its experiment, so that two experiments stay apart).
    label: Optional[str] = None


@dataclass
class RunConfig:
    """The whole run: ``system`` x ``dataset`` x ``model`` x ``train`` x ``eval`` x ``method``, a seed."""

    #: The system: ``_target_`` (``manifold_nets_examples.rigid_body.RigidBody``) and parameters.
    system: Any = MISSING
    dataset: DatasetConfig = field(default_factory=DatasetConfig)
    #: Train on this dataset file (written by ``save_dataset``, with ``train``/``val`` splits)
    #: instead of generating ``dataset``.
    data_file: Optional[str] = None
    model: ModelConfig = field(default_factory=ModelConfig)
    train: TrainSettings = field(default_factory=TrainSettings)
    eval: EvalConfig = field(default_factory=EvalConfig)
    method: MethodConfig = field(default_factory=MethodConfig)
    #: Seed of the model's initialisation, the batch order and the training noise.
    seed: int = 0
    #: Experiment name: the first level of the output folders.
    name: str = "default"
    #: The number the commands return to a hydra sweeper (Optuna minimises or maximises it):
    #: ``best_val_loss`` (the best epoch's validation loss), ``test_loss``, a metric column of
    #: the results table averaged over ``eval.sigmas`` (``R est``, ``R reduction %``, ...), or a
    #: column at one sigma, ``R est@0.1`` (:mod:`manifold_nets.objective`, docs/sweeps.md).
    objective: str = "best_val_loss"


def _run_id() -> str:
    """``YYYY-mm-dd_HH-MM-SS_<pid>``: unique among concurrent runs on one machine."""
    return time.strftime("%Y-%m-%d_%H-%M-%S") + f"_{os.getpid()}"


def register_configs() -> None:
    """Registers the schema (``run_schema``, ``dataset/dataset_schema``) and the ``mn_run_id``
    resolver (idempotent)."""
    ConfigStore.instance().store(name="run_schema", node=RunConfig)
    ConfigStore.instance().store(group="dataset", name="dataset_schema", node=DatasetConfig)
    if not OmegaConf.has_resolver("mn_run_id"):
        OmegaConf.register_new_resolver("mn_run_id", _run_id, use_cache=True)


register_configs()
