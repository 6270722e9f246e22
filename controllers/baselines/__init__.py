"""The paper's baselines on our task, built from TorchRL's pieces: MADDPG (:mod:`.maddpg`)."""

from controllers.baselines.maddpg import MADDPGConfig, MADDPGConfigError, MADDPGResult, train_maddpg

__all__ = ["MADDPGConfig", "MADDPGConfigError", "MADDPGResult", "train_maddpg"]
