"""What a control tick is configured with (:class:`StackConfig`) and what it returns
(:class:`TickResult`, :class:`PolicyStatus`); the tick itself is :mod:`stack.pipeline`."""

from __future__ import annotations

from dataclasses import dataclass, field
from enum import StrEnum

import numpy as np

from controllers.docking import DockingConfig
from controllers.mec import MecConfig, MecStatus
from controllers.safety import SafetyConfig, SafetyResult, SafetyStatus
from controllers.safety.latency import LatencyConfig, Prediction
from sim.scenario import clip_norm

FILTER_TOLERANCE = 0.05
"""[m/s^2] a filter answer this close to the (norm-clipped) policy command counts as unchanged."""


def filter_changed(a_nom: np.ndarray, a_safe: np.ndarray, accel_limit: float,
                   tolerance: float = FILTER_TOLERANCE) -> np.ndarray:
    """(...,) bool: the filter's answer ``a_safe`` (..., 2) [m/s^2] differs from the policy's
    ``a_nom``, clipped to ``accel_limit`` in norm, by more than ``tolerance`` (non-finite
    values read as 0)."""
    asked = clip_norm(np.nan_to_num(np.asarray(a_nom, dtype=np.float64)), accel_limit)
    return np.linalg.norm(np.nan_to_num(np.asarray(a_safe, dtype=np.float64)) - asked, axis=-1) > tolerance


class PolicyStatus(StrEnum):
    """What the observe + policy stages produced."""

    OK = "ok"
    INVALID_STATE = "invalid_state"            # the fleet state was not finite: braking
    NON_FINITE_OUTPUT = "non_finite_output"    # the policy returned NaN/inf: braking


@dataclass
class TickResult:
    """One control tick for N robots.

    Attributes:
        a_nom: (N, 2) policy command [m/s^2] (braking where the policy failed), finite.
        a_safe: (N, 2) command after the safety filter (``a_nom`` clipped to the actuator limit
            when the filter is off) [m/s^2].
        a_cmd: (N, 2) command to send [m/s^2], finite, norm <= accel_limit.
        policy_status: see :class:`PolicyStatus`.
        safety_status: the filter's :class:`SafetyStatus` (None: filter off).
        mec_status: the compensator's :class:`MecStatus` (None: MEC off).
        safety_reason: the filter's reason text ("" when unchanged or intervened).
        brake_reason: why a stage output was replaced by braking ("" when none was).
        stale: (N,) bool, robots treated as obstacles this tick (state older than the latency
            config's ``stale_after_s``, or not finite): they were sent the braking law.
        docking: (N,) bool, robots whose ``a_nom`` is the docking law (:mod:`controllers.docking`).
        detour: (N,) bool, robots whose ``a_nom`` follows a detour (:mod:`controllers.detour`).
        timings_ns: nanoseconds per stage: observe, policy, safety, mec, total.
    """

    a_nom: np.ndarray
    a_safe: np.ndarray
    a_cmd: np.ndarray
    policy_status: PolicyStatus
    safety_status: SafetyStatus | None
    mec_status: MecStatus | None
    safety_reason: str = ""
    brake_reason: str = ""
    stale: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=bool))
    docking: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=bool))
    detour: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=bool))
    timings_ns: dict[str, int] = field(default_factory=dict)

    @property
    def intervened(self) -> bool:
        """The safety filter changed the nominal command (any status but UNCHANGED)."""
        return self.safety_status is not None and self.safety_status is not SafetyStatus.UNCHANGED

    @property
    def infeasible(self) -> bool:
        """The barrier QP was infeasible and the slack QP (or braking) answered."""
        return self.safety_status is SafetyStatus.SLACK or "OSQP" in self.safety_reason

    @property
    def fallback(self) -> bool:
        """Some robot got a braking command from the filter's fallback or post-check."""
        return self.safety_status is SafetyStatus.FALLBACK_BRAKE

    @property
    def braking(self) -> bool:
        """A non-finite value was replaced by braking somewhere in the tick."""
        return self.policy_status is not PolicyStatus.OK or bool(self.brake_reason)

    def events(self) -> dict[str, bool]:
        return {"intervened": self.intervened, "infeasible": self.infeasible,
                "fallback": self.fallback, "braking": self.braking}


@dataclass(frozen=True)
class StackConfig:
    """Which stages run, and their settings.

    Attributes:
        safety: run the safety filter.
        mec: run the model error compensator.
        safety_config: settings of the filter (default: the fused fast path, see
            :mod:`controllers.safety.fused`; ``geometry="fcl"`` gives the same answers slower).
        mec_config: settings of the compensator.
        latency: what the filter assumes of the link (:mod:`controllers.safety.latency`; the
            default covers 150 ms of command delay; ``LatencyConfig(enabled=False)`` judges the
            measured state as it is).
        estimated_velocity: policy and filter read the compensator's velocity estimate (its
            Kalman observer, noise-adaptive, :mod:`controllers.mec`) instead of the measured
            velocity (only with ``mec``; stale rows keep their measurement).
        estimated_position: policy and filter read the position estimator's positions
            (:mod:`controllers.position_estimator`: a Kalman filter that measures each robot's
            position noise and passes exact measurements through unchanged); the filter grows
            each disc by the estimate's standard deviation.
        docking: the terminal mode that takes a robot near its free matched target onto it
            (:mod:`controllers.docking`) and the detours of robots held away from every target
            (:mod:`controllers.detour`), before the filter; ``DockingConfig(enabled=False)``
            leaves the policy's command as it is.
        all_tracker_discs: every disc a tracker reports enters the filter's QP; False (default):
            only those that can bind a listening robot this tick
            (:mod:`controllers.safety.relevance`; the same answer, a smaller QP).
        policy_kernel: an eager typed actor given in memory (a checkpoint's) runs by the
            compiled kernel of ``.npz`` files (:class:`stack.policy_io.ModuleKernel`: the same
            maths to 1e-5, its current weights, ~4x faster); False runs the module as given.
    """

    safety: bool = True
    mec: bool = True
    safety_config: SafetyConfig = field(default_factory=SafetyConfig)
    mec_config: MecConfig = field(default_factory=MecConfig)
    latency: LatencyConfig = field(default_factory=LatencyConfig)
    estimated_velocity: bool = True
    estimated_position: bool = True
    docking: DockingConfig = field(default_factory=DockingConfig)
    all_tracker_discs: bool = False
    policy_kernel: bool = True


@dataclass
class SafeStage:
    """The safety stage of one tick: the filter's result over M >= N robots (silent ones after
    the N commanded, then the extra discs of silent robots at rest, :meth:`Prediction.with_covers`);
    ``ids`` names the robots, the N commanded and the silent ones."""

    result: SafetyResult
    prediction: Prediction | None
    size: int
    ids: tuple[str, ...]

    def full(self, rows: np.ndarray) -> np.ndarray:
        """(M, 2): the N commanded rows, then the rest of the filter's (its answer, 0)."""
        if len(rows) == self.size:
            return rows
        return np.vstack([rows, self.result.a_safe[len(rows):]])


__all__ = ["FILTER_TOLERANCE", "PolicyStatus", "SafeStage", "StackConfig", "TickResult", "filter_changed"]
