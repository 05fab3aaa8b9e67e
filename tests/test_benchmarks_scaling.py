"""The scale-out benchmarks on CPU at tiny size: what they compare, and that a side is not run twice."""

from __future__ import annotations

import importlib.util
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from learn.synthetic import synthetic_run
from tests.conftest import tiny_train_config

ROOT = Path(__file__).resolve().parents[1]


def _bench(script: str, *args: str, timeout: int = 240) -> subprocess.CompletedProcess:
    env = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONPATH": str(ROOT)}
    done = subprocess.run([sys.executable, str(ROOT / "benchmarks" / script), *args], capture_output=True,
                          text=True, timeout=timeout, env=env, cwd=ROOT)
    assert done.returncode == 0, done.stdout[-2000:] + done.stderr[-3000:]
    return done


@pytest.mark.slow
def test_generation_scaling_sides_in_two_calls_and_sharded_simulations_are_byte_identical(tmp_path):
    # one batch of 16 cloths in one process against two workers of 8: on the CPU the clips are the same bytes
    common = ["--preset", "smoke", "--set", "sim.batch_size=16", "--set", "render.variants=paper",
              "--gpus-per-worker", "0", "--workers", "2", "--work", str(tmp_path / "work"), "--out", str(tmp_path)]
    first = _bench("generation_scaling.py", *common, "--side", "local")
    assert "waiting for the other side" in first.stdout
    assert (tmp_path / "work" / "local.json").is_file() and not list(tmp_path.glob("generation_scaling-*.json"))
    _bench("generation_scaling.py", *common, "--side", "process")
    result = json.loads((tmp_path / "generation_scaling-0gpu-smoke.json").read_text())
    assert result["baseline"]["clips"] == result["candidate"]["clips"] == {"wind-uniform1": 16}
    assert result["candidate"]["render"]["summary"]["executor"]["workers"] == 2
    assert result["simulations_byte_identical"] == {"sampled": 16, "identical": 16}
    assert set(result["speedup"]) == {"sim", "render", "total"}


@pytest.mark.slow
def test_train_scaling_keeps_the_global_batch_and_reuses_a_finished_side(tmp_path):
    run = synthetic_run(tmp_path / "run", tiny_train_config(epochs=2, num_threads=1))
    args = [str(run.root), "--setting", "wind-uniform1", "--variant", "paper", "--gpus", "2", "--device", "cpu",
            "--out", str(tmp_path)]
    _bench("train_scaling.py", *args)
    result = json.loads((tmp_path / "train_scaling-2gpu-lrcn.json").read_text())
    base, cand = result["baseline"], result["candidate"]
    assert (base["world_size"], cand["world_size"]) == (1, 2)
    assert cand["batch_per_process"] * 2 == base["batch_per_process"] == run.config.train.batch_size
    assert len(base["curve"]) == len(cand["curve"]) == 2
    assert base["process_seconds"] > 0 and cand["process_seconds"] > 0
    # both reach the common validation accuracy: the lower of their best
    assert result["common_val_acc"] == min(base["best_val_acc"], cand["best_val_acc"])
    assert base["seconds_to_common_val_acc"] is not None and cand["seconds_to_common_val_acc"] is not None
    assert result["test"]["1"]["test_windows"] == result["test"]["2"]["test_windows"] > 0
    assert "difference" in result["test"]
    # finished sides are read back, not trained again (their process time is then unknown)
    _bench("train_scaling.py", *args)
    again = json.loads((tmp_path / "train_scaling-2gpu-lrcn.json").read_text())
    assert again["baseline"]["process_seconds"] is None and again["candidate"]["curve"] == cand["curve"]


def test_train_step_wait_times_the_same_steps_with_and_without_a_wait(tmp_path):
    run = synthetic_run(tmp_path / "run", tiny_train_config(num_threads=1))
    out = tmp_path / "wait.json"
    done = _bench("train_step_wait.py", str(run.root), "--recipe", "baseline", "--warmup", "1", "--steps", "2",
                  "--out", str(out))
    result = json.loads(out.read_text())
    assert result["command"].startswith("python benchmarks/train_step_wait.py")
    for loop in ("with_a_wait_each_step", "as_training_runs"):
        assert result[loop]["windows_per_s"] > 0 and result[loop]["seconds"] > 0
    assert result["steps"] == 2 and result["batch_size"] == 8 and "windows/s as training runs" in done.stdout
    # more steps than the run has windows is refused, not silently shortened
    too_many = subprocess.run([sys.executable, str(ROOT / "benchmarks" / "train_step_wait.py"), str(run.root),
                               "--recipe", "baseline", "--steps", "1000"], capture_output=True, text=True,
                              env={**os.environ, "PYTHONPATH": str(ROOT)}, cwd=ROOT, timeout=240)
    assert too_many.returncode != 0 and "fewer than (warmup + steps) x batch" in too_many.stderr


def test_train_profile_times_each_layout_from_the_same_weights_against_the_first(tmp_path):
    run = synthetic_run(tmp_path / "run", tiny_train_config(num_threads=1))
    out = tmp_path / "profile.json"
    _bench("train_profile.py", str(run.root), "--recipe", "baseline", "--layouts", "eager,pad8", "--warmup", "1",
           "--steps", "2", "--profile-steps", "0", "--out", str(out))
    result = json.loads(out.read_text())
    assert result["command"].startswith("python benchmarks/train_profile.py")
    assert list(result["layouts"]) == ["eager", "pad8"] and result["layouts"]["eager"]["ratio"] == 1.0
    assert all(v["frames_per_s"] > 0 for v in result["layouts"].values()) and result["profile"] is None


def test_reader_step_times_both_ways_of_reading_the_two_shapes(tmp_path):
    out = tmp_path / "reader.json"
    done = _bench("reader_step.py", "--device", "cpu", "--batch-size", "2", "--frames", "4", "--warmup", "1",
                  "--steps", "2", "--out", str(out))
    result = json.loads(out.read_text())
    assert result["two_passes"]["step_ms"] > 0 and result["one_batch"]["step_ms"] > 0
    assert result["speedup"] > 0 and "as one batch" in done.stdout


def _train_profile_module(monkeypatch):
    monkeypatch.syspath_prepend(str(ROOT / "benchmarks"))          # its `from common import ...`
    spec = importlib.util.spec_from_file_location("train_profile", ROOT / "benchmarks" / "train_profile.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.mark.parametrize("channels_last", [False, True])
def test_conv1_input_padded_to_eight_channels_computes_the_same_sums(channels_last, monkeypatch):
    import torch

    from learn.models import build_model

    padded_conv = _train_profile_module(monkeypatch).PaddedConv
    torch.manual_seed(0)
    model = build_model("lrcn", image_size=64, width=8, fc6=32, hidden=16, motion=True).eval()
    x = torch.rand(2, 3, 3, 64, 64)
    if channels_last:
        model.cnn.to(memory_format=torch.channels_last)
        model.channels_last = True
    conv1 = model.cnn.features[0]

    def run():
        model.zero_grad()
        out = model(x)["logits"]
        out.sum().backward()
        return out.detach(), conv1.weight.grad.clone()

    plain, plain_grad = run()
    model.cnn.features[0] = padded_conv(conv1)
    padded, padded_grad = run()
    assert conv1.weight.shape[1] == 6      # the parameters keep their shape: checkpoints unchanged
    torch.testing.assert_close(padded, plain, rtol=1e-5, atol=1e-5)
    torch.testing.assert_close(padded_grad, plain_grad, rtol=1e-4, atol=1e-5)


def test_a_study_measured_across_calls_is_summed_per_stage_and_says_what_did_not_finish(tmp_path):
    from clothgap.config import preset
    from clothgap.runs import Run

    run = Run.create_or_resume(tmp_path / "study", preset("study"))
    calls = [{"stage": "sim", "rc": 0, "seconds": 393.0, "peak_gpu_mib": 7315, "mean_gpu_util_pct": 31.6,
              "peak_host_mib_over_start": 30380},
             {"stage": "render", "rc": 124, "seconds": 100.0, "peak_gpu_mib": 3992, "mean_gpu_util_pct": 80.0,
              "peak_host_mib_over_start": 8371},
             {"stage": "render", "rc": 0, "seconds": 300.0, "peak_gpu_mib": 4174, "mean_gpu_util_pct": 60.0,
              "peak_host_mib_over_start": 13759},
             {"stage": "train", "rc": 124, "seconds": 500.0, "peak_gpu_mib": 0, "mean_gpu_util_pct": 0.0,
              "peak_host_mib_over_start": 640}]
    (run.root / "gpu_timings.jsonl").write_text("".join(json.dumps(c) + "\n" for c in calls))
    out = tmp_path / "timings.json"
    _bench("study.py", "--timings", str(run.root), "--out", str(out))
    t = json.loads(out.read_text())["timings"]
    assert len(t["datasets"]) == 12 and "grid:wind-adaptive" in t["datasets"] and "grid:wind-uniform1" not in t["datasets"]
    render = t["stages"]["render"]
    assert render["calls"] == 2 and render["seconds"] == 400.0 and render["finished"] and render["peak_gpu_mib"] == 4174
    assert render["mean_gpu_util_pct"] == 65.0                        # weighted by each call's seconds
    assert not t["stages"]["train"]["finished"] and not t["finished"]
    assert t["unfinished"] == ["train", "eval", "report"] and t["stage_seconds"] == 1293.0
    assert "| render | 2 | 400.0 | yes |" in out.with_suffix(".md").read_text()
    missing = subprocess.run([sys.executable, str(ROOT / "benchmarks" / "study.py"), "--timings", str(tmp_path)],
                             capture_output=True, text=True, cwd=ROOT, env={**os.environ, "PYTHONPATH": str(ROOT)})
    assert missing.returncode != 0 and "gpu_timings.jsonl does not exist" in missing.stderr


def test_train_upload_moves_the_same_rows_both_ways_and_removes_its_array(tmp_path):
    out = tmp_path / "upload.json"
    _bench("train_upload.py", "--device", "cpu", "--clips", "12", "--train-clips", "5", "--frames", "3",
           "--size", "8", "--repeats", "1", "--workdir", str(tmp_path), "--out", str(out))
    result = json.loads(out.read_text())
    assert [r["way"] for r in result["runs"]] == ["whole", "chunked"]
    assert all(r["rows_checked_equal"] and r["seconds"] > 0 for r in result["runs"])
    assert result["set_gib"] == round(5 * 3 * 8 * 8 * 3 / 2**30, 2) and result["chunked_over_whole_seconds"] > 0
    assert [p.name for p in tmp_path.iterdir()] == ["upload.json"]      # the stand-in array is gone
