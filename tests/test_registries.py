"""The model and motion registries: every entry builds and runs, unknown names are config errors, the CLI lists them."""

from __future__ import annotations

import os
import subprocess
import sys

import numpy as np
import pytest

from learn.config import READOUTS, TrainConfig
from learn.registry import MODEL_NAMES, MODELS, describe_models, get_model_entry, training_grid, training_order
from sim.config import SimConfig
from sim.motions import MOTIONS, describe_motions, get_motion


def clothgap(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "clothgap", *args], capture_output=True, text=True,
                          env=dict(os.environ))


# ---------------------------------------------------------------- models

@pytest.mark.parametrize("name", MODEL_NAMES)
def test_every_registered_model_builds_and_runs_a_forward_pass(name):
    import torch

    from learn.models import build_model

    torch.manual_seed(0)
    model = build_model(name, image_size=32, width=4, fc6=8, hidden=8, dropout=0.0).eval()
    with torch.no_grad():
        out = model(torch.rand(2, 3, 3, 32, 32))
    assert out["logits"].shape == (2, 3, 54)
    assert torch.isfinite(out["logits"]).all()
    assert torch.allclose(model.probs(out).sum(-1), torch.ones(2))
    entry = get_model_entry(name)
    assert model.freeze_cnn == entry.freeze_cnn
    assert (model.temporal is None) == (entry.temporal is None)


@pytest.mark.parametrize("name", MODEL_NAMES)
def test_every_model_entry_is_complete_and_trained_after_what_it_needs(name):
    entry = MODELS[name]
    assert entry.name == name and entry.description.strip() and entry.title.strip()
    assert entry.temporal in ("lstm", "rnn", None)
    assert entry.readout is None or entry.readout in READOUTS
    if entry.needs is not None:
        assert entry.needs in MODELS
        order = training_order(reversed(MODEL_NAMES))
        assert order.index(entry.needs) < order.index(name)


def test_training_order_keeps_the_registry_order_otherwise():
    assert training_order(["base2", "base3", "lrcn", "base1"]) == ["lrcn", "base1", "base3", "base2"]


def test_the_training_grid_puts_each_model_after_what_it_needs_and_filters():
    from clothgap.config import StudyConfig
    from render.config import RenderConfig

    cfg = StudyConfig(sim=SimConfig(motions=("wind", "arm"), remeshing=("uniform1",)),
                      render=RenderConfig(variants=("paper", "grid")),
                      train=TrainConfig(models=("base2", "lrcn", "base1"), seeds=(0, 1)))
    grid = training_grid(cfg)
    assert len(grid) == 2 * 2 * 3 * 2 and len(set(grid)) == len(grid)
    for i, (setting, variant, model, seed) in enumerate(grid):
        if model == "base2":                                 # base2 freezes base1's CNN of the same cell
            assert (setting, variant, "base1", seed) in grid[:i]
    assert [g[:2] for g in grid[::6]] == cfg.pairs()        # (setting, variant) major, as the config pairs them
    only = training_grid(cfg, settings=["arm-uniform1"], models=["base2"], seeds=[1])
    assert only == [("arm-uniform1", v, "base2", 1) for v in ("paper", "grid")]


def test_an_unknown_model_is_a_config_problem_naming_the_known_ones():
    problems = TrainConfig(models=("lrcn", "alexnet")).problems()
    assert any("'alexnet'" in p and ", ".join(MODEL_NAMES) in p for p in problems), problems
    with pytest.raises(ValueError, match="known models: " + ", ".join(MODEL_NAMES)):
        get_model_entry("alexnet")


def test_config_checks_import_neither_torch_nor_warp():
    code = ("import sys; from clothgap.config import preset; "
            "assert not preset('smoke').train.problems() and not preset('smoke').sim.problems(); "
            "from learn.registry import describe_models; from sim.motions import describe_motions; "
            "print(sorted(m for m in ('torch', 'warp') if m in sys.modules))")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    assert r.stdout.strip() == "[]"


# ---------------------------------------------------------------- motions

@pytest.mark.parametrize("name", list(MOTIONS))
def test_every_registered_motion_simulates_a_tiny_clip_on_cpu(name):
    from sim.stage import build_scene, parse_setting, simulate_scenes
    from sim.mesh import square_cloth

    cfg = SimConfig(motions=(name,), grid_vertices=5, frames=3, substeps=4, settle_s=0.08, device="cpu")
    assert not cfg.problems()
    mesh = square_cloth(cfg.cloth_size_m, cfg.grid_vertices, 1)
    scenes = [build_scene(cfg, 0, i, parse_setting(f"{name}-uniform1"), mesh)[0] for i in (0, 53)]
    results = simulate_scenes(scenes, fps=cfg.fps, frames=cfg.frames, substeps=cfg.substeps, settle_s=cfg.settle_s,
                              device="cpu")
    for scene, result in zip(scenes, results):
        assert result.reason is None
        assert result.positions.shape == (cfg.frames, len(mesh.uv), 3)
        assert np.isfinite(result.positions).all()
        assert scene.motion_params                        # written to the clip's meta.json
    lo, hi = map(np.asarray, get_motion(name).view_box(cfg.cloth_size_m))
    assert (lo < hi).all() and hi[1] - lo[1] <= hi[0] - lo[0]   # the camera looks along y
    assert set(get_motion(name).settings) <= set(vars(cfg))     # its own settings are sim settings


def test_an_unknown_motion_is_a_config_problem_and_never_simulated():
    from sim.stage import parse_setting

    problems = SimConfig(motions=("wind", "swirl")).problems()
    assert any("'swirl'" in p and ", ".join(MOTIONS) in p for p in problems), problems
    with pytest.raises(ValueError, match="known motions: " + ", ".join(MOTIONS)):
        get_motion("swirl")
    with pytest.raises(ValueError, match="unknown motion 'swirl'"):
        parse_setting("swirl-uniform1")


@pytest.mark.parametrize("stage, flag, describe, names", [
    ("train", "--list-models", describe_models, MODEL_NAMES),
    ("sim", "--list-motions", describe_motions, tuple(MOTIONS)),
])
def test_cli_lists_each_registry(stage, flag, describe, names):
    r = clothgap(stage, flag)
    assert r.returncode == 0, r.stderr
    assert r.stdout == describe() + "\n"
    for name in names:
        assert f"{name}: " in r.stdout


def test_a_shared_regressor_is_trained_before_every_other_model_and_shares_their_job():
    from clothgap.executor import train_jobs
    from learn.registry import model_needs

    assert model_needs("base2") == "base1" and model_needs("lrcn") is None
    assert [model_needs(m, "lrcn") for m in ("lrcn", "base1", "base2", "base3")] == [None, "lrcn", "lrcn", "lrcn"]
    assert training_order(["base2", "base3", "lrcn", "base1"], "base3") == ["base3", "lrcn", "base1", "base2"]
    grid = [("w", "p", m, 0) for m in ("lrcn", "base1", "base3", "base2")] + [("w", "p", "lrcn", 1)]
    assert train_jobs(grid, lambda entry: "lrcn") == [grid[:4], grid[4:]]
    # with the regressor trained already, every reader is a job of its own; untrained and left out of the grid,
    # it is trained once, in the one job of its readers
    readers = [e for e in grid if e[2] != "lrcn"]
    assert train_jobs(readers, lambda entry: "lrcn") == [[e] for e in readers]
    assert train_jobs(readers, lambda entry: "lrcn", trained=lambda entry: False) == [readers]
    assert train_jobs([("w", "p", "base2", 0)]) == [[("w", "p", "base2", 0)]]


def test_readers_of_a_regressor_trained_in_the_same_call_wait_for_it_and_then_run_side_by_side():
    from clothgap.executor import train_jobs, train_waves

    shared = lambda entry: "lrcn"   # noqa: E731
    grid = [("w", "p", m, s) for s in (0, 1) for m in ("lrcn", "base1", "base2", "base3")]
    first, readers = train_waves(train_jobs(grid, shared), shared)
    assert first == [[("w", "p", "lrcn", 0)], [("w", "p", "lrcn", 1)]]
    assert readers == [[e] for e in grid if e[2] != "lrcn"]
    # no shared regressor: base2 stays behind its base1 in one job, a single wave
    plain = [("w", "p", m, 0) for m in ("lrcn", "base1", "base2")]
    assert train_waves(train_jobs(plain)) == [train_jobs(plain)]
    # a regressor trained in no job of this call (trained before, or trained inside its readers' job because the
    # grid leaves it out): nothing to wait for, one wave as train_jobs cut it
    readers_only = [e for e in grid if e[2] != "lrcn"]
    for trained in (None, lambda entry: False):
        jobs = train_jobs(readers_only, shared, trained)
        assert train_waves(jobs, shared) == [jobs]
    # a regressor of another recipe with its own readers: each recipe's readers wait in the second wave
    mixed = [("w", "p", "lrcn", 0, "a"), ("w", "p", "base1", 0, "a"), ("w", "p", "lrcn", 0, "b")]
    assert train_waves(train_jobs(mixed, shared), shared) == [[[mixed[0]], [mixed[2]]], [[mixed[1]]]]
