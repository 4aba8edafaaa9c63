"""The seqlock slot: hand-checked layout and rejections, and a round-trip property."""

import struct
import zlib

import pytest
from hypothesis import given, strategies as st

from rig_runtime import seqlock
from rig_runtime.seqlock import HEADER_BYTES


def test_write_then_read_returns_the_payload_and_an_even_sequence():
    buf = bytearray(64)
    assert seqlock.write(buf, 8, b"hello") == 2
    assert seqlock.read(buf, 8, 40) == (2, b"hello")
    assert seqlock.seq(buf, 8) == 2
    # the header as documented: lock u64 | crc32 u32 | length u32, then the payload
    lock, crc, n = struct.unpack_from("<QII", buf, 8)
    assert (lock, n) == (2, 5)
    assert crc == zlib.crc32(b"hello", zlib.crc32(b"\x05\x00\x00\x00"))
    assert bytes(buf[8 + HEADER_BYTES:8 + HEADER_BYTES + 5]) == b"hello"
    assert bytes(buf[:8]) == bytes(8)                       # nothing outside the slot


def test_a_never_written_slot_reads_none():
    buf = bytearray(64)
    assert seqlock.seq(buf, 0) == 0
    assert seqlock.read(buf, 0, 48) is None


def test_the_sequence_moves_by_two_per_write():
    buf = bytearray(64)
    seqs = [seqlock.write(buf, 0, bytes([k]) * 3) for k in range(5)]
    assert seqs == [2, 4, 6, 8, 10]
    assert seqlock.read(buf, 0, 48) == (10, b"\x04" * 3)


def test_an_odd_lock_reads_none_and_the_next_write_completes():
    buf = bytearray(64)
    seqlock.write(buf, 0, b"abc")
    buf[0] |= 1                                             # a writer caught mid-write
    assert seqlock.read(buf, 0, 48) is None
    buf[0] &= 0xFE
    assert seqlock.read(buf, 0, 48) == (2, b"abc")          # nothing changed meanwhile
    buf[0] |= 1                                             # a writer that died mid-write …
    assert seqlock.write(buf, 0, b"xyz") == 4               # … is followed by an even lock
    assert seqlock.read(buf, 0, 48) == (4, b"xyz")


@pytest.mark.parametrize("where", [HEADER_BYTES, HEADER_BYTES + 3, 8, 11])
def test_a_corrupted_payload_or_crc_byte_reads_none(where):
    buf = bytearray(64)
    seqlock.write(buf, 0, b"abcd")
    buf[where] ^= 0x40
    assert seqlock.read(buf, 0, 48) is None
    buf[where] ^= 0x40
    assert seqlock.read(buf, 0, 48) == (2, b"abcd")


def test_a_stale_header_over_a_new_sequence_is_not_an_empty_payload():
    """Stores seen out of order: the new lock, but length and CRC still zero."""
    buf = bytearray(64)
    struct.pack_into("<Q", buf, 0, 2)
    assert seqlock.read(buf, 0, 48) is None
    seqlock.write(buf, 0, b"abcd")
    struct.pack_into("<I", buf, 12, 3)                      # a torn length: CRC fails
    assert seqlock.read(buf, 0, 48) is None


def test_variable_length_payloads_and_the_capacity():
    buf = bytearray(HEADER_BYTES + 100)
    seqlock.write(buf, 0, b"x" * 100)
    assert seqlock.read(buf, 0, 100) == (2, b"x" * 100)
    assert seqlock.read(buf, 0, 99) is None                 # longer than the reader allows
    seqlock.write(buf, 0, b"")                              # shorter, then empty
    assert seqlock.read(buf, 0, 100) == (4, b"")
    seqlock.write(buf, 0, b"yz")
    assert seqlock.read(buf, 0, 100) == (6, b"yz")


def test_a_payload_that_does_not_fit_is_refused_before_the_slot_changes():
    buf = bytearray(HEADER_BYTES + 4)
    seqlock.write(buf, 0, b"abcd")
    before = bytes(buf)
    with pytest.raises(ValueError, match="do not fit"):
        seqlock.write(buf, 0, b"abcde")
    assert bytes(buf) == before


def test_works_on_a_memoryview_region():
    base = bytearray(128)
    region = memoryview(base)[32:96]
    seqlock.write(region, 16, b"payload")
    assert seqlock.read(region, 16, 40) == (2, b"payload")
    assert struct.unpack_from("<Q", base, 48)[0] == 2


@given(payloads=st.lists(st.binary(max_size=300), min_size=1, max_size=5),
       slot=st.integers(0, 16), pad=st.integers(0, 64))
def test_round_trip_property(payloads, slot, pad):
    off = 8 * slot
    buf = bytearray(off + HEADER_BYTES + 300 + pad)
    for k, p in enumerate(payloads, 1):
        s = seqlock.write(buf, off, p)
        assert s == 2 * k and seqlock.seq(buf, off) == s
        assert seqlock.read(buf, off, 300) == (s, p)
    assert bytes(buf[:off]) == bytes(off)                   # nothing before the slot


@given(payload=st.binary(min_size=1, max_size=200), data=st.data())
def test_any_single_corrupted_byte_of_crc_or_payload_reads_none(payload, data):
    buf = bytearray(HEADER_BYTES + 200)
    seqlock.write(buf, 0, payload)
    i = data.draw(st.sampled_from([*range(8, 12), *range(HEADER_BYTES, HEADER_BYTES + len(payload))]))
    buf[i] ^= data.draw(st.integers(1, 255))
    assert seqlock.read(buf, 0, 200) is None
