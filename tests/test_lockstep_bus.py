"""The lockstep bus: who receives a frame as buses join and leave a channel."""

from __future__ import annotations

import itertools

import can

from sim_backend.lockstep_bus import LockstepBus

_ids = itertools.count()


def _frame(cob: int) -> can.Message:
    return can.Message(arbitration_id=cob, data=bytes([cob & 0xFF]), is_extended_id=False)


def _ids_of(bus: LockstepBus) -> list[int]:
    """The COB-IDs of every frame queued at ``bus`` (taken)."""
    out = []
    while (m := bus.recv(0)) is not None:
        out.append(m.arbitration_id)
    return out


def test_receivers_follow_joins_and_leaves():
    ch = f"test-lockstep-{next(_ids)}"
    a, b = LockstepBus(channel=ch), LockstepBus(channel=ch)
    own = LockstepBus(channel=ch, receive_own_messages=True)
    try:
        a.send(_frame(0x181))
        assert _ids_of(b) == [0x181] and _ids_of(own) == [0x181] and a.recv(0) is None
        own.send(_frame(0x182))
        assert _ids_of(own) == [0x182] and _ids_of(a) == [0x182] and _ids_of(b) == [0x182]
        b.shutdown()
        a.send(_frame(0x183))
        assert b.recv(0) is None and _ids_of(own) == [0x183]
        late = LockstepBus(channel=ch)
        try:
            a.send(_frame(0x184))
            assert _ids_of(late) == [0x184] and _ids_of(own) == [0x184]
        finally:
            late.shutdown()
    finally:
        for bus in (a, b, own):
            bus.shutdown()


def test_frames_arrive_in_order_each_copied_once_for_the_receivers():
    ch = f"test-lockstep-{next(_ids)}"
    a, b = LockstepBus(channel=ch), LockstepBus(channel=ch)
    try:
        sent = [_frame(0x200 + i) for i in range(5)]
        a.send_many(sent)
        got = [b.recv(0) for _ in range(5)]
        assert [g.arbitration_id for g in got] == [0x200 + i for i in range(5)] and b.recv(0) is None
        assert all(g is not s and g.data == s.data for g, s in zip(got, sent))   # copied once
        a.send(_frame(0x181))
        assert b.recv(0).arbitration_id == 0x181 and b.recv(0) is None
    finally:
        a.shutdown()
        b.shutdown()
