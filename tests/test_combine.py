"""scripts/combined_variant.py and eval.combine on a fake run: finished models and eval predictions written
directly (no render, no training), with accuracies set per half so that a mix-up of the halves shows."""

from __future__ import annotations

import importlib.util
import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from clothgap.config import preset
from clothgap.runs import Run, atomic_write_json, clip_id, mark_done
from eval import predictions as preds
from eval.stage import prediction_path, record_path
from eval.trained import TrainedModel, checkpoint_sha256
from render.variants import USER_VARIANTS_ENV, get_variant

SCRIPT = Path(__file__).resolve().parents[1] / "scripts" / "combined_variant.py"

CLASSES = (0, 8, 45, 53)
PER_CLASS = 8                   # sequences 0..7 of each class: 16 test clips in each half
SETTING = "wind-uniform1"
TEST = "heldout"
# variant -> (clips right of the 16 on the even half, of the 16 on the odd half). The halves disagree: on the
# odd half lighting-random is worse than paper and grid is the best, so a report that used the even half, or
# both, or a select that looked at the odd half, gets other numbers.
RIGHT = {"paper": (6, 8), "lighting-random": (12, 4), "camera-noise": (9, 10), "grid": (3, 14),
         "randomised": (0, 11)}


def clips_of(run: Run, half: int) -> list[str]:
    """Test clips whose sequence number has parity ``half`` (the run's rule: index // number of classes)."""
    n = len(CLASSES) * PER_CLASS
    return [clip_id(i) for i in range(n) if (i // len(CLASSES)) % 2 == half]


def make_run(root: Path, right: dict[str, tuple[int, int]], seeds=(0,)) -> Run:
    """A run whose models trained on ``right``'s variants (``paper`` first) have eval predictions on heldout."""
    cfg = preset("smoke")
    cfg = replace(cfg, sim=replace(cfg.sim, classes=CLASSES, sequences_per_class=PER_CLASS),
                  render=replace(cfg.render, variants=tuple(right)),
                  train=replace(cfg.train, models=("lrcn",), seeds=tuple(seeds)),
                  eval=replace(cfg.eval, bootstrap=200))
    run = Run.create_or_resume(root, cfg)
    ids = [clip_id(i) for i in range(len(CLASSES) * PER_CLASS)]
    atomic_write_json(run.split_path(SETTING), {"by": "sequence", "seed": 0, "train": [], "val": [], "test": ids})
    for variant, counts in right.items():
        add_model(run, variant, counts, seeds)
    return run


def add_model(run: Run, variant: str, counts: tuple[int, int], seeds=(0,)) -> None:
    """A finished lrcn model of ``variant`` whose predictions on heldout are right on the first ``counts[h]``
    clips of half h (every sub-sequence of them) and wrong on the others, as eval writes them."""
    for seed in seeds:
        m = TrainedModel(SETTING, variant, "lrcn", seed, run.train_dir(SETTING, variant, "lrcn", seed))
        m.folder.mkdir(parents=True)
        (m.folder / "checkpoint.pt").write_bytes(f"stub {variant} {seed}".encode())
        mark_done(m.folder)
        rows = []
        for half in (0, 1):
            for k, cid in enumerate(clips_of(run, half)):
                truth = CLASSES[int(cid[1:]) % len(CLASSES)]
                pred = truth if k < counts[half] else CLASSES[(CLASSES.index(truth) + 1) % len(CLASSES)]
                probs = np.full(54, 0.1 / 53)
                probs[pred] = 0.9
                rows += [{"clip_id": cid, "start": s, "class_index": truth, "pred": pred, "probs": probs}
                         for s in (0, 5, 10)]
        path = prediction_path(run, m, TEST)
        preds.save(pd.DataFrame(rows), path)
        atomic_write_json(record_path(path), {"checkpoint_sha256": checkpoint_sha256(m),
                                              "clips": sorted({r["clip_id"] for r in rows}), "left_out": []})


def main(argv: list[str]) -> int:
    spec = importlib.util.spec_from_file_location("combined_variant", SCRIPT)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module.main(argv)


def select(run: Run, folder: Path, *extra: str) -> int:
    return main(["select", str(run.root), "--variants-dir", str(folder), *extra])


@pytest.fixture
def variants_dir(tmp_path, monkeypatch) -> Path:
    folder = tmp_path / "variants"
    folder.mkdir()
    monkeypatch.setenv(USER_VARIANTS_ENV, str(folder))
    return folder


def test_select_combines_exactly_the_variants_that_helped_on_the_even_half(tmp_path, variants_dir, capsys):
    run = make_run(tmp_path / "run", {v: RIGHT[v] for v in ("paper", "lighting-random", "camera-noise", "grid")})
    assert select(run, variants_dir) == 0
    out = capsys.readouterr().out
    assert "did not help" in out and "grid" in out

    combined = get_variant("randomised")         # loads from $CLOTHGAP_VARIANTS_DIR like any user variant
    paper = get_variant("paper")
    expected = {**get_variant("lighting-random").changes_from(paper), **get_variant("camera-noise").changes_from(paper)}
    assert combined.changes_from(paper) == expected
    assert "lighting-random" in combined.description and "camera-noise" in combined.description
    assert "grid" not in combined.description

    record = json.loads((run.eval_dir / "combined-randomised.json").read_text())
    assert record["chosen"] == ["lighting-random", "camera-noise"] and record["best_single"] == "lighting-random"
    gains = {c["variant"]: c["gain"] for c in record["candidates"]}
    # the even half only: 12/16 - 6/16 sub-sequences right, paired; grid 3/16 - 6/16
    assert gains["lighting-random"]["value"] == pytest.approx(6 / 16)
    assert gains["camera-noise"]["value"] == pytest.approx(3 / 16)
    assert gains["grid"]["value"] == pytest.approx(-3 / 16)
    assert all(g["low"] <= g["value"] <= g["high"] for g in gains.values())
    assert record["clips"][SETTING]["used"] == clips_of(run, 0) and not record["clips"][SETTING]["left_out"]


def test_select_again_gives_the_same_bytes_even_once_the_combined_variant_is_trained(tmp_path, variants_dir):
    run = make_run(tmp_path / "run", {v: RIGHT[v] for v in ("paper", "lighting-random", "camera-noise", "grid")})
    assert select(run, variants_dir) == 0
    files = [run.eval_dir / "combined-randomised.json", variants_dir / "randomised.toml"]
    first = [f.read_bytes() for f in files]
    assert select(run, variants_dir) == 0
    assert [f.read_bytes() for f in files] == first
    add_combined(run)
    assert select(run, variants_dir) == 0          # the combined variant is no candidate of its own selection
    assert [f.read_bytes() for f in files] == first


def test_a_conflict_keeps_the_variant_with_the_larger_gain(tmp_path, variants_dir):
    # diffuse and sheer both set bsdf (diffuse / principledthin); both help, diffuse more
    run = make_run(tmp_path / "run", {"paper": (4, 4), "diffuse": (10, 4), "sheer": (7, 4),
                                      "lighting-random": (5, 4)}, seeds=(0, 1))
    assert select(run, variants_dir) == 0
    record = json.loads((run.eval_dir / "combined-randomised.json").read_text())
    assert record["chosen"] == ["diffuse", "lighting-random"]
    (conflict,) = record["conflicts"]
    assert conflict["variant"] == "sheer" and conflict["kept"] == ["diffuse"] and conflict["keys"] == ["bsdf"]
    assert record["settings"] == {"bsdf": "diffuse", "lighting": "random"}
    assert get_variant("randomised").changes_from(get_variant("paper")) == record["settings"]
    assert {c["variant"]: c["seeds"] for c in record["candidates"]}["sheer"] == [0, 1]    # both seeds' rows
    assert record["candidates"][0]["gain"]["value"] == pytest.approx(6 / 16)


def test_nothing_helped_exits_3_and_writes_nothing(tmp_path, variants_dir, capsys):
    run = make_run(tmp_path / "run", {"paper": (9, 9), "lighting-random": (9, 12), "grid": (3, 12)})
    assert select(run, variants_dir) == 3
    assert "nothing written" in capsys.readouterr().out
    assert not list(variants_dir.iterdir()) and not (run.eval_dir / "combined-randomised.json").exists()


def add_combined(run: Run, measured: bool = False) -> Run:
    """What the user's pipeline call does to the fake run: randomised in the config, trained, evaluated."""
    cfg = run.config
    run = Run.create_or_resume(run.root, replace(cfg, render=replace(cfg.render,
                                                                     variants=(*cfg.render.variants, "randomised"))))
    add_model(run, "randomised", RIGHT["randomised"])
    return run


def test_report_uses_the_odd_half_only(tmp_path, variants_dir, capsys):
    run = make_run(tmp_path / "run", {v: RIGHT[v] for v in ("paper", "lighting-random", "camera-noise", "grid")})
    assert select(run, variants_dir) == 0
    run = add_combined(run)
    assert main(["report", str(run.root), "--name", "randomised"]) == 0
    assert "combined minus paper" in capsys.readouterr().out
    rep = json.loads((run.eval_dir / "combined-randomised-report.json").read_text())
    acc = {r["variant"]: r["acc"]["value"] for r in rep["rows"]}
    assert acc == pytest.approx({"paper": 8 / 16, "lighting-random": 4 / 16, "camera-noise": 10 / 16,
                                 "randomised": 11 / 16})
    assert rep["best_single"] == "lighting-random"          # chosen on the even half, not the odd one's best
    assert rep["combined_minus_reference"]["value"] == pytest.approx(3 / 16)
    assert rep["combined_minus_best_single"]["value"] == pytest.approx(7 / 16)
    assert rep["clips"][SETTING]["used"] == clips_of(run, 1)
    assert rep["measured"]["included"] is False and not rep["models_changed_since_selection"]
    md = (run.eval_dir / "combined-randomised-report.md").read_text()
    assert "| randomised | combined | 68.8 [" in md


def test_report_includes_the_measured_fabrics_when_they_are_there(tmp_path, variants_dir):
    run = make_run(tmp_path / "run", {v: RIGHT[v] for v in ("paper", "lighting-random", "camera-noise")})
    assert select(run, variants_dir) == 0
    run = add_combined(run)
    exact = {"paper": [1, 0, 0, 0], "lighting-random": [1, 1, 0, 0], "camera-noise": [0, 0, 0, 1],
             "randomised": [1, 1, 1, 0]}
    pd.DataFrame([{"setting": SETTING, "train_variant": v, "model": "lrcn", "seed": 0, "test_variant": TEST,
                   "fabric": f"fabric{i}", "exact": e} for v, es in exact.items() for i, e in enumerate(es)]
                 ).to_csv(run.eval_dir / "measured.csv", index=False)
    assert main(["report", str(run.root)]) == 0
    m = json.loads((run.eval_dir / "combined-randomised-report.json").read_text())["measured"]
    assert m["included"] and m["fabrics"] == ["fabric0", "fabric1", "fabric2", "fabric3"]
    assert m["combined_minus_reference"]["value"] == pytest.approx(0.5)
    assert m["combined_minus_best_single"]["value"] == pytest.approx(0.25)


def test_errors_are_one_line_naming_what_is_missing(tmp_path, variants_dir, capsys, monkeypatch):
    run = make_run(tmp_path / "run", {v: RIGHT[v] for v in ("paper", "lighting-random", "camera-noise")})

    def error(*argv: str) -> str:
        assert main(list(argv)) == 2
        lines = capsys.readouterr().err.strip().splitlines()
        assert len(lines) == 1 and lines[0].startswith("error: ")
        return lines[0]

    assert "combined-randomised.json" in error("report", str(run.root))
    assert "'daylight'" in error("select", str(run.root), "--test", "daylight")
    assert "model 'base9'" in error("select", str(run.root), "--model", "base9", "--setting", SETTING)
    assert "unknown setting" in error("select", str(run.root), "--setting", "arm-uniform1")
    assert "already a variant" in error("select", str(run.root), "--name", "grid")
    monkeypatch.delenv(USER_VARIANTS_ENV)
    assert "--variants-dir" in error("select", str(run.root))
    assert select(run, variants_dir) == 0
    assert "not trained yet" in error("report", str(run.root), "--variants-dir", str(variants_dir))
    monkeypatch.setenv(USER_VARIANTS_ENV, str(variants_dir))
    add_combined(run)
    monkeypatch.delenv(USER_VARIANTS_ENV)
    assert "--variants-dir" in error("report", str(run.root))     # the run names randomised: where is it?
    prediction_path(run, TrainedModel(SETTING, "randomised", "lrcn", 0, Path()), TEST).unlink()
    assert "not evaluated yet" in error("report", str(run.root), "--variants-dir", str(variants_dir))
    assert "--test heldout" in error("report", str(run.root), "--test", "daylight", "--variants-dir",
                                     str(variants_dir))
    prediction_path(run, TrainedModel(SETTING, "paper", "lrcn", 0, Path()), TEST).unlink()
    assert "no predictions" in error("select", str(run.root), "--setting", SETTING, "--variants-dir",
                                     str(variants_dir))
