"""Material cloning (the paper's Fig. 9): predict a video's cloth class, put that material on a skirt.

``clothgap clone VIDEO --run RUN_DIR [--model lrcn] [--setting S] [--variant V] [--out DIR]``

1. Predict. The video (anything PyAV reads, or a folder of frames) goes through
   the real-video path of ``eval.real``: frames resampled to the simulation's
   frame rate, centre-cropped and resized to the model's input, cut into
   ``clip_len``-frame sub-sequences and classified by a model trained in the
   run (``learn.predict.predict_clips``). The video's class is the argmax of the
   mean sub-sequence probabilities (as ``eval real``); the vote share (how many
   sub-sequences pick that class) and the mean probability are reported beside it.
2. Simulate. A skirt (``sim.garment``: an A-line frustum sewn from one
   unrolled-cone panel, waist pinned and turned back and forth) is given the
   class's material, the basis fabric scaled by the class's (p, k), and is
   simulated with the project's Warp solver. A softer and a stiffer class
   (``SOFTER_STEPS`` / ``STIFFER_STEPS`` grid steps away, clipped to the grid)
   are simulated in the same batch on the same waist motion, so the output shows
   what the prediction changes, as the paper's comparison does.
3. Render. Each skirt is rendered with Mitsuba by ``render.stage.render_clip``
   under a render variant of the run (by default the one the model was trained
   on), all with the same camera, lights, texture and background (one seed, one
   framing over every skirt's whole motion), so only the material differs.

Outputs in ``--out`` (default ``RUN_DIR/clone/<video>``)::

    clone.json             predicted class, p, k, confidence, vote share, top 3, the checkpoint,
                           garment, motion, sim and render settings, seeds, per-panel hem statistics
    clone.mp4              side by side: input | clone | softer | stiffer (H.264, PyAV)
    frames/0000.png ...    the same frames as PNG
    input/clip/            the frames the network saw (ldr/, meta.json)
    sim/<panel>/           each skirt as a SimClip (render mesh, seam split), meta.json
    render/<panel>/ldr/    each skirt's rendered frames

A missing video, an unreadable one, a run folder without a config or without a
trained model give a ``CloneError`` (a ``ConfigError``: the CLI prints one line).
"""

from __future__ import annotations

import dataclasses
import shutil
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np
import pandas as pd
from PIL import Image, ImageDraw

from clothgap.errors import ConfigError
from clothgap.runs import Run, atomic_write_json, fresh_dir, mark_done
from eval import predictions as preds
from eval.real import VideoError, model_geometry, per_video, read_video, write_clip
from sim import classes

GARMENTS = ("skirt",)
SOFTER_STEPS = (-2, -4)          # (p index, k index) steps from the predicted class to the softer one
STIFFER_STEPS = (2, 4)
SETTLE_S = 1.0                   # the skirt hangs on a still waist this long before recording
LABEL_PX = 14                    # height of the caption strip above each panel

Predictor = Callable[[Path, list[Path]], pd.DataFrame]


class CloneError(ConfigError):
    """The clone cannot be made from these inputs; the message says which and why."""


# ------------------------------------------------------------------ the model

def find_model(run: Run, model: str = "lrcn", setting: str | None = None, variant: str | None = None,
               seed: int | None = None) -> Path:
    """The training folder to predict with: ``train/<setting>/<variant>/<model>/s<seed>`` holding a
    ``checkpoint.pt``; finished (``DONE``) folders first, then the run config's order."""
    root = run.train_root
    found = sorted(root.glob("*/*/*/s*/checkpoint.pt")) if root.is_dir() else []
    if not found:
        raise CloneError(f"no trained model in {run.root} (no train/<setting>/<variant>/<model>/s<seed>/"
                         f"checkpoint.pt): run `clothgap train {run.root}` first")
    wanted = []
    for path in found:
        d = path.parent
        s, v, m, sd = d.parts[-4], d.parts[-3], d.parts[-2], d.name
        if m != model or (setting and s != setting) or (variant and v != variant) or \
                (seed is not None and sd != f"s{seed}"):
            continue
        wanted.append(d)
    if not wanted:
        have = ", ".join(sorted({"/".join(p.parent.parts[-4:]) for p in found}))
        ask = "/".join([setting or "*", variant or "*", model, f"s{seed}" if seed is not None else "s*"])
        raise CloneError(f"no trained model matching {ask} in {root}; trained: {have}")
    settings, variants = list(run.config.sim.settings()), list(run.config.render.variants)

    def order(d: Path):
        s, v = d.parts[-4], d.parts[-3]
        return (not (d / "DONE").is_file(), settings.index(s) if s in settings else len(settings),
                variants.index(v) if v in variants else len(variants), d.name)

    return sorted(wanted, key=order)[0]


def _predict_clips(train_dir: Path, clip_dirs: list[Path]) -> pd.DataFrame:
    from learn.predict import predict_clips

    return predict_clips(train_dir, clip_dirs)


def predict_video(video: Path, train_dir: Path, out_dir: Path, *, max_frames: int = 250,
                  frames_fps: float | None = None, predictor: Predictor | None = None) -> dict:
    """The video's class through the real-video path: class, p, k, confidence, vote share, top 3."""
    geometry = model_geometry(train_dir)
    try:
        frames = read_video(video, geometry["image_size"], geometry["fps"], max_frames, frames_fps)
    except VideoError as err:
        raise CloneError(f"cannot read the input video: {err}") from None
    if len(frames) < geometry["clip_len"]:
        raise CloneError(f"{video.name}: {len(frames)} frames at {geometry['fps']:g} fps, fewer than one "
                         f"{geometry['clip_len']}-frame sub-sequence the model needs")
    folder = out_dir / "input" / "clip"
    if folder.exists():
        shutil.rmtree(folder)
    write_clip(frames, folder, video.name)
    frame = (predictor or _predict_clips)(train_dir, [folder])
    if frame is None or len(frame) == 0:
        raise CloneError(f"{video.name}: the model returned no prediction")
    flat = preds.to_flat(frame)
    row = per_video(flat).iloc[0]
    probs = row[preds.PROB_COLUMNS].to_numpy(dtype=float)
    pred = int(row["pred"])
    top = np.argsort(-probs)[:3]
    p, k = classes.class_values(pred)
    return {"class_index": pred, "p": p, "k": k, "confidence": float(probs[pred]),
            "vote_share": float((flat["pred"] == pred).mean()), "subsequences": int(len(flat)),
            "frames_read": len(frames), "fps": geometry["fps"],
            "top3": [{"class_index": int(c), "p": classes.class_values(int(c))[0],
                      "k": classes.class_values(int(c))[1], "probability": float(probs[c])} for c in top]}


def comparison_classes(class_index: int, compare: bool = True) -> list[tuple[str, int]]:
    """(panel name, class) to simulate: the clone, then a softer and a stiffer class when they differ."""
    panels = [("clone", int(class_index))]
    if compare:
        pi, ki = classes.class_indices(class_index)
        for name, (dp, dk) in (("softer", SOFTER_STEPS), ("stiffer", STIFFER_STEPS)):
            c = classes.class_index(int(np.clip(pi + dp, 0, len(classes.P_VALUES) - 1)),
                                    int(np.clip(ki + dk, 0, len(classes.K_VALUES) - 1)))
            if c not in [c0 for _, c0 in panels]:
                panels.append((name, c))
    return panels


# ------------------------------------------------------------------ simulation

def hem_statistics(garment, positions: np.ndarray) -> dict:
    """How far the hem hangs below the waist, how far it flares out and how much it swings, per clip."""
    hem = positions[:, garment.hem]                       # (T, H, 3)
    waist = positions[:, garment.waist]
    centre = waist.mean(axis=1, keepdims=True)
    rel = hem - centre
    return {"hem_drop_m": float((centre[..., 2] - hem[..., 2]).mean()),
            "hem_radius_m": float(np.linalg.norm(rel[..., :2], axis=-1).mean()),
            # how fast the hem moves relative to the waist's centre, per frame (0 for a single frame)
            "hem_swing_m_per_frame": float(np.linalg.norm(np.diff(rel, axis=0), axis=-1).mean()) if len(hem) > 1
            else 0.0}


def simulate_panels(panels: list[tuple[str, int]], sim_cfg, garment, motion, *, frames: int, settle_s: float,
                    device: str, progress: bool = True) -> dict[str, np.ndarray]:
    """Each panel's skirt, (T, V, 3); a failed health check is retried with twice the substeps, then
    a failed comparison panel is left out and a failed clone is an error."""
    from sim.garment import simulate_skirts
    from sim.materials import load_material

    basis = load_material(sim_cfg.basis)
    # the basis density even under sim.density_range: a panel is its class, and a class has no weight of its own
    materials = [basis.scaled(*classes.class_values(c)) for _, c in panels]
    out: dict[str, np.ndarray] = {}
    todo = list(range(len(panels)))
    for substeps in (sim_cfg.substeps, 2 * sim_cfg.substeps):
        results = simulate_skirts(garment, [materials[i] for i in todo], motion, fps=sim_cfg.fps, frames=frames,
                                  substeps=substeps, settle_s=settle_s, cg_iterations=sim_cfg.cg_iterations,
                                  device=device)
        failed = []
        for i, r in zip(todo, results):
            if r.reason:
                failed.append(i)
                if progress:
                    print(f"[clone] {panels[i][0]} skirt ({substeps} substeps): {r.reason}", flush=True)
            else:
                out[panels[i][0]] = r.positions
        todo = failed
        if not todo:
            break
    if "clone" not in out:
        raise CloneError("the cloned skirt's simulation failed its health check twice (see above)")
    return out


# ------------------------------------------------------------------ rendering and the video

def _caption(panel: np.ndarray, text: str) -> np.ndarray:
    strip = Image.new("RGB", (panel.shape[1], LABEL_PX), (255, 255, 255))
    ImageDraw.Draw(strip).text((2, 1), text, fill=(0, 0, 0))
    return np.concatenate([np.asarray(strip), panel], axis=0)


def _panel_caption(name: str, class_index: int) -> str:
    p, k = classes.class_values(class_index)
    return f"{name} #{class_index} p={p:g} k={k:g}"


def write_mp4(frames: list[np.ndarray], path: Path, fps: float) -> None:
    """(H, W, 3) uint8 frames as an H.264 MP4 (MPEG-4 part 2 where libx264 is missing)."""
    import av
    from fractions import Fraction

    h, w = frames[0].shape[:2]
    ph, pw = h + h % 2, w + w % 2
    path.parent.mkdir(parents=True, exist_ok=True)
    with av.open(str(path), mode="w") as container:
        codec = "libx264" if "libx264" in av.codecs_available else "mpeg4"
        stream = container.add_stream(codec, rate=Fraction(fps).limit_denominator(1000))
        stream.width, stream.height, stream.pix_fmt = pw, ph, "yuv420p"
        if codec == "libx264":
            stream.options = {"crf": "18", "preset": "veryfast"}
        for image in frames:
            padded = np.pad(image, ((0, ph - h), (0, pw - w), (0, 0)), mode="edge")
            for packet in stream.encode(av.VideoFrame.from_ndarray(np.ascontiguousarray(padded), format="rgb24")):
                container.mux(packet)
        for packet in stream.encode():
            container.mux(packet)


# ------------------------------------------------------------------ entry point

@dataclass(frozen=True)
class CloneOptions:
    """How to clone: which trained model predicts, the garment and its simulation, the render."""

    # the model: train/<setting>/<variant>/<model>/s<seed> of the run (None: the first trained, ``find_model``)
    model: str = "lrcn"
    setting: str | None = None
    variant: str | None = None
    seed: int | None = None
    # the garment and its simulation
    garment: str = "skirt"
    motion: str = "twirl"               # how the waist moves (sim.garment.MOTIONS)
    frames: int = 50                    # frames of the clone (the input loops beside it when shorter)
    settle_s: float = SETTLE_S
    device: str | None = None           # Warp device of the skirt simulation (None: "cpu")
    compare: bool = True                # also a softer and a stiffer class
    shape: object = None                # a sim.garment.SkirtShape (None: its defaults)
    # the render
    render_variant: str | None = None   # None: the variant the model was trained on
    resolution: int = 128
    spp: int = 16
    backend: str | None = None          # Mitsuba variant (None: "auto": CUDA, else LLVM, else scalar)
    # reading the input video
    max_frames: int = 250
    frames_fps: float | None = None

    def check(self) -> None:
        """Raise a CloneError naming the first setting that cannot work."""
        if self.garment not in GARMENTS:
            raise CloneError(f"unknown garment {self.garment!r}; known garments: {', '.join(GARMENTS)}")
        if self.frames < 2:
            raise CloneError(f"the clone needs at least 2 frames, got {self.frames}")
        if self.resolution < 8 or self.spp < 1:
            raise CloneError(f"resolution must be >= 8 pixels and spp >= 1, got {self.resolution} and {self.spp}")
        from sim.garment import MOTIONS

        if self.motion not in MOTIONS:
            raise CloneError(f"unknown waist motion {self.motion!r}; known motions: {', '.join(MOTIONS)}")


@dataclass
class SimulatedSkirts:
    """The simulated panels of a clone: the skirt they share, its waist motion, each panel's positions."""

    shape: object                       # the sim.garment.SkirtShape
    mesh: object                        # the sim.garment.Skirt
    waist: object                       # the sim.garment.WaistMotion
    panels: list[tuple[str, int]]       # (panel name, class) of the panels that simulated
    positions: dict[str, np.ndarray]    # panel name -> (T, V, 3)
    device: str
    seconds: float


@dataclass
class RenderedPanels:
    """Each panel's rendered frames, what the clone.json says of it, and the render's own meta."""

    frames: dict[str, list[np.ndarray]]
    info: list[dict]
    render_meta: dict
    variant: str
    seconds: float


RENDER_INDEX = 0                        # every panel renders as clip 0 of the run: the same render draws


def clone_video(video: Path | str, run_dir: Path | str, options: CloneOptions = CloneOptions(), *,
                out: Path | str | None = None, predictor: Predictor | None = None, progress: bool = True) -> Path:
    """Predict ``video``'s class with a model of ``run_dir``, simulate and render a skirt of that material
    (and a softer and a stiffer one) and write the side-by-side video.

    Args:
        video: A video file PyAV reads, or a folder of frames.
        run_dir: A run folder holding a trained model.
        options: The model, garment, simulation and render settings (``CloneOptions``).
        out: The output folder (default ``RUN_DIR/clone/<video>``).
        predictor: Replaces ``learn.predict.predict_clips`` (tests).
        progress: Print each step's outcome.

    Returns:
        The path of the written ``clone.json``.

    Raises:
        CloneError: a missing or unreadable video, a bad option, a run without a matching trained model.
    """
    start = time.perf_counter()
    video, run_dir = Path(video), Path(run_dir)
    if not video.exists():
        raise CloneError(f"input video {video} does not exist")
    options.check()
    run = Run.open(run_dir)
    train_dir = find_model(run, options.model, options.setting, options.variant, options.seed)
    out_dir = Path(out) if out is not None else run.clone_dir(_name(video))
    out_dir.mkdir(parents=True, exist_ok=True)
    say = (lambda msg: print(f"[clone] {msg}", flush=True)) if progress else (lambda msg: None)
    say(f"model {train_dir}")

    prediction = predict_video(video, train_dir, out_dir, max_frames=options.max_frames,
                               frames_fps=options.frames_fps, predictor=predictor)
    say(f"{video.name}: class {prediction['class_index']} (p={prediction['p']:g}, k={prediction['k']:g}), "
        f"probability {prediction['confidence']:.2f}, {prediction['vote_share']:.0%} of "
        f"{prediction['subsequences']} sub-sequences")
    skirts = simulate_clone(run, prediction["class_index"], options, progress)
    say(f"simulated {', '.join(n for n, _ in skirts.panels)} in {skirts.seconds:.1f} s")
    rendered = render_panels(run, video, skirts, options, train_dir, out_dir, say)
    frames_dir = write_side_by_side(video, prediction, skirts.panels, rendered, options, out_dir)
    doc = clone_doc(video, run, train_dir, prediction, skirts, rendered, options, out_dir, frames_dir)
    doc["seconds"] = round(time.perf_counter() - start, 2)
    path = out_dir / "clone.json"
    atomic_write_json(path, doc)
    say(f"wrote {out_dir / 'clone.mp4'} and {path}")
    return path


def simulate_clone(run: Run, class_index: int, options: CloneOptions, progress: bool = True) -> SimulatedSkirts:
    """The skirt in the predicted class and, with ``options.compare``, a softer and a stiffer one."""
    from sim.garment import SkirtShape, WaistMotion, skirt
    from sim.solver import resolve_device

    device = resolve_device(options.device or "cpu")           # three small skirts: a CPU is plenty
    shape = options.shape or SkirtShape()
    mesh = skirt(shape)
    waist = WaistMotion(kind=options.motion)
    panels = comparison_classes(class_index, options.compare)
    t0 = time.perf_counter()
    positions = simulate_panels(panels, run.config.sim, mesh, waist, frames=options.frames,
                                settle_s=options.settle_s, device=device, progress=progress)
    return SimulatedSkirts(shape, mesh, waist, [(n, c) for n, c in panels if n in positions], positions, device,
                           time.perf_counter() - t0)


def _renderer(options: CloneOptions, train_dir: Path):
    """The render variant and RenderConfig of the clone; a bad variant or backend is a CloneError."""
    from render.backend import BackendError, load_mitsuba
    from render.config import RenderConfig
    from render.variants import VariantError, get_variant

    try:
        variant = get_variant(options.render_variant or train_dir.parts[-3])
    except VariantError as err:
        raise CloneError(str(err)) from None
    try:
        load_mitsuba(options.backend or "auto")
    except (BackendError, ValueError) as err:
        raise CloneError(f"render backend: {err}") from None
    config = RenderConfig(variants=(variant.name,), resolution=options.resolution, spp=options.spp,
                          backend=options.backend or "auto", write_hdr=False)
    return variant, config


def render_panels(run: Run, video: Path, skirts: SimulatedSkirts, options: CloneOptions, train_dir: Path,
                  out_dir: Path, say: Callable[[str], None]) -> RenderedPanels:
    """Render every panel under one camera (framed on every skirt's whole motion) and one seed, so that
    only the material differs; each panel's SimClip and frames are kept under ``out_dir``."""
    from render.stage import render_clip
    from sim.clip import SimClip
    from sim.materials import load_material

    variant, rconfig = _renderer(options, train_dir)
    cfg, mesh = run.config, skirts.mesh
    render_positions = {n: mesh.to_render(skirts.positions[n]) for n, _ in skirts.panels}
    allpos = np.concatenate([p.reshape(-1, 3) for p in render_positions.values()])
    bounds = (allpos.min(axis=0), allpos.max(axis=0))
    basis = load_material(cfg.sim.basis)
    info, frames = [], {}
    t0 = time.perf_counter()
    for name, c in skirts.panels:
        p, k = classes.class_values(c)
        meta = {"clip_id": name, "index": RENDER_INDEX, "class_index": c, "p_class": p, "k_class": k, "p": p,
                "k": k, "basis": cfg.sim.basis, "density": basis.density, "seed": cfg.seed, "fps": cfg.sim.fps,
                "frames": options.frames, "garment": options.garment, "motion": skirts.waist.params(),
                "skirt": dataclasses.asdict(skirts.shape), "source": f"clothgap clone of {video.name}"}
        clip = SimClip.from_fixed(meta, render_positions[name], mesh.render_faces, mesh.render_uv)
        clip.save(fresh_dir(out_dir / "sim" / name))
        clip.bounds = lambda b=bounds: b          # one framing for every panel: only the material differs
        folder = fresh_dir(out_dir / "render" / name)
        rmeta = render_clip(clip, variant, folder, config=rconfig, run_seed=cfg.seed, clip_index=RENDER_INDEX)
        mark_done(folder, {"frames": options.frames})
        frames[name] = [np.asarray(Image.open(folder / "ldr" / f"{t:04d}.png").convert("RGB"))
                        for t in range(options.frames)]
        stats = hem_statistics(mesh, skirts.positions[name])
        info.append({"panel": name, "class_index": c, "p": p, "k": k, **stats,
                     "sim": str(out_dir / "sim" / name), "frames": str(folder / "ldr")})
        say(f"rendered {name} (class {c}): hem {stats['hem_drop_m']:.3f} m below the waist, "
            f"{stats['hem_radius_m']:.3f} m out")
    return RenderedPanels(frames, info, rmeta, variant.name, time.perf_counter() - t0)


def write_side_by_side(video: Path, prediction: dict, panels: list[tuple[str, int]], rendered: RenderedPanels,
                       options: CloneOptions, out_dir: Path) -> Path:
    """input | clone | softer | stiffer, captioned, as ``frames/*.png`` and ``clone.mp4``; returns the frames'
    folder."""
    try:
        shown = read_video(video, options.resolution, prediction["fps"], options.frames, options.frames_fps)
    except VideoError as err:
        raise CloneError(f"cannot read the input video: {err}") from None
    frames_dir = fresh_dir(out_dir / "frames")
    side = []
    for t in range(options.frames):
        row = [_caption(shown[t % len(shown)], f"input {video.name}"[:40])]
        row += [_caption(rendered.frames[n][t], _panel_caption(n, c)) for n, c in panels]
        image = np.concatenate(row, axis=1)
        Image.fromarray(image).save(frames_dir / f"{t:04d}.png")
        side.append(image)
    write_mp4(side, out_dir / "clone.mp4", prediction["fps"])
    return frames_dir


def clone_doc(video: Path, run: Run, train_dir: Path, prediction: dict, skirts: SimulatedSkirts,
              rendered: RenderedPanels, options: CloneOptions, out_dir: Path, frames_dir: Path) -> dict:
    """What ``clone.json`` records: the prediction, the model, garment, material, sim and render settings,
    the seeds and the panels (``seconds`` is added by the caller)."""
    from sim.materials import load_material

    cfg = run.config
    return {
        "video": str(video),
        "predicted": {k: prediction[k] for k in ("class_index", "p", "k", "confidence", "vote_share",
                                                 "subsequences", "frames_read", "top3")},
        "class_index": prediction["class_index"], "p": prediction["p"], "k": prediction["k"],
        "confidence": prediction["confidence"],
        "model": {"checkpoint": str(train_dir / "checkpoint.pt"), "train_dir": str(train_dir),
                  "setting": train_dir.parts[-4], "variant": train_dir.parts[-3], "model": train_dir.parts[-2],
                  "seed": int(train_dir.name.lstrip("s"))},
        "garment": {"kind": options.garment, "shape": dataclasses.asdict(skirts.shape),
                    "motion": skirts.waist.params(), "vertices": skirts.mesh.num_vertices,
                    "faces": int(len(skirts.mesh.mesh.faces))},
        "material": {"basis": cfg.sim.basis, "density_kg_m2": load_material(cfg.sim.basis).density,
                     "note": "every stretching entry of the basis times p, every bending entry times k"},
        "sim": {"fps": cfg.sim.fps, "frames": options.frames, "substeps": cfg.sim.substeps,
                "settle_s": options.settle_s, "cg_iterations": cfg.sim.cg_iterations, "device": skirts.device,
                "seconds": round(skirts.seconds, 2)},
        "render": {"variant": rendered.variant, "resolution": options.resolution, "spp": options.spp,
                   "backend": rendered.render_meta["render"]["backend"], "seconds": round(rendered.seconds, 2)},
        "seeds": {"run_seed": cfg.seed, "render_clip_index": RENDER_INDEX,
                  "sampler_seed": rendered.render_meta["render"]["sampler_seed"],
                  "note": "the simulation is deterministic; render draws come from "
                          "clothgap.seeding.rng(run_seed, render_clip_index, RENDER, stream)"},
        "panels": rendered.info,
        "outputs": {"video": str(out_dir / "clone.mp4"), "frames": str(frames_dir),
                    "input_clip": str(out_dir / "input" / "clip")},
    }


def _name(video: Path) -> str:
    import re

    name = video.stem if video.is_file() else video.name
    return re.sub(r"[^A-Za-z0-9_.-]+", "_", name).strip("._") or "video"
