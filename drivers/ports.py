"""Serial ports by name or URL: a device path (``/dev/ttyUSB0``, a pty) or any URL pyserial
knows (``socket://HOST:PORT``, ``rfc2217://…``, ``mem://NAME`` for an in-process serial
line of :mod:`rig_runtime.wires`, served by :mod:`drivers.protocol_mem`).

``open_port`` is ``serial.serial_for_url`` with this package among pyserial's URL handler
packages. A port with a file descriptor (a tty) is read by the drivers with one TIOCINQ
query and one ``read(2)`` (:mod:`drivers.tty`); a port without one through pyserial's
``in_waiting`` and ``read`` — what the port is, not who is at its other end, decides.
"""

from __future__ import annotations

from typing import Any

import serial

__all__ = ["open_port"]

if "drivers" not in serial.protocol_handler_packages:
    serial.protocol_handler_packages.append("drivers")      # drivers/protocol_mem.py: mem://


def open_port(port: str, **settings: Any) -> serial.SerialBase:
    """The port opened with ``settings`` (pyserial's keywords); pyserial's exceptions (and
    ValueError for an unknown URL scheme) propagate."""
    return serial.serial_for_url(port, **settings)
