"""The vehicle's runtime parts as units (issue 18): the measured speed (rig_runtime.speed), its
supervisor rules (speed_disagree, speed_range), the speed schedule and standstill hold of the
PI-PD law and of a lane, per-carrier gains and references in the lanes. (Lockstep runs:
tests/test_vehicle_e2e.py.)"""

import dataclasses
import json
import math

import pytest

from rig_runtime import config
from rig_runtime.control import PController, PIPDController, make_controller
from rig_runtime.lanes import make_lanes
from rig_runtime.loop import log_columns
from rig_runtime.safety import SPEED_RULES, State, speed_disagree, speed_range
from rig_runtime.speed import SpeedEstimate, columns

from tests.test_safety import OK, chans, samples, supervisor

H = 0.005


@pytest.fixture(scope="module")
def vcfg():
    return config.load(config.CONFIG_DIR / "vehicle.yaml")


def wheels(v, r0=0.075, dw_f=0.0, dw_r=0.0, **over):
    """Wheel speeds (rad/s) of carriers rolling at ``v`` (m/s) with differences dw_*."""
    w = v / r0
    out = {"fl": w + dw_f / 2, "fr": w - dw_f / 2, "rl": w + dw_r / 2, "rr": w - dw_r / 2}
    out.update(over)
    return out


# ------------------------------------------------------------------ the measured speed
def test_contact_is_a_config_fact(cfg, vcfg):
    assert cfg.plant.in_contact == ("rear",)                  # the paper's set-up: front lifted
    assert vcfg.plant.in_contact == ("front", "rear")
    assert columns(cfg.plant) == ["v_meas", "rear_v"]
    assert columns(vcfg.plant) == ["v_meas", "front_v", "rear_v"]
    cols = log_columns(vcfg, [], [])
    assert cols.index("v_meas") == cols.index("dw_r") + 1       # after the measurement
    for c in ("front", "rear"):
        assert {f"{c}_y_ref", f"{c}_g", f"{c}_held"} <= set(cols)
    assert "y_ref" in cols                                      # the first lane's, for old tools


def test_speed_is_the_mean_wheel_speed_times_r0_with_its_sign():
    for v in (1.0, -1.0, 0.3):
        sp = SpeedEstimate(("front", "rear"), {"front": 0.08, "rear": 0.075}, H, 2.0)
        vals = {"fl": v / 0.08 + 0.4, "fr": v / 0.08 - 0.4, "rl": v / 0.075 + 1.0, "rr": v / 0.075 - 1.0}
        assert sp.update(vals) == pytest.approx(v, rel=1e-12)   # seeded: no filter transient
        assert sp.v == pytest.approx([v, v], rel=1e-12)         # Δω does not enter the speed


def test_speed_is_low_passed_at_the_configured_frequency():
    f = 2.0
    sp = SpeedEstimate(("rear",), {"rear": 0.075}, H, f)
    sp.update(wheels(1.0))
    n = round(1.0 / (2 * math.pi * f) / H)                      # one time constant
    for _ in range(n):
        sp.update(wheels(-1.0))
    # first order: 1 - 2 (1 - e^-1) after one time constant (±1 % for the discrete steps)
    assert sp.v_hat == pytest.approx(1.0 - 2.0 * (1.0 - math.exp(-1.0)), abs=0.01)
    for _ in range(20 * n):
        sp.update(wheels(-1.0))
    assert sp.v_hat == pytest.approx(-1.0, abs=1e-6)


def test_a_wheel_without_a_value_leaves_the_speed_where_it_was():
    sp = SpeedEstimate(("front", "rear"), {"front": 0.075, "rear": 0.075}, H, 2.0)
    assert math.isnan(sp.update(wheels(1.0, fl=math.nan)))       # front never measured: no v̂ yet
    assert sp.update(wheels(1.0)) == pytest.approx(1.0)
    assert sp.update(wheels(1.0, rr=math.nan)) == pytest.approx(1.0)
    assert sp.log_values() == pytest.approx([1.0, 1.0, 1.0])


# ------------------------------------------------------------------ the speed rules
class Speed:
    def __init__(self, carriers, v, v_hat):
        self.carriers, self.v, self.v_hat = carriers, v, v_hat


def test_speed_disagree_names_both_carriers_and_their_speeds(cfg):
    lim = cfg.limits
    assert speed_disagree(Speed(("front", "rear"), [1.0, 1.0 + 0.9 * lim.v_disagree_max], 1.0), lim, 2.0) is None
    f = speed_disagree(Speed(("front", "rear"), [1.0, 1.2], 1.1), lim, 2.0)
    assert (f.device, f.check, f.limit) == ("encoders", "speed_disagree", lim.v_disagree_max)
    assert f.value == pytest.approx(0.2)
    assert "front +1.000 m/s" in f.message and "rear +1.200 m/s" in f.message
    assert speed_disagree(Speed(("rear",), [5.0], 5.0), lim, 2.0) is None        # one carrier: nothing to compare


def test_speed_range_both_directions(cfg):
    lim = cfg.limits
    for v in (1.99, -1.99, math.nan):
        assert speed_range(Speed(("rear",), [v], v), lim, 2.0) is None
    for v in (2.01, -2.01):
        f = speed_range(Speed(("rear",), [v], v), lim, 2.0)
        assert (f.device, f.check, f.value, f.limit) == ("encoders", "speed_range", v, 2.0)
    assert SPEED_RULES == (speed_disagree, speed_range)


def test_the_supervisor_judges_the_speed_while_active(cfg):
    s, events, hw = supervisor(cfg)
    s.v_max = 2.0
    fast = Speed(("rear",), [2.5], 2.5)

    def cycle(t, speed):
        return s.cycle(t, samples(t, s.channels), OK, [("rear", 0.0, 0.0)], 0, True, "", speed)

    ok = Speed(("rear",), [1.0], 1.0)
    assert cycle(0.0, fast).state is State.IDLE             # the rules judge while active only
    s.request_arm(1.0)
    assert cycle(H, ok).state is State.ARMED
    assert cycle(2 * H, ok).state is State.RUNNING
    assert cycle(3 * H, None).state is State.RUNNING        # None: not judged
    assert cycle(4 * H, fast).state is State.FAULT
    assert (s.fault.device, s.fault.check) == ("encoders", "speed_range")
    assert s.limit("rear", 1.0, 4 * H) == 0.0


# ------------------------------------------------------------------ the schedule in the law
def pipd(cfg, **gains):
    c = cfg.controller
    return PIPDController(c, cfg.limits.u_max, cfg.limits.psi_ref_max,
                          dataclasses.replace(c.pipd, **gains) if gains else None)


def test_gain_factor_one_is_the_paper_law_bit_for_bit(cfg):
    a, b = pipd(cfg), pipd(cfg)
    b.set_gain_factor(1.0)
    a.start(0.0, 0.0, 0.0)
    b.start(0.0, 0.0, 0.0)
    for k in range(400):
        y, psi = 1e-4 * math.sin(0.05 * k), 1e-3 * math.cos(0.03 * k)
        assert a.step(2e-3, y, psi) == b.step(2e-3, y, psi)
        assert a.st == b.st


def test_gain_factor_scales_the_outer_pi_and_flips_its_sign(cfg):
    g = cfg.controller.pipd
    for factor in (2.0, -1.0):
        c = pipd(cfg)
        c.set_gain_factor(factor)
        c.start(0.0, 0.0, 0.0)
        c.step(0.0, 0.0, 0.0)
        c.step(1e-3, 0.0, 0.0)                       # e_y = 1 mm: ψ_ref = g (K_P e + K_I h/2 e)
        assert c.st.psi_ref == pytest.approx(factor * (g.K_P_y + g.K_I_y * 0.5 * H) * 1e-3, rel=1e-12)


def test_a_gain_factor_change_does_not_move_the_integral_part(cfg):
    c = pipd(cfg)
    c.start(0.0, 0.0, 0.0)
    for _ in range(200):
        c.step(1e-3, 0.0, 0.0)
    x_I = c.st.x_I
    c.set_gain_factor(-1.0)                          # the direction reverses
    c.step(0.0, 0.0, 0.0)                            # e_y = 0, e_y_prev = 1 mm: half a Tustin step of -e
    assert c.st.x_I == pytest.approx(x_I - 0.5 * H * 1e-3, rel=1e-12)
    assert c.st.psi_ref == pytest.approx(cfg.controller.pipd.K_I_y * c.st.x_I, rel=1e-12)


def test_hold_freezes_the_integrator_and_ramps_psi_ref_to_zero(cfg):
    c = pipd(cfg)
    c.start(0.0, 0.0, 0.0)
    for _ in range(100):
        c.step(1e-3, 0.0, 0.0)
    psi0, x_I = c.st.psi_ref, c.st.x_I
    assert psi0 > 0
    c.hold(0.1)                                      # 20 steps
    seen = []
    for _ in range(30):
        u = c.step(3e-3, 1e-4, 0.0)                  # the lateral error changes: nothing integrates
        seen.append(c.st.psi_ref)
        assert c.st.x_I == x_I
        assert u == c.st.u                           # the inner PD still acts on ψ_ref - ψ
    assert seen[:20] == pytest.approx([psi0 * (1 - k / 20) for k in range(1, 21)], abs=1e-15)
    assert seen[20:] == [0.0] * 10
    assert c.held


def test_resume_is_bumpless(cfg):
    c = pipd(cfg)
    c.start(0.0, 0.0, 0.0)
    for _ in range(50):
        c.step(1e-3, 0.0, 0.0)
    c.hold(0.1)
    for _ in range(10):
        c.step(1e-3, 0.0, 0.0)
    held_psi_ref = c.st.psi_ref                      # halfway down the ramp
    c.set_gain_factor(-2.0)                          # back out of the band, the other direction
    c.resume()
    c.step(2e-3, 5e-4, 0.0)
    assert not c.held
    assert c.st.psi_ref == pytest.approx(held_psi_ref, abs=1e-15)    # continuous: re-seeded x_I
    c.step(2e-3, 5e-4, 0.0)                          # then the scheduled law: -2 (K_P e + K_I x)
    g = cfg.controller.pipd
    assert c.st.psi_ref - held_psi_ref == pytest.approx(g.K_I_y * H * -2.0 * 1.5e-3, rel=1e-9)


def test_the_p_law_keeps_working(cfg):
    c = PController(cfg.controller, cfg.limits.u_max)
    assert c.step(1e-3, 0.0, 0.0) == pytest.approx(cfg.controller.K_P * 1e-3)
    c.set_gain_factor(-1.0)
    assert c.step(1e-3, 0.0, 0.0) == pytest.approx(-cfg.controller.K_P * 1e-3)
    c.hold(1.0)
    assert c.step(1e-3, 0.0, 0.0) == 0.0
    c.resume()
    assert c.step(1e-3, 0.0, 0.0) != 0.0


# ------------------------------------------------------------------ lanes
def test_lanes_get_their_own_gains_references_and_the_schedule(vcfg):
    fr = dataclasses.replace(vcfg.controller.pipd, K_P_y=4.0)      # per-carrier gains: law pipd's
    cfg = dataclasses.replace(vcfg, controller=dataclasses.replace(vcfg.controller, front=fr, law="pipd"))
    lanes = make_lanes(cfg, {"front": lambda t: 1e-3, "rear": lambda t: -1e-3})
    front, rear = lanes
    assert (front.carrier, rear.carrier) == ("front", "rear")
    assert front.controller.kpy == 4.0 and rear.controller.kpy == vcfg.controller.pipd.K_P_y
    front.control(0.0, False)
    rear.control(0.0, False)
    assert (front.y_ref, rear.y_ref) == (1e-3, -1e-3)
    sch = vcfg.controller.schedule
    rear.schedule(-0.5)
    assert rear.controller.g == pytest.approx(sch.v_design / -0.5) and not rear.controller.held
    rear.schedule(0.5 * sch.v_min)
    assert rear.controller.held
    rear.schedule(-0.5 * sch.v_min)
    assert rear.controller.held
    rear.schedule(math.nan)                          # no measured speed: no lateral control
    assert rear.controller.held
    rear.schedule(1.0)
    assert not rear.controller.held and rear.controller.g == pytest.approx(sch.v_design)
    assert rear.log_values()[2:] == (-1e-3, pytest.approx(sch.v_design), 0.0)


def test_without_a_schedule_nothing_is_scheduled(cfg):
    (lane,) = make_lanes(cfg, lambda t: 0.0)
    lane.schedule(0.0)
    lane.schedule(-1.0)
    assert lane.controller.g == 1.0 and not lane.controller.held


def test_open_loop_on_both_carriers_is_the_controller_off(vcfg):
    lanes = make_lanes(vcfg, lambda t: 0.0, open_loop=("both", lambda t: 0.25))
    assert [l.carrier for l in lanes] == ["front", "rear"]
    assert [l.control(1.0, True) for l in lanes] == [0.25, 0.25]


def test_make_controller_takes_the_carriers_gains(vcfg):
    fr = dataclasses.replace(vcfg.controller.pipd, K_D_psi=7.0)
    c = dataclasses.replace(vcfg.controller, front=fr, law="pipd")
    assert make_controller(c, 4.0, None, "front").kdp == 7.0
    assert make_controller(c, 4.0, None, "rear").kdp == vcfg.controller.pipd.K_D_psi
    assert make_controller(c, 4.0).kdp == vcfg.controller.pipd.K_D_psi


# ------------------------------------------------------------------ live views
def _vehicle_columns(vcfg):
    """The vehicle's log columns (the loop's own layout, four F/T sensors)."""
    from rig_runtime.config import LASER_ROLES, WHEELS
    from rig_runtime.safety import Channel
    chs = [Channel(r, "laser", 0, 1, 1) for r in LASER_ROLES] + [Channel(w, "wheel", -1, 1, 1) for w in WHEELS]
    return tuple(log_columns(vcfg, chs, [f"ft_{w}_{c}" for w in WHEELS for c in ("fx", "fy", "fz", "mx", "my", "mz")]))


def test_telemetry_carries_the_speed_and_the_schedule_state(vcfg):
    from rig_runtime.app.telemetry import MAX_DATAGRAM, RowSignals
    from tests.test_telemetry import make_rows
    cols = _vehicle_columns(vcfg)
    rs = RowSignals(cols)
    assert [g.key for g in rs.groups] == ["front", "rear", "speed", "timing", "currents"]
    block = make_rows(cols, 1)
    ix = {c: j for j, c in enumerate(cols)}
    block[0, ix["v_meas"]], block[0, ix["front_held"]], block[0, ix["front_g"]] = -0.15, 1.0, -6.5
    block[0, ix["front_y_ref"]], block[0, ix["y_ref"]] = 2e-3, 2e-3
    block[0, ix["rear_y_ref"]] = -1e-3
    msg = rs.message(rs.values(block)[0])
    assert msg["speed"]["v"] == -0.15 and set(msg["speed"]) == {"v", "front", "rear"}
    assert (msg["front"]["held"], msg["front"]["g"]) == (1.0, -6.5)
    assert (msg["front"]["y_ref"], msg["rear"]["y_ref"]) == (2e-3, -1e-3)      # each carrier's own
    assert len(json.dumps(rs.worst_case(), separators=(",", ":"))) < MAX_DATAGRAM // 2   # room for device health


def test_panel_shows_the_speed_and_a_held_lateral_loop(vcfg):
    from rig_runtime.app.panel import render
    from tests.test_panel import row_dict, text_of
    cols = _vehicle_columns(vcfg)
    row = row_dict(cols, v_meas=-0.123, front_held=1.0, rear_held=0.0, front_g=-8.13, rear_g=-8.13,
                   front_y_ref=0.002, rear_y_ref=-0.001, y_ref=0.002)
    text = text_of(render(row, {}, controlled=("front", "rear")), width=200)
    assert "v̂ -0.123 m/s" in text
    front = next(l for l in text.splitlines() if l.lstrip().startswith("front "))
    rear = next(l for l in text.splitlines() if l.lstrip().startswith("rear "))
    assert "HELD" in front and "-8.13" in front and "2.00" in front
    assert "HELD" not in rear and " on" in rear and "-1.00" in rear
