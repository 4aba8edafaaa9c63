"""The house's floors, as contracts on the import graph (every ``import`` statement,
module level or inside a function; the registry's ``importlib`` strings are not imports):

- core (``rig_runtime`` without ``rig_runtime.app``) imports only the core;
- ``drivers`` import the core and each other;
- ``sim_backend`` imports the core, itself and the drivers' codec modules only;
- the application (``rig_runtime.app``) sits on top;
- no import cycle between modules;
- the heavy libraries stay where they are used: in the core only the analysis imports scipy
  and only the log writer (``logfile``, run by the recording sidecar) imports h5py; no core
  module, driver or simulator module imports matplotlib. The loop module reaches none of
  them through any import (module level or in a function), and what a run's process imports
  at start-up (the ``rig`` entry point) reaches no h5py or matplotlib at module level.
  App-only modules (pre-run checks, step figures, log reading and export) live in
  ``rig_runtime.app``. tests/test_floors.py checks the same from running processes.
"""

from __future__ import annotations

import ast
import functools
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
PACKAGES = ("rig_runtime", "drivers", "sim_backend")
# the drivers' wire codecs (no I/O), which the simulator shares with the drivers
CODEC_MODULES = {"drivers.cia402", "drivers.optoncdt", "drivers.slcan_codec", "drivers.ft_modbus",
                 "drivers.ft_codec"}
# heavy third-party libraries and the only non-application modules that may import them
HEAVY = {"scipy": {"rig_runtime.analysis"}, "h5py": {"rig_runtime.logfile"}, "matplotlib": set()}
APP_ONLY = ("preflight", "metrics", "export")


def _modules() -> dict[str, Path]:
    out = {}
    for pkg in PACKAGES:
        for p in (ROOT / pkg).rglob("*.py"):
            parts = p.relative_to(ROOT).with_suffix("").parts
            name = ".".join(parts[:-1] if parts[-1] == "__init__" else parts)
            out[name] = p
    return out


def _tree(path: Path) -> ast.Module:
    """The module's syntax tree, parsed once per file version (every test here reads the
    whole tree of modules, some of them several times; nothing changes a tree)."""
    st = path.stat()
    return _parsed(path, st.st_mtime_ns, st.st_size)


@functools.lru_cache(maxsize=None)
def _parsed(path: Path, mtime_ns: int, size: int) -> ast.Module:
    return ast.parse(path.read_text(), str(path))


def _import_nodes(tree: ast.Module, toplevel: bool) -> list[ast.Import | ast.ImportFrom]:
    """Every import statement, or (``toplevel``) those that run when the module is imported:
    not inside a function, not under ``if TYPE_CHECKING:``."""
    if not toplevel:
        return [n for n in ast.walk(tree) if isinstance(n, (ast.Import, ast.ImportFrom))]
    out: list = []
    todo: list[ast.AST] = list(tree.body)
    while todo:
        n = todo.pop()
        if isinstance(n, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda)):
            continue
        if isinstance(n, ast.If) and isinstance(n.test, ast.Name) and n.test.id == "TYPE_CHECKING":
            todo.extend(n.orelse)
            continue
        if isinstance(n, (ast.Import, ast.ImportFrom)):
            out.append(n)
        todo.extend(ast.iter_child_nodes(n))
    return out


def _imports(name: str, path: Path, known: set[str], *, toplevel: bool = False,
             external: bool = False) -> set[str]:
    """The project modules ``name`` imports (a ``from pkg import mod`` names the module);
    with ``external``, the top-level names of the other (third-party) packages it imports."""
    is_pkg = path.name == "__init__.py"
    base = name.split(".") if is_pkg else name.split(".")[:-1]
    found = set()
    for node in _import_nodes(_tree(path), toplevel):
        if external:
            if isinstance(node, ast.Import):
                found |= {a.name.split(".")[0] for a in node.names}
            elif not node.level and node.module:
                found.add(node.module.split(".")[0])
            continue
        if isinstance(node, ast.Import):
            targets = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                mod = ".".join(base[:len(base) - node.level + 1] + ([node.module] if node.module else []))
            else:
                mod = node.module or ""
            targets = [f"{mod}.{a.name}" if f"{mod}.{a.name}" in known else mod for a in node.names]
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


def graph(*, toplevel: bool = False) -> dict[str, set[str]]:
    mods = _modules()
    known = set(mods)
    return {m: _imports(m, p, known, toplevel=toplevel) for m, p in mods.items()}


def third_party(*, toplevel: bool = False) -> dict[str, set[str]]:
    """Each module's imported third-party (and standard-library) top-level package names."""
    mods = _modules()
    return {m: _imports(m, p, set(mods), toplevel=toplevel, external=True) for m, p in mods.items()}


def reach(g: dict[str, set[str]], start: str) -> set[str]:
    """``start`` and every module it imports, directly or through others."""
    seen, todo = set(), [start]
    while todo:
        m = todo.pop()
        if m not in seen:
            seen.add(m)
            todo.extend(g.get(m, ()))
    return seen


def heavy_misplaced(ext: dict[str, set[str]]) -> list[str]:
    """Imports of a HEAVY library by a module outside the application that may not import it."""
    return sorted(f"{m} imports {lib}" for m, libs in ext.items() if floor(m) != "app"
                  for lib in libs & set(HEAVY) if m not in HEAVY[lib])


def heavy_reached(g: dict[str, set[str]], ext: dict[str, set[str]], start: str, libs) -> list[str]:
    """The modules ``start`` reaches in ``g`` that import one of ``libs``."""
    return sorted(f"{m} imports {lib}" for m in reach(g, start) for lib in ext.get(m, set()) & set(libs))


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


def test_heavy_libraries_stay_where_they_are_used():
    assert heavy_misplaced(third_party()) == []


def test_the_loop_module_reaches_no_scipy_h5py_or_matplotlib():
    """Through any import, at module level or in a function (the cheap gain check is
    ``gains.admissible``; the stability gate, ``tuning.check``, is not the loop's)."""
    assert heavy_reached(graph(), third_party(), "rig_runtime.loop", HEAVY) == []


def test_a_runs_process_imports_no_h5py_or_matplotlib_at_start_up():
    """What ``rig`` (the run's process) imports when it starts, and the recorder's loop side:
    module-level imports only (the sidecar imports the log writer in its own process; log
    reading and plots import them in the commands that need them, after a run). scipy may
    come with the pre-run stability gate (docs/performance.md)."""
    g, ext = graph(toplevel=True), third_party(toplevel=True)
    for start in ("rig_runtime.app.entry", "rig_runtime.app.cli", "rig_runtime.app.runner", "rig_runtime.recorder"):
        assert heavy_reached(g, ext, start, ("h5py", "matplotlib")) == [], start


def test_app_only_modules_live_in_the_application():
    mods = _modules()
    assert [m for m in APP_ONLY if f"rig_runtime.{m}" in mods] == []
    assert all(f"rig_runtime.app.{m}" in mods for m in APP_ONLY)


def test_the_heavy_contracts_catch_a_misplaced_import():
    g, ext = graph(), third_party()
    ext["rig_runtime.geometry"] = ext["rig_runtime.geometry"] | {"scipy"}         # a core module takes scipy
    assert heavy_misplaced(ext) == ["rig_runtime.geometry imports scipy"]
    g["rig_runtime.loop"] = g["rig_runtime.loop"] | {"rig_runtime.tuning"}        # loop -> the stability gate
    assert "rig_runtime.analysis imports scipy" in heavy_reached(g, ext, "rig_runtime.loop", HEAVY)
    top, text = graph(toplevel=True), third_party(toplevel=True)
    top["rig_runtime.recorder"] = top["rig_runtime.recorder"] | {"rig_runtime.logfile"}
    assert heavy_reached(top, text, "rig_runtime.app.cli", ("h5py",)) == ["rig_runtime.logfile imports h5py"]
    top["rig_runtime.app.commands"] = top["rig_runtime.app.commands"] | {"rig_runtime.app.export"}
    assert "rig_runtime.app.export imports h5py" in heavy_reached(top, text, "rig_runtime.app.cli", ("h5py",))


def test_the_contracts_catch_a_forbidden_import_and_a_cycle():
    g = graph()
    g["rig_runtime.loop"] = g["rig_runtime.loop"] | {"drivers.canopen402"}        # core -> drivers
    g["drivers.laser"] = g["drivers.laser"] | {"sim_backend.virtual_laser"}        # drivers -> simulation
    g["sim_backend.rig"] = g["sim_backend.rig"] | {"rig_runtime.app.runner"}       # simulation -> application
    g["sim_backend.rig"] |= {"drivers.canopen402"}                                  # simulation -> a driver
    g["rig_runtime.recorder"] = g["rig_runtime.recorder"] | {"rig_runtime.app.export"}  # core -> an app-only module
    v = violations(g)
    assert any(s.startswith("rig_runtime.loop -> drivers.canopen402") for s in v)
    assert any(s.startswith("drivers.laser -> sim_backend.virtual_laser") for s in v)
    assert any(s.startswith("sim_backend.rig -> rig_runtime.app.runner") for s in v)
    assert any(s.startswith("sim_backend.rig -> drivers.canopen402") for s in v)
    assert any(s.startswith("rig_runtime.recorder -> rig_runtime.app.export") for s in v)
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


def test_module_level_and_third_party_imports(tmp_path):
    p = tmp_path / "m.py"
    p.write_text("from typing import TYPE_CHECKING\nimport numpy as np\nfrom . import x\n"
                 "if TYPE_CHECKING:\n    import h5py\n    from pkg import y\n"
                 "try:\n    import yaml\nexcept ImportError:\n    pass\n"
                 "class C:\n    import json\n"
                 "def f():\n    import scipy.linalg\n    from pkg import z\n")
    known = {"pkg", "pkg.x", "pkg.y", "pkg.z", "pkg.m"}
    assert _imports("pkg.m", p, known) == {"pkg.x", "pkg.y", "pkg.z"}
    assert _imports("pkg.m", p, known, toplevel=True) == {"pkg.x"}
    assert _imports("pkg.m", p, known, external=True) == {"typing", "numpy", "h5py", "yaml", "json", "scipy", "pkg"}
    assert _imports("pkg.m", p, known, toplevel=True, external=True) == {"typing", "numpy", "yaml", "json"}
