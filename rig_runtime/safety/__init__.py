"""Safety supervisor, split by job (docs/safety.md, "The supervisor's modules"):

- ``types``: the value types (State, Fault, Finding, Sample, Converters, Pose, Step, Channel);
- ``rules``: every rule, written once, each returning a Finding or None;
- ``supervisor``: the state machine and the per-cycle check sequence;
- ``reconfig``: isolate / absorb / readmit keyed by device (degraded mode);
- ``limiter``: the output limiter.

The names other modules import are re-exported here."""

from .limiter import Limiter
from .reconfig import Isolation, Reconfiguration
from .rules import (ARM_RULES, CHANNEL_RULES, DEGRADED_STOP_RULES, DRIVE_LOSS_RULES, ISOLATING_RULES,
                    OBSERVER_RULES, OUTPUT_RULES, POSE_RULES, SPEED_RULES, SYSTEM_RULES, System, bus_error, corrupt_link, degraded_covariance,
                    innovation, innovation_dw, innovation_lateral, innovation_yaw, invalid, jump, not_finite,
                    out_of_range, speed_disagree, speed_range, stale, stuck)
from .supervisor import Supervisor
from .types import BAD_UNIT, Channel, Converters, Fault, Finding, Pose, Sample, State, Step

__all__ = [
    "ARM_RULES", "BAD_UNIT", "CHANNEL_RULES", "DRIVE_LOSS_RULES", "Channel", "Converters", "DEGRADED_STOP_RULES",
    "Fault", "Finding",
    "ISOLATING_RULES", "Isolation", "Limiter", "OBSERVER_RULES", "OUTPUT_RULES", "POSE_RULES", "Pose",
    "Reconfiguration", "SPEED_RULES", "SYSTEM_RULES", "Sample", "State", "Step", "Supervisor", "System", "bus_error",
    "corrupt_link", "degraded_covariance", "innovation", "innovation_dw", "innovation_lateral", "innovation_yaw",
    "invalid", "jump", "not_finite", "out_of_range", "speed_disagree", "speed_range", "stale", "stuck"]
