"""A render process's memory as it renders one dataset after another: its resident set and its pooled scenes.

    python benchmarks/render_pool_memory.py RUN --setting wind-uniform1 \\
        --variants paper,grid,color,lighting-random,heldout,daylight,paper,grid --out pool.json

Renders the setting's finished sim clips of RUN under each variant in turn, in this one process and the run's
render settings, into a scratch folder (not the run's), and after each variant records the process's resident
memory (VmRSS, after a garbage collection) and how many scenes ``render.scene``'s pool keeps alive (at most ``MAX_POOLED_SCENES`` structures a
process, least recently used dropped). Why a render worker's memory rises over a study's first datasets and where
it stops (issue 14: host memory across settings).
"""

from __future__ import annotations

import argparse
import gc
import re
import shutil
import sys
import tempfile
import tracemalloc
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import clothgap.config  # noqa: E402,F401  (registers the study config that Run.open reads)
from clothgap.files import print_json  # noqa: E402
from clothgap.runs import Run  # noqa: E402
from common import write_result  # noqa: E402  (benchmarks/common.py)


def resident_mib() -> int:
    return int(re.search(r"VmRSS:\s+(\d+)", Path("/proc/self/status").read_text()).group(1)) // 1024


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("run", type=Path)
    ap.add_argument("--setting", default="wind-uniform1")
    ap.add_argument("--variants", required=True, help="comma-separated, rendered in this order (repeats allowed)")
    ap.add_argument("--clips", type=int, default=4, help="clips rendered under each variant (default 4)")
    ap.add_argument("--flush-jit-caches", action="store_true",
                    help="after each variant, flush Dr.Jit's kernel and memory caches (dr.flush_kernel_cache, "
                         "dr.flush_malloc_cache): whether what stays resident is theirs")
    ap.add_argument("--trace-python", action="store_true",
                    help="also record the memory Python's own allocations hold (tracemalloc), to tell them from "
                         "native memory (Dr.Jit, Mitsuba, LLVM, CUDA)")
    ap.add_argument("--out", type=Path)
    args = ap.parse_args(argv)

    from render.backend import load_mitsuba
    from render.scene import MAX_POOLED_SCENES, scene_pool
    from render.stage import render_jobs
    from render.variants import get_variant

    run = Run.open(args.run)
    folder = run.sim_dir(args.setting)
    clips = [folder / c for c in run.done_clips(folder)][:args.clips]
    if not clips:
        raise SystemExit(f"render_pool_memory: no finished sim clips in {folder}")
    variants = [get_variant(name) for name in args.variants.split(",")]     # unknown names fail before any render
    if args.trace_python:
        tracemalloc.start()

    def row(after: str, pooled: int) -> dict:
        # live Python allocations, and what tracing them costs (counted in the resident memory too)
        python = ({"python_mib": round(tracemalloc.get_traced_memory()[0] / 2**20, 1),
                   "tracemalloc_mib": round(tracemalloc.get_tracemalloc_memory() / 2**20, 1)}
                  if args.trace_python else {})
        return {"after": after, "resident_mib": resident_mib(), "pooled_scenes": pooled, **python}

    rows = [row("start", 0)]           # before Mitsuba loads, so the first look's row includes it
    mi = load_mitsuba(run.config.render.backend)       # the backend render_jobs loads, so drjit imports after it
    import drjit as dr
    scratch = Path(tempfile.mkdtemp(prefix="render-pool-memory-"))
    try:
        for variant in variants:
            out = scratch / variant.name
            shutil.rmtree(out, ignore_errors=True)
            render_jobs(run, [(variant, args.setting, c, out / c.name) for c in clips], progress=False,
                        variants=[variant])
            gc.collect()                # what the look left unreferenced is freed before anything is read
            if args.flush_jit_caches:
                dr.flush_kernel_cache()
                dr.flush_malloc_cache()
            rows.append(row(variant.name, len(scene_pool(mi))))
            print(rows[-1], file=sys.stderr, flush=True)
    finally:
        shutil.rmtree(scratch, ignore_errors=True)
    result = {"run": str(args.run), "setting": args.setting, "clips": len(clips),
              "backend": run.config.render.backend, "resolution": run.config.render.resolution,
              "max_pooled_scenes": MAX_POOLED_SCENES, "flush_jit_caches": args.flush_jit_caches,
              "trace_python": args.trace_python, "rows": rows}
    if args.out:
        write_result("render_pool_memory.py", argv, result, args.out)
    else:
        print_json(result)


if __name__ == "__main__":
    main()
