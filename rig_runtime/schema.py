"""Turn parsed YAML into frozen dataclasses, refusing anything unexpected.

Each dataclass field may carry a constraint in ``field(metadata={"check": ...})``;
``positive``, ``nonneg``, ``nonzero``, ``unit_interval`` and ``probability`` are provided.
Errors name the file, the key path (``controller.gains.K_P_psi``) and what was expected;
a dataclass's ``REMOVED_KEYS`` (key -> what replaced it) names a key of older configs as removed.
"""

from __future__ import annotations

import dataclasses
import math
import types
import typing
from typing import Any, Callable, Literal, get_args, get_origin, get_type_hints

from .errors import ConfigError

Check = tuple[str, Callable[[Any], bool]]

positive: Check = ("a positive number", lambda v: v > 0)
nonneg: Check = ("a number >= 0", lambda v: v >= 0)
nonzero: Check = ("a non-zero number", lambda v: v != 0)
unit_interval: Check = ("a number in [0, 1]", lambda v: 0 <= v <= 1)
probability = unit_interval


def check(c: Check, default: Any = dataclasses.MISSING, **kw: Any) -> Any:
    """A dataclass field with a value constraint."""
    if default is dataclasses.MISSING and "default_factory" not in kw:
        return dataclasses.field(metadata={"check": c}, **kw)
    return dataclasses.field(default=default, metadata={"check": c}, **kw)


def _type_name(tp: Any) -> str:
    origin = get_origin(tp)
    if origin is Literal:
        return "one of " + ", ".join(repr(a) for a in get_args(tp))
    if origin in (typing.Union, types.UnionType):
        return " or ".join(_type_name(a) for a in get_args(tp))
    if origin is tuple:
        return "a list"
    if origin is dict:
        return "a mapping"
    if dataclasses.is_dataclass(tp):
        return "a mapping (section)"
    if tp is type(None):
        return "null"
    return {float: "a number", int: "an integer", str: "a string", bool: "true/false"}.get(tp, str(tp))


def _convert(tp: Any, value: Any, path: str, file: str | None) -> Any:
    origin = get_origin(tp)
    if origin in (typing.Union, types.UnionType):
        args = get_args(tp)
        if value is None and type(None) in args:
            return None
        options = [a for a in args if a is not type(None)]
        if len(options) == 1:  # Optional[X]: X's own error is the most precise
            return _convert(options[0], value, path, file)
        for a in options:
            try:
                return _convert(a, value, path, file)
            except ConfigError:
                continue
        raise ConfigError(file, path, _type_name(tp), value)
    if origin is Literal:
        if value not in get_args(tp):
            raise ConfigError(file, path, _type_name(tp), value)
        return value
    if origin is tuple:
        if not isinstance(value, (list, tuple)):
            raise ConfigError(file, path, "a list", value)
        args = get_args(tp)
        if len(args) == 2 and args[1] is Ellipsis:
            return tuple(_convert(args[0], v, f"{path}[{i}]", file) for i, v in enumerate(value))
        if len(args) != len(value):
            raise ConfigError(file, path, f"a list of {len(args)} items", value)
        return tuple(_convert(a, v, f"{path}[{i}]", file) for i, (a, v) in enumerate(zip(args, value)))
    if origin is dict:
        if not isinstance(value, dict):
            raise ConfigError(file, path, "a mapping", value)
        kt, vt = get_args(tp)
        return {_convert(kt, k, f"{path}.{k}", file): _convert(vt, v, f"{path}.{k}", file)
                for k, v in value.items()}
    if dataclasses.is_dataclass(tp):
        return build(tp, value, path, file)
    if tp is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ConfigError(file, path, "a number", value)
        if not math.isfinite(value):
            raise ConfigError(file, path, "a finite number", value)
        return float(value)
    if tp is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(file, path, "an integer", value)
        return value
    if tp is bool:
        if not isinstance(value, bool):
            raise ConfigError(file, path, "true/false", value)
        return value
    if tp is str:
        if not isinstance(value, str):
            raise ConfigError(file, path, "a string", value)
        return value
    if tp is Any:
        return value
    raise TypeError(f"schema: unsupported type {tp!r} at {path}")


def build(cls: type, data: Any, path: str = "", file: str | None = None) -> Any:
    """Build dataclass ``cls`` from a mapping, validating types, keys and constraints."""
    if data is None:
        data = {}
    if not isinstance(data, dict):
        raise ConfigError(file, path, f"a mapping for section {cls.__name__}", data)
    hints = get_type_hints(cls)
    fields = {f.name: f for f in dataclasses.fields(cls) if f.init}
    unknown = sorted(set(data) - set(fields))
    removed = getattr(cls, "REMOVED_KEYS", {})     # key -> what replaced it, for old configs
    for k in unknown:
        if k in removed:
            raise ConfigError(file, f"{path}.{k}" if path else str(k), f"no such key (removed: {removed[k]})")
    if unknown:
        p = f"{path}.{unknown[0]}" if path else str(unknown[0])
        raise ConfigError(file, p, "no such key (known: " + ", ".join(sorted(fields)) + ")", None)
    kwargs = {}
    for name, f in fields.items():
        p = f"{path}.{name}" if path else name
        if name not in data:
            if f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING:
                raise ConfigError(file, p, f"{_type_name(hints[name])} (missing key)")
            continue
        v = _convert(hints[name], data[name], p, file)
        c = f.metadata.get("check")
        if c is not None and v is not None and not c[1](v):
            raise ConfigError(file, p, c[0], v)
        kwargs[name] = v
    try:
        obj = cls(**kwargs)
    except ConfigError as e:
        if e.file is None:
            e = ConfigError(file, f"{path}.{e.key_path}" if path and e.key_path else (e.key_path or path), e.expected, e.got)
            raise e from None
        raise
    return obj


def to_dict(obj: Any) -> Any:
    """Plain-data form of a config object (for logs and --json)."""
    if dataclasses.is_dataclass(obj):
        return {f.name: to_dict(getattr(obj, f.name)) for f in dataclasses.fields(obj)}
    if isinstance(obj, (tuple, list)):
        return [to_dict(v) for v in obj]
    if isinstance(obj, dict):
        return {k: to_dict(v) for k, v in obj.items()}
    return obj
