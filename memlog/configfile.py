"""Config files (TOML, YAML, JSON) and typed construction of memlog's config dataclasses.

A config file holds one table per part of the pipeline (``[score]``, ``[select]``, ...), or the
scoring settings at top level (the original format). :func:`build` turns a mapping into a config
dataclass, checking every key and value against the field's type, so a mistake names the file,
the table, the key and what was expected::

    drive.toml: [score] mt: expected a number, got 'high' (str)
"""

from __future__ import annotations

import dataclasses
import json
import os
import types
import typing
from collections.abc import Mapping
from pathlib import Path
from typing import Any, TypeVar

from memlog.errors import ConfigError

__all__ = ["read_config_file", "config_section", "build", "check_ints", "SECTIONS"]

T = TypeVar("T")

#: The tables a config file may hold.
SECTIONS = ("score", "select", "map", "localize", "evaluate", "batch")


def read_config_file(path: str | os.PathLike[str]) -> dict[str, Any]:
    """The whole file as a dict; :class:`ConfigError` naming the file when it cannot be read."""
    p = Path(path)
    if not p.is_file():
        raise ConfigError(f"--config {p}: no such file")
    try:
        text = p.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise ConfigError(f"--config {p}: cannot read it ({exc})") from None
    suffix = p.suffix.lower()
    if suffix == ".toml":
        import tomllib

        try:
            data: Any = tomllib.loads(text)
        except tomllib.TOMLDecodeError as exc:
            raise ConfigError(f"{p}: invalid TOML: {exc}") from None
    elif suffix in (".yaml", ".yml"):
        from ruamel.yaml import YAML
        from ruamel.yaml.error import YAMLError

        try:
            data = YAML(typ="safe").load(text) or {}
        except YAMLError as exc:
            raise ConfigError(f"{p}: invalid YAML: {exc}") from None
    elif suffix == ".json":
        try:
            data = json.loads(text)
        except ValueError as exc:
            raise ConfigError(f"{p}: invalid JSON: {exc}") from None
    else:
        raise ConfigError(f"--config {p}: config files must be .toml, .yaml/.yml or .json")
    if not isinstance(data, dict):
        raise ConfigError(f"{p}: the top level must be a table of settings")
    return data


def config_section(data: Mapping[str, Any], name: str, where: str) -> dict[str, Any]:
    """The ``[name]`` table of a config file. Scoring settings may also sit at top level (then no
    other table may be there); unknown tables are refused."""
    tables = {k for k, v in data.items() if isinstance(v, dict)}
    unknown = tables - set(SECTIONS)
    if unknown:
        raise ConfigError(f"{where}: unknown table(s) {', '.join(sorted(unknown))} (known: {', '.join(SECTIONS)})")
    if not tables:  # the original format: scoring settings at top level
        return dict(data) if name == "score" else {}
    loose = sorted(set(data) - tables)
    if loose:
        raise ConfigError(f"{where}: setting(s) {', '.join(loose)} outside a table; put them under [score], "
                          "[select] ...")
    section = data.get(name, {})
    return dict(section)


def _type_name(tp: Any) -> str:
    if tp is float:
        return "a number"
    if tp is int:
        return "an integer"
    if tp is bool:
        return "true or false"
    if tp is str:
        return "a string"
    origin = typing.get_origin(tp)
    if origin is typing.Literal:
        return "one of " + ", ".join(repr(a) for a in typing.get_args(tp))
    if origin in (tuple, list):
        return "a list"
    return str(tp)


def _coerce(value: Any, tp: Any, where: str) -> Any:
    """``value`` checked against the annotation ``tp`` (and lists turned into tuples)."""
    origin = typing.get_origin(tp)
    if origin in (typing.Union, types.UnionType):
        args = typing.get_args(tp)
        if value is None and type(None) in args:
            return None
        errors = []
        for a in args:
            if a is type(None):
                continue
            try:
                return _coerce(value, a, where)
            except ConfigError as exc:
                errors.append(str(exc))
        raise ConfigError(errors[0] if len(errors) == 1 else
                          f"{where}: expected {' or '.join(_type_name(a) for a in args if a is not type(None))}, "
                          f"got {value!r} ({type(value).__name__})")
    if origin is typing.Literal:
        if value not in typing.get_args(tp):
            raise ConfigError(f"{where}: expected {_type_name(tp)}, got {value!r}")
        return value
    if origin in (tuple, list):
        if not isinstance(value, (list, tuple)):
            raise ConfigError(f"{where}: expected a list, got {value!r} ({type(value).__name__})")
        item_types = [a for a in typing.get_args(tp) if a is not Ellipsis]
        item = item_types[0] if item_types else Any
        if origin is tuple and len(item_types) > 1 and Ellipsis not in typing.get_args(tp):
            if len(value) != len(item_types):
                raise ConfigError(f"{where}: expected a list of {len(item_types)} values, got {len(value)}")
            return tuple(_coerce(v, a, f"{where}[{i}]") for i, (v, a) in enumerate(zip(value, item_types)))
        items = [_coerce(v, item, f"{where}[{i}]") for i, v in enumerate(value)]
        return tuple(items) if origin is tuple else items
    if tp is Any:
        return value
    if isinstance(tp, type) and dataclasses.is_dataclass(tp):  # a nested config: a table of its settings
        if isinstance(value, tp):
            return value
        if not isinstance(value, Mapping):
            raise ConfigError(f"{where}: expected a table of settings, got {value!r} ({type(value).__name__})")
        return build(tp, value, where)
    if tp is bool:
        if not isinstance(value, bool):
            raise ConfigError(f"{where}: expected true or false, got {value!r} ({type(value).__name__})")
        return value
    if tp is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(f"{where}: expected an integer, got {value!r} ({type(value).__name__})")
        return value
    if tp is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ConfigError(f"{where}: expected a number, got {value!r} ({type(value).__name__})")
        return float(value)
    if tp is str:
        if not isinstance(value, str):
            raise ConfigError(f"{where}: expected a string, got {value!r} ({type(value).__name__})")
        return value
    return value


def check_ints(config: Any, limits: Mapping[str, int], *, optional: bool = False) -> None:
    """The config dataclasses' integer check: ConfigError unless each field named in ``limits``
    is an integer (not a bool) at least its limit; with ``optional``, None passes too."""
    for name, low in limits.items():
        v = getattr(config, name)
        if v is None and optional:
            continue
        if isinstance(v, bool) or not isinstance(v, int) or v < low:
            raise ConfigError(f"{name} must be an integer >= {low}, got {v!r}")


def build(cls: type[T], values: Mapping[str, Any], where: str = "config", base: T | None = None) -> T:
    """An instance of the config dataclass ``cls`` from ``values`` (over ``base``, else the
    defaults), every key and value type-checked; the dataclass's own checks run last."""
    hints = typing.get_type_hints(cls)
    fields = {f.name for f in dataclasses.fields(cls) if f.init}  # type: ignore[arg-type]
    unknown = sorted(set(values) - fields)
    if unknown:
        raise ConfigError(f"{where}: unknown setting(s) {', '.join(unknown)} (known: {', '.join(sorted(fields))})")
    kw = {k: _coerce(v, hints[k], f"{where} {k}") for k, v in values.items()}
    try:
        if base is not None:
            return dataclasses.replace(base, **kw)  # type: ignore[type-var]
        return cls(**kw)
    except ConfigError as exc:
        raise ConfigError(f"{where}: {exc}") from None
