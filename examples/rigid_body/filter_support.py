"""What the rigid body's classical filters share: the check that a system has the paper's layout
``(vec R, p, b_Omega, b_v)``, and a dataset repeated block after block for their batched grid
searches (:mod:`.ekf_estimator`, :mod:`.complementary`).
"""

from __future__ import annotations

from manifold_nets.data import TrajectoryDataset

from .system import RigidBody


def _check_system(system, who: str) -> None:
    """The filters here work on the paper's layout ``(vec R, p, b_Omega, b_v)`` only."""
    if not isinstance(system, RigidBody):
        raise TypeError(f"{who} needs a RigidBody, got {type(system).__name__}.")
    if system.pose_group != "so3_r3":
        raise ValueError(
            f"{who} works on the paper's group SO(3) x R^3 x R^3 x R^3 (pose_group='so3_r3'); "
            f"this RigidBody has pose_group={system.pose_group!r}. Filter the so3_r3 system (the "
            "same data) and compare through System.metrics."
        )


def _repeat(data: TrajectoryDataset, reps: int) -> TrajectoryDataset:
    """``data`` with its sequences repeated ``reps`` times (block after block)."""
    return TrajectoryDataset(
        data.states.repeat(reps, 1, 1),
        data.measurements.repeat(reps, 1, 1),
        data.inputs.repeat(reps, 1, 1),
        dict(data.meta),
    )
