"""Training end to end on synthetic clips: outputs, resume after a kill, the grid, predictions."""

from __future__ import annotations

import json
import re

import pandas as pd
import pytest
import torch

import learn.train
from clothgap.config import ConfigError
from clothgap.runs import Run, is_done
from learn.predict import load_model, predict_clips
from learn.split import get_or_make_split
from learn.stage import run_train
from learn.synthetic import synthetic_run
from learn.train import train_one
from tests.conftest import SETTING, VARIANT, tiny_train_config


class SimulatedKill(Exception):
    pass


def kill_after_first_epoch(run: Run, monkeypatch) -> None:
    """Train lrcn until its first last.pt is written, then stop as a kill would."""
    save_state = learn.train._save_state

    def save_then_die(path, state):
        save_state(path, state)
        raise SimulatedKill

    monkeypatch.setattr(learn.train, "_save_state", save_then_die)
    with pytest.raises(SimulatedKill):
        train_one(run, SETTING, VARIANT, "lrcn", 0, progress=False)
    monkeypatch.setattr(learn.train, "_save_state", save_state)


def test_train_one_writes_its_folder_and_a_killed_run_resumes_to_the_same_weights(tmp_path, monkeypatch):
    cfg = tiny_train_config(augment=True)
    whole = synthetic_run(tmp_path / "whole", cfg)
    killed = synthetic_run(tmp_path / "killed", cfg)
    out = train_one(whole, SETTING, VARIANT, "lrcn", 0, progress=False)

    ckpt = torch.load(out / "checkpoint.pt", weights_only=True)
    assert {"model", "model_name", "model_args", "num_classes", "setting", "variant", "seed", "config"} <= set(ckpt)
    assert ckpt["num_classes"] == 54 and ckpt["model_name"] == "lrcn" and ckpt["variant"] == VARIANT
    metrics = pd.read_csv(out / "metrics.csv")
    assert list(metrics.columns) == ["epoch", "train_loss", "train_acc", "val_loss", "val_acc", "lr", "seconds"]
    assert metrics.epoch.tolist() == [0, 1, 2] and metrics.val_acc.notna().all()
    assert any((out / "tb").iterdir()) and (out / "last.pt").is_file() and is_done(out)
    assert json.loads((out / "config.json").read_text())["train"]["epochs"] == 3

    kill_after_first_epoch(killed, monkeypatch)
    resumed_dir = killed.train_dir(SETTING, VARIANT, "lrcn", 0)
    before_kill = pd.read_csv(resumed_dir / "metrics.csv")
    assert not is_done(resumed_dir) and len(before_kill) == 1
    train_one(killed, SETTING, VARIANT, "lrcn", 0, progress=False)

    resumed = torch.load(resumed_dir / "checkpoint.pt", weights_only=True)["model"]
    assert all(torch.equal(resumed[k], v) for k, v in ckpt["model"].items())
    again = pd.read_csv(resumed_dir / "metrics.csv")
    pd.testing.assert_frame_equal(again.drop(columns="seconds"), metrics.drop(columns="seconds"))
    assert again.seconds[0] == before_kill.seconds[0]   # epoch 0 was resumed from, not redone

    stamp = (out / "DONE").stat().st_mtime_ns
    assert train_one(whole, SETTING, VARIANT, "lrcn", 0, progress=False) == out   # finished: skipped
    assert (out / "DONE").stat().st_mtime_ns == stamp


def test_trained_model_beats_chance_on_held_out_sequences(tmp_path):
    run = synthetic_run(tmp_path / "run", tiny_train_config(epochs=20, val_fraction=0.0, dropout=0.0))
    out = train_one(run, SETTING, VARIANT, "lrcn", 0, progress=False)
    test_clips = [run.render_dir(VARIANT, SETTING) / c for c in get_or_make_split(run, SETTING)["test"]]
    pred = predict_clips(out, test_clips, device="cpu", batch_size=5)
    assert list(pred.columns) == ["clip_id", "start", "class_index", "pred", "probs"]
    assert len(pred) == len(test_clips) * 3 and pred.probs.iloc[0].shape == (54,)
    assert (pred.pred == pred.class_index).mean() > 0.5   # chance is 1/4; run seeds 0-7 gave 0.75-1
    assert not load_model(out).training


def test_run_train_grid_base2_freezes_base1s_cnn_and_writes_the_index(tmp_path):
    cfg = tiny_train_config(models=("base2", "base1"), epochs=1, val_fraction=0.0, factored=True)
    run = synthetic_run(tmp_path / "run", cfg)
    index = run_train(run, progress=False)
    assert [(e["model"], e["done"]) for e in index["entries"]] == [("base1", True), ("base2", True)]
    assert json.loads((run.root / "train" / "index.json").read_text()) == index
    base1 = torch.load(run.root / index["entries"][0]["dir"] / "checkpoint.pt", weights_only=True)["model"]
    base2 = torch.load(run.root / index["entries"][1]["dir"] / "checkpoint.pt", weights_only=True)["model"]
    assert all(torch.equal(base2[k], v) for k, v in base1.items() if k.startswith("cnn."))
    assert "temporal.weight_ih_l0" in base2 and "head_bend.weight" in base2


def test_pretrained_cnn_weights_come_from_a_local_file(tmp_path):
    donor = synthetic_run(tmp_path / "donor", tiny_train_config(models=("base1",), epochs=1, val_fraction=0.0))
    weights = train_one(donor, SETTING, VARIANT, "base1", 0, progress=False) / "checkpoint.pt"
    run = synthetic_run(tmp_path / "run", tiny_train_config(epochs=1, val_fraction=0.0, pretrained=str(weights)))
    out = train_one(run, SETTING, VARIANT, "lrcn", 0, progress=False)
    assert json.loads((out / "config.json").read_text())["cnn_init"] == str(weights)
    missing = synthetic_run(tmp_path / "missing", tiny_train_config(epochs=1, pretrained=str(tmp_path / "absent.pt")))
    with pytest.raises(FileNotFoundError, match="absent.pt"):
        train_one(missing, SETTING, VARIANT, "lrcn", 0, progress=False)


def test_unknown_model_in_the_grid_is_named(tmp_path):
    with pytest.raises(ConfigError, match="train.models: unknown model 'resnet'; known: lrcn"):
        synthetic_run(tmp_path / "bad", tiny_train_config(models=("lrcn", "resnet")))   # refused when the run starts
    run = synthetic_run(tmp_path / "run", tiny_train_config(epochs=1))
    run = Run(run.root, tiny_train_config(models=("lrcn", "resnet")))                  # a config never validated
    with pytest.raises(ValueError, match="resnet.*known: lrcn"):
        run_train(run, progress=False)


def test_split_by_subsequence_trains_on_exactly_the_train_windows(tmp_path):
    from learn.split import part_windows

    run = synthetic_run(tmp_path / "run", tiny_train_config(epochs=1, split_by="subsequence", clip_stride=6))
    out = train_one(run, SETTING, VARIANT, "lrcn", 0, progress=False)
    split = get_or_make_split(run, SETTING)
    assert split["by"] == "subsequence" and all("@" in item for item in split["train"])
    resolved = json.loads((out / "config.json").read_text())
    assert resolved["train_subsequences"] == len(split["train"])
    assert resolved["val_subsequences"] == len(split["val"])
    train, test = part_windows(split, "train"), part_windows(split, "test")
    assert set(train) & set(test)       # one simulation on both sides, as the protocol intends
    assert all(not set(train[c]) & set(test[c]) for c in set(train) & set(test))


def _sim_clips_for(run: Run, frames: int, flown: str | None = None) -> None:
    """Simulated clips beside the synthetic renders: a 6 x 6 sheet that sinks by its clip index and frame
    (clip ``flown`` is 100 m away, a sheet gone astray)."""
    import numpy as np

    from clothgap.runs import mark_done
    from sim.clip import SimClip

    u, v = np.meshgrid(np.linspace(0, 1, 6), np.linspace(0, 1, 6), indexing="ij")
    uv = np.stack([u.ravel(), v.ravel()], -1).astype(np.float32)
    rest = np.concatenate([uv, np.zeros((36, 1), np.float32)], 1)
    for cid in run.done_clips(run.render_dir(VARIANT, SETTING)):
        index = int(cid[1:])
        positions = rest[None] - np.array([0, 0, 0.01 * index])[None, None] \
            - 0.002 * np.arange(frames)[:, None, None] * np.array([0, 0, 1.0])
        if cid == flown:
            positions = positions + np.array([0, 100.0, 0])
        folder = run.sim_dir(SETTING) / cid
        SimClip.from_fixed({"class_index": 0}, positions.astype(np.float32), np.array([[0, 1, 6]], np.int32),
                           uv).save(folder)
        mark_done(folder)


def test_geometry_targets_follow_the_frame_cache_and_train_an_auxiliary_head(tmp_path):
    import numpy as np

    from clothgap.errors import MissingInputError
    from learn.dataset import build_cache
    from learn.geometry import geometry_targets

    cfg = tiny_train_config(aux_geometry=1.0, epochs=1)
    run = synthetic_run(tmp_path / "run", cfg)
    with pytest.raises(MissingInputError, match="c00000"):
        train_one(run, SETTING, VARIANT, "lrcn", 0, progress=False)   # the target needs the simulation
    _sim_clips_for(run, cfg.sim.frames)
    cache = build_cache(run, VARIANT, SETTING, 32, progress=False)
    targets = geometry_targets(run, SETTING, cache, progress=False)
    assert targets.shape == (cache.frames.shape[0], 192)
    assert float(np.abs(np.median(targets, axis=0)).max()) < 1e-4
    # Every z of clip c at frame t is -(0.01 c + 0.002 t), standardised: rows follow clips and frames.
    z = targets.reshape(len(targets), 64, 3)[:, 0, 2]
    for cid, clip in cache.clips.items():
        rows = z[clip.offset:clip.offset + clip.num_frames]
        assert np.all(np.diff(rows) < 0)                                          # sinks frame by frame
        step = rows[0] - rows[1]
        assert np.isclose(z[cache.clips["c00000"].offset] - rows[0], 5 * step * int(cid[1:]), rtol=1e-3)
    out = train_one(run, SETTING, VARIANT, "lrcn", 0, progress=False)
    state = torch.load(out / "checkpoint.pt", weights_only=True)
    assert state["model"]["head_geometry.weight"].shape == (192, 32)
    assert state["model_args"]["geometry_dim"] == 192
    assert load_model(out)(torch.rand(1, 6, 3, 32, 32))["geometry"].shape == (1, 6, 192)
    shape = pd.read_csv(out / "metrics.csv")[["train_shape", "val_shape"]]
    assert shape.notna().all().all() and (shape > 0).all().all()   # how well the lattice is read, per epoch


def test_lattices_read_in_a_process_pool_are_those_read_here(tmp_path):
    import numpy as np

    from learn.geometry import clip_lattices
    from sim.clip import SimClip

    cfg = tiny_train_config(aux_geometry=1.0, epochs=1)
    run = synthetic_run(tmp_path / "run", cfg)
    _sim_clips_for(run, cfg.sim.frames)
    # one clip whose mesh changes every frame, as an adaptive clip's does
    rng = np.random.default_rng(0)
    frames = [(rng.normal(size=(n, 3)).astype(np.float32), np.array([[0, 1, n - 1]], np.int32),
               rng.uniform(size=(n, 2)).astype(np.float32)) for n in rng.integers(40, 90, cfg.sim.frames)]
    SimClip.from_frames({"class_index": 0}, frames).save(run.sim_dir(SETTING) / "c00001")
    ids = run.done_clips(run.render_dir(VARIANT, SETTING))
    pooled = clip_lattices(run, SETTING, ids, progress=False, processes=2)
    run.lattice_cache_path(SETTING, 8).unlink()
    here = clip_lattices(run, SETTING, ids, progress=False, processes=0)
    assert all(np.array_equal(pooled[c], here[c]) for c in ids) and len(ids) == 16
    first = here["c00001"][0]                                     # each point is a vertex of its own frame
    assert all(any(np.array_equal(p, q) for q in frames[0][0]) for p in first)


def test_a_lattice_point_is_the_vertex_nearest_to_it_in_uv():
    import numpy as np

    from sim.lattice import lattice_vertices

    uv = np.random.default_rng(1).uniform([0.0, -0.5], [2.0, 0.5], size=(500, 2)).astype(np.float32)
    index = lattice_vertices(uv, 8)
    grid = (np.arange(8) + 0.5) / 8
    lo, hi = uv.min(0).astype(np.float64), uv.max(0).astype(np.float64)
    for k, (i, j) in enumerate(np.ndindex(8, 8)):
        point = lo + np.array([grid[i], grid[j]]) * (hi - lo)
        assert index[k] == np.argmin(np.linalg.norm(uv - point, axis=1))


def test_frame_centred_targets_leave_out_what_every_clip_does_at_that_frame(tmp_path):
    import numpy as np

    from learn.dataset import build_cache
    from learn.geometry import geometry_targets

    cfg = tiny_train_config(aux_geometry=1.0, geometry_centre="frame", epochs=1)
    run = synthetic_run(tmp_path / "run", cfg)
    _sim_clips_for(run, cfg.sim.frames)
    cache = build_cache(run, VARIANT, SETTING, 32, progress=False)
    # Every z of clip c at frame t is -(0.01 c + 0.002 t): the sinking all clips share is gone, the clips'
    # order stays.
    targets = geometry_targets(run, SETTING, cache, progress=False, centre="frame").reshape(-1, 64, 3)
    z = {cid: targets[c.offset:c.offset + c.num_frames, 0, 2] for cid, c in sorted(cache.clips.items())}
    assert all(np.allclose(rows, rows[0], atol=1e-4) for rows in z.values())
    firsts = [z[cid][0] for cid in sorted(z)]
    assert np.all(np.diff(firsts) < 0)
    out = train_one(run, SETTING, VARIANT, "lrcn", 0, progress=False)
    assert json.loads((out / "config.json").read_text())["train"]["geometry_centre"] == "frame"


def test_reader_truth_reaches_the_readers_through_training(tmp_path):
    readers = {}
    for weight in (0.0, 1.0):
        cfg = tiny_train_config(bottleneck=True, dropout=0.0, reader_truth=weight, epochs=1)
        run = synthetic_run(tmp_path / f"run{weight}", cfg)
        _sim_clips_for(run, cfg.sim.frames)
        out = train_one(run, SETTING, VARIANT, "lrcn", 0, progress=False)
        state = torch.load(out / "checkpoint.pt", weights_only=True)["model"]
        readers[weight] = state["reader.0.weight"]
        assert torch.isfinite(readers[weight]).all()
    # Same seed, same clips: only the true-lattice loss can make the readers differ.
    assert not torch.equal(readers[0.0], readers[1.0])


def test_train_fraction_trains_on_fewer_sequences_of_the_same_split(tmp_path):
    windows = {}
    for fraction in (1.0, 0.5):
        cfg = tiny_train_config(train_fraction=fraction, epochs=1)
        run = synthetic_run(tmp_path / f"run{fraction}", cfg)
        out = train_one(run, SETTING, VARIANT, "lrcn", 0, progress=False)
        windows[fraction] = json.loads((out / "config.json").read_text())["train_subsequences"]
    assert 0 < windows[0.5] < windows[1.0]


def test_a_lattice_head_over_three_frames_trains_and_loads(tmp_path):
    cfg = tiny_train_config(bottleneck=True, dropout=0.0, geometry_window=3, epochs=1)
    run = synthetic_run(tmp_path / "run", cfg)
    _sim_clips_for(run, cfg.sim.frames)
    out = train_one(run, SETTING, VARIANT, "lrcn", 0, progress=False)
    state = torch.load(out / "checkpoint.pt", weights_only=True)
    assert state["model_args"]["geometry_window"] == 3
    assert state["model"]["head_geometry.conv.weight"].shape == (192, 32, 3)
    assert load_model(out)(torch.rand(1, 6, 3, 32, 32))["geometry"].shape == (1, 6, 192)


def test_a_clip_gone_astray_does_not_flatten_every_other_target(tmp_path):
    import numpy as np

    from learn.dataset import build_cache
    from learn.geometry import TARGET_LIMIT, geometry_targets

    cfg = tiny_train_config(aux_geometry=1.0, epochs=1)
    run = synthetic_run(tmp_path / "run", cfg)
    _sim_clips_for(run, cfg.sim.frames, flown="c00003")
    cache = build_cache(run, VARIANT, SETTING, 32, progress=False)
    with pytest.warns(UserWarning, match="c00003"):
        targets = geometry_targets(run, SETTING, cache, progress=False)
    assert float(np.abs(targets).max()) == TARGET_LIMIT
    others = np.concatenate([targets[c.offset:c.offset + c.num_frames] for cid, c in cache.clips.items()
                             if cid != "c00003"])
    assert others[:, 2].std() > 0.3    # the sheets' sinking still spans the standardised range


def test_diverged_training_is_not_marked_done(tmp_path):
    from learn.train import TrainingDiverged

    run = synthetic_run(tmp_path / "run", tiny_train_config(lr=1e6, epochs=3))
    with pytest.raises(TrainingDiverged, match=r"train\.lr=1e\+06"):
        train_one(run, SETTING, VARIANT, "lrcn", 0, progress=False)
    folder = run.train_dir(SETTING, VARIANT, "lrcn", 0)
    assert not is_done(folder) and not (folder / "checkpoint.pt").exists()


class _Payload:
    """Unpickling this runs code: it creates the file it names."""

    def __init__(self, path):
        self.path = str(path)

    def __reduce__(self):
        return (open, (self.path, "w"))


def test_a_pickle_payload_in_last_pt_does_not_run(tmp_path, monkeypatch):
    run = synthetic_run(tmp_path / "run", tiny_train_config(epochs=2))
    kill_after_first_epoch(run, monkeypatch)
    folder = run.train_dir(SETTING, VARIANT, "lrcn", 0)
    marker = tmp_path / "payload-ran"
    torch.save({"model": _Payload(marker)}, folder / "last.pt")
    with pytest.warns(UserWarning, match="cannot be resumed from"):
        train_one(run, SETTING, VARIANT, "lrcn", 0, progress=False)
    assert not marker.exists() and is_done(folder)
    assert pd.read_csv(folder / "metrics.csv").epoch.tolist() == [0, 1]   # started over


def test_keep_best_checkpoints_the_best_validation_epoch(tmp_path):
    run = synthetic_run(tmp_path / "run", tiny_train_config(keep="best", epochs=4))
    out = train_one(run, SETTING, VARIANT, "lrcn", 0, progress=False)
    metrics = pd.read_csv(out / "metrics.csv")
    best_epoch = int(metrics.val_acc.idxmax())                 # the first epoch with the highest accuracy
    assert json.loads((out / "DONE").read_text())["kept_epoch"] == best_epoch
    kept = torch.load(out / "checkpoint.pt", weights_only=True)["model"]
    state = torch.load(out / "last.pt", weights_only=True)
    assert state["best"]["epoch"] == best_epoch
    assert all(torch.equal(kept[k], v) for k, v in state["best"]["model"].items())
    # The kept weights' validation predictions: every validation window once, scored as the kept epoch was.
    val = pd.read_csv(out / "val_predictions.csv", dtype={"clip_id": str})
    split = get_or_make_split(run, SETTING)
    assert set(val.clip_id) == set(split["val"]) and not val.duplicated(["clip_id", "start"]).any()
    probs = val[[f"prob_{i:02d}" for i in range(54)]].to_numpy()
    assert (probs.argmax(1) == val.pred).all() and abs(probs.sum(1) - 1).max() < 1e-4
    assert (val.pred == val.class_index).mean() == pytest.approx(metrics.val_acc[best_epoch], abs=1e-9)
    with pytest.raises(ConfigError, match="train.keep=best needs validation clips"):
        synthetic_run(tmp_path / "noval", tiny_train_config(keep="best", val_fraction=0.0))


@pytest.mark.slow
def test_parallel_training_trains_the_grid_side_by_side_as_one_process_does(tmp_path, capfd):
    from clothgap.api import train_selected
    from clothgap.executor import train_jobs

    cfg = tiny_train_config(models=("lrcn", "base2", "base1"), epochs=2, num_threads=1)
    grid = [("w", "p", "base1", 0), ("w", "p", "base2", 0), ("w", "p", "lrcn", 0), ("a", "p", "base1", 0)]
    # base2 starts from base1's CNN: the two share a job; everything else runs on its own
    assert train_jobs(grid) == [grid[:2], [grid[2]], [grid[3]]]
    alone = synthetic_run(tmp_path / "alone", cfg)
    side_by_side = synthetic_run(tmp_path / "side", cfg)
    folders = train_selected(side_by_side, progress=False, parallel=2)
    said = capfd.readouterr().err       # where a study's train stage spends its time, said as it goes
    assert re.search(r"ready in [\d.]+ s \(splits [\d.]+ s, caches [\d.]+ s, lattices [\d.]+ s\)", said), said
    assert re.search(r"train: wave 1 of 1, 3 model\(s\) in 2 job\(s\), [\d.]+ s", said), said
    train_selected(alone, progress=False)
    index = json.loads(side_by_side.train_index_path.read_text())
    assert [(e["model"], e["done"]) for e in index["entries"]] == [("lrcn", True), ("base1", True), ("base2", True)]
    assert [side_by_side.root / e["dir"] for e in index["entries"]] == folders
    for entry in index["entries"]:      # the same weights' curves: a model's training does not depend on where it ran
        a = pd.read_csv(alone.root / entry["dir"] / "metrics.csv")
        b = pd.read_csv(side_by_side.root / entry["dir"] / "metrics.csv")
        pd.testing.assert_frame_equal(a.drop(columns="seconds"), b.drop(columns="seconds"))


@pytest.mark.slow
def test_training_on_ray_gives_the_models_one_process_gives(tmp_path):
    pytest.importorskip("ray")
    from clothgap.api import train_selected
    from clothgap.executor import ExecutorOptions

    cfg = tiny_train_config(models=("lrcn", "base2", "base1"), epochs=2, num_threads=1)
    alone, on_ray = synthetic_run(tmp_path / "alone", cfg), synthetic_run(tmp_path / "ray", cfg)
    train_selected(alone, progress=False)
    # a fresh local instance with two CPUs: base1 and base2 in one task, lrcn in another
    folders = train_selected(on_ray, progress=False, options=ExecutorOptions("ray", workers=2))
    assert all(is_done(f) for f in folders) and len(folders) == 3
    for folder in folders:
        a = pd.read_csv(alone.root / folder.relative_to(on_ray.root) / "metrics.csv")
        pd.testing.assert_frame_equal(a.drop(columns="seconds"), pd.read_csv(folder / "metrics.csv").drop(columns="seconds"))
    with pytest.raises(ConfigError, match="--shard-size"):
        train_selected(on_ray, progress=False, options=ExecutorOptions("ray", workers=2, shard_size=4))


def _kill_fc6(monkeypatch, every_start: bool = False) -> None:
    """Every fc6 unit off for every input when a model is built from its first seed (or from every seed: a bias
    far below any input's reach): what the GPU training that never left chance looked like."""
    build = learn.train.build_training_model

    def build_then_kill(resolved, device):
        model = build(resolved, device)
        if every_start or not resolved.get("restarts"):
            with torch.no_grad():
                model.cnn.fc6[1].bias.fill_(-1e4)
        return model

    monkeypatch.setattr(learn.train, "build_training_model", build_then_kill)


def test_a_network_dead_from_its_first_epoch_is_trained_again_from_a_new_start(tmp_path, monkeypatch):
    run = synthetic_run(tmp_path / "run", tiny_train_config(epochs=2))
    _kill_fc6(monkeypatch)
    with pytest.warns(UserWarning, match="same output after epoch 0 .* start 2 of at most 3"):
        out = train_one(run, SETTING, VARIANT, "lrcn", 0, progress=False)
    done, config = json.loads((out / "DONE").read_text()), json.loads((out / "config.json").read_text())
    assert done["restarts"] == 1 and config["restarts"] == 1
    assert config["torch_seed"] == learn.train.restart_seed(config["first_torch_seed"], 1) != config["first_torch_seed"]
    assert pd.read_csv(out / "metrics.csv").epoch.tolist() == [0, 1]     # the dead start's epoch is not kept
    model = load_model(out)
    val = learn.train.window_sets(run, SETTING, VARIANT, run.config.train, torch.device("cpu"), False)[1]
    assert not learn.train.network_is_dead(model, val, 8)

    # killed after the restart's first epoch, it resumes as the restart instead of starting over
    (out / "DONE").unlink()
    (out / "checkpoint.pt").unlink()
    state = torch.load(out / "last.pt", weights_only=True)
    state["epoch"], state["metrics"] = 0, state["metrics"][:1]
    torch.save(state, out / "last.pt")
    first_epoch = state["metrics"][0]["seconds"]
    again = train_one(run, SETTING, VARIANT, "lrcn", 0, progress=False)
    assert json.loads((again / "DONE").read_text())["restarts"] == 1
    assert pd.read_csv(again / "metrics.csv").seconds[0] == pytest.approx(first_epoch, rel=1e-5)   # not redone


def test_a_network_dead_after_every_restart_is_an_error_and_not_done(tmp_path, monkeypatch):
    run = synthetic_run(tmp_path / "run", tiny_train_config(epochs=2))
    _kill_fc6(monkeypatch, every_start=True)
    with pytest.warns(UserWarning), pytest.raises(learn.train.TrainingDead, match="after 2 new starts"):
        train_one(run, SETTING, VARIANT, "lrcn", 0, progress=False)
    assert not is_done(run.train_dir(SETTING, VARIANT, "lrcn", 0))
    # run again, it goes on from its last start and is refused again: no dead epoch was saved for a resume to finish
    with pytest.raises(learn.train.TrainingDead, match="after 2 new starts"):
        train_one(run, SETTING, VARIANT, "lrcn", 0, progress=False)
    assert not is_done(run.train_dir(SETTING, VARIANT, "lrcn", 0))


def test_a_dead_network_in_its_last_epoch_is_never_finished_by_a_resume(tmp_path, monkeypatch):
    run = synthetic_run(tmp_path / "run", tiny_train_config(epochs=1))
    build = learn.train.build_training_model
    _kill_fc6(monkeypatch, every_start=True)
    with pytest.warns(UserWarning), pytest.raises(learn.train.TrainingDead):
        train_one(run, SETTING, VARIANT, "lrcn", 0, progress=False)
    folder = run.train_dir(SETTING, VARIANT, "lrcn", 0)
    assert not (folder / "last.pt").exists()
    monkeypatch.setattr(learn.train, "build_training_model", build)   # even if the next start were alive,
    out = train_one(run, SETTING, VARIANT, "lrcn", 0, progress=False)   # it trains; it does not finish a dead one
    assert is_done(out) and not learn.train.network_is_dead(load_model(out), learn.train.window_sets(
        run, SETTING, VARIANT, run.config.train, torch.device("cpu"), False)[1], 8)


def test_a_shared_regressor_is_taken_frozen_and_its_readers_train_on_its_shapes(tmp_path, monkeypatch):
    """Every model but the named one keeps that model's CNN and lattice head bit for bit and trains its readers
    on the shapes they predict: what it predicts from the frames is what it was scored with on the shapes, and
    a killed reader training resumes to the same weights."""
    from learn.dataset import build_cache
    from learn.split import part_windows
    from learn.windows import WindowSet

    cfg = tiny_train_config(bottleneck=True, dropout=0.0, reader_truth=1.0, bottleneck_noise=0.2, epochs=2,
                            models=("lrcn", "base3"), shared_regressor="lrcn")
    runs = {}
    for name in ("whole", "killed"):
        runs[name] = synthetic_run(tmp_path / name, cfg)
        _sim_clips_for(runs[name], cfg.sim.frames)
    out = train_one(runs["whole"], SETTING, VARIANT, "base3", 0, progress=False)      # trains lrcn first
    source = runs["whole"].train_dir(SETTING, VARIANT, "lrcn", 0)
    assert is_done(source)
    assert json.loads((out / "config.json").read_text())["cnn_init"] == str(source / "checkpoint.pt")
    regressor = torch.load(source / "checkpoint.pt", weights_only=True)["model"]
    reader = torch.load(out / "checkpoint.pt", weights_only=True)["model"]
    frozen = [k for k in regressor if k.startswith(("cnn.", "head_geometry."))]
    assert frozen and all(torch.equal(reader[k], regressor[k]) for k in frozen)
    assert "temporal.weight_hh_l0" in reader          # base3's own RNN, trained on the shapes
    metrics = pd.read_csv(out / "metrics.csv")
    assert metrics.train_loss.notna().all() and "train_shape" not in metrics   # no lattice loss: frozen
    from eval.ablation import training_speed
    shape_seconds = json.loads((out / "DONE").read_text())["shape_seconds"]
    speed = training_speed(out)
    assert shape_seconds > 0 and speed["shape_seconds"] == shape_seconds       # the shapes' pass is counted
    assert speed["train_seconds"] == pytest.approx(metrics.seconds.sum() + shape_seconds, abs=0.01)
    assert speed["data_seconds"] > 0      # the set-up (frames onto the device) is recorded apart from the epochs

    # The whole model from its checkpoint on the validation frames gives the probabilities written from shapes.
    model = load_model(out)
    split = get_or_make_split(runs["whole"], SETTING)
    cache = build_cache(runs["whole"], VARIANT, SETTING, cfg.train.image_size, progress=False)
    frames = WindowSet(cache, part_windows(split, "val"), cfg.train.clip_len, cfg.train.clip_stride)
    from_frames = frames.predict(model, cfg.train.batch_size)
    from_shapes = pd.read_csv(out / "val_predictions.csv", dtype={"clip_id": str})
    columns = [f"prob_{i:02d}" for i in range(54)]
    assert list(from_shapes.clip_id) == list(from_frames.clip_id)
    assert abs(from_shapes[columns].to_numpy() - pd.DataFrame(from_frames.probs.tolist()).to_numpy()).max() < 1e-5

    kill_train = learn.train._save_state

    def save_then_die(path, state):
        kill_train(path, state)
        if "base3" in str(path):
            raise SimulatedKill

    monkeypatch.setattr(learn.train, "_save_state", save_then_die)
    with pytest.raises(SimulatedKill):
        train_one(runs["killed"], SETTING, VARIANT, "base3", 0, progress=False)
    monkeypatch.setattr(learn.train, "_save_state", kill_train)
    resumed = torch.load(train_one(runs["killed"], SETTING, VARIANT, "base3", 0, progress=False) / "checkpoint.pt",
                         weights_only=True)["model"]
    assert all(torch.equal(resumed[k], v) for k, v in reader.items())

    # A regressor trained again at the same path while a reader was unfinished: the reader starts over on it
    # rather than resuming a last.pt whose frozen parts are the old regressor's.
    monkeypatch.setattr(learn.train, "_save_state", save_then_die)
    runs["retrained"] = synthetic_run(tmp_path / "retrained", cfg)
    _sim_clips_for(runs["retrained"], cfg.sim.frames)
    with pytest.raises(SimulatedKill):
        train_one(runs["retrained"], SETTING, VARIANT, "base3", 0, progress=False)
    monkeypatch.setattr(learn.train, "_save_state", kill_train)
    path = runs["retrained"].train_dir(SETTING, VARIANT, "lrcn", 0) / "checkpoint.pt"
    checkpoint = torch.load(path, weights_only=True)
    checkpoint["model"]["head_geometry.weight"] += 0.01
    torch.save(checkpoint, path)
    redone = torch.load(train_one(runs["retrained"], SETTING, VARIANT, "base3", 0, progress=False) / "checkpoint.pt",
                        weights_only=True)["model"]
    assert torch.equal(redone["head_geometry.weight"], checkpoint["model"]["head_geometry.weight"])


def test_readers_on_a_shared_regressor_train_their_own_number_of_epochs(tmp_path, monkeypatch):
    cfg = tiny_train_config(bottleneck=True, dropout=0.0, epochs=2, models=("lrcn", "base1"),
                            shared_regressor="lrcn", reader_epochs=5)
    run = synthetic_run(tmp_path / "run", cfg)
    _sim_clips_for(run, cfg.sim.frames)
    asked, compiles = [], learn.train.compiles      # which trainings ask to compile as readers (compile_readers)
    monkeypatch.setattr(learn.train, "compiles", lambda c, d, reads: asked.append(reads) or compiles(c, d, reads))
    reader = train_one(run, SETTING, VARIANT, "base1", 0, progress=False)
    assert asked == [False, True]                   # lrcn trains its CNN first, then base1 reads its shapes
    regressor = run.train_dir(SETTING, VARIANT, "lrcn", 0)
    assert len(pd.read_csv(regressor / "metrics.csv")) == 2 and len(pd.read_csv(reader / "metrics.csv")) == 5
    assert json.loads((reader / "DONE").read_text())["epochs"] == 5
    assert "train.reader_epochs is set but train.shared_regressor is not" in " ".join(
        tiny_train_config(bottleneck=True, reader_epochs=5).train.problems())


def test_a_shared_regressor_needs_the_bottleneck_and_a_model_that_trains_its_own_cnn(tmp_path):
    def problems(**train) -> str:
        return " | ".join(tiny_train_config(**train).train.problems())

    assert "train.shared_regressor is set but train.bottleneck is off" in problems(shared_regressor="lrcn")
    assert "starts from base1's CNN" in problems(shared_regressor="base2", bottleneck=True)
    assert "must be one of the models" in problems(shared_regressor="alexnet", bottleneck=True)
    assert problems(shared_regressor="base1", bottleneck=True) == ""
    with pytest.raises(ConfigError, match="shared_regressor"):
        synthetic_run(tmp_path / "run", tiny_train_config(shared_regressor="lrcn"))


def test_an_unfinished_folder_written_before_a_setting_existed_resumes(tmp_path, monkeypatch):
    """A train setting added since a folder's config.json was written counts as its default (the old behaviour):
    the folder resumes from its last epoch instead of starting over."""
    run = synthetic_run(tmp_path / "run", tiny_train_config())
    kill_after_first_epoch(run, monkeypatch)
    out = run.train_dir(SETTING, VARIANT, "lrcn", 0)
    config = json.loads((out / "config.json").read_text())
    for key in ("shared_regressor", "reader_epochs"):
        del config["train"][key]
    (out / "config.json").write_text(json.dumps(config))
    before = pd.read_csv(out / "metrics.csv")
    train_one(run, SETTING, VARIANT, "lrcn", 0, progress=False)
    assert pd.read_csv(out / "metrics.csv").seconds[0] == before.seconds[0]      # epoch 0 kept, not redone


def test_compile_readers_off_compiles_the_cnn_trainings_and_leaves_the_readers_eager(monkeypatch):
    from dataclasses import replace

    from clothgap.config import StudyConfig, preset
    from eval.ablation import recipe_config
    from learn.config import TrainConfig

    compiled = []
    monkeypatch.setattr(torch, "compile", lambda net, mode=None: compiled.append((net, mode)) or net)
    triton = ["installed"]                           # the CPU-only torch of CI has no Triton: pretend, then not
    real_find_spec = learn.train.importlib.util.find_spec
    monkeypatch.setattr(learn.train.importlib.util, "find_spec",
                        lambda name, *a: (triton[0] or None) if name == "triton" else real_find_spec(name, *a))
    cuda, model = torch.device("cuda", 0), torch.nn.Linear(2, 2)     # a device object: no GPU is touched
    cfg = replace(TrainConfig(), compile=True, compile_mode="reduce-overhead", compile_readers=False)
    assert learn.train.forward_net(model, cfg, cuda, reads_shapes=True) is model and compiled == []
    learn.train.forward_net(model, cfg, cuda, reads_shapes=False)
    assert compiled == [(model, "reduce-overhead")]
    learn.train.forward_net(model, replace(cfg, compile_readers=True), cuda, reads_shapes=True)   # the default
    learn.train.forward_net(model, cfg, torch.device("cpu"), reads_shapes=False)                 # never on a CPU
    assert len(compiled) == 2
    graphs = recipe_config(StudyConfig(), "graphs")
    assert (graphs.compile, graphs.compile_mode, graphs.compile_readers) == (True, "reduce-overhead", True)
    # The paper preset replays graphs in its CNN trainings and replays its readers' whole step from one graph
    # (not torch.compile); `eager` turns both off.
    paper = preset("paper")
    assert learn.train.compiles(paper.train, cuda, reads_shapes=False)
    assert not learn.train.compiles(paper.train, cuda, reads_shapes=True)
    assert learn.train.graphs_readers(paper.train, cuda) and not learn.train.graphs_readers(paper.train, torch.device("cpu"))
    assert not learn.train.compiles(recipe_config(paper, "eager"), cuda, reads_shapes=False)
    assert not learn.train.graphs_readers(recipe_config(paper, "eager"), cuda)
    assert learn.train.compiles(preset("study").train, cuda, reads_shapes=False)
    monkeypatch.setattr(learn.train, "_world_size", lambda: 2)     # torchrun's DDP trains eager
    assert not learn.train.compiles(paper.train, cuda, reads_shapes=False)
    monkeypatch.setattr(learn.train, "_world_size", lambda: 1)
    triton[0] = ""                                   # without Triton, compiling is refused by name
    with pytest.raises(ConfigError, match="train.compile=false"):
        learn.train.forward_net(model, paper.train, cuda)


def test_a_compile_failure_is_named_with_the_way_around_it():
    """torch.compile compiles at the first step; a backend that fails there (here a missing C++ compiler, as
    Inductor reports it) stops training with its cause and the setting that trains without compiling."""
    from torch._dynamo.exc import BackendCompilerFailed

    from learn.train import run_epoch

    cause = RuntimeError("No working C++ compiler found\n  in /usr/bin/c++: not found")
    try:
        failure = BackendCompilerFailed(lambda *a: None, cause, None)
    except TypeError:                                   # (backend, cause) before torch 2.6
        failure = BackendCompilerFailed(lambda *a: None, cause)

    class CompiledAndFailing(torch.nn.Module):
        def forward(self, x):
            raise failure

    batches = [(torch.zeros(2, 3), torch.zeros(2, dtype=torch.long), None)]
    with pytest.raises(ConfigError, match=r"(?s)RuntimeError: No working C\+\+ compiler found\n  in /usr/bin/c\+\+: "
                                          r"not found.*train.compile=false"):
        run_epoch(CompiledAndFailing(), None, batches, torch.device("cpu"))

    class Failing(torch.nn.Module):                     # any other error stays itself
        def forward(self, x):
            raise ValueError("a model bug")

    with pytest.raises(ValueError, match="a model bug"):
        run_epoch(Failing(), None, batches, torch.device("cpu"))
