"""Everything validated before anything starts (issue 11, items 4 and 5): every operator
mistake is one line naming the file/key/value/limit, exit 2, nothing configured or enabled,
no log left behind. A representative set runs `python -m rig_runtime` as a user would; the
rest calls the checks directly."""

import dataclasses
import json
import shutil
import subprocess
import sys
import time
from pathlib import Path

import h5py
import numpy as np
import pytest
import yaml

from rig_runtime import analysis, config
from rig_runtime.app import preflight
from rig_runtime.app.export import read_log, to_csv
from rig_runtime.errors import ConfigError, LogError, RigError
from rig_runtime.recorder import Recorder
from rig_runtime.scenario import FaultInjection, OpenLoop, RefPoint, Scenario, SineInput, load_scenario

from .conftest import ROOT
from .e2e import shipped_config_for

RIG = [sys.executable, "-m", "rig_runtime"]
BOMB = "a: &a [x, x, x, x, x, x, x, x, x]\n" + "".join(
    f"{c}: &{c} [*{p}, *{p}, *{p}, *{p}, *{p}, *{p}, *{p}, *{p}, *{p}]\n" for p, c in zip("abcdefgh", "bcdefghi"))


def rig(*args, cwd=None, env=None):
    # the timeout guards against a hang (the nan duration / YAML bomb); not a timed assertion
    return subprocess.run(RIG + [str(a) for a in args], capture_output=True, text=True, cwd=cwd, env=env, timeout=60)


def one_line_error(r, *needles):
    assert r.returncode == 2, (r.returncode, r.stdout[-2000:], r.stderr[-2000:])
    lines = r.stderr.splitlines()
    assert len(lines) == 1 and "error" in lines[0] and "Traceback" not in r.stderr, r.stderr
    for n in needles:
        assert n in lines[0], (n, lines[0])
    return lines[0]


def configs_copy(tmp_path, file=None, mutate=None):
    d = tmp_path / "configs"
    shutil.copytree(ROOT / "configs", d)
    if file:
        p = d / file
        data = yaml.safe_load(p.read_text())
        mutate(data)
        p.write_text(yaml.safe_dump(data))
    return d


def unstable_config(tmp_path):
    d = configs_copy(tmp_path, "controller.yaml", lambda c: c["controller"]["pipd"].__setitem__("K_P_psi", -40.0))
    return d


def scenario_file(tmp_path, text, name="bad"):
    p = tmp_path / f"{name}.yaml"
    p.write_text(f"name: {name}\nduration_s: 5\n" + text)
    return p


# --------------------------------------------------------------------------- stability gate
def test_tune_refuses_unstable_gains(tmp_path):
    d = unstable_config(tmp_path)
    r = rig("tune", "--config", d / "sim.yaml")
    line = one_line_error(r, "complete closed loop (19) unstable", "+0.643 1/s", "sampled loop as implemented")
    assert "FAIL" in r.stdout and "eigenvalues" in r.stdout      # the analysis is printed all the same
    r = rig("tune", "--config", d / "sim.yaml", "--json")
    assert r.returncode == 2
    out = json.loads(r.stdout)
    assert out["ok"] is False and any("(19)" in f for f in out["failures"])
    ok = rig("tune", "--json")
    assert ok.returncode == 0 and json.loads(ok.stdout)["ok"] is True and json.loads(ok.stdout)["failures"] == []
    assert line.startswith("rig tune: error:")


def test_tune_fails_on_a_design_check(cfg):
    c = dataclasses.replace(cfg, tuning=dataclasses.replace(cfg.tuning, slowest_eig_min=-3.0))
    f = analysis.tune_failures(c, analysis.tune(c))
    assert f == ["design check slowest_outer_eigenvalue fails: -1.963 (limit -3)"]


def test_dry_run_and_run_refuse_unstable_gains_before_anything(tmp_path):
    d = unstable_config(tmp_path)
    log = tmp_path / "x.h5"
    for cmd, conf in (("dry-run", "sim.yaml"), ("run", "rig.yaml"), ("check", "sim.yaml")):
        r = rig(cmd, "--config", d / conf, "--log", log, cwd=tmp_path)
        one_line_error(r, "controller.pipd", "eigenvalue at +0.945 1/s", str(d / conf))
        assert not log.exists() and not (tmp_path / "logs").exists()


def test_nothing_is_configured_when_a_check_fails(tmp_path, monkeypatch):
    """In-process: neither the dry run (simulator, devices) nor the rig's devices are ever
    built when a check fails: the checks come first."""
    import types

    from rig_runtime import devices
    from rig_runtime.app import cli

    def must_not_run(*a, **k):
        raise AssertionError("the run started")
    fake = types.ModuleType("rig_runtime.app.dryrun")
    fake.run_lockstep = must_not_run
    monkeypatch.setitem(sys.modules, "rig_runtime.app.dryrun", fake)
    monkeypatch.setattr(devices, "RigDevices", must_not_run)
    d = unstable_config(tmp_path)
    log = str(tmp_path / "x.h5")
    assert cli.main(["dry-run", "--config", str(d / "sim.yaml"), "--log", log]) == 2
    assert cli.main(["dry-run", "--duration", "nan", "--log", log]) == 2
    assert cli.main(["run", "--config", str(d / "rig.yaml"), "--log", log]) == 2
    assert cli.main(["run", "--config", str(ROOT / "configs" / "rig.yaml"), "--duration", "inf", "--log", log]) == 2
    assert not (tmp_path / "x.h5").exists()


def test_gate_covers_the_p_law_and_both_dampings(cfg):
    analysis.stability_gate(cfg)
    p = dataclasses.replace(cfg, controller=dataclasses.replace(cfg.controller, law="p", K_P=19000.0))
    with pytest.raises(analysis.UnstableLoopError, match="controller.K_P"):
        analysis.stability_gate(p)
    analysis.stability_gate(dataclasses.replace(p, controller=dataclasses.replace(p.controller, K_P=5000.0)))
    assert analysis.sampled_instability(cfg) is None
    huge = dataclasses.replace(cfg, plant=dataclasses.replace(cfg.plant, omega0=1e200))   # overflows: refused
    with pytest.raises(analysis.UnstableLoopError, match="cannot be computed"):
        analysis.stability_gate(huge)


# --------------------------------------------------------------------------- durations
@pytest.mark.parametrize("value", ["nan", "inf", "-inf", "0", "-1"])
def test_duration_must_be_finite_and_positive(tmp_path, value):
    r = rig("dry-run", f"--duration={value}", "--log", tmp_path / "x.h5", cwd=tmp_path)
    one_line_error(r, "--duration", "finite number of seconds > 0")
    assert not (tmp_path / "x.h5").exists() and not (tmp_path / "logs").exists()


def test_duration_check_direct():
    for v in (float("nan"), float("inf"), 0.0, -1.0, True):
        with pytest.raises(ConfigError):
            preflight.check_duration(v)
    preflight.check_duration(None)
    preflight.check_duration(0.5)


# --------------------------------------------------------------------------- scenarios against the rig
BAD_SCENARIOS = [
    ("faults: [{kind: dropout, t: 1, device: zz}]", ["faults[0].device", "'zz'", "b_f", "rl", "ft_rr"]),
    ("reference: []", ["reference", "at least one point"]),
    ("reference: [{t: 0, y_mm: 0}, {t: 1, y_mm: 50}]", ["reference[1].y_mm", "8 mm", "50"]),
    ("reference: [{t: 2, y_mm: 0}, {t: 1, y_mm: 1}]", ["reference[1]", "increasing"]),
    ("open_loop: {carrier: rear, steps: [[0, 0], [1, 50]]}", ["open_loop.steps[1]", "u_max = 4 A", "50"]),
]


@pytest.mark.parametrize("text, needles", BAD_SCENARIOS, ids=[n[0] for _, n in BAD_SCENARIOS])
def test_bad_scenario_is_one_line_before_anything(tmp_path, text, needles):
    sc = scenario_file(tmp_path, text)
    r = rig("dry-run", "--scenario", sc, "--log", tmp_path / "x.h5", cwd=tmp_path)
    one_line_error(r, str(sc), *needles)
    assert not (tmp_path / "x.h5").exists() and not (tmp_path / "logs").exists()


def _sc(**kw):
    return Scenario(name="t", duration_s=5.0, source="t.yaml", **kw)


@pytest.mark.parametrize("sc, key", [
    (lambda: _sc(faults=(FaultInjection(kind="no_heartbeat", t=1.0, device="b_f"),)), "faults[0].kind"),
    (lambda: _sc(faults=(FaultInjection(kind="bus_error", t=1.0, device="ft_rr"),)), "faults[0].kind"),
    (lambda: _sc(faults=(FaultInjection(kind="stall", t=1.0, device="rl"),)), "faults[0].device"),
    (lambda: _sc(faults=(FaultInjection(kind="dropout", t=1.0, device=""),)), "faults[0].device"),
    (lambda: _sc(open_loop=OpenLoop(carrier="front", steps=((0.0, 1.0),))), "open_loop.carrier"),
    (lambda: _sc(open_loop=OpenLoop(sine=(SineInput(amplitude_A=3.5, freq_mhz=5.0, bias_A=1.0),))), "open_loop.sine[0]"),
    (lambda: _sc(reference=(RefPoint(t=0.0, y_mm=-8.5),)), "reference[0].y_mm"),
])
def test_scenario_against_the_rig(cfg, sc, key):
    with pytest.raises(ConfigError) as ei:
        preflight.validate_scenario(cfg, sc())
    assert ei.value.key_path == key and ei.value.file == "t.yaml"


def test_disturbance_on_an_unsupervised_carrier(cfg):
    from rig_runtime.scenario import Disturbance
    sc = _sc(disturbances=(Disturbance(kind="pulse", carrier="front", t=1.0, duration_s=0.1, F_y=10.0),))
    with pytest.raises(ConfigError, match=r"disturbances\[0\].carrier"):
        preflight.validate_scenario(cfg, sc)
    both = dataclasses.replace(cfg, controlled=("front", "rear"))
    preflight.validate_scenario(both, sc)


def test_every_shipped_scenario_fits_the_shipped_rigs(cfg):
    rig_cfg = config.load(ROOT / "configs" / "rig.yaml")
    for p in sorted((ROOT / "configs" / "scenarios").glob("*.yaml")):
        sc = load_scenario(p)
        own = shipped_config_for(p.stem)
        if own is not None:                     # written for another set-up (the vehicle, the front's mirror)
            preflight.validate_scenario(config.load(own), sc)
            continue
        preflight.validate_scenario(cfg, sc)
        preflight.validate_scenario(rig_cfg, sc)
    ft = _sc(faults=(FaultInjection(kind="offset", t=1.0, device="ft_rl", amount=5.0),))
    preflight.validate_scenario(cfg, ft)


def test_scenario_fault_kinds_match_the_simulated_devices():
    from sim_backend import virtual_drive, virtual_ft, virtual_laser
    assert set(preflight.LASER_FAULTS) == set(virtual_laser.FAULT_KINDS)
    assert set(preflight.DRIVE_FAULTS) == set(virtual_drive.FAULT_KINDS)
    assert set(preflight.FT_FAULTS) == set(virtual_ft.FAULT_KINDS)


@pytest.mark.parametrize("text, key", [
    ("reference: [{t: 0, y_mm: 0}, {t: 0, y_mm: 1}]", "reference[1]"),
    ("reference: [{t: -1, y_mm: 0}]", "reference[0].t"),
    ("open_loop: {carrier: rear}", "open_loop.steps"),
    ("open_loop: {steps: [[0, 1]], sine: [{amplitude_A: 1, freq_mhz: 1}]}", "open_loop.steps"),
    ("open_loop: {steps: [[2, 1], [1, 0]]}", "open_loop.steps[1]"),
    ("duration_s: .nan", "duration_s"),
    ("duration_s: -3", "duration_s"),
])
def test_scenario_shape_at_load(tmp_path, text, key):
    p = tmp_path / "s.yaml"
    p.write_text("name: s\n" + ("" if text.startswith("duration_s") else "duration_s: 5\n") + text + "\n")
    with pytest.raises(ConfigError) as ei:
        load_scenario(p)
    assert ei.value.key_path == key and ei.value.file == str(p.resolve())


# --------------------------------------------------------------------------- YAML bounds
def test_billion_laughs_is_refused_at_once(tmp_path):
    p = tmp_path / "bomb.yaml"
    p.write_text(BOMB + "limits: *i\n")
    with pytest.raises(ConfigError, match="alias expansion"):
        config.load(p)
    t0 = time.perf_counter()
    r = rig("dry-run", "--config", p, "--log", tmp_path / "x.h5", cwd=tmp_path)
    wall = time.perf_counter() - t0
    line = one_line_error(r, "bomb.yaml", "alias expansion")
    assert len(line) < 400
    print(f"billion-laughs refused by a whole `rig dry-run` process in {wall:.2f} s")   # docs/safety.md
    s = tmp_path / "bomb-scenario.yaml"
    s.write_text(BOMB + "name: x\nduration_s: 1\nreference: *i\n")
    with pytest.raises(ConfigError, match="alias expansion"):
        load_scenario(s)


def test_nesting_size_and_recursion_bounds(tmp_path):
    deep = tmp_path / "deep.yaml"
    deep.write_text("limits: " + "[" * 5000 + "]" * 5000 + "\n")
    with pytest.raises(ConfigError, match="nesting deeper than"):
        config.load(deep)
    big = tmp_path / "big.yaml"
    big.write_text("# " + "x" * (config.MAX_YAML_BYTES + 10) + "\n")
    with pytest.raises(ConfigError, match="KiB"):
        config.load(big)
    rec = tmp_path / "rec.yaml"
    rec.write_text("limits: &a [*a]\n")
    with pytest.raises(ConfigError, match="refers to itself"):
        config.load(rec)
    binary = tmp_path / "bin.yaml"
    binary.write_bytes(b"limits: \xff\xfe\n")
    with pytest.raises(ConfigError, match="UTF-8"):
        config.load(binary)
    # anchors and aliases within the bounds still work
    ok = tmp_path / "ok.yaml"
    ok.write_text("geometry: &g {b0: 0.07, l_L: 0.8, l0: 0.27625, d0: 0.25}\n")
    assert config.load_sections(ok)["geometry"][0]["d0"] == 0.25


def test_no_message_formats_a_whole_value(tmp_path):
    d = configs_copy(tmp_path, "controller.yaml",
                     lambda c: c["limits"].__setitem__("u_max", [list(range(100)) for _ in range(100)]))
    with pytest.raises(ConfigError) as ei:
        config.load(d / "sim.yaml")
    assert "..." in str(ei.value) and len(str(ei.value)) < 400
    long = ConfigError("f", "k", "x", "y" * 10 ** 6)
    assert len(str(long)) < 200


# --------------------------------------------------------------------------- output paths
def test_log_path_checks(tmp_path):
    a_file = tmp_path / "file.txt"
    a_file.write_text("x")
    r = rig("dry-run", "--log", a_file / "x.h5", cwd=tmp_path)
    one_line_error(r, "--log", "is not a directory")
    r = rig("dry-run", "--log", a_file, cwd=tmp_path)
    one_line_error(r, "--log", "does not exist yet")
    r = rig("dry-run", "--log", tmp_path / "missing" / "x.h5", cwd=tmp_path)
    one_line_error(r, "--log", "does not exist")
    r = rig("dry-run", "--log", "/proc/rig-x.h5", cwd=tmp_path)     # not writable, even for root
    one_line_error(r, "--log", "not writable")
    assert not (tmp_path / "logs").exists()


def test_report_and_plot_need_matplotlib_and_a_directory(tmp_path):
    a_file = tmp_path / "file.txt"
    a_file.write_text("x")
    one_line_error(rig("dry-run", "--report", a_file, "--log", tmp_path / "x.h5", cwd=tmp_path),
                   "--report", "a directory (this is a file)")
    one_line_error(rig("tune", "--plot", a_file), "--plot", "a directory")
    fake = tmp_path / "no-mpl" / "matplotlib"
    fake.mkdir(parents=True)
    (fake / "__init__.py").write_text("raise ImportError('matplotlib is not installed here')\n")
    env = {**__import__("os").environ, "PYTHONPATH": str(fake.parent)}
    one_line_error(rig("dry-run", "--report", tmp_path / "rep", "--log", tmp_path / "x.h5", cwd=tmp_path, env=env),
                   "--report", "matplotlib")
    one_line_error(rig("tune", "--plot", tmp_path / "plots", env=env), "--plot", "matplotlib")
    assert not (tmp_path / "x.h5").exists() and not (tmp_path / "rep").exists()


def test_output_file_checks(tmp_path):
    with pytest.raises(ConfigError, match="does not exist"):
        preflight.check_output_file(tmp_path / "missing" / "o.csv", "--csv")
    with pytest.raises(ConfigError, match="directory"):
        preflight.check_output_file(tmp_path, "--csv")
    with pytest.raises(ConfigError, match="not writable"):
        preflight.check_output_file("/proc/o.csv", "--csv")
    preflight.check_output_file(tmp_path / "o.csv", "--csv")
    preflight.check_output_file(tmp_path / "new" / "deeper" / "gen.yaml", "--write-config", create_dir=True)
    f = tmp_path / "f"
    f.write_text("")
    with pytest.raises(ConfigError, match="not a directory"):
        preflight.check_output_file(f / "gen.yaml", "--write-config", create_dir=True)
    assert not (tmp_path / "new").exists()       # checking creates nothing


def test_sim_write_config_target(tmp_path):
    f = tmp_path / "f"
    f.write_text("")
    one_line_error(rig("sim", "--write-config", f / "x.yaml"), "--write-config", "not a directory")
    one_line_error(rig("sim", "--duration", "nan"), "--duration")


# --------------------------------------------------------------------------- log readers
def _real_log(path, rows=5000):
    rec = Recorder(path, ["t", "y"], attrs={"h": 0.005}, buffer_cycles=8192, flush_s=0.05)
    rec.open()
    for i in range(rows):
        rec.append((i * 0.005, float(i)))
    rec.close()
    return path


def test_export_recognises_what_is_not_a_rig_log(tmp_path):
    empty = tmp_path / "empty.h5"
    empty.write_bytes(b"")
    junk = tmp_path / "junk.h5"
    junk.write_bytes(bytes(range(256)) * 40)
    foreign = tmp_path / "foreign.h5"
    with h5py.File(foreign, "w") as f:
        f["x"] = np.arange(10)
    good = _real_log(tmp_path / "good.h5")
    data = good.read_bytes()
    truncated = tmp_path / "truncated.h5"
    truncated.write_bytes(data[: len(data) // 2])
    for p, needle in ((empty, "empty file"), (junk, "not an HDF5 file"), (foreign, "no rig-runtime-log"),
                      (truncated, "")):
        r = rig("export", p, "--csv", tmp_path / "out.csv")
        one_line_error(r, str(p), "not a readable rig log", needle)
        with pytest.raises(LogError):
            read_log(p)
    r = rig("export", good, "--csv", tmp_path / "missing" / "out.csv")
    one_line_error(r, "--csv", "does not exist")
    one_line_error(rig("export", good, "--csv", good), "--csv", "other than the log itself")
    assert to_csv(good, tmp_path / "ok.csv") == 5000         # the log is intact


def test_errors_are_rig_errors():
    """The CLI turns RigError subclasses (and only those) into the one line and exit 2."""
    assert issubclass(LogError, RigError) and issubclass(analysis.UnstableLoopError, ConfigError)


# --------------------------------------------------------------------------- rig check
def test_rig_check_prints_what_would_run(tmp_path):
    r = rig("check", "--scenario", "fault-dropout", "--duration", "3", "--log", tmp_path / "x.h5")
    assert r.returncode == 0, r.stderr
    out = r.stdout
    for needle in ("config: " + str(ROOT / "configs" / "sim.yaml"), "hardware: " + str(ROOT / "configs" / "hardware.yaml"),
                   "controlled carriers: rear", "K_P,psi = 40", "limits.u_max", "<= 16", "scenario: fault-dropout",
                   "dropout b_f", "duration: 3 s (--duration)", f"log: {tmp_path / 'x.h5'}", "ok"):
        assert needle in out, (needle, out)
    assert not (tmp_path / "x.h5").exists()
    rigc = rig("check", "--config", ROOT / "configs" / "rig.yaml", "--scenario", "single-step")
    assert rigc.returncode == 0 and "duration: 15 s (the scenario's duration_s)" in rigc.stdout
    one_line_error(rig("check", "--scenario", scenario_file(tmp_path, "faults: [{kind: stuck, t: 1, device: s_xx}]")),
                   "faults[0].device", "s_xx")
    loose = configs_copy(tmp_path, "controller.yaml", lambda c: c["limits"].__setitem__("u_max", 20.0))
    one_line_error(rig("check", "--config", loose / "sim.yaml"), "limits.u_max", "at most 16 A", "20.0",
                   "hardware.yaml")


def test_no_room_for_the_recording_ring_is_one_line(tmp_path):
    """A full /dev/shm (here: a file size limit below the ring's size) is refused when the
    recorder starts — one line, exit 2, no ring file, no log — not a SIGBUS in the loop later."""
    import resource
    import signal

    def small_files():
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)       # a write past the limit fails (EFBIG)
        resource.setrlimit(resource.RLIMIT_FSIZE, (64 * 1024, 64 * 1024))

    # this run's own ring files, whatever other runs on the machine create and remove meanwhile:
    # `rig dry-run` with every temporary file it makes written down (the ring is one)
    made = tmp_path / "made.txt"
    note = ("import sys, tempfile\n"
            "orig = tempfile.mkstemp\n"
            "def mkstemp(*a, **k):\n"
            "    fd, path = orig(*a, **k)\n"
            f"    with open({str(made)!r}, 'a') as f:\n"
            "        f.write(path + '\\n')\n"
            "    return fd, path\n"
            "tempfile.mkstemp = mkstemp\n"
            "from rig_runtime.app.entry import main\n"
            "sys.argv = ['rig'] + sys.argv[1:]\n"
            "sys.exit(main())\n")
    # a live output needs the recording sidecar (a lockstep run without one writes its log in-process)
    r = subprocess.run([sys.executable, "-c", note, "dry-run", "--log", str(tmp_path / "x.h5"),
                        "--telemetry", "udp://127.0.0.1:9"], capture_output=True,
                       text=True, cwd=tmp_path, timeout=60, preexec_fn=small_files)
    one_line_error(r, "recorder", "no shared memory for the recording ring")
    assert not (tmp_path / "x.h5").exists()
    rings = [p for p in made.read_text().split() if Path(p).name.startswith("rig-ring-")]
    assert rings                                    # the run tried to make its ring …
    assert not [p for p in rings if Path(p).exists()]       # … and left none behind


def test_a_lockstep_log_the_disk_refuses_is_a_recorder_fault(tmp_path):
    """A lockstep run writes its log in its own process: a write the disk refuses (here: a file
    size limit) is the recorder's fault while the run goes on — FAULT, exit 3, the cause named —
    not a crash, a traceback or a clean exit over a log that is not whole."""
    import resource
    import signal

    def small_files():
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)       # a write past the limit fails (EFBIG)
        resource.setrlimit(resource.RLIMIT_FSIZE, (256 * 1024, 256 * 1024))

    r = subprocess.run(RIG + ["dry-run", "--log", str(tmp_path / "x.h5"), "--json"], capture_output=True, text=True,
                       cwd=tmp_path, timeout=120, preexec_fn=small_files)
    assert r.returncode == 3, (r.returncode, r.stdout[-2000:], r.stderr[-2000:])
    assert "Traceback" not in r.stderr
    summary = json.loads(r.stdout)
    assert summary["final_state"] == "FAULT" and not summary["recorder"]["healthy"]
    assert [f["device"] for f in summary["faults"]] == ["recorder"] and "File too large" in summary["faults"][0]["message"]
    assert summary["ended_by"].startswith("fault: recorder")


def test_hold_on_fault_needs_a_ctl_socket(tmp_path):
    """A held fault ends only by `rig ctl reset-fault` or `stop`: without a socket (lockstep,
    --no-ctl) the run would cycle in FAULT until killed."""
    one_line_error(rig("dry-run", "--hold-on-fault", "--log", tmp_path / "a.h5", cwd=tmp_path),
                   "--hold-on-fault", "rig ctl")
    one_line_error(rig("dry-run", "--realtime", "--no-ctl", "--hold-on-fault", "--log", tmp_path / "b.h5",
                       cwd=tmp_path), "--hold-on-fault", "rig ctl")
    assert not list(tmp_path.glob("*.h5"))
