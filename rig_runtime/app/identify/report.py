"""Plots of ``rig identify --report`` in the style of the paper's Figs. 5-10: measured,
configured (nominal) model, identified model. Needs matplotlib (the ``plot`` extra)."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np

from rig_runtime.config import Plant as PlantParams

from . import free_response, lateral, verify, wheelspeed
from .experiments import Experiment
from .model import simulate_psi, simulate_record
from sim_backend.plant import LiftedCarrier
from ..plotting import pyplot




def write_report(P0: PlantParams, P: PlantParams, exps: list[Experiment], result: dict, out_dir) -> list[Path]:
    plt = pyplot()
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    files: list[Path] = []
    by = {k: [e for e in exps if e.kind == k] for k in ("free-response", "steps", "sine", "open-loop-steps")}

    def save(fig, name):
        fig.tight_layout()
        files.append(out / name)
        fig.savefig(files[-1], dpi=110)
        plt.close(fig)

    ol = by["open-loop-steps"]
    if ol:
        e = ol[0]
        fig, ax = plt.subplots(2, 1, figsize=(8, 6), sharex=True)
        ax[0].plot(e.t, e.y * 1e3, color="0.5", lw=1, label="measured")
        ax[0].plot(e.t, lateral.simulate(P0, e, P0.l0, P0.y_off) * 1e3, "b--", lw=1, label="configured (2b)")
        ys = lateral.simulate(P, e, P.l0, P.y_off)
        ax[0].plot(e.t, ys * 1e3, "g", lw=1, label="identified (2b)")
        ax[0].set_ylabel("y (mm)"); ax[0].legend(fontsize=8)
        ax[0].set_title("Fig. 5 style: lateral displacement, measured psi as input")
        ax[1].plot(e.t, (e.y - ys) * 1e3, "g", lw=0.8)
        ax[1].set_ylabel("error (mm)"); ax[1].set_xlabel("t (s)")
        save(fig, "fig5_lateral.png")

        fig, ax = plt.subplots(figsize=(8, 4))
        ax.plot(e.t, e.dw, color="0.75", lw=0.5, label="measured (raw)")
        ax.plot(e.t, wheelspeed.display_filter(e.dw, e.h), "k", lw=1, label="measured, 0.5 Hz fwd-bwd")
        pr = wheelspeed.predict(P, e, P.delta0, P.c11, 0.0)
        ax.plot(e.t, wheelspeed.display_filter(pr, e.h), "g", lw=1, label="identified (4), filtered")
        ax.set_xlabel("t (s)"); ax.set_ylabel("dw (rad/s)"); ax.legend(fontsize=8)
        ax.set_title("Fig. 6 style: differential wheel speed")
        save(fig, "fig6_wheel_speed.png")

        fig, ax = plt.subplots(2, 1, figsize=(8, 6), sharex=True)
        ax[0].plot(e.t, e.psi * 1e3, color="0.5", lw=1, label="measured")
        ax[0].plot(e.t, verify.simulate(P0, e) * 1e3, "b--", lw=1, label="configured model")
        ax[0].plot(e.t, verify.simulate(P, e) * 1e3, "g", lw=1, label="identified model")
        ax[0].set_ylabel("psi (mrad)"); ax[0].legend(fontsize=8)
        ax[0].set_title("Fig. 10 style: verification on the held-out open-loop steps")
        ax[1].plot(e.t, e.u, "k", lw=1); ax[1].set_ylabel("u (A)"); ax[1].set_xlabel("t (s)")
        save(fig, "fig10_verification.png")

    fr = by["free-response"]
    if fr:
        ex = next(x for x in result["experiments"] if x["kind"] == "free-response")
        D, off = ex["lifted"]["D"]["value"], ex["lifted"]["psi_off"]["value"]
        fig, ax = plt.subplots(figsize=(8, 4))
        for j, s in enumerate(free_response.releases(fr[0])):
            e = s.exp
            idx = np.arange(s.k0, s.k1 + 1)
            tt = e.t[idx] - e.t[s.k0]
            ax.plot(tt, e.psi[idx] * 1e3, color=str(0.3 + 0.1 * j), lw=1, label="measured" if j == 0 else None)
            rate0 = (e.psi[s.k0 + 1] - e.psi[s.k0]) / e.h
            y = simulate_psi(P, e.u, e.h, s.k0, s.k1, idx, psi0=e.psi[s.k0], rate0=rate0,
                             lifted=LiftedCarrier(D, off))
            ax.plot(tt, y * 1e3, "g", lw=0.8, label="identified (6), lifted" if j == 0 else None)
        ax.set_xlabel("t after release (s)"); ax.set_ylabel("psi (mrad)"); ax.legend(fontsize=8)
        ax.set_title("Fig. 7 style: free response of the lifted carrier")
        save(fig, "fig7_free_response.png")

    st = by["steps"]
    if st:
        e = st[0]
        fig, ax = plt.subplots(1, 2, figsize=(10, 4))
        k0 = int(np.flatnonzero(np.diff(e.u) != 0)[0]) + 1
        k1 = min(k0 + int(70 / e.h), len(e.t) - 1)
        idx = np.arange(0, k1 + 1)
        for a, sl in ((ax[0], slice(k0 - 20, k0 + int(1.0 / e.h))), (ax[1], slice(0, k1 + 1))):
            a.plot(e.t[sl], e.psi[sl] * 1e3, color="0.5", lw=1, label="measured")
            for PP, style, lab in ((P0, "b--", "configured (6)-(9), law (7)"), (P, "g", "identified (6)-(9), law (7)"),
                                   (replace(P, D_max=P.D_min), "c:", "identified, constant D_min"),
                                   (replace(P, D_min=P.D_max), "m:", "identified, constant D_max")):
                y = simulate_record(PP, e.u, e.h, e.psi, idx)
                a.plot(e.t[sl], y[sl] * 1e3, style, lw=1, label=lab)
            a.set_xlabel("t (s)"); a.set_ylabel("psi (mrad)")
        ax[0].set_title("Fig. 8 style: first second of the step"); ax[1].set_title("whole step")
        ax[0].legend(fontsize=7)
        save(fig, "fig8_steps.png")

    sn = by["sine"]
    if sn:
        e = sn[0]
        idx = np.arange(0, len(e.t), 10)
        fig, ax = plt.subplots(figsize=(6, 5))
        ax.plot(e.u[idx], e.psi[idx] * 1e3, color="0.5", lw=1, label="measured")
        for PP, style, lab in ((P0, "b--", "configured"), (P, "g", "identified"),
                               (replace(P, bouc_wen=None), "C1", "identified K, D, without hysteresis")):
            y = simulate_record(PP, e.u, e.h, e.psi, idx)
            ax.plot(e.u[idx], y * 1e3, style, lw=1, label=lab)
        ax.set_xlabel("u (A)"); ax.set_ylabel("psi (mrad)"); ax.legend(fontsize=8)
        ax.set_title("Fig. 9 style: yaw angle over input, sines")
        save(fig, "fig9_hysteresis.png")
    return files
