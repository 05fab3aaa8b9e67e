"""The private CUDA MPS daemon of workers that share a GPU (clothgap.cuda_mps).

These machines have no GPU and no NVIDIA driver, so the daemon's lifecycle is checked against a stand-in
``nvidia-cuda-mps-control`` on PATH that does what the real one does to processes and files (``-d`` leaves a
daemon process running, with the control pipe and its pid file in CUDA_MPS_PIPE_DIRECTORY; ``quit`` on stdin
ends it) and records each call. What the real daemon does to the renders was measured on H100s
(benchmarks/results/render_stage-mps-h100x4-n2592.json).
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from clothgap import cuda_mps as mps_module
from clothgap.config import ConfigError
from clothgap.cuda_mps import MPSError, cuda_mps, quit_orphans, renumber, shares_a_gpu
from clothgap.executor import ExecutorOptions, gpu_slots, run_shards, shard, visible_gpus

FAKE_CONTROL = """#!{python}
import json, os, pathlib, signal, subprocess, sys
record = os.environ["FAKE_MPS_RECORD"]
pipe = pathlib.Path(os.environ["CUDA_MPS_PIPE_DIRECTORY"])
if sys.argv[1:] == ["-d"]:
    if os.environ.get("FAKE_MPS_FAIL"):
        print("An instance of this daemon is already running", file=sys.stderr)
        sys.exit(1)
    daemon = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(300)"], start_new_session=True,
                              stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    # named "python" in /proc only once its exec is through (Popen may return before): as a real daemon is
    for _ in range(100000):
        if pathlib.Path(f"/proc/{{daemon.pid}}/comm").read_text().startswith("python"):
            break
    (pipe / "{pid_file}").write_text(str(daemon.pid))
    (pipe / "stand-in.pid").write_text(str(daemon.pid))        # what quit ends: only the process it started
    (pipe / "control").write_text("")
    event = {{"start": str(pipe), "visible": os.environ.get("CUDA_VISIBLE_DEVICES")}}
else:
    command = sys.stdin.read().strip()
    if command == "quit" and not os.environ.get("FAKE_MPS_DEAF"):
        try:
            os.kill(int((pipe / "stand-in.pid").read_text()), signal.SIGTERM)
        except (OSError, ValueError):
            pass
    event = {{command: str(pipe)}}
with open(record, "a") as f:
    f.write(json.dumps(event) + "\\n")
"""


@pytest.fixture
def control(tmp_path, monkeypatch):
    """A stand-in control program first on PATH; returns the file its calls are recorded in."""
    bin_dir = tmp_path / "bin"
    bin_dir.mkdir()
    program = bin_dir / mps_module.CONTROL
    program.write_text(FAKE_CONTROL.format(python=sys.executable, pid_file=mps_module.DAEMON_PID_FILE))
    program.chmod(0o755)
    record = tmp_path / "calls.jsonl"
    monkeypatch.setenv("PATH", f"{bin_dir}{os.pathsep}{os.environ['PATH']}")
    monkeypatch.setenv("FAKE_MPS_RECORD", str(record))
    monkeypatch.delenv("CUDA_MPS_PIPE_DIRECTORY", raising=False)
    monkeypatch.delenv("FAKE_MPS_FAIL", raising=False)
    monkeypatch.delenv("FAKE_MPS_DEAF", raising=False)
    monkeypatch.setattr(mps_module, "DEFAULT_PIPE_DIRECTORY", tmp_path / "no-system-daemon")
    monkeypatch.setattr(mps_module, "DAEMON_NAME", "python")      # the stand-in's daemon is a Python process
    return record


def wait_for_name(pid: int, name: str, timeout: float = 10.0) -> None:
    """Until /proc names ``pid`` ``name``: Linux lets a vfork parent (Popen) go on before the exec'd child's comm
    is set, so for a moment the child still carries its parent's name."""
    deadline = time.monotonic() + timeout
    while not Path(f"/proc/{pid}/comm").read_text().startswith(name):
        assert time.monotonic() < deadline, f"process {pid} is not named {name!r} after {timeout} s"
        time.sleep(0.01)


def calls(record: Path) -> list[dict]:
    return [json.loads(line) for line in record.read_text().splitlines()] if record.exists() else []


def daemon_pid(mps) -> int:
    return int((Path(mps.env["CUDA_MPS_PIPE_DIRECTORY"]) / mps_module.DAEMON_PID_FILE).read_text())


def gone(pid: int, within: float = 5.0) -> bool:
    deadline = time.monotonic() + within
    while mps_module._alive(pid) and time.monotonic() < deadline:
        time.sleep(0.05)
    return not mps_module._alive(pid)


def _report_env(run_root: str, indices: list[int]) -> dict:
    import time

    time.sleep(0.2)                  # long enough that every worker takes a shard
    return {"gpu": os.environ.get("CUDA_VISIBLE_DEVICES"), "pipe": os.environ.get("CUDA_MPS_PIPE_DIRECTORY"),
            "pid": os.getpid()}


def test_which_workers_share_a_gpu_and_how_the_daemon_numbers_them():
    assert not shares_a_gpu(None) and not shares_a_gpu(["0", "1"]) and not shares_a_gpu(["0,1", "2,3"])
    assert shares_a_gpu(["0", "0", "1", "1"]) and shares_a_gpu(["0,1", "1,2"])
    # a daemon started under CUDA_VISIBLE_DEVICES=2,3 sees those GPUs as 0 and 1
    assert renumber(["2", "2", "3", "3"], ["2", "3"]) == ["0", "0", "1", "1"]
    assert renumber(["GPU-b,GPU-a"], ["GPU-a", "GPU-b"]) == ["1,0"]
    with pytest.raises(ConfigError, match="'7' is not among the visible GPUs 2, 3"):
        renumber(["7"], ["2", "3"])


def test_workers_sharing_a_gpu_run_under_a_private_daemon_that_is_quit_afterwards(control, tmp_path, monkeypatch):
    monkeypatch.setenv("CUDA_VISIBLE_DEVICES", "3,5")
    visible = visible_gpus()
    slots = gpu_slots(visible, 0.5)
    assert slots == ["3", "3", "5", "5"]
    said: list[str] = []
    with cuda_mps(slots, visible, "auto", root=tmp_path, say=said.append) as mps:
        assert mps.state == "started" and mps.slots == ["0", "0", "1", "1"]
        pipe = Path(mps.env["CUDA_MPS_PIPE_DIRECTORY"])
        assert (pipe / "control").exists() and "CUDA_MPS_PIPE_DIRECTORY" not in os.environ   # the parent stays out
        daemon = daemon_pid(mps)
        assert mps_module._alive(daemon)
        got = run_shards(_report_env, "/nowhere", shard(range(8), 1),
                         options=ExecutorOptions("process", gpus_per_worker=0.5, progress=False),
                         gpu_slots=mps.slots, worker_env=mps.env)
    assert {r["pipe"] for r in got} == {str(pipe)}                  # every worker reaches the daemon
    assert {r["gpu"] for r in got} <= {"0", "1"}                    # ... by the daemon's numbers
    # the daemon saw the GPUs the parent sees, and was quit once the workers were done
    assert calls(control) == [{"start": str(pipe), "visible": "3,5"}, {"quit": str(pipe)}]
    assert not pipe.parent.exists() and any("daemon started" in s for s in said) and gone(daemon)


def test_a_daemon_deaf_to_quit_is_terminated_and_a_stage_stopped_by_sigterm_still_quits_its_daemon(
        control, tmp_path, monkeypatch):
    monkeypatch.setenv("FAKE_MPS_DEAF", "1")
    monkeypatch.setattr(mps_module, "QUIT_TIMEOUT_S", 0.5)
    with cuda_mps(["0", "0"], ["0"], "on", root=tmp_path, say=lambda m: None) as mps:
        daemon = daemon_pid(mps)
    assert gone(daemon) and not list(tmp_path.glob(mps_module.FOLDER_PREFIX + "*"))   # SIGTERM after the wait
    monkeypatch.delenv("FAKE_MPS_DEAF")
    with pytest.raises(SystemExit) as stopped:
        with cuda_mps(["0", "0"], ["0"], "on", root=tmp_path, say=lambda m: None) as mps:
            daemon = daemon_pid(mps)
            os.kill(os.getpid(), signal.SIGTERM)          # what `timeout` sends a stage
            time.sleep(5)
    assert stopped.value.code == 128 + signal.SIGTERM and gone(daemon)
    assert signal.getsignal(signal.SIGTERM) is signal.SIG_DFL    # the handler is only the block's


def test_without_a_shared_gpu_or_with_mps_off_no_daemon_starts(control, tmp_path):
    with cuda_mps(["0", "1"], ["0", "1"], "auto", root=tmp_path, say=lambda m: None) as mps:
        assert mps.slots == ["0", "1"] and mps.env == {} and mps.state.startswith("not used: no GPU is shared")
    with cuda_mps(["0", "0"], ["0"], "off", root=tmp_path, say=lambda m: None) as mps:
        assert mps.slots == ["0", "0"] and mps.env == {} and mps.state == "off"
    assert calls(control) == []


def test_a_daemon_already_serving_this_process_is_used_as_it_is(control, tmp_path, monkeypatch):
    monkeypatch.setenv("CUDA_MPS_PIPE_DIRECTORY", str(tmp_path / "theirs"))
    with cuda_mps(["2", "2"], ["2"], "on", root=tmp_path, say=lambda m: None) as mps:
        assert mps.state == "existing" and mps.slots == ["2", "2"] and mps.env == {}
    assert calls(control) == []                                     # neither started nor quit


def test_a_control_pipe_left_in_the_default_folder_by_a_daemon_that_is_gone_is_not_trusted(control, tmp_path):
    default = mps_module.DEFAULT_PIPE_DIRECTORY
    default.mkdir()
    (default / "control").write_text("")
    assert mps_module.existing_daemon({}) is None                   # no pid file: nothing serves it
    gone_pid = subprocess.Popen([sys.executable, "-c", "pass"])
    gone_pid.wait()
    (default / mps_module.DAEMON_PID_FILE).write_text(str(gone_pid.pid))
    assert mps_module.existing_daemon({}) is None
    # a live stand-in daemon (a Python process, as DAEMON_NAME says here); not pytest's own pid, whose
    # /proc comm is "pytest" when the suite runs through the pytest script
    live = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    try:
        wait_for_name(live.pid, "python")
        (default / mps_module.DAEMON_PID_FILE).write_text(str(live.pid))
        assert mps_module.existing_daemon({}) == str(default)
    finally:
        live.kill()
        live.wait()


def test_without_the_control_program_auto_runs_without_mps_and_on_refuses(tmp_path, monkeypatch):
    monkeypatch.setenv("PATH", str(tmp_path))                       # no nvidia-cuda-mps-control here
    monkeypatch.delenv("CUDA_MPS_PIPE_DIRECTORY", raising=False)
    monkeypatch.setattr(mps_module, "DEFAULT_PIPE_DIRECTORY", tmp_path / "no-system-daemon")
    said: list[str] = []
    with cuda_mps(["0", "0"], ["0"], "auto", root=tmp_path, say=said.append) as mps:
        assert mps.slots == ["0", "0"] and mps.env == {} and "not on PATH" in mps.state
    assert "time-slice" in said[0]
    with pytest.raises(MPSError, match="nvidia-cuda-mps-control is not on PATH"):
        with cuda_mps(["0", "0"], ["0"], "on", root=tmp_path, say=said.append):
            pass


def test_a_daemon_that_does_not_start_is_named(control, tmp_path, monkeypatch):
    monkeypatch.setenv("FAKE_MPS_FAIL", "1")
    with cuda_mps(["0", "0"], ["0"], "auto", root=tmp_path, say=lambda m: None) as mps:
        assert mps.env == {} and "already running" in mps.state
    with pytest.raises(MPSError, match="did not start a daemon: An instance of this daemon is already running"):
        with cuda_mps(["0", "0"], ["0"], "on", root=tmp_path, say=lambda m: None):
            pass
    assert not list(tmp_path.glob(mps_module.FOLDER_PREFIX + "*"))  # no folder left behind


def test_a_stale_pid_file_never_signals_a_process_that_is_not_the_daemon(control, tmp_path, monkeypatch):
    monkeypatch.setattr(mps_module, "DAEMON_NAME", "nvidia-cuda-mps")
    bystander = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    try:
        folder = tmp_path / f"{mps_module.FOLDER_PREFIX}stale"
        (folder / "pipe").mkdir(parents=True)
        for pid in (str(bystander.pid), "0", "-1", "nonsense"):
            (folder / "pipe" / mps_module.DAEMON_PID_FILE).write_text(pid)
            assert mps_module._daemon_pid(folder / "pipe") is None
            assert mps_module._quit(mps_module.CONTROL, folder, timeout=0.2)   # nothing of ours left to wait for
        assert bystander.poll() is None                                        # and the bystander lives
    finally:
        bystander.kill()
        bystander.wait()


STOPPED_STAGE = """
import sys, time
from pathlib import Path
sys.path.insert(0, {root!r})
from clothgap import cuda_mps as mps_module
from clothgap.executor import ExecutorOptions, run_shards, shard
from tests.test_cuda_mps import _slow_shard
mps_module.DAEMON_NAME = "python"
with mps_module.cuda_mps(["0", "0"], ["0"], "on", root=Path({folder!r}), say=lambda m: None) as mps:
    print(mps_module._daemon_pid(Path(mps.env["CUDA_MPS_PIPE_DIRECTORY"])), flush=True)
    run_shards(_slow_shard, "/nowhere", shard(range(8), 1), gpu_slots=mps.slots, worker_env=mps.env,
               options=ExecutorOptions("process", gpus_per_worker=0.5, progress=False))
"""


def _slow_shard(run_root: str, indices: list[int]) -> dict:
    time.sleep(4)
    return {}


def test_a_stage_sent_sigterm_stops_its_workers_at_once_and_quits_its_daemon(control, tmp_path):
    """Eight 4 s shards on two workers: SIGTERM to the stage's own process (not its group) ends it within
    seconds, not after every queued shard, and its daemon goes with it."""
    root = str(Path(__file__).resolve().parents[1])
    stage = subprocess.Popen([sys.executable, "-c", STOPPED_STAGE.format(root=root, folder=str(tmp_path))],
                             stdout=subprocess.PIPE, text=True, env=dict(os.environ, PYTHONPATH=root))
    daemon = int(stage.stdout.readline())
    time.sleep(2.5)                                         # the workers are inside their first shards
    t0 = time.monotonic()
    stage.send_signal(signal.SIGTERM)
    assert stage.wait(timeout=30) == 128 + signal.SIGTERM
    assert time.monotonic() - t0 < 8                        # the whole stage would take 16 s more
    assert gone(daemon) and not list(tmp_path.glob(mps_module.FOLDER_PREFIX + "*"))


def test_a_daemon_left_by_a_killed_run_is_quit_and_a_live_runs_daemon_is_not(control, tmp_path):
    gone = subprocess.Popen([sys.executable, "-c", "pass"])
    gone.wait()
    for name, owner in (("orphan", gone.pid), ("live", os.getpid())):
        folder = tmp_path / f"{mps_module.FOLDER_PREFIX}{name}"
        (folder / "pipe").mkdir(parents=True)
        (folder / mps_module.OWNER_FILE).write_text(str(owner))
    quit_ = quit_orphans(mps_module.CONTROL, tmp_path)
    assert [f.name for f in quit_] == [f"{mps_module.FOLDER_PREFIX}orphan"]
    assert calls(control) == [{"quit": str(tmp_path / f"{mps_module.FOLDER_PREFIX}orphan" / "pipe")}]
    assert not quit_[0].exists() and (tmp_path / f"{mps_module.FOLDER_PREFIX}live").exists()


def test_render_workers_sharing_a_gpu_get_the_daemon_and_sim_workers_only_when_asked(control, tmp_path,
                                                                                     monkeypatch):
    from clothgap.executor import run_stage
    from tests.conftest import tiny_sim_run

    monkeypatch.setenv("CUDA_VISIBLE_DEVICES", "0")                  # one "GPU", two workers on it (run on CPU)
    run = tiny_sim_run(tmp_path / "run", seed=3, classes=(0, 53))
    auto = run_stage(run, "sim", ExecutorOptions("process", gpus_per_worker=0.5, progress=False))
    assert auto["simulated"] == 2 and auto["executor"]["cuda_mps"] == "off" and calls(control) == []
    fresh = tiny_sim_run(tmp_path / "fresh", seed=3, classes=(0, 53))
    on = run_stage(fresh, "sim", ExecutorOptions("process", gpus_per_worker=0.5, progress=False, cuda_mps="on"))
    assert on["simulated"] == 2 and on["executor"]["cuda_mps"] == "started"
    assert [list(c)[0] for c in calls(control)] == ["start", "quit"]
    with pytest.raises(ConfigError, match="give the render workers their share of a GPU"):
        run_stage(fresh, "render", ExecutorOptions("process", workers=2, progress=False, cuda_mps="on"))
    with pytest.raises(MPSError, match="the workers have no GPUs"):
        with cuda_mps(None, [], "on", root=tmp_path, say=lambda m: None):
            pass


def test_mps_options_are_checked():
    with pytest.raises(ConfigError, match="--cuda-mps must be one of auto, on, off"):
        ExecutorOptions("process", cuda_mps="sometimes").validate()
    with pytest.raises(ConfigError, match="use it with --executor process"):
        ExecutorOptions("ray", cuda_mps="on").validate()
    assert ExecutorOptions("process", gpus_per_worker=0.25, cuda_mps="on").validate().cuda_mps == "on"
