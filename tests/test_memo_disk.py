"""memo.across_processes: a result kept on disk by every input's bytes and read back only
whole, with its own key and the allowed classes; anything else is ignored and computed.
The gate's pass and the observers' designs read back are the computed ones, and a run
whose config was seen before imports no scipy."""

import dataclasses
import os
import subprocess
import sys
from fractions import Fraction

import pytest

from rig_runtime import analysis, config, memo
from rig_runtime.app import preflight, runner

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


@pytest.fixture
def cache(tmp_path, monkeypatch):
    monkeypatch.setenv("RIG_CACHE_DIR", str(tmp_path / "cache"))
    monkeypatch.setattr(memo, "_disk_on", True)
    return tmp_path / "cache"


def counted(value=None, fail=False):
    calls = []

    def f(*args):
        calls.append(args)
        if fail:
            raise ValueError("refused")
        return value if value is not None else ("r", args)
    return f, calls


def entries(d, name):
    return sorted((d / name).glob("[0-9a-f]*")) if (d / name).exists() else []


def test_a_result_is_read_back_by_its_arguments(cache):
    f, calls = counted()
    g = memo.across_processes("t", f)
    assert g(1.0, "a") == ("r", (1.0, "a")) and len(calls) == 1
    assert g(1.0, "a") == ("r", (1.0, "a")) and len(calls) == 1       # from disk
    assert g(1.0 + 1e-15, "a") == ("r", (1.0 + 1e-15, "a")) and len(calls) == 2
    assert len(entries(cache, "t")) == 2


def test_a_raise_is_never_stored(cache):
    f, calls = counted(fail=True)
    g = memo.across_processes("t", f)
    for n in (1, 2):
        with pytest.raises(ValueError):
            g(1)
        assert len(calls) == n
    assert entries(cache, "t") == []


@pytest.mark.parametrize("damage", ["flip", "truncate", "empty", "other_key", "foreign_class"])
def test_a_damaged_or_foreign_entry_is_ignored_and_computed_again(cache, damage):
    f, calls = counted()
    g = memo.across_processes("t", f)
    g(1)
    (path,) = entries(cache, "t")
    raw = path.read_bytes()
    if damage == "flip":
        path.write_bytes(raw[:-3] + bytes([raw[-3] ^ 1]) + raw[-2:])
    elif damage == "truncate":
        path.write_bytes(raw[:len(raw) // 2])
    elif damage == "empty":
        path.write_bytes(b"")
    elif damage == "other_key":     # a whole entry, but of other arguments, under this key's name
        g(2)
        other = [p for p in entries(cache, "t") if p != path][0]
        path.write_bytes(other.read_bytes())
    elif damage == "foreign_class":   # a whole entry with this key whose value is a class not allowed
        key = f"t\n{memo.code_version()}\n{(1,)!r}"
        memo._write(path, key, ("r", Fraction(1, 3)))
    n = len(calls)
    assert g(1) == ("r", (1,)) and len(calls) == n + 1


def test_an_unwritable_or_turned_off_cache_computes(tmp_path, monkeypatch):
    blocker = tmp_path / "file"
    blocker.write_text("")
    monkeypatch.setenv("RIG_CACHE_DIR", str(blocker / "cache"))       # under a file: cannot be made
    f, calls = counted()
    g = memo.across_processes("t", f)
    assert g(1) == g(1) and len(calls) == 2
    monkeypatch.setenv("RIG_CACHE_DIR", "")
    assert g(1) == ("r", (1,)) and len(calls) == 3 and memo.cache_dir() is None


def test_compute_only_turns_the_disk_off_for_the_process(cache, monkeypatch):
    f, calls = counted()
    g = memo.across_processes("t", f)
    memo.compute_only()         # the fixture's monkeypatch restores the flag afterwards
    g(1), g(1)
    assert len(calls) == 2 and not cache.exists()


def test_the_source_digest_changes_with_a_byte_of_any_file(tmp_path):
    (tmp_path / "sub").mkdir()
    (tmp_path / "a.py").write_text("x = 1\n")
    (tmp_path / "sub" / "b.py").write_text("y = 2\n")
    d0 = memo.source_digest(tmp_path)
    assert memo.source_digest(tmp_path) == d0
    (tmp_path / "sub" / "b.py").write_text("y = 3\n")
    assert memo.source_digest(tmp_path) != d0


def test_the_gate_refuses_every_time_with_the_disk_on(cache):
    cfg = config.load(config.CONFIG_DIR / "sim.yaml")
    unstable = dataclasses.replace(cfg, controller=dataclasses.replace(cfg.controller, law="p", K_P=19000.0))
    gate = memo.across_processes("stability-gate", preflight._gate)
    for _ in range(2):
        with pytest.raises(analysis.UnstableLoopError, match="controller.K_P"):
            gate(unstable)
    assert entries(cache, "stability-gate") == []
    assert gate(cfg) is True and gate(cfg) is True and len(entries(cache, "stability-gate")) == 1


@pytest.mark.parametrize("name", ["sim.yaml", "vehicle.yaml"])
def test_designs_and_plan_read_back_equal_the_computed_ones(cache, name):
    """sim.yaml: a carrier's design; vehicle.yaml: the running gear's joint filter (its speed
    schedule left out: one design instead of 2 x 42, the same classes)."""
    from rig_runtime.app import observer_design as od
    cfg = config.load(config.CONFIG_DIR / name)
    if cfg.controller.schedule is not None:
        cfg = dataclasses.replace(cfg, controller=dataclasses.replace(cfg.controller, schedule=None))
    computed = od.designs(cfg)
    assert computed
    first, again = runner._designs_on_disk(cfg), runner._designs_on_disk(cfg)      # written, then read
    assert len(entries(cache, "observer-designs")) == 1
    assert first == computed and again == computed and again is not first
    assert runner.observer_designs(cfg) is runner.observer_designs(cfg)     # in a process: read once
    assert repr(again) == repr(computed)        # every float exactly (repr: the shortest exact text, -0.0 and nan too)
    if name == "vehicle.yaml":     # the joint filter: both carriers share one design, as computed
        assert again["front"].joint is again["rear"].joint
    slowest = memo.across_processes("plan-slowest", preflight._slowest)
    assert slowest(cfg) == slowest(cfg) == preflight._slowest(cfg)


def test_a_run_of_a_config_seen_before_imports_no_scipy(cache, tmp_path):
    """The first process composes the files and computes and keeps the gate, the plan and the
    designs; the second loads, checks and sets up the same run from the disk, without
    importing scipy or PyYAML."""
    code = ("import sys\n"
            "from rig_runtime import config\n"
            "from rig_runtime.app import preflight, runner\n"
            "from rig_runtime.scenario import load_scenario\n"
            "cfg = config.load(config.CONFIG_DIR / 'sim.yaml')\n"
            "preflight.check_run(cfg, load_scenario('single-step'), 0.1)\n"
            "assert runner.observer_designs(cfg)\n"
            "print(sorted({m.split('.')[0] for m in sys.modules} & {'scipy', 'yaml'}))\n")
    env = {**os.environ, "RIG_CACHE_DIR": str(cache)}
    out = [subprocess.run([sys.executable, "-c", code], cwd=ROOT, env=env, capture_output=True, text=True,
                          check=True).stdout.strip() for _ in range(2)]
    assert out == ["['scipy', 'yaml']", "[]"]


def test_a_config_file_composed_in_another_process_is_read_back_equal(cache, monkeypatch):
    calls = []
    compose = config._compose_bounded
    monkeypatch.setattr(config, "_compose_bounded", lambda text: calls.append(text) or compose(text))
    monkeypatch.setattr(config, "_PARSED", {})
    first = config.load(config.CONFIG_DIR / "vehicle.yaml")
    n = len(calls)
    assert n >= 2 and len(entries(cache, "yaml-document")) == n
    monkeypatch.setattr(config, "_PARSED", {})         # a new process: only the disk is left
    assert config.load(config.CONFIG_DIR / "vehicle.yaml") == first and len(calls) == n
    assert repr(config.load(config.CONFIG_DIR / "vehicle.yaml")) == repr(first)


def test_entries_are_bounded_the_least_recently_used_removed(cache, monkeypatch):
    monkeypatch.setattr(memo, "MAX_ON_DISK", 3)
    f, calls = counted()
    g = memo.across_processes("t", f)
    g(0)
    (first,) = entries(cache, "t")
    g(1), g(2)
    os.utime(first, ns=(1, 1))          # g(0)'s entry the least recently used ...
    g(0)                                # ... until read: marked used
    g(3)                                # a fourth: one removed
    assert len(entries(cache, "t")) == 3 and first.exists()
    n = len(calls)
    g(0), g(3)
    assert len(calls) == n
    stale, fresh = cache / "t" / ".tmp-dead", cache / "t" / ".tmp-writing"     # a writer's left-overs
    stale.write_bytes(b"x")
    fresh.write_bytes(b"x")
    os.utime(stale, ns=(1, 1))
    g(4)
    assert not stale.exists() and fresh.exists() and len(entries(cache, "t")) == 3


def test_without_disk_is_this_block_and_this_thread_only(cache):
    import threading
    f, calls = counted()
    g = memo.across_processes("t", f)
    seen = []
    with memo.without_disk():
        g(1), g(1)
        t = threading.Thread(target=lambda: seen.append(memo.cache_dir()))
        t.start()
        t.join()
    assert len(calls) == 2 and entries(cache, "t") == [] and seen == [cache]
    g(1), g(1)
    assert len(calls) == 3 and len(entries(cache, "t")) == 1


def test_rig_check_and_rig_run_neither_read_nor_write_the_disk(tmp_path):
    """``rig check`` writes nothing; ``rig run`` computes what lets the power stages on in its
    own process (here refused at the scenario, after its config was loaded)."""
    env = {**os.environ, "RIG_CACHE_DIR": str(tmp_path / "cache")}
    rig = [sys.executable, "-m", "rig_runtime"]
    ok = subprocess.run(rig + ["check", "--scenario", "single-step"], cwd=ROOT, env=env, capture_output=True,
                        text=True)
    assert ok.returncode == 0, ok.stderr
    bad = subprocess.run(rig + ["run", "--config", str(config.CONFIG_DIR / "sim.yaml"), "--scenario", "no-such"],
                         cwd=ROOT, env=env, capture_output=True, text=True)
    assert bad.returncode == 2 and "no-such" in bad.stderr, bad.stderr
    assert not (tmp_path / "cache").exists()
