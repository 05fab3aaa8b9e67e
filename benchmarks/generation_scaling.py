"""Generation on every GPU of one host: sim + render through one process worker per GPU vs this process alone.

    python benchmarks/generation_scaling.py --preset small [--set sim.device=cuda ...] [--gpus-per-worker 1]

Both runs start from empty run folders of the same config (under --work, removed
afterwards unless --keep): the baseline is ``--executor local`` (one process, the
first GPU), the candidate ``--executor process --gpus-per-worker G`` (one worker
per G visible GPUs, pinned with CUDA_VISIBLE_DEVICES), i.e. what
``clothgap pipeline --executor process --gpus-per-worker 1`` does. A small warm-up
run first fills the Warp and Dr.Jit kernel caches so neither side pays for
compiling. Writes benchmarks/results/generation_scaling-<n GPUs>gpu-<preset>.json
with the command, the seconds per stage and the speed-up; checks that both runs
wrote the same clips.
"""

from __future__ import annotations

import argparse
import json
import platform
import shutil
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

from clothgap.config import apply_overrides, preset
from clothgap.executor import ExecutorOptions, gpu_slots, run_stage, visible_gpus
from clothgap.runs import Run

RESULTS = Path(__file__).resolve().parent / "results"


def generate(root: Path, cfg, options: ExecutorOptions) -> dict:
    run = Run.create_or_resume(root, cfg)
    out = {}
    for stage in ("sim", "render"):
        t0 = time.perf_counter()
        summary = run_stage(run, stage, options)
        out[stage] = {"seconds": round(time.perf_counter() - t0, 3), "summary": summary}
    out["clips"] = {s: len(run.done_clips(run.render_dir(cfg.render.variants[0], s))) for s in cfg.sim.settings()}
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--preset", default="small")
    ap.add_argument("--set", dest="overrides", action="append", default=[], metavar="SECTION.KEY=VALUE")
    ap.add_argument("--gpus-per-worker", type=float, default=1.0)
    ap.add_argument("--work", type=Path, default=None, help="folder for the two runs (default: a temp folder)")
    ap.add_argument("--keep", action="store_true", help="keep the run folders")
    args = ap.parse_args()

    cfg = apply_overrides(preset(args.preset), args.overrides)
    gpus = visible_gpus()
    slots = gpu_slots(gpus, args.gpus_per_worker)
    work = args.work or Path(tempfile.mkdtemp(prefix="generation_scaling-"))
    try:
        warm = replace(cfg, sim=replace(cfg.sim, classes=cfg.sim.class_indices()[:2], sequences_per_class=1))
        generate(work / "warmup", warm, ExecutorOptions(progress=False))
        baseline = generate(work / "local", cfg, ExecutorOptions(progress=False))
        candidate = generate(work / "process", cfg, ExecutorOptions("process", gpus_per_worker=args.gpus_per_worker,
                                                                     progress=False))
    finally:
        if not args.keep:
            shutil.rmtree(work, ignore_errors=True)
    assert candidate["clips"] == baseline["clips"], (candidate["clips"], baseline["clips"])
    total = {k: sum(r[s]["seconds"] for s in ("sim", "render")) for k, r in (("local", baseline),
                                                                                ("process", candidate))}
    result = {
        "command": " ".join([Path(sys.argv[0]).name, *sys.argv[1:]]),
        "host": platform.node(), "gpus": gpus, "workers": len(slots), "gpus_per_worker": args.gpus_per_worker,
        "preset": args.preset, "overrides": args.overrides, "clips_per_setting": cfg.sim.num_clips(),
        "settings": cfg.sim.settings(), "variants": list(cfg.render.variants),
        "baseline": {"name": "local (one process, one GPU)", **baseline},
        "candidate": {"name": f"process x{len(slots)} (one worker per {args.gpus_per_worker:g} GPU)", **candidate},
        "speedup": {s: round(baseline[s]["seconds"] / max(candidate[s]["seconds"], 1e-9), 2) for s in ("sim", "render")}
        | {"total": round(total["local"] / max(total["process"], 1e-9), 2)},
    }
    RESULTS.mkdir(parents=True, exist_ok=True)
    path = RESULTS / f"generation_scaling-{len(gpus)}gpu-{args.preset}.json"
    path.write_text(json.dumps(result, indent=2, default=str) + "\n")
    print(json.dumps(result["speedup"]), f"-> {path}")


if __name__ == "__main__":
    main()
