"""Safety layer: FCL collision geometry, braking-distance barrier QP (OSQP), one-tick post-check.

Entry point: :class:`SafetyFilter` ``(scenario).filter(pos (N, 2), vel (N, 2), a_nom (N, 2))``
-> :class:`SafetyResult` with ``a_safe`` (N, 2) [m/s^2] and a :class:`SafetyStatus`.
"""

from controllers.safety.barrier import BarrierTerms, SafetyConfig, SafetyConfigError, barrier_terms
from controllers.safety.barrier_qp import SafetyFilter, SafetyResult, SafetyStatus
from controllers.safety.geometry import CollisionScene, SceneDistances, analytic_distances
from controllers.safety.postcheck import SweepChecker, braking_acceleration, predict_step

__all__ = [
    "BarrierTerms", "CollisionScene", "SafetyConfig", "SafetyConfigError", "SafetyFilter",
    "SafetyResult", "SafetyStatus", "SceneDistances", "SweepChecker", "analytic_distances",
    "barrier_terms", "braking_acceleration", "predict_step",
]
