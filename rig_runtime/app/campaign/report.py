"""``rig campaign report``: Markdown and PNG from a campaign directory — the pass rate with
its interval, the one-line answer, the worst runs with their reproducing commands, pass/fail
over the two parameters that separate passes from failures best, the Sobol' indices of the
chosen metrics (Saltelli designs) and where the failures lie (bounds, a PRIM box)."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from rig_runtime.errors import ConfigError

from . import discovery, stats
from .outcome import METRICS, split_name
from .store import DB_NAME, Store

WORST = 5


def _load(directory: Path):
    db = directory / DB_NAME
    if not db.is_file():
        raise ConfigError(None, "DIR", f"a campaign directory (no {DB_NAME})", str(directory))
    store = Store(db)
    try:
        meta = store.meta()
        cols, rows = store.table()
    finally:
        store.close()
    if not rows:
        raise ConfigError(None, "DIR", "a campaign with at least one finished run", str(directory))
    return meta, cols, rows


def _fmt_pct(x: float) -> str:
    return f"{100 * x:.1f}"


def answer_line(rate, lo, hi, judged: int, bounds: list[str], n_failed: int) -> str:
    head = (f"the gains hold in {_fmt_pct(rate)} % [{_fmt_pct(lo)}, {_fmt_pct(hi)}] of the sampled conditions "
            f"({judged} runs, 95 % exact interval)")
    if n_failed == 0:
        return head + "; no run failed"
    if bounds:
        return head + "; every failure has " + " and ".join(bounds)
    return head + "; the failures spread over the sampled ranges (no single bound encloses them)"


def write_report(directory: Path, out: Path) -> tuple[Path, str]:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    meta, cols, rows = _load(directory)
    spec, names = meta["spec"], meta["names"]
    idx = {c: i for i, c in enumerate(cols)}
    status = np.array([r[idx["status"]] for r in rows])
    X = np.array([[np.nan if r[idx["p:" + n]] is None else r[idx["p:" + n]] for n in names] for r in rows], float)
    judged_mask = status != "error"
    failed = np.isin(status, ("fail", "refused"))
    n_pass = int((status == "pass").sum())
    judged = int(judged_mask.sum())
    rate, lo, hi = stats.pass_rate(n_pass, judged)
    Xj, fj = X[judged_mask], failed[judged_mask]
    bounds = discovery.failure_bounds(names, Xj, fj)
    line = answer_line(rate, lo, hi, judged, bounds, int(fj.sum()))
    out.mkdir(parents=True, exist_ok=True)
    criteria = spec["criteria"]
    key = next(iter(criteria), "max_abs_e_y_mm")

    def metric(name):
        return np.array([np.nan if r[idx[name]] is None else r[idx[name]] for r in rows], float)

    # which parameters matter for pass/fail: KS separation; without failures, rank correlation with the key metric
    sep = stats.separation(Xj, fj)
    influence = sep if fj.any() and not fj.all() else stats.rank_correlation(X, metric(key))
    order = list(np.argsort(-influence))
    figs = []
    if len(names) >= 1:
        a = order[0]
        b = order[1] if len(names) > 1 else None
        fig, ax = plt.subplots(figsize=(6.4, 4.8))
        yv = X[:, b] if b is not None else metric(key)
        for st, color, mark in (("pass", "tab:green", "o"), ("fail", "tab:red", "x"), ("refused", "black", "s"),
                                ("error", "tab:gray", "^")):
            sel = status == st
            if sel.any():
                ax.scatter(X[sel, a], yv[sel], c=color, marker=mark, s=22, label=f"{st} ({int(sel.sum())})")
        box = discovery.prim_box(names, Xj, fj)
        if box and b is not None and (names[a] in box.limits or names[b] in box.limits):
            xa = box.limits.get(names[a], (np.nanmin(X[:, a]), np.nanmax(X[:, a])))
            yb = box.limits.get(names[b], (np.nanmin(X[:, b]), np.nanmax(X[:, b])))
            ax.add_patch(plt.Rectangle((xa[0], yb[0]), xa[1] - xa[0], yb[1] - yb[0], fill=False, ls="--",
                                       color="tab:red", label="PRIM box of the failures"))
        ax.set_xlabel(names[a])
        ax.set_ylabel(names[b] if b is not None else key)
        ax.set_title(f"{spec['name']}: pass/fail over the two most influential parameters")
        ax.legend(fontsize=8)
        fig.tight_layout()
        p = out / "pass-fail.png"
        fig.savefig(p, dpi=110)
        plt.close(fig)
        figs.append(p)
    else:
        box = None
    if box is None:
        box = discovery.prim_box(names, Xj, fj)

    sobol_rows = []
    if spec["design"]["method"] == "saltelli" and spec["sensitivity"]:
        n_expected = meta["n_runs"]
        complete = len(rows) == n_expected
        fig, axes = plt.subplots(1, len(spec["sensitivity"]), figsize=(4.2 * len(spec["sensitivity"]), 4.0),
                                 squeeze=False)
        for k, m in enumerate(spec["sensitivity"]):
            y = (status == "pass").astype(float) if m == "pass" else metric(m)
            if m == "pass":
                y[status == "error"] = np.nan
            res = stats.sobol_indices(names, y, seed=spec["design"]["seed"]) if complete else None
            sobol_rows.append((m, res, "runs missing (resume the campaign)" if not complete else
                               "a run without this value (refused, error or undefined)" if res is None else ""))
            ax = axes[0][k]
            if res is not None:
                xs = np.arange(len(names))
                ax.bar(xs - 0.2, res["S1"], 0.4, yerr=res["S1_conf"], capsize=3, label="first order S1")
                ax.bar(xs + 0.2, res["ST"], 0.4, yerr=res["ST_conf"], capsize=3, label="total order ST")
                ax.set_xticks(xs, [n.split(".")[-1] for n in names], rotation=45, ha="right", fontsize=8)
                ax.axhline(0, color="k", lw=0.5)
                ax.legend(fontsize=7)
            ax.set_title(f"Sobol' indices: {m}", fontsize=9)
        fig.tight_layout()
        p = out / "sobol.png"
        fig.savefig(p, dpi=110)
        plt.close(fig)
        figs.append(p)

    # worst runs: failures first, then by the key metric
    kv = metric(key)
    rank = sorted(range(len(rows)), key=lambda i: (status[i] == "pass", -(kv[i] if np.isfinite(kv[i]) else math.inf)))
    counts = {s: int((status == s).sum()) for s in ("pass", "fail", "refused", "error")}
    L = [f"# Campaign `{spec['name']}`", "", spec.get("description", "").strip(), "",
         f"**Answer:** {line}.", "",
         f"Spec `{spec['source']}`; base config `{spec['config']}`, scenario `{spec['scenario']}`"
         + (f", {spec['duration_s']:g} s" if spec.get("duration_s") else "") + f"; design {spec['design']['method']} "
         f"(n = {spec['design']['n']}, seed {spec['design']['seed']}); {len(rows)} of {meta['n_runs']} runs have a row: "
         + ", ".join(f"{v} {k}" for k, v in counts.items()) + ". Refused runs (the stability gate) count as failures; "
         "error rows are left out of the rate.", "",
         "Pass criteria: " + ", ".join((["no fault"] if spec["no_fault"] else []) +
                                      [f"{m} <= {v:g}" for m, v in criteria.items()]) + ".", "",
         "| parameter | distribution | separation of failures (KS) |", "| --- | --- | --- |"]
    for j, p in enumerate(spec["parameters"]):
        d = p["dist"]
        desc = (f"uniform [{d['lo']:.6g}, {d['hi']:.6g}]" if d["kind"] == "uniform" else
                f"normal ({d['mean']:.6g}, sd {d['sd']:.6g})" if d["kind"] == "normal" else
                "values " + ", ".join(f"{v:g}" for v in d["values"]))
        L.append(f"| `{p['name']}` | {desc} (nominal {p['nominal']:.6g}) | {sep[j]:.2f} |")
    L += ["", "## Where it fails", ""]
    if not fj.any():
        L.append("No run failed.")
    else:
        L.append("Every failure has " + " and ".join(bounds) + "." if bounds else
                 "No single bound on one parameter encloses every failure.")
        if box is not None and box.limits:
            L.append("")
            L.append(f"PRIM box (peeling {int(0.05 * 100)} % at a time, keeping >= 80 % of the failures): "
                     + ", ".join(f"{lo_:.4g} <= {n} <= {hi_:.4g}" for n, (lo_, hi_) in box.limits.items())
                     + f" — holds {100 * box.coverage:.0f} % of the failures; {100 * box.density:.0f} % of the "
                     f"{box.runs_inside} runs inside fail.")
    if sobol_rows:
        L += ["", "## Sobol' indices", "", "First-order (S1) and total-order (ST) indices with 95 % bootstrap "
              "intervals (SALib, 200 resamples). Indices of the unit-cube coordinates; they equal those of the values.", ""]
        for m, res, why in sobol_rows:
            if res is None:
                L.append(f"- `{m}`: not computed: {why}.")
                continue
            L += [f"`{m}`" + (" (constant over the runs: every index 0)" if res["constant"] else ""), "",
                  "| parameter | S1 | ST |", "| --- | --- | --- |"]
            for j, n in enumerate(names):
                L.append(f"| `{n}` | {res['S1'][j]:.3f} ± {res['S1_conf'][j]:.3f} | {res['ST'][j]:.3f} ± "
                         f"{res['ST_conf'][j]:.3f} |")
            L.append("")
    L += ["", f"## Worst runs (by {key})", "", "| run | status | " + key + " | why | reproduce |",
          "| --- | --- | --- | --- | --- |"]
    for i in rank[:WORST]:
        r = rows[i]
        why = (r[idx["why"]] or r[idx["error"]] or "").replace("|", "/")[:160]
        L.append(f"| {r[idx['run_id']]} | {status[i]} | {kv[i]:.4g} | {why} | `{r[idx['command']]}` |")
    L += ["", "## Figures", ""] + [f"![{p.stem}]({p.name})" for p in figs] + [""]
    L += ["Metrics: " + "; ".join(f"`{m}` {d}" for m, d in METRICS.items() if split_name(m)[0] is None)
          + "; `front_NAME`, `rear_NAME`: that carrier's own (NAME alone: the worst over the controlled carriers)."]
    md = out / "report.md"
    md.write_text("\n".join(L) + "\n")
    return md, line
