"""Real videos: predict each video's material class and correlate it with measured values
(the paper's Table 4). ``clothgap eval real VIDEO_DIR --truth truth.csv --model TRAIN_DIR --out OUT``.

Inputs
------
``VIDEO_DIR`` holds one entry per video: a video file (anything PyAV/FFmpeg reads:
mp4, avi, mov, mkv, ...) or a folder of frames (png/jpg/bmp/tif, sorted by name,
taken to be at the simulation's frame rate unless ``frames_fps`` says otherwise).
A file that cannot be decoded, or a video shorter than one sub-sequence, is
reported by name in ``skipped.csv`` and the others go on.

Truth CSV (one row per video; the column names follow the Bouman et al. 2013
ground-truth file, so that file works once a ``video`` column is added):

=====================  =====================================================
``video``              file or folder name in VIDEO_DIR, with or without the
                       extension (falls back to ``source_reference``)
``bending_N_m2``       measured bending stiffness (``stiffness`` also accepted)
``area_weight_kg_m2``  measured area weight / density (``density`` also accepted)
``wind``               optional: wind strength label (e.g. W1, W2, W3); the
                       table then has one row per strength, as the paper's
``label``              optional: fabric name; fabrics filmed several times are
                       resampled as one unit in the pooled bootstrap
=====================  =====================================================

What is correlated
------------------
Each video is cut into frames at the simulation's frame rate (so a
sub-sequence of ``train.clip_len`` frames spans the time the network was trained on), centre-cropped to a
square and resized to the model's input size; the frames go through the same
``learn.predict.predict_clips`` as simulated clips. The video's class is the
argmax of the mean sub-sequence probabilities. Two scores are correlated:

* ``bending``: the class's bending coefficient k times the basis material's mean
  bending stiffness (camel-ponte-roma, ``eval.classes.BASIS_MEAN_BENDING_N_M``),
  the model's estimate of stiffness. The stretching factor p does not enter: p
  scales in-plane stiffness, which the bending measurement does not see. Density
  is not part of the sub-space at all (a class has the basis density, or weights
  drawn apart from its label under ``sim.density_range``), so its correlation asks
  only whether stiffer-looking cloth is also heavier, as it is in Bouman's data.
* ``class_index``: the class index 0..53 itself, as the paper correlates it.

Pearson's and Spearman's r come with percentile bootstrap intervals over videos
(over fabrics when pooling wind strengths and ``label`` is given).

Outputs in OUT: ``videos.csv`` (per video: frames, sub-sequences, class, p, k,
scores, mean probabilities), ``table4.csv`` / ``table4.md``, ``skipped.csv``,
``scatter.png``, ``activations.png`` (conv5 overlays on the first videos, as the paper's
Fig. 6) and ``clips/<video>/`` (the frames the network saw). An input that is a finished
rendered clip's ``ldr/`` folder with square frames (the measured fabrics') is read where it
lies instead: the network reads it through the same resize, so the predictions are the same.
"""

from __future__ import annotations

import json
import re
import shutil
from pathlib import Path
from typing import Callable

import numpy as np
import pandas as pd
from PIL import Image

from clothgap.errors import InputError, MissingInputError, UserError
from clothgap.runs import atomic_write_text, is_done, mark_done
from clothgap.seeding import stream_id
from eval import classes, figures, metrics
from eval import predictions as preds
from render.frames import FRAMES_FILE, LDR_DIR, frame_count

IMAGE_SUFFIXES = {".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff"}
NOT_VIDEO_SUFFIXES = {".csv", ".json", ".txt", ".md", ".toml"}
STIFFNESS_COLUMNS = ("bending_N_m2", "stiffness")
DENSITY_COLUMNS = ("area_weight_kg_m2", "density")
VIDEO_COLUMNS = ("video", "source_reference")
SCORES = {"bending": "k x basis bending (N*m)", "class_index": "class index (paper)"}
DEFAULT_SIM_FPS = 25.0

Predictor = Callable[[Path, list[Path]], pd.DataFrame]


class VideoError(UserError, RuntimeError):
    """One input could not be used (or none could); the message names it and says why."""


# ------------------------------------------------------------------ truth

def read_truth(path: Path) -> pd.DataFrame:
    """The truth CSV with canonical columns ``video, stiffness, density[, wind, label]``.

    A missing file, an unreadable one or a missing column is an ``InputError`` naming the file (and the column)."""
    path = Path(path)
    if not path.is_file():
        raise MissingInputError(f"truth CSV {path} does not exist")
    try:
        frame = pd.read_csv(path)
    except (pd.errors.ParserError, pd.errors.EmptyDataError, UnicodeDecodeError) as err:
        raise InputError(f"truth CSV {path} cannot be read as CSV ({err})") from None

    def pick(options: tuple[str, ...], what: str) -> str:
        for name in options:
            if name in frame.columns:
                return name
        raise InputError(f"truth CSV {path}: no {what} column (expected one of {', '.join(options)}); "
                         f"its columns are {', '.join(map(str, frame.columns))}")

    out = pd.DataFrame({"video": frame[pick(VIDEO_COLUMNS, 'video')].astype(str),
                        "stiffness": pd.to_numeric(frame[pick(STIFFNESS_COLUMNS, 'stiffness')], errors="coerce"),
                        "density": pd.to_numeric(frame[pick(DENSITY_COLUMNS, 'density')], errors="coerce")})
    for optional in ("wind", "label"):
        if optional in frame.columns:
            out[optional] = frame[optional].astype(str)
    bad = out[~np.isfinite(out[["stiffness", "density"]].to_numpy(dtype=float)).all(axis=1)]
    if not bad.empty:
        raise InputError(f"truth CSV {path}: non-numeric, infinite or missing stiffness/density for video(s) "
                         f"{', '.join(bad['video'].head(5))}")
    twice = out[out.duplicated("video", keep=False)]
    if not twice.empty:
        # A video listed twice would be counted twice in every correlation.
        raise InputError(f"truth CSV {path}: video(s) listed more than once: "
                         f"{', '.join(sorted(set(twice['video']))[:5])}")
    return out


# ------------------------------------------------------------------ reading videos

def list_inputs(video_dir: Path) -> list[Path]:
    """Video files and frame folders in ``video_dir`` (hidden entries and tables left out); none is a VideoError."""
    if not video_dir.is_dir():
        raise MissingInputError(f"video folder {video_dir} does not exist")
    found = sorted(p for p in video_dir.iterdir()
                   if not p.name.startswith(".") and (p.is_dir() or p.suffix.lower() not in NOT_VIDEO_SUFFIXES))
    if not found:
        raise VideoError(f"video folder {video_dir} holds no videos or frame folders")
    return found


def _square(img: Image.Image, size: int) -> np.ndarray:
    """Centre square crop, resized to size x size RGB (the network's input is square)."""
    w, h = img.size
    s = min(w, h)
    img = img.convert("RGB").crop(((w - s) // 2, (h - s) // 2, (w - s) // 2 + s, (h - s) // 2 + s))
    return np.asarray(img.resize((size, size), Image.Resampling.BILINEAR))


def read_video(path: Path, size: int, fps: float, max_frames: int,
               frames_fps: float | None = None) -> list[np.ndarray]:
    """Frames of a video file or frame folder, resampled to ``fps`` (nearest earlier frame)."""
    if path.is_dir():
        files = sorted(p for p in path.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
        if not files:
            raise VideoError(f"{path.name}: folder holds no image files ({', '.join(sorted(IMAGE_SUFFIXES))})")
        step = (frames_fps or fps) / fps
        picks = np.floor(np.arange(0, len(files), step)).astype(int)[:max_frames]
        out = []
        for i in picks:
            try:
                with Image.open(files[i]) as img:
                    out.append(_square(img, size))
            except (OSError, ValueError, SyntaxError) as err:
                raise VideoError(f"{path.name}: frame {files[i].name} is unreadable ({err})") from err
        return out

    import av

    out: list[np.ndarray] = []
    try:
        with av.open(str(path)) as container:
            if not container.streams.video:
                raise VideoError(f"{path.name}: no video stream")
            stream = container.streams.video[0]
            rate = float(stream.average_rate or stream.guessed_rate or fps)
            next_time = None
            for i, frame in enumerate(container.decode(stream)):
                t = float(frame.time) if frame.time is not None else i / rate
                if next_time is None:
                    next_time = t
                if t + 0.5 / rate < next_time:
                    continue
                out.append(_square(frame.to_image(), size))
                next_time += 1.0 / fps
                if len(out) >= max_frames:
                    break
    except VideoError:
        raise
    except (av.FFmpegError, OSError, ValueError) as err:
        raise VideoError(f"{path.name}: cannot be decoded ({type(err).__name__}: {err})") from err
    return out


def _safe_name(name: str) -> str:
    return re.sub(r"[^A-Za-z0-9_.-]+", "_", name).strip("._") or "video"


def clip_folder_name(name: str, path: Path) -> str:
    """The ``clips/`` folder of an input: its name without a video file's extension, made safe."""
    return _safe_name(Path(name).stem if path.is_file() else name)


def check_distinct(listed: dict[str, Path]) -> None:
    """Refuse inputs that would share a clip folder (``x.mp4`` and a frame folder ``x/``, or ``a b`` and
    ``a_b``): one would overwrite the other's frames and the survivor would be counted twice."""
    by_folder: dict[str, list[str]] = {}
    for name, path in listed.items():
        by_folder.setdefault(clip_folder_name(name, Path(path)), []).append(name)
    clashes = {k: v for k, v in by_folder.items() if len(v) > 1}
    if clashes:
        text = "; ".join(f"{' and '.join(sorted(v))} would both be clips/{k}" for k, v in sorted(clashes.items()))
        raise InputError(f"inputs collide: {text}: rename one of each so every video has its own name")


def write_clip(frames: list[np.ndarray], folder: Path, video: str) -> Path:
    """A clip folder in the render contract (``ldr/%04d.png`` + meta.json) so predict_clips reads it."""
    (folder / "ldr").mkdir(parents=True, exist_ok=True)
    for t, img in enumerate(frames):
        Image.fromarray(img).save(folder / "ldr" / f"{t:04d}.png")
    meta = {"clip_id": video, "class_index": -1, "num_frames": len(frames), "source": "real video", "video": video}
    (folder / "meta.json").write_text(json.dumps(meta, indent=2))
    mark_done(folder)
    return folder


# ------------------------------------------------------------------ the model's geometry

def model_geometry(train_dir: Path) -> dict:
    """image_size, clip_len and the simulation fps the model was trained at.

    Read from the checkpoint and the run's config.json (train_dir is
    ``<run>/train/<setting>/<variant>/<model>/s<seed>``).
    """
    path = train_dir / "checkpoint.pt"
    if not path.is_file():
        raise MissingInputError(f"no checkpoint.pt in model folder {train_dir}: pass a finished train folder "
                                "(<run>/train/<setting>/<variant>/<model>/s<seed>)")
    from learn.predict import load_checkpoint

    ckpt = load_checkpoint(train_dir)           # a corrupt file is an InputError naming it
    geometry = {"image_size": int(ckpt["model_args"]["image_size"]),
                "clip_len": int(ckpt["config"]["train"]["clip_len"]), "fps": DEFAULT_SIM_FPS}
    run_config = train_dir.parents[4] / "config.json" if len(train_dir.parents) > 4 else None
    if run_config is not None and run_config.is_file():
        geometry["fps"] = float(json.loads(run_config.read_text()).get("sim", {}).get("fps", DEFAULT_SIM_FPS))
    return geometry


def _default_predictor(train_dir: Path, clip_dirs: list[Path]) -> pd.DataFrame:
    from learn.predict import predict_clips

    return predict_clips(train_dir, clip_dirs)


def match_truth(truth: pd.DataFrame, names) -> pd.Series:
    """Each truth row's input name (or None): by exact name, then by name without extension."""
    stem_of = {n: Path(n).stem for n in names}
    return truth["video"].map(lambda v: v if v in stem_of else next((n for n, s in stem_of.items() if s == v), None))


# ------------------------------------------------------------------ tables

def per_video(frame: pd.DataFrame) -> pd.DataFrame:
    """One row per video: class from mean sub-sequence probabilities, its (p, k) and scores."""
    seq = preds.per_sequence(frame).rename(columns={"clip_id": "video"}).drop(columns="class_index")
    seq["subsequences"] = frame.groupby("clip_id").size().reindex(seq["video"]).to_numpy()
    seq["p"] = classes.p_value(seq["pred"].to_numpy())
    seq["k"] = classes.k_value(seq["pred"].to_numpy())
    seq["bending"] = seq["k"] * classes.BASIS_MEAN_BENDING_N_M
    seq["class_index"] = seq["pred"]
    lead = ["video", "subsequences", "pred", "p", "k", "bending", "class_index"]
    return seq[lead + preds.PROB_COLUMNS]


def table4(joined: pd.DataFrame, *, resamples: int, confidence: float, seed: int) -> pd.DataFrame:
    """Correlation rows per wind group (and pooled) and score, as in the paper's Table 4."""
    groups = [("all", joined)]
    if "wind" in joined.columns:
        groups += [(f"wind {w}", g) for w, g in joined.groupby("wind", sort=True)]
    rows = []
    for name, g in groups:
        unit = g["label"] if (name == "all" and "label" in g.columns) else None
        for score, title in SCORES.items():
            row = {"group": name, "videos": len(g), "score": title}
            for target in ("stiffness", "density"):
                for method in ("pearson", "spearman"):
                    rng = np.random.default_rng([seed, len(rows), stream_id(target), stream_id(method)])
                    est = metrics.bootstrap_correlation(g[score], g[target], method=method, groups=unit,
                                                        resamples=resamples, confidence=confidence, rng=rng)
                    row.update(est.as_dict(f"{target}_{method}"))
            rows.append(row)
    return pd.DataFrame(rows)


def table4_markdown(table: pd.DataFrame, model: Path) -> str:
    head = ["Group", "Videos", "Score", "Stiffness r (Pearson)", "Stiffness rho (Spearman)",
            "Density r (Pearson)", "Density rho (Spearman)"]
    lines = [f"# Table 4: correlation with measured values (model `{model}`)", "",
             "r with 95% bootstrap interval. Paper (CNN+LSTM, 30 W3 videos): stiffness 0.50, density 0.64.", "",
             "| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for _, r in table.iterrows():
        cells = [r["group"], r["videos"], r["score"]] + [
            metrics.Estimate(r[f"{t}_{m}"], r[f"{t}_{m}_lo"], r[f"{t}_{m}_hi"]).fmt(1.0, 2)
            for t in ("stiffness", "density") for m in ("pearson", "spearman")]
        lines.append("| " + " | ".join(str(c) for c in cells) + " |")
    return "\n".join(lines) + "\n"


def _scatter(joined: pd.DataFrame):
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(8, 3.2))
    for ax, target, unit in ((axes[0], "stiffness", "measured bending stiffness"),
                             (axes[1], "density", "measured area weight")):
        for w, g in (joined.groupby("wind") if "wind" in joined else [("all", joined)]):
            ax.scatter(g[target], g["bending"], s=18, label=str(w), alpha=0.8)
        ax.set(xlabel=unit, ylabel="predicted bending (k x basis, N*m)", xscale="log", yscale="log")
        ax.grid(alpha=0.3)
    if "wind" in joined:
        axes[1].legend(fontsize=7, title="wind")
    fig.tight_layout()
    return fig


# ------------------------------------------------------------------ entry point

def evaluate_real(video_dir: Path | str, truth_csv: Path | str, train_dir: Path | str, out_dir: Path | str, *,
                  max_frames: int = 60, fps: float | None = None, frames_fps: float | None = None,
                  resamples: int = 1000, confidence: float = 0.95, seed: int = 0,
                  activations: int = 3, predictor: Predictor | None = None, progress: bool = True,
                  inputs: dict[str, Path] | None = None) -> Path:
    """Predict every video in ``video_dir``, correlate with ``truth_csv``; returns ``table4.csv``'s path.

    ``fps``: the rate videos are resampled to (default: the simulation's, from the
    run config); ``frames_fps``: the rate of frame folders (default: ``fps``);
    ``activations``: how many videos get conv5 overlays in ``activations.png`` (0: none);
    ``predictor`` replaces ``learn.predict.predict_clips`` (tests);
    ``inputs`` (video name -> file or frame folder) replaces the listing of
    ``video_dir`` (the measured-fabric set passes its rendered clips' ``ldr/`` folders).
    """
    video_dir, truth_csv, train_dir, out_dir = map(Path, (video_dir, truth_csv, train_dir, out_dir))
    truth = read_truth(truth_csv)              # every input is checked before the model is loaded
    listed = inputs if inputs is not None else {p.name: p for p in list_inputs(video_dir)}
    _check_inputs(truth, truth_csv, listed)
    geometry = model_geometry(train_dir)
    fps = fps or geometry["fps"]
    out_dir.mkdir(parents=True, exist_ok=True)

    clip_dirs, names, skipped = _write_clips(listed, out_dir, geometry, fps, max_frames, frames_fps, progress)
    atomic_write_text(out_dir / "skipped.csv", pd.DataFrame(skipped, columns=["video", "reason"]).to_csv(index=False))
    if not clip_dirs:
        raise VideoError(f"no readable video in {video_dir} ({len(skipped)} skipped; see {out_dir / 'skipped.csv'})")

    frame = preds.to_flat((predictor or _default_predictor)(train_dir, clip_dirs))
    videos = per_video(frame)
    atomic_write_text(out_dir / "videos.csv", videos.to_csv(index=False, float_format="%.6g"))

    key = match_truth(truth, names)
    missing = truth.loc[key.isna(), "video"].tolist()
    joined = truth.assign(video=key).dropna(subset=["video"]).merge(videos, on="video", how="inner")
    if progress and missing:
        print(f"[eval real] no readable video for truth row(s): {', '.join(missing)}", flush=True)
    table = table4(joined, resamples=resamples, confidence=confidence, seed=seed)
    table.insert(0, "model", str(train_dir))
    path = out_dir / "table4.csv"
    atomic_write_text(path, table.to_csv(index=False, float_format="%.6g"))
    atomic_write_text(out_dir / "table4.md", table4_markdown(table, train_dir)
                      + (f"\nTruth rows without a readable video: {', '.join(missing)}\n" if missing else "")
                      + (f"\nSkipped inputs: {', '.join(s['video'] for s in skipped)}\n" if skipped else ""))
    if len(joined) >= 2:
        figures.save(_scatter(joined), out_dir / "scatter.png")
    if activations:
        _activation_figure(train_dir, clip_dirs[:activations], out_dir / "activations.png")
    return path


def _check_inputs(truth: pd.DataFrame, truth_csv: Path, listed: dict[str, Path]) -> None:
    """The inputs have distinct names and no two truth rows name the same input."""
    check_distinct(listed)
    early = match_truth(truth, listed)
    twice = early[early.notna() & early.duplicated(keep=False)]
    if not twice.empty:
        raise InputError(f"truth CSV {truth_csv}: rows {', '.join(truth.loc[twice.index, 'video'])} name the same "
                         "video; give each video one row")


def _write_clips(listed: dict[str, Path], out_dir: Path, geometry: dict, fps: float, max_frames: int,
                 frames_fps: float | None, progress: bool) -> tuple[list[Path], dict[str, Path], list[dict]]:
    """Every readable input as a clip folder under ``out_dir / "clips"`` at the model's image size and ``fps``:
    returns the clip folders, the inputs they came from (name -> path), and the inputs skipped, with the reason."""
    skipped, clip_dirs, names = [], [], {}
    for name, path in listed.items():
        path = Path(path)
        rendered = _rendered_clip(name, path, geometry["clip_len"], fps, max_frames, frames_fps)
        if rendered is not None:
            clip_dirs.append(rendered)
            names[name] = path
            continue
        try:
            frames = read_video(path, geometry["image_size"], fps, max_frames, frames_fps)
            if len(frames) < geometry["clip_len"]:
                raise VideoError(f"{name}: {len(frames)} frames at {fps:g} fps, fewer than one "
                                 f"{geometry['clip_len']}-frame sub-sequence")
        except VideoError as err:
            skipped.append({"video": name, "reason": str(err)})
            if progress:
                print(f"[eval real] skipped {err}", flush=True)
            continue
        folder = out_dir / "clips" / clip_folder_name(name, path)
        if folder.exists():
            shutil.rmtree(folder)
        clip_dirs.append(write_clip(frames, folder, name))
        names[name] = path
        if progress:
            print(f"[eval real] {name}: {len(frames)} frames", flush=True)
    return clip_dirs, names, skipped


def _rendered_clip(name: str, path: Path, clip_len: int, fps: float, max_frames: int,
                   frames_fps: float | None) -> Path | None:
    """The clip folder when ``path`` is a finished rendered clip's ``ldr/`` that the network reads as it lies: its
    meta names it ``name`` and has a class, its frames are square (``learn.predict`` resizes them with the same
    bilinear filter as ``_square``), all of them at the model's rate, at least one sub-sequence. Else None: the
    input is read and copied like any frame folder."""
    clip = path.parent
    if path.name != LDR_DIR or frames_fps not in (None, fps) or not is_done(clip):
        return None
    try:
        meta = json.loads((clip / "meta.json").read_text())
        first = min(path.glob("*.png"), default=None)
        if not isinstance(meta, dict) or meta.get("clip_id", clip.name) != name or "class_index" not in meta \
                or first is None:
            return None
        with Image.open(first) as img:
            square = img.size[0] == img.size[1]
        count = frame_count(clip, meta)
        array = clip / FRAMES_FILE          # the predictor reads it before the PNGs: it must hold the same frames
        if array.is_file():
            shape = np.load(array, mmap_mode="r").shape
            square = square and shape[:1] == (count,) and shape[1] == shape[2] == img.size[0]
    except (OSError, ValueError, TypeError, EOFError):
        return None
    return clip if square and clip_len <= count <= max_frames else None


def _activation_figure(train_dir: Path, clip_dirs: list[Path], path: Path) -> None:
    """conv5 overlays on the first videos (the paper's Fig. 6 shows them on real frames)."""
    from eval.activations import clip_frames, overlay_figure
    from learn.predict import load_checkpoint, load_model

    size = int(load_checkpoint(train_dir)["model_args"]["image_size"])
    rows = {d.name: clip_frames(d, size) for d in clip_dirs}
    figures.save(overlay_figure(rows, load_model(train_dir, "cpu")), path)
