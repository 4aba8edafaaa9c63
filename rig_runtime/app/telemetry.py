"""Live telemetry over UDP as JSON datagrams that PlotJuggler's UDP server reads as they are.

A sidecar output (``rig_runtime.app.telemetry:UdpTelemetry``, constructed in the recording
sidecar as ``UdpTelemetry(info, host=..., port=..., every=...)``). Each sent row becomes one
datagram of at most ``MAX_DATAGRAM`` bytes::

    {"timestamp": 1234.565, "t_run": 3.2,
     "state": {"code": 2, "name": "RUNNING"},
     "front": {"y": ..., "psi": ..., "delta_omega": ...},
     "rear":  {"y": ..., "psi": ..., "dpsi": ..., "delta_omega": ..., "y_ref": ..., "psi_ref": ..., "u": ...,
               "g": ..., "held": ..., "y_hat": ..., "degraded": 0},
     "speed": {"v": ..., "rear": ...},
     "timing": {"lateness": ..., "work": ...},
     "currents": {"fl": ..., "fr": ..., "rl": ..., "rr": ...},
     "health": {"deadline_misses": 0, "skipped_periods": 0, "recorder_healthy": 1},
     "devices": {"b_f": {"state": 0, "bad_frames": 0, "timeouts": 0, "errors": 0}, ...}}

``<carrier>_law`` holds the control law's signals by the names the law declares (the log's
``law_signals`` attribute, :func:`rig_runtime.logformat.law_signals`; its columns
``<carrier>_<name>``), so a new law's signals appear without a change here. They travel in a
second datagram per row, ``{"timestamp": ..., "front_law": {...}, "rear_law": {...}}`` (same
timestamp: PlotJuggler joins them), so the first keeps its room for the health fields.
SI units throughout (m, rad, rad/s, A, s). Values that are NaN in the row are left out of
the datagram (JSON has no NaN; PlotJuggler shows a gap). The field set is fixed when the
output is built: ``RowSignals`` maps the log's columns to the nested fields once (a column
index per field) and the worst-case size of the row part is computed then; the device part
(from the ~5 Hz status snapshot) is encoded when a snapshot arrives and fitted into what is
left, dropping the least important fields first (driver counters, then per-device counters,
then the device list) rather than exceeding the limit.

The same field layout feeds the Foxglove output (``rig_runtime.app.foxglove_out``): the
selection of signals is written once, here.
"""

from __future__ import annotations

import json
import math
import socket
import sys
from dataclasses import dataclass
from typing import Any, Sequence
from urllib.parse import urlsplit

import numpy as np

from ..config import WHEELS
from ..errors import ConfigError
from ..logformat import law_signals
from ..safety import State

MAX_DATAGRAM = 2048            # bytes; PlotJuggler's UDP server reads datagrams up to this size
DEFAULT_PORT = 9870            # PlotJuggler's UDP server default
DEVICE_STATE_CODES = {"fresh": 0, "stale": 1, "invalid": 2}
STATE_NAMES = {int(s): s.name for s in State}
CARRIERS = (("front", "f"), ("rear", "r"))
# a float's longest JSON text (repr), used for the worst-case size of the row part
_WIDEST_FLOAT = -2.2250738585072014e-308
_SEP = (",", ":")


def parse_udp_url(url: str, *, option: str = "--telemetry") -> tuple[str, int]:
    """``udp://HOST:PORT`` (IPv6 as ``udp://[::1]:PORT``) -> ``(host, port)``; a
    ``ConfigError`` naming the option and what is wrong otherwise."""
    expected = "udp://HOST:PORT (e.g. udp://127.0.0.1:9870)"
    if not isinstance(url, str) or not url:
        raise ConfigError(None, option, expected, url)
    try:
        parts = urlsplit(url)
        port = parts.port
    except ValueError as e:
        raise ConfigError(None, option, f"{expected}; {e}", url) from None
    if parts.scheme != "udp":
        raise ConfigError(None, option, f"{expected}; the scheme must be udp://", url)
    if not parts.hostname:
        raise ConfigError(None, option, f"{expected}; the host is missing", url)
    if port is None or port == 0:
        raise ConfigError(None, option, f"{expected}; the port is missing (1-65535)", url)
    if parts.path not in ("", "/") or parts.query or parts.fragment or parts.username:
        raise ConfigError(None, option, f"{expected}; nothing may follow the port", url)
    return parts.hostname, port


class EveryNth:
    """Rows 0, N, 2N, ... of a stream that arrives in blocks of any size."""

    def __init__(self, every: int, option: str = "--telemetry-every"):
        if isinstance(every, bool) or not isinstance(every, int) or every < 1:
            raise ConfigError(None, option, "an integer >= 1 (send every Nth cycle)", every)
        self.every = every
        self.seen = 0

    def __call__(self, block: np.ndarray) -> np.ndarray:
        first = (-self.seen) % self.every
        self.seen += len(block)
        return block[first::self.every]


@dataclass(frozen=True)
class Group:
    """One nested object of a message: its key, its field names and their column indices."""

    key: str
    fields: tuple[str, ...]
    index: tuple[int, ...]


class RowSignals:
    """Which log columns feed which nested field, built once from the column list.

    ``t``, ``t_run`` and ``state`` come first, then the groups in priority order (the most
    important first): carriers, the measured speed, timing, currents, then each controlled
    carrier's law signals (``law``: the law's declared signal names, ``{carrier}_law``).
    ``base=False``: the law's groups alone, with ``timestamp`` only (the UDP output sends them
    as a datagram of their own, so that they never crowd the health fields out).
    ``values(block)`` selects the needed columns of many rows with one numpy take;
    ``message(v)`` builds the nested dict of one row from that selection by position, never by
    looking a column up by name.
    """

    def __init__(self, columns: Sequence[str], law: Sequence[str] = (), base: bool = True):
        pos = {c: i for i, c in enumerate(columns)}
        if "t" not in pos:
            raise ConfigError(None, "columns", "a row layout with a 't' column", tuple(columns)[:4])
        groups: list[Group] = []

        def group(key: str, pairs: Sequence[tuple[str, str]]) -> None:
            have = [(f, pos[c]) for f, c in pairs if c in pos]
            if have:
                groups.append(Group(key, tuple(f for f, _ in have), tuple(i for _, i in have)))

        for carrier, s in CARRIERS if base else ():
            pairs = [("y", f"y_{s}"), ("psi", f"psi_a{s}"), ("dpsi", f"{carrier}_de_psi"),
                     ("delta_omega", f"dw_{s}")]
            if f"{carrier}_u_cmd" in pos:          # a controlled carrier: its reference and u
                ref = f"{carrier}_y_ref" if f"{carrier}_y_ref" in pos else "y_ref"
                pairs += [("y_ref", ref), ("psi_ref", f"{carrier}_psi_ref"), ("u", f"{carrier}_u_cmd"),
                          ("g", f"{carrier}_g"), ("held", f"{carrier}_held")]     # the speed schedule
            # an observed carrier: the estimate and DEGRADED (1: the lane runs on y_hat)
            pairs += [("y_hat", f"{carrier}_obs_y_hat"), ("degraded", f"{carrier}_obs_degraded")]
            group(carrier, pairs)
        if base:
            group("speed", [("v", "v_meas"), ("front", "front_v"), ("rear", "rear_v")])     # measured, m/s
            group("timing", [("lateness", "lateness"), ("work", "work")])
            group("currents", [(w, f"i_{w}") for w in WHEELS])
        for carrier, _ in CARRIERS:
            if f"{carrier}_u_cmd" in pos:          # a controlled carrier: its law's signals by name
                group(f"{carrier}_law", [(n, f"{carrier}_{n}") for n in law])
        self.groups: tuple[Group, ...] = tuple(groups)
        self._t = self.t_index = pos["t"]
        self._t_run = pos.get("t_run", -1) if base else -1
        self._state = pos.get("state", -1) if base else -1
        # one flat index array: t, t_run, state, then every group's fields in order
        flat = [self._t, max(self._t_run, self._t), max(self._state, self._t)]
        self._slices: list[tuple[str, tuple[str, ...], int, int]] = []
        for g in self.groups:
            self._slices.append((g.key, g.fields, len(flat), len(flat) + len(g.fields)))
            flat.extend(g.index)
        self._take = np.asarray(flat, dtype=np.intp)

    def drop(self, key: str) -> None:
        """Leave a group out of every message from now on."""
        self._slices = [s for s in self._slices if s[0] != key]
        self.groups = tuple(g for g in self.groups if g.key != key)

    def values(self, block: np.ndarray) -> list[list[float]]:
        """The selected columns of each row of ``block`` (n, len(columns)) as Python lists."""
        return block.take(self._take, axis=1).tolist()

    def message(self, v: list[float]) -> dict[str, Any]:
        """One row's nested message; non-finite values are left out (JSON has no NaN)."""
        msg: dict[str, Any] = {"timestamp": v[0]}
        if self._t_run >= 0 and v[1] - v[1] == 0.0:
            msg["t_run"] = v[1]
        if self._state >= 0 and v[2] == v[2]:
            code = int(v[2])
            msg["state"] = {"code": code, "name": STATE_NAMES.get(code, "?")}
        for key, fields, a, b in self._slices:
            msg[key] = {f: x for f, x in zip(fields, v[a:b]) if x - x == 0.0}
        return msg

    def worst_case(self) -> dict[str, Any]:
        """A message with every field present and at its widest JSON text (for sizing)."""
        msg: dict[str, Any] = {"timestamp": _WIDEST_FLOAT, "t_run": _WIDEST_FLOAT,
                               "state": {"code": 4, "name": max(STATE_NAMES.values(), key=len)}}
        for key, fields, _, _ in self._slices:
            msg[key] = {f: _WIDEST_FLOAT for f in fields}
        return msg


def status_parts(st: dict) -> dict[str, Any]:
    """The health fields of a status snapshot, in priority order: loop/recorder health, the
    devices (state 0 fresh / 1 stale / 2 invalid, -1 unknown, and their counters), the
    drivers' counters. Missing keys are left out (tolerant of a partial snapshot)."""
    out: dict[str, Any] = {}
    timing = st.get("timing") or {}
    health = {k: timing[k] for k in ("deadline_misses", "skipped_periods", "overrun_periods")
              if isinstance(timing.get(k), (int, float)) and not isinstance(timing.get(k), bool)}
    rec = st.get("recorder") or {}
    if isinstance(rec.get("healthy"), bool):
        health["recorder_healthy"] = int(rec["healthy"])
    if health:
        out["health"] = health
    lost = st.get("wheels_lost")
    if isinstance(lost, list) and lost:        # RECONFIGURED: 1 per drive the run does without
        out["reconfigured"] = {str(w): 1 for w in lost}
    devices = {}
    for d in st.get("devices") or ():
        if not isinstance(d, dict) or not d.get("name"):
            continue
        entry = {"state": DEVICE_STATE_CODES.get(d.get("state"), -1)}
        for k in ("bad_frames", "timeouts", "errors"):
            if isinstance(d.get(k), (int, float)) and not isinstance(d.get(k), bool):
                entry[k] = d[k]
        devices[str(d["name"]).replace(" ", "_")] = entry
    if devices:
        out["devices"] = devices
    counters = {str(k).replace(" ", "_"): v for k, v in (st.get("counters") or {}).items() if isinstance(v, dict)}
    if counters:
        out["counters"] = counters
    return out


def _shrink(parts: dict[str, Any]):
    """Ever smaller versions of the status part: all, without driver counters, devices with
    their state only, without devices, nothing."""
    yield parts
    parts = {k: v for k, v in parts.items() if k != "counters"}
    yield parts
    if "devices" in parts:
        parts = dict(parts, devices={n: {"state": d["state"]} for n, d in parts["devices"].items()})
        yield parts
        parts = {k: v for k, v in parts.items() if k != "devices"}
        yield parts
    yield {}


class UdpTelemetry:
    """Sends every ``every``-th row as one JSON datagram to ``host:port`` (PlotJuggler's UDP
    server with the JSON parser).

    ``timestamp`` is the row's ``t``: the loop's clock in seconds (``time.monotonic`` in
    a real-time run, simulated time in a lockstep dry run), so datagram times and the log's
    ``/cycles/t`` and ``/events/t`` agree. The socket is non-blocking; a failed send
    (ECONNREFUSED, ENOBUFS, EAGAIN, ...) is counted in ``send_errors`` and never raised: the
    viewer is optional, the recording is not.
    """

    def __init__(self, info, host: str = "127.0.0.1", port: int = DEFAULT_PORT, every: int = 1):
        self._every = EveryNth(every)
        if isinstance(port, bool) or not isinstance(port, int) or not 0 < port < 65536:
            raise ConfigError(None, "telemetry port", "an integer port 1-65535", port)
        try:
            found = socket.getaddrinfo(host, port, type=socket.SOCK_DGRAM)
        except (OSError, UnicodeError) as e:
            raise ConfigError(None, "telemetry host", f"a resolvable host name or address ({e})", host) from None
        # IPv4 first: "localhost" often resolves to ::1 first while viewers listen on 0.0.0.0
        family, _, _, _, addr = min(found, key=lambda a: a[0] != socket.AF_INET)
        self.addr = addr
        self.signals = RowSignals(info.columns)
        self.law = RowSignals(info.columns, tuple(law_signals(info.attrs)), base=False)   # its own datagram
        self.dropped_fields: list[str] = []
        for sig in (self.signals, self.law):
            while sig.groups and len(self._encode(sig.worst_case())) > MAX_DATAGRAM:
                last = sig.groups[-1].key     # lowest priority first
                sig.drop(last)
                self.dropped_fields.append(last)
        self._status_budget = MAX_DATAGRAM - len(self._encode(self.signals.worst_case())) - 1
        self._status_text = ""                     # ',"health":{...},"devices":{...}' or ""
        self.status_dropped = 0                    # snapshots that had to be shortened
        self.sent = 0
        self.sent_law = 0                          # the law's datagrams (one per sent row)
        self.send_errors = 0
        self.last_error = ""
        self._sock = socket.socket(family, socket.SOCK_DGRAM)
        self._sock.setblocking(False)
        if self.dropped_fields:
            print(f"telemetry: datagrams would exceed {MAX_DATAGRAM} bytes; left out: "
                  f"{', '.join(self.dropped_fields)}", file=sys.stderr)

    @staticmethod
    def _encode(msg: dict) -> bytes:
        return json.dumps(msg, separators=_SEP, allow_nan=False).encode()

    def datagram(self, v: list[float]) -> bytes | None:
        """The datagram of one row's selected values (``RowSignals.values``); None if the row
        has no finite time."""
        if not v[0] - v[0] == 0.0:
            return None
        body = self._encode(self.signals.message(v))
        if self._status_text:
            body = body[:-1] + self._status_text + b"}"
        assert len(body) <= MAX_DATAGRAM, f"telemetry datagram of {len(body)} bytes"
        return body

    def rows(self, block: np.ndarray) -> None:
        block = self._every(block)
        if not len(block):
            return
        sock, addr = self._sock, self.addr
        law = self.law if self.law.groups else None
        law_rows = law.values(block) if law is not None else ()
        for i, v in enumerate(self.signals.values(block)):
            data = self.datagram(v)
            if data is None:
                continue
            try:
                sock.sendto(data, addr)
                self.sent += 1
                if law is not None:
                    sock.sendto(self._encode(law.message(law_rows[i])), addr)
                    self.sent_law += 1
            except OSError as e:
                self.send_errors += 1
                self.last_error = f"{type(e).__name__}: {e}"

    def event(self, ev: tuple) -> None:
        """Events reach the viewer through the rows (the state) and the status (faults)."""

    def status(self, st: dict) -> None:
        parts = status_parts(st)
        for i, candidate in enumerate(_shrink(parts)):
            try:
                text = json.dumps(candidate, separators=_SEP, allow_nan=False)[1:-1].encode() if candidate else b""
            except (TypeError, ValueError):      # a NaN or non-number counter: leave this version out
                continue
            if len(text) + 1 <= self._status_budget:
                self._status_text = (b"," + text) if text else b""
                self.status_dropped += i > 0
                return

    def close(self) -> None:
        self._sock.close()
        if self.send_errors:
            print(f"telemetry: {self.send_errors} datagrams not sent ({self.last_error})", file=sys.stderr)
