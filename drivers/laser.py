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
from .optoncdt import MAX_DISTANCE_X, X_PER_PERCENT, FrameDecoder, error_reason

__all__ = ["LaserReading", "LaserDriver"]

_os_read = os.read              # module-level so a test can make the port fail
_HUNG_UP = "device disconnected (hang-up on the port)"
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
        self._decoder = FrameDecoder()          # its latest chunk: what the latest poll decoded
        self._n_values = self._n_error_frames = self._n_read_errors = self._n_bytes = 0
        self._errors = 0                # error codes received and read errors
        self._health = Health(Freshness.FRESH, _NO_DATA)   # the latest value handed out
        self._value = math.nan          # latest valid value (or cycle mean), m; reported only
                                        # while the latest value is not an error code
        self._value_t = math.nan        # poll time at which it arrived
        self._latest_error: str | None = None  # reason if the latest value was an error code
        self._raw_x = -1

    # ------------------------------------------------------------------ transport
    def counters(self) -> dict[str, int]:
        return {"values": self._n_values, "error_frames": self._n_error_frames,
                "read_errors": self._n_read_errors, "bytes": self._n_bytes}

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

    # ------------------------------------------------------------------ cycle
    def poll(self, now: float) -> LaserReading:
        """Drain the port, decode, and report the latest value with its health.

        A tty is asked how many bytes its line discipline holds (:func:`drivers.tty.bytes_waiting`:
        never a wait for the kernel's worker) and read with one ``read(2)``; a port without a
        file descriptor with pyserial's ``read_all`` (never waits). A hang-up on either is a
        read error."""
        ser = self._ser
        dec = self._decoder
        n_valid = 0
        failed = None                           # why nothing could be read
        if ser is None:
            failed = "port not configured"
        else:
            try:
                fd = getattr(ser, "fd", None)
                if fd is not None:
                    n = bytes_waiting(fd, self._inq)
                    data = _os_read(fd, n) if n > 0 else b""
                else:                           # a port without a file descriptor (a URL)
                    data = ser.read_all()
            except BlockingIOError:
                data = b""
            except Exception as exc:  # noqa: BLE001 - poll must not raise inside the loop
                if isinstance(exc, HangUp):
                    exc = DeviceIOError(self.name, _HUNG_UP)
                self._errors += 1
                self._n_read_errors += 1
                dec.reset()
                failed = f"read error: {type(exc).__name__}: {exc}"
        if failed is not None:
            state, cause, value = Freshness.INVALID, failed, math.nan
        else:
            if data:
                self._n_bytes += len(data)
                if dec.decode(data):
                    # the latest value/error from this poll's values; how many are valid
                    last = self._raw_x = dec.last
                    if dec.distances_only:      # the usual case
                        n_valid = dec.count
                        valid = dec.values() if self._average else None
                    else:
                        valid = [x for x in dec.values() if x <= MAX_DISTANCE_X]
                        n_valid = len(valid)
                        n_err = dec.count - n_valid
                        self._errors += n_err
                        self._n_error_frames += n_err
                    self._n_values += n_valid
                    if last > MAX_DISTANCE_X:
                        self._latest_error = error_reason(last)    # _value keeps the last valid value
                    else:
                        self._latest_error = None
                        self._value = self._gain * (sum(valid) / n_valid if self._average else last) + self._bias
                        self._value_t = now
            else:
                dec.clear()
            if self._latest_error is not None:  # INVALID while the latest value is an error code
                state, cause, value = Freshness.INVALID, self._latest_error, math.nan
            else:
                state, cause, value = Freshness.FRESH, "" if self._n_values else _NO_DATA, self._value
        h = self._health = health(self._health, state, cause, dec.discarded, 0, self._errors)
        return LaserReading(self._role, value, self._value_t, h, n_valid, self._raw_x, self._n_values)

    @property
    def last_values(self) -> list[int]:
        """Raw values (distances and error codes) decoded by the latest poll."""
        return self._decoder.values()
