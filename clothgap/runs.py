"""Run folders: one folder per stage, one per clip, each finished by a marker.

Layout of a run (``runs/<name>`` unless the user names another folder)::

    config.json                                  resolved study config
    sim/<setting>/<clip_id>/                     clip.npz, meta.json, DONE
    render/<variant>/<setting>/<clip_id>/        frames.npy, [ldr/*.png, hdr/*.exr,] meta.json, DONE
    render/<variant>/<setting>/frames-<H>px.npy  with render.pack_frames: the clips' frames, none a clip
    splits/<setting>.json                        train/val/test clip ids (by sequence)
    train/<setting>/<variant>/<model>/s<seed>/   checkpoint.pt, metrics.csv, tb/, DONE
    eval/                                        predictions, tables (CSV, JSON)
    measured/sim/<setting>/<fabric>-<n>/         measured-fabric clips (eval.measured): clip.npz, meta.json, DONE
    measured/render/<variant>/<setting>/<fabric>-<n>/   their frames in the held-out variant
    sim_analysis/                                the sim stage's Table 2 / sensitivity (eval.sim_analysis)
    report/report.html

The ``DONE`` marker is written last, after everything else in the folder, so a
folder without it is unfinished: a re-run deletes and redoes it, and a killed
run loses nothing that was finished.
"""

from __future__ import annotations

import errno
import hashlib
import json
import shutil
import warnings
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from clothgap.errors import ConfigError, InputError, MissingInputError, StorageError
# The atomic writer lives in clothgap.files; the stages import it from here with the rest of a run folder's tools.
from clothgap.files import atomic_write_json, atomic_write_text  # noqa: F401
from clothgap.settings import changed_settings, load_config, save_config, shown, study_config, to_dict, validate

DONE = "DONE"

# Write failures the user fixes (free space, permissions), not bugs: reported as one line naming the path.
STORAGE_ERRNOS = frozenset({errno.ENOSPC, errno.EDQUOT, errno.EROFS, errno.EACCES, errno.EPERM, errno.EFBIG,
                            errno.ENOTDIR, errno.EEXIST, errno.EISDIR})


def storage_error(err: OSError, path: Path | str | None = None) -> StorageError | None:
    """A StorageError naming the path for a full / read-only / forbidden write, else None (a bug)."""
    if err.errno not in STORAGE_ERRNOS:
        return None
    where = err.filename or path
    return StorageError(f"cannot write {where}: {err.strerror or err}; finished work is kept: "
                        "run the same command again once this is fixed")


def is_done(folder: Path) -> bool:
    return (folder / DONE).is_file()


def mark_done(folder: Path, info: dict | None = None) -> None:
    """Write the marker last: the folder is complete once this file exists."""
    atomic_write_json(folder / DONE, info or {})


def read_meta(folder: Path, redo: str = "sim") -> dict:
    """A clip folder's meta.json, or an InputError naming it and how to redo the clip."""
    path = Path(folder) / "meta.json"
    fix = f"delete {folder} and run `clothgap {redo}` on the run again to redo that clip"
    try:
        meta = json.loads(path.read_text())
    except FileNotFoundError:
        raise MissingInputError(f"{path} is missing: {fix}") from None
    except (UnicodeDecodeError, json.JSONDecodeError) as e:
        raise InputError(f"{path} is not valid JSON ({e}): {fix}") from None
    if not isinstance(meta, dict):
        raise InputError(f"{path} is not a table of settings: {fix}")
    return meta


_HASHES: dict[tuple, str] = {}


def file_sha256(path: Path | str) -> str:
    """sha256 of a file's bytes, cached per (path, size, mtime, inode) within this process."""
    path = Path(path)
    st = path.stat()
    key = (str(path.resolve()), st.st_size, st.st_mtime_ns, st.st_ino)
    if key not in _HASHES:
        h = hashlib.sha256()
        with path.open("rb") as f:
            for block in iter(lambda: f.read(1 << 20), b""):
                h.update(block)
        _HASHES[key] = h.hexdigest()
    return _HASHES[key]


def fresh_dir(folder: Path) -> Path:
    """An empty folder for a unit of work that is about to be (re)done."""
    if folder.exists():
        shutil.rmtree(folder)
    folder.mkdir(parents=True)
    return folder


def finished_stages(root: Path) -> set[str]:
    """The stages with finished work in a run folder: a clip's DONE (sim, render; measured fabrics included),
    a split or a finished model (train, ablations included)."""
    root = Path(root)
    patterns = {"sim": ("sim/*/*/DONE", "measured/sim/*/*/DONE"),
                "render": ("render/*/*/*/DONE", "measured/render/*/*/*/DONE"),
                "train": ("splits/*.json", "train/*/*/*/*/DONE", "ablation/*/*/*/*/*/DONE")}
    return {stage for stage, globs in patterns.items() if any(next(root.glob(g), None) for g in globs)}


def _key_differences(data: dict, known: dict, prefix: str = "") -> tuple[list[str], list[str]]:
    """``(unknown, missing)`` dotted settings of ``data`` against ``known`` (a missing section is named whole)."""
    unknown = [f"{prefix}{k}" for k in data if k not in known]
    missing = []
    for key, default in known.items():
        if key not in data:
            missing.append(f"{prefix}{key}")
        elif isinstance(default, dict) and isinstance(data[key], dict):
            more_unknown, more_missing = _key_differences(data[key], default, f"{prefix}{key}.")
            unknown += more_unknown
            missing += more_missing
    return unknown, missing


def load_run_config(root: Path, check: bool = True) -> Any:
    """A run folder's config.json, every setting of the current code in it.

    A setting the code does not know is a ConfigError naming it (a run made by another version). A setting
    the file lacks is a ConfigError naming it and its default when finished work depends on it (its stage or a
    later one has finished work): that work may have been made with another value. Otherwise (execution and
    eval settings, stages not started) the default is taken with a warning and recorded in config.json.
    ``check=False`` (a generation worker, whose driver checked the file) only parses it.
    """
    path = Path(root) / "config.json"
    if not check:
        return load_config(path, check)
    try:
        data = json.loads(path.read_text())
    except (OSError, ValueError):
        data = None             # load_config says what is wrong with the file
    if not isinstance(data, dict):
        return load_config(path)
    cls = study_config()
    default = to_dict(cls())
    unknown, missing = _key_differences(data, default)
    if unknown:
        raise ConfigError(f"{path}: unknown setting(s) {', '.join(unknown)}: this clothgap does not have them (was "
                          "the run made by another version?); remove them from the file, or use the clothgap that "
                          "made the run")
    cfg = load_config(path)
    if not missing:
        return cfg
    values = to_dict(cfg)

    def value_of(key: str) -> object:
        node: object = values
        for part in key.split("."):
            node = node[part]   # type: ignore[index]
        return node

    done = finished_stages(root)
    order = cls.STAGES
    shaping = {key: [s for s in order[order.index(stage):] if s in done]
               for key in missing if (stage := cls.missing_setting_stage(key)) is not None}
    blocked = {key: stages for key, stages in shaping.items() if stages}
    if blocked:
        named = "; ".join(f"{key} (default {shown(value_of(key))}; {', '.join(stages)} work is done)"
                          for key, stages in blocked.items())
        raise ConfigError(f"{path} lacks setting(s) that finished work depends on: {named}. Add each to the file "
                          "with the value the run was made with (the default, if the run was made by a clothgap "
                          "without that setting)")
    shown_keys = ", ".join(missing[:8]) + (f" and {len(missing) - 8} more" if len(missing) > 8 else "")
    warnings.warn(f"{path} lacks setting(s) {shown_keys}; no finished work depends on them: taking the defaults, "
                  "recorded in the file", stacklevel=3)
    try:
        save_config(cfg, path)
    except OSError:
        pass                    # a read-only run folder still opens; the warning stays
    return cfg


def clip_id(index: int) -> str:
    return f"c{index:05d}"


def clip_index(cid: str) -> int:
    """The index of clip id ``cid`` (``clip_id``'s inverse): ``"c00018"`` -> 18."""
    if not (len(cid) > 1 and cid[0] == "c" and cid[1:].isdigit()):
        raise ValueError(f"{cid!r} is not a clip id (c and a number, e.g. c00018)")
    return int(cid[1:])


def select_clips(num_clips: int, indices: Sequence[int] | None = None) -> list[int]:
    """The clip indices a stage works on: all ``num_clips``, or the given ones (sorted, once each).

    Generation executors (``clothgap.executor``) give each worker its shard of indices this way.
    """
    if indices is None:
        return list(range(num_clips))
    chosen = sorted(set(int(i) for i in indices))
    bad = [i for i in chosen if not 0 <= i < num_clips]
    if bad:
        raise ConfigError(f"clip indices {bad[:5]} are outside this run's 0..{num_clips - 1}")
    return chosen


@dataclass(frozen=True)
class Run:
    root: Path
    # The study config (clothgap.config.StudyConfig, registered with clothgap.settings.use_study_config): typed
    # loosely here because the ground floor imports no stage config.
    config: Any

    # ---- opening and creating
    @classmethod
    def open(cls, root: Path | str, check: bool = True) -> "Run":
        """An existing run folder (one that a stage has already written); its config is validated unless
        ``check=False`` (a generation worker, whose driver validated it: a remote node may lack the
        driver's $CLOTHGAP_VARIANTS_DIR, which only render work needs)."""
        root = Path(root)
        if root.exists() and not root.is_dir():
            raise ConfigError(f"run folder {root} is a file, not a folder")
        if not root.is_dir():
            raise ConfigError(f"run folder {root} does not exist")
        return cls(root, load_run_config(root, check))

    @classmethod
    def create_or_resume(cls, root: Path | str, config: Any) -> "Run":
        """Start a run in ``root``, or resume it (a bad config is a ConfigError).

        A run folder that already holds a config takes a different one when the change only adds work (more
        settings, variants, models, seeds; see ``StudyConfig.invalidating_settings``) or touches settings
        of stages with no finished work yet; ``config.json`` is then rewritten. A change that would make
        finished work disagree with the config is a ConfigError naming each setting and the finished stage.
        """
        validate(config)
        root = Path(root)
        path = root / "config.json"
        if root.exists() and not root.is_dir():
            raise ConfigError(f"--out {root} is a file, not a folder: choose another --out folder")
        if path.is_file():
            existing = load_run_config(root)
            if to_dict(existing) == to_dict(config):
                return cls(root, existing)
            done = finished_stages(root)
            stages = config.STAGES
            blocked = {key: stage for key, stage in config.invalidating_settings(existing).items()
                       if any(s in done for s in stages[stages.index(stage):])}
            if blocked:
                changes = changed_settings(existing, config)
                named = "; ".join(f"{key} {shown(changes[key][0])} -> {shown(changes[key][1])} "
                                  f"({', '.join(s for s in stages[stages.index(stage):] if s in done)} work is done)"
                                  for key, stage in blocked.items())
                keep = " ".join(f"--set {key}={shown(changes[key][0])}" for key in blocked)
                raise ConfigError(
                    f"{root} already holds a run whose finished work this config would invalidate or leave out: {named}. "
                    "A run may gain settings, variants, models and seeds, and change eval settings, at any time; "
                    "other settings only before their stage has finished work. Leave those out (where a preset's "
                    f"default changed since the run was made, `{keep}` keeps the run's), or choose another --out folder")
            # Only adds work (or changes what nothing finished depends on): the run goes on under the new config.
            save_config(config, path)
            return cls(root, config)
        try:
            root.mkdir(parents=True, exist_ok=True)
            save_config(config, path)
        except OSError as e:
            err = storage_error(e, path)
            if err is None:
                raise
            raise ConfigError(f"cannot start a run in {root}: {e.strerror or e} ({e.filename or path}); "
                              "choose another --out folder") from None
        return cls(root, config)

    # ---- where things live
    def sim_dir(self, setting: str) -> Path:
        return self.root / "sim" / setting

    def render_dir(self, variant: str, setting: str) -> Path:
        return self.root / "render" / variant / setting

    def split_path(self, setting: str) -> Path:
        return self.root / "splits" / f"{setting}.json"

    def train_dir(self, setting: str, variant: str, model: str, seed: int) -> Path:
        return self.root / "train" / setting / variant / model / f"s{seed}"

    def measured_sim_dir(self, setting: str) -> Path:
        """Measured-fabric clips of ``setting`` (``<fabric>-<n>/``), simulated with the fabrics' own tables."""
        return self.measured_root / "sim" / setting

    def measured_render_dir(self, variant: str, setting: str) -> Path:
        return self.measured_root / "render" / variant / setting

    @property
    def render_root(self) -> Path:
        return self.root / "render"

    @property
    def train_root(self) -> Path:
        return self.root / "train"

    @property
    def train_index_path(self) -> Path:
        return self.train_root / "index.json"

    @property
    def measured_root(self) -> Path:
        return self.root / "measured"

    def frame_cache_path(self, variant: str, setting: str, size: int) -> Path:
        """The packed uint8 frames of a (variant, setting) at ``size`` px (``learn.dataset``)."""
        return self.root / "cache" / variant / setting / f"{size}.npy"

    def lattice_cache_path(self, setting: str, lattice: int) -> Path:
        """The simulated clips' ``lattice`` x ``lattice`` point grids of a setting (``learn.geometry``)."""
        return self.root / "cache" / "geometry" / setting / f"lattice-{lattice}.npz"

    def ablation_dir(self, recipe: str) -> Path:
        """A training recipe's own train tree (``eval.ablation``), laid out as ``train/``."""
        return self.root / "ablation" / recipe

    def clone_dir(self, name: str) -> Path:
        return self.root / "clone" / name

    def export_dir(self, setting: str, clip: str) -> Path:
        return self.root / "export" / setting / clip

    @property
    def sim_analysis_dir(self) -> Path:
        return self.root / "sim_analysis"

    @property
    def eval_dir(self) -> Path:
        return self.root / "eval"

    @property
    def report_dir(self) -> Path:
        return self.root / "report"

    def require(self, folder: Path, stage: str) -> Path:
        """A stage's input folder, or a clear error naming the command that makes it."""
        if not folder.is_dir() or not any(folder.iterdir()):
            raise ConfigError(f"{folder} is missing or empty: run `clothgap {stage} {self.root}` first")
        return folder

    def done_clips(self, folder: Path) -> list[str]:
        if not folder.is_dir():
            return []
        return sorted(p.name for p in folder.iterdir() if p.is_dir() and is_done(p))

    def simulated_settings(self) -> list[str]:
        """The run's settings with at least one finished sim clip, in the config's order."""
        return [s for s in self.config.sim.settings() if self.done_clips(self.sim_dir(s))]
