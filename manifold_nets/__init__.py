"""Learning on Lie groups: the residual-on-algebra observer, its data, training and evaluation.

Generic over any :class:`groups.LieGroup`; concrete systems live in ``examples/``. The names a
user needs, by where they sit in the data flow
(config -> system -> dataset -> observer rollout -> loss and metrics -> results):

=====================  ======================================================================
system                 :class:`System` (subclass it), :func:`manifold_nets.testing.check_system`
data                   :class:`TrajectoryDataset`, :func:`load_dataset`, :func:`save_dataset`,
                       :func:`make_dataset`, :func:`load_or_generate`,
                       :func:`collate_trajectories` (for ``torch.utils.data.DataLoader``),
                       :class:`SimulatedStream` (fresh sequences every epoch, for :func:`fit`)
observer               :class:`ResidualObserver` and its pieces (:mod:`manifold_nets.observer`),
                       :class:`RecurrentCore`, :class:`GRUCore`
training               :func:`fit`, :class:`TrainSettings`, :class:`MeasurementNoise`,
                       :func:`embedding_mse`
evaluation             :func:`evaluate`, :func:`factor_errors`, :class:`ErrorStateEKF`
                       (and :mod:`manifold_nets.baselines`)
config and artefacts   :class:`RunConfig` (the schema), :func:`build_observer`,
                       :func:`load_checkpoint`, :func:`save_checkpoint`
deployment             :func:`load_observer` (a run folder or checkpoint, in one call),
                       :func:`export_observer` (the online step, ``torch.export``)
=====================  ======================================================================

The commands (training, evaluation, data generation, sweeps, comparisons) live in
:mod:`manifold_nets.cli`, above the library; nothing here imports them.
"""

from .augmentation import MeasurementNoise
from .builders import build_observer
from .checkpoint import load_checkpoint, save_checkpoint
from .config import DatasetConfig, ModelConfig, RunConfig, TrainSettings
from .cores import GRUCore, RecurrentCore
from .data import (
    DatasetError,
    TrajectoryDataset,
    collate_trajectories,
    load_dataset,
    save_dataset,
)
from .datasets import load_or_generate, make_dataset
from .deploy import export_observer
from .ekf import ErrorStateEKF
from .evaluation import evaluate
from .loading import load_observer
from .losses import embedding_mse, factor_errors
from .observer import ResidualObserver
from .streaming import SimulatedStream
from .system import System
from .training import fit

__version__ = "0.1.0"

__all__ = [
    "System",
    "TrajectoryDataset",
    "DatasetError",
    "collate_trajectories",
    "load_dataset",
    "save_dataset",
    "make_dataset",
    "load_or_generate",
    "SimulatedStream",
    "ResidualObserver",
    "RecurrentCore",
    "GRUCore",
    "fit",
    "TrainSettings",
    "MeasurementNoise",
    "embedding_mse",
    "evaluate",
    "factor_errors",
    "ErrorStateEKF",
    "RunConfig",
    "DatasetConfig",
    "ModelConfig",
    "build_observer",
    "load_checkpoint",
    "save_checkpoint",
    "load_observer",
    "export_observer",
]
