"""`rig check --machine`: the readers' parsers on hand-written /proc, /sys and `ip` texts,
the device items against real files, ptys and sockets on 127.0.0.1, and the command end to
end (a missing serial port and an absent CAN interface fail, one line each; the shipped
simulator config says what applies)."""

import os
import pty
import socket
import subprocess
import sys
import threading

from rig_runtime import config
from rig_runtime.app import machine_check as mc
from drivers import ft_codec, ft_modbus
from tests.e2e import config_with

RIG = [sys.executable, "-m", "rig_runtime"]


def rig(*args, timeout=120):
    return subprocess.run(RIG + list(args), capture_output=True, text=True, timeout=timeout)


# --------------------------------------------------------------------------- parsers
def test_cpu_lists_and_kernel_command_line():
    assert mc.parse_cpu_list("1") == {1}
    assert mc.parse_cpu_list("1-3,5") == {1, 2, 3, 5}
    assert mc.parse_cpu_list("0-6:2") == {0, 2, 4, 6}
    assert mc.parse_cpu_list("domain,managed_irq,2-3") == {2, 3}
    iso = mc.parse_cmdline("BOOT_IMAGE=/vmlinuz root=/dev/sda1 ro quiet isolcpus=managed_irq,domain,1-2 "
                           "nohz_full=1-2 rcu_nocbs=1\n")
    assert iso == {"isolcpus": {1, 2}, "nohz_full": {1, 2}, "rcu_nocbs": {1}}
    # words after "--" go to init, not to the kernel
    assert mc.parse_cmdline("quiet -- isolcpus=1")["isolcpus"] == frozenset()
    assert mc.parse_cmdline("console=ttyS0 quiet") == {"isolcpus": frozenset(), "nohz_full": frozenset(),
                                                       "rcu_nocbs": frozenset()}


def test_preempt_rt_from_sys_uname_and_kernel_config():
    rt, ev = mc.parse_preempt_rt("1\n", "#1 SMP PREEMPT_RT Debian 6.1.76-1", "CONFIG_PREEMPT_RT=y\n")
    assert rt and "/sys/kernel/realtime=1" in ev and "CONFIG_PREEMPT_RT=y" in ev
    rt, ev = mc.parse_preempt_rt(None, "#1 SMP PREEMPT RT Mon Jan 1", None)      # older uname spelling
    assert rt
    rt, ev = mc.parse_preempt_rt(None, "#1 SMP PREEMPT_DYNAMIC @0",
                                 "CONFIG_PREEMPT_NONE=y\n# CONFIG_PREEMPT is not set\nCONFIG_PREEMPT_DYNAMIC=y\n")
    assert not rt
    assert ev == ("no /sys/kernel/realtime, uname -v: PREEMPT_DYNAMIC, "
                  "kernel config: CONFIG_PREEMPT_NONE=y CONFIG_PREEMPT_DYNAMIC=y")
    rt, _ = mc.parse_preempt_rt("0\n", "#1 SMP", "# CONFIG_PREEMPT_RT is not set\n")
    assert not rt


IP_CAN0 = """\
5: can0: <NOARP,UP,LOWER_UP,ECHO> mtu 16 qdisc pfifo_fast state UP mode DEFAULT group default qlen 10
    link/can  promiscuity 0 minmtu 0 maxmtu 0
    can state ERROR-ACTIVE (berr-counter tx 0 rx 0) restart-ms 100
\t  bitrate 500000 sample-point 0.875
\t  tq 125 prop-seg 6 phase-seg1 7 phase-seg2 2 sjw 1
\t  gs_usb: tseg1 1..16 tseg2 1..8 sjw 1..4 brp 1..1024 brp-inc 1
\t  clock 48000000 numtxqueues 1 numrxqueues 1 gso_max_size 65536 gso_max_segs 65535
"""
IP_CAN0_DOWN = """\
5: can0: <NOARP,ECHO> mtu 16 qdisc pfifo_fast state DOWN mode DEFAULT group default qlen 10
    link/can  promiscuity 0 minmtu 0 maxmtu 0
    can state STOPPED (berr-counter tx 0 rx 0) restart-ms 0
"""
IP_VCAN = """\
7: vcan0: <NOARP,UP,LOWER_UP> mtu 72 qdisc noqueue state UNKNOWN mode DEFAULT group default qlen 1000
    link/can  promiscuity 0 minmtu 0 maxmtu 0
    vcan numtxqueues 1 numrxqueues 1 gso_max_size 65536 gso_max_segs 65535
"""
IP_BUSOFF = IP_CAN0.replace("ERROR-ACTIVE", "BUS-OFF").replace("500000", "1000000")


def test_ip_details():
    assert mc.parse_ip_details(IP_CAN0) == {"up": True, "kind": "can", "bitrate": 500000, "can_state": "ERROR-ACTIVE"}
    assert mc.parse_ip_details(IP_CAN0_DOWN) == {"up": False, "kind": "can", "bitrate": None, "can_state": "STOPPED"}
    assert mc.parse_ip_details(IP_VCAN) == {"up": True, "kind": "vcan", "bitrate": None, "can_state": None}


def test_socketcan_items():
    j = mc.judge_socketcan
    assert j("CAN", "can0", 1000000, False, None, None).status == mc.FAIL
    down = j("CAN", "can0", 1000000, True, "0x80\n", IP_CAN0_DOWN)
    assert down.status == mc.FAIL and "down" in down.value and "bitrate 1000000" in down.fix
    wrong = j("CAN", "can0", 1000000, True, "0xc1\n", IP_CAN0)
    assert wrong.status == mc.FAIL and "500000" in wrong.value and "1000000" in wrong.value
    ok = j("CAN", "can0", 500000, True, "0xc1\n", IP_CAN0)
    assert ok.status == mc.PASS and "ERROR-ACTIVE" in ok.value
    assert j("CAN", "can0", 1000000, True, "0xc1\n", IP_BUSOFF).status == mc.FAIL
    assert j("CAN", "vcan0", 1000000, True, "0xc1\n", IP_VCAN).status == mc.PASS
    # without `ip`: /sys flags tell up/down; the bitrate stays unknown (a warning)
    assert j("CAN", "can0", 1000000, True, "0x80\n", None).status == mc.FAIL
    assert j("CAN", "can0", 1000000, True, "0xc1\n", None).status == mc.WARN


def test_isolation_governor_smt(cfg):
    import dataclasses
    pinned = dataclasses.replace(cfg, realtime=dataclasses.replace(cfg.realtime, cpu_affinity=(0,)))
    assert mc.check_isolation(pinned, "quiet isolcpus=0 nohz_full=0").status == mc.PASS
    it = mc.check_isolation(pinned, "quiet isolcpus=0")
    assert it.status == mc.WARN and "isolcpus=0 nohz_full=0" in it.fix
    assert mc.check_isolation(cfg, "isolcpus=1 nohz_full=1").status == mc.WARN       # not pinned
    absent = dataclasses.replace(cfg, realtime=dataclasses.replace(cfg.realtime, cpu_affinity=(4096,)))
    assert "does not exist" in mc.check_isolation(absent, "").value
    assert mc.check_governor({0: "performance", 1: "performance"}).status == mc.PASS
    g = mc.check_governor({0: "performance", 1: "powersave"})
    assert g.status == mc.WARN and "cpu1 powersave" in g.value
    assert mc.check_governor({}).status == mc.NA
    assert mc.check_smt("0\n").status == mc.PASS
    assert mc.check_smt("1\n").status == mc.WARN


# --------------------------------------------------------------------------- serial ports
def test_serial_port_missing_not_a_tty_and_held(tmp_path):
    assert mc.check_serial_port("laser b_f", str(tmp_path / "ttyNONE")).status == mc.FAIL
    f = tmp_path / "file"
    f.write_text("")
    assert "not a serial port" in mc.check_serial_port("laser b_f", str(f)).value
    master, slave = pty.openpty()
    name = os.ttyname(slave)
    os.close(slave)
    try:
        assert mc.check_serial_port("laser b_f", name).status == mc.PASS
        holder = subprocess.Popen([sys.executable, "-c", f"import sys; f = open({name!r}, 'rb', buffering=0); "
                                   "print('open', flush=True); sys.stdin.read()"],
                                  stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
        try:
            assert holder.stdout.readline().strip() == "open"
            it = mc.check_serial_port("laser b_f", name)
            assert it.status == mc.FAIL and str(holder.pid) in it.value
        finally:
            holder.communicate("")
    finally:
        os.close(master)


def test_holders_matches_link_targets():
    links = [(10, "/dev/ttyUSB0"), (11, "/dev/pts/3"), (12, "socket:[123]"), (13, "/dev/ttyUSB0")]
    assert mc.holders("/dev/ttyUSB0", links, own_pid=13) == [10]
    assert mc.holders("/dev/ttyUSB9", links, own_pid=1) == []


# --------------------------------------------------------------------------- F/T over Modbus TCP
def _one_answer_server():
    """A Modbus TCP server on 127.0.0.1 that answers one read of the wrench registers."""
    srv = socket.socket()
    srv.bind(("127.0.0.1", 0))
    srv.listen(1)
    seen = []

    def serve():
        conn, _ = srv.accept()
        with conn:
            buf = b""
            while (n := ft_modbus.frame_length(buf)) is None or len(buf) < n:
                chunk = conn.recv(256)
                if not chunk:
                    return
                buf += chunk
            tid, unit, fc, data = ft_modbus.decode_request(buf[:n])
            seen.append((unit, fc, data))
            conn.sendall(ft_modbus.encode_read_response(tid, unit, [0] * ft_codec.REG_COUNT))
    t = threading.Thread(target=serve, daemon=True)
    t.start()
    return srv, t, seen


def test_ft_sensor_answers_or_not():
    srv, t, seen = _one_answer_server()
    try:
        s = config.FTSensor(name="ft_fl", host="127.0.0.1", port=srv.getsockname()[1], unit_id=9)
        it = mc.check_ft_sensor(s)
        assert it.status == mc.PASS, it
        t.join(5)
        assert seen and seen[0][0] == 9 and seen[0][1] == ft_modbus.FC_READ_HOLDING
    finally:
        srv.close()
    closed = socket.socket()
    closed.bind(("127.0.0.1", 0))
    port = closed.getsockname()[1]
    closed.close()                                  # nothing listens there now
    it = mc.check_ft_sensor(config.FTSensor(name="ft_fl", host="127.0.0.1", port=port))
    assert it.status == mc.FAIL and f"127.0.0.1:{port}" in it.value
    assert mc.check_ft_sensor(config.FTSensor(name="ft_fl", host="127.0.0.1", port=0)).status == mc.NA


# --------------------------------------------------------------------------- the command
def test_missing_serial_port_and_absent_can_interface_fail_one_line_each(tmp_path):
    sim = config.load(config.CONFIG_DIR / "sim.yaml")
    lasers = [{"role": l.role, "port": l.port, "measuring_range_mm": l.measuring_range_mm, "offset_mm": l.offset_mm,
               "output_rate_hz": l.output_rate_hz} for l in sim.devices.lasers]
    lasers[0]["port"] = str(tmp_path / "ttyRIGMISSING0")
    cfg = config_with(config.CONFIG_DIR / "sim.yaml", tmp_path / "missing.yaml",
                      {"devices.lasers": lasers, "devices.can.interface": "socketcan",
                       "devices.can.channel": "rigcan9"})
    r = rig("check", "--machine", "--config", str(cfg), "--log", str(tmp_path / "x.h5"))
    assert r.returncode == 2, r.stdout + r.stderr
    errors = r.stderr.strip().splitlines()
    assert len(errors) == 2, r.stderr
    assert "laser b_f" in errors[0] and "ttyRIGMISSING0" in errors[0] and "does not exist" in errors[0]
    assert "rigcan9" in errors[1] and "does not exist" in errors[1]
    assert "Traceback" not in r.stderr
    assert "FAIL  laser b_f" in r.stdout and "N/A   laser b_r" in r.stdout


def test_shipped_sim_config_says_what_applies(tmp_path):
    r = rig("check", "--machine", "--config", str(config.CONFIG_DIR / "sim.yaml"), "--log", str(tmp_path / "x.h5"))
    assert r.returncode == 0, r.stderr
    out = r.stdout
    assert "ok: every check of `rig check` passed" in out
    for line in ("kernel real-time preemption", "CPU isolation", "RT priority", "memory lock",
                 "CPU frequency governor", "SMT"):
        assert line in out
    assert "N/A   laser s_rr" in out and "port 'sim'" in out
    assert "N/A   CAN virtual sim" in out
    assert "N/A   F/T ft_fl" in out
    assert "ok: nothing keeps `rig run` from working" in out
    kernel = next(l for l in out.splitlines() if "kernel real-time preemption" in l)
    assert kernel.split()[0] in ("PASS", "WARN")        # this machine's kernel decides which
    if kernel.split()[0] == "WARN":
        assert "fix: install a PREEMPT_RT kernel" in kernel


def test_plain_check_is_unchanged(tmp_path):
    r = rig("check", "--log", str(tmp_path / "x.h5"))
    assert r.returncode == 0, r.stderr
    assert "machine readiness" not in r.stdout and r.stdout.rstrip().endswith("ok: every check passed")
