"""The study's cost in one script: each stage against its baseline, and how cost grows with the study's size.

    python benchmarks/study.py --preset paper --sizes 4,16,48 --render-args "--executor process --workers 4 --gpus-per-worker 0.25" \
        --train-args "--parallel 8"
    python benchmarks/study.py --preset smoke --sizes 4 --quick            # a CPU check of the script itself

Two parts, in one run on one machine:

* ``baselines``: the three stage benchmarks, each timing the project's path against a
  named baseline in the same process (``sim_throughput.py``: one batch vs one clip at a
  time; ``render_throughput.py`` at 112 px: pooled + frozen scenes vs a scene per clip, and the stage
  writing frames.npy, each as a ratio to the path tracer's ceiling;
  ``train_throughput.py``: bf16 + compile + channels-last vs eager fp32); their JSON is
  embedded whole.
* ``scaling``: for each size in ``--sizes`` (sequences per class; 48 is the paper's
  2,592 per setting), a fresh run of ``--preset`` through the real CLI, stage by stage
  (sim, render, train, eval), with wall time, clips and frames, peak host memory of the
  stage's process tree and peak GPU memory (nvidia-smi) sampled while it runs, and the
  end-to-end time per setting. The table shows how each stage's cost grows with the
  number of clips.

Writes ``benchmarks/results/study-<device>-<time>.json`` and a Markdown table beside it.

A study too long for one call (the device's calls last at most 10 minutes) is measured by
``scripts/gpu/paper_study.sh`` stage by stage across resumable calls, each call's stage a line of
``RUN/gpu_timings.jsonl``; ``--timings RUN`` sums those per stage (calls, seconds, whether it finished, peak GPU
memory, peak host memory over the stage's start, GPU utilisation weighted by time) into the same kind of file:

    python benchmarks/study.py --timings /tmp/study --out benchmarks/results/study-h100x4.json
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shlex
import shutil
import subprocess
import sys
import tempfile
import threading
import time
from datetime import datetime, timezone
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
RESULTS = ROOT / "benchmarks" / "results"
STAGES = ("sim", "render", "train", "eval")


def gpu_used_mib() -> float | None:
    if shutil.which("nvidia-smi") is None:
        return None
    out = subprocess.run(["nvidia-smi", "--query-gpu=memory.used", "--format=csv,noheader,nounits"],
                         capture_output=True, text=True, check=False).stdout.split()
    return sum(float(x) for x in out) if out else None


def tree_rss_mib(pid: int) -> float:
    """Resident memory of a process and all its descendants (Linux /proc)."""
    children: dict[int, list[int]] = {}
    for entry in os.listdir("/proc"):
        if entry.isdigit():
            try:
                with open(f"/proc/{entry}/stat") as f:
                    ppid = int(f.read().rsplit(")", 1)[1].split()[1])
                children.setdefault(ppid, []).append(int(entry))
            except (OSError, ValueError, IndexError):
                continue
    total, todo = 0, [pid]
    while todo:
        p = todo.pop()
        todo += children.get(p, [])
        try:
            with open(f"/proc/{p}/statm") as f:
                total += int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")
        except OSError:
            continue
    return total / 2 ** 20


def run_measured(cmd: list[str], period: float = 0.5) -> dict:
    """Run ``cmd``; wall seconds, return code, peak host RSS of its process tree, peak GPU memory."""
    start = time.perf_counter()
    proc = subprocess.Popen(cmd, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                            env={**os.environ, "PYTHONUNBUFFERED": "1"})
    peaks = {"host": 0.0, "gpu": None}
    done = threading.Event()

    def sample() -> None:
        while not done.is_set():
            peaks["host"] = max(peaks["host"], tree_rss_mib(proc.pid))
            gpu = gpu_used_mib()
            if gpu is not None:
                peaks["gpu"] = max(peaks["gpu"] or 0.0, gpu)
            done.wait(period)

    sampler = threading.Thread(target=sample, daemon=True)
    sampler.start()
    output = proc.communicate()[0]
    done.set()
    sampler.join()
    return {"seconds": round(time.perf_counter() - start, 2), "rc": proc.returncode,
            "peak_host_rss_mib": round(peaks["host"], 1),
            "peak_gpu_used_mib": None if peaks["gpu"] is None else round(peaks["gpu"], 1),
            "tail": output.strip().splitlines()[-3:]}


def baselines(args, device: str, work: Path) -> dict:
    py = sys.executable
    quick = args.quick
    out: dict = {}
    sim_json = work / "sim.json"
    sim = [py, "benchmarks/sim_throughput.py", "--device", device, "--n", "16" if quick else "2592",
           "--baseline", "2" if quick else "8", "--frames", "10" if quick else "40", "--out", str(sim_json)]
    r = run_measured(sim)
    out["sim"] = {"command": shlex.join(sim[1:]), **r,
                  "result": json.loads(sim_json.read_text()) if sim_json.is_file() else None}
    render_json = work / "render.json"
    render = [py, "benchmarks/render_throughput.py", "--device", "cuda" if device.startswith("cuda") else "cpu",
              "--resolution", "32" if quick else "112", "--spp", "2" if quick else "16", "--clips", "3" if quick else "24",
              "--frames", "4" if quick else "40", "--procs", "" if quick else "4", "--procs-freeze",
              "--write", "--outputs", "npy", "--write-procs", "" if quick else "4", "--out", str(render_json)]
    r = run_measured(render)
    out["render"] = {"command": shlex.join(render[1:]), **r,
                     "result": json.loads(render_json.read_text()) if render_json.is_file() else None}
    train_json = work / "train.json"
    train = [py, "benchmarks/train_throughput.py", "--device", device, "--out", str(train_json)]
    if quick:
        train += ["--image-size", "32", "--width", "8", "--fc6", "32", "--hidden", "16", "--batch-size", "4",
                  "--steps", "3", "--warmup", "1"]
    r = run_measured(train)
    out["train"] = {"command": shlex.join(train[1:]), **r,
                    "result": json.loads(train_json.read_text()) if train_json.is_file() else None}
    return out


def scaling(args, work: Path) -> list[dict]:
    rows = []
    for size in args.sizes:
        run_dir = work / f"size{size}"
        overrides = [f"sim.sequences_per_class={size}", *args.overrides]
        sets = [x for o in overrides for x in ("--set", o)]
        row: dict = {"sequences_per_class": size, "stages": {}}
        for stage in STAGES:
            if stage == "sim":
                cmd = [sys.executable, "-m", "clothgap", "sim", "--preset", args.preset, "--out", str(run_dir), *sets]
            else:
                cmd = [sys.executable, "-m", "clothgap", stage, str(run_dir)]
                if stage == "render":
                    cmd += shlex.split(args.render_args)
                if stage == "train":
                    cmd += shlex.split(args.train_args)
            row["stages"][stage] = run_measured(cmd)
            print(f"size {size} {stage}: {row['stages'][stage]['seconds']} s "
                  f"(rc {row['stages'][stage]['rc']})", flush=True)
            if row["stages"][stage]["rc"]:
                break
        config = json.loads((run_dir / "config.json").read_text()) if (run_dir / "config.json").is_file() else {}
        settings = [f"{m}-{r}" for m in config.get("sim", {}).get("motions", []) for r in config.get("sim", {}).get("remeshing", [])]
        classes = len(config.get("sim", {}).get("classes") or range(54))
        row["settings"] = settings
        row["clips_per_setting"] = classes * size
        row["frames_per_clip"] = config.get("sim", {}).get("frames")
        total = sum(s["seconds"] for s in row["stages"].values())
        row["total_seconds"] = round(total, 2)
        row["seconds_per_setting"] = round(total / max(1, len(settings)), 2)
        rows.append(row)
        if not args.keep:
            shutil.rmtree(run_dir, ignore_errors=True)
    return rows


TIMED_STAGES = (*STAGES, "report")


def study_datasets(config: dict) -> list[str]:
    """The (variant:setting) datasets of a run's config.json: every variant on every setting, except a variant
    named in ``render.variant_settings``, which renders only the settings it is paired with there."""
    settings = [f"{m}-{r}" for m in config["sim"]["motions"] for r in config["sim"]["remeshing"]]
    pairs: dict[str, list[str]] = {}
    for pair in config["render"].get("variant_settings") or []:
        variant, setting = pair.split(":", 1)
        pairs.setdefault(variant, []).append(setting)
    return [f"{v}:{s}" for v in config["render"]["variants"] for s in pairs.get(v, settings)]


def from_timings(run: Path) -> dict:
    """A study measured in resumable calls: ``RUN/gpu_timings.jsonl`` summed per stage (see the module's doc)."""
    path = run / "gpu_timings.jsonl"
    if not path.is_file():
        raise SystemExit(f"error: {path} does not exist: --timings takes a run folder that "
                         "scripts/gpu/paper_study.sh measured")
    calls = [json.loads(line) for line in path.read_text().splitlines() if line.strip()]
    config = json.loads((run / "config.json").read_text())
    stages = {}
    for name in TIMED_STAGES:
        mine = [c for c in calls if c["stage"] == name]
        if not mine:
            continue
        seconds = sum(c["seconds"] for c in mine)
        utils = [(c["mean_gpu_util_pct"], c["seconds"]) for c in mine if c.get("mean_gpu_util_pct") is not None]
        stages[name] = {
            "calls": len(mine), "seconds": round(seconds, 1), "finished": mine[-1]["rc"] == 0,
            "peak_gpu_mib": max(c.get("peak_gpu_mib") or 0 for c in mine),
            "peak_host_mib_over_start": max((c.get("peak_host_mib_over_start") or 0) for c in mine),
            "mean_gpu_util_pct": round(sum(u * t for u, t in utils) / sum(t for _, t in utils), 1)
            if utils and sum(t for _, t in utils) > 0 else None}
    finished = all(stages.get(s, {}).get("finished") for s in TIMED_STAGES)
    return {"run": str(run), "preset": config.get("name"), "sequences_per_class": config["sim"]["sequences_per_class"],
            "datasets": study_datasets(config), "stages": stages,
            "stage_seconds": round(sum(st["seconds"] for st in stages.values()), 1),
            "finished": finished, "unfinished": [s for s in TIMED_STAGES if not stages.get(s, {}).get("finished")]}


def timings_markdown(report: dict) -> str:
    t = report["timings"]
    lines = [f"# Study cost, measured across calls ({report['time']})", "", f"`{report['command']}`", "",
             f"Preset `{t['preset']}`, {len(t['datasets'])} datasets, {t['sequences_per_class']} sequences a class; "
             f"stage time {t['stage_seconds']} s, " + ("every stage finished." if t["finished"] else
                                                        f"unfinished: {', '.join(t['unfinished'])}."), "",
             "| stage | calls | seconds | finished | peak GPU MiB | peak host MiB over its start | mean GPU util % |",
             "| --- | --- | --- | --- | --- | --- | --- |"]
    for name, st in t["stages"].items():
        lines.append(f"| {name} | {st['calls']} | {st['seconds']} | {'yes' if st['finished'] else 'no'} | "
                     f"{st['peak_gpu_mib']} | {st['peak_host_mib_over_start']} | "
                     f"{'-' if st['mean_gpu_util_pct'] is None else st['mean_gpu_util_pct']} |")
    return "\n".join(lines) + "\n"


def _cell(stage: dict | None) -> str:
    if stage is None:
        return "-"
    return str(stage["seconds"]) + ("" if stage["rc"] == 0 else f" (rc {stage['rc']})")


def markdown(report: dict) -> str:
    lines = [f"# Study cost on {report['device']} ({report['time']})", "", f"`{report['command']}`", "",
             "| sequences/class | clips/setting | settings | " + " | ".join(f"{s} s" for s in STAGES)
             + " | total s | s/setting | peak host MiB | peak GPU MiB |", "|" + " --- |" * (3 + len(STAGES) + 4)]
    for row in report["scaling"]:
        st = row["stages"]
        host = max((s["peak_host_rss_mib"] for s in st.values()), default=0)
        gpus = [s["peak_gpu_used_mib"] for s in st.values() if s["peak_gpu_used_mib"] is not None]
        lines.append(f"| {row['sequences_per_class']} | {row['clips_per_setting']} | {len(row['settings'])} | "
                     + " | ".join(_cell(st.get(s)) for s in STAGES)
                     + f" | {row['total_seconds']} | {row['seconds_per_setting']} | {host} | {max(gpus) if gpus else '-'} |")
    b = report.get("baselines") or {}
    if b:
        lines += ["", "| stage | baseline | ours | speed-up |", "| --- | --- | --- | --- |"]
        sim = (b.get("sim") or {}).get("result") or {}
        if sim:
            lines.append(f"| sim | one clip at a time: {sim['one_at_a_time']['sequences_per_s']:.2f} seq/s | "
                         f"batched: {sim['batched']['sequences_per_s']:.2f} seq/s | {sim['speedup']:.2f}x |")
        render = (b.get("render") or {}).get("result") or {}
        for rnd in render.get("rounds", []):
            rows = rnd["render_only"]
            best = max(rows, key=lambda k: rows[k]["frames_per_s"])
            lines.append(f"| render {render['settings']['resolution']} px {rnd['spp']} spp | scene per clip: "
                         f"{rows['scene_per_clip']['frames_per_s']} frames/s | {best}: {rows[best]['frames_per_s']} "
                         f"frames/s ({rows[best].get('ceiling_ratio')} of the ceiling) | {rows[best]['speedup']}x |")
            for name, row in (rnd.get("with_output") or {}).items():
                if "frames_per_s" in row:
                    lines.append(f"| render stage, {name} | | {row['frames_per_s']} frames/s "
                                 f"({row.get('ceiling_ratio')} of the ceiling) | |")
        train = (b.get("train") or {}).get("result") or {}
        if train:
            loops = train["loops"]
            fast = [k for k in loops if k != "eager_fp32"][0]
            lines.append(f"| train | eager fp32: {loops['eager_fp32']['clips_per_s']} clips/s | {fast}: "
                         f"{loops[fast]['clips_per_s']} clips/s | {train['speedup']}x |")
    return "\n".join(lines) + "\n"


def write_report(report: dict, out: Path, table: str) -> None:
    """The report as JSON at ``out`` and its Markdown table beside it, shown and said where."""
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(report, indent=2) + "\n")
    out.with_suffix(".md").write_text(table)
    print(table)
    print(f"wrote {out}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--preset", default="paper")
    ap.add_argument("--sizes", default="4,16,48", help="comma-separated sequences per class, one run each "
                    "(at least 4: with fewer, a split by sequence leaves no test clip and eval stops)")
    ap.add_argument("--set", dest="overrides", action="append", default=[], metavar="SECTION.KEY=VALUE")
    ap.add_argument("--render-args", default="", help="executor options for `clothgap render`, e.g. "
                    "\"--executor process --workers 4 --gpus-per-worker 0.25\"")
    ap.add_argument("--train-args", default="", help="options for `clothgap train`, e.g. \"--parallel 8\"")
    ap.add_argument("--device", default="auto", help="device of the stage benchmarks: cpu, cuda (auto: cuda if seen)")
    ap.add_argument("--skip-baselines", action="store_true")
    ap.add_argument("--quick", action="store_true", help="tiny baselines (a CPU check of the script)")
    ap.add_argument("--keep", action="store_true", help="keep the run folders (under --work)")
    ap.add_argument("--work", type=Path, help="folder for the runs (default: a temporary folder)")
    ap.add_argument("--out", type=Path, help="JSON path (default: benchmarks/results/study-<device>-<time>.json)")
    ap.add_argument("--timings", type=Path, metavar="RUN", help="summarise RUN/gpu_timings.jsonl (a study measured "
                    "by scripts/gpu/paper_study.sh across calls) instead of running anything")
    args = ap.parse_args()
    if args.timings is not None:
        report = {"command": shlex.join([Path(sys.executable).name, *sys.argv]),
                  "time": datetime.now(timezone.utc).isoformat(timespec="seconds"),
                  "timings": from_timings(args.timings)}
        stamp = datetime.now(timezone.utc).strftime("%Y%m%dT%H%M%S")
        write_report(report, args.out or RESULTS / f"study-timings-{stamp}.json", timings_markdown(report))
        return
    args.sizes = [int(s) for s in args.sizes.split(",") if s]
    device = args.device if args.device != "auto" else ("cuda" if gpu_used_mib() is not None else "cpu")
    work = args.work or Path(tempfile.mkdtemp(prefix="clothgap-study-"))
    work.mkdir(parents=True, exist_ok=True)
    report = {"command": shlex.join([Path(sys.executable).name, *sys.argv]),
              "time": datetime.now(timezone.utc).isoformat(timespec="seconds"),
              "device": device, "machine": platform.node(), "platform": platform.platform(),
              "gpu_memory_before_mib": gpu_used_mib()}
    if not args.skip_baselines:
        report["baselines"] = baselines(args, device, work)
    report["scaling"] = scaling(args, work)
    stamp = datetime.now(timezone.utc).strftime("%Y%m%dT%H%M%S")
    write_report(report, args.out or RESULTS / f"study-{device.replace(':', '')}-{stamp}.json", markdown(report))
    if args.work is None and not args.keep:
        shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()
