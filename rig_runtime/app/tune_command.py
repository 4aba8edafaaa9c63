"""``rig tune``: the tuning analysis of Sec. 5.1/5.2.3 for the configured gains.

Exit 0 when every loop of (15), (16), (19) and the sampled loop as implemented is stable
and every design check holds; otherwise the analysis is printed all the same and the
program ends with exit 2 and one line naming what failed (``analysis.tune_failures``)."""

from __future__ import annotations

import argparse
import json

from .command import arg, command


def _fmt_ev(ev) -> str:
    out = []
    for e in ev:
        out.append(f"{e.real:9.3f}" + (f"{e.imag:+.3f}j" if abs(e.imag) > 1e-9 else ""))
    return "[" + ", ".join(s.strip() for s in out) + "]"


@command("tune", "eigenvalues and design checks of Sec. 5.1/5.2.3 for the configured gains")
@arg("--config", help="config file (default: the shipped simulated rig, configs/sim.yaml)")
@arg("--json", action="store_true", help="print one JSON object instead of a table")
@arg("--plot", metavar="DIR", help="write PNGs into DIR (needs matplotlib): the P-law root locus with gains and "
                                   "the stability boundary, slowest pole vs D, the eigenvalues with the paper's")
@arg("--design", action="store_true", help="design the PI-PD gains for the configured plant (Sec. 5.2.3)")
@arg("--write", metavar="CONTROLLER.yaml", help="with --design: write a controller: fragment with the proposal")
def cmd_tune(args: argparse.Namespace) -> int:
    from .. import analysis, config
    from . import preflight
    cfg = config.load(args.config)
    if args.design or args.write:
        from .design_command import run_design
        return run_design(cfg, args)
    if args.plot:
        preflight.check_plot_dir(args.plot, "--plot")
    try:
        r = analysis.tune(cfg)
    except (ArithmeticError, ValueError) as e:          # numpy's LinAlgError is a ValueError
        from ..errors import ConfigError
        raise ConfigError(cfg.source, "plant", "parameters the tuning analysis can compute with "
                          f"({type(e).__name__}: {str(e)[:80]})") from None
    failures = analysis.tune_failures(cfg, r)
    files = _plot(cfg, r, args.plot) if args.plot else []
    if args.json:
        out = analysis.to_json(r)
        out["ok"], out["failures"] = not failures, failures
        if files:
            out["plots"] = [str(f) for f in files]
        print(json.dumps(out))
        return _verdict(failures)
    P = analysis.PAPER
    rows = [
        ("inner loop (15)", r.inner, P["inner"]),
        ("inner loop with differentiator (16)", r.inner_filtered, P["inner_filtered"]),
        (f"outer loop (17) [{cfg.tuning.outer_lateral_form}]", r.outer, P["outer"]),
        ("complete closed loop (19)", r.closed_loop, P["closed_loop"]),
        ("sampled loop as implemented (h, Tustin)", r.closed_loop_sampled, None),
        ("open-loop poles of (10)", r.open_loop_poles, None),
    ]
    print(f"config: {cfg.source}")
    pr = r.params
    print(f"plant: omega0={pr['omega0']:g} 1/s  D={pr['D']:g}  K={pr['K']:g} rad/A  c_y={pr['c_y']:.5f}  "
          f"lateral pole (10)={-pr['a_lat']:.4f} 1/s, (17)={-pr['a_outer']:.4f} 1/s")
    g = cfg.controller.pipd
    print(f"gains: K_P,y={g.K_P_y:g} K_I,y={g.K_I_y:g} K_P,psi={g.K_P_psi:g} K_D,psi={g.K_D_psi:g} T_f,psi={g.T_f_psi:g} s\n")
    w = max(len(n) for n, _, _ in rows)
    print(f"{'eigenvalues (1/s)':<{w}}  {'computed':<50} paper")
    for name, ev, paper in rows:
        print(f"{name:<{w}}  {_fmt_ev(ev):<50} {paper if paper else ''}")
    print(f"\nP control (Sec. 5.1): stability boundary K_P = {r.stability_boundary_kp:.0f} A/m (paper: 18605)")
    print("\ndesign checks (Sec. 5.2.3):")
    for k, c in r.checks.items():
        print(f"  {'ok  ' if c['ok'] else 'FAIL'} {k:<28} {c['value']:.4g} (limit {c['limit']:g})")
    if files:
        print("\nplots: " + ", ".join(str(f) for f in files))
    print("\n" + ("FAIL: " + "; ".join(failures) if failures else "ok: every loop stable, every design check holds"))
    return _verdict(failures)


def _plot(cfg, r, out_dir) -> list:
    """Root locus with gain labels and the stability boundary, slowest pole vs D, and the
    eigenvalue map with the paper's values overlaid (rig_runtime/app/figures.py)."""
    from .. import analysis
    from . import figures
    return figures.write_all(figures.tune_figures(cfg, r, analysis.PAPER), out_dir)


def _verdict(failures: list[str]) -> int:
    if failures:
        from ..errors import RigError
        raise RigError(f"{len(failures)} check(s) fail: " + "; ".join(failures))
    return 0
