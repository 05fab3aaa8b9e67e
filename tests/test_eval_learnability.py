"""The geometry probe: it reads what simulated clips carry, and it measures the sub-sequence leak."""

from __future__ import annotations

import json

import numpy as np

from clothgap.config import StudyConfig
from clothgap.runs import Run, clip_id, mark_done
import pytest

from clothgap.errors import ConfigError
from eval.learnability import markdown, markdown_measured, probe, probe_measured, run_probe
from sim.clip import SimClip
from sim.config import SimConfig
from tests.conftest import flat_sheet

CLASSES = (0, 8, 45, 53)


def _sheet_clip(folder, meta: dict, level: int, class_signal: float, rng, frames: int) -> None:
    """One clip of the toy sheet at class level ``level`` (its index in CLASSES), saved finished."""
    uv, rest = flat_sheet(6)
    signature = rng.normal(size=(36, 3)) * 0.02                      # this sequence's own shape
    shape = rest + class_signal * level * np.array([0, 0, 0.1]) + signature
    positions = shape[None] + rng.normal(size=(frames, 36, 3)) * 0.002
    SimClip.from_fixed(meta, positions, np.array([[0, 1, 6]], np.int32), uv).save(folder)
    mark_done(folder)


def _fake_sim_run(root, class_signal: float, per_class: int = 12, frames: int = 40) -> Run:
    """Clips of a 6 x 6 vertex sheet: the class moves it by ``class_signal``, a per-sequence draw moves it
    by a larger random amount (a nuisance like the wind), and every frame jitters a little."""
    cfg = StudyConfig(sim=SimConfig(classes=CLASSES, sequences_per_class=per_class, frames=frames))
    run = Run.create_or_resume(root, cfg)
    rng = np.random.default_rng(0)
    for i in range(len(CLASSES) * per_class):
        label = CLASSES[i % len(CLASSES)]
        _sheet_clip(run.sim_dir("wind-uniform1") / clip_id(i), {"class_index": label}, CLASSES.index(label),
                    class_signal, rng, frames)
    return run


def _acc(report, protocol, target, kind):
    return next(r["accuracy"] for r in report["results"]
                if (r["protocol"], r["target"], r["classifier"]) == (protocol, target, kind))


def test_probe_reads_the_class_when_the_geometry_carries_it(tmp_path):
    # (The toy's bending bins are an XOR of its z levels, so only class and stretching are linear.)
    run = _fake_sim_run(tmp_path / "run", class_signal=1.0, per_class=48)
    report = probe(run, "wind-uniform1", progress=False, classifiers=("linear", "nearest"))
    assert report["windows"] == 192 * 4 and report["clips"] == 192
    assert _acc(report, "sequence", "class", "linear") > 0.9
    assert _acc(report, "sequence", "stretching", "linear") > 0.9
    assert _acc(report, "sequence", "bending", "nearest") > 0.75
    # per true bin of each factor: the bins the test windows hold, their accuracies averaging to the whole
    row = next(r for r in report["results"] if (r["protocol"], r["target"], r["classifier"]) ==
               ("sequence", "stretching", "linear"))
    bins = row["accuracy_by_true_bin"]
    assert len(bins) >= 2 and all(0.0 <= a <= 1.0 for a in bins.values())
    assert set(bins) == {0, 5}                       # the stretching bins of classes 0, 8 (p 0.5) and 45, 53 (p 20)
    assert min(bins.values()) <= row["accuracy"] <= max(bins.values())
    assert all("accuracy_by_true_bin" not in r for r in report["results"] if r["target"] == "class")


def test_probe_measures_the_leak_of_the_split_by_subsequence(tmp_path):
    # No class signal at all: new sequences are guessed at chance, but a window whose neighbours from the
    # same simulation are in training is recognised.
    report = probe(_fake_sim_run(tmp_path / "run", class_signal=0.0), "wind-uniform1", progress=False,
                   classifiers=("nearest",))
    assert _acc(report, "sequence", "class", "nearest") < 0.5          # chance is 0.25 (4 classes seen)
    assert _acc(report, "subsequence", "class", "nearest") > 0.9
    assert "split by subsequence" in markdown(report)


def test_run_probe_writes_json_and_markdown(tmp_path):
    run = _fake_sim_run(tmp_path / "run", class_signal=1.0, per_class=6, frames=20)
    summary = run_probe(run, progress=False, classifiers=("nearest",))
    saved = json.loads((run.eval_dir / "learnability.json").read_text())
    assert summary["settings"] == ["wind-uniform1"] and saved["settings"][0]["clip_len"] == 10
    assert (run.eval_dir / "learnability.md").read_text().startswith("# What the simulated geometry tells")


def test_pixel_probe_reads_rendered_frames(tmp_path):
    # Synthetic rendered clips (learn.synthetic): per-sequence backgrounds make each clip recognisable,
    # so 1-NN on pixels finds a window's own sequence when the split lets it.
    from learn.config import TrainConfig
    from learn.synthetic import synthetic_run

    cfg = StudyConfig(sim=SimConfig(classes=CLASSES, sequences_per_class=6, frames=20),
                      train=TrainConfig(image_size=32))
    run = synthetic_run(tmp_path / "run", cfg)
    summary = run_probe(run, progress=False, pixels="paper", classifiers=("nearest",))
    report = json.loads((run.eval_dir / "learnability-pixels-paper.json").read_text())["settings"][0]
    assert summary["settings"] == ["wind-uniform1"] and report["source"] == "pixels of paper"
    assert report["features"] == 2 * 16 * 16 * 3 and report["windows"] == 24 * 2
    assert _acc(report, "subsequence", "class", "nearest") > 0.9


def test_measured_probe_reads_each_fabric_where_its_geometry_puts_it(tmp_path):
    from sim.measured import measured_values, table2_class

    def measured_meta(fabric: str) -> dict:        # the label part of a measured clip's meta (sim.measured)
        return {"class_index": table2_class(fabric), "fabric": fabric,
                "density": measured_values(fabric)["density_kg_m2"]}

    run = _fake_sim_run(tmp_path / "run", class_signal=1.0, per_class=12)
    with pytest.raises(ConfigError, match="no simulated measured-fabric clips"):
        probe_measured(run, "wind-uniform1", progress=False)
    # royal-target's Table 2 class is (20, 20) = class 53 and its clips move like class 53; navy-sparkle-sweat's is
    # (0.5, 2) = class 2, but its clips move like class 0 = (0.5, 0.5): two bending bins off.
    rng = np.random.default_rng(1)
    looks_like = {"royal-target": 53, "navy-sparkle-sweat": 0}
    for fabric, like in looks_like.items():
        for n in range(3):
            _sheet_clip(run.measured_sim_dir("wind-uniform1") / f"{fabric}-{n}",
                        measured_meta(fabric), CLASSES.index(like), 1.0, rng, 40)
    report = probe_measured(run, "wind-uniform1", progress=False, classifiers=("linear", "nearest"))
    assert report["measured_clips"] == 6 and report["measured_windows"] == 6 * 4
    for result in report["results"]:
        said = {f["fabric"]: f["pred"] for f in result["fabrics"]}
        assert said == looks_like
        rows = {f["fabric"]: f for f in result["fabrics"]}
        assert rows["royal-target"]["within1"] == 1 and rows["royal-target"]["class_dist"] == 0
        assert rows["navy-sparkle-sweat"]["within1"] == 0 and rows["navy-sparkle-sweat"]["class_dist"] == 2
        assert result["scores"]["exact"]["value"] == 0.5
        # no window of navy-sparkle-sweat can be within one bin of (0.5, 2) among the toy's classes
        assert 0.25 < result["window_within1"] <= 0.5
    assert "| royal-target | 3 | (20, 20) | (20, 20) | yes | 0 |" in markdown_measured(report)
    # only the clips asked for: a fourth clip of each fabric, left by an earlier call, is not read with --measured 3
    for fabric, like in looks_like.items():
        _sheet_clip(run.measured_sim_dir("wind-uniform1") / f"{fabric}-3",
                    measured_meta(fabric), CLASSES.index(like), 1.0, rng, 40)
    three = probe_measured(run, "wind-uniform1", sequences=3, progress=False, classifiers=("nearest",))
    assert three["measured_clips"] == 6 and all(f["clips"] == 3 for f in three["results"][0]["fabrics"])
    assert probe_measured(run, "wind-uniform1", progress=False, classifiers=("nearest",))["measured_clips"] == 8
    # the report shows it, in the measured fabrics' section, without any network's predictions of them
    from clothgap.runs import atomic_write_json
    from eval.report import write_report

    atomic_write_json(run.eval_dir / "learnability-measured.json", {"sequences": 3, "settings": [report]})
    doc = write_report(run).read_text()
    assert "The fabrics' simulated geometry" in doc and doc.count("1 of 2</td>") == 2     # linear and 1-NN
