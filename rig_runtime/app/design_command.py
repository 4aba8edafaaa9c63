"""Output of ``rig tune --design`` (the branch of ``rig tune`` in rig_runtime/app/tune_command.py)."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from rig_runtime.config import RigConfig
from rig_runtime.errors import ConfigError

from . import design as _design

PAPER_GAINS = {"K_P_y": 3.0, "K_I_y": 9.0, "K_P_psi": 40.0, "K_D_psi": 5.0}
PAPER_NOTES_T_F = 0.034144   # docs/paper-notes.md §2 (the printed 0.3 does not give its eigenvalues)


def _ev(ev) -> str:
    return "[" + ", ".join(f"{e.real:.2f}" + (f"{e.imag:+.2f}j" if abs(e.imag) > 1e-9 else "") for e in ev) + "]"


def _write_new(path: str, text: str) -> None:
    """``--write``: the designed controller fragment into a new file (never overwritten)."""
    p = Path(path)
    if p.exists():
        raise ConfigError(str(p), "", "a new file (refusing to overwrite)")
    p.write_text(text)


def run_design(cfg: RigConfig, args: argparse.Namespace) -> int:
    if not args.design:
        raise ConfigError(None, "--write", "--design as well (--write writes the designed gains)")
    from rig_runtime import coupled
    if coupled.applies(cfg):
        return run_vehicle_design(cfg, args)
    try:
        d = _design.design(cfg)
    except ValueError as e:
        raise ConfigError(cfg.source, "plant", str(e)) from None
    if args.write:
        _write_new(args.write, _design.controller_yaml(cfg, d.gains))
    g, c = d.gains, cfg.controller.pipd
    if args.json:
        out = _design.to_json(d)
        out["paper"] = {**PAPER_GAINS, "T_f_psi": PAPER_NOTES_T_F}
        if args.write:
            out["written"] = args.write
        print(json.dumps(out))
        return 0
    print(f"config: {cfg.source}")
    print(f"objective: {_design.OBJECTIVE}\n")
    print(f"{'gain':<10}{'proposed':>12}{'configured':>12}{'paper':>12}")
    paper = {**PAPER_GAINS, "T_f_psi": PAPER_NOTES_T_F}
    for k in ("K_P_y", "K_I_y", "K_P_psi", "K_D_psi", "T_f_psi"):
        print(f"{k:<10}{getattr(g, k):>12.4g}{getattr(c, k):>12.4g}{paper[k]:>12.4g}")
    print("\neigenvalues (1/s)                 proposed / configured")
    for name, key in (("inner (15)", "inner"), ("inner + differentiator (16)", "inner_filtered"),
                      ("outer (17)", "outer"), ("complete loop (19)", "closed_loop"),
                      ("sampled loop (h, Tustin)", "closed_loop_sampled")):
        print(f"  {name:<30} {_ev(getattr(d.result, key))}\n  {'':<30} {_ev(getattr(d.configured, key))}")
    print("\nchecks of the proposal:")
    for k, v in d.checks.items():
        print(f"  {'ok  ' if v['ok'] else 'FAIL'} {k:<30} {v['value']:.4g} (limit {v['limit']:g})")
    print(f"\nvs the paper: K_P,psi, K_D,psi as printed (40, 5); outer K_P,y {g.K_P_y:g} / K_I,y {g.K_I_y:g} vs 3 / 9 "
          f"(the paper's criteria allow K_P,y up to {cfg.tuning.psi_ref_design_max / cfg.tuning.y_design:g}; the paper "
          f"stops well inside them); T_f,psi {g.T_f_psi:.4g} s vs {PAPER_NOTES_T_F} s (docs/paper-notes.md)")
    if args.write:
        print(f"controller fragment: {args.write}")
    return 0 if all(v["ok"] for v in d.checks.values()) else 3


def run_vehicle_design(cfg: RigConfig, args: argparse.Namespace) -> int:
    """``rig tune --design`` on a vehicle config: every controlled carrier's scheduled gains
    on the coupled loop (design.design_vehicle); exit 0 if every check holds, else 3."""
    try:
        d = _design.design_vehicle(cfg)
    except ValueError as e:
        raise ConfigError(cfg.source, "controller", str(e)) from None
    if args.write:
        _write_new(args.write, _design.vehicle_yaml(cfg, d.gains))
    ok = all(v["ok"] for v in d.checks.values())
    if args.json:
        out = _design.vehicle_json(d)
        if args.write:
            out["written"] = args.write
        print(json.dumps(out))
        return 0 if ok else 3
    print(f"config: {cfg.source}")
    print(f"objective: {_design.VEHICLE_OBJECTIVE}\n")
    names = list(d.gains)
    print(f"{'gain':<10}" + "".join(f"{c + ' (proposed)':>18}{c + ' (configured)':>20}" for c in names))
    for k in ("K_P_y", "K_I_y", "K_P_psi", "K_D_psi", "T_f_psi"):
        print(f"{k:<10}" + "".join(f"{getattr(d.gains[c], k):>18.4g}{getattr(cfg.controller.gains(c), k):>20.4g}"
                                   for c in names))
    print("\ncoupled loop, proposed / configured: least-damped pole (1/s, D_min) and sampled |z| (gate cases)")
    for p, q in zip(d.result.points, d.configured.points):
        if p.v in (d.result.v_design, -d.result.v_design) or p is d.result.points[0] or p is d.result.points[-1]:
            print(f"  v = {p.v:+6.3f}  {_ev([p.least_damped])} |z| {p.spectral_radius:.6f}   /   "
                  f"{_ev([q.least_damped])} |z| {q.spectral_radius:.6f}")
    print("\nchecks of the proposal:")
    for k, v in d.checks.items():
        print(f"  {'ok  ' if v['ok'] else 'FAIL'} {k:<38} {v['value']:.4g} (limit {v['limit']:g})")
    if args.write:
        print(f"controller fragment: {args.write}")
    return 0 if ok else 3
