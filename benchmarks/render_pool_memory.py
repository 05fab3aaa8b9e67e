"""A render process's memory as it renders one dataset after another: its resident set and its pooled scenes.

    python benchmarks/render_pool_memory.py RUN --setting wind-uniform1 \\
        --variants paper,grid,color,lighting-random,heldout,daylight,paper,grid --out pool.json

Renders the setting's finished sim clips of RUN under each variant in turn, in this one process and the run's
render settings, into a scratch folder (not the run's), and after each variant records the process's resident
memory (VmRSS, after a garbage collection) and how many scenes ``render.scene``'s pool keeps alive (at most
``MAX_POOLED_SCENES`` structures a process, least recently used dropped). ``--one-call`` renders every look in one
call of the stage's loop, as a render worker does (its readings after each clip, no collection in between).
``--keep-looks`` turns off the stage's release of a finished look (``render.stage.release_look``): the baseline
of what it saves. Why a render worker's memory rises over a study's datasets (issue 14: host memory across
settings).
"""

from __future__ import annotations

import argparse
import gc
import shutil
import sys
import tempfile
import time
import tracemalloc
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import clothgap.config  # noqa: E402,F401  (registers the study config that Run.open reads)
from clothgap.runs import Run, is_done  # noqa: E402
from common import process_memory_mib, write_result  # noqa: E402  (benchmarks/common.py)


class ReadJobs(list):
    """The stage's job list, read after each clip with ``reading(job)``: a clip is read when the stage's loop asks
    for the next job (or finishes) and its folder is DONE, so the stage's passes over the list before it renders
    take no reading, and a failed clip none either."""

    def __init__(self, jobs, reading):
        super().__init__(jobs)
        self.reading, self.readings, self._read = reading, [], set()

    def __iter__(self):
        for k, job in enumerate(list.__iter__(self)):
            yield job
            if is_done(job[3]) and k not in self._read:
                self._read.add(k)
                self.readings.append({"after_job": k + 1, **self.reading(job)})


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
    ap.add_argument("--one-call", action="store_true",
                    help="every look in one render_jobs call, as a stage worker renders its shard, with a reading "
                         "after each clip")
    ap.add_argument("--keep-looks", action="store_true",
                    help="do not release a finished look's scenes and kernels (render.stage.RELEASE_LOOKS off): "
                         "the baseline")
    ap.add_argument("--out", type=Path)
    args = ap.parse_args(argv)

    from render.backend import load_mitsuba
    from render.scene import MAX_POOLED_SCENES, scene_pool
    import render.stage
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
        return {"after": after, "resident_mib": process_memory_mib()["resident_mib"], "pooled_scenes": pooled, **python}

    rows = [row("start", 0)]           # before Mitsuba loads, so the first look's row includes it
    mi = load_mitsuba(run.config.render.backend)       # the backend render_jobs loads, so drjit imports after it
    import drjit as dr
    render.stage.RELEASE_LOOKS = not args.keep_looks
    scratch = Path(tempfile.mkdtemp(prefix="render-pool-memory-"))
    try:
        if args.one_call:
            # a look named twice is rendered twice, into folders of its own
            start = time.perf_counter()
            jobs = ReadJobs(((variant, args.setting, c, scratch / f"{k}-{variant.name}" / c.name)
                             for k, variant in enumerate(variants) for c in clips),
                            lambda job: {"look": job[0].name, "resident_mib": process_memory_mib()["resident_mib"],
                                         "pooled_scenes": len(scene_pool(mi)),
                                         "seconds": round(time.perf_counter() - start, 2)})
            summary = render_jobs(run, jobs, progress=False, variants=variants)
            gc.collect()
            clip_rows = jobs.readings
            rows += [{"after": r["look"], "resident_mib": r["resident_mib"], "pooled_scenes": r["pooled_scenes"]}
                     for r in clip_rows if r["after_job"] % len(clips) == 0]      # each look's last clip
            rows.append(row("call returned", len(scene_pool(mi))))
        else:
            clip_rows = summary = None
            for variant in variants:
                out = scratch / variant.name
                shutil.rmtree(out, ignore_errors=True)
                render_jobs(run, [(variant, args.setting, c, out / c.name) for c in clips], progress=False,
                            variants=[variant])
                gc.collect()            # what the look left unreferenced is freed before anything is read
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
              "trace_python": args.trace_python, "one_call": args.one_call,
              "release_looks": not args.keep_looks, "rows": rows,
              **({"render_seconds": summary["seconds"], "frames": summary["frames"], "failed": summary["failed"],
                  "clip_readings": clip_rows} if clip_rows is not None else {})}
    write_result("render_pool_memory.py", argv, result, args.out)


if __name__ == "__main__":
    main()
