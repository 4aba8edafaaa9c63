"""Micro-Epsilon optoNCDT 1420-class laser triangulation sensors on RS-422: the driver.

:class:`LaserDriver` reads a serial port without blocking, decodes with the codec of
:mod:`drivers.optoncdt` (wire format, error codes) and turns the values into SI metres
with health.
"""

from __future__ import annotations

import math
import os
import select
from typing import NamedTuple

import serial

from rig_runtime.config import LaserDevice
from rig_runtime.errors import DeviceInitError, DeviceIOError
from rig_runtime.hardware import Driver, Freshness, Health, health

from .optoncdt import MAX_DISTANCE_X, X_PER_PERCENT, Decoded, FrameDecoder, error_reason

__all__ = ["LaserReading", "LaserDriver"]

_LDISC_FULL = 4095              # Linux n_tty holds this many unread bytes; more wait behind
_READ_CHUNK = 65536
_os_read = os.read              # module-level so a test can make the port fail
_HUP = select.POLLHUP | select.POLLERR | select.POLLNVAL
_NO_VALUES = Decoded(b"", [])
_NO_DATA = "no data yet"        # FRESH's note before the first valid value (t is NaN)


# --------------------------------------------------------------------------- driver
class LaserReading(NamedTuple):
    """One laser channel after a poll.

    What the driver observed, not a judgement of it: how old ``t`` may be and how many
    garbled bytes are too many is the supervisor's decision (``limits:``).

    ``value_m`` is the physical distance ``offset_mm + d_mm`` in metres of the latest valid
    value (or this cycle's mean with ``average``); NaN if the latest value was an error
    code, the port failed, or nothing valid has arrived yet. ``t`` is the ``now`` of the
    poll in which the latest valid value arrived (NaN before the first); it stays there
    while nothing new arrives, so its age tells how long the channel has been without a
    measurement. ``n_values`` counts the valid distance values decoded in this poll,
    ``values_total`` those since the port was opened; ``health.bad_frames`` counts the
    bytes discarded as garbled since then (so garbled data between two valid values is the
    difference of two readings' counts). ``raw_x`` is the latest value received (incl.
    error codes), -1 before the first. ``health`` is an immutable value (the same object
    poll after poll while nothing changes): INVALID only for what the device or the port
    said (an error code as the latest value, a read error, a hang-up), else FRESH — also
    when nothing arrived in this poll.
    """

    role: str
    value_m: float
    t: float
    health: Health
    n_values: int
    raw_x: int
    values_total: int


class LaserDriver(Driver):
    """One optoNCDT 1420 on a serial port (pyserial, non-blocking).

    ``port`` overrides ``cfg.port`` (the simulated backend passes a pty path). Health:
    INVALID when the latest value is an error code (cause names it) or the read failed
    (a hang-up included); FRESH otherwise, whatever the age of the latest value — the
    supervisor judges the age from ``t`` (one rule, one setting). ``poll`` never raises.
    ``last_values`` holds the raw values (distances and error codes) decoded by the latest
    poll, for a recorder that wants every sample.
    """

    def __init__(self, cfg: LaserDevice, port: str | None = None):
        super().__init__()
        self.cfg = cfg
        self.port = port if port is not None else cfg.port
        self.name = f"laser {cfg.role}"
        self._role = cfg.role
        # value_m = _gain·x + _bias  ==  (offset_mm + distance_mm_from_x(x, MR)) / 1000
        mr = cfg.measuring_range_mm
        self._gain = mr / (100.0 * X_PER_PERCENT * 1000.0)
        self._bias = (cfg.offset_mm - mr / 100.0) / 1000.0
        self._average = cfg.average
        self._ser: serial.Serial | None = None
        self._poller: select.poll | None = None
        self._reset_state()

    def _reset_state(self) -> None:
        """Fresh decoder, counters and latest-value memory (each open starts a session)."""
        self._decoder = FrameDecoder()
        self._last = _NO_VALUES                 # what the latest poll decoded
        self._counters = {"values": 0, "error_frames": 0, "read_errors": 0, "bytes": 0}
        self._errors = 0                # error codes received and read errors
        self._health = Health(Freshness.FRESH, _NO_DATA)   # the latest value handed out
        self._value = math.nan          # latest valid value (or cycle mean), m; reported only
                                        # while the latest value is not an error code
        self._value_t = math.nan        # poll time at which it arrived
        self._latest_error: str | None = None  # reason if the latest value was an error code
        self._raw_x = -1

    # ------------------------------------------------------------------ transport
    def counters(self) -> dict[str, int]:
        return dict(self._counters)

    def _configure(self) -> None:
        """Open the port 8N1 with ``timeout=0`` and drop bytes buffered before now."""
        self._reset_state()
        try:
            ser = serial.Serial(port=self.port, baudrate=self.cfg.baudrate,
                                bytesize=serial.EIGHTBITS, parity=serial.PARITY_NONE,
                                stopbits=serial.STOPBITS_ONE, timeout=0, write_timeout=0)
            ser.reset_input_buffer()
        except (serial.SerialException, OSError, ValueError) as exc:
            raise DeviceInitError(self.name, f"cannot open serial port {self.port!r}: {exc}") from exc
        self._ser = ser
        self._poller = select.poll()      # POLLHUP tells a vanished device from "no data yet"
        self._poller.register(ser.fd, select.POLLIN)

    def _close(self) -> None:
        self._poller = None
        ser, self._ser = self._ser, None
        if ser is not None:
            try:
                ser.close()
            except Exception:  # noqa: BLE001 - a vanished device must not stop shutdown
                pass

    def _read_available(self, data: bytes) -> bytes:
        """Finish a poll's first non-blocking ``read(2)`` (``data``) on the port pyserial
        opened (pyserial's ``in_waiting`` + ``read`` cost two system calls and ~5 µs more
        per poll): an empty read may be a hang-up; a read that filled the line discipline
        has more waiting behind it."""
        if not data:
            # VMIN = VTIME = 0: an empty read means "nothing yet" — unless the port also
            # polls readable, which is a hang-up (the device end is gone)
            if self._poller is not None and any(ev & _HUP for _, ev in self._poller.poll(0)):
                raise DeviceIOError(self.name, "device disconnected (hang-up on the port)")
            return data
        try:                    # the line discipline was full: more waits behind it
            return data + _os_read(self._ser.fd, _READ_CHUNK)
        except BlockingIOError:
            return data

    # ------------------------------------------------------------------ cycle
    def poll(self, now: float) -> LaserReading:
        """Drain the port, decode, and report the latest value with its health."""
        ser = self._ser
        if ser is None:
            return self._reading(Freshness.INVALID, "port not configured", math.nan, 0)
        try:
            # the usual case read here; an empty or full read is finished by _read_available
            data = _os_read(ser.fd, _READ_CHUNK)
            if not data or len(data) >= _LDISC_FULL:
                data = self._read_available(data)
        except BlockingIOError:
            data = b""
        except Exception as exc:  # noqa: BLE001 - poll must not raise inside the loop
            self._errors += 1
            self._counters["read_errors"] += 1
            self._last = _NO_VALUES
            self._decoder.reset()
            return self._reading(Freshness.INVALID, f"read error: {type(exc).__name__}: {exc}", math.nan, 0)
        if not data:
            self._last = _NO_VALUES
            return self._classify(0)
        self._counters["bytes"] += len(data)
        decoded = self._last = self._decoder.decode(data)
        return self._classify(self._take(decoded, now) if len(decoded) else 0)

    @property
    def last_values(self) -> list[int]:
        """Raw values (distances and error codes) decoded by the latest poll."""
        return self._last.values()

    def _take(self, decoded: Decoded, now: float) -> int:
        """Update the latest value/error from this cycle's values; return how many are valid."""
        last = decoded.last()
        self._raw_x = last
        if decoded.all_distances():             # the usual case
            n_valid = len(decoded)
            valid = decoded.values() if self._average else None
        else:
            valid = [x for x in decoded.values() if x <= MAX_DISTANCE_X]
            n_valid = len(valid)
            n_err = len(decoded) - n_valid
            self._errors += n_err
            self._counters["error_frames"] += n_err
        self._counters["values"] += n_valid
        if last > MAX_DISTANCE_X:
            self._latest_error = error_reason(last)    # _value keeps the last valid value
        else:
            self._latest_error = None
            x = sum(valid) / n_valid if self._average else last
            self._value = self._gain * x + self._bias
            self._value_t = now
        return n_valid

    def _classify(self, n_valid: int) -> LaserReading:
        """INVALID while the latest value is an error code, else FRESH (age is not judged here)."""
        if self._latest_error is not None:
            return self._reading(Freshness.INVALID, self._latest_error, math.nan, n_valid)
        return self._reading(Freshness.FRESH, "" if self._counters["values"] else _NO_DATA,
                             self._value, n_valid)

    def _reading(self, state: Freshness, cause: str, value: float, n_valid: int) -> LaserReading:
        h = self._health = health(self._health, state, cause, self._decoder.discarded, 0, self._errors)
        return LaserReading(self._role, value, self._value_t, h, n_valid, self._raw_x,
                            self._counters["values"])
