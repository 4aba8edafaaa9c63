"""What a tty holds for its reader, asked without waiting: the one ``TIOCINQ`` query the
serial drivers (lasers, the SLCAN adapter) make before they read.

An empty tty's ``read(2)``/``poll(2)`` first waits for the kernel's flip-buffer work
(``n_tty_read``/``n_tty_poll`` → ``tty_buffer_flush_work``), run by an ordinary-priority
kworker — a real-time loop would wait for it. ``TIOCINQ`` (= ``FIONREAD``) only counts what
the line discipline holds, so bytes the kworker has not moved yet are read one poll later.
A hung-up tty (the device end gone: pty master closed, USB adapter unplugged) answers every
ioctl with EIO.
"""

from __future__ import annotations

import errno
import fcntl
import termios

__all__ = ["HangUp", "bytes_waiting"]

_ioctl = fcntl.ioctl
_FIONREAD = termios.FIONREAD


class HangUp(OSError):
    """The tty's device end is gone."""


def bytes_waiting(fd: int, buf: bytearray) -> int:
    """Bytes the line discipline holds for ``fd`` (``buf``: a reused 4-byte buffer); a
    hang-up raises :class:`HangUp`, any other failure its ``OSError``."""
    try:
        _ioctl(fd, _FIONREAD, buf, True)
    except OSError as exc:
        if exc.errno == errno.EIO:
            raise HangUp(exc.errno, "hang-up on the port") from exc
        raise
    return int.from_bytes(buf, "little", signed=True)
