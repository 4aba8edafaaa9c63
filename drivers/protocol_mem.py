"""pyserial's URL handler for ``mem://NAME``: the host end of an in-process serial line
(:mod:`rig_runtime.wires`), opened with ``serial.serial_for_url`` like any port.

pyserial finds this module through ``serial.protocol_handler_packages`` (the package
``drivers`` is added there by :mod:`drivers.ports`). The port has no file descriptor
(``fd`` is None): a driver reads it through ``in_waiting`` and ``read`` or ``read_all``,
as any pyserial port without one (``socket://``, ``rfc2217://``). Line settings are
accepted and ignored (the wire carries bytes, not symbols). A hung-up line answers
``in_waiting`` and ``read_all`` with :class:`drivers.tty.HangUp` once its bytes are read,
as a tty's TIOCINQ does with EIO.
"""

from __future__ import annotations

import errno

from serial.serialutil import PortNotOpenError, SerialBase, SerialException

from rig_runtime import wires

from .tty import HangUp

__all__ = ["Serial"]


class Serial(SerialBase):
    """A pyserial port on the host end of an in-process serial line."""

    fd = None                           # no file descriptor: read by in_waiting + read

    def __init__(self, *args, **kwargs):
        self._end: wires.WireEnd | None = None
        super().__init__(*args, **kwargs)

    def open(self) -> None:
        if self.is_open:
            raise SerialException("port is already open")
        if self._port is None:
            raise SerialException("port must be configured before it can be used")
        try:
            self._end = wires.open_line(self._port)
        except FileNotFoundError as exc:
            raise SerialException(errno.ENOENT, f"could not open port {self._port}: {exc}") from exc
        self.is_open = True

    def close(self) -> None:
        self._end = None                # the line belongs to the device end; only this port closes
        self.is_open = False

    def _reconfigure_port(self) -> None:
        pass

    @property
    def in_waiting(self) -> int:
        end = self._end
        if end is None:
            raise PortNotOpenError()
        try:
            return end.pending()
        except ConnectionResetError as exc:
            raise HangUp(errno.EIO, "hang-up on the port") from exc

    def read(self, size: int = 1) -> bytes:
        end = self._end
        if end is None:
            raise PortNotOpenError()
        return end.read(size)

    def read_all(self) -> bytes:
        """Every unread byte, in one call (never waits)."""
        end = self._end
        if end is None:
            raise PortNotOpenError()
        rx = end.rx
        if rx.buf:
            return rx.read()
        if rx.closed:
            raise HangUp(errno.EIO, "hang-up on the port")
        return b""

    def write(self, data) -> int:
        end = self._end
        if end is None:
            raise PortNotOpenError()
        try:
            return end.write(bytes(data))
        except BrokenPipeError as exc:
            raise SerialException(f"write failed: {exc}") from exc

    def reset_input_buffer(self) -> None:
        if self._end is None:
            raise PortNotOpenError()
        self._end.rx.clear()

    def reset_output_buffer(self) -> None:
        pass

    def flush(self) -> None:
        pass

    # modem lines: none on this wire
    def _update_rts_state(self) -> None:
        pass

    def _update_dtr_state(self) -> None:
        pass

    def _update_break_state(self) -> None:
        pass

    @property
    def cts(self) -> bool:
        return True

    @property
    def dsr(self) -> bool:
        return True

    @property
    def ri(self) -> bool:
        return False

    @property
    def cd(self) -> bool:
        return True
