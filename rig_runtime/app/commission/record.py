"""The commissioning record: one JSON line per ``rig commission`` (the config's hash, date,
result, the checks run), so that ``rig run`` can warn when a config has no passed
commissioning on record. The record file is ``$RIG_COMMISSION_RECORD``, else
``$XDG_STATE_HOME/rig-runtime/commissioning.jsonl`` (``~/.local/state/…``)."""

from __future__ import annotations

import datetime as _dt
import hashlib
import json
import os
from pathlib import Path
from typing import Optional, Sequence

from ... import schema
from ...config import RigConfig
from . import CHECKS

# sections of the config that say what the rig is and how it is wired (the simulator's
# `sim:` section and the config's file name are not part of it)
_WIRING_SECTIONS = ("devices", "geometry", "plant", "limits", "controlled")


def default_path() -> Path:
    env = os.environ.get("RIG_COMMISSION_RECORD")
    if env:
        return Path(env)
    state = os.environ.get("XDG_STATE_HOME") or str(Path.home() / ".local" / "state")
    return Path(state) / "rig-runtime" / "commissioning.jsonl"


def config_hash(cfg: RigConfig) -> str:
    d = schema.to_dict(cfg)
    data = {k: d.get(k) for k in _WIRING_SECTIONS}
    return hashlib.sha256(json.dumps(data, sort_keys=True, default=str).encode()).hexdigest()[:16]


def append(cfg: RigConfig, passed: bool, checks: Sequence[str], path: Optional[Path] = None) -> Path:
    p = Path(path) if path is not None else default_path()
    p.parent.mkdir(parents=True, exist_ok=True)
    line = {"config_hash": config_hash(cfg), "config_source": cfg.source,
            "date": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
            "result": "pass" if passed else "fail", "checks": list(checks)}
    with open(p, "a") as f:
        f.write(json.dumps(line) + "\n")
    return p


def passed_on_record(cfg: RigConfig, path: Optional[Path] = None) -> bool:
    """Whether a commissioning with every check passed is on record for this config."""
    p = Path(path) if path is not None else default_path()
    try:
        lines = p.read_text().splitlines()
    except OSError:
        return False
    h = config_hash(cfg)
    for ln in lines:
        try:
            r = json.loads(ln)
        except ValueError:
            continue
        if r.get("config_hash") == h and r.get("result") == "pass" and set(CHECKS) <= set(r.get("checks", ())):
            return True
    return False
