"""MAPPO training of the formation policies: config, trainer, evaluation, checkpoints.

Entry points::

    train(MAPPOConfig(...), run_dir, resume=False) -> TrainResult   (converged_episode, ...)
    evaluate(actor, scenario, episodes=100, seed=0) -> EvalResult
    load_actor(checkpoint_path, num_robots=None) -> actor            (zero-shot on another N)
    converged_episode(episodes, success_rates, threshold=0.9)         (the convergence rule)
"""

from controllers.mappo.checkpoint import (
    CheckpointError,
    load_actor,
    load_checkpoint,
    save_checkpoint,
)
from controllers.mappo.config import MAPPOConfig, TrainConfigError
from controllers.mappo.evaluate import (
    ConvergenceTracker,
    EvalResult,
    converged_episode,
    evaluate,
    evaluation_due,
)
from controllers.mappo.losses import (
    ValueNormalizer,
    clipped_surrogate_loss,
    compute_gae,
    value_loss,
)
from controllers.mappo.trainer import MAPPOTrainer, TrainResult, train

__all__ = [
    "CheckpointError",
    "ConvergenceTracker",
    "EvalResult",
    "MAPPOConfig",
    "MAPPOTrainer",
    "TrainConfigError",
    "TrainResult",
    "ValueNormalizer",
    "clipped_surrogate_loss",
    "compute_gae",
    "converged_episode",
    "evaluate",
    "evaluation_due",
    "load_actor",
    "load_checkpoint",
    "save_checkpoint",
    "train",
    "value_loss",
]
