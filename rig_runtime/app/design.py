"""Gain design of Sec. 5.2.3 for the configured plant (``rig tune --design``).

Uses the linear model and the loop matrices of ``rig_runtime.analysis`` (nothing duplicated).
Objective and constraints, in the paper's order:

1. inner PD: the largest K_P,psi and K_D,psi for which each term alone stays within the input
   criterion (``tuning.u_design_max`` at ``psi_design`` and ``psi_rate_design``; the per-term
   reading of docs/paper-notes.md §5): K_P,psi = u/psi, K_D,psi = u/psi_dot. As much stiffness
   and damping as the input bound allows; the eigenvalues of (15) are reported.
2. T_f,psi: the largest (most noise filtering) time constant for which the slowest eigenvalue
   of (16) stays within ``TF_SLOW_TOL`` of the slowest of (15) and every eigenvalue of (16) is
   stable; the noise gain K_D,psi/T_f,psi (A per rad of sensor noise at high frequency) is
   reported and must stay below ``NOISE_GAIN_MAX``.
3. outer PI: K_P,y within the lateral criterion (K_P,y · y_design <= psi_ref_design_max) and the
   integrator as strong as the constraints allow: the largest K_I,y with (17)'s eigenvalues
   real and max Re <= ``tuning.slowest_eig_min``, the complete loop (19) stable with its
   slowest eigenvalue no slower than ``SLOW_19`` and its complex poles damped at least
   ``ZETA_MIN``, and the same for the sampled loop as implemented; among those, the K_P,y with the largest K_I,y (ties: the smaller K_P,y).
4. the complete loop (19) and the sampled loop as implemented (h, Tustin) are checked stable.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from rig_runtime import analysis, coupled
from rig_runtime.config import PIPDGains, RigConfig

TF_SLOW_TOL = 0.03      # |λ_slow(16) − λ_slow(15)| <= 3 % of |λ_slow(15)|
NOISE_GAIN_MAX = 1000.0  # A/rad: K_D/T_f; 5 µrad of yaw noise -> at most 5 mA
SLOW_19 = -0.5          # 1/s: slowest eigenvalue of the complete loop (the paper's design has -0.5)
ZETA_MIN = 0.7          # damping ratio of any complex pole pair of (19)
KP_Y_GRID = 0.25        # rad/m
KI_Y_GRID = 0.25        # rad/(m s)


@dataclass(frozen=True)
class Design:
    gains: PIPDGains
    result: analysis.TuneResult       # the analysis of the proposed gains
    configured: analysis.TuneResult   # the analysis of the configured gains
    configured_gains: PIPDGains
    checks: dict
    noise_gain: float


def with_gains(cfg: RigConfig, g: PIPDGains) -> RigConfig:
    return replace(cfg, controller=replace(cfg.controller, pipd=g, law="pipd"))     # the design is a PI-PD's


def _slowest(ev) -> float:
    return float(np.max(np.real(ev)))


def _zeta_ok(ev) -> bool:
    for e in ev:
        if abs(e.imag) > 1e-9 and -e.real / abs(e) < ZETA_MIN:
            return False
    return True


def design_tf(cfg: RigConfig, kp: float, kd: float) -> float:
    base = PIPDGains(K_P_y=0.0, K_I_y=0.0, K_P_psi=kp, K_D_psi=kd, T_f_psi=1e-3)
    slow15 = _slowest(np.linalg.eigvals(analysis.inner_matrix(with_gains(cfg, base))))

    def ok(T: float) -> bool:
        ev = np.linalg.eigvals(analysis.inner_filtered_matrix(with_gains(cfg, replace(base, T_f_psi=T))))
        return np.all(ev.real < 0) and abs(_slowest(ev) - slow15) <= TF_SLOW_TOL * abs(slow15)
    lo, hi = max(kd / NOISE_GAIN_MAX, 1e-4), 2.0
    if not ok(lo):
        return lo
    while ok(hi) and hi < 100:
        hi *= 2
    for _ in range(60):
        mid = np.sqrt(lo * hi)
        lo, hi = (mid, hi) if ok(mid) else (lo, mid)
    return float(lo)


def design(cfg: RigConfig) -> Design:
    t = cfg.tuning
    kp = t.u_design_max / t.psi_design
    kd = t.u_design_max / t.psi_rate_design
    Tf = design_tf(cfg, kp, kd)
    kp_y_max = t.psi_ref_design_max / t.y_design
    best = None
    for kpy in np.arange(KP_Y_GRID, kp_y_max + 1e-9, KP_Y_GRID):
        for kiy in np.arange(KI_Y_GRID, 200.0, KI_Y_GRID):
            g = PIPDGains(K_P_y=float(kpy), K_I_y=float(kiy), K_P_psi=kp, K_D_psi=kd, T_f_psi=Tf)
            c = with_gains(cfg, g)
            outer = np.linalg.eigvals(analysis.outer_matrix(c))
            if np.any(np.abs(outer.imag) > 1e-9) or _slowest(outer) > t.slowest_eig_min:
                if np.any(np.abs(outer.imag) > 1e-9):
                    break            # larger K_I only makes the pair more complex
                continue
            cl = np.linalg.eigvals(analysis.closed_loop_matrix(c))
            if _slowest(cl) > SLOW_19 or not _zeta_ok(cl):
                continue
            if best is not None and kiy <= best.K_I_y + 1e-12:
                continue
            sl = analysis.sampled_closed_loop(c)
            if _slowest(sl) >= 0 or not _zeta_ok(sl):
                continue
            if best is None or kiy > best.K_I_y + 1e-12:
                best = g
    if best is None:
        raise ValueError("no outer gains satisfy the constraints of Sec. 5.2.3 for this plant")
    res = analysis.tune(with_gains(cfg, best))
    checks = dict(res.checks)
    checks["complete_loop_stable"] = {"value": _slowest(res.closed_loop), "limit": 0.0, "ok": _slowest(res.closed_loop) < 0}
    checks["sampled_loop_stable"] = {"value": _slowest(res.closed_loop_sampled), "limit": 0.0,
                                     "ok": _slowest(res.closed_loop_sampled) < 0}
    checks["noise_gain_A_per_rad"] = {"value": kd / Tf, "limit": NOISE_GAIN_MAX, "ok": kd / Tf <= NOISE_GAIN_MAX}
    return Design(best, res, analysis.tune(cfg), cfg.controller.pipd, checks, kd / Tf)


def to_json(d: Design) -> dict:
    g = d.gains
    return {"gains": {"K_P_y": g.K_P_y, "K_I_y": g.K_I_y, "K_P_psi": g.K_P_psi, "K_D_psi": g.K_D_psi, "T_f_psi": g.T_f_psi},
            "objective": OBJECTIVE,
            "eigenvalues": {k: analysis.pairs(getattr(d.result, k)) for k in
                            ("inner", "inner_filtered", "outer", "closed_loop", "closed_loop_sampled")},
            "configured": {"gains": _gains(d.configured_gains),
                           "eigenvalues": {k: analysis.pairs(getattr(d.configured, k)) for k in
                                           ("inner", "inner_filtered", "outer", "closed_loop", "closed_loop_sampled")}},
            "checks": d.checks, "ok": all(c["ok"] for c in d.checks.values())}


def _gains(g: PIPDGains) -> dict:
    out = {"K_P_y": g.K_P_y, "K_I_y": g.K_I_y, "K_P_psi": g.K_P_psi, "K_D_psi": g.K_D_psi, "T_f_psi": g.T_f_psi}
    return {**out, "D_sched": g.D_sched} if g.D_sched else out


def controller_yaml(cfg: RigConfig, g: PIPDGains) -> str:
    c = cfg.controller
    return ("# Gains designed by `rig tune --design` (Sec. 5.2.3, rig_runtime/app/design.py)\n"
            f"# for the plant of {cfg.source}\n"
            "controller:\n"
            f"  h: {c.h!r}\n  law: pipd\n  pipd:\n"
            f"    K_P_y: {g.K_P_y:.6g}\n    K_I_y: {g.K_I_y:.6g}\n    K_P_psi: {g.K_P_psi:.6g}\n"
            f"    K_D_psi: {g.K_D_psi:.6g}\n    T_f_psi: {g.T_f_psi:.6g}\n"
            f"  K_P: {c.K_P!r}\n  discretization: {c.discretization}\n" + _tuning_yaml(cfg, g))


def _tuning_yaml(cfg: RigConfig, g: PIPDGains) -> str:
    """The configured live-tuning bounds, carried over: the fragment replaces the whole
    ``controller:`` section, and without them no gain could be set live. A designed gain
    outside its bounds is marked (the bounds are the operator's choice, not redesigned)."""
    c = cfg.controller
    if not c.tuning:
        return ""
    lines = [f"  tuning:             # live-tuning bounds, as configured in {cfg.source}\n"]
    for name, (lo, hi) in c.tuning.items():
        v = getattr(g, name, None) if name != "K_P" else c.K_P
        note = f"  # the designed {v:.6g} lies outside" if v is not None and not lo <= v <= hi else ""
        lines.append(f"    {name}: [{lo!r}, {hi!r}]{note}\n")
    return "".join(lines)


OBJECTIVE = ("inner: largest K_P,psi, K_D,psi with each term <= u_design_max at psi_design / psi_rate_design; "
             f"T_f,psi: largest with the slowest eigenvalue of (16) within {TF_SLOW_TOL:.0%} of (15)'s and "
             f"K_D/T_f <= {NOISE_GAIN_MAX:g} A/rad; outer: largest K_I,y with K_P,y y_design <= psi_ref_design_max, "
             f"(17) real with max Re <= slowest_eig_min, (19) max Re <= {SLOW_19} and complex poles damped >= {ZETA_MIN}")


# --------------------------------------------------------------------------- the vehicle (issue 18)
@dataclass(frozen=True)
class VehicleDesign:
    gains: dict                       # carrier -> PIPDGains (every controlled carrier in contact)
    result: "coupled.CoupledResult"   # the coupled analysis of the proposal over the range
    configured: "coupled.CoupledResult"
    checks: dict


D_SCHED_VEHICLE = 2.0   # the vehicle's yaw loop scheduled on D̂ of (7) (control.PIPDLaw; docs/vehicle.md §5)
KI_Y_VEHICLE = tuple(float(x) for x in np.round(np.geomspace(0.05, 20.0, 28), 4))   # rad/(m s)


def vehicle_gains(cfg: RigConfig, kpy: float, kiy: float, inner: dict) -> dict:
    """Each controlled carrier's gains for the reference outer gains (kpy, kiy): its own inner
    PD (``inner``) and outer gains scaled by c̄_y,ref / c̄_y,c, so that every carrier's lateral
    loop gain c̄_y v_d K is the same (the carriers' conicities may differ)."""
    lay = coupled.layout(cfg)
    ref = cfg.plant.carrier(lay.controlled[-1]).c_y
    out = {}
    for c in lay.controlled:
        s = ref / cfg.plant.carrier(c).c_y
        out[c] = replace(inner[c], K_P_y=kpy * s, K_I_y=kiy * s)
    return out


def with_vehicle_gains(cfg: RigConfig, gains: dict) -> RigConfig:
    """``cfg`` with each carrier's own gains (``controller.front`` / ``rear``); pipd = the rear's
    (else the first's), for what reads the common gains."""
    pipd = gains.get("rear") or next(iter(gains.values()))
    return replace(cfg, controller=replace(cfg.controller, pipd=pipd, front=gains.get("front"),
                                           rear=gains.get("rear"), law="pipd"))   # the design is a PI-PD's


def design_vehicle(cfg: RigConfig) -> VehicleDesign:
    """The scheduled gains of every controlled carrier in contact (the leading one included),
    designed at v_design on the coupled loop (rig_runtime/coupled.py) and checked over the range.

    1. inner PD per carrier as Sec. 5.2.3 (``design``'s steps 1, 2 on that carrier's yaw
       parameters): K_P,psi, K_D,psi from the input criterion, T_f,psi by :func:`design_tf`;
       scheduled on the damping D̂ (``D_SCHED_VEHICLE``: the gate judges every D_min/D_max
       combination of a vehicle config, and a leading carrier at D_max needs it);
    2. outer PI: one loop gain for all carriers (:func:`vehicle_gains`); over K_P,y within the
       lateral criterion (largest carrier K_P,y · y_design <= psi_ref_design_max) and K_I,y on
       ``KI_Y_VEHICLE``, the pair whose coupled loop at v_design (continuous, D_min) decays
       fastest, with every complex pole damped >= ``ZETA_MIN`` and the sampled loop as
       implemented stable at ±v_design, the range's ends and ±v_min in the gate's damping
       cases (``coupled.damping_cases``);
    3. the coupled loop over the whole range: continuous stable and the gate passes."""
    t = cfg.tuning
    lay = coupled.layout(cfg)
    if not lay.controlled:
        raise ValueError("no controlled carrier in contact with the rollers: nothing to design")
    kp = t.u_design_max / t.psi_design
    kd = t.u_design_max / t.psi_rate_design
    inner = {}
    for c in lay.controlled:
        own = replace(cfg, plant=cfg.plant.carrier(c))
        inner[c] = PIPDGains(K_P_y=0.0, K_I_y=0.0, K_P_psi=kp, K_D_psi=kd, T_f_psi=design_tf(own, kp, kd),
                             D_sched=D_SCHED_VEHICLE)
    ref = cfg.plant.carrier(lay.controlled[-1]).c_y
    scale_max = max(ref / cfg.plant.carrier(c).c_y for c in lay.controlled)
    kp_y_max = t.psi_ref_design_max / t.y_design / scale_max
    vd = coupled.design_speed(cfg)
    s = cfg.controller.schedule
    # the gate's speeds that decide in practice: ±v_design, the range's ends, the band's edges
    speeds = [vd] if s is None else [v for v in dict.fromkeys((vd, -vd, *s.v_range, s.v_min, -s.v_min))
                                     if s.v_range[0] <= v <= s.v_range[1]]
    best, best_slow = None, 0.0
    for kpy in np.arange(KP_Y_GRID, kp_y_max + 1e-9, KP_Y_GRID):
        for kiy in KI_Y_VEHICLE:
            c = with_vehicle_gains(cfg, vehicle_gains(cfg, float(kpy), kiy, inner))
            ev = np.linalg.eigvals(coupled.continuous_matrix(c, vd, coupled.d_min(c, lay.carriers), lay))
            slow = _slowest(ev)
            if slow >= best_slow - 1e-9 or not _zeta_ok(ev):
                continue
            if all(coupled._radius(coupled.sampled_matrix(c, v, D, lay)) < 1.0
                   for v in speeds for D in coupled.damping_cases(c, v, lay)):
                best, best_slow = (float(kpy), kiy), slow
    if best is None:
        raise ValueError("no outer gains make the coupled loop stable at v_design in the gate's damping "
                         "cases within the criteria of Sec. 5.2.3")
    gains = vehicle_gains(cfg, *best, inner)
    prop = with_vehicle_gains(cfg, gains)
    res = coupled.analyse(prop)
    bad = coupled.instability(prop)
    slowest = max(_slowest(p.eigenvalues) for p in res.points)
    checks = {
        "coupled_continuous_stable_over_range": {"value": slowest, "limit": 0.0, "ok": slowest < 0},
        "coupled_sampled_gate_over_range": {"value": max(p.spectral_radius for p in res.points), "limit": 1.0,
                                            "ok": bad is None},
        "zeta_min_at_v_design": {"value": min(p.zeta_min for p in res.points if p.v == vd), "limit": ZETA_MIN,
                                 "ok": all(p.zeta_min >= ZETA_MIN - 1e-9 for p in res.points if p.v == vd)},
        "worst_case_psi_ref_rad": {"value": max(g.K_P_y for g in gains.values()) * t.y_design,
                                   "limit": t.psi_ref_design_max,
                                   "ok": max(g.K_P_y for g in gains.values()) * t.y_design
                                   <= t.psi_ref_design_max + 1e-12},
    }
    return VehicleDesign(gains, res, coupled.analyse(cfg), checks)


def vehicle_yaml(cfg: RigConfig, gains: dict) -> str:
    """A ``controller:`` fragment with the designed gains: ``pipd`` alone when every carrier's
    are equal, else ``pipd`` (the rear's) and ``front`` / ``rear``; the schedule, h, law, K_P,
    discretization and the live-tuning bounds carried over."""
    c = cfg.controller
    vals = list(gains.values())
    equal = all(_gains(g) == _gains(vals[0]) for g in vals)

    def block(name: str, g: PIPDGains) -> str:
        return (f"  {name}:\n    K_P_y: {g.K_P_y:.6g}\n    K_I_y: {g.K_I_y:.6g}\n    K_P_psi: {g.K_P_psi:.6g}\n"
                f"    K_D_psi: {g.K_D_psi:.6g}\n    T_f_psi: {g.T_f_psi:.6g}\n"
                + (f"    D_sched: {g.D_sched:.6g}\n" if g.D_sched else ""))
    text = ("# Gains designed by `rig tune --design` for the vehicle (coupled loop, rig_runtime/app/design.py)\n"
            f"# for the plant of {cfg.source}\ncontroller:\n  h: {c.h!r}\n  law: pipd\n")
    text += block("pipd", gains.get("rear") or vals[0])
    if not equal:
        for name, g in gains.items():
            text += block(name, g)
    s = c.schedule
    if s is not None:
        text += (f"  schedule:\n    v_design: {coupled.design_speed(cfg)!r}\n    v_min: {s.v_min!r}\n"
                 f"    v_range: [{s.v_range[0]!r}, {s.v_range[1]!r}]\n    hold_ramp_s: {s.hold_ramp_s!r}\n"
                 f"    v_filter_hz: {s.v_filter_hz!r}\n")
    text += f"  K_P: {c.K_P!r}\n  discretization: {c.discretization}\n"
    return text + _tuning_yaml(cfg, gains.get("rear") or vals[0])


def vehicle_json(d: VehicleDesign) -> dict:
    return {"gains": {c: _gains(g) for c, g in d.gains.items()},
            "objective": VEHICLE_OBJECTIVE,
            **coupled.to_json(d.result),
            "configured": coupled.to_json(d.configured),
            "checks": d.checks, "ok": all(c["ok"] for c in d.checks.values())}


VEHICLE_OBJECTIVE = ("per carrier: inner PD as Sec. 5.2.3 on its own yaw parameters; outer PI: one lateral loop gain "
                     "c_y v_d K for every carrier, the fastest-decaying coupled loop at v_design (continuous, D_min) "
                     f"with complex poles damped >= {ZETA_MIN} and the sampled loop stable at +-v_design, the range's ends "
                     "and +-v_min in the gate's damping cases; then checked over the schedule's range")
