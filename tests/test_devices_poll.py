"""The device set's poll (rig_runtime.devices.RigDevices.poll) fills preallocated mappings and
samples in place: every cycle they hold exactly what the drivers reported, field by field as
the constructors of Sample / Converters would build it, and the objects (the mappings and each
channel's sample) are the same from cycle to cycle."""

from __future__ import annotations

import math

from rig_runtime import config
from rig_runtime.app.dryrun import run_lockstep
from rig_runtime.devices import Reading
from rig_runtime.hardware import Freshness
from rig_runtime.safety import Converters, Sample
from rig_runtime.scenario import load_scenario


def fields(sample) -> tuple:
    """A sample's fields by name, in Sample's order."""
    return tuple(getattr(sample, f) for f in Sample._fields)


def same(a, b) -> bool:
    """Equal field by field, NaN equal to NaN."""
    return len(a) == len(b) and all(x is y or x == y or (isinstance(x, float) and math.isnan(x) and math.isnan(y))
                                    for x, y in zip(a, b))


def test_poll_reports_what_the_drivers_observed(tmp_path):
    cfg = config.load("configs/sim.yaml")
    assert cfg.devices.ft.sensors          # the F/T part is exercised
    checked = []

    def prepare(sim, dev, clock):
        seen = {}

        def tap(obj, key):
            f = obj.poll

            def poll(now):
                r = seen[key] = f(now)
                return r
            obj.poll = poll
        tap(dev.drives, "drives")
        tap(dev.ft, "ft")
        for i, d in enumerate(dev.lasers):
            tap(d, f"laser{i}")
        outer = dev.poll
        objects = []

        def poll(now):
            r = outer(now)
            assert type(r) is Reading and r.t == now
            objects.append((id(r.samples), id(r.values), id(r.wrench), *map(id, r.samples.values())))
            rd, fr = seen["drives"], seen["ft"]
            want, vals, ok, cause, lost, off = {}, {}, True, "", [], []
            for w, x in rd.wheels.items():
                want[w], vals[w] = Sample(x.omega, x.t, x.health, x.syncs_unanswered), x.omega
                invalid = x.health.state is Freshness.INVALID
                if invalid:
                    lost.append((w, f"drive {x.wheel} (node {x.node_id}): {x.health.cause}"))
                    if ok:
                        ok, cause = False, lost[-1][1]
                if invalid or not x.enabled:
                    off.append(w)
            bus_ok = rd.bus.state is not Freshness.INVALID
            if ok and not bus_ok:
                ok, cause = False, f"CAN bus: {rd.bus.cause}"
            wrench = []
            for n in dev.ft_names:
                x = fr[n]
                want[n] = Sample(math.nan if x.wrench is None else x.wrench.fy, x.t, x.health)
                vals[n] = want[n].value
                wrench += [math.nan] * 6 if x.wrench is None else x.wrench.as_tuple()
            for i in range(len(dev.lasers)):
                x = seen[f"laser{i}"]
                want[x.role], vals[x.role] = Sample(x.value_m, x.t, x.health), x.value_m
            assert list(r.samples) == list(want) and list(r.values) == list(vals)
            assert all(same(fields(r.samples[n]), want[n]) for n in want)
            assert same(list(r.values.values()), list(vals.values()))
            assert same(list(r.wrench), wrench) and len(r.wrench) == len(dev.extra_columns)
            assert type(r.converters) is Converters
            assert same(r.converters, Converters(
                ok=ok, cause=cause, enabled=rd.enabled, bus_error_t=rd.bus_error_t, bus_cause=rd.bus.cause,
                drives=tuple(lost), not_enabled=tuple(off), bus_ok=bus_ok,
                torque=tuple((w, x.current_A) for w, x in rd.wheels.items())))
            checked.append(now)
            return r
        dev.poll = poll
        prepare.objects = objects

    summary, code = run_lockstep(cfg, load_scenario("single-step"), tmp_path / "x.h5", duration_s=0.3,
                                 prepare=prepare)
    assert code == 0 and summary["final_state"] == "IDLE"
    assert len(checked) == summary["cycles"] > 60
    assert len(set(prepare.objects)) == 1          # the same mappings and samples every cycle, filled in place

