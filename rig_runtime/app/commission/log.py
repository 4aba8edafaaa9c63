"""The commissioning's own normal log: written through the recorder like a run's HDF5 log
(``runner.open_recorder``), so ``rig log info``/``plot``/``export`` read it. Its rows are the
passive windows' cycles — a run's columns for the config (cycle fields, each laser's and
wheel's value and age, the F/T wrench, the geometry's measurement; the wheel currents all
zero: the power stages are off; no controller ran: its columns are NaN) — and the report is in its events: a ``commission`` event per
window and per item (``device`` the check, ``check`` pass/fail, the measured values in the
message) and one per likely wiring fault. Each bump session has its own log beside it."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Sequence

from ...config import RigConfig
from ...geometry import measure
from ...loop import LOGGED_KINDS, _channel_column
from ...safety import State
from ..runner import open_recorder, run_attrs
from .judge import Item

EVENT_KIND = "commission"


def item_text(i: Item) -> str:
    """An item's measured values, as the report prints them."""
    return ", ".join(f"{k}={v:+.3f}" if isinstance(v, float) and math.isfinite(v) else f"{k}={v}"
                     for k, v in i.measured.items())


class CommissionLog:
    def __init__(self, cfg: RigConfig, devices, path: Path, config_hash: str, when_full: str = "drop"):
        attrs = run_attrs(cfg, None, 0.0, {"scenario": "commission", "mode": "commission",
                                           "commission_config_hash": config_hash})
        self.rec = open_recorder(cfg, devices, path, attrs, when_full=when_full)
        self.path = Path(path)
        self.geometry = cfg.geometry
        self.columns: Sequence[str] = self.rec.columns
        self.chan_cols = {c.name: _channel_column(c) for c in devices.channels() if c.kind in LOGGED_KINDS}
        self.extra = list(devices.extra_columns)
        self.t_last = math.nan

    def cycle(self, t: float, lateness: float, reading) -> None:
        """One passive cycle's row, by column name (a column without a value: NaN; the cycle's
        work is not measured here)."""
        v: dict[str, float] = {"t": t, "t_run": 0.0, "lateness": lateness, "state": float(State.IDLE), "y_ref": 0.0}
        for name, col in self.chan_cols.items():
            s = reading.samples.get(name)
            if s is not None and math.isfinite(s.t):
                v[col], v[f"{col}_age"] = reading.values.get(name, math.nan), t - s.t
        v.update(zip(self.extra, reading.wrench))
        v.update(measure(reading.values, self.geometry)._asdict())
        self.rec.append([float(v.get(c, 0.0 if c.startswith("i_") else math.nan)) for c in self.columns])
        self.t_last = t

    def note(self, t: float, check: str, text: str) -> None:
        self.rec.event(t, EVENT_KIND, check, "window", message=text)

    def items(self, t: float, items: Sequence[Item], sessions: Sequence[dict], passed: bool) -> None:
        """The report: a pass/fail event per item with its measured values, one per likely fault
        and note, one per bump session's log, and the result."""
        for i in items:
            self.rec.event(t, EVENT_KIND, i.name, "pass" if i.passed else "fail", message=item_text(i))
            for f in i.faults:
                self.rec.event(t, EVENT_KIND, i.name, "likely fault", message=f)
            if i.note:
                self.rec.event(t, EVENT_KIND, i.name, "note", message=i.note)
        for s in sessions:
            if s.get("log"):
                self.rec.event(t, EVENT_KIND, s["check"], "log", message=str(s["log"]))
        self.rec.event(t, EVENT_KIND, "commissioning", "pass" if passed else "fail",
                       message=f"{sum(i.passed for i in items)} of {len(items)} checks passed")

    def close(self) -> None:
        self.rec.close()
