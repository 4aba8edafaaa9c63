"""The ``sim:`` section of a config: sensor models and initial state of the simulated rig."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal, Optional

from rig_runtime import schema
from rig_runtime.config import RigConfig
from rig_runtime.schema import check, nonneg, positive

from .miswire import Miswire


@dataclass(frozen=True, kw_only=True)
class SimConfig:
    laser_noise_m: float = check(nonneg, default=1.0e-6)      # ESTIMATE: optoNCDT 1420 repeatability ≈ 1–2 µm
    laser_latency_s: float = check(nonneg, default=0.0)
    laser_rate_hz: Optional[float] = check(positive, default=None)   # None: each laser's output_rate_hz
    encoder_noise_rad_s: float = check(nonneg, default=0.002)  # ESTIMATE: speed from encoder counts at 5 ms
    ft_noise_N: float = check(nonneg, default=0.2)            # ESTIMATE
    ft_rate_hz: Optional[float] = check(positive, default=None)      # None: devices.ft.poll_hz
    initial_y_mm: Optional[float] = None   # None: the plant's rest state for u = 0
    seed: int = 0
    wheel_dynamics: Literal["static", "dynamic"] = "static"   # relation (4), or the dynamic form (3)
    can_bus: Literal["lockstep", "virtual"] = "lockstep"      # python-can bus of the in-process sim
    # the lockstep simulator's laser and F/T wires: in-process byte pipes (rig_runtime/wires.py),
    # or the kernel's (pty pairs, Modbus TCP on 127.0.0.1) — the same bytes either way; `rig sim`
    # serves other processes and always uses the kernel's (docs/dry-run.md, "Wires")
    wires: Literal["memory", "kernel"] = "memory"
    # the rear carrier lifted off the rollers (scenario ``lifted_carrier: rear``, Sec. 4.3.2):
    # its contact-free damping and offset (Table 3, first row)
    lifted_D: float = check(positive, default=0.28)
    lifted_psi_off: float = 1.7e-3
    # what a miswired rig sends (sim_backend/miswire.py, docs/commissioning.md); None: wired as configured
    miswire: Optional[Miswire] = None
    # "commission": the simulated operator moves the vehicle by hand as `rig commission`'s
    # passive prompt asks, until the power stages are first on (sim_backend/hands.py)
    operator: Literal["none", "commission"] = "none"
    # with operator "commission": the power-on sessions the operator holds the carriers lifted
    # for (rig commission's lifted bumps: lifted-rear, lifted-front), from the first power-on
    operator_lifted_sessions: int = check(nonneg, default=2)


def sim_config(cfg: RigConfig) -> SimConfig:
    return schema.build(SimConfig, cfg.sim or {}, "sim", cfg.source)
