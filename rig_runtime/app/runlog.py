"""What a recorded log says about its run, for any log (``rig run``, lockstep or real-time
dry run, a run that ended in FAULT, a log cut short by a crash): the run's time origin,
the state changes and faults in run time, the limits and carriers of its config, the step
metrics of the reference it followed. ``rig log`` and ``--report`` build on it.

Run time is ``t − t_start``, ``t_start`` the loop time at which RUNNING began (the
``ARMED -> RUNNING`` event; the ``t_run`` column gives the same where the event is missing).
A log that never reached RUNNING keeps the time of its first row as origin
(``reached_running`` False).
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import LogError
from ..logformat import TRUTH_GROUP
from .export import _open, read_log, state_name
from .metrics import steps_from_log


CARRIERS = ("front", "rear")
#: per carrier: the wheels (left, right) and the measurement columns of y, ψ (carrier to frame), Δω
CARRIER_COLUMNS = {"front": {"wheels": ("fl", "fr"), "y": "y_f", "psi": "psi_af", "dw": "dw_f"},
                   "rear": {"wheels": ("rl", "rr"), "y": "y_r", "psi": "psi_ar", "dw": "dw_r"}}


@dataclass(frozen=True)
class Event:
    t_run: float        # s, run time (negative: before RUNNING)
    kind: str
    device: str
    check: str
    value: float
    limit: float
    message: str


@dataclass(frozen=True)
class RunLog:
    path: Path
    columns: dict[str, np.ndarray]
    events: tuple[Event, ...]
    attrs: dict[str, Any]
    rows: int
    h: float
    config: dict                # the config stored in the log ({} when it has none)
    t_start: float              # loop time when RUNNING began (first row's time if never)
    reached_running: bool

    @property
    def t_rel(self) -> np.ndarray:
        """Run time of every row, s."""
        return self.columns["t"] - self.t_start

    @property
    def limits(self) -> dict:
        return self.config.get("limits", {})

    @property
    def controlled(self) -> list[str]:
        """The controlled carriers (config; else the carriers with controller columns)."""
        c = self.config.get("controlled")
        if c:
            return [x for x in CARRIERS if x in c]
        return [x for x in CARRIERS if f"{x}_u_lim" in self.columns]

    def u(self, carrier: str) -> np.ndarray:
        """The differential current u applied to a carrier (A): left − right wire current."""
        a, b = CARRIER_COLUMNS[carrier]["wheels"]
        return self.columns[f"i_{a}"] - self.columns[f"i_{b}"]

    def has_u(self, carrier: str) -> bool:
        return all(f"i_{w}" in self.columns for w in CARRIER_COLUMNS[carrier]["wheels"])

    @property
    def carriers_in_use(self) -> list[str]:
        """Controlled carriers and any carrier that had current (an open-loop input)."""
        out = []
        for c in CARRIERS:
            driven = self.has_u(c) and bool(np.nanmax(np.abs(self.u(c)), initial=0.0) > 0)
            if c in self.controlled or driven:
                out.append(c)
        return out

    def faults(self) -> list[Event]:
        return [e for e in self.events if e.kind == "fault"]

    def state_changes(self) -> list[tuple[float, str, str]]:
        """(t_run, from, to) of every state event, in order."""
        out = []
        for e in self.events:
            if e.kind == "state" and "->" in e.message:
                a, _, b = e.message.partition("->")
                out.append((e.t_run, a.strip(), b.split(":")[0].strip()))
        return out

    @property
    def final_state(self) -> str:
        if self.rows:
            return state_name(self.columns["state"][-1])
        ch = self.state_changes()
        return ch[-1][2] if ch else "-"


def _str(v: Any) -> str:
    return v if isinstance(v, str) else ("" if v is None else str(v))


def load(path: str | Path) -> RunLog:
    """Read a log and work out its run time origin; :class:`LogError` if it is not a rig log
    or lacks the columns every log has (``t``, ``state``)."""
    d = read_log(path)
    c = d["columns"]
    for need in ("t", "state"):
        if need not in c:
            raise LogError(path, f"no '{need}' column")
    attrs = d["attrs"]
    try:
        cfg = json.loads(attrs["config"]) if isinstance(attrs.get("config"), str) else {}
    except ValueError:
        cfg = {}
    h = float(attrs.get("h") or cfg.get("controller", {}).get("h") or 0.005)
    ev = d["events"]
    t_start = math.nan
    for t, kind, msg in zip(ev["t"], ev["kind"], ev["message"]):
        if kind == "state" and "-> RUNNING" in _str(msg):
            t_start = float(t)
            break
    if math.isnan(t_start) and "t_run" in c:
        run = c["t_run"] > 0
        if np.any(run):
            t_start = float(np.median(c["t"][run] - c["t_run"][run]))
    reached = not math.isnan(t_start)
    if not reached:
        t_start = float(c["t"][0]) if d["rows"] else (float(ev["t"][0]) if len(ev["t"]) else 0.0)
    events = tuple(Event(float(t) - t_start, _str(k), _str(dv), _str(ch), float(v), float(lim), _str(m))
                   for t, k, dv, ch, v, lim, m in zip(*(ev[k] for k in ("t", "kind", "device", "check", "value",
                                                                          "limit", "message"))))
    return RunLog(Path(path), c, events, attrs, d["rows"], h, cfg, t_start, reached)


def truth(run: RunLog) -> dict[str, np.ndarray]:
    """The simulated plant's true state a dry run recorded beside the log (group
    ``sim_truth``: ``t``, ``y_f``, ``y_r``, ``psi_af``, ``psi_ar``), sampled at the log's
    rows; {} when the log has none (a run on the rig)."""
    with _open(run.path) as f:
        g = f.get(TRUTH_GROUP)
        if g is None or "t" not in g:
            return {}
        tr = {k: g[k][()].astype(np.float64) for k in g}
    if not len(tr["t"]) or not run.rows:
        return {}
    idx = np.clip(np.searchsorted(tr["t"], run.columns["t"] - 1e-9), 0, len(tr["t"]) - 1)
    return {k: v[idx] for k, v in tr.items()}


def degraded_intervals(run: RunLog) -> list[dict]:
    """Every interval in which a carrier ran on its observer's ŷ (its ``{carrier}_obs_degraded``
    column), in run time: ``carrier``, ``t_start``, ``t_end`` (None: the log ends DEGRADED),
    ``why`` (the DEGRADED event that began it: the laser, what was observed) and ``end``
    (what ended it: the readmission or the stop's reason — the first degraded event after
    the one that began it — else the fault or the state at its end)."""
    c, t, half = run.columns, run.t_rel, 0.5 * run.h
    out = []
    for car in CARRIERS:
        col = c.get(f"{car}_obs_degraded")
        if col is None:
            continue
        on = np.concatenate(([False], col == 1.0, [False]))
        edges = np.flatnonzero(np.diff(on.astype(np.int8)))
        for a, b in zip(edges[::2], edges[1::2]):
            t0 = float(t[a])
            t1 = float(t[b]) if b < run.rows else None
            hi = (t1 if t1 is not None else float(t[-1])) + half
            starts = [e for e in run.events if e.kind == "degraded" and e.message.startswith("DEGRADED:")
                      and e.t_run <= t0 + half]
            why = starts[-1].message if starts else "-"
            later = [e for e in run.events if e.kind == "degraded" and t0 + half < e.t_run <= hi
                     and not e.message.startswith("DEGRADED:")]
            at_end = [e for e in run.events if e.kind in ("fault", "state") and t1 is not None
                      and abs(e.t_run - t1) <= half]
            if later:
                end = later[0].message
            elif at_end:
                end = at_end[0].message if at_end[0].kind == "fault" else at_end[-1].message
            else:
                end = "the log ends DEGRADED" if t1 is None else "-"
            out.append({"carrier": car, "t_start": t0, "t_end": t1,
                        "duration_s": (t1 if t1 is not None else float(t[-1]) + run.h) - t0,
                        "why": why, "end": end})
    return sorted(out, key=lambda d: d["t_start"])


def reconfigurations(run: RunLog) -> list[dict]:
    """Every drive outage the run went on without (the supervisor's RECONFIGURED events), in
    run time: ``t_start`` and the event's message (which drive, why, which wheels carry on,
    the outage analysis' number). A RECONFIGURED carrier stays so until the run ends."""
    return [{"t_start": e.t_run, "why": e.message} for e in run.events if e.kind == "reconfigured"]


def scenario_of(run: RunLog):
    """The scenario the log names, from its recorded source path (else by name) if that file
    still gives the reference the log recorded; (scenario or None, why not)."""
    from ..errors import ConfigError
    from ..scenario import Reference, load_scenario
    name, src = _str(run.attrs.get("scenario")), _str(run.attrs.get("scenario_source"))
    if not name and not src:
        return None, "no scenario (reference held at 0)"
    sc = None
    for cand in (src, name):
        if cand:
            try:
                sc = load_scenario(cand)
                break
            except ConfigError:
                continue
    if sc is None:
        return None, f"scenario file of '{name or src}' not found"
    if "y_ref" in run.columns and run.rows:
        idx = np.flatnonzero(run.columns["state"] == 2.0)
        idx = idx[np.linspace(0, len(idx) - 1, min(len(idx), 2000)).astype(int)] if len(idx) else idx
        lanes = run.config.get("controlled") or run.controlled      # y_ref is the first lane's
        ref = Reference(sc.reference_for(lanes[0]) if lanes else sc.reference)
        y = np.array([ref(x) for x in run.t_rel[idx]])
        if len(idx) and np.nanmax(np.abs(y - run.columns["y_ref"][idx])) > 1e-9:
            return None, f"scenario file {sc.source} no longer gives the recorded reference"
    return sc, ""


def steps(run: RunLog) -> tuple[list[dict], str]:
    """Step metrics (rig_runtime.app.metrics) of the reference the run followed; ([], why) when none."""
    sc, why = scenario_of(run)
    if sc is None:
        return [], why
    if sc.open_loop is not None:
        return [], "open-loop scenario (no reference followed)"
    if not run.reached_running or "y_r" not in run.columns:
        return [], "never RUNNING"
    s = steps_from_log(run.path, sc, run.h)
    return s, "" if s else "the reference has no step"


def _stats(a: np.ndarray) -> dict:
    a = a[np.isfinite(a)]
    if not len(a):
        return {"p50": None, "p99": None, "max": None}
    return {"p50": float(np.percentile(a, 50)), "p99": float(np.percentile(a, 99)), "max": float(a.max())}


def is_lockstep(run: RunLog) -> bool:
    return "lockstep" in _str(run.attrs.get("mode"))


def info(run: RunLog) -> dict:
    """Everything ``rig log info`` reports, JSON-able (times in s, currents in A)."""
    c = run.columns
    t = c["t"]
    state = c["state"]
    running = state == 2.0
    ch = run.state_changes()
    t_end_running = next((tr for tr, a, _ in ch if a == "RUNNING"), None)
    if t_end_running is None and np.any(running):
        t_end_running = float(run.t_rel[running][-1]) + run.h
    st, why = steps(run)
    out: dict[str, Any] = {
        "log": str(run.path),
        "mode": _str(run.attrs.get("mode")) or "-",
        "rows": run.rows,
        "recorded_s": float(t[-1] - t[0] + run.h) if run.rows else 0.0,
        "running_s": float(t_end_running) if run.reached_running and t_end_running is not None else 0.0,
        "reached_running": run.reached_running,
        "final_state": run.final_state,
        "states": [{"t_run": tr, "from": a, "to": b} for tr, a, b in ch],
        "faults": [{"t_run": e.t_run, "device": e.device, "check": e.check, "value": e.value, "limit": e.limit,
                    "message": e.message} for e in run.faults()],
        "operator": [{"t_run": e.t_run, "message": e.message} for e in run.events if e.kind == "operator"],
        # rig commission's report (docs/commissioning.md): per check its result, measured values, likely faults
        "commission": [{"check": e.device, "what": e.check, "message": e.message} for e in run.events
                       if e.kind == "commission" and e.check != "window"],
        "scenario": _str(run.attrs.get("scenario")) or "-",
        "scenario_source": _str(run.attrs.get("scenario_source")) or "-",
        "config_source": _str(run.attrs.get("config_source")) or run.config.get("source") or "-",
        "start_time": _str(run.attrs.get("start_time")) or "-",
        "software_version": _str(run.attrs.get("software_version")) or "-",
        "controlled": run.controlled,
        "carriers_in_use": run.carriers_in_use,
        "max_abs_u_A": {k: float(np.nanmax(np.abs(run.u(k)), initial=0.0)) for k in run.carriers_in_use
                        if run.has_u(k)},
        "max_abs_wire_current_A": float(max((np.nanmax(np.abs(c[f"i_{w}"]), initial=0.0)
                                             for w in ("fl", "fr", "rl", "rr") if f"i_{w}" in c), default=0.0)),
        "limits": {k: run.limits.get(k) for k in ("u_max", "y_max", "psi_max")},
        "clock": "lockstep" if is_lockstep(run) else "realtime",
        "timing_us": None if is_lockstep(run) else {
            "lateness": _stats(c["lateness"] * 1e6) if "lateness" in c else None,
            "work": _stats(c["work"] * 1e6) if "work" in c else None},
        "recorder": {"closed_cleanly": "recorder_closed" in run.attrs,
                     "rows_dropped": int(run.attrs.get("rows_dropped", 0) or 0),
                     "error": _str(run.attrs.get("recorder_error"))},
        "steps": st,
        "steps_note": why,
        "degraded": degraded_intervals(run),
        "reconfigured": reconfigurations(run),
    }
    return out


def format_info(d: dict) -> list[str]:
    """``info`` as lines for people."""
    def num(v, fmt):
        return format(v, fmt) if v is not None and not (isinstance(v, float) and math.isnan(v)) else "-"
    lines = [f"log: {d['log']}",
             f"mode: {d['mode']}   software {d['software_version']}   started {d['start_time']}",
             f"config: {d['config_source']}",
             f"scenario: {d['scenario']}" + (f" ({d['scenario_source']})" if d["scenario_source"] != "-" else ""),
             f"rows: {d['rows']}   recorded {d['recorded_s']:.3f} s   RUNNING {d['running_s']:.3f} s"
             + ("" if d["reached_running"] else " (never reached RUNNING; times from the first row)"),
             f"final state: {d['final_state']}   controlled: {', '.join(d['controlled']) or '-'}   "
             f"limits: u_max {num(d['limits']['u_max'], 'g')} A, y_max {num(d['limits']['y_max'], 'g')} m"]
    u = ", ".join(f"{k} {v:.3f} A" for k, v in d["max_abs_u_A"].items()) or "-"
    lines.append(f"max |u| (differential current per carrier): {u}; "
                 f"max |i| per wheel (wire current): {d['max_abs_wire_current_A']:.3f} A")
    if d["timing_us"]:
        lat, work = d["timing_us"]["lateness"], d["timing_us"]["work"]
        if lat and work:
            lines.append(f"timing: lateness p50/p99/max {num(lat['p50'], '.1f')}/{num(lat['p99'], '.1f')}/"
                         f"{num(lat['max'], '.1f')} us, work p50/p99/max {num(work['p50'], '.1f')}/"
                         f"{num(work['p99'], '.1f')}/{num(work['max'], '.1f')} us")
    else:
        lines.append("timing: lockstep (simulated clock, no deadlines)")
    r = d["recorder"]
    if not r["closed_cleanly"] or r["rows_dropped"] or r["error"]:
        lines.append(f"recorder: {'closed cleanly' if r['closed_cleanly'] else 'NOT closed cleanly (process killed?)'}"
                     f", rows dropped {r['rows_dropped']}" + (f", error: {r['error']}" if r["error"] else ""))
    lines.append("states (run time): " + (", ".join(f"{b} at {tr:+.3f} s" for tr, a, b in
                                                    ((s["t_run"], s["from"], s["to"]) for s in d["states"])) or "-"))
    if d["faults"]:
        lines.append("faults (run time):")
        for f in d["faults"]:
            lines.append(f"  t={f['t_run']:+.3f} s: {f['device']} {f['check']} value={num(f['value'], '.6g')} "
                         f"limit={num(f['limit'], '.6g')} {f['message']}")
    else:
        lines.append("faults: none")
    if d.get("degraded"):
        lines.append("DEGRADED (run time; the carrier ran on the observer's estimate):")
        for g in d["degraded"]:
            end = f"{g['t_end']:+.3f} s" if g["t_end"] is not None else "end of log"
            lines.append(f"  {g['carrier']} {g['t_start']:+.3f} s -> {end} ({g['duration_s']:.3f} s): {g['why']}")
            lines.append(f"    ended: {g['end']}")
    if d.get("reconfigured"):
        lines.append("RECONFIGURED (run time; a drive lost, its carrier on the remaining wheels to the end):")
        for g in d["reconfigured"]:
            lines.append(f"  {g['t_start']:+.3f} s: {g['why']}")
    if d.get("commission"):
        lines.append("commissioning:")
        for e in d["commission"]:
            lines.append(f"  {e['check']} {e['what'].upper()}: {e['message']}" if e["what"] in ("pass", "fail")
                         else f"  {e['check']} log: {e['message']}" if e["what"] == "log"
                         else f"    {e['what']}: {e['message']}")
    if d["steps"]:
        lines.append("steps:" if not d.get("degraded") else "steps (on the y the lane controlled on: ŷ while DEGRADED):")
        several = len({s.get("carrier") for s in d["steps"]}) > 1
        for s in d["steps"]:
            lines.append(f"  {s['carrier'] + ' ' if several else ''}{s['from_mm']:+.2f} -> {s['to_mm']:+.2f} mm at {s['t0']:.2f} s: rise "
                         f"{num(s['rise_time_s'], '.2f')} s, overshoot {num(s['overshoot_pct'], '.1f')} %, settling "
                         f"{num(s['settling_time_s'], '.2f')} s, steady-state error {num(s['steady_state_error_mm'], '+.4f')} mm")
    else:
        lines.append(f"steps: - ({d['steps_note']})")
    return lines
