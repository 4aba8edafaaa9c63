"""A python-can bus for in-process simulation, like ``interface="virtual"`` but cheaper.

python-can's virtual bus deep-copies every frame for every receiver (≈ 16 µs each here),
which is most of the CAN cost of a lockstep dry run. This bus snapshots a sent frame once
into a fresh ``can.Message`` (its data copied to ``bytes``) and hands that same object to
every other bus on the channel: receivers must not modify received messages, which
neither python-can's listeners nor canopen do. ``recv(timeout)`` blocks like any bus, so
canopen's notifier threads work on it during start-up.
"""

from __future__ import annotations

import collections
import threading
import time
from typing import Any, Optional

import can

_channels: dict[str, list["LockstepBus"]] = {}
_lock = threading.Lock()


class LockstepBus(can.BusABC):
    def __init__(self, channel: str = "lockstep", receive_own_messages: bool = False, **kwargs: Any):
        super().__init__(channel=channel, **kwargs)
        self.channel_info = f"lockstep bus {channel}"
        self._channel = channel
        self._own = receive_own_messages
        self._queue: collections.deque = collections.deque()
        self._cond = threading.Condition()
        self._open = True
        with _lock:
            _channels.setdefault(channel, []).append(self)
            self._peers = _channels[channel]

    def send(self, msg: can.Message, timeout: Optional[float] = None) -> None:
        if not self._open:
            raise can.CanOperationError("lockstep bus is shut down")
        snap = can.Message(timestamp=time.time(), arbitration_id=msg.arbitration_id,
                           is_extended_id=msg.is_extended_id, is_remote_frame=msg.is_remote_frame,
                           is_error_frame=msg.is_error_frame, dlc=msg.dlc, data=bytes(msg.data),
                           channel=self._channel, check=False)
        for bus in self._peers:
            if bus is not self or self._own:
                with bus._cond:
                    bus._queue.append(snap)
                    bus._cond.notify()

    def _recv_internal(self, timeout: Optional[float]):
        q = self._queue
        if q:
            return q.popleft(), False
        if timeout == 0:
            return None, False
        with self._cond:
            end = None if timeout is None else time.monotonic() + timeout
            while not q:
                remaining = None if end is None else end - time.monotonic()
                if remaining is not None and remaining <= 0:
                    return None, False
                self._cond.wait(remaining)
            return q.popleft(), False

    def shutdown(self) -> None:
        if self._open:
            self._open = False
            with _lock:
                peers = _channels.get(self._channel, [])
                if self in peers:
                    peers.remove(self)
                if not peers:
                    _channels.pop(self._channel, None)
        super().shutdown()
