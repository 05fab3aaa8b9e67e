"""scripts/plot_learning_curves.py: a table of a results file with several, by name."""
import json
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SCRIPT = ROOT / "scripts" / "plot_learning_curves.py"


def _recipe(name: str) -> dict:
    curve = [{"epoch": e, "train_acc": 0.1 * e, "val_acc": 0.05 * e} for e in range(4)]
    return {"recipe": name, "model": "lrcn", "curves": {"s0": curve}}


def test_a_named_table_of_a_results_file_is_plotted_and_a_missing_one_named(tmp_path):
    results = tmp_path / "learn_levers.json"
    results.write_text(json.dumps({"tables": {"levers-a": {"recipes": [_recipe("baseline"), _recipe("camera")]}}}))
    plain = tmp_path / "plain.json"
    plain.write_text(json.dumps({"recipes": [_recipe("baseline")]}))
    out = tmp_path / "curves.png"
    done = subprocess.run([sys.executable, str(SCRIPT), str(out), f"{results}:levers-a", str(plain)],
                          capture_output=True, text=True)
    assert done.returncode == 0, done.stderr
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and out.stat().st_size > 10_000
    missing = subprocess.run([sys.executable, str(SCRIPT), str(out), f"{results}:levers-b"],
                             capture_output=True, text=True)
    assert missing.returncode != 0 and "has no table 'levers-b'; it has: levers-a" in missing.stderr
