"""The observer: the paper's loop in one short class, and the pieces a config lists.

======================  ====================================================================
the loop                :class:`ResidualObserver`, :class:`ObserverState`
the group update        :class:`GroupUpdate` (per-factor rules, the state dtype)
what it reads           :class:`Measurement`, :class:`RobustMeasurement`
priors                  :class:`NoPrior`, :class:`SystemPrior`, :class:`RobustSystemPrior`,
                        :class:`KinematicPrior`, :class:`ComplementaryPrior`
features                :class:`Embedding`, :class:`Readings`, :class:`Innovation`,
                        :class:`Rotated`, :class:`FramedInnovation`
heads                   :class:`PlainHead`, :class:`GainHead`, :class:`CentredHead`
step scales             :class:`OutputScale`, :class:`StepDecay`, :class:`Projection`
a covariance            :class:`CovarianceReadout`, :class:`CalibratedObserver`,
                        :class:`LevelScale`
a readings pre-filter   :class:`ReadingsFilter`, :class:`FilteredObserver`,
                        :func:`with_readings_filter`
an ensemble of seeds    :class:`EnsembleObserver` (the members' barycentre on the group)
against lock-out        :class:`LockOutGuard` (re-acquires a factor the robust weights shut
                        out)
your own piece          subclass :class:`Prior`, :class:`Feature`, :class:`Head` or
                        :class:`StepScale` with a ``name``: a config may then name it
======================  ====================================================================
"""

from .calibrated import CalibratedObserver, CalibratedState, CalibratedStep
from .covariance import CovarianceReadout
from .ensemble import EnsembleObserver, EnsembleState, EnsembleStep
from .features import Embedding, Feature, FramedInnovation, Innovation, Readings, Rotated
from .filtered import FilteredObserver, FilteredState, with_readings_filter
from .heads import CentredHead, GainHead, Head, PlainHead
from .level_scale import LevelScale
from .lock_out import GuardedRollout, GuardedState, GuardedStep, LockOutGuard
from .measurement import Measurement, RobustMeasurement, StepView
from .observer import ObserverState, ResidualObserver, Rollout
from .piece import PIECES, Piece
from .priors import (
    ComplementaryPrior,
    KinematicPrior,
    NoPrior,
    Prior,
    RobustSystemPrior,
    SystemPrior,
)
from .readings_filter import ReadingsFilter
from .robust import RobustWeights
from .scales import OutputScale, Projection, StepDecay, StepScale
from .update import UPDATE_RULES, GroupUpdate

__all__ = [
    "ResidualObserver", "ObserverState", "Rollout", "GroupUpdate", "UPDATE_RULES",
    "Measurement", "RobustMeasurement", "StepView", "Piece", "PIECES",
    "Prior", "NoPrior", "SystemPrior", "RobustSystemPrior", "KinematicPrior",
    "ComplementaryPrior",
    "Feature", "Embedding", "Readings", "Innovation", "Rotated", "FramedInnovation",
    "Head", "PlainHead", "GainHead", "CentredHead",
    "StepScale", "OutputScale", "StepDecay", "Projection", "RobustWeights",
    "CovarianceReadout", "CalibratedObserver", "CalibratedState", "CalibratedStep", "LevelScale",
    "ReadingsFilter", "FilteredObserver", "FilteredState", "with_readings_filter",
    "EnsembleObserver", "EnsembleState", "EnsembleStep",
    "LockOutGuard", "GuardedState", "GuardedRollout", "GuardedStep",
]
