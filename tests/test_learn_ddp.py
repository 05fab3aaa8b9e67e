"""The training entry point under torchrun: two CPU processes (gloo), one writer."""

from __future__ import annotations

import os
import subprocess
import sys

import pandas as pd
import pytest

from clothgap.runs import is_done
from learn.predict import predict_clips
from learn.synthetic import synthetic_run
from tests.conftest import SETTING, VARIANT, tiny_train_config


@pytest.mark.slow
def test_torchrun_two_processes_train_one_model(tmp_path):
    run = synthetic_run(tmp_path / "run", tiny_train_config(epochs=2, num_threads=1))
    cmd = [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc-per-node", "2",
           "-m", "learn", str(run.root), "--model", "lrcn", "--no-progress"]
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=90, env={**os.environ, "OMP_NUM_THREADS": "1"})
    assert done.returncode == 0, done.stdout[-2000:] + done.stderr[-3000:]
    out = run.train_dir(SETTING, VARIANT, "lrcn", 0)
    assert is_done(out) and len(pd.read_csv(out / "metrics.csv")) == 2
    assert (run.root / "splits" / f"{SETTING}.json").is_file()
    pred = predict_clips(out, [run.render_dir(VARIANT, SETTING) / "c00000"], device="cpu")
    assert len(pred) == 3


def test_a_selection_the_run_lacks_is_refused_before_any_training(tmp_path):
    run = synthetic_run(tmp_path / "run", tiny_train_config(models=("lrcn",), epochs=1))
    cmd = [sys.executable, "-m", "learn", str(run.root), "--model", "base1", "--seed", "3", "--no-progress"]
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=60)
    assert done.returncode == 2
    assert "--model base1: not in this run's config (lrcn)" in done.stderr
    assert not (run.root / "train").exists()
