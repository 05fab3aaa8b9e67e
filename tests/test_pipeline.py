"""The smoke study end to end, through the command a user types."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest

import clothgap.config  # noqa: F401  (registers the study config that Run.open reads)
from clothgap.runs import Run


# The smoke preset at a quarter of its size (2 classes x 4 sequences, 10 frames, 2 epochs): every stage, both
# variants and the report, in a third of the time.
SMALLER = ["sim.classes=0,53", "sim.sequences_per_class=4", "sim.frames=10", "sim.grid_vertices=8", "train.epochs=2"]


@pytest.mark.slow
def test_smoke_pipeline_end_to_end_and_resume(tmp_path):
    out = tmp_path / "smoke"
    cmd = [sys.executable, "-m", "clothgap", "pipeline", "--preset", "smoke", "--out", str(out),
           *[arg for s in SMALLER for arg in ("--set", s)]]
    r = subprocess.run(cmd, capture_output=True, text=True, env={**os.environ, "PYTHONUNBUFFERED": "1"})
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]

    run = Run.open(out)
    cfg = run.config
    setting = cfg.sim.settings()[0]
    n = cfg.sim.num_clips()
    # every stage wrote its outputs, each clip finished by its marker
    assert len(run.done_clips(run.sim_dir(setting))) == n
    assert len(run.done_clips(run.render_dir("paper", setting))) == n
    assert (run.train_dir(setting, "paper", "lrcn", 0) / "checkpoint.pt").is_file()
    table3 = (run.eval_dir / "table3.md").read_text()
    assert "wind" in table3 and "lrcn" in table3
    report = run.report_dir / "report.html"
    assert report.is_file() and report.stat().st_size > 10_000

    # the split is by sequence: no clip on two sides
    split = json.loads(run.split_path(setting).read_text())
    assert not set(split["train"]) & set(split["test"])
    assert len(split["train"]) + len(split["val"]) + len(split["test"]) == n

    # eval reports an accuracy. Better than chance is not asserted here: the split holds out a few sequences,
    # so accuracy moves in large steps that a chance-level model often reaches; tests/test_learn_train.py
    # asserts learning on synthetic clips instead.
    summary = json.loads((run.eval_dir / "summary.json").read_text())
    assert "accuracy" in json.dumps(summary)

    # a re-run skips everything that is finished ...
    done_marker = run.sim_dir(setting) / "c00000" / "DONE"
    before = done_marker.stat().st_mtime_ns
    r2 = subprocess.run(cmd, capture_output=True, text=True)
    assert r2.returncode == 0, r2.stderr[-3000:]
    assert done_marker.stat().st_mtime_ns == before
    # ... and redoes an unfinished clip (marker removed, as if killed mid-clip)
    (run.render_dir("paper", setting) / "c00003" / "DONE").unlink()
    r3 = subprocess.run([sys.executable, "-m", "clothgap", "render", str(out)], capture_output=True, text=True)
    assert r3.returncode == 0, r3.stderr[-3000:]
    assert len(run.done_clips(run.render_dir("paper", setting))) == n
