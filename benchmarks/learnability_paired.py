"""The geometry probe's noise, for two runs of the same clips (e.g. self-collision off and on).

    python benchmarks/learnability_paired.py RUN_A RUN_B [--seeds 0,1,2] [--out FILE]

`clothgap eval learnability` reports one fit of each classifier on one split, with no
interval. This script takes the probe's MLP under the `sequence` split (the same split in
both runs when they hold the same clip ids and classes, as runs of one preset and seed do)
and reports, per target (54 classes, stretching, bending) and run:

* the test accuracy and within-one-bin share for each MLP seed (seed 0 is the probe's own
  fit), so the spread of the fit itself shows;
* a 95 % bootstrap interval over test *sequences* (a sequence's windows are resampled
  together: they are not independent) of the seed-0 accuracy;
* the paired difference B - A of the seed-0 fits with its bootstrap interval, resampling the
  same test sequences in both runs.

Writes JSON (default: print only) with the command that made it.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

import clothgap.config  # noqa: F401  (registers the study config that Run.open reads)
from clothgap.runs import Run
from eval.learnability import _targets, fit_predict, load_windows, within_one_bin
from learn.split import split_sequences

BOOTSTRAP = 2000


def windows_and_split(root: Path, setting: str):
    run = Run.open(root)
    x, clips, _, labels = load_windows(run, setting, 10, 10, progress=False)
    first = {c: int(l) for c, l in zip(clips, labels)}
    split = split_sequences(first, 0.0, 1 / 6, run.config.seed)
    return x, clips, labels, split


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("run_a", type=Path)
    ap.add_argument("run_b", type=Path)
    ap.add_argument("--setting", default="wind-uniform1")
    ap.add_argument("--seeds", default="0,1,2")
    ap.add_argument("--out", type=Path)
    args = ap.parse_args()
    seeds = [int(s) for s in args.seeds.split(",")]
    t0 = time.perf_counter()
    runs = [windows_and_split(r, args.setting) for r in (args.run_a, args.run_b)]
    if runs[0][3] != runs[1][3] or not np.array_equal(runs[0][1], runs[1][1]):
        sys.exit("the two runs differ in clips or split: not a paired comparison")
    x_a, clips, labels, split = runs[0]
    test = set(split["test"])
    tr = np.array([c not in test for c in clips])
    te = ~tr
    # Bootstrap over test sequences: resample sequence ids, take all their windows.
    test_ids = sorted(test)
    of_seq = {c: np.flatnonzero(clips[te] == c) for c in test_ids}
    rng = np.random.default_rng(0)
    draws = [np.concatenate([of_seq[test_ids[j]] for j in rng.integers(0, len(test_ids), len(test_ids))])
             for _ in range(BOOTSTRAP)]

    def interval(values: np.ndarray) -> list[float]:
        boot = np.array([values[d].mean() for d in draws])
        return [float(np.percentile(boot, 2.5)), float(np.percentile(boot, 97.5))]

    targets = _targets(labels)
    classes = {"class": 54, "stretching": 6, "bending": 9}
    out = {"command": " ".join(["python", *sys.argv]), "setting": args.setting, "classifier": "mlp",
           "protocol": "sequence", "runs": [str(args.run_a), str(args.run_b)], "seeds": seeds,
           "test_sequences": len(test_ids), "test_windows": int(te.sum()), "bootstrap": BOOTSTRAP,
           "targets": {}}
    for target, n in classes.items():
        y = targets[target]
        row: dict = {}
        correct0 = []
        for name, (x, *_rest) in zip(("a", "b"), runs):
            fits = []
            for seed in seeds:
                pred = fit_predict("mlp", x[tr], y[tr], x[te], n, seed)
                ok = (pred == y[te]).astype(float)
                fits.append({"seed": seed, "accuracy": float(ok.mean()),
                             "within_one_bin": within_one_bin(target, pred, y[te])})
                if seed == seeds[0]:
                    correct0.append(ok)
                    row[name + "_interval_seed0"] = interval(ok)
                print(f"{target} {name} seed {seed}: {fits[-1]}", flush=True)
            acc = [f["accuracy"] for f in fits]
            row[name] = {"fits": fits, "accuracy_mean": float(np.mean(acc)),
                         "accuracy_spread": [float(min(acc)), float(max(acc))]}
        diff = correct0[1] - correct0[0]
        row["difference_b_minus_a_seed0"] = float(diff.mean())
        row["difference_interval"] = interval(diff)
        out["targets"][target] = row
    out["seconds"] = round(time.perf_counter() - t0, 1)
    text = json.dumps(out, indent=1)
    if args.out:
        args.out.write_text(text + "\n")
    print(text)


if __name__ == "__main__":
    main()
