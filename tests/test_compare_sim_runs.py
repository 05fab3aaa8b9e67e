"""scripts/compare_sim_runs.py: two runs of one seed agree to the byte and show no shift; other runs are told apart."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import pytest

from sim.stage import run_sim
from tests.conftest import tiny_sim_run

ROOT = Path(__file__).resolve().parents[1]


def _script():
    spec = importlib.util.spec_from_file_location("compare_sim_runs", ROOT / "scripts" / "compare_sim_runs.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_the_same_seed_twice_shows_nothing_and_a_larger_cloth_shows_its_size(tmp_path):
    compare = _script().compare
    runs = {}
    for name, sim in (("a", {}), ("b", {}), ("larger", {"cloth_size_m": 0.6})):
        runs[name] = tiny_sim_run(tmp_path / name, sequences_per_class=2, frames=4, **sim)
        run_sim(runs[name], progress=False)
    same = compare(runs["a"].root, runs["b"].root, "wind-uniform1")
    assert same["clips"] == 4
    assert all(v["mean"] == 0.0 for v in same["new_minus_old"].values())
    assert same["last_frame_rms_m"]["same_clip_old_vs_new"]["max"] == 0.0
    assert same["last_frame_rms_m"]["two_sequences_of_one_class_old"]["pairs"] == 2
    # a 0.6 m cloth against a 0.5 m one: wider, for every clip, far beyond the interval
    moved = compare(runs["a"].root, runs["larger"].root, "wind-uniform1")["new_minus_old"]["horizontal_extent_m"]
    assert moved["lo"] > 0.05
    with pytest.raises(SystemExit, match="nothing to compare"):
        compare(runs["a"].root, runs["b"].root, "arm-uniform1")
