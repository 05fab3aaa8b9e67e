"""A split that holds no test sequence is named as such, not as clips that are not rendered yet."""

import json

import pytest

from clothgap.config import ConfigError
from eval.stage import run_eval
from tests.test_eval_stage import make_fake_run, stub_predictor


def test_empty_test_split_says_what_would_fill_it(tmp_path):
    run = make_fake_run(tmp_path / "run")
    path = run.split_path(run.config.sim.settings()[0])
    split = json.loads(path.read_text())
    path.write_text(json.dumps({**split, "train": split["train"] + split["test"], "test": []}))
    with pytest.raises(ConfigError, match="holds no test sequence.*sequences_per_class") as e:
        run_eval(run, progress=False, predictor=stub_predictor)
    assert "clothgap render" not in str(e.value)     # rendering more would not help


def test_unrendered_test_clips_still_ask_for_the_render(tmp_path):
    run = make_fake_run(tmp_path / "run")
    for folder in (run.root / "render").rglob("DONE"):
        folder.unlink()
    with pytest.raises(ConfigError, match="no rendered test clips.*clothgap render"):
        run_eval(run, progress=False, predictor=stub_predictor)
