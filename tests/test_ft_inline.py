"""The inline F/T poller on a lockstep clock: the driver's ``poll(t)`` sends and collects,
``VirtualFTServer.answer_pending()`` (what the lockstep simulator calls inside its
``advance(t)``) answers in between — deterministic, no thread, no waiting. Also: the
``devices.ft.poller`` key, and the F/T modules' layering.

Times are binary fractions (h = 2^-7 s, poll_hz = 16, timeout 2^-3 s) so that which poll
crosses a bound does not depend on rounding."""

from __future__ import annotations

import ast
import concurrent.futures
import subprocess
import sys
import threading
from pathlib import Path

import pytest
import yaml

from rig_runtime.hardware import Freshness
from drivers.ft300 import FTSensorSet
from drivers.ft_codec import Wrench
from rig_runtime import config as rig_config
from drivers.ft300 import POLLERS
from rig_runtime.config import FT_POLLERS, FTBus, FTSensor
from rig_runtime.errors import ConfigError
from sim_backend.virtual_ft import VirtualFTServer

from .test_ft300 import quiet_port

ROOT = Path(__file__).resolve().parent.parent
H = 2.0 ** -7                   # 7.8125 ms "control period"
POLL_HZ = 16.0                  # a round every 8 periods
TIMEOUT_S = 2.0 ** -3           # 16 periods
T0 = 1.0


def inline_bus(*names: str, **kw) -> FTBus:
    return FTBus(poller="inline", poll_hz=POLL_HZ, timeout_s=TIMEOUT_S,
                 sensors=tuple(FTSensor(name=n) for n in names), **kw)



class Lockstep:
    """The simulated server and the driver, stepped like the lockstep dry run steps them:
    ``advance`` (the simulator answers what is pending), then the runtime's ``poll(t)``.

    The open (``configure()``) is the one part in wall-clock time: blocking reads that the
    server's thread answers. That thread's scheduling is not what these tests check; the
    tolerance they state is TIMEOUT_S (0.125 s) for each reply of the open — a later one
    would count a timeout and a reconnect, and the open is checked to have had neither."""

    def __init__(self, names: tuple[str, ...], reconnect_s: float = 4 * H, ports: dict | None = None) -> None:
        self.names = names
        self.srv = VirtualFTServer(list(names), ports=ports).start()
        self.drv = FTSensorSet(inline_bus(*names), self.srv.endpoints, reconnect_s=reconnect_s)
        try:
            self.drv.configure()         # blocking reads, answered by the server's own thread
        except BaseException:
            self.srv.close()
            raise
        late = [f"{s.name}: {s.timeouts} timeouts, {s.bad_frames} bad frames, {s.counters['connects']} connects"
                for s in self.drv.poller.core.sensors if s.timeouts or s.bad_frames or s.counters["connects"] != 1]
        if late:
            self.close()
            pytest.fail(f"the open had replies later than {TIMEOUT_S} s: {late}")
        self.srv.answer_pending()       # the first advance retires that thread
        self.k = 0

    @property
    def t(self) -> float:
        return T0 + self.k * H

    def step(self) -> dict:
        self.k += 1
        self.srv.answer_pending()
        return self.drv.poll(self.t)

    def close(self) -> None:
        self.drv.close()
        self.srv.close()


@pytest.fixture
def ls():
    x = Lockstep(("ft_fl", "ft_fr", "ft_rl", "ft_rr"))
    yield x
    x.close()


def is_round(k: int) -> bool:
    """Whether poll ``k`` (k ≥ 1 after the fixture's start) sends requests."""
    return (k - 1) % round(1 / (POLL_HZ * H)) == 0


# --------------------------------------------------------------------------- the pipeline
def test_requests_of_poll_k_are_answered_in_between_and_seen_in_poll_k_plus_1(ls):
    names = ls.names
    assert not [t for t in threading.enumerate() if t.name.startswith(("ft-poll", "virtual-ft"))]
    first = ls.drv.poll(ls.t)
    # read at open: no time on this clock yet, so infinitely old (the supervisor's stale rule)
    assert all(r.t == -float("inf") and r.health.fresh for r in first.values())
    served = {n: ls.srv.served(n) for n in names}
    for rnd in range(40):
        w = Wrench(fx=float(rnd), fy=-rnd / 2, mz=rnd / 1000)     # whole counts: decoded exactly
        for n in names:
            ls.srv.set_wrench(n, w)
        r = ls.step()                                   # answers the requests of the previous poll…
        assert all(ls.srv.served(n) == served[n] + rnd + 1 for n in names)
        assert all(r[n].wrench == w and r[n].t == ls.t for n in names), rnd  # …seen now
        assert all(r[n].health.fresh for n in names)
        for _ in range(7):                              # no round due: nothing sent, nothing served…
            later = ls.step()
            assert all(later[n].t == r[n].t and later[n].health is r[n].health for n in names)
            assert later is r                           # …nothing new published: the same readings
        assert all(ls.srv.served(n) == served[n] + rnd + 1 for n in names)


def _trace(faults: dict[int, tuple]) -> list:
    """Every reading of one sensor over 120 polls, with faults switched at given polls."""
    x = Lockstep(("a", "b"))
    try:
        out = []
        for k in range(1, 121):
            if k in faults:
                kind, params = faults[k]
                x.srv.clear("a") if kind == "clear" else x.srv.inject("a", kind, **params)
            x.srv.set_wrench("a", Wrench(fy=0.01 * k))
            for n, r in x.step().items():
                h = r.health
                out.append((k, n, r.wrench, r.t, h.state, h.cause, h.timeouts, h.errors,
                            h.bad_frames, x.drv.counters()))
        return out
    finally:
        x.close()


def test_inline_polling_is_deterministic():
    faults = {10: ("dropout", {}), 50: ("clear", None), 60: ("out_of_range", {"code": 6}),
              75: ("clear", None), 80: ("corrupt", {"mode": "truncate"}), 100: ("clear", None)}
    one, two = _trace(faults), _trace(faults)
    assert one == two
    states = {row[4] for row in one}
    assert states == {Freshness.FRESH, Freshness.INVALID}       # the driver judges no age


def test_a_timeout_is_counted_in_simulated_time_and_only_for_the_silent_sensors():
    x = Lockstep(("a", "b", "c"))
    try:
        x.srv.inject("a", "dropout")
        x.srv.inject("c", "dropout")
        x.srv.set_wrench("b", Wrench(mx=0.5))
        x.step()                                        # k = 1: requests to all three
        t_sent = x.t
        while True:
            r = x.step()
            if x.t - t_sent >= TIMEOUT_S:
                break
            assert r["a"].health.timeouts == r["c"].health.timeouts == 0
        assert x.t - t_sent == TIMEOUT_S
        assert r["b"].wrench == Wrench(mx=0.5) and r["b"].health.timeouts == 0
        for n in ("a", "c"):                            # the poll that reaches the timeout
            assert r[n].health.timeouts == 1 and "timeout" in r[n].health.cause
            assert x.drv.counters()[f"{n}.connects"] == 1
        x.srv.clear("a")
        x.srv.clear("c")
        while not is_round(x.k):
            r = x.step()
        r = x.step()                                    # reconnected at the round, answered next poll
        assert all(v.health.fresh and v.t == x.t for v in r.values()), r
        assert x.drv.counters()["a.connects"] == 2 and x.drv.counters()["b.connects"] == 1
    finally:
        x.close()


def test_a_silent_sensor_keeps_its_t_and_is_not_judged_by_age(ls):
    """In simulated time: after a dropout, t stays at the last sample's arrival however
    long it lasts (the age is the supervisor's to judge); timeouts are counted, one per
    request left unanswered for TIMEOUT_S; the state stays FRESH."""
    ls.step()
    r = ls.step()
    assert r["ft_fl"].health.fresh
    t_sample = r["ft_fl"].t
    ls.srv.inject("ft_fl", "dropout")
    # polls 3..66: requests go out at the rounds of polls 9, 25, 41, 57 (each unanswered for
    # 16 periods times out at the round that sends the next): timeouts at polls 25, 41, 57
    for _ in range(64):
        r = ls.step()
        assert r["ft_fl"].t == t_sample and r["ft_fl"].health.state is Freshness.FRESH
    assert ls.t - r["ft_fl"].t == 64 * H
    assert r["ft_fl"].health.timeouts == 3 and "timeout" in r["ft_fl"].health.cause
    assert r["ft_fr"].health.fresh and r["ft_fr"].health.cause == "" and r["ft_fr"].t == ls.t


def test_garbled_and_truncated_replies_are_bad_frames(ls):
    ls.step()
    ls.srv.inject("ft_fl", "corrupt")                   # garbled: rejected when it arrives
    while not is_round(ls.k):
        ls.step()
    r = ls.step()
    assert r["ft_fl"].health.bad_frames == 1 and "byte count 255" in r["ft_fl"].health.cause
    ls.srv.inject("ft_fl", "corrupt", mode="truncate")  # half a reply: waits for the rest until the timeout
    while not is_round(ls.k):
        ls.step()
    t_sent = ls.t
    r = ls.step()
    while ls.t - t_sent < TIMEOUT_S:
        assert r["ft_fl"].health.bad_frames == 1
        r = ls.step()
    assert r["ft_fl"].health.bad_frames == 2 and "truncated response" in r["ft_fl"].health.cause
    assert r["ft_fl"].health.timeouts == 0


def test_pymodbus_client_is_answered_by_answer_pending():
    """The lockstep way of serving, read by an independent client: pymodbus's blocking
    client in a thread, the server answering only when ``answer_pending()`` is called."""
    from pymodbus.client import ModbusTcpClient

    with VirtualFTServer(["a"]) as srv:
        srv.set_wrench("a", Wrench(fx=-12.34, mz=1.5))
        assert srv.answer_pending() == 0               # retires the thread: nothing answers now
        host, port = srv.endpoints["a"]
        client = ModbusTcpClient(host, port=port, timeout=5, retries=0)
        assert client.connect()
        try:
            with concurrent.futures.ThreadPoolExecutor(1) as ex:
                for count in (6, 2):
                    fut = ex.submit(client.read_holding_registers, 180, count=count, device_id=9)
                    answered = 0
                    while not fut.done():
                        answered += srv.answer_pending()
                    rr = fut.result()
                    assert answered == 1 and not rr.isError()
                    assert rr.registers == [64302, 0, 0, 0, 0, 1500][:count]
        finally:
            client.close()


def test_an_exception_response_is_invalid(ls):
    ls.srv.inject("ft_rr", "out_of_range", code=4)
    ls.step()
    r = ls.step()
    assert r["ft_rr"].health.state is Freshness.INVALID
    assert r["ft_rr"].health.cause == "Modbus exception 4 (server device failure)"


def test_lost_server_is_reported_and_reconnected_in_simulated_time():
    x = Lockstep(("a",), ports={"a": quiet_port()})     # reopened on that port below
    try:
        x.step()
        assert x.step()["a"].health.fresh
        port = x.srv.endpoints["a"][1]
        x.srv.close()
        causes = []
        for _ in range(40):
            causes.append(x.step()["a"].health)
        h = causes[-1]
        assert h.state is Freshness.INVALID and "cannot connect" in h.cause and "refused" in h.cause
        c = x.drv.counters()
        assert c["a.disconnects"] == 1 and c["a.connect_failures"] >= 2
        fails = c["a.connect_failures"]
        assert fails <= 40 * H / (4 * H) + 1           # backs off reconnect_s = 4 periods (of poll time)
        srv2 = VirtualFTServer(["a"], ports={"a": port}).start()
        srv2.answer_pending()
        x.srv = srv2
        srv2.set_wrench("a", Wrench(fz=7.0))
        r = None
        for _ in range(20):
            r = x.step()["a"]
            if r.health.fresh:
                break
        assert r.health.fresh and r.wrench == Wrench(fz=7.0) and x.drv.counters()["a.connects"] == 2
    finally:
        x.close()


# --------------------------------------------------------------------------- configuration
def _load_with_ft(tmp_path: Path, **ft) -> rig_config.RigConfig:
    src = ROOT / "configs" / "sim.yaml"
    raw = yaml.safe_load(src.read_text())
    raw["include"] = [str(src.parent / i) for i in raw["include"]]
    raw["devices"]["ft"].update(ft)
    path = tmp_path / "rig.yaml"
    path.write_text(yaml.safe_dump(raw))
    return rig_config.load(path)


def test_every_configurable_poller_exists():
    assert tuple(POLLERS) == FT_POLLERS


def test_shipped_configs_choose_their_poller():
    assert rig_config.load(ROOT / "configs" / "sim.yaml").devices.ft.poller == "inline"
    assert rig_config.load(ROOT / "configs" / "rig.yaml").devices.ft.poller == "process"
    assert rig_config.load(ROOT / "configs" / "sim-process.yaml").devices.ft.poller == "process"
    assert FTBus().poller == "process"


def test_unknown_poller_names_the_key(tmp_path):
    with pytest.raises(ConfigError) as ei:
        _load_with_ft(tmp_path, poller="fork")
    assert ei.value.key_path == "devices.ft.poller" and "rig.yaml" in str(ei.value)
    assert "process, thread, inline" in str(ei.value) and "'fork'" in str(ei.value)
    with pytest.raises(ConfigError, match="poller: expected one of process, thread, inline"):
        FTBus(poller="fork")


def test_inline_with_an_rtu_sensor_is_refused_by_the_config(tmp_path):
    rtu = {"name": "ft_fl", "transport": "rtu", "serial_port": "/dev/ttyUSB0"}
    with pytest.raises(ConfigError) as ei:
        _load_with_ft(tmp_path, sensors=[rtu])
    assert ei.value.key_path == "devices.ft.poller" and "RTU sensors (ft_fl)" in str(ei.value)
    assert _load_with_ft(tmp_path, sensors=[rtu], poller="thread").devices.ft.poller == "thread"
    with pytest.raises(ConfigError, match="poller"):
        FTBus(poller="inline", sensors=(FTSensor(name="x", transport="rtu", serial_port="/dev/null"),))


# --------------------------------------------------------------------------- layering
FT_MODULES = ("ft300", "ft_codec", "ft_modbus", "ft_poll", "ft_pollers", "ft_process")


def _imports(module: str) -> set[str]:
    """The ``drivers`` modules a driver module imports (statically or in a function)."""
    tree = ast.parse((ROOT / "drivers" / f"{module}.py").read_text())
    out = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom):
            name = node.module or ""
            if node.level == 1:
                out.add(name)
            elif name.startswith("drivers."):
                out.add(name.split(".", 1)[1])
        elif isinstance(node, ast.Import):
            out |= {a.name.split(".", 1)[1] for a in node.names if a.name.startswith("drivers.")}
    return out


def test_the_ft_modules_import_no_cycle():
    graph = {m: _imports(m) & set(FT_MODULES) for m in FT_MODULES}

    def reach(m: str, seen: set[str]) -> set[str]:
        for n in graph[m] - seen:
            seen.add(n)
            reach(n, seen)
        return seen

    assert all(m not in reach(m, set()) for m in FT_MODULES), graph
    assert graph["ft_codec"] == graph["ft_modbus"] == set()


def test_the_simulated_sensors_import_the_codec_not_the_driver():
    code = ("import sys, sim_backend.virtual_ft; "
            "print(sorted(m for m in sys.modules if m.startswith('drivers.')))")
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, check=True)
    loaded = set(eval(out.stdout))
    assert {"drivers.ft_codec", "drivers.ft_modbus"} <= loaded
    assert not loaded & {"drivers.ft300", "drivers.ft_poll", "drivers.ft_pollers", "drivers.ft_process"}


def test_the_driver_has_no_simulation_hook():
    hooks = ("poll_devices", "start_thread=", "serve_inline", "answer_pending", "attach_ft", "lockstep")
    for m in ("ft300", "ft_poll", "ft_pollers", "ft_process"):
        text = (ROOT / "drivers" / f"{m}.py").read_text()
        assert not [h for h in hooks if h in text], m
