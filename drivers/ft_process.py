"""The ``process`` F/T poller (``devices.ft.poller: process``, the default): the polling
core (:mod:`drivers.ft_poll`) in its own OS process, publishing into shared memory that the
control loop reads without locks, waits or system calls.

Why: pymodbus calls (and any Python work of the pollers) hold the interpreter lock; in a
thread of the runtime process they delayed the 5 ms loop thread by up to ~1 ms. In a
separate process they cannot.

* Start: ``multiprocessing`` with the ``spawn`` context (the runtime may run SCHED_FIFO and
  have threads, so it must not fork). The parent moves the child to SCHED_OTHER right after
  the start and the child does it again itself (it inherits the parent's policy, CPU
  affinity optional via ``cpus``). The child ignores SIGINT (Ctrl-C goes to the whole process
  group; the runtime stops the rig on it and still needs the sensors meanwhile).
* Handshake: the child connects and reads every sensor exactly as the in-process pollers'
  ``start()`` does and reports success, or the ``DeviceInitError`` (device, message, OS
  error), over a pipe before :meth:`ProcessPoller.start` returns; the parent re-raises it.
  Timestamps are ``time.monotonic()`` in the child (system-wide, the runtime's clock).
* Lifetime: the child stops on a ``"stop"`` message, on EOF of the pipe (the parent is gone,
  however it died) or when its parent pid changes; ``close()`` asks, joins, then terminates
  (then kills) after ``timeout_s + 2`` s.
* Shared memory: one fixed-size slot per sensor, written by exactly one poll thread of the
  child, read by the loop: a seqlock with a CRC (:mod:`rig_runtime.seqlock` has the
  protocol). A rejected read keeps the previous state; the next ``poll()`` retries.
"""

from __future__ import annotations

import logging
import multiprocessing
import multiprocessing.connection
import os
import signal
import struct
import time
from multiprocessing import shared_memory
from typing import Any, Callable, Optional

from rig_runtime import seqlock
from rig_runtime.clock import as_background_process, as_background_thread
from rig_runtime.config import FTBus

from rig_runtime.errors import DeviceInitError, picklable
from .ft_codec import Wrench
from .ft_poll import PollCore, Poller, Published

__all__ = ["ProcessPoller", "SlotWriter", "SlotReader", "SLOT_SIZE", "CAUSE_BYTES"]

CAUSE_BYTES = 240
# t, fx..mz | has_wrench, timeouts, errors, bad_frames, samples, connects, connect_failures,
# disconnects | exception code (-1: none), cause length, link down | cause (UTF-8, truncated)
_PAYLOAD = struct.Struct(f"<7d8QiH?x{CAUSE_BYTES}s")
SLOT_SIZE = seqlock.HEADER_BYTES + _PAYLOAD.size   # a multiple of 8: every slot's lock is aligned
_START_GRACE_S = 30.0                       # interpreter start + imports on a loaded machine
_WATCH_S = 0.2                              # how often the child looks at its parent


class SlotWriter:
    """Child side: publish :class:`Published` states into the slots (one writer per slot)."""

    def __init__(self, buf: memoryview) -> None:
        self._buf = buf                     # the SharedMemory's own view: no extra buffer exports

    def write(self, k: int, p: Published) -> None:
        w = p.wrench
        vals = (0.0,) * 6 if w is None else (w.fx, w.fy, w.fz, w.mx, w.my, w.mz)
        counters = dict(p.counters)
        cause = p.cause.encode("utf-8", "replace")[:CAUSE_BYTES]
        payload = _PAYLOAD.pack(p.t, *vals, w is not None, p.timeouts, p.errors, p.bad_frames,
                                counters.get("samples", 0), counters.get("connects", 0),
                                counters.get("connect_failures", 0), counters.get("disconnects", 0),
                                -1 if p.exc_code is None else p.exc_code, len(cause), p.link_down, cause)
        seqlock.write(self._buf, k * SLOT_SIZE, payload)


class SlotReader:
    """Loop side: ``refresh()`` sets ``sensors[k].pub`` from every slot whose sequence
    number moved and whose copy is consistent; costs one 8-byte read per sensor otherwise."""

    def __init__(self, buf: memoryview, sensors: tuple, make_pub: Callable[..., Any]) -> None:
        self._buf = buf
        self._sensors = sensors
        self._make = make_pub
        self._offs = tuple(k * SLOT_SIZE for k in range(len(sensors)))
        self._last = [0] * len(sensors)     # 0: nothing published yet (a published slot is ≥ 2)
        self._ks = tuple(range(len(sensors)))
        self.rejected = 0                   # torn or inconsistent copies seen (retried next time)

    def refresh(self) -> None:
        buf, last, seq_of = self._buf, self._last, seqlock.seq
        for k, off in zip(self._ks, self._offs):
            if seq_of(buf, off) != last[k]:
                self._load(k, off)

    def _load(self, k: int, off: int) -> None:
        r = seqlock.read(self._buf, off, _PAYLOAD.size)
        if r is None:
            self.rejected += 1
            return
        s1, payload = r
        (t, fx, fy, fz, mx, my, mz, has_w, timeouts, errors, bad_frames, samples, connects,
         connect_failures, disconnects, exc, n, link_down, cause) = _PAYLOAD.unpack(payload)
        self._sensors[k].pub = self._make(
            (fx, fy, fz, mx, my, mz) if has_w else None, t, cause[:n].decode("utf-8", "ignore"),
            None if exc < 0 else exc, timeouts, errors, bad_frames,
            (("samples", samples), ("connects", connects), ("connect_failures", connect_failures),
             ("disconnects", disconnects)), link_down)
        self._last[k] = s1


def _make_pub(w6: Optional[tuple], *rest: Any) -> Published:
    """The parent's :class:`Published` from a slot (the saturation worked out from the six
    floats again: the slot does not carry it)."""
    if w6 is None:
        return Published(None, *rest)
    w = Wrench(*w6)
    return Published(w, *rest, w.saturation)


class ProcessPoller(Poller):
    """Parent side: the child process, its pipe and the shared memory it publishes into.
    The parent's own :class:`PollCore` opens nothing: it gives the layout (and checks it,
    ConfigError before anything starts) and holds the states the reader takes over."""

    def __init__(self, cfg: FTBus, endpoints: dict[str, tuple[str, int]], reconnect_s: float,
                 cpus: Optional[tuple[int, ...]] = None) -> None:
        super().__init__(cfg, endpoints, reconnect_s)
        self._cfg = cfg
        self._endpoints = dict(endpoints)
        self._reconnect_s = reconnect_s
        self._cpus = cpus
        self.process: Optional[multiprocessing.process.BaseProcess] = None
        self._conn: Optional[multiprocessing.connection.Connection] = None
        self._shm: Optional[shared_memory.SharedMemory] = None
        self._reader: Optional[SlotReader] = None
        self._dead = ""

    # ------------------------------------------------------------------ start
    def start(self) -> None:
        """Spawn the child; return once it has read every sensor, else raise DeviceInitError."""
        try:
            self._start()
        except BaseException:
            self.close()
            raise
        self._reader.refresh()              # type: ignore[union-attr]  # what the child read at open

    def _start(self) -> None:
        ctx = multiprocessing.get_context("spawn")
        n = len(self.core.sensors)
        self._shm = shared_memory.SharedMemory(create=True, size=n * SLOT_SIZE)
        self._shm.buf[:n * SLOT_SIZE] = bytes(n * SLOT_SIZE)
        here, there = ctx.Pipe(duplex=True)
        self._conn = here
        args = (self._cfg, self._endpoints, self._reconnect_s, self._shm.name,
                there, os.getpid(), self._cpus, logging.getLogger("pymodbus").level)
        proc = ctx.Process(target=child_main, args=args, name="ft-poll", daemon=True)
        try:
            proc.start()
        finally:
            there.close()                   # the child has its own copy: EOF here once it is gone
        self.process = proc
        as_background_process(proc.pid)    # as early as possible; the child repeats it
        budget = _START_GRACE_S + sum(
            self._cfg.timeout_s * (1 + 2 * len(link.sensors) * 3) for link in self.core.links)
        ready = multiprocessing.connection.wait([here, proc.sentinel], budget)
        if here in ready:
            try:
                msg = here.recv()
            except (EOFError, OSError):
                msg = None
        else:
            msg = None
        if msg is None:
            proc.join(0.5)
            what = (f"exited with code {proc.exitcode}" if proc.exitcode is not None
                    else f"did not report within {budget:g} s")
            raise DeviceInitError("ft", f"poll process {what} before reading the sensors")
        if msg[0] == "error":
            _, device, message, cause = msg
            raise DeviceInitError(device, message) from cause
        self._reader = SlotReader(self._shm.buf, self.core.sensors, _make_pub)

    # ------------------------------------------------------------------ running
    def latest(self, now: float) -> tuple[Published, ...]:
        """Every slot whose sequence moved is taken over first (one 8-byte read per sensor)."""
        if self._reader is not None:
            self._reader.refresh()
        return super().latest(now)

    def failure(self) -> str:
        """"" while the child runs; otherwise why the samples stopped (cheap once dead)."""
        if not self._dead and self.process is not None and self.process.exitcode is not None:
            self._dead = f"F/T poll process exited with code {self.process.exitcode}"
        return self._dead

    # ------------------------------------------------------------------ stop
    def close(self) -> None:
        """Stop and join the child (terminate, then kill, if it does not finish in time), take
        over its last published states, release the shared memory. Idempotent."""
        proc, conn = self.process, self._conn
        if conn is not None:
            try:
                conn.send("stop")
            except (OSError, ValueError):
                pass
        if proc is not None:
            proc.join(self._cfg.timeout_s + 2.0)
            if proc.exitcode is None:
                proc.terminate()
                proc.join(1.0)
            if proc.exitcode is None:
                proc.kill()
                proc.join(1.0)
            self.failure()
        if conn is not None:
            conn.close()
            self._conn = None
        if self._reader is not None:
            self._reader.refresh()          # the child's last words: latest() keeps them after close
            self._reader = None
        if self._shm is not None:
            self._shm.close()
            try:
                self._shm.unlink()
            except FileNotFoundError:
                pass
            self._shm = None
        if proc is not None:
            try:
                proc.close()
            except ValueError:              # still running after kill: leave it to the OS
                pass
            self.process = None


# --------------------------------------------------------------------------- child
def child_main(cfg: FTBus, endpoints: dict[str, tuple[str, int]], reconnect_s: float, shm_name: str, conn: multiprocessing.connection.Connection,
               parent_pid: int, cpus: Optional[tuple[int, ...]], pymodbus_log_level: int) -> None:
    """Entry point of the poll process: open like in-process, report, poll until told to
    stop or orphaned. (Spawned: the parent's logging setup is not inherited, so the
    pymodbus logger level — which the runtime lowers — is passed on.)"""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    logging.getLogger("pymodbus").setLevel(pymodbus_log_level)
    as_background_thread()
    if cpus:
        try:
            os.sched_setaffinity(0, set(cpus))
        except (OSError, AttributeError):
            pass
    shm = shared_memory.SharedMemory(name=shm_name)
    core = PollCore(cfg, endpoints, time.monotonic, reconnect_s)
    writer = SlotWriter(shm.buf)
    for k, s in enumerate(core.sensors):
        s.sink = (lambda p, k=k: writer.write(k, p))
    try:
        try:
            core.open()
        except DeviceInitError as exc:
            conn.send(("error", exc.device, _message(exc), picklable(exc.__cause__)))
            return
        except Exception as exc:            # noqa: BLE001 - reported to the parent, which raises
            conn.send(("error", "ft", f"poll process: {type(exc).__name__}: {exc}", None))
            return
        core.start_threads()
        conn.send(("ok",))
        while True:
            try:
                if conn.poll(_WATCH_S):
                    conn.recv()             # "stop"
                    break
            except (EOFError, OSError):     # the parent is gone
                break
            if os.getppid() != parent_pid:
                break
    finally:
        core.close()
        shm.close()
        conn.close()


def _message(exc: DeviceInitError) -> str:
    text = str(exc)
    prefix = f"{exc.device}: "
    return text[len(prefix):] if text.startswith(prefix) else text
