"""The report shows the gap: heatmap, axis ranking with intervals, frames side by side; links that resolve
however the run folder was named; tables that scroll; empty cells that say why."""

from __future__ import annotations

import re
import shutil
from dataclasses import replace
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from clothgap.config import save_config
from clothgap.runs import Run
from eval import figures, tables
from eval.report import _photo, write_report
from eval.stage import run_eval
from tests.test_eval_stage import VARIANT_SETTINGS, make_fake_run, stub_predictor


@pytest.fixture(scope="module")
def evaluated(tmp_path_factory) -> Path:
    """Three rendered variants, models trained on two of them (reinhard is a test-only variant), evaluated."""
    root = tmp_path_factory.mktemp("report") / "run"
    run = make_fake_run(root, variants=("paper", "grid", "reinhard"))
    shutil.rmtree(root / "train" / "wind-uniform1" / "reinhard")
    save_config(replace(run.config, render=replace(run.config.render, variants=("paper", "grid"))),
                root / "config.json")
    run_eval(Run.open(root), progress=False, predictor=stub_predictor)
    return run.root


def hrefs(doc: str) -> list[str]:
    return [h for h in re.findall(r'href="([^"]*)"', doc) if not h.startswith("#")]


@pytest.mark.parametrize("relative", [True, False])
def test_links_resolve_from_a_relative_or_absolute_run_folder(evaluated, monkeypatch, relative):
    monkeypatch.chdir(evaluated.parent)
    run = Run.open(Path(evaluated.name) if relative else evaluated)
    path = write_report(run)
    links = hrefs(path.read_text())
    assert len(links) >= 6          # config, table3.csv, domain_gap.csv, axis_ranking.csv, checkpoints
    for link in links:
        assert (evaluated / "report" / link).exists(), link
    assert {"../eval/table3.csv", "../eval/domain_gap.csv", "../eval/axis_ranking.csv", "../config.json"} <= set(links)


def test_report_shows_the_gap_and_says_why_cells_are_empty(evaluated):
    doc = write_report(Run.open(evaluated)).read_text()
    gap = doc[doc.index('<h2 id="gap">'):]
    gap = gap[:gap.index("<h2", 5)] if "<h2" in gap[5:] else gap
    # the heatmap (eval's figure), the ranking as a bar chart, then its table
    assert gap.count("<img") >= 2 and "Render axes ranked" in gap
    assert "mean_gain_lo" not in gap and "[" in gap.split("Render axes ranked")[1]     # intervals shown as [lo, hi]
    # the frames of every rendered variant side by side, the test-only one included
    assert "Sample frames per render variant" in doc
    # no model was trained on reinhard: its gap cells say so instead of staying blank
    assert "n/a: no model was trained on the test variant" in doc
    assert "<td></td>" not in doc
    assert "overflow-x:auto" in doc


def test_axis_ranking_interval_brackets_the_gain(evaluated):
    ranking = pd.read_csv(evaluated / "eval" / "axis_ranking.csv")
    assert list(ranking["axis"]) == ["texture"]
    r = ranking.iloc[0]
    assert np.isfinite([r.mean_gain_lo, r.mean_gain_hi]).all()
    assert r.mean_gain_lo <= r.mean_gain <= r.mean_gain_hi and r.mean_gain_lo < r.mean_gain_hi
    # the interval is that of the same mean gain recomputed from the domain-gap table
    gap = pd.read_csv(evaluated / "eval" / "domain_gap.csv")
    again = tables.rank_axes(gap, VARIANT_SETTINGS)
    assert again.iloc[0]["mean_gain"] == pytest.approx(r.mean_gain, rel=1e-5)       # the CSV keeps 6 digits
    assert np.isnan(again.iloc[0]["mean_gain_lo"])       # no cells given: no interval, not a made-up one


def test_report_embeds_the_in_domain_and_test_only_confusion_matrices_only(evaluated):
    doc = write_report(Run.open(evaluated)).read_text()
    start = doc.index('<h2 id="confusion">')
    section = doc[start:doc.index("<h2", start + 5)]
    shown = re.findall(r'<img alt="wind-uniform1, lrcn: trained on ([\w-]+), tested on ([\w-]+)"', section)
    # paper and grid trained and tested on themselves; reinhard is tested only; paper<->grid are left to the tables
    assert sorted(shown) == [("grid", "grid"), ("grid", "reinhard"), ("paper", "paper"), ("paper", "reinhard")]
    assert len(list((evaluated / "eval" / "figures" / "confusion").rglob("*.png"))) == 6    # eval draws every cell
    assert "The other 2 cells" in section
    assert {"../eval/results.csv", "../eval/domain_gap.csv"} <= set(hrefs(section))


def test_rendered_frames_embed_as_jpeg_where_that_is_smaller():
    rng = np.random.default_rng(0)
    ramp = np.linspace(0, 200, 112)[None, :, None] + np.linspace(0, 50, 112)[:, None, None]
    photo = [np.clip(ramp + rng.normal(0, 12, (112, 112, 3)), 0, 255).astype(np.uint8) for _ in range(3)]
    flat = [np.full((16, 16, 3), 90 * i, np.uint8) for i in range(3)]
    for frames, mime in ((photo, "image/jpeg"), (flat, "image/png")):
        png = figures.png_bytes(figures.frame_grid({"clip": frames}, ["a", "b", "c"]))
        assert f'src="data:{mime};base64,' in _photo(png, "frames")


def test_the_gap_section_answers_which_training_variant_carries_to_a_test_only_look(evaluated):
    doc = write_report(Run.open(evaluated)).read_text()
    start = doc.index("<h3>On reinhard, a look no model trained on</h3>")
    table = doc[start:doc.index("</table>", start)]
    rows = re.findall(r"<tr>(.*?)</tr>", table)[1:]
    assert len(rows) == 2                                       # the models trained on paper and on grid
    gap = pd.read_csv(evaluated / "eval" / "domain_gap.csv")
    on = gap[gap["test_variant"] == "reinhard"].sort_values("gain", ascending=False)
    assert [re.findall(r"<td>([\w-]+)</td>", r)[2] for r in rows] == list(on["train_variant"])
    assert "within1" in table and "bend_acc" in table
