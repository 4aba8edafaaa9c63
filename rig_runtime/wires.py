"""In-process wires: the same bytes as on a pty or a TCP connection, without a kernel
object in between (lockstep dry runs: ``sim.wires: memory``, docs/dry-run.md).

A :class:`BytePipe` carries bytes one way, in order, up to ``capacity`` unread bytes (more
is refused, as a full tty buffer refuses it). Two pipes make a duplex :class:`Wire` with
two :class:`WireEnd` objects. Two kinds of named endpoint, each a URL ``mem://NAME``:

* a serial line (:func:`serial_line`): one wire between a device and its host port; the
  host side is opened by name (``open_line``; the drivers reach it through pyserial's
  ``serial_for_url``, see ``drivers/protocol_mem.py``), like a pty's slave path;
* a stream server (:func:`listen`): every :func:`connect` to the name makes a new wire,
  handed to the server's ``accept`` queue, like a TCP listener on 127.0.0.1.

Reads never wait unless asked to (:meth:`WireEnd.wait_readable`, for a blocking start-up
read with a timeout); a write wakes a waiting reader only if one waits. One writer and one
reader per direction (the pattern of every wire here) need no lock: ``bytearray`` appends
and deletions of a prefix are single operations under the interpreter lock. Closing either
end hangs the wire up: the other end reads what is left, then sees the hang-up.
"""

from __future__ import annotations

import itertools
import threading
import time
from collections import deque
from typing import Callable, Optional

__all__ = ["SCHEME", "BytePipe", "Wire", "WireEnd", "Listener", "serial_line", "close_line", "open_line",
           "listen", "connect", "unique_name", "is_url"]

SCHEME = "mem://"
DEFAULT_CAPACITY = 1 << 16      # unread bytes a pipe holds (a pty's buffers hold about as much)

_lines: dict[str, "Wire"] = {}
_listeners: dict[str, "Listener"] = {}
_lock = threading.Lock()
_ids = itertools.count()


def is_url(name: str) -> bool:
    return isinstance(name, str) and name.startswith(SCHEME)


def unique_name(prefix: str) -> str:
    """A name no other wire of this process has (``prefix`` says what it is for)."""
    return f"{prefix}-{next(_ids)}"


def _key(name: str) -> str:
    return name[len(SCHEME):] if name.startswith(SCHEME) else name


class BytePipe:
    """Bytes one way. ``on_data``: called (in the writer's thread) after each write that
    added bytes — a server that answers at once hooks in here."""

    __slots__ = ("buf", "capacity", "closed", "on_data", "_cond", "_waiting")

    def __init__(self, capacity: int = DEFAULT_CAPACITY) -> None:
        self.buf = bytearray()
        self.capacity = capacity
        self.closed = False
        self.on_data: Optional[Callable[[], None]] = None
        self._cond: Optional[threading.Condition] = None
        self._waiting = 0

    def write(self, data: bytes) -> int:
        """Append what fits; returns the bytes taken (0 on a hung-up pipe)."""
        if self.closed:
            return 0
        buf = self.buf
        n = len(data)
        room = self.capacity - len(buf)
        if n > room:
            data = data[:max(room, 0)]
            n = len(data)
        if n:
            buf += data
            if self._waiting:
                self._wake()
            if self.on_data is not None:
                self.on_data()
        return n

    def read(self, n: int = -1) -> bytes:
        """Up to ``n`` unread bytes (all with ``n`` < 0), never waiting."""
        buf = self.buf
        if n < 0 or n >= len(buf):
            data = bytes(buf)
        else:
            data = bytes(buf[:n])
        del buf[:len(data)]
        return data

    def clear(self) -> None:
        del self.buf[:]

    def close(self) -> None:
        self.closed = True
        self._wake()

    def _wake(self) -> None:
        cond = self._cond
        if cond is not None:
            with cond:
                cond.notify_all()

    def wait(self, timeout: Optional[float]) -> bool:
        """Wait until bytes are unread or the pipe is hung up (at most ``timeout`` s);
        whether there are bytes."""
        if self.buf or self.closed:
            return bool(self.buf)
        if self._cond is None:
            self._cond = threading.Condition()
        end = None if timeout is None else time.monotonic() + timeout
        with self._cond:
            self._waiting += 1
            try:
                while not self.buf and not self.closed:
                    left = None if end is None else end - time.monotonic()
                    if left is not None and left <= 0:
                        break
                    self._cond.wait(left)
            finally:
                self._waiting -= 1
        return bool(self.buf)


class WireEnd:
    """One end of a :class:`Wire`: writes go into ``tx``, reads come from ``rx``."""

    __slots__ = ("name", "rx", "tx")

    def __init__(self, name: str, rx: BytePipe, tx: BytePipe) -> None:
        self.name = name
        self.rx = rx
        self.tx = tx

    @property
    def hung_up(self) -> bool:
        """The wire is closed (by either end)."""
        return self.rx.closed or self.tx.closed

    def pending(self) -> int:
        """Unread bytes; :class:`ConnectionResetError` once the wire is hung up and drained."""
        n = len(self.rx.buf)
        if not n and self.rx.closed:
            raise ConnectionResetError("hang-up on the wire")
        return n

    def read(self, n: int = -1) -> bytes:
        return self.rx.read(n)

    def write(self, data: bytes) -> int:
        if self.tx.closed:
            raise BrokenPipeError("hang-up on the wire")
        return self.tx.write(data)

    def wait_readable(self, timeout: Optional[float]) -> bool:
        return self.rx.wait(timeout)

    # the calls a stream client makes on a non-blocking socket, with a socket's answers
    def send(self, data: bytes) -> int:
        return self.write(data)

    def recv(self, n: int) -> bytes:
        """Up to ``n`` bytes; b"" once hung up and drained; BlockingIOError while empty."""
        rx = self.rx
        if rx.buf:
            return rx.read(n)
        if rx.closed:
            return b""
        raise BlockingIOError("nothing to read")

    def close(self) -> None:
        """Hang the wire up for both ends."""
        self.rx.close()
        self.tx.close()


class Wire:
    """A duplex wire: ``a`` and ``b`` are its two ends."""

    def __init__(self, name: str, capacity: int = DEFAULT_CAPACITY) -> None:
        ab, ba = BytePipe(capacity), BytePipe(capacity)
        self.name = name
        self.a = WireEnd(name, rx=ba, tx=ab)
        self.b = WireEnd(name, rx=ab, tx=ba)

    def close(self) -> None:
        self.a.close()


# --------------------------------------------------------------------------- serial lines
def serial_line(name: str, capacity: int = DEFAULT_CAPACITY) -> Wire:
    """A named serial line: ``a`` is the device's end, ``b`` the host's (what
    :func:`open_line` hands out); the URL is ``mem://NAME``. Unregistered when closed
    through :func:`close_line`."""
    w = Wire(name, capacity)
    with _lock:
        if name in _lines:
            raise ValueError(f"a wire named {name!r} exists already")
        _lines[name] = w
    return w


def close_line(w: Wire) -> None:
    with _lock:
        if _lines.get(w.name) is w:
            del _lines[w.name]
    w.close()


def open_line(url: str) -> WireEnd:
    """The host end of the serial line ``url`` (``mem://NAME`` or ``NAME``);
    FileNotFoundError if there is none (like a device path that does not exist)."""
    key = _key(url)
    with _lock:
        w = _lines.get(key)
    if w is None or w.a.hung_up:
        raise FileNotFoundError(f"no in-process serial line {SCHEME}{key}")
    return w.b


# --------------------------------------------------------------------------- stream servers
class Listener:
    """A named stream endpoint: each :func:`connect` appends the server's end of a new wire
    to ``accepted`` and calls ``on_connect`` (if set) with it."""

    def __init__(self, name: str, capacity: int) -> None:
        self.name = name
        self.capacity = capacity
        self.accepted: deque[WireEnd] = deque()
        self.on_connect: Optional[Callable[[WireEnd], None]] = None
        self.closed = False

    @property
    def url(self) -> str:
        return SCHEME + self.name

    def close(self) -> None:
        with _lock:
            if _listeners.get(self.name) is self:
                del _listeners[self.name]
        self.closed = True


def listen(name: str, capacity: int = DEFAULT_CAPACITY) -> Listener:
    with _lock:
        if name in _listeners:
            raise ValueError(f"an endpoint named {name!r} exists already")
        ls = _listeners[name] = Listener(name, capacity)
    return ls


def connect(url: str) -> WireEnd:
    """A new connection to the endpoint ``url``; the client's end. ConnectionRefusedError
    if nothing listens there (like a closed TCP port)."""
    key = _key(url)
    with _lock:
        ls = _listeners.get(key)
    if ls is None or ls.closed:
        raise ConnectionRefusedError(f"nothing listens at {SCHEME}{key}")
    w = Wire(key, ls.capacity)
    ls.accepted.append(w.a)
    if ls.on_connect is not None:
        ls.on_connect(w.a)
    return w.b
