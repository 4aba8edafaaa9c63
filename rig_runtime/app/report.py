"""``--report DIR``: the figures of ``rig log plot`` (rig_runtime/app/figures.py, the same
code) and a short Markdown summary of a run (needs matplotlib, the ``plot`` extra)."""

from __future__ import annotations

from pathlib import Path

from . import figures, runlog


def write_report(log: Path, out_dir, scenario, summary: dict) -> list[Path]:
    run = runlog.load(log)
    ol = scenario.open_loop.carrier if scenario is not None and scenario.open_loop is not None else None
    name = scenario.name if scenario else "run"
    files = figures.write_all(figures.log_figures(run, ol, title=f"{name}: y, ψ, Δω, u (Figs. 15/16 style)"), out_dir)
    out = Path(out_dir)
    md = out / "summary.md"
    wire = summary["max_abs_wire_current_A"]
    lines = [f"# Dry run: {name}", "",
             f"- final state: **{summary['final_state']}**, cycles: {summary['cycles']}",
             f"- max |u| (differential current per carrier): {summary['max_abs_current_A']:.3f} A; "
             f"max |i| per wheel (wire current): {wire:.3f} A",
             f"- log: `{summary['log']}`", ""]
    if run.faults():
        lines += ["## Faults", "", "| t (s, run time) | device | check | value | limit | message |", "|---|---|---|---|---|---|"]
        for f in run.faults():
            lines.append(f"| {f.t_run:+.3f} | {f.device} | {f.check} | {f.value:.6g} | {f.limit:.6g} | {f.message} |")
        lines.append("")
    if summary.get("steps"):
        lines += ["## Steps", "", "| t0 (s) | from (mm) | to (mm) | rise (s) | overshoot (%) | settling (s) | steady-state error (mm) |",
                  "|---|---|---|---|---|---|---|"]
        fmt = lambda v, f: format(v, f) if v is not None else "–"  # noqa: E731
        for s in summary["steps"]:
            lines.append(f"| {s['t0']:.1f} | {s['from_mm']:+.2f} | {s['to_mm']:+.2f} | {fmt(s['rise_time_s'], '.2f')} | "
                         f"{fmt(s['overshoot_pct'], '.1f')} | {fmt(s['settling_time_s'], '.2f')} | {fmt(s['steady_state_error_mm'], '+.4f')} |")
        lines.append("")
    lines += ["Plots: " + ", ".join(f"`{p.name}`" for p in files), ""]
    md.write_text("\n".join(lines))
    files.append(md)
    return files
