"""The ``plant:`` fragment written by ``rig identify --write``: the configured plant with every
identified value replaced and marked IDENTIFIED (date, logs, residual of its fit)."""

from __future__ import annotations

import datetime as _dt
from pathlib import Path

from rig_runtime.config import Plant as PlantParams
from rig_runtime.errors import ConfigError

_ORDER = ("v", "b", "r0", "delta0", "l0", "y_off", "c11", "J_x", "k_tau", "omega0", "K", "D_min", "D_max",
          "c_udot_max", "u_filter_hz", "psi_off")


def render(P: PlantParams, identified: dict, logs: list[str], when: str | None = None) -> str:
    """``identified``: {name: (value, residual_rms, step)} with dotted names for bouc_wen."""
    when = when or _dt.datetime.now(_dt.timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
    lines = [f"# Plant identified by `rig identify` on {when}",
             "# from: " + ", ".join(logs),
             "# Values without IDENTIFIED are the configured ones (not identifiable from these experiments).",
             "plant:"]

    def line(key: str, value, indent: str, name: str) -> str:
        s = f"{indent}{key}: {value!r}"
        if name in identified:
            v, rms, step = identified[name]
            s = f"{indent}{key}: {v:.6g}"
            s += f"   # IDENTIFIED {when} ({step}, residual RMS {rms:.3g})"
        return s
    for k in _ORDER:
        lines.append(line(k, getattr(P, k), "  ", k))
    bw = P.bouc_wen
    if bw is not None or any(k.startswith("bouc_wen.") for k in identified):
        lines.append("  bouc_wen:")
        for k in ("a", "A", "beta", "gamma", "n"):
            lines.append(line(k, getattr(bw, k) if bw is not None else (1.0 if k == "A" else 1), "    ", f"bouc_wen.{k}"))
    lines.append(f"  front_contact: {str(P.front_contact).lower()}")
    return "\n".join(lines) + "\n"


def write(path: str | Path, text: str) -> None:
    p = Path(path)
    if p.exists():
        raise ConfigError(str(p), "", "a new file (refusing to overwrite an existing plant file)")
    p.parent.mkdir(parents=True, exist_ok=True)
    p.write_text(text)
