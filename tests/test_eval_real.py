"""eval.real: videos written here with PyAV, one corrupt file, a freshly initialised model."""

import dataclasses
import json
from pathlib import Path

import av
import numpy as np
import pandas as pd
import pytest
import torch
from PIL import Image
from scipy import stats

from clothgap.config import preset, save_config
from eval import classes
from eval.real import evaluate_real, read_truth


def write_video(path: Path, frames: int = 12, size: int = 64, shade: int = 0) -> None:
    with av.open(str(path), "w") as out:
        codec = "h264" if "libx264" in av.codecs_available else "mpeg4"
        stream = out.add_stream(codec, rate=25)
        stream.width = stream.height = size
        stream.pix_fmt = "yuv420p"
        for t in range(frames):
            img = np.zeros((size, size, 3), np.uint8)
            img[:, : 4 + 4 * t] = (shade, 255 - shade, 128)          # a moving edge
            for packet in stream.encode(av.VideoFrame.from_ndarray(img, format="rgb24")):
                out.mux(packet)
        for packet in stream.encode():
            out.mux(packet)


def fresh_model(root: Path) -> Path:
    """A run folder with config.json and one untrained lrcn in the checkpoint contract format."""
    from learn.models import build_model, model_args

    cfg = preset("smoke")
    cfg = dataclasses.replace(cfg, train=dataclasses.replace(cfg.train, width=4, fc6=16, hidden=8))
    save_config(cfg, root / "config.json")
    train_dir = root / "train" / "wind-uniform1" / "paper" / "lrcn" / "s0"
    train_dir.mkdir(parents=True)
    torch.manual_seed(0)
    args = model_args(cfg.train)
    model = build_model("lrcn", **args)
    torch.save({"model": model.state_dict(), "model_name": "lrcn", "model_args": args, "num_classes": 54,
                "setting": "wind-uniform1", "variant": "paper", "seed": 0,
                "config": {"train": dataclasses.asdict(cfg.train)}}, train_dir / "checkpoint.pt")
    return train_dir


def test_real_videos_end_to_end_with_a_corrupt_file(tmp_path):
    videos = tmp_path / "videos"
    videos.mkdir()
    for i in range(3):
        write_video(videos / f"fabric{i}_w1.mp4", shade=60 * i)
    (videos / "broken.mp4").write_bytes(b"\x00\x01 not a video " * 50)
    frames = videos / "fabric3_w1"                       # a folder of frames works too
    frames.mkdir()
    for t in range(12):
        Image.fromarray(np.full((48, 80, 3), 10 * t, np.uint8)).save(frames / f"{t:03d}.png")
    truth = tmp_path / "truth.csv"
    pd.DataFrame({"video": ["fabric0_w1.mp4", "fabric1_w1", "fabric2_w1.mp4", "fabric3_w1", "broken.mp4"],
                  "bending_N_m2": [1e-5, 3e-5, 9e-5, 2e-4, 1e-4], "area_weight_kg_m2": [0.1, 0.2, 0.3, 0.4, 0.5],
                  "wind": ["W1"] * 5}).to_csv(truth, index=False)

    out = tmp_path / "out"
    path = evaluate_real(videos, truth, fresh_model(tmp_path / "run"), out, resamples=50, progress=False)
    skipped = pd.read_csv(out / "skipped.csv")
    assert list(skipped["video"]) == ["broken.mp4"] and "cannot be decoded" in skipped["reason"][0]
    per_video = pd.read_csv(out / "videos.csv")
    assert sorted(per_video["video"]) == ["fabric0_w1.mp4", "fabric1_w1.mp4", "fabric2_w1.mp4", "fabric3_w1"]
    assert per_video["pred"].between(0, 53).all() and (per_video["subsequences"] == 1).all()
    table = pd.read_csv(path)
    assert list(table["group"].unique()) == ["all", "wind W1"] and (table["videos"] == 4).all()
    assert "broken.mp4" in (out / "table4.md").read_text()
    assert len(list((out / "clips" / "fabric0_w1" / "ldr").glob("*.png"))) == 12
    assert (out / "activations.png").stat().st_size > 1000              # conv5 overlays (Fig. 6)


def test_rendered_clips_are_read_where_they_lie_with_the_predictions_of_a_copy(tmp_path):
    """The measured fabrics' clips are rendered clips: the network reads them in place instead of a copy per
    model, through the same resize, so each video's prediction is the copy's to the byte."""
    from clothgap.runs import mark_done

    rng = np.random.default_rng(0)
    rendered, plain = tmp_path / "render", tmp_path / "plain"
    # Read in place: PNGs only, and PNGs beside frames.npy (the render stage writes both from one array).
    # Copied: frames not square, a meta naming another clip, a clip not finished, frames.npy of other frames.
    names = ("pngs-0", "npy-0", "oblong-0", "renamed-0", "unfinished-0", "npy-short-0")
    for i, name in enumerate(names):
        clip = rendered / name
        (clip / "ldr").mkdir(parents=True)
        (plain / name).mkdir(parents=True)
        frames = rng.integers(0, 256, (12, 12, 20 if name == "oblong-0" else 12, 3), dtype=np.uint8)
        for t, frame in enumerate(frames):
            Image.fromarray(frame).save(clip / "ldr" / f"{t:04d}.png")
            Image.fromarray(frame).save(plain / name / f"{t:04d}.png")
        if name.startswith("npy"):
            np.save(clip / "frames.npy", frames if name == "npy-0" else frames[:10])
        meta = {"clip_id": "other" if name == "renamed-0" else name, "class_index": i, "num_frames": 12}
        (clip / "meta.json").write_text(json.dumps(meta))
        if name != "unfinished-0":
            mark_done(clip)
    truth = tmp_path / "truth.csv"
    pd.DataFrame({"video": list(names), "bending_N_m2": np.linspace(1e-5, 9e-5, len(names)),
                  "area_weight_kg_m2": np.linspace(0.1, 0.6, len(names))}).to_csv(truth, index=False)
    model = fresh_model(tmp_path / "run")
    outs = {}
    for how, inputs in (("in place", {n: rendered / n / "ldr" for n in names}), ("copied", {n: plain / n for n in names})):
        outs[how] = tmp_path / how
        evaluate_real(tmp_path, truth, model, outs[how], resamples=20, activations=1, progress=False, inputs=inputs)
    assert (outs["in place"] / "videos.csv").read_text() == (outs["copied"] / "videos.csv").read_text()
    assert sorted(p.name for p in (outs["in place"] / "clips").iterdir()) == sorted(set(names) - {"pngs-0", "npy-0"})
    assert len(list((outs["copied"] / "clips").iterdir())) == len(names)


def test_correlations_match_scipy_and_group_by_wind(tmp_path):
    videos = tmp_path / "videos"
    rng = np.random.default_rng(0)
    k_index = {}
    rows = []
    for fabric in range(8):
        for wind in ("W1", "W3"):
            name = f"f{fabric}_{wind}"
            folder = videos / name
            folder.mkdir(parents=True)
            for t in range(10):
                Image.fromarray(np.zeros((8, 8, 3), np.uint8)).save(folder / f"{t:02d}.png")
            k_index[name] = int(rng.integers(0, 9))
            rows.append({"video": name, "stiffness": 1e-5 * (1 + k_index[name] + rng.random()),
                         "density": rng.random(), "wind": wind, "label": f"fabric {fabric}"})
    truth = tmp_path / "truth.csv"
    pd.DataFrame(rows).to_csv(truth, index=False)

    def stub(train_dir, clip_dirs):
        out = []
        for d in clip_dirs:
            name = json.loads((d / "meta.json").read_text())["clip_id"]
            probs = np.zeros(54)
            probs[classes.class_of(1, k_index[name])] = 1.0
            out.append({"clip_id": name, "start": 0, "class_index": -1, "pred": int(probs.argmax()), "probs": probs})
        return pd.DataFrame(out)

    path = evaluate_real(videos, truth, fresh_model(tmp_path / "run"), tmp_path / "out", resamples=200,
                         predictor=stub, progress=False)
    table = pd.read_csv(path)
    assert list(table["group"].unique()) == ["all", "wind W1", "wind W3"]
    truth_frame = pd.DataFrame(rows)
    for group, sub in (("all", truth_frame), ("wind W3", truth_frame[truth_frame.wind == "W3"])):
        bending = np.array([classes.K_VALUES[k_index[v]] for v in sub["video"]]) * classes.BASIS_MEAN_BENDING_N_M
        row = table[(table.group == group) & table.score.str.startswith("k x")].iloc[0]
        assert row["stiffness_pearson"] == pytest.approx(stats.pearsonr(bending, sub["stiffness"]).statistic)
        assert row["density_spearman"] == pytest.approx(stats.spearmanr(bending, sub["density"]).statistic)
        assert row["stiffness_pearson_lo"] <= row["stiffness_pearson"] <= row["stiffness_pearson_hi"]


def test_truth_csv_errors_name_the_column(tmp_path):
    bad = tmp_path / "t.csv"
    pd.DataFrame({"video": ["a"], "area_weight_kg_m2": [0.1]}).to_csv(bad, index=False)
    with pytest.raises(ValueError, match="stiffness column"):
        read_truth(bad)
    bouman_like = tmp_path / "b.csv"
    pd.DataFrame({"source_reference": ["MIT_FABRIC_01"], "label": ["Lycra"], "area_weight_kg_m2": [0.24],
                  "bending_N_m2": [7.2e-5]}).to_csv(bouman_like, index=False)
    assert list(read_truth(bouman_like).columns) == ["video", "stiffness", "density", "label"]


def test_basis_bending_constant_matches_the_material_table():
    from sim.materials import load_material

    assert classes.BASIS_MEAN_BENDING_N_M == pytest.approx(load_material("camel-ponte-roma").bending.mean(), rel=1e-4)
