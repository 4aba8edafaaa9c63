"""The synthesis report: the Pareto front of the evaluated candidates (a PNG), the chosen point
and why, every criterion against its demand in every case for it, the worst case; ``--write``
the chosen gains as the base config's ``controller`` section with them applied.

The chosen point: among the feasible candidates (every demand met in every case) on the
Pareto front of the objectives' worst values, the one with the smallest sum of objectives
each divided by its demand (an objective without a demand: by the front's median) — the
front's point closest to "everything at zero" in units of what was demanded. Without a
feasible candidate: the one with the smallest total violation, said so."""

from __future__ import annotations

import copy
import math
from pathlib import Path
from types import SimpleNamespace
from typing import Optional

import numpy as np
import yaml

from ..campaign import materialize, paths
from . import store as sstore
from .criteria import normalised


def _spec(meta: dict) -> SimpleNamespace:
    s = meta["spec"]
    crit = [SimpleNamespace(**c) for c in s["criteria"]]
    return SimpleNamespace(name=s["name"], config=Path(s["config"]), criteria=crit,
                           objectives=[c for c in crit if c.objective],
                           tunables=[SimpleNamespace(**t) for t in s["tunables"]],
                           cases=[SimpleNamespace(**c) for c in s["cases"]], optimizer=s["optimizer"])


def front(F: np.ndarray) -> np.ndarray:
    """Indices of the non-dominated rows of F (minimisation; pymoo's sorting)."""
    from pymoo.util.nds.non_dominated_sorting import NonDominatedSorting
    if len(F) == 0:
        return np.zeros(0, int)
    return np.asarray(NonDominatedSorting().do(F, only_non_dominated_front=True), int)


def choose(spec, cands: list[dict]) -> tuple[Optional[dict], str, list[dict]]:
    """(the chosen candidate, why, the Pareto front it was chosen from)."""
    if not cands:
        return None, "no candidate was evaluated", []
    feas = [c for c in cands if c["feasible"]]
    if not feas:
        c = min(cands, key=lambda c: c["violation"])
        return c, (f"no candidate meets every demand in every case; #{c['candidate']} misses them least "
                   f"(total relative violation {c['violation']:.3g})"), []
    F = np.array([c["objectives"] for c in feas], float)
    on = [feas[i] for i in front(F)]
    Ff = np.array([c["objectives"] for c in on], float)
    ref = np.median(Ff, axis=0)
    best = min(on, key=lambda c: normalised(spec, c["objectives"], ref))
    terms = ", ".join(f"{o.name} {v:.4g}/" + (f"{o.demand:g}" if o.demand is not None else f"{r:.4g} (median)")
                      for o, v, r in zip(spec.objectives, best["objectives"], ref))
    return best, (f"meets every demand in every case; of the {len(on)} feasible candidates on the Pareto front "
                  f"({len(feas)} feasible of {len(cands)}), the smallest sum of objectives relative to their demands: "
                  f"{terms}"), on


def _plot(spec, cands, on, chosen, path: Path) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, ax = plt.subplots(figsize=(7, 5))
    F = np.array([c["objectives"] for c in cands], float)
    ok = np.array([c["feasible"] for c in cands])
    shown = F < 1e5                     # an undefined objective (a refused run) is not plotted
    names = [o.name for o in spec.objectives]
    if F.shape[1] >= 2:
        xs, ys = F[:, 0], F[:, 1]
        ax.set_xlabel(f"{names[0]} (worst over the cases)")
        ax.set_ylabel(f"{names[1]} (worst over the cases)")
    else:
        xs, ys = np.array([c["candidate"] for c in cands], float), F[:, 0]
        ax.set_xlabel("candidate")
        ax.set_ylabel(f"{names[0]} (worst over the cases)")
    sel = shown.all(axis=1)
    ax.scatter(xs[sel & ~ok], ys[sel & ~ok], marker="x", c="0.6", label="misses a demand")
    ax.scatter(xs[sel & ok], ys[sel & ok], c="tab:blue", label="meets every demand")
    if on:
        P = np.array([[c["objectives"][0], c["objectives"][1] if F.shape[1] >= 2 else 0] for c in on], float)
        if F.shape[1] >= 2:
            order = np.argsort(P[:, 0])
            ax.plot(P[order, 0], P[order, 1], "-o", c="tab:red", mfc="none", label="Pareto front (feasible)")
    if chosen is not None:
        cx = chosen["objectives"][0] if F.shape[1] >= 2 else chosen["candidate"]
        cy = chosen["objectives"][1] if F.shape[1] >= 2 else chosen["objectives"][0]
        if cx < 1e5 and cy < 1e5:
            ax.scatter([cx], [cy], marker="*", s=250, c="gold", edgecolors="k", zorder=5, label="chosen")
    for o, f in zip(spec.objectives[:2], (ax.axvline, ax.axhline)):
        if o.demand is not None and F.shape[1] >= 2:
            f(o.demand, ls=":", c="k", lw=0.8)
    ax.set_title(f"rig synthesize {spec.name}: {len(cands)} candidates")
    ax.legend(fontsize=8)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def _fmt(v) -> str:
    return "undefined" if v is None or (isinstance(v, float) and not math.isfinite(v)) else f"{v:.4g}"


def write_report(d: Path, out: Path, write: Optional[Path] = None) -> tuple[Path, str]:
    st = sstore.open_existing(d)
    try:
        spec = _spec(st.meta())
        cands = sstore.candidates(st)
        chosen, why, on = choose(spec, cands)
        runs = {}
        if chosen is not None:
            cur = st.db.execute("SELECT * FROM case_runs WHERE candidate = ? ORDER BY run_id", (chosen["candidate"],))
            cols = [c[0] for c in cur.description]
            runs = {r["case_name"]: r for r in (dict(zip(cols, x)) for x in cur.fetchall())}
    finally:
        st.close()
    out.mkdir(parents=True, exist_ok=True)
    png = out / "pareto.png"
    if cands:
        _plot(spec, cands, on, chosen, png)
    names = [t.name for t in spec.tunables]
    L = [f"# Synthesis {spec.name}", ""]
    if chosen is None:
        answer = f"{spec.name}: {why}"
        L += [answer, ""]
    else:
        x = ", ".join(f"{n} = {chosen['x'][i]:.6g}" for i, n in enumerate(names))
        answer = f"{spec.name}: chosen candidate #{chosen['candidate']} ({x}): {why}"
        L += [f"**Chosen:** candidate #{chosen['candidate']} (generation {chosen['generation']}): {x}.", "",
              f"**Why:** {why}.", "",
              f"{len(cands)} candidates evaluated, {sum(c['feasible'] for c in cands)} meet every demand in every case; "
              f"{len(spec.cases)} cases; optimizer {spec.optimizer['method']} (pymoo), population "
              f"{spec.optimizer['population']}, {spec.optimizer['generations']} generations, seed "
              f"{spec.optimizer['seed']}.", "", f"![Pareto front]({png.name})", ""]
        L += ["## Every criterion against its demand, per case (the chosen point)", ""]
        case_names = [c.name for c in spec.cases]
        L += ["| criterion | demand | " + " | ".join(case_names) + " | worst (case) |",
              "| --- | --- | " + " | ".join("---" for _ in case_names) + " | --- |"]
        worst_case_score: dict[str, float] = {}
        for c in spec.criteria:
            cells = []
            for k in spec.cases:
                r = runs.get(k.name, {})
                if not c.linear and k.scenario is None:
                    cells.append("-")
                    continue
                v = r.get(c.name)
                ok = c.demand is None or (v is not None and v <= c.demand)
                cells.append(_fmt(v) + ("" if ok else " ✗"))
                if c.demand is not None:
                    score = math.inf if v is None else (v - c.demand) / (abs(c.demand) or 1.0)
                    if score > worst_case_score.get(k.name, (-math.inf, ""))[0]:
                        worst_case_score[k.name] = (score, c.name)
            demand = "-" if c.demand is None else f"≤ {c.demand:g}"
            L.append(f"| `{c.name}`{' (objective)' if c.objective else ''} | {demand} | " + " | ".join(cells) +
                     f" | {_fmt(chosen['worst'].get(c.name))} ({chosen['worst_case'].get(c.name)}) |")
        if worst_case_score:
            wc = max(worst_case_score, key=lambda n: worst_case_score[n][0])
            sc, crit = worst_case_score[wc]
            how = ("undefined" if sc == math.inf else f"{100 * sc:.3g} % beyond its demand" if sc > 0
                   else "exactly at its demand" if sc == 0 else f"{100 * -sc:.3g} % inside its demand")
            L += ["", f"**The worst case:** `{wc}`: the case closest to (or furthest beyond) a demand, relative to "
                  f"that demand — `{crit}` {how}."]
        L += ["", "## Reproducing the chosen point's runs", ""]
        for k in spec.cases:
            r = runs.get(k.name)
            if r:
                L.append(f"- `{k.name}`: `{r['command']}`")
        L += ["", "## The Pareto front (feasible candidates)", "",
              "| candidate | " + " | ".join(names) + " | " + " | ".join(o.name for o in spec.objectives) + " |",
              "| --- | " + " | ".join("---" for _ in names) + " | " + " | ".join("---" for _ in spec.objectives) + " |"]
        for c in sorted(on, key=lambda c: c["objectives"]):
            L.append(f"| {c['candidate']} | " + " | ".join(f"{v:.4g}" for v in c["x"]) + " | " +
                     " | ".join(f"{v:.4g}" for v in c["objectives"]) + " |")
        if write is not None:
            _write_controller(spec, dict(zip(names, chosen["x"])), write, d, chosen["candidate"])
            L += ["", f"Written: `{write}` (the base config's controller section with the chosen gains)."]
    md = out / "report.md"
    md.write_text("\n".join(L) + "\n")
    return md, answer


def _write_controller(spec, x: dict, path: Path, d: Path, k: int) -> None:
    """The base config's ``controller`` section with the chosen values (campaign/paths.py)."""
    base = materialize.config_base(spec.config, {})
    sections = copy.deepcopy({"controller": base.sections.get("controller") or {}})
    for name in paths.order(x):
        paths.apply(sections, name, float(x[name]), base.sections)
    body = yaml.safe_dump(sections, sort_keys=False, default_flow_style=None, width=120)
    path.write_text(f"# rig synthesize report {d}: candidate #{k} of {spec.name} (the base config's controller "
                    f"section with the chosen gains)\n{body}")
