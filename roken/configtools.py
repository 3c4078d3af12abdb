"""YAML -> typed dataclasses, with `--set dotted.key=value` overrides.

Every stage owns a small dataclass config; `roken.config.Config` nests them. Loading is strict: an unknown
key or a value of the wrong type is an error that names the key, so a typo in a 5000-map run fails at once
instead of silently running with a default.
"""
from __future__ import annotations

import dataclasses
import types
import typing
from pathlib import Path
from typing import Any

import yaml


class ConfigError(ValueError):
    """A config file or override that does not fit the schema."""


def _coerce(value: Any, tp: Any, key: str) -> Any:
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
            except ConfigError as e:
                errors.append(str(e))
        raise ConfigError(f"{key}: {value!r} does not fit {tp}")
    if dataclasses.is_dataclass(tp):
        if not isinstance(value, dict):
            raise ConfigError(f"{key}: expected a mapping, got {value!r}")
        return from_dict(tp, value, prefix=key + ".")
    if origin in (list, tuple):
        if isinstance(value, str):  # "2,4,8" on the command line
            value = [v for v in value.split(",") if v.strip()]
        if not isinstance(value, (list, tuple)):
            value = [value]
        inner = args[0] if args else Any
        return [_coerce(v, inner, f"{key}[{i}]") for i, v in enumerate(value)]
    if origin is dict:
        if not isinstance(value, dict):
            raise ConfigError(f"{key}: expected a mapping, got {value!r}")
        kt, vt = args if args else (Any, Any)
        return {_coerce(k, kt, key): _coerce(v, vt, f"{key}.{k}") for k, v in value.items()}
    if tp is bool:
        if isinstance(value, bool):
            return value
        if isinstance(value, str) and value.lower() in ("true", "false", "1", "0", "yes", "no"):
            return value.lower() in ("true", "1", "yes")
        raise ConfigError(f"{key}: expected true/false, got {value!r}")
    if tp is int:
        if isinstance(value, bool) or not isinstance(value, (int, str)):
            raise ConfigError(f"{key}: expected an integer, got {value!r}")
        try:
            return int(value)
        except ValueError:
            raise ConfigError(f"{key}: expected an integer, got {value!r}") from None
    if tp is float:
        if isinstance(value, bool):
            raise ConfigError(f"{key}: expected a number, got {value!r}")
        try:
            return float(value)
        except (TypeError, ValueError):
            raise ConfigError(f"{key}: expected a number, got {value!r}") from None
    if tp is str:
        if isinstance(value, (dict, list)):
            raise ConfigError(f"{key}: expected a string, got {value!r}")
        return str(value)
    return value


def from_dict(cls: type, data: dict, prefix: str = "") -> Any:
    """Build dataclass `cls` from `data`; unknown keys and bad types raise ConfigError."""
    hints = typing.get_type_hints(cls)
    names = {f.name for f in dataclasses.fields(cls)}
    unknown = sorted(set(data) - names)
    if unknown:
        raise ConfigError(
            f"unknown config key(s) {', '.join(prefix + k for k in unknown)}; "
            f"valid keys under '{prefix.rstrip('.') or 'top level'}': {', '.join(sorted(names))}"
        )
    kwargs = {k: _coerce(v, hints[k], prefix + k) for k, v in data.items()}
    return cls(**kwargs)


def to_dict(cfg: Any) -> dict:
    return dataclasses.asdict(cfg)


def _set_dotted(tree: dict, dotted: str, value: Any) -> None:
    parts = dotted.split(".")
    node = tree
    for p in parts[:-1]:
        node = node.setdefault(p, {})
        if not isinstance(node, dict):
            raise ConfigError(f"--set {dotted}: '{p}' is not a section")
    node[parts[-1]] = value


def parse_override(text: str) -> tuple[str, Any]:
    if "=" not in text:
        raise ConfigError(f"--set expects dotted.key=value, got {text!r}")
    key, raw = text.split("=", 1)
    try:
        value = yaml.safe_load(raw) if raw.strip() else ""
    except yaml.YAMLError:
        value = raw
    return key.strip(), value


def _merge(base: dict, extra: dict, cls: type) -> dict:
    """`extra` over `base`; sections (dataclasses) merge key by key, any other value (a dict-valued field
    such as map.families included) is replaced whole, so a file lists exactly the families it wants."""
    out = dict(base)
    hints = typing.get_type_hints(cls)
    for k, v in extra.items():
        if isinstance(v, dict) and isinstance(out.get(k), dict) and dataclasses.is_dataclass(hints.get(k)):
            out[k] = _merge(out[k], v, hints[k])
        else:
            out[k] = v
    return out


def load(cls: type, path: str | Path | None = None, overrides: list[str] | None = None) -> Any:
    """Defaults of `cls`, then the YAML file at `path`, then each `dotted.key=value` override."""
    tree = to_dict(cls())
    if path is not None:
        p = Path(path)
        try:
            loaded = yaml.safe_load(p.read_text()) or {}
        except OSError as e:
            raise ConfigError(f"config {p}: cannot read ({e.strerror}); pass an existing YAML file") from None
        except yaml.YAMLError as e:
            raise ConfigError(f"config {p}: not valid YAML ({e})") from None
        if not isinstance(loaded, dict):
            raise ConfigError(f"config {p}: the top level must be a mapping")
        _check_keys(cls, loaded, "")
        tree = _merge(tree, loaded, cls)
    for text in overrides or []:
        key, value = parse_override(text)
        _check_path(cls, key)
        _set_dotted(tree, key, value)
    return from_dict(cls, tree)


def with_overrides(cfg: Any, overrides: dict[str, Any]) -> Any:
    """A copy of config `cfg` with `{dotted.key: value}` set, checked like --set (unknown keys are errors)."""
    tree = to_dict(cfg)
    for key, value in overrides.items():
        _check_path(type(cfg), key)
        _set_dotted(tree, key, value)
    return from_dict(type(cfg), tree)


def _check_keys(cls: type, data: dict, prefix: str) -> None:
    from_dict_keys = {f.name: f for f in dataclasses.fields(cls)}
    hints = typing.get_type_hints(cls)
    for k, v in data.items():
        if k not in from_dict_keys:
            raise ConfigError(
                f"unknown config key {prefix + k}; valid keys: {', '.join(sorted(from_dict_keys))}"
            )
        if dataclasses.is_dataclass(hints[k]) and isinstance(v, dict):
            _check_keys(hints[k], v, prefix + k + ".")


def _check_path(cls: type, dotted: str) -> None:
    node = cls
    parts = dotted.split(".")
    for i, p in enumerate(parts):
        if not dataclasses.is_dataclass(node):
            raise ConfigError(f"--set {dotted}: '{'.'.join(parts[:i])}' is not a section")
        hints = typing.get_type_hints(node)
        if p not in hints:
            raise ConfigError(
                f"--set {dotted}: unknown key '{p}'; valid keys here: {', '.join(sorted(hints))}"
            )
        node = hints[p]


# Fields added to a config section after evaluation folders were being written, in the order they were added,
# each with the value that gives the behaviour from before it existed. A stored config, or an episode file's
# fingerprint, from before a field existed reads as having it at that value, so that adding a field never stops
# a finished evaluation from resuming (roken/eval/folder.py). Adding a config field that the episode
# fingerprint hashes (a plan.* field): append it here; tests/test_resume_fields.py checks that none is missing.
LATER_FIELDS: tuple[tuple[str, Any], ...] = (
    ("plan.noise", "fresh"),  # 2026-12-01
    ("plan.verify_moves", 0),  # 2026-12-02
    ("plan.guide_follow", 0.0),
    ("plan.guide_follow_range", 10.0),
    ("plan.noise_scale", 1.0),
    ("plan.subgoal", 0.0),
    ("plan.subgoal_sight", True),
    ("plan.subgoal_after_hold", 0),
    ("plan.select_team", 0.0),  # 2026-12-03
    ("plan.geo_inflate", 0.0),
    ("plan.geo_inflate_weight", 2.0),
    ("plan.verify_steps", False),  # 2026-12-04
    ("plan.keep_previous", False),  # 2026-12-05
    ("dataset.restart_every", 0),  # 2026-12-06
    ("expert.warm_start", False),
    ("model.prev_move", False),  # 2026-12-06, fourth session
    ("samples.prev_noise", 0.0),
    ("samples.early_prob", 0.0),
    ("samples.early_steps", 40),
    ("expert.disturb", 0.0),  # 2026-12-07, ninth session
    ("expert.disturb_steps", 8),
    ("expert.disturb_mode", "random"),
    ("dataset.disturb_window", 16),
)


def with_later_fields(d: dict) -> dict:
    """A copy of config dict `d` (to_dict's nesting) with every LATER_FIELDS key its section lacks set to the
    value from before the field existed (a section `d` does not hold stays absent)."""
    out = {k: (dict(v) if isinstance(v, dict) else v) for k, v in d.items()}
    for dotted, value in LATER_FIELDS:
        section, key = dotted.split(".", 1)
        if isinstance(out.get(section), dict) and key not in out[section]:
            out[section][key] = value
    return out


def without_later_fields(d: dict, since: int = 0) -> dict:
    """A copy of config dict `d` without the fields LATER_FIELDS[since:] that are at the value from before they
    existed: the dict a config of that era would have hashed (since = len(LATER_FIELDS): `d` itself)."""
    out = {k: (dict(v) if isinstance(v, dict) else v) for k, v in d.items()}
    for dotted, value in LATER_FIELDS[since:]:
        section, key = dotted.split(".", 1)
        if isinstance(out.get(section), dict) and key in out[section] and out[section][key] == value:
            del out[section][key]
    return out
