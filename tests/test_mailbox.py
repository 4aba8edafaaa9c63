"""The operator mailbox: codec round trips, one command taken once, answers matched to
their command, torn and corrupted copies rejected (and taken on the next call)."""

import math
import struct

import pytest
from hypothesis import given, strategies as st

from rig_runtime import mailbox, seqlock
from rig_runtime.mailbox import KINDS, MESSAGE_BYTES, NAME_BYTES, SIZE, Command, Mailbox

names = st.text(max_size=NAME_BYTES).filter(lambda s: len(s.encode("utf-8")) <= NAME_BYTES)
values = st.floats(allow_nan=True, allow_infinity=True)


def pair():
    buf = bytearray(SIZE)
    return buf, Mailbox(memoryview(buf)), Mailbox(memoryview(buf))   # server side, loop side


def same(a: float, b: float) -> bool:
    return (math.isnan(a) and math.isnan(b)) or a == b


@given(kind=st.sampled_from(KINDS), name=names, value=values)
def test_command_round_trip(kind, name, value):
    _, server, loop = pair()
    seq = server.submit(kind, name, value)
    cmd = loop.take()
    assert isinstance(cmd, Command) and cmd.seq == seq
    assert (cmd.kind, cmd.name) == (kind, name) and same(cmd.value, value)
    assert loop.take() is None                  # taken once


@given(ok=st.booleans(), message=st.text(max_size=400))
def test_answer_round_trip(ok, message):
    _, server, loop = pair()
    seq = server.submit("stop")
    assert server.result(seq) is None           # pending
    loop.answer(loop.take().seq, ok, message)
    got_ok, got = server.result(seq)
    assert got_ok is ok
    raw = message.encode("utf-8", "replace")
    assert got.encode("utf-8") == raw[:len(got.encode("utf-8"))]   # a prefix, cut at a character
    assert len(got.encode("utf-8")) <= MESSAGE_BYTES
    if len(raw) <= MESSAGE_BYTES:
        assert got == message.encode("utf-8", "replace").decode("utf-8")


@given(cmds=st.lists(st.tuples(st.sampled_from(KINDS), names, values), min_size=1, max_size=6))
def test_sequence_numbers_grow_and_each_answer_names_its_command(cmds):
    _, server, loop = pair()
    seqs = []
    for kind, name, value in cmds:
        seq = server.submit(kind, name, value)
        assert not seqs or seq > seqs[-1]
        seqs.append(seq)
        cmd = loop.take()
        assert cmd.seq == seq
        loop.answer(seq, True, f"done {seq}")
        assert server.result(seq) == (True, f"done {seq}")
        if len(seqs) > 1:
            assert server.result(seqs[-2]) is None   # the slot holds the latest answer only


def test_nothing_pending_on_a_zero_filled_region():
    _, server, loop = pair()
    assert loop.take() is None
    assert server.result(0) is None


def test_an_untaken_command_is_replaced_by_the_next():
    _, server, loop = pair()
    server.submit("set", "K_P_y", 4.0)
    seq = server.submit("stop")
    cmd = loop.take()
    assert (cmd.seq, cmd.kind, cmd.name) == (seq, "stop", "") and math.isnan(cmd.value)
    assert loop.take() is None


def test_a_command_being_written_is_taken_on_the_next_call():
    buf, server, loop = pair()
    seq = server.submit("set", "K_I_y", 12.0)
    struct.pack_into("<Q", buf, 0, seq + 1)     # the writer is mid-write again (odd)
    assert loop.take() is None and loop.rejected == 1
    struct.pack_into("<Q", buf, 0, seq)         # … and done
    assert loop.take() == Command(seq, "set", "K_I_y", 12.0)


def test_a_corrupted_copy_is_rejected():
    buf, server, loop = pair()
    seq = server.submit("set", "K_I_y", 12.0)
    good = buf[16]
    buf[16] ^= 0xFF                             # payload differs from its CRC (torn or reordered stores)
    assert loop.take() is None and loop.rejected == 1
    buf[16] = good
    assert loop.take().seq == seq
    loop.answer(seq, True, "ok")
    off = mailbox._ANS_OFF + 16 + 12
    buf[off] ^= 0x01                            # a torn answer is not returned either
    assert server.result(seq) is None
    buf[off] ^= 0x01
    assert server.result(seq) == (True, "ok")


def test_unknown_kind_and_long_name_are_refused_at_submit():
    _, server, _ = pair()
    with pytest.raises(ValueError, match="unknown command kind"):
        server.submit("format-disk")
    with pytest.raises(ValueError, match="longer than"):
        server.submit("set", "x" * (NAME_BYTES + 1), 1.0)


def test_too_small_a_region_is_refused():
    with pytest.raises(ValueError, match=f"needs {SIZE} bytes"):
        Mailbox(memoryview(bytearray(SIZE - 1)))


def test_take_with_nothing_pending_reads_only_the_sequence_number(monkeypatch):
    """Nothing pending: one unpack of the command slot's lock, no payload copy or CRC."""
    _, server, loop = pair()
    loop.take() if server.submit("stop") else None
    calls = []
    monkeypatch.setattr(seqlock, "read", lambda *a: calls.append(a))
    monkeypatch.setattr(seqlock.zlib, "crc32", lambda *a: calls.append(a))
    for _ in range(100):
        assert loop.take() is None
    assert calls == []
