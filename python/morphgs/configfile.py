"""Run config files: TOML read as written, `section.key=value` overrides, and typed sections.

Torch-free. A config section becomes a frozen dataclass through `config_from_dict`, which refuses
unknown keys and values of the wrong type with a `ConfigError` naming the file, section and key.
"""

from __future__ import annotations

import dataclasses
import os
import sys
import types
import typing
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any, TypeVar

from morphgs._core import MorphgsError

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover - Python 3.10 has no tomllib
    try:
        import tomli as tomllib
    except ImportError as e:
        raise ImportError("reading run configs on Python 3.10 needs tomli: pip install tomli") from e

__all__ = ["ConfigError", "config_from_dict", "load_toml", "merge", "parse_overrides"]

T = TypeVar("T")


class ConfigError(MorphgsError):
    """A run config that cannot be used (names the file, section and key)."""


def load_toml(path: str | os.PathLike[str]) -> tuple[str, dict[str, Any]]:
    """(text as written, parsed dict) of a TOML file.

    Raises:
        FileNotFoundError: no such file. ConfigError: not valid TOML (with the line).
    """
    p = Path(path)
    if not p.is_file():
        raise FileNotFoundError(f"{p}: no such config file")
    text = p.read_text(encoding="utf-8")
    return text, loads(text, source=str(p))


def loads(text: str, *, source: str) -> dict[str, Any]:
    """Parse TOML text; errors name `source`."""
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as e:
        raise ConfigError(f"{source}: not valid TOML: {e}") from None


def merge(base: Mapping[str, Any], over: Mapping[str, Any]) -> dict[str, Any]:
    """Deep merge: tables merge key by key, anything else in `over` replaces."""
    out = dict(base)
    for k, v in over.items():
        if isinstance(v, Mapping) and isinstance(out.get(k), Mapping):
            out[k] = merge(out[k], v)
        else:
            out[k] = v
    return out


def parse_overrides(items: Sequence[str]) -> dict[str, Any]:
    """`["optim.lr=1e-3", "data.size=[64, 96]", "model=tiny"]` -> a nested dict.

    Values are TOML values (numbers, booleans, arrays, quoted strings); anything that does not
    parse as one is taken as a bare string.

    Raises:
        ConfigError: an item without `=`, or an empty key.
    """
    out: dict[str, Any] = {}
    for item in items:
        key, sep, raw = item.partition("=")
        key = key.strip()
        if not sep or not key or any(not part for part in key.split(".")):
            raise ConfigError(f"override {item!r}: expected SECTION.KEY=VALUE")
        try:
            value = tomllib.loads(f"v = {raw.strip()}")["v"]
        except tomllib.TOMLDecodeError:
            value = raw.strip()
        node = out
        parts = key.split(".")
        for part in parts[:-1]:
            node = node.setdefault(part, {})
            if not isinstance(node, dict):
                raise ConfigError(f"override {item!r}: {part} is both a value and a section")
        node[parts[-1]] = value
    return out


def _type_name(tp: Any) -> str:
    return getattr(tp, "__name__", None) or str(tp).replace("typing.", "")


def _coerce(value: Any, tp: Any, where: str) -> Any:
    origin = typing.get_origin(tp)
    args = typing.get_args(tp)
    if origin in (typing.Union, types.UnionType):
        if value is None and type(None) in args:
            return None
        errors = []
        for a in args:
            if a is type(None):
                continue
            try:
                return _coerce(value, a, where)
            except ConfigError as e:
                errors.append(str(e))
        raise ConfigError(errors[0] if len(errors) == 1 else f"{where}: expected {_type_name(tp)}, got {value!r}")
    if origin is tuple:
        if not isinstance(value, (list, tuple)):
            raise ConfigError(f"{where}: expected an array, got {value!r}")
        if len(args) == 2 and args[1] is Ellipsis:
            return tuple(_coerce(v, args[0], where) for v in value)
        if len(value) != len(args):
            raise ConfigError(f"{where}: expected an array of {len(args)} values, got {value!r}")
        return tuple(_coerce(v, a, where) for v, a in zip(value, args))
    if tp is bool:
        if not isinstance(value, bool):
            raise ConfigError(f"{where}: expected true or false, got {value!r}")
        return value
    if tp is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(f"{where}: expected an integer, got {value!r}")
        return value
    if tp is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ConfigError(f"{where}: expected a number, got {value!r}")
        return float(value)
    if tp is str:
        if not isinstance(value, str):
            raise ConfigError(f"{where}: expected a string, got {value!r}")
        return value
    return value


def config_from_dict(cls: type[T], values: Mapping[str, Any] | None, *, section: str, source: str = "config") -> T:
    """A frozen dataclass from one config section: defaults for missing keys, types checked.

    Args:
        cls: the dataclass.
        values: the section's table (None: all defaults).
        section: its name (for messages); source: the file or origin (for messages).

    Raises:
        ConfigError: an unknown key (lists the known ones), a value of the wrong type, or a value
        the dataclass refuses.
    """
    values = dict(values or {})
    if not isinstance(values, dict):
        raise ConfigError(f"{source}: [{section}] must be a table")
    hints = typing.get_type_hints(cls)
    names = [f.name for f in dataclasses.fields(cls)]  # type: ignore[arg-type]
    unknown = sorted(set(values) - set(names))
    if unknown:
        raise ConfigError(f"{source}: [{section}] unknown key {unknown[0]!r} (known: {', '.join(names)})")
    kwargs = {k: _coerce(v, hints[k], f"{source}: [{section}] {k}") for k, v in values.items()}
    try:
        return cls(**kwargs)
    except (ValueError, TypeError) as e:
        raise ConfigError(f"{source}: [{section}] {e}") from None
