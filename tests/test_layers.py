"""The house's floors, as contracts on the import graph (every ``import`` statement,
module level or inside a function; the registry's ``importlib`` strings are not imports):

- core (``rig_runtime`` without ``rig_runtime.app``) imports only the core;
- ``drivers`` import the core and each other;
- ``sim_backend`` imports the core, itself and the drivers' codec modules only;
- the application (``rig_runtime.app``) sits on top;
- no import cycle between modules.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
PACKAGES = ("rig_runtime", "drivers", "sim_backend")
# the drivers' wire codecs (no I/O), which the simulator shares with the drivers
CODEC_MODULES = {"drivers.cia402", "drivers.optoncdt", "drivers.slcan_codec", "drivers.ft_modbus",
                 "drivers.ft_codec"}


def _modules() -> dict[str, Path]:
    out = {}
    for pkg in PACKAGES:
        for p in (ROOT / pkg).rglob("*.py"):
            parts = p.relative_to(ROOT).with_suffix("").parts
            name = ".".join(parts[:-1] if parts[-1] == "__init__" else parts)
            out[name] = p
    return out


def _imports(name: str, path: Path, known: set[str]) -> set[str]:
    """The project modules ``name`` imports (a ``from pkg import mod`` names the module)."""
    is_pkg = path.name == "__init__.py"
    base = name.split(".") if is_pkg else name.split(".")[:-1]
    found = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            targets = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                mod = ".".join(base[:len(base) - node.level + 1] + ([node.module] if node.module else []))
            else:
                mod = node.module or ""
            targets = [f"{mod}.{a.name}" if f"{mod}.{a.name}" in known else mod for a in node.names]
        else:
            continue
        for t in targets:
            while t and t not in known:
                t = t.rpartition(".")[0]
            if t and t != name:
                found.add(t)
    return found


def floor(module: str) -> str:
    if module in ("rig_runtime.app", "rig_runtime.__main__") or module.startswith("rig_runtime.app."):
        return "app"
    return module.split(".")[0].replace("rig_runtime", "core")


def allowed(src: str, dst: str) -> bool:
    """May module ``src`` import module ``dst``?"""
    a, b = floor(src), floor(dst)
    if a == "app" or b == "core" or a == b:
        return True
    if a == "sim_backend" and b == "drivers":
        return dst in CODEC_MODULES
    return False


def graph() -> dict[str, set[str]]:
    mods = _modules()
    known = set(mods)
    return {m: _imports(m, p, known) for m, p in mods.items()}


def violations(g: dict[str, set[str]]) -> list[str]:
    return sorted(f"{s} -> {d} ({floor(s)} may not import {floor(d)})"
                  for s, ds in g.items() for d in ds if not allowed(s, d))


def cycles(g: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components with more than one module (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on: set[str] = set()
    out: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v); on.add(v)
        for w in g.get(v, ()):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop(); on.discard(w); comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                out.append(sorted(comp))

    for v in sorted(g):
        if v not in index:
            visit(v)
    return out


def test_floors_hold():
    assert violations(graph()) == []


def test_no_import_cycles():
    assert cycles(graph()) == []


def test_the_contracts_catch_a_forbidden_import_and_a_cycle():
    g = graph()
    g["rig_runtime.loop"] = g["rig_runtime.loop"] | {"drivers.canopen402"}        # core -> drivers
    g["drivers.laser"] = g["drivers.laser"] | {"sim_backend.virtual_laser"}        # drivers -> simulation
    g["sim_backend.rig"] = g["sim_backend.rig"] | {"rig_runtime.app.runner"}       # simulation -> application
    g["sim_backend.rig"] |= {"drivers.canopen402"}                                  # simulation -> a driver
    v = violations(g)
    assert any(s.startswith("rig_runtime.loop -> drivers.canopen402") for s in v)
    assert any(s.startswith("drivers.laser -> sim_backend.virtual_laser") for s in v)
    assert any(s.startswith("sim_backend.rig -> rig_runtime.app.runner") for s in v)
    assert any(s.startswith("sim_backend.rig -> drivers.canopen402") for s in v)
    g["rig_runtime.geometry"] = g["rig_runtime.geometry"] | {"rig_runtime.loop"}   # loop imports geometry
    assert any({"rig_runtime.geometry", "rig_runtime.loop"} <= set(c) for c in cycles(g))


@pytest.mark.parametrize("src, expected", [
    ("from . import x", {"pkg.x"}),
    ("from .x import y", {"pkg.x"}),
    ("import pkg.x.deep", {"pkg.x"}),
    ("def f():\n    from pkg import x", {"pkg.x"}),
])
def test_import_resolution(tmp_path, src, expected):
    p = tmp_path / "m.py"
    p.write_text(src)
    assert _imports("pkg.m", p, {"pkg", "pkg.x", "pkg.m"}) == expected
