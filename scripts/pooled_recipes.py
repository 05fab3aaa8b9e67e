"""Two training recipes compared over several seeds each, paired on the same test clips.

`clothgap eval ablation` pairs one recipe's seed with the first recipe's; this pools seeds: for each test
window (a whole clip at the presets' clip length), the fraction of a recipe's seeds that read it right (exact
class, within one grid step, the stretching and the bending factor), then the difference of the two recipes'
means with a 95 % interval from resampling test clips, paired by clip (eval.metrics.bootstrap_mean_difference,
1,000 resamples, generator seed 0).

    python scripts/pooled_recipes.py RUN --setting wind-uniform1 --look heldout \\
        --a lighting-random:camera+epochs=80@0,camera+epochs=80+seeds=1@1 \\
        --b lighting-random:baseline@0,baseline+seeds=1@1

A side is VARIANT:RECIPE@SEED,RECIPE@SEED,...: the render variant the recipe trained on, and the ablation
folders' recipe names (`RUN/ablation/RECIPE/SETTING/VARIANT/lrcn/sSEED`). --look own scores each on its training
variant's test clips, --look V on the same clips rendered as V (`eval ablation --test-variant V`), --look val on
the validation windows (the kept weights' val_predictions.csv that training writes: choose recipes there). --b-run takes
the reference from another run of the same simulations (the same seed and clips, e.g. rendered at another size).
--b-model compares with another model of the reference (default: --model's).
--a-ensemble (--b-ensemble) scores that side's seeds as one model instead: each window's class probabilities
averaged over the seeds, the most probable class its prediction (what N seeds trained and kept together give).
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import pandas as pd

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from eval import metrics  # noqa: E402
from eval import predictions as preds  # noqa: E402


def _side(spec: str) -> tuple[str, list[tuple[str, int]]]:
    variant, sep, members = spec.partition(":")
    if not sep or not members:
        raise SystemExit(f"{spec!r}: expected VARIANT:RECIPE@SEED[,RECIPE@SEED...]")
    pairs = []
    for member in members.split(","):
        recipe, at, seed = member.rpartition("@")
        if not at or not seed.isdigit():
            raise SystemExit(f"{member!r} in {spec!r}: expected RECIPE@SEED")
        pairs.append((recipe, int(seed)))
    return variant, pairs


SCORES = {"acc": metrics.correct, "within1": metrics.within_one_bin, "stretch_acc": metrics.stretch_correct,
          "bend_acc": metrics.bend_correct}


def _scores(run: Path, setting: str, model: str, look: str, spec: str,
            ensemble: bool = False) -> tuple[dict[str, np.ndarray], pd.DataFrame]:
    """Per test window (sorted by clip and start), for each of ``SCORES`` the fraction of seeds that got it (with
    ``ensemble``, whether the seeds' mean probabilities got it); the windows (clip_id, start)."""
    variant, members = _side(spec)
    name = {"own": "test_predictions.csv", "val": "val_predictions.csv"}.get(look, f"test_predictions-{look}.csv")
    frames = []
    for recipe, seed in members:
        path = run / "ablation" / recipe / setting / variant / model / f"s{seed}" / name
        if not path.is_file() and look == "val":
            raise SystemExit(f"{path}: no validation predictions (training writes them when its split has "
                             "validation clips; a model trained before it did has none: train the recipe again)")
        if not path.is_file():
            how = "" if look == "own" else f" --test-variant {look}"
            raise SystemExit(f"{path}: no predictions (train the recipe with `clothgap eval ablation`{how} first)")
        frames.append(pd.read_csv(path).sort_values(["clip_id", "start"]).reset_index(drop=True))
    windows = frames[0][["clip_id", "start"]]
    for frame, (recipe, seed) in zip(frames, members):
        if not frame[["clip_id", "start"]].equals(windows):
            raise SystemExit(f"{recipe}@{seed}: its test windows differ from {members[0][0]}@{members[0][1]}'s")
    if ensemble:
        for frame, (recipe, seed) in zip(frames, members):
            if any(c not in frame.columns for c in preds.PROB_COLUMNS):
                raise SystemExit(f"{recipe}@{seed}: its predictions hold no class probabilities (prob_00 .. "
                                 "prob_53): no ensemble")
        stacked = pd.concat([f.assign(seed=i) for i, f in enumerate(frames)], ignore_index=True)
        one = windows.merge(preds.seed_average(stacked), on=["clip_id", "start"], how="left")
        return {name: score(one["class_index"], one["pred"]) for name, score in SCORES.items()}, windows
    return {name: np.mean([score(f["class_index"], f["pred"]) for f in frames], axis=0)
            for name, score in SCORES.items()}, windows


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                     formatter_class=argparse.RawDescriptionHelpFormatter, epilog=__doc__)
    parser.add_argument("run", type=Path)
    parser.add_argument("--setting", required=True)
    parser.add_argument("--model", default="lrcn")
    parser.add_argument("--b-model", help="the reference's model, if another (e.g. a reader on a shared regressor "
                                          "against lrcn itself): default --model")
    parser.add_argument("--look", default="own", help="own (test clips), val (validation windows), or a test-only "
                                                      "variant such as heldout")
    parser.add_argument("--a", required=True, help="VARIANT:RECIPE@SEED,... (the side whose gain is reported)")
    parser.add_argument("--b", required=True, help="VARIANT:RECIPE@SEED,... (the reference)")
    parser.add_argument("--b-run", type=Path, help="the reference's run, if another (the same simulations, e.g. "
                                                   "rendered at another resolution): default RUN")
    parser.add_argument("--a-ensemble", action="store_true", help="score --a's seeds as one averaged model")
    parser.add_argument("--b-ensemble", action="store_true", help="score --b's seeds as one averaged model")
    args = parser.parse_args(argv)
    a_scores, a_windows = _scores(args.run, args.setting, args.model, args.look, args.a, args.a_ensemble)
    b_model = args.b_model or args.model
    b_scores, b_windows = _scores(args.b_run or args.run, args.setting, b_model, args.look, args.b,
                                  args.b_ensemble)
    if not a_windows.equals(b_windows):
        raise SystemExit("--a and --b were scored on different windows: no paired comparison")
    clips = a_windows["clip_id"].to_numpy()    # resampled by clip: a clip's windows go together
    out = {"run": str(args.run), "b_run": str(args.b_run or args.run), "setting": args.setting,
           "model": args.model, "b_model": b_model, "look": args.look, "a": args.a, "b": args.b,
           "a_ensemble": args.a_ensemble, "b_ensemble": args.b_ensemble, "test_windows": len(a_windows),
           "test_clips": len(set(clips))}
    for name in SCORES:
        a, b = a_scores[name], b_scores[name]
        out.update(metrics.bootstrap_mean(a, clips).as_dict(f"a_{name}"))
        out.update(metrics.bootstrap_mean(b, clips).as_dict(f"b_{name}"))
        out.update(metrics.bootstrap_mean_difference(a, clips, b, clips).as_dict(f"{name}_a_minus_b"))
    json.dump(out, sys.stdout, indent=1)
    print()
    print(f"a {100 * out['a_acc']:.1f} % against b {100 * out['b_acc']:.1f} %: {100 * out['acc_a_minus_b']:+.1f} "
          f"[{100 * out['acc_a_minus_b_lo']:+.1f}, {100 * out['acc_a_minus_b_hi']:+.1f}] points "
          f"({'validation windows' if args.look == 'val' else args.look + ' test clips'}; {len(a_windows)} windows)",
          file=sys.stderr)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
