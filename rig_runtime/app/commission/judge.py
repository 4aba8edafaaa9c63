"""The judgement of each commissioning item from what was observed: pass/fail, the measured
values and, on a failure, the likely wiring fault in words. Plain functions on recorded
series; nothing here touches a device."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from statistics import median
from typing import Mapping, Optional, Sequence

from ...config import RigConfig
from ...config import WHEELS
from ...allocation import split
from ...lanes import CARRIER_WHEELS
from ...observer import dw_row

# what the passive prompt asks for: the sign each laser's reading must move with
# (push left: the vehicle moves away from the lateral lasers; rear carrier nose-left:
# s_rl grows, s_rr shrinks; front carrier nose-right: s_fl shrinks, s_fr grows)
EXPECTED_LASER_SIGN = {"b_f": +1, "b_r": +1, "s_rl": +1, "s_rr": -1, "s_fl": -1, "s_fr": +1}
LASER_RESPONSE_M = 0.1e-3           # a laser "responds" when its reading moves by this much
YAW_PAIR_CORR = 0.5                 # one carrier's yaw lasers: |correlation| at least 0.5 (they move together)
ENCODER_TOLERANCE = 0.2             # |ω| within ±20 % of v / r0
PSI_RESPONSE_RAD = 0.5e-3           # a bump "moves the yaw angle" by at least this much
DW_RESPONSE_RAD_S = 0.015           # an encoder "answers" a bump: Δω moves by this much
RELATION4_BAND = (0.5, 1.5)         # measured Δω over the Δω relation (4) predicts
LIFTED_RESPONSE_RAD_S = 0.3         # a lifted wheel "answers" a bump: its ω moves by this much (~3 rad/s expected)


@dataclass(frozen=True)
class Item:
    """One line of the report."""
    name: str
    passed: bool
    measured: Mapping[str, float] = field(default_factory=dict)
    faults: tuple[str, ...] = ()
    note: str = ""

    def as_dict(self) -> dict:
        return {"name": self.name, "passed": self.passed, "measured": dict(self.measured),
                "faults": list(self.faults), "note": self.note}


def deflection(series: Sequence[float]) -> float:
    """The largest excursion from the series' median (the rest value), signed."""
    finite = [v for v in series if math.isfinite(v)]
    if not finite:
        return math.nan
    m = median(finite)
    return max((v - m for v in finite), key=abs)


def _corr(a: Sequence[float], b: Sequence[float]) -> float:
    pairs = [(x, y) for x, y in zip(a, b) if math.isfinite(x) and math.isfinite(y)]
    if len(pairs) < 3:
        return math.nan
    ma = sum(x for x, _ in pairs) / len(pairs)
    mb = sum(y for _, y in pairs) / len(pairs)
    sab = sum((x - ma) * (y - mb) for x, y in pairs)
    saa = sum((x - ma) ** 2 for x, _ in pairs)
    sbb = sum((y - mb) ** 2 for _, y in pairs)
    return sab / math.sqrt(saa * sbb) if saa > 0 and sbb > 0 else math.nan


def _carriers_move_together(series: Mapping[str, Sequence[float]], front: tuple[str, str],
                            rear: tuple[str, str]) -> bool:
    """A turned carrier moves its two yaw lasers together (in opposite directions if both
    read with the right sign: the signs are judged apart)."""
    return all(abs(_corr(series.get(a, ()), series.get(b, ()))) >= YAW_PAIR_CORR for a, b in (front, rear))


def judge_lasers(series: Mapping[str, Sequence[float]]) -> Item:
    """Each laser moved, in the direction the prompt's motions give it (docs/conventions.md),
    and each carrier's two yaw lasers moved together (moving the rear carrier changes s_rl
    and s_rr, not s_fl and s_fr)."""
    dev = {r: deflection(series.get(r, ())) for r in EXPECTED_LASER_SIGN}
    silent = [r for r in EXPECTED_LASER_SIGN if not math.isfinite(dev[r]) or abs(dev[r]) < LASER_RESPONSE_M]
    faults = [f"{r} does not respond (moved {dev[r] * 1e3:+.3f} mm, at least {LASER_RESPONSE_M * 1e3:.1f} mm expected)"
              for r in silent]
    cross: set[str] = set()
    yaw = ("s_fl", "s_fr", "s_rl", "s_rr")
    if not silent or not set(silent) & set(yaw):
        f, r = ("s_fl", "s_fr"), ("s_rl", "s_rr")
        if not _carriers_move_together(series, f, r):
            for a in f:
                for b in r:
                    ex = {**series, a: series.get(b, ()), b: series.get(a, ())}
                    if not cross and _carriers_move_together(ex, f, r):
                        faults.append(f"{a} and {b} appear swapped ({a} moves with the rear carrier, "
                                      f"{b} with the front)")
                        cross = {a, b}
            if not cross:
                faults.append("the yaw lasers of a carrier do not move together: s_fl/s_fr and s_rl/s_rr are "
                              "not each one carrier's pair (check which laser looks at which carrier)")
                cross = set(yaw)
    wrong = [r for r, s in EXPECTED_LASER_SIGN.items()
             if r not in silent and r not in cross and math.copysign(1, dev[r]) != s]
    left = list(wrong)
    # two wrong lasers whose expected directions are opposite: each reads what the other should
    for a in wrong:
        for b in wrong:
            if a < b and a in left and b in left and EXPECTED_LASER_SIGN[a] == -EXPECTED_LASER_SIGN[b] \
                    and abs(abs(dev[a]) - abs(dev[b])) <= 0.5 * max(abs(dev[a]), abs(dev[b])):
                faults.append(f"{a} and {b} appear swapped (each moves the way the other should; "
                              "or both read with the wrong sign)")
                left.remove(a)
                left.remove(b)
    faults += [f"{r} reads with the wrong sign (moved {dev[r] * 1e3:+.3f} mm, expected "
               f"{'+' if EXPECTED_LASER_SIGN[r] > 0 else '-'})" for r in left]
    measured = {f"{r}_mm": dev[r] * 1e3 for r in dev}
    if not {"b_f", "b_r"} & (set(silent) | set(wrong)):
        df, dr = rear_end_push(series.get("b_f", ()), series.get("b_r", ()))
        measured.update(rear_end_b_f_mm=df * 1e3, rear_end_b_r_mm=dr * 1e3)
        if not abs(dr - df) >= LASER_RESPONSE_M:
            faults.append("the rear end was not seen pushed alone (b_f and b_r always moved alike): b_f and b_r "
                          "are not told apart (push the rear end to the left, holding the front end)")
        elif abs(df) > abs(dr):
            faults.append(f"b_f and b_r appear swapped (b_f moves most when the rear end is pushed alone: "
                          f"b_f {df * 1e3:+.3f} mm, b_r {dr * 1e3:+.3f} mm)")
    return Item("lasers", not faults, measured, tuple(faults))


def rear_end_push(b_f: Sequence[float], b_r: Sequence[float]) -> tuple[float, float]:
    """Both lateral lasers' excursions from their rest values at the sample where they differ
    most: the rear end pushed alone (the front end held) moves b_r by far the most, a push
    of the whole vehicle moves both alike. (NaN, NaN) without a common sample."""
    pairs = [(f, r) for f, r in zip(b_f, b_r) if math.isfinite(f) and math.isfinite(r)]
    if not pairs:
        return math.nan, math.nan
    mf, mr = median(f for f, _ in pairs), median(r for _, r in pairs)
    return max(((f - mf, r - mr) for f, r in pairs), key=lambda d: abs(d[1] - d[0]))


def rolling_wheels(cfg: RigConfig) -> tuple[str, ...]:
    """The wheels on the rollers in the rig's set-up (a carrier with ``plant.front_contact:
    false`` is lifted: its wheels do not turn with the rollers)."""
    return tuple(w for w in WHEELS if w[0] == "r" or cfg.plant.front_contact)


def judge_encoders(series: Mapping[str, Sequence[float]], cfg: RigConfig,
                   node_ids: Optional[Mapping[str, int]] = None) -> Item:
    """Every wheel on the rollers reports the roller speed v / r0, with its sign (a lifted
    carrier's wheels are judged by its lifted bump, but must not report the roller speed: a
    rolling wheel's drive that reports no speed and a lifted wheel's drive that reports the
    roller speed have their node IDs exchanged)."""
    expect = cfg.plant.v / cfg.plant.r0
    faults, meas = [], {}
    rolling = rolling_wheels(cfg)
    for w in rolling:
        vals = [v for v in series.get(w, ()) if math.isfinite(v)]
        om = median(vals) if vals else math.nan
        meas[f"omega_{w}_rad_s"] = om
        if not math.isfinite(om) or abs(om) < (1 - ENCODER_TOLERANCE) * abs(expect):
            faults.append(f"encoder {w} does not report the roller speed ({om:+.2f} rad/s, expected {expect:+.2f})")
        elif math.copysign(1, om) != math.copysign(1, expect):
            faults.append(f"encoder {w} reads with the wrong sign ({om:+.2f} rad/s, expected {expect:+.2f})")
        elif abs(om) > (1 + ENCODER_TOLERANCE) * abs(expect):
            faults.append(f"encoder {w} reports {om:+.2f} rad/s, expected {expect:+.2f} (velocity_factor?)")
    meas["expected_rad_s"] = expect
    lifted = [w for w in WHEELS if w not in rolling]
    silent = [w for w in rolling if not abs(meas[f"omega_{w}_rad_s"]) >= (1 - ENCODER_TOLERANCE) * abs(expect)]
    for w in lifted:
        vals = [v for v in series.get(w, ()) if math.isfinite(v)]
        om = median(vals) if vals else math.nan
        if abs(om) >= (1 - ENCODER_TOLERANCE) * abs(expect):
            meas[f"omega_{w}_rad_s"] = om
            ids = node_ids or {}
            if silent:
                s = silent.pop(0)
                faults = [f for f in faults if not f.startswith(f"encoder {s} does not report")]
                faults.append(f"drives {s} and {w} appear swapped: drive node {ids.get(s, '?')} ({s}) reports no roller "
                              f"speed, node {ids.get(w, '?')} ({w}, lifted) reports {om:+.2f} rad/s (node IDs; or "
                              "their encoder cables, if a lifted bump found the encoders crossed between the carriers)")
            else:
                faults.append(f"the drive of {w} (node {ids.get(w, '?')}) reports the roller speed ({om:+.2f} rad/s) "
                              f"though its carrier is lifted (node IDs, or the set-up is not this config's)")
    note = (f"{', '.join(lifted)}: lifted in this rig's set-up (plant.front_contact: false), not turned by the "
            "rollers; judged by the lifted bump" if lifted else "")
    return Item("encoders", not faults, meas, tuple(faults), note)


def encoder_signs(encoders: Optional[Item]) -> dict[str, int]:
    """The sign each wheel's encoder reads a forward roll with (+1 right, -1 inverted), for the
    wheels the encoders check judged (a wheel that reported no speed is not among them)."""
    if encoders is None:
        return {}
    exp = encoders.measured.get("expected_rad_s", math.nan)
    out = {}
    for w in WHEELS:
        om = encoders.measured.get(f"omega_{w}_rad_s", math.nan)
        if math.isfinite(om) and math.isfinite(exp) and abs(om) >= (1 - ENCODER_TOLERANCE) * abs(exp):
            out[w] = 1 if math.copysign(1, om) == math.copysign(1, exp) else -1
    return out


def judge_lifted(carrier: str, u_A: float, pulse_s: float, rec: Mapping[str, Sequence[float]], cfg: RigConfig,
                 node_ids: Mapping[str, int], enc_signs: Mapping[str, int]) -> Item:
    """A pulse of ``u_A`` (±u/2 on the carrier's two wheels) with the carrier lifted: each wheel
    spins freely, J_x dω/dt = k_τ i, so each of the pair's encoders must answer on its own,
    turning the way its own drive's current pushes (the other carrier's wheels must not
    answer). With the encoder's sign known from the rollers (``enc_signs``), a wheel turning
    backwards names its drive's current polarity. ``rec`` as for :func:`judge_bump`, plus
    ``omega_<wheel>`` per cycle."""
    p = cfg.plant
    name = f"lifted-{carrier}"
    run = rec["running"]
    on = [i for i, r in enumerate(run) if r]
    if not on or on[0] < 3:
        return Item(name, False, {}, (f"the lifted {carrier} bump did not run (never RUNNING)",))
    i0 = on[0]
    # the wheels at rest before the pulse: the cycles with the power stages on (the operator
    # has lifted the carrier before), at most 20
    pre = [i for i in range(max(0, i0 - 20), i0) if rec["enabled"][i]] or list(range(max(0, i0 - 5), i0))
    base = {w: median(rec[f"omega_{w}"][i] for i in pre) for w in WHEELS}
    n = len(run)
    dom = {w: max((rec[f"omega_{w}"][i] - base[w] for i in range(i0, n)), key=abs) for w in WHEELS}
    l, r = CARRIER_WHEELS[carrier]
    cur = dict(zip((l, r), split(u_A)))
    expect = {w: p.k_tau * cur[w] * pulse_s / p.J_x for w in (l, r)}    # the free wheel, friction neglected
    measured: dict[str, float] = {"u_A": u_A}
    for w in WHEELS:
        measured[f"dw_{w}_rad_s"] = dom[w]
    polarity: dict[str, int] = {}
    for w in (l, r):
        measured[f"expected_dw_{w}_rad_s"] = expect[w]
        measured[f"J_x_est_{w}"] = abs(p.k_tau * cur[w] * pulse_s / dom[w]) if dom[w] else math.nan
    answered = {w for w in WHEELS if abs(dom[w]) >= LIFTED_RESPONSE_RAD_S}
    faults = []
    strays = [w for w in WHEELS if w not in (l, r) and w in answered]
    if strays:
        faults.append(f"the {carrier} pulse (drive nodes {node_ids[l]}, {node_ids[r]}) is answered at drive node "
                      + " and ".join(f"{node_ids[w]} ({w}: {dom[w]:+.2f} rad/s)" for w in strays)
                      + f": an encoder of the {carrier} wheels is wired to a drive of the other carrier (encoder "
                        "cables crossed between the carriers)")
    for w in (l, r):
        if w not in answered:
            faults.append(f"wheel {w} does not answer the pulse of its drive (node {node_ids[w]}, {cur[w]:+.2f} A: "
                          f"Δω {dom[w]:+.3f} rad/s, about {expect[w]:+.2f} expected)"
                          + ("" if strays else f": is the {carrier} carrier lifted? (on the rollers the answer is "
                                               "~100 times smaller)"))
    # the way each wheel turned: its reading, corrected by its encoder's sign where the rollers told it
    for w in (l, r):
        if w in answered:
            read = 1 if math.copysign(1, dom[w]) == math.copysign(1, cur[w]) else -1
            polarity[w] = read * enc_signs.get(w, 1)
    inverted = [w for w in (l, r) if polarity.get(w) == -1]
    notes = [f"{w} read backwards as its encoder is inverted (the encoders check): its drive's current polarity "
             "is right" for w in (l, r) if polarity.get(w) == 1 and enc_signs.get(w, 1) < 0]
    if len(inverted) == 2 and not any(enc_signs.get(w, 1) < 0 for w in inverted):
        faults.append(f"wheels {l} and {r} both turned backwards: drives {l} and {r} both appear to have their "
                      f"current polarity inverted, or the encoders of {l} and {r} are exchanged (bump-{carrier} on "
                      "the rollers tells which: a wrong yaw sign is the polarity)")
    else:
        for w in inverted:
            faults.append(f"drive {w} current polarity appears inverted (node {node_ids[w]}: wheel {w} turned "
                          f"{dom[w] * enc_signs.get(w, 1):+.2f} rad/s for {cur[w]:+.2f} A"
                          + (", its encoder read inverted" if enc_signs.get(w, 1) < 0 else "") + ")"
                          + (f" — or encoder {w} reads with the wrong sign (not judged on the rollers)"
                             if w not in enc_signs else ""))
    for w in WHEELS:
        measured[f"polarity_{w}"] = float(polarity[w]) if w in polarity else math.nan
    return Item(name, not faults, measured, tuple(faults), "; ".join(notes))


def _slope(x: Sequence[float], y: Sequence[float]) -> float:
    sxx = sum(a * a for a in x)
    return sum(a * b for a, b in zip(x, y)) / sxx if sxx > 0 else math.nan


def judge_bump(carrier: str, u_A: float, rec: Mapping[str, Sequence[float]], cfg: RigConfig,
               node_ids: Mapping[str, int], yaw_lasers_ok: Optional[bool] = None,
               lifted: Optional[Item] = None, encoders_ok: Optional[bool] = None) -> Item:
    """A pulse of ``u_A`` on ``carrier``: its yaw angle moves with the sign of K·u (K > 0),
    its own pair's Δω answers (the other pair's does not), and Δω follows relation (4)
    (Δω = Γ v b / (2 r0²) y + b / (2 r0) ψ̇ + v k_τ / (r0² c11) u) when the carrier rolls.
    ``lifted``: the carrier's lifted bump, whose per-wheel polarity names the wheel when the
    yaw angle does not move; ``yaw_lasers_ok``/``encoders_ok`` False: the faults say the
    laser or encoder check failed for this carrier first.

    ``rec``: per cycle ``t``, ``running`` (1 while RUNNING), and for both carriers
    ``psi_<c>``, ``dw_<c>``, ``y_<c>``, ``u_<c>`` (the current let through)."""
    p = cfg.plant
    other = "front" if carrier == "rear" else "rear"
    t, run = rec["t"], rec["running"]
    on = [i for i, r in enumerate(run) if r]
    name = f"bump-{carrier}"
    if not on or on[0] < 3:
        return Item(name, False, {}, (f"the {carrier} bump did not run (never RUNNING)",))
    i0 = on[0]
    # the pose at the pulse's first cycle (the yaw angle has not moved yet: it is second order;
    # a hand on the vehicle before the ARM is off by then), Δω as it rolled before the pulse
    base = {k: rec[k][i0] for k in (f"psi_{carrier}", f"psi_{other}", f"y_{carrier}")}
    base.update({k: median(rec[k][max(0, i0 - 40):i0]) for k in (f"dw_{carrier}", f"dw_{other}")})
    idx = on + list(range(on[-1] + 1, len(t)))
    dpsi = max((rec[f"psi_{carrier}"][i] - base[f"psi_{carrier}"] for i in idx), key=abs)
    dpsi_other = max((rec[f"psi_{other}"][i] - base[f"psi_{other}"] for i in idx), key=abs)
    ddw = max((rec[f"dw_{carrier}"][i] - base[f"dw_{carrier}"] for i in idx), key=abs)
    ddw_other = max((rec[f"dw_{other}"][i] - base[f"dw_{other}"] for i in idx), key=abs)
    h = cfg.controller.h
    # relation (4) over the pulse and after it: the prediction from the measured y, ψ̇ and u
    gvb, b2r, vk = dw_row(cfg)
    psi = rec[f"psi_{carrier}"]
    pred, meas = [], []
    for i in idx:
        if i0 + 2 <= i < len(t) - 2:      # differences inside the pulse's session only
            rate = (psi[i + 2] + psi[i + 1] - psi[i - 1] - psi[i - 2]) / (6 * h)
            pred.append(gvb * (rec[f"y_{carrier}"][i] - base[f"y_{carrier}"]) + b2r * rate + vk * rec[f"u_{carrier}"][i])
            meas.append(rec[f"dw_{carrier}"][i] - base[f"dw_{carrier}"])
    rolls = carrier == "rear" or p.front_contact
    ratio = _slope(pred, meas) if rolls else math.nan
    l, r = CARRIER_WHEELS[carrier]
    measured = {"u_A": u_A, "dpsi_mrad": dpsi * 1e3, "dpsi_other_mrad": dpsi_other * 1e3,
                "ddw_rad_s": ddw, "ddw_other_rad_s": ddw_other, "relation4_ratio": ratio,
                "expected_psi_mrad": p.K * u_A * 1e3}
    faults = []
    moved = abs(dpsi) >= PSI_RESPONSE_RAD
    psi_sign_ok = moved and math.copysign(1, dpsi) == math.copysign(1, u_A)
    lasers_hint = "" if yaw_lasers_ok is not False else f" (the {carrier} yaw lasers failed the laser check: fix them first)"
    if encoders_ok is False:
        lasers_hint += f" (an encoder of {l}/{r} failed the encoders check: fix it first)"
    if not moved:
        if abs(dpsi_other) >= PSI_RESPONSE_RAD:
            faults.append(f"the {carrier} bump moved the {other} carrier: the drives of {l}/{r} appear to "
                          f"sit on the {other} wheels (node IDs)")
        else:
            named = [w for w in (l, r) if lifted is not None and lifted.measured.get(f"polarity_{w}") == -1.0]
            who = (f"drive {named[0]} current polarity appears inverted (named by lifted-{carrier})" if len(named) == 1
                   else f"drive {l} or {r} current polarity appears inverted")
            faults.append(f"the {carrier} bump did not move the yaw angle ({dpsi * 1e3:+.2f} mrad): {who} "
                          f"(both wheels pushed the same way)")
    ratio_ok = not rolls or (math.isfinite(ratio) and RELATION4_BAND[0] <= ratio <= RELATION4_BAND[1])
    ratio_neg = rolls and math.isfinite(ratio) and ratio <= -RELATION4_BAND[0]
    other_rolls = other == "rear" or p.front_contact
    if moved and rolls and abs(ddw) < DW_RESPONSE_RAD_S:
        faults.append(f"no encoder of the {carrier} pair answers the bump (Δω moved {ddw:+.3f} rad/s)"
                      + (f"; the {other} pair's did ({ddw_other:+.3f} rad/s)"
                         if other_rolls and abs(ddw_other) >= DW_RESPONSE_RAD_S else ""))
    elif moved and not psi_sign_ok:
        if ratio_neg:
            faults.append(f"drives {l} and {r} appear swapped: drive node {node_ids[l]} moves wheel {r} and node "
                          f"{node_ids[r]} wheel {l} (yaw moved {dpsi * 1e3:+.2f} mrad, Δω against relation (4))")
        elif rolls:
            faults.append(f"the {carrier} yaw angle moved the wrong way ({dpsi * 1e3:+.2f} mrad for u = {u_A:+.2f} A) "
                          f"with Δω as (4) says: drives {l} and {r} both appear to have their current polarity "
                          f"inverted")
        else:
            faults.append(f"the {carrier} yaw angle moved the wrong way ({dpsi * 1e3:+.2f} mrad for u = {u_A:+.2f} A): "
                          f"drives {l} and {r} appear swapped (node IDs {node_ids[l]}, {node_ids[r]}) or both have "
                          f"their current polarity inverted (not rolling: Δω cannot tell which)")
    elif moved and not ratio_ok:
        faults.append(f"Δω of the {carrier} pair does not follow relation (4) (measured / predicted = {ratio:+.2f}): "
                      f"the encoders of {l} and {r} appear swapped or one reads with the wrong sign")
    faults = [f + lasers_hint for f in faults]
    note = "" if rolls else f"{carrier} carrier not in rolling contact (plant.front_contact: false): relation (4) not checked"
    return Item(name, not faults, measured, tuple(faults), note)
