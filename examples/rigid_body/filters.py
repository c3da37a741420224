"""Classical filters for the paper's rigid body: the error-state EKF's model and a complementary
filter.

**The EKF model** (:class:`RigidBodyFilterModel`). The filter's state is the system's own state
``(R, p, b_Omega, b_v)`` on ``SO(3) x R^3 x R^3 x R^3`` with the right error
``R = Rhat exp(dtheta)``, ``p = phat + dp``, ``b = bhat + db`` (12-dimensional). The simulator has
measurement noise only, but the filter sees the velocities only through the biased, noisy
readings of ``y_{k+1}``, so for the filter::

    drive   (Omega, v) = (Omega^m - b_Omega - w3, v^m - b_v - w4)
            w3, w4 ~ N(0, sigma^2 I): process noise
    step    the system's exact step with that drive; the biases are constant states
    update  (R^m, p^m) = (R exp(w1), p + w2) from the system's ``measure``, compared through the
            system's ``measurement_residual``: (log(Rhat^T R^m), p^m - phat),
            w1, w2 ~ N(0, sigma^2 I)

The velocity readings serve the prediction only; using them in the update as well would count
their noise twice. The rotation residual ``log(Rhat^T R^m)`` is the noise ``w1`` itself to first
order (the noise is a right perturbation), and it is exact for any size of error, where the
difference of ``vec R`` would be a 9-vector of rank-3 covariance, curved away from the group.

:meth:`RigidBodyFilterModel.process_jacobians` and
:meth:`~RigidBodyFilterModel.measurement_jacobians` are the analytic multiplicative-EKF Jacobians
of this discrete model (exact, including the derivative of ``J_l(phi) v`` in ``phi``), used with
``ErrorStateEKF(model, jacobians="analytic")``; the tests check them against autograd and finite
differences. The filter asks for them through :meth:`~RigidBodyFilterModel.linearize_step`
(the step and ``F``, ``G`` from one ``exp(phi)``, ``J_l(phi)``),
:meth:`~RigidBodyFilterModel.linearize_measurement` and
:meth:`~RigidBodyFilterModel.linearize_reset`.

**The EKF as an estimator** (:class:`RigidBodyEKF`): the generic
:class:`manifold_nets.ekf.ErrorStateEKF` on that model, started at step 5 from a batch
estimate of the biases over the first 5 measurements (:func:`initialize_from_measurements`;
inside the 10 steps the paper's table skips), or from the prior at step 0.

**The complementary filter** (:class:`ComplementaryFilter`): the passive nonlinear complementary
filter with bias estimation of Mahony, Hamel and Pflimlin (IEEE TAC 2008, eq. 13 with the bias
law of Theorem 5.1), discretised with the exact step,

    Rhat^- = Rhat exp((Omega^m - bhat) dt),    omega = vex(P_a(Rhat^-^T R^m)),
    Rhat   = Rhat^- exp(k_P omega dt),         bhat <- bhat - k_I omega dt,

with ``P_a(M) = (M - M^T)/2``, and the same structure for the position with a body-frame bias
(``p^- = p + Rhat J_l v_hat dt``, ``e = p^m - p^-``, ``p = p^- + k_p e dt``,
``b_v <- b_v - k_b Rhat^T e dt``). Its four gains are chosen by :func:`tune_complementary_gains`,
a grid search on a validation set simulated in code (its own seed, never the inference set).

The code is in four modules, gathered here: :mod:`.filter_model` (the EKF's model and its
Jacobians), :mod:`.ekf_estimator` (the EKF as an estimator, its start and its tuning),
:mod:`.complementary` (the complementary filter and its gains) and :mod:`.filter_support`
(what they share).
"""

from __future__ import annotations

from .complementary import (  # noqa: F401  (_-names: importable here as they always were)
    _DEFAULT_GRID,
    ComplementaryFilter,
    ComplementaryGains,
    tune_complementary_gains,
)
from .ekf_estimator import (  # noqa: F401
    _EKF_GRID,
    _SO3,
    CHI2_99_6DOF,
    RigidBodyEKF,
    initialize_from_measurements,
    log,
    tune_ekf_noise,
)
from .filter_model import (  # noqa: F401
    RigidBodyFilterModel,
    _noise_param,
    _scaled_eye,
    jl_times_v_derivative,
)
from .filter_support import _check_system, _repeat  # noqa: F401

__all__ = [
    "ComplementaryFilter",
    "ComplementaryGains",
    "CHI2_99_6DOF",
    "RigidBodyEKF",
    "RigidBodyFilterModel",
    "initialize_from_measurements",
    "jl_times_v_derivative",
    "tune_complementary_gains",
    "tune_ekf_noise",
]
