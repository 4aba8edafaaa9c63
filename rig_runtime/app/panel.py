"""A live terminal panel for a run (rich), modelled on Simulink Real-Time's TET monitor.

A sidecar output (``rig_runtime.app.panel:LivePanel``, constructed in the recording sidecar
as ``LivePanel(info, stream=None, force=False, refresh_per_second=2)``). It shows the state
with elapsed and remaining time (and DEGRADED: the carriers running on the observer's ŷ,
and why — the latest DEGRADED event), the reference and y/ŷ/ψ/u of each controlled carrier,
the control law's signals by the names the law declares (the log's ``law_signals``), each
device's health and counters, the faults with their cause, and the timing monitor (cycle
work and wake-up lateness last/p50/p99/max, deadline misses, skipped/overrun periods).

What is shown is ``render(row, status, events, ...)``: a pure function of the latest row
(column name -> value), the latest status snapshot and the recent events, so it is tested
by rendering into a recording console. ``LivePanel`` only keeps those three and lets
``rich.live.Live`` redraw them from its own refresh thread (in the sidecar process, never
the loop's). It draws on ``stream`` (default: standard error, where the status line goes,
so standard output stays for results such as ``--json``) and does nothing when that is not
a terminal, unless ``force``.
Display units: mm, mrad, A, µs (the values inside stay SI).
"""

from __future__ import annotations

import math
import sys
from typing import Any, Mapping, Sequence

from rich.console import Console, Group
from rich.live import Live
from rich.table import Table
from rich.text import Text

from ..logformat import display_unit, law_signals
from ..safety import State

MISSING = "-"
STATE_STYLE = {"IDLE": "dim", "ARMED": "yellow", "RUNNING": "bold green", "STOPPING": "yellow",
               "FAULT": "bold white on red"}
DEVICE_STYLE = {"fresh": "green", "stale": "yellow", "invalid": "bold red"}
CARRIERS = ("front", "rear")
MAX_EVENTS = 50
MAX_FAULTS = 6


def _num(x: Any) -> float | None:
    """A finite number, or None (missing, NaN, not a number)."""
    if isinstance(x, bool) or not isinstance(x, (int, float)):
        return None
    return float(x) if math.isfinite(x) else None


def _fmt(x: Any, scale: float = 1.0, digits: int = 2) -> str:
    v = _num(x)
    return MISSING if v is None else f"{v * scale:.{digits}f}"


def _int(x: Any) -> str:
    v = _num(x)
    return MISSING if v is None else str(int(v))


def _get(d: Any, *keys: str) -> Any:
    """``d[k1][k2]...`` or None when any level is missing."""
    for k in keys:
        if not isinstance(d, Mapping) or k not in d:
            return None
        d = d[k]
    return d


def _state_name(row: Mapping[str, float], status: Mapping) -> str:
    code = _num(row.get("state"))
    if code is not None:
        try:
            return State(int(code)).name
        except ValueError:
            return f"state {int(code)}"
    name = status.get("state")
    return name if isinstance(name, str) and name else MISSING


def _clock(seconds: float | None) -> str:
    if seconds is None:
        return MISSING
    m, s = divmod(max(seconds, 0.0), 60.0)
    return f"{int(m)}:{s:04.1f}"


def _degraded(row: Mapping) -> list[str]:
    """The carriers the row shows DEGRADED (``{carrier}_obs_degraded`` = 1: on ŷ)."""
    return [c for c in CARRIERS if _num(row.get(f"{c}_obs_degraded")) == 1.0]


def _header(row, status, duration_s) -> Text:
    state = _state_name(row, status)
    t_run = _num(row.get("t_run"))
    if t_run is None:
        t_run = _num(status.get("t_run"))
    duration = _num(status.get("duration_s"))
    if duration is None:
        duration = _num(duration_s)
    text = Text.assemble(("rig ", "bold"), (f" {state} ", STATE_STYLE.get(state, "bold")))
    deg = _degraded(row)
    if deg:
        text.append(" ")
        text.append(f" DEGRADED: {', '.join(deg)} on ŷ ", "bold black on yellow")
    text.append(f"   elapsed {_clock(t_run)}")
    if duration is None:
        text.append("   remaining - (until stopped)")
    else:
        remaining = None if t_run is None else duration - t_run
        text.append(f"   remaining {_clock(remaining)} of {_clock(duration)}")
    y_ref = _num(row.get("y_ref"))
    text.append(f"   y_ref {_fmt(y_ref, 1e3)} mm")
    if "v_meas" in row:                 # the measured roller speed (the schedule's input)
        text.append(f"   v̂ {_fmt(row.get('v_meas'), 1.0, 3)} m/s")
    return text


def _controlled(row: Mapping, status: Mapping, controlled: Sequence[str] | None) -> list[str]:
    if controlled:
        return list(controlled)
    c = status.get("controlled")
    if isinstance(c, (list, tuple)) and c:
        return [str(x) for x in c]
    return [c for c in CARRIERS if f"{c}_u_cmd" in row]


def _carriers(row, status, controlled) -> Table:
    t = Table(title="carriers", title_justify="left", expand=False, box=None, pad_edge=False)
    for name, just in (("carrier", "left"), ("y_ref mm", "right"), ("y mm", "right"), ("ŷ mm", "right"),
                       ("e_y mm", "right"), ("ψ_ref mrad", "right"), ("ψ mrad", "right"), ("u A", "right"),
                       ("u_lim A", "right"), ("g", "right"), ("schedule", "left"), ("on", "left")):
        t.add_column(name, justify=just)
    deg = _degraded(row)
    for c in _controlled(row, status, controlled):
        s = c[0]
        held = _num(row.get(f"{c}_held"))
        on = Text("ŷ DEGRADED", "bold black on yellow") if c in deg else \
            Text("y" if f"{c}_obs_degraded" in row else MISSING)
        t.add_row(c, _fmt(row.get(f"{c}_y_ref", row.get("y_ref")), 1e3), _fmt(row.get(f"y_{s}"), 1e3),
                  _fmt(row.get(f"{c}_obs_y_hat"), 1e3),
                  _fmt(row.get(f"{c}_e_y"), 1e3), _fmt(row.get(f"{c}_psi_ref"), 1e3), _fmt(row.get(f"psi_a{s}"), 1e3),
                  _fmt(row.get(f"{c}_u_cmd"), 1.0, 3), _fmt(row.get(f"{c}_u_lim"), 1.0, 3),
                  _fmt(row.get(f"{c}_g"), 1.0, 2),
                  MISSING if held is None else Text("HELD", "bold yellow") if held else "on", on)
    return t


def _law(row, status, controlled, law: Mapping[str, str]) -> Table | None:
    """The control law's signals (``law``: name -> SI unit, as the law declares them), one row
    per controlled carrier that has their columns; None without any."""
    carriers = [c for c in _controlled(row, status, controlled) if any(f"{c}_{n}" in row for n in law)]
    if not law or not carriers:
        return None
    t = Table(title="control law", title_justify="left", expand=False, box=None, pad_edge=False)
    t.add_column("carrier", justify="left")
    shown = [(n, *display_unit(u)) for n, u in law.items()]
    for n, unit, _ in shown:
        t.add_column(f"{n} {unit}".rstrip(), justify="right")
    for c in carriers:
        t.add_row(c, *(_fmt(row.get(f"{c}_{n}"), scale, 3) for n, _, scale in shown))
    return t


def _degraded_why(row, events) -> Text | None:
    """While a carrier is DEGRADED: why (the latest DEGRADED event's message)."""
    deg = _degraded(row)
    if not deg:
        return None
    why = [e[6] for e in events if len(e) >= 7 and e[1] == "degraded" and str(e[6]).startswith("DEGRADED:")]
    text = Text(f"DEGRADED ({', '.join(deg)} on the observer's estimate): ", "bold")
    text.append(str(why[-1]) if why else MISSING, "yellow")
    return text


def _reconfigured_why(row, status, events) -> Text | None:
    """While the run goes on RECONFIGURED (a drive lost): the latest RECONFIGURED event."""
    if _state_name(row, status) not in ("RUNNING", "STOPPING"):
        return None
    why = [str(e[6]) for e in events if len(e) >= 7 and e[1] == "reconfigured"]
    if not why:
        return None
    text = Text("RECONFIGURED: ", "bold black on yellow")
    text.append(why[-1].removeprefix("RECONFIGURED: "), "yellow")
    return text


def _devices(status) -> Table:
    t = Table(title="devices", title_justify="left", box=None, pad_edge=False)
    for name, just in (("device", "left"), ("kind", "left"), ("health", "left"), ("age ms", "right"),
                       ("bad frames", "right"), ("timeouts", "right"), ("errors", "right"), ("cause", "left")):
        t.add_column(name, justify=just)
    devices = status.get("devices")
    if not isinstance(devices, (list, tuple)) or not devices:
        t.add_row(*[MISSING] * 8)
        return t
    for d in devices:
        if not isinstance(d, Mapping):
            continue
        st = d.get("state") if isinstance(d.get("state"), str) else MISSING
        t.add_row(str(d.get("name", MISSING)), str(d.get("kind", MISSING)), Text(st, DEVICE_STYLE.get(st, "")),
                  _fmt(d.get("age_s"), 1e3, 1), _int(d.get("bad_frames")), _int(d.get("timeouts")),
                  _int(d.get("errors")), str(d.get("cause") or ""))
    return t


def _faults(status, events) -> Text:
    """Faults from the status snapshot (run-relative time); before the first snapshot that
    has them, from the fault events."""
    lines: list[str] = []
    faults = status.get("faults")
    if isinstance(faults, (list, tuple)) and faults:
        for f in faults[-MAX_FAULTS:]:
            if isinstance(f, Mapping):
                lines.append(_fault_line(f.get("t_run"), f.get("device"), f.get("check"), f.get("value"),
                                         f.get("limit"), f.get("message")))
    else:
        for ev in [e for e in events if len(e) >= 7 and e[1] == "fault"][-MAX_FAULTS:]:
            lines.append(_fault_line(None, ev[2], ev[3], ev[4], ev[5], ev[6]))
    if not lines:
        return Text("faults: none", style="green")
    text = Text("faults:\n", style="bold red")
    text.append("\n".join(lines), style="red")
    return text


def _fault_line(t_run, device, check, value, limit, message) -> str:
    when = f"t={_fmt(t_run, 1.0, 3)} s " if _num(t_run) is not None else ""
    what = " ".join(str(p) for p in (device, check) if p)
    vl = f" (value {_num(value):.4g}, limit {_num(limit):.4g})" \
        if _num(value) is not None and _num(limit) is not None else ""
    return f"  {when}{what}: {message or MISSING}{vl}"


def _timing(row, status) -> Table:
    tm = status.get("timing") if isinstance(status.get("timing"), Mapping) else {}
    t = Table(title="timing (TET monitor)", title_justify="left", box=None, pad_edge=False)
    for name in ("µs", "last", "p50", "p99", "max"):
        t.add_column(name, justify="left" if name == "µs" else "right")
    for label, key, col in (("cycle work", "work_us", "work"), ("lateness", "lateness_us", "lateness")):
        last = _get(tm, key, "last")
        if _num(last) is None:
            last = None if _num(row.get(col)) is None else row[col] * 1e6
        t.add_row(label, _fmt(last, 1.0, 1), *(_fmt(_get(tm, key, q), 1.0, 1) for q in ("p50", "p99", "max")))
    return t


def _counts(status) -> Text:
    tm = status.get("timing") if isinstance(status.get("timing"), Mapping) else {}
    text = Text(f"cycles {_int(tm.get('cycles'))}")
    for key, label, always in (("deadline_misses", "deadline misses", True),
                               ("skipped_periods", "skipped periods", False),
                               ("overrun_periods", "overrun periods", False)):
        if always or key in tm:
            n = _num(tm.get(key))
            text.append(f"   {label} ")
            text.append(_int(n), "bold red" if n else "")
    rec = status.get("recorder") if isinstance(status.get("recorder"), Mapping) else {}
    healthy = rec.get("healthy")
    text.append(f"   recorder rows {_int(rec.get('rows'))} ")
    if healthy is True:
        text.append("ok", "green")
    elif healthy is False:
        text.append(f"UNHEALTHY {rec.get('error') or ''}".rstrip(), "bold red")
    else:
        text.append(MISSING)
    return text


def _counters(status) -> Table | None:
    """The drivers' counters, one line per driver (cut at the panel's width)."""
    c = status.get("counters")
    if not isinstance(c, Mapping) or not c:
        return None
    t = Table(title="driver counters", title_justify="left", box=None, pad_edge=False, show_header=False)
    t.add_column("driver", no_wrap=True, min_width=min(40, max(len(str(d)) for d in c)))
    t.add_column("counters", no_wrap=True, overflow="ellipsis", style="dim")
    for driver, counts in c.items():
        if isinstance(counts, Mapping):
            t.add_row(str(driver), " ".join(f"{k} {_int(v)}" for k, v in counts.items()))
    return t if t.row_count else None


def render(row: Mapping[str, float] | None, status: Mapping | None, events: Sequence[tuple] = (), *,
           controlled: Sequence[str] | None = None, duration_s: float | None = None,
           law: Mapping[str, str] | None = None) -> Group:
    """The panel for the latest ``row`` (column -> value), ``status`` snapshot and recent
    ``events`` (the log's event tuples); ``law``: the control law's signals (name -> SI unit,
    the log's ``law_signals``). Anything missing shows as ``-``. (One frame costs
    a few ms of the sidecar's CPU, hence the modest default refresh rate of LivePanel.)"""
    row = row or {}
    status = status if isinstance(status, Mapping) else {}
    parts: list[Any] = [_header(row, status, duration_s), Text(""), _carriers(row, status, controlled)]
    signals = _law(row, status, controlled, law or {})
    if signals is not None:
        parts += [Text(""), signals]
    parts += [Text(""), _devices(status)]
    counters = _counters(status)
    if counters is not None:
        parts += [Text(""), counters]
    why = _degraded_why(row, events)
    if why is not None:
        parts += [Text(""), why]
    why = _reconfigured_why(row, status, events)
    if why is not None:
        parts += [Text(""), why]
    parts += [Text(""), _faults(status, events), Text(""), _timing(row, status), _counts(status)]
    return Group(*parts)


class LivePanel:
    """Keeps the latest row, status and events and redraws ``render`` of them with
    ``rich.live.Live`` (its own refresh thread) while attached to a terminal."""

    def __init__(self, info, stream=None, force: bool = False, refresh_per_second: float = 2.0):
        self.columns = tuple(info.columns)
        attrs = info.attrs if isinstance(info.attrs, Mapping) else {}
        self.duration_s = _num(attrs.get("duration_s"))
        self.law = law_signals(attrs)
        self.stream = sys.stderr if stream is None else stream   # stdout stays for results (--json)
        isatty = getattr(self.stream, "isatty", None)
        self.enabled = bool(force) or bool(isatty and isatty())
        self._row: Any = None
        self._status: Mapping = {}
        self._events: tuple = ()
        self._live: Live | None = None
        if self.enabled:
            console = Console(file=self.stream, force_terminal=True if force else None)
            self._live = Live(console=console, get_renderable=self.renderable,
                              refresh_per_second=refresh_per_second, redirect_stdout=False, redirect_stderr=False)
            self._live.start()

    def renderable(self) -> Group:
        """What the panel shows now (called from the refresh thread: reads only whole,
        replaced objects)."""
        row = self._row
        values = {} if row is None else dict(zip(self.columns, row.tolist()))
        return render(values, self._status, self._events, duration_s=self.duration_s, law=self.law)

    def rows(self, block) -> None:
        if self.enabled and len(block):
            self._row = block[-1].copy()

    def event(self, ev: tuple) -> None:
        if self.enabled:
            self._events = (*self._events[-(MAX_EVENTS - 1):], tuple(ev))

    def status(self, st: dict) -> None:
        if self.enabled:
            self._status = st

    def close(self) -> None:
        if self._live is not None:
            live, self._live = self._live, None
            live.stop()                                    # draws the final state once more
