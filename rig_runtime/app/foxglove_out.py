"""Live signals to Foxglove through the ``foxglove-sdk`` WebSocket server, and logs to MCAP.

``FoxgloveServer`` is a sidecar output (``rig_runtime.app.foxglove_out:FoxgloveServer``,
constructed as ``FoxgloveServer(info, host="127.0.0.1", port=8765, every=1)``); in Foxglove,
*Open connection* -> *Foxglove WebSocket* -> ``ws://127.0.0.1:8765``. ``export_mcap`` writes
a recorded log as an MCAP file with the same topics and schemas.

Topics (JSON messages with a JSON Schema, SI units; the fields are those of the UDP
telemetry, ``rig_runtime.app.telemetry.RowSignals``, so both views show the same signals):

    /rig/state      timestamp, t_run, code, name         every row
    /rig/front      y, psi, delta_omega (+ dpsi, y_ref, psi_ref, u when controlled)
    /rig/rear       same
    /rig/timing     lateness, work (s)
    /rig/currents   fl, fr, rl, rr (A)
    /rig/front_law  the control law's signals by the names it declares (e_y, psi_ref, …; w, w_cross
    /rig/rear_law   with law decoupled), controlled carriers only
    /rig/health     health, devices, counters             each status snapshot (~5 Hz; live only)
    /rig/events     foxglove.Log: state changes, faults, operator actions

Each message carries ``timestamp`` (s, the loop's clock: ``time.monotonic`` in real time,
simulated time in a lockstep dry run) and is logged with that time as its log time. The SDK
is imported lazily: without it, constructing an output or exporting raises a ``ConfigError``
that says how to install it. The SDK's server speaks the WebSocket subprotocol
``foxglove.sdk.v1`` (the successor of ``foxglove.websocket.v1``, same messages).
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any, Sequence

from ..errors import ConfigError
from ..logformat import law_signals
from .telemetry import EveryNth, RowSignals, status_parts

INSTALL_HINT = "the foxglove extra: pip install 'rig-runtime[foxglove]'"
TOPIC = "/rig/"
_NUMBER = {"type": "number"}
_COUNT = {"type": "integer"}
_LOG_LEVEL = {"fault": "Error", "operator": "Warning", "state": "Info"}


def _sdk(option: str = "--foxglove"):
    """The ``foxglove`` module, or a ConfigError naming the extra to install."""
    try:
        import foxglove
        import foxglove.channels
        import foxglove.messages
    except ImportError:
        raise ConfigError(None, option, INSTALL_HINT, "foxglove-sdk not installed") from None
    return foxglove


def parse_address(text: str, *, option: str = "--foxglove", default_host: str = "127.0.0.1") -> tuple[str, int]:
    """``[HOST:]PORT`` -> ``(host, port)`` (host 127.0.0.1 when omitted); ConfigError otherwise."""
    expected = "[HOST:]PORT (e.g. 8765 or 127.0.0.1:8765)"
    host, sep, port = str(text).rpartition(":")
    host = host.strip("[]") if sep else default_host
    if not port.isdigit() or not 0 < int(port) < 65536:
        raise ConfigError(None, option, f"{expected}; the port must be 1-65535", text)
    if sep and not host:
        raise ConfigError(None, option, f"{expected}; the host is empty", text)
    return host, int(port)


def _schema(title: str, properties: dict[str, Any]) -> dict[str, Any]:
    return {"title": title, "type": "object", "properties": {"timestamp": _NUMBER, **properties}}


def schemas(signals: RowSignals) -> dict[str, dict[str, Any]]:
    """The JSON Schema of each JSON topic (the key is the topic without ``/rig/``)."""
    out = {"state": _schema("rig.State", {"t_run": _NUMBER, "code": _COUNT, "name": {"type": "string"}})}
    for g in signals.groups:
        out[g.key] = _schema("rig." + "".join(p.capitalize() for p in g.key.split("_")), {f: _NUMBER for f in g.fields})
    device = {"type": "object", "properties": {"state": _COUNT, "bad_frames": _COUNT, "timeouts": _COUNT,
                                               "errors": _COUNT}}
    out["health"] = _schema("rig.Health", {
        "health": {"type": "object", "properties": {"deadline_misses": _COUNT, "skipped_periods": _COUNT,
                                                    "overrun_periods": _COUNT, "recorder_healthy": _COUNT}},
        "devices": {"type": "object", "additionalProperties": device},
        "counters": {"type": "object", "additionalProperties": {"type": "object", "additionalProperties": _NUMBER}},
    })
    return out


def _ns(t: float) -> int | None:
    return int(round(t * 1e9)) if t - t == 0.0 and t >= 0.0 else None


class Topics:
    """The channels of one Foxglove context (a live server or an MCAP file) and the rule that
    turns rows, status snapshots and events into their messages: written once for both."""

    def __init__(self, fg, context, columns: Sequence[str], law: Sequence[str] = ()):
        self.fg = fg
        self.signals = RowSignals(columns, law)
        self.channels = {key: fg.Channel(TOPIC + key, schema=s, context=context)
                         for key, s in schemas(self.signals).items()}
        self.events = fg.channels.LogChannel(TOPIC + "events", context=context)
        self._row_channels = [(g.key, self.channels[g.key]) for g in self.signals.groups]
        self._state = self.channels["state"]
        self._health = self.channels["health"]
        self._last_t = float("nan")

    def rows(self, block) -> int:
        """Log the rows of ``block`` on the channels that have a subscriber (a client, an
        MCAP file); returns how many rows were logged."""
        n = 0
        state_ch = self._state if self._state.has_sinks() else None
        active = [(key, ch) for key, ch in self._row_channels if ch.has_sinks()]
        if state_ch is None and not active:        # nobody listens: encode nothing
            return 0
        for v in self.signals.values(block):
            msg = self.signals.message(v)
            ts = msg["timestamp"]
            ns = _ns(ts)
            if ns is None:
                continue
            if state_ch is not None:
                state_ch.log({"timestamp": ts, **({"t_run": msg["t_run"]} if "t_run" in msg else {}),
                              **msg.get("state", {})}, log_time=ns)
            for key, ch in active:
                ch.log({"timestamp": ts, **msg[key]}, log_time=ns)
            self._last_t = ts
            n += 1
        return n

    def status(self, st: dict) -> None:
        t = st.get("t") if isinstance(st.get("t"), (int, float)) else self._last_t
        ns = _ns(float(t))
        if ns is not None and self._health.has_sinks():
            self._health.log({"timestamp": float(t), **status_parts(st)}, log_time=ns)

    def event(self, ev: tuple) -> None:
        t, kind, device, check, value, limit, message = ev
        ns = _ns(float(t))
        if ns is None or not self.events.has_sinks():
            return
        m = self.fg.messages
        detail = [p for p in (str(device or ""), str(check or "")) if p]
        for name, x in (("value", value), ("limit", limit)):
            if isinstance(x, (int, float)) and x - x == 0.0:
                detail.append(f"{name} {x:g}")
        text = str(message) + (f" [{', '.join(detail)}]" if detail else "")
        self.events.log(m.Log(timestamp=m.Timestamp(ns // 1_000_000_000, ns % 1_000_000_000),
                              level=getattr(m.LogLevel, _LOG_LEVEL.get(str(kind), "Info")),
                              message=text, name=str(kind)), log_time=ns)


class FoxgloveServer:
    """A Foxglove WebSocket server (foxglove-sdk) streaming the run's signals; binds to
    127.0.0.1 unless told otherwise. ``port=0`` picks a free port (``self.port``)."""

    def __init__(self, info, host: str = "127.0.0.1", port: int = 8765, every: int = 1):
        fg = _sdk()
        self._every = EveryNth(every, "foxglove every")
        if isinstance(port, bool) or not isinstance(port, int) or not 0 <= port < 65536:
            raise ConfigError(None, "--foxglove", "a port 1-65535", port)
        self.context = fg.Context()
        self.topics = Topics(fg, self.context, info.columns, tuple(law_signals(info.attrs)))
        try:
            self.server = fg.start_server(name="rig-runtime", host=host, port=port, context=self.context)
        except Exception as e:  # noqa: BLE001 - the SDK raises its own types (address in use, bad host)
            raise ConfigError(None, "--foxglove", f"an address to listen on ({str(e).splitlines()[0]})",
                              f"{host}:{port}") from None
        self.host = host
        self.port = self.server.port

    def rows(self, block) -> None:
        block = self._every(block)
        if len(block):
            self.topics.rows(block)

    def event(self, ev: tuple) -> None:
        self.topics.event(ev)

    def status(self, st: dict) -> None:
        self.topics.status(st)

    def close(self) -> None:
        self.server.stop()


def export_mcap(log_path: str | Path, out_path: str | Path) -> int:
    """Write a log (``rig_runtime.app.export.read_log``) as an MCAP file Foxglove opens, with the
    topics and schemas of the live server (a log has no status snapshots: ``/rig/health``
    stays empty). Refuses to overwrite ``out_path``. Returns the number of rows written."""
    from .export import read_log

    fg = _sdk("mcap export")
    out = Path(out_path)
    if out.exists():
        raise ConfigError(str(out), "", "a file that does not exist yet (an export never overwrites)")
    log = read_log(log_path)
    cols = log["columns"]
    import numpy as np

    block = np.column_stack(list(cols.values())) if cols else np.empty((0, 0))
    ctx = fg.Context()
    topics = Topics(fg, ctx, list(cols), tuple(law_signals(log["attrs"])))
    try:
        writer = fg.open_mcap(os.fspath(out), context=ctx)
    except Exception as e:  # noqa: BLE001 - the SDK's own error types
        raise ConfigError(str(out), "", f"a writable output file ({str(e).splitlines()[0]})") from None
    with writer:
        ev = log["events"]
        events = sorted(zip(*(ev[k] for k in ("t", "kind", "device", "check", "value", "limit", "message"))),
                        key=lambda e: e[0])
        n, k, step = 0, 0, 1024
        for a in range(0, log["rows"], step):               # events interleaved in time order
            chunk = block[a:a + step]
            t_end = chunk[-1, topics.signals.t_index]
            while k < len(events) and events[k][0] <= t_end:
                topics.event(events[k])
                k += 1
            n += topics.rows(chunk)
        for e in events[k:]:
            topics.event(e)
    return n
