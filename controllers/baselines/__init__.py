"""The paper's baselines on our task: MADDPG and GASIL-MADDPG from TorchRL's pieces
(:mod:`.maddpg`, :mod:`.gasil`) and Deep Dyna-Q (:mod:`.ddq`), run by one off-policy loop
(:mod:`.offpolicy`) with SDPA-MAPPO's reward, evaluation and convergence rule."""

from controllers.baselines.ddq import DDQConfig, train_ddq
from controllers.baselines.maddpg import MADDPGConfig, MADDPGConfigError, train_maddpg
from controllers.baselines.offpolicy import BaselineConfigError, BaselineResult

BASELINES = {"maddpg": (MADDPGConfig, train_maddpg), "gasil-maddpg": (MADDPGConfig, train_maddpg),
             "ddq": (DDQConfig, train_ddq)}
"""``formation train --algo NAME`` -> (its config class, its train function)."""

__all__ = ["BASELINES", "BaselineConfigError", "BaselineResult", "DDQConfig", "MADDPGConfig", "MADDPGConfigError",
           "train_ddq", "train_maddpg"]
