"""Verification harness of the plant integrator (sim_backend/plant.py): held-input
scenarios, the integrator run over them, and the stiff reference solver
(``scipy.integrate.solve_ivp``, Radau) it is checked against. Used by tests/test_plant.py and
benchmarks/sim_speed.py; docs/plant-model.md has the measured errors."""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import Any, Optional, Sequence

import numpy as np

from rig_runtime.config import Plant as PlantParams
from sim_backend.plant import Plant


# --------------------------------------------------------------------------- scenarios
@dataclass(frozen=True)
class Scenario:
    """Inputs held over each step k: columns du_f, du_r, F_y_f, F_y_r, M_z_f, M_z_r; ``speed``
    (optional) the roller speed held over each step k (m/s; None: the plant's fixed v)."""

    name: str
    params: PlantParams
    dt: float
    inputs: np.ndarray
    initial: dict = field(default_factory=dict)
    speed: Optional[np.ndarray] = None

    @property
    def t(self) -> np.ndarray:
        return np.arange(len(self.inputs) + 1) * self.dt


def _inputs(n: int) -> np.ndarray:
    return np.zeros((n, 6))


def scenario_open_loop_steps(params: PlantParams, h: float = 0.005, t_end: float = 120.0,
                             levels: Sequence[tuple[float, float]] = (
                                 (0.0, 0.0), (20.0, 1.0), (40.0, 0.0), (60.0, -1.0),
                                 (80.0, 0.5), (100.0, -0.5))) -> Scenario:
    """Open-loop steps of du_r like Fig. 3: (start time, level) pairs, front lifted and idle."""
    n = int(round(t_end / h))
    U = _inputs(n)
    tk = np.arange(n) * h
    for t0, lv in levels:
        U[tk >= t0 - 1e-9, 1] = lv
    return Scenario("open_loop_steps", params, h, U)


def scenario_sine(params: PlantParams, nu: float, amplitude: float = 0.7, h: float = 0.005,
                  hold: Optional[float] = None, periods: float = 1.0) -> Scenario:
    """du_r = amplitude sin(2 pi nu t) over ``periods`` periods (Fig. 9; one step more, so the
    record ends just past the last rising zero crossing), sampled and held every ``hold``
    seconds (default: every step h; ``hold`` is rounded to a multiple of h)."""
    n = int(math.ceil(periods / nu / h - 1e-9)) + 1    # just past the end of the last period
    m = 1 if hold is None else max(1, int(round(hold / h)))
    tk = (np.arange(n) // m) * m * h
    U = _inputs(n)
    U[:, 1] = amplitude * np.sin(2.0 * np.pi * nu * tk)
    return Scenario(f"sine_{nu * 1e3:g}mHz", params, h, U)


def scenario_free_response(params: PlantParams, psi0: float = 0.01, D: float = 0.28,
                           h: float = 0.005, t_end: float = 3.0) -> Scenario:
    """Free response of the lifted, linear carrier (Sec. 4.3.2): du = 0, psi(0) = psi0, D fixed."""
    P = replace(params, bouc_wen=None, D_min=D, D_max=D)
    n = int(round(t_end / h))
    return Scenario("free_response", P, h, _inputs(n), {"psi_ar": psi0})


def simulate(scenario: Scenario, plant: Optional[Plant] = None, **plant_kw: Any) -> np.ndarray:
    """Run the integrator over the scenario; returns states (n+1, n_states) at t = k dt
    (layout ``STATE_NAMES``). A given ``plant`` is reset and used with its own parameters."""
    pl = plant if plant is not None else Plant(scenario.params, **plant_kw)
    pl.reset(**scenario.initial)
    f, r = pl._front, pl._rear
    dyn = pl.dynamic

    def row() -> tuple:
        x = (pl._y_f, pl._y_r, f.psi, f.p, f.z, f.e, r.psi, r.p, r.z, r.e)
        return x + (pl._dw_f, pl._dw_r) if dyn else x
    rows = [row()]
    dt = scenario.dt
    step = pl.step
    if scenario.speed is None:
        for u in scenario.inputs.tolist():
            step(dt, *u)
            rows.append(row())
    else:
        set_speed = pl.set_speed
        for u, v in zip(scenario.inputs.tolist(), scenario.speed.tolist()):
            set_speed(v)
            step(dt, *u)
            rows.append(row())
    return np.array(rows)


def reference(scenario: Scenario, rtol: float = 1e-10, atol: float = 1e-12, method: str = "Radau",
              **plant_kw: Any) -> np.ndarray:
    """The same scenario with ``scipy.integrate.solve_ivp`` (restarted wherever the held
    inputs or the speed change, so it sees exactly the same ZOH input); states at t = k dt."""
    from scipy.integrate import solve_ivp

    pl = Plant(scenario.params, **plant_kw)
    pl.reset(**scenario.initial)
    U = scenario.inputs
    n = len(U)
    dt = scenario.dt
    out = np.empty((n + 1, pl.n_states))
    x = pl.state_vector()
    out[0] = x
    prev = (pl._front.du, pl._rear.du, 0.0, 0.0, 0.0, 0.0)
    V = scenario.speed
    held = U if V is None else np.column_stack((U, V))
    change = np.flatnonzero(np.any(np.diff(held, axis=0) != 0.0, axis=1)) + 1
    bounds = np.concatenate(([0], change, [n]))
    for k0, k1 in zip(bounds[:-1], bounds[1:]):
        t_eval = np.arange(k0 + 1, k1 + 1) * dt
        if V is not None:
            pl.set_speed(float(V[k0]))
        x = pl.input_jump(x, prev, U[k0])
        prev = tuple(U[k0])
        sol = solve_ivp(pl.rhs, (k0 * dt, k1 * dt), x, method=method, t_eval=t_eval,
                        args=(tuple(U[k0]),), rtol=rtol, atol=atol)
        if not sol.success:
            raise RuntimeError(f"reference solver failed on [{k0 * dt}, {k1 * dt}]: {sol.message}")
        out[k0 + 1:k1 + 1] = sol.y.T
        x = sol.y[:, -1]
    return out


def loop_width(du: np.ndarray, psi: np.ndarray) -> float:
    """Width of the psi-du loop (Fig. 9): psi where du crosses zero falling minus psi where it
    crosses zero rising (the last crossing of each kind), by linear interpolation.  ``du`` and
    ``psi`` are sampled at the same instants; |du| below 1e-12 max|du| counts as zero."""
    du = np.asarray(du, dtype=float)
    psi = np.asarray(psi, dtype=float)
    s = np.sign(np.where(np.abs(du) <= 1e-12 * np.max(np.abs(du)), 0.0, du))
    up = np.flatnonzero((s[:-1] < 0) & (s[1:] >= 0))
    dn = np.flatnonzero((s[:-1] > 0) & (s[1:] <= 0))
    if len(up) == 0 or len(dn) == 0:
        raise ValueError("du has no rising and falling zero crossing")

    def at(i: int) -> float:
        w = 1.0 if s[i + 1] == 0 else du[i] / (du[i] - du[i + 1])
        return float(psi[i] + w * (psi[i + 1] - psi[i]))

    return at(dn[-1]) - at(up[-1])
