"""Safety layer: FCL collision geometry, braking-distance barrier QP (OSQP), one-tick post-check.

The default path is the fused one (:mod:`controllers.safety.fused`: closed-form rows and sweep
check in one vectorised pass, FCL's swept capsule near contact); ``SafetyConfig(geometry="fcl")``
is the reference path on the FCL scene, with the same answers.

Entry point: :class:`SafetyFilter` ``(scenario).filter(pos (N, 2), vel (N, 2), a_nom (N, 2))``
-> :class:`SafetyResult` with ``a_safe`` (N, 2) [m/s^2] and a :class:`SafetyStatus`.
"""

from controllers.safety.barrier import BarrierTerms, SafetyConfig, SafetyConfigError, barrier_terms
from controllers.safety.barrier_qp import SafetyFilter, SafetyResult, SafetyStatus
from controllers.safety.fused import FusedScene, FusedTerms
from controllers.safety.geometry import CollisionScene, SceneDistances, analytic_distances
from controllers.safety.postcheck import SweepChecker, braking_acceleration, predict_step

__all__ = [
    "BarrierTerms", "CollisionScene", "FusedScene", "FusedTerms", "SafetyConfig", "SafetyConfigError",
    "SafetyFilter", "SafetyResult", "SafetyStatus", "SceneDistances", "SweepChecker", "analytic_distances",
    "barrier_terms", "braking_acceleration", "predict_step",
]
