"""The command line: every subcommand has --help, and bad input gets a clear error."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from clothgap.config import ConfigError, StudyConfig, apply_overrides, from_dict, preset, to_dict
from clothgap.runs import Run, clip_id, fresh_dir, is_done, mark_done
from clothgap.seeding import RENDER, SIM, rng


def clothgap(*args: str, cwd: Path | None = None) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "clothgap", *args], capture_output=True, text=True, cwd=cwd)


@pytest.mark.parametrize("sub", [[], ["sim"], ["sim", "run"], ["sim", "sensitivity"], ["sim", "table2"],
                                 ["render"], ["train"], ["eval"], ["eval", "real"], ["eval", "measured"],
                                 ["report"], ["pipeline"]])
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


def test_unknown_option_and_bad_override_are_named(tmp_path):
    r = clothgap("train", "--bogus")
    assert r.returncode == 2 and "--bogus" in r.stderr
    r = clothgap("sim", "--preset", "smoke", "--set", "sim.frames=abc", "--out", str(tmp_path / "y"))
    assert r.returncode == 2 and "sim.frames" in r.stderr and "Traceback" not in r.stderr
    r = clothgap("sim", "--preset", "smoke", "--set", "sim.nosuch=1", "--out", str(tmp_path / "z"))
    assert r.returncode == 2 and "nosuch" in r.stderr


def test_config_round_trips_through_json(tmp_path):
    cfg = apply_overrides(preset("smoke"), ["sim.frames=30", "render.variants=paper,grid"])
    assert cfg.sim.frames == 30 and cfg.render.variants == ("paper", "grid")
    back = from_dict(StudyConfig, json.loads(json.dumps(to_dict(cfg))))
    assert back == cfg
    with pytest.raises(ConfigError):
        apply_overrides(cfg, ["nosection.x=1"])


def test_resuming_a_run_with_another_config_is_refused(tmp_path):
    Run.create_or_resume(tmp_path, preset("smoke"))
    assert Run.open(tmp_path).config == preset("smoke")
    with pytest.raises(ConfigError, match="different config"):
        Run.create_or_resume(tmp_path, apply_overrides(preset("smoke"), ["seed=3"]))


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
