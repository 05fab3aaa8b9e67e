"""The simulation's Warp kernels compiled for the GPU machine ahead of time, here, on a machine without a GPU.

A fresh GPU machine otherwise compiles them on its first simulation: 18.5 s of a 40.1 s sim stage on an H100
(benchmarks/results/render_stage-mps-h100x4-n2592.json), and every session starts on a fresh machine.

    python scripts/gpu/warp_aot.py [--arch 90] [--out .gpu/warp-aot]     here, after the GPU bundle is built
    python scripts/gpu/warp_aot.py --check                               on the GPU machine (scripts/gpu/env.sh)

The first writes, in the layout of Warp's kernel cache (``OUT/<warp version>/wp_<module>_<hash>/``), every
module of the ``sim`` package that defines kernels as a cubin and as PTX for each ``--arch`` (90: the H100 and
H200); the runtime takes the one its driver calls for (a cubin when the driver is older than Warp's toolkit).
Carry OUT with the last staging call (``carry: [".gpu/p4", ".gpu/warp-aot"]``); ``scripts/gpu/env.sh`` copies it
into the machine's kernel cache (WARP_CACHE_PATH). A module whose hash differs there (another Warp version, a kernel changed since) is
compiled as before, so a stale cache costs nothing but its transfer. ``--check`` loads each module on the
first GPU and says whether it came from the cache and how long it took; run it before anything simulates on
the machine (a simulation puts what it compiles in the same cache).
"""

from __future__ import annotations

import argparse
import importlib
import os
import pkgutil
import shutil
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))


def kernel_modules() -> list:
    """The ``sim`` package's Python modules that define Warp kernels, imported."""
    import warp as wp

    import sim

    found = []
    for info in sorted(pkgutil.iter_modules(sim.__path__), key=lambda i: i.name):
        module = importlib.import_module(f"sim.{info.name}")
        if any(isinstance(v, wp.Kernel) for v in vars(module).values()):
            found.append(module)
    return found


def build(out: Path, archs: list[int]) -> None:
    os.environ["WARP_CACHE_PATH"] = str(out)      # before Warp initialises: its kernel cache is out/<version>
    import warp as wp

    wp.config.quiet = True
    wp.init()
    # What a GPU loads (Device.get_cuda_compile_arch): with a driver older than Warp's CUDA toolkit a cubin of the
    # GPU's own architecture, else PTX of the lower of that and the lowest architecture among the machine's GPUs
    # (Warp's default PTX architecture there): the GPU's own on a machine of one kind of GPU.
    for module in kernel_modules():
        for use_ptx in (False, True):
            started = time.perf_counter()
            paths = wp.compile_aot_module(module, arch=archs, use_ptx=use_ptx)
            print(f"{module.__name__}: {', '.join(Path(p).name for p in paths)} "
                  f"({time.perf_counter() - started:.1f} s)", flush=True)
    cache = Path(wp.config.kernel_cache_dir)
    for source in cache.glob("*/*.cu"):           # the runtime loads the meta and the binary only
        source.unlink()
    size = sum(f.stat().st_size for f in cache.rglob("*") if f.is_file())
    print(f"wrote {cache} ({size / 2**20:.1f} MiB)")


def check() -> int:
    """Load every kernel module on the first GPU; 0 when all came from the cache, 1 when any was compiled."""
    import warp as wp

    wp.init()
    if not wp.is_cuda_available():
        print("no CUDA device: --check runs on the GPU machine", file=sys.stderr)
        return 2
    device = wp.get_device("cuda:0")
    compiled = 0
    for module in kernel_modules():
        warp_module = wp.get_module(module.__name__)
        folder = Path(wp.config.kernel_cache_dir) / warp_module.get_module_identifier(block_dim=256)
        # the binary this GPU and driver load (cubin or PTX, and its architecture): Warp's own naming
        binary = folder / warp_module._get_compile_output_name(device, block_dim=256)
        had = binary.is_file()
        started = time.perf_counter()
        wp.load_module(module, device=device)
        took = time.perf_counter() - started
        compiled += not had
        print(f"{module.__name__}: {binary.name} {'from the cache' if had else 'compiled'}, {took:.2f} s",
              flush=True)
    return 1 if compiled else 0


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--arch", type=int, action="append", help="CUDA architecture (default: 90); repeatable")
    ap.add_argument("--out", type=Path, default=ROOT / ".gpu" / "warp-aot")
    ap.add_argument("--check", action="store_true", help="on the GPU machine: load each module, say where from")
    args = ap.parse_args(argv)
    if args.check:
        return check()
    shutil.rmtree(args.out, ignore_errors=True)
    build(args.out, args.arch or [90])
    return 0


if __name__ == "__main__":
    sys.exit(main())
