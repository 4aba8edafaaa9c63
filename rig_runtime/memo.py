"""Pure functions of a configuration, computed once per process per configuration — and,
for the expensive ones a run's start needs, kept on disk across processes.

The stability gate, the coupled analysis (``app/preflight.py``) and the drive-outage table
(``loop.py``) depend on the config alone and cost tens to hundreds of milliseconds for a
vehicle config; a run asks for the gate twice (``rig check``'s checks and the runner's
own), and a warm worker (a campaign's, a test session's) runs the same config again and again. The key is the arguments' ``repr``:
a config is a tree of frozen dataclasses whose repr shows every field (none is hidden), so
two configs share a result only if every value is the same. A call that raises is not kept
(it raises again the next time). Callers treat a result as read-only (the analyses return
frozen dataclasses and tuples).

:func:`across_processes` keeps a result in the user's cache directory for the next process
(``rig dry-run`` from the shell, a test's ``rig`` process): the gate's verdict and the
observers' designs need scipy, whose import alone is a third of a dry run's start. The key
is every input's bytes: the arguments' ``repr``, the function's name, and the code version —
the bytes of every source file of this package, numpy's, scipy's and PyYAML's version
files, the Python version, the machine (name, architecture) and the BLAS thread settings. An entry
holds its whole key text and a SHA-256 of its payload; it is used only if both match and
its payload unpickles to the allowed classes alone — anything else (missing, corrupt,
another key, unreadable, an unwritable directory) is ignored and the function computed.
A call that raises is never stored. ``RIG_CACHE_DIR`` names the directory (empty: no disk
cache); default ``$XDG_CACHE_HOME/rig-runtime`` (``~/.cache/rig-runtime``). Each function
keeps at most ``MAX_ON_DISK`` entries, the least recently used removed (a read marks an
entry used). :func:`compute_only` turns the disk off for the process (``rig run`` on the
rig: what lets the power stages on is computed in the run's own process, never read);
:func:`without_disk` for a block of this thread (a campaign's run: a config never seen
again, its entries would only be written).
"""

from __future__ import annotations

import contextlib
import functools
import hashlib
import io
import os
import pickle
import sys
import tempfile
import threading
import time
from collections import OrderedDict
from pathlib import Path
from typing import Any, Callable, Iterable, Optional

MAX_KEPT = 32           # configs kept per function, the least recently used dropped
_MAGIC = b"rig-runtime memo 1\n"
_ENV_DIR = "RIG_CACHE_DIR"
_BLAS_ENV = ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS")
MAX_ON_DISK = 64        # entries per function on disk, the least recently used removed
_disk_on = True
_thread = threading.local()     # .off: this thread's block without the disk (without_disk)


def by_config(fn: Callable[..., Any], maxsize: int = MAX_KEPT) -> Callable[..., Any]:
    """``fn`` remembered by the ``repr`` of its positional arguments."""
    kept: OrderedDict[str, Any] = OrderedDict()
    lock = threading.Lock()

    @functools.wraps(fn)
    def call(*args: Any) -> Any:
        key = repr(args)
        with lock:
            if key in kept:
                kept.move_to_end(key)
                return kept[key]
        value = fn(*args)
        with lock:
            kept[key] = value
            while len(kept) > maxsize:
                kept.popitem(last=False)
        return value

    call.cache_clear = kept.clear       # type: ignore[attr-defined]
    return call


def compute_only() -> None:
    """This process reads and writes no disk cache from now on (every call computes)."""
    global _disk_on
    _disk_on = False


@contextlib.contextmanager
def without_disk():
    """In this block this thread reads and writes no disk cache (every call computes)."""
    was = getattr(_thread, "off", False)
    _thread.off = True
    try:
        yield
    finally:
        _thread.off = was


def cache_dir() -> Optional[Path]:
    """The disk cache's directory, None when turned off (``RIG_CACHE_DIR`` empty,
    :func:`compute_only`, :func:`without_disk`)."""
    if not _disk_on or getattr(_thread, "off", False):
        return None
    d = os.environ.get(_ENV_DIR)
    if d is not None:
        return Path(d) if d else None
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "rig-runtime"


def _version_file(package: str, file: str) -> bytes:
    """``package/file``'s bytes (numpy's and scipy's ``version.py``, PyYAML's ``__init__.py``
    carry their full version), found without importing the package; empty if not installed."""
    import importlib.util
    try:
        spec = importlib.util.find_spec(package)
    except (ImportError, ValueError):
        return b""
    if spec is None or not spec.submodule_search_locations:
        return b""
    for d in spec.submodule_search_locations:
        try:
            return (Path(d) / file).read_bytes()
        except OSError:
            continue
    return b""


def source_digest(root: Path) -> str:
    """SHA-256 of every ``.py`` file under ``root``, by relative path and bytes."""
    h = hashlib.sha256()
    for p in sorted(root.rglob("*.py")):
        h.update(str(p.relative_to(root)).encode() + b"\0")
        h.update(p.read_bytes() + b"\0")
    return h.hexdigest()


@functools.lru_cache(maxsize=1)
def code_version() -> str:
    """SHA-256 of what a cached result's computation could depend on besides its arguments:
    this package's source (every ``.py`` file, by relative path and bytes), numpy's,
    scipy's and PyYAML's version files, the Python version, the machine and the BLAS thread settings."""
    h = hashlib.sha256(source_digest(Path(__file__).resolve().parent).encode())
    for pkg, file in (("numpy", "version.py"), ("scipy", "version.py"), ("yaml", "__init__.py")):
        h.update(pkg.encode() + b"\0" + _version_file(pkg, file) + b"\0")
    u = os.uname()
    h.update(repr((sys.version, sys.implementation.cache_tag, u.sysname, u.nodename, u.machine,
                   [os.environ.get(v) for v in _BLAS_ENV])).encode())
    return h.hexdigest()


class _Unpickler(pickle.Unpickler):
    """Rebuilds only the classes a cached function returns (``allowed``: (module, name))."""

    def __init__(self, data: bytes, allowed: frozenset[tuple[str, str]]):
        super().__init__(io.BytesIO(data))
        self._allowed = allowed

    def find_class(self, module: str, name: str):  # noqa: D102 - pickle hook
        if (module, name) not in self._allowed:
            raise pickle.UnpicklingError(f"{module}.{name} is not a class this cache may hold")
        return super().find_class(module, name)


def _read(path: Path, key: str, allowed: frozenset[tuple[str, str]]) -> tuple[bool, Any]:
    """(True, value) of a whole entry with this key, else (False, None)."""
    try:
        raw = path.read_bytes()
    except OSError:
        return False, None
    digest_end = len(_MAGIC) + 64
    if not raw.startswith(_MAGIC) or len(raw) < digest_end + 1 or raw[digest_end:digest_end + 1] != b"\n":
        return False, None
    payload = raw[digest_end + 1:]
    if hashlib.sha256(payload).hexdigest().encode() != raw[len(_MAGIC):digest_end]:
        return False, None
    try:
        stored_key, value = _Unpickler(payload, allowed).load()
    except Exception:               # a corrupt or foreign payload is ignored, whatever it raises
        return False, None
    if stored_key != key:
        return False, None
    try:
        os.utime(path)              # used: the last to be removed
    except OSError:
        pass
    return True, value


def _write(path: Path, key: str, value: Any) -> None:
    """The entry written whole or not at all (a temporary file renamed); any failure ignored."""
    try:
        payload = pickle.dumps((key, value), protocol=pickle.HIGHEST_PROTOCOL)
        data = _MAGIC + hashlib.sha256(payload).hexdigest().encode() + b"\n" + payload
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=".tmp-")
        try:
            with os.fdopen(fd, "wb") as f:
                f.write(data)
            os.replace(tmp, path)
        except BaseException:
            os.unlink(tmp)
            raise
        _prune(path.parent)
    except (OSError, pickle.PicklingError, TypeError, AttributeError):
        pass


_STALE_TMP_NS = 3600 * 10**9   # a temporary file this old was left by a writer that died


def _prune(d: Path) -> None:
    """At most ``MAX_ON_DISK`` entries in ``d``: the least recently used removed (and the
    temporary files of writers that died)."""
    found = []
    now = time.time_ns()
    for p in d.iterdir():
        try:
            mtime = p.stat().st_mtime_ns
        except OSError:
            continue
        if not p.name.startswith("."):
            found.append((mtime, p))
        elif p.name.startswith(".tmp-") and now - mtime > _STALE_TMP_NS:
            found.append((-1, p))           # removed below, first
    entries = sum(1 for m, _ in found if m >= 0)
    drop = [p for m, p in found if m < 0]
    if entries > MAX_ON_DISK:
        drop += [p for _, p in sorted(x for x in found if x[0] >= 0)[:entries - MAX_ON_DISK]]
    for p in drop:
        try:
            p.unlink()
        except OSError:
            pass


def across_processes(name: str, fn: Callable[..., Any], allowed: Iterable[tuple[str, str]] = ()) -> Callable[..., Any]:
    """``fn`` kept in the disk cache by its name, the code version and the ``repr`` of its
    positional arguments (see the module docstring); ``allowed``: the (module, class) pairs its
    results are made of (plain tuples, numbers, strings, dicts need none)."""
    allowed = frozenset(allowed)

    @functools.wraps(fn)
    def call(*args: Any) -> Any:
        d = cache_dir()
        if d is None:
            return fn(*args)
        key = f"{name}\n{code_version()}\n{args!r}"
        path = d / name / hashlib.sha256(key.encode()).hexdigest()
        found, value = _read(path, key, allowed)
        if found:
            return value
        value = fn(*args)
        _write(path, key, value)
        return value

    return call
