"""The command line: every subcommand has --help, and bad input gets a clear error."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from clothgap.config import PRESETS, ConfigError, StudyConfig, apply_overrides, from_dict, preset, to_dict, validate
from clothgap.runs import Run, clip_id, fresh_dir, is_done, mark_done
from clothgap.seeding import RENDER, SIM, rng


def clothgap(*args: str, cwd: Path | None = None, env: dict | None = None) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "clothgap", *args], capture_output=True, text=True, cwd=cwd,
                          env={**os.environ, **(env or {})})


def assert_user_error(r: subprocess.CompletedProcess, *names: str) -> None:
    """A one-line-style error on stderr that names each of ``names``, a non-zero exit and no traceback."""
    out = r.stdout + r.stderr
    assert r.returncode != 0, out
    assert "Traceback" not in out, out
    assert "error" in r.stderr.lower(), out
    for name in names:
        assert name in r.stderr, (name, out)


@pytest.mark.parametrize("sub", [[], ["sim"], ["sim", "run"], ["sim", "sensitivity"], ["sim", "table2"],
                                 ["sim", "cantilever"],
                                 ["render"], ["train"], ["eval"], ["eval", "real"], ["eval", "measured"],
                                 ["eval", "learnability"], ["report"], ["pipeline"]])
def test_every_subcommand_has_help(sub):
    r = clothgap(*sub, "--help")
    assert r.returncode == 0, r.stderr
    assert "Usage:" in r.stdout


def test_unknown_preset_is_named(tmp_path):
    r = clothgap("pipeline", "--preset", "nope", "--out", str(tmp_path / "x"))
    assert r.returncode == 2
    assert "unknown preset 'nope'" in r.stderr and "smoke" in r.stderr
    assert "Traceback" not in r.stderr


def test_missing_run_folder_is_named(tmp_path):
    r = clothgap("render", str(tmp_path / "missing"))
    assert r.returncode == 2
    assert "missing" in r.stderr and "does not exist" in r.stderr
    assert "Traceback" not in r.stderr


def test_missing_stage_input_names_the_command_to_run(tmp_path):
    Run.create_or_resume(tmp_path / "r", preset("smoke"))
    r = clothgap("render", str(tmp_path / "r"))
    assert r.returncode == 2
    assert "clothgap sim" in r.stderr and "Traceback" not in r.stderr


def test_eval_learnability_names_what_is_missing_or_wrong(tmp_path):
    Run.create_or_resume(tmp_path / "r", preset("smoke"))
    assert_user_error(clothgap("eval", "learnability", str(tmp_path / "r")), "clothgap sim")
    folder = tmp_path / "r" / "sim" / "wind-uniform1" / "c00000"
    folder.mkdir(parents=True)
    assert_user_error(clothgap("eval", "learnability", str(tmp_path / "r"), "--setting", "arm-uniform9"),
                      "arm-uniform9", "wind-uniform1")
    assert_user_error(clothgap("eval", "learnability", str(tmp_path / "r"), "--stride", "5"), "--stride 5")
    assert_user_error(clothgap("eval", "learnability", str(tmp_path / "r"), "--measured", "2", "--pixels", "paper"),
                      "--measured", "--pixels")


def test_unknown_option_and_bad_override_are_named(tmp_path):
    r = clothgap("train", "--bogus")
    assert r.returncode == 2 and "--bogus" in r.stderr
    r = clothgap("sim", "--preset", "smoke", "--set", "sim.frames=abc", "--out", str(tmp_path / "y"))
    assert r.returncode == 2 and "sim.frames" in r.stderr and "Traceback" not in r.stderr
    r = clothgap("sim", "--preset", "smoke", "--set", "sim.nosuch=1", "--out", str(tmp_path / "z"))
    assert r.returncode == 2 and "nosuch" in r.stderr


# Each bad setting fails when the run starts, before any work (no folder is created), naming the setting,
# the bad value and what is allowed.
BAD_SETTINGS = [
    ("sim", "sim.motions=swim", ["sim.motions", "'swim'", "wind, arm"]),
    ("sim", "sim.classes=0,99", ["sim.classes", "99", "0..53"]),
    ("sim", "sim.remeshing=uniform4", ["sim.remeshing", "'uniform4'", "uniform1, uniform2, uniform3, adaptive"]),
    ("sim", "sim.frames=0", ["sim.frames=0", ">= 1"]),
    ("sim", "sim.frames=-5", ["sim.frames=-5", ">= 1"]),
    ("sim", "sim.sequences_per_class=0", ["sim.sequences_per_class=0", ">= 1"]),
    ("sim", "sim.basis=silk", ["sim.basis='silk'", "camel-ponte-roma"]),
    ("sim", "sim.device=gpu7", ["sim.device='gpu7'", "cuda:N"]),
    ("render", "render.variants=nope", ["render.variants", "'nope'", "paper"]),
    ("sim", "render.variants=nope", ["render.variants", "'nope'"]),
    ("render", "render.backend=opengl", ["render.backend='opengl'", "scalar_rgb"]),
    ("render", "render.resolution=0", ["render.resolution=0", ">= 1"]),
    ("render", "render.spp=-1", ["render.spp=-1", ">= 1"]),
    ("train", "train.models=lrcn,resnet", ["train.models", "'resnet'", "lrcn, base1, base2, base3"]),
    ("train", "train.image_size=50", ["train.image_size=50", "multiple of 16"]),
    ("train", "train.schedule=linear", ["train.schedule='linear'", "cosine, step"]),
    ("train", "train.val_fraction=0.8", ["train.val_fraction=0.8", "nothing to train on"]),
    ("eval", "eval.confidence=1.5", ["eval.confidence=1.5", "(0, 1)"]),
]


@pytest.mark.parametrize("command, override, names", BAD_SETTINGS, ids=[b[1] for b in BAD_SETTINGS])
def test_bad_setting_is_named_before_any_work(tmp_path, command, override, names):
    out = tmp_path / "run"
    r = clothgap(command, "--preset", "smoke", "--out", str(out), "--set", override)
    assert_user_error(r, *names)
    assert r.returncode == 2 and not out.exists()


def test_every_bad_setting_is_named_at_once(tmp_path):
    r = clothgap("sim", "--preset", "smoke", "--out", str(tmp_path / "r"),
                 "--set", "sim.motions=swim", "--set", "render.spp=0")
    assert_user_error(r, "2 invalid settings", "'swim'", "render.spp=0")


def test_presets_are_valid_and_validate_names_the_setting():
    for name in PRESETS:
        assert validate(preset(name)) == preset(name)
    with pytest.raises(ConfigError, match=r"sim\.motions: unknown motion 'swim'; known: wind, arm"):
        validate(apply_overrides(preset("smoke"), ["sim.motions=swim"]))
    with pytest.raises(ConfigError, match="unknown render variant .nope."):
        Run.create_or_resume(Path("/nonexistent/never-created"),
                             apply_overrides(preset("smoke"), ["render.variants=nope"]))


def test_bad_tonemap_in_a_user_variant_file_is_named(tmp_path):
    folder = tmp_path / "variants"
    folder.mkdir()
    (folder / "mine.toml").write_text('description = "a typo in the tone mapper"\ntonemap = "nope"\n')
    env = {"CLOTHGAP_VARIANTS_DIR": str(folder)}
    r = clothgap("render", "--preset", "smoke", "--out", str(tmp_path / "r"), "--set", "render.variants=mine",
                 env=env)
    assert_user_error(r, "'mine'", "tonemap='nope'", "srgb_clip, reinhard, filmic")
    r = clothgap("render", "--list-variants", env=env)
    assert_user_error(r, "tonemap='nope'")


def test_bad_setting_in_a_run_config_is_named_when_loaded(tmp_path):
    Run.create_or_resume(tmp_path / "r", preset("smoke"))
    path = tmp_path / "r" / "config.json"
    data = json.loads(path.read_text())
    data["sim"]["motions"] = ["swim"]                  # edited by hand
    path.write_text(json.dumps(data))
    r = clothgap("render", str(tmp_path / "r"))
    assert_user_error(r, "config.json", "sim.motions", "'swim'")
    path.write_text("{not json")
    assert_user_error(clothgap("sim", str(tmp_path / "r")), "config.json", "not valid JSON")


def test_clone_numbers_are_checked_by_the_parser(tmp_path):
    r = clothgap("clone", str(tmp_path / "v.mp4"), "--run", str(tmp_path), "--spp", "0")
    assert r.returncode == 2 and "--spp" in r.stderr and "Traceback" not in r.stderr


@pytest.fixture
def real_inputs(tmp_path):
    """eval real's inputs: one (undecodable) video, a truth CSV, an empty train folder."""
    videos = tmp_path / "videos"
    videos.mkdir()
    (videos / "a.mp4").write_bytes(b"not decoded: the inputs are checked before any video is read")
    truth = tmp_path / "truth.csv"
    truth.write_text("video,bending_N_m2,area_weight_kg_m2\na.mp4,1e-5,0.1\n")
    train = tmp_path / "train"
    train.mkdir()
    return videos, truth, train


def eval_real(videos, truth, train, out):
    return clothgap("eval", "real", str(videos), "--truth", str(truth), "--model", str(train), "--out", str(out))


def test_eval_real_truth_csv_without_a_column(tmp_path, real_inputs):
    videos, _, train = real_inputs
    truth = tmp_path / "no-stiffness.csv"
    truth.write_text("video,area_weight_kg_m2\na.mp4,0.1\n")
    r = eval_real(videos, truth, train, tmp_path / "out")
    assert_user_error(r, "no-stiffness.csv", "stiffness", "bending_N_m2")
    truth.write_text("")
    assert_user_error(eval_real(videos, truth, train, tmp_path / "out"), "no-stiffness.csv", "cannot be read")


def test_eval_real_empty_video_folder(tmp_path, real_inputs):
    _, truth, train = real_inputs
    empty = tmp_path / "empty"
    empty.mkdir()
    assert_user_error(eval_real(empty, truth, train, tmp_path / "out"), str(empty), "no videos")


def test_eval_real_train_folder_without_checkpoint(tmp_path, real_inputs):
    videos, truth, train = real_inputs
    assert_user_error(eval_real(videos, truth, train, tmp_path / "out"), "checkpoint.pt", str(train))
    assert not (tmp_path / "out").exists()


def test_eval_real_missing_paths_are_named(tmp_path, real_inputs):
    videos, truth, train = real_inputs
    assert_user_error(eval_real(tmp_path / "nope", truth, train, tmp_path / "out"), "video folder", "nope")
    assert_user_error(eval_real(videos, tmp_path / "t.csv", train, tmp_path / "out"), "truth CSV", "t.csv")


def test_config_round_trips_through_json(tmp_path):
    cfg = apply_overrides(preset("smoke"), ["sim.frames=30", "render.variants=paper,grid"])
    assert cfg.sim.frames == 30 and cfg.render.variants == ("paper", "grid")
    back = from_dict(StudyConfig, json.loads(json.dumps(to_dict(cfg))))
    assert back == cfg
    with pytest.raises(ConfigError):
        apply_overrides(cfg, ["nosection.x=1"])


def test_resuming_a_run_with_another_config_is_refused_once_work_is_done(tmp_path):
    Run.create_or_resume(tmp_path, preset("smoke"))
    assert Run.open(tmp_path).config == preset("smoke")
    mark_done(tmp_path / "sim" / "wind-uniform1" / clip_id(0))
    with pytest.raises(ConfigError, match="finished work this config would invalidate or leave out: seed 0 -> 3"):
        Run.create_or_resume(tmp_path, apply_overrides(preset("smoke"), ["seed=3"]))
    assert Run.open(tmp_path).config == preset("smoke")


def test_done_marker_and_fresh_dir(tmp_path):
    d = tmp_path / clip_id(7)
    assert d.name == "c00007"
    fresh_dir(d)
    (d / "partial.bin").write_bytes(b"x")
    assert not is_done(d)
    fresh_dir(d)  # an unfinished folder is redone from scratch
    assert not (d / "partial.bin").exists()
    mark_done(d, {"ok": True})
    assert is_done(d)


def test_seeds_are_per_clip_per_stage_and_per_stream():
    a = rng(0, 3, SIM, "material").random(4)
    assert (a == rng(0, 3, SIM, "material").random(4)).all()
    assert not (a == rng(0, 4, SIM, "material").random(4)).all()
    assert not (a == rng(0, 3, RENDER, "material").random(4)).all()
    assert not (a == rng(0, 3, SIM, "motion").random(4)).all()
    assert not (a == rng(1, 3, SIM, "material").random(4)).all()
