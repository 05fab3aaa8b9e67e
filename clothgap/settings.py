"""Settings kept as frozen dataclasses: built from plain data, laid over, compared, checked, written and read.

Generic over the config class, so the ground floor imports no stage: each stage's own config (``sim.config``,
...) and the study config that composes them (``clothgap.config``, top floor) are handled by the same functions.
A run folder's ``config.json`` is read as the study config that the top floor registers with
``use_study_config`` when it is imported (every entry point imports it: the CLI, the API, the executor,
``python -m learn``).
"""

from __future__ import annotations

import dataclasses
import json
import math
import typing
from pathlib import Path
from typing import Any

from clothgap.errors import ConfigError
from clothgap.files import atomic_write_text

# ---------------------------------------------------------------- (de)serialisation


def to_dict(cfg: Any) -> dict:
    return dataclasses.asdict(cfg)


def _coerce(tp: Any, value: Any, where: str) -> Any:
    origin = typing.get_origin(tp)
    if dataclasses.is_dataclass(tp):
        if not isinstance(value, dict):
            raise ConfigError(f"{where}: expected a table of settings, got {value!r}")
        return from_dict(tp, value, where)
    if origin is tuple:
        if isinstance(value, str):
            value = [v for v in value.split(",") if v]
        if not isinstance(value, (list, tuple)):
            raise ConfigError(f"{where}: expected a list, got {value!r}")
        (item_tp, _ellipsis) = typing.get_args(tp)
        return tuple(_coerce(item_tp, v, where) for v in value)
    if tp is bool:
        if isinstance(value, str):
            if value.lower() in ("1", "true", "yes", "on"):
                return True
            if value.lower() in ("0", "false", "no", "off"):
                return False
            raise ConfigError(f"{where}: expected true or false, got {value!r}")
        return bool(value)
    if tp in (int, float, str):
        if tp is not str and isinstance(value, (dict, list, tuple, bool)):
            raise ConfigError(f"{where}: expected {tp.__name__}, got {value!r}")
        try:
            out = tp(value)
        except (TypeError, ValueError, OverflowError):
            raise ConfigError(f"{where}: expected {tp.__name__}, got {value!r}") from None
        if tp is float and not math.isfinite(out):
            raise ConfigError(f"{where}: expected a finite number, got {value!r}")
        return out
    return value


def from_dict(cls: type, data: dict, where: str = "config") -> Any:
    """Build a (nested) config dataclass from plain data, naming any unknown key."""
    hints = typing.get_type_hints(cls)
    names = {f.name for f in dataclasses.fields(cls)}
    unknown = set(data) - names
    if unknown:
        raise ConfigError(f"{where}: unknown setting(s) {', '.join(sorted(unknown))}; "
                          f"known: {', '.join(sorted(names))}")
    kwargs = {k: _coerce(hints[k], v, f"{where}.{k}") for k, v in data.items()}
    return cls(**kwargs)


def apply_overrides(cfg: Any, overrides: list[str]) -> Any:
    """Apply ``section.key=value`` overrides, e.g. ``sim.frames=30`` or ``render.variants=paper,grid``."""
    data = to_dict(cfg)
    for item in overrides:
        if "=" not in item:
            raise ConfigError(f"override {item!r} is not of the form section.key=value")
        path, value = item.split("=", 1)
        keys = path.strip().split(".")
        node = data
        for key in keys[:-1]:
            if not isinstance(node.get(key), dict):
                raise ConfigError(f"override {item!r}: {key!r} is not a config section "
                                  f"(sections: {', '.join(k for k, v in data.items() if isinstance(v, dict))})")
            node = node[key]
        if keys[-1] not in node:
            raise ConfigError(f"override {item!r}: unknown setting {keys[-1]!r}; "
                              f"known: {', '.join(sorted(node))}")
        node[keys[-1]] = value
    return from_dict(type(cfg), data)


def apply_settings(cfg: Any, settings: dict, where: str = "config") -> Any:
    """``cfg`` with the nested tables of ``settings`` laid over it (what a config file gives).

    Only the keys named change; an unknown section or setting is a ConfigError naming it, ``where`` and what is known.
    """
    data = to_dict(cfg)

    def lay(node: dict, new: dict, at: str) -> None:
        for key, value in new.items():
            if key not in node:
                raise ConfigError(f"{where}: unknown setting {at}{key}; known: {', '.join(sorted(node))}")
            if isinstance(node[key], dict):
                if not isinstance(value, dict):
                    raise ConfigError(f"{where}: {at}{key} is a section ([{at}{key}] in TOML), got {value!r}")
                lay(node[key], value, f"{at}{key}.")
            else:
                node[key] = value

    lay(data, settings, "")
    try:
        return from_dict(type(cfg), data)
    except ConfigError as e:
        raise ConfigError(f"{where}: {e}") from None


# ---------------------------------------------------------------- comparing and checking


def _flat(data: dict, prefix: str = "") -> dict:
    out = {}
    for key, value in data.items():
        if isinstance(value, dict):
            out.update(_flat(value, f"{prefix}{key}."))
        else:
            out[f"{prefix}{key}"] = value
    return out


def shown(value: Any) -> str:
    """A setting's value as ``--set`` takes it (lists joined by commas)."""
    return ",".join(map(str, value)) if isinstance(value, (list, tuple)) else str(value)


def changed_settings(old: Any, new: Any) -> dict[str, tuple[Any, Any]]:
    """``{"section.key": (old value, new value)}`` for every setting that differs."""
    a, b = _flat(to_dict(old)), _flat(to_dict(new))
    return {k: (a[k], b[k]) for k in a if a[k] != b[k]}


def validate(cfg: Any, where: str = "") -> Any:
    """``cfg`` when it is valid, else a ConfigError naming every bad setting, its value and what is allowed.

    Called when a run starts and whenever a run's config.json is loaded, so bad
    settings fail before any work (and never deep inside Warp, Mitsuba or torch).
    The config says what is wrong with it: ``cfg.problems()``.
    """
    found = cfg.problems()
    if len(found) == 1:
        raise ConfigError(f"{where}{found[0]}")
    if found:
        raise ConfigError(f"{where}{len(found)} invalid settings:\n  " + "\n  ".join(found))
    return cfg


# ---------------------------------------------------------------- the study config a run folder holds

_study_config: list[type] = []


def use_study_config(cls: type) -> type:
    """Make ``cls`` the config that run folders hold (``config.json``); returns ``cls``, so it works as a decorator.

    Besides being a dataclass of settings, the class gives what ``clothgap.runs`` asks of it: ``problems()``,
    ``invalidating_settings(old)``, ``missing_setting_stage(key)`` and ``STAGES``.
    """
    _study_config[:] = [cls]
    return cls


def study_config() -> type:
    """The registered study config class (``clothgap.config.StudyConfig``)."""
    if not _study_config:
        raise ConfigError("no study config is loaded, so a run's config.json cannot be read: import clothgap.config "
                          "(or clothgap.api) before opening a run")
    return _study_config[0]


def save_config(cfg: Any, path: Path) -> None:
    atomic_write_text(path, json.dumps(to_dict(cfg), indent=2) + "\n")


def load_config(path: Path, check: bool = True) -> Any:
    """A run's config.json as the study config, validated (``check=False``: only parsed, for workers whose
    driver validated it)."""
    cls = study_config()
    if not path.is_file():
        raise ConfigError(f"no config at {path}: is this a clothgap run folder? "
                          "(start one with `clothgap sim --preset NAME --out DIR`)")
    try:
        data = json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise ConfigError(f"{path} is not valid JSON ({e})") from None
    except OSError as e:
        raise ConfigError(f"{path} cannot be read: {e.strerror or e}") from None
    if not isinstance(data, dict):
        raise ConfigError(f"{path}: expected a table of settings, got {type(data).__name__}")
    cfg = from_dict(cls, data)
    return validate(cfg, f"{path}: ") if check else cfg
