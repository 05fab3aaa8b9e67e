"""The simulation's Warp kernels compiled ahead of time for the GPU machine land where its runtime looks."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.slow
def test_kernels_compiled_here_are_named_as_a_gpu_of_that_architecture_loads_them(tmp_path):
    out = tmp_path / "aot"
    subprocess.run([sys.executable, str(ROOT / "scripts/gpu/warp_aot.py"), "--out", str(out)], check=True,
                   capture_output=True, text=True)
    # What the runtime computes for a CUDA launch (block_dim 256), in a process of its own like the GPU machine's.
    names = subprocess.run(
        [sys.executable, "-c", "import sys; sys.path.insert(0, sys.argv[1]); import warp as wp; wp.config.quiet = True; "
         "wp.init(); import sim.kernels, sim.collision, sim.garment; "
         "print('names', wp.config.version, *(wp.get_module(m).get_module_identifier(block_dim=256) "
         "for m in ('sim.kernels', 'sim.collision', 'sim.garment')))", str(ROOT)],
        check=True, capture_output=True, text=True).stdout.splitlines()[-1].split()   # after Warp's own messages
    assert names[0] == "names"
    version, identifiers = names[1], names[2:]
    cache = out / version
    assert sorted(p.name for p in cache.iterdir()) == sorted(identifiers)
    for name in identifiers:
        files = sorted(p.name for p in (cache / name).iterdir())
        assert f"{name}.meta" in files and f"{name}.sm90.cubin" in files       # a driver older than Warp's toolkit
        assert f"{name}.sm90.ptx" in files                                     # a newer one
        assert not any(f.endswith(".cu") for f in files)
