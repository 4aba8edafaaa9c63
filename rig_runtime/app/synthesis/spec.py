"""The synthesis spec (YAML; docs/synthesis.md): the tunables with their bounds, the cases
(scenario, seed, speed, parameter values; ``corners`` multiplies them), the criteria with
their demands (which are objectives), and the optimizer. Validated — including every case's
config at the tunables' bounds and every case's scenario — before anything runs; a refusal
is one :class:`ConfigError` naming the spec file and key (exit 2)."""

from __future__ import annotations

import dataclasses
import itertools
import re
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Optional

import yaml

from rig_runtime import config as rig_config
from rig_runtime.errors import ConfigError
from rig_runtime.scenario import SCENARIO_DIR, load_scenario

from ..campaign import materialize, paths
from ..campaign.outcome import METRIC_NAMES, METRICS, unavailable
from ..campaign.spec import _distribution, _number, _resolve, nominal_value
from .linear import LINEAR

TOP_KEYS = ("name", "description", "base", "tunables", "cases", "corners", "criteria", "optimizer")
CASE_KEYS = ("name", "scenario", "duration_s", "seed", "speed", "set")
METHODS = ("nsga2", "nsga3")


@dataclass(frozen=True, kw_only=True)
class Tunable:
    name: str                   # a parameter path under controller. (campaign/paths.py)
    lo: float
    hi: float
    nominal: float              # the base config's value (the first candidate starts there)


@dataclass(frozen=True, kw_only=True)
class Case:
    name: str
    values: dict                # parameter path -> value (plant.v for a speed)
    scenario: Optional[dict]    # the scenario as written for this case (None: linear criteria only)
    duration_s: Optional[float]
    seed: int


@dataclass(frozen=True, kw_only=True)
class Criterion:
    name: str
    linear: bool                # from the analysis (else from the lockstep runs: a campaign metric)
    demand: Optional[float]     # upper bound (None: an objective without a demand)
    objective: bool             # minimised (its worst over the cases)


@dataclass(frozen=True, kw_only=True)
class Optimizer:
    method: str
    population: int
    generations: int
    seed: int
    start: str                  # config: the first candidate is the base config's gains; none


@dataclass(frozen=True, kw_only=True)
class SynthesisSpec:
    name: str
    source: str
    description: str
    config: Path
    settle_s: float
    tunables: tuple[Tunable, ...]
    cases: tuple[Case, ...]
    criteria: tuple[Criterion, ...]
    optimizer: Optimizer

    @property
    def objectives(self) -> tuple[Criterion, ...]:
        return tuple(c for c in self.criteria if c.objective)

    @property
    def linear_names(self) -> tuple[str, ...]:
        return tuple(c.name for c in self.criteria if c.linear)

    def to_json(self) -> dict:
        d = dataclasses.asdict(self)
        d["config"] = str(self.config)
        return d


def _err(src: str, key: str, expected: str, got: Any = None) -> ConfigError:
    return ConfigError(src, key, expected, got)


def _int(s: str, key: str, v: Any, lo: int) -> int:
    if isinstance(v, bool) or not isinstance(v, int) or v < lo:
        raise _err(s, key, f"an integer >= {lo}", v)
    return v


def _tunables(s: str, raw: Any, sections: dict) -> tuple[Tunable, ...]:
    if not isinstance(raw, dict) or not raw:
        raise _err(s, "tunables", "a mapping of controller parameters to their bounds [lo, hi]", raw)
    out = []
    for name, b in raw.items():
        key = f"tunables.{name}"
        name = str(name)
        nominal = paths.nominal(sections, name)
        if not name.startswith("controller.") or nominal is None:
            raise _err(s, key, "a number of the base config's controller section (controller.pipd.K_P_y, "
                       "controller.front.K_I_y, …)", name)
        if not isinstance(b, list) or len(b) != 2:
            raise _err(s, key, "bounds [lo, hi]", b)
        lo, hi = (_number(s, key, x) for x in b)
        if not lo < hi:
            raise _err(s, key, "lo < hi", b)
        out.append(Tunable(name=name, lo=lo, hi=hi, nominal=nominal))
    return tuple(out)


def _scenario_dict(s: str, key: str, src: Path, name: Any) -> tuple[Path, dict]:
    try:
        p = _resolve(src, str(name), SCENARIO_DIR, "scenario")
    except ConfigError:
        raise _err(s, key, f"an existing scenario file (relative to the spec or to {SCENARIO_DIR})", name) from None
    return p, rig_config.read_config_file(p)


def _case(s: str, src: Path, i: int, raw: Any, sections: dict) -> tuple[Case, Optional[Path]]:
    key = f"cases[{i}]"
    if not isinstance(raw, dict):
        raise _err(s, key, "a mapping {name, scenario, duration_s, seed, speed, set}", raw)
    extra = set(raw) - set(CASE_KEYS)
    if extra:
        raise _err(s, key, "only " + ", ".join(CASE_KEYS), sorted(extra))
    name = raw.get("name", f"case{i}")
    if not isinstance(name, str) or not re.fullmatch(r"[A-Za-z0-9_.+=-]+", name):
        raise _err(s, f"{key}.name", "a name of letters, digits, _ . + = -", name)
    values: dict[str, float] = {}
    for pname, v in (raw.get("set") or {}).items():
        pname = str(pname)
        if nominal_value(sections, {}, pname) is None or pname.split(".")[0] not in ("plant", "limits", "sim"):
            raise _err(s, f"{key}.set.{pname}", "a number of the base config's plant, limits or sim section", pname)
        values[pname] = _number(s, f"{key}.set.{pname}", v)
    sc_path, scenario = None, None
    if "scenario" in raw:
        sc_path, scenario = _scenario_dict(s, f"{key}.scenario", src, raw["scenario"])
    if "speed" in raw:
        v = _number(s, f"{key}.speed", raw["speed"])
        values["plant.v"] = v
        if scenario is not None and scenario.get("speed"):
            scenario = dict(scenario, speed=[{"t": 0, "v": v}])      # the case's speed, constant
    duration = raw.get("duration_s")
    if duration is not None:
        duration = _number(s, f"{key}.duration_s", duration, positive=True)
    seed = _int(s, f"{key}.seed", raw.get("seed", 0), 0)
    return Case(name=name, values=values, scenario=scenario, duration_s=duration, seed=seed), sc_path


def _corners(s: str, src: Path, raw: Any, sections: dict) -> list[dict]:
    """Every combination of each corner parameter's ends (``{pct: P}``, ``{uniform: [lo, hi]}``,
    ``{identified: FILE}``: the 95 % interval's ends; ``{values: [...]}``: each value)."""
    if raw is None:
        return [{}]
    if not isinstance(raw, dict):
        raise _err(s, "corners", "a mapping of parameters to their ranges", raw)
    axes = []
    for name, dist in raw.items():
        name = str(name)
        nominal = nominal_value(sections, {}, name)
        if nominal is None or name.split(".")[0] not in ("plant", "limits", "sim"):
            raise _err(s, f"corners.{name}", "a number of the base config's plant, limits or sim section", name)
        if isinstance(dist, dict) and "identified" in dist and "as" not in dist:
            dist = dict(dist, **{"as": "uniform"})
        d = _distribution(src, name, dist, nominal, "lhs")
        levels = d.grid() if d.kind == "values" else dataclasses.replace(d, levels=d.levels or 2).grid()
        axes.append([(name, float(x)) for x in levels])
    return [dict(c) for c in itertools.product(*axes)]


def _criteria(s: str, raw: Any, cases: list[Case], sc_objs: dict, controlled) -> tuple[Criterion, ...]:
    if not isinstance(raw, dict) or not raw:
        raise _err(s, "criteria", "a mapping of criteria to {demand: D, objective: true|false}", raw)
    out = []
    for name, c in raw.items():
        key = f"criteria.{name}"
        name = str(name)
        if name not in LINEAR and name not in METRICS:
            raise _err(s, key, "a linear criterion (" + ", ".join(LINEAR) + ") or a simulated metric ("
                       + METRIC_NAMES + ")", name)
        if not isinstance(c, dict) or set(c) - {"demand", "objective"} or not c:
            raise _err(s, key, "{demand: D, objective: true|false}", c)
        demand = c.get("demand")
        if demand is not None:
            demand = _number(s, f"{key}.demand", demand)
        objective = c.get("objective", False)
        if not isinstance(objective, bool):
            raise _err(s, f"{key}.objective", "true or false", objective)
        if demand is None and not objective:
            raise _err(s, key, "a demand, or objective: true", c)
        linear = name in LINEAR
        if not linear:
            simulated = [k for k in cases if k.scenario is not None]
            if not simulated:
                raise _err(s, key, "a case with a scenario for a simulated criterion", name)
            for k in simulated:
                why = unavailable(name, sc_objs[k.name], controlled)
                if why:
                    raise _err(s, key, f"{why} (case {k.name})", name)
        out.append(Criterion(name=name, linear=linear, demand=demand, objective=objective))
    if not any(c.objective for c in out):
        raise _err(s, "criteria", "at least one criterion with objective: true")
    return tuple(out)


def _optimizer(s: str, raw: Any) -> Optimizer:
    if not isinstance(raw, dict):
        raise _err(s, "optimizer", "a mapping {method, population, generations, seed, start}", raw)
    extra = set(raw) - {"method", "population", "generations", "seed", "start"}
    if extra:
        raise _err(s, "optimizer", "only method, population, generations, seed, start", sorted(extra))
    method = raw.get("method", "nsga2")
    if method not in METHODS:
        raise _err(s, "optimizer.method", "one of " + ", ".join(METHODS), method)
    start = raw.get("start", "config")
    if start not in ("config", "none"):
        raise _err(s, "optimizer.start", "config (the first candidate is the base config's) or none", start)
    return Optimizer(method=method, population=_int(s, "optimizer.population", raw.get("population", 20), 2),
                     generations=_int(s, "optimizer.generations", raw.get("generations", 10), 1),
                     seed=_int(s, "optimizer.seed", raw.get("seed", 0), 0), start=start)


def load_spec(path: str | Path) -> SynthesisSpec:
    """Read and validate a synthesis spec; every case's config at the tunables' bounds and
    every case's scenario are loaded here (one line naming the file and key on a refusal)."""
    src = Path(path).resolve()
    if not src.is_file():
        raise _err(str(path), "", "an existing synthesis spec file")
    raw = rig_config.read_config_file(src)
    s = str(src)
    for k in raw:
        if k not in TOP_KEYS:
            raise _err(s, str(k), "a known key (" + ", ".join(TOP_KEYS) + ")")
    base = raw.get("base", {})
    if not isinstance(base, dict) or set(base) - {"config", "settle_s"}:
        raise _err(s, "base", "a mapping {config, settle_s}", base)
    cfg_path = _resolve(src, str(base.get("config", "sim.yaml")), rig_config.CONFIG_DIR, "config")
    settle = _number(s, "base.settle_s", base.get("settle_s", 0.0), nonneg=True)
    cfg = rig_config.load(cfg_path)
    if cfg.devices.ft.poller == "process":
        raise _err(str(cfg_path), "devices.ft.poller", "'inline' or 'thread' for a synthesis (Dask's daemonic "
                   "workers cannot start the 'process' poller's child)", "process")
    sections = {k: v for k, (v, _) in rig_config.load_sections(cfg_path).items()}
    tunables = _tunables(s, raw.get("tunables"), sections)
    cases_raw = raw.get("cases")
    if not isinstance(cases_raw, list) or not cases_raw:
        raise _err(s, "cases", "a list of at least one case", cases_raw)
    corners = _corners(s, src, raw.get("corners"), sections)
    cases: list[Case] = []
    sc_objs: dict = {}
    for i, c in enumerate(cases_raw):
        case, _ = _case(s, src, i, c, sections)
        for corner in corners:
            name = case.name + "".join(f"@{n.removeprefix('plant.')}={v:.4g}" for n, v in corner.items())
            cases.append(dataclasses.replace(case, name=name, values={**case.values, **corner}))
    if len({c.name for c in cases}) != len(cases):
        raise _err(s, "cases", "cases with distinct names", [c.name for c in cases])
    _check_cases(s, cfg_path, sections, tunables, cases, sc_objs)
    criteria = _criteria(s, raw.get("criteria"), cases, sc_objs, cfg.controlled)
    name = raw.get("name", src.stem)
    if not isinstance(name, str) or not re.fullmatch(r"[A-Za-z0-9_.-]+", name):
        raise _err(s, "name", "a name of letters, digits, _ . -", name)
    return SynthesisSpec(name=name, source=s, description=str(raw.get("description", "")), config=cfg_path,
                         settle_s=settle, tunables=tunables, cases=tuple(cases), criteria=criteria,
                         optimizer=_optimizer(s, raw.get("optimizer", {})))


def _check_cases(s: str, cfg_path: Path, sections: dict, tunables, cases: list[Case], sc_objs: dict) -> None:
    """Each case's scenario loads; each case's config loads with every tunable at its lower
    and at its upper bound (the config's rules, the hardware ceilings)."""
    base = materialize.config_base(cfg_path, {})
    with tempfile.TemporaryDirectory(prefix="rig-synthesize-check-") as tmp:
        d = Path(tmp)
        for j, case in enumerate(cases):
            if case.scenario is not None:
                p = d / f"case-{j}.yaml"
                p.write_text(yaml.safe_dump(case.scenario, sort_keys=False))
                try:
                    sc_objs[case.name] = load_scenario(p)
                except ConfigError as e:
                    raise _err(s, f"cases.{case.name}.scenario", f"a valid scenario ({e})") from None
            for end in ("lo", "hi"):
                values = {**case.values, **{t.name: getattr(t, end) for t in tunables}}
                cfg, _ = materialize.write_run_files(d, base, values, j, d)
                try:
                    rig_config.load(cfg)
                except ConfigError as e:
                    raise _err(s, f"cases.{case.name}", f"values the config accepts with the tunables at their "
                               f"{'lower' if end == 'lo' else 'upper'} bounds ({e.key_path}: expected {e.expected})",
                               e.got) from None
