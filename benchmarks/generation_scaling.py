"""Generation on every GPU of one host: sim + render through one process worker per GPU vs this process alone.

    python benchmarks/generation_scaling.py --preset paper --set sim.motions=wind --set sim.remeshing=uniform1 \
        --work /tmp/gs [--side local | --side process]

Both runs start from empty run folders of the same config under --work: the baseline
is ``--executor local`` (one process, the first GPU), the candidate ``--executor
process --gpus-per-worker G`` (one worker per G visible GPUs, pinned with
CUDA_VISIBLE_DEVICES), i.e. what ``clothgap pipeline --executor process
--gpus-per-worker 1`` does. A small warm-up run first fills the Warp and Dr.Jit
kernel caches so neither side pays for compiling. ``--side`` runs one side and
keeps its timings in ``WORK/<side>.json`` (a paper-size setting takes about five
minutes on one GPU: two calls of a 10-minute limit); the comparison is written once
both sides are there. A side whose timings exist is not run again; one cut off is
started afresh. Writes benchmarks/results/generation_scaling-<n GPUs>gpu-<preset>.json
with the command, the seconds per stage, the speed-up, the peak memory of each GPU
per side, and checks that both runs wrote the same clips (and how many of a sample
of simulations are byte-identical across the two).
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

sys.path.insert(0, str(Path(__file__).resolve().parent))
from gpu_memory import PeakGpuMemory  # noqa: E402

RESULTS = Path(__file__).resolve().parent / "results"


SIDES = ("local", "process")


def generate(root: Path, cfg, options: ExecutorOptions) -> dict:
    run = Run.create_or_resume(root, cfg)
    out = {}
    for stage in ("sim", "render"):
        t0 = time.perf_counter()
        with PeakGpuMemory() as memory:
            summary = run_stage(run, stage, options)
        out[stage] = {"seconds": round(time.perf_counter() - t0, 3), "peak_gpu_mib": memory.peak_mib,
                      "summary": summary}
    out["clips"] = {s: len(run.done_clips(run.render_dir(cfg.render.variants[0], s))) for s in cfg.sim.settings()}
    return out


def side_options(side: str, gpus_per_worker: float, workers: int | None) -> ExecutorOptions:
    if side == "local":
        return ExecutorOptions(progress=False)
    return ExecutorOptions("process", gpus_per_worker=gpus_per_worker, workers=workers, progress=False)


def run_side(work: Path, side: str, cfg, gpus_per_worker: float, workers: int | None) -> dict:
    """One side's timings, from ``WORK/<side>.json`` when that side has finished before."""
    done = work / f"{side}.json"
    if done.is_file():
        return json.loads(done.read_text())
    shutil.rmtree(work / side, ignore_errors=True)      # cut off before: its times would not be one run's
    if not (work / "warmup" / "WARM").is_file():
        shutil.rmtree(work / "warmup", ignore_errors=True)
        warm = replace(cfg, sim=replace(cfg.sim, classes=cfg.sim.class_indices()[:2], sequences_per_class=1))
        generate(work / "warmup", warm, ExecutorOptions(progress=False))
        (work / "warmup" / "WARM").touch()
    result = generate(work / side, cfg, side_options(side, gpus_per_worker, workers))
    done.write_text(json.dumps(result, indent=2, default=str) + "\n")
    return result


def identical_simulations(a: Path, b: Path, settings: list[str], sample: int = 32) -> dict:
    """How many of ``sample`` clips (evenly spaced) have byte-identical simulation files in both runs."""
    same = total = 0
    for setting in settings:
        clips = sorted(p.name for p in (a / "sim" / setting).iterdir() if (p / "DONE").is_file())
        for name in clips[:: max(1, len(clips) // sample)][:sample]:
            files = sorted(f.name for f in (a / "sim" / setting / name).iterdir() if f.suffix in (".npz", ".npy"))
            total += 1
            same += all((a / "sim" / setting / name / f).read_bytes() == (b / "sim" / setting / name / f).read_bytes()
                        for f in files)
    return {"sampled": total, "identical": same}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--preset", default="small")
    ap.add_argument("--set", dest="overrides", action="append", default=[], metavar="SECTION.KEY=VALUE")
    ap.add_argument("--gpus-per-worker", type=float, default=1.0,
                    help="GPUs per process worker; 0: CPU workers (--workers of them; a CPU check of this script)")
    ap.add_argument("--workers", type=int, default=None, help="process workers (default: one per GPU slot)")
    ap.add_argument("--side", choices=SIDES, action="append",
                    help="run only this side now (repeatable; default both); the comparison waits for both")
    ap.add_argument("--work", type=Path, default=None, help="folder for the runs (default: a temp folder)")
    ap.add_argument("--out", type=Path, default=None, help="folder for the result JSON (default benchmarks/results)")
    ap.add_argument("--keep", action="store_true", help="keep the run folders (always kept with --side)")
    args = ap.parse_args()

    cfg = apply_overrides(preset(args.preset), args.overrides)
    gpus = visible_gpus() if args.gpus_per_worker else []
    slots = gpu_slots(gpus, args.gpus_per_worker, args.workers) if args.gpus_per_worker else [""] * (args.workers or 2)
    workers = args.workers or (None if args.gpus_per_worker else len(slots))
    if args.side and args.work is None:
        ap.error("--side needs --work: the other side's timings are kept there")
    work = args.work or Path(tempfile.mkdtemp(prefix="generation_scaling-"))
    work.mkdir(parents=True, exist_ok=True)
    results = {}
    for side in args.side or SIDES:
        print(f"[generation_scaling] {side} ...", flush=True)
        results[side] = run_side(work, side, cfg, args.gpus_per_worker, workers)
        print(f"[generation_scaling] {side}: " + ", ".join(f"{s} {results[side][s]['seconds']} s"
                                                           for s in ("sim", "render")), flush=True)
    for side in SIDES:
        if side not in results and (work / f"{side}.json").is_file():
            results[side] = json.loads((work / f"{side}.json").read_text())
    if len(results) < len(SIDES):
        print(f"[generation_scaling] waiting for the other side (--side {set(SIDES) - set(results)})")
        return
    baseline, candidate = results["local"], results["process"]
    if candidate["clips"] != baseline["clips"]:
        raise SystemExit(f"the two runs wrote different clips: {candidate['clips']} vs {baseline['clips']}")
    same = identical_simulations(work / "local", work / "process", cfg.sim.settings())
    if not (args.keep or args.side):
        shutil.rmtree(work, ignore_errors=True)
    total = {k: sum(r[s]["seconds"] for s in ("sim", "render")) for k, r in (("local", baseline),
                                                                                ("process", candidate))}
    result = {
        "command": " ".join(["python benchmarks/generation_scaling.py", *sys.argv[1:]]),
        "host": platform.node(), "gpus": gpus, "workers": len(slots), "gpus_per_worker": args.gpus_per_worker,
        "preset": args.preset, "overrides": args.overrides, "clips_per_setting": cfg.sim.num_clips(),
        "settings": cfg.sim.settings(), "variants": list(cfg.render.variants),
        "baseline": {"name": "local (one process, one GPU)", **baseline},
        "candidate": {"name": f"process x{len(slots)} (one worker per {args.gpus_per_worker:g} GPU)"
                      if args.gpus_per_worker else f"process x{len(slots)} (CPU workers)", **candidate},
        "simulations_byte_identical": same,
        "speedup": {s: round(baseline[s]["seconds"] / max(candidate[s]["seconds"], 1e-9), 2) for s in ("sim", "render")}
        | {"total": round(total["local"] / max(total["process"], 1e-9), 2)},
    }
    out = RESULTS if args.out is None else args.out
    out.mkdir(parents=True, exist_ok=True)
    path = out / f"generation_scaling-{len(gpus)}gpu-{args.preset}.json"
    path.write_text(json.dumps(result, indent=2, default=str) + "\n")
    print(json.dumps(result["speedup"]), json.dumps(same), f"-> {path}")


if __name__ == "__main__":
    main()
