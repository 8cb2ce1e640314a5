"""Loading configuration: frozen dataclasses (one per stage, defaults in their definitions), then a
YAML file, then ``key=value`` overrides. Unknown keys and ill-typed values fail with the key named.

Dotted keys reach nested stages: ``vo.keyframe_parallax_px=12``.
"""
from __future__ import annotations

import dataclasses
import typing
from pathlib import Path
from typing import Any

from mona_vo.errors import ConfigError


def _coerce(value: Any, annotation: Any, key: str) -> Any:
    origin = typing.get_origin(annotation)
    args = typing.get_args(annotation)
    if origin is typing.Union or (origin is not None and str(origin) == "<class 'types.UnionType'>"):
        if value is None and type(None) in args:
            return None
        if isinstance(value, str) and value.lower() in ("none", "null") and type(None) in args:
            return None
        last = None
        for a in args:
            if a is type(None):
                continue
            try:
                return _coerce(value, a, key)
            except ConfigError as exc:
                last = exc
        raise last or ConfigError(f"config key '{key}': cannot use {value!r}")
    if origin in (tuple, list):
        if isinstance(value, str):
            value = [v for v in value.replace("(", "").replace(")", "").split(",") if v.strip()]
        if not isinstance(value, (list, tuple)):
            raise ConfigError(f"config key '{key}': expected a list, got {value!r}")
        inner = args[0] if args else str
        return origin(_coerce(v, inner, key) for v in value)
    if annotation is bool:
        if isinstance(value, bool):
            return value
        if isinstance(value, str) and value.lower() in ("1", "true", "yes", "on", "0", "false", "no", "off"):
            return value.lower() in ("1", "true", "yes", "on")
        raise ConfigError(f"config key '{key}': expected true/false, got {value!r}")
    if annotation in (int, float):
        try:
            out = annotation(value)
        except (TypeError, ValueError):
            raise ConfigError(f"config key '{key}': expected a number, got {value!r}") from None
        if annotation is int and isinstance(value, float) and value != int(value):
            raise ConfigError(f"config key '{key}': expected an integer, got {value!r}")
        return out
    if annotation is str:
        return str(value)
    return value


def _hints(cls) -> dict[str, Any]:
    return typing.get_type_hints(cls)


def apply_overrides(cfg, overrides: dict[str, Any], prefix: str = ""):
    """A copy of the frozen dataclass ``cfg`` with ``overrides`` (possibly nested dicts or dotted
    keys) applied and type-checked. Unknown keys raise :class:`ConfigError`."""
    nested: dict[str, dict] = {}
    direct: dict[str, Any] = {}
    for key, value in overrides.items():
        head, _, rest = key.partition(".")
        if rest:
            nested.setdefault(head, {})[rest] = value
        elif isinstance(value, dict):
            nested.setdefault(head, {}).update(value)
        else:
            direct[head] = value
    hints = _hints(type(cfg))
    fields = {f.name for f in dataclasses.fields(cfg)}
    changes = {}
    for key in list(direct) + list(nested):
        if key not in fields:
            valid = ", ".join(sorted(fields))
            raise ConfigError(f"unknown config key '{prefix}{key}' (valid: {valid})")
    for key, value in direct.items():
        current = getattr(cfg, key)
        if dataclasses.is_dataclass(current):
            raise ConfigError(f"config key '{prefix}{key}' is a section; set its fields, e.g. {prefix}{key}.<field>=...")
        changes[key] = _coerce(value, hints[key], prefix + key)
    for key, sub in nested.items():
        current = getattr(cfg, key)
        if not dataclasses.is_dataclass(current):
            raise ConfigError(f"config key '{prefix}{key}' has no sub-keys")
        changes[key] = apply_overrides(current, sub, prefix + key + ".")
    out = dataclasses.replace(cfg, **changes)
    validate = getattr(out, "validate", None)
    if callable(validate):
        validate()
    return out


def parse_set_options(items: list[str] | None) -> dict[str, str]:
    """``["a.b=1", "c=x"]`` -> ``{"a.b": "1", "c": "x"}``; a malformed item raises ConfigError."""
    out = {}
    for item in items or []:
        key, sep, value = item.partition("=")
        if not sep or not key.strip():
            raise ConfigError(f"--set expects key=value, got '{item}'")
        out[key.strip()] = value.strip()
    return out


def load_config(cls_or_default, yaml_path: str | Path | None = None, overrides: dict | None = None):
    """Defaults of ``cls_or_default``, then the YAML file, then ``overrides``."""
    cfg = cls_or_default() if isinstance(cls_or_default, type) else cls_or_default
    if yaml_path is not None:
        import yaml

        path = Path(yaml_path)
        try:
            data = yaml.safe_load(path.read_text()) or {}
        except FileNotFoundError:
            raise ConfigError(f"{path}: config file not found") from None
        except yaml.YAMLError as exc:
            raise ConfigError(f"{path}: not valid YAML ({str(exc).splitlines()[0]})") from None
        if not isinstance(data, dict):
            raise ConfigError(f"{path}: a config file must hold a mapping of keys to values")
        cfg = apply_overrides(cfg, data)
    if overrides:
        cfg = apply_overrides(cfg, overrides)
    return cfg


def to_dict(cfg) -> dict:
    """JSON-able nested dict of a config dataclass (saved with every result)."""
    return dataclasses.asdict(cfg)
