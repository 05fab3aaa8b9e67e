"""scripts/lattice_variance.py: how much of the lattice target the frame index and the class explain."""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path

import numpy as np
import pytest

from clothgap.config import StudyConfig
from clothgap.runs import Run, clip_id, mark_done
from sim.clip import SimClip
from sim.config import SimConfig
from tests.conftest import flat_sheet

SCRIPT = Path(__file__).resolve().parents[1] / "scripts" / "lattice_variance.py"
CLASSES = (0, 8, 45, 53)


def _script():
    spec = importlib.util.spec_from_file_location("lattice_variance", SCRIPT)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _run(root, per_class: int = 4, frames: int = 12, sag_scale: float = 0.05) -> Run:
    """A sheet that swings the same way in every clip (large), sags by its class (small), plus noise."""
    cfg = StudyConfig(sim=SimConfig(classes=CLASSES, sequences_per_class=per_class, frames=frames))
    run = Run.create_or_resume(root, cfg)
    rng = np.random.default_rng(0)
    uv, rest = flat_sheet(9)
    swing = np.sin(np.linspace(0, 3, frames))[:, None, None] * np.array([0.0, 0.3, 0.0])
    for i in range(len(CLASSES) * per_class):
        label = CLASSES[i % len(CLASSES)]
        sag = sag_scale * CLASSES.index(label) * np.array([0.0, 0.0, 1.0]) * uv[:, :1]
        positions = rest[None] + swing + sag[None] + rng.normal(size=(frames, 81, 3)) * 0.003
        folder = run.sim_dir("wind-uniform1") / clip_id(i)
        meta = {"class_index": label, "sequence": i // len(CLASSES), "motion": "wind"}
        SimClip.from_fixed(meta, positions.astype(np.float32), np.array([[0, 1, 9]], np.int32), uv).save(folder)
        mark_done(folder)
    return run


def test_the_frame_index_explains_the_common_swing_and_the_class_the_rest(tmp_path):
    _run(tmp_path / "run")
    result = _script().main([str(tmp_path / "run"), "--setting", "wind-uniform1", "--out", str(tmp_path / "r.json")])
    mse = result["mse"]
    assert result["clips"] == 16 and result["held_out_clips"] == 8
    assert mse["frame"] < 0.5 * mse["constant"]                 # the swing every clip shares
    assert mse["class_and_frame"] < 0.2 * mse["frame"]          # the sag only the class knows
    assert (tmp_path / "r.json").is_file()


def test_the_reader_reads_the_class_from_whole_clips_of_frame_centred_lattices(tmp_path, capsys):
    spec = importlib.util.spec_from_file_location("reader_ceiling", SCRIPT.parent / "reader_ceiling.py")
    reader_ceiling = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(reader_ceiling)
    _run(tmp_path / "run", per_class=6)
    reader_ceiling.main([str(tmp_path / "run"), "--setting", "wind-uniform1", "--clip-len", "12", "--centre",
                         "frame", "--epochs", "40"])
    result = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert (result["clip_len"], result["centre"]) == (12, "frame")
    assert result["test_windows"] == result["test_sequences"] > 0      # one whole-clip window a sequence
    assert result["top1"] >= 0.75                                       # the sag tells the class


def test_the_reader_reads_each_measured_fabric_from_its_simulated_lattice(tmp_path, capsys):
    # The measured fabrics are simulated for real (their own tables, this run's wind), a clip each, and the
    # reader trained on the run's clips names a class for each, set against its Table 2 class.
    spec = importlib.util.spec_from_file_location("reader_ceiling", SCRIPT.parent / "reader_ceiling.py")
    reader_ceiling = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(reader_ceiling)
    run = _run(tmp_path / "run", per_class=6)
    reader_ceiling.main([str(tmp_path / "run"), "--setting", "wind-uniform1", "--clip-len", "12", "--epochs", "2",
                         "--measured", "1"])
    measured = json.loads(capsys.readouterr().out.strip().splitlines()[-1])["measured"]
    from sim.measured import table2_class, table2_fabrics

    assert measured["fabrics"] == len(table2_fabrics()) == len(measured["rows"])
    assert {r["fabric"] for r in measured["rows"]} == set(table2_fabrics())
    for r in measured["rows"]:
        assert r["table2_class"] == table2_class(r["fabric"]) and 0 <= r["pred"] < 54 and r["grid_steps"] >= 0
        assert (r["grid_steps"] == 0) == (r["pred"] == r["table2_class"])
    steps = [r["grid_steps"] for r in measured["rows"]]
    assert measured["exact"] == steps.count(0) and measured["within_one_step"] == sum(s <= 1 for s in steps)
    # the goal's count: at most one bin off in p and in k (every fabric one grid step away, and some two)
    from eval import classes

    for r in measured["rows"]:
        dp, dk = (abs(int(index(r["pred"])) - int(index(r["table2_class"]))) for index in (classes.p_index,
                                                                                         classes.k_index))
        assert r["within_one_bin"] == (dp <= 1 and dk <= 1)
    assert measured["within_one_bin"] == sum(r["within_one_bin"] for r in measured["rows"])
    assert measured["within_one_bin"] >= measured["within_one_step"]
    # simulated once into the run's measured folder, where `clothgap eval measured` would find them
    assert len(run.done_clips(run.measured_sim_dir("wind-uniform1"))) == len(table2_fabrics())


def _reader_ceiling():
    spec = importlib.util.spec_from_file_location("reader_ceiling", SCRIPT.parent / "reader_ceiling.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_the_statistics_reader_reads_the_class_from_the_windows_shape_statistics(tmp_path, capsys):
    _run(tmp_path / "run", per_class=6)
    _reader_ceiling().main([str(tmp_path / "run"), "--setting", "wind-uniform1", "--clip-len", "12", "--epochs", "100",
                            "--reader", "stats"])
    result = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert result["reader"] == "stats" and result["test_windows"] > 0
    assert result["top1"] >= 0.75                                       # the mean shape holds the sag


def test_the_statistics_reader_reads_what_the_learnability_probes_read():
    import torch

    from eval.learnability import window_features

    window = np.random.default_rng(0).normal(size=(7, 64, 3)).astype(np.float32)
    ours = _reader_ceiling().StatsReader.statistics(torch.from_numpy(window.reshape(1, 7, -1)))[0].numpy()
    assert np.allclose(ours, window_features(window), atol=1e-5)


def test_a_transfer_run_is_read_with_the_reader_trained_on_this_one(tmp_path, capsys):
    # The same clips read as the run's own test clips; the same clip ids with every sag halved (a material of
    # another shape under the same labels) read worse; a run of other clip ids is named, not read.
    _run(tmp_path / "run", per_class=6)
    _run(tmp_path / "same", per_class=6)
    _run(tmp_path / "halved", per_class=6, sag_scale=0.025)
    _run(tmp_path / "other", per_class=5)
    reader_ceiling = _reader_ceiling()
    reader_ceiling.main([str(tmp_path / "run"), "--setting", "wind-uniform1", "--clip-len", "12", "--epochs", "40",
                         "--transfer", str(tmp_path / "same"), str(tmp_path / "halved")])
    result = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    same, halved = result["transfer"]
    assert same["windows"] == halved["windows"] == result["test_windows"]
    assert {k: same[k] for k in ("top1", "within_one", "bending")} == \
        {k: result[k] for k in ("top1", "within_one", "bending")}
    assert halved["top1"] < result["top1"]
    with pytest.raises(SystemExit, match="not this run's"):
        reader_ceiling.main([str(tmp_path / "run"), "--setting", "wind-uniform1", "--clip-len", "12", "--epochs",
                             "1", "--transfer", str(tmp_path / "other")])
    _run(tmp_path / "tiny", per_class=2)                                # too few sequences for a test split
    with pytest.raises(SystemExit, match="the reader needs both"):
        reader_ceiling.main([str(tmp_path / "tiny"), "--setting", "wind-uniform1", "--clip-len", "12"])
