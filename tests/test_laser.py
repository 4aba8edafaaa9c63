"""optoNCDT 1420 laser: codec (hand-worked values, properties) and driver against the
virtual device over a real pty."""

from __future__ import annotations

import copy
import dataclasses
import json
import math
import pickle
import time

import numpy as np
import pytest

import drivers.laser as laser_mod
import serial
from hypothesis import given, settings
from hypothesis import strategies as st

from rig_runtime.errors import DeviceInitError
from rig_runtime.hardware import Freshness
from drivers.laser import LaserDriver
from drivers.optoncdt import (
    ERROR_CODES,
    MAX_DISTANCE_X,
    MAX_X,
    FrameDecoder,
    distance_mm_from_x,
    encode_value,
    encode_values,
    error_reason,
    x_from_distance_mm,
    xs_from_distance_mm,
)
from rig_runtime.config import LaserDevice
import sim_backend.virtual_laser as vl_mod
from sim_backend.virtual_laser import VirtualLaser

MR = 50.0                    # measuring range of the b_f/b_r lasers in configs/, mm
OFFSET = 45.0                # their offset_mm
STEP_M = MR * 102 / 65520 / 100 / 1000   # one x step in metres (≈ 0.78 µm for MR 50)
H = 0.005                    # control period, s


# =========================================================================== codec
@pytest.mark.parametrize("x, mr, d_mm", [
    (0, 50, -0.5),              # (102/65520·0 − 1)·50/100 = −1·0.5 = −0.5 = −MR/100
    (65520, 50, 50.5),          # (102 − 1)·0.5 = 50.5 = 1.01·MR
    (32760, 50, 25.0),          # (102·32760/65520 − 1)·0.5 = (51 − 1)·0.5 = 25 = MR/2
    (32760, 25, 12.5),          # (51 − 1)·0.25 = 12.5
    # start of the measuring range: 102·643 = 65586 = 65520 + 66 -> (66/65520)·0.5 ≈ 0.0005
    (643, 50, 66 / 65520 * 0.5),
    # end of the measuring range: 102·64877 = 6617454 = 101·65520 − 66 -> (100 − 66/65520)·0.5 ≈ 49.9995
    (64877, 50, (100 - 66 / 65520) * 0.5),
    (6552, 10, 0.92),           # 102·6552/65520 = 10.2 -> (10.2 − 1)·0.1 = 0.92
])
def test_distance_formula_hand_values(x, mr, d_mm):
    assert distance_mm_from_x(x, mr) == pytest.approx(d_mm, abs=1e-12)


def test_distance_inverse_rounds_and_clips():
    assert x_from_distance_mm(25.0, 50) == 32760
    assert x_from_distance_mm(-0.5, 50) == 0
    assert x_from_distance_mm(50.5, 50) == MAX_DISTANCE_X
    assert x_from_distance_mm(-3.0, 50) == 0            # clipped below
    assert x_from_distance_mm(80.0, 50) == MAX_DISTANCE_X  # clipped above
    # one step is 50·102/65520/100 mm ≈ 0.000778 mm; 0.4 step above 25 mm rounds down, 0.6 up
    step_mm = 50 * 102 / 65520 / 100
    assert x_from_distance_mm(25.0 + 0.4 * step_mm, 50) == 32760
    assert x_from_distance_mm(25.0 + 0.6 * step_mm, 50) == 32761
    with pytest.raises(ValueError):
        x_from_distance_mm(math.nan, 50)


def test_byte_layout_of_known_values():
    # 32760 = 0x7FF8: L6 = 0x38, M6 = (0x7FF8 >> 6) & 63 = 0x3F, H6 = 0x7FF8 >> 12 = 7
    # check: 56 + 63·64 + 7·4096 = 56 + 4032 + 28672 = 32760
    assert encode_value(32760) == bytes([0b00_111000, 0b01_111111, 0b10_000111])
    # 262076 = 0x3FFBC: L6 = 60, M6 = 62, H6 = 63; 60 + 62·64 + 63·4096 = 262076
    assert encode_value(262076) == bytes([0x3C, 0x7E, 0xBF])
    assert encode_value(0) == b"\x00\x40\x80"
    assert encode_value(MAX_X) == b"\x3f\x7f\xbf"
    for b, flag in zip(encode_value(12345), (0b00, 0b01, 0b10)):
        assert b >> 6 == flag
    with pytest.raises(ValueError):
        encode_value(MAX_X + 1)
    with pytest.raises(ValueError):
        encode_value(-1)
    assert encode_values([0, 32760, 262076]) == encode_value(0) + encode_value(32760) + encode_value(262076)
    assert encode_values([]) == b""
    with pytest.raises(ValueError):
        encode_values([1, MAX_X + 1])
    with pytest.raises(ValueError):
        encode_values([-1])
    xs = [int(x) for x in np.random.default_rng(1).integers(0, MAX_X + 1, 500)]
    assert encode_values(xs) == b"".join(encode_value(x) for x in xs)        # the frames it keeps too
    assert encode_values(xs) == b"".join(encode_value(x) for x in xs)
    assert encode_values(np.array(xs[:3])) == encode_values(xs[:3])


def test_many_distances_convert_like_one_with_the_device_codes_outside_the_span():
    mr, off = 25.0, 25.0
    d_m = [0.0249, 0.02495, 0.025, 0.0375, 0.05, 0.05025, 0.0503, float("inf"), -float("inf")]
    noise = [0.0, 1e-6, -1e-6, 3.3e-7]
    for d0 in d_m:
        xs = xs_from_distance_mm(noise, mr, base=d0, scale=1000.0, offset_mm=off, below=-1, above=-2)
        for e, x in zip(noise, xs):
            rel = (d0 + e) * 1000.0 - off
            want = -1 if rel < -0.25 else -2 if rel > 25.25 else x_from_distance_mm(rel, mr)
            assert x == want, (d0, e)
    assert xs_from_distance_mm([-3.0, 25.0, 80.0], 50) == [0, 32760, MAX_DISTANCE_X]    # clipped
    with pytest.raises(ValueError):
        xs_from_distance_mm([1.0, math.nan], 50)


def test_error_codes_decode_with_reason():
    assert error_reason(0) is None
    assert error_reason(MAX_DISTANCE_X) is None
    assert error_reason(262076) == "no peak (262076)"
    assert error_reason(262082) == "laser off (262082)"
    assert error_reason(262075) == "too much data for the baud rate (262075)"
    assert error_reason(MAX_DISTANCE_X + 1) == "unknown code 65521"
    assert error_reason(262079) == "unknown code 262079"   # a gap in the manual's table
    assert set(ERROR_CODES) == {262075, 262076, 262077, 262078, 262080, 262081, 262082}
    dec = FrameDecoder()
    assert dec.feed(encode_value(262078)) == [262078]
    assert error_reason(262078) == "peak after range (262078)"


def test_decoder_keeps_partial_frames_across_calls():
    data = encode_values([100, 200, 300])
    dec = FrameDecoder()
    out = []
    for i in range(len(data)):              # one byte at a time
        out += dec.feed(data[i:i + 1])
    assert out == [100, 200, 300]
    assert dec.discarded == 0 and dec.pending == 0 and dec.frames == 3
    assert dec.feed(b"") == []


def test_decoder_resynchronises_after_a_lost_byte():
    a, b, c = encode_value(100), encode_value(200), encode_value(300)
    dec = FrameDecoder()
    # frame b lost its M byte: L_b H_b cannot be a frame -> 2 bytes discarded
    assert dec.feed(a + b[0:1] + b[2:3] + c) == [100, 300]
    assert dec.discarded == 2
    # lost H at the end of one call, next call starts a new frame: L M discarded
    assert dec.feed(a[:2]) == []
    assert dec.pending == 2
    assert dec.feed(c) == [300]
    assert dec.discarded == 4
    # a byte flagged 11 is never part of a frame
    assert dec.feed(b"\xff" + a + b"\xc0") == [100]
    assert dec.discarded == 6
    dec.feed(a[:1])
    dec.reset()
    assert dec.pending == 0 and dec.discarded == 7


# --------------------------------------------------------------------------- properties
values = st.integers(0, MAX_X)


@given(values)
def test_value_bytes_value_round_trip(x):
    assert FrameDecoder().feed(encode_value(x)) == [x]


@given(st.integers(0, MAX_DISTANCE_X), st.sampled_from([10.0, 25.0, 50.0, 100.0, 200.0, 500.0]))
def test_distance_round_trip(x, mr):
    assert x_from_distance_mm(distance_mm_from_x(x, mr), mr) == x


def _chunked(data: bytes, cuts: list[int]) -> list[bytes]:
    """Split data at the given (sorted, deduplicated) offsets."""
    edges = [0] + sorted({c % (len(data) + 1) for c in cuts}) + [len(data)]
    return [data[a:b] for a, b in zip(edges, edges[1:])]


def _feed_all(dec: FrameDecoder, chunks: list[bytes]) -> list[int]:
    out: list[int] = []
    for c in chunks:
        out += dec.feed(c)
    return out


# garbage flagged 11 can never be part of a frame, so it must always be detected
flag11 = st.binary(min_size=1, max_size=4).map(lambda b: bytes(0xC0 | (v & 0x3F) for v in b))


@settings(max_examples=300)
@given(st.lists(values, max_size=40), st.data(), st.lists(st.integers(0, 10_000), max_size=8))
def test_garbage_inside_and_between_frames(xs, data, cuts):
    """Garbage anywhere (inside frames too): every untouched frame comes back, in order,
    nothing else does, and every byte of garbage and of damaged frames is counted."""
    stream = b""
    expected, touched, garbage = [], 0, 0
    for x in xs:
        frame = encode_value(x)
        # 0..3 insertion points in this frame, at offsets 0 (before it), 1 or 2 (inside it)
        where = data.draw(st.lists(st.integers(0, 2), max_size=3, unique=True))
        pieces = bytearray()
        for i in range(3):
            if i in where:
                g = data.draw(flag11)
                pieces += g
                garbage += len(g)
            pieces.append(frame[i])
        stream += bytes(pieces)
        inside = any(w in (1, 2) for w in where)
        touched += inside
        if not inside:
            expected.append(x)
    dec = FrameDecoder()
    assert _feed_all(dec, _chunked(stream, cuts)) == expected
    assert dec.discarded == garbage + 3 * touched
    assert dec.pending == 0


def _has_frame(chunk: bytes) -> bool:
    flags = [b >> 6 for b in chunk]
    return any(flags[i:i + 3] == [0, 1, 2] for i in range(len(flags) - 2))


any_garbage = st.binary(min_size=1, max_size=6).filter(lambda g: not _has_frame(g))


@settings(max_examples=300)
@given(st.lists(st.tuples(values, st.one_of(st.just(b""), any_garbage)), max_size=40),
       st.lists(st.integers(0, 10_000), max_size=8))
def test_arbitrary_garbage_between_frames(pairs, cuts):
    """Arbitrary bytes (any flags, but not themselves a complete frame) between frames:
    every frame is recovered and no value is made up; all garbage is counted."""
    stream = b"".join(g + encode_value(x) for x, g in pairs)
    dec = FrameDecoder()
    assert _feed_all(dec, _chunked(stream, cuts)) == [x for x, _ in pairs]
    assert dec.discarded == sum(len(g) for _, g in pairs)


@settings(max_examples=300)
@given(st.binary(max_size=300), st.lists(st.integers(0, 10_000), max_size=8))
def test_any_bytes_are_accounted_and_chunking_does_not_matter(data, cuts):
    """Every byte ends up in a frame, discarded or pending; chunk boundaries change nothing."""
    whole = FrameDecoder()
    ref = whole.feed(data)
    dec = FrameDecoder()
    assert _feed_all(dec, _chunked(data, cuts)) == ref
    assert 3 * dec.frames + dec.discarded + dec.pending == len(data)
    assert (dec.discarded, dec.pending) == (whole.discarded, whole.pending)
    assert all(0 <= x <= MAX_X for x in ref)


# =========================================================================== driver + virtual device
def _cfg(**kw) -> LaserDevice:
    return LaserDevice(role="b_f", port="sim", measuring_range_mm=MR, offset_mm=OFFSET, **kw)


@pytest.fixture
def rig(request):
    """(virtual laser, configured driver); parametrize indirectly with dicts for cfg/virtual kwargs."""
    opts = getattr(request, "param", {})
    cfg = _cfg(**opts.get("cfg", {}))
    vl = VirtualLaser(cfg, seed=7, **opts.get("virtual", {}))
    drv = LaserDriver(cfg, port=vl.port_name)
    drv.configure()
    yield vl, drv
    drv.close()
    vl.close()


def _cycle(vl: VirtualLaser, drv: LaserDriver, k: int):
    """One lockstep control period ending at k·h: the device emits, then the driver polls."""
    vl.emit_until(k * H)
    return drv.poll(k * H)


def test_fresh_readings_equal_the_distance(rig):
    vl, drv = rig
    for k, d in enumerate([0.0452, 0.0600, 0.0700, 0.0949], start=1):
        vl.set_distance(d)
        r = _cycle(vl, drv, k)
        assert r.health.state is Freshness.FRESH, r.health.cause
        assert abs(r.value_m - d) <= STEP_M / 2 + 1e-12
        assert r.n_values == 20                      # 4 kHz · 5 ms
        assert r.t == k * H
        assert r.role == "b_f"
        assert r.raw_x == x_from_distance_mm(d * 1000 - OFFSET, MR)
    assert r.health.bad_frames == 0 and r.health.errors == 0
    assert drv.counters()["values"] == 80


def test_reading_is_an_immutable_snapshot(rig):
    vl, drv = rig
    r1 = _cycle(vl, drv, 1)
    vl.inject("out_of_range")
    r2 = _cycle(vl, drv, 2)
    assert r1.health.state is Freshness.FRESH and r2.health.state is Freshness.INVALID
    with pytest.raises(AttributeError):
        r1.value_m = 0.0  # type: ignore[misc]


def test_health_is_reused_while_unchanged_and_is_frozen(rig):
    """The same Health object poll after poll while state/cause/counts do not change, a new
    one when they do; Health is frozen; the statistics are a new dict from counters()."""
    vl, drv = rig
    vl.set_distance(0.06)
    r1 = _cycle(vl, drv, 1)
    c1 = drv.counters()
    r2 = _cycle(vl, drv, 2)
    assert r2.health is r1.health                    # only the statistics changed: the same value
    assert c1 == {"values": 20, "error_frames": 0, "read_errors": 0, "bytes": 60}
    c2 = drv.counters()
    assert c2["values"] == 40 and json.loads(json.dumps(c2))["bytes"] == 120
    assert type(c2) is dict and c2 is not drv.counters() and pickle.loads(pickle.dumps(c2)) == c2
    c2["values"] = 0                                 # a copy: the driver's statistics are untouched
    assert drv.counters()["values"] == 40 and c1["values"] == 20
    with pytest.raises(dataclasses.FrozenInstanceError):
        r1.health.state = Freshness.STALE  # type: ignore[misc]
    with pytest.raises(dataclasses.FrozenInstanceError):
        r1.health.errors = 5  # type: ignore[misc]
    assert copy.deepcopy(r1.health) == r1.health and pickle.loads(pickle.dumps(r1.health)) == r1.health
    vl.inject("out_of_range")
    r3 = _cycle(vl, drv, 3)
    assert r3.health is not r2.health and r3.health.state is Freshness.INVALID and r2.health.fresh
    assert r3.health.errors == 20 and r2.health.errors == 0      # the old value is unchanged
    r4 = _cycle(vl, drv, 4)                          # more error codes: the count changed
    assert r4.health is not r3.health and r4.health.errors == 40
    vl.clear("out_of_range")
    r5 = _cycle(vl, drv, 5)
    r6 = _cycle(vl, drv, 6)
    assert r5.health.fresh and r6.health is r5.health


@pytest.mark.parametrize("average", [False, True])
def test_average_is_the_mean_of_the_cycle(average):
    cfg = _cfg(average=average)
    with VirtualLaser(cfg) as vl, LaserDriver(cfg, port=vl.port_name) as drv:
        d1, d2 = 0.0500, 0.0600
        vl.set_distance(d1)
        vl.emit_until(0.0025)                        # 10 frames at d1
        vl.set_distance(d2)
        r = _cycle(vl, drv, 1)                       # 10 more at d2, one poll
        assert r.n_values == 20
        expected = (d1 + d2) / 2 if average else d2
        assert abs(r.value_m - expected) <= STEP_M / 2 + 1e-12


def test_arrival_time_is_kept_and_age_is_not_judged(rig):
    """The driver reports when the latest value arrived; how old is too old is the
    supervisor's rule: a quiet device stays FRESH here, with its old t."""
    vl, drv = rig
    vl.set_distance(0.06)
    r = _cycle(vl, drv, 1)
    assert r.t == 0.005 and r.values_total == 20
    # the device goes quiet without a fault: nothing emitted, the driver keeps polling
    for now in (0.010, 0.025, 0.0251, 10.0):
        r = drv.poll(now)
        assert r.health.state is Freshness.FRESH and r.health.cause == ""
        assert r.t == 0.005 and r.n_values == 0 and r.values_total == 20
    assert abs(r.value_m - 0.06) <= STEP_M          # the last value is kept, with its old t


def test_before_first_data():
    """Nothing arrived yet: no value, t NaN (never), no complaint from the device."""
    cfg = _cfg()
    with VirtualLaser(cfg) as vl, LaserDriver(cfg, port=vl.port_name) as drv:
        for now in (1.0, 1.1):
            r = drv.poll(now)
            assert r.health.state is Freshness.FRESH and r.health.cause == "no data yet"
            assert math.isnan(r.value_m) and math.isnan(r.t) and r.raw_x == -1
            assert r.n_values == 0 and r.values_total == 0


def test_dropout_keeps_t_and_recovers(rig):
    vl, drv = rig
    vl.set_distance(0.07)
    _cycle(vl, drv, 1)
    vl.inject("dropout")
    rs = [_cycle(vl, drv, k) for k in range(2, 8)]
    assert [r.t for r in rs] == [1 * H] * 6                          # age grows with the polls
    assert {r.health for r in rs} == {rs[0].health} and rs[0].health.fresh
    assert [r.values_total for r in rs] == [20] * 6
    assert vl.frames_suppressed == 6 * 20
    vl.clear("dropout")
    r = _cycle(vl, drv, 8)
    assert r.health.fresh and r.t == 8 * H and r.n_values == 20 and r.values_total == 40


def _pipe_driver(average: bool = False):
    """A driver whose port is the read end of a pipe (bytes written are what it polls)."""
    import os as _os
    r, w = _os.pipe()
    _os.set_blocking(r, False)
    drv = LaserDriver(_cfg(average=average), port="/dev/null")
    drv._ser = type("Port", (), {"fd": r})()
    return drv, r, w


def test_a_garbled_only_link_is_counted_not_judged():
    """Only garbage after one valid value: t stays at that value's arrival, the valid count
    stands still, the garbled byte count grows by exactly the bytes sent (0xC0..0xFF carry
    the flag bits 11, which no frame byte has), and the state stays FRESH — naming the
    corruption is the supervisor's rule."""
    import os as _os
    drv, r, w = _pipe_driver()
    try:
        _os.write(w, encode_value(32760))            # one valid frame, 3 bytes
        first = drv.poll(1.0)
        assert first.values_total == 1 and first.t == 1.0 and first.health.bad_frames == 0
        for k in range(1, 5):
            _os.write(w, bytes([0xC0, 0xD5, 0xFF, 0xE1, 0xC3, 0xF0, 0xEE]))     # 7 garbage bytes
            got = drv.poll(1.0 + k * H)
            assert got.health.bad_frames == 7 * k
            assert got.t == 1.0 and got.values_total == 1 and got.n_values == 0
            assert got.health.state is Freshness.FRESH and got.value_m == first.value_m
        assert drv.counters()["bytes"] == 3 + 4 * 7 and drv.counters()["values"] == 1
    finally:
        _os.close(r)
        _os.close(w)


def test_out_of_range_is_invalid_with_reason(rig):
    vl, drv = rig
    vl.set_distance(0.06)
    _cycle(vl, drv, 1)
    vl.inject("out_of_range")
    r = _cycle(vl, drv, 2)
    assert r.health.state is Freshness.INVALID
    assert r.health.cause == "no peak (262076)"
    assert math.isnan(r.value_m) and r.raw_x == 262076 and r.n_values == 0
    assert r.health.errors == 20 and drv.counters()["error_frames"] == 20
    assert r.t == 1 * H                              # the last valid value's arrival, still
    r = drv.poll(2 * H + 0.001)                      # no new frames: stays INVALID, not FRESH
    assert r.health.state is Freshness.INVALID and math.isnan(r.value_m)
    assert r.values_total == 20                      # error codes are not values
    vl.inject("out_of_range", code=262082)
    assert _cycle(vl, drv, 3).health.cause == "laser off (262082)"
    vl.inject("out_of_range", code=100_000)
    assert _cycle(vl, drv, 4).health.cause == "unknown code 100000"
    vl.clear("out_of_range")
    r = _cycle(vl, drv, 5)
    assert r.health.fresh and abs(r.value_m - 0.06) <= STEP_M


def test_distance_outside_the_span_is_reported_by_the_device(rig):
    vl, drv = rig
    vl.set_distance((OFFSET + 1.02 * MR) / 1000)     # beyond 101 % of MR
    assert _cycle(vl, drv, 1).health.cause == "peak after range (262078)"
    vl.set_distance((OFFSET - 0.02 * MR) / 1000)     # before −1 % of MR
    assert _cycle(vl, drv, 2).health.cause == "peak before range (262077)"


def test_errors_in_the_middle_of_a_cycle_count_but_latest_decides(rig):
    vl, drv = rig
    vl.set_distance(0.06)
    vl.inject("out_of_range")
    vl.emit_until(0.002)                             # 8 error frames
    vl.clear("out_of_range")
    r = _cycle(vl, drv, 1)                           # then 12 distances
    assert r.health.fresh and r.n_values == 12 and r.health.errors == 8


@pytest.mark.parametrize("rig", [{"virtual": {"noise_std_m": 20e-6}}], indirect=True)
def test_corrupt_frames_are_dropped_never_made_up(rig):
    vl, drv = rig
    vl.inject("corrupt", p=0.3)
    got = sent = 0
    for k in range(1, 41):
        vl.set_distance(0.06 + 1e-5 * k)             # a new distance each cycle
        sent_x = _sent_x(vl, k)
        r = drv.poll(k * H)
        assert set(drv.last_values) <= set(sent_x)   # nothing that was not sent
        assert _is_subsequence(drv.last_values, sent_x)
        got += r.n_values
        sent += len(sent_x)
    assert vl.frames_corrupted > 0.2 * sent
    assert got < sent - 0.2 * sent and got > 0.5 * sent
    assert r.health.bad_frames > 0 and r.health.bad_frames == drv._decoder.discarded


def _sent_x(vl: VirtualLaser, k: int) -> list[int]:
    """Emit cycle k while capturing the values the device measured (before corruption)."""
    captured: list[int] = []
    orig = vl_mod.encode_values
    vl_mod.encode_values = lambda xs: (captured.extend(xs), orig(xs))[1]
    try:
        vl.emit_until(k * H)
    finally:
        vl_mod.encode_values = orig
    return captured


def _is_subsequence(sub: list[int], seq: list[int]) -> bool:
    it = iter(seq)
    return all(any(x == y for y in it) for x in sub)


def test_corrupt_off_means_no_bad_frames(rig):
    vl, drv = rig
    vl.inject("corrupt", p=0.0)
    for k in range(1, 5):
        assert _cycle(vl, drv, k).health.bad_frames == 0


def test_stuck_repeats_the_last_value(rig):
    vl, drv = rig
    vl.set_distance(0.06)
    r0 = _cycle(vl, drv, 1)
    vl.inject("stuck")
    vl.set_distance(0.08)
    r = _cycle(vl, drv, 2)
    assert r.health.fresh and r.value_m == r0.value_m and set(drv.last_values) == {r0.raw_x}
    vl.clear("stuck")
    assert abs(_cycle(vl, drv, 3).value_m - 0.08) <= STEP_M


@pytest.mark.parametrize("rig", [{"virtual": {"noise_std_m": 20e-6}}], indirect=True)
def test_stuck_before_anything_was_sent_sticks_at_the_next_noise_free_value(rig):
    vl, drv = rig
    vl.inject("stuck")
    vl.set_distance(0.07)
    r = _cycle(vl, drv, 1)
    assert set(drv.last_values) == {x_from_distance_mm(0.07 * 1000 - OFFSET, MR)} and r.n_values == 20
    vl.set_distance(0.08)
    _cycle(vl, drv, 2)
    assert set(drv.last_values) == {r.raw_x} and vl.faults["stuck"]["x"] == r.raw_x
    vl.clear("stuck")
    _cycle(vl, drv, 3)
    assert len(set(drv.last_values)) > 1                                 # noisy again


def test_offset_fault_shifts_the_distance(rig):
    vl, drv = rig
    vl.set_distance(0.06)
    vl.inject("offset", amount_m=0.002)
    assert abs(_cycle(vl, drv, 1).value_m - 0.062) <= STEP_M
    vl.clear()
    assert abs(_cycle(vl, drv, 2).value_m - 0.060) <= STEP_M


def test_unknown_fault_kind_is_refused(rig):
    vl, _ = rig
    with pytest.raises(ValueError, match="unknown laser fault"):
        vl.inject("smoke")
    with pytest.raises(ValueError):
        vl.inject("corrupt", p=2.0)


def test_frame_count_follows_the_sample_clock(rig):
    vl, drv = rig
    total, t = 0, 0.0
    for k in range(1, 201):
        t += H          # accumulated like a loop clock: t·4000 falls just below 20·k from k = 10 on
        vl.emit_until(t)
        drv.poll(t)
        total += len(drv.last_values)
        assert total == 20 * k
    vl.emit_until(t)                                 # same time again: nothing new
    assert drv.poll(t).n_values == 0


@pytest.mark.parametrize("rig", [{"virtual": {"latency_s": 0.0025}}], indirect=True)
def test_latency_delays_frames(rig):
    vl, drv = rig
    assert _cycle(vl, drv, 1).n_values == 10         # the last 10 samples are still "in flight"
    assert _cycle(vl, drv, 2).n_values == 20


def test_noise_is_deterministic_for_a_seed():
    cfg = _cfg()
    runs = []
    for _ in range(2):
        with VirtualLaser(cfg, noise_std_m=5e-6, seed=42) as vl, LaserDriver(cfg, port=vl.port_name) as drv:
            vl.set_distance(0.06)
            _cycle(vl, drv, 1)
            runs.append(list(drv.last_values))
    assert runs[0] == runs[1] and len(set(runs[0])) > 3


def test_full_pty_buffer_drops_instead_of_blocking(rig):
    vl, drv = rig
    t0 = time.monotonic()
    vl.emit_until(3.0)                               # 12000 frames = 36 kB, far more than a pty holds
    # a blocking write would wait for a reader forever; tens of ms normally, room for a stall
    assert time.monotonic() - t0 < 5.0
    assert vl.bytes_dropped > 0
    assert vl.bytes_written + vl.bytes_dropped == 36_000
    got: list[int] = []
    for i in range(30):                              # drain it all
        drv.poll(3.0 + i * H)
        got += drv.last_values
    sent_x = x_from_distance_mm(vl.distance_m * 1000 - OFFSET, MR)
    assert got and set(got) == {sent_x}
    assert 3 * len(got) <= vl.bytes_written


def test_realtime_mode_emits_at_wall_clock_rate(rig):
    vl, drv = rig
    vl.set_distance(0.065)
    t0 = time.monotonic()
    vl.start_realtime()
    vl.start_realtime()                              # second start is a no-op
    time.sleep(0.05)
    r = drv.poll(time.monotonic())
    # never ahead of the wall clock: at most one frame per 1/rate since the start
    assert r.n_values <= vl.rate_hz * (time.monotonic() - t0) + 1, r.n_values
    total = r.n_values                               # ≈ 200 at 4 kHz for 50 ms, unless the thread was late
    deadline = time.monotonic() + 2.0
    while total < 100:
        assert time.monotonic() < deadline, f"{total} values within 2 s"
        time.sleep(0.01)
        r = drv.poll(time.monotonic())
        total += r.n_values
    assert total <= vl.rate_hz * (time.monotonic() - t0) + 1, total
    vl.stop()
    vl.stop()
    assert r.n_values > 0 and r.health.fresh and abs(r.value_m - 0.065) <= STEP_M


def test_open_missing_port_names_the_port():
    drv = LaserDriver(_cfg(), port="/dev/does-not-exist-laser")
    with pytest.raises(DeviceInitError) as ei:
        drv.configure()
    assert "/dev/does-not-exist-laser" in str(ei.value)
    assert ei.value.device == "laser b_f"
    assert isinstance(ei.value.__cause__, serial.SerialException)
    assert not drv.is_configured
    drv.close()                                       # closing a never-configured driver is fine


def test_port_defaults_to_the_config():
    drv = LaserDriver(LaserDevice(role="s_fl", port="/dev/ttyNOPE9", measuring_range_mm=25))
    with pytest.raises(DeviceInitError, match="ttyNOPE9"):
        drv.configure()


def test_close_is_idempotent_and_context_manager(rig):
    vl, _ = rig
    with LaserDriver(_cfg(), port=vl.port_name) as drv:
        assert drv.is_configured
    assert not drv.is_configured
    drv.close()
    r = drv.poll(1.0)                                 # never raises
    assert r.health.state is Freshness.INVALID and r.health.cause == "port not configured"
    vl.close()
    vl.close()


def test_serial_exception_in_poll_is_reported_not_raised(rig, monkeypatch):
    vl, drv = rig
    vl.set_distance(0.06)
    _cycle(vl, drv, 1)

    def boom(*_a):
        raise OSError(5, "Input/output error")

    vl.emit_until(2 * H)
    monkeypatch.setattr(laser_mod, "_os_read", boom)
    r = drv.poll(2 * H)
    assert r.health.state is Freshness.INVALID
    assert "OSError" in r.health.cause and "Input/output error" in r.health.cause
    assert r.health.errors == 1 and drv.counters()["read_errors"] == 1
    assert math.isnan(r.value_m)
    monkeypatch.undo()
    assert _cycle(vl, drv, 3).health.fresh


@pytest.mark.parametrize("pending", [False, True])
def test_device_gone_is_invalid(rig, pending):
    """The far end disappears (cable pulled) with nothing or frames still unread: the pty
    slave is hung up, and the next poll says so (TIOCINQ answers EIO; bytes are lost)."""
    vl, drv = rig
    _cycle(vl, drv, 1)
    if pending:
        vl.emit_until(2 * H)                          # readable at the slave (lockstep wait)
    vl.close()
    r = drv.poll(2 * H)
    assert r.health.state is Freshness.INVALID and "read error" in r.health.cause
    assert "device disconnected (hang-up on the port)" in r.health.cause
    assert drv.counters()["read_errors"] == 1 and math.isnan(r.value_m)
    assert drv.poll(3 * H).health.state is Freshness.INVALID      # and every poll after
    assert drv.counters()["read_errors"] == 2


def test_a_poll_reads_only_what_the_line_discipline_holds(rig, monkeypatch):
    """No read(2) while TIOCINQ says 0 (an empty tty's read waits for the kernel's
    flip-buffer worker), else one read of exactly the bytes it reported."""
    vl, drv = rig
    reads: list[int] = []
    real_read = laser_mod._os_read

    def watched(fd, n):
        reads.append(n)
        return real_read(fd, n)

    monkeypatch.setattr(laser_mod, "_os_read", watched)
    r = drv.poll(0.0)                                 # nothing sent yet
    assert reads == [] and r.health.state is Freshness.FRESH and r.n_values == 0
    vl.set_distance(0.06)
    r = _cycle(vl, drv, 1)                            # 20 frames, readable before the poll
    assert reads == [60] and r.n_values == 20 and r.health.fresh
    r = drv.poll(1 * H + 0.001)                       # drained: no read again
    assert reads == [60] and r.n_values == 0 and r.t == 1 * H


@settings(max_examples=150, deadline=None)
@given(xs=st.lists(st.one_of(st.integers(0, MAX_X), st.integers(60000, MAX_X), st.sampled_from(sorted(ERROR_CODES))),
                   min_size=1, max_size=40),
       average=st.booleans())
def test_poll_decodes_like_the_decoder(xs, average):
    """A poll gives what the frame decoder gives (values, latest value, validity, mean)."""
    import os as _os

    r, w = _os.pipe()
    _os.set_blocking(r, False)
    try:
        drv = LaserDriver(_cfg(average=average), port="/dev/null")
        drv._ser = type("Port", (), {"fd": r})()
        _os.write(w, encode_values(xs))
        got = drv.poll(1.0)
        assert drv.last_values == xs
        ref = FrameDecoder().feed(encode_values(xs))
        valid = [x for x in ref if x <= MAX_DISTANCE_X]
        assert got.raw_x == xs[-1] and got.n_values == len(valid)
        if xs[-1] > MAX_DISTANCE_X:
            assert got.health.state is Freshness.INVALID and math.isnan(got.value_m)
        else:
            x = sum(valid) / len(valid) if average else xs[-1]
            assert got.health.state is Freshness.FRESH
            assert got.value_m == pytest.approx(drv._gain * x + drv._bias, abs=1e-12)
    finally:
        _os.close(r)
        _os.close(w)


def test_last_values_is_always_a_list(rig):
    vl, drv = rig
    r = drv.poll(0.0)                                  # nothing arrived yet
    assert type(drv.last_values) is list and drv.last_values == [] and r.n_values == 0
    vl.set_distance(0.06)
    _cycle(vl, drv, 1)
    assert type(drv.last_values) is list and len(drv.last_values) == 20
    drv.poll(1 * H)                                    # no new bytes
    assert type(drv.last_values) is list and drv.last_values == []


@settings(max_examples=100, deadline=None)
@given(polls=st.lists(st.tuples(st.lists(st.integers(0, MAX_DISTANCE_X), max_size=5),
                                st.integers(0, 6)), min_size=1, max_size=12))
def test_counts_and_arrival_time_follow_what_was_sent(polls):
    """Each poll gets whole valid frames, then garbage bytes (flag bits 11): the cumulative
    valid count, the garbled byte count and t are exactly what was sent and when; the state
    is FRESH throughout (no error code, no read error)."""
    import os as _os
    drv, r, w = _pipe_driver()
    try:
        n_valid = n_bad = 0
        t_last = math.nan
        for k, (xs, garbage) in enumerate(polls):
            now = 1.0 + k * H
            _os.write(w, encode_values(xs) + bytes([0xC0 + (i * 7) % 64 for i in range(garbage)]))
            got = drv.poll(now)
            n_valid += len(xs)
            n_bad += garbage
            if xs:
                t_last = now
            assert got.values_total == n_valid and got.n_values == len(xs)
            assert got.health.bad_frames == n_bad
            assert got.t == t_last or (math.isnan(got.t) and math.isnan(t_last))
            assert got.health.state is Freshness.FRESH
    finally:
        _os.close(r)
        _os.close(w)
