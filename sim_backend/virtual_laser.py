"""The other end of a laser's RS-422 wire: an optoNCDT 1420 simulated on a pty pair, or on
an in-process serial line (``wire="memory"``: :mod:`rig_runtime.wires`, ``mem://`` URL).

The plant gives the physical distance (``offset_mm`` included, metres); the device samples
it at ``output_rate_hz``, adds noise, turns it into 16-bit wire values with the codec of
``drivers.laser`` (the one source of truth for the frame layout) and writes the frames to
the pty master (or the line's device end). The driver opens ``port_name`` (the slave's
path, or the line's URL) with pyserial like a real port; both wires carry the same bytes.

Time: frame k (k = 1, 2, …) is sampled at k/rate and written at k/rate + latency, so after
``emit_until(t)`` exactly ``floor((t − latency)·rate)`` frames have been produced —
independent of how the calls are spaced. Lockstep backends call ``emit_until`` each step
(or emit all lasers at once through a :class:`LaserGroup`: the same frames by the same
path, the pty writes back to back and one wait for all); ``start_realtime`` runs the same
on a thread against the monotonic clock.

Faults (``inject(kind, **params)``, ``clear(kind)``):
  dropout                      no bytes on the wire (the sample clock keeps running)
  corrupt  p=0.1, detectable=True
                               a fraction p of frames damaged: one byte dropped, one byte
                               replaced or 1–3 bytes inserted. ``detectable`` damage uses
                               bytes flagged ``11`` (never part of a frame), which a decoder
                               can always reject; ``detectable=False`` uses any byte value,
                               which can forge values no decoder can tell from real ones
                               (the protocol has no checksum)
  stuck                        repeat the last value sent
  offset   amount_m            add amount_m to the distance
  drift    amount_m            add amount_m to the distance; the simulated rig moves it at the
                               scenario's rate (``set_drift``): a reading creeping off the truth
  out_of_range  code=262076    send an error code instead of the distance
A distance outside the device's span (−1 % … 101 % of MR) is sent as 262077/262078, as the
real sensor does. A full pty buffer never blocks: the bytes that do not fit are dropped
and counted in ``bytes_dropped``.
"""

from __future__ import annotations

import fcntl
import math
import os
import select
import termios
import threading
import time
import tty
from collections import deque
from typing import Any

import numpy as np

from drivers.optoncdt import MAX_X, encode_values, xs_from_distance_mm
from rig_runtime import wires
from rig_runtime.config import LaserDevice

__all__ = ["FAULT_KINDS", "LaserGroup", "VirtualLaser"]

FAULT_KINDS = ("dropout", "corrupt", "stuck", "offset", "out_of_range", "drift")
PEAK_BEFORE_RANGE = 262077
PEAK_AFTER_RANGE = 262078
NO_PEAK = 262076
_EPS = 1e-9     # k/rate computed in floats: 0.005·4000 may land just below 20
_LDISC_CAP = 4095   # bytes the Linux n_tty line discipline holds; more waits in the flip buffer
_NOISE_BLOCK = 4096  # standard normals drawn from the generator at a time
_SPIN_S = 20e-6      # waiting for pty delivery: spin this long, then sleep in poll()
# Lockstep gives up waiting for the kernel only after this long (counted in delivery_timeouts):
# a frame the driver does not see that cycle breaks determinism, and on a loaded machine the
# kernel's worker may not run for tens of milliseconds. Delivery itself takes microseconds.
_DELIVERY_TIMEOUT_S = 2.0
_FIONREAD = termios.FIONREAD
_floor = math.floor
_ioctl = fcntl.ioctl


class VirtualLaser:
    """A simulated optoNCDT 1420 writing binary frames into a pty.

    Sensor model: ``noise_std_m`` Gaussian noise per sample (set at construction: the noise
    is drawn already scaled, a block at a time), optional extra
    ``quantization_m`` (the 16-bit wire value quantizes to MR·102/65520/100 anyway),
    ``latency_s`` from sampling to the wire, ``seed`` (int, SeedSequence or numpy
    Generator) for reproducible noise and faults. ``wire``: "pty" (a kernel pty pair) or
    "memory" (an in-process serial line: bytes are readable as soon as they are written,
    nothing to wait for; a full line drops what does not fit, as a full pty does).
    """

    def __init__(self, cfg: LaserDevice, *, noise_std_m: float = 0.0, quantization_m: float = 0.0,
                 latency_s: float = 0.0, seed: Any = None, output_rate_hz: float | None = None,
                 wire: str = "pty"):
        if noise_std_m < 0 or quantization_m < 0 or latency_s < 0:
            raise ValueError("noise_std_m, quantization_m and latency_s must be >= 0")
        if wire not in ("pty", "memory"):
            raise ValueError(f"wire must be 'pty' or 'memory', got {wire!r}")
        self.cfg = cfg
        self.rate_hz = float(output_rate_hz if output_rate_hz is not None else cfg.output_rate_hz)
        self.noise_std_m = noise_std_m
        self.quantization_m = quantization_m
        self.latency_frames = round(latency_s * self.rate_hz)
        self._noise_rng, self._fault_rng = _rngs(seed)
        # noise samples drawn, m (noise_std_m · e for each standard normal e, drawn in blocks
        # of _NOISE_BLOCK), and the next one to use
        self._noise: list[float] = []
        self._ni = 0
        self._mr = float(cfg.measuring_range_mm)
        self._off = float(cfg.offset_mm)
        self._qbuf = bytearray(4)       # FIONREAD result, reused
        self._distance_m = cfg.offset_mm / 1000.0 + cfg.measuring_range_mm / 2000.0  # mid-range
        self._faults: dict[str, dict[str, Any]] = {}
        self._last_x: int | None = None
        self._queue: deque[int] = deque()     # sampled, not yet released (latency)
        self._sampled = 0                     # frames sampled so far (the sample clock)
        self._released = 0
        # statistics
        self.frames_sent = 0          # frames handed to the wire (before write errors)
        self.frames_suppressed = 0    # frames not sent because of a dropout
        self.frames_corrupted = 0
        self.bytes_written = 0
        self.bytes_dropped = 0        # did not fit into the pty buffer
        self.delivery_timeouts = 0    # emit_until(wait=True) gave up waiting for the kernel
        self._lock = threading.Lock()
        self._thread: threading.Thread | None = None
        self._stop_evt = threading.Event()
        self._line: wires.Wire | None = None
        self._pipe: wires.BytePipe | None = None     # the memory line's device -> host pipe
        if wire == "memory":
            self._master = self._slave = -1
            self._line = wires.serial_line(wires.unique_name(f"laser-{cfg.role}"))
            self._pipe = self._line.a.tx
            self.port_name = wires.SCHEME + self._line.name
        else:
            self._master, self._slave = os.openpty()
            tty.setraw(self._slave)
            os.set_blocking(self._master, False)
            self.port_name = os.ttyname(self._slave)

    # ------------------------------------------------------------------ plant side
    @property
    def distance_m(self) -> float:
        return self._distance_m

    def set_distance(self, d_m: float) -> None:
        """The physical distance (offset included) the sensor sees from now on, m."""
        self._distance_m = float(d_m)

    @property
    def t(self) -> float:
        """Sample time of the last frame produced, s."""
        return self._sampled / self.rate_hz

    def emit_until(self, t: float, wait: bool = True) -> int:
        """Produce and write every frame due up to simulated time t; return bytes written.

        The kernel hands pty bytes to the reading side asynchronously (a worker thread,
        typically 10–30 µs, ms under load), so with ``wait`` (lockstep) this returns only
        once the bytes are readable at the slave — a poll right after sees all of them.
        """
        with self._lock:
            q0 = self._slave_queued() if wait else 0
            n = self._emit(t)
            if wait and n:
                self._wait_delivered(min(q0 + n, _LDISC_CAP))
            return n

    def _emit(self, t: float) -> int:
        """Sample the frames due by t, release those past the latency, encode and damage them
        as the faults say (nothing in a dropout) and write them; bytes written. Lock held.

        A sample: the distance (+ an offset or drift fault) plus noise, quantized, turned
        into wire values by the codec with the device's codes outside its span — or a
        fault's code (out of range, stuck)."""
        k = _floor(t * self.rate_hz + _EPS)
        n = k - self._sampled
        f = self._faults
        xs = None
        if n > 0:
            d0 = self._distance_m
            code = stuck = None
            if f:
                code = _fault_code(f)
                stuck = f.get("stuck")          # (stuck before anything was sent)
                d0 += self._bias()
            if code is None:
                if stuck is None and self.noise_std_m > 0:
                    ni = self._ni
                    if ni + n > len(self._noise):
                        self._draw(n)
                        ni = 0
                    noise = self._noise[ni:ni + n]
                    self._ni = ni + n
                else:
                    noise = [0.0] * n       # d0 + 0.0 == d0
                q = self.quantization_m
                if q > 0:
                    noise = [round((d0 + e) / q) * q for e in noise]
                    d0 = 0.0                # 0.0 + d == d
                # (d, mr_mm, base, scale, offset_mm, below, above) by position: the per-cycle call
                xs = xs_from_distance_mm(noise, self._mr, d0, 1000.0, self._off, PEAK_BEFORE_RANGE,
                                         PEAK_AFTER_RANGE)
                if stuck is not None:       # ... sticks at this noise-free value
                    stuck["x"] = xs[-1]
            else:
                xs = [code] * n
            self._last_x = xs[-1]
            self._sampled = k
        if self.latency_frames:
            if xs is not None:
                self._queue.extend(xs)
            n = k - self.latency_frames - self._released
            if n <= 0:
                return 0
            pop = self._queue.popleft
            xs = [pop() for _ in range(n)]
        elif xs is None:
            return 0
        self._released += n
        if f and "dropout" in f:
            self.frames_suppressed += n
            return 0
        self.frames_sent += n
        data = encode_values(xs)
        if f and "corrupt" in f:
            data = self._corrupt(data, n, f["corrupt"])
        # non-blocking: what does not fit is dropped and counted
        pipe = self._pipe
        if pipe is not None:
            w = pipe.write(data)
        else:
            try:
                w = os.write(self._master, data)
            except OSError:             # BlockingIOError included: a full pty
                w = 0
        self.bytes_written += w
        if w != len(data):
            self.bytes_dropped += len(data) - w
        return w

    # ------------------------------------------------------------------ real time
    def start_realtime(self, period_s: float = 0.001) -> None:
        """Emit at wall-clock rate on a daemon thread, continuing from the current sample time."""
        if self._thread is not None and self._thread.is_alive():
            return
        self._stop_evt.clear()
        t_sim0, t_wall0 = self.t, time.monotonic()

        def run() -> None:
            while not self._stop_evt.wait(period_s):
                self.emit_until(t_sim0 + time.monotonic() - t_wall0, wait=False)

        self._thread = threading.Thread(target=run, name=f"virtual laser {self.cfg.role}", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        """Stop the real-time thread (no-op if it is not running)."""
        self._stop_evt.set()
        if self._thread is not None:
            self._thread.join()
            self._thread = None

    # ------------------------------------------------------------------ faults
    def inject(self, kind: str, **params: Any) -> None:
        """Start a fault (see the module docstring); replaces one of the same kind."""
        if kind not in FAULT_KINDS:
            raise ValueError(f"unknown laser fault {kind!r} (known: {', '.join(FAULT_KINDS)})")
        if kind == "corrupt" and not 0.0 <= params.get("p", 0.1) <= 1.0:
            raise ValueError("corrupt: p must be in [0, 1]")
        if kind == "out_of_range" and not 0 <= params.get("code", NO_PEAK) <= MAX_X:
            raise ValueError(f"out_of_range: code must be in 0..{MAX_X}")
        with self._lock:
            if kind == "stuck":         # the last value sent (none yet: the next noise-free one)
                params.setdefault("x", self._last_x)
            self._faults[kind] = params

    def clear(self, kind: str | None = None) -> None:
        """End one fault, or all with ``kind=None``."""
        with self._lock:
            if kind is None:
                self._faults.clear()
            else:
                self._faults.pop(kind, None)

    @property
    def faults(self) -> dict[str, dict[str, Any]]:
        return {k: dict(v) for k, v in self._faults.items()}

    # ------------------------------------------------------------------ model
    def _bias(self) -> float:
        """What the offset and drift faults add to the distance, m."""
        f = self._faults
        return float(f.get("offset", {}).get("amount_m", 0.0)) + float(f.get("drift", {}).get("amount_m", 0.0))

    def set_drift(self, amount_m: float) -> None:
        """The drift fault's current bias (no-op unless a drift is injected)."""
        with self._lock:
            d = self._faults.get("drift")
            if d is not None:
                d["amount_m"] = float(amount_m)

    def _draw(self, n: int) -> None:
        """Keep the unused noise samples and draw blocks until n are there (the seeded
        generator's sequence, the same however the frames are split into calls)."""
        left = self._noise[self._ni:]
        while len(left) < n:
            left += (self.noise_std_m * self._noise_rng.standard_normal(_NOISE_BLOCK)).tolist()
        self._noise, self._ni = left, 0

    def _corrupt(self, data: bytes, n: int, params: dict[str, Any]) -> bytes:
        """Damage a fraction p of the n frames in data (one damage per frame)."""
        p, detectable = float(params.get("p", 0.1)), bool(params.get("detectable", True))
        rng = self._fault_rng
        hit = np.flatnonzero(rng.random(n) < p)
        if hit.size == 0:
            return data
        buf = bytearray(data)
        for i in hit[::-1]:                     # back to front: earlier offsets stay valid
            pos = 3 * int(i) + int(rng.integers(3))
            mode = int(rng.integers(3))
            if mode == 0:                       # drop a byte
                del buf[pos]
            elif mode == 1:                     # replace a byte
                buf[pos] = self._garbage_byte(buf[pos], detectable)
            else:                               # insert 1..3 bytes
                buf[pos:pos] = bytes(self._garbage_byte(None, detectable)
                                     for _ in range(int(rng.integers(1, 4))))
        self.frames_corrupted += int(hit.size)
        return bytes(buf)

    def _garbage_byte(self, old: int | None, detectable: bool) -> int:
        """A random byte: flagged 11 if it must be detectable, and never equal to ``old``."""
        rng = self._fault_rng
        while True:
            b = int(rng.integers(0xC0, 0x100)) if detectable else int(rng.integers(0, 0x100))
            if b != old:
                return b

    def _slave_queued(self) -> int:
        """Bytes readable at the slave end now (FIONREAD into a reused buffer; a memory
        line: its unread bytes)."""
        if self._pipe is not None:
            return len(self._pipe.buf)
        b = self._qbuf
        try:
            _ioctl(self._slave, _FIONREAD, b, True)
        except OSError:
            return 0
        return int.from_bytes(b, "little", signed=True)

    def _wait_delivered(self, target: int, timeout_s: float = _DELIVERY_TIMEOUT_S) -> None:
        """Spin (then nap) until ``target`` bytes are readable at the slave, or time out."""
        _await_delivery([(self, target)], timeout_s)

    # ------------------------------------------------------------------ lifetime
    def close(self) -> None:
        """Stop the thread and close both pty ends (or hang the line up). Idempotent."""
        self.stop()
        with self._lock:
            if self._line is not None:
                wires.close_line(self._line)
            for name in ("_master", "_slave"):
                fd = getattr(self, name)
                if fd >= 0:
                    try:
                        os.close(fd)
                    except OSError:
                        pass
                    setattr(self, name, -1)

    def __enter__(self) -> VirtualLaser:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __del__(self) -> None:  # pragma: no cover - safety net for forgotten fds
        try:
            self.close()
        except Exception:  # noqa: BLE001
            pass


def _fault_code(f: dict[str, dict[str, Any]]) -> int | None:
    """The code an out-of-range or stuck fault sends instead of a measurement, if any."""
    if "out_of_range" in f:
        return int(f["out_of_range"].get("code", NO_PEAK))
    stuck = f.get("stuck")
    return None if stuck is None or stuck["x"] is None else int(stuck["x"])


def _rngs(seed: Any) -> tuple[np.random.Generator, np.random.Generator]:
    """Independent generators for noise and faults, so a fault never shifts the noise."""
    if isinstance(seed, np.random.Generator):
        return seed, seed.spawn(1)[0]
    ss = seed if isinstance(seed, np.random.SeedSequence) else np.random.SeedSequence(seed)
    a, b = ss.spawn(2)
    return np.random.default_rng(a), np.random.default_rng(b)


def _await_delivery(pending: list[tuple[VirtualLaser, int]], timeout_s: float = _DELIVERY_TIMEOUT_S) -> None:
    """Wait until each laser's slave end holds its target byte count, or time out (counted
    in ``delivery_timeouts``). Lockstep only: nobody reads the slaves meanwhile.

    Spins for up to ``_SPIN_S`` (the kernel worker usually delivers within tens of µs on
    the other CPU), then sleeps in ``poll()`` on the slaves that have nothing yet: an idle
    CPU lets the scheduler run the worker here when the other CPU is busy."""
    t0 = 0.0
    while True:
        left = []
        empty = []
        for p in pending:
            q = p[0]._slave_queued()
            if q < p[1]:
                left.append(p)
                if q == 0:
                    empty.append(p[0]._slave)
        if not left:
            return
        pending = left
        now = time.perf_counter()
        if not t0:
            t0 = now
        elif now - t0 > timeout_s:
            for vl, _ in pending:
                vl.delivery_timeouts += 1
            return
        if now - t0 > _SPIN_S:
            if empty:
                poller = select.poll()
                for fd in empty:
                    poller.register(fd, select.POLLIN)
                poller.poll(1)
            else:
                time.sleep(20e-6)


class LaserGroup:
    """Lockstep emission of several virtual lasers: ``emit(t)`` has every laser produce and
    write its frames due by ``t`` (its own path, as ``emit_until``); ``wait()`` returns once
    the kernel delivered them to the pty slave ends. pty delivery runs on a kernel worker, so
    the caller does other work in between; a memory line has its bytes readable within the
    write (nothing to wait for).
    """

    def __init__(self, lasers: list[VirtualLaser]):
        self.lasers = list(lasers)
        self._poller = select.poll()
        self._by_fd: dict[int, VirtualLaser] = {}
        for vl in self.lasers:
            if vl._pipe is None:
                self._poller.register(vl._slave, select.POLLIN)
                self._by_fd[vl._slave] = vl
        self._pending: list[tuple[VirtualLaser, int]] = []

    def emit(self, t: float) -> int:
        """Write every laser's frames due by ``t`` (not waiting for delivery); bytes written."""
        pend: list[tuple[VirtualLaser, int]] = []
        self._pending = pend
        # unread bytes at the pty slaves (the runtime normally drained them), one poll for all
        q0s = {fd: self._by_fd[fd]._slave_queued() for fd, _ in self._poller.poll(0)} if self._by_fd else None
        total = 0
        for vl in self.lasers:
            if vl._thread is None:      # lockstep: nobody else emits meanwhile
                w = vl._emit(t)
            else:
                with vl._lock:
                    w = vl._emit(t)
            total += w
            if w and q0s is not None and vl._pipe is None:
                pend.append((vl, min(q0s.get(vl._slave, 0) + w, _LDISC_CAP)))
        return total

    def wait(self) -> None:
        """Return once the bytes of the last ``emit`` are readable at every slave end."""
        pending, self._pending = self._pending, []
        if pending:
            _await_delivery(pending)
