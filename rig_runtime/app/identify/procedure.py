"""The identification procedure in the paper's order, each step on its own experiment:

1. relation (4) on the open-loop steps: delta0, c11 (and the offset dw_off);
2. lateral (2b) on the open-loop steps, with delta0 from 1: l0, y_off;
3. free responses of the lifted carrier: omega0 (and the lifted D, psi_off);
4. long steps: K, psi_off from stationary values, D_min / D_max before / after 0.2 s, c_udot_max;
5. sines: K (linear), then K, psi_off, Bouc-Wen a, beta, gamma with the damping of 4;
   then, with both records, the joint refinement of the whole yaw model (``joint``: the
   hysteresis biases the linear damping fits of 4, and the sines alone barely see the
   saturation of the hysteresis);
6. verification on the held-out open-loop steps (not used by the yaw fits).

Steps whose experiment is missing are skipped and their parameters keep the configured
values (reported under ``skipped``). Each step's time is measured (``timing_s``).

``run`` identifies one carrier from its own experiments, starting from that carrier's
configured values (``Plant.carrier``); ``run_carriers`` groups the experiments by carrier
(the rear's from the paper's set-up at v > 0, the front's from the mirrored one at v < 0)
and runs the procedure once per carrier.
"""

from __future__ import annotations

import statistics
import time
from dataclasses import replace

from rig_runtime.config import CARRIERS, Plant as PlantParams
from rig_runtime.errors import ConfigError

from . import free_response, joint, lateral, sines, steps, verify, wheelspeed
from .experiments import SPEED_STEADY, Experiment
from .model import bouc_wen

SINE_TOL = 1e-3     # the sines' own fit only starts the joint refinement: a loose tolerance


def _param(fit_, name) -> dict:
    i = fit_.names.index(name)
    lo, hi = fit_.ci95[i]
    return {"value": float(fit_.values[i]), "ci95": [float(lo), float(hi)]}


def run_carriers(plant: PlantParams, exps: list[Experiment]) -> dict[str, dict]:
    """carrier -> ``run``'s result on that carrier's experiments (carriers in CARRIERS order),
    each from the carrier's configured values."""
    if not exps:
        raise ConfigError(None, "LOG", "at least one experiment log")
    return {c: run(plant.carrier(c), [e for e in exps if e.carrier == c])
            for c in CARRIERS if any(e.carrier == c for e in exps)}


def run(P: PlantParams, exps: list[Experiment]) -> dict:
    """One carrier's identification; ``P`` its configured values (start values and constants)."""
    if not exps:
        raise ConfigError(None, "LOG", "at least one experiment log")
    carriers = sorted({e.carrier for e in exps})
    if len(carriers) != 1:
        raise ValueError("experiments of one carrier at a time (got " + ", ".join(carriers) + ")")
    exps = [e if e.v is not None else replace(e, v=P.v) for e in exps]
    by = {k: [e for e in exps if e.kind == k] for k in ("free-response", "steps", "sine", "open-loop-steps")}
    params: dict[str, dict] = {}
    written: dict[str, tuple] = {}
    experiments: list[dict] = []
    timing: dict[str, float] = {}
    skipped: list[str] = []
    cur = P

    def put(name, fit_, step, key=None):
        params[key or name] = _param(fit_, name)
        written[key or name] = (params[key or name]["value"], fit_.rms, step)

    def exp_entry(kind, es, fits: dict, extra: dict | None = None):
        experiments.append({"kind": kind, "logs": [e.source for e in es],
                            "fits": {k: f.as_dict() for k, f in fits.items()}, **(extra or {})})

    # 1, 2: open-loop steps (Fig. 3 input)
    ol = by["open-loop-steps"]
    if ol:
        t0 = time.perf_counter()
        ws = wheelspeed.identify(cur, ol)
        put("delta0", ws, "relation (4)")
        put("c11", ws, "relation (4)")
        cur = replace(cur, delta0=ws.value("delta0"), c11=ws.value("c11"))
        timing["relation_4"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        lat = lateral.identify(cur, ol)
        eq = "lateral (2a)" if exps[0].carrier == "front" else "lateral (2b)"
        put("l0", lat, eq)
        put("y_off", lat, eq)
        cur = replace(cur, l0=lat.value("l0"), y_off=lat.value("y_off"))
        timing["lateral"] = time.perf_counter() - t0
        exp_entry("open-loop-steps", ol, {"relation_4": ws, "lateral": lat},
                  {"dw_off": _param(ws, "dw_off")})
    else:
        skipped += ["relation_4 (no open-loop-steps log)", "lateral (no open-loop-steps log)"]

    # 3: free response
    fr = by["free-response"]
    if fr:
        t0 = time.perf_counter()
        f, segs = free_response.identify(cur, fr)
        put("omega0", f, "free response")
        cur = replace(cur, omega0=f.value("omega0"))
        timing["free_response"] = time.perf_counter() - t0
        exp_entry("free-response", fr, {"free_response": f},
                  {"lifted": {"D": _param(f, "D"), "psi_off": _param(f, "psi_off")},
                   "releases": [{"log": s.exp.source, "t_s": float(s.exp.t[s.k0])} for s in segs]})
    else:
        skipped.append("free_response (no free-response log)")

    # 4: steps (linear, as the paper)
    st = by["steps"]
    sr = None
    if st:
        t0 = time.perf_counter()
        sr = steps.identify(cur, st)
        cur = replace(cur, D_min=sr.fast.value("D_min"), D_max=max(sr.tail.value("D_max"), sr.fast.value("D_min")),
                      c_udot_max=sr.law.value("c_udot_max"))
        timing["steps"] = time.perf_counter() - t0
    else:
        skipped.append("steps (no steps log)")

    # 5: sines
    sn = by["sine"]
    hy = lin = sine_fit = None
    if sn:
        t0 = time.perf_counter()
        lin = sines.identify_linear(cur, sn)
        timing["sines_linear"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        hy = sines.identify_hysteresis(cur, sn, lin.value("K"), tol=SINE_TOL if sr is not None else 1e-8)
        cur = _with_hysteresis(cur, hy)
        sine_fit = hy
        timing["sines_hysteresis"] = time.perf_counter() - t0
        if sr is not None:
            t0 = time.perf_counter()
            jf = joint.refine(cur, st, sn, sr.static.value("psi_off"))
            cur = replace(cur, K=jf.value("K"), psi_off=jf.value("psi_off"), D_min=jf.value("D_min"),
                          D_max=max(jf.value("D_max"), jf.value("D_min")), c_udot_max=jf.value("c_udot_max"),
                          bouc_wen=bouc_wen(jf.value("bouc_wen.a"), jf.value("bouc_wen.beta"),
                                            jf.value("bouc_wen.gamma")))
            hy = jf
            timing["joint_steps_sines"] = time.perf_counter() - t0
        step_name = "steps and sines jointly" if hy is not sine_fit else "sines, Bouc-Wen (8)/(9)"
        for n in ("K", "psi_off", "bouc_wen.a", "bouc_wen.beta", "bouc_wen.gamma"):
            put(n, hy, step_name)
        fits = {"linear": lin, "hysteresis": sine_fit}
        if hy is not sine_fit:
            fits["joint_steps_sines"] = hy
        exp_entry("sine", sn, fits, {"psi_off": _param(hy, "psi_off"), "K_linear": _param(lin, "K")})
    else:
        skipped.append("sines (no sine log)")

    if sr is not None:
        fits = {"tail": sr.tail, "static": sr.static, "fast": sr.fast, "law": sr.law}
        if hy is not None and hy is not sine_fit:
            for n in ("D_min", "D_max", "c_udot_max"):
                put(n, hy, "steps and sines jointly")
        else:
            put("D_min", sr.fast, "steps, first 0.2 s")
            put("D_max", sr.tail, "steps, tail")
            put("c_udot_max", sr.law, "steps, law (7)")
        exp_entry("steps", st, fits, {
            "K_stationary": _param(sr.static, "K"), "psi_off": _param(sr.static, "psi_off"),
            "psi_off_with_hysteresis": (_param(hy, "psi_off_steps") if hy is not None and hy is not sine_fit
                                        else None),
            "linear": {"D_min": _param(sr.fast, "D_min"), "D_max": _param(sr.tail, "D_max"),
                       "c_udot_max": _param(sr.law, "c_udot_max")}})

    # 6: verification
    verification = {}
    if ol:
        t0 = time.perf_counter()
        verification = {"experiment": "open-loop-steps", "logs": [e.source for e in ol],
                        "identified": [verify.errors(cur, e) for e in ol],
                        "configured": [verify.errors(P, e) for e in ol]}
        timing["verification"] = time.perf_counter() - t0
    speeds = distinct_speeds([float(e.v) for e in exps if e.kind != "free-response"])
    return {"carrier": carriers[0], "v": speeds, "parameters": params, "experiments": experiments,
            "verification": verification, "skipped": skipped, "timing_s": timing, "_plant": cur,
            "_written": written}


def _with_hysteresis(P: PlantParams, hy) -> PlantParams:
    return replace(P, K=hy.value("K"), psi_off=hy.value("psi_off"),
                   bouc_wen=bouc_wen(hy.value("bouc_wen.a"), hy.value("bouc_wen.beta"), hy.value("bouc_wen.gamma")))


def public(result: dict) -> dict:
    """The JSON object of ``rig identify --json`` (without the internal plant object)."""
    return {k: v for k, v in result.items() if not k.startswith("_")}


def identified_plant(result: dict) -> PlantParams:
    return result["_plant"]


__all__ = ["run", "run_carriers", "public", "identified_plant"]


def distinct_speeds(vs: list[float]) -> list[float]:
    """The speeds the experiments ran at, one per roller speed: measured speeds within
    ``SPEED_STEADY`` of each other (an experiment's own steadiness bound) are one speed,
    reported as their median."""
    out: list[list[float]] = []
    for v in sorted(vs):
        if out and abs(v - out[-1][0]) <= SPEED_STEADY * abs(out[-1][0]):
            out[-1].append(v)
        else:
            out.append([v])
    return [statistics.median(g) for g in out]
