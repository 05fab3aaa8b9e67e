"""Training recipes compared on the same test clips: recipes, folders, scores, the CLI."""

from __future__ import annotations

import json
import re

import pandas as pd
import pytest
from clothgap.config import ConfigError, StudyConfig
from eval import predictions as preds
from eval.ablation import recipe_config, run_ablation
from learn.split import get_or_make_split, part_windows
from clothgap.runs import clip_index
from learn.synthetic import synthetic_run, write_synthetic_clip
from tests.conftest import tiny_train_config
from tests.test_cli import assert_user_error, clothgap

SETTING, VARIANT = "wind-uniform1", "paper"


def tiny() -> StudyConfig:
    return tiny_train_config(epochs=2, dropout=0.5)


def test_recipes_compose_levers_and_settings():
    cfg = recipe_config(tiny(), "augment+best+lr=0.01")
    assert cfg.augment and cfg.keep == "best" and cfg.lr == 0.01 and cfg.epochs == 2
    assert recipe_config(tiny(), "baseline") == tiny().train
    with pytest.raises(ConfigError, match="unknown lever 'sharpen'"):
        recipe_config(tiny(), "augment+sharpen")
    with pytest.raises(ConfigError, match="train.keep"):
        recipe_config(tiny(), "keep=always")


def test_ablation_scores_every_recipe_on_the_same_test_windows(tmp_path):
    run = synthetic_run(tmp_path / "run", tiny())
    summary = run_ablation(run, SETTING, VARIANT, ["baseline", "augment+best+seeds=1"], progress=False)
    report = json.loads((run.eval_dir / f"ablation-{SETTING}-{VARIANT}.json").read_text())
    assert summary["json"].endswith(f"ablation-{SETTING}-{VARIANT}.json")
    first, second = report["recipes"]
    test = part_windows(get_or_make_split(run, SETTING), "test")
    assert first["sequences"] == second["sequences"] == len(test) == report["test_sequences"]
    assert report["test_sequences_in_split"] == len(test)
    assert first["rows"] == second["rows"] == len(test) * 3          # windows at 0, 5, 10 of 16 frames
    assert "acc_minus_first" not in first and second["acc_minus_first_lo"] <= second["acc_minus_first_hi"]
    assert second["changes"] == {"augment": True, "keep": "best", "seeds": [1]}
    assert first["seeds"] == [0] and second["seeds"] == [1]              # a recipe may train another seed
    assert 0 <= first["within1"] <= 1 and first["within1"] >= first["acc"]
    # the video-level answer: one decision per test sequence from its windows' mean probabilities
    frame = pd.read_csv(run.root / "ablation" / "baseline" / SETTING / VARIANT / "lrcn" / "s0" / "test_predictions.csv")
    seq = preds.per_sequence(preds.load(run.root / "ablation" / "baseline" / SETTING / VARIANT / "lrcn" / "s0"
                                        / "test_predictions.csv"))
    assert len(frame) == first["rows"] and len(seq) == first["sequences"]
    assert first["seq_acc"] == pytest.approx((seq["class_index"] == seq["pred"]).mean())
    assert first["seq_acc_lo"] <= first["seq_acc"] <= first["seq_acc_hi"]
    assert len(second["curves"]["s1"]) == 2 and second["speed"][0]["train_windows"] > 0
    folder = run.root / "ablation" / "augment+best+seeds=1" / SETTING / VARIANT / "lrcn" / "s1"
    assert (folder / "DONE").is_file() and (folder / "test_predictions.csv").is_file()
    stamp = (folder / "DONE").stat().st_mtime_ns
    run_ablation(run, SETTING, VARIANT, ["baseline", "augment+best+seeds=1"], progress=False)   # all reused
    assert (folder / "DONE").stat().st_mtime_ns == stamp
    md = (run.eval_dir / f"ablation-{SETTING}-{VARIANT}.md").read_text()
    assert "| augment+best+seeds=1 | lrcn |" in md and "| per sequence % |" in md


def test_ablation_scores_recipes_on_a_test_only_look_of_the_same_clips_too(tmp_path):
    cfg = tiny()
    run = synthetic_run(tmp_path / "run", cfg)
    recipes = ["baseline", "augment"]
    with pytest.raises(ConfigError, match="test variant 'heldout' has 0 of the 4 test clips"):
        run_ablation(run, SETTING, VARIANT, recipes, progress=False, test_variants=["heldout"])
    assert not (run.root / "ablation").exists()                 # refused before anything was trained
    run_ablation(run, SETTING, VARIANT, recipes, progress=False)
    alone = json.loads((run.eval_dir / f"ablation-{SETTING}-{VARIANT}.json").read_text())
    # the split's test clips in another look (other pixels, the same labels), as `render --test-variant` makes
    test = part_windows(get_or_make_split(run, SETTING), "test")
    labels = [c for c in cfg.sim.class_indices() for _ in range(cfg.sim.sequences_per_class)]
    first, *rest = sorted(test)
    write_synthetic_clip(run.render_dir("heldout", SETTING) / first, clip_index(first), labels[clip_index(first)],
                         cfg.sim.frames, cfg.render.resolution, cfg.seed, "heldout", SETTING)
    with pytest.raises(ConfigError, match="has 1 of the 4 test clips"):         # scored on every test clip or none
        run_ablation(run, SETTING, VARIANT, recipes, progress=False, test_variants=["heldout"])
    for cid in rest:
        write_synthetic_clip(run.render_dir("heldout", SETTING) / cid, clip_index(cid), labels[clip_index(cid)],
                             cfg.sim.frames, cfg.render.resolution, cfg.seed, "heldout", SETTING)
    run_ablation(run, SETTING, VARIANT, recipes, progress=False, test_variants=["heldout", VARIANT])
    report = json.loads((run.eval_dir / f"ablation-{SETTING}-{VARIANT}.json").read_text())
    assert report["test_variants"] == ["heldout"]               # the training look is not a test variant
    for own, row in zip(alone["recipes"], report["recipes"]):
        # the training look's scores are those of an ablation without test variants, to the bit
        assert {k: v for k, v in row.items() if k not in ("on", "speed")} == \
               {k: v for k, v in own.items() if k != "speed"}
        on = row["on"]["heldout"]
        assert on["sequences"] == len(test) and on["rows"] == row["rows"]
        assert on["acc_lo"] <= on["acc"] <= on["acc_hi"] and on["within1"] >= on["acc"]
    assert "acc_minus_first" not in report["recipes"][0]["on"]["heldout"]
    diff = report["recipes"][1]["on"]["heldout"]
    assert diff["acc_minus_first_lo"] <= diff["acc_minus_first"] <= diff["acc_minus_first_hi"]
    assert diff["acc_minus_first"] == pytest.approx(diff["acc"] - report["recipes"][0]["on"]["heldout"]["acc"])
    folder = run.root / "ablation" / "augment" / SETTING / VARIANT / "lrcn" / "s0"
    kept = preds.load(folder / "test_predictions-heldout.csv")
    assert sorted(set(kept["clip_id"])) == sorted(test)
    md = (run.eval_dir / f"ablation-{SETTING}-{VARIANT}.md").read_text()
    assert "rendered as `heldout`" in md and md.count("| augment | lrcn |") == 2

    # the run's report shows both tables, the test-only look's numbers the JSON's
    from eval.report import write_report

    html = write_report(run).read_text()
    section = html[html.index('<h2 id="ablations">'):]
    assert f"ablation-{SETTING}-{VARIANT}.json" in section and "rendered as <code>heldout</code>" in section
    assert section.count("<td>augment</td>") == 2


def test_the_report_shows_each_look_of_a_recipe_comparison_with_its_own_numbers(tmp_path):
    from eval.report import write_report

    run = synthetic_run(tmp_path / "run", tiny())

    def scores(acc: float, diff: float | None) -> dict:
        out = {"acc": acc, "acc_lo": acc - 0.05, "acc_hi": acc + 0.05, "within1": 0.9, "within1_lo": 0.8,
               "within1_hi": 0.95, "stretch_acc": 0.7, "bend_acc": 0.6}
        if diff is not None:
            out.update(acc_minus_first=diff, acc_minus_first_lo=diff - 0.02, acc_minus_first_hi=diff + 0.02)
        return out

    report = {"setting": SETTING, "variant": VARIANT, "base_train": {}, "test_sequences": 4,
              "test_variants": ["heldout"],
              "recipes": [{"recipe": "baseline", "model": "lrcn", "seeds": [0], "speed": [{"kept_epoch": 3}],
                           **scores(0.4321, None), "on": {"heldout": scores(0.0617, None)}},
                          {"recipe": "camera", "model": "lrcn", "seeds": [0, 1], "speed": [{"kept_epoch": None}],
                           **scores(0.3789, -0.0532), "on": {"heldout": scores(0.1543, 0.0926)}}]}
    (run.eval_dir).mkdir(parents=True, exist_ok=True)
    (run.eval_dir / "levers.json").write_text(json.dumps(report))
    (run.eval_dir / "empty.json").write_text(json.dumps({"recipes": [], "base_train": {}}))   # nothing to show
    (run.eval_dir / "other.json").write_text(json.dumps({"cells": 3}))                        # not a comparison
    section = write_report(run).read_text().split('<h2 id="ablations">')[1]
    own, heldout = section.split("rendered as <code>heldout</code>")
    assert "43.2" in own and "37.9" in own and "-5.32" in own and "<td>0, 1</td>" in own and "<td>3</td>" in own
    assert "6.2" in heldout and "15.4" in heldout and "9.26" in heldout
    assert "43.2" not in heldout and "15.4" not in own
    assert "empty.json" not in section and "other.json" not in section


def test_ablation_cli_checks_recipes_and_pairs_first(tmp_path):
    run = synthetic_run(tmp_path / "run", tiny())
    result = clothgap("eval", "ablation", str(run.root), "--recipe", "baseline", "--recipe", "nonsense")
    assert_user_error(result, "unknown lever 'nonsense'")
    assert not (run.root / "ablation").exists()
    result = clothgap("eval", "ablation", str(run.root), "--recipe", "baseline", "--setting", "arm-uniform1")
    assert_user_error(result, "not a pair this run renders")


def test_a_split_without_test_sequences_is_refused_before_any_training(tmp_path):
    # 4 sequences a class, test share 0.1: round(0.4) is no test sequence, so no recipe could be scored
    run = synthetic_run(tmp_path / "run", tiny_train_config(epochs=2, test_fraction=0.1))
    assert not part_windows(get_or_make_split(run, SETTING), "test")
    with pytest.raises(ConfigError, match="holds no test sequence .*4 sequence.* a class, train.test_fraction=0.1"):
        run_ablation(run, SETTING, VARIANT, ["baseline"], progress=False)
    assert not (run.root / "ablation").exists()                         # nothing trained
    for parallel in ("1", "2"):                                       # --parallel trains before it scores
        result = clothgap("eval", "ablation", str(run.root), "--recipe", "baseline", "--parallel", parallel)
        assert_user_error(result, "holds no test sequence")
        assert not (run.root / "ablation").exists()


@pytest.mark.slow
def test_ablation_trains_recipes_side_by_side_as_one_process_does(tmp_path):
    cfg = tiny_train_config(epochs=2, dropout=0.5, num_threads=1)
    alone, side = synthetic_run(tmp_path / "alone", cfg), synthetic_run(tmp_path / "side", cfg)
    recipes = ("baseline", "best+lr=0.01", "augment+seeds=1")
    args = [x for r in recipes for x in ("--recipe", r)]
    for run, extra in ((alone, []), (side, ["--parallel", "3"])):
        result = clothgap("eval", "ablation", str(run.root), *args, *extra)
        assert result.returncode == 0, result.stdout[-2000:] + result.stderr[-3000:]
    a = json.loads((alone.eval_dir / f"ablation-{SETTING}-{VARIANT}.json").read_text())["recipes"]
    b = json.loads((side.eval_dir / f"ablation-{SETTING}-{VARIANT}.json").read_text())["recipes"]
    assert [r["recipe"] for r in b] == list(recipes) and [r["seeds"] for r in b] == [[0], [0], [1]]
    for x, y in zip(a, b):      # each recipe's own settings and folder, whichever process trained it
        assert x["acc"] == y["acc"] and x["seq_acc"] == y["seq_acc"]
        for s in x["curves"]:
            assert [{k: v for k, v in e.items() if k != "seconds"} for e in x["curves"][s]] == \
                   [{k: v for k, v in e.items() if k != "seconds"} for e in y["curves"][s]]


def test_the_ablation_command_names_every_lever():
    # The levers are a registry (eval.ablation.LEVERS); the command's help lists them for its users.
    from click.testing import CliRunner

    from clothgap.cli import cli
    from eval.ablation import LEVERS

    text = " ".join(CliRunner().invoke(cli, ["eval", "ablation", "--help"]).output.split())
    named = re.search(r"named lever \(([^)]*)\)", text)
    assert named and named.group(1).split(", ") == list(LEVERS), named and named.group(1)
