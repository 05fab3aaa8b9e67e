"""Peak GPU memory of every visible GPU while a block runs, sampled from nvidia-smi (a process's own
allocator cannot see the memory that other processes, e.g. pool workers, hold)."""

from __future__ import annotations

import subprocess
import tempfile
from pathlib import Path


class PeakGpuMemory:
    """``with PeakGpuMemory() as mem: ...`` then ``mem.peak_mib`` -> {GPU index: peak MiB used}.

    Empty where nvidia-smi is missing (a CPU machine). Samples every ``interval_ms``; memory that another
    process held before the block started counts too (start from an idle GPU to read the block's own peak).
    """

    def __init__(self, interval_ms: int = 500):
        self.interval_ms = interval_ms
        self.peak_mib: dict[str, int] = {}
        self._proc: subprocess.Popen | None = None
        self._log: Path | None = None

    def __enter__(self) -> "PeakGpuMemory":
        self._log = Path(tempfile.mkstemp(prefix="gpu_memory-", suffix=".csv")[1])
        try:
            self._proc = subprocess.Popen(
                ["nvidia-smi", "--query-gpu=index,memory.used", "--format=csv,noheader,nounits",
                 "-lms", str(self.interval_ms)], stdout=self._log.open("w"), stderr=subprocess.DEVNULL)
        except OSError:
            self._proc = None
        return self

    def __exit__(self, *exc) -> None:
        if self._proc is not None:
            self._proc.terminate()
            self._proc.wait(timeout=10)
        for line in self._log.read_text().splitlines() if self._log else []:
            parts = [p.strip() for p in line.split(",")]
            if len(parts) == 2 and parts[1].isdigit():
                self.peak_mib[parts[0]] = max(self.peak_mib.get(parts[0], 0), int(parts[1]))
        if self._log:
            self._log.unlink(missing_ok=True)
