"""A python-can bus for in-process simulation, like ``interface="virtual"`` but cheaper.

python-can's virtual bus deep-copies every frame for every receiver (≈ 16 µs each here),
which is most of the CAN cost of a lockstep dry run. This bus snapshots a sent frame once
into a fresh ``can.Message`` (its data copied) and hands that same object to every other
bus on the channel: receivers must not modify received messages, which neither
python-can's listeners nor canopen do. ``send_owned`` skips even that copy for a sender
that gives its message up. ``recv(timeout)`` blocks like any bus, so canopen's notifier
threads work on it during start-up; ``recv`` without filters skips ``BusABC.recv``'s
filter and logging layer (the lockstep cycle drains with ``recv(0)``). Each bus keeps the
list of the buses a frame it sends goes to, updated when a bus joins or leaves the channel
(not worked out per frame).
"""

from __future__ import annotations

import collections
import threading
import time
from typing import Any, Optional

import can

_channels: dict[str, list["LockstepBus"]] = {}
_lock = threading.Lock()
_Message = can.Message
_now = time.time


def _received_copy(msg: can.Message, channel: str, timestamp: float) -> can.Message:
    """The frame as its receivers get it: a new message, data copied once (a bytearray is
    kept); positional arguments cost a third of the keyword call."""
    return _Message(timestamp, msg.arbitration_id, msg.is_extended_id, msg.is_remote_frame,
                    msg.is_error_frame, channel, msg.dlc, bytearray(msg.data),
                    msg.is_fd, True, msg.bitrate_switch, msg.error_state_indicator)


def _update_receivers(peers: "list[LockstepBus]") -> None:
    """Each bus of a channel: the buses its frames go to (the others, itself too with
    ``receive_own_messages``), in the order they joined. Caller holds ``_lock``."""
    for bus in peers:
        bus._receivers = [b for b in peers if b is not bus or bus._own]


class LockstepBus(can.BusABC):
    def __init__(self, channel: str = "lockstep", receive_own_messages: bool = False, **kwargs: Any):
        self._waiting = 0               # receivers blocked in recv(timeout > 0)
        super().__init__(channel=channel, **kwargs)
        self.channel_info = f"lockstep bus {channel}"
        self._channel = channel
        self._own = receive_own_messages
        self._queue: collections.deque = collections.deque()
        self._cond = threading.Condition()
        self._open = True
        self._receivers: list[LockstepBus] = []     # the buses a frame sent here goes to
        with _lock:
            peers = _channels.setdefault(channel, [])
            peers.append(self)
            _update_receivers(peers)

    def send(self, msg: can.Message, timeout: Optional[float] = None) -> None:
        if not self._open:
            raise can.CanOperationError("lockstep bus is shut down")
        self._deliver(_received_copy(msg, self._channel, _now()))

    def send_many(self, msgs: "list[can.Message]") -> None:
        """Send several frames in order, each copied as by :meth:`send` (the batch call
        ``DriveBus.write`` uses for SYNC + RPDOs when a bus offers it)."""
        if not self._open:
            raise can.CanOperationError("lockstep bus is shut down")
        deliver, ch, now = self._deliver, self._channel, _now()
        for msg in msgs:
            deliver(_received_copy(msg, ch, now))

    def send_owned(self, msg: can.Message) -> None:
        """Send ``msg`` itself, not a copy: the caller must never touch it again."""
        if not self._open:
            raise can.CanOperationError("lockstep bus is shut down")
        msg.timestamp = _now()
        msg.channel = self._channel
        self._deliver(msg)

    def send_many_owned(self, msgs: "list[can.Message]") -> None:
        """Send several messages in order, each as by :meth:`send_owned` (one time stamp for
        the batch, as :meth:`send_many`): the caller must never touch them again."""
        if not self._open:
            raise can.CanOperationError("lockstep bus is shut down")
        deliver, ch, now = self._deliver, self._channel, _now()
        for msg in msgs:
            msg.timestamp = now
            msg.channel = ch
            deliver(msg)

    def _deliver(self, msg: can.Message) -> None:
        for bus in self._receivers:
            bus._queue.append(msg)
            # a receiver counts itself under the lock before it checks the queue, so a
            # zero here means it will see this frame without being woken
            if bus._waiting:
                with bus._cond:
                    bus._cond.notify()

    def recv(self, timeout: Optional[float] = None) -> Optional[can.Message]:
        if self._filters is None:
            q = self._queue
            if q:
                return q.popleft()
            if timeout == 0:
                return None
        return super().recv(timeout)

    def _recv_internal(self, timeout: Optional[float]):
        q = self._queue
        if q:
            return q.popleft(), False
        if timeout == 0:
            return None, False
        with self._cond:
            self._waiting += 1
            try:
                end = None if timeout is None else time.monotonic() + timeout
                while not q:
                    remaining = None if end is None else end - time.monotonic()
                    if remaining is not None and remaining <= 0:
                        return None, False
                    self._cond.wait(remaining)
                return q.popleft(), False
            finally:
                self._waiting -= 1

    def shutdown(self) -> None:
        if self._open:
            self._open = False
            with _lock:
                peers = _channels.get(self._channel, [])
                if self in peers:
                    peers.remove(self)
                self._receivers = []
                _update_receivers(peers)
                if not peers:
                    _channels.pop(self._channel, None)
        super().shutdown()
