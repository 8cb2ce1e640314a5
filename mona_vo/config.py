"""Configuration: frozen dataclasses (one per stage, defaults in their definitions), then a YAML
file, then ``key=value`` overrides. Every key is checked when the configuration is built: unknown
keys, ill-typed values and values outside their allowed range fail with one line that names the
key as it is typed (``vo.ba.max_iterations``) and what it allows.

Each field states its rule once, where it is defined, with :func:`setting`::

    grid_size: int = setting(16, ge=2)          # k: new points on a k x k grid, one per cell
    refine: str = setting("global", choices=("global", "none"))   # ...

and its trailing comment (with comment-only lines under it) is its documentation, printed by
``mona-vo config`` (:func:`to_yaml`). Cross-field rules stay in each class's ``validate()``.

Dotted keys reach nested stages: ``vo.keyframe_parallax_px=12``.
"""
from __future__ import annotations

import dataclasses
import re
import typing
from pathlib import Path
from typing import Any

from mona_vo.errors import ConfigError

RULE = "mona_vo.rule"   # key of a field's Rule in dataclasses.Field.metadata


@dataclasses.dataclass(frozen=True)
class Rule:
    """What one config value may be: bounds for numbers, a set of names for text (a tuple, or a
    registry whose ``names()`` are read when checked), a regular expression, or free text
    (``text``: what it holds, e.g. "a file path; '' = from weights"). ``zero``: 0 is allowed
    besides the bounds (a key whose 0 stands for another key's value)."""

    ge: float | None = None
    gt: float | None = None
    le: float | None = None
    lt: float | None = None
    choices: Any = None
    pattern: str | None = None
    text: str | None = None
    zero: bool = False

    def names(self) -> list[str] | None:
        if self.choices is None:
            return None
        return list(self.choices.names()) if hasattr(self.choices, "names") else list(self.choices)

    def describe(self, kind: type) -> str:
        """The allowed values in words, e.g. 'an integer >= 1', 'a number in (0, 1]'."""
        if kind is bool:
            return "true or false"
        names = self.names()
        if names is not None:
            return "one of " + ", ".join(names)
        if self.pattern is not None:
            return f"text matching {self.pattern}"
        if self.text is not None:
            return f"text ({self.text})"
        what = ("an integer" if kind is int else "a number") + (" 0 or" if self.zero else "")
        lo = ("[", self.ge) if self.ge is not None else ("(", self.gt) if self.gt is not None else None
        hi = ("]", self.le) if self.le is not None else (")", self.lt) if self.lt is not None else None
        if lo and hi:
            return f"{what} in {lo[0]}{_num(lo[1])}, {_num(hi[1])}{hi[0]}"
        if lo:
            return f"{what} {'>=' if lo[0] == '[' else '>'} {_num(lo[1])}"
        if hi:
            return f"{what} {'<=' if hi[0] == ']' else '<'} {_num(hi[1])}"
        return what

    def allows(self, value: Any) -> bool:
        if isinstance(value, bool) or value is None:
            return True
        if isinstance(value, (int, float)):
            if self.zero and value == 0:
                return True
            return ((self.ge is None or value >= self.ge) and (self.gt is None or value > self.gt)
                    and (self.le is None or value <= self.le) and (self.lt is None or value < self.lt))
        names = self.names()
        if names is not None:
            return value in names
        if self.pattern is not None:
            return re.fullmatch(self.pattern, str(value)) is not None
        return True

    def out_of_range_example(self, kind: type) -> Any | None:
        """A value of the right type that this rule refuses (for tests); None for free text."""
        if kind is bool:
            return None
        if kind in (int, float):
            step = 1 if kind is int else 1e-3
            if self.ge is not None:
                return kind(self.ge - step) if kind is float else int(self.ge) - 1
            if self.gt is not None:
                return kind(self.gt)
            if self.le is not None:
                return kind(self.le + step) if kind is float else int(self.le) + 1
            if self.lt is not None:
                return kind(self.lt)
            return None
        if self.names() is not None or self.pattern is not None:
            return "bogus value!"
        return None


def _num(v: float) -> str:
    return f"{v:g}"


def setting(default: Any, *, ge: float | None = None, gt: float | None = None,
            le: float | None = None, lt: float | None = None, choices: Any = None,
            pattern: str | None = None, text: str | None = None, zero: bool = False):
    """A dataclass field with its default and its rule (see :class:`Rule`). Booleans need no
    bounds; numbers give at least one bound; text gives ``choices``, ``pattern`` or ``text``."""
    rule = Rule(ge=ge, gt=gt, le=le, lt=lt, choices=choices, pattern=pattern, text=text,
                zero=zero)
    return dataclasses.field(default=default, metadata={RULE: rule})


# --------------------------------------------------------------------------- coercion

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
        raise ConfigError(f"config key '{key}': expected true or false, got {value!r}")
    if annotation in (int, float):
        what = "an integer" if annotation is int else "a number"
        if isinstance(value, bool) or isinstance(value, (list, dict)) or value is None:
            raise ConfigError(f"config key '{key}': expected {what}, got {value!r}")
        try:
            number = float(value)
        except (TypeError, ValueError):
            raise ConfigError(f"config key '{key}': expected {what}, got {value!r}") from None
        if number != number or number in (float("inf"), float("-inf")):
            raise ConfigError(f"config key '{key}': expected a finite number, got {value!r}")
        if annotation is int:
            if number != int(number):
                raise ConfigError(f"config key '{key}': expected an integer, got {value!r}")
            return int(number)
        return number
    if annotation is str:
        if isinstance(value, (dict, list)):
            raise ConfigError(f"config key '{key}': expected text, got {value!r}")
        return "" if value is None else str(value)
    return value


def _hints(cls) -> dict[str, Any]:
    return typing.get_type_hints(cls)


def apply_overrides(cfg, overrides: dict[str, Any], prefix: str = ""):
    """A copy of the frozen dataclass ``cfg`` with ``overrides`` (possibly nested dicts or dotted
    keys) applied and type-converted. Unknown keys raise :class:`ConfigError`. Ranges and
    cross-field rules are checked by :func:`check_config` (``load_config`` calls it)."""
    nested: dict[str, dict] = {}
    direct: dict[str, Any] = {}
    for key, value in overrides.items():
        head, _, rest = str(key).partition(".")
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
            import difflib

            close = difflib.get_close_matches(key, sorted(fields), n=1)
            hint = (f"did you mean '{prefix}{close[0]}'?" if close else
                    f"keys here: {', '.join(sorted(fields))}")
            raise ConfigError(f"unknown config key '{prefix}{key}'; {hint} (`mona-vo config` lists every key)")
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
    return dataclasses.replace(cfg, **changes)


# --------------------------------------------------------------------------- checking

def leaves(cfg, prefix: str = ""):
    """``(dotted key, dataclasses.Field, value, type)`` of every value of ``cfg``, depth first."""
    hints = _hints(type(cfg))
    for f in dataclasses.fields(cfg):
        value = getattr(cfg, f.name)
        if dataclasses.is_dataclass(value):
            yield from leaves(value, prefix + f.name + ".")
        else:
            yield prefix + f.name, f, value, hints[f.name]


def check_fields(cfg, prefix: str = "") -> None:
    """Every value of ``cfg`` (nested sections too) against its type and :func:`setting` rule;
    the first bad one raises ConfigError naming ``prefix`` + its dotted key."""
    for key, f, value, kind in leaves(cfg, prefix):
        if kind in (int, float, bool, str):
            ok_type = (isinstance(value, bool) if kind is bool else
                       isinstance(value, str) if kind is str else
                       isinstance(value, (int, float)) and not isinstance(value, bool)
                       and (kind is float or float(value).is_integer()))
            if not ok_type:
                raise ConfigError(f"config key '{key}': expected {Rule().describe(kind)}, got {value!r}")
        rule = f.metadata.get(RULE)
        if rule is not None and not rule.allows(value):
            raise ConfigError(f"config key '{key}': {value!r} is not allowed; expected {rule.describe(kind)}")


def check_config(cfg, prefix: str = "") -> None:
    """:func:`check_fields`, then the config's own cross-field ``validate()``."""
    check_fields(cfg, prefix)
    validate = getattr(cfg, "validate", None)
    if callable(validate):
        validate()


# --------------------------------------------------------------------------- loading

def parse_set_options(items: list[str] | None) -> dict[str, str]:
    """``["a.b=1", "c=x"]`` -> ``{"a.b": "1", "c": "x"}``; a malformed item raises ConfigError."""
    out = {}
    for item in items or []:
        key, sep, value = item.partition("=")
        if not sep or not key.strip():
            raise ConfigError(f"--set expects key=value, e.g. --set vo.grid_size=20, got '{item}'")
        out[key.strip()] = value.strip()
    return out


def load_config(cls_or_default, yaml_path: str | Path | None = None, overrides: dict | None = None):
    """Defaults of ``cls_or_default``, then the YAML file, then ``overrides``; the result is
    checked (:func:`check_config`) before it is returned."""
    cfg = cls_or_default() if isinstance(cls_or_default, type) else cls_or_default
    if yaml_path is not None:
        import yaml

        path = Path(yaml_path)
        try:
            data = yaml.safe_load(path.read_text()) or {}
        except FileNotFoundError:
            raise ConfigError(f"{path}: config file not found") from None
        except (OSError, UnicodeDecodeError) as exc:
            raise ConfigError(f"{path}: cannot read the config file ({exc})") from None
        except yaml.YAMLError as exc:
            raise ConfigError(f"{path}: not valid YAML ({str(exc).splitlines()[0]})") from None
        if not isinstance(data, dict):
            raise ConfigError(f"{path}: a config file must hold a mapping of keys to values")
        try:
            cfg = apply_overrides(cfg, data)
        except ConfigError as exc:
            raise ConfigError(f"{path}: {exc}") from None
    if overrides:
        cfg = apply_overrides(cfg, overrides)
    check_config(cfg)
    return cfg


def to_dict(cfg) -> dict:
    """JSON-able nested dict of a config dataclass (saved with every result)."""
    return dataclasses.asdict(cfg)


# --------------------------------------------------------------------------- documentation

def field_docs(cls) -> dict[str, str]:
    """Field name -> its documentation: the comment on the field's line(s) and the comment-only
    lines indented under it, joined."""
    import ast
    import inspect
    import io
    import textwrap
    import tokenize

    try:
        source = textwrap.dedent(inspect.getsource(cls))
    except (OSError, TypeError):
        return {}
    body = ast.parse(source).body[0].body
    comments: dict[int, tuple[int, str, bool]] = {}   # line -> (column, text, alone on its line)
    lines = source.splitlines()
    for tok in tokenize.generate_tokens(io.StringIO(source).readline):
        if tok.type == tokenize.COMMENT:
            row, col = tok.start
            alone = not lines[row - 1][:col].strip()
            comments[row] = (col, tok.string.lstrip("#").strip(), alone)
    docs = {}
    for i, node in enumerate(body):
        if not isinstance(node, ast.AnnAssign) or not isinstance(node.target, ast.Name):
            continue
        end = body[i + 1].lineno - 1 if i + 1 < len(body) else len(lines)
        parts = [comments[r][1] for r in range(node.lineno, node.end_lineno + 1) if r in comments]
        for r in range(node.end_lineno + 1, end + 1):
            if r in comments and comments[r][2] and comments[r][0] > node.col_offset:
                parts.append(comments[r][1])
            elif lines[r - 1].strip():
                break
        docs[node.target.id] = " ".join(p for p in parts if p)
    return docs


def _yaml_scalar(value: Any) -> str:
    import yaml

    return yaml.safe_dump([value], default_flow_style=True, width=10**6).strip()[1:-1]


def _comment(text: str, pad: str, width: int = 100) -> list[str]:
    import textwrap

    return textwrap.wrap(text, width=max(40, width - len(pad)), initial_indent=f"{pad}# ",
                         subsequent_indent=f"{pad}#   ", break_on_hyphens=False)


def to_yaml(cfg, *, indent: int = 0) -> str:
    """``cfg`` as YAML that :func:`load_config` reads back to an equal config, each key under a
    comment: its documentation and its allowed values."""
    hints = _hints(type(cfg))
    docs = field_docs(type(cfg))
    pad = " " * indent
    out = []
    for f in dataclasses.fields(cfg):
        value = getattr(cfg, f.name)
        doc = docs.get(f.name, "")
        if dataclasses.is_dataclass(value):
            out.extend(_comment(doc or "section", pad))
            out.append(f"{pad}{f.name}:")
            out.append(to_yaml(value, indent=indent + 2).rstrip("\n"))
            continue
        rule = f.metadata.get(RULE) or Rule()
        allowed = rule.describe(hints[f.name])
        allowed = "[" + allowed.replace(" ", "\0") + "]"    # kept on one line when wrapped
        out.extend(line.replace("\0", " ") for line in _comment(f"{doc + ' ' if doc else ''}{allowed}", pad))
        out.append(f"{pad}{f.name}: {_yaml_scalar(value)}")
    return "\n".join(out) + "\n"
