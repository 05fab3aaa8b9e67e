"""A private CUDA MPS control daemon for the workers that share a GPU.

Without MPS, processes on one GPU time-slice it: four render workers on an H100 render no more frames a
second than one (~420, 0.27 of the path tracer's ceiling), because a frame's host work (~2.2 ms) waits on
its own kernels (~0.65 ms). Under an MPS control daemon their kernels run side by side: four frozen
processes reach 0.81 of the ceiling, and the render stage on four H100s took 28 s instead of 62
(benchmarks/results/render_stage-mps-h100x4-n2592.json).

``cuda_mps(slots, mode)`` starts a daemon with its own pipe and log folders (so it neither joins nor
disturbs a daemon someone else runs), hands the workers the environment that connects them to it and
their GPUs renumbered as the daemon sees them, and quits it afterwards. The GPUs' settings (compute
mode, MIG) are not touched. A daemon left behind by a killed run is quit the next time one starts.

Modes: ``auto`` uses MPS when two or more workers share a GPU and the control program exists, and runs
without it otherwise (saying why); ``on`` refuses to run without it; ``off`` never starts one. A daemon
already serving this process's environment (CUDA_MPS_PIPE_DIRECTORY set, or one in NVIDIA's default
folder) is used as it is.
"""

from __future__ import annotations

import contextlib
import os
import shutil
import subprocess
import tempfile
import time
from collections import Counter
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path

from clothgap.config import ConfigError

MODES = ("auto", "on", "off")
CONTROL = "nvidia-cuda-mps-control"
DEFAULT_PIPE_DIRECTORY = Path("/tmp/nvidia-mps")     # where CUDA looks for a daemon when the variable is unset
OWNER_FILE = "owner.pid"
FOLDER_PREFIX = "clothgap-mps-"
START_TIMEOUT_S = 20.0


class MPSError(ConfigError):
    """MPS was asked for (``--cuda-mps on``) and cannot be had here."""


@dataclass
class MPSSession:
    """What the workers get: their GPU slots as the daemon numbers them, the environment that reaches it, and
    ``state`` for the stage's summary ("started", "existing", "off", or "not used: <why>")."""

    slots: list[str] | None
    env: dict[str, str] = field(default_factory=dict)
    state: str = "off"


def shares_a_gpu(slots: Sequence[str] | None) -> bool:
    """Whether two or more workers would run on one GPU."""
    if not slots:
        return False
    counts = Counter(g for slot in slots for g in slot.split(","))
    return max(counts.values()) > 1


def renumber(slots: Sequence[str], visible: Sequence[str]) -> list[str]:
    """Each slot's GPUs as positions in ``visible``: a daemon started under CUDA_VISIBLE_DEVICES=2,3 numbers
    those GPUs 0 and 1, and refuses a client that asks for GPU 2."""
    position = {g: str(i) for i, g in enumerate(visible)}
    try:
        return [",".join(position[g] for g in slot.split(",")) for slot in slots]
    except KeyError as e:
        raise ConfigError(f"GPU slot {e.args[0]!r} is not among the visible GPUs {', '.join(visible)}") from None


def existing_daemon(environ: dict[str, str] | None = None) -> str | None:
    """The pipe folder of a daemon this process's CUDA clients would already connect to, if any."""
    environ = os.environ if environ is None else environ
    pipe = environ.get("CUDA_MPS_PIPE_DIRECTORY")
    if pipe:
        return pipe
    return str(DEFAULT_PIPE_DIRECTORY) if (DEFAULT_PIPE_DIRECTORY / "control").exists() else None


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def _quit(control: str, folder: Path, timeout: float = 30.0) -> None:
    env = dict(os.environ, CUDA_MPS_PIPE_DIRECTORY=str(folder / "pipe"), CUDA_MPS_LOG_DIRECTORY=str(folder / "log"))
    with contextlib.suppress(OSError, subprocess.SubprocessError):
        subprocess.run([control], input="quit\n", text=True, env=env, capture_output=True, timeout=timeout)


def quit_orphans(control: str, root: Path | None = None) -> list[Path]:
    """Quit the daemons of runs that were killed (their owner process is gone) and remove their folders."""
    root = Path(root or tempfile.gettempdir())
    quit_ = []
    for folder in sorted(root.glob(FOLDER_PREFIX + "*")):
        try:
            owner = int((folder / OWNER_FILE).read_text().strip())
        except (OSError, ValueError):
            continue
        if _alive(owner):
            continue
        _quit(control, folder)
        shutil.rmtree(folder, ignore_errors=True)
        quit_.append(folder)
    return quit_


def _start(control: str, root: Path | None = None) -> Path:
    """Start a daemon with its own pipe and log folders (kept short: the pipe is a Unix socket path)."""
    folder = Path(tempfile.mkdtemp(prefix=FOLDER_PREFIX, dir=root))
    (folder / "pipe").mkdir()
    (folder / "log").mkdir()
    (folder / OWNER_FILE).write_text(str(os.getpid()))
    env = dict(os.environ, CUDA_MPS_PIPE_DIRECTORY=str(folder / "pipe"), CUDA_MPS_LOG_DIRECTORY=str(folder / "log"))
    try:
        done = subprocess.run([control, "-d"], env=env, capture_output=True, text=True, timeout=START_TIMEOUT_S)
    except (OSError, subprocess.SubprocessError) as e:
        shutil.rmtree(folder, ignore_errors=True)
        raise MPSError(f"{control} -d could not run: {e}") from None
    deadline = time.monotonic() + START_TIMEOUT_S
    while done.returncode == 0 and not (folder / "pipe" / "control").exists() and time.monotonic() < deadline:
        time.sleep(0.05)
    if done.returncode != 0 or not (folder / "pipe" / "control").exists():
        why = (done.stderr or done.stdout).strip() or f"exit {done.returncode}, no control pipe"
        _quit(control, folder)
        shutil.rmtree(folder, ignore_errors=True)
        raise MPSError(f"{control} -d did not start a daemon: {why}")
    return folder


@contextlib.contextmanager
def cuda_mps(slots: Sequence[str] | None, visible: Sequence[str], mode: str = "auto", *,
             root: Path | None = None, say=print) -> Iterator[MPSSession]:
    """Run the block with an MPS daemon serving ``slots`` (the workers' CUDA_VISIBLE_DEVICES entries, taken
    from ``visible``, this process's GPUs) when ``mode`` asks for one; yields the workers' session."""
    if mode not in MODES:
        raise ConfigError(f"--cuda-mps must be one of {', '.join(MODES)}, got {mode!r}")
    slots = list(slots) if slots is not None else None
    if mode == "off" or (mode == "auto" and not shares_a_gpu(slots)):
        yield MPSSession(slots, state="off" if mode == "off" else "not used: no GPU is shared by two workers")
        return
    if not slots:
        raise MPSError("--cuda-mps on, but the workers have no GPUs (give --gpus-per-worker)")
    pipe = existing_daemon()
    if pipe is not None:
        say(f"cuda mps: using the daemon already running ({pipe})")
        yield MPSSession(slots, state="existing")
        return
    control = shutil.which(CONTROL)
    if control is None:
        if mode == "on":
            raise MPSError(f"--cuda-mps on, but {CONTROL} is not on PATH (it comes with the NVIDIA driver)")
        why = f"not used: {CONTROL} is not on PATH"
        say(f"cuda mps {why}; workers sharing a GPU will time-slice it")
        yield MPSSession(slots, state=why)
        return
    for folder in quit_orphans(control, root):
        say(f"cuda mps: quit a daemon a killed run left behind ({folder.name})")
    try:
        folder = _start(control, root)
    except MPSError as e:
        if mode == "on":
            raise
        say(f"cuda mps not used: {e}; workers sharing a GPU will time-slice it")
        yield MPSSession(slots, state=f"not used: {e}")
        return
    try:
        session = MPSSession(renumber(slots, visible),
                             {"CUDA_MPS_PIPE_DIRECTORY": str(folder / "pipe"),
                              "CUDA_MPS_LOG_DIRECTORY": str(folder / "log")}, "started")
        say(f"cuda mps: daemon started for {len(slots)} workers on {len(set(slots))} GPU slot(s)")
        yield session
    finally:
        _quit(control, folder)
        shutil.rmtree(folder, ignore_errors=True)
