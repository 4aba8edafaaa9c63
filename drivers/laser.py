"""Micro-Epsilon optoNCDT 1420-class laser triangulation sensors on RS-422: the driver.

:class:`LaserDriver` reads a serial port without blocking, decodes with the codec of
:mod:`drivers.optoncdt` (wire format, error codes) and turns the values into SI metres
with health.
"""

from __future__ import annotations

import math
import os
from typing import NamedTuple

import serial

from rig_runtime.config import LaserDevice
from rig_runtime.errors import DeviceInitError, DeviceIOError
from rig_runtime.hardware import Driver, Freshness, Health, health

from .ports import open_port
from .tty import HangUp, bytes_waiting
from .optoncdt import MAX_DISTANCE_X, X_PER_PERCENT, Decoded, FrameDecoder, error_reason

__all__ = ["LaserReading", "LaserDriver"]

_os_read = os.read              # module-level so a test can make the port fail
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

    ``port`` overrides ``cfg.port`` (the simulated backend passes a pty path or a
    ``mem://`` URL). Any name pyserial opens is a port (:mod:`drivers.ports`): a tty is
    read with one TIOCINQ query and one ``read(2)``, a port without a file descriptor
    (a URL) with pyserial's ``read_all`` — the same bytes either way. Health:
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
        self._inq = bytearray(4)        # TIOCINQ's answer, reused poll after poll
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
            ser = open_port(self.port, baudrate=self.cfg.baudrate,
                            bytesize=serial.EIGHTBITS, parity=serial.PARITY_NONE,
                            stopbits=serial.STOPBITS_ONE, timeout=0, write_timeout=0)
            ser.reset_input_buffer()
        except (serial.SerialException, OSError, ValueError) as exc:
            raise DeviceInitError(self.name, f"cannot open serial port {self.port!r}: {exc}") from exc
        self._ser = ser

    def _close(self) -> None:
        ser, self._ser = self._ser, None
        if ser is not None:
            try:
                ser.close()
            except Exception:  # noqa: BLE001 - a vanished device must not stop shutdown
                pass

    def _pending(self, fd: int) -> int:
        """Bytes the line discipline holds for us (:func:`drivers.tty.bytes_waiting`: asked,
        not read blind, so the loop never waits for the kernel's worker); a hang-up raises."""
        try:
            return bytes_waiting(fd, self._inq)
        except HangUp as exc:
            raise DeviceIOError(self.name, "device disconnected (hang-up on the port)") from exc

    def _read_all(self, ser) -> bytes:
        """What a port without a file descriptor holds (pyserial's ``read_all``: never
        waits); a hang-up raises as for a tty."""
        try:
            return ser.read_all()
        except HangUp as exc:
            raise DeviceIOError(self.name, "device disconnected (hang-up on the port)") from exc

    # ------------------------------------------------------------------ cycle
    def poll(self, now: float) -> LaserReading:
        """Drain the port, decode, and report the latest value with its health."""
        ser = self._ser
        if ser is None:
            return self._reading(Freshness.INVALID, "port not configured", math.nan, 0)
        try:
            fd = getattr(ser, "fd", None)
            if fd is not None:
                # read only what the line discipline holds: never a wait for the kernel's worker
                n = self._pending(fd)
                data = _os_read(fd, n) if n > 0 else b""
            else:                               # a port without a file descriptor (a URL)
                data = self._read_all(ser)
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
        return self._classify(self._take(decoded, now) if decoded.count else 0)

    @property
    def last_values(self) -> list[int]:
        """Raw values (distances and error codes) decoded by the latest poll."""
        return self._last.values()

    def _take(self, decoded: Decoded, now: float) -> int:
        """Update the latest value/error from this cycle's values; return how many are valid."""
        last = decoded.last()
        self._raw_x = last
        if decoded.all_distances():             # the usual case
            n_valid = decoded.count
            valid = decoded.values() if self._average else None
        else:
            valid = [x for x in decoded.values() if x <= MAX_DISTANCE_X]
            n_valid = len(valid)
            n_err = decoded.count - n_valid
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
