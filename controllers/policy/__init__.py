"""Policy networks: SDPA actors (typed and slot variants), the MLP baseline, centralised critics.

Shapes: token observations (E, N, T = 2N+1, F = 4) with mask (E, N, T); flat observations
(E, N, 4N+2); actions (E, N, 2) [m/s^2]; values (E, N).
"""

from controllers.policy.actor import (
    MLPActor,
    SlotSDPAActor,
    TypedSDPAActor,
    build_actor,
    count_parameters,
    grow_slot_actor,
)
from controllers.policy.config import ActorConfig, CriticConfig, PolicyConfigError
from controllers.policy.critic import AttentionCritic, MLPCritic, build_critic, mix_values
from controllers.policy.layers import gaussian_entropy, gaussian_log_prob

__all__ = [
    "ActorConfig",
    "AttentionCritic",
    "CriticConfig",
    "MLPActor",
    "MLPCritic",
    "PolicyConfigError",
    "SlotSDPAActor",
    "TypedSDPAActor",
    "build_actor",
    "build_critic",
    "count_parameters",
    "gaussian_entropy",
    "gaussian_log_prob",
    "grow_slot_actor",
    "mix_values",
]
