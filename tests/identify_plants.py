"""Simulated identification experiments for the recovery tests and the benchmark: plants
whose parameters differ from the shipped ones by up to ±30 % (offsets with other signs), the
same for a front carrier of its own in the mirrored set-up (``front_plants``), and short
versions of the ident-* scenarios (short enough to be cheap, long enough for the tests'
tolerances: docs/identification.md §5), for either carrier (``short_text``).

``record_and_identify`` records every plant's short set and identifies it in worker
processes (two: the machine's cores), each scenario one job, each plant's identification a
job submitted once its four logs are there: the tests share one experiment set per plant.
"""

from __future__ import annotations

import contextlib
import io
import json
import multiprocessing
import os
from concurrent.futures import ProcessPoolExecutor, as_completed
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
duration_s: 9
open_loop: {carrier: rear, steps: [[0, 0.0]]}
disturbances:
  - {kind: constant, carrier: rear, t: 4, duration_s: 1.5, M_z: -2.5}
""",
    "steps": """name: t-steps
experiment: steps
duration_s: 85
open_loop: {carrier: rear, steps: [[0, 0.0], [5, 0.8], [45, -0.8]]}
""",
    "sine": """name: t-sine
experiment: sine
duration_s: 105
open_loop:
  carrier: rear
  sine: [{amplitude_A: 0.6, freq_mhz: 9.6, t0: 0}]
""",
    "open-loop-steps": """name: t-open-loop-steps
experiment: open-loop-steps
duration_s: 70
open_loop: {carrier: rear, steps: [[0, 0.0], [5, 0.4], [17, 0.8], [29, 0.0], [41, -0.8], [53, 0.0]]}
""",
}
FRONT_SPEED = -1.0      # the mirrored set-up: the front carrier trails at v < 0


def short_text(kind: str, carrier: str = "rear") -> str:
    """The short scenario of ``kind`` for ``carrier``: the rear's in the paper's set-up, the
    front's the mirror (every ``rear`` key the front's, rollers at ``FRONT_SPEED``)."""
    text = SHORT[kind]
    if carrier == "front":
        text = text.replace("carrier: rear", "carrier: front").replace("name: t-", "name: t-front-")
        text += f"speed: [{{t: 0, v: {FRONT_SPEED}}}]\n"
    return text


def short_scenario(tmp: Path, kind: str, carrier: str = "rear"):
    """The short scenario of ``kind`` for ``carrier``, written to ``tmp`` and loaded (each
    kind its own file: the experiments of one plant are recorded in parallel)."""
    p = tmp / f"t-{carrier}-{kind}.yaml"
    p.write_text(short_text(kind, carrier))
    return load_scenario(p)


def standard_scenarios(carrier: str = "rear") -> dict:
    """The shipped experiment scenarios of ``carrier`` (the front's: ident-front-*)."""
    names = (("free-response", "ident-free-response"), ("steps", "ident-steps"), ("sine", "ident-sine"),
             ("open-loop-steps", "open-loop-steps"))
    if carrier == "front":
        names = tuple((k, "ident-front-" + n.removeprefix("ident-")) for k, n in names)
    return {k: load_scenario(SCENARIO_DIR / f"{n}.yaml") for k, n in names}


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


def front_plants() -> dict:
    """name -> (RigConfig of the mirrored set-up, truth dict of the lifted front): the shipped
    rear (common values) and a front carrier of its own (``plant.front``) differing from it by
    up to ±30 % (offsets of other signs), as plants A and B differ from the shipped one;
    configs/sim-ident-front.yaml's set-up (front on the rollers, rear out of contact, front lane)."""
    from rig_runtime.config import CarrierPlant
    cfg = config.load(config.CONFIG_DIR / "sim-ident-front.yaml")
    out = {}
    for name, (variant, lifted) in plants().items():
        if name == "shipped":
            continue
        V = variant.plant
        own = CarrierPlant(**{k: getattr(V, k) for k in ("omega0", "K", "D_min", "D_max", "c_udot_max", "delta0",
                                                         "l0", "y_off", "psi_off", "c11", "bouc_wen")})
        out[f"front-{name}"] = (replace(cfg, plant=replace(cfg.plant, front=own), sim={**(cfg.sim or {}), **lifted}),
                                lifted)
    return out


def all_plants() -> dict:
    """name -> (RigConfig, lifted truth, carrier): the rear's plants and the front's."""
    return {**{n: (*v, "rear") for n, v in plants().items()}, **{n: (*v, "front") for n, v in front_plants().items()}}


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


# ------------------------------------------------------------------ shared runs for the tests
def _record_one(name: str, kind: str, tmp: str) -> str:
    cfg, _, carrier = all_plants()[name]
    sc = short_scenario(Path(tmp), kind, carrier)       # only its own file: the other kinds' workers write theirs
    (log,) = record(cfg, {kind: sc}, Path(tmp), prefix=name)
    return str(log)


def _identify(name: str, logs: list[str], tmp: str) -> dict:
    """``rig identify --json`` on the logs (for the shipped plant also --write and --report);
    the JSON object and what the command wrote. The fits run serially here (a pool worker
    cannot fork the Jacobian workers; the numbers do not depend on it)."""
    from rig_runtime.app.cli import main
    from rig_runtime.app.identify import fit
    fit.WORKERS = 1
    argv = ["identify", *logs, "--json"]
    if name.startswith("front-"):
        argv += ["--config", str(config.CONFIG_DIR / "sim-ident-front.yaml")]
    extra = {}
    if name == "shipped":
        extra = {"write": str(Path(tmp) / "plant-identified.yaml"), "report": str(Path(tmp) / "report")}
        argv += ["--write", extra["write"], "--report", extra["report"]]
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        code = main(argv)
    if code == 0:
        (Path(tmp) / "identify.json").write_text(out.getvalue())      # kept with the logs, for a look afterwards
    return {"code": code, "json": json.loads(out.getvalue()) if code == 0 else None, "stderr": err.getvalue(),
            "logs": logs, **extra}


def record_and_identify(names, tmp: Path, workers: int = 2) -> dict:
    """name -> ``_identify``'s dict, every plant's short set recorded (seed 0) in ``tmp/name``."""
    kinds = list(SHORT)
    dirs = {n: tmp / n for n in names}
    for d in dirs.values():
        d.mkdir(parents=True, exist_ok=True)
    # A process pool that notices a dead worker (BrokenProcessPool) instead of waiting for its
    # lost task forever, as multiprocessing.Pool does.
    with ProcessPoolExecutor(max(1, min(workers, os.cpu_count() or 1)),
                             mp_context=multiprocessing.get_context("spawn")) as pool:
        recs = {n: [pool.submit(_record_one, n, k, str(dirs[n])) for k in kinds] for n in names}
        plant_of = {f: n for n, fs in recs.items() for f in fs}
        idents = {}
        for f in as_completed(plant_of):
            n = plant_of[f]
            f.result()                                  # a failed recording fails here, named
            if n not in idents and all(r.done() for r in recs[n]):
                idents[n] = pool.submit(_identify, n, [r.result() for r in recs[n]], str(dirs[n]))
        return {n: r.result() for n, r in idents.items()}
