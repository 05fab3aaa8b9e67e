"""scripts/pooled_recipes.py: seeds pooled per clip, the two recipes paired on the same test clips."""
import json
import subprocess
import sys
from pathlib import Path

import pandas as pd
import pytest

ROOT = Path(__file__).resolve().parents[1]
SCRIPT = ROOT / "scripts" / "pooled_recipes.py"


def _write(run: Path, recipe: str, seed: int, preds: list[int], truth: list[int], look: str = "") -> None:
    folder = run / "ablation" / recipe / "wind-uniform1" / "paper" / "lrcn" / f"s{seed}"
    folder.mkdir(parents=True, exist_ok=True)
    ids = [f"c{i:05d}" for i in range(len(truth))]
    pd.DataFrame({"clip_id": ids, "start": 0, "class_index": truth, "pred": preds}).to_csv(
        folder / f"test_predictions{'-' + look if look else ''}.csv", index=False)


def _run(run: Path, *args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, str(SCRIPT), str(run), "--setting", "wind-uniform1", *args],
                          capture_output=True, text=True, cwd=ROOT)


def test_pooling_averages_seeds_per_clip_and_pairs_the_clips(tmp_path):
    truth = list(range(20))
    wrong = [(t + 27) % 54 for t in truth]   # three steps off in stretching: not within one
    _write(tmp_path, "good", 0, truth, truth, "heldout")
    _write(tmp_path, "good+seeds=1", 1, truth[:10] + wrong[10:], truth, "heldout")
    _write(tmp_path, "base", 0, wrong, truth, "heldout")
    done = _run(tmp_path, "--look", "heldout", "--a", "paper:good@0,good+seeds=1@1", "--b", "paper:base@0")
    assert done.returncode == 0, done.stderr
    out = json.loads(done.stdout)
    assert out["test_clips"] == out["test_windows"] == 20
    assert out["a_stretch_acc"] == pytest.approx(0.75) and out["b_stretch_acc"] == 0.0   # three steps off
    assert out["a_acc"] == pytest.approx(0.75)           # 20 right of 20, then 10 of 20
    assert out["b_acc"] == 0.0
    assert out["acc_a_minus_b"] == pytest.approx(0.75)
    assert out["acc_a_minus_b_lo"] > 0.5                  # every clip moves the same way: a tight interval
    same = json.loads(_run(tmp_path, "--look", "heldout", "--a", "paper:base@0", "--b", "paper:base@0").stdout)
    assert same["acc_a_minus_b"] == same["acc_a_minus_b_lo"] == same["acc_a_minus_b_hi"] == 0.0
    # the reference from another run of the same clips
    _write(tmp_path / "other", "base", 0, truth, truth, "heldout")
    other = json.loads(_run(tmp_path, "--look", "heldout", "--a", "paper:base@0", "--b", "paper:base@0",
                            "--b-run", str(tmp_path / "other")).stdout)
    assert other["b_acc"] == 1.0 and other["acc_a_minus_b"] == -1.0 and other["b_run"] == str(tmp_path / "other")
    # the reference's another model: base2 reading a shared regressor against lrcn itself
    base2 = tmp_path / "ablation" / "shared" / "wind-uniform1" / "paper" / "base2" / "s0"
    _write(tmp_path, "shared", 0, truth, truth, "heldout")
    (tmp_path / "ablation" / "shared" / "wind-uniform1" / "paper" / "lrcn").rename(base2.parent)
    models = json.loads(_run(tmp_path, "--look", "heldout", "--model", "base2", "--a", "paper:shared@0",
                             "--b", "paper:base@0", "--b-model", "lrcn").stdout)
    assert models["a_acc"] == 1.0 and models["b_acc"] == 0.0 and models["b_model"] == "lrcn"


def test_a_missing_look_and_other_clips_are_refused_by_name(tmp_path):
    truth = list(range(6))
    _write(tmp_path, "a", 0, truth, truth)
    _write(tmp_path, "b", 0, truth[:5], truth[:5])
    missing = _run(tmp_path, "--look", "heldout", "--a", "paper:a@0", "--b", "paper:a@0")
    assert missing.returncode != 0 and "test_predictions-heldout.csv: no predictions" in missing.stderr
    other = _run(tmp_path, "--a", "paper:a@0,b@0", "--b", "paper:a@0")
    assert other.returncode != 0 and "b@0: its test windows differ from a@0's" in other.stderr
    unpaired = _run(tmp_path, "--a", "paper:b@0", "--b", "paper:a@0")
    assert unpaired.returncode != 0 and "different windows" in unpaired.stderr
    bad = _run(tmp_path, "--a", "paper:a", "--b", "paper:a@0")
    assert bad.returncode != 0 and "expected RECIPE@SEED" in bad.stderr


def _write_probs(run: Path, recipe: str, seed: int, probs, truth: list[int]) -> None:
    """Predictions with class probabilities (prob_00 .. prob_53), the argmax the prediction."""
    import numpy as np

    folder = run / "ablation" / recipe / "wind-uniform1" / "paper" / "lrcn" / f"s{seed}"
    folder.mkdir(parents=True, exist_ok=True)
    probs = np.asarray(probs, float)
    frame = pd.DataFrame({"clip_id": [f"c{i:05d}" for i in range(len(truth))], "start": 0, "class_index": truth,
                          "pred": probs.argmax(1)})
    frame = pd.concat([frame, pd.DataFrame(probs, columns=[f"prob_{c:02d}" for c in range(54)])], axis=1)
    frame.to_csv(folder / "test_predictions.csv", index=False)


def test_an_ensemble_scores_the_seeds_mean_probabilities(tmp_path):
    import numpy as np

    truth = [0, 10, 20, 30]
    # Each seed puts 0.4 on the true class and 0.6 on a wrong one of its own: each is always wrong, and their
    # mean (0.4 on the truth, 0.3 on each wrong class) always right.
    first, second = np.zeros((4, 54)), np.zeros((4, 54))
    for i, t in enumerate(truth):
        first[i, t], first[i, t + 5] = 0.4, 0.6
        second[i, t], second[i, t + 7] = 0.4, 0.6
    _write_probs(tmp_path, "base", 0, first, truth)
    _write_probs(tmp_path, "base+seeds=1", 1, second, truth)
    spec = "paper:base@0,base+seeds=1@1"
    out = json.loads(_run(tmp_path, "--a", spec, "--a-ensemble", "--b", spec).stdout)
    assert out["a_ensemble"] and not out["b_ensemble"]
    assert out["a_acc"] == 1.0 and out["b_acc"] == 0.0 and out["acc_a_minus_b"] == 1.0
    _write(tmp_path, "plain", 0, truth, truth)     # predictions without probabilities cannot be averaged
    refused = _run(tmp_path, "--a", "paper:plain@0", "--a-ensemble", "--b", spec)
    assert refused.returncode != 0 and "plain@0: its predictions hold no class probabilities" in refused.stderr
    mixed = _run(tmp_path, "--a", "paper:base@0,plain@0", "--a-ensemble", "--b", spec)   # a later seed without them
    assert mixed.returncode != 0 and "plain@0: its predictions hold no class probabilities" in mixed.stderr


def test_look_val_reads_the_validation_predictions(tmp_path):
    truth = [0, 1, 2, 3]
    _write(tmp_path, "a", 0, truth, truth)
    folder = tmp_path / "ablation" / "a" / "wind-uniform1" / "paper" / "lrcn" / "s0"
    pd.DataFrame({"clip_id": ["c00100", "c00101"], "start": 0, "class_index": [5, 6], "pred": [5, 9]}).to_csv(
        folder / "val_predictions.csv", index=False)
    out = json.loads(_run(tmp_path, "--look", "val", "--a", "paper:a@0", "--b", "paper:a@0").stdout)
    assert out["test_windows"] == 2 and out["a_acc"] == 0.5
    _write(tmp_path, "old", 0, truth, truth)       # trained before validation predictions were written
    missing = _run(tmp_path, "--look", "val", "--a", "paper:old@0", "--b", "paper:a@0")
    assert missing.returncode != 0 and "no validation predictions" in missing.stderr
