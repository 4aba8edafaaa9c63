"""``--report DIR``: PNG plots in the style of the paper's Figs. 15–18 and a short
Markdown summary of a run (needs matplotlib, the ``plot`` extra)."""

from __future__ import annotations

from pathlib import Path


from ..export import read_log
from .plotting import pyplot




def write_report(log: Path, out_dir, scenario, summary: dict) -> list[Path]:
    plt = pyplot()
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    d = read_log(log)
    c = d["columns"]
    run = c["t_run"] > 0
    t = c["t_run"][run]
    files: list[Path] = []
    carrier = "rear" if "rear_u_lim" in c else "front"
    u = c[f"{carrier}_u_lim"][run]

    fig, ax = plt.subplots(4, 1, figsize=(8, 9), sharex=True)
    ax[0].plot(t, c["y_ref"][run] * 1e3, "k--", lw=1, label="y_ref")
    ax[0].plot(t, c["y_r"][run] * 1e3, color="tab:green", lw=1, label="y (rear)")
    ax[0].set_ylabel("y (mm)"); ax[0].legend(loc="best", fontsize=8)
    ax[1].plot(t, c["psi_ar"][run] * 1e3, color="tab:green", lw=1)
    ax[1].set_ylabel("ψ (mrad)")
    ax[2].plot(t, c["dw_r"][run], color="tab:green", lw=0.6)
    ax[2].set_ylabel("Δω (rad/s)")
    ax[3].plot(t, u, color="tab:green", lw=1)
    ax[3].set_ylabel("u (A)"); ax[3].set_xlabel("t (s)")
    for a in ax:
        a.grid(alpha=0.3)
    fig.suptitle(f"{scenario.name if scenario else 'run'}: lateral displacement, yaw angle, Δω, input (Figs. 15/16 style)")
    fig.tight_layout()
    files.append(out / "response.png"); fig.savefig(files[-1], dpi=110); plt.close(fig)

    if scenario is not None and scenario.disturbances:
        ft = [k for k in ("ft_rr_fy", "ft_rr_mz") if k in c]
        fig, ax = plt.subplots(2, 1, figsize=(8, 6), sharex=True)
        for k in ft:
            ax[0].plot(t, c[k][run], lw=1, label=k)
        ax[0].set_ylabel("F (N) / M (N m)"); ax[0].legend(fontsize=8); ax[0].set_title("right force–torque sensor (Fig. 17 style)")
        ax[1].plot(t, c["y_r"][run] * 1e3, color="tab:green", lw=1)
        ax[1].set_ylabel("y (mm)"); ax[1].set_xlabel("t (s)"); ax[1].set_title("lateral displacement (Fig. 18 style)")
        for a in ax:
            a.grid(alpha=0.3)
        fig.tight_layout()
        files.append(out / "disturbances.png"); fig.savefig(files[-1], dpi=110); plt.close(fig)

    if scenario is not None and scenario.open_loop is not None:
        fig, ax = plt.subplots(figsize=(6, 5))
        ax.plot(u, c["psi_ar"][run] * 1e3, lw=0.8)
        ax.set_xlabel("Δu (A)"); ax.set_ylabel("ψ (mrad)"); ax.grid(alpha=0.3)
        ax.set_title("yaw angle over input (Fig. 9 style)")
        fig.tight_layout()
        files.append(out / "psi_over_u.png"); fig.savefig(files[-1], dpi=110); plt.close(fig)

    md = out / "summary.md"
    lines = [f"# Dry run: {scenario.name if scenario else 'run'}", "",
             f"- final state: **{summary['final_state']}**, cycles: {summary['cycles']}, "
             f"max |u|: {summary['max_abs_current_A']:.3f} A",
             f"- log: `{summary['log']}`", ""]
    if summary.get("faults"):
        lines += ["## Faults", "", "| t (s) | device | check | value | limit | message |", "|---|---|---|---|---|---|"]
        for f in summary["faults"]:
            lines.append(f"| {f['t']:.3f} | {f['device']} | {f['check']} | {f['value']} | {f['limit']} | {f['message']} |")
        lines.append("")
    if summary.get("steps"):
        lines += ["## Steps", "", "| t0 (s) | from (mm) | to (mm) | rise (s) | overshoot (%) | settling (s) | steady-state error (mm) |",
                  "|---|---|---|---|---|---|---|"]
        fmt = lambda v, f: format(v, f) if v is not None else "–"
        for s in summary["steps"]:
            lines.append(f"| {s['t0']:.1f} | {s['from_mm']:+.2f} | {s['to_mm']:+.2f} | {fmt(s['rise_time_s'], '.2f')} | "
                         f"{fmt(s['overshoot_pct'], '.1f')} | {fmt(s['settling_time_s'], '.2f')} | {fmt(s['steady_state_error_mm'], '+.4f')} |")
        lines.append("")
    lines += ["Plots: " + ", ".join(f"`{p.name}`" for p in files), ""]
    md.write_text("\n".join(lines))
    files.append(md)
    return files
