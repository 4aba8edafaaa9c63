"""The application's figures, one function each, returning a matplotlib ``Figure`` (tests
inspect its artists; :func:`save` writes and closes it). ``rig log plot``, ``rig log
compare``, ``rig dry-run --report`` and ``rig tune --plot`` all draw with these.

Run figures (Figs. 15–18 style) are over run time (s since RUNNING began) and carry:
a dotted vertical line at every state change (labelled with the new state on the top axes),
a red vertical line at every fault (labelled ``device check``), dashed ±u_max, ±y_max, ±ψ_max
lines from the config stored in the log (in view when the signal comes within half of the
limit, else noted in the corner), and every carrier in use (front blue, rear green).
Artists that tests look for carry a ``gid``: ``state:<NAME>``, ``fault:<device>:<check>``,
``limit:+u_max`` … , ``y:<carrier>``, ``u:<carrier>``; the observer figure ``y_hat:<carrier>``,
``y_true:<carrier>`` (a dry run's simulated truth), ``err:<carrier>``, ``T_<m>:<carrier>`` and
``degraded:<carrier>`` (the shaded DEGRADED intervals); the control law's figure
``<signal>:<carrier>`` (one panel per signal the law declares, the log's ``law_signals``).
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Optional

import numpy as np

from ..logformat import display_unit, law_signals
from .plotting import pyplot
from .runlog import CARRIER_COLUMNS, RunLog, degraded_intervals

CARRIER_COLOR = {"front": "tab:blue", "rear": "tab:green"}
STATE_COLOR = {"IDLE": "0.4", "ARMED": "tab:orange", "RUNNING": "tab:blue", "STOPPING": "tab:purple",
               "FAULT": "tab:red"}
DPI = 110


def save(fig, path: Path) -> Path:
    """Write ``fig`` as PNG and close it."""
    plt = pyplot()
    try:
        fig.savefig(path, dpi=DPI)
    finally:
        plt.close(fig)
    return Path(path)


# ------------------------------------------------------------------ markers shared by run figures
def _markers(ax, run: RunLog, label: bool) -> None:
    """State changes and faults as vertical lines; with ``label`` their names along the top
    (changes closer than 2 % of the run's span share one label, ``ARMED→RUNNING``)."""
    import matplotlib.transforms as mtransforms
    tr = mtransforms.blended_transform_factory(ax.transData, ax.transAxes)
    changes = run.state_changes()
    for t, _, new in changes:
        ax.axvline(t, color=STATE_COLOR.get(new, "0.4"), ls=":", lw=0.9, gid=f"state:{new}")
    if label and changes:
        t_rel = run.t_rel
        near = 0.02 * (float(t_rel[-1] - t_rel[0]) if len(t_rel) > 1 else 1.0)
        groups: list[list] = []
        for t, _, new in changes:
            if groups and t - groups[-1][0] <= near:
                groups[-1][1].append(new)
            else:
                groups.append([t, [new]])
        for t, names in groups:
            ax.text(t, 1.01, "→".join(names), transform=tr, rotation=90, va="bottom", ha="center", fontsize=6,
                    color=STATE_COLOR.get(names[-1], "0.4"), gid="state-label:" + "→".join(names))
    for e in run.faults():
        ax.axvline(e.t_run, color="red", lw=1.3, gid=f"fault:{e.device}:{e.check}")
        if label:
            ax.text(e.t_run, 0.5, f"{e.device} {e.check} ", transform=tr, va="center", ha="right", fontsize=7,
                    color="red", gid=f"fault-label:{e.device}:{e.check}",
                    bbox={"facecolor": "white", "edgecolor": "none", "alpha": 0.8, "pad": 1})


def _limit(ax, value: Optional[float], scale: float, name: str, unit: str = "") -> None:
    """Dashed ±limit lines (``value`` in SI, drawn times ``scale``). Call after the data is
    plotted: while the data stays below half the limit the axes keep the data's scale (the
    lines lie outside the view) and a note in the corner gives the limit, so that a small
    response stays readable; closer to the limit both are in view."""
    if value is None:
        return
    data = [np.asarray(l.get_ydata(), float) for l in ax.get_lines()
            if not (l.get_gid() or "").startswith(("state:", "fault:", "limit:"))]
    data = np.concatenate([d[np.isfinite(d)] for d in data]) if data else np.array([])
    lo, hi = (float(data.min()), float(data.max())) if len(data) else (0.0, 0.0)
    v = value * scale
    for sign in (1, -1):
        ax.axhline(sign * v, color="0.25", ls="--", lw=0.8,
                   gid=f"limit:{'+' if sign > 0 else '-'}{name}",
                   label=f"±{name}" if sign > 0 else None)
    if max(abs(lo), abs(hi)) < 0.5 * v:
        pad = max(0.1 * (hi - lo), 0.02 * v)
        ax.set_ylim(lo - pad, hi + pad)
        ax.text(0.995, 0.98, f"±{name} = {v:g} {unit} (beyond this scale)", transform=ax.transAxes, ha="right",
                va="top", fontsize=7, color="0.25", gid=f"limit-note:{name}")


def _finish(fig, axes, xlabel: str = "run time t (s) [0 = RUNNING began]") -> None:
    for a in axes:
        a.grid(alpha=0.3)
    axes[-1].set_xlabel(xlabel)
    fig.tight_layout()


def _ft_sensors(run: RunLog, carriers: list[str]) -> list[str]:
    """F/T sensor names (``ft_rr``) with data, of the given carriers (``ft_r*`` is rear)."""
    out = []
    for c in run.columns:
        m = re.fullmatch(r"(ft_(\w+))_fy", c)
        if m and np.any(np.isfinite(run.columns[c])):
            side = m.group(2)[:1]
            if {"f": "front", "r": "rear"}.get(side) in carriers:
                out.append(m.group(1))
    return out


# ------------------------------------------------------------------ run figures
def response(run: RunLog, title: str = ""):
    """Figs. 15/16 style: lateral displacement with the reference, yaw angle, Δω and the
    differential current u of every carrier in use, with limits, states and faults."""
    plt = pyplot()
    c, t, lim = run.columns, run.t_rel, run.limits
    carriers = run.carriers_in_use
    fig, ax = plt.subplots(4, 1, figsize=(9, 10), sharex=True)
    if "y_ref" in c:
        ax[0].plot(t, c["y_ref"] * 1e3, "k--", lw=1, label="y_ref", gid="y_ref")
    for k in carriers:
        cc, col = CARRIER_COLUMNS[k], CARRIER_COLOR[k]
        for a, key, scale, name in ((ax[0], "y", 1e3, "y"), (ax[1], "psi", 1e3, "ψ"), (ax[2], "dw", 1.0, "Δω")):
            if cc[key] in c:
                a.plot(t, c[cc[key]] * scale, color=col, lw=0.6 if key == "dw" else 1,
                       label=f"{name} {k}" + (" (carrier to frame)" if key == "psi" else ""), gid=f"{key}:{k}")
        if run.has_u(k):
            ax[3].plot(t, run.u(k), color=col, lw=1, label=f"u {k} (applied)", gid=f"u:{k}")
        if f"{k}_u_cmd" in c:
            ax[3].plot(t, c[f"{k}_u_cmd"], color=col, lw=0.7, ls="--", alpha=0.7, label=f"u {k} (controller)",
                       gid=f"u_cmd:{k}")
    _limit(ax[0], lim.get("y_max"), 1e3, "y_max", "mm")
    _limit(ax[1], lim.get("psi_max"), 1e3, "psi_max", "mrad")
    _limit(ax[3], lim.get("u_max"), 1.0, "u_max", "A")
    ax[0].set_ylabel("lateral displacement y (mm)")
    ax[1].set_ylabel("yaw angle ψ (mrad)")
    ax[2].set_ylabel("Δω = ω_left − ω_right (rad/s)")
    ax[3].set_ylabel("differential current u (A)")
    _time_panels(fig, ax, run, title or f"{run.path.name}: y, ψ, Δω, u (Figs. 15/16 style)", ncol=3)
    return fig


def _time_panels(fig, ax, run: RunLog, title: str, ncol: int) -> None:
    """State and fault markers on every panel (labelled on the first), legends, the title."""
    for i, a in enumerate(ax):
        _markers(a, run, label=i == 0)
        if a.get_legend_handles_labels()[0]:
            a.legend(loc="upper left", fontsize=7, ncol=ncol)
    fig.suptitle(title, fontsize=10)
    _finish(fig, ax)


def forces(run: RunLog, title: str = ""):
    """Figs. 17/18 style: lateral force F_y and yaw moment M_z of the F/T sensors of the
    carriers in use (each on its own axes), and the lateral displacement (scaled to the data)."""
    plt = pyplot()
    c, t = run.columns, run.t_rel
    carriers = run.carriers_in_use
    sensors = _ft_sensors(run, carriers)
    fig, ax = plt.subplots(3, 1, figsize=(9, 8), sharex=True)
    styles = ["-", "--", "-.", ":"]
    for i, s in enumerate(sensors):
        ax[0].plot(t, c[f"{s}_fy"], lw=1, ls=styles[i % 4], label=f"{s} F_y", gid=f"fy:{s}")
        ax[1].plot(t, c[f"{s}_mz"], lw=1, ls=styles[i % 4], label=f"{s} M_z", gid=f"mz:{s}")
    for k in (k for k in carriers if CARRIER_COLUMNS[k]["y"] in c):
        ax[2].plot(t, c[CARRIER_COLUMNS[k]["y"]] * 1e3, color=CARRIER_COLOR[k], lw=1, label=f"y {k}", gid=f"y:{k}")
    # no ±y_max here: the response figure has it, this panel is scaled to the disturbance response
    ax[0].set_ylabel("lateral force F_y (N)")
    ax[1].set_ylabel("yaw moment M_z (N m)")
    ax[2].set_ylabel("lateral displacement y (mm)")
    _time_panels(fig, ax, run, title or f"{run.path.name}: force–torque sensors (Fig. 17 style) and y (Fig. 18 style)", ncol=4)
    return fig


def psi_over_u(run: RunLog, carrier: str, title: str = ""):
    """Fig. 9 style: yaw angle over the differential current of an open-loop carrier (RUNNING only)."""
    plt = pyplot()
    c = run.columns
    on = c["state"] == 2.0
    fig, ax = plt.subplots(figsize=(6, 5))
    ax.plot(run.u(carrier)[on], c[CARRIER_COLUMNS[carrier]["psi"]][on] * 1e3, lw=0.8,
            color=CARRIER_COLOR[carrier], gid=f"psi_u:{carrier}")
    ax.set_xlabel(f"differential current u {carrier} (A)")
    ax.set_ylabel(f"yaw angle ψ {carrier} (mrad)")
    ax.grid(alpha=0.3)
    ax.set_title(title or "yaw angle over input (Fig. 9 style)", fontsize=10)
    fig.tight_layout()
    return fig


def has_forces(run: RunLog) -> bool:
    return bool(_ft_sensors(run, run.carriers_in_use))


def compare(runs: list[RunLog], labels: list[str]):
    """Overlay of several runs over run time: y with each reference, ψ and u of every
    carrier in use in any of them (log colours: C0, C1, …; front dashed, rear solid)."""
    plt = pyplot()
    fig, ax = plt.subplots(3, 1, figsize=(9, 8), sharex=True)
    carriers = [k for k in ("front", "rear") if any(k in r.carriers_in_use for r in runs)]
    ls = {"front": "--", "rear": "-"}
    for i, (r, name) in enumerate(zip(runs, labels)):
        col, c, t = f"C{i}", r.columns, r.t_rel
        if "y_ref" in c:
            ax[0].plot(t, c["y_ref"] * 1e3, color=col, lw=0.8, ls=":", label=f"{name}: y_ref", gid=f"y_ref:{i}")
        for k in carriers:
            cc = CARRIER_COLUMNS[k]
            if cc["y"] in c:
                ax[0].plot(t, c[cc["y"]] * 1e3, color=col, ls=ls[k], lw=1, label=f"{name}: y {k}", gid=f"y:{k}:{i}")
            if cc["psi"] in c:
                ax[1].plot(t, c[cc["psi"]] * 1e3, color=col, ls=ls[k], lw=1, label=f"{name}: ψ {k}", gid=f"psi:{k}:{i}")
            if r.has_u(k):
                ax[2].plot(t, r.u(k), color=col, ls=ls[k], lw=1, label=f"{name}: u {k}", gid=f"u:{k}:{i}")
        for e in r.faults():
            for a in ax:
                a.axvline(e.t_run, color=col, lw=1.3, alpha=0.8, gid=f"fault:{e.device}:{e.check}:{i}")
    lim = runs[0].limits
    _limit(ax[0], lim.get("y_max"), 1e3, "y_max", "mm")
    _limit(ax[2], lim.get("u_max"), 1.0, "u_max", "A")
    ax[0].set_ylabel("lateral displacement y (mm)")
    ax[1].set_ylabel("yaw angle ψ (mrad)")
    ax[2].set_ylabel("differential current u (A)")
    for a in ax:
        if a.get_legend_handles_labels()[0]:
            a.legend(loc="upper left", fontsize=7, ncol=2)
    fig.suptitle("comparison: " + " vs ".join(labels), fontsize=10)
    _finish(fig, ax)
    return fig


def observed(run: RunLog) -> list[str]:
    """The carriers with an observer in the log (``{carrier}_obs_y_hat`` columns)."""
    return [k for k in CARRIER_COLUMNS if f"{k}_obs_y_hat" in run.columns]


def observer(run: RunLog, truth: Optional[dict] = None, title: str = ""):
    """The observer of every observed carrier (docs/observer.md): the measured y, the estimate
    ŷ and — when the log has the dry run's simulated truth — the true y; the estimate's error
    against the truth (else against the measurement) with the ±σ_y band the observer reports;
    the innovation statistics with the
    threshold ``limits.innovation_chi2``. The DEGRADED intervals are shaded on every panel."""
    plt = pyplot()
    c, t = run.columns, run.t_rel
    truth = truth or {}
    fig, ax = plt.subplots(3, 1, figsize=(9, 9), sharex=True)
    for k in observed(run):
        cc, col = CARRIER_COLUMNS[k], CARRIER_COLOR[k]
        y_hat = c[f"{k}_obs_y_hat"]
        if cc["y"] in c:
            ax[0].plot(t, c[cc["y"]] * 1e3, color="0.55", lw=0.8, label=f"y {k} (measured)", gid=f"y:{k}")
        ax[0].plot(t, y_hat * 1e3, color=col, lw=1, label=f"ŷ {k} (observer)", gid=f"y_hat:{k}")
        y_true = truth.get(cc["y"])
        if y_true is not None:
            ax[0].plot(t, y_true * 1e3, color="k", lw=0.8, ls="--", label=f"y {k} (simulated truth)",
                       gid=f"y_true:{k}")
            ax[1].plot(t, (y_hat - y_true) * 1e3, color=col, lw=0.8, label=f"ŷ − y_true {k}", gid=f"err:{k}")
            if cc["y"] in c:
                ax[1].plot(t, (c[cc["y"]] - y_true) * 1e3, color="0.55", lw=0.6,
                           label=f"y measured − y_true {k}", gid=f"err_meas:{k}")
        elif cc["y"] in c:
            ax[1].plot(t, (y_hat - c[cc["y"]]) * 1e3, color=col, lw=0.8, label=f"ŷ − y measured {k}",
                       gid=f"err:{k}")
        sig = c.get(f"{k}_obs_sigma_y")          # ±σ_y of ŷ's error the observer reports (its outage table)
        if sig is not None:
            ax[1].fill_between(t, -sig * 1e3, sig * 1e3, color=col, alpha=0.15, lw=0, label=f"±σ_y {k}",
                               gid=f"sigma_y:{k}")
        for m, ls in (("lat", "-"), ("psi", "--"), ("dw", ":")):
            name = f"{k}_obs_T_{m}"
            if name in c:
                ax[2].plot(t, c[name], color=col, ls=ls, lw=0.8, label=f"T_{m} {k}", gid=f"T_{m}:{k}")
    thr = run.limits.get("innovation_chi2")
    if thr is not None:
        ax[2].axhline(thr, color="0.25", ls="--", lw=0.8, gid="limit:innovation_chi2",
                      label=f"innovation_chi2 = {thr:g}")
    ax[2].set_yscale("symlog", linthresh=1.0)
    ax[2].set_ylim(bottom=0.0)
    for g in degraded_intervals(run):
        t1 = g["t_end"] if g["t_end"] is not None else float(t[-1])
        for i, a in enumerate(ax):
            a.axvspan(g["t_start"], t1, color=CARRIER_COLOR[g["carrier"]], alpha=0.12, lw=0,
                      gid=f"degraded:{g['carrier']}", label=f"DEGRADED {g['carrier']}" if i == 0 else None)
    ax[0].set_ylabel("lateral displacement (mm)")
    ax[1].set_ylabel("error (mm)")
    ax[2].set_ylabel("innovation statistic T (χ²(1))")
    what = "ŷ against y and the simulated truth" if truth else "ŷ against y"
    _time_panels(fig, ax, run, title or f"{run.path.name}: observer, {what}; DEGRADED shaded", ncol=3)
    return fig


def law_columns(run: RunLog) -> dict[str, list[str]]:
    """The control law's signals the log has (``law_signals``, in the law's order): name ->
    the controlled carriers with its column ``{carrier}_{name}``; {} for a log without them."""
    out = {n: [k for k in run.controlled if f"{k}_{n}" in run.columns] for n in law_signals(run.attrs)}
    return {n: ks for n, ks in out.items() if ks}


def law(run: RunLog, title: str = ""):
    """The control law's signals, one panel per signal the law declares (its unit on the axis,
    mm/mrad for m/rad), every controlled carrier in its colour, with states and faults."""
    plt = pyplot()
    c, t = run.columns, run.t_rel
    units = law_signals(run.attrs)
    cols = law_columns(run)
    fig, ax = plt.subplots(len(cols), 1, figsize=(9, 1.5 + 1.6 * len(cols)), sharex=True, squeeze=False)
    ax = list(ax[:, 0])
    for a, (n, carriers) in zip(ax, cols.items()):
        unit, scale = display_unit(units[n])
        for k in carriers:
            a.plot(t, c[f"{k}_{n}"] * scale, color=CARRIER_COLOR[k], lw=0.9, label=f"{n} {k}", gid=f"{n}:{k}")
        a.set_ylabel(f"{n} ({unit})" if unit else n)
    law_name = run.config.get("controller", {}).get("law", "")
    _time_panels(fig, ax, run, title or f"{run.path.name}: the control law's signals ({law_name})", ncol=2)
    return fig


def log_figures(run: RunLog, open_loop_carrier: Optional[str] = None, title: str = "") -> dict:
    """The figures of one run, by file stem: ``response`` always, ``forces`` when the log has
    F/T data of a carrier in use, ``psi_over_u`` for an open-loop carrier, ``observer`` when
    the log has an observer's columns (with the simulated truth when it has that), ``law``
    when it has the control law's signals (:func:`law`)."""
    from .runlog import truth
    figs = {"response": response(run, title)}
    if has_forces(run):
        figs["forces"] = forces(run)
    if open_loop_carrier in CARRIER_COLUMNS:       # one carrier's input ("both": no single one)
        figs["psi_over_u"] = psi_over_u(run, open_loop_carrier)
    if observed(run):
        figs["observer"] = observer(run, truth(run))
    if law_columns(run):
        figs["law"] = law(run)
    return figs


def write_all(figs: dict, out_dir: Path) -> list[Path]:
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    return [save(f, out / f"{name}.png") for name, f in figs.items()]


# ------------------------------------------------------------------ tuning figures (rig tune --plot)
def root_locus(cfg, r, paper: dict):
    """Fig. 11 style: closed-loop poles of the P law u = K_P (y_ref − y) for K_P from 0 to
    1.2× the stability boundary; markers and labels at fractions of the boundary, the
    boundary poles (on the imaginary axis) marked, the part beyond it red."""
    from .. import analysis
    plt = pyplot()
    kb = r.stability_boundary_kp
    fig, ax = plt.subplots(figsize=(7, 5.5))
    kps = np.linspace(0, kb, 400)
    loci = analysis.root_locus(cfg, kps)
    beyond = analysis.root_locus(cfg, np.linspace(kb, 1.2 * kb, 80))
    for j in range(loci.shape[1]):
        ax.plot(loci[:, j].real, loci[:, j].imag, "-", color="tab:blue", lw=1.2,
                label="stable (K_P < boundary)" if j == 0 else None, gid=f"locus:{j}")
        ax.plot(beyond[:, j].real, beyond[:, j].imag, "-", color="tab:red", lw=1.2,
                label="unstable (K_P > boundary)" if j == 0 else None, gid=f"locus-unstable:{j}")
    ax.plot(r.open_loop_poles.real, r.open_loop_poles.imag, "kx", ms=9, mew=2, label="open-loop poles", gid="open-loop")
    po = paper.get("open_loop_slow")
    if po:
        ax.plot(po, [0.0] * len(po), "o", mfc="none", mec="0.3", ms=11, label="paper: open-loop poles (Sec. 5.1)",
                gid="paper-open-loop")
    fracs = (0.1, 0.25, 0.5, 0.75)
    for f in fracs:
        k = f * kb
        p = analysis.root_locus(cfg, np.array([k]))[0]
        sel = p[np.abs(p.real) < 60]
        ax.plot(sel.real, sel.imag, ".", color="k", ms=6, gid=f"gain:{k:.0f}")
        top = sel[np.argmax(sel.imag)] if len(sel) else None
        if top is not None:
            ax.annotate(f"K_P={k:.0f}", (top.real, top.imag), xytext=(4, 4), textcoords="offset points", fontsize=7,
                        gid=f"gain-label:{k:.0f}")
    pb = analysis.root_locus(cfg, np.array([kb]))[0]
    pb = pb[np.abs(pb.real) < 1e-3 * max(1.0, np.abs(pb).max())]
    ax.plot(pb.real, pb.imag, "D", color="tab:red", ms=8, gid="boundary",
            label=f"boundary K_P = {kb:.0f} A/m" + (f" (paper {paper['stability_boundary_kp']:.0f})"
                                                    if "stability_boundary_kp" in paper else ""))
    for p in pb[pb.imag > 0]:
        ax.annotate(f"boundary K_P={kb:.0f}\n(ω={p.imag:.1f} 1/s)", (p.real, p.imag), xytext=(-110, 0),
                    textcoords="offset points", fontsize=7, color="tab:red", gid="boundary-label",
                    arrowprops={"arrowstyle": "->", "color": "tab:red", "lw": 0.8})
    ax.axvline(0, color="0.3", lw=0.8)
    ax.axhline(0, color="0.7", lw=0.5)
    ax.set_xlim(min(-90, r.open_loop_poles.real.min() * 1.1), 20)
    ax.set_xlabel("Re (1/s)"); ax.set_ylabel("Im (1/s)")
    ax.set_title(f"Root locus of the P law (Fig. 11 style), D = {r.params['D']:g}", fontsize=10)
    ax.legend(fontsize=7, loc="lower left")
    ax.grid(alpha=0.3)
    fig.tight_layout()
    return fig


def slowest_vs_D(cfg, r):
    """Fig. 12 style: the largest real part of the P-law poles over K_P, for several D."""
    from .. import analysis
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(7, 5))
    kp = np.logspace(1, 6, 300)
    for D in cfg.tuning.D_values:
        rl = analysis.root_locus(cfg, kp, D=D)
        ax.semilogx(kp, rl.real.max(axis=1), label=f"D = {D:g}", gid=f"D:{D:g}")
    ax.axhline(0, color="0.3", lw=0.8)
    ax.axvline(r.stability_boundary_kp, color="tab:red", ls="--", lw=0.8, gid="boundary",
               label=f"boundary at D_min: K_P = {r.stability_boundary_kp:.0f}")
    ax.set_ylim(-10, 5)
    ax.set_xlabel("K_P (A/m)"); ax.set_ylabel("max Re(pole) (1/s)"); ax.legend(fontsize=7)
    ax.set_title("Slowest closed-loop pole of the P law vs damping (Fig. 12 style)", fontsize=10)
    ax.grid(alpha=0.3, which="both")
    fig.tight_layout()
    return fig


EIG_SETS = (("inner", "inner (15)", "o", "tab:blue"), ("inner_filtered", "inner + filter (16)", "s", "tab:orange"),
            ("outer", "outer (17)", "^", "tab:green"), ("closed_loop", "closed loop (19)", "D", "tab:red"),
            ("closed_loop_sampled", "sampled, as implemented", "+", "tab:purple"))


def eigenvalues(r, paper: dict):
    """The eigenvalues of the PI-PD loops, computed (hollow markers) and the paper's printed
    values (Sec. 5.2.3, ``paper[...]``; filled markers, same shape and colour): on top one row
    per loop over the real part (the printed values are real), below the complex plane."""
    plt = pyplot()
    fig, (ax, bx) = plt.subplots(2, 1, figsize=(8, 7.5), gridspec_kw={"height_ratios": [1.1, 1]})
    names = []
    for row, (key, name, m, col) in enumerate(EIG_SETS):
        ev = getattr(r, key)
        names.append(name)
        ax.plot(ev.real, np.full(len(ev), row + 0.12), m, color=col, mfc="none", ms=9, gid=f"computed-row:{key}",
                label="computed" if row == 0 else None)
        bx.plot(ev.real, ev.imag, m, color=col, mfc="none", ms=9, label=name, gid=f"computed:{key}")
        if key in paper:
            pv = np.asarray(paper[key], dtype=float)
            ax.plot(pv, np.full(len(pv), row - 0.12), m, color=col, ms=6, gid=f"paper:{key}",
                    label="paper (Sec. 5.2.3)" if key == "inner" else None)
            for v in pv:
                ax.annotate(f"{v:g}", (v, row - 0.12), xytext=(0, 5), textcoords="offset points", ha="center",
                            fontsize=6, color=col)
            bx.plot(pv, np.zeros_like(pv), m, color=col, ms=4, gid=f"paper-plane:{key}")
    ax.set_yticks(range(len(names)), names, fontsize=8)
    ax.set_ylim(len(names) - 0.4, -0.7)
    lo = min(float(np.min(getattr(r, k).real)) for k, *_ in EIG_SETS)
    lo = min(lo, *(min(paper[k]) for k, *_ in EIG_SETS if k in paper))
    for a in (ax, bx):
        a.set_xscale("symlog", linthresh=1)
        a.set_xlim(1.5 * lo, 1.0)
        a.axvline(0, color="0.3", lw=0.8)
        a.grid(alpha=0.3, which="both")
    ax.legend(fontsize=7, loc="lower right")
    ax.set_title("Eigenvalues of the PI-PD loops: computed (hollow) vs the paper's (filled)", fontsize=10)
    bx.set_xlabel("Re (1/s)"); bx.set_ylabel("Im (1/s)")
    bx.legend(fontsize=7, ncol=2)
    fig.tight_layout()
    return fig


def tune_figures(cfg, r, paper: dict) -> dict:
    return {"root_locus": root_locus(cfg, r, paper), "p_slowest_vs_D": slowest_vs_D(cfg, r),
            "eigenvalues": eigenvalues(r, paper)}
