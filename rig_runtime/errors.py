"""The project's error hierarchy.

Every error names what it is about (a config key path, a device) so that a one-line
message tells the operator the cause. Library errors are wrapped with ``raise … from``.
"""

from __future__ import annotations

import reprlib

_SHORT = reprlib.Repr()
_SHORT.maxlevel, _SHORT.maxlist, _SHORT.maxtuple, _SHORT.maxdict = 2, 4, 4, 4
_SHORT.maxstring, _SHORT.maxother, _SHORT.maxlong = 60, 60, 40
MAX_VALUE_CHARS = 80


def short_repr(value: object) -> str:
    """A value for an error message: nested containers and long strings cut (``...``),
    at most ``MAX_VALUE_CHARS`` characters whatever the value (never formats it whole)."""
    try:
        text = _SHORT.repr(value)
    except Exception:  # noqa: BLE001 - a broken __repr__ must not hide the error itself
        text = f"<{type(value).__name__}>"
    return text if len(text) <= MAX_VALUE_CHARS else text[:MAX_VALUE_CHARS - 3] + "..."


class RigError(Exception):
    """Base of every error rig-runtime raises on purpose."""


class ConfigError(RigError):
    """A configuration file is malformed, incomplete or non-physical."""

    def __init__(self, file: str | None, key_path: str, expected: str, got: object = None):
        self.file = file
        self.key_path = key_path
        self.expected = expected
        self.got = got
        got_txt = "" if got is None else f", got {short_repr(got)}"
        parts = [p for p in (file, key_path) if p]
        super().__init__(": ".join(parts + [f"expected {expected}{got_txt}"]))

    def __reduce__(self):
        """Picklable with its fields (a worker process or a Dask task sends it back whole)."""
        return (type(self), (self.file, self.key_path, self.expected, self.got))


class DeviceError(RigError):
    """A device could not be used; names the device."""

    def __init__(self, device: str, message: str):
        self.device = device
        self.message = message
        super().__init__(f"{device}: {message}")

    def __reduce__(self):
        """Picklable with its fields (see ConfigError)."""
        return (type(self), (self.device, self.message))


class DeviceInitError(DeviceError):
    """Opening or configuring a device failed (port missing, node not answering, …)."""


class DeviceIOError(DeviceError):
    """Reading or writing a device failed after it was opened."""


class DeviceTimeoutError(DeviceIOError):
    """A device did not answer within its configured time."""


class LogError(RigError):
    """A file given as a log is not a readable rig log (not HDF5, another program's HDF5,
    empty or truncated); names the file and why."""

    def __init__(self, path: object, why: str):
        self.path = str(path)
        super().__init__(f"{path}: not a readable rig log ({why})")


def picklable(exc: BaseException | None) -> BaseException | None:
    """``exc`` if it survives pickling (the OS error behind a failed open: refused,
    unreachable, …), else its text as a RuntimeError: a helper process sends the cause of
    a failure to its parent, which raises it ``from`` this."""
    if exc is None:
        return None
    import pickle
    try:
        pickle.loads(pickle.dumps(exc))
        return exc
    except Exception:                       # noqa: BLE001 - anything that does not round-trip
        return RuntimeError(f"{type(exc).__name__}: {exc}")
