"""The study config: the four stages' configs composed, with named presets (top floor: it knows every stage).

A run writes its resolved config as ``config.json`` at the top of its folder;
``load_config`` reads it back, so every stage (and a resumed run) sees exactly
the settings the run started with. The generic reading, writing and overriding
lives in ``clothgap.settings`` (ground floor); importing this module registers
``StudyConfig`` there as the config a run folder holds.
"""

from __future__ import annotations

import tomllib
import typing
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import ClassVar

from clothgap.errors import ConfigError
from clothgap.settings import (apply_overrides, apply_settings, changed_settings, from_dict, load_config,  # noqa: F401
                               save_config, shown, to_dict, use_study_config, validate)
from eval.config import EvalConfig
from learn.config import TrainConfig
from render.config import RenderConfig
from sim.config import SimConfig


@use_study_config
@dataclass(frozen=True)
class StudyConfig:
    name: str = "study"
    seed: int = 0
    sim: SimConfig = field(default_factory=SimConfig)
    render: RenderConfig = field(default_factory=RenderConfig)
    train: TrainConfig = field(default_factory=TrainConfig)
    eval: EvalConfig = field(default_factory=EvalConfig)

    # The stages in order; a setting shapes the work of its own stage and of every stage after it.
    STAGES: ClassVar[tuple[str, ...]] = ("sim", "render", "train", "eval")

    def pairs(self) -> list[tuple[str, str]]:
        """(setting, variant) pairs the run renders, trains and evaluates, setting-major."""
        settings = self.sim.settings()
        return [(setting, variant) for setting in settings for variant in self.render.variants
                if setting in self.render.settings_of(variant, settings)]

    def problems(self) -> list[str]:
        """Everything wrong with a resolved config: its own settings', then each stage's."""
        out = []
        if not self.name or "/" in self.name or "\\" in self.name:
            out.append(f"name={self.name!r}: must be a non-empty folder name")
        if self.seed < 0:
            out.append(f"seed={self.seed}: must be >= 0")
        for stage in (self.sim, self.render, self.train, self.eval):
            out += stage.problems()
        if self.sim.frames < self.train.clip_len:
            # Found here, not after sim and render ran: a clip shorter than one window gives no training item.
            out.append(f"sim.frames={self.sim.frames} is shorter than train.clip_len={self.train.clip_len}: "
                       "every clip must hold at least one sub-sequence")
        settings = self.sim.settings()
        for pair in self.render.variant_settings:
            setting = pair.partition(":")[2]
            if setting and setting not in settings:
                out.append(f"render.variant_settings: {pair!r} names setting {setting!r}, which the run does not "
                           f"simulate ({', '.join(settings)})")
        return out

    def invalidating_settings(self, old: StudyConfig) -> dict[str, str]:
        """The settings changed from ``old`` that would make a stage's finished work disagree with this config:
        ``{"section.key": first stage it shapes}``.

        Not listed: execution settings (``EXECUTION_SETTINGS``), lists that only grow (``GROWING_SETTINGS``: more
        settings, variants, models or seeds), ``render.variant_settings`` when every variant keeps the settings it
        had, and ``eval.*`` (``clothgap eval`` recomputes its tables and checks what it reuses). The run seed shapes
        the simulations, hence everything.
        """
        out = {}
        for key, (before, after) in changed_settings(old, self).items():
            section = key.partition(".")[0]
            if key in EXECUTION_SETTINGS or section == "eval":
                continue
            if key in GROWING_SETTINGS and set(before) <= set(after):
                continue
            if _motion_of_setting(key) not in (None, *old.sim.motions):
                continue                    # it shapes one motion's clips only, and the run has none of them yet
            if key == "render.variant_settings":
                settings = self.sim.settings()
                if all(set(old.render.settings_of(v, settings)) <= set(self.render.settings_of(v, settings))
                       for v in old.render.variants):
                    continue
            out[key] = section if section in self.STAGES else "sim"
        return out

    @classmethod
    def missing_setting_stage(cls, key: str) -> str | None:
        """The first stage whose finished work depends on a setting that a run's config.json lacks; None when no
        result depends on it (execution and eval settings), or its default is what runs made before it existed
        did (``DEFAULT_KEEPS_OLD_BEHAVIOUR``): the default may then be filled in."""
        section = key.partition(".")[0]
        if key in EXECUTION_SETTINGS or key in DEFAULT_KEEPS_OLD_BEHAVIOUR or section in ("name", "eval"):
            return None
        return section if section in cls.STAGES else "sim"


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
    # The paper's setting (Section 7.1) for one GPU, with eight times its 2,592 sequences a setting. Wind clips vary
    # only the wind speed, as the paper varies "the external force magnitude" (docs/learnability.md:
    # with pose, gathering and direction drawn too, the geometry of new simulations tells a plain MLP
    # 27 % of the classes; with speed alone, 84 %); arm clips likewise draw only the forearm's speed
    # (placement drawn too: 27 % on 864 clips; speed alone: 50 %, docs/learnability.md section 4).
    # The best recipe of docs/learning.md, chosen on validation clips: the CNN regresses the cloth's
    # lattice from each frame and its difference from the previous one, the classes are read from that
    # lattice alone (bottleneck), fc6 without dropout (with AlexNet's 0.5 the regressor barely leaves
    # the mean shape), the readers trained on the true lattice too, both lattices noised (0.2), best
    # validation epoch kept, weight decay 0.05, and the whole 40-frame clip as one window in batches of 16
    # (measured at 40 epochs): against 20-frame windows in batches of 32 it reads +13.6 points [10.5, 16.6] of new
    # wind simulations (76.7 %, a second seed 77.1 %) and +14.7 [11.2, 18.0] of arm ones, chosen on
    # validation on both motions (wind 78.5 against 62.6 %, arm 39.6 against 25.3 %), for fewer frames a
    # step: with windows shorter than the clip the network memorises and misses the part of the motion a
    # window leaves out (the arm's sweep fills the first 8-19 frames). Twice
    # the paper's 48 sequences a class: with the same recipe, 96 a class read 57.6 % of new simulations
    # where the paper's 35 training sequences a class read 45.6 % (+11.9 points [9.6, 14.2], the largest
    # lever measured; docs/learning.md), for twice the render time of a setting. 80 epochs over 40 at
    # this size, chosen on validation windows on both motions (arm +3.3 points [+0.1, +6.7], wind +4.9
    # [+2.6, +7.0]; on test clips +4.0 and +6.5): at 40 the network still underfits (arm ends at 51-64 %
    # training accuracy, wind at 87-88 %); weight decay 0.01 and no lattice noise were not chosen. Self-collision
    # on: at 1.13x the GPU time of a setting it removes every intersecting triangle pair, which 71 of
    # 2,592 wind clips had (docs/simulation.md). One lattice regressor a (setting, variant, seed): the class
    # loss never reaches the CNN, so lrcn trains it and base1-3 train their readers on its frozen shapes
    # (train.shared_regressor), a Table 3 row in two CNN trainings instead of about seven; on wind's
    # validation windows base1 and base2 lost nothing that way against their own CNN (+5.9 [+1.9, +9.6] and
    # +4.6 [+0.6, +8.5] points, one seed: one draw of the regressors' spread;
    # benchmarks/results/table3-shared-wind-arm-h100x2-n5184.json). 384 sequences a class (20,736 clips a setting),
    # chosen on arm's validation windows each time the data doubled, seeds 0 and 1 pooled, the same validation and test
    # clips, the smaller set being half of the training sequences (train.train_fraction=0.5): 192 over 96 +8.5 points
    # [+5.8, +11.0] (on test clips 44.0 against 35.0 %; benchmarks/results/learn_data192-arm-uniform1-h100x2.json), 384
    # over 192 +10.3 [+8.5, +11.9] (on test clips 68.1 against 57.3 %, 90.6 % within one bin;
    # benchmarks/results/learn_data384-arm-uniform1-h100x4.json), each for twice a setting's sim, render, epoch time and
    # disk (at 384: ~31 GB of packed frames at 112 px a setting). Wind, measured after the choices: 192 over 96 +8.9
    # points on test clips (89.2 against 80.3 %, benchmarks/results/table3-192-wind-h100x2.json); at 384 its Table 3 row
    # reads 93.7 % (benchmarks/results/table3-wind384-h100x4.json; another run than 192's, not paired).
    # Arm's cloth framed 1.3x closer than its camera box (sim.arm_view_zoom), chosen on arm's validation windows at 192
    # a class (+10.0 points [+7.6, +12.5]; on test clips 57.9 against 49.2 %, seeds 0 and 1 pooled, the same simulations
    # rendered both ways; benchmarks/results/table3-close192-arm-h100x2.json): its cloth is wide and low in the box,
    # which holds the rarest poses. Wind's framing was not compared. 120 epochs over 80 were not chosen (arm's
    # validation windows -1.0 points [-3.0, +1.0]; benchmarks/results/learn_epochs120-arm-uniform1-h100x2.json). The CNN
    # trainings replay CUDA graphs (train.compile, mode reduce-overhead): at 192 a class, two lrcn a GPU, an epoch took
    # 6.10 s against 8.05 eager (1.32x; about 21 s more in the first epoch to compile), the same file. The readers on
    # the shared regressor are not compiled (train.compile_readers=false: torch.compile's graphs ran base2's and
    # base3's 1.1-1.6x slower, docs/learning.md); each replays its whole training step from one CUDA graph instead
    # (train.reader_graphs): on an H100 a step took 0.26-0.64 ms against 2.6-3.6 ms eager (base1 10.2x, base2 5.7x,
    # base3 7.5x; benchmarks/results/reader_step-graphed-cuda-*-h100.json), and a Table 3 row's six readers at 384 a
    # class trained in 142 s on four H100s. Compiling changes rounding, not the computation; a graphed reader draws its
    # bottleneck noise from the same generator in another order, as reproducible as an eager one but not the same draws.
    return StudyConfig(
        name="paper",
        sim=SimConfig(motions=("wind", "arm"), remeshing=("uniform1", "uniform2", "uniform3", "adaptive"),
                      sequences_per_class=384, frames=40, device="cuda", wind_nuisance="speed",
                      arm_nuisance="speed", arm_view_zoom=1.3, self_collision=True),
        # The network's frames only, packed: PNG and EXR cost more host time than the path tracer at 112 px
        # (render.frames), and packed frames are on disk once (a setting at 384 a class: ~31 GB, not twice that)
        render=RenderConfig(variants=("paper",), resolution=112, spp=16, backend="cuda_ad_rgb",
                            write_png=False, write_hdr=False, pack_frames=True),
        train=TrainConfig(models=("lrcn", "base1", "base2", "base3"), image_size=112, epochs=80,
                          batch_size=16, clip_len=40, weight_decay=0.05, width=64, fc6=512, hidden=256, device="cuda",
                          motion=True, keep="best", bottleneck=True, dropout=0.0, reader_truth=1.0,
                          bottleneck_noise=0.2, shared_regressor="lrcn", compile=True, compile_mode="reduce-overhead",
                          compile_readers=False, reader_graphs=True),
        eval=EvalConfig(measured_sequences=4, sim_analysis=("table2", "sensitivity")),
    )


# The paper's Table 3: per motion, adaptive meshes with grid, colour and random textures, and uniform
# 1-3 with random ones: twelve (setting, texture) datasets.
TABLE3_PAIRS = tuple(f"{variant}:{motion}-adaptive" for variant in ("grid", "color") for motion in ("wind", "arm"))


def _study() -> StudyConfig:
    # The paper's whole study on one GPU: the paper preset plus the grid and colour textures on the
    # adaptive settings only (render.variant_settings), twelve datasets in all, at the paper's own 48
    # sequences a class (2,592 a setting): at the paper preset's 384 the twelve datasets are 10 million
    # frames, more than an H100's path tracer renders in a session at its ceiling.
    # 80 epochs like the paper preset: validation chose 80 over 40 at 48 sequences a class on arm (27.4 ->
    # 30.7 %, framed closer 33.0 -> 39.6 %) and at 24 on wind (33.3 -> 48.1 %), docs/learning.md; more
    # epochs at 48 a class were not measured.
    base = _paper()
    return replace(base, name="study", sim=replace(base.sim, sequences_per_class=48),
                   render=replace(base.render, variants=("paper", "grid", "color"), variant_settings=TABLE3_PAIRS))


PRESETS: dict[str, typing.Callable[[], StudyConfig]] = {"smoke": _smoke, "small": _small, "paper": _paper,
                                                        "study": _study}


def preset(name: str) -> StudyConfig:
    try:
        return PRESETS[name]()
    except KeyError:
        raise ConfigError(f"unknown preset {name!r}; known presets: {', '.join(PRESETS)}") from None


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


# ---------------------------------------------------------------- changing a run's config

# Settings that say where or how fast work runs, not what it computes (within float rounding across devices),
# and the run's name: a resumed run may change them at any time.
# (render.write_png / write_hdr only add inspection files; clips rendered before keep what they wrote.)
EXECUTION_SETTINGS = frozenset({"name", "sim.device", "sim.batch_size", "render.writer_threads", "render.write_png",
                                "render.write_hdr", "render.frames_in_flight", "train.device", "train.num_threads",
                                "train.num_workers"})
# Settings added after runs existed whose default is what the code did before they existed: a run's
# config.json without one was made by an older clothgap and gets the default (recorded), not an error.
# Adding a setting whose default changes results means leaving it out of this set. (sim.arm_view_zoom: the code
# between commits 184d41c and e357c18 framed arm 1.3x closer without the setting; no run of it was kept.)
DEFAULT_KEEPS_OLD_BEHAVIOUR = frozenset({"sim.self_collision", "sim.collision_thickness", "train.bottleneck",
                                         "train.bottleneck_noise", "train.reader_truth", "train.conv5_pool",
                                         "train.geometry_window", "train.augment_crop", "train.aux_geometry",
                                         "train.label_smoothing", "sim.arm_nuisance",
                                         "render.frames_in_flight", "train.compile_mode", "train.augment_camera",
                                         "train.shared_regressor", "train.reader_epochs", "sim.arm_view_zoom",
                                         "train.compile_readers", "train.reader_graphs", "sim.density_range",
                                         "sim.table_spread", "sim.table_shape"})
# Lists a resumed run may extend: an item more is more work downstream, nothing finished changes.
GROWING_SETTINGS = frozenset({"sim.motions", "sim.remeshing", "render.variants", "train.models", "train.seeds"})

def _motion_of_setting(key: str) -> str | None:
    """The motion whose clips alone read sim setting ``key`` (``sim.motions.Motion.settings``), else None."""
    from sim.motions import MOTIONS          # numpy only

    name = key.removeprefix("sim.") if key.startswith("sim.") else None
    return next((m.name for m in MOTIONS.values() if name in m.settings), None)


# The names callers use; the config itself holds the logic (clothgap.runs reaches it through the instance).
STAGES = StudyConfig.STAGES
pairs = StudyConfig.pairs
problems = StudyConfig.problems


def invalidating_settings(old: StudyConfig, new: StudyConfig) -> dict[str, str]:
    """``new.invalidating_settings(old)``: the changed settings that would make finished work disagree with ``new``."""
    return new.invalidating_settings(old)


def with_name(cfg: StudyConfig, name: str) -> StudyConfig:
    return replace(cfg, name=name)
