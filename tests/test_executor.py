"""Generation executors: shards of clip indices run here, in a process pool or on Ray, with the same clips.

Every path must give the plain ``run_sim``/``run_render`` clips bit for bit (the
sim on the CPU is independent of how clips are batched), skip what is finished,
and redo what a killed worker left unfinished, exactly once.
"""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from clothgap.config import ConfigError
from clothgap.executor import (ExecutorOptions, ShardError, check_reachable, default_shard_size, gpu_slots,
                               merge_summaries, ray_session, run_shards, run_stage, shard, sim_shard)
from clothgap.runs import DONE, Run, clip_id, fresh_dir, is_done, select_clips
from render.config import RenderConfig
from tests.conftest import RENDER_BACKEND, tiny_sim_run

SETTING = "wind-uniform1"


def tiny_run(root: Path) -> Run:
    """Four clips of three frames on a 6x6 grid, rendered at 12 px: a second or two to simulate on one core."""
    return tiny_sim_run(root, seed=3, classes=(0, 53, 20, 8), render=RenderConfig(
        variants=("paper",), resolution=12, spp=1, backend=RENDER_BACKEND, write_hdr=False))


def sim_arrays(run: Run, setting: str = SETTING) -> dict[str, tuple]:
    """Every clip's arrays (as bytes) and meta, by clip id."""
    out = {}
    for c in run.done_clips(run.sim_dir(setting)):
        folder = run.sim_dir(setting) / c
        with np.load(folder / "clip.npz") as z:
            arrays = {k: (z[k].dtype.str, z[k].shape, z[k].tobytes()) for k in sorted(z.files)}
        out[c] = (arrays, json.loads((folder / "meta.json").read_text()))
    return out


def render_pixels(run: Run, variant: str = "paper", setting: str = SETTING) -> dict[str, list[bytes]]:
    out = {}
    for c in run.done_clips(run.render_dir(variant, setting)):
        ldr = sorted((run.render_dir(variant, setting) / c / "ldr").iterdir())
        out[c] = [np.asarray(Image.open(p)).tobytes() for p in ldr]
    return out


# ---------------------------------------------------------------- pieces

def test_shards_are_consecutive_and_cover_every_index_once():
    assert shard(range(10), 4) == [[0, 1, 2, 3], [4, 5, 6, 7], [8, 9]]
    assert shard([], 3) == []
    assert default_shard_size(10, 3) == 4 and default_shard_size(2, 8) == 1 and default_shard_size(7, 0) == 7
    for n, size in ((1, 1), (17, 5), (64, 64)):
        flat = [i for s in shard(range(n), size) for i in s]
        assert flat == list(range(n))
    with pytest.raises(ConfigError):
        shard(range(3), 0)
    assert select_clips(4) == [0, 1, 2, 3] and select_clips(4, [3, 1, 3]) == [1, 3]
    with pytest.raises(ConfigError, match="outside"):
        select_clips(4, [4])


def test_gpu_slots_pin_one_worker_per_gpu_or_share():
    assert gpu_slots(["0", "1"], 1) == ["0", "1"]
    assert gpu_slots(["0", "1", "2", "3"], 2) == ["0,1", "2,3"]
    assert gpu_slots(["0", "1", "2"], 2) == ["0,1"]
    assert gpu_slots(["0", "1"], 0.5) == ["0", "0", "1", "1"]
    assert gpu_slots(["4", "5"], 1, workers=1) == ["4"]
    with pytest.raises(ConfigError, match="no GPU"):
        gpu_slots([], 1)
    with pytest.raises(ConfigError, match="needs 4 GPUs"):
        gpu_slots(["0", "1"], 1, workers=4)
    with pytest.raises(ConfigError, match="whole number"):
        gpu_slots(["0", "1"], 1.5)


def _report_gpu(run_root: str, indices: list[int]) -> dict:
    import time

    time.sleep(0.3)                  # long enough that both workers take shards
    return {"gpu": os.environ.get("CUDA_VISIBLE_DEVICES"), "pid": os.getpid()}


def test_process_workers_are_pinned_to_their_own_gpus(monkeypatch):
    from clothgap.executor import visible_gpus

    monkeypatch.setenv("CUDA_VISIBLE_DEVICES", "3,5")
    slots = gpu_slots(visible_gpus(), 1)
    assert slots == ["3", "5"]
    got = run_shards(_report_gpu, "/nowhere", shard(range(6), 1),
                     options=ExecutorOptions("process", gpus_per_worker=1, progress=False), gpu_slots=slots)
    by_pid: dict[int, set] = {}
    for r in got:
        by_pid.setdefault(r["pid"], set()).add(r["gpu"])
    assert all(len(g) == 1 for g in by_pid.values())        # a worker keeps its GPU
    assert sorted(g for gs in by_pid.values() for g in gs) == ["3", "5"]   # one worker per GPU


def test_options_are_checked():
    ExecutorOptions().validate()
    ExecutorOptions("ray", workers=2, address="auto", gpus_per_worker=0.5).validate()
    for bad, msg in ((ExecutorOptions("dask"), "unknown executor"),
                     (ExecutorOptions("process", address="auto"), "--executor ray"),
                     (ExecutorOptions("local", workers=4), "--executor process or ray"),
                     (ExecutorOptions("process", workers=0), "at least 1"),
                     (ExecutorOptions("ray", gpus_per_worker=-1), "negative")):
        with pytest.raises(ConfigError, match=msg):
            bad.validate()


def test_summaries_merge_counts_and_failures():
    sim = merge_summaries("sim", [{"simulated": 2, "skipped": 1, "failed": 0, "retried": 1, "seconds": 3.0,
                                   "phases_s": {"scenes": 0.5, "simulate": 2.0}},
                                  {"simulated": 1, "skipped": 0, "failed": 1, "retried": 1, "seconds": 2.0,
                                   "phases_s": {"simulate": 1.5}}])
    assert sim == {"simulated": 3, "skipped": 1, "failed": 1, "retried": 2, "failed_clips": [], "seconds": 0.0,
                   "phases_s": {"scenes": 0.5, "simulate": 3.5}}
    parts = [{"backend": "scalar_rgb", "rendered": 2, "skipped": 0, "failed": [], "frames": 6,
              "skipped_backgrounds": {}, "seconds": 1.0, "seconds_per_clip": 0.5, "seconds_per_frame": 0.1},
             {"backend": "scalar_rgb", "rendered": 0, "skipped": 1, "failed": [{"clip_id": "c00003"}], "frames": 0,
              "skipped_backgrounds": {"x.png": "bad"}, "seconds": 0.2}]
    r = merge_summaries("render", parts)
    assert r["rendered"] == 2 and r["skipped"] == 1 and r["failed"] == [{"clip_id": "c00003"}]
    assert r["frames"] == 6 and r["skipped_backgrounds"] == {"x.png": "bad"} and r["seconds_per_clip"] == 0.5


def test_unreachable_ray_address_and_missing_ray_are_clear_errors(monkeypatch):
    with socket.socket() as s:          # a port nobody listens on
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    for address in (f"ray://127.0.0.1:{port}", f"127.0.0.1:{port}"):
        with pytest.raises(ConfigError, match="cannot reach the Ray cluster"):
            check_reachable(address, timeout=2)
    check_reachable("auto")
    monkeypatch.setitem(sys.modules, "ray", None)          # as if Ray were not installed
    with pytest.raises(ConfigError, match=r"pip install 'clothgap\[ray\]'"):
        with ray_session(ExecutorOptions("ray")):
            pass


def test_cli_names_bad_executor_options(tmp_path):
    def clothgap(*args):
        return subprocess.run([sys.executable, "-m", "clothgap", *args], capture_output=True, text=True)

    r = clothgap("sim", "--preset", "smoke", "--out", str(tmp_path / "r"), "--executor", "process", "--address", "auto")
    assert r.returncode == 2 and "--executor ray" in r.stderr and "Traceback" not in r.stderr
    r = subprocess.run([sys.executable, "-m", "clothgap", "sim", "--preset", "smoke", "--out", str(tmp_path / "g"),
                        "--executor", "process", "--gpus-per-worker", "1"], capture_output=True, text=True,
                       env={**os.environ, "CUDA_VISIBLE_DEVICES": ""})
    assert r.returncode == 2 and "no GPU is visible" in r.stderr and "Traceback" not in r.stderr
    r = clothgap("render", str(tmp_path / "r"), "--executor", "nope")
    assert r.returncode == 2 and "nope" in r.stderr
    assert not (tmp_path / "r").exists()                 # options are checked before a run is started


# ---------------------------------------------------------------- the same clips on every path

def test_local_shards_and_process_pool_give_the_plain_clips(tmp_path):
    from render.stage import run_render
    from sim.stage import run_sim

    plain = tiny_run(tmp_path / "plain")
    assert run_sim(plain, progress=False)["simulated"] == 4
    run_render(plain, progress=False)
    expected_sim, expected_px = sim_arrays(plain), render_pixels(plain)
    assert len(expected_sim) == 4 and len(expected_px) == 4

    local = tiny_run(tmp_path / "local")
    s = run_stage(local, "sim", ExecutorOptions("local", shard_size=1, progress=False))
    assert s["simulated"] == 4 and s["executor"]["shards"] == 4
    assert sim_arrays(local) == expected_sim                 # bit for bit, whatever the batches

    pooled = tiny_run(tmp_path / "pooled")
    opts = ExecutorOptions("process", workers=2, progress=False)
    s = run_stage(pooled, "sim", opts)
    assert s["simulated"] == 4 and s["executor"] == {"name": "process", "workers": 2, "shards": 2}
    assert sim_arrays(pooled) == expected_sim
    r = run_stage(pooled, "render", opts)
    assert r["rendered"] == 4 and r["failed"] == [] and r["frames"] == 12
    assert render_pixels(pooled) == expected_px
    again = run_stage(pooled, "sim", opts)                   # idempotent: nothing is done twice
    assert again["simulated"] == 0 and again["skipped"] == 4


def _dying_sim_shard(run_root: str, indices: list[int]) -> dict:
    """A worker that finishes one clip, starts the next, and is killed (SIGKILL) - once per run."""
    flag = Path(run_root) / "killed-once.json"
    try:
        fd = os.open(flag, os.O_CREAT | os.O_EXCL | os.O_WRONLY)
    except FileExistsError:
        return sim_shard(run_root, indices)
    sim_shard(run_root, indices[:1])
    run = Run.open(run_root)
    finished = run.sim_dir(SETTING) / clip_id(indices[0])
    partial = fresh_dir(run.sim_dir(SETTING) / clip_id(indices[1]))
    (partial / "clip.npz").write_bytes(b"half a clip")
    os.write(fd, json.dumps({"finished": finished.name, "done_mtime_ns": (finished / DONE).stat().st_mtime_ns,
                             "partial": partial.name}).encode())
    os.close(fd)
    os.kill(os.getpid(), signal.SIGKILL)
    raise AssertionError("unreachable")


def test_killed_worker_clips_are_redone_and_none_twice(tmp_path):
    run = tiny_run(tmp_path / "run")
    expected = sim_arrays(_plain_sim(tmp_path / "plain"))

    # a worker killed mid-shard: the pool is rebuilt and the unfinished shards run again
    parts = run_shards(_dying_sim_shard, str(run.root), shard(range(4), 2),
                       options=ExecutorOptions("process", workers=2, progress=False), label="sim")
    killed = json.loads((run.root / "killed-once.json").read_text())
    summary = merge_summaries("sim", parts)
    assert summary["simulated"] + summary["skipped"] == 4 and summary["failed"] == 0
    folder = run.sim_dir(SETTING)
    assert sorted(p.name for p in folder.iterdir()) == [clip_id(i) for i in range(4)]   # each clip once
    assert all(is_done(folder / clip_id(i)) for i in range(4))
    assert (folder / killed["finished"] / DONE).stat().st_mtime_ns == killed["done_mtime_ns"]  # not redone
    assert sim_arrays(run) == expected                        # the half-written clip was redone from scratch
    assert not [p for p in folder.rglob("*") if ".tmp" in p.name]

    # a run killed for good leaves folders without DONE: the next run redoes just those
    (folder / clip_id(1) / DONE).unlink()
    (folder / clip_id(1) / "clip.npz").write_bytes(b"torn")
    fresh_dir(folder / clip_id(2))
    done_before = {i: (folder / clip_id(i) / DONE).stat().st_mtime_ns for i in (0, 3)}
    s = run_stage(run, "sim", ExecutorOptions("process", workers=2, progress=False))
    assert s["simulated"] == 2 and s["skipped"] == 2
    assert {i: (folder / clip_id(i) / DONE).stat().st_mtime_ns for i in (0, 3)} == done_before
    assert sim_arrays(run) == expected


def _failing_shard(run_root: str, indices: list[int]) -> dict:
    if 2 in indices:
        raise ValueError(f"no good: {indices}")
    return {}


def test_a_failing_shard_is_named():
    with pytest.raises(ShardError, match=r"sim shard 1 \(clips 2\.\.3\) failed: ValueError: no good"):
        run_shards(_failing_shard, "/nowhere", [[0, 1], [2, 3]],
                   options=ExecutorOptions("process", workers=1, progress=False), label="sim")


def _plain_sim(root: Path) -> Run:
    from sim.stage import run_sim

    run = tiny_run(root)
    run_sim(run, progress=False)
    return run


@pytest.mark.slow
def test_ray_on_a_local_instance_gives_the_plain_clips(tmp_path):
    pytest.importorskip("ray")
    from render.stage import run_render

    plain = _plain_sim(tmp_path / "plain")
    run_render(plain, progress=False)
    run = tiny_run(tmp_path / "ray")
    # address None: a fresh local instance with --workers CPUs (ray.init(num_cpus=2)), shut down after;
    # both stages use the one instance (run_stage joins a session that is already up)
    opts = ExecutorOptions("ray", workers=2, progress=False)
    with ray_session(opts) as ray:
        assert ray.cluster_resources()["CPU"] == 2
        s = run_stage(run, "sim", opts)
        assert s["simulated"] == 4 and s["executor"] == {"name": "ray", "workers": 2, "shards": 2}
        r = run_stage(run, "render", replace(opts, shard_size=3))
        assert r["rendered"] == 4 and r["failed"] == [] and r["executor"]["shards"] == 2
        # a look for testing only, on some clips: the Ray tasks render it (a partial of render_shard)
        t = run_stage(run, "render", opts, indices=[0, 1], test_variants=["heldout"])
        done = sorted(p.parent.name for p in (run.root / "render" / "heldout").rglob("DONE"))
        assert t["rendered"] == len(done) > 0 and t["failed"] == [] and t["executor"]["name"] == "ray"
        assert ray.is_initialized()
        # a Ray worker killed mid-shard: Ray runs the task again, the finished clip is kept
        killed_run = tiny_run(tmp_path / "killed")
        parts = run_shards(_dying_sim_shard, str(killed_run.root), shard(range(4), 2), options=opts, label="sim")
        assert sum(p["simulated"] + p["skipped"] for p in parts) == 4
        killed = json.loads((killed_run.root / "killed-once.json").read_text())
        done = killed_run.sim_dir(SETTING) / killed["finished"] / DONE
        assert done.stat().st_mtime_ns == killed["done_mtime_ns"]
        assert sim_arrays(killed_run) == sim_arrays(plain)
    assert sim_arrays(run) == sim_arrays(plain)
    assert render_pixels(run) == render_pixels(plain)
    assert not ray.is_initialized()


def test_unknown_variant_is_a_config_error_before_any_shard(tmp_path):
    run = tiny_run(tmp_path / "r")
    run = Run(run.root, replace(run.config, render=replace(run.config.render, variants=("paper", "nosuch"))))
    with pytest.raises(ConfigError, match="unknown render variant 'nosuch'"):
        run_stage(run, "render", ExecutorOptions("process", workers=2, progress=False))


def test_process_workers_share_the_host_cpus_between_their_own_pools(monkeypatch):
    from clothgap import parallel
    from clothgap.executor import _init_worker

    monkeypatch.delenv(parallel.HOST_PROCESSES_ENV, raising=False)
    monkeypatch.setattr(parallel.os, "cpu_count", lambda: 32)
    assert parallel.host_processes() == 32 and parallel.share_of_host(2) == 16 and parallel.share_of_host(64) == 1
    monkeypatch.setenv("CUDA_VISIBLE_DEVICES", "")
    _init_worker(None, parallel.share_of_host(2), {})      # what a worker of a pool of two runs first
    assert parallel.host_processes() == 16
    for bad in ("0", "-3", "many", ""):
        monkeypatch.setenv(parallel.HOST_PROCESSES_ENV, bad)
        assert parallel.host_processes() == 32
