"""What a run shows while it runs: the live outputs the recording sidecar feeds (named
here, constructed in the sidecar), and the status snapshot the loop hands it a few times a
second (device health and counters, timing counts, faults, gains — what is not in the cycle
row). The snapshot is built in the loop's cycle (≈ 50 µs every 0.2 s): statistics that can be
computed from the rows — the lateness and work distributions — are the sidecar's."""

from __future__ import annotations

import math
from ..loop import ControlLoop

UDP = "rig_runtime.app.telemetry:UdpTelemetry"
FOXGLOVE = "rig_runtime.app.foxglove_out:FoxgloveServer"
PANEL = "rig_runtime.app.panel:LivePanel"
CTL = "rig_runtime.app.ctl_server:CtlServer"

STATUS_FAULTS = 10     # the newest faults in a snapshot (a held run may collect many); all are in the log


def _num(x: float):
    return x if x == x and abs(x) != math.inf else None


def snapshot(loop: ControlLoop, duration_s: float) -> dict:
    """The status of a running loop (JSON-able; see docs/live-views.md)."""
    sup = loop.supervisor
    st = loop.stats
    t = loop.cycle.t
    t0 = loop.t_start
    started = t0 is not None
    rec = loop.recorder
    return {
        "t": t,
        "t_run": t - t0 if started else None,
        "duration_s": _num(duration_s),
        "state": sup.state.name,
        "controlled": list(loop.cfg.controlled),
        "faults": [{**f.as_dict(), "t_run": (f.t - t0) if started else None} for f in sup.faults[-STATUS_FAULTS:]],
        "faults_total": len(sup.faults),
        "wheels_lost": sorted(sup.wheels_lost),        # RECONFIGURED: the drives the run does without
        "devices": [{"name": c.name, "kind": c.kind, "state": c.state.value, "cause": c.cause,
                     "value": _num(c.value), "age_s": _num(t - c.t), "bad_frames": c.bad} for c in loop.channels],
        "counters": loop.dev.counters() if hasattr(loop.dev, "counters") else {},
        # the lateness and work distributions are the sidecar's (from every row's columns)
        "timing": {"cycles": st.cycles, "deadline_misses": st.deadline_misses, "skipped_periods": st.skipped_periods},
        "recorder": ({"rows": rec.rows_written, "healthy": rec.healthy, "error": rec.error}
                     if rec is not None else None),
        "gains": loop.gains(),
    }


class StatusPublisher:
    """The loop's status hook (every 0.2 s): a snapshot into the sidecar's status slot."""

    def __init__(self, recorder, duration_s: float):
        self.recorder = recorder
        self.duration_s = duration_s

    def __call__(self, loop: ControlLoop) -> None:
        self.recorder.publish_status(snapshot(loop, self.duration_s))


def outputs_for(*, telemetry: str | None = None, telemetry_every: int = 1, foxglove: str | None = None,
                panel: bool = False, ctl_socket: str | None = None) -> list[tuple[str, dict]]:
    """The live outputs a command asked for, as the sidecar constructs them."""
    out: list[tuple[str, dict]] = []
    if telemetry:
        from .telemetry import parse_udp_url
        host, port = parse_udp_url(telemetry)
        out.append((UDP, {"host": host, "port": port, "every": telemetry_every}))
    if foxglove:
        from .foxglove_out import parse_address
        host, port = parse_address(foxglove)
        out.append((FOXGLOVE, {"host": host, "port": port}))
    if panel:
        out.append((PANEL, {}))
    if ctl_socket:
        out.append((CTL, {"path": ctl_socket}))
    return out
