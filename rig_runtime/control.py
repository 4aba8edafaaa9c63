"""Controllers of Sec. 5: the cascaded PI-PD law (11)–(14) and the P baseline of Sec. 5.1,
plus open-loop input generators for identification experiments.

Discretisation (h = 5 ms): Tustin (bilinear) for the outer integrator (14) and for the
differentiator G(s) = s/(T_f s + 1) of (12). Tustin maps the stable left half plane onto
the unit disc for any h, so the filter stays stable and well damped even for T_f close to
h, and it matches the continuous frequency response best up to a few Hz where the loop's
eigenvalues (< 70 1/s ≈ 11 Hz) live. The derivative acts on the error e_ψ = ψ_ref − ψ, so
the D term sees ψ̇_ref as in (11) without measuring ẏ.

The step is pure-Python scalar arithmetic: it runs every 5 ms inside the loop.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

from .config import PIPD_GAINS, PIPDGains
from .config import Controller as ControllerConfig


@dataclass(slots=True)
class PIPDInternals:
    """What one step computed, for the recorder."""

    e_y: float = 0.0
    x_I: float = 0.0
    psi_ref: float = 0.0
    e_psi: float = 0.0
    de_psi: float = 0.0      # filtered derivative of e_ψ
    u_unsat: float = 0.0
    u: float = 0.0


class PIPDController:
    """Cascaded PI (outer, y → ψ_ref) and PD (inner, ψ → u) control law.

    ``step(y_ref, y, psi)`` returns the saturated current command; ``limit_feedback(u)``
    tells the controller what was actually applied after the safety limits, so that the
    outer integrator does not wind up against a limit it did not impose itself.

    The speed schedule (docs/vehicle.md) acts through two calls between steps:
    ``set_gain_factor(g)`` makes the outer PI's gains K_P_y·g and K_I_y·g (the integrator
    integrates g·e_y, so its share of ψ_ref does not jump when g changes: it holds the yaw
    angle the offsets need, which does not depend on the speed); ``hold(ramp_s)`` freezes
    the integrator and ramps ψ_ref linearly to 0 over ``ramp_s`` while the inner PD keeps
    ψ at ψ_ref; ``resume()`` re-seeds the integrator at the next step so that ψ_ref goes on
    from where the hold left it. With g = 1 and no hold the law is the paper's, bit for bit.
    """

    def __init__(self, cfg: ControllerConfig, u_max: float, psi_ref_max: float | None = None,
                 gains: PIPDGains | None = None):
        g = gains if gains is not None else cfg.pipd
        self.h = cfg.h
        self.kpy, self.kiy, self.kpp, self.kdp, self.tf = g.K_P_y, g.K_I_y, g.K_P_psi, g.K_D_psi, g.T_f_psi
        self.u_max = u_max
        self.psi_ref_max = psi_ref_max
        den = 2.0 * self.tf + self.h
        self._a = (2.0 * self.tf - self.h) / den   # Tustin of s/(T s + 1)
        self._b = 2.0 / den
        self.st = PIPDInternals()
        self._e_y_prev = 0.0
        self._e_psi_prev = 0.0
        self._dI = 0.0          # integration done in the last step (undone on limit feedback)
        self._started = False
        self.g = 1.0            # the schedule's gain factor on K_P_y, K_I_y (1: fixed gains)
        self.held = False       # the lateral loop holds (standstill band)
        self._reseed = False    # resumed: the next step re-seeds x_I (ψ_ref continuous)
        self._psi_hold = 0.0    # ψ_ref when the hold began
        self._hold_n = 1        # steps of the ramp to 0
        self._hold_k = 0        # steps held so far

    def reset(self) -> None:
        """Forget all history; the next step starts bumplessly."""
        self.st = PIPDInternals()
        self._e_y_prev = self._e_psi_prev = self._dI = 0.0
        self._started = False
        self.held = self._reseed = False

    def set_gain_factor(self, g: float) -> None:
        """The schedule's factor on the outer PI's gains from the next step on (sign included)."""
        self.g = g

    def hold(self, ramp_s: float) -> None:
        """Enter the hold: integrator frozen, ψ_ref from its latest value linearly to 0 over
        ``ramp_s`` (at least one step); the inner PD keeps running."""
        if not self.held:
            self.held = True
            self._reseed = False
            self._psi_hold = self.st.psi_ref
            self._hold_n = max(1, round(ramp_s / self.h))
            self._hold_k = 0

    def resume(self) -> None:
        """Leave the hold: the next step re-seeds x_I so that ψ_ref is continuous (bumpless)."""
        if self.held:
            self.held = False
            self._reseed = True

    def start(self, y_ref: float, y: float, psi: float, u0: float = 0.0) -> None:
        """Bumpless start: choose x_I so that ψ_ref = ψ (no proportional jump) and seed the
        differentiator with the current error (no derivative kick)."""
        e_y = y_ref - y
        x_I = (psi + u0 / self.kpp - self.kpy * self.g * e_y) / self.kiy if self.kiy else 0.0
        self.st = PIPDInternals(e_y=e_y, x_I=x_I, psi_ref=psi + u0 / self.kpp, u=u0, u_unsat=u0)
        self._e_y_prev = e_y
        self._e_psi_prev = u0 / self.kpp
        self._started = True
        self.held = self._reseed = False

    def step(self, y_ref: float, y: float, psi: float) -> float:
        if not self._started:
            self.start(y_ref, y, psi)
        st = self.st
        e_y = y_ref - y
        g = self.g
        if self.held:                       # standstill: integrator frozen, ψ_ref ramps to 0
            dI = 0.0
            x_I = st.x_I
            k = self._hold_k = self._hold_k + 1
            psi_ref = self._psi_hold * (1.0 - k / self._hold_n) if k < self._hold_n else 0.0
        else:
            if self._reseed:                # resumed: ψ_ref goes on from the held value
                self._reseed = False
                dI = 0.0
                x_I = (st.psi_ref - self.kpy * g * e_y) / self.kiy if self.kiy else 0.0
            else:
                dI = 0.5 * self.h * g * (e_y + self._e_y_prev)
                x_I = st.x_I + dI
            psi_ref = self.kpy * g * e_y + self.kiy * x_I
        lim = self.psi_ref_max
        if lim is not None and (psi_ref > lim or psi_ref < -lim):
            clipped = lim if psi_ref > 0 else -lim
            if (dI > 0) == (psi_ref > 0):   # clamp: integrate only out of the limit
                x_I -= dI
                dI = 0.0
            psi_ref = clipped
        e_psi = psi_ref - psi
        de = self._a * st.de_psi + self._b * (e_psi - self._e_psi_prev)
        u_unsat = self.kpp * e_psi + self.kdp * de
        u = u_unsat
        if u > self.u_max:
            u = self.u_max
        elif u < -self.u_max:
            u = -self.u_max
        if u != u_unsat and (dI > 0) == (u_unsat > 0) and dI != 0.0:
            x_I -= dI   # conditional integration: do not integrate further into saturation
            dI = 0.0
        st.e_y, st.x_I, st.psi_ref, st.e_psi, st.de_psi, st.u_unsat, st.u = e_y, x_I, psi_ref, e_psi, de, u_unsat, u
        self._dI = dI
        self._e_y_prev = e_y
        self._e_psi_prev = e_psi
        return u

    GAINS = dict(zip(PIPD_GAINS, ("kpy", "kiy", "kpp", "kdp", "tf")))     # config name -> attribute

    def gains(self) -> dict[str, float]:
        """The gains in force, by their config names."""
        return {n: getattr(self, a) for n, a in self.GAINS.items()}

    def set_gain(self, name: str, value: float) -> None:
        """Change one gain between two steps (the loop calls it at a cycle boundary; the
        change was checked by :func:`rig_runtime.tuning.check`).

        Bumpless where the law allows it:

        * ``K_P_y``, ``K_I_y`` (outer PI): x_I is rescaled/shifted so that ψ_ref =
          K_P_y e_y + K_I_y x_I computed from the last step's e_y and x_I is the same with
          the new gains: ψ_ref does not jump; from the next step on it moves as the new
          gains make it.
        * ``T_f_psi``: the differentiator's state (its output de_ψ and the last e_ψ) is kept,
          only its coefficients change: the D term does not jump.
        * ``K_P_psi``, ``K_D_psi`` (inner PD) are *not* bumpless: u = K_Pψ e_ψ + K_Dψ de_ψ
          steps by ΔK_Pψ e_ψ + ΔK_Dψ de_ψ (small near equilibrium, where e_ψ ≈ 0); the filter
          state is kept, and the supervisor's rate limit (limits.du_max) bounds the step on
          the wire.

        Before the first step (not started) only the gain changes; ``start`` then chooses
        x_I with it. Raises ValueError for a name that is not a gain of this law or a value
        that is not a finite positive number (limits are not gains: they cannot be set here).
        """
        attr = self.GAINS.get(name)
        if attr is None:
            raise ValueError(f"{name!r} is not a gain of the PI-PD law ({', '.join(self.GAINS)})")
        v = _positive(name, value)
        st = self.st
        if self._started and name in ("K_P_y", "K_I_y") and self.kiy:
            g = self.g
            psi_ref = self.kpy * g * st.e_y + self.kiy * st.x_I      # unclipped, as the last step made it
            kpy, kiy = (v, self.kiy) if name == "K_P_y" else (self.kpy, v)
            st.x_I = (psi_ref - kpy * g * st.e_y) / kiy
        setattr(self, attr, v)
        if name == "T_f_psi":
            den = 2.0 * self.tf + self.h
            self._a = (2.0 * self.tf - self.h) / den
            self._b = 2.0 / den

    def limit_feedback(self, u_applied: float) -> None:
        """The safety layer applied ``u_applied`` instead of the last output: undo this
        cycle's integration if it pushed toward the limit."""
        st = self.st
        if u_applied != st.u and self._dI != 0.0 and (self._dI > 0) == (st.u > u_applied):
            st.x_I -= self._dI
            self._dI = 0.0


class PController:
    """The P baseline of Sec. 5.1: u = K_P (y_ref − y), saturated. Scheduled, K_P·g; held,
    u = 0 (the law has no yaw loop to keep ψ at 0 with)."""

    def __init__(self, cfg: ControllerConfig, u_max: float):
        self.kp = cfg.K_P
        self.u_max = u_max
        self.st = PIPDInternals()
        self.g = 1.0
        self.held = False

    def reset(self) -> None:
        self.st = PIPDInternals()

    def start(self, y_ref: float, y: float, psi: float, u0: float = 0.0) -> None:
        self.reset()
        self.held = False

    def set_gain_factor(self, g: float) -> None:
        self.g = g

    def hold(self, ramp_s: float) -> None:
        self.held = True

    def resume(self) -> None:
        self.held = False

    def step(self, y_ref: float, y: float, psi: float) -> float:
        e = y_ref - y
        u = 0.0 if self.held else self.kp * self.g * e
        u_sat = min(self.u_max, max(-self.u_max, u))
        st = self.st
        st.e_y, st.u_unsat, st.u = e, u, u_sat
        return u_sat

    def gains(self) -> dict[str, float]:
        return {"K_P": self.kp}

    def set_gain(self, name: str, value: float) -> None:
        """Change K_P between two steps. Not bumpless: the law has no state to absorb the
        change, u steps by ΔK_P (y_ref − y); the supervisor's rate limit bounds the step on
        the wire. ValueError for another name or a value that is not finite and positive."""
        if name != "K_P":
            raise ValueError(f"{name!r} is not a gain of the P law (K_P)")
        self.kp = _positive(name, value)

    def limit_feedback(self, u_applied: float) -> None:
        pass


def _positive(name: str, value: float) -> float:
    """A gain's new value as a float; ValueError unless finite and positive."""
    v = float(value)
    if not (math.isfinite(v) and v > 0):
        raise ValueError(f"{name}: {value!r} is not a finite positive number")
    return v


def make_controller(cfg: ControllerConfig, u_max: float, psi_ref_max: float | None = None,
                    carrier: str | None = None):
    """The configured control law (with ``carrier``: that carrier's gains, ``cfg.gains``)."""
    if cfg.law == "p":
        return PController(cfg, u_max)
    return PIPDController(cfg, u_max, psi_ref_max, cfg.gains(carrier) if carrier is not None else None)


# --------------------------------------------------------------------------- open loop
class StepSequence:
    """Piecewise-constant input: ``[(t0, u0), (t1, u1), …]`` (Fig. 3 style); 0 before the
    first step (several steps at one time: the last one given with the largest u, as sorted).

    Each call moves an index from the step in force at the previous call's t: O(1) amortised
    while t does not decrease from call to call — the loop's run time (a restart after an
    operator's fault reset goes back once) — and still right for any t (it walks back)."""

    __slots__ = ("times", "values", "_i")

    def __init__(self, steps: Sequence[tuple[float, float]]):
        pts = sorted((float(t), float(u)) for t, u in steps)
        self.times = [t for t, _ in pts]
        self.values = [u for _, u in pts]
        self._i = -1            # the step in force at the previous call (-1: none yet)

    def __call__(self, t: float) -> float:
        times, i = self.times, self._i
        last = len(times) - 1
        while i < last and times[i + 1] <= t:
            i += 1
        while i >= 0 and times[i] > t:
            i -= 1
        self._i = i
        return self.values[i] if i >= 0 else 0.0


class Sinusoid:
    """``amplitude · sin(2π f t) + bias`` with f in mHz, as in Sec. 4.3.4 (4.8 / 2.4 mHz)."""

    def __init__(self, amplitude: float, freq_mhz: float, bias: float = 0.0, t0: float = 0.0):
        self.amplitude, self.w, self.bias, self.t0 = amplitude, 2 * math.pi * freq_mhz * 1e-3, bias, t0

    def __call__(self, t: float) -> float:
        if t < self.t0:
            return self.bias
        return self.bias + self.amplitude * math.sin(self.w * (t - self.t0))


class ZeroInput:
    """Δu = 0: free response."""

    def __call__(self, t: float) -> float:
        return 0.0
