"""``rig check --machine``: is this machine ready for ``rig run`` with this config?

Each item is a :class:`Item` — pass / warn / fail / n/a, the measured value and a one-line
fix. ``fail`` is what would keep ``rig run`` from working (a device it cannot open); the
real-time settings ``rig run`` applies "when the OS permits" (``clock.apply_realtime``) are
warnings: the run works, with worse timing.

The readers are split in two: small ``parse_*`` functions that take the text of a file or a
command's output (unit-tested with hand-written inputs) and thin ``read_*``/``check_*``
functions that fetch that text from /proc, /sys or ``ip``. Nothing here opens a device:
serial ports are looked at with ``stat``/``access`` and the /proc/*/fd links, CAN
interfaces through /sys and ``ip -details link``; only the F/T hosts are spoken to (one
Modbus read, short timeout, only the configured hosts).
"""

from __future__ import annotations

import gzip
import os
import re
import resource
import shutil
import socket
import stat
import subprocess
from dataclasses import dataclass
from pathlib import Path
from typing import Iterable, Optional

from ..config import RigConfig

PASS, WARN, FAIL, NA = "pass", "warn", "fail", "n/a"


@dataclass(frozen=True)
class Item:
    """One readiness item: what was checked, its status, what was found, how to fix it."""

    name: str
    status: str          # PASS, WARN, FAIL or NA
    value: str
    fix: str = ""


# --------------------------------------------------------------------------- pure parsers
def parse_cpu_list(text: str) -> frozenset[int]:
    """A kernel CPU list ("1", "1-3,5", "2-7:2") as a set; flags in it (isolcpus'
    "domain,managed_irq,1-3") are skipped."""
    cpus: set[int] = set()
    for part in text.strip().split(","):
        part = part.strip()
        m = re.fullmatch(r"(\d+)(?:-(\d+)(?::(\d+))?)?", part)
        if not m:
            continue
        a = int(m.group(1))
        b = int(m.group(2)) if m.group(2) else a
        step = int(m.group(3)) if m.group(3) else 1
        cpus.update(range(a, b + 1, step))
    return frozenset(cpus)


def parse_cmdline(text: str) -> dict[str, frozenset[int]]:
    """The CPU isolation options of a kernel command line (/proc/cmdline):
    ``{"isolcpus", "nohz_full", "rcu_nocbs"}`` -> CPU sets (empty when absent)."""
    out = {k: frozenset() for k in ("isolcpus", "nohz_full", "rcu_nocbs")}
    for word in text.split():
        if word == "--":                    # what follows is for init, not the kernel
            break
        key, _, value = word.partition("=")
        if key in out:
            out[key] = parse_cpu_list(value)
    return out


def parse_preempt_rt(sys_realtime: Optional[str], uname_version: str, kconfig: Optional[str]) -> tuple[bool, str]:
    """Whether the kernel has real-time preemption, and the evidence: /sys/kernel/realtime
    ("1" on PREEMPT_RT kernels; absent otherwise), ``uname -v`` ("PREEMPT_RT"/"PREEMPT RT"),
    the kernel config (CONFIG_PREEMPT_RT=y) where readable."""
    evidence = []
    rt = False
    if sys_realtime is not None:
        rt |= sys_realtime.strip() == "1"
        evidence.append(f"/sys/kernel/realtime={sys_realtime.strip()}")
    else:
        evidence.append("no /sys/kernel/realtime")
    if re.search(r"PREEMPT[_ ]RT", uname_version):
        rt = True
    model = re.search(r"PREEMPT(?:_RT|_DYNAMIC| RT)?", uname_version)
    evidence.append(f"uname -v: {model.group(0) if model else 'no PREEMPT'}")
    if kconfig is not None:
        m = re.search(r"^CONFIG_PREEMPT_RT=y", kconfig, re.M)
        rt |= bool(m)
        chosen = [f"CONFIG_{k}=y" for k in ("PREEMPT_RT", "PREEMPT", "PREEMPT_LAZY", "PREEMPT_VOLUNTARY",
                                              "PREEMPT_NONE", "PREEMPT_DYNAMIC")
                  if re.search(rf"^CONFIG_{k}=y", kconfig, re.M)]
        evidence.append(f"kernel config: {' '.join(chosen)}" if chosen else "kernel config: no preemption model")
    return rt, ", ".join(evidence)


def parse_ip_details(text: str) -> dict:
    """What ``ip -details link show DEV`` says about a CAN interface: ``up`` (the UP flag),
    ``kind`` ("can", "vcan", …), ``bitrate`` (None for vcan), ``can_state`` (ERROR-ACTIVE,
    BUS-OFF, …)."""
    flags = re.search(r"<([^>]*)>", text)
    kind = re.search(r"^\s*(vcan|vxcan|can|slcan)\b", text, re.M)
    bitrate = re.search(r"\bbitrate (\d+)", text)
    state = re.search(r"\bcan (?:<[^>]*> )?state (\S+)", text)
    return {"up": bool(flags and "UP" in flags.group(1).split(",")),
            "kind": kind.group(1) if kind else None,
            "bitrate": int(bitrate.group(1)) if bitrate else None,
            "can_state": state.group(1) if state else None}


def holders(path: str, fd_links: Iterable[tuple[int, str]], own_pid: int) -> list[int]:
    """The processes other than ``own_pid`` that hold ``path`` open, from (pid, link target)
    pairs as /proc/PID/fd/* give them."""
    real = os.path.realpath(path)
    return sorted({pid for pid, target in fd_links if pid != own_pid and target in (path, real)})


# --------------------------------------------------------------------------- readers
def _read(path: str) -> Optional[str]:
    try:
        return Path(path).read_text()
    except OSError:
        return None


def read_kernel_config() -> Optional[str]:
    """/proc/config.gz or /boot/config-$(uname -r), whichever is readable (None: neither)."""
    try:
        with gzip.open("/proc/config.gz", "rt") as f:
            return f.read()
    except OSError:
        return _read(f"/boot/config-{os.uname().release}")


def fd_links() -> list[tuple[int, str]]:
    """(pid, target) of every open file descriptor this user may see under /proc."""
    out = []
    for d in Path("/proc").iterdir():
        if not d.name.isdigit():
            continue
        try:
            for fd in (d / "fd").iterdir():
                try:
                    out.append((int(d.name), os.readlink(fd)))
                except OSError:
                    pass
        except OSError:
            pass
    return out


def _ip_details(dev: str) -> Optional[str]:
    ip = shutil.which("ip")
    if ip is None:
        return None
    try:
        r = subprocess.run([ip, "-details", "link", "show", dev], capture_output=True, text=True, timeout=5)
    except (OSError, subprocess.TimeoutExpired):
        return None
    return r.stdout if r.returncode == 0 else None


# --------------------------------------------------------------------------- machine items
def check_kernel() -> Item:
    rt, evidence = parse_preempt_rt(_read("/sys/kernel/realtime"), os.uname().version, read_kernel_config())
    if rt:
        return Item("kernel real-time preemption", PASS, f"PREEMPT_RT ({evidence})")
    return Item("kernel real-time preemption", WARN, f"not PREEMPT_RT ({evidence})",
                "install a PREEMPT_RT kernel (Debian/Ubuntu: apt install linux-image-rt-amd64 / "
                "linux-realtime) and boot it")


def check_isolation(cfg: RigConfig, cmdline: Optional[str] = None) -> Item:
    cpus = cfg.realtime.cpu_affinity
    name = "CPU isolation"
    text = cmdline if cmdline is not None else (_read("/proc/cmdline") or "")
    iso = parse_cmdline(text)
    found = ", ".join(f"{k}={sorted(v)}" for k, v in iso.items() if v) or "no isolcpus/nohz_full"
    if not cpus:
        return Item(name, WARN, f"realtime.cpu_affinity not set; kernel: {found}",
                    "set realtime.cpu_affinity to a CPU isolated on the kernel command line")
    want = set(cpus)
    n = os.cpu_count() or 1
    missing_cpu = sorted(c for c in want if c >= n)
    if missing_cpu:
        return Item(name, WARN, f"realtime.cpu_affinity {sorted(want)}: CPU {missing_cpu} does not exist "
                    f"({n} CPUs)", f"set realtime.cpu_affinity to CPUs 0..{n - 1}")
    if want <= iso["isolcpus"] and want <= iso["nohz_full"]:
        return Item(name, PASS, f"realtime.cpu_affinity {sorted(want)}; kernel: {found}")
    cpu_s = ",".join(map(str, sorted(want)))
    return Item(name, WARN, f"realtime.cpu_affinity {sorted(want)} not isolated; kernel: {found}",
                f"add isolcpus={cpu_s} nohz_full={cpu_s} rcu_nocbs={cpu_s} to the kernel command line "
                "(GRUB_CMDLINE_LINUX in /etc/default/grub, update-grub, reboot)")


def _limit_text(v: int) -> str:
    return "unlimited" if v == resource.RLIM_INFINITY else str(v)


def check_rt_priority(cfg: RigConfig) -> Item:
    """RLIMIT_RTPRIO against realtime.sched_fifo_priority, and whether sched_setscheduler
    works (tried on this thread, then set back)."""
    prio = cfg.realtime.sched_fifo_priority
    name = "RT priority"
    soft, hard = resource.getrlimit(resource.RLIMIT_RTPRIO)
    limit = f"RLIMIT_RTPRIO {_limit_text(soft)}/{_limit_text(hard)}"
    if prio is None:
        return Item(name, WARN, f"realtime.sched_fifo_priority not set ({limit})",
                    "set realtime.sched_fifo_priority (e.g. 80) so the loop runs SCHED_FIFO")
    err = try_sched_fifo(prio)
    euid = os.geteuid()
    if err is None:
        how = "root" if euid == 0 else limit
        return Item(name, PASS, f"SCHED_FIFO {prio} works ({how})")
    return Item(name, WARN, f"SCHED_FIFO {prio} refused: {err} ({limit})",
                f"allow it: '@realtime - rtprio {prio}' in /etc/security/limits.d/rig.conf and the user in "
                "group realtime (log in again), or setcap cap_sys_nice+ep on the interpreter")


def try_sched_fifo(priority: int) -> Optional[str]:
    """Switch this thread to SCHED_FIFO ``priority`` and back; None if it worked, else why not."""
    try:
        old_policy, old_param = os.sched_getscheduler(0), os.sched_getparam(0)
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
    except (OSError, AttributeError) as e:
        return str(e)
    os.sched_setscheduler(0, old_policy, old_param)
    return None


def check_memlock(cfg: RigConfig) -> Item:
    name = "memory lock"
    soft, hard = resource.getrlimit(resource.RLIMIT_MEMLOCK)
    limit = f"RLIMIT_MEMLOCK {_limit_text(soft)}/{_limit_text(hard)}"
    if not cfg.realtime.mlockall:
        return Item(name, WARN, f"realtime.mlockall off ({limit})",
                    "set realtime.mlockall: true (no page faults in the loop)")
    err = try_mlockall()
    if err is None:
        return Item(name, PASS, f"mlockall works ({'root' if os.geteuid() == 0 else limit})")
    return Item(name, WARN, f"mlockall refused: {err} ({limit})",
                "allow it: '@realtime - memlock unlimited' in /etc/security/limits.d/rig.conf (log in again)")


def try_mlockall() -> Optional[str]:
    """mlockall(MCL_CURRENT | MCL_FUTURE) and munlockall at once; None if it worked."""
    import ctypes
    libc = ctypes.CDLL(None, use_errno=True)
    if libc.mlockall(1 | 2) != 0:
        e = ctypes.get_errno()
        return os.strerror(e)
    libc.munlockall()
    return None


def check_governor(governors: Optional[dict[int, str]] = None) -> Item:
    name = "CPU frequency governor"
    if governors is None:
        governors = {}
        for p in sorted(Path("/sys/devices/system/cpu").glob("cpu[0-9]*/cpufreq/scaling_governor")):
            text = _read(str(p))
            if text is not None:
                governors[int(p.parent.parent.name[3:])] = text.strip()
    if not governors:
        return Item(name, NA, "no cpufreq (a VM, or frequency fixed by the firmware)")
    other = {c: g for c, g in governors.items() if g != "performance"}
    value = ", ".join(f"cpu{c} {g}" for c, g in sorted(governors.items()))
    if not other:
        return Item(name, PASS, value)
    return Item(name, WARN, value, "cpupower frequency-set -g performance (and disable deep C-states in the BIOS)")


def check_smt(active: Optional[str] = None) -> Item:
    name = "SMT (hyper-threading)"
    active = active if active is not None else _read("/sys/devices/system/cpu/smt/active")
    if active is None:
        return Item(name, NA, "no /sys/devices/system/cpu/smt")
    if active.strip() == "0":
        return Item(name, PASS, "off")
    return Item(name, WARN, "on: the loop's CPU shares its core with a sibling",
                "boot with nosmt (or echo off > /sys/devices/system/cpu/smt/control), or isolate both siblings")


# --------------------------------------------------------------------------- device items
def check_serial_port(name: str, port: str, links: Optional[list[tuple[int, str]]] = None) -> Item:
    """The port exists, is a character device, this user may read and write it, and no other
    process holds it open (never opened here: opening a tty can toggle DTR and reset a device)."""
    try:
        st = os.stat(port)
    except OSError as e:
        return Item(name, FAIL, f"serial port {port} does not exist ({e.strerror})",
                    "plug the adapter in, or set the port in the config (ls -l /dev/serial/by-id/)")
    if not stat.S_ISCHR(st.st_mode):
        return Item(name, FAIL, f"{port} is not a serial port (not a character device)", "set the port in the config")
    if not os.access(port, os.R_OK | os.W_OK):
        return Item(name, FAIL, f"serial port {port}: no read/write permission",
                    "add the user to the port's group (usually dialout) and log in again")
    pids = holders(port, links if links is not None else fd_links(), os.getpid())
    if pids:
        return Item(name, FAIL, f"serial port {port} is held by process {', '.join(map(str, pids))}",
                    "stop that process (ps -p PID; ModemManager and serial consoles are the usual ones)")
    return Item(name, PASS, f"serial port {port}: present, read/write, not held by another process")


def check_can(cfg: RigConfig) -> Item:
    can = cfg.devices.can
    name = f"CAN {can.interface} {can.channel}"
    if can.interface == "virtual":
        return Item(name, NA, "python-can virtual bus inside the runtime's process: nothing on this machine to check")
    if can.interface in ("slcan", "rig_slcan"):
        port = can.channel.split("@")[0]
        it = check_serial_port(name, port)
        if it.status == PASS:
            return Item(name, PASS, f"{it.value}; bitrate {can.bitrate} is set by the runtime over SLCAN when it "
                        "opens the adapter (not checked)")
        return it
    if can.interface != "socketcan":
        return Item(name, NA, f"interface {can.interface}: not checked (only socketcan, slcan, virtual are)")
    return judge_socketcan(name, can.channel, can.bitrate, Path("/sys/class/net", can.channel).exists(),
                           _read(f"/sys/class/net/{can.channel}/flags"), _ip_details(can.channel))


def judge_socketcan(name: str, channel: str, bitrate: int, exists: bool, sys_flags: Optional[str],
                    ip_details: Optional[str]) -> Item:
    """A socketcan interface from what /sys/class/net/CHANNEL and ``ip -details link`` say."""
    if not exists:
        return Item(name, FAIL, f"CAN interface {channel} does not exist",
                    "plug in the CAN adapter / load its driver (ip -details link; dmesg), or set devices.can.channel")
    up_cmd = f"ip link set {channel} up type can bitrate {bitrate}"
    info = parse_ip_details(ip_details) if ip_details is not None else None
    up = info["up"] if info is not None else bool(sys_flags and int(sys_flags.strip(), 16) & 0x1)
    if not up:
        return Item(name, FAIL, f"CAN interface {channel} is down", f"{up_cmd} (as root)")
    if info is None:
        return Item(name, WARN, f"CAN interface {channel} up; bitrate unknown (no `ip` command)",
                    "install iproute2 to check the bitrate")
    if info["kind"] in ("vcan", "vxcan"):
        return Item(name, PASS, f"{info['kind']} {channel} up (virtual CAN: no bitrate)")
    if info["bitrate"] is not None and info["bitrate"] != bitrate:
        return Item(name, FAIL, f"CAN interface {channel} at {info['bitrate']} bit/s, configured {bitrate}",
                    f"ip link set {channel} down; {up_cmd}")
    if info["can_state"] in ("BUS-OFF", "STOPPED"):
        return Item(name, FAIL, f"CAN interface {channel} state {info['can_state']}",
                    f"check wiring and termination; ip link set {channel} down; {up_cmd}")
    state = f", state {info['can_state']}" if info["can_state"] else ""
    return Item(name, PASS, f"CAN interface {channel} up at {info['bitrate']} bit/s{state}")


def check_ft_sensor(sensor, timeout_s: float = 0.5) -> Item:
    """The host resolves and answers one Modbus read of the wrench registers (TCP), or the
    RTU serial port is there. Port 0 is the simulator's: allocated when it starts."""
    name = f"F/T {sensor.name}"
    if sensor.transport == "rtu":
        return check_serial_port(name, sensor.serial_port)
    if sensor.port == 0:
        return Item(name, NA, f"{sensor.host}:0: the simulator's endpoint, allocated when it starts")
    try:
        addr = socket.getaddrinfo(sensor.host, sensor.port, type=socket.SOCK_STREAM)[0][4][0]
    except OSError as e:
        return Item(name, FAIL, f"host {sensor.host} does not resolve ({e})",
                    "make the name resolve (DNS, /etc/hosts) or put the sensor's address in the config")
    err = modbus_read(addr, sensor.port, sensor.unit_id, timeout_s)
    if err:
        return Item(name, FAIL, f"{sensor.host} ({addr}:{sensor.port}): {err}",
                    "power and network of the sensor (ping it), its port and unit id in the config")
    return Item(name, PASS, f"{sensor.host} ({addr}:{sensor.port}) answers a Modbus read")


def modbus_read(host: str, port: int, unit_id: int, timeout_s: float) -> Optional[str]:
    """One read of the F/T wrench registers with pymodbus; None if it answered, else why not."""
    from pymodbus.client import ModbusTcpClient
    from drivers.ft_codec import REG_COUNT, REG_START
    from .quiet import quiet_device_libraries
    quiet_device_libraries()
    client = ModbusTcpClient(host, port=port, timeout=timeout_s, retries=0)
    try:
        if not client.connect():
            return f"no connection within {timeout_s:g} s"
        r = client.read_holding_registers(REG_START, count=REG_COUNT, device_id=unit_id)
        if r.isError():
            return f"Modbus error reply: {r}"
        return None
    except Exception as e:          # pymodbus raises its own exception tree for I/O and timeouts
        return f"no Modbus answer ({type(e).__name__}: {e})"
    finally:
        client.close()


def check_machine(cfg: RigConfig) -> list[Item]:
    """Every readiness item for ``rig run`` with ``cfg`` on this machine, in a fixed order."""
    items = [check_kernel(), check_isolation(cfg), check_rt_priority(cfg), check_memlock(cfg),
             check_governor(), check_smt()]
    links = None
    for laser in cfg.devices.lasers:
        name = f"laser {laser.role}"
        if laser.port == "sim":
            items.append(Item(name, NA, "port 'sim': a pty of the in-process simulator"))
            continue
        if links is None:
            links = fd_links()
        items.append(check_serial_port(name, laser.port, links))
    if cfg.devices.can.drives:
        items.append(check_can(cfg))
    items.extend(check_ft_sensor(s) for s in cfg.devices.ft.sensors)
    return items


def describe(items: list[Item]) -> list[str]:
    """One line per item: status, name, measured value, and the fix where there is one."""
    w = max((len(i.name) for i in items), default=0)
    return [f"{i.status.upper():4s}  {i.name:<{w}}  {i.value}" + (f"  -> fix: {i.fix}" if i.fix and i.status != PASS
                                                                   else "") for i in items]


def report_machine(cfg) -> int:
    """``rig check --machine`` after ``rig check``'s own checks passed (``commands.cmd_check``):
    every readiness item; exit 2 with one line per failing item."""
    import sys
    items = check_machine(cfg)
    print(f"machine readiness for `rig run --config {cfg.source}`:")
    for line in describe(items):
        print(f"  {line}")
    failed = [i for i in items if i.status == FAIL]
    warned = sum(i.status == WARN for i in items)
    for i in failed:
        print(f"rig check: error: {i.name}: {i.value}" + (f" (fix: {i.fix})" if i.fix else ""), file=sys.stderr)
    if failed:
        return 2
    print(f"ok: nothing keeps `rig run` from working on this machine ({warned} warning(s))")
    return 0
