"""`clothgap eval` with every prediction reused, at a domain-gap study's size: the host's share of the stage.

    python benchmarks/eval_aggregation.py [--baseline REV] [--classes 54] [--sequences 4] [--variants 9]
                                          [--resamples 1000] [--out FILE]

Builds a run on disk with nothing simulated, rendered or trained: per test clip a meta.json and DONE
under every render variant, per model a stub checkpoint and DONE, a split whose test part is every clip
(``classes`` x ``sequences`` sequences, one sub-sequence each as in the paper preset), and one prediction
CSV per (training variant, test variant) from a seeded stand-in predictor. The training variants are the
first ``variants`` of a domain-gap study's list; ``heldout`` is rendered for testing only. Then times, on
that run:

* ``eval``: ``eval.stage.run_eval`` with every prediction reused (what a second `clothgap eval` costs on
  the host: reading the predictions, results.csv, table3, domain_gap.csv with its paired bootstrap
  differences and correlations, axis_ranking.csv, a confusion figure per cell, the gap figure, summary.json);
* ``load`` and ``tables``: its parts ``predict_all`` (reading the predictions) and ``_write_tables``;
* ``measured_tables``: the measured-fabric tables (``eval.measured``: fabric, correlation and match tables)
  of one model per training variant, 10 fabrics x 4 clips, as `clothgap eval` rebuilds them each time.

With ``--baseline REV`` the same run is timed, in the same invocation, with the code of git revision REV
(``git archive``) and with the working tree, one after the other on the same folder, and every file the
two write under eval/ (csv, md, json, png) is compared byte for byte. Writes JSON (default
benchmarks/results/eval_aggregation-<host>.json) with the command that made it.
"""

from __future__ import annotations

import argparse
import importlib
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
if "--worker" not in sys.argv:      # a worker imports the code its PYTHONPATH names (a baseline's, or this tree)
    sys.path.insert(0, str(ROOT))
STUDY_VARIANTS = ("paper", "grid", "diffuse", "fabric-table", "lighting-random", "room", "filmic", "camera-noise",
                  "motion-blur")
TEST_ONLY = "heldout"
MEASURED_CLIPS = 4


def build_run(root: Path, classes: int, sequences: int, variants: list[str], resamples: int):
    """The stand-in run and its predictions (``predict_all`` with a seeded stand-in predictor)."""
    import numpy as np
    import pandas as pd

    from clothgap.config import preset
    from clothgap.runs import Run, clip_id, clip_index, mark_done
    from eval.stage import predict_all
    from eval.trained import finished_models
    from render.variants import get_variant

    cfg = preset("paper")
    cfg = replace(cfg, sim=replace(cfg.sim, motions=("wind",), remeshing=("uniform1",),
                                   classes=tuple(range(classes)), sequences_per_class=sequences),
                  render=replace(cfg.render, variants=tuple(variants)),
                  train=replace(cfg.train, models=("lrcn",), seeds=(0,)),
                  eval=replace(cfg.eval, bootstrap=resamples, measured_sequences=0, sim_analysis=()))
    run = Run.create_or_resume(root, cfg)
    setting = cfg.sim.settings()[0]
    ids = [clip_id(i) for i in range(classes * sequences)]
    for variant in [*variants, TEST_ONLY]:
        render = get_variant(variant).settings()
        for i, cid in enumerate(ids):
            folder = run.render_dir(variant, setting) / cid
            folder.mkdir(parents=True)
            (folder / "meta.json").write_text(json.dumps({"clip_id": cid, "index": i, "setting": setting,
                                                          "class_index": i // sequences, "variant": variant,
                                                          "render": render}))
            mark_done(folder)
    run.split_path(setting).parent.mkdir(parents=True, exist_ok=True)
    run.split_path(setting).write_text(json.dumps({"by": "sequence", "seed": 0, "train": [], "val": [],
                                                   "test": ids}))
    for variant in variants:
        folder = run.train_dir(setting, variant, "lrcn", 0)
        folder.mkdir(parents=True)
        (folder / "checkpoint.pt").write_bytes(variant.encode())
        mark_done(folder)

    def predictor(train_dir: Path, clip_dirs: list[Path]) -> pd.DataFrame:
        train_variant, test_variant = train_dir.parts[-3], clip_dirs[0].parts[-3]
        rng = np.random.default_rng([len(train_variant), sum(map(ord, train_variant + "/" + test_variant))])
        truth = np.array([clip_index(d.name) // sequences for d in clip_dirs])
        hit = rng.random(len(truth)) < (0.6 if train_variant == test_variant else 0.35)
        pred = np.where(hit, truth, rng.integers(0, classes, len(truth)))
        logits = rng.standard_normal((len(truth), 54))
        logits[np.arange(len(truth)), pred] += 3.0
        probs = np.exp(logits) / np.exp(logits).sum(axis=1, keepdims=True)
        return pd.DataFrame({"clip_id": [d.name for d in clip_dirs], "start": 0, "class_index": truth,
                             "pred": probs.argmax(axis=1), "probs": list(probs)})

    predict_all(run, finished_models(run), predictor, progress=False)
    return run


def measured_videos():
    """A measured-fabric set's per-clip predictions: 10 fabrics x ``MEASURED_CLIPS`` clips, seeded."""
    import numpy as np
    import pandas as pd

    from eval import predictions as preds
    from sim.measured import measured_values, table2_fabrics

    rng = np.random.default_rng(1)
    rows = []
    for fabric in table2_fabrics():
        values = measured_values(fabric)
        for n in range(MEASURED_CLIPS):
            probs = rng.dirichlet(np.full(54, 0.3))
            rows.append({"video": f"{fabric}-{n}", "fabric": fabric, "pred": int(probs.argmax()),
                         **dict(zip(preds.PROB_COLUMNS, probs)),
                         **{k: values[k] for k in ("stretching_N_m", "bending_N_m", "density_kg_m2")}})
    return pd.DataFrame(rows)


def time_side(root: Path, variants: list[str], resamples: int) -> dict:
    """This interpreter's eval code on the run at ``root``: seconds of each part (the worker's job)."""
    from clothgap import seeding
    from clothgap.runs import Run
    from eval import measured
    from eval.stage import _write_tables, predict_all, run_eval
    from eval.trained import finished_models

    def refuse(train_dir, clip_dirs):
        raise RuntimeError(f"{train_dir} on {clip_dirs[0].parent}: every prediction should be reused")

    run = Run.open(root)
    out = {}
    t0 = time.perf_counter()
    short = run_eval(run, progress=False, predictor=refuse)
    out["eval"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    cells = predict_all(run, finished_models(run), refuse, progress=False)[0]
    out["load"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    _write_tables(run, cells)
    out["tables"] = time.perf_counter() - t0

    videos = measured_videos()
    folder = run.eval_dir / "benchmark_measured"
    folder.mkdir(exist_ok=True)
    t0 = time.perf_counter()
    for variant in variants:
        def rng_for(*parts, variant=variant):
            return seeding.rng(0, 0, seeding.EVAL, "bootstrap", "measured", variant, *parts)

        opts = {"resamples": resamples, "confidence": 0.95, "rng_for": rng_for}
        table = measured.fabric_table(videos)
        corr = measured.correlation_table(videos, table, **opts)
        match = measured.match_table(table, **opts)
        for name, frame in (("fabrics", table), ("correlations", corr), ("match", match)):
            (folder / f"{variant}-{name}.csv").write_text(frame.to_csv(index=False, float_format="%.6g"))
    out["measured_tables"] = time.perf_counter() - t0
    out = {k: round(v, 2) for k, v in out.items()}
    out["cells"], out["reused"] = short["cells"], short["reused"]
    return out


def run_side(code: Path, root: Path, variants: list[str], resamples: int) -> dict:
    """``time_side`` in a fresh interpreter importing the code under ``code``."""
    env = {**os.environ, "PYTHONPATH": str(code)}
    done = subprocess.run([sys.executable, str(Path(__file__).resolve()), "--worker", str(root),
                           "--variants-list", ",".join(variants), "--resamples", str(resamples)],
                          capture_output=True, text=True, env=env, cwd=code)
    if done.returncode != 0:
        sys.exit(f"the worker on {code} failed:\n{done.stdout[-2000:]}\n{done.stderr[-4000:]}")
    return json.loads(done.stdout.strip().splitlines()[-1])


def compare(a: Path, b: Path) -> dict:
    """Files under two eval/ folders (predictions aside): how many are the same bytes, and which are not."""
    def files(root: Path) -> set[str]:
        return {str(p.relative_to(root)) for p in root.rglob("*") if p.is_file()
                and p.relative_to(root).parts[0] != "predictions"}

    fa, fb = files(a), files(b)
    differ = sorted(f for f in fa & fb if (a / f).read_bytes() != (b / f).read_bytes())
    return {"files": len(fa & fb), "identical": len(fa & fb) - len(differ), "differ": differ,
            "only_baseline": sorted(fa - fb), "only_current": sorted(fb - fa)}


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--classes", type=int, default=54)
    ap.add_argument("--sequences", type=int, default=4, help="test sequences per class")
    ap.add_argument("--variants", type=int, default=9, help="training variants (each also a test variant)")
    ap.add_argument("--resamples", type=int, default=1000)
    ap.add_argument("--baseline", metavar="REV", help="also time git revision REV's code on the same run")
    ap.add_argument("--keep", type=Path, help="build the run here and keep it (default: a temporary folder)")
    ap.add_argument("--out", type=Path)
    ap.add_argument("--worker", type=Path, help=argparse.SUPPRESS)
    ap.add_argument("--variants-list", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.worker:
        importlib.import_module("clothgap.config")      # registers the study config that Run.open reads
        print(json.dumps(time_side(args.worker, args.variants_list.split(","), args.resamples)))
        return
    if not 1 <= args.variants <= len(STUDY_VARIANTS):
        ap.error(f"--variants must be 1..{len(STUDY_VARIANTS)}")
    variants = list(STUDY_VARIANTS[: args.variants])
    work = Path(tempfile.mkdtemp(prefix="eval-aggregation-")) if args.keep is None else args.keep
    root, pristine = work / "run", work / "pristine"
    t0 = time.perf_counter()
    build_run(root, args.classes, args.sequences, variants, args.resamples)
    shutil.copytree(root, pristine)
    built = time.perf_counter() - t0
    print(f"built {root} in {built:.1f} s", flush=True)

    sides: dict[str, dict] = {}
    trees = {"current": ROOT}
    if args.baseline:
        rev = subprocess.run(["git", "rev-parse", args.baseline], capture_output=True, text=True, cwd=ROOT,
                             check=True).stdout.strip()
        tree = work / f"code-{rev[:10]}"
        tree.mkdir()
        archive = subprocess.run(["git", "archive", rev], capture_output=True, cwd=ROOT, check=True).stdout
        subprocess.run(["tar", "-x", "-C", str(tree)], input=archive, check=True)
        trees = {"baseline": tree, "current": ROOT}
    for side, code in trees.items():
        shutil.rmtree(root)
        shutil.copytree(pristine, root)
        sides[side] = run_side(code, root, variants, args.resamples)
        print(f"{side}: {json.dumps(sides[side])}", flush=True)
        shutil.move(root / "eval", work / f"eval-{side}")
    result = {
        "size": {"classes": args.classes, "test_sequences": args.classes * args.sequences,
                 "training_variants": variants, "test_variants": [*variants, TEST_ONLY],
                 "cells": len(variants) * (len(variants) + 1), "resamples": args.resamples,
                 "measured_models": len(variants), "measured_clips": 10 * MEASURED_CLIPS},
        "host": {"cpus": os.cpu_count(), "python": sys.version.split()[0]},
        "build_seconds": round(built, 1),
        "seconds": sides,
    }
    if args.baseline:
        result["baseline"] = rev
        result["speedup"] = {k: round(sides["baseline"][k] / sides["current"][k], 2)
                             for k in ("eval", "load", "tables", "measured_tables") if sides["current"][k] > 0}
        result["outputs"] = compare(work / "eval-baseline", work / "eval-current")
        print(f"speed-up {result['speedup']}; {result['outputs']['identical']} of {result['outputs']['files']} "
              f"files identical", flush=True)
    if args.keep is None:
        shutil.rmtree(work)
    from benchmarks.common import RESULTS, write_result

    out = args.out or RESULTS / f"eval_aggregation-cpu{os.cpu_count()}.json"
    write_result("eval_aggregation.py", argv, result, out)


if __name__ == "__main__":
    main()
