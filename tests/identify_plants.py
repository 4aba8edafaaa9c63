"""Simulated identification experiments for the recovery tests and the benchmark: plants
whose parameters differ from the shipped ones by up to ±30 % (offsets with other signs),
and short versions of the ident-* scenarios (the shortest that still identify)."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

from rig_runtime import config
from rig_runtime.config import BoucWen
from rig_runtime.scenario import load_scenario, SCENARIO_DIR

SHORT = {
    "free-response": """name: t-free-response
experiment: free-response
lifted_carrier: rear
initial_psi_mrad: 8.0
duration_s: 14
open_loop: {carrier: rear, steps: [[0, 0.0]]}
disturbances:
  - {kind: constant, carrier: rear, t: 4, duration_s: 1.5, M_z: -2.5}
  - {kind: constant, carrier: rear, t: 9, duration_s: 1.5, M_z: 2.0}
""",
    "steps": """name: t-steps
experiment: steps
duration_s: 125
open_loop: {carrier: rear, steps: [[0, 0.0], [5, 0.8], [65, -0.8]]}
""",
    "sine": """name: t-sine
experiment: sine
duration_s: 210
open_loop:
  carrier: rear
  sine: [{amplitude_A: 0.6, freq_mhz: 4.8, t0: 0}]
""",
    "open-loop-steps": """name: t-open-loop-steps
experiment: open-loop-steps
duration_s: 150
open_loop: {carrier: rear, steps: [[0, 0.0], [10, 0.4], [40, 0.8], [70, 0.0], [100, -0.8], [130, 0.0]]}
""",
}


def short_scenarios(tmp: Path) -> dict:
    out = {}
    for kind, text in SHORT.items():
        p = tmp / f"t-{kind}.yaml"
        p.write_text(text)
        out[kind] = load_scenario(p)
    return out


def standard_scenarios() -> dict:
    return {k: load_scenario(SCENARIO_DIR / f"{n}.yaml") for k, n in
            (("free-response", "ident-free-response"), ("steps", "ident-steps"), ("sine", "ident-sine"),
             ("open-loop-steps", "open-loop-steps"))}


def plants() -> dict:
    """name -> (RigConfig of the simulated truth, truth dict incl. the lifted carrier)."""
    cfg = config.load()
    P = cfg.plant
    bw = P.bouc_wen
    out = {"shipped": (cfg, {"lifted_D": 0.28, "lifted_psi_off": 1.7e-3})}
    variants = {
        "A": dict(omega0=P.omega0 * 1.2, K=P.K * 0.8, D_min=P.D_min * 1.25, D_max=P.D_max * 0.75,
                  c_udot_max=P.c_udot_max * 1.3, delta0=P.delta0 * 1.25, l0=P.l0 * 0.8, y_off=0.5e-3,
                  psi_off=1.0e-3, c11=P.c11 * 0.8,
                  bouc_wen=BoucWen(a=0.4, A=1.0, beta=bw.beta * 1.2, gamma=bw.gamma * 1.2, n=1)),
        "B": dict(omega0=P.omega0 * 0.75, K=P.K * 1.15, D_min=P.D_min * 0.75, D_max=P.D_max * 1.3,
                  c_udot_max=P.c_udot_max * 0.75, delta0=P.delta0 * 0.8, l0=P.l0 * 1.1, y_off=-0.4e-3,
                  psi_off=-2.0e-3, c11=P.c11 * 1.3,
                  bouc_wen=BoucWen(a=0.55, A=1.0, beta=bw.beta * 0.8, gamma=bw.gamma * 0.8, n=1)),
    }
    lifted = {"A": {"lifted_D": 0.35, "lifted_psi_off": -1.0e-3}, "B": {"lifted_D": 0.22, "lifted_psi_off": 2.2e-3}}
    for name, kw in variants.items():
        c = replace(cfg, plant=replace(P, **kw), sim={**(cfg.sim or {}), **lifted[name]})
        out[name] = (c, lifted[name])
    return out


def record(cfg, scenarios: dict, tmp: Path, seed: int = 0, prefix: str = "") -> list[Path]:
    """Run every scenario in lockstep on ``cfg``'s simulated plant; the logs' paths."""
    from rig_runtime.app.dryrun import run_lockstep
    logs = []
    for kind, sc in scenarios.items():
        log = tmp / f"{prefix}{sc.name}-{seed}.h5"
        summary, code = run_lockstep(cfg, sc, log, seed=seed)
        assert code == 0 and summary["final_state"] == "IDLE", (kind, summary["faults"])
        logs.append(log)
    return logs
