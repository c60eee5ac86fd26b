"""Strict, typed configuration: YAML files and ``key=value`` overrides mapped onto dataclasses.

Every task declares its configuration as a (nested) dataclass. :func:`load_config` reads a YAML
file, applies dotted command-line overrides (``optim.lr=0.01``) and builds the dataclass, raising
:class:`ConfigError` for unknown keys and for values of the wrong type, with the full dotted key in
the message. Nothing is silently dropped or coerced except ``int`` → ``float``.
"""
from __future__ import annotations

import dataclasses
import math
import re
import types
import typing
from pathlib import Path
from typing import Any, Mapping, TypeVar

import yaml

T = TypeVar("T")


class ConfigError(ValueError):
    """A configuration file or override is invalid (unknown key, wrong type, bad syntax)."""


class _StrictLoader(yaml.SafeLoader):
    """YAML safe loader that rejects duplicate mapping keys and reads ``1e-3`` as a float.

    PyYAML follows YAML 1.1, where a float needs a dot (``1.0e-3``) and ``1e-3`` is a string; every
    other YAML tool (and Python) reads it as a number, so we do too.
    """

    def construct_mapping(self, node: yaml.MappingNode, deep: bool = False) -> dict[Any, Any]:
        """Build a mapping; a key that occurs twice raises a ``ConstructorError`` naming it and its line."""
        seen: dict[Any, Any] = {}
        for key_node, _ in node.value:
            key = self.construct_object(key_node, deep=True)
            if key in seen:
                raise yaml.constructor.ConstructorError(
                    None, None, f"duplicate key {key!r} (first at line {seen[key].line + 1})", key_node.start_mark)
            seen[key] = key_node.start_mark
        return super().construct_mapping(node, deep=deep)


_FLOAT = re.compile(r"""^(?:[-+]?(?:[0-9][0-9_]*)\.[0-9_]*(?:[eE][-+]?[0-9]+)?
    |[-+]?(?:[0-9][0-9_]*)(?:[eE][-+]?[0-9]+)
    |\.[0-9_]+(?:[eE][-+]?[0-9]+)?
    |[-+]?\.(?:inf|Inf|INF)
    |\.(?:nan|NaN|NAN))$""", re.X)
_StrictLoader.yaml_implicit_resolvers = {k: list(v) for k, v in yaml.SafeLoader.yaml_implicit_resolvers.items()}
for _first in "-+.0123456789":
    _StrictLoader.yaml_implicit_resolvers[_first] = [
        (tag, rx) for tag, rx in _StrictLoader.yaml_implicit_resolvers.get(_first, [])
        if tag != "tag:yaml.org,2002:float"]
    _StrictLoader.add_implicit_resolver("tag:yaml.org,2002:float", _FLOAT, [_first])


def yaml_load(text: str) -> Any:
    """Parse YAML text strictly (:class:`_StrictLoader`): duplicate keys are errors, ``1e-3`` is a float."""
    return yaml.load(text, Loader=_StrictLoader)  # noqa: S506 - a SafeLoader subclass


class FieldError(ConfigError):
    """A field of a config section is out of range; :func:`from_dict` adds the section's dotted prefix (once:
    an error of a section loaded inside another's validation, e.g. ``eval.render``, already has its own)."""

    def __init__(self, key: str, expected: str, value: Any, prefixed: bool = False, detail: str | None = None) -> None:
        self.detail = f"expected {expected}, got {value!r}" if detail is None else detail
        super().__init__(f"{key}: {self.detail}")
        self.key, self.expected, self.value, self.prefixed = key, expected, value, prefixed

    def with_prefix(self, prefix: str) -> "FieldError":
        """The same error with the section's dotted prefix on the key (unchanged when it has one already)."""
        return self if self.prefixed else FieldError(prefix + self.key, self.expected, self.value, True, self.detail)


def require(ok: bool, key: str, expected: str, value: Any) -> None:
    """In a config dataclass's ``__post_init__``: raise :class:`FieldError` (``"<key>: expected <expected>,
    got <value>"``, the key relative to the section) unless ``ok``."""
    if not ok:
        raise FieldError(key, expected, value)


def require_fields(obj: Any, **rules: str) -> None:
    """Range rules for fields of ``obj``: ``">=N"`` or ``">N"`` (a number N), ``"prob"`` (in (0, 1]),
    ``"unit"`` (in [0, 1]), ``"rate"`` (in [0, 1): Adam's betas), ``"open"`` (in (0, 1)) or ``"finite"``; a list or
    tuple must hold valid items only,
    and ``None`` values (optional fields) pass. NaN fails every rule."""
    for name, rule in rules.items():
        value = getattr(obj, name)
        ok, expected = _rule(rule)
        values = value if isinstance(value, (list, tuple)) else [value]
        require(all(v is None or ok(v) for v in values), name, expected, value)


def _rule(rule: str) -> tuple[Any, str]:
    """``(predicate, what it expects)`` of a :func:`require_fields` rule."""
    named = {"prob": (lambda v: 0 < v <= 1, "a value in (0, 1]"), "unit": (lambda v: 0 <= v <= 1, "a value in [0, 1]"),
             "rate": (lambda v: 0 <= v < 1, "a value in [0, 1)"), "open": (lambda v: 0 < v < 1, "a value in (0, 1)"),
             "finite": (math.isfinite, "a finite number")}
    if rule in named:
        return named[rule]
    match = re.fullmatch(r"(>=|>)(-?\d+(?:\.\d+)?)", rule)
    if match is None:
        raise ValueError(f"require_fields: unknown rule {rule!r}")
    op, bound = match.group(1), float(match.group(2))
    text = f"a value {op} {match.group(2)}"
    return ((lambda v: v >= bound) if op == ">=" else (lambda v: v > bound)), text


def _type_name(tp: Any) -> str:
    return getattr(tp, "__name__", None) or str(tp).replace("typing.", "")


def _coerce(value: Any, tp: Any, key: str) -> Any:
    """Check ``value`` against the annotation ``tp`` and build nested dataclasses."""
    origin = typing.get_origin(tp)
    args = typing.get_args(tp)
    if tp is Any:
        return value
    if origin in (typing.Union, types.UnionType):
        if value is None and type(None) in args:
            return None
        errors = []
        for arg in args:
            if arg is type(None):
                continue
            try:
                return _coerce(value, arg, key)
            except ConfigError as exc:
                errors.append(str(exc))
        raise ConfigError(f"{key}: expected {_type_name(tp)}, got {value!r}")
    if origin is typing.Literal:
        if value not in args:
            raise ConfigError(f"{key}: expected one of {list(args)}, got {value!r}")
        return value
    if dataclasses.is_dataclass(tp):
        if not isinstance(value, Mapping):
            raise ConfigError(f"{key}: expected a mapping for section '{tp.__name__}', got {value!r}")
        return from_dict(tp, value, prefix=key + ".")
    if origin in (list, tuple):
        if not isinstance(value, (list, tuple)):
            raise ConfigError(f"{key}: expected a list, got {value!r}")
        if origin is tuple and args and args[-1] is not Ellipsis:
            if len(value) != len(args):
                raise ConfigError(f"{key}: expected {len(args)} items, got {len(value)}")
            return tuple(_coerce(v, a, f"{key}[{i}]") for i, (v, a) in enumerate(zip(value, args)))
        inner = args[0] if args else Any
        seq = [_coerce(v, inner, f"{key}[{i}]") for i, v in enumerate(value)]
        return tuple(seq) if origin is tuple else seq
    if origin is dict:
        if not isinstance(value, Mapping):
            raise ConfigError(f"{key}: expected a mapping, got {value!r}")
        return dict(value)
    if tp is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ConfigError(f"{key}: expected a number, got {value!r}")
        return float(value)
    if tp is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(f"{key}: expected an integer, got {value!r}")
        return value
    if tp is bool:
        if not isinstance(value, bool):
            raise ConfigError(f"{key}: expected true/false, got {value!r}")
        return value
    if tp is str:
        if not isinstance(value, str):
            raise ConfigError(f"{key}: expected a string, got {value!r}")
        return value
    if isinstance(tp, type) and not isinstance(value, tp):
        raise ConfigError(f"{key}: expected {_type_name(tp)}, got {value!r}")
    return value


def from_dict(cls: type[T], data: Mapping[str, Any], prefix: str = "") -> T:
    """Build dataclass ``cls`` from ``data``; unknown keys and wrong types raise :class:`ConfigError`."""
    hints = typing.get_type_hints(cls)
    names = {f.name for f in dataclasses.fields(cls) if f.init}
    unknown = sorted(set(data) - names)
    if unknown:
        raise ConfigError(
            f"unknown config key(s) {', '.join(prefix + u for u in unknown)}; "
            f"valid keys here: {', '.join(sorted(names))}"
        )
    kwargs = {name: _coerce(value, hints[name], prefix + name) for name, value in data.items()}
    try:
        return cls(**kwargs)
    except FieldError as exc:
        raise exc.with_prefix(prefix) from None
    except ConfigError:
        raise
    except (TypeError, ValueError) as exc:  # a library's own check, "<field>: <what is wrong>" (e.g. the U-Net's)
        key, sep, detail = str(exc).partition(": ")
        if not sep or key not in names:
            raise ConfigError(f"{prefix.rstrip('.') or cls.__name__}: {exc}") from None
        raise FieldError(key, "", data.get(key), detail=detail).with_prefix(prefix) from None


def to_dict(cfg: Any) -> dict[str, Any]:
    """Plain nested dict (YAML-serialisable) of a config dataclass."""
    def conv(v: Any) -> Any:
        if dataclasses.is_dataclass(v):
            return {f.name: conv(getattr(v, f.name)) for f in dataclasses.fields(v)}
        if isinstance(v, (list, tuple)):
            return [conv(x) for x in v]
        return v

    return conv(cfg)


def parse_override(text: str) -> tuple[list[str], Any]:
    """Split ``a.b.c=value`` into (["a","b","c"], value) with the value parsed as YAML."""
    if "=" not in text:
        raise ConfigError(f"override {text!r} is not of the form key=value")
    key, raw = text.split("=", 1)
    key = key.strip()
    if not key:
        raise ConfigError(f"override {text!r} has an empty key")
    try:
        value = yaml_load(raw) if raw.strip() else ""
    except yaml.YAMLError as exc:
        raise ConfigError(f"override {text!r}: cannot parse value: {_one_line(exc)}") from exc
    return key.split("."), value


def apply_overrides(data: dict[str, Any], overrides: list[str]) -> dict[str, Any]:
    """Return a copy of ``data`` with dotted ``key=value`` overrides applied."""
    out: dict[str, Any] = yaml.safe_load(yaml.safe_dump(data)) or {}
    for text in overrides:
        path, value = parse_override(text)
        node = out
        for part in path[:-1]:
            nxt = node.setdefault(part, {})
            if not isinstance(nxt, dict):
                raise ConfigError(f"override {text!r}: '{part}' is not a section")
            node = nxt
        node[path[-1]] = value
    return out


def _one_line(exc: Exception) -> str:
    """A parser's multi-line message on one line."""
    return " ".join(str(exc).split())


def merge(base: Mapping[str, Any], over: Mapping[str, Any]) -> dict[str, Any]:
    """``over`` deep-merged onto ``base`` (mappings merge key by key; any other value replaces)."""
    out = dict(base)
    for key, value in over.items():
        out[key] = merge(out[key], value) if isinstance(value, Mapping) and isinstance(out.get(key), Mapping) \
            else value
    return out


def read_yaml(path: str | Path, _seen: tuple[Path, ...] = ()) -> dict[str, Any]:
    """Read a YAML mapping, with a clear error for a missing or malformed file.

    A top-level ``base: <file>`` (relative to this file's folder) includes another config: this file's
    keys are deep-merged onto it (:func:`merge`), so a variant names only what it changes.
    """
    p = Path(path)
    data = _read_mapping(p)
    if "base" not in data:
        return data
    base = data.pop("base")
    if not isinstance(base, str) or not base:
        raise ConfigError(f"{p}: base: expected a config file name, got {base!r}")
    base_path = p.parent / base
    if base_path.resolve() in _seen or base_path.resolve() == p.resolve():
        raise ConfigError(f"{p}: base: {base} includes itself")
    return merge(read_yaml(base_path, _seen + (p.resolve(),)), data)


def _read_mapping(p: Path) -> dict[str, Any]:
    """One YAML file as a mapping (no includes)."""
    if not p.is_file():
        raise ConfigError(f"config file not found: {p}")
    try:
        text = p.read_bytes().decode("utf-8")
    except UnicodeDecodeError as exc:
        raise ConfigError(f"config file {p} is not UTF-8 text (binary or corrupt?): {exc}") from exc
    except OSError as exc:
        raise ConfigError(f"config file {p} cannot be read: {exc.strerror or exc}") from exc
    if "\x00" in text:
        raise ConfigError(f"config file {p} is not a text file (it contains NUL bytes)")
    try:
        data = yaml_load(text)
    except yaml.YAMLError as exc:
        raise ConfigError(f"config file {p} is not valid YAML: {_one_line(exc)}") from exc
    if data is None:
        return {}
    if not isinstance(data, dict):
        raise ConfigError(f"config file {p} must contain a mapping at the top level")
    return data


def load_config(cls: type[T], data: Mapping[str, Any], overrides: list[str] | None = None) -> T:
    """Build ``cls`` from a mapping plus dotted overrides (strict)."""
    return from_dict(cls, apply_overrides(dict(data), list(overrides or [])))
