"""A private CUDA MPS control daemon for the workers that share a GPU.

Without MPS, processes on one GPU time-slice it: four render workers on an H100 render no more frames a
second than one (~420, 0.27 of the path tracer's ceiling), because a frame's host work (~2.2 ms) waits on
its own kernels (~0.65 ms). Under an MPS control daemon their kernels run side by side: four frozen
processes reach 0.81 of the ceiling, and the render stage on four H100s took 28 s instead of 62
(benchmarks/results/render_stage-mps-h100x4-n2592.json).

``cuda_mps(slots, mode)`` starts a daemon with its own pipe and log folders (so it neither joins nor
disturbs a daemon someone else runs), hands the workers the environment that connects them to it and
their GPUs renumbered as the daemon sees them, and quits it afterwards. The GPUs' settings (compute
mode, MIG) are not touched. A stage stopped by SIGTERM (``timeout``) still quits its daemon; one left
behind by a killed run is quit the next time a daemon starts.

Modes: ``auto`` uses MPS when two or more workers share a GPU and the control program exists, and runs
without it otherwise (saying why); ``on`` refuses to run without it; ``off`` never starts one. A daemon
already serving this process's environment (CUDA_MPS_PIPE_DIRECTORY set, or a live one in NVIDIA's
default folder) is used as it is, the workers' GPU numbers unchanged.
"""

from __future__ import annotations

import contextlib
import os
import shutil
import signal
import subprocess
import tempfile
import threading
import time
from collections import Counter
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path

from clothgap.errors import ConfigError
from clothgap.files import process_alive as _alive

MODES = ("auto", "on", "off")
CONTROL = "nvidia-cuda-mps-control"
DEFAULT_PIPE_DIRECTORY = Path("/tmp/nvidia-mps")     # where CUDA looks for a daemon when the variable is unset
OWNER_FILE = "owner.pid"
DAEMON_PID_FILE = "nvidia-cuda-mps-control.pid"       # the control daemon writes it into its pipe folder
FOLDER_PREFIX = "clothgap-mps-"
DAEMON_NAME = "nvidia-cuda-mps"     # how /proc/<pid>/comm names the control daemon (15 characters kept)
START_TIMEOUT_S = 20.0
QUIT_TIMEOUT_S = 8.0      # for the quit call, and again for the daemon to go: within learn_grid's 20 s grace
SHORT_TMP = Path("/tmp")
SOCKET_ROOM = 60          # characters a daemon's folder may take: its sockets' paths must stay under ~108


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


def _daemon_env(folder: Path) -> dict[str, str]:
    """The variables that point a client (or the control program) at the daemon of ``folder``."""
    return {"CUDA_MPS_PIPE_DIRECTORY": str(folder / "pipe"), "CUDA_MPS_LOG_DIRECTORY": str(folder / "log")}


def _daemon_pid(pipe: Path) -> int | None:
    """The control daemon's pid from its pid file, if that process is still the daemon (a stale file's pid may
    belong to another process by now, which must never be signalled)."""
    try:
        pid = int((pipe / DAEMON_PID_FILE).read_text().strip())
    except (OSError, ValueError):
        return None
    if pid <= 0:
        return None
    try:
        if not Path(f"/proc/{pid}/comm").read_text().startswith(DAEMON_NAME):
            return None
    except OSError:
        return None       # gone (or no /proc: then it is not signalled either)
    return pid


def existing_daemon(environ: dict[str, str] | None = None) -> str | None:
    """The pipe folder of a daemon this process's CUDA clients would already connect to, if any: the one the
    environment names, or a live one in NVIDIA's default folder (a control pipe left by a daemon that is gone
    serves no one)."""
    environ = os.environ if environ is None else environ
    pipe = environ.get("CUDA_MPS_PIPE_DIRECTORY")
    if pipe:
        return pipe
    pid = _daemon_pid(DEFAULT_PIPE_DIRECTORY)
    live = (DEFAULT_PIPE_DIRECTORY / "control").exists() and pid is not None and _alive(pid)
    return str(DEFAULT_PIPE_DIRECTORY) if live else None


def _quit(control: str, folder: Path, timeout: float | None = None) -> bool:
    """Ask the daemon of ``folder`` to quit and wait for it to go (SIGTERM if it does not); whether it is gone.
    A daemon that outlives this keeps its folder, so the next start finds it as an orphan and tries again."""
    timeout = QUIT_TIMEOUT_S if timeout is None else timeout
    pid = _daemon_pid(folder / "pipe")
    with contextlib.suppress(OSError, subprocess.SubprocessError):
        subprocess.run([control], input="quit\n", text=True, env={**os.environ, **_daemon_env(folder)},
                       stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, timeout=timeout)
    if pid is None:
        return True
    deadline = time.monotonic() + timeout
    while _alive(pid) and time.monotonic() < deadline:
        time.sleep(0.1)
    if _alive(pid):
        with contextlib.suppress(OSError):
            os.kill(pid, signal.SIGTERM)
        time.sleep(1.0)
    return not _alive(pid)


def _remove(control: str, folder: Path) -> None:
    if _quit(control, folder):
        shutil.rmtree(folder, ignore_errors=True)


def quit_orphans(control: str, root: Path | None = None) -> list[Path]:
    """Quit the daemons of runs that were killed (their owner process is gone) and remove their folders."""
    root = _daemon_root(root)
    quit_ = []
    for folder in sorted(root.glob(FOLDER_PREFIX + "*")):
        try:
            owner = int((folder / OWNER_FILE).read_text().strip())
        except (OSError, ValueError):
            continue
        if _alive(owner):
            continue
        _remove(control, folder)
        quit_.append(folder)
    return quit_


def _daemon_root(root: Path | None) -> Path:
    """Where daemon folders go: the temp folder, or /tmp when its path would make the sockets' paths too long."""
    if root is not None:
        return Path(root)
    tmp = Path(tempfile.gettempdir())
    return tmp if len(str(tmp)) + len(FOLDER_PREFIX) + 20 < SOCKET_ROOM else SHORT_TMP


def _start(control: str, root: Path | None = None) -> Path:
    """Start a daemon with its own pipe and log folders (kept short: the pipe is a Unix socket path)."""
    folder = Path(tempfile.mkdtemp(prefix=FOLDER_PREFIX, dir=_daemon_root(root)))
    (folder / "pipe").mkdir()
    (folder / "log").mkdir()
    (folder / OWNER_FILE).write_text(str(os.getpid()))
    said = folder / "log" / "start.txt"
    # its output to a file, not a pipe: a daemon that kept a captured pipe open would hold the call until timeout
    try:
        with open(said, "w") as out:
            done = subprocess.run([control, "-d"], env={**os.environ, **_daemon_env(folder)},
                                  stdin=subprocess.DEVNULL, stdout=out, stderr=out, timeout=START_TIMEOUT_S)
    except (OSError, subprocess.SubprocessError) as e:
        _remove(control, folder)
        raise MPSError(f"{control} -d could not run: {e}") from None
    deadline = time.monotonic() + START_TIMEOUT_S
    while done.returncode == 0 and not (folder / "pipe" / "control").exists() and time.monotonic() < deadline:
        time.sleep(0.05)
    if done.returncode != 0 or not (folder / "pipe" / "control").exists():
        why = said.read_text().strip() or f"exit {done.returncode}, no control pipe"
        _remove(control, folder)
        raise MPSError(f"{control} -d did not start a daemon: {why}")
    return folder


@contextlib.contextmanager
def _sigterm_as_exit() -> Iterator[None]:
    """SIGTERM (``timeout``, a scheduler) raises SystemExit for the block, so its cleanup runs; Python's default
    would end the process without it and leave the daemon running. Only the main thread can set a handler."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def stop(signum, frame):
        raise SystemExit(128 + signum)

    previous = signal.signal(signal.SIGTERM, stop)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous if previous is not None else signal.SIG_DFL)


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
        raise MPSError("--cuda-mps on, but the workers have no GPUs to share (none is visible, they run on the CPU, "
                       "or --gpus-per-worker was not given)")
    pipe = existing_daemon()
    if pipe is not None:
        say(f"cuda mps: using the daemon already running ({pipe}); the workers' GPU numbers are left as they are")
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
        with _sigterm_as_exit():
            session = MPSSession(renumber(slots, visible), _daemon_env(folder), "started")
            say(f"cuda mps: daemon started for {len(slots)} workers on {len(set(slots))} GPU slot(s)")
            yield session
    finally:
        _remove(control, folder)
