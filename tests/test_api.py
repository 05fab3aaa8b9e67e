"""Studies as scripts: the Python API, the example sweeps, config files and adding work to a finished run."""

from __future__ import annotations

import json
import os
import runpy
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from clothgap import api
from clothgap.cli import resolve_run
from clothgap.config import ConfigError, apply_overrides, apply_settings, preset, read_config_file, validate
from clothgap.runs import Run, mark_done

ROOT = Path(__file__).resolve().parent.parent
# The smallest study that still has a test clip of each class: 2 classes x 2 sequences, half of them held out,
# rendered in the paper's variant only (the tests add others).
TINY = {"render.variants": "paper", "sim.classes": "0,53", "sim.sequences_per_class": 2, "sim.frames": 10, "train.epochs": 1,
        "train.test_fraction": 0.5, "eval.bootstrap": 50}
TINY_SET = [f"{k}={v}" for k, v in TINY.items()]


def clothgap(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "clothgap", *args], capture_output=True, text=True,
                          env={**os.environ, "PYTHONPATH": str(ROOT)})


@pytest.fixture(scope="module")
def paper_run(tmp_path_factory) -> Path:
    """A tiny run with the paper variant simulated, rendered and trained (copied by each test that adds to it)."""
    root = tmp_path_factory.mktemp("api") / "base"
    study = api.start(root, preset="smoke", settings=TINY)
    study.simulate(progress=False)
    study.render(progress=False)
    study.train(progress=False)
    return root


def copy_of(run: Path, tmp_path: Path) -> Path:
    return Path(shutil.copytree(run, tmp_path / run.name))


def frames_of(path: Path) -> np.ndarray:
    """A rendered file's pixels in [0, 1] (HDR: radiance): frames.npy's array, or an image's."""
    if path.suffix == ".npy":
        frames = np.load(path)
        return frames / 255.0 if frames.dtype == np.uint8 else frames.astype(np.float64)
    if path.suffix == ".exr":
        from render.exr import read_exr

        return np.asarray(read_exr(path), dtype=np.float64)
    from PIL import Image

    return np.asarray(Image.open(path), dtype=np.float64) / 255


def sim_stamps(root: Path) -> dict[str, int]:
    return {str(p.relative_to(root)): p.stat().st_mtime_ns for p in sorted(root.glob("sim/*/*/DONE"))}


def run_example(name: str, out: Path) -> api.Study:
    module = runpy.run_path(str(ROOT / "examples" / name), run_name="example")
    return module["main"](["--out", str(out), "--preset", "smoke", *[a for s in TINY_SET for a in ("--set", s)]])


@pytest.mark.slow
@pytest.mark.parametrize("example, added", [("lighting_sweep.py", ("lighting-random", "daylight")),
                                            ("texture_sweep.py", ("grid", "color"))])
def test_example_sweep_adds_variants_to_a_finished_run(paper_run, tmp_path, capsys, example, added):
    root = copy_of(paper_run, tmp_path)
    sims, paper_model = sim_stamps(root), root / "train/wind-uniform1/paper/lrcn/s0/DONE"
    paper_stamp = paper_model.stat().st_mtime_ns
    study = run_example(example, root)

    variants = ("paper", *added)
    assert study.variants == variants
    # nothing finished was redone: the simulations and the paper model are the same files
    assert sim_stamps(root) == sims and paper_model.stat().st_mtime_ns == paper_stamp
    # every model tested on every variant, read back as DataFrames
    matrix = study.gap_matrix()
    assert sorted(matrix.index) == sorted(variants) and sorted(matrix.columns) == sorted(variants)
    assert matrix.notna().all().all() and ((matrix >= 0) & (matrix <= 1)).all().all()
    gap = study.domain_gap()
    assert len(gap) == len(variants) ** 2
    assert set(study.axis_ranking()["axis"]) <= {"texture", "lighting"}
    assert (root / "report" / "report.html").is_file()
    assert "report:" in capsys.readouterr().out


@pytest.mark.slow
def test_a_test_only_variant_is_rendered_and_tested_but_not_trained_on(paper_run, tmp_path):
    study = api.open(copy_of(paper_run, tmp_path))
    summary = study.render(test_variants=["heldout"], progress=False)
    # only the clips the split tests on: one sequence of each of the two classes
    from learn.split import get_or_make_split, part_clips

    tested = part_clips(get_or_make_split(Run.open(study.root), "wind-uniform1"), "test")
    assert summary["rendered"] == 0 and summary["test_variants"]["rendered"] == len(tested) == 2
    done = sorted(p.parent.name for p in (study.root / "render" / "heldout" / "wind-uniform1").glob("*/DONE"))
    assert done == tested
    study.evaluate(progress=False)
    assert study.variants == ("paper",) and not (study.root / "train" / "wind-uniform1" / "heldout").exists()
    gap = study.domain_gap().set_index("test_variant")
    assert list(gap["train_variant"]) == ["paper", "paper"]
    assert np.isfinite(gap.loc["heldout", "acc"]) and np.isnan(gap.loc["heldout", "gap"])   # no heldout model


@pytest.mark.slow
def test_cli_renders_a_test_only_variant_without_making_it_a_training_variant(paper_run, tmp_path):
    from learn.split import make_split, part_clips

    root = copy_of(paper_run, tmp_path)
    shutil.rmtree(root / "splits")                 # as before training: the split training would make is used
    # through the process executor, a clip a worker: the workers render the test look, not the run's own
    r = clothgap("render", str(root), "--test-variant", "heldout", "--executor", "process", "--workers", "2")
    assert r.returncode == 0, r.stderr
    assert "render (test only)" in r.stdout and '"rendered": 2' in r.stdout      # the split's two test clips
    done = sorted(p.parent.name for p in (root / "render" / "heldout" / "wind-uniform1").glob("*/DONE"))
    assert done == part_clips(make_split(Run.open(root), "wind-uniform1"), "test") and len(done) == 2
    assert '"workers": 2' in r.stdout.split("render (test only)")[1]
    # the same frames as one process renders
    here = api.open(copy_of(paper_run, tmp_path / "here"))
    assert here.render(test_variants=["heldout"], progress=False)["test_variants"]["rendered"] == 2
    for clip in done:
        a, b = (r / "render" / "heldout" / "wind-uniform1" / clip for r in (root, here.root))
        files = sorted(p.relative_to(a) for p in a.rglob("*") if p.suffix in (".npy", ".png", ".exr"))
        assert files and files == sorted(p.relative_to(b) for p in b.rglob("*") if p.suffix in (".npy", ".png", ".exr"))
        for f in files:
            x, y = frames_of(a / f), frames_of(b / f)
            # equal but for a rare single path (a reused scene's rounding, Mitsuba's BVH ties: as in
            # test_eval_measured's shard test)
            assert x.shape == y.shape and (np.abs(x - y) > 1e-5).mean() <= 0.01, f
    assert not (root / "splits").exists()          # and not saved: a train setting may still change before training
    assert Run.open(root).config.render.variants == ("paper",)          # the config is not changed
    r = clothgap("render", str(root), "--test-variant", "no-such-look")
    assert r.returncode != 0 and "no-such-look" in r.stderr and "Traceback" not in r.stderr


def test_cli_adds_a_variant_to_a_finished_run_and_refuses_what_invalidates_it(paper_run, tmp_path):
    root = copy_of(paper_run, tmp_path)
    # adding a variant only adds work: accepted and said, then the stage asks for the renders it needs
    r = clothgap("train", str(root), "--set", "render.variants=paper,grid")
    assert "render.variants paper -> paper,grid" in r.stderr, r.stderr
    assert "render/grid/wind-uniform1 is missing" in r.stderr and "Traceback" not in r.stderr
    assert Run.open(root).config.render.variants == ("paper", "grid")
    # changing what finished simulations and models were made with is refused, naming each setting
    r = clothgap("render", str(root), "--set", "sim.frames=12", "--set", "train.lr=0.1", "--set",
                 "render.variants=paper,grid,color")
    assert r.returncode == 2 and "Traceback" not in r.stderr
    assert "sim.frames 10 -> 12" in r.stderr and "train.lr 0.002 -> 0.1" in r.stderr, r.stderr
    assert "render.variants" not in r.stderr.split("invalidate")[1]
    assert Run.open(root).config.render.variants == ("paper", "grid")     # nothing of the refused change was kept


def test_settings_change_freely_until_their_stage_has_finished_work(tmp_path):
    root = tmp_path / "r"
    Run.create_or_resume(root, preset("smoke"))
    changed = apply_overrides(preset("smoke"), ["render.spp=8", "seed=3", "train.epochs=2"])
    assert Run.create_or_resume(root, changed).config.render.spp == 8        # nothing finished yet
    mark_done(root / "sim" / "wind-uniform1" / "c00000")
    with pytest.raises(ConfigError, match=r"seed 3 -> 4 \(sim work is done\)"):
        Run.create_or_resume(root, apply_overrides(changed, ["seed=4"]))
    # the render stage has no finished clip: its settings may still change, and execution settings always
    assert Run.create_or_resume(root, apply_overrides(changed, ["render.spp=2", "sim.device=cpu"])).config.render.spp == 2
    mark_done(root / "train" / "wind-uniform1" / "paper" / "lrcn" / "s0")
    with pytest.raises(ConfigError, match=r"render.spp 2 -> 4 \(train work is done\)") as refused:
        Run.create_or_resume(root, apply_overrides(Run.open(root).config, ["render.spp=4"]))
    # and says how to keep the run's value (a preset's default that changed since the run was made)
    assert "`--set render.spp=2` keeps the run's" in str(refused.value)
    keep = apply_overrides(Run.open(root).config, ["render.spp=4", "render.spp=2"])
    assert Run.create_or_resume(root, keep).config.render.spp == 2
    # lists may grow (more models, seeds, variants) and eval settings change at any time
    grown = apply_overrides(Run.open(root).config, ["train.models=lrcn,base1", "train.seeds=0,1",
                                                    "render.variants=paper,grid", "eval.bootstrap=10"])
    assert Run.create_or_resume(root, grown).config == grown
    with pytest.raises(ConfigError, match=r"train.models lrcn,base1 -> base1"):
        Run.create_or_resume(root, apply_overrides(grown, ["train.models=base1"]))
    # an arm setting shapes arm clips only: free on a run that has none, refused once it has
    framed = apply_overrides(grown, ["sim.arm_view_zoom=1.3", "sim.arm_nuisance=speed"])
    assert Run.create_or_resume(root, framed).config.sim.arm_view_zoom == 1.3        # the smoke run is wind only
    with_arm = apply_overrides(framed, ["sim.motions=wind,arm"])
    Run.create_or_resume(root, with_arm)
    mark_done(root / "sim" / "arm-uniform1" / "c00000")
    with pytest.raises(ConfigError, match=r"sim.arm_view_zoom 1.3 -> 1.0 \(sim, train work is done\)"):
        Run.create_or_resume(root, apply_overrides(with_arm, ["sim.arm_view_zoom=1"]))


def test_config_file_then_set(tmp_path):
    study = tmp_path / "study.toml"
    study.write_text('preset = "smoke"\n[sim]\nframes = 30\nclasses = [0, 8]\n[render]\n'
                     'variants = ["paper", "grid"]\nspp = 3\n')
    run = resolve_run(None, None, tmp_path / "r", ("render.spp=5",), study)
    cfg = run.config
    assert cfg.sim.frames == 30 and cfg.sim.classes == (0, 8) and cfg.render.variants == ("paper", "grid")
    assert cfg.render.spp == 5                                   # --set applies after the file
    assert cfg.train == preset("smoke").train                     # the rest is the file's preset
    assert json.loads((tmp_path / "r" / "config.json").read_text())["render"]["spp"] == 5
    # the API reads the same file
    assert api.start(tmp_path / "r", config_file=study, settings={"render.spp": 5}).config == cfg
    # --preset on the command line goes over the file's preset, the file's settings over both
    bigger = resolve_run(None, "small", tmp_path / "r2", (), study).config
    assert bigger.sim.sequences_per_class == preset("small").sim.sequences_per_class and bigger.sim.frames == 30


def test_example_config_files_are_valid_at_both_sizes():
    files = sorted((ROOT / "examples").glob("*.toml"))
    assert files
    for path in files:
        name, settings = read_config_file(path)
        for base in (name, "paper"):
            validate(apply_settings(preset(base), settings, str(path)))


@pytest.mark.parametrize("text, names", [
    ("[render\nspp = 3\n", ["bad.toml", "not valid TOML"]),
    ('preset = "smoke"\n[rendr]\nspp = 3\n', ["bad.toml", "unknown setting rendr", "render"]),
    ('preset = "smoke"\n[render]\nspp = 3\nfoo = 1\n', ["bad.toml", "unknown setting render.foo", "resolution"]),
    ('preset = "smoke"\n[sim]\nframes = "many"\n', ["bad.toml", "sim.frames", "expected int"]),
    ('preset = "nope"\n', ["unknown preset 'nope'"]),
])
def test_bad_config_file_is_one_error_line(tmp_path, text, names):
    path = tmp_path / "bad.toml"
    path.write_text(text)
    r = clothgap("sim", "--config", str(path), "--out", str(tmp_path / "r"))
    assert r.returncode == 2, r.stdout + r.stderr
    assert "Traceback" not in r.stderr and r.stderr.startswith("error: ")
    for name in names:
        assert name in r.stderr, (name, r.stderr)
    assert not (tmp_path / "r").exists()


def test_api_names_what_is_missing(tmp_path):
    study = api.start(tmp_path / "r", preset="smoke")
    with pytest.raises(ConfigError, match="unknown render variant 'nope'"):
        study.add_variants("nope")
    with pytest.raises(FileNotFoundError, match="evaluate the run first"):
        study.domain_gap()
    with pytest.raises(ConfigError, match="clothgap sim"):
        study.render()
    with pytest.raises(ConfigError, match="does not exist"):
        api.open(tmp_path / "elsewhere")


@pytest.mark.slow
def test_added_variants_train_side_by_side(paper_run, tmp_path):
    study = api.open(copy_of(paper_run, tmp_path)).add_variants("grid", "color")
    study.render(progress=False)
    before = {p: p.stat().st_mtime_ns for p in study.root.glob("train/*/paper/*/s*/DONE")}
    folders = study.train(progress=False, parallel=2)
    assert {f.parts[-2] for f in folders} == {"lrcn"} and {f.parts[-3] for f in folders} == {"paper", "grid", "color"}
    assert all((f / "DONE").is_file() for f in folders)
    assert {p: p.stat().st_mtime_ns for p in before} == before          # the finished paper model was kept
    index = json.loads((study.root / "train" / "index.json").read_text())
    assert all(e["done"] for e in index["entries"]) and len(index["entries"]) == 3
