"""scripts/gpu/learn_grid.py: recipes with different models in one training pool, cut at a deadline and resumed."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

from learn.synthetic import synthetic_run
from tests.conftest import tiny_train_config

SCRIPT = Path(__file__).resolve().parents[1] / "scripts" / "gpu" / "learn_grid.py"
GRID = ["--job", "baseline:lrcn,base1,base2", "--job", "baseline+lr=0.01:lrcn",
        "--table", "models=baseline:lrcn,base1,base2", "--table", "levers=baseline,baseline+lr=0.01:lrcn"]


def learn_grid(run, out: Path, deadline: float) -> subprocess.CompletedProcess:
    out.mkdir(exist_ok=True)
    return subprocess.run([sys.executable, str(SCRIPT), str(run.root), "--parallel", "2", "--deadline", str(deadline),
                           "--out", str(out), *GRID], capture_output=True, text=True,
                          env={**os.environ, "PYTHONPATH": str(SCRIPT.parents[2])})


def scores(path: Path) -> list[tuple]:
    return [(r["recipe"], r["model"], r["acc"], r["seq_acc"]) for r in json.loads(path.read_text())["recipes"]]


def test_a_grid_cut_at_its_deadline_resumes_to_the_tables_of_one_call(tmp_path):
    cfg = tiny_train_config(epochs=2, num_threads=1)
    whole, cut = synthetic_run(tmp_path / "whole", cfg), synthetic_run(tmp_path / "cut", cfg)

    r = learn_grid(whole, tmp_path / "out-whole", deadline=600)
    assert r.returncode == 0, r.stdout[-2000:] + r.stderr[-3000:]
    assert ", finished" in r.stdout      # "training call: N s, finished", not "to be resumed"

    # A deadline that stops training before the models finish: no table is written from unfinished models.
    r = learn_grid(cut, tmp_path / "out-cut", deadline=3)
    assert r.returncode == 0, r.stdout[-2000:] + r.stderr[-3000:]
    assert "to be resumed" in r.stdout and "not finished yet" in r.stdout
    assert not (cut.eval_dir / "models.json").exists() and not (tmp_path / "out-cut" / "models.json").exists()
    r = learn_grid(cut, tmp_path / "out-cut", deadline=600)
    assert r.returncode == 0, r.stdout[-2000:] + r.stderr[-3000:]

    # Each recipe with its own models: base1 and base2 for one recipe only, lrcn for both.
    models = scores(tmp_path / "out-cut" / "models.json")
    assert [(m[0], m[1]) for m in models] == [("baseline", "lrcn"), ("baseline", "base1"), ("baseline", "base2")]
    assert [m[:2] for m in scores(tmp_path / "out-cut" / "levers.json")] == \
        [("baseline", "lrcn"), ("baseline+lr=0.01", "lrcn")]
    assert not (cut.ablation_dir("baseline+lr=0.01") / "wind-uniform1" / "paper" / "base1").exists()
    # Resumed epoch by epoch, the models score as those of the uninterrupted call.
    for name in ("models", "levers"):
        assert scores(tmp_path / "out-cut" / f"{name}.json") == scores(tmp_path / "out-whole" / f"{name}.json")
