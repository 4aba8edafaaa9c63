"""The campaign spec (YAML): what to run, what to vary and how, how to sample, what passes.
Validated before anything runs; every refusal is one :class:`ConfigError` naming the spec
file and key (exit 2). The parameters are checked against the base config here (names,
values); :func:`.materialize.check_extremes` then checks their ranges against the config's
rules and the hardware ceilings. docs/campaigns.md describes the format."""

from __future__ import annotations

import dataclasses
import json
import math
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Optional

from rig_runtime import config as rig_config
from rig_runtime.errors import ConfigError
from rig_runtime.scenario import SCENARIO_DIR

from . import paths
from .distributions import Distribution
from .outcome import METRIC_NAMES, METRICS, unavailable

METHODS = ("sobol", "lhs", "random", "grid", "saltelli")
KEEP_LOGS = ("none", "failing", "all")
TOP_KEYS = ("name", "description", "base", "parameters", "seed", "design", "pass", "keep_logs", "sensitivity")
DIST_KEYS = ("uniform", "pct", "normal", "values", "identified")
SCENARIO_GAIN = "scenario.disturbance_gain"        # multiplies F_y and M_z of every disturbance
_DIST_RE = re.compile(r"^scenario\.disturbances\[(\d+)\]\.(F_y|M_z)$")
# config sections whose numbers may be varied (the plant per carrier as the config has it,
# the gains, the limits within the hardware ceilings, the simulated sensors)
VARIABLE_SECTIONS = ("plant", "controller", "limits", "sim")


@dataclass(frozen=True, kw_only=True)
class Parameter:
    name: str                   # a dotted key path: plant.delta0, controller.pipd.K_P_y, sim.laser_noise_m, …
    dist: Distribution
    nominal: float              # the base config's (or scenario's) value


@dataclass(frozen=True, kw_only=True)
class Design:
    method: str
    n: int                      # samples (sobol/lhs/random), base samples (saltelli), ignored (grid)
    seed: int


@dataclass(frozen=True, kw_only=True)
class Spec:
    name: str
    source: str                 # the spec file
    description: str
    config: Path                # the base config file
    scenario: Path              # the base scenario file
    duration_s: Optional[float]
    settle_s: float             # the y, psi metrics start this long after RUNNING began
    parameters: tuple[Parameter, ...]
    seed_per_run: bool          # True: run i has seed seed_value + i; False: every run seed_value
    seed_value: int
    design: Design
    criteria: dict[str, float]  # metric -> upper bound
    no_fault: bool
    keep_logs: str
    sensitivity: tuple[str, ...]

    def to_json(self) -> dict:
        d = dataclasses.asdict(self)
        d["config"], d["scenario"] = str(self.config), str(self.scenario)
        return d


def _err(src: str, key: str, expected: str, got: Any = None) -> ConfigError:
    return ConfigError(src, key, expected, got)


def _number(src: str, key: str, v: Any, *, positive: bool = False, nonneg: bool = False) -> float:
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
        raise _err(src, key, "a finite number", v)
    if positive and not v > 0:
        raise _err(src, key, "a number > 0", v)
    if nonneg and v < 0:
        raise _err(src, key, "a number >= 0", v)
    return float(v)


def _resolve(src: Path, name: str, default_dir: Path, what: str) -> Path:
    p = Path(name)
    if not p.suffix:
        p = default_dir / f"{name}.yaml"
    for cand in ([p] if p.is_absolute() else [src.parent / p, default_dir / p]):
        if cand.exists():
            return cand.resolve()
    raise _err(str(src), f"base.{what}", f"an existing {what} file (relative to the spec or to {default_dir})", name)


def nominal_value(sections: dict, scenario: dict, name: str) -> Optional[float]:
    """The base value of a parameter, or None if the name is not a number of the base
    config or scenario (a carrier's name, ``plant.front.delta0``: that carrier's value,
    :mod:`.paths`). ``sim.*`` falls back to the simulator's defaults."""
    if name == SCENARIO_GAIN:
        return 1.0
    m = _DIST_RE.match(name)
    if m:
        ds = scenario.get("disturbances") or []
        i = int(m.group(1))
        return float(ds[i].get(m.group(2), 0.0)) if i < len(ds) and isinstance(ds[i], dict) else None
    if name.split(".")[0] not in VARIABLE_SECTIONS:
        return None
    v = paths.nominal(sections, name)
    if v is None and name.startswith("sim."):
        from sim_backend.simconfig import SimConfig
        f = {x.name: x for x in dataclasses.fields(SimConfig)}.get(name[4:])
        v = f.default if f is not None and f.default is not dataclasses.MISSING else None
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        return None
    return float(v)


def _identified(src: Path, key: str, path: str, pname: str, as_: str) -> Distribution:
    """A ``rig identify --json`` result: the estimate and its 95 % interval as a normal
    (sd = half-width / 1.96) or as a uniform over the interval."""
    p = Path(path) if Path(path).is_absolute() else src.parent / path
    try:
        data = json.loads(p.read_text())
        entry = data["parameters"][pname]
        value, (lo, hi) = float(entry["value"]), (float(entry["ci95"][0]), float(entry["ci95"][1]))
    except OSError as e:
        raise _err(str(src), key, f"a readable `rig identify --json` file ({e.strerror})", path) from None
    except (ValueError, KeyError, TypeError, IndexError):
        raise _err(str(src), key, f"a `rig identify --json` result with parameters.{pname}.value and ci95", path) from None
    if not (math.isfinite(lo) and math.isfinite(hi) and lo <= value <= hi):
        raise _err(str(src), key, "an identified value inside a finite 95 % interval", [lo, value, hi])
    if as_ == "uniform":
        return Distribution(kind="uniform", lo=lo, hi=hi)
    return Distribution(kind="normal", mean=value, sd=(hi - lo) / (2 * 1.96))


def _distribution(src: Path, name: str, raw: Any, nominal: float, method: str) -> Distribution:
    key = f"parameters.{name}"
    s = str(src)
    if not isinstance(raw, dict):
        raise _err(s, key, "a mapping with one of " + ", ".join(DIST_KEYS), raw)
    kinds = [k for k in raw if k in DIST_KEYS]
    extra = [k for k in raw if k not in DIST_KEYS + ("levels", "as")]
    if len(kinds) != 1 or extra:
        raise _err(s, key, "exactly one of " + ", ".join(DIST_KEYS) + " (and optionally levels)", sorted(raw))
    kind, v = kinds[0], raw[kinds[0]]
    levels = raw.get("levels")
    if levels is not None and (isinstance(levels, bool) or not isinstance(levels, int) or levels < 2):
        raise _err(s, f"{key}.levels", "an integer >= 2", levels)
    if kind == "uniform":
        if not isinstance(v, list) or len(v) != 2:
            raise _err(s, f"{key}.uniform", "[lo, hi]", v)
        lo, hi = (_number(s, f"{key}.uniform", x) for x in v)
        if not lo < hi:
            raise _err(s, f"{key}.uniform", "lo < hi", v)
        d = Distribution(kind="uniform", lo=lo, hi=hi, levels=levels)
    elif kind == "pct":
        p = _number(s, f"{key}.pct", v, positive=True)
        if nominal == 0:
            raise _err(s, f"{key}.pct", "a parameter whose configured value is not 0 (use uniform)", nominal)
        a, b = sorted((nominal * (1 - p / 100), nominal * (1 + p / 100)))
        d = Distribution(kind="uniform", lo=a, hi=b, levels=levels)
    elif kind == "normal":
        if not isinstance(v, dict) or set(v) != {"mean", "sd"}:
            raise _err(s, f"{key}.normal", "{mean: M, sd: S}", v)
        mean = _number(s, f"{key}.normal.mean", v["mean"])
        sd = _number(s, f"{key}.normal.sd", v["sd"])
        if sd < 0:
            raise _err(s, f"{key}.normal.sd", "a standard deviation >= 0", sd)
        d = Distribution(kind="normal", mean=mean, sd=sd, levels=levels)
    elif kind == "values":
        if not isinstance(v, list) or not v:
            raise _err(s, f"{key}.values", "a non-empty list of numbers", v)
        d = Distribution(kind="values", values=tuple(_number(s, f"{key}.values", x) for x in v))
    else:
        if not isinstance(v, str):
            raise _err(s, f"{key}.identified", "the path of a `rig identify --json` result", v)
        as_ = raw.get("as", "normal")
        if as_ not in ("normal", "uniform"):
            raise _err(s, f"{key}.as", "normal or uniform", as_)
        if not name.startswith("plant."):
            raise _err(s, key, "a plant parameter for an identified distribution", name)
        d = _identified(src, f"{key}.identified", v, name.split(".")[-1], as_)   # plant.front.K: K
    if method == "grid" and d.kind != "values" and d.levels is None:
        raise _err(s, f"{key}.levels", "levels (points per axis) for a grid design, or values")
    return d


def _design(s: str, raw: Any) -> Design:
    if not isinstance(raw, dict):
        raise _err(s, "design", "a mapping {method, n, seed}", raw)
    unknown = set(raw) - {"method", "n", "seed"}
    if unknown:
        raise _err(s, "design", "only method, n, seed", sorted(unknown))
    method = raw.get("method")
    if method not in METHODS:
        raise _err(s, "design.method", "one of " + ", ".join(METHODS), method)
    n = raw.get("n", 0 if method == "grid" else None)
    if isinstance(n, bool) or not isinstance(n, int) or (method != "grid" and n < 1):
        raise _err(s, "design.n", "an integer >= 1 (samples; base samples for saltelli)", n)
    if method in ("sobol", "saltelli") and n & (n - 1):
        raise _err(s, "design.n", f"a power of 2 for a {method} design (its balance properties need it)", n)
    seed = raw.get("seed", 0)
    if isinstance(seed, bool) or not isinstance(seed, int) or seed < 0:
        raise _err(s, "design.seed", "an integer >= 0", seed)
    return Design(method=method, n=n, seed=seed)


def load_spec(path: str | Path) -> Spec:
    """Read and validate a campaign spec (errors: one line naming the file and key)."""
    src = Path(path).resolve()
    if not src.is_file():
        raise _err(str(path), "", "an existing campaign spec file")
    raw = rig_config.read_config_file(src)
    s = str(src)
    for k in raw:
        if k not in TOP_KEYS:
            raise _err(s, str(k), "a known key (" + ", ".join(TOP_KEYS) + ")")
    base = raw.get("base")
    if not isinstance(base, dict) or "scenario" not in base:
        raise _err(s, "base", "a mapping {config, scenario, duration_s}", base)
    if set(base) - {"config", "scenario", "duration_s", "settle_s"}:
        raise _err(s, "base", "only config, scenario, duration_s, settle_s", sorted(base))
    settle = _number(s, "base.settle_s", base.get("settle_s", 0.0), nonneg=True)
    cfg_path = _resolve(src, str(base.get("config", "sim.yaml")), rig_config.CONFIG_DIR, "config")
    sc_path = _resolve(src, str(base["scenario"]), SCENARIO_DIR, "scenario")
    duration = base.get("duration_s")
    if duration is not None:
        duration = _number(s, "base.duration_s", duration, positive=True)
    cfg = rig_config.load(cfg_path)                 # the base itself must be valid
    if cfg.devices.ft.poller == "process":
        # Dask's worker processes are daemonic: a run that starts a multiprocessing child fails there
        raise _err(str(cfg_path), "devices.ft.poller", "'inline' or 'thread' for a campaign (the 'process' poller "
                   "starts a multiprocessing child, which Dask's daemonic workers cannot have)", "process")
    sections = {k: v for k, (v, _) in rig_config.load_sections(cfg_path).items()}
    scenario = rig_config.read_config_file(sc_path)
    design = _design(s, raw.get("design"))
    params_raw = raw.get("parameters")
    if not isinstance(params_raw, dict) or not params_raw:
        raise _err(s, "parameters", "a mapping of at least one parameter to its distribution", params_raw)
    params = []
    for name, dist in params_raw.items():
        nominal = nominal_value(sections, scenario, str(name))
        if nominal is None:
            raise _err(s, f"parameters.{name}", "a number of the base config (plant.*, controller.*, limits.*, sim.*) "
                       f"or {SCENARIO_GAIN} or scenario.disturbances[i].F_y|M_z (unknown parameter)", name)
        params.append(Parameter(name=str(name), dist=_distribution(src, str(name), dist, nominal, design.method),
                                nominal=nominal))
    if any(p.name == "plant.v" for p in params) and scenario.get("speed"):
        # the simulator follows the scenario's speed profile: plant.v would vary nothing
        raise _err(s, "parameters.plant.v", f"a scenario without a speed: profile (the profile of {sc_path.name} "
                   "sets the roller speed, so plant.v would vary nothing)", "plant.v")
    seed = raw.get("seed", {"per_run": 0})
    if isinstance(seed, dict) and set(seed) == {"per_run"} and isinstance(seed["per_run"], int) \
            and not isinstance(seed["per_run"], bool) and seed["per_run"] >= 0:
        per_run, seed_value = True, seed["per_run"]
    elif isinstance(seed, int) and not isinstance(seed, bool) and seed >= 0:
        per_run, seed_value = False, seed
    else:
        raise _err(s, "seed", "an integer >= 0 (every run that seed) or {per_run: BASE} (run i: BASE + i)", seed)
    crit = raw.get("pass", {"no_fault": True})
    if not isinstance(crit, dict) or not crit:
        raise _err(s, "pass", "a mapping of criteria (no_fault: true, METRIC: upper bound)", crit)
    no_fault = crit.get("no_fault", False)
    if not isinstance(no_fault, bool):
        raise _err(s, "pass.no_fault", "true or false", no_fault)
    from rig_runtime.scenario import load_scenario
    scenario_obj = load_scenario(sc_path)
    criteria = {}
    for k, v in crit.items():
        if k == "no_fault":
            continue
        if k not in METRICS:
            raise _err(s, f"pass.{k}", "a known metric (" + METRIC_NAMES + ")", k)
        why = unavailable(k, scenario_obj, cfg.controlled)
        if why:
            raise _err(s, f"pass.{k}", why, k)
        criteria[k] = _number(s, f"pass.{k}", v, nonneg=True)
    keep = raw.get("keep_logs", "failing")
    if keep not in KEEP_LOGS:
        raise _err(s, "keep_logs", "one of " + ", ".join(KEEP_LOGS), keep)
    sens = raw.get("sensitivity", [])
    if not isinstance(sens, list):
        raise _err(s, "sensitivity", "a list of metrics (or pass)", sens)
    for m in sens:
        if m != "pass" and m not in METRICS:
            raise _err(s, "sensitivity", "known metrics (" + METRIC_NAMES + ") or pass", m)
    if sens and design.method != "saltelli":
        raise _err(s, "sensitivity", "a saltelli design for Sobol indices (design.method: saltelli)", design.method)
    name = raw.get("name", src.stem)
    if not isinstance(name, str) or not re.fullmatch(r"[A-Za-z0-9_.-]+", name):
        raise _err(s, "name", "a name of letters, digits, _ . -", name)
    return Spec(name=name, source=s, description=str(raw.get("description", "")), config=cfg_path,
                scenario=sc_path, duration_s=duration, settle_s=settle, parameters=tuple(params), seed_per_run=per_run,
                seed_value=seed_value, design=design, criteria=criteria, no_fault=no_fault, keep_logs=keep,
                sensitivity=tuple(sens))
