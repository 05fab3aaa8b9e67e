"""The study config: one frozen dataclass per stage, composed, with named presets.

A run writes its resolved config as ``config.json`` at the top of its folder;
``load_config`` reads it back, so every stage (and a resumed run) sees exactly
the settings the run started with.
"""

from __future__ import annotations

import dataclasses
import json
import math
import tomllib
import typing
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

from clothgap.errors import ConfigError
from eval.config import EvalConfig
from learn.config import TrainConfig
from render.config import RenderConfig
from sim.config import SimConfig


@dataclass(frozen=True)
class StudyConfig:
    name: str = "study"
    seed: int = 0
    sim: SimConfig = field(default_factory=SimConfig)
    render: RenderConfig = field(default_factory=RenderConfig)
    train: TrainConfig = field(default_factory=TrainConfig)
    eval: EvalConfig = field(default_factory=EvalConfig)


def _smoke() -> StudyConfig:
    # Four classes at the corners of the (p, k) grid, four sequences each: a real
    # study that finishes in a minute on 2 CPU cores. Two variants (the paper's random
    # textures and the grid), so the domain-gap matrix, the axis ranking and the side-by-side
    # frames of the report have something to show.
    return StudyConfig(
        name="smoke",
        sim=SimConfig(classes=(0, 8, 45, 53), sequences_per_class=4, grid_vertices=16, frames=20, device="cpu"),
        render=RenderConfig(variants=("paper", "grid"), resolution=32, spp=2),
        train=TrainConfig(models=("lrcn",), image_size=32, epochs=6, batch_size=8, width=16, fc6=64,
                          hidden=32, val_fraction=0.0, test_fraction=0.25, lr=2e-3),
        eval=EvalConfig(bootstrap=200),
    )


def _small() -> StudyConfig:
    # All 54 classes, a few sequences each: a CPU afternoon or a GPU minute.
    return StudyConfig(
        name="small",
        sim=SimConfig(motions=("wind", "arm"), sequences_per_class=6, frames=30),
        render=RenderConfig(variants=("paper",), resolution=64, spp=4),
        train=TrainConfig(models=("lrcn", "base1"), epochs=15),
        eval=EvalConfig(measured_sequences=2, sim_analysis=("table2", "sensitivity")),
    )


def _paper() -> StudyConfig:
    # The paper's scale for one GPU: 2,592 sequences per setting (Section 7.1). Wind clips vary
    # only the wind speed, as the paper varies "the external force magnitude" (docs/learnability.md:
    # with pose, gathering and direction drawn too, the geometry of new simulations tells a plain MLP
    # 27 % of the classes; with speed alone, 84 %); arm clips likewise draw only the forearm's speed
    # (placement drawn too: 27 % on 864 clips; speed alone: 50 %, docs/learnability.md section 4).
    # The best recipe of docs/learning.md, chosen on validation clips: the CNN regresses the cloth's
    # lattice from each frame and its difference from the previous one, the classes are read from that
    # lattice alone (bottleneck), fc6 without dropout (with AlexNet's 0.5 the regressor barely leaves
    # the mean shape), best validation epoch kept.
    return StudyConfig(
        name="paper",
        sim=SimConfig(motions=("wind", "arm"), remeshing=("uniform1", "uniform2", "uniform3", "adaptive"),
                      sequences_per_class=48, frames=40, device="cuda", wind_nuisance="speed",
                      arm_nuisance="speed"),
        # frames.npy only: PNG and EXR cost more host time than the path tracer at 112 px (render.frames)
        render=RenderConfig(variants=("paper",), resolution=112, spp=16, backend="cuda_ad_rgb",
                            write_png=False, write_hdr=False),
        train=TrainConfig(models=("lrcn", "base1", "base2", "base3"), image_size=112, epochs=30,
                          batch_size=64, width=64, fc6=512, hidden=256, device="cuda",
                          motion=True, keep="best", bottleneck=True, dropout=0.0),
        eval=EvalConfig(measured_sequences=4, sim_analysis=("table2", "sensitivity")),
    )


# The paper's Table 3: per motion, adaptive meshes with grid, colour and random textures, and uniform
# 1-3 with random ones: twelve (setting, texture) datasets.
TABLE3_PAIRS = tuple(f"{variant}:{motion}-adaptive" for variant in ("grid", "color") for motion in ("wind", "arm"))


def _study() -> StudyConfig:
    # The paper's whole study on one GPU: the paper preset plus the grid and colour textures on the
    # adaptive settings only (render.variant_settings), twelve datasets in all.
    base = _paper()
    return replace(base, name="study", render=replace(base.render, variants=("paper", "grid", "color"),
                                                      variant_settings=TABLE3_PAIRS))


PRESETS: dict[str, typing.Callable[[], StudyConfig]] = {"smoke": _smoke, "small": _small, "paper": _paper,
                                                        "study": _study}


def preset(name: str) -> StudyConfig:
    try:
        return PRESETS[name]()
    except KeyError:
        raise ConfigError(f"unknown preset {name!r}; known presets: {', '.join(PRESETS)}") from None


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


def apply_overrides(cfg: StudyConfig, overrides: list[str]) -> StudyConfig:
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
    return from_dict(StudyConfig, data)


def read_config_file(path: Path | str) -> tuple[str | None, dict]:
    """A study's settings kept in a TOML file: ``(preset named in it or None, the settings as nested tables)``.

    The file has the shape of ``config.json``, with an optional top-level ``preset`` to start from::

        preset = "smoke"
        [render]
        variants = ["paper", "grid"]
        [sim]
        frames = 30

    A missing or unreadable file, bad TOML or a ``preset`` that is not a string is a ConfigError naming the file;
    unknown settings are named when the settings are applied (``apply_settings``).
    """
    path = Path(path)
    try:
        with path.open("rb") as f:
            data = tomllib.load(f)
    except FileNotFoundError:
        raise ConfigError(f"config file {path} does not exist") from None
    except IsADirectoryError:
        raise ConfigError(f"config file {path} is a folder, not a TOML file") from None
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as e:
        raise ConfigError(f"config file {path} is not valid TOML ({e})") from None
    except OSError as e:
        raise ConfigError(f"config file {path} cannot be read: {e.strerror or e}") from None
    name = data.pop("preset", None)
    if name is not None and not isinstance(name, str):
        raise ConfigError(f"{path}: preset must be a preset's name ({', '.join(PRESETS)}), got {name!r}")
    return name, data


def apply_settings(cfg: StudyConfig, settings: dict, where: str = "config") -> StudyConfig:
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
        return from_dict(StudyConfig, data)
    except ConfigError as e:
        raise ConfigError(f"{where}: {e}") from None


# ---------------------------------------------------------------- changing a run's config

# Settings that say where or how fast work runs, not what it computes (within float rounding across devices),
# and the run's name: a resumed run may change them at any time.
# (render.write_png / write_hdr only add inspection files; clips rendered before keep what they wrote.)
EXECUTION_SETTINGS = frozenset({"name", "sim.device", "sim.batch_size", "render.writer_threads", "render.write_png",
                                "render.write_hdr", "train.device", "train.num_threads", "train.num_workers"})
# Settings added after runs existed whose default is what the code did before they existed: a run's
# config.json without one was made by an older clothgap and gets the default (recorded), not an error.
# Adding a setting whose default changes results means leaving it out of this set.
DEFAULT_KEEPS_OLD_BEHAVIOUR = frozenset({"sim.self_collision", "sim.collision_thickness", "train.bottleneck",
                                         "train.bottleneck_noise", "train.reader_truth", "train.aux_geometry", "train.label_smoothing",
                                         "sim.arm_nuisance"})
# Lists a resumed run may extend: an item more is more work downstream, nothing finished changes.
GROWING_SETTINGS = frozenset({"sim.motions", "sim.remeshing", "render.variants", "train.models", "train.seeds"})
# The stages in order; a setting shapes the work of its own stage and of every stage after it.
STAGES = ("sim", "render", "train", "eval")


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


def changed_settings(old: StudyConfig, new: StudyConfig) -> dict[str, tuple[Any, Any]]:
    """``{"section.key": (old value, new value)}`` for every setting that differs."""
    a, b = _flat(to_dict(old)), _flat(to_dict(new))
    return {k: (a[k], b[k]) for k in a if a[k] != b[k]}


def invalidating_settings(old: StudyConfig, new: StudyConfig) -> dict[str, str]:
    """The changed settings that would make a stage's finished work disagree with the config:
    ``{"section.key": first stage it shapes}``.

    Not listed: execution settings (``EXECUTION_SETTINGS``), lists that only grow (``GROWING_SETTINGS``: more
    settings, variants, models or seeds), ``render.variant_settings`` when every variant keeps the settings it
    had, and ``eval.*`` (``clothgap eval`` recomputes its tables and checks what it reuses). The run seed shapes
    the simulations, hence everything.
    """
    out = {}
    for key, (before, after) in changed_settings(old, new).items():
        section = key.partition(".")[0]
        if key in EXECUTION_SETTINGS or section == "eval":
            continue
        if key in GROWING_SETTINGS and set(before) <= set(after):
            continue
        if key == "render.variant_settings":
            settings = new.sim.settings()
            if all(set(old.render.settings_of(v, settings)) <= set(new.render.settings_of(v, settings))
                   for v in old.render.variants):
                continue
        out[key] = section if section in STAGES else "sim"
    return out


def problems(cfg: StudyConfig) -> list[str]:
    """Everything wrong with a resolved config: its own settings', then each stage's."""
    out = []
    if not cfg.name or "/" in cfg.name or "\\" in cfg.name:
        out.append(f"name={cfg.name!r}: must be a non-empty folder name")
    if cfg.seed < 0:
        out.append(f"seed={cfg.seed}: must be >= 0")
    for stage in (cfg.sim, cfg.render, cfg.train, cfg.eval):
        out += stage.problems()
    if cfg.sim.frames < cfg.train.clip_len:
        # Found here, not after sim and render ran: a clip shorter than one window gives no training item.
        out.append(f"sim.frames={cfg.sim.frames} is shorter than train.clip_len={cfg.train.clip_len}: "
                   "every clip must hold at least one sub-sequence")
    settings = cfg.sim.settings()
    for pair in cfg.render.variant_settings:
        setting = pair.partition(":")[2]
        if setting and setting not in settings:
            out.append(f"render.variant_settings: {pair!r} names setting {setting!r}, which the run does not "
                       f"simulate ({', '.join(settings)})")
    return out


def pairs(cfg: StudyConfig) -> list[tuple[str, str]]:
    """(setting, variant) pairs the run renders, trains and evaluates, setting-major."""
    return [(setting, variant) for setting in cfg.sim.settings() for variant in cfg.render.variants
            if setting in cfg.render.settings_of(variant, cfg.sim.settings())]


def validate(cfg: StudyConfig, where: str = "") -> StudyConfig:
    """``cfg`` when it is valid, else a ConfigError naming every bad setting, its value and what is allowed.

    Called when a run starts and whenever a run's config.json is loaded, so bad
    settings fail before any work (and never deep inside Warp, Mitsuba or torch).
    """
    found = problems(cfg)
    if len(found) == 1:
        raise ConfigError(f"{where}{found[0]}")
    if found:
        raise ConfigError(f"{where}{len(found)} invalid settings:\n  " + "\n  ".join(found))
    return cfg


def save_config(cfg: StudyConfig, path: Path) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".tmp")
    try:
        tmp.write_text(json.dumps(to_dict(cfg), indent=2) + "\n")
        tmp.replace(path)
    except BaseException:
        tmp.unlink(missing_ok=True)     # a full disk leaves no half-written config behind
        raise


def load_config(path: Path, check: bool = True) -> StudyConfig:
    """A run's config.json, validated (``check=False``: only parsed, for workers whose driver validated it)."""
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
    cfg = from_dict(StudyConfig, data)
    return validate(cfg, f"{path}: ") if check else cfg


def with_name(cfg: StudyConfig, name: str) -> StudyConfig:
    return replace(cfg, name=name)
