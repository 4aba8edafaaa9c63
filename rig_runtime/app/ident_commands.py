"""``rig identify`` (registered with the CLI on import): the paper's identification (Sec. 4)
from recorded experiments; docs/identification.md."""

from __future__ import annotations

import argparse
import json

from .command import arg, command


def _fmt(v: float) -> str:
    return f"{v:.6g}"


@command("identify", "identify the plant parameters (paper Sec. 4) from experiment logs, per carrier")
@arg("--config", help="config file whose plant gives start values and fixed constants (default: configs/sim.yaml)")
@arg("logs", nargs="+", metavar="LOG", help="run logs (.h5) or CSV files of identification experiments")
@arg("--carrier", choices=("front", "rear"),
     help="take every log as this carrier's (default: each log's own carrier, from the log)")
@arg("--json", action="store_true", help="print one JSON object")
@arg("--write", metavar="PLANT.yaml", help="write a plant: fragment with the identified values (new file)")
@arg("--report", metavar="DIR", help="write plots (measured, configured model, identified model) into DIR")
def cmd_identify(args: argparse.Namespace) -> int:
    from rig_runtime import config
    from rig_runtime.errors import ConfigError

    from .identify import plantfile, procedure
    from .identify.experiments import load_experiment
    from pathlib import Path
    cfg = config.load(args.config)
    if args.write and Path(args.write).exists():     # before minutes of fitting, not after
        raise ConfigError(args.write, "", "a new file (refusing to overwrite an existing plant file)")
    exps = [load_experiment(p, args.carrier) for p in args.logs]
    try:
        results = procedure.run_carriers(cfg.plant, exps)
    except ValueError as e:
        raise ConfigError(None, "experiments", str(e)) from None
    identified = {c: r["_written"] for c, r in results.items()}
    _, _, marks = plantfile.plant_sections(cfg.plant, identified)
    out = {"parameters": {**{k: {**results["rear"]["parameters"][k], "carrier": "rear"} for k in marks[""]},
                          **{f"front.{k}": {**results["front"]["parameters"][k], "carrier": "front"}
                             for k in marks["front"]}},
           "carriers": {c: procedure.public(r) for c, r in results.items()}}
    if args.write:
        plantfile.write(args.write, plantfile.render_carriers(cfg.plant, identified, [e.source for e in exps]))
        out["written"] = args.write
    if args.report:
        from .identify.report import write_report
        out["report"] = []
        for c, r in results.items():
            d = Path(args.report) if len(results) == 1 else Path(args.report) / c
            mine = [e for e in exps if e.carrier == c]
            out["report"] += [str(p) for p in write_report(cfg.plant.carrier(c), procedure.identified_plant(r),
                                                            mine, r, d)]
    if args.json:
        print(json.dumps(out))
        return 0
    print(f"config: {cfg.source}")
    for c, r in out["carriers"].items():
        _print_carrier(cfg, c, r, [e for e in exps if e.carrier == c])
    if args.write:
        print(f"\nplant fragment: {args.write}")
    if args.report:
        print("report: " + ", ".join(out["report"]))
    return 0


def _print_carrier(cfg, carrier: str, out: dict, exps) -> None:
    conf_plant = cfg.plant.carrier(carrier)
    speeds = ", ".join(f"{v:+.3g}" for v in out["v"]) or "-"
    print(f"\n== {carrier} carrier (roller speed {speeds} m/s)")
    print("experiments: " + ", ".join(f"{e.name} ({e.kind})" for e in exps))
    print(f"\n{'parameter':<16}{'identified':>14}  {'95 % interval':<30}{'configured':>12}")
    for name, p in out["parameters"].items():
        conf = conf_plant
        for part in name.split("."):
            conf = getattr(conf, part, None) if conf is not None else None
        lo, hi = p["ci95"]
        print(f"{name:<16}{_fmt(p['value']):>14}  [{_fmt(lo)}, {_fmt(hi)}]".ljust(62) + f"{_fmt(conf) if conf is not None else '-':>12}")
    for ex in out["experiments"]:
        extra = []
        if "psi_off" in ex and ex["psi_off"]:
            extra.append(f"psi_off {_fmt(ex['psi_off']['value'])} rad")
        if "lifted" in ex:
            extra.append(f"lifted D {_fmt(ex['lifted']['D']['value'])}, psi_off {_fmt(ex['lifted']['psi_off']['value'])} rad")
        if "K_stationary" in ex:
            extra.append(f"K from stationary values {_fmt(ex['K_stationary']['value'])} rad/A")
        if ex.get("psi_off_with_hysteresis"):
            extra.append(f"psi_off with the hysteresis (joint fit) {_fmt(ex['psi_off_with_hysteresis']['value'])} rad")
        if "K_linear" in ex:
            extra.append(f"K of the linear fit {_fmt(ex['K_linear']['value'])} rad/A")
        if "linear" in ex:
            lin = ex["linear"]
            extra.append("linear damping fits D_min {} D_max {} c_udot_max {}".format(
                *(_fmt(lin[k]["value"]) for k in ("D_min", "D_max", "c_udot_max"))))
        print(f"\n{ex['kind']}: " + "; ".join(extra))
        for fname, f in ex["fits"].items():
            flags = ", ".join(f"{c['a']}~{c['b']} ({c['correlation']:+.3f})" for c in f["poorly_identifiable"])
            print(f"  {fname:<12} residual RMS {f['residual_rms']:.3g}" + (f"   poorly identifiable apart: {flags}" if flags else ""))
    v = out["verification"]
    if v:
        for ident, conf in zip(v["identified"], v["configured"]):
            print(f"\nverification (open-loop steps, held out): yaw RMS error identified {ident['psi_rms_rad']:.3g} rad "
                  f"(configured {conf['psi_rms_rad']:.3g}), max {ident['psi_max_abs_rad']:.3g} rad; "
                  f"y RMS {ident['y_rms_m']:.3g} m (configured {conf['y_rms_m']:.3g})")
    for s in out["skipped"]:
        print(f"skipped: {s}")
    print("\ntime per step (s): " + ", ".join(f"{k} {t:.2f}" for k, t in out["timing_s"].items()))
