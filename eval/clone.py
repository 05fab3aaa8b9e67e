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
    root = run.root / "train"
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

def clone_video(video: Path | str, run_dir: Path | str, *, model: str = "lrcn", setting: str | None = None,
                variant: str | None = None, seed: int | None = None, garment: str = "skirt",
                motion: str = "twirl", out: Path | str | None = None, frames: int = 50,
                render_variant: str | None = None, resolution: int = 128, spp: int = 16,
                backend: str | None = None, device: str | None = None, compare: bool = True,
                settle_s: float = SETTLE_S, max_frames: int = 250, frames_fps: float | None = None,
                shape=None, predictor: Predictor | None = None, progress: bool = True) -> Path:
    """Predict ``video``'s class with a model of ``run_dir``, simulate and render a skirt of that material
    (and a softer and a stiffer one), write the side-by-side video; returns ``clone.json``'s path.

    ``frames``: frames of the clone (the input loops beside it when shorter); ``render_variant``:
    default the variant the model was trained on; ``backend``: Mitsuba variant (default "auto": CUDA,
    else LLVM, else scalar); ``device``: Warp device of the skirt simulation (default "cpu");
    ``shape``: a ``sim.garment.SkirtShape``; ``predictor`` replaces ``learn.predict.predict_clips`` (tests).
    """
    start = time.perf_counter()
    video, run_dir = Path(video), Path(run_dir)
    if not video.exists():
        raise CloneError(f"input video {video} does not exist")
    if garment not in GARMENTS:
        raise CloneError(f"unknown garment {garment!r}; known garments: {', '.join(GARMENTS)}")
    if frames < 2:
        raise CloneError(f"the clone needs at least 2 frames, got {frames}")
    if resolution < 8 or spp < 1:
        raise CloneError(f"resolution must be >= 8 pixels and spp >= 1, got {resolution} and {spp}")
    from sim.garment import MOTIONS, SkirtShape, WaistMotion, skirt

    if motion not in MOTIONS:
        raise CloneError(f"unknown waist motion {motion!r}; known motions: {', '.join(MOTIONS)}")
    run = Run.open(run_dir)
    train_dir = find_model(run, model, setting, variant, seed)
    out_dir = Path(out) if out is not None else run.root / "clone" / _name(video)
    out_dir.mkdir(parents=True, exist_ok=True)
    say = (lambda msg: print(f"[clone] {msg}", flush=True)) if progress else (lambda msg: None)
    say(f"model {train_dir}")

    # 1. predict
    prediction = predict_video(video, train_dir, out_dir, max_frames=max_frames, frames_fps=frames_fps,
                               predictor=predictor)
    say(f"{video.name}: class {prediction['class_index']} (p={prediction['p']:g}, k={prediction['k']:g}), "
        f"probability {prediction['confidence']:.2f}, {prediction['vote_share']:.0%} of "
        f"{prediction['subsequences']} sub-sequences")

    # 2. simulate
    from sim.solver import resolve_device

    cfg = run.config
    sim_device = resolve_device(device or "cpu")           # three small skirts: a CPU is plenty
    shape = shape or SkirtShape()
    skirt_mesh = skirt(shape)
    waist = WaistMotion(kind=motion)
    panels = comparison_classes(prediction["class_index"], compare)
    t0 = time.perf_counter()
    simulated = simulate_panels(panels, cfg.sim, skirt_mesh, waist, frames=frames, settle_s=settle_s,
                                device=sim_device, progress=progress)
    panels = [(n, c) for n, c in panels if n in simulated]
    sim_seconds = time.perf_counter() - t0
    say(f"simulated {', '.join(n for n, _ in panels)} in {sim_seconds:.1f} s")

    # 3. render, all panels under one camera (framed on every skirt's whole motion) and one seed
    from render.config import RenderConfig
    from render.stage import render_clip
    from render.variants import VariantError, get_variant
    from sim.clip import SimClip
    from sim.materials import load_material

    try:
        rvariant = get_variant(render_variant or train_dir.parts[-3])
    except VariantError as err:
        raise CloneError(str(err)) from None
    from render.backend import BackendError, load_mitsuba

    try:
        load_mitsuba(backend or "auto")
    except (BackendError, ValueError) as err:
        raise CloneError(f"render backend: {err}") from None
    rconfig = RenderConfig(variants=(rvariant.name,), resolution=resolution, spp=spp, backend=backend or "auto",
                           write_hdr=False)
    render_positions = {n: skirt_mesh.to_render(simulated[n]) for n, _ in panels}
    allpos = np.concatenate([p.reshape(-1, 3) for p in render_positions.values()])
    bounds = (allpos.min(axis=0), allpos.max(axis=0))
    basis = load_material(cfg.sim.basis)
    render_index = 0
    panel_info, rendered = [], {}
    t0 = time.perf_counter()
    for name, c in panels:
        p, k = classes.class_values(c)
        meta = {"clip_id": name, "index": render_index, "class_index": c, "p_class": p, "k_class": k, "p": p,
                "k": k, "basis": cfg.sim.basis, "density": basis.density, "seed": cfg.seed, "fps": cfg.sim.fps,
                "frames": frames, "garment": garment, "motion": waist.params(),
                "skirt": dataclasses.asdict(shape), "source": f"clothgap clone of {video.name}"}
        clip = SimClip.from_fixed(meta, render_positions[name], skirt_mesh.render_faces, skirt_mesh.render_uv)
        clip.save(fresh_dir(out_dir / "sim" / name))
        clip.bounds = lambda b=bounds: b          # one framing for every panel: only the material differs
        folder = fresh_dir(out_dir / "render" / name)
        rmeta = render_clip(clip, rvariant, folder, config=rconfig, run_seed=cfg.seed, clip_index=render_index)
        mark_done(folder, {"frames": frames})
        rendered[name] = [np.asarray(Image.open(folder / "ldr" / f"{t:04d}.png").convert("RGB"))
                          for t in range(frames)]
        stats = hem_statistics(skirt_mesh, simulated[name])
        panel_info.append({"panel": name, "class_index": c, "p": p, "k": k, **stats,
                           "sim": str(out_dir / "sim" / name), "frames": str(folder / "ldr")})
        say(f"rendered {name} (class {c}): hem {stats['hem_drop_m']:.3f} m below the waist, "
            f"{stats['hem_radius_m']:.3f} m out")
    render_seconds = time.perf_counter() - t0

    # 4. side by side: input | clone | softer | stiffer
    try:
        shown = read_video(video, resolution, prediction["fps"], frames, frames_fps)
    except VideoError as err:
        raise CloneError(f"cannot read the input video: {err}") from None
    frames_dir = fresh_dir(out_dir / "frames")
    side = []
    for t in range(frames):
        row = [_caption(shown[t % len(shown)], f"input {video.name}"[:40])]
        row += [_caption(rendered[n][t], _panel_caption(n, c)) for n, c in panels]
        image = np.concatenate(row, axis=1)
        Image.fromarray(image).save(frames_dir / f"{t:04d}.png")
        side.append(image)
    write_mp4(side, out_dir / "clone.mp4", prediction["fps"])

    doc = {
        "video": str(video),
        "predicted": {k: prediction[k] for k in ("class_index", "p", "k", "confidence", "vote_share",
                                                 "subsequences", "frames_read", "top3")},
        "class_index": prediction["class_index"], "p": prediction["p"], "k": prediction["k"],
        "confidence": prediction["confidence"],
        "model": {"checkpoint": str(train_dir / "checkpoint.pt"), "train_dir": str(train_dir),
                  "setting": train_dir.parts[-4], "variant": train_dir.parts[-3], "model": train_dir.parts[-2],
                  "seed": int(train_dir.name.lstrip("s"))},
        "garment": {"kind": garment, "shape": dataclasses.asdict(shape), "motion": waist.params(),
                    "vertices": skirt_mesh.num_vertices, "faces": int(len(skirt_mesh.mesh.faces))},
        "material": {"basis": cfg.sim.basis, "density_kg_m2": basis.density,
                     "note": "every stretching entry of the basis times p, every bending entry times k"},
        "sim": {"fps": cfg.sim.fps, "frames": frames, "substeps": cfg.sim.substeps, "settle_s": settle_s,
                "cg_iterations": cfg.sim.cg_iterations, "device": sim_device, "seconds": round(sim_seconds, 2)},
        "render": {"variant": rvariant.name, "resolution": resolution, "spp": spp,
                   "backend": rmeta["render"]["backend"], "seconds": round(render_seconds, 2)},
        "seeds": {"run_seed": cfg.seed, "render_clip_index": render_index,
                  "sampler_seed": rmeta["render"]["sampler_seed"],
                  "note": "the simulation is deterministic; render draws come from "
                          "clothgap.seeding.rng(run_seed, render_clip_index, RENDER, stream)"},
        "panels": panel_info,
        "outputs": {"video": str(out_dir / "clone.mp4"), "frames": str(frames_dir),
                    "input_clip": str(out_dir / "input" / "clip")},
        "seconds": round(time.perf_counter() - start, 2),
    }
    path = out_dir / "clone.json"
    atomic_write_json(path, doc)
    say(f"wrote {out_dir / 'clone.mp4'} and {path}")
    return path


def _name(video: Path) -> str:
    import re

    name = video.stem if video.is_file() else video.name
    return re.sub(r"[^A-Za-z0-9_.-]+", "_", name).strip("._") or "video"
